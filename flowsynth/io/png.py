"""PNG and PPM images: 8-bit sRGB colour, 16-bit id / mask maps, and a minimal 16-bit PNG codec.

8-bit colour PNG and binary PPM (P6, FlyingChairs' image format) go through Pillow. Pillow cannot
write 16-bit RGB PNGs and reads them back reduced to 8 bits, so 16-bit images (id maps here, KITTI
flow in :mod:`flowsynth.io.kitti`) use :func:`encode_png16` / :func:`decode_png`, a small
dependency-free codec on ``zlib`` + ``struct``:

- the encoder writes 16-bit greyscale or RGB, non-interlaced, filter type 2 ("up") on every row,
  which is vectorised and compresses smooth maps well;
- the decoder reads any non-interlaced 8- or 16-bit greyscale, grey+alpha, RGB or RGBA PNG. Rows
  with filter 0-2 (what the encoder writes) decode vectorised; filter 3-4 rows, which other
  encoders such as libpng may choose, take a slower per-byte Python loop (not benchmarked).
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from typing import Any

import numpy as np
from PIL import Image

from flowsynth.errors import ExportError, ShapeError
from flowsynth.io.atomic import atomic_write_bytes

__all__ = [
    "ZLIB_LEVEL",
    "decode_png",
    "encode_png16",
    "read_mask_png",
    "read_ppm",
    "read_rgb_png",
    "read_u16_png",
    "write_mask_png",
    "write_ppm",
    "write_rgb_png",
    "write_u16_png",
]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # PNG colour type -> samples per pixel (no palette)
_U16_MAX = 65535
# zlib level of encode_png16. benchmarks/speed/png_level.py, a 1242x375 KITTI flow map of a flowsynth sample:
# level 1 13 ms / 212 kB, level 3 19 ms / 174 kB, level 6 54 ms / 125 kB, level 9 0.37 s / 111 kB
# (docs/decisions/0010-png16-zlib-level-3.md).
ZLIB_LEVEL = 3


def _chunk(tag: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + tag + payload + struct.pack(">I", zlib.crc32(tag + payload))


def encode_png16(image: np.ndarray, *, level: int = ZLIB_LEVEL) -> bytes:
    """Encode a 16-bit greyscale (H, W) or RGB (H, W, 3) image as PNG bytes.

    Args:
        image: uint16 array, (H, W) for greyscale or (H, W, 3) with channels R, G, B.
        level: zlib compression level 0-9.
    """
    if image.dtype != np.uint16 or not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)):
        raise ShapeError(f"encode_png16 expects uint16 (H, W) or (H, W, 3), got {image.dtype} {image.shape}")
    h, w = image.shape[:2]
    if h == 0 or w == 0:
        raise ShapeError(f"cannot encode an empty image of shape {image.shape}")
    color_type = 0 if image.ndim == 2 else 2
    rows = np.ascontiguousarray(image, dtype=">u2").view(np.uint8).reshape(h, -1)
    filtered = rows.copy()
    filtered[1:] -= rows[:-1]  # filter "up": byte minus the byte above, modulo 256
    raw = np.concatenate([np.full((h, 1), 2, np.uint8), filtered], axis=1)
    ihdr = struct.pack(">IIBBBBB", w, h, 16, color_type, 0, 0, 0)
    return (
        _SIGNATURE
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), level))
        + _chunk(b"IEND", b"")
    )


def _unfilter_slow(ftype: int, line: np.ndarray, prior: np.ndarray, bpp: int) -> np.ndarray:
    """Undo filter 3 (average) or 4 (Paeth) of one row; inherently sequential along the row."""
    cur = bytearray(line.tobytes())
    up = prior.tobytes()
    for i in range(len(cur)):
        a = cur[i - bpp] if i >= bpp else 0
        b = up[i]
        if ftype == 3:
            cur[i] = (cur[i] + ((a + b) >> 1)) & 0xFF
        else:
            c = up[i - bpp] if i >= bpp else 0
            p = a + b - c
            pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
            pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            cur[i] = (cur[i] + pred) & 0xFF
    return np.frombuffer(bytes(cur), np.uint8)


def decode_png(data: bytes, *, name: str = "<bytes>") -> np.ndarray:
    """Decode a non-interlaced 8/16-bit greyscale, grey+alpha, RGB or RGBA PNG.

    Args:
        data: the file contents.
        name: used in error messages (the file path).

    Returns:
        (H, W) for greyscale, else (H, W, C) with C = 2, 3 or 4 in file order (R, G, B[, A]);
        uint8 or uint16 as stored.

    Raises:
        ExportError: not a PNG, corrupt (bad CRC, truncated data), or an unsupported variant
            (palette, bit depth below 8, interlaced).
    """
    if not data.startswith(_SIGNATURE):
        raise ExportError(f"{name} is not a PNG file")
    pos, header, idat = len(_SIGNATURE), None, []
    while pos + 8 <= len(data):
        length, tag = struct.unpack(">I4s", data[pos : pos + 8])
        payload = data[pos + 8 : pos + 8 + length]
        crc = data[pos + 8 + length : pos + 12 + length]
        if (
            len(payload) != length
            or len(crc) != 4
            or struct.unpack(">I", crc)[0] != zlib.crc32(tag + payload)
        ):
            raise ExportError(f"{name}: corrupt PNG chunk {tag!r} at byte {pos}")
        if tag == b"IHDR":
            header = struct.unpack(">IIBBBBB", payload)
        elif tag == b"IDAT":
            idat.append(payload)
        elif tag == b"IEND":
            break
        pos += 12 + length
    if header is None or not idat:
        raise ExportError(f"{name}: PNG without IHDR or IDAT chunk")
    w, h, depth, color_type, _, _, interlace = header
    if color_type not in _CHANNELS or depth not in (8, 16) or interlace != 0:
        raise ExportError(
            f"{name}: unsupported PNG (colour type {color_type}, bit depth {depth}, interlace {interlace}); "
            "only non-interlaced 8/16-bit grey, grey+alpha, RGB, RGBA are read"
        )
    channels = _CHANNELS[color_type]
    bpp = channels * depth // 8
    stride = w * bpp
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as exc:
        raise ExportError(f"{name}: corrupt PNG image data ({exc})") from exc
    if len(raw) != h * (stride + 1):
        raise ExportError(f"{name}: PNG image data has {len(raw)} bytes, expected {h * (stride + 1)}")
    rows = np.frombuffer(raw, np.uint8).reshape(h, stride + 1)
    out = np.empty((h, stride), np.uint8)
    prior = np.zeros(stride, np.uint8)
    for y in range(h):
        ftype, line = int(rows[y, 0]), rows[y, 1:]
        if ftype == 0:
            cur = line
        elif ftype == 1:
            cur = np.cumsum(line.reshape(w, bpp), axis=0, dtype=np.uint8).reshape(-1)
        elif ftype == 2:
            cur = line + prior
        elif ftype in (3, 4):
            cur = _unfilter_slow(ftype, line, prior, bpp)
        else:
            raise ExportError(f"{name}: invalid PNG filter type {ftype} in row {y}")
        out[y] = cur
        prior = out[y]
    pixels = out.view(">u2").astype(np.uint16) if depth == 16 else out
    return pixels.reshape(h, w) if channels == 1 else pixels.reshape(h, w, channels)


def _rgb_to_u8(rgb: Any, fn: str) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8, rounded to nearest, out-of-range clipped."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[0] != 3:
        raise ShapeError(f"{fn} expects rgb of shape (3, H, W), got {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise ShapeError(f"{fn} expects float rgb in [0, 1], got dtype {a.dtype}")
    if not np.isfinite(a).all():
        raise ExportError(f"{fn}: rgb contains NaN or inf, which an 8-bit image cannot store")
    return np.rint(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8).transpose(1, 2, 0)


def _save_pillow(path: str | os.PathLike[str], hwc: np.ndarray, fmt: str) -> None:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(hwc)).save(buf, format=fmt)
    atomic_write_bytes(path, buf.getvalue())


def _load_pillow(path: str | os.PathLike[str]) -> np.ndarray:
    with Image.open(path) as im:
        hwc = np.asarray(im.convert("RGB"), dtype=np.float32)
    return np.ascontiguousarray(hwc.transpose(2, 0, 1)) / np.float32(255.0)


def write_rgb_png(path: str | os.PathLike[str], rgb: Any) -> None:
    """Write sRGB colour as an 8-bit RGB PNG.

    Args:
        path: destination file; written atomically.
        rgb: (3, H, W) float in [0, 1] (numpy, or a CPU torch tensor); stored as round(255 * x),
            values outside [0, 1] clipped.

    Raises:
        ShapeError: wrong shape or non-float dtype.
        ExportError: NaN / inf values, or the file cannot be written.
    """
    _save_pillow(path, _rgb_to_u8(rgb, "write_rgb_png"), "PNG")


def read_rgb_png(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a colour image (PNG, or anything Pillow opens) as (3, H, W) float32 in [0, 1]."""
    return _load_pillow(path)


