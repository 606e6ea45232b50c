"""Middlebury ``.flo`` optical-flow files (FlyingChairs, Sintel, MPI tools, ``cv2.readOpticalFlow``).

Layout, all little-endian::

    float32  magic = 202021.25   (the bytes spell "PIEH")
    int32    width W
    int32    height H
    float32  u0, v0, u1, v1, ...  H*W interleaved (dx, dy) pairs, row-major from the top-left pixel

flowsynth arrays are channels-first: flow (2, H, W) float32 [px], channel 0 = dx (u, to the right),
channel 1 = dy (v, downwards). The format carries no validity mask; invalid pixels keep whatever
value the array holds (flowsynth writes its flow as computed, see ``valid_fw``).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from flowsynth.errors import ExportError, ShapeError
from flowsynth.io.atomic import atomic_write_bytes

__all__ = ["FLO_MAGIC", "MIDDLEBURY_FILES", "UNKNOWN_FLOW", "read_flo", "read_middlebury", "write_flo"]

FLO_MAGIC = np.float32(202021.25)
"""Magic number at the start of a ``.flo`` file."""

_HEADER_BYTES = 12


def write_flo(path: str | os.PathLike[str], flow: Any) -> None:
    """Write a (2, H, W) flow field as a Middlebury ``.flo`` file.

    Args:
        path: destination file; written atomically.
        flow: (2, H, W) floating array (numpy, or a CPU torch tensor), (dx, dy) [px]. float32 values
            round-trip bit-exactly; other float dtypes are converted to float32. May be
            non-contiguous.

    Raises:
        ShapeError: wrong shape or a non-float dtype.
        ExportError: the file cannot be written.
    """
    f = np.asarray(flow)
    if f.ndim != 3 or f.shape[0] != 2 or f.shape[1] == 0 or f.shape[2] == 0:
        raise ShapeError(f"write_flo expects flow of shape (2, H, W) with H, W > 0, got {f.shape}")
    if not np.issubdtype(f.dtype, np.floating):
        raise ShapeError(f"write_flo expects a float array, got dtype {f.dtype}")
    _, h, w = f.shape
    header = FLO_MAGIC.astype("<f4").tobytes() + np.array([w, h], dtype="<i4").tobytes()
    # (2, H, W) -> (H, W, 2): tobytes() emits C order whatever the memory layout.
    body = f.transpose(1, 2, 0).astype("<f4").tobytes()
    atomic_write_bytes(path, header + body)


def read_flo(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a Middlebury ``.flo`` file.

    Returns:
        (2, H, W) float32 array, (dx, dy) [px], C-contiguous.

    Raises:
        ExportError: the magic number is wrong, the size in the header is not positive, or the
            file length does not match ``12 + 8 * W * H`` bytes.
        FileNotFoundError: the file does not exist.
    """
    with open(path, "rb") as fh:
        data = fh.read()
    if len(data) < _HEADER_BYTES:
        raise ExportError(f"{path} is not a .flo file: {len(data)} bytes, shorter than the 12-byte header")
    magic = np.frombuffer(data, dtype="<f4", count=1)[0]
    if magic != FLO_MAGIC:
        raise ExportError(
            f"{path} is not a .flo file: magic number {magic!r}, expected 202021.25 (bytes 'PIEH')"
        )
    w, h = (int(x) for x in np.frombuffer(data, dtype="<i4", count=2, offset=4))
    if w <= 0 or h <= 0:
        raise ExportError(f"{path}: invalid .flo size {w} x {h} in the header")
    expected = _HEADER_BYTES + 8 * w * h
    if len(data) != expected:
        raise ExportError(
            f"{path}: .flo header says {w} x {h} ({expected} bytes) but the file has {len(data)} bytes"
        )
    uv = np.frombuffer(data, dtype="<f4", offset=_HEADER_BYTES).reshape(h, w, 2)
    return np.ascontiguousarray(uv.transpose(2, 0, 1), dtype=np.float32)


MIDDLEBURY_FILES = ("frame10.png", "frame11.png", "flow10.flo")
"""A Middlebury flow pair's files inside its folder NAME/ (``other-color-twoframes`` and ``other-gt-flow``)."""

UNKNOWN_FLOW = 1e9
"""A ``.flo`` component above this magnitude marks unknown flow (Middlebury's convention)."""


def read_middlebury(
    root: str | os.PathLike[str], names: tuple[str, ...] | None = None
) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Read the flow pairs of a folder in Middlebury's layout: every NAME/ holding ``MIDDLEBURY_FILES`` (frame 1,
    frame 2 and the ground truth), as its archives unpack; other folders are skipped.

    Args:
        root: the folder.
        names: only these pairs (missing ones skipped); None: every pair, sorted by name.

    Returns:
        [(name, img1, img2, flow, known)]: images (3, H, W) float32 in [0, 1], flow (2, H, W) float32 [px] with 0
        where unknown, known (H, W) bool (both components at most ``UNKNOWN_FLOW`` in magnitude).

    Raises:
        FileNotFoundError: ``root`` is not a folder.
    """
    from flowsynth.io.png import read_rgb_png

    base = os.fspath(root)
    if not os.path.isdir(base):
        raise FileNotFoundError(f"{base}: no such folder (Middlebury layout: NAME/{', '.join(MIDDLEBURY_FILES)})")
    found = sorted(d for d in os.listdir(base) if os.path.isdir(os.path.join(base, d)))
    out = []
    for name in found if names is None else [n for n in names if n in found]:
        files = [os.path.join(base, name, f) for f in MIDDLEBURY_FILES]
        if not all(os.path.isfile(f) for f in files):
            continue
        flow = read_flo(files[2])
        known = (np.abs(flow) <= UNKNOWN_FLOW).all(0)
        out.append((name, read_rgb_png(files[0]), read_rgb_png(files[1]),
                    np.where(known[None], flow, np.float32(0)).astype(np.float32), known))
    return out
