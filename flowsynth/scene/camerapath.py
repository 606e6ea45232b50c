"""Camera paths of BouncingThings: translation, a moving look-at target, and pan / tilt / roll.

A path is :class:`CameraMotion` (drawn by :func:`sample_camera_motion`) evaluated at the frame times
t_k = k / fps by :func:`camera_poses`:

- the eye moves in a straight line from ``eye0`` at ``eye_velocity``, reflected inside the camera box
  (the inner 70% of the camera zone, :func:`camera_box`);
- the look-at target moves from ``target0`` at ``target_velocity``, reflected inside the objects' region;
- (pan, tilt, roll) offsets start at ``angles0`` and change at ``angle_rates`` [rad/s], reflected inside
  ``±cfg.camera_angle_limit``;
- world_R_cam = look_at(eye, target) @ Ry(pan) @ Rx(tilt) @ Rz(roll) in OpenCV camera axes, a gimbal: pan
  turns about the look-at frame's vertical image axis (y), tilt about the panned horizontal axis (x), roll
  about the optical axis (z). With the other offsets at zero each turns about the camera's own axis.

Flow in pixels (``cfg.flow_px`` set). The drawn motion fixes the path's shape: directions, and the mix of
translation, target motion and rotation. One scale factor s multiplies every velocity and rate so that
the median |flow| of the room between frames 0 and 1 equals a target u drawn log-uniformly from
``cfg.flow_px``. The room's flow is computed exactly, by projecting the room points seen through a grid
of pixels of frame 0 into frame 1 (:func:`room_flow_median`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, replace

import numpy as np

from flowsynth.caches import register
from flowsynth.scene.camera import Camera
from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.scene.motion import reflect_in_box

__all__ = ["CameraMotion", "camera_box", "camera_poses", "look_at", "room_flow_median", "sample_camera_motion",
           "scale_to_flow"]

PROBE_GRID = (16, 12)
"""Pixels (columns, rows) of the grid whose room points measure the camera's flow [count]."""
SCALE_ITERATIONS = 6
"""Most fixed-point iterations s <- s * u / median_flow(s) when matching the camera's flow to a target."""
SCALE_RTOL = 0.005
"""Relative tolerance of that match; the flow is nearly linear in s, so one or two iterations suffice."""


@dataclass(frozen=True)
class CameraMotion:
    """A camera path before evaluation; all arrays float64, world frame.

    Attributes:
        eye0: (3,) eye position at t = 0 [m].
        eye_velocity: (3,) [m/s].
        target0: (3,) look-at point at t = 0 [m].
        target_velocity: (3,) [m/s].
        angles0: (3,) (pan, tilt, roll) offsets at t = 0 [rad].
        angle_rates: (3,) (pan, tilt, roll) rates [rad/s].
    """

    eye0: np.ndarray
    eye_velocity: np.ndarray
    target0: np.ndarray
    target_velocity: np.ndarray
    angles0: np.ndarray
    angle_rates: np.ndarray

    def scaled(self, s: float) -> CameraMotion:
        """The same path with every velocity and rate multiplied by ``s``."""
        return replace(self, eye_velocity=self.eye_velocity * s, target_velocity=self.target_velocity * s,
                       angle_rates=self.angle_rates * s)


