"""Ray casting: the per-asset BVHs (``blas``), the clip's top-level acceleration (``SceneAccel``: instances, screen
``tiles``, exact culls) and the one primary cast per frame into the G-buffer (``cast_gbuffer``). Warp launches over
tables built with numpy; ``blas`` and ``tiles`` are exported as modules for benchmarks (``tiles.TILE``)."""

from flowsynth.raycast import blas, tiles
from flowsynth.raycast.accel import SceneAccel, pinhole, prepare_clip, resolve_device
from flowsynth.raycast.gbuffer import GBuffer, HostGBuffer, cast_gbuffer, scene_arrays, to_torch

__all__ = [
    "GBuffer",
    "HostGBuffer",
    "SceneAccel",
    "blas",
    "cast_gbuffer",
    "pinhole",
    "prepare_clip",
    "resolve_device",
    "scene_arrays",
    "tiles",
    "to_torch",
]
