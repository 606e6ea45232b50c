"""Datasets: ``BouncingThings`` streams generated samples, ``FlowPairs`` as torchvision's optical-flow tuples and
``Mixture`` from several configs by weights or a curriculum; ``Exported`` reads a folder ``flowsynth export`` wrote,
``Shards`` streams the shards of a ``webdataset`` export (shuffled, split by worker and rank). ``loader`` is a
DataLoader whose workers survive CUDA (forkserver, not fork)."""

from flowsynth.datasets.bouncing import BouncingThings, sample_seed
from flowsynth.datasets.device_batches import DeviceBatches
from flowsynth.datasets.flowpairs import FlowPairs
from flowsynth.datasets.loader import loader

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
