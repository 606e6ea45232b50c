"""The kinds of generated dataset, by name: ``"bouncing"`` (``BouncingThingsConfig`` -> ``BouncingThings``),
``"layers"`` (``LayersConfig`` -> ``Layers``) and ``"mixture"`` (``MixtureConfig`` -> ``Mixture``, whose sources are of
the first two kinds, ``SOURCE_KINDS``). The one description of a kind: what export, statistics, previews,
``FlowPairs`` and a mixture's presets use to take any kind the same way: ``config_kind``, ``config_from``,
``make_stream``, ``stream_outputs``.

The mixture kind is registered by ``datasets/mixture.py`` (``register_kind``), which builds on this module; importing
``flowsynth.datasets`` registers it."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.datasets.layers import Layers, LayersConfig, layer_outputs, refuse_scene_options
from flowsynth.errors import ConfigError
from flowsynth.scene import BouncingThingsConfig

__all__ = ["KINDS", "SOURCE_KINDS", "config_from", "config_kind", "make_stream", "register_kind", "stream_outputs"]

KINDS = ("bouncing", "layers", "mixture")
"""Names of the dataset kinds."""
SOURCE_KINDS = ("bouncing", "layers")
"""The kinds a source of a mixture may be."""
_CONFIGS: dict[str, type] = {"bouncing": BouncingThingsConfig, "layers": LayersConfig}
_MIXTURE: list = []  # (MixtureConfig, Mixture), once datasets/mixture.py has registered them
_NAMES = {"bouncing": "a BouncingThingsConfig", "layers": "a LayersConfig", "mixture": "a MixtureConfig"}


def register_kind(config_cls: type, stream_cls: type) -> None:
    """Make ``config_cls`` the config and ``stream_cls`` the stream of the ``"mixture"`` kind (what
    ``datasets/mixture.py`` calls once, at import)."""
    _CONFIGS["mixture"] = config_cls
    _MIXTURE[:] = [(config_cls, stream_cls)]


def _expected(kinds: Sequence[str]) -> str:
    names = [_NAMES[k] for k in kinds]
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} or {names[-1]}"


def config_kind(cfg, kinds: Sequence[str] = KINDS) -> str:
    """``"bouncing"`` for a ``BouncingThingsConfig``, ``"layers"`` for a ``LayersConfig``, ``"mixture"`` for a
    ``MixtureConfig``; ConfigError for anything else or a kind not among ``kinds`` (``SOURCE_KINDS``: a mixture's
    source)."""
    for kind in kinds:
        if kind in _CONFIGS and isinstance(cfg, _CONFIGS[kind]):
            return kind
    what = "a source config" if tuple(kinds) == SOURCE_KINDS else "a dataset config"
    raise ConfigError(f"{what} must be {_expected(kinds)}, got {type(cfg).__name__}")


def config_from(kind: str, values: dict[str, Any], kinds: Sequence[str] = KINDS):
    """The config of ``kind`` (one of ``kinds``: ``KINDS``, or ``SOURCE_KINDS`` for a mixture's source) from a dict
    of its fields (``to_dict``'s form: for a mixture, its preset dict); ConfigError for an unknown kind or field."""
    if kind not in kinds or kind not in _CONFIGS:
        raise ConfigError(f"unknown {'source' if tuple(kinds) == SOURCE_KINDS else 'dataset'} kind {kind!r}; "
                          f"kinds: {list(kinds)}")
    return _CONFIGS[kind].from_dict(dict(values) if kind in SOURCE_KINDS else values)


def stream_outputs(cfg, outputs: Sequence[str], *, drop_unknown: bool = False) -> tuple[str, ...]:
    """The output keys a stream of ``cfg`` makes for ``outputs``: ``flowsynth.plan.make_plan``'s for BouncingThings
    (aliases and frame gaps expanded), ``layer_outputs``' for Layers, for a mixture the keys every source makes
    (``drop_unknown``: leave out what the kind does not give, for a layout's default set). ConfigError for keys the
    kind (a mixture: one of its sources, named) does not give."""
    kind = config_kind(cfg)
    if kind == "mixture":
        per = []
        for name, c in cfg.sources:
            try:
                per.append(stream_outputs(c, outputs, drop_unknown=drop_unknown))
            except ConfigError as e:
                raise ConfigError(f"mixture source {name!r}: {e}") from e
        keys = tuple(k for k in per[0] if all(k in p for p in per[1:]))
        if not keys:
            raise ConfigError(f"no output of {list(outputs)} is given by every source of the mixture")
        return keys
    if kind == "layers":
        return layer_outputs(outputs, drop_unknown=drop_unknown)
    from flowsynth.plan import make_plan

    return make_plan(outputs, flow_gaps=cfg.flow_gaps, stereo_baseline=cfg.stereo_baseline).outputs


def make_stream(cfg, outputs: Sequence[str], seed: int = 0, length: int | None = None, *, start: int = 0,
                occlusion: str = "exact", device: str = "cpu", threads: int | None = None):
    """``BouncingThings``, ``Layers`` or ``Mixture`` of ``cfg``'s kind. ``occlusion``, ``device`` and ``threads``
    are BouncingThings' (a mixture passes them to its BouncingThings sources; a Layers stream renders with torch on
    the CPU, its occlusion exact from the layer order: ConfigError for ``occlusion="depth"``, another device or
    ``threads`` there, and for a mixture of Layers sources only, ``layers.refuse_scene_options``)."""
    kind = config_kind(cfg)
    if kind == "bouncing":
        return BouncingThings(cfg, outputs, seed, length, start=start, occlusion=occlusion, device=device,
                              threads=threads)
    if kind == "mixture":
        mixture = _MIXTURE[0][1]
        return mixture(cfg, None, outputs, seed, length, start=start, occlusion=occlusion, device=device,
                       threads=threads)
    refuse_scene_options(occlusion, device, threads)
    return Layers(cfg, outputs, seed, length, start=start)
