"""Free flight (``physics.FREE_FLIGHT``): a clip whose colliders stay out of contact range at every substep runs on a
bodies-only Newton model, and its trajectory is the full model's bit for bit.

Oracles:
- the full model: the same clips with free flight off (walls, colliders and collision pipeline built); trajectories
  must be equal exactly, and the full model must have found no contact in any clip free flight kept;
- python-fcl's GJK distance between the colliders: wherever ``clear_of_contact`` says clear, the true distance
  exceeds the clearance it claims; two spheres, and a box against a wall, at distances either side of the threshold.
"""

from __future__ import annotations


import fcl
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import flowsynth as fs
from flowsynth.scene import physics
from flowsynth.scene.assets import Asset, Collider, get_asset, unit_hull
from flowsynth.scene.motion import simulate
from flowsynth.scene.sampling import sample_layout, simulation_config

FIELDS = ("poses", "velocity", "angular_velocity", "substeps")
CONFIGS = {
    "default": fs.BouncingThingsConfig(width=64, height=48, num_frames=2),
    # every primitive kind, falling under gravity for four frames: gravity bends the paths between frames
    "primitives_gravity": fs.BouncingThingsConfig(width=64, height=48, num_frames=4, flow_px=None,
                                                  assets=("box", "sphere", "cylinder", "capsule", "cone"),
                                                  num_objects=(3, 6), gravity=(0.0, 0.0, -9.81),
                                                  restitution=0.6, friction=0.3, min_speed=0.5, max_speed=4.0),
    # one key for every clip (object count and substeps fixed): each clip after the first runs on a scene reset
    # from another clip's, with other masses and, with flow_px, another speed band
    "one_key": fs.BouncingThingsConfig(width=64, height=48, num_frames=2, num_objects=(5, 5), substeps=12),
}


def _clips(cfg, indices):
    """(simulation config, layout) of each index, as sample_scene simulates it."""
    layouts = [sample_layout(cfg, 0, i) for i in indices]
    return [(simulation_config(cfg, layout), layout) for layout in layouts]


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_free_flight_equals_the_full_model(name, monkeypatch):
    clips = _clips(CONFIGS[name], range(16))
    monkeypatch.setattr(physics, "FREE_FLIGHT_ODDS", 0.0)  # every clip that passes the guess is tried
    tries = []  # per simulate call: free flight's result, or "untried"
    free_flight = physics._free_flight
    monkeypatch.setattr(physics, "_free_flight", lambda *a: tries.__setitem__(-1, free_flight(*a)) or tries[-1])
    peaks, builds = [], []
    advance, init = physics.NewtonScene.advance_frame, physics.NewtonScene.__init__

    def spy(scene, *args):  # the full model's most contacts in any substep, per clip
        advance(scene, *args)
        if scene.pipeline is not None:
            peaks.append(int(scene.peak.numpy()[0]))

    def counting(scene, *args, colliders=True, **kwargs):
        builds.append(colliders)
        init(scene, *args, colliders=colliders, **kwargs)

    monkeypatch.setattr(physics.NewtonScene, "advance_frame", spy)
    monkeypatch.setattr(physics.NewtonScene, "__init__", counting)

    def run(sim_cfg, layout):
        tries.append("untried")
        return simulate(sim_cfg, layout.assets, layout.initial), tries[-1]

    fs.clear_caches()
    monkeypatch.setattr(physics, "FREE_FLIGHT", False)
    full = []
    for sim_cfg, layout in clips:
        peaks.clear()
        full.append((run(sim_cfg, layout)[0], max(peaks)))
    monkeypatch.setattr(physics, "FREE_FLIGHT", True)
    outcomes = []
    for order in (range(len(clips)), range(len(clips))[::-1]):  # the second pass on kept bodies-only scenes
        builds.clear()
        for k in order:
            got, free = run(*clips[k])
            want, peak = full[k]
            for f in FIELDS:
                assert np.array_equal(getattr(got, f), getattr(want, f)), (k, f)
            if free is not None and free != "untried":
                assert peak == 0, "free flight kept a clip in which the full model found a contact"
            outcomes.append(free)
    assert False not in builds, "the second pass built a bodies-only scene: the kept ones were not reused"
    kept = sum(o is not None and o != "untried" for o in outcomes[:len(clips)])
    failed = sum(o is None for o in outcomes[:len(clips)])
    assert 0 < kept < len(clips), f"{kept} of {len(clips)} clips kept by free flight: nothing compared"
    if name == "primitives_gravity":  # four frames under gravity: some tries run and then fail
        assert failed > 0


