"""Visualisation: flow colour wheel, depth / id / normal colouring, boxes, labelled contact sheets.

Inputs are numpy arrays or torch tensors (any device; converted with ``.detach().cpu()``), in the
layouts of a flowsynth sample (docs/conventions.md). Every function returns an (H, W, 3) uint8 RGB
numpy image. Drawing and saving use Pillow; there is no matplotlib dependency. A preview carries its keys: the
flow colour wheel with its rim in px (``flow_legend``) and the depth scale in m (``depth_colorbar``).
"""

from __future__ import annotations

import dataclasses
import io
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from flowsynth.errors import ConfigError, ShapeError
from flowsynth.io import atomic_write_bytes
from flowsynth.plan import split_gap_key

__all__ = [
    "SheetLayout",
    "contact_sheet",
    "depth_colorbar",
    "depth_range",
    "depth_to_color",
    "draw_boxes",
    "draw_tracks",
    "flow_legend",
    "flow_to_color",
    "ids_to_color",
    "make_colorwheel",
    "mask_to_color",
    "normals_to_color",
    "preview_tiles",
    "sample_preview",
    "save_png",
    "sheet_layout",
    "vectors_to_color",
]

# Middlebury colour wheel (Baker et al. 2011), segment lengths in hues: red-yellow, yellow-green, ...
_WHEEL_SEGMENTS = (15, 6, 4, 11, 13, 6)  # RY, YG, GC, CB, BM, MR
# viridis at 0, 1/4, 1/2, 3/4, 1 (matplotlib's values, sRGB 8-bit), interpolated linearly.
_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], np.float64)
_DEPTH_PERCENTILES = (1.0, 99.0)  # inverse-depth range mapped onto the colormap [%]
_GOLDEN = 0.618033988749895  # hue step between consecutive ids
RGB = tuple[int, int, int]
_PAD = 2  # contact sheet: pixels between tiles and around labels [px]
_BACKGROUND = (32, 32, 32)  # contact sheet and legends: dark grey
LEGEND_MIN = 48
"""[px] the smallest width and height of a legend tile (the flow key, a depth scale), whatever the image size."""


def _np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu()
        if x.dtype.is_floating_point and x.dtype.itemsize < 4:
            x = x.float()
        x = x.numpy()
    return np.asarray(x)


def _plane(x: Any, name: str) -> np.ndarray:
    """(H, W) or (1, H, W) -> (H, W)."""
    a = _np(x)
    if a.ndim == 3 and a.shape[0] == 1:
        a = a[0]
    if a.ndim != 2:
        raise ShapeError(f"{name} must be (H, W) or (1, H, W), got shape {a.shape}")
    return a


def make_colorwheel() -> np.ndarray:
    """The Middlebury flow colour wheel: (55, 3) uint8 RGB, hue 0 = red, in the segment order above."""
    ramps = [np.floor(255 * np.arange(n) / n) for n in _WHEEL_SEGMENTS]
    full = [np.full(n, 255.0) for n in _WHEEL_SEGMENTS]
    zero = [np.zeros(n) for n in _WHEEL_SEGMENTS]
    r = np.concatenate([full[0], 255 - ramps[1], zero[2], zero[3], ramps[4], full[5]])
    g = np.concatenate([ramps[0], full[1], full[2], 255 - ramps[3], zero[4], zero[5]])
    b = np.concatenate([zero[0], zero[1], ramps[2], full[3], full[4], 255 - ramps[5]])
    return np.stack([r, g, b], axis=1).astype(np.uint8)


