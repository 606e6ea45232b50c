"""The G-buffer primitive: one primary ray per pixel centre and frame, cast on a ``SceneAccel``.

``fs.render`` (``flowsynth.renderer``) casts it once per clip; the right camera of ``flowsynth.stereo`` casts it
again. It sits below both, so neither imports the other (docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flowsynth.accel import SceneAccel, pinhole
from flowsynth.kernels import wp_runtime
from flowsynth.parallel import BAND0, launch_bands
from flowsynth.scene import Scene

__all__ = ["GBuffer", "cast_gbuffer", "scene_arrays"]


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
