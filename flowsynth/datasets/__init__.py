"""Datasets: ``BouncingThings`` (3D scenes) and ``Layers`` (2D layers) stream samples, ``Mixture`` mixes their configs
(``MixtureConfig``: a preset file), ``DeviceBatches`` renders batches on a device, ``FlowPairs`` gives torchvision's
tuples, ``loader`` workers survive CUDA; ``Exported`` and ``Shards`` read what ``flowsynth export`` wrote."""

from flowsynth.datasets.bouncing import BouncingThings, sample_seed
from flowsynth.datasets.device_batches import DeviceBatches
from flowsynth.datasets.flowpairs import FlowPairs
from flowsynth.datasets.kinds import KINDS, SOURCE_KINDS, config_from, config_kind, make_stream, stream_outputs
from flowsynth.datasets.layer_draws import PairDraw, draw_pair
from flowsynth.datasets.layer_render import CATEGORY_NAMES as LAYER_CATEGORIES
from flowsynth.datasets.layer_render import render_layers
from flowsynth.datasets.layers import LAYERS_OUTPUTS, Layers, LayersConfig, layers_pairs
from flowsynth.datasets.meta import ALL, ALWAYS_KEYS, META, META_OUTPUTS
from flowsynth.datasets.mixture import Mixture, MixtureConfig  # registers the mixture kind (kinds.register_kind)
from flowsynth.datasets.workers import loader

__all__ = ["ALL", "ALWAYS_KEYS", "KINDS", "LAYERS_OUTPUTS", "LAYER_CATEGORIES", "META", "META_OUTPUTS", "SOURCE_KINDS",
           "BouncingThings", "DeviceBatches", "Exported", "FlowPairs", "Layers", "LayersConfig", "Mixture",
           "MixtureConfig", "PairDraw", "Shards", "config_from", "config_kind", "draw_pair", "layers_pairs", "loader",
           "make_stream", "render_layers", "sample_seed", "stream_outputs"]


def __getattr__(name: str):
    if name == "Exported":
        from flowsynth.datasets.exported import Exported

        return Exported
    if name == "Shards":
        from flowsynth.datasets.shards import Shards

        return Shards
    raise AttributeError(f"module 'flowsynth.datasets' has no attribute {name!r}")
