"""Warp kernels, one family per module (``raycast``, ``blas``, ``reproject``, ``shade``, ``texture``, ``tonemap``,
``dof``; ``specialise`` builds their variants), each imported on first use, so ``import flowsynth`` compiles nothing.
Only Warp and numpy here, and of flowsynth only the fork guard (``flowsynth.processes``)."""
from __future__ import annotations

import functools
import os
import sys
import tempfile

from flowsynth.processes import check_not_forked_from_cuda

# The kernel families are exported by name and imported where they are used (``from flowsynth.kernels.raycast import
# primary_kernel``, inside the launcher): importing one imports Warp.
__all__ = ["RENDER_MODES", "blas", "dof", "raycast", "reproject", "shade", "specialise", "texture", "tonemap",
           "wp_runtime"]

# The shading models that kernels/shade.py implements (docs/rendering.md); flowsynth.plan re-exports them.
RENDER_MODES = ("flat", "direct", "path")

# Printed by Warp's C library (fprintf, not Python logging) on machines without an NVIDIA driver.
# flowsynth runs Warp on the CPU, so the notice is not the user's business.
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def wp_runtime():
    """The ``warp`` module, imported and initialised once per process (quietly): where flowsynth reaches Warp.

    Raises ``ForkError`` (every call, before Warp is touched) in a process forked from one that had initialised CUDA,
    where Warp cannot run (``flowsynth.processes.check_not_forked_from_cuda``). Warp's own "no CUDA driver" notice is
    dropped; anything else Warp prints while initialising reaches stderr unchanged.
    """
    check_not_forked_from_cuda()
    return _initialised_warp()


@functools.cache
def _initialised_warp():
    """Import and initialise Warp once per process (quietly); returns the ``warp`` module."""
    import warp as wp

    if hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True
    _init_without_driver_notice(wp)
    return wp


def _init_without_driver_notice(wp) -> None:
    """``wp.init()`` with file descriptor 2 captured, then replayed without the no-driver line."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable stderr: nothing to keep clean
        wp.init()
        return
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        text = captured.read().decode(errors="replace")
    kept = "".join(line for line in text.splitlines(keepends=True) if _NO_DRIVER not in line)
    if kept:
        sys.stderr.write(kept)
        sys.stderr.flush()
