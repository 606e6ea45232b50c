"""PFM (portable float map), the format of FlyingThings3D's disparity and disparity change.

A file is the ASCII header ``Pf`` (one channel) or ``PF`` (three), ``W H``, then a scale whose sign gives
the byte order (negative: little-endian; flowsynth writes -1.0), then float32 rows from the BOTTOM row of
the image to the top. Read by OpenCV (``cv2.imread(path, cv2.IMREAD_UNCHANGED)``) and torchvision's
stereo datasets; values round-trip bit-exactly.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np

from flowsynth.errors import ExportError
from flowsynth.io.atomic import atomic_write_bytes

__all__ = ["read_pfm", "write_pfm"]


def write_pfm(path: str | Path, image: np.ndarray) -> None:
    """Write an (H, W) or (3, H, W) float array as float32 PFM (little-endian), atomically."""
    a = np.asarray(image, np.float32)
    if a.ndim == 3 and a.shape[0] == 3:
        a, kind = a.transpose(1, 2, 0), b"PF"
    elif a.ndim == 2:
        kind = b"Pf"
    else:
        raise ExportError(f"PFM holds (H, W) or (3, H, W) images, got shape {a.shape}")
    buf = io.BytesIO()
    buf.write(kind + b"\n%d %d\n-1.0\n" % (a.shape[1], a.shape[0]))
    buf.write(np.ascontiguousarray(a[::-1], dtype="<f4").tobytes())
    atomic_write_bytes(path, buf.getvalue())


def read_pfm(path: str | Path) -> np.ndarray:
    """Read a PFM file: (H, W) float32 for ``Pf``, (3, H, W) for ``PF``."""
    data = Path(path).read_bytes()
    m = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+(\S+)\s", data)
    if m is None:
        raise ExportError(f"{path} is not a PFM file")
    kind, w, h, scale = m[1], int(m[2]), int(m[3]), float(m[4])
    c = 3 if kind == b"PF" else 1
    a = np.frombuffer(data, "<f4" if scale < 0 else ">f4", count=w * h * c, offset=m.end())
    a = a.reshape(h, w, c)[::-1].astype(np.float32)
    return a[..., 0].copy() if c == 1 else np.ascontiguousarray(a.transpose(2, 0, 1))