def test_contact_range_is_the_models():
    """contact_range is what the built full model holds: each object's margin + gap, and the walls' gap (margin 0)."""
    cfg = CONFIGS["primitives_gravity"]
    layout = sample_layout(cfg, 0, 3)
    scene = physics.NewtonScene(cfg, layout.assets, layout.initial, 10)
    margin, gap = scene.model.shape_margin.numpy(), scene.model.shape_gap.numpy()
    reach, wall_gap = physics.contact_range(cfg, layout.assets, 10)
    n = len(layout.assets)
    np.testing.assert_allclose(margin[6:] + gap[6:], reach, rtol=1e-6)
    np.testing.assert_allclose(gap[:6], wall_gap, rtol=1e-6)
    assert (margin[:6] == 0).all() and len(margin) == 6 + n


def _fcl(asset: Asset, q: np.ndarray) -> fcl.CollisionObject:
    """The asset's collider at pose q (px py pz qx qy qz qw) as an fcl object (fcl's capsule, cylinder and cone are
    centred on their axis as Newton's and flowsynth's are)."""
    c = asset.collider
    if c.kind == "sphere":
        geom = fcl.Sphere(c.params[0])
    elif c.kind == "box":
        geom = fcl.Box(*(2.0 * np.asarray(c.params)))
    elif c.kind in ("capsule", "cylinder", "cone"):
        geom = getattr(fcl, c.kind.capitalize())(c.params[0], 2.0 * c.params[1])
    else:
        hull = unit_hull(asset.name)
        v = np.asarray(hull.vertices) * asset.size
        f = np.asarray(hull.faces)
        geom = fcl.Convex(v, len(f), np.hstack([np.full((len(f), 1), 3), f]).ravel())
    R = Rotation.from_quat(q[3:]).as_matrix()
    return fcl.CollisionObject(geom, fcl.Transform(R, q[:3]))


def _distance(a, qa, b, qb) -> float:
    return fcl.distance(_fcl(a, qa), _fcl(b, qb), fcl.DistanceRequest(), fcl.DistanceResult())


KINDS = ("rock", "crystal", "box", "sphere", "capsule", "cylinder", "cone")


def _bisect(gap, target: float, lo: float, hi: float) -> float:
    """s in [lo, hi] with gap(s) close below ``target``; gap(lo) < target < gap(hi), gap non-decreasing."""
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(mid) < target else (lo, mid)
    return lo


def test_clear_of_contact_is_conservative_against_fcl():
    """Pairs of every collider kind in random orientations, moved apart along a random direction until fcl's distance
    is just below the clearance (bisection): never called clear, also as one pose among several; and pairs at random
    distances: called clear only beyond the clearance, and most pairs well clear are called clear."""
    cfg = fs.BouncingThingsConfig(room_size=(40.0, 40.0, 40.0), camera_clearance=1.0)
    rng = np.random.default_rng(0)
    lo, hi = (np.asarray(x) for x in cfg.object_bounds)
    centre = (lo + hi) / 2
    verdicts = []
    for _ in range(300):
        assets = [get_asset(str(k), float(rng.uniform(0.05, 1.2))) for k in rng.choice(KINDS, 2)]
        reach, _ = physics.contact_range(cfg, assets, 8)
        need = physics.CLEARANCE_FACTOR * reach.sum() + physics.CLEARANCE_SLACK
        rot = Rotation.random(2, random_state=rng).as_quat()
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)

        def poses(s, u=u, rot=rot):
            q = np.zeros((1, 2, 7))
            q[0, :, :3] = centre
            q[0, 1, :3] += s * u
            q[0, :, 3:] = rot
            return q

        def dist(s, assets=assets, poses=poses):
            q = poses(s)
            return _distance(assets[0], q[0, 0], assets[1], q[0, 1])

        far = sum(a.size for a in assets) + need + 1.0
        s_near = _bisect(dist, 0.99 * need, 0.0, far)
        assert dist(s_near) < need
        near = poses(s_near)
        assert not physics.clear_of_contact(cfg, assets, near, 8), [a.name for a in assets]
        many = np.concatenate([poses(far), poses(far * 2), near, poses(far * 3)])  # S = 4, the third near
        assert not physics.clear_of_contact(cfg, assets, many, 8)
        s = rng.uniform(0.0, far)
        clear = physics.clear_of_contact(cfg, assets, poses(s), 8)
        if clear:
            assert dist(s) > need, (dist(s), need, [a.name for a in assets])
        verdicts.append((clear, dist(s) > need * 1.5))
    assert any(c for c, _ in verdicts) and any(not c for c, _ in verdicts)
    assert np.mean([c for c, far_enough in verdicts if far_enough]) > 0.8


