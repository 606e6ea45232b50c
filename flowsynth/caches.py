"""One registry of flowsynth's per-process caches, so that ``fs.clear_caches()`` empties them all.

flowsynth keeps what it derives from an asset or a file once per process: scaled meshes and their cleaned copies,
hulls, BVH trees and culling planes, loaded textures, pixel rays. Each such cache is registered here by the module
that defines it, under a dotted name (``"accel.hulls"``), where it is defined::

    _HULLS: OrderedDict = register("accel.hulls", OrderedDict())

    @register("assets.get_asset")
    @functools.lru_cache(maxsize=1024)
    def get_asset(name, size): ...

A cache is anything with ``clear()`` (a dict, ``OrderedDict``, ``weakref.WeakKeyDictionary``) or ``cache_clear()``
(``functools.cache`` / ``lru_cache``). tests/test_caches.py finds every module-level cache of the package and fails
on one that is not registered here (or named there as no cache: compiled kernels, constants computed once).

Caches keyed by a mesh object trust that the mesh does not change: ``flowsynth.scene.meshes.freeze`` makes its vertex
and face arrays read-only before it enters one, so an in-place edit raises instead of reusing a stale tree.

This module imports only ``flowsynth.errors`` and ``flowsynth.kernels.specialise`` (Warp-free: the kernels package
imports nothing of flowsynth, so its one cache, the specialised kernels, is registered here): every layer may register
here (docs/architecture.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from flowsynth.errors import ConfigError
from flowsynth.kernels import specialise

__all__ = ["clear_caches", "register", "registered"]

C = TypeVar("C")

_REGISTRY: dict[str, Any] = {}  # name -> the cache object itself (not a cache: the registry)


def _clearer(cache: Any) -> Callable[[], None]:
    clear = getattr(cache, "cache_clear", None) or getattr(cache, "clear", None)
    if not callable(clear):
        raise TypeError(f"a cache needs clear() or cache_clear(), got {type(cache).__name__}")
    return clear


def register(name: str, cache: Any = None):
    """Register ``cache`` under ``name`` and return it; ``register(name)`` alone is a decorator (put it above
    ``functools.lru_cache``). Registering a name again replaces its cache (a reloaded module)."""
    if not isinstance(name, str) or not name:
        raise TypeError(f"a cache's name must be a non-empty string, got {name!r}")
    if cache is None:
        return lambda c: register(name, c)
    _clearer(cache)  # fail here, not in clear_caches, on an object that cannot be cleared
    _REGISTRY[name] = cache
    return cache


def registered() -> dict[str, Any]:
    """{name: cache} of every registered cache (of the modules imported so far; the others are empty)."""
    return dict(_REGISTRY)


def clear_caches(*names: str) -> list[str]:
    """Empty the named caches, or every registered cache when no name is given; returns the names cleared.

    Nothing is lost but time: each cache refills on its next use, and results stay the same. Use it to free
    memory in a long-lived process, or to time cold work. Raises ConfigError for a name never registered.
    """
    unknown = [n for n in names if n not in _REGISTRY]
    if unknown:
        raise ConfigError(f"no cache named {unknown}; registered: {sorted(_REGISTRY)}")
    chosen = list(names) if names else sorted(_REGISTRY)
    for n in chosen:
        _clearer(_REGISTRY[n])()
    return chosen


# the kernels' one cache (flowsynth/kernels/specialise.py): Warp kernels per combination of flags
register("kernels.specialised", specialise.KERNELS)
