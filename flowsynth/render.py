"""``fs.render``: one primary ray cast per frame -> G-buffer -> requested ground truth, as torch tensors.

Output keys, shapes and meaning are those of docs/conventions.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from flowsynth.accel import SceneAccel, pinhole
from flowsynth.kernels import wp_runtime
from flowsynth.parallel import BAND0, launch_bands
from flowsynth.plan import Plan, make_plan
from flowsynth.scene import Scene

__all__ = ["GBuffer", "cast_gbuffer", "render"]


@dataclass
class GBuffer:
    """Raw per-pixel result of the primary cast for F frames (numpy, (F, H, W, ...)).

    ``item`` is -1 where the ray hits nothing, else ``f * N + n`` for instance n (0-based);
    ``dist`` ray length [m]; ``point`` object-frame hit point [m]; ``normal`` camera frame.
    """

    dist: np.ndarray
    item: np.ndarray
    face: np.ndarray
    point: np.ndarray | None
    normal: np.ndarray | None
    num_instances: int

    @property
    def hit(self) -> np.ndarray:
        return self.item >= 0

    @property
    def instance_index(self) -> np.ndarray:
        """0-based instance index per pixel, -1 where nothing is hit."""
        return np.where(self.item >= 0, self.item % max(self.num_instances, 1), -1)


def cast_gbuffer(accel: SceneAccel, camera, *, want_normals: bool, want_points: bool,
                 max_dist: float = 1e9, threads: int | None = None) -> GBuffer:
    """One primary ray per pixel centre for each of the accel's F frames: one kernel launch, cut into row
    bands over ``threads`` threads (``flowsynth.parallel``; None = all cores)."""
    F, H, W = accel.F, camera.height, camera.width
    if accel.empty:
        return GBuffer(np.zeros((F, H, W), np.float32), np.full((F, H, W), -1, np.int32),
                       np.full((F, H, W), -1, np.int32),
                       np.zeros((F, H, W, 3), np.float32) if want_points else None,
                       np.zeros((F, H, W, 3), np.float32) if want_normals else None, 0)
    wp = wp_runtime()
    from flowsynth.kernels.raycast import primary_kernel

    dev = accel.device
    dist = wp.empty((F, H, W), dtype=wp.float32, device=dev)  # the kernel writes every pixel
    item = wp.empty((F, H, W), dtype=wp.int32, device=dev)
    face = wp.empty((F, H, W), dtype=wp.int32, device=dev)
    shape3 = (F, H, W) if want_points else (1, 1, 1)
    point = wp.empty(shape3, dtype=wp.vec3, device=dev)
    normal = wp.empty((F, H, W) if want_normals else (1, 1, 1), dtype=wp.vec3, device=dev)
    launch_bands(
        primary_kernel(want_normals, want_points, not camera.is_pinhole), (F, H, W), 1,
        [accel.instances(), accel.tile_lists(camera), pinhole(camera, dev), float(max_dist), BAND0],
        [dist, item, face, point, normal], dev, threads, row_loop=True,
    )
    return GBuffer(dist.numpy(), item.numpy(), face.numpy(), point.numpy() if want_points else None,
                   normal.numpy() if want_normals else None, accel.N)


def scene_arrays(scene: Scene) -> tuple[list, np.ndarray, np.ndarray]:
    """(meshes, cam_T_world (T,4,4), world_T_obj (T,N,4,4)) of a scene, float64."""
    meshes = [o.mesh for o in scene.objects]
    T = scene.num_frames
    world_T_obj = (np.stack([o.poses for o in scene.objects], 1) if meshes else np.zeros((T, 0, 4, 4)))
    return meshes, scene.cam_T_world, world_T_obj


def render(scene: Scene, outputs: list[str] | tuple[str, ...] = ("depth",), *, device: str = "cpu",
           occlusion: str = "exact", **options) -> dict[str, torch.Tensor]:
    """Render the requested ground truth of every frame of ``scene``.

    Args:
        scene: camera path and objects.
        outputs: keys from ``flowsynth.plan.OUTPUTS`` (see docs/conventions.md for shapes and units).
        device: Warp device for the kernels ("cpu", or "cuda" where available). Results are CPU tensors.
        occlusion: "exact" (visibility rays) or "depth" (cheaper depth-buffer comparison; benchmarks/accuracy.py
            measures what each costs and how often each is wrong).
        options: further ``flowsynth.plan.make_plan`` options, e.g. ``threads`` (ray-launch threads; None =
            every core the process may use, 1 inside DataLoader and export workers; see flowsynth.parallel).

    Returns:
        dict mapping each requested key to a CPU tensor.
    """
    plan = make_plan(outputs, occlusion=occlusion, **options)
    return render_plan(scene, plan, device=device)


def render_plan(scene: Scene, plan: Plan, device: str = "cpu") -> dict[str, torch.Tensor]:
    """Run the stages of ``plan`` on ``scene``."""
    if plan.seed is None:  # the renderer's noise seed: the scene's unless the plan sets one
        plan = replace(plan, seed=int(scene.render_seed))
    meshes, cam_T_world, world_T_obj = scene_arrays(scene)
    accel = SceneAccel(meshes, cam_T_world, world_T_obj, device=device)
    gb = cast_gbuffer(accel, scene.camera, want_normals=plan.normals, want_points=plan.points, threads=plan.threads)
    out: dict[str, torch.Tensor] = {}
    out.update(gbuffer_outputs(scene, gb, plan, world_T_obj))
    if plan.flow_stage:
        from flowsynth.flow import flow_outputs

        out.update(flow_outputs(scene, accel, gb, plan, world_T_obj, cam_T_world))
    if plan.stereo:
        from flowsynth.stereo import stereo_outputs

        out.update(stereo_outputs(scene, accel, gb, plan, world_T_obj, cam_T_world, device=device, done=out))
    if plan.tracks:
        from flowsynth.tracks import track_outputs

        out.update(track_outputs(scene, accel, gb, plan, world_T_obj, cam_T_world))
    if plan.boxes:
        from flowsynth.annotations import object_tables

        out.update(object_tables(scene, gb, plan, world_T_obj, cam_T_world))
    if plan.rgb:
        from flowsynth.shading import render_rgb

        out["rgb"] = render_rgb(scene, accel, gb, plan, device=device)
    if "K" in plan.outputs:
        out["K"] = torch.from_numpy(scene.camera.K.astype(np.float32))
    if "cam_T_world" in plan.outputs:
        out["cam_T_world"] = torch.from_numpy(cam_T_world.astype(np.float32))
    return {k: out[k] for k in plan.outputs}


def gbuffer_outputs(scene: Scene, gb: GBuffer, plan: Plan, world_T_obj: np.ndarray) -> dict[str, torch.Tensor]:
    """depth, distance, normals, position, instance, category, asset from the raw G-buffer."""
    out = {}
    want = set(plan.outputs)
    idx = gb.instance_index
    if "distance" in want:
        out["distance"] = torch.from_numpy(gb.dist[:, None].copy())
    if "depth" in want:
        dz = scene.camera.pixel_rays_numpy()[..., 2]
        out["depth"] = torch.from_numpy((gb.dist.astype(np.float64) * dz).astype(np.float32)[:, None])
    if "normals" in want:
        out["normals"] = torch.from_numpy(np.ascontiguousarray(gb.normal.transpose(0, 3, 1, 2)))
    if "position" in want:
        from flowsynth.flow import world_points

        pos = world_points(gb, world_T_obj, moved=False, threads=plan.threads)[0]
        out["position"] = torch.from_numpy(np.ascontiguousarray(pos.astype(np.float32).transpose(0, 3, 1, 2)))
    lut = {
        "instance": np.array([o.instance for o in scene.objects], np.int32),
        "category": np.array([o.category for o in scene.objects], np.int32),
        "asset": np.array([o.asset for o in scene.objects], np.int32),
    }
    for key, table in lut.items():
        if key in want:
            table0 = np.concatenate([table, np.zeros(1, np.int32)])  # index -1 -> 0
            out[key] = torch.from_numpy(table0[idx][:, None].copy())
    return out
