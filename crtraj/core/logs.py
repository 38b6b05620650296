"""The ``crtraj`` logger on the command line: level from ``-v``/``-q``, one ``crtraj: message`` line per
record on stderr.

Every module logs to ``logging.getLogger(__name__)`` (loggers under ``crtraj.``); a library user configures
logging as they like, the command line calls `configure_logging` once per run.
"""

from __future__ import annotations

import logging
import sys


class _StderrHandler(logging.Handler):
    """Writes records to the current ``sys.stderr`` (looked up per record, so a redirected or captured
    stderr gets them)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            sys.stderr.write(self.format(record) + "\n")
            sys.stderr.flush()
        except Exception:  # logging must never end the command
            self.handleError(record)


def configure_logging(verbose: int = 0, quiet: bool = False) -> logging.Logger:
    """Set up the ``crtraj`` logger for the command line: level WARNING (-v INFO, -vv DEBUG, -q ERROR),
    one ``crtraj: message`` line per record on stderr. Repeated calls replace the level, not the handler."""
    log = logging.getLogger("crtraj")
    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    log.setLevel(level)
    if not any(isinstance(h, _StderrHandler) for h in log.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("crtraj: %(message)s"))
        log.addHandler(handler)
    log.propagate = False
    return log