def flow_to_color(flow: Any, max_flow: float | None = None) -> np.ndarray:
    """Colour-code a flow field with the Middlebury wheel (as torchvision ``flow_to_image``).

    Hue is the direction (+x red, +y (down) orange-yellow, -x cyan-blue, -y (up) blue-violet),
    saturation the magnitude divided by ``max_flow``; zero flow is white. Magnitudes above
    ``max_flow`` are darkened to 75 % as in the Middlebury code. NaN / inf vectors count as zero.

    Args:
        flow: (2, H, W) float (dx, dy) [px].
        max_flow: normalising magnitude [px]; default the largest finite magnitude in ``flow``.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    f = _np(flow).astype(np.float64)
    if f.ndim != 3 or f.shape[0] != 2:
        raise ShapeError(f"flow_to_color expects flow of shape (2, H, W), got {f.shape}")
    f = np.where(np.isfinite(f).all(axis=0), f, 0.0)
    u, v = f
    rad = np.hypot(u, v)
    norm = float(rad.max(initial=0.0)) if max_flow is None else float(max_flow)
    if norm > 0:
        u, v, rad = u / norm, v / norm, rad / norm
    wheel = make_colorwheel().astype(np.float64) / 255.0
    # angle in [-1, 1]: -1 and 1 both mean +x (red), wheel index 0 and len - 1
    fk = (np.arctan2(-v, -u) / np.pi + 1) / 2 * (len(wheel) - 1)
    k0 = np.floor(fk).astype(np.int64)
    frac = (fk - k0)[..., None]
    col = (1 - frac) * wheel[k0] + frac * wheel[(k0 + 1) % len(wheel)]
    col = np.where((rad <= 1)[..., None], 1 - rad[..., None] * (1 - col), col * 0.75)
    return np.floor(255 * col).astype(np.uint8)


def _colormap(x: np.ndarray) -> np.ndarray:
    """x in [0, 1] -> (..., 3) uint8 viridis."""
    pos = np.clip(x, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i0 = np.minimum(np.floor(pos).astype(np.int64), len(_VIRIDIS) - 2)
    t = (pos - i0)[..., None]
    return np.rint((1 - t) * _VIRIDIS[i0] + t * _VIRIDIS[i0 + 1]).astype(np.uint8)


def _inverse_range(depth: Any, valid: Any | None) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """(depth (H, W) float64, its mask of valid hits, lo, hi): the inverse-depth range [1/m] that
    ``depth_to_color`` maps onto viridis; None when no pixel is valid."""
    d = _plane(depth, "depth").astype(np.float64)
    ok = np.isfinite(d) & (d > 0)
    if valid is not None:
        ok &= _plane(valid, "valid").astype(bool)
    if not ok.any():
        return None
    lo, hi = np.percentile(1.0 / d[ok], _DEPTH_PERCENTILES)
    return d, ok, float(lo), float(hi)


def depth_range(depth: Any, valid: Any | None = None) -> tuple[float, float] | None:
    """(near, far) [m]: the depths ``depth_to_color`` colours yellow and purple (the 99th and 1st percentiles of
    inverse depth over the valid pixels); None when no pixel is valid. Arguments as ``depth_to_color``'s."""
    r = _inverse_range(depth, valid)
    return None if r is None else (1.0 / r[3], 1.0 / r[2])


def depth_to_color(depth: Any, valid: Any | None = None) -> np.ndarray:
    """Colour inverse depth with viridis: near = yellow, far = purple, no hit / invalid = black.

    Args:
        depth: (H, W) or (1, H, W) float depth or distance [m]; 0 = no hit.
        valid: optional (H, W) or (1, H, W) bool; pixels that are False are black.

    Returns:
        (H, W, 3) uint8 RGB; inverse depth normalised between its 1st and 99th percentile over
        valid pixels (so a few very near pixels do not flatten the rest), clipped outside.
    """
    r = _inverse_range(depth, valid)
    if r is None:
        return np.zeros((*_plane(depth, "depth").shape, 3), np.uint8)
    d, ok, lo, hi = r
    out = np.zeros((*d.shape, 3), np.uint8)
    inv = 1.0 / d[ok]
    out[ok] = _colormap((inv - lo) / (hi - lo) if hi > lo else np.ones_like(inv))
    return out


