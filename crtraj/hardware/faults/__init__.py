"""Fault injection on the simulated Dynamixel bus, measured: the servos as the bus left them when the host went
silent (killed, or its adapter pulled out), their stop measured densely, and the true tendon tensions of a run.
Used by the fault tests and ``benchmarks/faults.py``."""

from __future__ import annotations

from crtraj.hardware.faults._runs import FaultPort, SilencePort, StopMeasure, measure_stop

__all__ = ["FaultPort", "SilencePort", "StopMeasure", "measure_stop"]
