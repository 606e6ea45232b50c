"""``Mixture``: one stream drawn from several configs of either source kind (``BouncingThingsConfig``,
``LayersConfig``), reproducibly, with an optional curriculum; ``MixtureConfig``: its configs and weights, what a
preset file holds, a dataset config as the other two are (``flowsynth.datasets.make_stream`` makes its Mixture).

Sample i comes from config k = ``source(i)``, drawn from the weights in force at index i with a generator seeded
by (seed, i) alone, and is exactly sample i of that config's own stream (``BouncingThings(configs[k], outputs,
seed)`` or ``Layers(configs[k], outputs, seed)``): a pure function of (configs, weights, seed, i), whatever the
workers, ranks or order of reading. Iteration, sharding, epochs and ``state_dict`` are ``IndexStream``'s.

A curriculum is a list of stages ``[(until, weights), ...]``: index i uses the weights of the first stage with
i < until (the last stage's ``until`` may be None: open-ended). "chairs, then things" is
``[(20000, {"chairs": 1}), (None, {"chairs": 1, "things": 3})]``.

All configs must give samples of one shape (width, height and num_frames equal, and max_objects among the
BouncingThings configs), so that ``default_collate`` batches a mixture. Each item holds the outputs (every source
must give each), ``index``, ``seed`` and ``source`` (int64, k). ``"meta"`` among the outputs names the metadata keys
every source has: ``provenance``, and ``K`` and ``cam_T_world`` when every source is a BouncingThings config.

A preset file is JSON::

    {"format": "flowsynth-mixture", "version": 1,
     "sources": [{"name": "things", "kind": "bouncing", "config": {...}},
                 {"name": "chairs", "kind": "layers", "config": {...}}],
     "weights": {"things": 1, "chairs": 1}}

``kind`` is one of ``kinds.SOURCE_KINDS``, ``config`` the config's ``to_dict()``, and ``weights`` null (equal weights),
a dict, or a curriculum ``[[until, {...}], ..., [null, {...}]]``. ``MixtureConfig.to_file`` writes one and
``MixtureConfig.from_file`` reads one (``to_dict`` / ``from_dict``: the same JSON as a dict, as every dataset config
has); ``Mixture.to_preset`` / ``from_preset`` call them. The outputs, seed and stream options are arguments, not part
of the preset.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.datasets.kinds import SOURCE_KINDS, config_from, config_kind, register_kind
from flowsynth.datasets.layers import Layers, refuse_scene_options
from flowsynth.datasets.stream import IndexStream, check_index
from flowsynth.errors import ConfigError
from flowsynth.options import check_int

__all__ = ["PRESET_FORMAT", "Mixture", "MixtureConfig"]

MIX_SALT = 0x6D1C  # keeps the source draw apart from every other generator seeded by (seed, i)
SHAPE_FIELDS = ("width", "height", "num_frames")
PRESET_FORMAT = "flowsynth-mixture"
"""The ``format`` of a preset file (version 1)."""
_ALWAYS = ("index", "seed")  # keys every source's items hold besides the outputs



@dataclasses.dataclass(frozen=True)
class MixtureConfig:
    """A mixture's named source configs and their weights, checked once: what a preset file holds (module
    docstring), without outputs, seed or stream options. A config never changes once made.

    ``MixtureConfig(configs, weights)`` takes ``Mixture``'s ``configs`` and ``weights`` arguments (a dict or list of
    configs or BouncingThings preset names; weights, a curriculum or None) and keeps them in the normal forms below.
    Raises ConfigError as ``Mixture`` does for its configs and weights.
    """

    sources: tuple[tuple[str, Any], ...]
    """(name, ``BouncingThingsConfig`` or ``LayersConfig``) pairs in order; ``Mixture.source(i)`` indexes them."""
    weights: Any = None
    """None (equal weights), {name: weight}, or a curriculum [[until, {name: weight} or None], ...]: the preset's
    JSON form."""

    def __post_init__(self) -> None:
        from flowsynth.scene import BouncingThingsConfig

        configs = self.sources
        if isinstance(configs, Mapping):
            items = list(configs.items())
        elif isinstance(configs, Sequence) and not isinstance(configs, str) and all(
                isinstance(c, tuple) and len(c) == 2 and isinstance(c[0], str) for c in configs) and configs:
            items = list(configs)  # (name, config) pairs: the normal form
        elif isinstance(configs, Sequence) and not isinstance(configs, str):
            items = [(str(k), c) for k, c in enumerate(configs)]
        else:
            raise ConfigError(f"configs must be a dict or a list of configs or preset names, got {configs!r}")
        if not items:
            raise ConfigError("a Mixture needs at least one config")
        items = [(str(k), BouncingThingsConfig.preset(c) if isinstance(c, str) else c) for k, c in items]
        for name, c in items:
            try:
                config_kind(c, SOURCE_KINDS)
            except ConfigError:
                raise ConfigError(f"config {name!r} must be a BouncingThingsConfig, a LayersConfig or a preset name, "
                                  f"got {type(c).__name__}") from None
        _check_shapes(items)
        _stages(self.weights, [k for k, _ in items])
        object.__setattr__(self, "sources", tuple(items))
        object.__setattr__(self, "weights", _plain_weights(self.weights))

    @property
    def configs(self) -> dict[str, Any]:
        """name -> source config, in order."""
        return dict(self.sources)

    @property
    def width(self) -> int:
        """Image width of every source [px]."""
        return self.sources[0][1].width

    @property
    def height(self) -> int:
        """Image height of every source [px]."""
        return self.sources[0][1].height

    @property
    def num_frames(self) -> int:
        """Frames per sample of every source."""
        return self.sources[0][1].num_frames

    def check_files(self) -> None:
        """Each source's ``check_files`` (the meshes, textures and folders it names); ConfigError naming the
        source."""
        for name, c in self.sources:
            try:
                c.check_files()
            except ConfigError as e:
                raise ConfigError(f"mixture source {name!r}: {e}") from e

    def to_dict(self) -> dict:
        """The preset (module docstring) as a JSON-compatible dict; ``from_dict(cfg.to_dict()) == cfg``."""
        sources = [{"name": n, "kind": config_kind(c, SOURCE_KINDS), "config": c.to_dict()} for n, c in self.sources]
        return {"format": PRESET_FORMAT, "version": 1, "sources": sources, "weights": self.weights}

    @classmethod
    def from_dict(cls, preset: dict) -> MixtureConfig:
        """The config of a preset dict (``to_dict``'s form); ConfigError naming what is wrong with it."""
        if not isinstance(preset, dict) or preset.get("format") != PRESET_FORMAT:
            raise ConfigError(f"a mixture preset is a JSON object with \"format\": \"{PRESET_FORMAT}\"")
        if preset.get("version") != 1:
            raise ConfigError(f"mixture preset version {preset.get('version')!r} is not supported (version 1)")
        unknown = sorted(set(preset) - {"format", "version", "sources", "weights"})
        if unknown:
            raise ConfigError(f"unknown mixture preset key(s) {unknown}; a preset holds format, version, sources and "
                              "weights")
        sources = preset.get("sources")
        if not isinstance(sources, list) or not sources:
            raise ConfigError("a mixture preset needs \"sources\": a non-empty list of {name, kind, config}")
        configs = {}
        for n, s in enumerate(sources):
            if not isinstance(s, dict) or set(s) != {"name", "kind", "config"} or not isinstance(s["config"], dict):
                raise ConfigError(f"mixture preset source {n} must be {{\"name\", \"kind\", \"config\"}}, got {s!r}")
            if str(s["name"]) in configs:
                raise ConfigError(f"mixture preset source name {s['name']!r} is used twice")
            try:
                configs[str(s["name"])] = config_from(s["kind"], s["config"], SOURCE_KINDS)
            except ConfigError as e:
                raise ConfigError(f"mixture preset source {s['name']!r}: {e}") from e
        weights = preset.get("weights")
        if isinstance(weights, list):
            weights = [tuple(stage) if isinstance(stage, list) else stage for stage in weights]
        return cls(configs, weights)

    def to_file(self, path: str | os.PathLike) -> Path:
        """Write the preset file ``path``: ``to_dict()`` as JSON, atomically, its folder made if missing; returns its
        path. The one writer of preset files (``flowsynth tune`` and ``Mixture.to_preset`` call it)."""
        from flowsynth.io import write_json

        Path(path).parent.mkdir(parents=True, exist_ok=True)
        write_json(Path(path), self.to_dict())
        return Path(path)

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> MixtureConfig:
        """The config of the preset file ``path`` (JSON, ``to_file``'s); ConfigError for a missing file, bad JSON or
        a bad preset, naming the file and what is wrong. The one reader of preset files (the CLI's ``--mixture`` and
        ``Mixture.from_preset`` call it)."""
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"mixture preset {str(p)!r} does not exist")
        try:
            preset = json.loads(p.read_text())
        except (ValueError, UnicodeDecodeError) as e:
            raise ConfigError(f"mixture preset {str(p)!r} is not valid JSON: {e}") from e
        try:
            return cls.from_dict(preset)
        except ConfigError as e:
            raise ConfigError(f"mixture preset {str(p)!r}: {e}") from e


