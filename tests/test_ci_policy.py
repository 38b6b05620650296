"""The suite's own rules: a test needing a tool (Chromium, a C compiler) or an optional extra (ompl, dask)
skips locally but FAILS under CI=true when it is missing, and no test skips on a missing tool any other way;
and numbers compared as multisets pair up however near-ties happen to sort."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_same_multiset, require_module, require_tool

TESTS = Path(__file__).resolve().parent
HELPERS = {"require_tool", "require_module"}


# ---------------------------------------------------------------- the helpers
def test_require_tool_finds_a_tool_on_path(tmp_path, monkeypatch):
    tool = tmp_path / "fake-browser"
    tool.write_text("#!/bin/sh\n")
    tool.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setenv("CI", "true")
    assert require_tool("no-such-tool", "fake-browser") == str(tool)


@pytest.mark.parametrize("ci", ["true", "TRUE", "1"])
def test_missing_tool_or_module_fails_under_ci(tmp_path, monkeypatch, ci):
    monkeypatch.setenv("PATH", str(tmp_path))  # an empty directory: nothing is installed
    monkeypatch.setenv("CI", ci)
    with pytest.raises(pytest.fail.Exception, match=r"none of chromium, chromium-browser is on PATH.*CI=true"):
        require_tool("chromium", "chromium-browser")
    monkeypatch.setitem(sys.modules, "ompl", None)  # import ompl now raises ImportError
    with pytest.raises(pytest.fail.Exception, match=r"optional module ompl is not importable.*CI=true"):
        require_module("ompl")


@pytest.mark.parametrize("ci", [None, "", "false", "0"])
def test_missing_tool_or_module_skips_locally(tmp_path, monkeypatch, ci):
    monkeypatch.setenv("PATH", str(tmp_path))
    if ci is None:
        monkeypatch.delenv("CI", raising=False)
    else:
        monkeypatch.setenv("CI", ci)
    with pytest.raises(pytest.skip.Exception, match="none of cc, gcc is on PATH"):
        require_tool("cc", "gcc")
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(pytest.skip.Exception, match="optional module distributed is not importable"):
        require_module("distributed")


def test_require_module_returns_the_module():
    assert require_module("json").dumps([1]) == "[1]"


# ------------------------------------------------------------- every use of them
def _sites() -> list[str]:
    """Node ids of every test that needs a tool or extra: tests that call require_tool/require_module,
    and tests that take a fixture that does, or that takes such a fixture (found in the source, so a new use is
    covered too)."""
    out = []
    for path in sorted(TESTS.glob("test_*.py")):
        if path.name == Path(__file__).name:
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        funcs = [n for n in tree.body if isinstance(n, ast.FunctionDef)]

        def calls_helper(fn: ast.FunctionDef) -> bool:
            return any(
                isinstance(c, ast.Call) and isinstance(c.func, ast.Name) and c.func.id in HELPERS for c in ast.walk(fn)
            )

        fixtures = [fn for fn in funcs if not fn.name.startswith("test_")]
        needing = {fn.name for fn in fixtures if calls_helper(fn)}
        # and fixtures that take one of those, at any depth (a browser fixture on a `chromium` one)
        grown = True
        while grown:
            more = {fn.name for fn in fixtures if needing & {a.arg for a in fn.args.args}} - needing
            needing |= more
            grown = bool(more)
        for fn in funcs:
            if fn.name.startswith("test_") and (calls_helper(fn) or needing & {a.arg for a in fn.args.args}):
                out.append(f"tests/{path.name}::{fn.name}")
    return out


def test_no_test_skips_on_a_missing_tool_by_itself():
    """Only the helpers decide what happens when a tool or extra is missing."""
    offenders = []
    for path in sorted(TESTS.glob("*.py")):
        if path.name in ("conftest.py", Path(__file__).name):
            continue
        for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if "importorskip(" in line or "shutil.which(" in line or "find_spec(" in line:
                offenders.append(f"{path.name}:{i}: {line.strip()}")
    assert not offenders, offenders


def test_every_test_needing_a_tool_or_extra_fails_in_ci_without_it(tmp_path):
    """Run every such test with CI=true, an empty PATH and ompl, dask, distributed, dynamixel_sdk and rclpy
    unimportable: each must be reported failed (or errored, for a fixture), none passed or skipped."""
    sites = _sites()
    # the known uses, so the source scan itself cannot silently find nothing
    assert {
        "tests/test_viz.py::test_browser_animation_carries_robot_from_start_to_goal",
        "tests/test_export.py::test_compiled_library_round_trip",
        "tests/test_steer.py::test_jit_compiles_privately_and_matches_plain",
        "tests/test_bench.py::test_ompl_plans_in_space_time_and_passes_the_dense_check",
        "tests/test_bench.py::test_dask_local_cluster_runs_the_bench",
        "tests/test_dynamixel.py::test_crc_agrees_with_the_sdk_on_random_packets",
        "tests/test_ros_bridge.py::test_round_trip_reaches_the_goal_without_collision",
        "tests/test_viz_page.py::test_panel_shows_the_recorded_numbers_at_three_times",  # browser, on chromium
    } <= set(sites), sites
    (tmp_path / "bin").mkdir()
    (tmp_path / "block_extras.py").write_text(
        "import sys\n\n"
        "for name in ('ompl', 'dask', 'distributed', 'dynamixel_sdk', 'rclpy'):\n    sys.modules[name] = None\n"
    )
    env = {
        **os.environ,
        "CI": "true",
        "PATH": str(tmp_path / "bin"),
        "PYTHONPATH": os.pathsep.join([str(tmp_path), str(TESTS.parent), os.environ.get("PYTHONPATH", "")]),
    }
    report = tmp_path / "report.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "block_extras"]
    proc = subprocess.run(
        [*cmd, f"--junitxml={report}", *sites], cwd=TESTS.parent, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 1, proc.stdout[-3000:] + proc.stderr[-2000:]
    outcome = {}
    for case in ET.parse(report).iter("testcase"):
        # a parametrized test is one site; every one of its cases must fail
        base = case.get("name").split("[", 1)[0]
        name = f"tests/{case.get('classname').rsplit('.', 1)[-1]}.py::{base}"
        kinds = {child.tag for child in case} & {"failure", "error", "skipped"}
        seen = outcome.get(name)
        outcome[name] = kinds if seen is None else (seen | kinds if seen and kinds else set())
    assert set(outcome) == set(sites), (sorted(outcome), sites)
    wrong = {name: sorted(k) for name, k in outcome.items() if not k or "skipped" in k}
    assert not wrong, (wrong, proc.stdout[-3000:])
    # and each failed for the missing tool or extra, not for something else
    for case in ET.parse(report).iter("testcase"):
        text = " ".join((e.get("message") or "") + (e.text or "") for e in case if e.tag in ("failure", "error"))
        assert "(CI=true: required here, not skipped)" in text, (case.get("name"), text[-1000:])


# ---------------------------------------------------------- multiset comparison
def test_multiset_compare_ignores_how_near_ties_sort():
    # a conjugate pair whose real parts differ in the last bit sorts differently on each side
    a = np.array([1.0 + 2.0j, 1.0 + 2e-16 - 2.0j, 0.5])
    b = np.array([1.0 - 2.0j, 1.0 + 2e-16 + 2.0j, 0.5])
    assert np.max(np.abs(np.sort_complex(a) - np.sort_complex(b))) > 1.0  # what the old comparison saw
    assert_same_multiset(a, b, atol=1e-12)
    assert_same_multiset(b[::-1], a, atol=1e-12)


def test_multiset_compare_rejects_different_multisets():
    with pytest.raises(AssertionError, match="no partner within"):
        assert_same_multiset([1.0, 2.0], [1.0, 3.0], atol=1e-9)
    with pytest.raises(AssertionError, match="no partner within"):
        assert_same_multiset([1.0, 1.0, 2.0], [1.0, 2.0, 2.0], atol=1e-9)  # counts matter, not just membership
    with pytest.raises(AssertionError, match="3 values, expected 2"):
        assert_same_multiset([1.0, 2.0, 3.0], [1.0, 2.0], atol=1e-9)


def test_multiset_compare_finds_a_pairing_greedy_nearest_misses():
    # nearest-first would pair 1.0 with 0.6 and leave 0.0 with 1.6; the pairing 0.0-0.6, 1.0-1.6 is within 0.6
    assert_same_multiset([0.0, 1.0], [0.6, 1.6], atol=0.6 + 1e-12)
    with pytest.raises(AssertionError):
        assert_same_multiset([0.0, 1.0], [0.6, 1.6], atol=0.5)


# --------------------------------------------------------------------- .ci/run
def test_ci_script_runs_exactly_the_readme_test_command():
    readme = (TESTS.parent / "README.md").read_text(encoding="utf-8")
    block = readme.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    command = block[block.index(next(line for line in block if line.startswith("# 2."))) + 1]
    assert "pytest" in command
    script = (TESTS.parent / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    between = script[script.index("# --- the README's test command ---") + 1 :]
    assert between[1] == f"{command} || rc=$?", between[:3]
    assert "export CI=true" in script


# ------------------------------------------------------- what .ci/run installs
CI_TOOLS = TESTS.parent / ".ci" / "tools"


def _tool_table() -> dict[str, str]:
    """.ci/tools' table, tool -> Debian package, as the script itself prints it."""
    out = subprocess.run(["bash", str(CI_TOOLS), "--list"], capture_output=True, text=True, check=True).stdout
    return dict(line.split() for line in out.splitlines() if line.strip())