def test_clear_of_contact_walls_against_fcl():
    """Each kind in random poses near a random one of the six walls: called clear only where fcl's distance to the
    wall (a thin box beyond object_bounds) exceeds the clearance; and called clear wherever it does (the extent along
    an axis is exact)."""
    cfg = fs.BouncingThingsConfig(room_size=(10.0, 8.0, 6.0))
    rng = np.random.default_rng(1)
    lo, hi = (np.asarray(x) for x in cfg.object_bounds)
    centre = (lo + hi) / 2
    verdicts = []
    for _ in range(300):
        asset = get_asset(str(rng.choice(KINDS)), float(rng.uniform(0.1, 1.2)))
        reach, wall_gap = physics.contact_range(cfg, [asset], 8)
        need = physics.CLEARANCE_FACTOR * (reach[0] + wall_gap) + physics.CLEARANCE_SLACK
        axis, side = int(rng.integers(3)), int(rng.choice([-1, 1]))
        plane = (hi if side > 0 else lo)[axis]
        half = np.full(3, 100.0)
        half[axis] = 0.01
        at = np.zeros(3)
        at[axis] = plane + side * 0.01
        wall = fcl.CollisionObject(fcl.Box(*(2 * half)), fcl.Transform(np.eye(3), at))
        q = np.zeros((1, 1, 7))
        q[0, 0, :3] = centre
        q[0, 0, axis] = plane - side * rng.uniform(0.0, asset.size)
        q[0, 0, 3:] = Rotation.random(random_state=rng).as_quat()
        clear = physics.clear_of_contact(cfg, [asset], q, 8)
        dist = fcl.distance(_fcl(asset, q[0, 0]), wall, fcl.DistanceRequest(), fcl.DistanceResult())
        if clear:
            assert dist > need, (dist, need, asset.name)
        verdicts.append((clear, dist > need + 1e-6))
    assert any(c for c, _ in verdicts) and any(not c for c, _ in verdicts)
    assert all(c for c, far in verdicts if far)


def _sphere(r: float) -> Asset:
    a = get_asset("sphere", 2.0 * r)
    assert a.collider == Collider("sphere", (r,), a.collider.hull) and a.size == pytest.approx(2.0 * r)
    return a


def test_clear_of_contact_spheres_and_walls_at_the_threshold():
    cfg = fs.BouncingThingsConfig(room_size=(10.0, 8.0, 6.0))
    a = _sphere(0.3)
    reach, _ = physics.contact_range(cfg, [a, a], 8)
    need = physics.CLEARANCE_FACTOR * 2 * reach[0] + physics.CLEARANCE_SLACK
    lo, hi = (np.asarray(x) for x in cfg.object_bounds)
    centre = (lo + hi) / 2
    for surface_gap, want in ((need * 1.01, True), (need * 0.99, False)):
        q = np.zeros((1, 2, 7))
        q[..., 6] = 1.0
        q[0, 0, :3] = centre
        q[0, 1, :3] = centre + np.array([0.6 + surface_gap, 0.0, 0.0])
        assert physics.clear_of_contact(cfg, [a, a], q, 8) is want
    box = get_asset("box", 1.0)
    hx = box.collider.params[0]
    box_reach, box_wall = physics.contact_range(cfg, [box], 8)
    wall_need = physics.CLEARANCE_FACTOR * (box_reach[0] + box_wall) + physics.CLEARANCE_SLACK
    for surface_gap, want in ((wall_need * 1.01, True), (wall_need * 0.99, False)):
        q = np.zeros((1, 1, 7))
        q[..., 6] = 1.0
        q[0, 0, :3] = centre
        q[0, 0, 0] = hi[0] - hx - surface_gap  # the +x face of the unrotated box, surface_gap from the wall
        assert physics.clear_of_contact(cfg, [box], q, 8) is want
