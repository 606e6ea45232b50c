"""OpenEXR files: named float32 channels, losslessly compressed (ZIP by default), bit-exact round trip.

Uses the ``OpenEXR`` Python package (3.x API: ``OpenEXR.File(header, channels)``). Three traps of that
API are handled here:

- a non-contiguous array (a slice, a transpose) is written silently wrong (openexr #1929), so every
  channel is copied to a C-contiguous 2-D array first;
- an (H, W, 2) or (H, W, 3) array is stored as R/G/B channels with garbage, so only 2-D (H, W)
  channels are accepted;
- ``OpenEXR.File`` replaces the arrays in the dict it is given by ``Channel`` objects, so a private
  dict is passed and the caller's stays intact.

Channel names used by flowsynth for its outputs (:data:`CHANNEL_NAMES`; a layer prefix with ``.``
is the EXR convention that viewers such as ``exrheader`` and Nuke group by):

============  ===========================  =====================================================
output        channels                     meaning
============  ===========================  =====================================================
depth         ``Z``                        planar z [m], 0 = no hit
distance      ``D``                        ray length [m], 0 = no hit
flow          ``flow.x``, ``flow.y``       (dx, dy) [px] (flow_fw and flow_bw go in separate files)
normals       ``N.X``, ``N.Y``, ``N.Z``    unit normal, camera frame, 0 = no hit
position      ``P.X``, ``P.Y``, ``P.Z``    world point [m], 0 = no hit
scene_flow    ``SF.X``, ``SF.Y``, ``SF.Z``  3D motion [m], source camera frame, 0 = no hit
disparity     ``disparity``                 stereo disparity or its change [px], 0 = no hit
============  ===========================  =====================================================
"""

from __future__ import annotations

import errno
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import OpenEXR

from flowsynth.errors import ExportError, ShapeError, StorageError
from flowsynth.io.atomic import atomic_path

__all__ = ["CHANNEL_NAMES", "COMPRESSIONS", "read_exr", "read_tensor_exr", "write_exr", "write_tensor_exr"]

CHANNEL_NAMES: dict[str, tuple[str, ...]] = {
    "depth": ("Z",),
    "distance": ("D",),
    "flow": ("flow.x", "flow.y"),
    "normals": ("N.X", "N.Y", "N.Z"),
    "position": ("P.X", "P.Y", "P.Z"),
    "scene_flow": ("SF.X", "SF.Y", "SF.Z"),
    "disparity": ("disparity",),
}
"""EXR channel names per flowsynth output, in channel order of the (C, H, W) tensor."""

COMPRESSIONS: dict[str, Any] = {
    "none": OpenEXR.NO_COMPRESSION,
    "rle": OpenEXR.RLE_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
}
"""Lossless compressions by name (float32 channels round-trip bit-exactly with each). ZIP is the default:
on a default sample's depth and flow (benchmarks/speed/export.py) PIZ is 1.5 % smaller but takes 3.7x the
write time, ZIPS and RLE are larger. Flow barely compresses with any of them (0.99x raw): its float32
mantissas are noise (docs/decisions/0011-exr-zip-default.md)."""

_NATIVE = (np.float32, np.float16, np.uint32)  # pixel types EXR stores as-is


def _prepare_channel(name: str, array: Any, shape: tuple[int, int] | None) -> np.ndarray:
    a = np.asarray(array)
    if a.ndim != 2:
        raise ShapeError(
            f"EXR channel {name!r} must be a 2-D (H, W) array, got shape {a.shape}; "
            "split multi-channel arrays into one named channel each (e.g. write_tensor_exr)"
        )
    if shape is not None and a.shape != shape:
        raise ShapeError(f"EXR channel {name!r} has shape {a.shape}, other channels have {shape}")
    if a.dtype.type not in _NATIVE:
        if not np.issubdtype(a.dtype, np.floating):
            raise ShapeError(f"EXR channel {name!r} has dtype {a.dtype}; use float32 (or float16 / uint32)")
        a = a.astype(np.float32)
    return np.ascontiguousarray(a)


