"""Rendering of a layered pair (``layer_draws.PairDraw``) with torch: images, exact flow, validity, occlusion from the
layer order, and the layer map.

Frame t shows the background's source warped by A^t and each shape k, on top of the ones before it, where
``inside_k(B_k^-t q)``, textured with its source warped by B_k^t (A, B_k: the (3, 3) forms of the draws' motions).
A shape is its part in frame 0's image [-1/2, W - 1/2) x [-1/2, H - 1/2), as the helper draws its masks in the image:
what lies outside never shows, so a shape's texture is sampled in the image.
Frame 0 is the sources themselves. Warps sample bilinearly at B^-t q, pixel centres at integers (``grid_sample``,
``align_corners=False``): the background reflects at the image border (OpenCV's BORDER_REFLECT), a shape's texture
is 0 outside the image (BORDER_CONSTANT), as the learning benchmark's ``chairs2d_pairs`` warps them. Coordinates and
flow are float64, cast to float32 at the end.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import torch

from flowsynth.datasets.layer_draws import Ellipse, PairDraw

__all__ = ["BACKGROUND_CATEGORY", "CATEGORY_NAMES", "render_layers"]

BACKGROUND_CATEGORY = 1
"""``category`` of the background (the room's category in a BouncingThings sample)."""
CATEGORY_NAMES = {1: "background", 2: "shape:ellipse", 3: "shape:polygon"}
"""``category`` id -> name: the background, then a shape's kind (objects' ids start at 2, as in BouncingThings)."""


def _h(m) -> np.ndarray:
    """(2, 3) -> (3, 3) float64."""
    return np.vstack([np.asarray(m, np.float64), [0.0, 0.0, 1.0]])


def _apply(m: np.ndarray | None, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The points (x, y) mapped by the (3, 3) affine ``m`` (None: unchanged, bit for bit)."""
    if m is None:
        return x, y
    return m[0, 0] * x + m[0, 1] * y + m[0, 2], m[1, 0] * x + m[1, 1] * y + m[1, 2]


class _Maps:
    """The draws' motions as (3, 3) matrices and their powers: ``power(k, t)`` is layer k's M^t (None for t = 0);
    layer 0 is the background."""

    def __init__(self, draw: PairDraw, height: int, width: int) -> None:
        self.mats = [_h(draw.motion)] + [_h(layer.motion) for layer in draw.layers]
        self.shapes = [None] + [layer.shape for layer in draw.layers]
        self.height, self.width = height, width
        self._powers: dict[tuple[int, int], np.ndarray | None] = {}

    def power(self, k: int, t: int) -> np.ndarray | None:
        if t == 0:
            return None
        if (k, t) not in self._powers:
            m = self.mats[k] if t > 0 else np.linalg.inv(self.mats[k])
            self._powers[k, t] = np.linalg.matrix_power(m, abs(t))
        return self._powers[k, t]

    def bounds(self, k: int) -> tuple[float, float, float, float]:
        """A box (x min, y min, x max, y max) [px] that holds layer k's shape in frame 0's image."""
        x0, y0, x1, y1 = self.shapes[k].bounds()
        return max(x0, -0.5), max(y0, -0.5), min(x1, self.width - 0.5), min(y1, self.height - 0.5)

    def inside(self, k: int, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Whether the frame-0 points (u, v) lie in layer k: in its shape and in frame 0's image [-1/2, W - 1/2) x
        [-1/2, H - 1/2) (the helper's masks are drawn in the image; what lies outside it never shows)."""
        return self.shapes[k].inside(u, v) & (u >= -0.5) & (u < self.width - 0.5) & (v >= -0.5) & \
            (v < self.height - 0.5)

    def window(self, k: int, t: int) -> tuple[slice, slice]:
        """Rows and columns of the frame-t pixels layer k may cover: its bounds moved by M^t, grown by a pixel."""
        x0, y0, x1, y1 = self.bounds(k)
        cx, cy = _apply(self.power(k, t), torch.tensor([x0, x1, x0, x1], dtype=torch.float64),
                        torch.tensor([y0, y0, y1, y1], dtype=torch.float64))
        c0, c1 = max(math.floor(float(cx.min())) - 1, 0), min(math.ceil(float(cx.max())) + 2, self.width)
        r0, r1 = max(math.floor(float(cy.min())) - 1, 0), min(math.ceil(float(cy.max())) + 2, self.height)
        return slice(r0, max(r0, r1)), slice(c0, max(c0, c1))

    def layer_at(self, t: int, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
        """The topmost layer (int64, 0 = background) at each pixel of frame t (``xs``, ``ys``: the (H, W) pixel
        centres)."""
        lay = torch.zeros(xs.shape, dtype=torch.int64)
        for k in range(1, len(self.mats)):
            rows, cols = self.window(k, t)
            sub = lay[rows, cols]
            sub[self.inside(k, *_apply(self.power(k, -t), xs[rows, cols], ys[rows, cols]))] = k
        return lay

    def covered_above(self, t: int, x: torch.Tensor, y: torch.Tensor, below: torch.Tensor) -> torch.Tensor:
        """Whether a layer above ``below`` (per point) covers the frame-t points (x, y) (any shape)."""
        out = torch.zeros(x.shape, dtype=torch.bool)
        for k in range(1, len(self.mats)):
            u, v = _apply(self.power(k, -t), x, y)
            x0, y0, x1, y1 = self.bounds(k)
            near = (below < k) & (u >= x0) & (u <= x1) & (v >= y0) & (v <= y1)  # the exact test only here
            out[near] |= self.inside(k, u[near], v[near])
        return out

    def move(self, lay: torch.Tensor, t: int, x: torch.Tensor, y: torch.Tensor, step: int):
        """The pixels (x, y) of frame t, of layer ``lay`` (per pixel), moved ``step`` frames (+1 forward, -1 back)
        by their layer's motion."""
        tx, ty = _apply(self.power(0, step), x, y)
        for k in range(1, len(self.mats)):
            rows, cols = self.window(k, t)
            mine = lay[rows, cols] == k
            if bool(mine.any()):
                u, v = _apply(self.power(k, step), x[rows, cols], y[rows, cols])
                tx[rows, cols] = torch.where(mine, u, tx[rows, cols])
                ty[rows, cols] = torch.where(mine, v, ty[rows, cols])
        return tx, ty


def _warp(src: torch.Tensor, m: np.ndarray, x: torch.Tensor, y: torch.Tensor, padding: str,
          box: tuple[float, float, float, float] | None = None) -> torch.Tensor:
    """(3, H, W) ``src`` sampled bilinearly at the points m (x, y) ((h, w) float64): (3, h, w) float32
    (``padding``: grid_sample's). ``box`` (x min, y min, x max, y max) [px], where every point that matters lies:
    only the pixels around it are read (the zero padding outside the image stays where it is)."""
    H, W = src.shape[-2:]
    u, v = _apply(m, x, y)
    c0, r0, c1, r1 = 0, 0, W, H
    if box is not None:
        c0, r0 = max(math.floor(box[0]) - 1, 0), max(math.floor(box[1]) - 1, 0)
        c1, r1 = min(math.ceil(box[2]) + 2, W), min(math.ceil(box[3]) + 2, H)
    w, h = c1 - c0, r1 - r0
    grid = torch.stack([(2 * (u - c0) + 1) / w - 1, (2 * (v - r0) + 1) / h - 1], -1)[None]
    part = src[None, :, r0:r1, c0:c1].to(torch.float64)
    sampled = torch.nn.functional.grid_sample(part, grid, mode="bilinear", padding_mode=padding, align_corners=False)
    return sampled[0].to(torch.float32)


def render_layers(draw: PairDraw, texture: Callable[[int], torch.Tensor], width: int, height: int, num_frames: int,
                  outputs: Sequence[str]) -> dict[str, torch.Tensor]:
    """Render ``outputs`` of the layered clip ``draw`` (module docstring).

    Args:
        draw: the background, its motion and the shapes (``draw_pair``).
        texture: source index -> (3, height, width) float32 image in [0, 1].
        width, height: image size [px].
        num_frames: T >= 1 (>= 2 for the per-pair keys).
        outputs: keys among ``rgb`` (T, 3, H, W) float32; ``flow_fw`` / ``flow_bw`` (T-1, 2, H, W) float32 [px],
            exact for every pixel (M p - p for the layer M of pixel p), also where the target leaves the image;
            ``valid_fw`` / ``valid_bw`` (T-1, 1, H, W) bool: the flow is defined, True at every pixel (each sees
            a layer, and 2D layers have nothing behind a camera: docs/conventions.md's meaning, as BouncingThings');
            ``oof_fw`` / ``oof_bw``: the target leaves the image [-1/2, W - 1/2) x [-1/2, H - 1/2);
            ``occ_fw`` / ``occ_bw``: ``oof``, or a layer above the pixel's own covers its target in the other frame;
            ``instance`` (T, 1, H, W) int32: the layer (0 = background, k = the k-th shape drawn, higher on top);
            ``category`` (T, 1, H, W) int32 (``CATEGORY_NAMES``).

    Returns:
        {key: tensor} for ``outputs``.
    """
    maps = _Maps(draw, height, width)
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                            indexing="ij")
    lays = [maps.layer_at(t, xs, ys) for t in range(num_frames)]
    out: dict[str, torch.Tensor] = {}
    if "rgb" in outputs:
        out["rgb"] = torch.stack([_frame(maps, draw, texture, lays[t], t, xs, ys) for t in range(num_frames)])
    pair_keys = [k for k in outputs if k.endswith(("_fw", "_bw"))]
    for direction, step in (("fw", 1), ("bw", -1)):
        if not any(k.endswith(direction) for k in pair_keys):
            continue
        per: dict[str, list] = {}
        for t in range(num_frames - 1):
            src, dst = (t, t + 1) if step == 1 else (t + 1, t)
            lay = lays[src]
            tx, ty = maps.move(lay, src, xs, ys, step)
            inside = (tx >= -0.5) & (tx < width - 0.5) & (ty >= -0.5) & (ty < height - 0.5)
            per.setdefault("flow", []).append(torch.stack([tx - xs, ty - ys]).to(torch.float32))
            per.setdefault("valid", []).append(torch.ones_like(inside)[None])
            per.setdefault("oof", []).append(~inside[None])
            if f"occ_{direction}" in outputs:
                per.setdefault("occ", []).append((~inside | maps.covered_above(dst, tx, ty, lay))[None])
        for name, frames in per.items():
            if f"{name}_{direction}" in outputs:
                out[f"{name}_{direction}"] = torch.stack(frames)
    if "instance" in outputs:
        out["instance"] = torch.stack(lays)[:, None].to(torch.int32)
    if "category" in outputs:
        kinds = torch.tensor([BACKGROUND_CATEGORY] + [2 if isinstance(s, Ellipse) else 3 for s in maps.shapes[1:]],
                             dtype=torch.int32)
        out["category"] = kinds[torch.stack(lays)][:, None]
    return {k: out[k] for k in outputs}


def _frame(maps: _Maps, draw: PairDraw, texture, lay: torch.Tensor, t: int, xs, ys) -> torch.Tensor:
    """Frame t's (3, H, W) float32 image."""
    src = texture(draw.background)
    img = src.clone() if t == 0 else _warp(src, maps.power(0, -t), xs, ys, "reflection")
    for k, layer in enumerate(draw.layers, start=1):
        rows, cols = maps.window(k, t)
        mask = lay[rows, cols] == k
        if not bool(mask.any()):
            continue
        tex = texture(layer.texture)
        tex = tex[:, rows, cols] if t == 0 else _warp(tex, maps.power(k, -t), xs[rows, cols], ys[rows, cols], "zeros",
                                                      maps.bounds(k))
        img[:, rows, cols] = torch.where(mask, tex, img[:, rows, cols])
    return img
