"""Configuration of the BouncingThings scene generator: one frozen, validated dataclass.

Every field has a default; invalid values raise :class:`flowsynth.errors.ConfigError` naming the field and the fix.
Sequences are stored as tuples so a config is hashable and never mutates. Units: metres, seconds, radians
(degrees only in ``fov_deg``). World frame: right-handed, +z up, the floor at z = 0 (docs/scenes.md).

The render options (``OPTION_NAMES``: spp, edge_spp, ..., the final_* fields) are fields under their
``flowsynth.options.RenderOptions`` names, with RenderOptions' defaults (but ``max_objects``), and are validated by
building one (``cfg.render_options``): one rule and one default per option (docs/rendering.md, Options).

Constructing a config reads no file: mesh paths, globs and ``texture_dir`` are checked by their form only, and are
resolved when a scene is sampled (``flowsynth.scene.sampling``; ``check_files`` does it up front), so
``from_dict(meta["config"])`` works on a machine without the meshes and textures it names.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from dataclasses import dataclass
from typing import Any

from flowsynth.errors import AssetError, ConfigError
from flowsynth.options import OPTION_NAMES, RENDER_MODES, RenderOptions, check_int, is_int

__all__ = ["CAMERA_MOTIONS", "FLOW_PX_WIDTH", "MOTIONS", "PRESETS", "RENDER_MODES", "BouncingThingsConfig",
           "config_from_dict"]

MOTIONS = ("physics", "kinematic", "static")
CAMERA_MOTIONS = ("static", "moving")
# Initial placement needs free space: total bounding-sphere volume of the largest possible object set
# may fill at most this fraction of the objects' region (random sequential packing jams near 0.38).
MAX_PACKING_FRACTION = 0.25
_OPT = RenderOptions()  # the render options' defaults (RenderOptions is their one definition)
FLOW_PX_WIDTH = 512
"""[px] The default ``flow_px_width``: the image width ``flow_px`` is stated at (FlyingChairs' 512x384;
docs/decisions/0029-flow-px-width.md)."""
DATASET_MAX_OBJECTS = 32
"""The config's ``max_objects``: a stream pads every sample's object tables to one size so that default_collate
stacks them (RenderOptions' None, the scene's own count, would not); 32 leaves room above ``num_objects``' 12."""


