"""The build cache: entries reused when the key is the same, rebuilt when it changes, corrupt or foreign
entries detected and rebuilt (never loaded), atomic builds, the no-compiler path, list and clear."""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from conftest import require_tool

from crtraj.core.build_cache import MANIFEST, BuildCache, BuildKey, default_root, find_compiler
from crtraj.core.fileio import MARKER
from crtraj.model.codegen import codegen_builder, compiled_functions

# A stand-in compiler for the cache's own logic: the cache only records its identity; the build steps
# below write their "library" bytes themselves.
FAKE_CC = sys.executable


class Builder:
    """A build step that writes known bytes as the library and counts its calls."""

    def __init__(self, payload: bytes = b"\x7fELF fake library") -> None:
        self.payload = payload
        self.calls = 0

    def __call__(self, folder: Path, compiler: str) -> Path:
        self.calls += 1
        assert compiler == FAKE_CC
        assert [p.name for p in folder.iterdir()] == [MARKER], "a build starts in a folder holding only the marker"
        lib = folder / "libthing.so"
        lib.write_bytes(self.payload)
        return lib


def robot_key(robot_file: Path) -> BuildKey:
    """A key from a robot file's content, as the validity kernels key theirs."""
    return BuildKey("thing", {"robot": robot_file.read_text(), "generator": 1})


def test_reused_when_unchanged_and_rebuilt_when_the_robot_file_changes(tmp_path):
    robot = tmp_path / "robot.toml"
    robot.write_text('[robot]\nname = "a"\n')
    b = Builder()
    lib1 = BuildCache(tmp_path / "c", compiler=FAKE_CC).library(robot_key(robot), b)
    assert lib1.read_bytes() == b.payload and b.calls == 1
    # a new process (a new cache object) finds the same entry: no build
    cache2 = BuildCache(tmp_path / "c", compiler=FAKE_CC)
    assert cache2.library(robot_key(robot), b) == lib1 and b.calls == 1 and cache2.builds == 0
    robot.write_text('[robot]\nname = "a"\ncable_radius = 2.0\n')
    lib2 = cache2.library(robot_key(robot), b)
    assert b.calls == 2 and lib2 != lib1 and lib1.exists()
    assert {e.path for e in cache2.entries()} == {lib1.parent, lib2.parent}
    assert all(e.valid for e in cache2.entries())


def test_key_is_canonical_and_covers_environment(tmp_path):
    c = BuildCache(tmp_path, compiler=FAKE_CC)
    k1 = BuildKey("thing", {"a": np.array([1.0, 2.0]), "b": 3})
    k2 = BuildKey("thing", {"b": 3, "a": [1.0, 2.0]})
    assert c.digest(k1) == c.digest(k2)
    assert c.digest(k1) != c.digest(BuildKey("thing", {"a": [1.0, 2.0], "b": 4}))
    env = c.environment()
    assert env["casadi"] == ca.__version__ and env["compiler"]["path"]
    assert f"{sys.version_info[0]}.{sys.version_info[1]}" in env["python"]
    # another compiler (its identity) is another environment, so another entry
    other = BuildCache(tmp_path, compiler=__file__)  # any other file stands for another compiler
    assert other.digest(k1) != c.digest(k1)
    with pytest.raises(ValueError, match="build key name"):
        BuildKey("../x")


@pytest.mark.parametrize("damage", ["library_bytes", "library_missing", "manifest_garbage", "manifest_sha"])
def test_corrupt_entry_is_detected_and_rebuilt(tmp_path, damage):
    key = BuildKey("thing", {"v": 1})
    b = Builder()
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    lib = cache.library(key, b)
    if damage == "library_bytes":
        lib.write_bytes(b"\x7fELF evil library")  # same length or not, the hash differs
    elif damage == "library_missing":
        lib.unlink()
    elif damage == "manifest_garbage":
        (lib.parent / MANIFEST).write_text("{not json")
    else:
        man = json.loads((lib.parent / MANIFEST).read_text())
        man["sha256"] = "0" * 64
        (lib.parent / MANIFEST).write_text(json.dumps(man))
    assert cache.lookup(key) is None
    assert [(e.valid, e.state.split(":")[0]) for e in cache.entries()] == [
        (False, "unreadable manifest" if damage == "manifest_garbage" else "corrupt")
    ]
    again = cache.library(key, b)
    assert b.calls == 2 and again == lib and again.read_bytes() == b.payload
    assert cache.lookup(key) == lib
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no temporary folders left"


def test_foreign_entry_under_the_right_name_is_rebuilt(tmp_path):
    """An intact entry of another key moved to this key's folder name is not loaded."""
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    mine, theirs = BuildKey("thing", {"v": 1}), BuildKey("thing", {"v": 2})
    foreign = cache.library(theirs, Builder(b"\x7fELF theirs"))
    target = cache.entry_dir(mine)
    shutil.copytree(foreign.parent, target)
    assert cache.lookup(mine) is None
    b = Builder(b"\x7fELF mine")
    assert cache.library(mine, b).read_bytes() == b"\x7fELF mine" and b.calls == 1
    # an entry made in another environment (another CasADi, say) is foreign too
    man = json.loads((target / MANIFEST).read_text())
    man["env"]["casadi"] = "0.0.1"
    (target / MANIFEST).write_text(json.dumps(man))
    assert cache.lookup(mine) is None


