"""Rectified stereo: a right camera at ``stereo_baseline`` B metres along the left camera's +x axis.

The right camera has the left camera's intrinsics K and orientation in every frame:
world_T_cam_right[t] = world_T_cam[t] @ [I (B, 0, 0); 0 1]. A camera-frame point X = (x, y, z) of the left
camera is (x - B, y, z) in the right one, so it projects to the same row and to u_R = u_L - fx B / z
(skew included): the disparity of a surface at depth z is d = fx B / z [px], for either view.

| key                 | shape, dtype         | value                                                              |
|---------------------|----------------------|--------------------------------------------------------------------|
| rgb_right           | (T,3,H,W) float32    | the right view, shaded with the left view's lights (by the         |
|                     |                      | renderer, from ``right_view``: an image, not geometry)             |
| depth_right         | (T,1,H,W) float32    | planar depth of the right view [m], 0 = no hit                     |
| disparity           | (T,1,H,W) float32    | fx B / depth [px] of the left view, 0 = no hit                     |
| disparity_right     | (T,1,H,W) float32    | fx B / depth_right [px], 0 = no hit                                |
| disparity_change    | (T-1,1,H,W) float32  | fx B / z_{t+1} - fx B / z_t [px] of the surface point seen at the  |
|                     |                      | left pixel of frame t (FlyingThings3D); 0 where not valid_fw       |
| disparity_occ       | (T,1,H,W) bool       | the left pixel's surface point is not visible in the right view    |
| disparity_occ_right | (T,1,H,W) bool       | the right pixel's surface point is not visible in the left view    |

Both occlusion masks are ``occ`` of flowsynth/truth/flow.py with the other view as target: out of frame,
behind the camera, or hidden per the exact visibility ray (always "exact"; False where no hit).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from flowsynth.raycast import SceneAccel
from flowsynth.truth.flow import reproject_pixels

__all__ = ["RIGHT_VIEW_KEYS", "RightView", "right_poses", "right_view", "stereo_outputs"]

# The keys that need the right view's own cast (``right_view``).
RIGHT_VIEW_KEYS = frozenset({"rgb_right", "depth_right", "disparity_right", "disparity_occ", "disparity_occ_right"})


def right_poses(world_T_cam: np.ndarray, baseline: float) -> np.ndarray:
    """(T, 4, 4) world_T_cam of the right camera: the left pose moved by ``baseline`` [m] along its +x."""
    shift = np.eye(4)
    shift[0, 3] = baseline
    return world_T_cam @ shift


def _occlusion(camera, accel, gb, cam_T_obj_target: np.ndarray, threads) -> np.ndarray:
    """(T, 1, H, W) bool: hit pixels of ``gb`` whose point is not visible from the target view (same frame)."""
    return reproject_pixels(gb, cam_T_obj_target, camera.K, 0, 0, gb.shape[0], accel=accel, camera=camera,
                            occlusion="exact", threads=threads)["occ"]


class RightView(NamedTuple):
    """The right camera's view of a clip: its poses, scene acceleration and G-buffer."""

    world_T_cam: np.ndarray  # (T, 4, 4) world_T_cam of the right camera
    cam_T_world: np.ndarray  # (T, 4, 4) its inverse
    accel: SceneAccel
    gb: object  # flowsynth.raycast.GBuffer of the right view


def right_view(scene, world_T_obj: np.ndarray, plan, device: str = "cpu") -> RightView | None:
    """The right view, cast once when the plan asks for a key of it (``RIGHT_VIEW_KEYS``), else None; normals only for
    ``rgb_right``, object-frame points only for ``rgb_right`` and ``disparity_occ_right``."""
    from flowsynth.raycast import cast_gbuffer

    want = set(plan.outputs)
    if not want & RIGHT_VIEW_KEYS:
        return None
    world_T_cam_r = right_poses(scene.world_T_cam, plan.stereo_baseline)
    cam_T_world_r = np.linalg.inv(world_T_cam_r)
    accel_r = SceneAccel([o.mesh for o in scene.objects], cam_T_world_r, world_T_obj, device=device)
    need_points = bool(want & {"rgb_right", "disparity_occ_right"})
    gb_r = cast_gbuffer(accel_r, scene.camera, want_normals="rgb_right" in want, want_points=need_points,
                        threads=plan.threads)
    return RightView(world_T_cam_r, cam_T_world_r, accel_r, gb_r)


def stereo_outputs(scene, accel, gb, plan, world_T_obj: np.ndarray, cam_T_world: np.ndarray,
                   right: RightView | None = None, done=()) -> dict[str, torch.Tensor]:
    """Every stereo key the plan asks for except ``rgb_right`` (an image: the renderer shades it from ``right``) and
    those in ``done`` (``disparity_change`` rides on the flow stage's fw gap-1 pass when that runs:
    flowsynth/truth/flow.py); ``accel``/``gb`` are the left view's, ``right`` is ``right_view``'s (needed for the right
    view's keys)."""
    want = set(plan.outputs) - set(done) - {"rgb_right"}
    B = plan.stereo_baseline
    cam = scene.camera
    fB = cam.fx * B
    dz = cam.pixel_rays_numpy()[..., 2]
    out: dict[str, np.ndarray | torch.Tensor] = {}
    if "disparity" in want:
        out["disparity"] = _disparity(gb, dz, fB)
    if "disparity_change" in want:
        cam_T_obj = np.matmul(cam_T_world[:, None], world_T_obj)
        out["disparity_change"] = reproject_pixels(gb, cam_T_obj, cam.K, 0, 1, max(gb.shape[0] - 1, 0), fB=fB,
                                                   threads=plan.threads)["dc"]
    if want & RIGHT_VIEW_KEYS:
        if "depth_right" in want:
            out["depth_right"] = (right.gb.host().dist * dz).astype(np.float32)[:, None]  # dist is 0 where no hit
        if "disparity_right" in want:
            out["disparity_right"] = _disparity(right.gb, dz, fB)
        if "disparity_occ" in want:
            out["disparity_occ"] = _occlusion(cam, right.accel, gb, np.matmul(right.cam_T_world[:, None], world_T_obj),
                                              plan.threads)
        if "disparity_occ_right" in want:
            out["disparity_occ_right"] = _occlusion(cam, accel, right.gb, np.matmul(cam_T_world[:, None], world_T_obj),
                                                    plan.threads)
    return {k: v if isinstance(v, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(v)).to(
        torch.bool if v.dtype == bool else torch.float32) for k, v in out.items()}


def _disparity(gb, dz: np.ndarray, fB: float) -> np.ndarray:
    """(T, 1, H, W) float32 fB / z of a view, z = dist * dz its planar depth in float64 (rounded once); 0 where
    no hit."""
    host = gb.host()  # computed on the host
    d = np.zeros(host.dist.shape, np.float32)
    np.divide(fB, host.dist * dz, out=d, where=host.hit)
    return d[:, None]
