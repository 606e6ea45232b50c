"""The fork guard (``flowsynth.processes``): checked where flowsynth reaches Warp and where it enters Newton.

This CPU machine cannot initialise CUDA, so the parent's ``cuda_initialised`` is made to answer True (the at-fork
hook reads it there, before each fork) and forked children report what they raised.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp

import pytest

import flowsynth as fs
from flowsynth import processes
from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.datasets.device_batches import SceneSet
from flowsynth.kernels import wp_runtime
from flowsynth.scene import physics

TIMEOUT = 300  # [s]
CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(2, 3), max_objects=3)


def _report(q, job) -> None:
    try:
        job()
        q.put("ran")
    except Exception as e:  # reported to the parent, which asserts on it
        q.put(f"{type(e).__name__}: {e}")


def _forked(job) -> str:
    """What ``job`` did in a child forked from this process: "ran", or the exception it raised."""
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_report, args=(q, job))
    p.start()
    got = q.get(timeout=TIMEOUT)
    p.join(TIMEOUT)
    assert p.exitcode == 0
    return got


def _in_forked_child(job, cuda: bool, monkeypatch) -> str:
    monkeypatch.setattr(processes, "cuda_initialised", lambda: cuda)
    return _forked(job)


def _physics_scene_0():
    BouncingThings(CFG, outputs=["depth"], seed=5).scene(0)


def _grandchild_without_cuda_of_its_own():
    """Fork again from a child that did not initialise CUDA itself, and report the grandchild's answer."""
    processes.cuda_initialised = lambda: False  # this child's own state (a forked copy: the parent keeps its own)
    got = _forked(wp_runtime)
    if got.startswith("ForkError"):
        raise fs.ForkError(got)


@pytest.mark.parametrize("job", [wp_runtime, _physics_scene_0, _grandchild_without_cuda_of_its_own],
                         ids=["wp_runtime", "physics, a cached Newton scene", "a grandchild"])
def test_a_child_forked_after_cuda_refuses_at_warp_and_newton(job, monkeypatch):
    """The same job runs in a child forked from a parent without CUDA and raises ForkError, saying what to do, in one
    forked from a parent with CUDA: at ``wp_runtime`` though the parent had initialised Warp already (its cache does
    not skip the check), at Newton though the parent had built the clip's Newton scene (the child would reset and
    reuse it, without a new model's set-up), and in a grandchild whose own parent never initialised CUDA."""
    wp_runtime()
    _physics_scene_0()  # the parent's Warp and Newton caches, inherited by the children
    assert physics._FREE or physics._SCENES  # a Newton scene a child would reset and reuse
    assert _in_forked_child(job, False, monkeypatch) == "ran"
    got = _in_forked_child(job, True, monkeypatch)
    assert got.startswith("ForkError") and "fs.datasets.loader" in got and "forkserver" in got, got


def test_the_guard_is_no_blanket_ban(monkeypatch):
    """A kinematic scene and its host tables (what DeviceBatches' scene workers make) reach neither Warp nor Newton:
    a child forked after CUDA makes them."""
    kinematic = dataclasses.replace(CFG, motion="kinematic")
    scenes = SceneSet(kinematic, 5, BouncingThings(kinematic, outputs=["depth"]).plan)
    assert _in_forked_child(lambda: scenes[0], True, monkeypatch) == "ran"
