"""The one exception type users see for bad input."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input: a one-line message that names the offending field or value."""


class AdmissionError(InputError):
    """A well-formed motion that may not drive a device (failed, collided, unsafe, another robot, ...).

    Raised by `crtraj.hardware.admission.admit` before anything is sent. The command line prints its
    one-line message and exits 1: the input is readable, the motion is refused.
    """