@dataclass(frozen=True)
class BouncingThingsConfig:
    """Rigid objects bouncing in a box-shaped room, seen by a pinhole camera (FlyingThings-like)."""

    width: int = 320
    """Image width [px], >= 1. The default 320x240 clips of 24 frames are a general stream (clips for tracks, frame
    gaps and scene flow over time, as Kubric's MOVi); docs/statistics.md and the learning judge measure 512x384
    pairs (``--width 512 --height 384 --num-frames 2``). Motion is stated at 512 px wide (``flow_px_width``), so
    both move the same share of the image."""
    height: int = 240
    """Image height [px], >= 1."""
    num_frames: int = 24
    """Frames per clip T, >= 1 (a flow pair is frames 0 and 1 of any clip; ``--num-frames 2`` renders only those)."""
    fps: float = 24.0
    """Frame rate [1/s], > 0."""
    fov_deg: float = 60.0
    """Horizontal field of view [deg], in (0, 180) (of the pinhole part when a lens model is set)."""
    camera_model: str = "pinhole"
    """Lens model: "pinhole", "brown_conrady" or "kannala_brandt" (equations: flowsynth/scene/camera.py,
    docs/conventions.md; OpenCV's conventions). A lens model allows no stereo outputs."""
    camera_dist: tuple[float, ...] = ()
    """Lens coefficients in OpenCV's order: (k1, k2, p1, p2[, k3[, k4, k5, k6]]) for brown_conrady, (k1, k2, k3,
    k4) for kannala_brandt, empty for pinhole; with ``camera_dist_max``, the lower ends of their ranges. On the
    command line a negative first value needs '=': --camera-dist=-0.2,0.05,0,0."""
    camera_dist_max: tuple[float, ...] | None = None
    """Upper ends of the lens coefficients' ranges: each sample draws coefficient i uniformly in [camera_dist[i],
    camera_dist_max[i]] (from its own generator: the other draws are unchanged); None: camera_dist is fixed."""
    num_objects: tuple[int, int] = (4, 12)
    """(min, max) number of flying objects per scene, drawn uniformly (inclusive) [count]."""
    assets: tuple[str, ...] = ("box", "sphere", "cylinder", "capsule", "cone", "torus", "rock", "crystal",
                               "star", "blob")
    """Built-in asset names (flowsynth.scene.assets.BUILTIN_ASSETS) and/or mesh file paths or globs (resolved and loaded
    when a scene is sampled, not when the config is made)."""
    object_size: tuple[float, float] = (0.4, 1.2)
    """(min, max) bounding-sphere diameter of an object [m]; drawn log-uniformly over ``size_levels``."""
    size_levels: int = 8
    """Number of distinct object sizes, log-spaced over ``object_size`` [count]; sizes repeat so meshes are
    shared between instances and samples (renderer caches). 1 means always the min size."""
    min_speed: float = 0.1
    """Lower bound of every object's linear speed [m/s], >= 0."""
    max_speed: float = 8.0
    """Upper bound of every object's linear speed [m/s], >= min_speed (also with ``flow_px``)."""
    angular_speed: tuple[float, float] = (0.0, 2.0)
    """(min, max) angular speed of an object [rad/s]."""
    motion: str = "physics"
    """"physics" (Newton rigid bodies), "kinematic" (constant velocities, walls reflect) or "static"."""
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Gravity vector in the world frame [m/s^2] (physics only); (0, 0, -9.81) for a falling world."""
    restitution: float = 1.0
    """Coefficient of restitution of every contact, in [0, 1] (physics only)."""
    friction: float = 0.0
    """Coulomb friction coefficient of every contact, >= 0 (physics only)."""
    substeps: int | None = None
    """Physics substeps per frame [count]; None picks them from speeds and sizes (docs/scenes.md)."""
    flow_px: tuple[float, float] | None = (2.0, 48.0)
    """(min, max) per-frame flow magnitude to aim for [px of an image ``flow_px_width`` wide]; None sets speeds in
    m/s and rad/s directly. A sample ``width`` px wide aims at flow_px x width / flow_px_width (``flow_px_scaled``),
    so its motion is the same share of the image at every size: (2, 48) is 2-48 px at 512 px wide and 0.25-6 px
    at 64. Each object draws a target u log-uniformly from the scaled range and its speed becomes
    u * distance * fps / (f * max(0.5, sin angle(velocity, line of sight))) with f the focal length [px],
    clipped into [min_speed, max_speed]; the camera draws its own u and its drawn path (directions and the
    mix of translation, target motion and rotation from the camera fields below) is scaled so that the
    median flow of the room between frames 0 and 1 is u (flowsynth/scene/camerapath.py). What comes out is
    measured by ``flowsynth stats``, not promised."""
    flow_px_width: int = FLOW_PX_WIDTH
    """The image width [px] that ``flow_px`` is stated at, >= 1: 512, the width of the 512x384 pairs that
    docs/statistics.md measures, so the default motion at any size has their proportions. Equal to ``width``,
    flow_px is in the rendered image's own pixels."""
    rest_fraction: float = 0.0
    """Chance in [0, 1] that each object starts at rest (no velocity, no spin; it moves only when something hits
    it) and, drawn once more per clip, that the camera holds still: the still regions real video shows beside
    moving ones. 0 draws nothing (the samples of a config without it are unchanged)."""
    camera_motion: str = "moving"
    """"static" or "moving": the eye translates (reflected inside the camera zone), the look-at target
    moves, and pan / tilt / roll offsets turn the camera (flowsynth/scene/camerapath.py)."""
    camera_speed: tuple[float, float] = (0.2, 1.0)
    """(min, max) speed of the eye when ``camera_motion == "moving"`` [m/s] (with ``flow_px``: before scaling)."""
    camera_target_speed: tuple[float, float] = (0.0, 1.0)
    """(min, max) speed of the look-at target [m/s] (with ``flow_px``: before scaling)."""
    camera_pan: float = 0.3
    """Largest pan rate, turning about the image's vertical axis [rad/s], >= 0; a clip draws its rate
    uniformly in [-camera_pan, camera_pan] (with ``flow_px``: before scaling)."""
    camera_tilt: float = 0.15
    """Largest tilt rate, turning about the image's horizontal axis [rad/s], >= 0 (as camera_pan)."""
    camera_roll: float = 0.15
    """Largest roll rate, turning about the optical axis [rad/s], >= 0 (as camera_pan)."""
    camera_angle_limit: tuple[float, float, float] = (0.5, 0.3, 0.3)
    """Bounds of the (pan, tilt, roll) offsets from the look-at direction [rad], each >= 0; offsets reflect
    off ±limit, so the camera keeps facing the objects' region."""
    planar_motion: bool = False
    """Objects, the eye and the look-at target start moving parallel to the first frame's image plane
    (FlyingChairs-like 2D motion); collisions and walls may turn them later."""
    spawn_margin: float = 0.1
    """Fraction of the image width / height kept free at each border when aiming objects' start positions
    into the view, in (-0.5, 0.5); negative lets objects start partly out of frame."""
    room_size: tuple[float, float, float] = (10.0, 8.0, 6.0)
    """Room interior extent (x, y, z) [m]; the room spans x, y in [-size/2, size/2] and z in [0, size_z]."""
    camera_clearance: float = 2.0
    """Depth of the camera zone along x next to the wall x = -size_x/2 [m]; objects stay out of it."""
    max_objects: int = DATASET_MAX_OBJECTS
    """Rows of the padded per-object tables [count], >= 1; num_objects max must be <= max_objects."""
    render_mode: str = _OPT.render_mode
    """RGB shading: "flat" (lit, no shadows), "direct" (lights and shadows) or "path" (path traced)."""
    spp: int = _OPT.spp
    """Samples per pixel for RGB, >= 1 [count]."""
    edge_spp: int = _OPT.edge_spp
    """Samples per pixel for RGB at silhouettes, >= 1 [count]: a pixel whose 4-neighbour sees another instance
    (or the sky) gets max(spp, edge_spp) samples, so object outlines are anti-aliased at a fraction of what
    spp = edge_spp everywhere costs (docs/rendering.md, Anti-aliasing); 1 = off."""
    shutter: float = _OPT.shutter
    """Shutter open time as a fraction of the frame interval, in [0, 1]; 0 disables motion blur."""
    bounces: int = _OPT.bounces
    """Path-tracing bounces after the primary hit (render_mode "path"), in [0, MAX_BOUNCES = 64] [count]."""
    tonemap: str = _OPT.tonemap
    """Linear radiance -> display: "clamp" or "reinhard", then sRGB encoding (docs/rendering.md)."""
    exposure: float = _OPT.exposure
    """Radiance multiplier before tone mapping, >= 0."""
    flow_gaps: tuple[int, ...] = _OPT.flow_gaps
    """Frame gaps k of the per-pair outputs (flow, masks, scene flow) [frames]: a requested ``flow_fw`` gives
    ``flow_fw`` for k = 1 and ``flow_fw_kK`` (T-K pairs (t, t+K)) for every other K; needs K < num_frames."""
    num_tracks: int = _OPT.num_tracks
    """Point tracks per clip Q (outputs ``tracks`` = target_points, occluded, query_points), >= 1 [count]."""
    track_sampling: str = _OPT.track_sampling
    """Where query points are drawn: "uniform" (any surface), "objects" (not the room) or "edges" (near depth
    edges); see flowsynth/truth/tracks.py."""
    stereo_baseline: float = _OPT.stereo_baseline
    """Distance of a rectified right camera along the left camera's +x [m], >= 0; 0 = no right camera.
    Needed (> 0) for rgb_right, depth_right, disparity* (flowsynth/truth/stereo.py)."""
    smooth_shading: bool = _OPT.smooth_shading
    """Shade curved meshes with interpolated corner normals instead of flat faces (RenderOptions.smooth_shading);
    off by default."""
    texture_px: tuple[float, float] = (2.0, 64.0)
    """(min, max) size on screen [px] of texture features at each surface's expected viewing distance: fractal
    patterns span the range over several octaves, stripes/checks and image texels fall inside it. Larger values
    (e.g. (50, 500)) give large-scale patterns."""
    texture_dir: str | None = None
    """Folder of image textures (jpg/png) for objects and walls (add "image" to ``texture_families``); None
    uses procedural textures only. Images are tiled at ``texture_px`` scale, not stretched (docs/rendering.md).
    Read when a scene is sampled, not when the config is made."""
    texture_families: tuple[str, ...] = ("noise", "value", "cells", "stripes", "checks", "blend")
    """Texture families to draw each surface's material from (non-empty;
    flowsynth.appearance.materials.TEXTURE_FAMILIES). "solid" (one flat colour) and "leaves" (dead-leaves discs) are
    drawn only when listed."""
    # The final pass, output ``rgb_final`` (flowsynth/renderer/finalpass.py; models and defaults: docs/rendering.md,
    # Final pass). Only read when rgb_final is requested; the ground truth never depends on them.
    final_shutter: float = _OPT.final_shutter
    """Final pass: shutter open time [fraction of the frame interval] in [0, 1], centred on the frame instant
    (the ground truth's instant); 0 = no motion blur (the clean pass's own ``shutter`` then applies)."""
    final_time_samples: int = _OPT.final_time_samples
    """Final pass: motion-blur time samples per pixel [count], >= 1 (its spp is max(spp, this))."""
    final_dof_prob: float = _OPT.final_dof_prob
    """Final pass: probability in [0, 1] that a clip has depth of field (thin lens)."""
    final_aperture: tuple[float, float] = _OPT.final_aperture
    """Final pass: (min, max) aperture diameter of a clip with depth of field [m], >= 0, drawn log-uniformly."""
    final_focus: float | None = _OPT.final_focus
    """Final pass: focus distance (planar depth) [m], > 0; None draws it per clip as the depth of a random object
    pixel of the middle frame."""
    final_max_coc: float = _OPT.final_max_coc
    """Final pass: largest circle-of-confusion diameter [px] in [0, 64]; larger ones are clamped."""
    final_shot_noise: tuple[float, float] = _OPT.final_shot_noise
    """Final pass: (min, max) Poisson gain a [linear intensity] in [0, 1], drawn uniformly per clip: shot-noise
    variance a x at linear signal x (1 = white)."""
    final_read_noise: tuple[float, float] = _OPT.final_read_noise
    """Final pass: (min, max) read-noise standard deviation b [linear intensity] in [0, 1], drawn uniformly per
    clip."""
    final_exposure_jitter: float = _OPT.final_exposure_jitter
    """Final pass: standard deviation of each frame's exposure change [stops, log2 of the gain], in [0, 4]."""
    final_wb_jitter: float = _OPT.final_wb_jitter
    """Final pass: standard deviation of each frame's red and blue white-balance gains [natural log], in [0, 1]."""
    final_fog_density: float = _OPT.final_fog_density
    """Final pass: fog extinction coefficient sigma [1/m], >= 0; 0 = no fog."""
    final_fog_color: tuple[float, float, float] = _OPT.final_fog_color
    """Final pass: radiance of the fog [linear RGB], each >= 0."""

    def __post_init__(self) -> None:
        _validate(self)

    @property
    def room_bounds(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(lo, hi) corners of the room interior [m]."""
        x, y, z = self.room_size
        return (-x / 2, -y / 2, 0.0), (x / 2, y / 2, z)

    @property
    def object_bounds(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(lo, hi) corners of the region objects stay in [m]: the room minus the camera zone."""
        (lx, ly, lz), hi = self.room_bounds
        return (lx + self.camera_clearance, ly, lz), hi

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> BouncingThingsConfig:
        """A named preset (``PRESETS``: "default", "chairs", "things") with ``overrides`` applied.

        Raises ConfigError for an unknown name or invalid overrides.
        """
        if name not in PRESETS:
            raise ConfigError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
        return cls.from_dict({**PRESETS[name], **overrides})

    @property
    def flow_px_scaled(self) -> tuple[float, float] | None:
        """``flow_px`` at this config's ``width``: (min, max) x width / flow_px_width [px of the rendered image], the
        range the flow targets are drawn from; None without flow_px. Equal to ``flow_px`` when width is
        flow_px_width."""
        if self.flow_px is None:
            return None
        s = self.width / self.flow_px_width
        return self.flow_px[0] * s, self.flow_px[1] * s

    @property
    def render_options(self) -> RenderOptions:
        """The render options this config's samples are made with (its fields of the same names). A sample
        re-renders from its provenance alone: ``cfg = BouncingThingsConfig.from_dict(meta["meta"]["config"])`` and
        ``fs.render(fs.Scene.from_meta(meta), keys, options=cfg.render_options)`` (docs/rendering.md, Provenance)."""
        return RenderOptions(**{name: getattr(self, name) for name in OPTION_NAMES})

    def plan_options(self) -> dict[str, Any]:
        """``render_options`` as keywords of ``flowsynth.plan.make_plan`` and ``fs.render``."""
        return {name: getattr(self, name) for name in OPTION_NAMES}

    def check_files(self) -> tuple[str, ...]:
        """Resolve the files this config names, as sampling a scene does: every mesh path and glob of ``assets``
        loaded (returns the asset keys, globs expanded) and ``texture_dir`` listed. Raises AssetError / ConfigError
        naming the path that is missing or unreadable. Constructing a config never reads files; this does."""
        from flowsynth.scene.assets import resolve_assets
        from flowsynth.appearance import list_textures

        keys = resolve_assets(self.assets, field="assets")
        if self.texture_dir is not None:
            list_textures(self.texture_dir)
        return keys

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible dict (tuples become lists); ``from_dict(cfg.to_dict()) == cfg``."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> BouncingThingsConfig:
        """Build a config from a dict such as ``to_dict()`` wrote; missing keys take defaults.

        Raises ConfigError on keys that are not fields (listing the valid ones).
        """
        return config_from_dict(cls, d)


def config_from_dict(cls: type, d: dict[str, Any]):
    """``cls(**d)`` for a config dataclass ``cls`` (``BouncingThingsConfig``, ``LayersConfig``): ``d`` as its
    ``to_dict()`` wrote it, missing keys taking the defaults. Raises ConfigError when ``d`` is not a dict or holds keys
    that are not fields of ``cls`` (naming them and the valid ones), and whatever ``cls`` raises for bad values."""
    if not isinstance(d, dict):
        raise ConfigError(f"from_dict expects a dict, got {type(d).__name__}")
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(d) - set(names), key=str)
    if unknown:
        hints = [f"{k!r}: did you mean {close[0]!r}?" for k in unknown
                 if (close := difflib.get_close_matches(str(k), names, n=1))]
        raise ConfigError(f"unknown {cls.__name__} field(s) {unknown}; " + "".join(h + " " for h in hints)
                          + f"valid fields: {names}")
    return cls(**d)


