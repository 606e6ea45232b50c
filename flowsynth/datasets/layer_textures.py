"""``TextureBank``: the images a ``Layers`` stream's backgrounds and shapes are cut from, without files by default.

Default: frame 0 (``rgb``) of samples 0..size-1 of ``BouncingThings`` at the stream's width and height (one frame,
the default config otherwise; frame 0 does not depend on num_frames) and seed ``TEXTURE_SEED``, a stream apart from
any training stream, quantised to 8 bits as the learning benchmark's ``chairs2d`` arm was textured (its frames went
through uint8 pools). A frame is rendered the first time a draw picks it, then kept for the life of the process
(``fs.clear_caches`` empties it): a DataLoader worker renders the frames its samples pick. What that costs: one
frame at 256x192 took 0.26 s on a busy 2-core CPU (plus about 7 s the first time a process loads the kernels), so the
default 600 frames (as many as the learning benchmark's 2D pools were textured from: one frame for every two pairs
of a 1200-pair pool) add about 160 s per process, spread over its first samples; 3 bytes a pixel each (88 MB at
256x192).

With ``texture_dir``: every image of the folder (``flowsynth.appearance.list_textures``: sorted by name), cut to the
stream's aspect ratio about its centre and resized to its size with torch (bilinear, antialiased), read once per
process.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from flowsynth.caches import register
from flowsynth.errors import AssetError

__all__ = ["TEXTURE_SEED", "TextureBank"]

TEXTURE_SEED = 7_340_033
"""Seed of the BouncingThings stream the default bank's frames come from."""

_FRAMES: dict = register("layers.bank_frames", {})  # (width, height, seed, j) -> (3, H, W) uint8
_FOLDERS: dict = register("layers.texture_dirs", {})  # (files, sizes, mtimes, width, height) -> (m, 3, H, W) float32


class TextureBank:
    """Source j of a ``Layers`` stream as a (3, height, width) float32 image in [0, 1] (``bank[j]``).

    Args:
        width, height: the stream's image size [px].
        size: frames in the default bank (ignored with ``texture_dir``).
        seed: seed of the BouncingThings stream of the default bank.
        texture_dir: a folder of images, or None for the default bank.

    Holds no image itself (the per-process caches do), so it pickles small to DataLoader workers.
    """

    def __init__(self, width: int, height: int, size: int, seed: int, texture_dir: str | None) -> None:
        self.width, self.height, self.size, self.seed, self.texture_dir = width, height, size, seed, texture_dir

    def __len__(self) -> int:
        if self.texture_dir is None:
            return self.size
        from flowsynth.appearance import list_textures

        return len(list_textures(self.texture_dir))

    def __getitem__(self, j: int) -> torch.Tensor:
        if self.texture_dir is not None:
            return self._folder()[j]
        key = (self.width, self.height, self.seed, int(j))
        if key not in _FRAMES:
            _FRAMES[key] = self._render(int(j))
        return _FRAMES[key].to(torch.float32) / 255.0

    def _render(self, j: int) -> torch.Tensor:
        from flowsynth.datasets.bouncing import BouncingThings
        from flowsynth.scene import BouncingThingsConfig

        cfg = BouncingThingsConfig(width=self.width, height=self.height, num_frames=1)
        rgb = BouncingThings(cfg, outputs=["rgb"], seed=self.seed).sample(j)["rgb"][0]
        return (rgb * 255).round().clamp(0, 255).to(torch.uint8)

    def _folder(self) -> torch.Tensor:
        from flowsynth.appearance import list_textures

        files = list_textures(self.texture_dir)
        stats = [os.stat(f) for f in files]
        key = (tuple(map(str, files)), tuple(s.st_size for s in stats), tuple(s.st_mtime_ns for s in stats),
               self.width, self.height)
        if key not in _FOLDERS:
            _FOLDERS.clear()  # one folder at a time: a changed file replaces the old images
            _FOLDERS[key] = torch.stack([fit_image(read_image(f), self.width, self.height) for f in files])
        return _FOLDERS[key]


def read_image(path: str | os.PathLike) -> torch.Tensor:
    """An image file as (3, h, w) float32 sRGB in [0, 1] (Pillow; grey and RGBA become RGB). Raises AssetError when
    Pillow cannot read it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            a = np.asarray(im.convert("RGB"), np.float32) / 255.0
    except (OSError, UnidentifiedImageError) as e:
        raise AssetError(f"image {str(Path(path))!r} cannot be decoded by Pillow: {e}") from e
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))


def fit_image(img: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(3, h, w) ``img`` cut about its centre to the aspect ratio width : height, then resized to (3, height, width)
    (bilinear, antialiased when shrinking), clamped to [0, 1]."""
    h, w = img.shape[-2:]
    if w * height > h * width:  # too wide: keep the full height
        cw, ch = max(1, round(h * width / height)), h
    else:
        cw, ch = w, max(1, round(w * height / width))
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    crop = img[:, y0:y0 + ch, x0:x0 + cw]
    out = torch.nn.functional.interpolate(crop[None], size=(height, width), mode="bilinear", align_corners=False,
                                          antialias=True)[0]
    return out.clamp(0.0, 1.0)
