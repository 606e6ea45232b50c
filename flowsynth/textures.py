"""Image textures: files found in a folder, loaded as linear RGB, and their mip pyramids (cached per process).

Plain numpy and Pillow: importing this module loads no Warp kernel. A material's "image" layer (docs/rendering.md)
names a file; flowsynth.shading packs its mip levels into the texel table the shading kernel reads.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from flowsynth.caches import register
from flowsynth.errors import AssetError, ConfigError

__all__ = ["IMAGE_EXTENSIONS", "MAX_TEXTURE_SIZE", "list_textures", "load_texture", "mip_pyramid", "srgb_to_linear"]

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
# Image textures larger than this [px] along their longer side are downscaled on load (Lanczos).
MAX_TEXTURE_SIZE = 1024


def list_textures(texture_dir) -> list[Path]:
    """The image files (``IMAGE_EXTENSIONS``) directly inside ``texture_dir``, sorted by name.

    Raises ConfigError when the folder does not exist or holds no images.
    """
    root = Path(texture_dir)
    if not root.is_dir():
        raise ConfigError(f"texture_dir {str(root)!r} does not exist or is not a folder; "
                          "pass a folder of pictures (png, jpg, ...) or leave it unset")
    files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise ConfigError(f"texture_dir {str(root)!r} holds no images with extensions {IMAGE_EXTENSIONS}")
    return files


def load_texture(path) -> np.ndarray:
    """An image texture as (h, w, 3) float32 linear RGB (sRGB decoded), at most MAX_TEXTURE_SIZE px a side.

    Cached per process by path, size and modification time. Raises AssetError if Pillow cannot read it.
    """
    return _load_texture(*_texture_key(path))


@register("textures.images")
@functools.lru_cache(maxsize=64)
def _load_texture(path: str, _size: int, _mtime: int) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            if max(im.size) > MAX_TEXTURE_SIZE:
                k = MAX_TEXTURE_SIZE / max(im.size)
                im = im.resize((max(1, round(im.width * k)), max(1, round(im.height * k))), Image.LANCZOS)
            srgb = np.asarray(im, np.float32) / 255.0
    except (OSError, UnidentifiedImageError) as e:
        raise AssetError(f"image texture {path!r} cannot be decoded by Pillow: {e}") from e
    return srgb_to_linear(srgb)


def mip_pyramid(path) -> list[np.ndarray]:
    """Mip levels of an image texture: level 0 is ``load_texture(path)`` (h, w, 3) float32 linear RGB; level
    l + 1 averages 2x2 texels of level l (an odd side wraps around, as the texture tiles), down to 1 x 1.
    Cached with the texture."""
    return _pyramid(*_texture_key(path))


def _texture_key(path) -> tuple[str, int, int]:
    p = Path(path)
    try:
        st = p.stat()
    except OSError as e:
        raise AssetError(f"image texture {str(p)!r} cannot be read: {e}") from e
    return str(p.resolve()), st.st_size, st.st_mtime_ns


@register("textures.mip_pyramids")
@functools.lru_cache(maxsize=64)
def _pyramid(path: str, size: int, mtime: int) -> list[np.ndarray]:
    levels = [_load_texture(path, size, mtime)]
    while max(levels[-1].shape[:2]) > 1:
        a = levels[-1].astype(np.float64)
        if a.shape[0] % 2 and a.shape[0] > 1:
            a = np.concatenate([a, a[:1]], 0)
        if a.shape[1] % 2 and a.shape[1] > 1:
            a = np.concatenate([a, a[:, :1]], 1)
        h, w = max(a.shape[0] // 2, 1), max(a.shape[1] // 2, 1)
        a = a.reshape(h, a.shape[0] // h, w, a.shape[1] // w, 3).mean(axis=(1, 3))
        levels.append(a.astype(np.float32))
    return levels


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear (IEC 61966-2-1)."""
    c = np.asarray(c, np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)