def write_ppm(path: str | os.PathLike[str], rgb: Any) -> None:
    """Write sRGB colour as an 8-bit binary PPM (P6), FlyingChairs' image format.

    Args and errors as :func:`write_rgb_png`.
    """
    _save_pillow(path, _rgb_to_u8(rgb, "write_ppm"), "PPM")


def read_ppm(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a binary PPM as (3, H, W) float32 in [0, 1]."""
    return _load_pillow(path)


def write_mask_png(path: str | os.PathLike[str], mask: Any) -> None:
    """Write a mask as an 8-bit greyscale PNG, 255 = True, 0 = False (Sintel's occlusion maps).

    Args:
        path: destination file; written atomically.
        mask: (H, W) bool array (numpy, or a CPU torch tensor).

    Raises:
        ShapeError: not a 2-D bool array.
    """
    a = np.asarray(mask)
    if a.ndim != 2 or a.dtype != np.bool_:
        raise ShapeError(f"write_mask_png expects an (H, W) bool array, got {a.dtype} {a.shape}")
    _save_pillow(path, a.astype(np.uint8) * np.uint8(255), "PNG")


def read_mask_png(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a greyscale mask PNG as (H, W) bool: True where the value is above half of the range."""
    with Image.open(path) as im:
        a = np.asarray(im)
    if a.ndim != 2:
        raise ExportError(f"{path}: expected a greyscale mask PNG, got shape {a.shape}")
    return a > (np.iinfo(a.dtype).max // 2 if np.issubdtype(a.dtype, np.integer) else 0.5)


def write_u16_png(path: str | os.PathLike[str], values: Any) -> None:
    """Write an id map or mask as a 16-bit greyscale PNG, exactly.

    Args:
        path: destination file; written atomically.
        values: (H, W) integer or bool array (numpy, or a CPU torch tensor), e.g. one frame of
            ``instance`` squeezed to (H, W). Values must lie in [0, 65535].

    Raises:
        ShapeError: not 2-D, or not an integer / bool dtype.
        ExportError: a value is negative or above 65535, or the file cannot be written.
    """
    a = np.asarray(values)
    if a.ndim != 2:
        raise ShapeError(f"write_u16_png expects an (H, W) array, got shape {a.shape}")
    if a.dtype != np.bool_ and not np.issubdtype(a.dtype, np.integer):
        raise ShapeError(f"write_u16_png expects integer or bool values, got dtype {a.dtype}")
    if a.size and a.dtype != np.bool_ and (a.min() < 0 or a.max() > _U16_MAX):
        raise ExportError(
            f"write_u16_png({path}): values span [{a.min()}, {a.max()}], a 16-bit PNG holds [0, 65535]"
        )
    atomic_write_bytes(path, encode_png16(a.astype(np.uint16)))


def read_u16_png(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a greyscale 8- or 16-bit PNG (id map or mask).

    Returns:
        (H, W) int32 with the stored values (0..65535), torch-friendly.

    Raises:
        ExportError: not a greyscale PNG of a supported kind.
    """
    with open(path, "rb") as fh:
        pixels = decode_png(fh.read(), name=str(path))
    if pixels.ndim != 2:
        raise ExportError(f"{path}: expected a greyscale PNG, got {pixels.shape[2]} channels per pixel")
    return pixels.astype(np.int32)
