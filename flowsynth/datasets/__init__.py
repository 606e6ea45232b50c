"""Datasets: ``BouncingThings`` streams generated samples; ``FlowPairs`` adapts them to torchvision's
optical-flow tuples; ``Exported`` reads a folder written by ``flowsynth export``; ``Shards`` streams the
shards of a ``webdataset`` export (shuffled, split by worker and rank); ``Mixture`` streams samples of several
configs (presets) by reproducible weights or a curriculum."""

from flowsynth.datasets.bouncing import BouncingThings, sample_seed
from flowsynth.datasets.flowpairs import FlowPairs

__all__ = ["BouncingThings", "Exported", "FlowPairs", "Mixture", "Shards", "sample_seed"]


def __getattr__(name: str):
    if name == "Exported":
        from flowsynth.datasets.exported import Exported

        return Exported
    if name == "Mixture":
        from flowsynth.datasets.mixture import Mixture

        return Mixture
    if name == "Shards":
        from flowsynth.datasets.shards import Shards

        return Shards
    raise AttributeError(f"module 'flowsynth.datasets' has no attribute {name!r}")
