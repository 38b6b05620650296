"""The documentation: the README's Python runs, the README stays a front door, the generated references match
the code they are generated from (parsed here from their Markdown, independently of the generator), and
crtraj runs without the [bench] extra's rich and toppra."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import importlib
import importlib.util
import io
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from crtraj.bench.records import LABELS, BenchOptions
from crtraj.bench.runner import make_progress
from crtraj.cli import build_parser
from crtraj.core.errors import InputError
from crtraj.core.fields import Table
from crtraj.io.problem import SECTIONS, Problem
from crtraj.planning.options import PlannerOptions

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
HOOK = ROOT / "docs" / "hooks" / "references.py"


def _hook():
    """The mkdocs hook module, loaded from its file as mkdocs loads it."""
    spec = importlib.util.spec_from_file_location("crtraj_docs_references", HOOK)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


# ------------------------------------------------------------------------------------------------ README
def _readme() -> str:
    return (ROOT / "README.md").read_text(encoding="utf-8")


def test_readme_is_a_front_door():
    """At most 250 lines, the two commands first, and no history: no dated entries, no load notes."""
    text = _readme()
    assert len(text.splitlines()) <= 250
    first_block = text.split("```bash\n", 1)[1].split("```", 1)[0]
    assert "# 1." in first_block and "# 2." in first_block
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", text), "dated entries belong in CHANGELOG.md"
    assert "load average" not in text and "issue 1" not in text.lower()


def test_readme_links_point_at_files_that_exist():
    """Every relative link and image of the README names a file of the repository."""
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", _readme())
    local = [t for t in targets if "://" not in t]
    assert local, "the README links its docs and picture"
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing


def test_readme_python_quick_start_runs():
    """Each ```python block of the README runs as it is, from the repository root."""
    blocks = re.findall(r"```python\n(.*?)```", _readme(), flags=re.S)
    assert blocks
    for code in blocks:
        proc = subprocess.run(
            [sys.executable, "-c", code], cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=900
        )
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert proc.stdout.strip(), "the quick start prints its result"


# ---------------------------------------------------------------------------------- examples and tutorials
# Every script of examples/ runs as a user runs it (its arguments, then a line it must print, a regular
# expression). Shell scripts (the rod calibration: minutes of rod simulation) are the command line's.
EXAMPLES = {
    "plan_static.py": ([], r"cspace: exact .*\n(.*\n)*wrote .*plan_static\.json"),
    "replan_dynamic.py": (["{tmp}/replan"], r"reached goal yes, collisions 0 .*\n(.*\n)*horizon NLP: solved"),
    "stream_sim.py": ([], r"run_path: done .*\n(.*\n)*live: +done"),
    # the calibrated file moves the true robot's tip onto the plan (the nominal one misses it by ~150 mm)
    "calibrate_synthetic.py": ([], r"refused: --time-offset.*\n(.*\n)*calibrated plan: .* max 0\.[0-4]\d* mm"),
    "view_result.py": (["--pose", "{tmp}/pose.html"], r"wrote .*pose\.html"),
}


def test_every_example_is_run():
    assert sorted(p.name for p in (ROOT / "examples").glob("*.py")) == sorted(EXAMPLES)


def _run_python(args: list[str], cwd: Path) -> str:
    proc = subprocess.run([sys.executable, *args], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_example_runs(name, tmp_path):
    args, expected = EXAMPLES[name]
    out = _run_python([f"examples/{name}", *(a.format(tmp=tmp_path) for a in args)], ROOT)
    assert re.search(expected, out), out[-3000:]


def test_your_robot_tutorial_runs(tmp_path):
    """docs/tutorials/your-robot.md as a reader follows it: its robot file saved as my_robot.toml, then its
    Python: a scene, a plan, verified, admitted and streamed to the simulated device to the end."""
    page = (ROOT / "docs" / "tutorials" / "your-robot.md").read_text(encoding="utf-8")
    assert "Save this as `my_robot.toml`" in page
    (toml,) = re.findall(r"```toml\n(.*?)```", page, flags=re.S)
    (code,) = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    assert len(code.strip().splitlines()) <= 12
    (tmp_path / "my_robot.toml").write_text(toml, encoding="utf-8")
    out = _run_python(["-c", code], tmp_path)
    assert re.fullmatch(r"exact in [\d.]+ s, [\d.]+ mm beyond D_sf; streamed: done\n", out), out


@pytest.mark.slow
@pytest.mark.parametrize("page", ["tutorials/plan-and-stream.md", "tutorials/replan-live.md", "concepts/model.md"])
def test_tutorial_python_runs(page):
    """The Python of the other pages runs as written, from the repository root."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / page).read_text(encoding="utf-8"), flags=re.S)
    assert blocks
    for code in blocks:
        _run_python(["-c", code], ROOT)


# ------------------------------------------------------------------------------------------ CLI reference
def _parser_options(parser: argparse.ArgumentParser) -> dict[str, set[str]]:
    """command -> its option strings and positional names, read from the parser itself."""
    out: dict[str, set[str]] = {"": set()}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                nested = _parser_options(sub)  # a command with its own commands: `model compare`
                out[name] = nested.pop("")
                out |= {f"{name} {n}": opts for n, opts in nested.items()}
        elif action.option_strings:
            out[""] |= set(action.option_strings)
        else:
            out[""].add(action.metavar or action.dest)
    return out


def _reference_options(markdown: str) -> dict[str, set[str]]:
    """command -> the option names in its table, parsed from the generated Markdown."""
    out: dict[str, set[str]] = {}
    command = None
    for line in markdown.splitlines():
        m = re.match(r"^## `crtraj ?([\w -]*)`$", line)
        if m:
            command = m.group(1)
            out[command] = set()
        elif command is not None and line.startswith("| `"):
            first = line[2:].split(" | ", 1)[0]
            out[command] |= set(re.findall(r"`([^`]+)`", first))
    return out


