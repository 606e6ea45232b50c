"""fs.datasets.Layers, FlyingChairs-style 2D layers: the learning benchmark's draws call for call, flow against an
analytic warp, occlusion against a brute-force layer test, the helper's OpenCV pools within boundary pixels.

Oracles: the helper ``benchmarks/learning/sets.py:chairs2d_pairs`` run under recording wrappers of its generator and
of OpenCV (the draws, masks and matrices it used); textures that are affine functions of the pixel, which bilinear
sampling reproduces exactly (so frame t is known in closed form); a per-pixel Python loop over the layers with its
own inside-tests (ray crossing counted in Python, the ellipse's implicit equation).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from flowsynth.datasets.layer_draws import OUTLINE_PX, Ellipse, Polygon, draw_pair
from flowsynth.datasets.layer_render import render_layers
from flowsynth.datasets.layers import LAYERS_OUTPUTS, layers_pairs

REPO = Path(__file__).resolve().parents[1]
IMAGE_TOL = 2e-5  # bilinear sampling of an affine texture in float64, stored as float32: rounding only
FLOW_TOL = 1e-4  # [px] float32 flow of |flow| up to ~100 px; the helper's float64 -> float32 too


def _sets():
    sys.path.insert(0, str(REPO / "benchmarks" / "learning"))
    import sets

    return sets


_GENERATOR = np.random.default_rng  # the real one, whatever a test patches


class Recorder:
    """A numpy Generator that records every call: (method, args, kwargs, result)."""

    def __init__(self, seed):
        self.rng, self.calls = _GENERATOR(seed), []

    def __getattr__(self, name):
        fn = getattr(self.rng, name)

        def call(*args, **kwargs):
            out = fn(*args, **kwargs)
            self.calls.append((name, args, kwargs, np.array(out).tolist()))
            return out

        return call


def _record_helper(monkeypatch, n, seed, sources):
    """Run the helper with its generator and OpenCV's drawing and warping recorded."""
    import cv2

    sets = _sets()
    rec, drawn, warps = {}, [], []
    real_rng, real_ellipse, real_poly, real_warp = np.random.default_rng, cv2.ellipse, cv2.fillPoly, cv2.warpAffine

    def rng(s):
        rec["r"] = Recorder(s)
        return rec["r"]

    def ellipse(mask, centre, axes, angle, *a):
        out = real_ellipse(mask, centre, axes, angle, *a)
        drawn.append(("ellipse", centre, axes, angle, mask.copy()))
        return out

    def fill(mask, pts, *a):
        out = real_poly(mask, pts, *a)
        drawn.append(("polygon", [tuple(map(int, p)) for p in pts[0]], mask.copy()))
        return out

    def warp(src, M, size, **kw):
        out = real_warp(src, M, size, **kw)
        warps.append((M.copy(), kw, out))
        return out

    monkeypatch.setattr(np.random, "default_rng", rng)
    monkeypatch.setattr(cv2, "ellipse", ellipse)
    monkeypatch.setattr(cv2, "fillPoly", fill)
    monkeypatch.setattr(cv2, "warpAffine", warp)
    pools = sets.chairs2d_pairs(n, seed, sources)
    monkeypatch.setattr(np.random, "default_rng", real_rng)
    return pools, rec["r"].calls, drawn, warps


def _affine_sources(m, h, w, seed=0):
    """m textures whose every channel is a + b x + c y (values in [0.1, 0.9] over the image)."""
    rng = np.random.default_rng(seed)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    coef = rng.uniform(-1, 1, (m, 3, 2))
    out = []
    for c in coef:
        ch = [0.5 + 0.4 * (cx * (xs / (w - 1) - 0.5) + cy * (ys / (h - 1) - 0.5)) for cx, cy in c]
        out.append(torch.stack(ch))
    return torch.stack(out).to(torch.float32), coef


def _texture_value(coef, x, y, h, w):
    """The affine texture of ``coef`` (3, 2) at the points (x, y), (3, ...) float64."""
    return np.stack([0.5 + 0.4 * (cx * (x / (w - 1) - 0.5) + cy * (y / (h - 1) - 0.5)) for cx, cy in coef])


