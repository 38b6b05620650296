"""Test helpers for the Dynamixel tests: the stage's homing section, a virtual clock the simulator can call,
the in-process simulator behind the command line (`in_process`), sim 1's plan once per module, and simulated
servos that count as homed (marker lit, matching state entries)."""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

import pytest
from conftest import PROBLEMS

from crtraj.cli import main
from crtraj.core import clock as clock_module
from crtraj.core.clock import VirtualClock
from crtraj.hardware.dynamixel import _link as dynamixel
from crtraj.hardware.dynamixel import _protocol as dxl
from crtraj.hardware.dynamixel._homing_state import HomedServo, HomingState, multi_turn, state_path
from crtraj.hardware.dynamixel._protocol import X
from crtraj.hardware.dynamixel._sim_chain import ServoChain
from crtraj.hardware.dynamixel._sim_port import SimPort

ROBOT = PROBLEMS / "robots" / "cdsr2.toml"
Z_HOMING = """
[robot.homing.z]
method = "hard_stop"
reference = -200.0     # mm: the stage's lower mechanical stop
direction = -1
speed = 20.0           # mm/s
current = 300.0        # mA
"""


def robot_text(homing: str = Z_HOMING) -> str:
    """cdsr2.toml's text with the ``[robot.homing.z]`` table it ships replaced by `homing` (appended)."""
    text = ROBOT.read_text()
    shipped = re.search(r"^\[robot\.homing\.z\]\n(?:(?!\[)[^\n]+\n)*", text, flags=re.M)
    assert shipped, "cdsr2.toml ships a [robot.homing.z] table"
    return text[: shipped.start()] + text[shipped.end() :] + homing


class Clock(VirtualClock):
    """Virtual time shared by the link's users and the simulated servos (which call it)."""

    def __call__(self) -> float:
        return self.now()


_SERVED: dict[str, InProcessSim] = {}  # the started in-process simulators, by device name


class InProcessSim:
    """`SimDynamixel`'s test interface (`path`, `chain`, `clock`, `locked`, `start`, `stop`, a context) without a
    pseudo-terminal or a thread: opening `path` through the Dynamixel link gives the SDK a fresh `SimPort` on the
    chain at `clock` (once `serve_in_process` is in place), so the SDK's reply timeouts are virtual time too
    and nothing depends on how fast the machine answers."""

    _made = 0

    def __init__(self, chain: ServoChain, *, clock: VirtualClock, wire_time: bool = False) -> None:
        InProcessSim._made += 1
        self.path = f"/dev/crtraj-sim{InProcessSim._made}"  # no such file: only the seam knows it
        self.chain, self.clock, self.wire_time = chain, clock, wire_time
        self.ports: list[SimPort] = []

    def open(self) -> SimPort:
        self.ports.append(SimPort(self.chain, self.clock, name=self.path, wire_time=self.wire_time))
        return self.ports[-1]

    @property
    def wrong_baud(self) -> int:
        """Packets its ports ignored because the host's rate was not the bus rate."""
        return sum(p.wrong_baud for p in self.ports)

    def locked(self) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext()  # one thread: nothing to lock against

    def start(self) -> InProcessSim:
        _SERVED[self.path] = self
        return self

    def stop(self) -> None:
        _SERVED.pop(self.path, None)

    def __enter__(self) -> InProcessSim:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve_in_process(monkeypatch) -> None:
    """Through the library's port seam (undone after the test): the path of a started `InProcessSim` opens its
    `SimPort`; any other device as before."""
    real = dynamixel.port_factory

    def factory(sdk, name: str):
        sim = _SERVED.get(name)
        return real(sdk, name) if sim is None else sim.open()

    monkeypatch.setattr(dynamixel, "port_factory", factory)


def in_process(monkeypatch, chain: ServoChain, clock: VirtualClock) -> InProcessSim:
    """`chain` served in process for the whole test, and every use case's clock `clock` (the library's clock
    seam): `crtraj.cli.main` then drives the simulated servos with the SDK's real bytes, on virtual time."""
    serve_in_process(monkeypatch)
    monkeypatch.setattr(clock_module, "clock_factory", lambda: clock)
    sim = InProcessSim(chain, clock=clock).start()
    monkeypatch.setitem(_SERVED, sim.path, sim)
    return sim


@pytest.fixture(scope="module")
def sim1_plan(tmp_path_factory) -> Path:
    """`crtraj plan problems/paper_static.toml --seed 1` (the paper's simulation 1), once per module."""
    out = tmp_path_factory.mktemp("plan") / "plan.json"
    assert main(["plan", str(PROBLEMS / "paper_static.toml"), "--seed", "1", "--out", str(out)]) == 0
    return out


def write(chain: ServoChain, dxl_id: int, addr: int, value: int, size: int, now: float = 0.0) -> None:
    """A WRITE instruction to the chain, as another program on the bus would send it."""
    params = addr.to_bytes(2, "little") + value.to_bytes(size, "little", signed=value < 0)
    chain.handle(dxl.Packet(dxl_id, dxl.WRITE, params), now)


def homed_state(chain: ServoChain, acts, now: float = 0.0) -> HomingState:
    """Mark every servo of `chain` homed (LED 1, Operating Mode 4) where it stands, and the state file's entries
    that match them: what `crtraj home` leaves behind for servos whose readings are already absolute."""
    entries = []
    for k, dxl_id in enumerate(acts.bus.ids):
        write(chain, dxl_id, X.OPERATING_MODE, X.EXTENDED_POSITION, 1, now)  # the marker counts in mode 4 or 5
        write(chain, dxl_id, X.LED, 1, 1, now)
        if multi_turn(acts)[k]:
            entries.append(
                HomedServo(
                    dxl_id,
                    acts.names[k],
                    chain.register(dxl_id, X.MODEL_NUMBER, 2),
                    chain.register(dxl_id, X.HOMING_OFFSET, 4),
                    "index",
                    "2026-12-02T00:00:00+00:00",
                    chain.register(dxl_id, X.MODEL_INFORMATION, 4),
                    chain.register(dxl_id, X.FIRMWARE, 1),
                    chain.register(dxl_id, X.PRESENT_POSITION, 4),
                )
            )
    return HomingState(tuple(entries))


def homed_at(plan: Path, robot_file: Path, text: str):
    """The robot file `robot_file` written with `text` (its homing state beside it), and servos homed standing at
    `plan`'s start with the device time reached, as `crtraj sim-dynamixel --at` serves them: (robot file,
    chain, device time)."""
    from crtraj.app.devices import admit_result
    from crtraj.hardware.actuators import Actuators
    from crtraj.hardware.dynamixel import home_in_place, robot_chain
    from crtraj.io.problem import load_robot

    robot_file.write_text(text)
    robot = load_robot(robot_file)
    acts = Actuators.from_robot(robot)
    start = admit_result(str(plan), str(robot_file), rate=100.0).values[0]
    chain = robot_chain(robot, acts, start)
    homed, reached = home_in_place(robot, acts, chain, start)
    HomingState(tuple(homed)).save(state_path(robot_file))
    return robot_file, chain, reached