# Config fields that are render options (flowsynth.options.RenderOptions), under the same names.
PLAN_OPTIONS = OPTION_NAMES

PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "chairs": {
        "width": 512, "height": 384, "num_frames": 2, "flow_px": (1.0, 40.0), "planar_motion": True,
        "camera_target_speed": (0.0, 0.0), "camera_pan": 0.0, "camera_tilt": 0.0, "camera_roll": 0.3,
        "num_objects": (8, 16), "motion": "kinematic",
    },
    "things": {
        "width": 960, "height": 540, "num_frames": 10, "flow_px": (2.0, 100.0), "flow_px_width": 960,
        "num_objects": (5, 20),
        "camera_clearance": 1.0, "spawn_margin": -0.2, "camera_target_speed": (0.5, 2.0),
        "camera_pan": 0.6, "camera_tilt": 0.3, "camera_roll": 0.3, "camera_angle_limit": (0.7, 0.4, 0.4),
        "motion": "kinematic",
    },
}
"""Named configs (``BouncingThingsConfig.preset(name)``, ``--preset NAME``): changes from the defaults.

- "default": the recommended flow-training stream (moving, rotating camera; flow aimed at 2-48 px at 512 px wide).
- "chairs": FlyingChairs-like (Dosovitskiy et al. 2015): 512x384 pairs, large mostly planar motions of
  objects and camera (image-plane translation and roll), flow aimed at 1-40 px.
- "things": FlyingThings3D-like (Mayer et al. 2016): 960x540, 10-frame clips, 5-20 objects that
  intersect freely (kinematic, as in FlyingThings3D), some near the camera and partly out of frame, a
  moving and rotating camera, flow aimed at 2-100 px at its 960 px width (``flow_px_width``).
Each preset's motion scales with the width it is rendered at (``flow_px_width``).
docs/statistics.md lists what each one measures against the published datasets.
"""


