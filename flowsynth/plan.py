"""Which pipeline stages a request needs. Stages whose outputs nobody asked for never run.

| stage            | runs when any of these is requested                                  |
|------------------|----------------------------------------------------------------------|
| primary cast     | always (one per frame)                                               |
| hit points       | position, flow_*, valid_*, occ_*, oof_*, motion, rgb                 |
| normals          | normals, rgb                                                         |
| reprojection     | flow_*, valid_*, occ_*, oof_* (per direction and frame gap), motion  |
| scene flow       | scene_flow_* (per direction and frame gap)                           |
| visibility rays  | occ_* with occlusion="exact" (per direction and gap), point tracks   |
| point tracks     | target_points, occluded, query_points (alias ``tracks``)             |
| right camera     | rgb_right, depth_right, disparity*, (stereo_baseline > 0)            |
| object tables    | object_* , world_T_obj, box*, visible_pixels                         |
| shading          | rgb                                                                   |
| final pass       | rgb_final (a second shading with its own shutter, then lens and sensor effects) |
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

from flowsynth.errors import ConfigError
from flowsynth.options import (  # re-exported: the options' one definition is flowsynth/options.py
    DEFAULT_BOUNCES,
    DEFAULT_RENDER_MODE,
    DEFAULT_TONEMAP,
    FINAL_OPTIONS,
    MAX_BOUNCES,
    OPTION_NAMES,
    RENDER_MODES,
    TONEMAPS,
    TRACK_SAMPLING,
    FinalPass,
    RenderOptions,
    check_flow_gaps,
)
from flowsynth.parallel import resolve_threads

__all__ = ["CORE_OUTPUTS", "DEFAULT_BOUNCES", "DEFAULT_RENDER_MODE", "DEFAULT_TONEMAP", "FINAL_KEYS", "FINAL_OPTIONS",
           "FLOW_KEYS", "GAP_KEYS", "GBUFFER_KEYS", "MAX_BOUNCES", "OCCLUSION_METHODS", "OUTPUTS", "RENDER_MODES",
           "SCENE_FLOW_KEYS", "STEREO_KEYS", "TABLE_KEYS", "TONEMAPS", "TRACK_KEYS", "TRACK_SAMPLING", "FinalPass",
           "Plan", "RenderOptions", "expand_outputs", "gap_key", "make_plan", "split_gap_key"]

GBUFFER_KEYS = ("depth", "distance", "normals", "position", "instance", "category", "asset")
FLOW_KEYS = ("flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "motion")
TABLE_KEYS = ("object_valid", "object_category", "object_asset", "world_T_obj", "box3d_corners",
              "box2d_amodal", "box2d_visible", "visible_pixels")
CAMERA_KEYS = ("K", "cam_T_world")
SCENE_FLOW_KEYS = ("scene_flow_fw", "scene_flow_bw")
# Per-pair keys that exist for every frame gap k of ``flow_gaps``: k = 1 under these names, k >= 2 as
# ``gap_key(key, k)`` = KEY_kK (e.g. flow_fw_k2), shape (T-k, C, H, W), index t = pair (t, t+k).
GAP_KEYS = FLOW_KEYS[:-1] + SCENE_FLOW_KEYS
# Point tracks in the TAP-Vid layout (flowsynth/truth/tracks.py); the alias ``tracks`` requests all three.
TRACK_KEYS = ("target_points", "occluded", "query_points")
ALIASES = {"tracks": TRACK_KEYS}
# Rectified right camera at ``stereo_baseline`` metres along the left camera's +x (flowsynth/truth/stereo.py).
STEREO_KEYS = ("rgb_right", "depth_right", "disparity", "disparity_right", "disparity_change", "disparity_occ",
               "disparity_occ_right")
# The outputs before scene flow, tracks and stereo (benchmarks/speed/throughput.py keeps timing this set).
CORE_OUTPUTS = ("rgb",) + GBUFFER_KEYS + FLOW_KEYS + TABLE_KEYS + CAMERA_KEYS
# The "final" pass beside the clean ``rgb``: motion blur, depth of field, fog, exposure / white balance, sensor noise
# (flowsynth/renderer/finalpass.py, docs/rendering.md "Final pass"); ground truth stays that of the clean pinhole
# geometry.
FINAL_KEYS = ("rgb_final",)
OUTPUTS = CORE_OUTPUTS + SCENE_FLOW_KEYS + TRACK_KEYS + STEREO_KEYS + FINAL_KEYS
_GAP_RE = re.compile(r"^(?P<base>[a-z_]+_(?:fw|bw))_k(?P<k>[0-9]+)$")
OCCLUSION_METHODS = ("exact", "depth")


@dataclass(frozen=True, kw_only=True)
class Plan:
    """The stages needed for ``outputs`` under ``options``; flags are derived, never set by hand (``make_plan``).

    Every render option reads through the plan as well: ``plan.spp`` is ``plan.options.spp``, ``plan.final_pass``
    is ``plan.options.final_pass``; ``with_options`` changes some."""

    outputs: tuple[str, ...]
    options: RenderOptions = field(default_factory=RenderOptions)
    occlusion: str = "exact"
    seed: int | None = None
    """The renderer's noise seed; None: the scene's ``render_seed``."""
    threads: int | None = None
    shutter_offset: float = 0.0
    """[frames] added to every motion-blur sample time: -shutter / 2 centres the shutter on the frame instant
    (the final pass sets it; make_plan leaves 0, the shutter opening at the frame instant)."""

    def __getattr__(self, name: str):  # only for names that are no attribute of the plan: the render options
        if name in OPTION_NAMES or name == "final_pass":
            return getattr(self.options, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def with_options(self, **changes) -> Plan:
        """This plan with some render options changed (validated as ``RenderOptions`` validates them)."""
        return replace(self, options=RenderOptions.from_options(self.options, **changes))

    def _any(self, *keys: str) -> bool:
        return any(k in self.outputs for k in keys)

    @property
    def rgb(self) -> bool:
        return "rgb" in self.outputs

    @property
    def final(self) -> bool:
        return self._any(*FINAL_KEYS)

    @property
    def pair_jobs(self) -> tuple[tuple[str, int], ...]:
        """(direction "fw"/"bw", gap k) of every frame pairing some requested key needs, in a fixed order."""
        keys = [split_gap_key(k) for k in self.outputs]
        jobs = {(base[-2:], k) for base, k in filter(None, keys)}
        if "motion" in self.outputs:
            jobs.add(("fw", 1))
        return tuple(sorted(jobs, key=lambda j: (j[1], j[0] == "bw")))

    @property
    def fw(self) -> bool:
        return any(d == "fw" for d, _ in self.pair_jobs)

    @property
    def bw(self) -> bool:
        return any(d == "bw" for d, _ in self.pair_jobs)

    @property
    def flow_stage(self) -> bool:
        return bool(self.pair_jobs)

    @property
    def tracks(self) -> bool:
        return self._any(*TRACK_KEYS)

    @property
    def stereo(self) -> bool:
        return self._any(*STEREO_KEYS)

    @property
    def points(self) -> bool:
        return (self.flow_stage or self.rgb or self.final or self.tracks or "position" in self.outputs
                or self._any("disparity_change", "disparity_occ"))

    @property
    def normals(self) -> bool:
        return self._any("normals", "rgb", *FINAL_KEYS)

    @property
    def boxes(self) -> bool:
        return self._any(*TABLE_KEYS)


def gap_key(key: str, k: int) -> str:
    """Name of per-pair ``key`` (one of GAP_KEYS) for frame gap k: the key itself for k = 1, else KEY_kK."""
    return key if k == 1 else f"{key}_k{k}"


def split_gap_key(key: str) -> tuple[str, int] | None:
    """(base key in GAP_KEYS, gap k) of a per-pair key such as ``occ_bw_k4``; None for other keys."""
    if key in GAP_KEYS:
        return key, 1
    m = _GAP_RE.match(key)
    if m and m["base"] in GAP_KEYS and int(m["k"]) >= 2 and m["k"] == str(int(m["k"])):
        return m["base"], int(m["k"])
    return None


def expand_outputs(outputs, flow_gaps=(1,)) -> tuple[str, ...]:
    """Requested keys with every GAP_KEYS base name replaced by its keys for each gap of ``flow_gaps``
    and every alias (``tracks``) by the keys it stands for."""
    gaps = check_flow_gaps(flow_gaps)
    out: list[str] = []
    for key in outputs:
        out += [gap_key(key, k) for k in gaps] if key in GAP_KEYS else list(ALIASES.get(key, [key]))
    return tuple(dict.fromkeys(out))


def make_plan(outputs, options: RenderOptions | None = None, *, occlusion: str = "exact", seed: int | None = None,
              threads: int | None = None, **changes) -> Plan:
    """Validate a list of output keys and derive the plan. Raises ConfigError naming the valid keys.

    ``options``: a ``flowsynth.options.RenderOptions`` (None: the defaults); ``changes``: render options by name
    (the RenderOptions fields, e.g. ``spp=4``, ``final_shutter=0.3``), applied on top of ``options`` and validated
    by RenderOptions (one rule per option; defaults and why: docs/rendering.md, Options).
    ``flow_gaps``: each requested ``flow_fw`` etc. becomes ``gap_key(key, k)`` for every k (``flow_fw`` for k = 1,
    ``flow_fw_k2`` for k = 2, ...); keys named with a gap (``flow_fw_k3``) may also be requested directly.
    ``Plan.outputs`` holds the expanded keys.

    ``occlusion``: OCCLUSION_METHODS. ``threads``: threads of every ray launch (None = all cores the process may
    use, 1 inside DataLoader and export workers; flowsynth.parallel). Results do not depend on it. ``seed``: the
    renderer's noise seed; None (default) uses the scene's ``render_seed``."""
    options = RenderOptions.from_options(options, **changes)
    if isinstance(outputs, str):
        outputs = [s for s in outputs.split(",") if s]
    outputs = tuple(dict.fromkeys(outputs))
    if not outputs:
        raise ConfigError(f"outputs is empty; choose from {', '.join(OUTPUTS)}")
    outputs = expand_outputs(outputs, options.flow_gaps)
    unknown = [k for k in outputs if k not in OUTPUTS and split_gap_key(k) is None]
    if unknown:
        raise ConfigError(f"unknown output(s) {unknown}; valid outputs are: {', '.join(OUTPUTS)}, "
                          f"and KEY_kK (frame gap K >= 2) for KEY in {', '.join(GAP_KEYS)}")
    if occlusion not in OCCLUSION_METHODS:
        raise ConfigError(f"occlusion must be one of {OCCLUSION_METHODS}, got {occlusion!r}")
    if threads is not None:
        resolve_threads(threads)
    stereo = [k for k in outputs if k in STEREO_KEYS]
    if stereo and options.stereo_baseline == 0:
        raise ConfigError(f"{stereo} need a right camera: set stereo_baseline > 0 [m] (e.g. 0.1)")
    return Plan(outputs=outputs, options=options, occlusion=occlusion, seed=None if seed is None else int(seed),
                threads=threads)
