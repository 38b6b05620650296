"""The documentation: the README's Python runs, the README stays a front door, the generated references match
the code they are generated from (parsed here from their Markdown, independently of the generator), and
crtraj runs without the [bench] extra's rich and toppra."""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import importlib.util
import io
import os
import re
import shutil
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
    "scene_meshes.py": (
        ["{tmp}/data"],
        r"wrote .*plate_hole\.stl \(768 triangles\)\nwrote .*bent_pipe\.stl \(5664 triangles\)",
    ),
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