def test_cli_reference_matches_the_parser():
    """Every command and option of the reference exists in the parser, and every one of the parser is there."""
    reference = _reference_options(_hook().cli_markdown())
    parser = _parser_options(build_parser())
    assert {"plan", "replan", "stream", "calibrate"} <= set(parser)
    assert reference == parser


def test_cli_reference_check_sees_a_missing_option():
    """The comparison above fails when the reference lacks one option row."""
    markdown = _hook().cli_markdown()
    lines = markdown.splitlines()
    row = next(i for i, line in enumerate(lines) if line.startswith("| `--seed`"))
    cut = "\n".join(lines[:row] + lines[row + 1 :])
    assert _reference_options(cut) != _parser_options(build_parser())


def test_cli_reference_gives_defaults_and_help():
    """A row carries the parser's default and help text (plan --planner, bench --counts)."""
    markdown = _hook().cli_markdown()
    assert "| `--counts` | `COUNTS` | `1,3,5,7` |" in markdown
    assert re.search(r"\| `--planner` \| `cspace` \\\| `rrt` \\\| `rrtstar` \|  \| default: \[planner\]", markdown)
    assert str(ROOT) not in markdown, "paths in defaults are relative to the repository"


# ------------------------------------------------------------------------------- problem-file reference
def _reference_tables(markdown: str) -> dict[str, tuple[str, dict[str, str]]]:
    """section -> (class path, key -> default literal), parsed from the generated Markdown."""
    out: dict[str, tuple[str, dict[str, str]]] = {}
    section = None
    for line in markdown.splitlines():
        m = re.match(r"^## `\[([\w.-]+)\]`$", line)
        if m:
            section = m.group(1)
            out[section] = ("", {})
            continue
        if section is None:
            continue
        m = re.match(r"^Read by `([\w.]+)`\.$", line)
        if m:
            out[section] = (m.group(1), out[section][1])
        m = re.match(r"^\| `(\w+)` \| [^|]+ \| (`(.*?)`)? \|", line)
        if m:
            out[section][1][m.group(1)] = (m.group(3) or "").replace("&#124;", "|")
    return out


