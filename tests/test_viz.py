"""Visualisation: the Middlebury colour wheel against an independent scalar oracle, colourings,
boxes, contact sheets and the sample preview."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from flowsynth.errors import ConfigError, ShapeError
from flowsynth.viz import (
    LEGEND_MIN,
    contact_sheet,
    depth_colorbar,
    depth_range,
    depth_to_color,
    draw_boxes,
    flow_legend,
    flow_to_color,
    ids_to_color,
    make_colorwheel,
    mask_to_color,
    normals_to_color,
    preview_tiles,
    sample_preview,
    save_png,
    sheet_layout,
)


def _wheel_oracle() -> list[tuple[float, float, float]]:
    """The wheel from its definition (Baker et al. 2011): six hue ramps of 15, 6, 4, 11, 13, 6 steps,
    from red through yellow, green, cyan, blue and magenta back to red."""
    ramps = [
        (15, lambda f: (255, f, 0)),  # red -> yellow, green rises
        (6, lambda f: (255 - f, 255, 0)),  # yellow -> green, red falls
        (4, lambda f: (0, 255, f)),  # green -> cyan, blue rises
        (11, lambda f: (0, 255 - f, 255)),  # cyan -> blue, green falls
        (13, lambda f: (f, 0, 255)),  # blue -> magenta, red rises
        (6, lambda f: (255, 0, 255 - f)),  # magenta -> red, blue falls
    ]
    return [colour(math.floor(255 * i / n)) for n, colour in ramps for i in range(n)]


def _color_oracle(u: float, v: float, max_flow: float) -> tuple[int, int, int]:
    """Scalar Middlebury colouring of one vector (flow_vis / torchvision algorithm)."""
    wheel = _wheel_oracle()
    n = len(wheel)
    u, v = u / max_flow, v / max_flow
    rad = math.hypot(u, v)
    fk = (math.atan2(-v, -u) / math.pi + 1) / 2 * (n - 1)
    k0 = math.floor(fk)
    k1 = (k0 + 1) % n
    f = fk - k0
    out = []
    for c in range(3):
        col = ((1 - f) * wheel[k0][c] + f * wheel[k1][c]) / 255
        col = 1 - rad * (1 - col) if rad <= 1 else col * 0.75
        out.append(math.floor(255 * col))
    return tuple(out)


def test_colorwheel_matches_definition() -> None:
    wheel = make_colorwheel()
    assert wheel.shape == (55, 3) and wheel.dtype == np.uint8
    np.testing.assert_array_equal(wheel, np.array(_wheel_oracle()))


@pytest.mark.parametrize("angle_deg", [0, 30, 90, 135, 180, 200, 270, 333])
@pytest.mark.parametrize("fraction", [1.0, 0.5])
def test_flow_to_color_matches_oracle(angle_deg: float, fraction: float) -> None:
    max_flow = 8.0
    a = math.radians(angle_deg)
    u, v = fraction * max_flow * math.cos(a), fraction * max_flow * math.sin(a)
    flow = np.zeros((2, 2, 3), np.float32)
    flow[:, 0, 0] = [u, v]
    flow[:, 1, 2] = [max_flow, 0.0]  # sets the default normalisation to max_flow
    img = flow_to_color(flow)
    assert img.shape == (2, 3, 3) and img.dtype == np.uint8
    expected = _color_oracle(float(np.float32(u)), float(np.float32(v)), max_flow)
    assert np.abs(img[0, 0].astype(int) - expected).max() <= 1  # float32 vs float64 rounding
    np.testing.assert_array_equal(img[0, 1], [255, 255, 255])  # zero flow is white


def test_flow_to_color_known_directions() -> None:
    flow = np.array([[1.0, -1.0, 0.0, 0.0], [0.0, 0.0, 1.0, -1.0]], np.float32).reshape(2, 1, 4)
    img = flow_to_color(torch.from_numpy(flow))
    np.testing.assert_array_equal(img[0, 0], [255, 0, 0])  # +x: red
    assert img[0, 1, 2] == 255 and img[0, 1, 0] == 0  # -x: cyan-blue
    assert img[0, 2, 0] == 255 and img[0, 2, 2] == 0 and img[0, 2, 1] > 200  # +y (down): orange-yellow
    assert img[0, 3, 2] == 255 and img[0, 3, 1] == 0  # -y (up): blue-violet


def test_flow_to_color_edge_cases() -> None:
    np.testing.assert_array_equal(flow_to_color(np.zeros((2, 3, 4))), 255)
    flow = np.zeros((2, 1, 3), np.float32)
    flow[:, 0, 0] = [np.nan, 1.0]
    flow[:, 0, 1] = [4.0, 0.0]
    flow[:, 0, 2] = [2.0, 0.0]
    img = flow_to_color(flow, max_flow=2.0)
    np.testing.assert_array_equal(img[0, 0], [255, 255, 255])  # non-finite -> zero flow
    np.testing.assert_array_equal(img[0, 2], [255, 0, 0])
    np.testing.assert_array_equal(img[0, 1], [191, 0, 0])  # beyond max_flow: darkened to 75 %
    with pytest.raises(ShapeError):
        flow_to_color(np.zeros((3, 4, 2)))


def test_depth_ids_normals_mask() -> None:
    depth = np.array([[[0.0, 1.0, 2.0, 4.0]]], np.float32)
    img = depth_to_color(depth)
    assert img.shape == (1, 4, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[0, 0], 0)  # no hit
    np.testing.assert_array_equal(img[0, 1], [253, 231, 37])  # nearest: yellow
    np.testing.assert_array_equal(img[0, 3], [68, 1, 84])  # farthest: purple
    np.testing.assert_array_equal(depth_to_color(depth, valid=np.array([[True, False, True, True]]))[0, 1], 0)

    ids = np.arange(64, dtype=np.int32).reshape(1, 8, 8)
    col = ids_to_color(torch.from_numpy(ids))
    np.testing.assert_array_equal(col[0, 0], 0)
    colours = {tuple(c) for c in col.reshape(-1, 3)[1:]}
    assert len(colours) == 63 and (0, 0, 0) not in colours
    np.testing.assert_array_equal(ids_to_color(np.full((2, 2), 5))[1, 1], col[0, 5])  # same id, same colour

    normals = np.zeros((3, 1, 2), np.float32)
    normals[:, 0, 0] = [0.0, 0.0, -1.0]
    rgb = normals_to_color(normals)
    np.testing.assert_array_equal(rgb[0, 0], [128, 128, 0])
    np.testing.assert_array_equal(rgb[0, 1], 0)

    m = mask_to_color(np.array([[[True, False]]]))
    np.testing.assert_array_equal(m, [[[255, 255, 255], [0, 0, 0]]])


def test_draw_boxes() -> None:
    img = np.zeros((20, 30, 3), np.uint8)
    boxes = np.array([[2, 3, 10, 12], [15, 5, 25, 15], [np.nan, 0, 1, 1]], np.float32)
    out = draw_boxes(
        img, boxes, np.array([True, False, True]), colors=[(255, 0, 0), (0, 255, 0), (0, 0, 255)]
    )
    assert out.shape == img.shape and out.dtype == np.uint8 and not img.any()
    np.testing.assert_array_equal(out[3, 2], [255, 0, 0])
    np.testing.assert_array_equal(out[12, 10], [255, 0, 0])
    np.testing.assert_array_equal(out[7, 6], 0)  # interior untouched
    assert not out[..., 1].any() and not out[..., 2].any()  # invalid and non-finite boxes not drawn


def test_contact_sheet_layout() -> None:
    tiles = [(f"t{k}", np.full((10, 16, 3), 40 * k, np.uint8)) for k in range(1, 6)]
    sheet = contact_sheet(tiles, columns=2, scale=2)
    assert sheet.dtype == np.uint8 and sheet.ndim == 3 and sheet.shape[2] == 3
    assert sheet.shape[1] == 2 * (32 + 2) + 2  # columns * (scaled width + pad) + pad
    rows = 3
    label_h = (sheet.shape[0] - 2) // rows - 20 - 2
    assert label_h > 4 and sheet.shape[0] == rows * (20 + label_h + 2) + 2
    y0 = 2 + label_h  # the first tile, below its label
    np.testing.assert_array_equal(sheet[y0 : y0 + 20, 2 : 2 + 32], 40)
    with pytest.raises(ConfigError):
        contact_sheet([])


def _fake_sample(t: int = 3, n: int = 4, h: int = 24, w: int = 32) -> dict:
    g = torch.Generator().manual_seed(0)
    instance = torch.zeros(t, 1, h, w, dtype=torch.int32)
    instance[:, :, 4:12, 5:15] = 1
    instance[:, :, 14:20, 18:30] = 2
    boxes = torch.tensor([[5.0, 4.0, 14.0, 11.0], [18.0, 14.0, 29.0, 19.0], [0, 0, 0, 0], [0, 0, 0, 0]])
    return {
        "rgb": torch.rand(t, 3, h, w, generator=g),
        "flow_fw": torch.randn(t - 1, 2, h, w, generator=g) * 3,
        "flow_bw": torch.randn(t - 1, 2, h, w, generator=g),
        "occ_fw": torch.rand(t - 1, 1, h, w, generator=g) > 0.7,
        "depth": torch.rand(t, 1, h, w, generator=g) * 5,
        "normals": torch.nn.functional.normalize(torch.randn(t, 3, h, w, generator=g), dim=1),
        "instance": instance,
        "box2d_visible": boxes.expand(t, n, 4).clone(),
        "object_valid": torch.tensor([True, True, False, False]),
        "visible_pixels": torch.tensor([[80, 66, 0, 0]] * t),
        "category": torch.tensor([3, 1, 0, 0]),  # object table, not a per-pixel map: ignored
        "K": torch.eye(3),
        "index": 0,
        "seed": 42,
    }


def test_sample_preview_all_keys(tmp_path: Path) -> None:
    sample = _fake_sample()
    img = sample_preview(sample)
    assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    # rgb x2, flow_fw, flow_bw, the flow key, occ_fw, depth, its scale, normals, instance, boxes = 11 tiles -> 3 rows
    # of 4, cells as wide as the legends (LEGEND_MIN) or the longest word of a label ("box2d_visible")
    from PIL import ImageFont

    inner = max(LEGEND_MIN, int(ImageFont.load_default().getbbox("box2d_visible")[2]))
    assert img.shape[1] == 4 * (inner + 2) + 2
    path = tmp_path / "preview.png"
    save_png(path, img)
    with Image.open(path) as im:
        np.testing.assert_array_equal(np.asarray(im), img)
    numpy_sample = {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in sample.items()}
    np.testing.assert_array_equal(sample_preview(numpy_sample), img)
    no_rgb = {k: v for k, v in sample.items() if k != "rgb"}
    assert sample_preview(no_rgb, columns=10).shape[1] == 9 * (inner + 2) + 2  # boxes drawn on the id map
    with pytest.raises(ConfigError):
        sample_preview({"index": 0})


def _overlap(a, b) -> bool:
    """Two boxes (x0, y0, x1, y1), x1 and y1 exclusive, share a pixel."""
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


@pytest.mark.parametrize("size", [(1, 1), (64, 48)])
def test_preview_reads_at_the_smallest_size(size) -> None:
    """The preview of a rendered sample at 1x1 px (the smallest size a config allows) and 64x48 px: it has a flow key
    and a depth scale; no two texts (title, labels), no text and tile, no two tiles overlap, every text lies inside
    the sheet; and the sheet's pixels that are not its background all lie in a text's ink box or a tile (so the boxes
    say where Pillow drew)."""
    import flowsynth as fs
    from flowsynth.cli import PREVIEW_BOUNCING

    W, H = size
    cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, motion="kinematic")
    sample = fs.datasets.BouncingThings(cfg, list(PREVIEW_BOUNCING), seed=0).sample(0)
    tiles = preview_tiles(sample)
    labels = [label for label, _ in tiles]
    assert any(lab.startswith("flow key: rim ") and lab.endswith(" px") for lab in labels), labels
    assert any(lab.startswith("depth [m]: ") for lab in labels), labels
    title = "sample 0 of a_mixture_preset_with_a_long_name.json: source 'things' (bouncing)"
    layout = sheet_layout(labels, [t.shape[:2] for _, t in tiles], 4, title=title)
    boxes = [ink for _, _, ink in layout.texts] + list(layout.tiles)
    for n, a in enumerate(boxes):
        assert 0 <= a[0] and 0 <= a[1] and a[2] <= layout.size[0] and a[3] <= layout.size[1], a
        for b in boxes[n + 1:]:
            assert not _overlap(a, b), (a, b)
    sheet = sample_preview(sample, title=title)
    assert sheet.shape[:2] == layout.size[::-1]
    inside = np.zeros(sheet.shape[:2], bool)
    for x0, y0, x1, y1 in boxes:
        inside[y0:y1, x0:x1] = True
    drawn = (sheet != np.array([32, 32, 32], np.uint8)).any(axis=-1)
    assert not (drawn & ~inside).any(), np.argwhere(drawn & ~inside)[:5]


def test_flow_legend_is_the_key_of_the_flow_tile() -> None:
    """The legend's pixel at offset f r / max_flow from its centre has the colour of flow f in flow_to_color(...,
    max_flow) (within the colour change of the half-pixel rounding); white at the centre, grey outside the disk, all
    white for no motion."""
    m, h, w = 7.5, 49, 61
    key = flow_legend(m, h, w)
    r, cy, cx = (h - 1) / 2, (h - 1) / 2, (w - 1) / 2
    rng = np.random.default_rng(0)
    angles, mags = rng.uniform(-np.pi, np.pi, 40), rng.uniform(0, m, 40)
    flows = np.stack([mags * np.cos(angles), mags * np.sin(angles)])[:, None]  # (2, 1, 40)
    want = flow_to_color(flows, max_flow=m)[0]
    for k in range(40):
        y, x = int(round(cy + flows[1, 0, k] * r / m)), int(round(cx + flows[0, 0, k] * r / m))
        assert np.abs(key[y, x].astype(int) - want[k]).max() <= 24, (k, key[y, x], want[k])
    np.testing.assert_array_equal(key[int(cy), int(cx)], 255)
    np.testing.assert_array_equal(key[0, 0], 32)
    still = flow_legend(0.0, h, w)
    assert (still[int(cy), int(cx) - 24:int(cx) + 25] == 255).all() and (still[int(cy), :5] == 32).all()


def test_depth_colorbar_is_the_scale_of_the_depth_tile() -> None:
    """depth_range is (1 / 99th, 1 / 1st percentile of inverse depth) [m] (numpy); a pixel at depth d in that range
    has the colour of the bar's column (1/d - 1/far) / (1/near - 1/far) (W - 1); purple (far) left, yellow (near)
    right; tick marks at 1, 2, 5 m at the foot of the band (the upper half), their numbers below it."""
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.7, 12.0, (30, 40))
    depth[0, :5] = 0.0  # no hit
    near, far = depth_range(depth)
    inv = 1 / depth[depth > 0]
    assert (near, far) == pytest.approx((1 / np.percentile(inv, 99), 1 / np.percentile(inv, 1)), rel=1e-12)
    width = 200
    bar = depth_colorbar(near, far, 40, width)
    img = depth_to_color(depth)
    lo, hi = 1 / far, 1 / near
    ok = (depth >= near) & (depth <= far)
    for i, j in np.argwhere(ok)[:: 37]:
        col = int(round((1 / depth[i, j] - lo) / (hi - lo) * (width - 1)))
        assert np.abs(bar[0, col].astype(int) - img[i, j]).max() <= 6, (depth[i, j], bar[0, col], img[i, j])
    np.testing.assert_array_equal(bar[0, 0], [68, 1, 84])
    np.testing.assert_array_equal(bar[0, -1], [253, 231, 37])
    for d in (1.0, 2.0, 5.0):
        col = int(round((1 / d - lo) / (hi - lo) * (width - 1)))
        np.testing.assert_array_equal(bar[19, col], 255)
        assert (bar[21:, max(col - 8, 0):col + 8] > 128).all(axis=-1).any(), d  # its number (anti-aliased)
    assert (bar[21:, :] == 32).all(axis=-1).mean() > 0.5  # grey under the band but for the numbers
    np.testing.assert_array_equal(depth_colorbar(near, far, 12, width)[:, 0], [[68, 1, 84]] * 12)  # no room: band only
