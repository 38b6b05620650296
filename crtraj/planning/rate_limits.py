"""Actuator speed and acceleration limits on configuration motion: `crtraj.model.rate_limits.RateLimits`.

They are part of the robot description (`crtraj.model.actuator_limits`); this name stays for the
planning and control code that imports them from here.
"""

from crtraj.model.rate_limits import RateLimits

__all__ = ["RateLimits"]
