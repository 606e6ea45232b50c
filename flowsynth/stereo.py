"""Rectified stereo: a right camera at ``stereo_baseline`` B metres along the left camera's +x axis.

The right camera has the left camera's intrinsics K and orientation in every frame:
world_T_cam_right[t] = world_T_cam[t] @ [I (B, 0, 0); 0 1]. A camera-frame point X = (x, y, z) of the left
camera is (x - B, y, z) in the right one, so it projects to the same row and to u_R = u_L - fx B / z
(skew included): the disparity of a surface at depth z is d = fx B / z [px], for either view.

| key                 | shape, dtype         | value                                                              |
|---------------------|----------------------|--------------------------------------------------------------------|
| rgb_right           | (T,3,H,W) float32    | the right view, shaded with the left view's lights                 |
| depth_right         | (T,1,H,W) float32    | planar depth of the right view [m], 0 = no hit                     |
| disparity           | (T,1,H,W) float32    | fx B / depth [px] of the left view, 0 = no hit                     |
| disparity_right     | (T,1,H,W) float32    | fx B / depth_right [px], 0 = no hit                                |
| disparity_change    | (T-1,1,H,W) float32  | fx B / z_{t+1} - fx B / z_t [px] of the surface point seen at the  |
|                     |                      | left pixel of frame t (FlyingThings3D); 0 where not valid_fw       |
| disparity_occ       | (T,1,H,W) bool       | the left pixel's surface point is not visible in the right view    |
| disparity_occ_right | (T,1,H,W) bool       | the right pixel's surface point is not visible in the left view    |

Both occlusion masks are ``occ`` of flowsynth/flow.py with the other view as target: out of frame,
behind the camera, or hidden per the exact visibility ray (always "exact"; False where no hit).
"""

from __future__ import annotations

import copy

import numpy as np
import torch

from flowsynth.raycast import SceneAccel
from flowsynth.flow import reproject_pixels

__all__ = ["right_poses", "stereo_outputs"]


def right_poses(world_T_cam: np.ndarray, baseline: float) -> np.ndarray:
    """(T, 4, 4) world_T_cam of the right camera: the left pose moved by ``baseline`` [m] along its +x."""
    shift = np.eye(4)
    shift[0, 3] = baseline
    return world_T_cam @ shift


def _occlusion(camera, accel, gb, cam_T_obj_target: np.ndarray, threads) -> np.ndarray:
    """(T, 1, H, W) bool: hit pixels of ``gb`` whose point is not visible from the target view (same frame)."""
    return reproject_pixels(gb, cam_T_obj_target, camera.K, 0, 0, gb.shape[0], accel=accel, camera=camera,
                            occlusion="exact", threads=threads)["occ"]


def stereo_outputs(scene, accel, gb, plan, world_T_obj: np.ndarray, cam_T_world: np.ndarray,
                   device: str = "cpu", done=()) -> dict[str, torch.Tensor]:
    """Every stereo key the plan asks for except those in ``done`` (``disparity_change`` rides on the flow
    stage's fw gap-1 pass when that runs: flowsynth/flow.py); ``accel``/``gb`` are the left view's."""
    from flowsynth.raycast import cast_gbuffer

    want = set(plan.outputs) - set(done)
    B = plan.stereo_baseline
    cam = scene.camera
    fB = cam.fx * B
    dz = cam.pixel_rays_numpy()[..., 2]
    out: dict[str, np.ndarray | torch.Tensor] = {}
    meshes = [o.mesh for o in scene.objects]
    if "disparity" in want:
        out["disparity"] = _disparity(gb, dz, fB)
    if "disparity_change" in want:
        cam_T_obj = np.matmul(cam_T_world[:, None], world_T_obj)
        out["disparity_change"] = reproject_pixels(gb, cam_T_obj, cam.K, 0, 1, max(gb.shape[0] - 1, 0), fB=fB,
                                                   threads=plan.threads)["dc"]
    right_keys = {"rgb_right", "depth_right", "disparity_right", "disparity_occ", "disparity_occ_right"}
    if want & right_keys:
        world_T_cam_r = right_poses(scene.world_T_cam, B)
        cam_T_world_r = np.linalg.inv(world_T_cam_r)
        accel_r = SceneAccel(meshes, cam_T_world_r, world_T_obj, device=device)
        need_points = bool(want & {"rgb_right", "disparity_occ_right"})
        gb_r = cast_gbuffer(accel_r, cam, want_normals="rgb_right" in want, want_points=need_points,
                            threads=plan.threads)
        if "depth_right" in want:
            out["depth_right"] = (gb_r.host().dist * dz).astype(np.float32)[:, None]  # dist is 0 where no hit
        if "disparity_right" in want:
            out["disparity_right"] = _disparity(gb_r, dz, fB)
        if "disparity_occ" in want:
            out["disparity_occ"] = _occlusion(cam, accel_r, gb, np.matmul(cam_T_world_r[:, None], world_T_obj),
                                              plan.threads)
        if "disparity_occ_right" in want:
            out["disparity_occ_right"] = _occlusion(cam, accel, gb_r, np.matmul(cam_T_world[:, None], world_T_obj),
                                                    plan.threads)
        if "rgb_right" in want:
            out["rgb_right"] = _rgb_right(scene, accel_r, gb, gb_r, plan, world_T_cam_r, device)
    return {k: v if isinstance(v, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(v)).to(
        torch.bool if v.dtype == bool else torch.float32) for k, v in out.items()}


def _disparity(gb, dz: np.ndarray, fB: float) -> np.ndarray:
    """(T, 1, H, W) float32 fB / z of a view, z = dist * dz its planar depth in float64 (rounded once); 0 where
    no hit."""
    host = gb.host()  # computed on the host
    d = np.zeros(host.dist.shape, np.float32)
    np.divide(fB, host.dist * dz, out=d, where=host.hit)
    return d[:, None]


def _rgb_right(scene, accel_r, gb, gb_r, plan, world_T_cam_r: np.ndarray, device: str) -> torch.Tensor:
    """The right view shaded with exactly the left view's lights (defaults are placed from the left view)."""
    from flowsynth.appearance import resolve_lights
    from flowsynth.shading import median_hit_distance, render_rgb

    right = copy.copy(scene)
    right.lights = resolve_lights(scene.lights, scene.world_T_cam[0], median_hit_distance(gb))
    right.world_T_cam = world_T_cam_r
    return render_rgb(right, accel_r, gb_r, plan, device=device)
