"""PNG and PPM images: 8-bit sRGB colour, 16-bit id / mask maps, and a minimal 16-bit PNG codec.

8-bit colour PNG and binary PPM (P6, FlyingChairs' image format) go through Pillow. Pillow cannot
write 16-bit RGB PNGs and reads them back reduced to 8 bits, so 16-bit images (id maps here, KITTI
flow in :mod:`flowsynth.io.kitti`) use :func:`encode_png16` / :func:`decode_png`, a small
dependency-free codec on ``zlib`` + ``struct``:

- the encoder writes 16-bit greyscale or RGB, non-interlaced, filter type 2 ("up") on every row,
  which is vectorised and compresses smooth maps well;
- the decoder reads any non-interlaced 8- or 16-bit greyscale, grey+alpha, RGB or RGBA PNG, with any
  of the five filter types on each row, vectorised with numpy: an image whose rows all use filter
  0-2 (what the encoder writes) decodes row by row; one with filter 3 or 4 rows (libpng's choice for
  most rows of a KITTI flow map) decodes one anti-diagonal of pixels at a time (:func:`_unfilter_diagonal`).
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


def _unfilter_diagonal(ftypes: np.ndarray, rows: np.ndarray, w: int, bpp: int) -> np.ndarray:
    """Undo PNG filters 0-4, any mix of them, of a whole image.

    Args:
        ftypes: (H,) uint8, the filter type of each row.
        rows: (H, W * bpp) uint8, the filtered bytes without their filter-type byte.
        w: pixels per row.
        bpp: bytes per pixel (1 to 8).

    Returns:
        (H, W * bpp) uint8, the image bytes.

    A byte depends only on the same byte of the pixels left, above and above-left of it, so every pixel of one
    anti-diagonal (x + y = d) decodes at once: H + W - 1 vectorised steps in place of a loop over every byte.
    """
    h = len(ftypes)
    ys, xs = np.mgrid[0:h, 0:w]
    skew = np.zeros((h + w + 1, h + 1, bpp), np.int16)  # pixel (y, x) at [x + y + 2, y + 1], zeros around it
    raw = np.zeros_like(skew)
    raw[xs + ys + 2, ys + 1] = rows.reshape(h, w, bpp)
    kind = [(ftypes == k)[:, None] for k in range(4)]
    for d in range(h + w - 1):
        lo, hi = max(0, d - w + 1), min(h, d + 1)  # the rows that diagonal d crosses
        a, b, c = skew[d + 1, lo + 1 : hi + 1], skew[d + 1, lo:hi], skew[d, lo:hi]  # left, above, above-left
        pa, pb, pc = np.abs(b - c), np.abs(a - c), np.abs(a + b - 2 * c)  # Paeth: |p - a|, |p - b|, |p - c|
        pred = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
        for k, choice in ((3, (a + b) >> 1), (2, b), (1, a), (0, 0)):  # average, up, sub, none
            np.copyto(pred, choice, where=kind[k][lo:hi], casting="unsafe")
        skew[d + 2, lo + 1 : hi + 1] = (raw[d + 2, lo + 1 : hi + 1] + pred) & 0xFF
    return skew[xs + ys + 2, ys + 1].astype(np.uint8).reshape(h, w * bpp)


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
    ftypes = rows[:, 0]
    bad = np.flatnonzero(ftypes > 4)
    if bad.size:
        raise ExportError(f"{name}: invalid PNG filter type {ftypes[bad[0]]} in row {bad[0]}")
    if (ftypes > 2).any():
        out = _unfilter_diagonal(ftypes, rows[:, 1:], w, bpp)
    else:  # none, sub and up: each row at once, from the row above
        out = np.empty((h, stride), np.uint8)
        prior = np.zeros(stride, np.uint8)
        for y in range(h):
            ftype, line = int(ftypes[y]), rows[y, 1:]
            if ftype == 0:
                out[y] = line
            elif ftype == 1:
                out[y] = np.cumsum(line.reshape(w, bpp), axis=0, dtype=np.uint8).reshape(-1)
            else:
                out[y] = line + prior
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
