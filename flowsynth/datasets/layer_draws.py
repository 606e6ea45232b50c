"""The draws of a FlyingChairs-style layered pair: a background and 2-5 shapes (ellipses and polygons), each under its
own random affine motion, drawn from a numpy ``Generator`` in a fixed order.

``draw_pair`` consumes the generator exactly as the learning benchmark's ``chairs2d_pairs`` loop body does
(benchmarks/learning/sets.py), call for call: the background's texture, its motion, the number of shapes, then per
shape its texture, centre, kind, outline and motion. So one generator over n pairs gives that helper's draws, shapes
and motions. Sizes and shifts scale with ``width / 128`` (the helper's shapes and shifts were set at 128 px wide).

A shape is what OpenCV's ``cv2.ellipse`` / ``cv2.fillPoly`` fill, written as an analytic inside-test in the shape's
own coordinates (pixel centres at integers, x right, y down): OpenCV fills every pixel its outline touches, which is
the exact shape grown by ``OUTLINE_PX``, and rounds an ellipse's angle to a whole degree. So frame t's mask at q is
``inside(M^-t q)``, exact, for the shape's motion M.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

__all__ = ["BASE_WIDTH", "OUTLINE_PX", "Ellipse", "PairDraw", "Polygon", "ShapeLayer", "affine", "draw_pair"]

BASE_WIDTH = 128
"""[px] the width the shapes' sizes and the shifts are given at; they scale with width / BASE_WIDTH."""
OUTLINE_PX = 0.5
"""[px] what OpenCV's filled shapes add around the exact outline: a pixel whose centre lies within this of the shape
is filled (its one-pixel outline). Measured at 256x192 over 200 of the helper's shapes of each kind, the pixels
whose inside-test disagrees with OpenCV's mask: ellipses 2.5% of their area at 0, 0.5% at 0.5; polygons 4.6% at 0,
0.8% at 0.5."""


def affine(rng: np.random.Generator, shift_px: float, rot: float, zoom: float, size: tuple[int, int]) -> np.ndarray:
    """A (2, 3) float64 affine map of pixel coordinates about the centre of an image of ``size`` (w, h): rotation by
    an angle uniform in [-rot, rot] [rad], scale exp(uniform in [-zoom, zoom]), then a translation of standard
    normal components times ``shift_px`` [px]. Draws uniform, uniform, normal(2), in that order."""
    a = rng.uniform(-rot, rot)
    s = np.exp(rng.uniform(-zoom, zoom))
    c = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2])
    R = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t = c - R @ c + rng.normal(size=2) * shift_px
    return np.concatenate([R, t[:, None]], 1)