def test_failed_build_leaves_the_cache_as_it_was(tmp_path):
    cache = BuildCache(tmp_path, compiler=FAKE_CC)

    def broken(folder: Path, compiler: str) -> Path:
        (folder / "half.c").write_text("int")
        raise RuntimeError("C compiler failed")

    with pytest.raises(RuntimeError, match="C compiler failed"):
        cache.library(BuildKey("thing"), broken)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RuntimeError, match="no library written"):
        cache.library(BuildKey("thing"), lambda folder, cc: tmp_path / "elsewhere.so")
    assert cache.entries() == []


def test_without_a_compiler_nothing_is_built_and_it_says_so_once(tmp_path, monkeypatch):
    out = io.StringIO()
    cache = BuildCache(tmp_path, compiler=None, notice=out)
    b = Builder()
    assert cache.library(BuildKey("thing"), b) is None
    assert cache.library(BuildKey("other"), b) is None
    assert b.calls == 0
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 and "no C compiler" in lines[0] and "interpreted" in lines[0]
    monkeypatch.setenv("CRTRAJ_CC", "none")
    assert find_compiler() is None
    monkeypatch.setenv("CRTRAJ_CACHE_DIR", str(tmp_path / "here"))
    assert default_root() == tmp_path / "here" and BuildCache().root == tmp_path / "here"


def test_clear_removes_only_cache_folders(tmp_path):
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    cache.library(BuildKey("thing", {"v": 1}), Builder())
    cache.library(BuildKey("thing", {"v": 2}), Builder())
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "project").mkdir()
    (tmp_path / ".tmp-thing-dead").mkdir()  # left by a killed build
    assert cache.clear() == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "project"]


def test_compiled_casadi_function_round_trip(tmp_path):
    """Real codegen + compiler: the cached library evaluates like the CasADi graph, and a hit skips make()."""
    cc = require_tool("cc", "gcc")
    x = ca.SX.sym("x", 3)
    calls = []

    def make():
        calls.append(1)
        return [ca.Function("bc_norm", [x], [ca.sqrt(ca.sumsqr(x)) + ca.sin(x[0])])]

    key = BuildKey("bc_test", {"v": 1})
    f = compiled_functions(BuildCache(tmp_path, compiler=cc), key, ["bc_norm"], make)["bc_norm"]
    g = compiled_functions(BuildCache(tmp_path, compiler=cc), key, ["bc_norm"], make)["bc_norm"]
    v = np.array([0.3, -1.2, 2.5])
    ref = np.linalg.norm(v) + np.sin(v[0])
    assert calls == [1]
    assert abs(float(f(v)) - ref) < 1e-12 and abs(float(g(v)) - ref) < 1e-12


def test_clear_keeps_a_users_folder_that_holds_a_manifest(tmp_path):
    """--clear deletes only folders carrying crtraj's marker: a user's folder with a manifest.json stays."""
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    lib = cache.library(BuildKey("thing", {"v": 1}), Builder())
    user = tmp_path / "photos-2024"
    user.mkdir()
    (user / MANIFEST).write_text('{"format": 2, "mine": true}')
    (user / "a.jpg").write_bytes(b"\xff\xd8 not ours")
    forged = tmp_path / "thing-0123"  # a marker of another kind or version is not crtraj's entry marker
    forged.mkdir()
    (forged / MANIFEST).write_text("{}")
    (forged / MARKER).write_text('{"crtraj_folder": "build-cache-entry", "version": 99}')
    os.mkfifo(tmp_path / "fifo-dir")  # not a folder: not listed, not touched
    (tmp_path / "odd").mkdir()
    os.mkfifo(tmp_path / "odd" / MANIFEST)  # unreadable and unmarked: listed as both, kept
    states = {e.path.name: e.state for e in cache.entries()}
    assert states["odd"].startswith("unreadable manifest: not a regular file")
    assert states["odd"].endswith("; not crtraj's (no marker; left alone)")
    assert states[user.name].startswith("not crtraj's") and states[forged.name].startswith("not crtraj's")
    assert states[lib.parent.name] == "ok"
    assert cache.clear() == 1
    assert not lib.parent.exists()
    assert (user / "a.jpg").read_bytes() == b"\xff\xd8 not ours" and (forged / MARKER).exists()
    assert (tmp_path / "odd" / MANIFEST).exists() and (tmp_path / "fifo-dir").exists()


