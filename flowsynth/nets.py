"""torchvision's RAFT-small, built on demand: the net that ``flowsynth tune``, the learning benchmark and the tests
train. torchvision is optional (never a dependency of flowsynth): ``raft_small`` imports it when called and raises
``DependencyError`` when it is missing.
"""

from __future__ import annotations

import sys
import types

from flowsynth.errors import DependencyError

__all__ = ["raft_small"]

INSTALL = 'pip install --no-deps "torchvision==0.28.0"'  # --no-deps: its wheel would pull a CUDA torch
META = "torchvision._meta_registrations"  # the module that registers torchvision's C++ operators with torch


def raft_small(weights=None):
    """torchvision's ``raft_small(weights=weights)`` (0.99 M parameters; random weights for ``None``), called as
    ``net(img1, img2, num_flow_updates=N)`` on (B, 3, H, W) images in [-1, 1] with H, W multiples of 8 and at least
    128, returning the list of its N (B, 2, H, W) flow estimates [px].

    torchvision is imported as it is. Only where that import fails on torchvision's C++ operators
    ("operator torchvision::nms does not exist": a wheel built against another torch lacks them) are the
    half-imported torchvision modules dropped and ``torchvision._meta_registrations`` stood in for by an empty module
    before a second import: the models need none of the operators. Raises DependencyError when torchvision is not
    installed.
    """
    try:
        try:
            build = _import_raft()
        except (ImportError, RuntimeError) as e:
            if "torchvision::" not in str(e):
                raise
            for name in [n for n, m in sys.modules.items() if m is not None and n.split(".")[0] == "torchvision"]:
                del sys.modules[name]
            sys.modules[META] = types.ModuleType(META)
            build = _import_raft()
    except ImportError as e:
        raise DependencyError(f"RAFT-small needs torchvision, which is not installed ({e}): {INSTALL}") from e
    return build(weights=weights)


def _import_raft():
    from torchvision.models.optical_flow import raft_small as build

    return build
