"""Rigid-body physics for BouncingThings: Newton's XPBD solver on the Warp CPU device.

Colliders are the assets' primitives or convex hulls; the walls of ``cfg.object_bounds`` are static boxes.
Substeps per frame follow :func:`choose_substeps`; after every substep each linear speed is clamped into
[min_speed, max_speed] and each angular speed into ``angular_speed`` (docs/scenes.md). Newton is imported only
here, on first use. Also here: the reuse of finished Newton scenes (``SCENE_REUSE``), free flight (``FREE_FLIGHT``:
clips clear of contact on a bodies-only model, bit for bit) and the memoisation of Newton's private kernel
factories, scoped to flowsynth's own calls (``memoise_newton_kernel_factories``).
``flowsynth.scene.motion.simulate`` dispatches here for ``motion="physics"``.
"""

from __future__ import annotations

import contextlib
import functools
import math
import threading
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from typing import ClassVar

import numpy as np

from flowsynth.caches import register
from flowsynth.errors import ConfigError
from flowsynth.kernels import wp_runtime
from flowsynth.processes import check_not_forked_from_cuda
from flowsynth.scene.assets import Asset, unit_hull
from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.scene.trajectory import (InitialState, Trajectory, pose_matrices, quat_to_rotation,
                                        rotation_to_quat_xyzw, simulate_static)

__all__ = [
    "NewtonScene",
    "choose_substeps",
    "memoise_newton_kernel_factories",
    "simulate_physics",
    "wall_boxes",
]

SUBSTEP_FRACTION = 0.05
"""Largest approach of two object surfaces within one substep, as a fraction of the smallest object size.
benchmarks/accuracy/physics.py: the first mesh penetration above 1% of a size appears at 0.17, none at <= 0.05
(docs/decisions/0005-physics-substep-rule.md)."""
MIN_SUBSTEPS = 2
"""Fewest physics substeps per frame [count]."""
MAX_SUBSTEPS = 256
"""Most physics substeps per frame chosen automatically [count]; cfg.substeps may exceed it."""
MARGIN_FRACTION = 0.0025
"""Collision margin of every object collider, as a fraction of the smallest object size: colliders are
kept twice this far apart (and this far from walls), so residual solver penetration stays in the gap."""
XPBD_ITERATIONS = 4
"""XPBD constraint iterations per substep [count]."""
CONTACTS_PER_SHAPE = 4
"""Rigid-contact slots per shape (objects and the six walls) in the collision pipeline's buffers [count], at least
(see :func:`_contact_capacity`). The most contacts at once seen in 60 default scenes (4-12 objects, 24 frames
each) was 14, and 36 with 40 objects: about one per shape. Newton's own estimate (1000 and up) makes every
contact kernel of every substep walk thousands of empty slots. When some substep fills the buffer (contacts may
then have been dropped), the clip is simulated again with Newton's estimate (:func:`simulate_physics`), so the
capacity never changes a trajectory."""
DENSITY = 1000.0
"""Density of every object [kg/m^3]; mass and inertia come from the collider's convex hull."""
EPS_SPEED = 1e-6
"""Speeds below this [m/s] or [rad/s] have no usable direction (float32 state)."""
_FREE_JOINTS = False
"""Give every body a free joint (Newton's ``add_body``) instead of none (``add_link``). A free joint constrains
nothing, but XPBD still runs a joint pass per iteration for it (a zero correction plus a pose renormalisation:
trajectories differ by float32 round-off, tests/test_motion.py), and joints slow the model build and every
substep (with the one-substep capture: Newton 0.099 -> 0.059 s per 2-frame 256x192 sample,
docs/decisions/0006-newton-graph-replay.md). True only in tests comparing the two."""
SCENE_REUSE = True
"""Keep each finished :class:`NewtonScene` (model, collision pipeline, solver, captured substep) per process and run a
later clip with the same key on it, its arrays reset, instead of building and capturing another: the key is the
simulation's config, substeps, contact capacity and the assets (name, size, collider) in order, everything but the
initial state (a scene is kept from a key's second clip on), so the trajectory is the fresh scene's bit for bit
(tests/test_scene_reuse.py; docs/decisions/0020-newton-scene-reuse.md). False builds every clip afresh."""
SCENE_CACHE_SIZE = 16
"""Most Newton scenes kept for reuse per process [count], least recently used dropped first."""
_SCENES: OrderedDict = register("physics.newton_scenes", OrderedDict())  # key -> idle NewtonScene
# keys of the last SCENE_KEYS_SEEN clips: a scene is kept (and pays the snapshot of its captured memory, ~2% of a
# default depth-only sample's profile) only when its key came before, so a dataset whose keys never repeat pays nothing
_SEEN: OrderedDict = register("physics.newton_scene_keys", OrderedDict())  # key -> None
SCENE_KEYS_SEEN = 256
FREE_FLIGHT = True
"""Run each clip first on a bodies-only Newton model (:class:`NewtonScene` with ``colliders=False``: the same bodies,
no colliders, walls or collision pipeline; kept per object count and substeps, ``FREE_CACHE_SIZE``) and keep that
trajectory when it is clear of contact: at the start of every substep, what the full model's collision pipeline
would be given, each pair of colliders and each collider and wall lie more than ``CLEARANCE_FACTOR`` times their
contact range apart (:func:`clear_of_contact`). The full model would then find no contact in any substep, and its
solver runs the same kernels on the same numbers, so the trajectory is the full model's bit for bit
(tests/test_free_flight.py); otherwise the clip runs on the full model. docs/decisions/0022-free-flight.md."""
CLEARANCE_FACTOR = 1.25
"""Free flight holds only where every gap exceeds this many times the contact range, plus CLEARANCE_SLACK: the sum of
the two shapes' margins and detection gaps, within which Newton's narrow phase writes a contact (speculative contacts
are off) [ratio]."""
CLEARANCE_CHUNK = 256
"""Near (substep, pair) rows checked at once by :func:`clear_of_contact` [count]: bounds its temporaries."""
CLEARANCE_SLACK = 1e-3
"""Absolute part of the clearance free flight needs [m] (float32 geometry, Newton's 1e-4 enlargement of shapes
without margin)."""
FREE_CACHE_SIZE = 128
"""Most bodies-only Newton scenes kept per process [count] (one per object count and substeps in use; a few
hundred kB each), least recently used dropped first."""
_FREE: OrderedDict = register("physics.newton_free_scenes", OrderedDict())  # key -> idle bodies-only NewtonScene
FREE_FLIGHT_ODDS = 0.2
"""Free flight is tried while the running share of clips it kept (this process's tries with the same frame and
object counts, a moving average over about ten) is at least this [ratio]; below it, every ``FREE_FLIGHT_PROBE``-th
clip still tries, so the share follows the stream. Long clips rarely stay clear of contact, and a failed try costs
its reset and replays; a kept one saves the full model's build (benchmarks/speed/scene_setup.py --free-flight). Only
time depends on this: either path gives the same trajectory."""
FREE_FLIGHT_PROBE = 16
FREE_FLIGHT_COUNTS = {"tried": 0, "kept": 0}
"""This process's physics clips that free flight ran (passed the guess and the gate), and those it kept [count]
(benchmarks read them; ``fs.clear_caches`` leaves them)."""
_FREE_ODDS: dict = register("physics.free_flight_odds", {})  # (frames, objects) -> [moving share kept, clips since]


