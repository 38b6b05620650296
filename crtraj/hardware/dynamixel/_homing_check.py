"""`crtraj home --check`: whether each actuator's position is proven, read from the servos without writing or
moving anything.

`ReadOnlyLink` opens the port like `crtraj.hardware.dynamixel._link.DynamixelTransport` (the same connect checks:
every id answers with its model number and no hardware error; serial errors are the link's `LinkLostError`) but
only ever reads. `proven` then asks, per servo, what the stream's power-up check asks
(`PowerUpCheck`): a multi-turn actuator needs its homed marker, Operating Mode 4 or
5, the state file's offset and identity, a reading within half a turn of where crtraj let it go, and no Bus
Watchdog stop since; a spool needs a reading that unwraps into its limits.
"""

from __future__ import annotations

import contextlib
from typing import Any

from crtraj.core.errors import InputError
from crtraj.hardware.actuators import Actuators
from crtraj.hardware.dynamixel import _link
from crtraj.hardware.dynamixel._checks import ServoCheck, check_baud
from crtraj.hardware.dynamixel._homing_state import HomingState, PowerUpCheck, multi_turn, unwrap, windows
from crtraj.hardware.dynamixel._link import LINK_ERRORS, DynamixelTransport, _sdk, parse_url
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.transport import LinkLostError, TransportError


class ReadOnlyLink:
    """The servos of `actuators.bus` on ``dynamixel:///dev/PORT[?baud=N]``, for reads only (see the module doc)."""

    def __init__(self, url: str, actuators: Actuators) -> None:
        self._sdk = sdk = _sdk()
        device, baud = parse_url(url)
        self.bus, self.device, self.baud = actuators.bus, device, check_baud(baud)
        self._ph, self._lost = sdk.PacketHandler(2.0), None
        # looked up at each open, not bound at import: the port seam (`_link.port_factory`) is the link's
        self._port = port = _link.port_factory(sdk, device)
        try:
            opened = port.openPort() and DynamixelTransport._set_baud(port, self.baud)
        except Exception as exc:  # pyserial raises SerialException / OSError / ValueError
            raise TransportError(f"{device}: cannot open ({exc})") from None
        if not opened:
            raise TransportError(f"{device}: cannot open at {self.baud} baud")
        try:
            ServoCheck(self).run()
        except BaseException:
            self.close()
            raise

    _set_baud = staticmethod(DynamixelTransport._set_baud)
    _bus = DynamixelTransport._bus
    _ask = DynamixelTransport._ask

    read = DynamixelTransport.read

    def write(self, dxl_id: int, addr: int, value: int, size: int, what: str) -> None:
        raise AssertionError(f"home --check writes nothing ({what})")

    def close(self) -> None:
        """Close the port (idempotent); nothing is written."""
        if self._port is not None:
            with contextlib.suppress(*LINK_ERRORS):
                self._port.closePort()
            self._port = None


def proven(io: Any, acts: Actuators, state: HomingState, command: str) -> list[tuple[str, str | None]]:
    """(actuator, None when its position is proven, else why not and what to do), for every actuator; reads only."""
    check = PowerUpCheck(io, acts, state, command)
    bus, win, multi = acts.bus, windows(acts), multi_turn(acts)
    out: list[tuple[str, str | None]] = []
    for k, dxl_id in enumerate(bus.ids):
        try:
            marked = io.read(dxl_id, X.LED, 1) == 1
            if multi[k] and io.read(dxl_id, X.BUS_WATCHDOG, 1) & 0xFF == X.WATCHDOG_TRIPPED:
                raise InputError(f"servo {bus.name_of(dxl_id)}: its bus watchdog stopped it; run {command}")
            reading = io.read(dxl_id, X.PRESENT_POSITION, 4)
            if multi[k]:
                check._check_homed(k, dxl_id, marked)
            elif not marked:
                shift = unwrap(reading, int(win[k][0]), int(win[k][1]), int(bus.ticks_per_rev[k]))
                reading += 0 if shift is None else shift
            if not win[k][0] <= reading <= win[k][1]:
                raise InputError(f"servo {bus.name_of(dxl_id)}: reads {reading} ticks, outside its position limits")
            out.append((bus.names[k], None))
        except (InputError, TransportError) as exc:
            if isinstance(exc, LinkLostError):
                raise
            out.append((bus.names[k], str(exc)))
    return out
