"""Object motion for BouncingThings: rigid-body physics (Newton), kinematic, or static.

All three return world_T_obj poses (T, N, 4, 4) float64 at the frame times t_k = k / fps, k = 0..T-1,
with orthonormal rotations. The object origin is the centre of its bounding sphere (flowsynth.scene.assets)
and is also its centre of mass in the physics, so "speed" is the speed of the origin.

- ``physics``: Newton's XPBD solver on the Warp CPU device (``flowsynth.scene.physics``: the Newton back-end, its
  scoped patches and scene reuse; ``simulate_physics``, ``choose_substeps`` and ``NewtonScene`` are re-exported
  here).
- ``kinematic``: constant speed and angular velocity; the bounding sphere reflects specularly off the
  walls of ``cfg.object_bounds`` (closed form). Objects may intersect each other (FlyingThings style).
- ``static``: every pose equals the initial pose.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from flowsynth.errors import ConfigError, ShapeError
from flowsynth.scene.assets import Asset
from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.scene.physics import (NewtonScene, choose_substeps, memoise_newton_kernel_factories, simulate_physics,
                                     wall_boxes)
from flowsynth.scene.trajectory import InitialState, Trajectory, pose_matrices, quat_to_rotation, simulate_static

__all__ = [
    "InitialState",
    "NewtonScene",
    "Trajectory",
    "choose_substeps",
    "memoise_newton_kernel_factories",
    "quat_to_rotation",
    "reflect_in_box",
    "rotation_exp",
    "simulate",
    "simulate_kinematic",
    "simulate_physics",
    "simulate_static",
    "wall_boxes",
]


def simulate(cfg: BouncingThingsConfig, assets: Sequence[Asset], initial: InitialState, *,
             num_frames: int | None = None, substeps: int | None = None) -> Trajectory:
    """Move N objects according to ``cfg.motion``.

    Args:
        cfg: scene configuration (motion, fps, speeds, room, gravity, restitution, friction).
        assets: the N objects' assets (colliders and sizes).
        initial: state at t = 0.
        num_frames: T; defaults to ``cfg.num_frames``.
        substeps: physics substeps per frame; defaults to ``cfg.substeps``, else :func:`choose_substeps`.
    """
    T = cfg.num_frames if num_frames is None else int(num_frames)
    n = len(assets)
    for name, shape in (("position", (n, 3)), ("rotation", (n, 3, 3)), ("velocity", (n, 3)),
                        ("angular_velocity", (n, 3))):
        got = np.shape(getattr(initial, name))
        if got != shape:
            raise ShapeError(f"initial.{name} must have shape {shape} for {n} assets, got {got}")
    if cfg.motion == "static":
        return simulate_static(initial, T)
    if cfg.motion == "kinematic":
        return simulate_kinematic(cfg, assets, initial, T)
    return simulate_physics(cfg, assets, initial, T, substeps=substeps)



def simulate_kinematic(cfg: BouncingThingsConfig, assets: Sequence[Asset], initial: InitialState,
                       num_frames: int) -> Trajectory:
    """Constant speed and angular velocity; bounding spheres reflect off the walls of cfg.object_bounds."""
    t = np.arange(num_frames, dtype=np.float64) / cfg.fps
    lo, hi = (np.asarray(b, dtype=np.float64) for b in cfg.object_bounds)
    r = np.array([a.size / 2.0 for a in assets], dtype=np.float64)[:, None]  # (N, 1)
    pos, vel = reflect_in_box(initial.position[None], initial.velocity[None], t[:, None, None],
                              lo + r, hi - r)
    R = rotation_exp(t[:, None, None] * initial.angular_velocity[None]) @ initial.rotation[None]
    w = np.broadcast_to(initial.angular_velocity, vel.shape).copy()
    return Trajectory(pose_matrices(pos, R), vel, w, 0)


def reflect_in_box(p0: np.ndarray, v: np.ndarray, t: np.ndarray, lo: np.ndarray, hi: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Point moving at velocity ``v`` from ``p0`` at t = 0, reflected specularly inside the box [lo, hi].

    Closed form: each axis folds x0 + v t into [lo, hi] with period 2 (hi - lo). Arrays broadcast;
    the last axis is x, y, z [m], [m/s], and ``t`` [s]. Returns (position [m], velocity [m/s] at t).
    """
    L = hi - lo
    if np.any(L < 0):
        raise ConfigError("reflect_in_box: box is smaller than the moving sphere; enlarge the room")
    L = np.maximum(L, 1e-12)
    u = np.mod(p0 - lo + v * t, 2.0 * L)
    back = u > L
    return lo + np.where(back, 2.0 * L - u, u), np.where(back, -v, v) * np.ones_like(u)


def rotation_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors (..., 3) [rad] (Rodrigues' formula)."""
    theta = np.linalg.norm(rotvec, axis=-1)[..., None, None]
    k = rotvec / np.maximum(theta[..., 0], 1e-300)
    K = np.zeros(rotvec.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)