def choose_substeps(cfg: BouncingThingsConfig, sizes: Sequence[float]) -> int:
    """Physics substeps per frame so that no two surfaces approach by more than SUBSTEP_FRACTION times the
    smallest object size within one substep.

    The fastest relative approach of two surface points is 2 max_speed + max_angular_speed * max_size
    (each object translates at <= max_speed and a point at distance <= size/2 from the origin rotates
    at <= angular_speed * size / 2); walls approach at half that. Result clamped to
    [MIN_SUBSTEPS, MAX_SUBSTEPS] and rounded up to an even number (kept from when substeps ran in captured
    pairs, so the counts did not change).
    """
    if len(sizes) == 0:
        return MIN_SUBSTEPS
    s_min, s_max = float(min(sizes)), float(max(sizes))
    approach = 2.0 * cfg.max_speed + cfg.angular_speed[1] * s_max  # [m/s]
    n = math.ceil(approach / cfg.fps / (SUBSTEP_FRACTION * s_min))
    n = min(max(n, MIN_SUBSTEPS), MAX_SUBSTEPS)
    return int(n + n % 2)


def simulate_physics(cfg: BouncingThingsConfig, assets: Sequence[Asset], initial: InitialState,
                     num_frames: int, *, substeps: int | None = None) -> Trajectory:
    """Rigid-body dynamics with Newton (XPBD, Warp CPU). See the module docstring and docs/scenes.md.

    Raises ForkError in a process forked from one that had initialised CUDA (``flowsynth.processes``): the Newton
    entry, whether the clip builds a model, reuses a cached one or flies free."""
    N = len(assets)
    if N == 0:
        return simulate_static(initial, num_frames)
    check_not_forked_from_cuda()
    sizes = [a.size for a in assets]
    n_sub = int(substeps or cfg.substeps or choose_substeps(cfg, sizes))
    n_sub += n_sub % 2  # even, as when substeps ran in captured pairs: the same substeps as before
    if FREE_FLIGHT and num_frames > 1 and _likely_clear(cfg, assets, initial, n_sub):
        odds = _FREE_ODDS.setdefault((num_frames, N), [1.0, 0])
        odds[1] += 1
        if odds[0] >= FREE_FLIGHT_ODDS or odds[1] >= FREE_FLIGHT_PROBE:
            free = _free_flight(cfg, assets, initial, num_frames, n_sub)
            odds[:] = [0.9 * odds[0] + 0.1 * (free is not None), 0]
            FREE_FLIGHT_COUNTS["tried"] += 1
            FREE_FLIGHT_COUNTS["kept"] += free is not None
            if free is not None:
                return free
    for contact_max in (_contact_capacity(N), None):  # None: Newton's estimate, after an overflow
        key = _scene_key(cfg, assets, n_sub, contact_max)
        sim = _SCENES.pop(key, None) if SCENE_REUSE else None  # popped: never two clips on one scene at once
        if sim is None or not sim.reset(initial):
            sim = NewtonScene(cfg, assets, initial, n_sub, contact_max)
            sim.reusable = SCENE_REUSE and key in _SEEN
        if SCENE_REUSE:
            _SEEN.pop(key, None)
            _keep(_SEEN, key, None, SCENE_KEYS_SEEN)
        frames = _run_frames(sim, num_frames)
        if SCENE_REUSE and sim.can_reset:
            _keep(_SCENES, key, sim, SCENE_CACHE_SIZE)
        if sim.contact_max is None or not sim.overflowed():  # Newton's estimate already, or nothing dropped
            break
    return Trajectory(*frames, n_sub)


