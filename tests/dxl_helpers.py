"""Test helpers for the Dynamixel tests: the stage's homing section, a virtual clock the simulator can call,
the in-process simulator behind the command line (`in_process`), sim 1's plan once per module, and simulated
servos that count as homed (marker lit, matching state entries)."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import PROBLEMS

from crtraj.cli import main
from crtraj.core import clock as clock_module
from crtraj.core.clock import VirtualClock
from crtraj.hardware import dynamixel
from crtraj.hardware import dynamixel_protocol as dxl
from crtraj.hardware.dynamixel_protocol import X
from crtraj.hardware.homing_state import HomedServo, HomingState, multi_turn
from crtraj.hardware.sim_dynamixel import ServoChain
from crtraj.hardware.sim_dynamixel_port import SimPort

ROBOT = PROBLEMS / "robots" / "cdsr2.toml"
Z_HOMING = """
[robot.homing.z]
method = "hard_stop"
reference = -200.0     # mm: the stage's lower mechanical stop
direction = -1
speed = 20.0           # mm/s
current = 300.0        # mA
"""


class Clock(VirtualClock):
    """Virtual time shared by the link's users and the simulated servos (which call it)."""

    def __call__(self) -> float:
        return self.now()


def in_process(monkeypatch, chain: ServoChain, clock: VirtualClock, device: str = "/dev/crtraj-sim0") -> list[SimPort]:
    """Through the library's test seams (undone after the test): every use case's clock is `clock`, and the
    Dynamixel link opens a fresh in-process `SimPort` on `chain` for `device` (any other device as before):
    `crtraj.cli.main` then drives the simulated servos with the SDK's real bytes, on virtual time. The ports
    opened, in order."""
    opened: list[SimPort] = []
    real = dynamixel.port_factory

    def factory(sdk, name: str):
        if name != device:
            return real(sdk, name)
        opened.append(SimPort(chain, clock, name=name))
        return opened[-1]

    monkeypatch.setattr(clock_module, "clock_factory", lambda: clock)
    monkeypatch.setattr(dynamixel, "port_factory", factory)
    return opened


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
    """Mark every servo of `chain` homed (LED 1) where it stands, and the state file's entries that match
    them: what `crtraj home` leaves behind for servos whose readings are already absolute."""
    entries = []
    for k, dxl_id in enumerate(acts.bus.ids):
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
                )
            )
    return HomingState(tuple(entries))