@dataclasses.dataclass(frozen=True)
class Ellipse:
    """A filled ellipse as ``cv2.ellipse(img, centre, axes, angle, 0, 360, 1, -1)`` draws it."""

    centre: tuple[int, int]
    """(x, y) [px]."""
    axes: tuple[int, int]
    """Semi-axes (along the turned x, along the turned y) [px]."""
    angle: float
    """Turn from +x towards +y (clockwise on screen) [deg], as drawn; the shape turns by it rounded to a whole
    degree, as OpenCV draws it."""

    def bounds(self) -> tuple[float, float, float, float]:
        """(x min, y min, x max, y max) [px] of a box that holds the filled ellipse."""
        r = max(self.axes) + OUTLINE_PX
        return self.centre[0] - r, self.centre[1] - r, self.centre[0] + r, self.centre[1] + r

    def inside(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Whether the points (x, y) (float64 tensors of one shape, [px]) lie in the filled ellipse (bool)."""
        t = np.radians(np.rint(self.angle))
        dx, dy = x - self.centre[0], y - self.centre[1]
        u, v = dx * np.cos(t) + dy * np.sin(t), dy * np.cos(t) - dx * np.sin(t)
        return (u / (self.axes[0] + OUTLINE_PX)) ** 2 + (v / (self.axes[1] + OUTLINE_PX)) ** 2 <= 1.0

    def to_dict(self) -> dict:
        return {"kind": "ellipse", "centre": list(self.centre), "axes": list(self.axes), "angle": self.angle}


@dataclasses.dataclass(frozen=True)
class Polygon:
    """A filled polygon as ``cv2.fillPoly(img, [points], 1)`` draws it: even-odd interior (a polygon whose edges
    cross has holes where they overlap), its edges included."""

    points: tuple[tuple[int, int], ...]
    """Vertices (x, y) [px], in order; the last joins the first."""

    def bounds(self) -> tuple[float, float, float, float]:
        """(x min, y min, x max, y max) [px] of a box that holds the filled polygon."""
        xs, ys = [p[0] for p in self.points], [p[1] for p in self.points]
        return min(xs) - OUTLINE_PX, min(ys) - OUTLINE_PX, max(xs) + OUTLINE_PX, max(ys) + OUTLINE_PX

    def inside(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Whether the points (x, y) (float64 tensors of one shape, [px]) lie in the filled polygon (bool)."""
        inside = torch.zeros(x.shape, dtype=torch.bool)
        near = torch.zeros(x.shape, dtype=torch.bool)
        n = len(self.points)
        for k in range(n):
            (x0, y0), (x1, y1) = self.points[k], self.points[(k + 1) % n]
            if y0 != y1:  # even-odd: a ray towards -x crosses this edge
                xc = x0 + (y - y0) * ((x1 - x0) / (y1 - y0))
                inside ^= ((y0 > y) != (y1 > y)) & (x < xc)
            ex, ey = x1 - x0, y1 - y0
            s = ((x - x0) * ex + (y - y0) * ey) / max(ex * ex + ey * ey, 1)
            s = s.clamp(0.0, 1.0)
            near |= (x - x0 - s * ex) ** 2 + (y - y0 - s * ey) ** 2 <= OUTLINE_PX ** 2
        return inside | near

    def to_dict(self) -> dict:
        return {"kind": "polygon", "points": [list(p) for p in self.points]}


@dataclasses.dataclass(frozen=True)
class ShapeLayer:
    """One shape of a pair: its outline in frame 0, its texture and its motion."""

    shape: Ellipse | Polygon
    texture: int
    """Index of its texture among the pair's sources."""
    motion: tuple[tuple[float, ...], ...]
    """(2, 3) affine map [px] of frame t's points to frame t + 1's."""

    def to_dict(self) -> dict:
        return {**self.shape.to_dict(), "texture": self.texture, "motion": [list(r) for r in self.motion]}


@dataclasses.dataclass(frozen=True)
class PairDraw:
    """Everything drawn for one sample: the background and its motion, the shapes from bottom to top."""

    background: int
    """Index of the background's source."""
    motion: tuple[tuple[float, ...], ...]
    """(2, 3) affine map [px] of the background, frame t to t + 1."""
    layers: tuple[ShapeLayer, ...]
    """The shapes in drawing order: layer k + 1 covers layers 0..k (0 is the background)."""

    def to_dict(self) -> dict:
        """JSON-compatible: every number as drawn (float64 values round-trip through JSON exactly)."""
        return {"background": self.background, "motion": [list(r) for r in self.motion],
                "layers": [layer.to_dict() for layer in self.layers]}


def _matrix(m: np.ndarray) -> tuple[tuple[float, ...], ...]:
    return tuple(tuple(float(v) for v in row) for row in m)


def draw_pair(rng: np.random.Generator, width: int, height: int, n_sources: int,
              motion_scale: float = 1.0) -> PairDraw:
    """Draw one pair's layers from ``rng``, in the order of ``chairs2d_pairs``' loop body (module docstring).

    Args:
        rng: the generator; advanced by exactly the helper's draws for one pair.
        width, height: image size [px]; sizes and shifts scale with width / BASE_WIDTH.
        n_sources: number of textures the background and the shapes pick from (uniformly, with repetition).
        motion_scale: multiplies every shift, rotation and log-zoom range (0: nothing moves).

    Returns:
        the ``PairDraw``: the background's source and motion, then 2-5 layers, each an ellipse (semi-axes 6-30 px
        times the scale) or a polygon (3-7 vertices at 6-30 px from its centre, in angle order) centred in the
        middle 80% of the image, with a shift of 1-6 px (times the scale) a frame.
    """
    k = width / BASE_WIDTH
    background = int(rng.integers(n_sources))
    A = affine(rng, 1.5 * k * motion_scale, 0.05 * motion_scale, 0.05 * motion_scale, (width, height))
    layers = []
    for _shape in range(rng.integers(2, 6)):
        texture = int(rng.integers(n_sources))
        centre = (int(rng.uniform(0.1, 0.9) * width), int(rng.uniform(0.1, 0.9) * height))
        if rng.uniform() < 0.5:
            axes = (int(k * rng.uniform(6, 30)), int(k * rng.uniform(6, 30)))
            shape = Ellipse(centre, axes, float(rng.uniform(0, 180)))
        else:
            n_pts = rng.integers(3, 8)
            ang = np.sort(rng.uniform(0, 2 * np.pi, n_pts))
            r = k * rng.uniform(6, 30, n_pts)
            pts = np.stack([centre[0] + r * np.cos(ang), centre[1] + r * np.sin(ang)], 1).astype(np.int32)
            shape = Polygon(tuple((int(px), int(py)) for px, py in pts))
        B = affine(rng, rng.uniform(1.0, 6.0) * k * motion_scale, 0.15 * motion_scale, 0.1 * motion_scale,
                   (width, height))
        layers.append(ShapeLayer(shape, texture, _matrix(B)))
    return PairDraw(background, _matrix(A), tuple(layers))
