"""Warp kernels. Only Warp and numpy here: nothing in this package imports the torch-facing pipeline.

Modules are imported on first use, so ``import flowsynth`` compiles nothing.
"""
from __future__ import annotations

import functools

__all__ = ["RENDER_MODES", "wp_runtime"]

# The shading models that kernels/shade.py implements (docs/rendering.md); flowsynth.plan re-exports them.
RENDER_MODES = ("flat", "direct", "path")


@functools.cache
def wp_runtime():
    """Import and initialise Warp once per process (quietly); returns the ``warp`` module."""
    import warp as wp

    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True
    wp.init()
    return wp
