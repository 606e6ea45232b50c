"""The kinds of generated dataset, by name: ``"bouncing"`` (``BouncingThingsConfig`` -> ``BouncingThings``) and
``"layers"`` (``LayersConfig`` -> ``Layers``). What export, statistics, previews and ``Mixture`` presets use to take
either kind the same way: ``config_kind``, ``config_from``, ``make_stream``, ``stream_outputs``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.datasets.layers import Layers, LayersConfig, layer_outputs
from flowsynth.errors import ConfigError

__all__ = ["KINDS", "config_from", "config_kind", "make_stream", "stream_outputs"]

KINDS = ("bouncing", "layers")
"""Names of the dataset kinds."""


def config_kind(cfg) -> str:
    """``"bouncing"`` for a ``BouncingThingsConfig``, ``"layers"`` for a ``LayersConfig``; ConfigError otherwise."""
    from flowsynth.scene import BouncingThingsConfig

    if isinstance(cfg, BouncingThingsConfig):
        return "bouncing"
    if isinstance(cfg, LayersConfig):
        return "layers"
    raise ConfigError(f"a dataset config must be a BouncingThingsConfig or a LayersConfig, got {type(cfg).__name__}")


def config_from(kind: str, values: dict[str, Any]):
    """The config of ``kind`` (``KINDS``) from a dict of its fields (``to_dict``'s form; lists become tuples for a
    BouncingThingsConfig); ConfigError for an unknown kind or field."""
    from flowsynth.scene import BouncingThingsConfig

    if kind == "bouncing":
        return BouncingThingsConfig.from_dict({k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})
    if kind == "layers":
        return LayersConfig.from_dict(dict(values))
    raise ConfigError(f"unknown dataset kind {kind!r}; kinds: {list(KINDS)}")


def stream_outputs(cfg, outputs: Sequence[str], *, drop_unknown: bool = False) -> tuple[str, ...]:
    """The output keys a stream of ``cfg`` makes for ``outputs``: ``flowsynth.plan.make_plan``'s for BouncingThings
    (aliases and frame gaps expanded), ``layer_outputs``' for Layers (``drop_unknown``: leave out what Layers does
    not give, for a layout's default set). ConfigError for keys the kind does not give."""
    if config_kind(cfg) == "layers":
        return layer_outputs(outputs, drop_unknown=drop_unknown)
    from flowsynth.plan import make_plan

    return make_plan(outputs, flow_gaps=cfg.flow_gaps, stereo_baseline=cfg.stereo_baseline).outputs


def make_stream(cfg, outputs: Sequence[str], seed: int = 0, length: int | None = None, *, start: int = 0,
                occlusion: str = "exact", device: str = "cpu", threads: int | None = None
                ) -> BouncingThings | Layers:
    """``BouncingThings`` or ``Layers`` of ``cfg``'s kind. ``occlusion``, ``device`` and ``threads`` are
    BouncingThings' (a Layers stream renders with torch on the CPU, its occlusion exact from the layer order:
    ConfigError for ``occlusion="depth"`` or another device there)."""
    if config_kind(cfg) == "bouncing":
        return BouncingThings(cfg, outputs, seed, length, start=start, occlusion=occlusion, device=device,
                              threads=threads)
    if occlusion != "exact":
        raise ConfigError(f"a Layers stream's occlusion is exact, from the layer order; occlusion={occlusion!r} is "
                          "BouncingThings'")
    if device != "cpu":
        raise ConfigError(f"a Layers stream renders on the CPU with torch; device={device!r} is BouncingThings'")
    return Layers(cfg, outputs, seed, length, start=start)
