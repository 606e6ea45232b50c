"""Newton scene reuse (``physics.SCENE_REUSE``): a clip run on a kept scene, its arrays reset, is the clip a fresh scene
gives, bit for bit, whatever clips ran before it.

The oracle is the fresh build: the same samples made with reuse off (``SCENE_REUSE = False``, caches cleared), each
on a Newton model finalised, a pipeline built and a substep captured for it alone. Reuse runs the samples in index
order and in reverse, so each sample follows different ones; poses, velocities, substeps and rendered outputs must
equal the fresh ones exactly, and reuse must actually have happened (fewer scenes built than clips).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth.scene import motion, physics
from flowsynth.scene.sampling import sample_layout, sample_scene

INDICES = list(range(12))
BASE = fs.BouncingThingsConfig(width=32, height=24, num_frames=3, flow_px=None, size_levels=1,
                               object_size=(0.5, 0.5), room_size=(5.0, 4.0, 3.0), camera_clearance=1.0,
                               min_speed=1.0, max_speed=4.0, angular_speed=(0.0, 3.0))
CONFIGS = {
    # one asset and size: the key is the object count alone (2-4), so most clips reuse a scene
    "spheres": replace(BASE, assets=("sphere",), num_objects=(2, 4)),
    # convex hulls falling under gravity with friction, crowded so that they collide
    "falling_rocks": replace(BASE, assets=("rock",), num_objects=(3, 4), gravity=(0.0, 0.0, -9.81),
                             restitution=0.6, friction=0.3, num_frames=4),
    # two kinds in random order: keys differ by the order of the kinds as well
    "capsules_crystals": replace(BASE, assets=("capsule", "crystal"), num_objects=(2, 2)),
}
OUTPUTS = ("depth", "flow_fw", "instance")


def _count_builds(monkeypatch) -> list:
    built = []
    init = physics.NewtonScene.__init__

    def counting(self, *args, **kwargs):
        built.append(args[3])  # substeps
        init(self, *args, **kwargs)

    monkeypatch.setattr(physics.NewtonScene, "__init__", counting)
    return built


def _clips(cfg, order, reuse: bool, monkeypatch, render: bool) -> tuple[dict, int]:
    """{index: (poses (n, T, 4, 4), substeps, outputs)} of ``order``'s samples, and the Newton scenes built."""
    fs.clear_caches()
    monkeypatch.setattr(physics, "SCENE_REUSE", reuse)
    monkeypatch.setattr(physics, "FREE_FLIGHT", False)  # every clip on the full model (tests/test_free_flight.py)
    built = _count_builds(monkeypatch)
    out = {}
    for i in order:
        scene = sample_scene(cfg, 0, i)
        poses = np.stack([o.poses for o in scene.objects if not o.background])
        outputs = fs.render(scene, OUTPUTS, threads=1) if render else {}
        out[i] = (poses, scene.meta["substeps"], outputs)
    monkeypatch.undo()
    return out, len(built)


@pytest.mark.parametrize("name", list(CONFIGS))
def test_reused_scenes_give_the_fresh_clips_in_any_order(monkeypatch, name):
    cfg = CONFIGS[name]
    render = name == "spheres"
    fresh, built_fresh = _clips(cfg, INDICES, False, monkeypatch, render)
    forward, built_forward = _clips(cfg, INDICES, True, monkeypatch, render)
    backward, built_backward = _clips(cfg, INDICES[::-1], True, monkeypatch, render)
    fs.clear_caches()
    assert built_fresh == len(INDICES)
    assert built_forward < len(INDICES) and built_backward < len(INDICES), "no scene was reused"
    moved = 0
    for i in INDICES:
        poses, substeps, outputs = fresh[i]
        moved += int(not np.array_equal(poses[:, 1:], poses[:, :-1]))
        for other in (forward, backward):
            assert other[i][1] == substeps
            np.testing.assert_array_equal(other[i][0], poses, err_msg=f"{name}, sample {i}")
            for key in OUTPUTS if render else ():
                assert torch.equal(other[i][2][key], outputs[key]), f"{name}, sample {i}, {key}"
    assert moved == len(INDICES)


def test_reuse_after_a_contact_overflow(monkeypatch):
    """With room for one contact, a colliding clip fills the buffer and is simulated again at Newton's estimate: both
    scenes (the small and the retried) are kept and reused, and the trajectories stay the fresh ones."""
    cfg = replace(CONFIGS["falling_rocks"], num_objects=(4, 4))
    layouts = [sample_layout(cfg, 0, i) for i in range(4)]

    def run(reuse: bool, order):
        fs.clear_caches()
        monkeypatch.setattr(physics, "SCENE_REUSE", reuse)
        monkeypatch.setattr(physics, "_contact_capacity", lambda n: 1)
        monkeypatch.setattr(physics, "FREE_FLIGHT", False)
        built = _count_builds(monkeypatch)
        got = {i: motion.simulate(cfg, layouts[i].assets, layouts[i].initial) for i in order}
        monkeypatch.undo()
        return got, len(built)

    fresh, built_fresh = run(False, range(4))
    reused, built_reused = run(True, [3, 1, 0, 2])
    fs.clear_caches()
    assert built_fresh > 4  # some clip filled the buffer and was simulated again
    assert built_reused < built_fresh  # kept from a key's second clip on, small and retried scenes are reused
    for i in range(4):
        for k in ("poses", "velocity", "angular_velocity"):
            np.testing.assert_array_equal(getattr(reused[i], k), getattr(fresh[i], k))


