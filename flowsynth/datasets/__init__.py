"""Datasets: ``BouncingThings`` streams samples (``loader``: workers that survive CUDA), ``DeviceBatches`` renders
batches on a device, ``FlowPairs`` gives torchvision's tuples, ``Mixture`` mixes configs; ``Exported`` and ``Shards``
read what ``flowsynth export`` wrote (a folder; a ``webdataset``'s shards, shuffled, split by worker and rank)."""

from flowsynth.datasets.bouncing import BouncingThings, sample_seed
from flowsynth.datasets.device_batches import DeviceBatches
from flowsynth.datasets.flowpairs import FlowPairs
from flowsynth.datasets.workers import loader

__all__ = ["BouncingThings", "DeviceBatches", "Exported", "FlowPairs", "Mixture", "Shards", "loader", "sample_seed"]


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
