"""Which pipeline stages a request needs. Stages whose outputs nobody asked for never run.

| stage            | runs when any of these is requested                                  |
|------------------|----------------------------------------------------------------------|
| primary cast     | always (one per frame)                                               |
| hit points       | position, flow_*, valid_*, occ_*, oof_*, motion, rgb                 |
| normals          | normals, rgb                                                         |
| reprojection     | flow_*, valid_*, occ_*, oof_* (per direction), motion                |
| visibility rays  | occ_fw / occ_bw with occlusion="exact" (per direction)               |
| object tables    | object_* , world_T_obj, box*, visible_pixels                         |
| shading          | rgb                                                                   |
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from flowsynth.errors import ConfigError
from flowsynth.kernels import RENDER_MODES
from flowsynth.parallel import resolve_threads

__all__ = ["DEFAULT_BOUNCES", "DEFAULT_RENDER_MODE", "DEFAULT_TONEMAP", "FLOW_KEYS", "GBUFFER_KEYS", "MAX_BOUNCES",
           "OCCLUSION_METHODS", "OUTPUTS", "RENDER_MODES", "TABLE_KEYS", "TONEMAPS", "Plan", "make_plan"]

GBUFFER_KEYS = ("depth", "distance", "normals", "position", "instance", "category", "asset")
FLOW_KEYS = ("flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "motion")
TABLE_KEYS = ("object_valid", "object_category", "object_asset", "world_T_obj", "box3d_corners",
              "box2d_amodal", "box2d_visible", "visible_pixels")
CAMERA_KEYS = ("K", "cam_T_world")
OUTPUTS = ("rgb",) + GBUFFER_KEYS + FLOW_KEYS + TABLE_KEYS + CAMERA_KEYS
OCCLUSION_METHODS = ("exact", "depth")
# RGB options: the one definition of their choices, ranges and defaults (config, Plan and shading use these;
# the models are in docs/rendering.md). RENDER_MODES is defined beside the kernels that implement them.
DEFAULT_RENDER_MODE = "flat"
TONEMAPS = ("clamp", "reinhard")
DEFAULT_TONEMAP = "clamp"
MAX_BOUNCES = 64  # path-tracing bounces after the first hit lie in [0, MAX_BOUNCES]
DEFAULT_BOUNCES = 3


@dataclass(frozen=True)
class Plan:
    """The stages needed for ``outputs``; flags are derived, never set by hand."""

    outputs: tuple[str, ...]
    occlusion: str = "exact"
    max_objects: int | None = None
    render_mode: str = DEFAULT_RENDER_MODE
    spp: int = 1
    shutter: float = 0.0
    seed: int = 0
    bounces: int = DEFAULT_BOUNCES
    tonemap: str = DEFAULT_TONEMAP
    exposure: float = 1.0
    threads: int | None = None

    def _any(self, *keys: str) -> bool:
        return any(k in self.outputs for k in keys)

    @property
    def rgb(self) -> bool:
        return "rgb" in self.outputs

    @property
    def fw(self) -> bool:
        return self._any("flow_fw", "valid_fw", "occ_fw", "oof_fw", "motion")

    @property
    def bw(self) -> bool:
        return self._any("flow_bw", "valid_bw", "occ_bw", "oof_bw")

    @property
    def flow_stage(self) -> bool:
        return self.fw or self.bw

    @property
    def points(self) -> bool:
        return self.flow_stage or self.rgb or "position" in self.outputs

    @property
    def normals(self) -> bool:
        return self._any("normals", "rgb")

    @property
    def boxes(self) -> bool:
        return self._any(*TABLE_KEYS)


def make_plan(outputs, occlusion: str = "exact", max_objects: int | None = None,
              render_mode: str = DEFAULT_RENDER_MODE, spp: int = 1, shutter: float = 0.0, seed: int = 0,
              bounces: int = DEFAULT_BOUNCES, tonemap: str = DEFAULT_TONEMAP, exposure: float = 1.0,
              threads: int | None = None) -> Plan:
    """Validate a list of output keys and derive the plan. Raises ConfigError naming the valid keys.

    ``threads``: threads of every ray launch (None = all cores the process may use, 1 inside DataLoader and
    export workers; flowsynth.parallel). Results do not depend on it."""
    if isinstance(outputs, str):
        outputs = [s for s in outputs.split(",") if s]
    outputs = tuple(dict.fromkeys(outputs))
    if not outputs:
        raise ConfigError(f"outputs is empty; choose from {', '.join(OUTPUTS)}")
    unknown = [k for k in outputs if k not in OUTPUTS]
    if unknown:
        raise ConfigError(f"unknown output(s) {unknown}; valid outputs are: {', '.join(OUTPUTS)}")
    if occlusion not in OCCLUSION_METHODS:
        raise ConfigError(f"occlusion must be one of {OCCLUSION_METHODS}, got {occlusion!r}")
    if max_objects is not None and (not isinstance(max_objects, int) or max_objects < 0):
        raise ConfigError(f"max_objects must be a non-negative integer, got {max_objects!r}")
    if render_mode not in RENDER_MODES:
        raise ConfigError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if not isinstance(spp, int) or spp < 1:
        raise ConfigError(f"spp must be an integer >= 1, got {spp!r}")
    if not (0.0 <= float(shutter) <= 1.0):
        raise ConfigError(f"shutter must be in [0, 1] (fraction of the frame interval), got {shutter!r}")
    if isinstance(bounces, bool) or not isinstance(bounces, int) or not 0 <= bounces <= MAX_BOUNCES:
        raise ConfigError(f"bounces must be an integer in [0, {MAX_BOUNCES}], got {bounces!r}")
    if tonemap not in TONEMAPS:
        raise ConfigError(f"tonemap must be one of {TONEMAPS}, got {tonemap!r}")
    if not (math.isfinite(float(exposure)) and float(exposure) >= 0.0):
        raise ConfigError(f"exposure must be finite and >= 0, got {exposure!r}")
    if threads is not None:
        resolve_threads(threads)
    return Plan(outputs, occlusion, max_objects, render_mode, int(spp), float(shutter), int(seed), int(bounces),
                tonemap, float(exposure), threads)
