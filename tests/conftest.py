"""Shared fixtures: the default robot and its model, built once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model

ROOT = Path(__file__).resolve().parent.parent
PROBLEMS = ROOT / "problems"


@pytest.fixture(scope="session")
def robot():
    return load_robot(PROBLEMS / "robots" / "cdsr2.toml")


@pytest.fixture(scope="session")
def model(robot):
    return Model(robot)