def test_draws_are_the_helpers_call_for_call(monkeypatch):
    """One generator over 12 pairs: the library draws exactly the helper's calls (method, arguments, results) and
    hands OpenCV's drawing and warping exactly the helper's centres, axes, angles, vertices and matrices."""
    w, h, n = 256, 192, 12
    sources = torch.rand(5, 3, h, w)
    _, calls, drawn, warps = _record_helper(monkeypatch, n, 7, sources)
    rec = Recorder(7)
    draws = [draw_pair(rec, w, h, len(sources)) for _ in range(n)]
    assert rec.calls == calls
    shapes = [layer.shape for d in draws for layer in d.layers]
    assert len(shapes) == len(drawn) and {type(s) for s in shapes} == {Ellipse, Polygon}
    for s, got in zip(shapes, drawn):
        if isinstance(s, Ellipse):
            assert got[0] == "ellipse" and got[1:4] == (s.centre, s.axes, s.angle)
        else:
            assert got[0] == "polygon" and got[1] == list(s.points)
    expected = []  # the helper warps: the background by A, then per shape the mask and the texture by B
    for d in draws:
        expected.append(d.motion)
        expected += [m for layer in d.layers for m in (layer.motion, layer.motion)]
    assert len(warps) == len(expected)
    for (M, _, _), m in zip(warps, expected):
        np.testing.assert_array_equal(M, np.array(m))


