"""torchvision's optical-flow dataset classes: the readers nobody here wrote that prove the export layouts.

torchvision is a test dependency only, installed by scripts/setup.sh with ``--no-deps`` (its wheel would
otherwise pull a CUDA torch). That wheel's C++ operators do not match the CPU torch, and importing
``torchvision._meta_registrations`` fails on them ("operator torchvision::nms does not exist"); the
dataset classes need none of them, so an empty module stands in for it.

For the same reason its PNG decoder (``torchvision.io.decode_png``, C++) cannot load, and KittiFlow reads
its 16-bit flow PNGs with it. Where it is missing, OpenCV's decoder stands in (another reader nobody here
wrote); torchvision's own code still finds the files, pairs them and converts the values.
"""

import sys
import types

import cv2
import numpy as np
import torch


def _read_file(path: str) -> str:
    return path


def _decode_png(path: str) -> torch.Tensor:
    """(C, H, W) in file order (R, G, B), as torchvision.io.decode_png returns it, via OpenCV (B, G, R)."""
    bgr = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    return torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1].transpose(2, 0, 1)).astype(np.int32))


def datasets():
    """The ``torchvision.datasets`` module, its PNG decoding done by OpenCV where torchvision's is missing."""
    sys.modules.setdefault("torchvision._meta_registrations", types.ModuleType("torchvision._meta_registrations"))
    import torchvision.datasets
    from torchvision.datasets import _optical_flow
    from torchvision.io.image import _has_image_ops

    if not _has_image_ops():
        _optical_flow.read_file, _optical_flow.decode_png = _read_file, _decode_png
    return torchvision.datasets