def _plain(v: Any) -> Any:
    return [_plain(x) for x in v] if isinstance(v, (tuple, list)) else v


def _set(cfg: BouncingThingsConfig, name: str, value: Any) -> None:
    object.__setattr__(cfg, name, value)


def _int(cfg, name: str, lo: int, hi: int | None = None) -> int:
    v = check_int(name, getattr(cfg, name), lo, hi)
    _set(cfg, name, v)
    return v


def _float(cfg, name: str, value: Any = None, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, hi_open: bool = False) -> float:
    v = getattr(cfg, name) if value is None else value
    if isinstance(v, bool) or not (isinstance(v, (int, float)) or is_int(v)):
        raise ConfigError(f"{name} must be a number, got {v!r}")
    v = float(v)
    if not math.isfinite(v):
        raise ConfigError(f"{name} must be finite, got {v}")
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise ConfigError(f"{name} must be {'>' if lo_open else '>='} {lo}, got {v}")
    if hi is not None and (v > hi or (hi_open and v == hi)):
        raise ConfigError(f"{name} must be {'<' if hi_open else '<='} {hi}, got {v}")
    return v


def _tuple(cfg, name: str, n: int) -> tuple:
    v = getattr(cfg, name)
    if isinstance(v, (str, bytes)) or not hasattr(v, "__len__") or len(v) != n:
        raise ConfigError(f"{name} must be a sequence of {n} values, got {v!r}")
    return tuple(v)