def _boundary(lay: np.ndarray) -> np.ndarray:
    """Pixels with a 4-neighbour of another layer (or at 1 px of one: the 3x3 neighbourhood)."""
    p = np.pad(lay, 1, mode="edge")
    h, w = lay.shape
    out = np.zeros(lay.shape, bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out |= p[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] != lay
    return out


def test_pools_match_the_helpers_but_for_boundary_pixels(monkeypatch):
    """At the same seed and sources the library's pool is the helper's: the layer maps of both frames (the helper's
    from its OpenCV masks) differ only on pixels next to a layer boundary, on under 1.5% of pixels; the flow is the
    helper's wherever the frame-1 layers agree; frame 1 is the helper's there bit for bit, and frame 2 within
    OpenCV's 1/32 px rounding of the sampling position (smooth sources) away from boundaries."""
    w, h, n = 128, 96, 8
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    sources = torch.stack([torch.stack([0.5 + 0.4 * torch.sin(xs / (6 + j)), 0.5 + 0.4 * torch.cos(ys / (5 + j)),
                                        0.5 + 0.4 * torch.sin((xs + ys) / (9 + j))]) for j in range(6)]).float()
    (img1, img2, flow, valid), _, drawn, warps = _record_helper(monkeypatch, n, 3, sources)
    lib = layers_pairs(n, 3, sources, outputs=("rgb", "flow_fw", "instance"))
    assert valid.min() == 1  # the helper's flow is defined everywhere, as the library's
    rng = np.random.default_rng(3)
    counts = [len(draw_pair(rng, w, h, len(sources)).layers) for _ in range(n)]
    assert len(warps) == sum(1 + 2 * c for c in counts)
    k = 0
    mismatch = total = 0
    for i, n_shapes in enumerate(counts):
        warps_i, warps = warps[:1 + 2 * n_shapes], warps[1 + 2 * n_shapes:]
        ref1, ref2 = np.zeros((h, w), np.int64), np.zeros((h, w), np.int64)
        for s in range(n_shapes):
            ref1[drawn[k + s][-1].astype(bool)] = s + 1
            ref2[warps_i[1 + 2 * s][2].astype(bool)] = s + 1
        k += n_shapes
        for t, ref in ((0, ref1), (1, ref2)):
            got = lib["instance"][i, t, 0].numpy()
            bad = got != ref
            assert not (bad & ~_boundary(got)).any(), (i, t)
            mismatch, total = mismatch + int(bad.sum()), total + bad.size
        agree = lib["instance"][i, 0, 0].numpy() == ref1
        d = (lib["flow_fw"][i, 0] - flow[i]).norm(dim=0).numpy()
        assert d[agree].max() <= FLOW_TOL
        assert torch.equal(lib["rgb"][i, 0][:, torch.from_numpy(agree)], img1[i][:, torch.from_numpy(agree)])
        inner = ~_boundary(ref2) & ~_boundary(lib["instance"][i, 1, 0].numpy())
        inner[:2], inner[-2:], inner[:, :2], inner[:, -2:] = False, False, False, False
        diff = (lib["rgb"][i, 1] - img2[i]).abs().amax(0).numpy()[inner]
        assert diff.max() < 0.02 and diff.mean() < 2e-3, (diff.max(), diff.mean())
    assert mismatch / total < 0.015, mismatch / total


@pytest.mark.parametrize("seed", [0, 5])
def test_frames_and_flow_against_an_analytic_warp(seed):
    """Affine textures: every pixel of frame t (3 frames) is its layer's texture at M^-t q, in closed form; frame t+1
    sampled bilinearly at p + flow_fw(p) is frame t at p, and frame t at q + flow_bw(q) is frame t+1 at q, wherever
    the four pixels around the target are of the pixel's own layer (tolerance IMAGE_TOL)."""
    w, h, T = 96, 64, 3
    src, coef = _affine_sources(6, h, w, seed)
    draw = draw_pair(np.random.default_rng(seed), w, h, len(src), motion_scale=1.5)
    out = render_layers(draw, src.__getitem__, w, h, T, ("rgb", "flow_fw", "flow_bw", "instance"))
    mats = [np.vstack([np.array(m), [0, 0, 1]]) for m in [draw.motion] + [la.motion for la in draw.layers]]
    texs = [draw.background] + [la.texture for la in draw.layers]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    for t in range(T):
        lay = out["instance"][t, 0].numpy()
        for k in np.unique(lay):
            inv = np.linalg.matrix_power(np.linalg.inv(mats[k]), t)
            u, v = inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2], inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]
            m = (lay == k) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)  # sampled inside the source
            want = _texture_value(coef[texs[k]], u, v, h, w)
            assert np.abs(out["rgb"][t].numpy()[:, m] - want[:, m]).max() <= IMAGE_TOL
    checked = 0
    for t in range(T - 1):
        for key, src_t, dst_t in (("flow_fw", t, t + 1), ("flow_bw", t + 1, t)):
            f = out[key][t].numpy().astype(np.float64)
            tx, ty = xs + f[0], ys + f[1]
            lay_s, lay_d = out["instance"][src_t, 0].numpy(), out["instance"][dst_t, 0].numpy()
            x0, y0 = np.floor(tx).astype(int), np.floor(ty).astype(int)
            ok = (x0 >= 0) & (x0 < w - 1) & (y0 >= 0) & (y0 < h - 1)
            x0c, y0c = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
            for dy in (0, 1):
                for dx in (0, 1):
                    ok &= lay_d[y0c + dy, x0c + dx] == lay_s
            for k in np.unique(lay_s):  # the four pixels are sampled 2 px or more inside their texture
                inv = np.linalg.matrix_power(np.linalg.inv(mats[k]), src_t)
                u, v = inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2], inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]
                ok &= (lay_s != k) | ((u >= 3) & (u <= w - 4) & (v >= 3) & (v <= h - 4))
            img = out["rgb"][dst_t].numpy().astype(np.float64)
            ax, ay = tx - x0c, ty - y0c
            warped = (img[:, y0c, x0c] * (1 - ax) * (1 - ay) + img[:, y0c, x0c + 1] * ax * (1 - ay)
                      + img[:, y0c + 1, x0c] * (1 - ax) * ay + img[:, y0c + 1, x0c + 1] * ax * ay)
            src_img = out["rgb"][src_t].numpy()
            assert np.abs(warped[:, ok] - src_img[:, ok]).max() <= 2 * IMAGE_TOL
            checked += int(ok.sum())
    assert checked > 0.5 * (T - 1) * 2 * h * w