def _keep(cache: OrderedDict, key, value, limit: int) -> None:
    """``cache[key] = value`` as the newest entry, the oldest dropped beyond ``limit``."""
    cache[key] = value
    while len(cache) > limit:
        cache.popitem(last=False)


def _run_frames(sim: NewtonScene, num_frames: int, clear=None) -> tuple | None:
    """(poses, velocities, angular velocities) of ``num_frames`` frames stepped on ``sim``. With ``clear``, each
    frame's substep start poses (S, N, 7) go to ``clear`` and the clip stops, returning None, when it says False."""
    N = sim.model.body_count
    poses = np.empty((num_frames, N, 4, 4))
    vel = np.empty((num_frames, N, 3))
    ang = np.empty((num_frames, N, 3))
    track = [sim.state0.body_q.numpy().copy()] if clear else None
    for k in range(num_frames):
        if k > 0:
            sim.advance_frame(track)
            if clear:
                # the poses collided so far: all but the newest, which starts the next frame (or meets no collide())
                ok = clear(np.stack(track[:-1]))
                del track[:-1]
                if not ok:
                    return None
        poses[k], vel[k], ang[k] = sim.read()
    return poses, vel, ang


def _likely_clear(cfg: BouncingThingsConfig, assets: Sequence[Asset], initial: InitialState, n_sub: int) -> bool:
    """A guess whether free flight keeps a clip, costing no scene: clear of contact at the start and where straight
    flight at the initial velocities, unrotated, puts the objects a frame later. Free flight tries only the clips
    it passes: in 80 default clips it passed 55, all of them kept, of the 57 kept when every clip is tried; in 80 of
    benchmarks/_common.py's full-sample clips (20 objects) it passed 34, 33 of them kept, of 35."""
    q0 = np.concatenate([initial.position, rotation_to_quat_xyzw(initial.rotation)], 1)
    q1 = q0.copy()
    q1[:, :3] += initial.velocity / cfg.fps
    return clear_of_contact(cfg, assets, np.stack([q0, q1]), n_sub)


def _free_flight(cfg: BouncingThingsConfig, assets: Sequence[Asset], initial: InitialState, num_frames: int,
                 n_sub: int) -> Trajectory | None:
    """The clip on a bodies-only scene (``FREE_FLIGHT``), or None as soon as some substep's poses come within
    contact range (checked frame by frame, so a clip that meets a contact early costs little)."""
    key = (len(assets), n_sub, cfg.fps, tuple(cfg.gravity), cfg.restitution, cfg.friction, _FREE_JOINTS)
    sim = _FREE.pop(key, None)  # popped: never two clips on one scene at once
    if sim is None or not sim.reset(initial, assets, cfg):
        sim = NewtonScene(cfg, assets, initial, n_sub, colliders=False)
        sim.reusable = True
    frames = _run_frames(sim, num_frames, lambda q: clear_of_contact(cfg, assets, q, n_sub))
    if sim.can_reset:
        _keep(_FREE, key, sim, FREE_CACHE_SIZE)
    return None if frames is None else Trajectory(*frames, n_sub)


def contact_range(cfg: BouncingThingsConfig, assets: Sequence[Asset], substeps: int) -> tuple[np.ndarray, float]:
    """(per object, wall) contact range [m] of a clip's colliders: each shape's margin plus detection gap, as
    :class:`NewtonScene` sets them; two shapes are paired by Newton's broad phase within the sum of theirs."""
    s_min = min(a.size for a in assets)
    s_max = max(a.size for a in assets)
    approach = (2.0 * cfg.max_speed + cfg.angular_speed[1] * s_max) / (cfg.fps * substeps)
    return np.full(len(assets), MARGIN_FRACTION * s_min + approach), approach