def test_a_file_where_an_entry_belongs_is_moved_aside_and_rebuilt(tmp_path):
    """A regular file (or a user's folder) under an entry's name is kept, renamed aside; the entry is built."""
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    key = BuildKey("thing", {"v": 1})
    cache.entry_dir(key).write_bytes(b"user data")
    lib = cache.library(key, Builder())
    assert lib.read_bytes() == Builder().payload and cache.lookup(key) == lib
    aside = [p for p in tmp_path.iterdir() if p.name.startswith(".aside-")]
    assert len(aside) == 1 and aside[0].read_bytes() == b"user data"


def test_an_entry_that_does_not_load_is_rebuilt_once_then_reported(tmp_path):
    """A library whose hash matches its manifest but fails to load is rebuilt once; twice is an error."""
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    key = BuildKey("thing", {"v": 1})
    b = Builder()
    first = cache.library(key, b)
    loads = []

    def loader(lib: Path) -> bytes:
        loads.append(lib)
        if len(loads) == 1:
            raise OSError(f"{lib}: invalid ELF header")
        return lib.read_bytes()

    assert cache.load(key, b, loader) == b.payload
    assert b.calls == 2 and len(loads) == 2 and cache.lookup(key) is not None

    def never(lib: Path) -> None:
        raise OSError("invalid ELF header")

    with pytest.raises(RuntimeError, match=r"rebuilt library does not load \(invalid ELF header\)"):
        cache.load(key, b, never)
    assert b.calls == 3 and first.parent.name == cache.entry_dir(key).name


def test_list_shows_unreadable_manifests(tmp_path):
    """An entry whose manifest is a FIFO or not JSON is listed as unreadable, not skipped (and never hangs)."""
    cache = BuildCache(tmp_path, compiler=FAKE_CC)
    lib1 = cache.library(BuildKey("thing", {"v": 1}), Builder())
    lib2 = cache.library(BuildKey("thing", {"v": 2}), Builder())
    (lib1.parent / MANIFEST).unlink()
    os.mkfifo(lib1.parent / MANIFEST)
    (lib2.parent / MANIFEST).write_text("{not json")
    states = sorted(e.state for e in cache.entries())
    assert len(states) == 2 and all(s.startswith("unreadable manifest: ") for s in states)
    assert any("regular file" in s for s in states), states
    assert cache.clear() == 2 and cache.entries() == []


def _norm_functions(calls: list[int]):
    x = ca.SX.sym("x", 3)

    def make():
        calls.append(1)
        return [ca.Function("bc_norm", [x], [ca.sqrt(ca.sumsqr(x)) + ca.sin(x[0])])]

    return make


def test_a_corrupt_compiled_library_whose_hash_matches_is_rebuilt_once_and_works(tmp_path):
    """A cached library replaced by junk, its manifest hash updated to match (so it verifies), fails to load:
    compiled_functions rebuilds it once and the rebuilt functions evaluate like the CasADi graph."""
    cc = require_tool("cc", "gcc")
    calls: list[int] = []
    key = BuildKey("bc_corrupt", {"v": 1})
    # built, never loaded in this process (a library loaded here must not be rewritten under it)
    lib = BuildCache(tmp_path, compiler=cc).library(key, codegen_builder(_norm_functions(calls), key.name))
    junk = b"\x7fELF" + b"\x00" * 60
    lib.unlink()
    lib.write_bytes(junk)
    man = json.loads((lib.parent / MANIFEST).read_text())
    man.update(size=len(junk), sha256=hashlib.sha256(junk).hexdigest())
    (lib.parent / MANIFEST).write_text(json.dumps(man))
    cache = BuildCache(tmp_path, compiler=cc)
    assert cache.lookup(key) == lib  # it passes the hash check
    f = compiled_functions(cache, key, ["bc_norm"], _norm_functions(calls))["bc_norm"]
    v = np.array([0.3, -1.2, 2.5])
    assert abs(float(f(v)) - (np.linalg.norm(v) + np.sin(v[0]))) < 1e-12
    assert cache.builds == 1 and len(calls) == 2
    assert cache.lookup(key) is not None and cache.lookup(key).read_bytes() != junk


def test_a_compiled_library_that_does_not_load_after_its_rebuild_is_reported_in_one_line(tmp_path):
    """A compiler whose output never loads: built, rebuilt once, then one RuntimeError line naming the entry."""
    fake = tmp_path / "fake-cc"
    fake.write_text('#!/bin/sh\nwhile [ $# -gt 0 ]; do [ "$1" = "-o" ] && printf "not a library" > "$2"; shift; done\n')
    fake.chmod(0o755)
    calls: list[int] = []
    cache = BuildCache(tmp_path / "cache", compiler=str(fake))
    key = BuildKey("bc_junk", {"v": 1})
    with pytest.raises(RuntimeError) as info:
        compiled_functions(cache, key, ["bc_norm"], _norm_functions(calls))
    msg = str(info.value)
    assert "\n" not in msg and "rebuilt library does not load" in msg and str(cache.entry_dir(key)) in msg
    assert cache.builds == 2 and len(calls) == 2