class Mixture(IndexStream):
    """A stream of samples from several configs.

    Args:
        configs: name -> ``BouncingThingsConfig``, ``LayersConfig`` or a BouncingThings preset name
            (``BouncingThingsConfig.preset``), or a sequence of them (named by their position); or a
            ``MixtureConfig`` (then ``weights`` is its own: pass None).
        weights: name -> weight >= 0 (a missing name weighs 0; None: equal weights), or a curriculum: a list of
            ``(until, weights)`` stages (module docstring).
        outputs, seed, length, start: as ``BouncingThings``; every source must give every output.
        occlusion, device, threads: the BouncingThings sources' (a Layers source renders with torch on the CPU,
            its occlusion exact from the layer order); ConfigError for any but the defaults when no source is a
            BouncingThings config (``layers.refuse_scene_options``): nothing would honour them.

    Attributes: ``config`` (its ``MixtureConfig``), ``names``, ``configs`` (name -> config), ``weights`` (the
    preset's form), ``parts`` (each source's own stream), ``outputs``.

    Raises ConfigError for configs of different sample shapes or of another type, outputs a source does not give,
    unknown names, negative or all-zero weights, or stages whose ``until`` do not increase.
    """

    def __init__(self, configs, weights=None, outputs: Sequence[str] = ("rgb", "flow_fw"), seed: int = 0,
                 length: int | None = None, *, start: int = 0, occlusion: str = "exact", device: str = "cpu",
                 threads: int | None = None) -> None:
        if isinstance(configs, MixtureConfig):
            if weights is not None:
                raise ConfigError("weights belong to the MixtureConfig; pass weights=None with one")
            self.config = configs
        else:
            self.config = MixtureConfig(configs, weights)
        items = self.config.sources
        self.names = [k for k, _ in items]
        self.weights = self.config.weights
        self.stages = _stages(self.weights, self.names)
        self._init_stream(seed, length, start)
        if all(config_kind(c, SOURCE_KINDS) == "layers" for _, c in items):
            refuse_scene_options(occlusion, device, threads, what="a Mixture of Layers sources only")
        self.parts = []
        for name, c in items:
            try:
                self.parts.append(BouncingThings(c, outputs, seed, length, start=start, occlusion=occlusion,
                                                 device=device, threads=threads)
                                  if config_kind(c, SOURCE_KINDS) == "bouncing"
                                  else Layers(c, outputs, seed, length, start=start))
            except ConfigError as e:
                raise ConfigError(f"mixture source {name!r}: {e}") from e
        common = set.intersection(*(set(p.outputs) for p in self.parts))
        self.outputs = tuple(k for k in self.parts[0].outputs if k in common)
        self.keys = frozenset((*self.outputs, *_ALWAYS))
        self.configs = dict(items)
        self.cfg, self.device = items[0][1], device

    def source(self, i: int) -> int:
        """The config index of sample ``i``."""
        i = check_index(i)
        p = next(w for until, w in self.stages if until is None or i < until)
        rng = np.random.default_rng([self.seed, i, MIX_SALT])
        return int(rng.choice(len(p), p=p))

    def scene(self, i: int):
        """The simulated scene behind sample ``i`` (from its source's config); ConfigError when that source is a
        Layers config (2D layers have no scene: ``Layers.draw`` says what a layered sample is made of)."""
        part = self.parts[self.source(i)]
        if not isinstance(part, BouncingThings):
            raise ConfigError(f"sample {i} comes from the Layers source {self.names[self.source(i)]!r}, which has "
                              "no 3D scene; its draw is parts[k].draw(i)")
        return part.scene(i)

    def sample(self, i: int) -> dict[str, torch.Tensor]:
        """Sample ``i``: sample i of its source's stream (the keys every source gives), plus ``source`` (int64)."""
        k = self.source(i)
        out = {key: v for key, v in self.parts[k].sample(i).items() if key in self.keys}
        out["source"] = torch.tensor(k, dtype=torch.int64)
        return out

    # -- presets: MixtureConfig.to_file / from_file, on the stream ------------------------------------------------
    def to_preset(self, path: str | os.PathLike) -> Path:
        """``self.config.to_file(path)``: write this mixture's preset file; returns its path."""
        return self.config.to_file(path)

    @classmethod
    def from_preset(cls, path: str | os.PathLike, outputs: Sequence[str] = ("rgb", "flow_fw"), seed: int = 0,
                    length: int | None = None, **kwargs) -> Mixture:
        """``Mixture(MixtureConfig.from_file(path), None, outputs, seed, length, **kwargs)``: the mixture of the
        preset file ``path``, the keywords as ``Mixture``'s. ConfigError as ``MixtureConfig.from_file`` raises."""
        return cls(MixtureConfig.from_file(path), None, outputs, seed, length, **kwargs)


