"""The kinds of generated dataset, by name: ``"bouncing"`` (``BouncingThingsConfig`` -> ``BouncingThings``),
``"layers"`` (``LayersConfig`` -> ``Layers``) and ``"mixture"`` (``MixtureConfig`` -> ``Mixture``, whose sources are of
the first two kinds). What export, statistics, previews and ``FlowPairs`` use to take any kind the same way:
``config_kind``, ``config_from``, ``make_stream``, ``stream_outputs``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.datasets.layers import Layers, layer_outputs, refuse_scene_options
from flowsynth.errors import ConfigError

__all__ = ["KINDS", "config_from", "config_kind", "make_stream", "stream_outputs"]

KINDS = ("bouncing", "layers", "mixture")
"""Names of the dataset kinds."""


def config_kind(cfg) -> str:
    """``"bouncing"`` for a ``BouncingThingsConfig``, ``"layers"`` for a ``LayersConfig``, ``"mixture"`` for a
    ``MixtureConfig``; ConfigError otherwise."""
    from flowsynth.datasets.mixture import MixtureConfig, source_kind

    if isinstance(cfg, MixtureConfig):
        return "mixture"
    try:
        return source_kind(cfg)
    except ConfigError:
        raise ConfigError(f"a dataset config must be a BouncingThingsConfig, a LayersConfig or a MixtureConfig, got "
                          f"{type(cfg).__name__}") from None


def config_from(kind: str, values: dict[str, Any]):
    """The config of ``kind`` (``KINDS``) from a dict of its fields (``to_dict``'s form: for a mixture, its preset
    dict); ConfigError for an unknown kind or field."""
    from flowsynth.datasets.mixture import SOURCE_KINDS, MixtureConfig, source_config

    if kind == "mixture":
        return MixtureConfig.from_dict(values)
    if kind in SOURCE_KINDS:
        return source_config(kind, values)
    raise ConfigError(f"unknown dataset kind {kind!r}; kinds: {list(KINDS)}")


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
        from flowsynth.datasets.mixture import Mixture

        return Mixture(cfg, None, outputs, seed, length, start=start, occlusion=occlusion, device=device,
                       threads=threads)
    refuse_scene_options(occlusion, device, threads)
    return Layers(cfg, outputs, seed, length, start=start)