@register("physics.support_points")
@functools.lru_cache(maxsize=4096)
def _support_points(name: str, size: float, kind: str, params: tuple) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The collider of an asset (its name, size, collider kind and params) in its object frame [m] as (points (K, 3),
    disc radii (K,), radius, bounding radius): the convex hull of the points, each swept by a disc of its radius in
    the object's xy plane, then by a ball of the radius. Box and convex hull: vertices; sphere: the centre and a
    ball; capsule: the axis segment and a ball; cylinder: the end centres with discs; cone: the base centre with
    a disc and the apex. The support along a unit axis u is max_k p_k.u + disc_k |u_xy| + radius, exact for each
    kind. The bounding radius bounds the collider about the origin."""
    if kind == "box":
        pts, rad = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * np.array(params), 0.0
        disc = np.zeros(8)
    elif kind == "sphere":
        pts, disc, rad = np.zeros((1, 3)), np.zeros(1), float(params[0])
    elif kind in ("capsule", "cylinder", "cone"):
        r, h = float(params[0]), float(params[1])
        pts = np.array([[0.0, 0.0, -h], [0.0, 0.0, h]])
        disc, rad = {"capsule": ([0.0, 0.0], r), "cylinder": ([r, r], 0.0), "cone": ([r, 0.0], 0.0)}[kind]
        disc = np.array(disc)
    else:
        pts, rad = np.asarray(unit_hull(name).vertices, dtype=np.float64) * size, 0.0
        disc = np.zeros(len(pts))
    pts.flags.writeable = disc.flags.writeable = False
    # a disc's rim point is perpendicular to z, its centre on z for every kind with a disc
    return pts, disc, rad, float(np.sqrt((pts ** 2).sum(1) + disc ** 2).max()) + rad


def clear_of_contact(cfg: BouncingThingsConfig, assets: Sequence[Asset], body_q: np.ndarray, substeps: int) -> bool:
    """Are the colliders at every pose of ``body_q`` (S, N, 7: px py pz qx qy qz qw, Newton's state) further than
    ``CLEARANCE_FACTOR`` times their contact range (:func:`contact_range`) plus ``CLEARANCE_SLACK`` from each other and
    from the walls of ``cfg.object_bounds``? Bounding spheres decide where they can. Elsewhere the exact extent along
    each world axis decides against the walls, and for a pair, a lower bound of the distance: their separation along
    the line between the origins, a world axis or an axis of either object (support functions of
    :func:`_support_points`). So True is conservative."""
    q = np.asarray(body_q, dtype=np.float64)
    S, N = q.shape[:2]
    reach, wall_gap = contact_range(cfg, assets, substeps)
    supports = [_support_points(a.name, float(a.size), a.collider.kind, tuple(map(float, a.collider.params)))
                for a in assets]
    bound = np.array([sup[3] for sup in supports])
    centre = q[..., :3]

    def extent(s: np.ndarray, n: np.ndarray, R: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lowest, highest) projection, each (M, X), of objects n at poses s (rotations R (M, 3, 3)) onto unit axes
        (M, X, 3)."""
        K = max(len(supports[k][0]) for k in set(n.tolist()))
        pts = np.stack([np.resize(supports[k][0], (K, 3)) for k in n])  # padded by repeats
        disc = np.stack([np.resize(supports[k][1], K) for k in n])
        rad = np.array([supports[k][2] for k in n])[:, None]
        proj = np.matmul(axes, np.matmul(R, np.transpose(pts, (0, 2, 1))))  # (M, X, K)
        flat = np.sqrt(np.clip(1.0 - np.einsum("mxc,mc->mx", axes, R[:, :, 2]) ** 2, 0.0, 1.0))  # |u_xy|, object
        wide = flat[:, :, None] * disc[:, None, :]
        at = np.einsum("mxc,mc->mx", axes, centre[s, n])
        return at + (proj - wide).min(-1) - rad, at + (proj + wide).max(-1) + rad

    lo, hi = (np.asarray(x, dtype=np.float64) for x in cfg.object_bounds)
    need = CLEARANCE_FACTOR * (reach + wall_gap) + CLEARANCE_SLACK
    outer = (centre - (bound + need)[:, None] < lo) | (centre + (bound + need)[:, None] > hi)  # (S, N, 3)
    if outer.any():
        s, n = np.nonzero(outer.any(-1))
        low, high = extent(s, n, quat_to_rotation(q[s, n, 3:]), np.broadcast_to(np.eye(3), (len(s), 3, 3)))
        if (high + need[n, None] > hi).any() or (low - need[n, None] < lo).any():
            return False
    if N < 2:
        return True
    i, j = np.triu_indices(N, 1)
    need = CLEARANCE_FACTOR * (reach[i] + reach[j]) + CLEARANCE_SLACK
    d = centre[:, j] - centre[:, i]  # (S, P, 3)
    dist = np.linalg.norm(d, axis=-1)
    near = dist <= bound[i] + bound[j] + need
    if not near.any():
        return True
    s_all, p_all = np.nonzero(near)
    for c in range(0, len(s_all), CLEARANCE_CHUNK):  # in chunks: the projections are (M, 10, K) per object
        s, p = s_all[c:c + CLEARANCE_CHUNK], p_all[c:c + CLEARANCE_CHUNK]
        a, b = i[p], j[p]
        R_a, R_b = quat_to_rotation(q[s, a, 3:]), quat_to_rotation(q[s, b, 3:])
        axes = np.concatenate([(d[s, p] / np.maximum(dist[s, p], 1e-12)[:, None])[:, None],
                               np.broadcast_to(np.eye(3), (len(s), 3, 3)),
                               np.transpose(R_a, (0, 2, 1)), np.transpose(R_b, (0, 2, 1))], axis=1)  # (M, 10, 3)
        low_a, high_a = extent(s, a, R_a, axes)
        low_b, high_b = extent(s, b, R_b, axes)
        sep = np.maximum(low_b - high_a, low_a - high_b)  # b beyond a, or a beyond b, along each axis
        if not (sep.max(-1) > need[p]).all():
            return False
    return True


def _speed_band(cfg: BouncingThingsConfig) -> np.ndarray:
    """The clamp kernel's band: min and max linear speed [m/s], then angular speed [rad/s]."""
    return np.array([cfg.min_speed, cfg.max_speed, *cfg.angular_speed], dtype=np.float32)


def _scene_key(cfg: BouncingThingsConfig, assets: Sequence[Asset], substeps: int, contact_max: int | None) -> tuple:
    """Everything a :class:`NewtonScene` is built from but the initial state: the whole config (hashable, frozen),
    substeps, contact capacity, whether bodies get free joints, and per asset its name, size and collider (a
    convex collider's Newton hull is the per-process one of its name)."""
    shapes = tuple((a.name, float(a.size), a.collider.kind, tuple(float(x) for x in a.collider.params))
                   for a in assets)
    return cfg, int(substeps), contact_max, _FREE_JOINTS, shapes


def _contact_capacity(num_objects: int) -> int:
    """Rigid-contact slots of the first simulation of a clip with ``num_objects`` objects: CONTACTS_PER_SHAPE per
    shape (the objects and the six wall boxes of ``wall_boxes``), and at least (N + 1)^2. The second bound keeps
    the trajectory that of Newton's estimate bit for bit: XPBD's restitution pass hashes each body pair to slot
    key mod capacity (key = (lo + 1)(N + 1) + hi + 1 < (N + 1)^2) and sums the pairs' corrections in slot order,
    so slot must equal key as it does under Newton's estimate (1000 and up). :class:`NewtonScene` uses Newton's
    estimate instead where that is no larger."""
    return max(CONTACTS_PER_SHAPE * (num_objects + 6), (num_objects + 1) ** 2)


def wall_boxes(cfg: BouncingThingsConfig, s_max: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, half extents) [m] of the six static wall boxes around ``cfg.object_bounds``, each thicker
    than anything of size ``s_max`` can travel in a substep."""
    lo, hi = (np.asarray(x, dtype=np.float64) for x in cfg.object_bounds)
    thick = max(1.0, 2.0 * s_max)
    centre, half = (lo + hi) / 2.0, (hi - lo) / 2.0
    boxes = []
    for axis in range(3):
        for side in (-1.0, 1.0):
            h = half + thick
            h[axis] = thick / 2.0
            p = centre.copy()
            p[axis] = (lo if side < 0 else hi)[axis] + side * thick / 2.0
            boxes.append((p, h))
    return boxes


class NewtonScene:
    """A Newton model of the objects and walls, stepped one frame at a time: what ``simulate_physics`` runs
    (public for benchmarks/physics*.py: ``advance_frame`` replays a captured ``substep``; ``read`` the state)."""

    def __init__(self, cfg: BouncingThingsConfig, assets: Sequence[Asset], initial: InitialState,
                 substeps: int, contact_max: int | None = None, device: str = "cpu", colliders: bool = True) -> None:
        wp_runtime()  # quiet Warp initialisation before Newton's import initialises it loudly
        import newton
        import warp as wp

        try:
            on_cpu = wp.get_device(device).is_cpu
        except (RuntimeError, ValueError):  # a device Warp does not find
            on_cpu = False
        if not on_cpu:  # the state is read and reset through numpy views of its arrays
            raise ConfigError(f"physics runs on a CPU device only (NewtonScene writes its state through numpy "
                              f"views), got device {device!r}")
        self.cfg, self.substeps, self.device = cfg, substeps, device
        self.dt = 1.0 / (cfg.fps * substeps)
        s_min = min(a.size for a in assets)
        s_max = max(a.size for a in assets)
        # Contact detection gap per shape; a pair's gaps add, so contacts are found before two surfaces can
        # close twice the largest approach within one substep.
        approach = (2.0 * cfg.max_speed + cfg.angular_speed[1] * s_max) * self.dt
        b = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=tuple(cfg.gravity))
        shape_cfg = newton.ModelBuilder.ShapeConfig(
            mu=cfg.friction, restitution=cfg.restitution, density=DENSITY, gap=approach,
            margin=MARGIN_FRACTION * s_min, mu_torsional=0.0, mu_rolling=0.0,
        )
        wall_cfg = newton.ModelBuilder.ShapeConfig(
            mu=cfg.friction, restitution=cfg.restitution, density=0.0, gap=approach, margin=0.0,
            mu_torsional=0.0, mu_rolling=0.0,
        )
        if colliders:
            for p, h in wall_boxes(cfg, s_max):
                b.add_shape_box(-1, xform=wp.transform(wp.vec3(*p), wp.quat_identity()),
                                hx=float(h[0]), hy=float(h[1]), hz=float(h[2]), cfg=wall_cfg)
        else:  # one static shape, as the walls are: XPBD then runs its restitution pass as with colliders (no
            b.add_shape_sphere(-1, radius=1.0, cfg=wall_cfg)  # collision pipeline runs, so it meets nothing)
        for i, (asset, xform, (mass, inertia)) in enumerate(zip(assets, _body_xforms(initial), _mass_props(assets))):
            body = (b.add_body if _FREE_JOINTS else b.add_link)(
                xform=xform, com=wp.vec3(0.0, 0.0, 0.0),
                mass=mass, inertia=wp.mat33(*inertia.ravel()), lock_inertia=True, label=f"object_{i}")
            if colliders:
                _add_collider(b, body, asset, shape_cfg)
        self._inertia_checks = (b.balance_inertia, b.bound_mass or 0.0, b.bound_inertia or 0.0,
                                b.inertia_relative_tolerance, b.inertia_absolute_tolerance, b.inertia_correction)
        with memoise_newton_kernel_factories():  # Newton's factories memoised for flowsynth's own calls only
            self.model = b.finalize(device=self.device)
        self.state0, self.state1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        self._set_velocities(initial)
        # rigid-contact capacity: contact_max slots (None: Newton's estimate); self.peak holds the most contacts
        # any substep counted, so that overflowed() can tell when some may have been dropped
        if colliders and contact_max is not None and contact_max >= _newton_contact_estimate(self.model):
            contact_max = None
        self.contact_max = contact_max
        self.peak = wp.zeros(1, dtype=wp.int32, device=self.device)
        if colliders:
            with memoise_newton_kernel_factories():
                self.pipeline = newton.CollisionPipeline(self.model, broad_phase="sap",
                                                         rigid_contact_max=contact_max)
            self.contacts = self.pipeline.contacts()
        else:  # an empty contact buffer: the solver runs its contact kernels on no contacts, as the full model's does
            self.pipeline = None
            self.contacts = newton.Contacts(contact_max or _contact_capacity(len(assets)), 0, device=self.device,
                                            requested_attributes=self.model.get_requested_contact_attributes())
        self.band = wp.array(_speed_band(cfg), dtype=wp.float32, device=self.device)  # the clamp's, read per launch
        self.solver = newton.solvers.SolverXPBD(self.model, iterations=XPBD_ITERATIONS,
                                                enable_restitution=True)
        # Last direction of motion / rotation axis, used when a speed must be raised from zero.
        self.last_dir = wp.array(_unit_or(initial.velocity, [1.0, 0.0, 0.0]), dtype=wp.vec3, device=self.device)
        self.last_axis = wp.array(_unit_or(initial.angular_velocity, [0.0, 0.0, 1.0]), dtype=wp.vec3,
                                  device=self.device)
        self.graph = None
        self.reusable = False  # snapshot the captured substep's memory at capture, for reset()
        self._snapshot: list[tuple[np.ndarray, np.ndarray]] | None = None

    @property
    def can_reset(self) -> bool:
        """The scene was asked to be reusable at its capture and its captured memory was snapshotted: ``reset``
        can restore it."""
        return self.reusable and self._snapshot is not None

    def _set_velocities(self, initial: InitialState) -> None:
        qd = self.state0.body_qd.numpy()  # a view of the CPU array: written in place
        qd[:, :3] = initial.velocity
        qd[:, 3:] = initial.angular_velocity

    def reset(self, initial: InitialState, assets: Sequence[Asset] | None = None,
              cfg: BouncingThingsConfig | None = None) -> bool:
        """Make this scene what a fresh one of the same key (:func:`_scene_key`) built for ``initial`` would be
        after its capture: every memory region the captured substep reads or writes gets back the content it had
        right after this scene's own capture, then the arrays that depend on the initial state (the model's and both
        states' poses, state0's velocities, the last directions) are written as ``__init__`` writes them, and Newton's
        ray-query shape BVH is refitted to the new poses. Returns False, changing nothing, when there is no capture
        to reuse (``reusable`` was False at the capture). A scene without colliders takes the bodies' masses and
        inertias of ``assets`` too, through the kernels ``ModelBuilder.finalize`` derives the inverses with, and the
        speed band of ``cfg`` (its key leaves the band out); a scene with colliders keeps its own config (its key
        holds the whole config)."""
        import warp as wp

        if self._snapshot is None or len(initial.position) != self.model.body_count:
            return False
        if self.pipeline is None and (assets is None or cfg is None):
            raise ValueError("a scene without colliders is reset with the clip's assets and config (masses, band)")
        for view, saved in self._snapshot:
            np.copyto(view, saved)
        if self.pipeline is None:
            self._set_masses(assets)
            self.cfg = cfg
            self.band.numpy()[...] = _speed_band(cfg)
        q = wp.array(_body_xforms(initial), dtype=wp.transform, device=self.device).numpy()
        for arr in (self.model.body_q, self.state0.body_q, self.state1.body_q):
            arr.numpy()[...] = q
        self._set_velocities(initial)
        self.last_dir.numpy()[...] = _unit_or(initial.velocity, [1.0, 0.0, 0.0])
        self.last_axis.numpy()[...] = _unit_or(initial.angular_velocity, [0.0, 0.0, 1.0])
        if getattr(self.model, "bvh_shapes", None) is not None:  # Newton's ray-query BVH (finalize builds it at the
            self.model.bvh_refit_shapes(self.state0)  # initial poses; no substep reads it): at the new poses
        return True

    def _set_masses(self, assets: Sequence[Asset]) -> None:
        """Write the bodies' masses and inertias as ``finalize`` does, then the inverses and the solver's effective
        inverses by the same kernels."""
        import newton
        import warp as wp
        from newton._src.sim.builder import compute_body_inverses_kernel, validate_and_correct_inertia_kernel

        m = self.model
        props = _mass_props(assets)
        m.body_mass.numpy()[...] = np.array([mass for mass, _ in props], dtype=np.float32)
        m.body_inertia.numpy()[...] = np.array([inertia for _, inertia in props], dtype=np.float32)
        count = wp.zeros(1, dtype=wp.int32, device=self.device)
        wp.launch(validate_and_correct_inertia_kernel, dim=m.body_count, device=self.device,
                  inputs=[m.body_mass, m.body_inertia, *self._inertia_checks, count])
        wp.launch(compute_body_inverses_kernel, dim=m.body_count, device=self.device,
                  inputs=[m.body_mass, m.body_inertia], outputs=[m.body_inv_mass, m.body_inv_inertia])
        self.solver.notify_model_changed(newton.ModelFlags.BODY_INERTIAL_PROPERTIES)  # the effective inverses

    def advance_frame(self, track: list | None = None) -> None:
        """Advance one frame. One substep is captured once into a Warp CPU graph and replayed ``substeps``
        times: replay skips Python launch overhead (~30 launches per substep; benchmarks/speed/physics_graph.py
        measures plain against replayed stepping); one substep instead of two halves the capture, a fixed
        cost per scene (~0.02 s, a third of a 2-frame clip's physics; docs/decisions/0006-newton-graph-replay.md)."""
        import warp as wp

        if self.graph is None:
            with wp.ScopedCapture(device=self.device) as capture:
                self.substep()
            self.graph = capture.graph
            if self.reusable:
                self._snapshot = _graph_memory_snapshot(self.graph)
        if track is None:
            for _ in range(self.substeps):
                wp.capture_launch(self.graph)
            return
        view = self.state0.body_q.numpy()
        for _ in range(self.substeps):  # track: each substep's resulting poses appended (a copy of state0)
            wp.capture_launch(self.graph)
            track.append(view.copy())

    def substep(self) -> None:
        """collide and step state0 -> state1, then clamp the speeds of state1 into state0 (one launch that
        also copies the poses back, so every substep starts from state0 and one substep can be captured)."""
        import warp as wp

        if self.pipeline is not None:
            self.pipeline.collide(self.state0, self.contacts)
        self.solver.step(self.state0, self.state1, self.control, self.contacts, self.dt)
        wp.launch(_clamp_kernel(), dim=self.model.body_count, device=self.device,
                  inputs=[self.band, self.state1.body_q, self.state1.body_qd, self.contacts.rigid_contact_count],
                  outputs=[self.state0.body_q, self.state0.body_qd, self.last_dir, self.last_axis, self.peak])

    def overflowed(self) -> bool:
        """Did some substep fill the rigid-contact buffer? Then contacts may have been dropped: Newton's narrow
        phase skips a pair once the count reaches the capacity (the count then stays there) or counts past it."""
        return int(self.peak.numpy()[0]) >= self.pipeline.rigid_contact_max

    def read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = self.state0.body_q.numpy().astype(np.float64)  # (N, 7): px py pz qx qy qz qw
        qd = self.state0.body_qd.numpy().astype(np.float64)
        R = quat_to_rotation(q[:, 3:])
        return pose_matrices(q[:, :3], R), qd[:, :3], qd[:, 3:]


@functools.cache
def _clamp_kernel():
    """Warp kernel that copies each body's pose and clamps its linear and angular speed into a band,
    keeping directions (from the solver's output state into its input state); thread 0 also keeps the most
    rigid contacts any substep has found (``peak``).

    Built on first use so that importing this module never imports Warp.
    """
    import warp as wp

    eps = float(EPS_SPEED)

    @wp.func
    def clamp_norm(x: wp.vec3, last: wp.vec3, lo: float, hi: float):
        n = wp.length(x)
        d = last
        if n > eps:
            d = x / n
        target = wp.clamp(n, lo, hi)
        y = x
        if n > eps or target > 0.0:
            y = d * target
        return y, d

    @wp.kernel(enable_backward=False)
    def clamp_body_speeds(
        band: wp.array(dtype=float),  # min, max linear speed; min, max angular speed
        body_q_in: wp.array(dtype=wp.transform),
        body_qd_in: wp.array(dtype=wp.spatial_vector),
        contact_count: wp.array(dtype=wp.int32),
        # outputs
        body_q: wp.array(dtype=wp.transform),
        body_qd: wp.array(dtype=wp.spatial_vector),
        last_dir: wp.array(dtype=wp.vec3),
        last_axis: wp.array(dtype=wp.vec3),
        peak: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        if i == 0:
            peak[0] = wp.max(peak[0], contact_count[0])
        qd = body_qd_in[i]
        v, dv = clamp_norm(wp.spatial_top(qd), last_dir[i], band[0], band[1])
        w, dw = clamp_norm(wp.spatial_bottom(qd), last_axis[i], band[2], band[3])
        body_q[i] = body_q_in[i]
        body_qd[i] = wp.spatial_vector(v, w)
        last_dir[i] = dv
        last_axis[i] = dw

    return clamp_body_speeds


# Newton's narrow phase builds fresh Warp kernels from factory functions for every CollisionPipeline;
# Warp then re-generates and re-hashes their code on first launch (0.3-3 s per scene, measured in
# benchmarks/accuracy/physics.py; docs/decisions/0007-newton-memoisation.md), although every scene asks for the same few
# variants. These factories are pure functions of their (hashable) arguments, so one kernel per argument tuple
# serves all pipelines.
_NEWTON_KERNEL_FACTORIES = ("create_narrow_phase_primitive_kernel", "create_narrow_phase_kernel_gjk_mpr")
# ModelBuilder.finalize recomputes the edge adjacency of every convex hull for every model (numpy, ~10-30 ms
# a hull), a pure function of the hull; the hulls are the per-process newton.Mesh objects of
# _newton_unit_hull, so one result per hull serves every model (benchmarks/accuracy/physics.py, "memoisation").
_NEWTON_BUILDER_FUNCTIONS = ("_convex_hull_adjacency",)
# (module name, function name) -> the memoised wrapper of Newton's function (it holds the kernels / adjacencies);
# kept across the windows of memoise_newton_kernel_factories, so that every scene of the process shares them
_NEWTON_MEMOS: dict = register("physics.newton_memos", {})


class _NewtonPatch:
    """The state of memoise_newton_kernel_factories' windows: how many are open (all threads together) and what the
    first one replaced. ``lock`` guards both, and every install and restore."""

    lock: ClassVar[threading.Lock] = threading.Lock()
    depth: ClassVar[int] = 0
    replaced: ClassVar[list] = []  # [(module, name, Newton's function, its memoised wrapper)] while depth > 0


def _newton_targets() -> list:
    from newton._src.geometry import narrow_phase
    from newton._src.sim import builder

    return ([(narrow_phase, name, functools.cache) for name in _NEWTON_KERNEL_FACTORIES]
            + [(builder, name, functools.lru_cache(maxsize=1024)) for name in _NEWTON_BUILDER_FUNCTIONS])


@contextlib.contextmanager
def memoise_newton_kernel_factories() -> Iterator[None]:
    """While open, Newton's narrow-phase kernel factories and hull adjacency are memoised (one kernel per argument
    tuple, one adjacency per hull; the memos last for the process); on leaving the last open one, Newton's module
    attributes are its own functions again (identity). :class:`NewtonScene` builds its model and its collision
    pipeline inside one, so flowsynth's scenes share the kernels while no other Newton user of the process sees a
    patch outside flowsynth's calls. Re-entrant and thread-safe: a lock and a count of the open windows of all
    threads. While one is open, another thread calling those Newton functions directly gets the memoised ones,
    which return what the originals would (pure functions). Private Newton API: tests/test_newton_internals.py
    fails, naming this function, when Newton renames them or stops looking them up in those modules. Why, and the
    public hook that would replace it: docs/decisions/0007-newton-memoisation.md."""
    _enter_newton_patch()
    try:
        yield
    finally:
        _leave_newton_patch()


def _enter_newton_patch() -> None:
    with _NewtonPatch.lock:
        if _NewtonPatch.depth == 0:
            for module, name, wrap in _newton_targets():
                fn = getattr(module, name, None)
                if not callable(fn):
                    continue
                key = (module.__name__, name)
                memo = _NEWTON_MEMOS.get(key)
                if memo is None or memo.__wrapped__ is not fn:  # the first window, or Newton's function changed
                    memo = _NEWTON_MEMOS[key] = wrap(fn)
                setattr(module, name, memo)
                _NewtonPatch.replaced.append((module, name, fn, memo))
        _NewtonPatch.depth += 1


def _leave_newton_patch() -> None:
    with _NewtonPatch.lock:
        _NewtonPatch.depth -= 1
        if _NewtonPatch.depth == 0:
            for module, name, fn, memo in _NewtonPatch.replaced:
                if getattr(module, name, None) is memo:  # what someone else put there since stays
                    setattr(module, name, fn)
            _NewtonPatch.replaced.clear()


def _newton_contact_estimate(model) -> int:
    """The rigid-contact capacity Newton's CollisionPipeline picks for ``model`` when given none. Private Newton
    API: tests/test_newton_internals.py fails, naming this function, when it moves or stops being the default."""
    from newton._src.sim.collide import _estimate_rigid_contact_max

    return int(_estimate_rigid_contact_max(model))


def _graph_memory_snapshot(graph) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """(numpy view, copy) of every memory region a captured Warp CPU graph touches: each array its launches were
    given, and the scratch arrays Newton allocated while it was captured (the graph keeps those alive; no attribute
    of the scene reaches them). None, and so no reuse, where a region cannot be read back. Private Warp API
    (``Graph._apic_capture._regions``): tests/test_scene_reuse.py fails, naming this function, when it moves."""
    regions = getattr(getattr(graph, "_apic_capture", None), "_regions", None)
    if not isinstance(regions, dict) or not regions:
        return None
    out = []
    for key, region in regions.items():
        base = region[3] if isinstance(region, tuple) and len(region) == 4 else None
        if key[0] != "warp" or base is None or not hasattr(base, "numpy") or base.ptr is None:
            return None
        if not base.is_contiguous:
            return None
        view = base.numpy()
        out.append((view, view.copy()))
    return out


def _body_xforms(initial: InitialState) -> list:
    """The bodies' initial poses as Warp transforms (float32), as the model builder is given them."""
    import warp as wp

    quats = rotation_to_quat_xyzw(initial.rotation)
    return [wp.transform(wp.vec3(*p), wp.quat(*q)) for p, q in zip(initial.position, quats)]


def _mass_props(assets: Sequence[Asset]) -> list[tuple[float, np.ndarray]]:
    """(mass [kg], inertia about the origin (3, 3) [kg m^2]) of each asset's collider hull at DENSITY."""
    return [(DENSITY * float(a.collider.hull.volume),
             DENSITY * np.asarray(a.collider.hull.moment_inertia_frame(np.eye(4)), dtype=np.float64)) for a in assets]


def _add_collider(b, body: int, asset: Asset, shape_cfg) -> None:
    c = asset.collider
    if c.kind == "box":
        b.add_shape_box(body, hx=c.params[0], hy=c.params[1], hz=c.params[2], cfg=shape_cfg)
    elif c.kind == "sphere":
        b.add_shape_sphere(body, radius=c.params[0], cfg=shape_cfg)
    elif c.kind == "capsule":
        b.add_shape_capsule(body, radius=c.params[0], half_height=c.params[1], cfg=shape_cfg)
    elif c.kind == "cylinder":
        b.add_shape_cylinder(body, radius=c.params[0], half_height=c.params[1], cfg=shape_cfg)
    elif c.kind == "cone":
        b.add_shape_cone(body, radius=c.params[0], half_height=c.params[1], cfg=shape_cfg)
    else:
        s = asset.size
        b.add_shape_convex_hull(body, mesh=_newton_unit_hull(asset.name), scale=(s, s, s), cfg=shape_cfg)


@register("physics.newton_unit_hull")
@functools.lru_cache(maxsize=1024)
def _newton_unit_hull(name: str):
    """newton.Mesh of the unit-size convex collider of asset ``name``, shared by every instance and scale
    (Newton preprocesses each distinct hull once per model)."""
    wp_runtime()
    import newton

    hull = unit_hull(name)
    return newton.Mesh(np.asarray(hull.vertices, dtype=np.float32),
                       np.asarray(hull.faces, dtype=np.int32).ravel(),
                       compute_inertia=False)


def _unit_or(x: np.ndarray, fallback: Sequence[float]) -> np.ndarray:
    """Rows of x (N, 3) normalised; rows shorter than EPS_SPEED become ``fallback``."""
    n = np.linalg.norm(x, axis=1, keepdims=True)
    return np.where(n > EPS_SPEED, x / np.maximum(n, EPS_SPEED), np.asarray(fallback, np.float64))
