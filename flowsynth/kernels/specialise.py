"""One cache of Warp kernels specialised per combination of flags (``wp.static`` branches compiled out).

A kernel builder takes flags (which outputs to write, a render mode, a lens) and returns a kernel whose unrequested
branches are compiled out. ``specialised_builder`` makes such a builder build each combination once per process::

    @specialised_builder
    def primary_kernel(want_normals: bool, want_points: bool, lens: bool = False):
        @wp.kernel(enable_backward=False, module="unique")
        def primary(...): ...
        return primary

The kernels live in one dict, ``KERNELS``, keyed by (builder, flags); flowsynth.caches registers it as
``kernels.specialised`` (this package imports nothing of flowsynth). Clearing it loses nothing but a dict lookup:
Warp keeps a ``module="unique"`` kernel per content hash, so a rebuilt kernel is the same object.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Hashable
from typing import Any, TypeVar

__all__ = ["KERNELS", "specialised", "specialised_builder"]

F = TypeVar("F", bound=Callable[..., Any])

KERNELS: dict = {}  # (builder name, flags) -> kernel; registered in flowsynth.caches as kernels.specialised


def specialised(name: str, builder: Callable[..., Any], key: tuple[Hashable, ...]) -> Any:
    """``builder(*key)``, built once per process per (``name``, ``key``)."""
    k = (name, key)
    kernel = KERNELS.get(k)
    if kernel is None:
        kernel = KERNELS[k] = builder(*key)
    return kernel


def specialised_builder(builder: F) -> F:
    """A kernel builder that builds each combination of its arguments once (``specialised``, keyed by the builder's
    qualified name and its arguments, defaults filled in, so ``f(True)`` and ``f(True, False)`` share a kernel when
    False is the default)."""
    name = f"{builder.__module__}.{builder.__qualname__}"
    sig = inspect.signature(builder)

    @functools.wraps(builder)
    def get(*args, **kwargs):
        bound = sig.bind(*args, **kwargs)
        bound.apply_defaults()
        return specialised(name, builder, tuple(bound.arguments.values()))

    return get  # type: ignore[return-value]