def _range(cfg, name: str, *, lo: float, lo_open: bool = False, integer: bool = False) -> tuple:
    a, b = _tuple(cfg, name, 2)
    if integer:
        for x in (a, b):
            if not is_int(x):
                raise ConfigError(f"{name} must be two integers (min, max), got {getattr(cfg, name)!r}")
        a, b = int(a), int(b)
        if a < lo:
            raise ConfigError(f"{name}: min must be >= {lo}, got {a}")
    else:
        a = _float(cfg, f"{name}[0] (min)", a, lo=lo, lo_open=lo_open)
        b = _float(cfg, f"{name}[1] (max)", b, lo=lo, lo_open=lo_open)
    if a > b:
        raise ConfigError(f"{name}: min {a} > max {b}; pass (min, max) with min <= max")
    _set(cfg, name, (a, b))
    return a, b


def _choice(cfg, name: str, options: tuple[str, ...]) -> None:
    v = getattr(cfg, name)
    if v not in options:
        raise ConfigError(f"{name} must be one of {list(options)}, got {v!r}")


def _lens(cfg: BouncingThingsConfig) -> None:
    """camera_model, camera_dist and camera_dist_max: a valid lens at both ends of every range."""
    from flowsynth.scene.camera import Camera, check_lens

    model, lo = check_lens(cfg.camera_model, cfg.camera_dist)
    _set(cfg, "camera_dist", lo)
    if cfg.camera_dist_max is not None:
        _, hi = check_lens(model, cfg.camera_dist_max)
        if len(hi) != len(lo):
            raise ConfigError(f"camera_dist_max must have as many coefficients as camera_dist ({len(lo)}), "
                              f"got {len(hi)}")
        for i, (a, b) in enumerate(zip(lo, hi)):
            if a > b:
                raise ConfigError(f"camera_dist[{i}] = {a} > camera_dist_max[{i}] = {b}; pass min <= max")
        _set(cfg, "camera_dist_max", hi)
    fov = _float(cfg, "fov_deg", lo=0.0, hi=180.0, lo_open=True, hi_open=True)
    for d in (lo, cfg.camera_dist_max or lo):
        cam = Camera.from_fov(1, 1, fov, model=model, dist=d)
        if cam.lens_limit <= 0:
            raise ConfigError(f"camera_dist {d}: the {model} model folds at the optical axis (no pixel would be "
                              "covered); use smaller coefficients")


