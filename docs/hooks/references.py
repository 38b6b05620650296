"""mkdocs hook: the references that are generated from the code at every build, so they cannot go stale.

- ``reference/cli.md``: every command, option, default and help text of ``crtraj``'s argparse parser
  (`crtraj.cli.build_parser`), walked action by action.
- ``reference/problem-file.md``: every key of every options table a problem file may hold, with its type,
  default, bounds and unit, from the ``option()`` metadata of the `crtraj.core.options.Options` subclasses
  whose ``SECTION`` is a table the problem reader knows (`crtraj.io.problem.SECTIONS`). The classes are
  found by importing every module that uses the options base, not from a list kept here.
- the result-schema table of ``architecture.md``, from `crtraj.io.run_schema.schema_table_markdown`, put
  where the page has the marker ``<!-- result-schema-table -->``.

The generators are plain functions (`cli_markdown`, `problem_markdown`) so that tests can call them.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import inspect
import json
import logging
import math
import os
import re
import textwrap
import typing
from pathlib import Path
from typing import Any

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "crtraj"
SCHEMA_MARKER = "<!-- result-schema-table -->"
# Only for checking the rest of the site before the result schema module exists: the build then shows a
# notice instead of the table. Never set in CI.
ALLOW_MISSING_SCHEMA = "CRTRAJ_DOCS_ALLOW_MISSING_SCHEMA"
CLI_PAGE = "reference/cli.md"
PROBLEM_PAGE = "reference/problem-file.md"

log = logging.getLogger("mkdocs.plugins.crtraj_references")

# Units a docstring may give in brackets right after a key's name, e.g. "max_speed: ... (mm/s)".
_UNIT = re.compile(r"^(rad or mm|mm/s\^2|rad/s\^2|mm/s|rad/s|mm|rad|ms|Hz|deg|1/s|s|m)(,|;|$| )")


# ----------------------------------------------------------------------------- small Markdown helpers
def _cell(text: Any) -> str:
    """`text` made safe inside a Markdown table cell (one line, no pipes, no raw HTML)."""
    s = " ".join(str(text).split())
    return s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace("|", "\\|")


def _code(text: str) -> str:
    """Inline code that survives a table cell (backticks cannot be escaped inside one)."""
    return f"`{text.replace('|', '&#124;')}`"


def _relative(value: Any) -> Any:
    """A default that is a path inside the repository, written relative to it (not this machine's path)."""
    if isinstance(value, str) and value.startswith(str(ROOT) + os.sep):
        return os.path.relpath(value, ROOT)
    return value


# ----------------------------------------------------------------------------- the CLI reference
def _subcommands(parser: argparse.ArgumentParser) -> tuple[dict[str, argparse.ArgumentParser], dict[str, str]]:
    """(name -> subparser, name -> one-line help) of `parser`'s subcommands, in the order they were added."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            commands: dict[str, argparse.ArgumentParser] = {}
            for name, sub in action.choices.items():
                commands[name] = sub
                nested, nested_helps = _subcommands(sub)  # e.g. `model compare`
                commands |= {f"{name} {n}": p for n, p in nested.items()}
                helps |= {f"{name} {n}": h for n, h in nested_helps.items()}
            return commands, helps
    return {}, {}


def _option_row(parser: argparse.ArgumentParser, action: argparse.Action) -> str:
    """One table row: the option's names (or a positional's name), its value, default and help."""
    if action.option_strings:
        names = ", ".join(_code(s) for s in action.option_strings)
    else:
        names = _code(action.metavar or action.dest) + " (positional)"
    if action.choices is not None:
        value = " \\| ".join(_code(str(c)) for c in action.choices)
    elif action.nargs == 0:
        value = "flag"
    else:
        value = _code(str(action.metavar or action.dest.upper()))
    hidden = action.nargs == 0 or action.default in (None, argparse.SUPPRESS)  # flags, "not given"
    shown = "" if hidden else _code(str(_relative(action.default)))
    text = parser._get_formatter()._expand_help(action) if action.help else ""
    return f"| {names} | {value} | {shown} | {_cell(text)} |"


def _command_section(title: str, parser: argparse.ArgumentParser, summary: str) -> list[str]:
    lines = [f"## `{title}`", ""]
    if summary:
        lines += [_cell(summary).replace("\\|", "|") + ".", ""]
    if parser.description:
        lines += [textwrap.fill(" ".join(parser.description.split()), 110), ""]
    usage = parser.format_usage().strip().removeprefix("usage: ")
    lines += ["```text", usage, "```", ""]
    lines += ["| option | value | default | description |", "| --- | --- | --- | --- |"]
    lines += [_option_row(parser, a) for a in parser._actions if not isinstance(a, argparse._SubParsersAction)]
    return [*lines, ""]


def cli_markdown(parser: argparse.ArgumentParser | None = None) -> str:
    """The CLI reference page: one section per command with every option, its default and its help."""
    if parser is None:
        parser = importlib.import_module("crtraj.cli").build_parser()
    commands, helps = _subcommands(parser)
    lines = [
        "# Command-line reference",
        "",
        "Generated from `crtraj.cli.build_parser()` when the site is built: every command, option, default and",
        "help text below is the parser's own. Exit codes: 0 success; 1 a well-formed task that could not be",
        "done (its status on stderr); 2 bad input, one line `crtraj: error: ...` naming the file, key or flag.",
        "",
        "Commands: " + ", ".join(f"[`{name}`](#crtraj-{name.replace(' ', '-')})" for name in commands) + ".",
        "",
    ]
    lines += _command_section(parser.prog, parser, "")
    for name, sub in commands.items():
        lines += _command_section(f"{parser.prog} {name}", sub, helps.get(name, ""))
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the problem-file reference
def _options_modules() -> list[str]:
    """Every crtraj module that uses the options base (found in the source, so a new one is covered)."""
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        if "crtraj.core.options import" in path.read_text(encoding="utf-8"):
            rel = path.relative_to(ROOT).with_suffix("")
            names.append(".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts))
    return names


def _all_subclasses(cls: type) -> list[type]:
    out: list[type] = []
    for sub in cls.__subclasses__():
        out += [sub, *_all_subclasses(sub)]
    return out


def options_classes() -> list[type]:
    """The `Options` classes of the problem file's tables: SECTION is a known table or a sub-table of one,
    in the problem reader's table order."""
    for name in _options_modules():
        importlib.import_module(name)
    base = importlib.import_module("crtraj.core.options").Options
    tables = list(importlib.import_module("crtraj.io.problem").SECTIONS)
    found = {c for c in _all_subclasses(base) if c.SECTION.split(".")[0] in tables}
    return sorted(found, key=lambda c: (tables.index(c.SECTION.split(".")[0]), c.SECTION, c.__qualname__))


