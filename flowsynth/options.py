"""The render options: one definition, one validation rule and one default each (docs/rendering.md, Options).

:class:`RenderOptions` is what ``fs.render`` / ``fs.make_plan`` take (``options=RenderOptions(...)``, or the same
names as keywords) and what a ``BouncingThingsConfig`` derives from its fields of the same names
(``cfg.render_options``); the config validates those fields by building one. :class:`FinalPass` groups the
``final_*`` options of the final pass (``rgb_final``). Invalid values raise ConfigError naming the option.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from flowsynth.errors import ConfigError
from flowsynth.kernels import RENDER_MODES

__all__ = ["DEFAULT_BOUNCES", "DEFAULT_RENDER_MODE", "DEFAULT_TONEMAP", "FINAL_OPTIONS", "MAX_BOUNCES",
           "OPTION_NAMES", "RENDER_MODES", "TONEMAPS", "TRACK_SAMPLING", "FinalPass", "RenderOptions",
           "check_flow_gaps", "check_int", "is_int"]

# RGB options: the one definition of their choices, ranges and defaults (the models: docs/rendering.md).
# RENDER_MODES is defined beside the kernels that implement them.
DEFAULT_RENDER_MODE = "flat"
TONEMAPS = ("clamp", "reinhard")
DEFAULT_TONEMAP = "clamp"
MAX_BOUNCES = 64  # path-tracing bounces after the first hit lie in [0, MAX_BOUNCES]
DEFAULT_BOUNCES = 3
TRACK_SAMPLING = ("uniform", "objects", "edges")


# ------------------------------------------------------------------------------------------ the rules

def _numpy_kind(v: Any) -> str:
    """The numpy dtype kind of a numpy scalar or 0-d array ("i", "u", "f", ...); "" for anything else (a torch
    tensor, an array of more than one value, a plain Python value)."""
    return getattr(getattr(v, "dtype", None), "kind", "") if getattr(v, "ndim", 1) == 0 else ""


def is_int(v: Any) -> bool:
    """An integer, Python's or numpy's (a scalar), and not a bool."""
    return not isinstance(v, bool) and (isinstance(v, int) or _numpy_kind(v) in ("i", "u"))


def check_int(name: str, v: Any, lo: int, hi: int | None = None) -> int:
    """``v`` as an int in [lo, hi] (hi None: no upper bound); ConfigError naming ``name`` otherwise."""
    if not is_int(v) or int(v) < lo or (hi is not None and int(v) > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ConfigError(f"{name} must be an integer {bound}, got {v!r}")
    return int(v)


def check_number(name: str, v: Any, lo: float | None = None, hi: float | None = None) -> float:
    """``v`` as a finite float in [lo, hi] (None: unbounded on that side); ConfigError naming ``name`` otherwise."""
    if isinstance(v, bool) or not (isinstance(v, (int, float)) or _numpy_kind(v) in ("i", "u", "f")):
        raise ConfigError(f"{name} must be a number, got {v!r}")
    x = float(v)
    if not math.isfinite(x) or (lo is not None and x < lo) or (hi is not None and x > hi):
        bound = ("" if lo is None and hi is None else f" >= {lo}" if hi is None else f" <= {hi}" if lo is None
                 else f" in [{lo}, {hi}]")
        raise ConfigError(f"{name} must be a finite number{bound}, got {v!r}")
    return x


def check_tuple(name: str, v: Any, n: int, lo: float, hi: float | None = None) -> tuple[float, ...]:
    """``v`` as n numbers in [lo, hi]; for n = 2 a (min, max) range with min <= max."""
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) != n:
        raise ConfigError(f"{name} must be a sequence of {n} numbers, got {v!r}")
    out = tuple(check_number(name, x, lo, hi) for x in v)
    if n == 2 and out[0] > out[1]:
        raise ConfigError(f"{name}: min {out[0]} > max {out[1]}; pass (min, max) with min <= max")
    return out


def check_bool(name: str, v: Any) -> bool:
    """``v`` as a bool; ConfigError naming ``name`` unless it is True or False (numpy's included)."""
    if not isinstance(v, (bool, np.bool_)):
        raise ConfigError(f"{name} must be True or False, got {v!r}")
    return bool(v)


def check_choice(name: str, v: Any, options: tuple[str, ...]) -> str:
    if not isinstance(v, str) or v not in options:
        raise ConfigError(f"{name} must be one of {list(options)}, got {v!r}")
    return v


def check_flow_gaps(flow_gaps: Any) -> tuple[int, ...]:
    """Frame gaps as a tuple of distinct integers >= 1 in the given order (duplicates dropped)."""
    if isinstance(flow_gaps, (str, bytes)) or not hasattr(flow_gaps, "__iter__") or not hasattr(flow_gaps, "__len__"):
        raise ConfigError(f"flow_gaps must be a non-empty sequence of integers >= 1, e.g. (1, 2, 4); got {flow_gaps!r}")
    gaps = tuple(flow_gaps)
    if not gaps or not all(is_int(k) and int(k) >= 1 for k in gaps):
        raise ConfigError(f"flow_gaps must be a non-empty sequence of integers >= 1, e.g. (1, 2, 4); got {flow_gaps!r}")
    return tuple(dict.fromkeys(int(k) for k in gaps))


# ------------------------------------------------------------------------------------------ final pass

@dataclass(frozen=True)
class FinalPass:
    """Settings of the final pass, ``rgb_final`` (flowsynth/renderer/finalpass.py; the models: docs/rendering.md, Final
    pass).

    ``RenderOptions``, ``BouncingThingsConfig`` and ``make_plan`` take each field as ``final_<name>``. Per-clip values
    (DoF or not, aperture, focus, noise levels) and per-frame gains are drawn from the scene's render seed. Validated
    here (ConfigError naming the ``final_`` field); values are normalised to floats and tuples."""

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
        set_ = object.__setattr__
        set_(self, "shutter", check_number("final_shutter", self.shutter, 0.0, 1.0))
        set_(self, "time_samples", check_int("final_time_samples", self.time_samples, 1))
        set_(self, "dof_prob", check_number("final_dof_prob", self.dof_prob, 0.0, 1.0))
        set_(self, "aperture", check_tuple("final_aperture", self.aperture, 2, 0.0))
        if self.focus is not None:
            set_(self, "focus", check_number("final_focus", self.focus, 0.0))
            if self.focus == 0.0:
                raise ConfigError("final_focus must be > 0 [m] or None (drawn per clip), got 0")
        set_(self, "max_coc", check_number("final_max_coc", self.max_coc, 0.0, 64.0))
        set_(self, "shot_noise", check_tuple("final_shot_noise", self.shot_noise, 2, 0.0, 1.0))
        set_(self, "read_noise", check_tuple("final_read_noise", self.read_noise, 2, 0.0, 1.0))
        set_(self, "exposure_jitter", check_number("final_exposure_jitter", self.exposure_jitter, 0.0, 4.0))
        set_(self, "wb_jitter", check_number("final_wb_jitter", self.wb_jitter, 0.0, 1.0))
        set_(self, "fog_density", check_number("final_fog_density", self.fog_density, 0.0))
        set_(self, "fog_color", check_tuple("final_fog_color", self.fog_color, 3, 0.0))

    @classmethod
    def from_options(cls, options: dict) -> FinalPass:
        """From ``final_<name>`` keyword options (FINAL_OPTIONS); ConfigError for any other name."""
        unknown = sorted(k for k in options if k not in FINAL_OPTIONS)
        if unknown:
            raise ConfigError(f"unknown render option(s) {unknown}; the final pass's options are: "
                              f"{', '.join(FINAL_OPTIONS)} (the others: flowsynth.options.RenderOptions)")
        return cls(**{k.removeprefix("final_"): v for k, v in options.items()})


# RenderOptions / make_plan / fs.render / BouncingThingsConfig names of the FinalPass fields.
FINAL_OPTIONS = tuple("final_" + f.name for f in dataclasses.fields(FinalPass))
_FP = FinalPass()  # the final_* defaults of RenderOptions are FinalPass's own


# ------------------------------------------------------------------------------------------ render options

@dataclass(frozen=True, kw_only=True)
class RenderOptions:
    """Every option that changes what is rendered, validated on construction (ConfigError naming the option) and
    normalised (ints, floats, tuples). Keyword-only. Why each default is what it is: docs/rendering.md, Options.

    Not options of the image: ``occlusion``, ``seed`` (None: the scene's render seed) and ``threads`` stay
    arguments of ``fs.render`` / ``make_plan``."""

    render_mode: str = DEFAULT_RENDER_MODE
    """RGB shading: "flat" (lit, no shadows), "direct" (lights and shadows) or "path" (path traced)."""
    spp: int = 1
    """RGB samples per pixel [count], >= 1."""
    edge_spp: int = 4
    """RGB samples of a pixel at a silhouette (a 4-neighbour sees another instance or the sky), max(spp, edge_spp)
    [count], >= 1; 1 = off (docs/decisions/0009-edge-spp-default-4.md)."""
    shutter: float = 0.0
    """Shutter open time [fraction of the frame interval] in [0, 1]; 0 = no motion blur."""
    bounces: int = DEFAULT_BOUNCES
    """Path-tracing bounces after the primary hit (render_mode "path") [count], in [0, MAX_BOUNCES]."""
    tonemap: str = DEFAULT_TONEMAP
    """Linear radiance -> display: "clamp" or "reinhard", then sRGB encoding."""
    exposure: float = 1.0
    """Radiance multiplier before tone mapping, finite and >= 0."""
    max_objects: int | None = None
    """Rows of the padded per-object tables [count], >= 1; None: the scene's own object count."""
    flow_gaps: tuple[int, ...] = (1,)
    """Frame gaps k of the per-pair outputs [frames], distinct integers >= 1 (flowsynth.plan.gap_key)."""
    num_tracks: int = 256
    """Point tracks per clip Q [count], >= 1."""
    track_sampling: str = "uniform"
    """Where track query points are drawn: "uniform", "objects" or "edges" (flowsynth/truth/tracks.py)."""
    stereo_baseline: float = 0.0
    """Distance of the rectified right camera along the left camera's +x [m], finite and >= 0; 0 = none."""
    smooth_shading: bool = False
    """Shade with normals interpolated from the mesh's corner normals (smoothed across edges under
    SMOOTH_CREASE_DEG), so a tessellated sphere shades round; False: flat face normals. Textures, the ``normals``
    output and all geometry stay on the faces (docs/rendering.md, Shading normals)."""
    final_shutter: float = _FP.shutter
    """Final pass (FinalPass.shutter)."""
    final_time_samples: int = _FP.time_samples
    """Final pass (FinalPass.time_samples)."""
    final_dof_prob: float = _FP.dof_prob
    """Final pass (FinalPass.dof_prob)."""
    final_aperture: tuple[float, float] = _FP.aperture
    """Final pass (FinalPass.aperture)."""
    final_focus: float | None = _FP.focus
    """Final pass (FinalPass.focus)."""
    final_max_coc: float = _FP.max_coc
    """Final pass (FinalPass.max_coc)."""
    final_shot_noise: tuple[float, float] = _FP.shot_noise
    """Final pass (FinalPass.shot_noise)."""
    final_read_noise: tuple[float, float] = _FP.read_noise
    """Final pass (FinalPass.read_noise)."""
    final_exposure_jitter: float = _FP.exposure_jitter
    """Final pass (FinalPass.exposure_jitter)."""
    final_wb_jitter: float = _FP.wb_jitter
    """Final pass (FinalPass.wb_jitter)."""
    final_fog_density: float = _FP.fog_density
    """Final pass (FinalPass.fog_density)."""
    final_fog_color: tuple[float, float, float] = _FP.fog_color
    """Final pass (FinalPass.fog_color)."""

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "render_mode", check_choice("render_mode", self.render_mode, RENDER_MODES))
        set_(self, "spp", check_int("spp", self.spp, 1))
        set_(self, "edge_spp", check_int("edge_spp", self.edge_spp, 1))
        set_(self, "shutter", check_number("shutter", self.shutter, 0.0, 1.0))
        set_(self, "bounces", check_int("bounces", self.bounces, 0, MAX_BOUNCES))
        set_(self, "tonemap", check_choice("tonemap", self.tonemap, TONEMAPS))
        set_(self, "exposure", check_number("exposure", self.exposure, 0.0))
        if self.max_objects is not None:
            set_(self, "max_objects", check_int("max_objects", self.max_objects, 1))
        set_(self, "flow_gaps", check_flow_gaps(self.flow_gaps))
        set_(self, "num_tracks", check_int("num_tracks", self.num_tracks, 1))
        set_(self, "track_sampling", check_choice("track_sampling", self.track_sampling, TRACK_SAMPLING))
        set_(self, "stereo_baseline", check_number("stereo_baseline", self.stereo_baseline, 0.0))
        set_(self, "smooth_shading", check_bool("smooth_shading", self.smooth_shading))
        fp = FinalPass.from_options({name: getattr(self, name) for name in FINAL_OPTIONS})  # FinalPass's rules
        for name in FINAL_OPTIONS:
            set_(self, name, getattr(fp, name.removeprefix("final_")))

    @property
    def final_pass(self) -> FinalPass:
        """The ``final_*`` options as a FinalPass."""
        return FinalPass.from_options({name: getattr(self, name) for name in FINAL_OPTIONS})

    def to_dict(self) -> dict[str, Any]:
        """{option name: value} of every option (the keywords ``fs.render`` takes)."""
        return {name: getattr(self, name) for name in OPTION_NAMES}

    @classmethod
    def from_options(cls, options: RenderOptions | None = None, **changes: Any) -> RenderOptions:
        """``options`` (default: the defaults) with the keyword ``changes`` applied; ConfigError naming the valid
        options for any other name."""
        unknown = sorted(k for k in changes if k not in OPTION_NAMES)
        if unknown:
            raise ConfigError(f"unknown render option(s) {unknown}; valid options: {', '.join(OPTION_NAMES)} "
                              "(and occlusion, seed, threads)")
        if options is None:
            return cls(**changes)
        if not isinstance(options, RenderOptions):
            raise ConfigError(f"options must be a flowsynth.RenderOptions, got {type(options).__name__}")
        return dataclasses.replace(options, **changes) if changes else options


OPTION_NAMES = tuple(f.name for f in dataclasses.fields(RenderOptions))
"""The names of the render options, in RenderOptions' order (also BouncingThingsConfig fields)."""