def depth_colorbar(near: float, far: float, height: int, width: int) -> np.ndarray:
    """The scale of ``depth_to_color`` for the range (near, far) [m] (``depth_range``): (height, width, 3) uint8.
    Its band (the upper half; all of it when height < 24) has in column x the colour of the depth whose inverse is
    1/far + x / (width - 1) (1/near - 1/far): purple (far) on the left, yellow (near) on the right, linear in inverse
    depth, as the depth tile. White ticks at the columns of 1, 2, 5 x 10^k m within the range, in the band's lowest
    quarter, and their values [m] below the band where they fit."""
    if height < 1 or width < 2:
        raise ShapeError(f"depth_colorbar needs height >= 1 and width >= 2, got {height}x{width}")
    band = height // 2 if height >= 24 else height
    bar = np.full((height, width, 3), _BACKGROUND, np.uint8)
    bar[:band] = _colormap(np.arange(width) / (width - 1))[None]
    lo, hi = 1.0 / far, 1.0 / near
    ticks = [(d, int(round((1.0 / d - lo) / (hi - lo) * (width - 1)))) for d in _nice_values(near, far)] \
        if hi > lo else []
    for _, col in ticks:
        bar[band - max(1, band // 4):band, col] = 255
    if band == height:
        return bar
    im = Image.fromarray(bar)
    draw, font, right = ImageDraw.Draw(im), ImageFont.load_default(), -_PAD
    for d, col in sorted(ticks, key=lambda t: t[1]):
        text = f"{d:g}"
        x0, _, x1, y1 = font.getbbox(text)
        x = min(max(col - (x1 - x0) // 2, 0), width - x1)
        if x - x0 >= right + _PAD and band + 1 + y1 <= height:
            draw.text((x, band + 1), text, fill=(255, 255, 255), font=font)
            right = x + x1
    return np.asarray(im)


def _nice_values(near: float, far: float) -> list[float]:
    """1, 2 and 5 x 10^k inside [near, far] (at most 6, spread)."""
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        return []
    k0, k1 = int(np.floor(np.log10(near))), int(np.ceil(np.log10(far)))
    vals = [m * 10.0**k for k in range(k0, k1 + 1) for m in (1, 2, 5) if near <= m * 10.0**k <= far]
    return vals[:: max(1, -(-len(vals) // 6))]


def flow_legend(max_flow: float, height: int, width: int) -> np.ndarray:
    """The key of ``flow_to_color(..., max_flow)``: (height, width, 3) uint8, a disk of radius
    r = (min(height, width) - 1) / 2 px around the centre whose pixel at offset (dx, dy) from the centre has the
    colour of the flow (dx, dy) max_flow / r: white at the centre, the rim's saturated hues at |flow| = max_flow
    (+x red, +y down). Outside the disk: the sheet's grey."""
    if height < 1 or width < 1:
        raise ShapeError(f"flow_legend needs height, width >= 1, got {height}x{width}")
    r = max((min(height, width) - 1) / 2, 0.5)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    dx, dy = x - (width - 1) / 2, y - (height - 1) / 2
    if max_flow > 0:
        img = flow_to_color(np.stack([dx, dy]) * (float(max_flow) / r), max_flow=float(max_flow))
    else:  # no motion: every pixel of the flow tile is white
        img = np.full((height, width, 3), 255, np.uint8)
    img[np.hypot(dx, dy) > r] = _BACKGROUND
    return img


def ids_to_color(ids: Any) -> np.ndarray:
    """Colour an (H, W) or (1, H, W) integer id map (instance, category, asset); id 0 = black.

    Consecutive ids get hues of the flow colour wheel a golden-ratio step apart; saturation and value
    vary with a hash of the id. Neighbouring ids stay distinguishable and id k has one colour everywhere.
    """
    a = _plane(ids, "ids").astype(np.int64)
    uniq, inverse = np.unique(a, return_inverse=True)
    hashed = (uniq.astype(np.uint64) * np.uint64(2654435761)) % np.uint64(2**32)
    wheel = make_colorwheel().astype(np.float64)
    hue = wheel[np.floor((uniq * _GOLDEN) % 1.0 * len(wheel)).astype(np.int64) % len(wheel)]
    sat = 0.55 + 0.45 * ((hashed >> np.uint64(8)) % np.uint64(256)).astype(np.float64)[:, None] / 255
    val = 0.75 + 0.25 * ((hashed >> np.uint64(16)) % np.uint64(256)).astype(np.float64)[:, None] / 255
    palette = np.rint(val * (255 - sat * (255 - hue))).astype(np.uint8)
    palette[uniq == 0] = 0
    return palette[inverse.reshape(a.shape)]


def normals_to_color(normals: Any) -> np.ndarray:
    """Colour (3, H, W) unit normals (camera frame) as RGB = (n + 1) / 2; zero normals (no hit) black."""
    n = _np(normals).astype(np.float64)
    if n.ndim != 3 or n.shape[0] != 3:
        raise ShapeError(f"normals_to_color expects (3, H, W), got {n.shape}")
    n = np.where(np.isfinite(n), n, 0.0).transpose(1, 2, 0)
    rgb = np.rint(np.clip((n + 1) / 2, 0, 1) * 255).astype(np.uint8)
    rgb[~(n != 0).any(axis=-1)] = 0
    return rgb


def vectors_to_color(vec: Any) -> np.ndarray:
    """Colour (3, H, W) vectors (scene flow [m]) as RGB = (v / max|v| + 1) / 2: zero motion is grey."""
    v = _np(vec).astype(np.float64)
    if v.ndim != 3 or v.shape[0] != 3:
        raise ShapeError(f"vectors_to_color expects (3, H, W), got {v.shape}")
    v = np.where(np.isfinite(v), v, 0.0)
    norm = float(np.linalg.norm(v, axis=0).max(initial=0.0))
    v = v / norm if norm > 0 else v
    return np.rint(np.clip((v.transpose(1, 2, 0) + 1) / 2, 0, 1) * 255).astype(np.uint8)


def draw_tracks(img: np.ndarray, points: Any, occluded: Any, *, max_tracks: int = 64) -> np.ndarray:
    """Draw point tracks on a copy of ``img`` (H, W, 3) uint8: each track's visible positions joined by
    lines, a dot where it is in the first frame, colour by track (``ids_to_color`` of track number + 1).

    Args:
        points: (Q, T, 2) float (x, y) [px], TAP-Vid ``target_points``.
        occluded: (Q, T) bool; occluded positions are not drawn.
        max_tracks: draw at most the first this many tracks.
    """
    p = _np(points).astype(np.float64)
    occ = _np(occluded).astype(bool)
    if p.ndim != 3 or p.shape[2] != 2 or occ.shape != p.shape[:2]:
        raise ShapeError(f"draw_tracks expects points (Q, T, 2) and occluded (Q, T), got {p.shape}, {occ.shape}")
    q = min(len(p), max_tracks)
    colors = ids_to_color(np.arange(1, q + 1)[None])[0]
    im = Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8))
    draw = ImageDraw.Draw(im)
    for n in range(q):
        c = tuple(int(x) for x in colors[n])
        for t in range(p.shape[1] - 1):
            if not (occ[n, t] or occ[n, t + 1]):
                draw.line([tuple(p[n, t]), tuple(p[n, t + 1])], fill=c, width=1)
        if not occ[n, 0]:
            x, y = p[n, 0]
            draw.ellipse([x - 1.5, y - 1.5, x + 1.5, y + 1.5], fill=c)
    return np.asarray(im)


def mask_to_color(mask: Any) -> np.ndarray:
    """(H, W) or (1, H, W) bool mask -> (H, W, 3) uint8: True white, False black."""
    m = _plane(mask, "mask").astype(bool)
    return np.repeat(np.where(m, 255, 0).astype(np.uint8)[..., None], 3, axis=-1)


def draw_boxes(
    img: np.ndarray, boxes: Any, valid: Any, colors: Sequence[RGB] | None = None, *, width: int = 1
) -> np.ndarray:
    """Draw xyxy boxes on a copy of ``img``, an (H, W, 3) uint8 RGB image.

    Args:
        boxes: (N, 4) float xyxy [px], e.g. ``box2d_visible[t]``; non-finite boxes are skipped.
        valid: (N,) bool; only True boxes are drawn.
        colors: N RGB triples; default ``ids_to_color`` of instance id n + 1, matching the id map.
        width: line width [px].
    """
    b = _np(boxes).astype(np.float64)
    keep = _np(valid).astype(bool)
    if b.ndim != 2 or b.shape[1] != 4 or keep.shape != (b.shape[0],):
        raise ShapeError(f"draw_boxes expects boxes (N, 4) and valid (N,), got {b.shape} and {keep.shape}")
    if colors is None:
        colors = [tuple(int(c) for c in rgb) for rgb in ids_to_color(np.arange(1, b.shape[0] + 1)[None])[0]]
    im = Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8))
    draw = ImageDraw.Draw(im)
    for n in np.flatnonzero(keep & np.isfinite(b).all(axis=1)):
        x0, y0, x1, y1 = b[n]
        draw.rectangle([min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)], outline=colors[n], width=width)
    return np.asarray(im)


@dataclasses.dataclass(frozen=True)
class SheetLayout:
    """Where ``contact_sheet`` puts everything: ``size`` (W', H') [px]; ``texts``: (line, (x, y) where it is drawn,
    its ink box (x0, y0, x1, y1) as Pillow measures it); ``tiles``: each tile's box (x0, y0, x1, y1), x1 and y1
    exclusive. Boxes never overlap: a label is wrapped at its spaces to its cell's width, and a cell is as wide as
    its largest tile and its longest word."""

    size: tuple[int, int]
    texts: list[tuple[str, tuple[int, int], tuple[int, int, int, int]]]
    tiles: list[tuple[int, int, int, int]]


def _wrap(text: str, font, width: int) -> list[str]:
    """``text`` in lines no wider than ``width`` [px], broken at spaces (a longer word keeps a line of its own)."""
    lines: list[str] = []
    for word in text.split():
        if lines and font.getbbox(f"{lines[-1]} {word}")[2] <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines or [""]


def sheet_layout(labels: Sequence[str], sizes: Sequence[tuple[int, int]], columns: int = 4, *,
                 title: str | None = None) -> SheetLayout:
    """The layout of ``contact_sheet`` for tiles of ``sizes`` ((H, W) [px], scaled) under ``labels``: a grid of
    ``columns``, each cell as wide as the largest tile and the longest word of any label, each label wrapped to that
    width, the title (if any) one line above it (the sheet widened to it where it is wider)."""
    font = ImageFont.load_default()
    line_h = int(font.getbbox("Ag")[3]) + 1
    inner_w = max([w for _, w in sizes] + [int(font.getbbox(word)[2]) for lab in labels for word in lab.split()])
    wrapped = [_wrap(lab, font, inner_w) for lab in labels]
    label_h = max(len(lines) for lines in wrapped) * line_h + _PAD
    cell_w, cell_h = inner_w + _PAD, max(h for h, _ in sizes) + label_h + _PAD
    rows, cols = -(-len(labels) // columns), min(columns, len(labels))
    width = cols * cell_w + _PAD
    texts = []
    head = [title] if title else []
    for n, line in enumerate(head):
        xy = (_PAD, _PAD + n * line_h)
        texts.append((line, xy, _ink(font, line, xy)))
    top = len(head) * line_h + _PAD if head else 0
    tiles = []
    for k, (lines, (h, w)) in enumerate(zip(wrapped, sizes, strict=True)):
        x, y = _PAD + (k % columns) * cell_w, top + _PAD + (k // columns) * cell_h
        for n, line in enumerate(lines):
            texts.append((line, (x, y + n * line_h), _ink(font, line, (x, y + n * line_h))))
        tiles.append((x, y + label_h, x + w, y + label_h + h))
    return SheetLayout((max(width, *(t[2][2] + _PAD for t in texts)) if texts else width,
                        top + rows * cell_h + _PAD), texts, tiles)


def _ink(font, line: str, xy: tuple[int, int]) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = font.getbbox(line)
    return (xy[0] + x0, xy[1] + y0, xy[0] + x1, xy[1] + y1)


def contact_sheet(tiles: Sequence[tuple[str, np.ndarray]], columns: int = 4, scale: int = 1, *,
                  title: str | None = None) -> np.ndarray:
    """Lay labelled images out on a grid, label text above each tile (Pillow's default font).

    Args:
        tiles: (label, (H, W, 3) uint8) pairs; sizes may differ (cells fit the largest).
        columns: tiles per row.
        scale: integer nearest-neighbour upscaling of every tile.
        title: a line of text above the grid (None: none); the sheet is widened to it if it is wider.

    Returns:
        (H', W', 3) uint8 RGB on dark grey, laid out by :func:`sheet_layout`: labels wrapped at spaces to the cells'
        width, so no two texts, nor a text and a tile, overlap at any tile size.
    """
    if not tiles or columns < 1 or scale < 1:
        raise ConfigError("contact_sheet needs at least one tile, columns >= 1 and scale >= 1")
    if any(np.ndim(t) != 3 or np.shape(t)[2] != 3 for _, t in tiles):
        raise ShapeError(f"tiles must be (H, W, 3) uint8, got shapes {[np.shape(t) for _, t in tiles]}")
    imgs = [np.repeat(np.repeat(np.asarray(t, np.uint8), scale, 0), scale, 1) for _, t in tiles]
    font = ImageFont.load_default()
    layout = sheet_layout([label for label, _ in tiles], [im.shape[:2] for im in imgs], columns, title=title)
    sheet = Image.new("RGB", layout.size, _BACKGROUND)
    draw = ImageDraw.Draw(sheet)
    for line, xy, _ in layout.texts:
        draw.text(xy, line, fill=(255, 255, 255), font=font)
    for (x0, y0, _, _), im in zip(layout.tiles, imgs, strict=True):
        sheet.paste(Image.fromarray(np.ascontiguousarray(im)), (x0, y0))
    return np.asarray(sheet)


def save_png(path: str | os.PathLike[str], img: np.ndarray, text: Mapping[str, str] | None = None) -> None:
    """Save an (H, W, 3) uint8 RGB image as PNG, atomically; ``text`` goes into tEXt chunks (key -> value)."""
    from PIL.PngImagePlugin import PngInfo

    a = np.asarray(img)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ShapeError(f"save_png expects (H, W, 3) uint8, got {a.dtype} {a.shape}")
    info = PngInfo()
    for key, value in (text or {}).items():
        info.add_text(key, value)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(a)).save(buf, format="PNG", pnginfo=info)
    atomic_write_bytes(path, buf.getvalue())


def _rgb_tile(rgb: np.ndarray) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    u8 = np.rint(np.clip(np.nan_to_num(rgb.astype(np.float64)), 0, 1) * 255).astype(np.uint8)
    return u8.transpose(1, 2, 0)


def sample_preview(sample: Mapping[str, Any], *, columns: int = 4, scale: int = 1,
                   title: str | None = None) -> np.ndarray:
    """Contact sheet of the first frame / pair of a flowsynth sample dict (the tiles of :func:`preview_tiles`),
    under ``title`` if given (what the sample is: ``flowsynth preview`` names a mixture sample's source there).

    Returns:
        (H', W', 3) uint8 RGB, see :func:`contact_sheet`.

    Raises:
        ConfigError: the sample has no previewable key (:func:`preview_tiles`).
    """
    return contact_sheet(preview_tiles(sample), columns=columns, scale=scale, title=title)


def preview_tiles(sample: Mapping[str, Any]) -> list[tuple[str, np.ndarray]]:
    """The labelled tiles ``sample_preview`` lays out, with their keys: a flow key (``flow_legend``, its rim the
    flow tiles' shared maximum in px) after the flow tiles, and a scale (``depth_colorbar``, its range in m in the
    label) after each depth or distance tile; both at least ``LEGEND_MIN`` px a side.

    Uses whichever of these keys are present: ``rgb`` (T,3,H,W) frames 0 and 1; ``flow_fw`` /
    ``flow_bw`` (T-1,2,H,W) pair 0 with one shared ``max_flow``; masks ``valid_fw``, ``occ_fw``,
    ``occ_bw``, ``motion`` (T-1,1,H,W) pair 0; flows at frame gaps k >= 2 (``flow_fw_k2`` ...) pair 0;
    ``scene_flow_fw`` / ``scene_flow_bw`` (T-1,3,H,W) pair 0; stereo ``rgb_right``, ``depth_right``,
    ``disparity``, ``disparity_right``, ``disparity_occ``, ``disparity_occ_right`` frame 0; ``depth`` /
    ``distance`` (T,1,H,W), ``normals`` (T,3,H,W), id maps ``instance`` / ``category`` / ``asset`` (T,1,H,W), frame 0;
    ``box2d_visible`` (T,N,4) with ``object_valid`` (N,) (and ``visible_pixels`` (T,N) if present)
    drawn on rgb frame 0, or on the instance map when there is no rgb; point tracks ``target_points``
    (Q,T,2) with ``occluded`` (Q,T) drawn the same way (first 64 tracks, visible segments).

    Raises:
        ConfigError: none of the keys above is present.
    """
    s = {k: _np(v) for k, v in sample.items() if isinstance(k, str)}
    tiles: list[tuple[str, np.ndarray]] = []
    if "rgb" in s:
        tiles += [(f"rgb t={t}", _rgb_tile(s["rgb"][t])) for t in range(min(2, len(s["rgb"])))]
    if "rgb_right" in s:
        tiles.append(("rgb_right t=0", _rgb_tile(s["rgb_right"][0])))
    flows = [k for k in ("flow_fw", "flow_bw") if k in s and len(s[k])]
    if flows:
        mags = [np.hypot(*np.nan_to_num(s[k][0], posinf=0.0, neginf=0.0)).max(initial=0.0) for k in flows]
        shared = float(max(mags))
        for k in flows:
            tiles.append((f"{k} 0 (max {shared:.1f} px)", flow_to_color(s[k][0], max_flow=shared or None)))
        h, w = s[flows[0]].shape[-2:]
        tiles.append((f"flow key: rim {shared:.1f} px", flow_legend(shared, *_legend_size(h, w))))
    gapped = [k for k in s if split_gap_key(k) and split_gap_key(k)[1] > 1 and k.startswith("flow_") and len(s[k])]
    for k in gapped:
        mx = float(np.hypot(*np.nan_to_num(s[k][0], posinf=0.0, neginf=0.0)).max(initial=0.0))
        tiles.append((f"{k} 0 (max {mx:.1f} px)", flow_to_color(s[k][0])))
    for k in ("valid_fw", "occ_fw", "occ_bw", "motion"):
        if k in s and len(s[k]):
            tiles.append((f"{k} 0", mask_to_color(s[k][0])))
    for k in ("scene_flow_fw", "scene_flow_bw"):
        if k in s and len(s[k]):
            mx = float(np.linalg.norm(s[k][0], axis=0).max(initial=0.0))
            tiles.append((f"{k} 0 (max {mx:.2g} m)", vectors_to_color(s[k][0])))
    for k in ("depth", "distance"):
        if k in s:
            tiles.append((f"{k} t=0", depth_to_color(s[k][0])))
            span = depth_range(s[k][0])
            if span is not None:
                h, w = _legend_size(*s[k].shape[-2:])
                tiles.append((f"{k} [m]: {span[1]:.3g} to {span[0]:.3g}",
                              depth_colorbar(*span, max(24, h // 3), w)))
    for k in ("depth_right", "disparity", "disparity_right"):  # disparity ~ 1 / depth: same colouring
        if k in s:
            d = s[k][0].astype(np.float64)
            tiles.append((f"{k} t=0", depth_to_color(1.0 / np.where(d > 0, d, np.inf)) if k != "depth_right"
                          else depth_to_color(d)))
    for k in ("disparity_occ", "disparity_occ_right"):
        if k in s:
            tiles.append((f"{k} t=0", mask_to_color(s[k][0])))
    if "normals" in s:
        tiles.append(("normals t=0", normals_to_color(s["normals"][0])))
    for k in ("instance", "category", "asset"):
        if k in s and s[k].ndim == 4:  # per-pixel maps; object tables of the same name are (N,)
            tiles.append((f"{k} t=0", ids_to_color(s[k][0])))
    if "box2d_visible" in s and ("rgb" in s or "instance" in s):
        boxes = s["box2d_visible"][0]
        keep = s["object_valid"].astype(bool) if "object_valid" in s else np.ones(len(boxes), bool)
        if "visible_pixels" in s:
            keep = keep & (s["visible_pixels"][0] > 0)
        base = _rgb_tile(s["rgb"][0]) if "rgb" in s else ids_to_color(s["instance"][0])
        tiles.append(("box2d_visible t=0", draw_boxes(base, boxes, keep)))
    if "target_points" in s and "occluded" in s and ("rgb" in s or "instance" in s):
        base = _rgb_tile(s["rgb"][0]) if "rgb" in s else ids_to_color(s["instance"][0])
        tiles.append((f"tracks ({len(s['target_points'])}) on t=0", draw_tracks(base, s["target_points"],
                                                                               s["occluded"])))
    if not tiles:
        raise ConfigError(f"sample_preview: no previewable key (rgb, flow_fw, depth, ...) in {sorted(s)}")
    return tiles


def _legend_size(h: int, w: int) -> tuple[int, int]:
    """(height, width) of a legend beside (h, w) tiles: theirs, at least ``LEGEND_MIN`` each."""
    return max(int(h), LEGEND_MIN), max(int(w), LEGEND_MIN)