def _toml(value: Any, hint: Any) -> str:
    """`value` as a TOML literal (a tuple of key/value pairs, as the solver tables are held, is a table)."""
    if isinstance(value, tuple) and not value and "tuple[tuple[str" in str(hint).replace(" ", ""):
        return "{}"
    if isinstance(value, tuple) and value and all(isinstance(p, tuple) and len(p) == 2 for p in value):
        return "{ " + ", ".join(f"{k} = {_toml(v, None)}" for k, v in value) + " }"
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml(v, None) for v in value) + "]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, float) and not math.isfinite(value):
        return "inf" if value > 0 else ("-inf" if value < 0 else "nan")
    return repr(value)


def _type_name(hint: Any) -> str:
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    optional = len(args) < len(typing.get_args(hint))
    base = args[0] if optional and len(args) == 1 else hint
    name = {float: "float", int: "integer", bool: "bool", str: "string"}.get(base, "table or array")
    return f"{name} (optional)" if optional else name


def _bounds(spec: Any) -> str:
    if spec is None or not spec.read:
        return "checked by the class"
    parts = []
    if spec.choices is not None:
        parts.append("one of " + ", ".join(_code(c) for c in spec.choices))
    for op, v in ((">", spec.gt), (">=", spec.ge), ("<", spec.lt), ("<=", spec.le)):
        if v is not None:
            parts.append(f"{_cell(op)} {v:g}")
    return ", ".join(parts)


def _unit(doc: str, key: str) -> str:
    """The unit the class docstring gives in brackets after `key` (``key: ... (mm/s)``, ``key (s)``), else ''."""
    pattern = rf"(?<![\w.`'\"]){re.escape(key)}(?=\s*[:(/,])([^.;,]*?)\(([^()]{{1,100}})\)"
    for m in re.finditer(pattern, doc):
        if len(m.group(1)) <= 80:
            unit = _UNIT.match(m.group(2).strip())
            if unit:
                return unit.group(1)
    return ""


