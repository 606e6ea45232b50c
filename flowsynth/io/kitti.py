"""KITTI 2012/2015 optical-flow PNGs: 16-bit RGB, flow quantised to 1/64 px.

Encoding, as in the KITTI devkit (``io_flow.h``), channels in PNG file order R, G, B::

    R = u * 64 + 2**15      u = dx [px], representable range [-512, 511.984375]
    G = v * 64 + 2**15      v = dy [px]
    B = 1 if valid else 0

Like the devkit, invalid pixels are stored as (0, 0, 0). Unlike the devkit, which truncates, the
writer rounds to the nearest 1/64 px, so the error of a valid in-range value is at most 1/128 px;
values outside the range are clipped to it. OpenCV's ``cv2.imread(path, cv2.IMREAD_UNCHANGED)``
returns these files as B, G, R (valid, v, u).

The format is lossy (1/64 px steps, 512 px range): flowsynth's lossless flow lives in ``.flo`` or
EXR files; this writer exists for KITTI-layout exports and KITTI-trained tools.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from flowsynth.errors import ExportError, ShapeError
from flowsynth.io.atomic import atomic_write_bytes
from flowsynth.io.png import decode_png, encode_png16

__all__ = ["KITTI_FLOW_MAX", "KITTI_FLOW_MIN", "KITTI_FLOW_SCALE", "read_kitti_flow", "write_kitti_flow"]

KITTI_FLOW_SCALE = 64.0
"""Stored units per pixel of flow."""
_OFFSET = 2.0**15
KITTI_FLOW_MIN = -_OFFSET / KITTI_FLOW_SCALE
"""Smallest representable flow component [px] (-512)."""
KITTI_FLOW_MAX = (65535.0 - _OFFSET) / KITTI_FLOW_SCALE
"""Largest representable flow component [px] (511.984375)."""


def write_kitti_flow(path: str | os.PathLike[str], flow: Any, valid: Any) -> None:
    """Write flow and its validity mask as a KITTI 16-bit flow PNG.

    Args:
        path: destination ``.png``; written atomically.
        flow: (2, H, W) float array (numpy, or a CPU torch tensor), (dx, dy) [px]; clipped to
            [KITTI_FLOW_MIN, KITTI_FLOW_MAX] and rounded to 1/64 px.
        valid: (H, W) bool, e.g. ``valid_fw[t, 0]``. Pixels whose flow is NaN or inf are written
            as invalid too.

    Raises:
        ShapeError: wrong shapes or dtypes.
        ExportError: the file cannot be written.
    """
    f = np.asarray(flow)
    m = np.asarray(valid)
    if f.ndim != 3 or f.shape[0] != 2:
        raise ShapeError(f"write_kitti_flow expects flow of shape (2, H, W), got {f.shape}")
    if not np.issubdtype(f.dtype, np.floating):
        raise ShapeError(f"write_kitti_flow expects float flow, got dtype {f.dtype}")
    if m.shape != f.shape[1:] or m.dtype != np.bool_:
        raise ShapeError(
            f"write_kitti_flow expects valid as a bool (H, W) = {f.shape[1:]} array, got {m.dtype} {m.shape}"
        )
    ok = m & np.isfinite(f).all(axis=0)
    f64 = np.where(ok, f.astype(np.float64), 0.0)
    stored = np.rint(np.clip(f64 * KITTI_FLOW_SCALE + _OFFSET, 0.0, 65535.0)).astype(np.uint16)
    image = np.zeros((*ok.shape, 3), np.uint16)
    image[..., 0] = np.where(ok, stored[0], 0)
    image[..., 1] = np.where(ok, stored[1], 0)
    image[..., 2] = ok
    atomic_write_bytes(path, encode_png16(image))


def read_kitti_flow(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI 16-bit flow PNG.

    Returns:
        ``(flow, valid)``: flow (2, H, W) float32 (dx, dy) [px], 0 where invalid; valid (H, W) bool
        (B channel > 0).

    Raises:
        ExportError: not a 16-bit RGB PNG of a supported kind.
    """
    with open(path, "rb") as fh:
        image = decode_png(fh.read(), name=str(path))
    if image.dtype != np.uint16 or image.ndim != 3 or image.shape[2] != 3:
        raise ExportError(f"{path}: a KITTI flow PNG is 16-bit RGB, got {image.dtype} {image.shape}")
    valid = image[..., 2] > 0
    flow = (image[..., :2].astype(np.float32) - np.float32(_OFFSET)) / np.float32(KITTI_FLOW_SCALE)
    flow[~valid] = 0.0
    return np.ascontiguousarray(flow.transpose(2, 0, 1)), valid
