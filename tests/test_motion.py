"""Motion: physics keeps meshes apart and inside the room with speeds in the band; kinematic is exact;
kinematic and static never import Newton.

Penetration is measured with python-fcl (trimesh's CollisionManager) on the visual meshes, independent of
Newton's own collision detection.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.scene.motion import (
    InitialState,
    choose_substeps,
    reflect_in_box,
    simulate,
)
from flowsynth.scene.sampling import sample_layout
from oracle import max_penetration

ROOT = Path(__file__).resolve().parents[1]
# Deepest allowed overlap of two visual meshes, and deepest allowed excursion of a vertex beyond a wall,
# as a fraction of the (smaller) object's size.
PENETRATION_TOL = 0.01
# Relative slack on speeds read from the float32 physics state (float32 round-off is ~1e-7).
SPEED_RTOL = 1e-5
# Relative slack on speeds from frame-to-frame displacements (float32 positions over a >= 4 cm chord).
CHORD_RTOL = 1e-3

# A small crowded room so objects collide often: 8-10 objects of 0.3-0.6 m in 3 x 3.5 x 3 m.
SLOW = BouncingThingsConfig(room_size=(4.0, 3.5, 3.0), camera_clearance=1.0, num_objects=(8, 10),
                            object_size=(0.3, 0.6), angular_speed=(0.0, 3.0), num_frames=24, width=64,
                            height=48,
                            min_speed=1.0, max_speed=3.0, flow_px=None)
# One frame's motion (up to 12 / 24 = 0.5 m) exceeds the smallest object (0.3 m).
FAST = replace(SLOW, min_speed=6.0, max_speed=12.0)
FALLING = replace(SLOW, min_speed=0.5, max_speed=4.0, gravity=(0.0, 0.0, -9.81), restitution=0.6,
                  friction=0.3)
CASES = [("slow", SLOW, 0), ("slow", SLOW, 1), ("slow", SLOW, 2), ("fast", FAST, 0), ("fast", FAST, 1),
         ("falling", FALLING, 0)]


@pytest.fixture(scope="module")
def runs():
    """(cfg, layout, trajectory) per case, simulated once."""
    out = {}
    for name, cfg, index in CASES:
        layout = sample_layout(cfg, 0, index)
        out[name, index] = (cfg, layout, simulate(cfg, layout.assets, layout.initial))
    return out


def max_wall_excursion(cfg, assets, poses) -> float:
    """Farthest any mesh vertex gets outside the room over all frames / that object's size (<= 0 inside)."""
    lo, hi = (np.asarray(b) for b in cfg.room_bounds)
    worst = -np.inf
    for i, a in enumerate(assets):
        V = np.einsum("tij,vj->tvi", poses[:, i, :3, :3], a.mesh.vertices) + poses[:, i, None, :3, 3]
        worst = max(worst, float(max((lo - V).max(), (V - hi).max())) / a.size)
    return worst


@pytest.mark.parametrize("name, index", [(n, i) for n, _, i in CASES])
def test_physics_meshes_never_interpenetrate(runs, name, index):
    cfg, layout, traj = runs[name, index]
    assert traj.poses.shape == (cfg.num_frames, len(layout.assets), 4, 4)
    assert max_penetration(layout.assets, traj.poses) <= PENETRATION_TOL


@pytest.mark.parametrize("name, index", [(n, i) for n, _, i in CASES])
def test_physics_objects_stay_in_the_room(runs, name, index):
    cfg, layout, traj = runs[name, index]
    assert max_wall_excursion(cfg, layout.assets, traj.poses) <= PENETRATION_TOL


@pytest.mark.parametrize("name, index", [(n, i) for n, _, i in CASES])
def test_physics_speeds_stay_in_the_band(runs, name, index):
    cfg, _, traj = runs[name, index]
    speed = np.linalg.norm(traj.velocity, axis=-1)
    assert speed.min() >= cfg.min_speed * (1 - SPEED_RTOL) and speed.max() <= cfg.max_speed * (1 + SPEED_RTOL)
    w = np.linalg.norm(traj.angular_velocity, axis=-1)
    w_lo, w_hi = cfg.angular_speed
    assert w.min() >= w_lo * (1 - SPEED_RTOL) and w.max() <= w_hi * (1 + SPEED_RTOL)
    # Displacement per frame: never faster than max_speed (plus what gravity adds within one substep,
    # before that substep's clamp); where the direction did not change within the frame (no contact), not
    # slower than min_speed either.
    p = traj.poses[:, :, :3, 3]
    chord = np.linalg.norm(np.diff(p, axis=0), axis=-1) * cfg.fps
    gravity_kick = np.linalg.norm(cfg.gravity) / (cfg.fps * traj.substeps)
    assert chord.max() <= cfg.max_speed * (1 + CHORD_RTOL) + gravity_kick
    u = traj.velocity / np.linalg.norm(traj.velocity, axis=-1, keepdims=True)
    straight = (u[1:] * u[:-1]).sum(-1) > 1 - 1e-6
    assert chord[straight].min() >= cfg.min_speed * (1 - CHORD_RTOL) - gravity_kick
    assert (~straight).sum() > 0, "no collisions happened: the test scene is too sparse"