def write_exr(path: str | os.PathLike[str], channels: Mapping[str, np.ndarray], *, compression: str = "zip") -> None:
    """Write named 2-D channels to a single-part scanline EXR, losslessly compressed.

    Args:
        path: destination file (``.exr``); written atomically.
        channels: name -> (H, W) array, all the same shape. float32, float16 and uint32 are stored
            as-is (float32 round-trips bit-exactly, NaN and inf included); other floating dtypes
            are converted to float32. Arrays may be non-contiguous; the caller's dict is not
            modified.
        compression: a key of :data:`COMPRESSIONS`.

    Raises:
        ShapeError: no channels, a channel that is not 2-D, shapes differ, or a non-float dtype.
        ValueError: unknown ``compression``.
        StorageError: the file system refused the write (disk full, permissions); ``errno`` set.
        ExportError: the file cannot be written.
    """
    if compression not in COMPRESSIONS:
        raise ValueError(f"EXR compression must be one of {sorted(COMPRESSIONS)}, got {compression!r}")
    if not channels:
        raise ShapeError("write_exr needs at least one channel")
    shape: tuple[int, int] | None = None
    prepared: dict[str, np.ndarray] = {}
    for name, array in channels.items():
        prepared[name] = _prepare_channel(name, array, shape)
        shape = prepared[name].shape
    header = {"compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        try:
            with OpenEXR.File(header, prepared) as exr:
                exr.write(str(tmp))
        except RuntimeError as exc:
            # The channels were validated above, so OpenEXR failing now is the file system (disk full,
            # permissions): a StorageError (CLI exit 3), with the errno recovered from OpenEXR's message.
            raise StorageError(f"OpenEXR could not write {path}: {exc}", _errno_in(str(exc))) from exc
        except (ValueError, TypeError) as exc:
            raise ExportError(f"OpenEXR could not write {path}: {exc}") from exc


def _errno_in(message: str) -> int | None:
    """The OS error number whose text (``os.strerror``) appears in ``message``, or None."""
    for code in (errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS, errno.EIO, errno.ENOENT):
        if os.strerror(code) in message:
            return code
    return None


def read_exr(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read every channel of a single-part EXR file.

    Returns:
        name -> (H, W) array in the stored pixel type (float32, float16 or uint32). Channels are
        never grouped into RGB(A) arrays.

    Raises:
        ExportError: the file is missing or not a readable EXR file.
    """
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            return {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except (RuntimeError, ValueError, OSError) as exc:
        raise ExportError(f"cannot read EXR file {path}: {exc}") from exc


def write_tensor_exr(path: str | os.PathLike[str], array: Any, names: Sequence[str], *,
                     compression: str = "zip") -> None:
    """Write a channels-first array as one EXR channel per plane.

    Args:
        path: destination ``.exr`` file; written atomically.
        array: (C, H, W) float array (numpy, or a CPU torch tensor), e.g. one frame of ``normals``.
        names: C channel names, e.g. ``CHANNEL_NAMES["normals"]``.
        compression: a key of :data:`COMPRESSIONS`.

    Raises:
        ShapeError: ``array`` is not 3-D or ``len(names) != C``.
    """
    a = np.asarray(array)
    if a.ndim != 3 or a.shape[0] != len(names):
        raise ShapeError(
            f"write_tensor_exr expects a (C, H, W) array with C = len(names) = {len(names)}, "
            f"got shape {a.shape}"
        )
    write_exr(path, {name: a[c] for c, name in enumerate(names)}, compression=compression)


def read_tensor_exr(path: str | os.PathLike[str], names: Sequence[str]) -> np.ndarray:
    """Read the channels ``names`` of an EXR file, stacked channels-first.

    Returns:
        (C, H, W) array, C = ``len(names)``, in the stored pixel type (float32 for flowsynth files).

    Raises:
        ExportError: the file cannot be read or lacks one of ``names`` (the message lists those it has).
    """
    channels = read_exr(path)
    missing = [n for n in names if n not in channels]
    if missing:
        raise ExportError(f"EXR file {path} has no channel(s) {missing}; it has {sorted(channels)}")
    return np.stack([channels[n] for n in names])
