"""The G-buffer primitive: one primary ray per pixel centre and frame, cast on a ``SceneAccel``.

``fs.render`` (``flowsynth.renderer.pipeline``) casts it once per clip; the right camera of ``flowsynth.truth.stereo``
casts it again. It sits below both, so neither imports the other (docs/architecture.md).

The G-buffer stays in Warp arrays on the accel's device: the stages that run kernels (flow, position and motion,
shading) read those arrays. ``GBuffer.host()`` is the one hand-over to numpy, made at most once per G-buffer (no
copy on the CPU), for the stages that compute on the host: tracks, object tables, stereo disparity and the final
pass's depth. ``to_torch`` is the edge where a stage's Warp output becomes a CPU tensor.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from flowsynth.kernels import wp_runtime
from flowsynth.parallel import BAND0, launch_image
from flowsynth.raycast.accel import SceneAccel, pinhole
from flowsynth.scene import Scene

__all__ = ["GBuffer", "HostGBuffer", "cast_gbuffer", "scene_arrays", "to_torch"]


@dataclass
class HostGBuffer:
    """The G-buffer's arrays in numpy, (F, H, W, ...): what ``GBuffer.host()`` returns (fields as there)."""

    dist: np.ndarray
    item: np.ndarray
    face: np.ndarray
    point: np.ndarray | None
    normal: np.ndarray | None
    frame_start: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.item >= 0

    @property
    def instance_index(self) -> np.ndarray:
        """0-based instance index per pixel (within its clip), -1 where nothing is hit (item frame_start[f] + n in
        frame f: n = item - frame_start[f], a subtraction rather than a remainder)."""
        offset = self.frame_start[:-1].astype(self.item.dtype).reshape(-1, 1, 1)
        return np.where(self.item >= 0, self.item - offset, -1)


@dataclass
class GBuffer:
    """Raw per-pixel result of the primary cast for F frames (every frame of a batch of clips): Warp arrays (F, H, W)
    on ``device``.

    ``item`` int32 is -1 where the ray hits nothing, else ``frame_start[f] + n`` for instance n (0-based; f N + n
    in one clip of N instances, ``SceneAccel``); ``frame_start`` (F + 1,) numpy int64; ``dist``
    float32 ray length [m] (0 where no hit); ``face`` int32 the hit face (-1 where no hit); ``point`` vec3
    object-frame hit point [m] and ``normal`` vec3 camera-frame normal, or None when not cast. ``host()``: the
    same in numpy.
    """

    dist: Any
    item: Any
    face: Any
    point: Any | None
    normal: Any | None
    frame_start: np.ndarray
    device: str
    _host: HostGBuffer | None = field(default=None, repr=False, compare=False)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(F, H, W)."""
        return tuple(self.dist.shape)

    @property
    def num_instances(self) -> int:
        """Items of every frame together (0: nothing to hit anywhere)."""
        return int(self.frame_start[-1])

    def host(self) -> HostGBuffer:
        """The G-buffer in numpy: made on the first call (a view on the CPU, one copy from another device), the
        same object after. The hand-over of the stages that compute on the host."""
        if self._host is None:
            self._host = HostGBuffer(self.dist.numpy(), self.item.numpy(), self.face.numpy(),
                                     None if self.point is None else self.point.numpy(),
                                     None if self.normal is None else self.normal.numpy(), self.frame_start)
        return self._host


def to_torch(a) -> torch.Tensor:
    """A Warp array as a CPU tensor: ``wp.to_torch`` (shares the memory on the CPU), copied to the host from
    another device. The edge where a stage's output leaves Warp."""
    return wp_runtime().to_torch(a).cpu()


def cast_gbuffer(accel: SceneAccel, camera, *, want_normals: bool, want_points: bool,
                 max_dist: float = 1e9, threads: int | None = None) -> GBuffer:
    """One primary ray per pixel centre for each of the accel's F frames (every frame of a batch of clips, which
    share ``camera``): one kernel launch, a thread per pixel on a GPU, cut into row bands over ``threads`` threads
    on the CPU (``flowsynth.parallel``; None = all cores), on the accel's device."""
    F, H, W = accel.F, camera.height, camera.width
    wp = wp_runtime()
    dev = accel.device
    if accel.empty:
        return GBuffer(wp.zeros((F, H, W), dtype=wp.float32, device=dev),
                       wp.full((F, H, W), -1, dtype=wp.int32, device=dev),
                       wp.full((F, H, W), -1, dtype=wp.int32, device=dev),
                       wp.zeros((F, H, W), dtype=wp.vec3, device=dev) if want_points else None,
                       wp.zeros((F, H, W), dtype=wp.vec3, device=dev) if want_normals else None,
                       accel.frame_start, dev)
    from flowsynth.kernels.raycast import primary_kernel

    dist = wp.empty((F, H, W), dtype=wp.float32, device=dev)  # the kernel writes every pixel
    item = wp.empty((F, H, W), dtype=wp.int32, device=dev)
    face = wp.empty((F, H, W), dtype=wp.int32, device=dev)
    point = wp.empty((F, H, W) if want_points else (1, 1, 1), dtype=wp.vec3, device=dev)
    normal = wp.empty((F, H, W) if want_normals else (1, 1, 1), dtype=wp.vec3, device=dev)
    launch_image(lambda per_pixel: primary_kernel(want_normals, want_points, not camera.is_pinhole, per_pixel),
                 (F, H, W), [accel.instances(), accel.tile_lists(camera), pinhole(camera, dev), float(max_dist), BAND0],
                 [dist, item, face, point, normal], dev, threads)
    return GBuffer(dist, item, face, point if want_points else None, normal if want_normals else None,
                   accel.frame_start, dev)


def scene_arrays(scene: Scene) -> tuple[list, np.ndarray, np.ndarray]:
    """(meshes, cam_T_world (T,4,4), world_T_obj (T,N,4,4)) of a scene, float64."""
    meshes = [o.mesh for o in scene.objects]
    T = scene.num_frames
    world_T_obj = (np.stack([o.poses for o in scene.objects], 1) if meshes else np.zeros((T, 0, 4, 4)))
    return meshes, scene.cam_T_world, world_T_obj
