"""Image textures: files found in a folder, loaded as linear RGB, and their mip pyramids (cached per process).

Plain numpy and Pillow: importing this module loads no Warp kernel. A material's "image" layer (docs/rendering.md)
names a file; flowsynth.renderer.shading packs its mip levels into the texel table the shading kernel reads.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from flowsynth.caches import register
from flowsynth.errors import AssetError, ConfigError

__all__ = ["IMAGE_EXTENSIONS", "MAX_TEXTURE_SIZE", "NATURAL_KINDS", "list_textures", "load_texture", "mip_pyramid",
           "natural_image", "srgb_to_linear"]

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


# --- textures with the statistics of natural images, made without files ---------------------------------------
NATURAL_KINDS = ("pink", "leaves", "edges")


def natural_image(kind: str, seed: int, size: int = 512) -> np.ndarray:
    """A (size, size, 3) float32 sRGB image in [0, 1] with a statistic of photographs, drawn from ``seed``:

    - "pink": a random-phase field whose amplitude spectrum falls as 1/f^a, a in [0.8, 1.6] (photographs: about 1),
      in a luminance and two weaker, smoother opponent-colour channels;
    - "leaves": dead leaves (Matheron; Lee, Mumford and Huang 2001): discs whose radii follow p(r) ~ r^-3 from 3 px
      to size / 4, painted front to back until the plane is covered, each a colour drawn from natural colour
      statistics with a faint 1/f shading: occlusion edges at every scale;
    - "edges": sparse sharp edges over smooth regions: 6-30 polygons of sizes spread over two octaves and more,
      each a flat colour with a gentle linear gradient, on a smooth background.
    """
    if kind not in NATURAL_KINDS:
        raise ConfigError(f"natural texture kind {kind!r} is none of {NATURAL_KINDS}")
    rng = np.random.default_rng([46, seed])
    if kind == "pink":
        lum = _pink(rng, size, rng.uniform(0.8, 1.6))
        chroma = [_pink(rng, size, rng.uniform(1.4, 2.0)) for _ in range(2)]
        y = 0.45 + rng.uniform(0.12, 0.25) * lum
        img = _opponent_to_rgb(y, rng.uniform(0.02, 0.08) * chroma[0], rng.uniform(0.02, 0.08) * chroma[1], rng)
    elif kind == "leaves":
        img = _dead_leaves(rng, size)
    else:
        img = _edges(rng, size)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _pink(rng: np.random.Generator, size: int, a: float) -> np.ndarray:
    """A zero-mean, unit-variance field of amplitude spectrum 1/f^a (periodic: it tiles)."""
    fy, fx = np.fft.fftfreq(size)[:, None], np.fft.fftfreq(size)[None, :]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    spec = f ** (-a) * np.exp(2j * np.pi * rng.random((size, size)))
    spec[0, 0] = 0.0
    field = np.fft.ifft2(spec).real
    return (field - field.mean()) / max(field.std(), 1e-12)


def _natural_colour(rng: np.random.Generator, n: int) -> np.ndarray:
    """n sRGB colours: luminance log-normal about 0.35, mostly low saturation, hues anywhere."""
    y = np.clip(np.exp(rng.normal(np.log(0.35), 0.6, n)), 0.02, 0.98)
    sat = rng.beta(1.2, 3.0, n)
    hue = rng.random(n) * 2 * np.pi
    return np.clip(y[:, None] * (1 + sat[:, None] * np.stack([np.cos(hue), np.cos(hue - 2.09), np.cos(hue + 2.09)],
                                                             1)), 0, 1)


def _opponent_to_rgb(y, rg, by, rng) -> np.ndarray:
    tint = _natural_colour(rng, 1)[0] - _natural_colour(rng, 1)[0].mean()
    return np.stack([y + rg + 0.5 * by, y - rg + 0.5 * by, y - by], -1) + 0.3 * tint


def _dead_leaves(rng: np.random.Generator, size: int) -> np.ndarray:
    img = np.zeros((size, size, 3))
    covered = np.zeros((size, size), bool)
    rmin, rmax = 3.0, size / 4
    shade = 0.06 * _pink(rng, size, 1.0)[..., None]
    ys, xs = np.mgrid[0:size, 0:size]
    for _ in range(20000):  # front to back: a disc shows only where nothing nearer covers it
        u = rng.random()
        r = 1.0 / np.sqrt(1 / rmin ** 2 - u * (1 / rmin ** 2 - 1 / rmax ** 2))  # inverse CDF of p(r) ~ r^-3
        cx, cy = rng.random(2) * size
        y0, y1 = int(max(cy - r, 0)), int(min(cy + r + 1, size))
        x0, x1 = int(max(cx - r, 0)), int(min(cx + r + 1, size))
        if y1 <= y0 or x1 <= x0:
            continue
        disc = (xs[y0:y1, x0:x1] - cx) ** 2 + (ys[y0:y1, x0:x1] - cy) ** 2 <= r * r
        new = disc & ~covered[y0:y1, x0:x1]
        if new.any():
            img[y0:y1, x0:x1][new] = _natural_colour(rng, 1)[0]
            covered[y0:y1, x0:x1] |= new
        if covered.all():
            break
    img[~covered] = _natural_colour(rng, 1)[0]
    return img * (1 + shade)


def _edges(rng: np.random.Generator, size: int) -> np.ndarray:
    from PIL import Image, ImageDraw

    ys, xs = np.mgrid[0:size, 0:size] / size
    base = _natural_colour(rng, 1)[0]
    img = base * (1 + 0.15 * _pink(rng, size, 2.0)[..., None] * rng.uniform(0.3, 1.0))
    for _ in range(int(rng.integers(6, 31))):
        r = size * np.exp(rng.uniform(np.log(0.02), np.log(0.35)))
        cx, cy = rng.random(2) * size
        k = int(rng.integers(3, 9))
        ang = np.sort(rng.uniform(0, 2 * np.pi, k))
        rad = r * rng.uniform(0.5, 1.0, k)
        mask = Image.new("L", (size, size), 0)
        ImageDraw.Draw(mask).polygon([(float(cx + q * np.cos(t)), float(cy + q * np.sin(t)))
                                      for q, t in zip(rad, ang)], fill=1)
        m = np.asarray(mask, bool)
        g = rng.normal(0, 0.15, 2)
        colour = _natural_colour(rng, 1)[0]
        img[m] = (colour * (1 + g[0] * (xs[m, None] - cx / size) + g[1] * (ys[m, None] - cy / size)))
    return img
