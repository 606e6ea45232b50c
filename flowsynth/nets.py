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


def raft_small(weights=None):
    """torchvision's ``raft_small(weights=weights)`` (0.99 M parameters; random weights for ``None``), called as
    ``net(img1, img2, num_flow_updates=N)`` on (B, 3, H, W) images in [-1, 1] with H, W multiples of 8 and at least
    128, returning the list of its N (B, 2, H, W) flow estimates [px].

    A torchvision wheel built against another torch lacks its C++ operators; its models need none of them, so the
    module that registers them (``torchvision._meta_registrations``) is stood in for by an empty one before the
    import. Raises DependencyError when torchvision is not installed.
    """
    sys.modules.setdefault("torchvision._meta_registrations", types.ModuleType("torchvision._meta_registrations"))
    try:
        from torchvision.models.optical_flow import raft_small as build
    except ImportError as e:
        raise DependencyError(f"RAFT-small needs torchvision, which is not installed ({e}): {INSTALL}") from e
    return build(weights=weights)
