"""Datasets: ``BouncingThings`` streams generated samples; ``FlowPairs`` adapts them to torchvision's
optical-flow tuples; ``Exported`` reads a folder written by ``flowsynth export``."""

from flowsynth.datasets.bouncing import BouncingThings, sample_seed
from flowsynth.datasets.flowpairs import FlowPairs

__all__ = ["BouncingThings", "Exported", "FlowPairs", "sample_seed"]


def __getattr__(name: str):
    if name == "Exported":
        from flowsynth.datasets.exported import Exported

        return Exported
    raise AttributeError(f"module 'flowsynth.datasets' has no attribute {name!r}")