def _class(path: str) -> type:
    module, name = path.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


def test_problem_reference_covers_every_options_table():
    """The problem reader's options tables are all there, and each lists every declared key of its class."""
    tables = _reference_tables(_hook().problem_markdown())
    assert {"steer", "planner", "replan", "loop", "tracking", "stream", "feed", "view", "ros"} <= set(tables)
    for section, (path, keys) in tables.items():
        assert section.split(".")[0] in SECTIONS
        cls = _class(path)
        assert section == cls.SECTION
        declared = {f.name for f in dataclasses.fields(cls) if "crtraj.option" in f.metadata}
        subtables = {f.name for f in dataclasses.fields(cls) if isinstance(getattr(f.default, "SECTION", None), str)}
        assert set(keys) == declared - subtables, section
        assert {f"{section}.{name}" for name in subtables} <= set(tables), section  # each sub-table has its own


def test_a_problem_built_from_the_reference_defaults_loads(tmp_path):
    """Every key with its documented default, written as a problem file, is accepted by the problem reader
    and gives that value back."""
    # the robot file's own tables ([robot.mechanics]) are not problem-file tables: the robot is named by path
    tables = {k: v for k, v in _reference_tables(_hook().problem_markdown()).items() if not k.startswith("robot.")}
    robot = (ROOT / "problems" / "robots" / "cdsr2.toml").as_posix()
    lines = [f'robot = "{robot}"']
    for section, (_, keys) in tables.items():
        lines.append(f"[{section}]")
        lines += [f"{key} = {literal}" for key, literal in keys.items() if literal]
    path = tmp_path / "from_reference.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    problem = Problem.load(path)
    for section, (class_path, keys) in tables.items():
        top, _, sub = section.partition(".")
        cls = _class(class_path)
        if not sub:
            parsed = problem.options(cls, top)
        elif top in tables:
            continue  # the parent table's class reads its sub-tables
        else:
            parsed = cls.from_table(Table(problem.raw[top][sub], section))
        data = parsed.to_dict()
        for key, literal in keys.items():
            expected = tomllib.loads(f"v = {literal}")["v"] if literal else None
            if isinstance(expected, (int, float, bool, str)):
                assert data[key] == expected, f"{section}.{key}"


def test_reference_defaults_check_sees_a_wrong_key(tmp_path):
    """The reader refuses a key the reference would invent, so the check above can fail."""
    path = tmp_path / "bad.toml"
    robot = (ROOT / "problems" / "robots" / "cdsr2.toml").as_posix()
    path.write_text(f'robot = "{robot}"\n[planner]\nno_such_key = 1\n', encoding="utf-8")
    with pytest.raises(InputError, match="no_such_key"):
        Problem.load(path).options(PlannerOptions, "planner")


# ---------------------------------------------------------------------- without the [bench] extra
_WITHOUT_BENCH_EXTRA = """
import importlib, sys
sys.modules["rich"] = None  # import rich (and rich.progress) now raises ImportError
sys.modules["rich.progress"] = None
sys.modules["toppra"] = None
from crtraj.cli import _USE_CASES
for target in _USE_CASES.values():
    importlib.import_module(target.split(":")[0])
from crtraj.bench.runner import make_progress
from crtraj.bench.records import BenchOptions


class Record:
    planner, claimed, verified = "rrt", True, True

    def is_success(self):
        return True


bar = make_progress(BenchOptions(planners=("rrt",)), 1)  # no stream given: rich if it were there
bar.start()
bar.advance(Record())
bar.stop()
"""