@pytest.mark.parametrize("name, index", [(n, i) for n, _, i in CASES])
def test_physics_poses_are_rigid(runs, name, index):
    _, _, traj = runs[name, index]
    R = traj.poses[..., :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    assert (np.linalg.det(R) > 0).all()
    bottom = np.broadcast_to([0.0, 0.0, 0.0, 1.0], R.shape[:-2] + (4,))
    np.testing.assert_array_equal(traj.poses[..., 3, :], bottom)


def test_physics_is_deterministic(runs):
    cfg, layout, traj = runs["slow", 0]
    again = simulate(cfg, layout.assets, layout.initial)
    np.testing.assert_array_equal(again.poses, traj.poses)


def test_first_frame_is_the_initial_state(runs):
    _, layout, traj = runs["slow", 1]
    np.testing.assert_allclose(traj.poses[0, :, :3, 3], layout.initial.position, atol=1e-6)
    np.testing.assert_allclose(traj.poses[0, :, :3, :3], layout.initial.rotation, atol=1e-6)


@pytest.mark.parametrize("name, cfg, index", [("slow", SLOW, 1), ("fast", FAST, 0), ("falling", FALLING, 1)])
def test_bodies_without_joints_move_as_with_free_joints(monkeypatch, name, cfg, index):
    """The bodies have no joint (faster); Newton's free joint constrains nothing, so four colliding frames
    with one per body (``add_body``, the reference) agree to float32 round-off (measured <= 6e-6)."""
    from flowsynth.scene import physics

    cfg = replace(cfg, num_frames=4)
    layout = sample_layout(cfg, 0, index)
    got = simulate(cfg, layout.assets, layout.initial)
    monkeypatch.setattr(physics, "_FREE_JOINTS", True)
    ref = simulate(cfg, layout.assets, layout.initial)
    assert not np.array_equal(got.poses[1:], got.poses[:-1])  # they move
    np.testing.assert_allclose(got.poses, ref.poses, rtol=0, atol=1e-5)
    np.testing.assert_allclose(got.velocity, ref.velocity, rtol=0, atol=1e-4)
    np.testing.assert_allclose(got.angular_velocity, ref.angular_velocity, rtol=0, atol=1e-4)


@pytest.mark.parametrize("name, cfg, index", [("slow", SLOW, 0), ("fast", FAST, 1), ("falling", FALLING, 0)])
def test_contact_capacity_never_changes_a_trajectory(monkeypatch, name, cfg, index):
    """The collision pipeline holds a few contact slots per shape (and at least (N + 1)^2, see
    ``physics._contact_capacity``) instead of Newton's estimate (its own default, the reference here): colliding
    clips come out bit for bit the same. With room for one contact
    only, the full buffer is noticed and the clip simulated again with Newton's estimate: the same again."""
    from flowsynth.scene import physics

    cfg = replace(cfg, num_frames=6)
    layout = sample_layout(cfg, 0, index)
    sims = []  # every simulation's Newton scene

    class Spy(physics.NewtonScene):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            sims.append(self)

    monkeypatch.setattr(physics, "NewtonScene", Spy)
    monkeypatch.setattr(physics, "SCENE_REUSE", False)  # each simulation on a scene of its own
    got = simulate(cfg, layout.assets, layout.initial)
    monkeypatch.setattr(physics, "_contact_capacity", lambda n: None)
    ref = simulate(cfg, layout.assets, layout.initial)
    monkeypatch.setattr(physics, "_contact_capacity", lambda n: 1)
    retried = simulate(cfg, layout.assets, layout.initial)
    n = len(layout.assets)
    (cap, peak), (cap_ref, peak_ref), (one, peak_one), (cap_again, _) = [
        (sim.pipeline.rigid_contact_max, int(sim.peak.numpy()[0])) for sim in sims]  # most contacts at once
    print(f"{name}: {n} objects, capacity {cap} (Newton's estimate {cap_ref}), most contacts at once {peak}")
    assert cap == max(physics.CONTACTS_PER_SHAPE * (n + 6), (n + 1) ** 2) < cap_ref and 1 < peak == peak_ref < cap
    assert one == 1 and peak_one >= 1 and cap_again == cap_ref
    for a, b in ((got, ref), (retried, ref)):
        for k in ("poses", "velocity", "angular_velocity"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


def test_substep_rule():
    sizes = [0.3, 0.6]
    slow = choose_substeps(BouncingThingsConfig(min_speed=0.1, max_speed=0.2, angular_speed=(0, 0.1)), sizes)
    fast = choose_substeps(BouncingThingsConfig(min_speed=1.0, max_speed=12.0, angular_speed=(0, 3.0)), sizes)
    assert 2 <= slow < fast and slow % 2 == 0 and fast % 2 == 0
    assert choose_substeps(SLOW, [0.6, 0.6]) < choose_substeps(SLOW, [0.3, 0.6])


def test_kinematic_is_closed_form_and_reflects_off_walls():
    cfg = replace(SLOW, motion="kinematic", num_frames=40)
    layout = sample_layout(cfg, 0, 0)
    traj = simulate(cfg, layout.assets, layout.initial)
    t = np.arange(cfg.num_frames) / cfg.fps
    sizes = np.array([a.size for a in layout.assets])
    # Speeds and angular velocities are constant; rotations follow exp(t [w]x) R0 exactly.
    speed0 = np.linalg.norm(layout.initial.velocity, axis=-1)
    np.testing.assert_allclose(np.linalg.norm(traj.velocity, axis=-1),
                               np.broadcast_to(speed0, t.shape + sizes.shape))
    # Reference exponential map: scipy's rotation-vector conversion, not flowsynth.scene.motion.rotation_exp.
    w = t[:, None, None] * layout.initial.angular_velocity  # (T, n, 3) rotation vectors [rad]
    R = Rotation.from_rotvec(w.reshape(-1, 3)).as_matrix().reshape(w.shape + (3,)) @ layout.initial.rotation
    assert np.abs(layout.initial.angular_velocity).max() > 0.1, "no object spins: the test scene is too still"
    np.testing.assert_allclose(traj.poses[..., :3, :3], R, atol=1e-12)
    # Until an object's first wall contact its origin moves on a straight line at its initial velocity;
    # contacts only flip velocity components.
    p = traj.poses[:, :, :3, 3]
    v0 = layout.initial.velocity
    for i in range(len(sizes)):
        changed = np.flatnonzero((traj.velocity[:, i] != v0[i]).any(-1))
        k = changed[0] if len(changed) else cfg.num_frames
        np.testing.assert_allclose(p[:k, i], layout.initial.position[i] + t[:k, None] * v0[i], atol=1e-12)
    np.testing.assert_array_equal(np.abs(traj.velocity), np.broadcast_to(np.abs(v0), traj.velocity.shape))
    assert (traj.velocity != v0).any(), "no wall contact in 40 frames: the test scene is too sparse"
    # Bounding spheres stay inside the objects' region, so meshes stay inside the room.
    lo, hi = (np.asarray(b) for b in cfg.object_bounds)
    assert (p - sizes[:, None] / 2 >= lo - 1e-12).all() and (p + sizes[:, None] / 2 <= hi + 1e-12).all()
    assert max_wall_excursion(cfg, layout.assets, traj.poses) <= 0


def test_reflect_in_box_folds_positions():
    lo, hi = np.zeros(3), np.ones(3)
    t = np.array([[0.25], [0.75], [2.5]])
    p, v = reflect_in_box(np.array([0.5, 0.5, 0.5]), np.array([1.0, 0.0, -0.25]), t, lo, hi)
    np.testing.assert_allclose(p, [[0.75, 0.5, 0.4375], [0.75, 0.5, 0.3125], [1.0, 0.5, 0.125]])
    np.testing.assert_allclose(v[:, 0], [1.0, -1.0, 1.0])
    np.testing.assert_allclose(v[:, 2], [-0.25, -0.25, 0.25])


def test_static_keeps_the_initial_pose():
    cfg = BouncingThingsConfig(motion="static", num_frames=5)
    layout = sample_layout(cfg, 0, 0)
    traj = simulate(cfg, layout.assets, layout.initial)
    assert (traj.poses == traj.poses[0]).all() and (traj.velocity == 0).all()


def test_empty_scene():
    cfg = BouncingThingsConfig(num_objects=(0, 0), num_frames=3)
    empty = InitialState(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)))
    assert simulate(cfg, [], empty).poses.shape == (3, 0, 4, 4)


@pytest.mark.parametrize("motion", ["kinematic", "static"])
def test_kinematic_and_static_never_import_newton(motion):
    code = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {str(ROOT)!r})
        import flowsynth as fs
        from flowsynth.scene.sampling import sample_scene
        cfg = fs.BouncingThingsConfig(motion={motion!r}, num_frames=4, camera_motion="moving")
        scene = sample_scene(cfg, 0, 0)
        assert len(scene.objects) >= 2
        print("newton" in sys.modules, "warp" in sys.modules)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-2:] == ["False", "False"]