def _required_tools() -> list[tuple[str, tuple[str, ...]]]:
    """(place, names) of every require_tool call in the tests: any one of the names satisfies it."""
    calls = []
    for path in sorted(TESTS.glob("test_*.py")):
        if path.name == Path(__file__).name:  # this file calls it with made-up names on purpose
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "require_tool":
                names = tuple(a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str))
                calls.append((f"{path.name}:{node.lineno}", names))
    return calls


def test_ci_installs_every_tool_a_test_requires():
    """Each require_tool call names at least one tool that .ci/tools installs, so a fresh CI machine has it."""
    table = _tool_table()
    calls = _required_tools()
    assert {"ffprobe", "chromium", "cc"} <= {n for _, names in calls for n in names}  # the scan finds the known uses
    orphans = [f"{where}: {', '.join(names)}" for where, names in calls if not set(names) & set(table)]
    assert not orphans, f"tools no row of .ci/tools installs: {orphans}"
    run = (TESTS.parent / ".ci" / "run").read_text()
    assert run.index("bash .ci/tools") < run.index("python -m pytest"), ".ci/run installs the tools before the tests"


def _stub_path(tmp_path: Path, present: tuple[str, ...]) -> tuple[dict, Path]:
    """A PATH holding only bash, a few utilities, a recording stub apt-get and stubs of the `present` tools."""
    bin_ = tmp_path / "bin"
    bin_.mkdir(parents=True)
    for util in ("bash", "sed"):
        (bin_ / util).symlink_to(shutil.which(util))
    log = tmp_path / "apt.log"
    (bin_ / "apt-get").write_text(f'#!{shutil.which("bash")}\necho "$@" >> {log}\n')
    (bin_ / "id").write_text(f"#!{shutil.which('bash')}\necho 0\n")  # root: no sudo
    for tool in present:
        (bin_ / tool).write_text(f"#!{shutil.which('bash')}\nexit 0\n")
    for f in bin_.iterdir():
        if not f.is_symlink():
            f.chmod(0o755)
    return {"PATH": str(bin_), "HOME": str(tmp_path)}, log


