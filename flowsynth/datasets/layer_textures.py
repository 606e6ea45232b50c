"""``TextureBank``: the images a ``Layers`` stream's backgrounds and shapes are cut from, without files by default.

Default: frame 0 (``rgb``) of samples 0..size-1 of ``BouncingThings`` at the stream's width and height (one frame,
the default config otherwise; frame 0 does not depend on num_frames) and seed ``TEXTURE_SEED``, a stream apart from
any training stream, quantised to 8 bits as the learning benchmark's ``chairs2d`` arm was textured (its frames went
through uint8 pools). A frame is rendered the first time a draw picks it, then kept for the life of the process
(``fs.clear_caches`` empties it): a DataLoader worker renders the frames its samples pick. What that costs: one
BouncingThings frame rendered per bank frame, the first time a process picks it (and the render kernels loaded once
per process), 3 bytes a pixel kept; measured in docs/decisions/0023-raft-judge.md.

With ``texture_dir``: every image of the folder (``flowsynth.appearance.list_textures``: sorted by name), cut to the
stream's aspect ratio about its centre and resized to its size with torch (bilinear, antialiased). The bank lists the
folder and reads all its images the first time it is used, and keeps them: images added, removed or changed later
are not seen by that bank (a new ``Layers`` lists the folder again).
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from flowsynth.caches import register
from flowsynth.errors import AssetError

__all__ = ["TEXTURE_SEED", "TextureBank"]

TEXTURE_SEED = 7_340_033
"""Seed of the BouncingThings stream the default bank's frames come from."""

_FRAMES: dict = register("layers.bank_frames", {})  # (width, height, seed, j) -> (3, H, W) uint8


class TextureBank:
    """Source j of a ``Layers`` stream as a (3, height, width) float32 image in [0, 1] (``bank[j]``).

    Args:
        width, height: the stream's image size [px].
        size: frames in the default bank (ignored with ``texture_dir``).
        seed: seed of the BouncingThings stream of the default bank.
        texture_dir: a folder of images, or None for the default bank.

    ``len(bank)``: ``size``, or the number of images in ``texture_dir``. With ``texture_dir``, the first ``len`` or
    ``bank[j]`` lists the folder (ConfigError when it is missing or holds no image) and the first ``bank[j]`` reads
    every image of that listing (AssetError naming a file Pillow cannot read); both are kept by this bank, so later
    lookups read no file and see no change to the folder. A pickled bank (a DataLoader worker's copy) carries the
    listing but no image: each process reads the images once. The default bank's frames are kept per process, not
    here.
    """

    def __init__(self, width: int, height: int, size: int, seed: int, texture_dir: str | None) -> None:
        self.width, self.height, self.size, self.seed, self.texture_dir = width, height, size, seed, texture_dir
        self._files: list[Path] | None = None  # texture_dir's listing, once listed
        self._images: torch.Tensor | None = None  # (m, 3, height, width) float32, once read

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_images": None}

    def __len__(self) -> int:
        if self.texture_dir is None:
            return self.size
        return len(self._listing())

    def __getitem__(self, j: int) -> torch.Tensor:
        if self.texture_dir is not None:
            if self._images is None:
                self._images = torch.stack([fit_image(read_image(f), self.width, self.height)
                                            for f in self._listing()])
            return self._images[j]
        key = (self.width, self.height, self.seed, int(j))
        if key not in _FRAMES:
            _FRAMES[key] = self._render(int(j))
        return _FRAMES[key].to(torch.float32) / 255.0

    def _listing(self) -> list[Path]:
        if self._files is None:
            from flowsynth.appearance import list_textures

            self._files = list_textures(self.texture_dir)
        return self._files

    def _render(self, j: int) -> torch.Tensor:
        from flowsynth.datasets.bouncing import BouncingThings
        from flowsynth.scene import BouncingThingsConfig

        cfg = BouncingThingsConfig(width=self.width, height=self.height, num_frames=1)
        rgb = BouncingThings(cfg, outputs=["rgb"], seed=self.seed).sample(j)["rgb"][0]
        return (rgb * 255).round().clamp(0, 255).to(torch.uint8)


def read_image(path: str | os.PathLike) -> torch.Tensor:
    """An image file as (3, h, w) float32 sRGB in [0, 1] (``flowsynth.io.read_rgb_png``: Pillow; grey and RGBA become
    RGB). Raises AssetError when Pillow cannot read it."""
    from flowsynth.io import read_rgb_png

    try:
        return torch.from_numpy(read_rgb_png(path))
    except OSError as e:  # PIL's UnidentifiedImageError is one
        raise AssetError(f"image {str(Path(path))!r} cannot be decoded by Pillow: {e}") from e


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