# -- brute force: per pixel, loop over the layers, with inside-tests of its own ---------------------------------------
def _inside_bf(shape, x: float, y: float) -> bool:
    if isinstance(shape, Ellipse):
        a = math.radians(round(shape.angle))
        dx, dy = x - shape.centre[0], y - shape.centre[1]
        u, v = math.cos(a) * dx + math.sin(a) * dy, -math.sin(a) * dx + math.cos(a) * dy
        return (u / (shape.axes[0] + OUTLINE_PX)) ** 2 + (v / (shape.axes[1] + OUTLINE_PX)) ** 2 <= 1
    pts, crossings = shape.points, 0
    for (x0, y0), (x1, y1) in zip(pts, pts[1:] + pts[:1]):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            crossings += 1
        ex, ey = x1 - x0, y1 - y0
        s = min(max(((x - x0) * ex + (y - y0) * ey) / max(ex * ex + ey * ey, 1), 0.0), 1.0)
        if math.hypot(x - x0 - s * ex, y - y0 - s * ey) <= OUTLINE_PX:
            return True
    return crossings % 2 == 1


def _top_bf(draw, mats, t: int, x: float, y: float, w: int, h: int) -> int:
    """The topmost layer at (x, y) of frame t: a shape counts where it lies in frame 0's image."""
    top = 0
    for k, layer in enumerate(draw.layers, start=1):
        inv = np.linalg.inv(np.linalg.matrix_power(mats[k], t))  # the oracle inverts the power; the library powers
        u, v = inv[0] @ (x, y, 1.0), inv[1] @ (x, y, 1.0)  # the inverse
        if _inside_bf(layer.shape, u, v) and -0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5:
            top = k
    return top


@pytest.mark.parametrize("seed", [1, 2])
def test_occlusion_validity_and_layers_against_brute_force(seed):
    """instance, valid, oof and occ both ways over 3 frames, per pixel: the topmost layer by a loop over the layers
    (a shape counts in frame 0's image), the target by the pixel's layer's motion, out of frame when the target leaves
    the image, occluded when out of the image or when the topmost layer at the target in the other frame is another
    one; valid everywhere (docs/conventions.md: the flow is defined, also out of frame). Equal on every pixel."""
    w, h, T = 48, 36, 3
    src, _ = _affine_sources(4, h, w)
    draw = draw_pair(np.random.default_rng(seed), w, h, len(src), motion_scale=2.0)
    out = render_layers(draw, src.__getitem__, w, h, T, LAYERS_OUTPUTS)
    mats = [np.vstack([np.array(m), [0, 0, 1]]) for m in [draw.motion] + [la.motion for la in draw.layers]]
    occluded = left = 0
    for t in range(T):
        lay = np.array([[_top_bf(draw, mats, t, x, y, w, h) for x in range(w)] for y in range(h)])
        np.testing.assert_array_equal(out["instance"][t, 0].numpy(), lay)
    for t in range(T - 1):
        for d, (s, r) in (("fw", (t, t + 1)), ("bw", (t + 1, t))):
            lay = out["instance"][s, 0].numpy()
            for y in range(h):
                for x in range(w):
                    m = mats[lay[y, x]] if r > s else np.linalg.inv(mats[lay[y, x]])
                    tx, ty = m[0] @ (x, y, 1.0), m[1] @ (x, y, 1.0)
                    inside = -0.5 <= tx < w - 0.5 and -0.5 <= ty < h - 0.5
                    occ = not inside or _top_bf(draw, mats, r, tx, ty, w, h) != lay[y, x]
                    assert bool(out[f"valid_{d}"][t, 0, y, x])  # the flow is defined at every pixel
                    assert bool(out[f"oof_{d}"][t, 0, y, x]) == (not inside)
                    assert bool(out[f"occ_{d}"][t, 0, y, x]) == occ, (d, t, x, y)
                    np.testing.assert_allclose(out[f"flow_{d}"][t, :, y, x].numpy(), [tx - x, ty - y], atol=FLOW_TOL)
                    occluded += occ and inside
                    left += not inside
    assert occluded > 0, "no pixel occluded inside the image: the layer test went untested"
    assert left > 0, "no target leaves the image: valid and oof there went untested"
