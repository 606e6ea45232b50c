"""Export layouts as plug-ins: one :class:`Layout` subclass per module of this package, found by name.

Every module here is imported on the first :func:`get` / :func:`names` call, and each registers its
layout with :func:`register`; adding a layout is adding one module (and its test). Built-in layouts:

- ``native``: one folder per sample, every output lossless (:mod:`flowsynth.io.sampleio`);
- ``flyingchairs``: ``FlyingChairs/data/NNNNN_img1.ppm`` ... for ``torchvision.datasets.FlyingChairs``;
- ``kitti``: ``KittiFlow/training/image_2`` + ``flow_occ`` for ``torchvision.datasets.KittiFlow``;
- ``sintel``: ``Sintel/training/clean`` + ``flow`` + ``occlusions`` for ``torchvision.datasets.Sintel``;
- ``flyingthings3d``: FlyingThings3D's "subset" tree, stereo (PFM disparity, disparity change) + flow;
- ``webdataset``: tar shards ``shard-NNNNNN.tar`` of many samples each, for ``webdataset`` and Ray Data.
"""

from __future__ import annotations

import importlib
import pkgutil

from flowsynth.errors import ConfigError
from flowsynth.io.layouts.base import EXR_COMPRESSIONS, Layout

__all__ = ["EXR_COMPRESSIONS", "Layout", "get", "names", "register"]

_REGISTRY: dict[str, type[Layout]] = {}
_NOT_PLUGINS = ("base",)


def register(cls: type[Layout]) -> type[Layout]:
    """Class decorator: make ``cls`` available as ``get(cls.name)``."""
    if cls.name in _REGISTRY and _REGISTRY[cls.name] is not cls:
        raise ValueError(f"two export layouts are named {cls.name!r}: {_REGISTRY[cls.name]} and {cls}")
    _REGISTRY[cls.name] = cls
    return cls


def _discover() -> None:
    for mod in pkgutil.iter_modules(__path__):
        if mod.name not in _NOT_PLUGINS and not mod.name.startswith("_"):
            importlib.import_module(f"{__name__}.{mod.name}")


def names() -> tuple[str, ...]:
    """Registered layout names, ``native`` first, the others sorted."""
    _discover()
    return tuple(sorted(_REGISTRY, key=lambda n: (n != "native", n)))


def get(name: str, **options) -> Layout:
    """A layout instance by name.

    Args:
        name: one of :func:`names`.
        options: keyword arguments of :class:`Layout` (``exr_compression``).

    Raises:
        ConfigError: unknown name (the message lists the known ones) or a bad option.
    """
    _discover()
    if name not in _REGISTRY:
        raise ConfigError(f"unknown layout {name!r}; choose one of {', '.join(names())}")
    return _REGISTRY[name](**options)