def _check_shapes(items: list) -> None:
    """ConfigError unless every config gives samples of one shape (module docstring)."""
    name0, first = items[0]
    for name, c in items:
        diff = [f for f in SHAPE_FIELDS if getattr(c, f) != getattr(first, f)]
        if diff:
            raise ConfigError(f"config {name!r} differs from {name0!r} in {diff}: a Mixture's samples must share one "
                              f"shape (set {', '.join(diff)} alike)")
    things = [(name, c) for name, c in items if config_kind(c, SOURCE_KINDS) == "bouncing"]
    for name, c in things:
        if c.max_objects != things[0][1].max_objects:
            raise ConfigError(f"config {name!r} differs from {things[0][0]!r} in ['max_objects']: a Mixture's "
                              "samples must share one shape (set max_objects alike)")


def _plain_weights(weights):
    """``weights`` in the preset's JSON form (None, a dict, or a list of [until, dict] stages)."""
    if weights is None:
        return None
    if isinstance(weights, Mapping):
        return {str(k): float(v) for k, v in weights.items()}
    return [[None if until is None else int(until), None if w is None else {str(k): float(v) for k, v in w.items()}]
            for until, w in weights]


def _stages(weights, names: list[str]) -> list[tuple[int | None, np.ndarray]]:
    """[(until, probabilities over names)] from ``Mixture``'s ``weights`` argument, checked."""
    if weights is None or isinstance(weights, Mapping):
        stages = [(None, weights)]
    elif isinstance(weights, Sequence) and not isinstance(weights, str) and weights:
        stages = list(weights)
    else:
        raise ConfigError(f"weights must be None, a dict name -> weight, or a list of (until, weights) stages, "
                          f"got {weights!r}")
    out, last = [], 0
    for n, stage in enumerate(stages):
        if not (isinstance(stage, Sequence) and len(stage) == 2):
            raise ConfigError(f"curriculum stage {n} must be (until, weights), got {stage!r}")
        until, w = stage
        if until is not None:
            until = check_int(f"curriculum stage {n}'s until (increasing)", until, last + 1)
        if until is None and n != len(stages) - 1:
            raise ConfigError(f"curriculum stage {n}: only the last stage may be open-ended (until None)")
        w = dict.fromkeys(names, 1.0) if w is None else w
        if not isinstance(w, Mapping) or set(w) - set(names):
            raise ConfigError(f"weights must name configs among {names}, got {w!r}")
        p = np.array([float(w.get(k, 0.0)) for k in names])
        if not np.all(np.isfinite(p)) or (p < 0).any() or p.sum() <= 0:
            raise ConfigError(f"weights must be finite, >= 0 and not all 0, got {w!r}")
        out.append((None if until is None else int(until), p / p.sum()))
        last = until if until is not None else last
    if out[-1][0] is not None:
        out.append((None, out[-1][1]))  # past the last stage: its weights go on
    return out


register_kind(MixtureConfig, Mixture)
