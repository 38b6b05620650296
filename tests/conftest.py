"""Shared fixtures and helpers: the default robot and its model (built once per session), the CI
policy for tests that need a tool or an optional extra, and an order-free comparison of numbers."""

from __future__ import annotations

import fcntl
import importlib
import os
import shutil
import signal
import socket
import sys
import tempfile
from pathlib import Path
from types import ModuleType
from typing import NoReturn

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from crtraj.control.horizon import Replanner
from crtraj.control.loop import ClosedLoop
from crtraj.core import interrupt
from crtraj.core.build_cache import BuildCache
from crtraj.core.clock import VirtualClock
from crtraj.core.tomledit import set_values
from crtraj.io.problem import load_robot
from crtraj.model.kinematics import Model
from crtraj.planning.result import PlanResult, PlanStatus
from crtraj.world.obstacle import Obstacle
from crtraj.world.scene import Scene

ROOT = Path(__file__).resolve().parent.parent
PROBLEMS = ROOT / "problems"
# A planner's or solver's wall-time limit in tests that expect a result: only a hang bound. The iteration
# limits (PlannerOptions.max_iterations, ReplanOptions.max_iter) and the seed decide the outcome, so it is
# the same on a slow machine.
PLANNER_HANG_S = 600.0
PAPER = PROBLEMS / "paper_dynamic.toml"