def _validate(cfg: BouncingThingsConfig) -> None:
    _int(cfg, "width", 1)
    _int(cfg, "height", 1)
    _int(cfg, "num_frames", 1)
    _set(cfg, "fps", _float(cfg, "fps", lo=0.0, lo_open=True))
    _set(cfg, "fov_deg", _float(cfg, "fov_deg", lo=0.0, hi=180.0, lo_open=True, hi_open=True))
    _lens(cfg)
    _render_options(cfg)
    n_hi = _range(cfg, "num_objects", lo=0, integer=True)[1]
    if n_hi > cfg.max_objects:
        raise ConfigError(f"num_objects: max {n_hi} exceeds max_objects={cfg.max_objects}; "
                          f"raise max_objects to at least {n_hi} or lower num_objects")
    s_hi = _range(cfg, "object_size", lo=0.0, lo_open=True)[1]
    _int(cfg, "size_levels", 1)
    _set(cfg, "min_speed", _float(cfg, "min_speed", lo=0.0))
    _set(cfg, "max_speed", _float(cfg, "max_speed", lo=0.0))
    if cfg.min_speed > cfg.max_speed:
        raise ConfigError(f"min_speed {cfg.min_speed} > max_speed {cfg.max_speed}; "
                          "pass min_speed <= max_speed")
    _range(cfg, "angular_speed", lo=0.0)
    _choice(cfg, "motion", MOTIONS)
    gravity = _tuple(cfg, "gravity", 3)
    _set(cfg, "gravity", tuple(_float(cfg, f"gravity[{i}]", g) for i, g in enumerate(gravity)))
    _set(cfg, "restitution", _float(cfg, "restitution", lo=0.0, hi=1.0))
    _set(cfg, "friction", _float(cfg, "friction", lo=0.0))
    if cfg.substeps is not None:
        _int(cfg, "substeps", 1, 10_000)
    _choice(cfg, "camera_motion", CAMERA_MOTIONS)
    _range(cfg, "camera_speed", lo=0.0)
    _range(cfg, "camera_target_speed", lo=0.0)
    for name in ("camera_pan", "camera_tilt", "camera_roll"):
        _set(cfg, name, _float(cfg, name, lo=0.0))
    limit = _tuple(cfg, "camera_angle_limit", 3)
    _set(cfg, "camera_angle_limit", tuple(_float(cfg, f"camera_angle_limit[{i}]", v, lo=0.0, hi=math.pi / 2)
                                          for i, v in enumerate(limit)))
    if cfg.flow_px is not None:
        _range(cfg, "flow_px", lo=0.0, lo_open=True)
    _int(cfg, "flow_px_width", 1)
    _set(cfg, "rest_fraction", _float(cfg, "rest_fraction", lo=0.0, hi=1.0))
    if not isinstance(cfg.planar_motion, bool):
        raise ConfigError(f"planar_motion must be True or False, got {cfg.planar_motion!r}")
    _set(cfg, "spawn_margin", _float(cfg, "spawn_margin", lo=-0.5, hi=0.5, lo_open=True, hi_open=True))
    room = tuple(_float(cfg, f"room_size[{i}]", v, lo=0.0, lo_open=True)
                 for i, v in enumerate(_tuple(cfg, "room_size", 3)))
    _set(cfg, "room_size", room)
    _set(cfg, "camera_clearance", _float(cfg, "camera_clearance", lo=0.0, lo_open=True))
    if cfg.camera_clearance >= 0.5 * room[0]:
        raise ConfigError(f"camera_clearance {cfg.camera_clearance} m must be less than half of room_size[0] "
                          f"({room[0]} m); lower it or enlarge the room")
    lo, hi = cfg.object_bounds
    free = min(b - a for a, b in zip(lo, hi))
    if s_hi >= free:
        raise ConfigError(f"object_size: max {s_hi} m does not fit the objects' region "
                          f"(smallest side {free:.3g} m);"
                          " lower object_size or enlarge room_size")
    volume = math.prod(b - a - s_hi for a, b in zip(lo, hi))
    filled = n_hi * math.pi / 6 * s_hi**3
    if filled > MAX_PACKING_FRACTION * volume:
        raise ConfigError(f"num_objects/object_size: {n_hi} objects of {s_hi} m fill "
                          f"{filled / volume:.0%} of the "
                          f"room (max {MAX_PACKING_FRACTION:.0%}); lower num_objects or object_size, "
                          "or enlarge room_size")
    if cfg.texture_dir is not None and not isinstance(cfg.texture_dir, str):
        raise ConfigError(f"texture_dir must be a folder path or None, got {cfg.texture_dir!r}")
    _range(cfg, "texture_px", lo=0.0, lo_open=True)
    fams = cfg.texture_families
    if isinstance(fams, str) or not fams or not all(isinstance(f, str) and f for f in fams):
        raise ConfigError(f"texture_families must be a non-empty sequence of names, got {fams!r}")
    _set(cfg, "texture_families", tuple(fams))
    from flowsynth.appearance import check_texture_families

    try:  # names only: texture_dir is read when a scene is sampled
        check_texture_families(cfg.texture_families, cfg.texture_dir)
    except ConfigError as e:
        raise ConfigError(f"texture_families/texture_dir: {e}") from None
    _validate_assets(cfg)


def _render_options(cfg: BouncingThingsConfig) -> None:
    """The render-option fields, checked and normalised by flowsynth.options.RenderOptions (errors name the field):
    the one rule of each option, as fs.render applies it. The config adds one: max_objects is a number."""
    if cfg.max_objects is None:
        raise ConfigError("max_objects must be an integer >= 1 in a config (every sample's object tables have that "
                          "many rows), got None")
    options = RenderOptions(**{name: getattr(cfg, name) for name in OPTION_NAMES})
    for name in OPTION_NAMES:
        _set(cfg, name, getattr(options, name))


def _validate_assets(cfg: BouncingThingsConfig) -> None:
    """Asset entries by their form (built-in name, path or glob); the files are read when a scene is sampled."""
    assets = cfg.assets
    if isinstance(assets, str):
        assets = (assets,)
    if not hasattr(assets, "__iter__") or len(assets) == 0:
        raise ConfigError(f"assets must be a non-empty sequence of asset names or mesh paths, got {assets!r}")
    _set(cfg, "assets", tuple(assets))
    from flowsynth.scene.assets import check_asset_entries

    try:
        check_asset_entries(cfg.assets, field="assets")
    except AssetError as e:
        raise ConfigError(str(e)) from e
