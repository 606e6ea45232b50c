"""``Layers``: a stream of FlyingChairs-style 2D pairs: a background and 2-5 shapes (ellipses and polygons), each under
its own random affine motion, with exact flow, validity, occlusion from the layer order and the layer map.

Sample i is a pure function of (config, seed, i): its draws come from a generator seeded by (seed, i) alone
(``draw``), so it is the same in every run, worker and after a resume; iteration, sharding, epochs and
``state_dict`` are ``IndexStream``'s, as for ``BouncingThings``. The draws are the learning benchmark's
``chairs2d_pairs`` (``layer_draws``), the rendering is torch's (``layer_render``), the textures flowsynth's own
frames or a folder's images (``layer_textures``). ``layers_pairs`` is the helper's own loop: one generator over n
pairs, the same draws, shapes and motions as ``chairs2d_pairs(n, seed, sources, motion_scale)``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from flowsynth.datasets.layer_draws import PairDraw, draw_pair
from flowsynth.datasets.layer_render import render_layers
from flowsynth.datasets.layer_textures import TEXTURE_SEED, TextureBank
from flowsynth.datasets.meta import ALL, PROVENANCE, split_meta
from flowsynth.datasets.stream import IndexStream, check_index
from flowsynth.errors import ConfigError, ShapeError
from flowsynth.options import check_int
from flowsynth.scene import config_from_dict

__all__ = ["LAYERS_OUTPUTS", "Layers", "LayersConfig", "layer_outputs", "layers_pairs", "refuse_scene_options"]

LAYERS_OUTPUTS = ("rgb", "flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw",
                  "instance", "category")
"""The outputs a ``Layers`` sample can hold (``layer_render.render_layers`` says what each is)."""
PAIR_KEYS = tuple(k for k in LAYERS_OUTPUTS if k.endswith(("_fw", "_bw")))
LAYERS_SALT = 0x1A7E  # keeps a sample's draws apart from every other generator seeded by (seed, i)
MIN_SIZE = 32  # [px] the smallest width and height: the smallest shape, 6 px at 128 px wide, is 1.5 px there
MAX_MOTION = 200.0
"""The largest motion_scale x (num_frames - 1) (``LayersConfig.motion_scale`` says why)."""


@dataclasses.dataclass(frozen=True)
class LayersConfig:
    """What a ``Layers`` stream makes; every field has a default, and a config never changes once made."""

    width: int = 320
    """Image width [px], >= 32. Shape sizes and shifts scale with width / 128."""
    height: int = 240
    """Image height [px], >= 32."""
    num_frames: int = 2
    """Frames per sample T >= 1; frame t shows every layer moved t times by its affine motion (2 or more for
    flow)."""
    motion_scale: float = 1.0
    """Multiplies every shift, rotation and log-zoom range of the motions (>= 0; 0: nothing moves), with
    motion_scale x max(num_frames - 1, 1) <= ``MAX_MOTION`` (200). Why: a shape's log-zoom a frame is at most
    0.1 x motion_scale, so no frame's map (M^t, t < num_frames) scales by more than e^20 (5e8) or less than e^-20:
    each stays invertible (determinant >= e^-40 in float64), and coordinates and flow, that zoom times the image size
    and the shifts, stay far inside float32 (largest value 3.4e38, e^88.7). At motion_scale 1000 and 2 frames,
    exp(100) overflows float32."""
    texture_dir: str | None = None
    """A folder of images the background and the shapes are cut from (each image fitted to the frame); None: the
    default bank of flowsynth frames (``texture_bank`` of them)."""
    texture_bank: int = 600
    """Frames in the default texture bank [count, >= 1]: frame 0 of BouncingThings samples 0..texture_bank-1 at
    this width and height, each rendered once per process, the first time a draw picks it, and kept (3 bytes a
    pixel). The default is as many frames as the learning benchmark's 2D pools were textured from (600 for 1200
    pairs); what rendering them costs: docs/decisions/0023-raft-judge.md."""
    texture_seed: int = TEXTURE_SEED
    """Seed of the BouncingThings stream of the default bank (>= 0): keep it apart from the training streams'."""

    def __post_init__(self) -> None:
        for name, lo in (("width", MIN_SIZE), ("height", MIN_SIZE), ("num_frames", 1), ("texture_bank", 1),
                         ("texture_seed", 0)):
            object.__setattr__(self, name, check_int(name, getattr(self, name), lo))
        object.__setattr__(self, "motion_scale", check_motion_scale(self.motion_scale, self.num_frames))
        if self.texture_dir is not None:
            if not isinstance(self.texture_dir, (str, bytes)) and not hasattr(self.texture_dir, "__fspath__"):
                raise ConfigError(f"texture_dir must be a folder path or None, got {self.texture_dir!r}")
            object.__setattr__(self, "texture_dir", str(self.texture_dir))

    def check_files(self) -> None:
        """List ``texture_dir`` (ConfigError when it is missing or holds no image); a config reads no file when it
        is made."""
        if self.texture_dir is not None:
            from flowsynth.appearance import list_textures

            list_textures(self.texture_dir)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible dict; ``from_dict(cfg.to_dict()) == cfg``."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LayersConfig:
        """A config from a dict such as ``to_dict()`` wrote; missing keys take defaults. ConfigError on keys that
        are not fields (listing the valid ones)."""
        return config_from_dict(cls, d)


