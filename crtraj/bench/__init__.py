"""Benchmarks and scenario suites. Above: io."""