def test_ci_tools_installs_each_missing_tool_on_a_bare_machine(tmp_path):
    """With none of the tools (nor python3) on PATH, a single install call names every row's package, the C headers
    and python3-venv; a machine that has them all installs nothing."""
    env, log = _stub_path(tmp_path / "bare", ())
    subprocess.run([env["PATH"] + "/bash", str(CI_TOOLS)], env=env, check=True, capture_output=True)
    installs = [line.split() for line in log.read_text().splitlines() if line.startswith("install")]
    assert len(installs) == 1, log.read_text()
    wanted = set(_tool_table().values()) | {"libc6-dev", "python3-venv"}
    assert set(installs[0]) - {"install", "-y", "-qq", "--no-install-recommends"} == wanted
    env, log = _stub_path(tmp_path / "full", (*_tool_table(), "python3"))
    subprocess.run([env["PATH"] + "/bash", str(CI_TOOLS)], env=env, check=True, capture_output=True)
    assert not log.exists(), log.read_text()


def test_the_heavy_first_files_are_test_files_of_the_suite():
    """Every file conftest hands out first exists (a renamed file would silently lose its place), once."""
    from conftest import HEAVY_FIRST

    here = Path(__file__).resolve().parent
    assert len(set(HEAVY_FIRST)) == len(HEAVY_FIRST)
    assert [name for name in HEAVY_FIRST if not (here / name).is_file()] == []
