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

import dataclasses
import math
import re
from dataclasses import dataclass

from flowsynth.errors import ConfigError
from flowsynth.kernels import RENDER_MODES
from flowsynth.parallel import resolve_threads

__all__ = ["CORE_OUTPUTS", "DEFAULT_BOUNCES", "DEFAULT_RENDER_MODE", "DEFAULT_TONEMAP", "FINAL_KEYS", "FINAL_OPTIONS",
           "FLOW_KEYS", "GAP_KEYS", "GBUFFER_KEYS", "MAX_BOUNCES", "OCCLUSION_METHODS", "OUTPUTS", "RENDER_MODES",
           "SCENE_FLOW_KEYS", "STEREO_KEYS", "TABLE_KEYS", "TONEMAPS", "TRACK_KEYS", "TRACK_SAMPLING", "FinalPass",
           "Plan", "expand_outputs", "gap_key", "make_plan", "split_gap_key"]

GBUFFER_KEYS = ("depth", "distance", "normals", "position", "instance", "category", "asset")
FLOW_KEYS = ("flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "motion")
TABLE_KEYS = ("object_valid", "object_category", "object_asset", "world_T_obj", "box3d_corners",
              "box2d_amodal", "box2d_visible", "visible_pixels")
CAMERA_KEYS = ("K", "cam_T_world")
SCENE_FLOW_KEYS = ("scene_flow_fw", "scene_flow_bw")
# Per-pair keys that exist for every frame gap k of ``flow_gaps``: k = 1 under these names, k >= 2 as
# ``gap_key(key, k)`` = KEY_kK (e.g. flow_fw_k2), shape (T-k, C, H, W), index t = pair (t, t+k).
GAP_KEYS = FLOW_KEYS[:-1] + SCENE_FLOW_KEYS
# Point tracks in the TAP-Vid layout (flowsynth/tracks.py); the alias ``tracks`` requests all three.
TRACK_KEYS = ("target_points", "occluded", "query_points")
TRACK_SAMPLING = ("uniform", "objects", "edges")
ALIASES = {"tracks": TRACK_KEYS}
# Rectified right camera at ``stereo_baseline`` metres along the left camera's +x (flowsynth/stereo.py).
STEREO_KEYS = ("rgb_right", "depth_right", "disparity", "disparity_right", "disparity_change", "disparity_occ",
               "disparity_occ_right")
# The outputs before scene flow, tracks and stereo (benchmarks/throughput.py keeps timing this set).
CORE_OUTPUTS = ("rgb",) + GBUFFER_KEYS + FLOW_KEYS + TABLE_KEYS + CAMERA_KEYS
# The "final" pass beside the clean ``rgb``: motion blur, depth of field, fog, exposure / white balance, sensor noise
# (flowsynth/finalpass.py, docs/rendering.md "Final pass"); ground truth stays that of the clean pinhole geometry.
FINAL_KEYS = ("rgb_final",)
OUTPUTS = CORE_OUTPUTS + SCENE_FLOW_KEYS + TRACK_KEYS + STEREO_KEYS + FINAL_KEYS
_GAP_RE = re.compile(r"^(?P<base>[a-z_]+_(?:fw|bw))_k(?P<k>[0-9]+)$")
OCCLUSION_METHODS = ("exact", "depth")
# RGB options: the one definition of their choices, ranges and defaults (config, Plan and shading use these;
# the models are in docs/rendering.md). RENDER_MODES is defined beside the kernels that implement them.
DEFAULT_RENDER_MODE = "flat"
TONEMAPS = ("clamp", "reinhard")
DEFAULT_TONEMAP = "clamp"
MAX_BOUNCES = 64  # path-tracing bounces after the first hit lie in [0, MAX_BOUNCES]
DEFAULT_BOUNCES = 3


def _final_number(name: str, v, lo: float, hi: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise ConfigError(f"final_{name} must be a finite number, got {v!r}")
    if float(v) < lo or (hi is not None and float(v) > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ConfigError(f"final_{name} must be {bound}, got {v!r}")
    return float(v)


def _final_tuple(name: str, v, n: int, lo: float, hi: float | None = None) -> tuple[float, ...]:
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) != n:
        raise ConfigError(f"final_{name} must be a sequence of {n} numbers, got {v!r}")
    out = tuple(_final_number(name, x, lo, hi) for x in v)
    if n == 2 and out[0] > out[1]:
        raise ConfigError(f"final_{name}: min {out[0]} > max {out[1]}; pass (min, max) with min <= max")
    return out


@dataclass(frozen=True)
class FinalPass:
    """Settings of the final pass, ``rgb_final`` (flowsynth/finalpass.py; the models: docs/rendering.md, Final pass).

    ``BouncingThingsConfig`` and ``make_plan`` take each field as ``final_<name>``. Per-clip values (DoF or not,
    aperture, focus, noise levels) and per-frame gains are drawn from the scene's render seed. Validated here
    (ConfigError naming the ``final_`` field); values are normalised to floats and tuples."""

    shutter: float = 0.5
    """Shutter open time [fraction of the frame interval] in [0, 1], centred on the frame instant; 0 = no blur."""
    time_samples: int = 8
    """Time samples per pixel of the motion blur (the final render's spp is max(spp, this)) [count], >= 1."""
    dof_prob: float = 0.3
    """Probability that a clip has depth of field, in [0, 1]."""
    aperture: tuple[float, float] = (0.01, 0.04)
    """(min, max) aperture diameter A of a clip with depth of field [m], drawn log-uniformly."""
    focus: float | None = None
    """Focus distance d_f [m] (planar depth), > 0; None: the depth of a random object pixel of the middle frame."""
    max_coc: float = 16.0
    """Largest circle-of-confusion diameter [px] in [0, 64]; larger ones are clamped (bounds the gather's cost)."""
    shot_noise: tuple[float, float] = (0.0, 0.002)
    """(min, max) Poisson gain a [linear intensity per photo-electron], in [0, 1], drawn uniformly per clip:
    variance a x at signal x."""
    read_noise: tuple[float, float] = (0.0, 0.004)
    """(min, max) standard deviation b of the Gaussian read noise [linear intensity], in [0, 1], drawn uniformly
    per clip."""
    exposure_jitter: float = 0.1
    """Standard deviation of each frame's exposure change [stops = log2 gain], in [0, 4]."""
    wb_jitter: float = 0.03
    """Standard deviation of each frame's red and blue white-balance gain [natural log of the gain], in [0, 1]."""
    fog_density: float = 0.0
    """Extinction coefficient sigma of homogeneous fog [1/m], >= 0; 0 = no fog."""
    fog_color: tuple[float, float, float] = (0.5, 0.5, 0.55)
    """Radiance the fog tends to with distance [linear RGB], each >= 0."""

    def __post_init__(self) -> None:
        setattr_ = object.__setattr__
        setattr_(self, "shutter", _final_number("shutter", self.shutter, 0.0, 1.0))
        n = self.time_samples
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"final_time_samples must be an integer >= 1, got {n!r}")
        setattr_(self, "dof_prob", _final_number("dof_prob", self.dof_prob, 0.0, 1.0))
        setattr_(self, "aperture", _final_tuple("aperture", self.aperture, 2, 0.0))
        if self.focus is not None:
            setattr_(self, "focus", _final_number("focus", self.focus, 0.0))
            if self.focus == 0.0:
                raise ConfigError("final_focus must be > 0 [m] or None (drawn per clip), got 0")
        setattr_(self, "max_coc", _final_number("max_coc", self.max_coc, 0.0, 64.0))
        setattr_(self, "shot_noise", _final_tuple("shot_noise", self.shot_noise, 2, 0.0, 1.0))
        setattr_(self, "read_noise", _final_tuple("read_noise", self.read_noise, 2, 0.0, 1.0))
        setattr_(self, "exposure_jitter", _final_number("exposure_jitter", self.exposure_jitter, 0.0, 4.0))
        setattr_(self, "wb_jitter", _final_number("wb_jitter", self.wb_jitter, 0.0, 1.0))
        setattr_(self, "fog_density", _final_number("fog_density", self.fog_density, 0.0))
        setattr_(self, "fog_color", _final_tuple("fog_color", self.fog_color, 3, 0.0))

    @classmethod
    def from_options(cls, options: dict) -> FinalPass:
        """From ``final_<name>`` keyword options (FINAL_OPTIONS); ConfigError for any other name."""
        unknown = sorted(k for k in options if k not in FINAL_OPTIONS)
        if unknown:
            raise ConfigError(f"unknown render option(s) {unknown}; the final pass's options are: "
                              f"{', '.join(FINAL_OPTIONS)} (the others: flowsynth.plan.make_plan)")
        return cls(**{k.removeprefix("final_"): v for k, v in options.items()})


# make_plan / fs.render / BouncingThingsConfig names of the FinalPass fields.
FINAL_OPTIONS = tuple("final_" + f.name for f in dataclasses.fields(FinalPass))


@dataclass(frozen=True)
class Plan:
    """The stages needed for ``outputs``; flags are derived, never set by hand."""

    outputs: tuple[str, ...]
    occlusion: str = "exact"
    max_objects: int | None = None
    render_mode: str = DEFAULT_RENDER_MODE
    spp: int = 1
    edge_spp: int = 1
    shutter: float = 0.0
    seed: int | None = None
    bounces: int = DEFAULT_BOUNCES
    tonemap: str = DEFAULT_TONEMAP
    exposure: float = 1.0
    threads: int | None = None
    flow_gaps: tuple[int, ...] = (1,)
    num_tracks: int = 256
    track_sampling: str = "uniform"
    stereo_baseline: float = 0.0
    final_pass: FinalPass = FinalPass()
    shutter_offset: float = 0.0
    """[frames] added to every motion-blur sample time: -shutter / 2 centres the shutter on the frame instant
    (the final pass sets it; make_plan leaves 0, the shutter opening at the frame instant)."""

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


def _check_gaps(flow_gaps) -> tuple[int, ...]:
    if isinstance(flow_gaps, (int, str)) or not hasattr(flow_gaps, "__iter__"):
        raise ConfigError(f"flow_gaps must be a sequence of integers >= 1, e.g. (1, 2, 4); got {flow_gaps!r}")
    gaps = tuple(flow_gaps)
    if not gaps or any(isinstance(k, bool) or not isinstance(k, int) or k < 1 for k in gaps):
        raise ConfigError(f"flow_gaps must be a non-empty sequence of integers >= 1, e.g. (1, 2, 4); "
                          f"got {flow_gaps!r}")
    return tuple(dict.fromkeys(gaps))


def expand_outputs(outputs, flow_gaps=(1,)) -> tuple[str, ...]:
    """Requested keys with every GAP_KEYS base name replaced by its keys for each gap of ``flow_gaps``
    and every alias (``tracks``) by the keys it stands for."""
    gaps = _check_gaps(flow_gaps)
    out: list[str] = []
    for key in outputs:
        out += [gap_key(key, k) for k in gaps] if key in GAP_KEYS else list(ALIASES.get(key, [key]))
    return tuple(dict.fromkeys(out))


def make_plan(outputs, occlusion: str = "exact", max_objects: int | None = None,
              render_mode: str = DEFAULT_RENDER_MODE, spp: int = 1, shutter: float = 0.0, seed: int | None = None,
              bounces: int = DEFAULT_BOUNCES, tonemap: str = DEFAULT_TONEMAP, exposure: float = 1.0,
              threads: int | None = None, flow_gaps=(1,), num_tracks: int = 256,
              track_sampling: str = "uniform", stereo_baseline: float = 0.0, edge_spp: int = 1,
              **final_options) -> Plan:
    """Validate a list of output keys and derive the plan. Raises ConfigError naming the valid keys.

    ``num_tracks`` (Q >= 1) and ``track_sampling`` (TRACK_SAMPLING): point tracks, see flowsynth/tracks.py.
    ``stereo_baseline`` [m]: distance of the right camera (0 = no right camera; STEREO_KEYS need > 0).
    ``flow_gaps``: frame gaps k of the per-pair keys (GAP_KEYS): each requested ``flow_fw`` etc. becomes
    ``gap_key(key, k)`` for every k (``flow_fw`` for k = 1, ``flow_fw_k2`` for k = 2, ...); keys named with
    a gap (``flow_fw_k3``) may also be requested directly. ``Plan.outputs`` holds the expanded keys.

    ``edge_spp``: RGB samples of pixels at silhouettes and creases, max(spp, edge_spp) (docs/rendering.md).
    ``threads``: threads of every ray launch (None = all cores the process may use, 1 inside DataLoader and
    export workers; flowsynth.parallel). Results do not depend on it. ``seed``: the renderer's noise seed; None
    (default) uses the scene's ``render_seed``. ``final_options``: the final pass's settings as ``final_<name>``
    keywords (FINAL_OPTIONS; FinalPass documents each), used when ``rgb_final`` is requested."""
    if isinstance(outputs, str):
        outputs = [s for s in outputs.split(",") if s]
    outputs = tuple(dict.fromkeys(outputs))
    if not outputs:
        raise ConfigError(f"outputs is empty; choose from {', '.join(OUTPUTS)}")
    gaps = _check_gaps(flow_gaps)
    outputs = expand_outputs(outputs, gaps)
    unknown = [k for k in outputs if k not in OUTPUTS and split_gap_key(k) is None]
    if unknown:
        raise ConfigError(f"unknown output(s) {unknown}; valid outputs are: {', '.join(OUTPUTS)}, "
                          f"and KEY_kK (frame gap K >= 2) for KEY in {', '.join(GAP_KEYS)}")
    if occlusion not in OCCLUSION_METHODS:
        raise ConfigError(f"occlusion must be one of {OCCLUSION_METHODS}, got {occlusion!r}")
    if max_objects is not None and (not isinstance(max_objects, int) or max_objects < 0):
        raise ConfigError(f"max_objects must be a non-negative integer, got {max_objects!r}")
    if render_mode not in RENDER_MODES:
        raise ConfigError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    if not isinstance(spp, int) or spp < 1:
        raise ConfigError(f"spp must be an integer >= 1, got {spp!r}")
    if isinstance(edge_spp, bool) or not isinstance(edge_spp, int) or edge_spp < 1:
        raise ConfigError(f"edge_spp must be an integer >= 1, got {edge_spp!r}")
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
    if isinstance(num_tracks, bool) or not isinstance(num_tracks, int) or num_tracks < 1:
        raise ConfigError(f"num_tracks must be an integer >= 1, got {num_tracks!r}")
    if track_sampling not in TRACK_SAMPLING:
        raise ConfigError(f"track_sampling must be one of {TRACK_SAMPLING}, got {track_sampling!r}")
    if isinstance(stereo_baseline, bool) or not isinstance(stereo_baseline, (int, float)) or not (
            math.isfinite(stereo_baseline) and stereo_baseline >= 0):
        raise ConfigError(f"stereo_baseline must be a finite number >= 0 [m], got {stereo_baseline!r}")
    final = FinalPass.from_options(final_options)
    stereo = [k for k in outputs if k in STEREO_KEYS]
    if stereo and stereo_baseline == 0:
        raise ConfigError(f"{stereo} need a right camera: set stereo_baseline > 0 [m] (e.g. 0.1)")
    return Plan(outputs, occlusion, max_objects, render_mode, int(spp), int(edge_spp), float(shutter),
                None if seed is None else int(seed), int(bounces),
                tonemap, float(exposure), threads, gaps, num_tracks, track_sampling, float(stereo_baseline), final)
