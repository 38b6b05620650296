"""Use cases called by the CLI and the examples: plan a problem, run a loop, stream a result. Above: viz, bench."""