def check_motion_scale(m, num_frames: int) -> float:
    """``m`` as a float; ConfigError unless it is a number >= 0 with m x max(num_frames - 1, 1) <= ``MAX_MOTION``
    (``LayersConfig.motion_scale``)."""
    if isinstance(m, bool) or not isinstance(m, (int, float, np.floating, np.integer)) or not math.isfinite(m) \
            or m < 0:
        raise ConfigError(f"motion_scale must be a finite number >= 0, got {m!r}")
    steps = max(num_frames - 1, 1)
    if float(m) * steps > MAX_MOTION:
        raise ConfigError(f"motion_scale x max(num_frames - 1, 1) must be <= {MAX_MOTION:g} (beyond it the zoom of "
                          f"the last frame overflows), got {float(m)!r} x {steps}; lower motion_scale to "
                          f"{MAX_MOTION / steps:g} or less")
    return float(m)


def refuse_scene_options(occlusion: str = "exact", device: str = "cpu", threads: int | None = None, *,
                         what: str = "a Layers stream") -> None:
    """ConfigError for a ``BouncingThings`` stream option that ``what``, a stream of 2D layers only, cannot honour:
    its occlusion is exact, from the layer order (``occlusion`` must be "exact"), it renders with torch on the CPU
    (``device`` "cpu") with torch's own threads (``threads`` None: set ``torch.set_num_threads`` instead)."""
    if occlusion != "exact":
        raise ConfigError(f"{what} cannot honour occlusion={occlusion!r}, a BouncingThings option: 2D layers' "
                          "occlusion is exact, from the layer order; leave it at 'exact'")
    if device != "cpu":
        raise ConfigError(f"{what} cannot honour device={device!r}, a BouncingThings option: 2D layers render "
                          "with torch on the CPU; leave it at 'cpu'")
    if threads is not None:
        raise ConfigError(f"{what} cannot honour threads={threads!r}, a BouncingThings option (its ray launches): "
                          "2D layers render with torch's threads; leave it None (torch.set_num_threads sets those)")


def layer_outputs(outputs: Sequence[str], *, drop_unknown: bool = False) -> tuple[str, ...]:
    """``outputs`` checked against ``LAYERS_OUTPUTS`` (duplicates dropped, order kept). Raises ConfigError naming
    what a Layers sample gives for any other key, or with ``drop_unknown`` leaves those out (a layout's defaults)."""
    if isinstance(outputs, str) or not isinstance(outputs, Sequence) or not all(isinstance(k, str) for k in outputs):
        raise ConfigError(f"outputs must be a sequence of output names, got {outputs!r}")
    keys = tuple(dict.fromkeys(outputs))
    unknown = [k for k in keys if k not in LAYERS_OUTPUTS]
    if unknown and not drop_unknown:
        raise ConfigError(f"a Layers sample has no {unknown} (2D layers have no depth, camera or 3D outputs); "
                          f"Layers gives {list(LAYERS_OUTPUTS)}")
    keys = tuple(k for k in keys if k in LAYERS_OUTPUTS)
    if not keys:
        raise ConfigError(f"no output left for a Layers sample; choose from {list(LAYERS_OUTPUTS)}")
    return keys