def test_every_command_imports_without_rich_and_toppra():
    """With rich and toppra not importable, every command's use case imports and bench progress is plain."""
    proc = subprocess.run(
        [sys.executable, "-c", _WITHOUT_BENCH_EXTRA], cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stderr.splitlines()[-1] == f"bench: {LABELS['rrt']} 1/1, success 1/1"


@dataclasses.dataclass
class _Record:
    planner: str
    ok: bool
    claimed: bool = True
    verified: bool = True

    def is_success(self) -> bool:
        return self.ok


def test_plain_progress_prints_about_ten_lines_per_planner():
    """20 runs per planner: a line every 2 runs with the running success count (every third run fails)."""
    out = io.StringIO()
    bar = make_progress(BenchOptions(planners=("rrt", "cspace")), 40, stream=out)
    bar.start()
    expected = []
    for planner in ("rrt", "cspace"):
        ok = 0
        for n in range(1, 21):
            ok += n % 3 != 0
            bar.advance(_Record(planner, n % 3 != 0))
            if n % 2 == 0:
                expected.append(f"bench: {LABELS[planner]} {n}/20, success {ok}/{n}")
    bar.stop()
    assert out.getvalue().splitlines() == expected


# ------------------------------------------------------------------ the tutorials' simulator blocks
TUTORIALS = ROOT / "docs" / "tutorials"
SIMULATORS = ("crtraj sim-dynamixel",)  # the blocks that start one are run end to end, as written
_PTY = re.compile(r"sim-dynamixel on (/dev/pts/\d+)")
_EXIT = re.compile(r"^\(exit (\d+)\) ")


def _simulator_blocks() -> list:
    """One pytest param per ```bash block of docs/tutorials/ that starts a simulator: (file, text)."""
    out = []
    for md in sorted(TUTORIALS.glob("*.md")):
        blocks = re.findall(r"^```bash\n(.*?)^```", md.read_text(encoding="utf-8"), flags=re.S | re.M)
        for k, text in enumerate(blocks):
            if any(s in text for s in SIMULATORS):
                out.append(pytest.param(md.name, text, id=f"{md.name}#{k + 1}"))
    return out


def _steps(text: str) -> list[tuple[str, list[str]]]:
    """The block's commands, each with the output lines the tutorial shows under it (``#   ...`` lines)."""
    steps: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        if line.startswith("#   ") and steps:
            steps[-1][1].append(line[4:].strip())
        elif line.strip() and not line.startswith("#"):
            steps.append((line, []))
    return steps


def _shown(expected: str) -> re.Pattern:
    """The tutorial's shown output line as a pattern: ``...`` stands for any text, /dev/pts/N for a pty."""
    parts = [re.escape(p).replace("/dev/pts/N", r"/dev/pts/\d+") for p in expected.split("...")]
    return re.compile(".*".join(parts))


def _check_step(command: str, shown: list[str], proc: subprocess.CompletedProcess) -> None:
    """Exit code 0 (or the ``(exit N)`` shown) and every shown line somewhere in the output."""
    output = proc.stdout + proc.stderr
    want = next((int(m.group(1)) for m in map(_EXIT.match, shown) if m), 0)
    assert proc.returncode == want, f"{command}\nexit {proc.returncode}, expected {want}\n{output[-3000:]}"
    for line in shown:
        pattern = _shown(_EXIT.sub("", line))
        assert any(pattern.fullmatch(out) for out in output.splitlines()), f"{command}\nno line {line!r}\n{output}"


def _start_background(command: str, env: dict[str, str], cwd: Path) -> tuple[subprocess.Popen, str, str]:
    """Start `command` (without its ``&``) in its own process group; the pseudo-terminal it prints, and its output
    up to that line."""
    proc = subprocess.Popen(
        ["bash", "-c", command],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    seen = []
    for line in proc.stdout:  # it prints its path once it serves (after homing, with --at)
        seen.append(line)
        m = _PTY.search(line)
        if m:
            return proc, m.group(1), "".join(seen)
    raise AssertionError(f"{command}\nprinted no pseudo-terminal:\n{''.join(seen)}")


@pytest.mark.slow
@pytest.mark.parametrize(("tutorial", "text"), _simulator_blocks())
def test_tutorial_simulator_blocks_run_as_written(tutorial, text, tmp_path):
    """Each such block runs line by line in a folder holding a copy of problems/, with `.venv/bin/` the test's
    interpreter's and /dev/pts/N the pseudo-terminal the simulator printed; ``CMD &`` starts in the background
    and ``kill %1`` stops it (else it is stopped at the end). Every command exits 0, or with the ``(exit N)``
    the tutorial shows under it, and prints every line shown under it (``...``: any text)."""
    shutil.copytree(ROOT / "problems", tmp_path / "problems")
    env, bin_dir = _env(), f"{Path(sys.executable).parent}/"
    jobs: list[subprocess.Popen] = []
    pty = None
    try:
        for command, shown in _steps(text):
            command = command.replace(".venv/bin/", bin_dir)
            command = command if pty is None else command.replace("/dev/pts/N", pty)
            shell = re.sub(r"\s+#.*$", "", command).strip()
            if shell.endswith("&"):
                job, pty, printed = _start_background(shell[:-1], env, tmp_path)
                jobs.append(job)
                _check_step(command, shown, subprocess.CompletedProcess(shell, 0, printed, ""))
            elif (m := re.fullmatch(r"kill %(\d+)", shell)) is not None:
                _stop(jobs[int(m.group(1)) - 1])
            else:
                proc = subprocess.run(
                    ["bash", "-c", shell], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=800
                )
                _check_step(command, shown, proc)
    finally:
        for job in jobs:
            _stop(job)
    assert jobs, f"{tutorial}: the block started no simulator"


def _stop(job: subprocess.Popen) -> None:
    """SIGTERM to the job's process group (the shell and the simulator), then wait for it."""
    if job.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(job.pid, signal.SIGTERM)
        job.wait(timeout=30)
    job.stdout.close()


def test_tutorial_step_check_sees_a_wrong_exit_code_and_a_missing_line():
    """The checks above fail on a command that exits otherwise than shown, or does not print a shown line."""
    steps = _steps("a --x\n#   (exit 2) crtraj: error: servo id 7 (z): not homed ... run crtraj home ...\nb\n")
    assert steps == [
        ("a --x", ["(exit 2) crtraj: error: servo id 7 (z): not homed ... run crtraj home ..."]),
        ("b", []),
    ]
    line = "crtraj: error: servo id 7 (z): not homed since its power-up; run crtraj home --dynamixel /dev/pts/3\n"
    _check_step("a", steps[0][1], subprocess.CompletedProcess("a", 2, "", line))
    with pytest.raises(AssertionError, match="exit 1, expected 2"):
        _check_step("a", steps[0][1], subprocess.CompletedProcess("a", 1, "", line))
    with pytest.raises(AssertionError, match="no line"):
        _check_step("a", steps[0][1], subprocess.CompletedProcess("a", 2, "", line.replace("not homed", "homed")))
    assert _simulator_blocks(), "the tutorials try the simulator"


# ------------------------------------------------------------------ the mechanics page's block
def test_mechanics_page_block_runs_as_written(tmp_path):
    """docs/concepts/mechanics.md's block runs in a folder holding a copy of problems/, with the test interpreter's
    `crtraj` first on PATH: it exits 0, the PCC plan's rod check says CONTACT and the rod plan's says D_sf holds."""
    md = (ROOT / "docs" / "concepts" / "mechanics.md").read_text(encoding="utf-8")
    (block,) = re.findall(r"^```bash\n(.*?)^```", md, flags=re.S | re.M)
    shutil.copytree(ROOT / "problems", tmp_path / "problems")
    env = _env()
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    proc = subprocess.run(
        ["bash", "-e", "-c", block], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    assert "D_sf CONTACT" in out and "PCC plan refused by the rod" in out, out[-3000:]
    rod_check = out.split("out/shelf-rod.json: plan", 1)[1]
    assert re.search(r"Cosserat: min clearance \d+\.\d+ mm .*: D_sf holds", rod_check), rod_check