# The suite's heaviest test files, heaviest first (seconds summed over each file's tests in CI run f12, three
# workers beside a CPU hog): they are handed out first, so that no worker starts a 250 s file when the others are
# nearly done (longest-first on three workers: 906 s of 2,718 s of work, against 1,014 s when xdist handed files
# out by their number of tests). pyproject's addopts turns xdist's own reorder off (--no-loadscope-reorder).
HEAVY_FIRST = (
    "test_docs_tutorials.py",  # 269 s
    "test_scene_examples.py",  # 128 s
    "test_e2e_stream.py",  # 106 s
    "test_docs.py",  # 89 s
    "test_homing_cli.py",  # 78 s
    "test_horizon_stage.py",  # 74 s
    "test_viz_live_page.py",  # 67 s
    "test_dynamixel.py",  # 66 s
    "test_viz_page.py",  # 64 s
    "test_bench.py",  # 62 s
    "test_cosserat.py",  # 61 s
    "test_verify_cosserat.py",  # 56 s
    "test_signals.py",  # 54 s
    "test_live_replay.py",  # 54 s
    "test_horizon_lean.py",  # 53 s
    "test_reference_worker.py",  # 52 s
    "test_kill.py",  # 51 s
    # 248 s: last of the heavy files, so that it starts after test_docs_tutorials.py has ended (at about 400 s):
    # the two tutorial files' real-time commands (simulators and streams at niceness -10) starved each other
    # beside the hog when both started at 0 s (f13: a stream's telemetry lost for 110 ms, three times in a row)
    "test_docs_tutorials_tools.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The heavy files first, in HEAVY_FIRST's order; every other file after them in collection order (a stable
    sort: each file's tests stay together and in their order)."""
    rank = {name: i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def paper_copy(folder: Path, name: str = "paper_dynamic.toml", values: dict | None = None) -> Path:
    """problems/paper_dynamic.toml written to folder/name, comments kept, with its robot path made absolute,
    without its 4 ms step deadline, and with `values` ({(table, key): value}, `set_values`) set. Without the
    deadline, which steps fall back depends on nothing but the problem: what a test of anything else checks
    must not depend on how fast the machine is at the time (live, late NLP results would be dropped)."""
    robot = str(PAPER.parent / "robots" / "cdsr2.toml")
    text = set_values(PAPER.read_text(), {("robot",): robot, ("replan", "step_deadline"): 0.0, **(values or {})})
    p = Path(folder) / name
    p.write_text(text)
    return p


@pytest.fixture(autouse=True, scope="session")
def private_build_cache(tmp_path_factory):
    """Compiled kernels built by the tests (and their child processes) go to a cache folder of this session,
    never to the user's cache directory; CRTRAJ_CACHE_DIR set by the caller is kept."""
    with pytest.MonkeyPatch.context() as mp:
        if not os.environ.get("CRTRAJ_CACHE_DIR"):
            mp.setenv("CRTRAJ_CACHE_DIR", str(_session_cache_folder(tmp_path_factory)))
        yield


def _session_cache_folder(tmp_path_factory) -> Path:
    """The run's cache folder. Under pytest-xdist every worker has its own base temp folder, inside one folder of
    the run: the workers share the cache there, so a library is compiled once per run, not once per worker (the
    cache publishes an entry by one rename, so two workers building the same entry at once both stay correct)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        folder = tmp_path_factory.getbasetemp().parent / "crtraj-cache"
        folder.mkdir(exist_ok=True)
        return folder
    return tmp_path_factory.mktemp("crtraj-cache")


@pytest.fixture(scope="session")
def build_cache(private_build_cache) -> BuildCache:
    """The session's build cache (the folder of `private_build_cache`, which commands run by the tests use too): a
    library built by one test file is loaded by the others, never compiled again. Tests of the cache itself (builds
    counted, entries corrupted) make their own."""
    return BuildCache()


@pytest.fixture(autouse=True)
def no_stop_requested():
    """Each test starts and ends with no stop requested. A test that signals its own process inside
    `interrupt.policy` leaves the request behind (in a command's process it ends the process), and a later
    library call would raise it at its first safe point (`interrupt.check`), far from its cause. Cleared after
    the test too: the next file's module fixtures are built before this fixture runs for its first test (f14:
    test_dynamixel's SIGTERM test left its request, and test_cosserat's module rod raised it while being built,
    which ended the worker's session)."""
    state = interrupt._state
    state.signum = state.count = state.shield = 0
    yield
    state.signum = state.count = state.shield = 0


@pytest.fixture(scope="session")
def robot():
    return load_robot(PROBLEMS / "robots" / "cdsr2.toml")


@pytest.fixture(scope="session")
def model(robot):
    return Model(robot)


# ------------------------------------------------------------------ CI policy
def in_ci() -> bool:
    """True when the CI environment variable says so (CI=true, as GitHub Actions and .ci/run set it)."""
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def missing(what: str) -> NoReturn:
    """Skip the calling test because `what` is missing here; under CI=true fail it instead, since
    CI must run every test (a skipped test there is a silently untested feature)."""
    if in_ci():
        pytest.fail(f"{what} (CI=true: required here, not skipped)", pytrace=False)
    pytest.skip(what)


def require_tool(*names: str, hint: str = "") -> str:
    """Full path of the first of `names` found on PATH; skips locally (fails under CI=true) if none is."""
    for name in names:
        path = shutil.which(name)
        if path:
            return path
    missing(f"none of {', '.join(names)} is on PATH" + (f" ({hint})" if hint else ""))


def require_module(name: str, hint: str = "") -> ModuleType:
    """The imported optional module `name`; skips locally (fails under CI=true) if it cannot be imported."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        missing(f"optional module {name} is not importable: {exc}" + (f" ({hint})" if hint else ""))


# ------------------------------------------------------------------ ROS domains
_DOMAIN_LOCKS: list[int] = []  # open lock files of the domains this process holds (closed when it exits)


def reserve_ros_domain(first: int = 10, count: int = 190) -> int:
    """A ROS domain id in first..first + count - 1 that no other process on this machine holds, held by this
    one until it exits (an exclusive flock on a file in the temp folder; the kernel drops it with the process,
    also on SIGKILL). Two test runs side by side (several checkouts, CI beside a developer) on one domain see
    each other's nodes on the same topic names: the robot of one would execute the other's trajectories. The
    search starts at a pid-dependent id, so a second reservation by this process gets another domain."""
    folder = Path(tempfile.gettempdir())
    start = os.getpid() % count
    for k in range(count):
        domain = first + (start + len(_DOMAIN_LOCKS) + k) % count
        fd = os.open(folder / f"crtraj-ros-domain-{domain}.lock", os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _DOMAIN_LOCKS.append(fd)
        return domain
    raise RuntimeError(f"no free ROS domain in {first}..{first + count - 1}: {count} test runs hold them all")


# ------------------------------------------------------------ order-free compare
def assert_same_multiset(actual, expected, atol: float) -> None:
    """Assert two 1-D arrays of (complex) numbers are equal as multisets within `atol`.

    Pairs them by an optimal assignment that minimises the number of pairs farther apart than `atol`
    (zero whenever any pairing within `atol` exists), so the verdict does not depend on how ties or
    near-ties (a conjugate pair whose real parts differ in the last bit) happen to be sorted.
    """
    a = np.asarray(actual).reshape(-1)
    b = np.asarray(expected).reshape(-1)
    assert a.shape == b.shape, f"{a.size} values, expected {b.size}"
    cost = np.abs(a[:, None] - b[None, :])
    rows, cols = linear_sum_assignment((cost > atol).astype(float))
    worst = int(np.argmax(cost[rows, cols]))
    d = cost[rows[worst], cols[worst]]
    assert d <= atol, f"{a[rows[worst]]} has no partner within {atol} (nearest unused: {b[cols[worst]]}, |d| = {d:.3g})"


def default_sigint() -> None:
    """Popen preexec_fn for a child that a test stops with SIGINT (its Ctrl-C).

    A shell that runs the suite in the background (CI runners, nohup, `cmd &`) starts every child with SIGINT
    ignored, and Python keeps an inherited SIG_IGN, so the child would never see its Ctrl-C. With the default
    disposition restored before exec, Python installs its KeyboardInterrupt handler as it does in a terminal.
    """
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def calls_of(fn) -> int:
    """The Python and C function calls `fn()` makes on this thread (`sys.setprofile` watches only this one): a
    measure of work that does not depend on the machine's speed."""
    count = [0]

    def hook(frame, event, arg):
        if event in ("call", "c_call"):
            count[0] += 1

    sys.setprofile(hook)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return count[0]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing is bound to right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def plan_result(model: Model, t, X, status: PlanStatus = PlanStatus.EXACT) -> PlanResult:
    """A `PlanResult` of the timed configurations X (N, nx) at t (N,) s, tips and cables from `model`: a
    path to hand to the checks without running a planner."""
    X = np.asarray(X, dtype=float)
    return PlanResult(
        status=status,
        message="test",
        planner="test",
        seed=0,
        t=np.asarray(t, dtype=float),
        configs=X,
        tips=model.tip_position(X),
        cables=model.cables(X),
    )


# The closed-loop tests' small problem: from XS toward XG's tip, past a breathing ball (mm, rad).
XS = np.array([0.3, 0.0, 0.0, 0.0, 0.0])
XG = np.array([-0.6, 0.5, -0.3, 0.2, -40.0])
BALL = Obstacle(center=(-3.5, 76.8, 394.4), radius=30.0, amplitude=8.0, omega=0.5, phase=-0.43, name="ball")


class LoopClock:
    """A `crtraj.core.clock.Clock` on a live-feed test's `feed_clock.VirtualClock` (whose time is an
    attribute, and whose sleep runs the callbacks it passes): the loop paces and times on the feed's clock."""

    def __init__(self, clock) -> None:
        self.clock = clock

    def now(self) -> float:
        return self.clock.now

    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds)


class SlowReplanner(Replanner):
    """A replanner whose k-th step's solve takes cost(k) s on the virtual clock; keeps every step's result
    (`results`). The loop's first solve is its untimed warm-up before step 0: neither charged nor kept."""

    def __init__(self, *args, clock: VirtualClock, cost, **kw) -> None:
        super().__init__(*args, **kw)
        self.clock, self.cost, self.k = clock, cost, -1
        self.results: list = []

    def solve(self, *args, **kw):
        res = super().solve(*args, **kw)
        if self.k >= 0:
            self.clock.advance(self.cost(self.k))
            self.results.append(res)
        self.k += 1
        return res


def straight_loop(model: Model, scene: Scene, **kw) -> ClosedLoop:
    """The closed loop from XS toward XG's tip among `scene` (goal configuration XG unless kw gives a
    reference); kw: `ClosedLoop.build`'s keyword options (the fields of `LoopSpec`)."""
    return ClosedLoop.build(model, scene, model.tip_position(XG), XS, **{"goal_config": XG, **kw})