class Layers(IndexStream):
    """Endless (or ``length``-long per epoch) stream of layered 2D samples.

    Args:
        cfg: a ``LayersConfig`` (defaults when None).
        outputs: keys of ``LAYERS_OUTPUTS``, and ``provenance`` (a JSON string: the config, seed, index and every
            draw; ``"meta"`` names it too), or ``"all"`` for all of them (the per-pair keys with two frames or
            more); ``index`` and ``seed`` (int64 scalars) are always added.
        seed: dataset seed; any integer >= 0, 0 included.
        length: samples per epoch, or None for an endless stream.
        start: first index of the stream.

    Each item is a dict of tensors with the shapes and dtypes of ``BouncingThings``' keys of the same names:
    ``rgb`` (T, 3, H, W) float32 in [0, 1]; ``flow_*`` (T-1, 2, H, W) float32 [px]; ``valid_*``, ``occ_*``,
    ``oof_*`` (T-1, 1, H, W) bool; ``instance``, ``category`` (T, 1, H, W) int32 (``layer_render.render_layers``).
    ``valid_*`` means what it means in every dataset, that the flow is defined: every pixel sees a layer, so it is
    True everywhere and the flow is exact at every pixel; a target that leaves the image is ``oof_*``.

    Raises ConfigError for a config of another type, outputs a Layers sample does not have, per-pair outputs with
    num_frames < 2, or a bad seed, length or start.
    """

    def __init__(self, cfg: LayersConfig | None = None, outputs: Sequence[str] = ("rgb", "flow_fw"), seed: int = 0,
                 length: int | None = None, *, start: int = 0) -> None:
        cfg = LayersConfig() if cfg is None else cfg
        if not isinstance(cfg, LayersConfig):
            raise ConfigError(f"cfg must be a LayersConfig, got {type(cfg).__name__}")
        every = () if isinstance(outputs, str) or not isinstance(outputs, Sequence) or ALL not in outputs else \
            LAYERS_OUTPUTS if cfg.num_frames > 1 else tuple(k for k in LAYERS_OUTPUTS if k not in PAIR_KEYS)
        keys, self.provenance = split_meta(outputs, (PROVENANCE,), every)
        self.outputs = layer_outputs(keys)
        pairs = [k for k in self.outputs if k in PAIR_KEYS]
        if pairs and cfg.num_frames < 2:
            raise ConfigError(f"{pairs} need num_frames >= 2, got {cfg.num_frames}; raise num_frames or leave them out")
        self._init_stream(seed, length, start)
        self.cfg = cfg
        self.outputs += (PROVENANCE,) if self.provenance else ()
        self.textures = TextureBank(cfg.width, cfg.height, cfg.texture_bank, cfg.texture_seed, cfg.texture_dir)

    def draw(self, i: int) -> PairDraw:
        """What sample ``i`` is made of: ``draw_pair`` from a generator seeded by (seed, i)."""
        rng = np.random.default_rng([self.seed, check_index(i), LAYERS_SALT])
        return draw_pair(rng, self.cfg.width, self.cfg.height, len(self.textures), self.cfg.motion_scale)

    def sample(self, i: int) -> dict[str, torch.Tensor]:
        """Sample ``i``: exactly the item the stream yields for index ``i``."""
        i = check_index(i)
        d = self.draw(i)
        cfg = self.cfg
        out: dict[str, Any] = render_layers(d, self.textures.__getitem__, cfg.width, cfg.height, cfg.num_frames,
                                            [k for k in self.outputs if k != PROVENANCE])
        out["index"] = torch.tensor(i, dtype=torch.int64)
        out["seed"] = torch.tensor(self.seed, dtype=torch.int64)
        if self.provenance:
            out[PROVENANCE] = json.dumps({"dataset": "layers", "config": cfg.to_dict(), "seed": self.seed,
                                          "index": i, "draw": d.to_dict()}, separators=(",", ":"))
        return out


def layers_pairs(n: int, seed: int, sources: torch.Tensor, motion_scale: float = 1.0,
                 outputs: Sequence[str] = ("rgb", "flow_fw", "valid_fw")) -> dict[str, torch.Tensor]:
    """n two-frame samples drawn by one generator, ``np.random.default_rng(seed)``, over n pairs: the draws, shapes
    and motions of the learning benchmark's ``chairs2d_pairs(n, seed, sources, motion_scale)``, rendered by torch.

    Args:
        n: number of pairs, >= 1.
        seed: the generator's seed.
        sources: (m, 3, H, W) float images in [0, 1], the backgrounds and textures (H, W >= 32).
        motion_scale: multiplies every shift, rotation and log-zoom range; 0 to ``MAX_MOTION``
            (``LayersConfig.motion_scale``).
        outputs: keys of ``LAYERS_OUTPUTS``.

    Returns:
        {key: (n, ...) tensor}: each key as in a ``Layers`` sample of 2 frames, stacked (``rgb`` (n, 2, 3, H, W),
        ``flow_fw`` (n, 1, 2, H, W), ...).
    """
    n = check_int("n", n, 1)
    if not isinstance(sources, torch.Tensor) or sources.ndim != 4 or sources.shape[1] != 3 or len(sources) == 0:
        raise ShapeError(f"sources must be a (m, 3, H, W) tensor with m >= 1, got "
                         f"{tuple(sources.shape) if isinstance(sources, torch.Tensor) else type(sources).__name__}")
    H, W = sources.shape[-2:]
    if H < MIN_SIZE or W < MIN_SIZE:
        raise ShapeError(f"sources must be at least {MIN_SIZE}x{MIN_SIZE} px, got {W}x{H}")
    keys = layer_outputs(outputs)
    motion_scale = check_motion_scale(motion_scale, 2)
    src = sources.to(torch.float32)
    rng = np.random.default_rng(seed)
    items = [render_layers(draw_pair(rng, W, H, len(src), motion_scale), src.__getitem__, W, H, 2, keys)
             for _ in range(n)]
    return {k: torch.stack([it[k] for it in items]) for k in keys}