def _arrays(scene) -> tuple[dict, set]:
    """Every Warp array an attribute of the scene reaches (model, states, control, contacts, pipeline, solver), by
    attribute path, as numpy copies; and their data pointers."""
    import warp as wp

    out, ptrs, seen, stack = {}, set(), set(), [("scene", scene)]
    while stack:
        path, x = stack.pop()
        if id(x) in seen:
            continue
        seen.add(id(x))
        if isinstance(x, wp.array):
            if x.ptr is not None and x.size:
                out[path] = x.numpy().copy()
                ptrs.add(x.ptr)
        elif isinstance(x, (list, tuple)):
            stack.extend((f"{path}[{k}]", v) for k, v in enumerate(x))
        elif isinstance(x, dict):
            stack.extend((f"{path}[{k!r}]", v) for k, v in x.items())
        elif type(x).__module__.split(".")[0] in ("newton", "flowsynth") and hasattr(x, "__dict__"):
            stack.extend((f"{path}.{k}", v) for k, v in vars(x).items() if k not in ("graph", "_snapshot"))
    return out, ptrs


def test_a_reset_scene_equals_a_fresh_one(monkeypatch):
    """Array by array: a scene that ran one clip and was reset for another sample equals a scene built and captured
    for that sample, and so does every memory region of its captured substep."""
    monkeypatch.setattr(physics, "SCENE_REUSE", True)
    cfg = replace(CONFIGS["falling_rocks"], num_objects=(3, 3))
    a, b = (sample_layout(cfg, 0, i) for i in (0, 1))
    n_sub = physics.choose_substeps(cfg, [x.size for x in a.assets])
    cap = physics._contact_capacity(3)
    assert physics._scene_key(cfg, a.assets, n_sub, cap) == physics._scene_key(cfg, b.assets, n_sub, cap)
    assert not np.array_equal(a.initial.position, b.initial.position)
    used = physics.NewtonScene(cfg, a.assets, a.initial, n_sub, cap)
    used.reusable = True
    for _ in range(3):
        used.advance_frame()
    assert used.reset(b.initial)
    fresh, again = (physics.NewtonScene(cfg, b.assets, b.initial, n_sub, cap) for _ in range(2))
    for scene in (fresh, again):
        scene.reusable = True
        scene.advance_frame()  # captures (and steps; compared below only after a reset to the start)
        assert scene.reset(b.initial)
    (got, ptrs), (want, _), (want_again, _) = _arrays(used), _arrays(fresh), _arrays(again)
    assert got.keys() == want.keys() == want_again.keys() and len(got) > 100
    # arrays Newton allocates uninitialised (wp.empty) and flowsynth never fills differ between two fresh builds
    # of one sample: no reuse can match them, and nothing flowsynth runs reads them
    garbage = {p for p in want if not np.array_equal(want[p], want_again[p])}
    assert garbage <= {"scene.solver.model.bvh_shape_world_transforms"}, garbage
    for path in want.keys() - garbage:
        np.testing.assert_array_equal(got[path], want[path], err_msg=path)
    # the captured substep's memory, region by region: the scene's own arrays as above; the scratch Newton allocates
    # while the substep is captured (kept by the graph alone, often uninitialised, so written before it is read,
    # or two fresh builds would step differently) is restored too, and the clips above show it holds no state
    regions = [used._snapshot, fresh._snapshot, again._snapshot]
    assert len(regions[0]) == len(regions[1]) == len(regions[2]) > len(got) // 4
    own = 0
    for (view_u, _), (view_f, _), (view_a, _) in zip(*regions):
        if view_u.ctypes.data in ptrs and np.array_equal(view_f, view_a):
            own += 1
            np.testing.assert_array_equal(view_u, view_f)
    assert own >= len(regions[0]) // 2
    for _ in range(3):
        used.advance_frame()
        fresh.advance_frame()
    for x, y in zip(used.read(), fresh.read()):
        np.testing.assert_array_equal(x, y)


def test_reuse_needs_warps_capture_regions():
    """``physics._graph_memory_snapshot`` reads Warp's private ``Graph._apic_capture._regions``; without it no scene is
    ever reused (correct, but every clip builds and captures again)."""
    import warp as wp

    cfg = replace(CONFIGS["spheres"], num_objects=(2, 2))
    layout = sample_layout(cfg, 0, 0)
    scene = physics.NewtonScene(cfg, layout.assets, layout.initial, 2)
    scene.advance_frame()
    regions = getattr(getattr(scene.graph, "_apic_capture", None), "_regions", None)
    assert isinstance(regions, dict) and regions, (
        "Warp's CPU graph no longer keeps _apic_capture._regions: update "
        f"flowsynth.scene.physics._graph_memory_snapshot for Warp {wp.__version__}, or Newton scenes are never reused")
    assert all(isinstance(r, tuple) and len(r) == 4 for r in regions.values())
    assert physics._graph_memory_snapshot(scene.graph) is not None