def look_at(eye: np.ndarray, target: np.ndarray,
            up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """world_T_cam (..., 4, 4) for cameras at ``eye`` (..., 3) looking at ``target`` [m], OpenCV axes:
    z forward, x right, y down, with ``up`` (world) pointing up in the image."""
    eye, target = np.broadcast_arrays(np.asarray(eye, np.float64), np.asarray(target, np.float64))
    z = _unit(target - eye)
    x = _unit(_cross(z, np.broadcast_to(np.asarray(up, np.float64), z.shape)))
    y = _cross(z, x)
    T = np.zeros(eye.shape[:-1] + (4, 4))
    T[..., :3, 0], T[..., :3, 1], T[..., :3, 2], T[..., :3, 3] = x, y, z, eye
    T[..., 3, 3] = 1.0
    return T


def camera_box(cfg: BouncingThingsConfig) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the box the camera centre moves in: the inner 70% of the camera zone [m]."""
    (x0, y0, z0), (_, y1, z1) = cfg.room_bounds
    lo = np.array([x0 + 0.15 * cfg.camera_clearance, y0 + 0.15 * (y1 - y0), z0 + 0.15 * (z1 - z0)])
    hi = np.array([x0 + 0.85 * cfg.camera_clearance, y1 - 0.15 * (y1 - y0), z1 - 0.15 * (z1 - z0)])
    return lo, hi


def sample_camera_motion(cfg: BouncingThingsConfig, rng: np.random.Generator) -> CameraMotion:
    """Draw a camera path in physical units (draw order: eye, target, angles, eye direction, eye speed,
    target direction, target speed, rates). A static camera has zero velocities and rates;
    ``cfg.planar_motion`` keeps the eye and the target moving parallel to the first image plane."""
    lo, hi = camera_box(cfg)
    eye0 = lo + (hi - lo) * rng.uniform([0.3, 0.25, 0.25], [0.7, 0.75, 0.75])
    olo, ohi = (np.asarray(b) for b in cfg.object_bounds)
    target0 = (olo + ohi) / 2.0 + (ohi - olo) * rng.uniform(-0.1, 0.1, size=3)
    limit = np.asarray(cfg.camera_angle_limit)
    angles0 = rng.uniform(-0.5, 0.5, size=3) * limit
    forward = (look_at(eye0, target0)[:3, :3] @ _offset(angles0[None])[0])[:, 2]
    eye_dir = _direction(rng, forward if cfg.planar_motion else None)
    eye_speed = rng.uniform(*cfg.camera_speed)
    target_dir = _direction(rng, forward if cfg.planar_motion else None)
    target_speed = rng.uniform(*cfg.camera_target_speed)
    bounds = np.array([cfg.camera_pan, cfg.camera_tilt, cfg.camera_roll])
    rates = rng.uniform(-1.0, 1.0, size=3) * bounds
    if cfg.camera_motion == "static":
        zero = np.zeros(3)
        return CameraMotion(eye0, zero, target0, zero, angles0, zero)
    return CameraMotion(eye0, eye_dir * eye_speed, target0, target_dir * target_speed, angles0, rates)


def camera_poses(cfg: BouncingThingsConfig, m: CameraMotion, num_frames: int | None = None) -> np.ndarray:
    """(T, 4, 4) float64 world_T_cam of path ``m`` at t_k = k / cfg.fps (module docstring)."""
    T = cfg.num_frames if num_frames is None else num_frames
    t = np.arange(T, dtype=np.float64)[:, None] / cfg.fps
    lo, hi = camera_box(cfg)
    eye, _ = reflect_in_box(m.eye0, m.eye_velocity, t, lo, hi)
    olo, ohi = (np.asarray(b, np.float64) for b in cfg.object_bounds)
    target, _ = reflect_in_box(m.target0, m.target_velocity, t, olo, ohi)
    limit = np.asarray(cfg.camera_angle_limit, np.float64)
    angles, _ = reflect_in_box(m.angles0, m.angle_rates, t, -limit, limit)
    poses = look_at(eye, target)
    poses[:, :3, :3] = poses[:, :3, :3] @ _offset(angles)
    return poses


def _offset(angles: np.ndarray) -> np.ndarray:
    """(T, 3, 3) Ry(pan) @ Rx(tilt) @ Rz(roll) of (T, 3) (pan, tilt, roll) angles [rad]."""
    c, s = np.cos(angles), np.sin(angles)
    cp, ct, cr = c.T
    sp, st, sr = s.T
    # Ry(p) Rx(t) Rz(r), multiplied out
    R = np.empty(angles.shape[:-1] + (3, 3))
    R[:, 0, 0] = cp * cr + sp * st * sr
    R[:, 0, 1] = -cp * sr + sp * st * cr
    R[:, 0, 2] = sp * ct
    R[:, 1, 0] = ct * sr
    R[:, 1, 1] = ct * cr
    R[:, 1, 2] = -st
    R[:, 2, 0] = -sp * cr + cp * st * sr
    R[:, 2, 1] = sp * sr + cp * st * cr
    R[:, 2, 2] = cp * ct
    return R


def room_flow_median(cfg: BouncingThingsConfig, world_T_cam: np.ndarray) -> float:
    """Median |flow| [px] from frame 0 to frame 1 of the room points seen through a ``PROBE_GRID`` of pixels.

    Each probe ray of frame 0 (``world_T_cam[0]``) is cut with the room box (the camera is inside it); the
    exit point is projected with frame 1's camera (``world_T_cam[1]``). Objects are ignored: this is the
    flow of the background.
    """
    uv, X = _room_probe(cfg, world_T_cam[0])
    return _median_flow(cfg, uv, X, world_T_cam[1])


def scale_to_flow(cfg: BouncingThingsConfig, m: CameraMotion, target_px: float) -> tuple[CameraMotion, float]:
    """``m`` scaled so that :func:`room_flow_median` of its first two frames is ``target_px`` [px], within
    ``SCALE_RTOL``. Returns (scaled motion, achieved median [px]). A motion without velocities or rates is
    returned as is."""
    uv, X = _room_probe(cfg, camera_poses(cfg, m, 1)[0])  # frame 0 does not depend on the scale
    s = 1.0
    achieved = _median_flow(cfg, uv, X, camera_poses(cfg, m, 2)[1])
    for _ in range(SCALE_ITERATIONS):
        if achieved <= 0.0 or abs(achieved / target_px - 1.0) <= SCALE_RTOL:
            break
        s *= target_px / achieved
        achieved = _median_flow(cfg, uv, X, camera_poses(cfg, m.scaled(s), 2)[1])
    return (m.scaled(s), achieved) if achieved > 0.0 else (m, achieved)


def _room_probe(cfg: BouncingThingsConfig, world_T_cam0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(uv (P, 2) probe pixels [px], X (P, 3) room points they see from world_T_cam0 [m])."""
    uv, rays_cam = _probe_rays(cfg.width, cfg.height, cfg.fov_deg)
    rays = rays_cam @ world_T_cam0[:3, :3].T
    eye = world_T_cam0[:3, 3]
    lo, hi = (np.asarray(b, np.float64) for b in cfg.room_bounds)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_exit = np.min(np.where(rays > 0, (hi - eye) / rays, np.where(rays < 0, (lo - eye) / rays, np.inf)), 1)
    return uv, eye + rays * t_exit[:, None]


def _median_flow(cfg: BouncingThingsConfig, uv: np.ndarray, X: np.ndarray, world_T_cam1: np.ndarray) -> float:
    K = Camera.from_fov(cfg.width, cfg.height, cfg.fov_deg).K
    R, t = world_T_cam1[:3, :3], world_T_cam1[:3, 3]
    Xc = (X - t) @ R  # cam_T_world applied: R^T (X - t)
    uv1 = (Xc @ K.T)[:, :2] / np.maximum(Xc[:, 2:], 1e-9)
    return float(np.median(np.linalg.norm(uv1 - uv, axis=1)))


@register("camerapath.probe_rays")
@functools.lru_cache(maxsize=64)
def _probe_rays(width: int, height: int, fov_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Probe pixels (P, 2) [px] and their camera-frame ray directions (P, 3), z = 1."""
    K = Camera.from_fov(width, height, fov_deg).K
    gu, gv = np.meshgrid(np.linspace(0.05, 0.95, PROBE_GRID[0]) * (width - 1),
                         np.linspace(0.05, 0.95, PROBE_GRID[1]) * (height - 1))
    uv = np.stack([gu.ravel(), gv.ravel()], 1)
    return uv, np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(K).T


def _direction(rng: np.random.Generator, normal: np.ndarray | None) -> np.ndarray:
    """A random unit vector; perpendicular to ``normal`` when given (3 normal draws either way)."""
    d = rng.normal(size=3)
    if normal is not None:
        d = d - np.dot(d, normal) * normal
    return _unit(d)


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.sqrt(np.sum(x * x, axis=-1, keepdims=True))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (np.cross without its axis bookkeeping, which dominates for 3-vectors)."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)
