"""The suite is hermetic: tests build what they need under tmp_path and never read machine paths."""

from __future__ import annotations

import ast
import os
import pathlib
import tempfile

import pytest

TESTS = pathlib.Path(__file__).parent
# Absolute locations whose content depends on the machine, not on the test.
MACHINE_PATHS = ("/tmp", "/var/tmp", "/home", "/root", "/opt", "/usr/share", "/mnt", "/media", "~/")


def _string_constants(path: pathlib.Path):
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            yield node.lineno, node.value


def test_no_test_names_a_machine_path():
    offenders = [f"{p.name}:{line}: {s!r}" for p in sorted(TESTS.glob("*.py")) if p.name != pathlib.Path(__file__).name
                 for line, s in _string_constants(p) if s.startswith(MACHINE_PATHS)]
    assert not offenders, "tests must build their inputs under tmp_path:\n" + "\n".join(offenders)


@pytest.mark.skipif(os.environ.get("FLOWSYNTH_HERMETIC") != "1", reason="only under scripts/test.sh")
def test_harness_gives_fresh_tmp_and_home():
    # scripts/test.sh (what .ci/run calls) points TMPDIR and HOME at fresh sibling folders of one run folder and
    # RAY_TMPDIR at a fresh one; the Warp kernel cache lives in the repository, not under HOME.
    root = pathlib.Path(__file__).resolve().parents[1]
    tmp = pathlib.Path(tempfile.gettempdir()).resolve()
    home = pathlib.Path(os.environ["HOME"]).resolve()
    assert tmp.name == "tmp" and home.name == "home" and home.parent == tmp.parent
    assert tmp.parent.name.startswith(("fs.", "run."))
    assert not any(home.iterdir()) or all(p.name.startswith(".") for p in home.iterdir())
    assert pathlib.Path(os.environ["WARP_CACHE_PATH"]).resolve().is_relative_to((root / ".cache").resolve())
    # Sockets live under TMPDIR (multiprocessing's resource sharer: how DataLoader workers send tensors) and
    # RAY_TMPDIR, and an AF_UNIX path may not exceed 107 bytes: the harness keeps both short however long the
    # checkout's path is (under a 65-character checkout, DataLoader workers hung and Ray failed to start)
    listener = os.path.join(tempfile.gettempdir(), "pymp-k2x9_a1b", "listener-3q8w_0zr")
    ray_tmp = os.environ["RAY_TMPDIR"]
    socket = os.path.join(ray_tmp, "ray", "session_2026-11-24_23-48-42_950359_1234567", "sockets", "plasma_store")
    assert pathlib.Path(ray_tmp).is_dir()
    for path in (listener, socket):
        assert len(path.encode()) <= 107, path