def _section_markdown(cls: type) -> list[str]:
    spec_key = "crtraj.option"
    hints = typing.get_type_hints(cls)
    doc = " ".join((cls.__doc__ or "").split())
    lines = [f"## `[{cls.SECTION}]`", "", f"Read by `{cls.__module__}.{cls.__qualname__}`.", ""]
    lines += ["| key | type | default | bounds | unit |", "| --- | --- | --- | --- | --- |"]
    subtables = []
    for f in dataclasses.fields(cls):
        spec = f.metadata.get(spec_key)
        if spec is None:
            continue
        if isinstance(getattr(f.default, "SECTION", None), str):
            subtables.append(f"[`[{f.default.SECTION}]`](#{f.default.SECTION.replace('.', '')})")
            continue  # a sub-table: its keys have their own table below
        default = "" if f.default is None else _code(_toml(f.default, hints[f.name]))
        row = [_code(f.name), _type_name(hints[f.name]), default, _bounds(spec), _unit(doc, f.name)]
        lines.append("| " + " | ".join(row) + " |")
    if subtables:
        lines += ["", "Sub-tables: " + ", ".join(subtables) + "."]
    if cls.__doc__:
        lines += ["", '??? note "What the keys mean (the class docstring)"', ""]
        lines += ["    " + ln if ln.strip() else "" for ln in inspect.cleandoc(cls.__doc__).splitlines()]
    return [*lines, ""]


def task_markdown() -> list[str]:
    """The `[task]` table's keys, from `crtraj.io.problem.TASK_KEYS` (the keys `Task.from_table` reads)."""
    keys = importlib.import_module("crtraj.io.problem").TASK_KEYS
    # a heading other than the options tables' (`## [section]`): this table is no `Options` class
    lines = ["## The `[task]` table", "", "Read by `crtraj.io.problem.Task` (not an options class).", ""]
    lines += ["| key | type | default | unit | meaning |", "| --- | --- | --- | --- | --- |"]
    for key, typ, default, unit, meaning in keys:
        lines.append(
            f"| {_code(key)} | {_cell(typ)} | {_code(default) if default else ''} | {unit} | {_cell(meaning)} |"
        )
    return [*lines, ""]


def problem_markdown() -> str:
    """The problem-file reference page: every options table, key by key."""
    classes = options_classes()
    lines = [
        "# Problem-file reference",
        "",
        "Generated from the code when the site is built: each table below is an options class of crtraj, and",
        "each row one field declared with `option(default, ...)` (`crtraj.core.options`), which checks a",
        "problem file and a Python caller alike. An empty default means *derived* (see the notes). Unknown",
        "keys are errors. Units: mm, rad, s, unless the row says otherwise.",
        "",
        "The `robot` and `[scene]` tables are described in [Problem files](../concepts/problems.md).",
        "",
        "Tables: `[task]`, " + ", ".join(f"`[{c.SECTION}]`" for c in classes) + ".",
        "",
        *task_markdown(),
    ]
    for cls in classes:
        lines += _section_markdown(cls)
    return "\n".join(lines)


# ----------------------------------------------------------------------------- the result-schema table
def schema_table() -> str:
    """The result schema's table from `crtraj.io.run_schema`; a missing module fails the build."""
    try:
        run_schema = importlib.import_module("crtraj.io.run_schema")
        return run_schema.schema_table_markdown()
    except (ImportError, AttributeError) as exc:
        if os.environ.get(ALLOW_MISSING_SCHEMA) == "1":
            log.info("result schema table left out (%s): %s", ALLOW_MISSING_SCHEMA, exc)
            return "!!! warning\n    The result-schema table is generated from `crtraj.io.run_schema`, missing here.\n"
        raise PluginError(
            f"architecture.md: cannot generate the result-schema table: crtraj.io.run_schema."
            f"schema_table_markdown() is not importable ({exc}); it comes with the result-schema change"
        ) from exc


# ----------------------------------------------------------------------------- the mkdocs events
def on_files(files: Any, config: Any) -> Any:
    """Add the generated reference pages to the site."""
    for page, make in ((CLI_PAGE, cli_markdown), (PROBLEM_PAGE, problem_markdown)):
        files.append(File.generated(config, page, content=make()))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Put the generated result-schema table where a page has the marker."""
    if SCHEMA_MARKER in markdown:
        markdown = markdown.replace(SCHEMA_MARKER, schema_table())
    return markdown
