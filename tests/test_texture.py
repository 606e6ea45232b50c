"""Texture at pixel scale: screen-space material sampling, per-wall materials, footprint filtering against a
supersampled reference (no aliasing), mip-mapped photographs tiled at pixel scale, light exposure."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

import flowsynth as fs
from flowsynth.scene.assets import ROOM_WALLS, room_walls
from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.appearance.lights import Light
from flowsynth.appearance.materials import sample_material
from flowsynth.appearance.textures import mip_pyramid
from flowsynth.scene.sampling import ROOM_CATEGORY, expose_lights, sample_scene, wall_distances
from flowsynth.stats import textureless_fraction

AMBIENT = [Light("ambient", (1.0, 1.0, 1.0), 1.0)]  # flat mode then renders radiance = albedo exactly


def tilted_plane(W: int, H: int, material: dict, tilt_deg: float = 60.0) -> tuple[fs.Scene, np.ndarray]:
    """A 40 m square plane 4 m in front of the camera, tilted about the image x axis (receding upwards).
    Returns the scene and the plane's world_T_obj (object frame: the plane is z = 0)."""
    cam = fs.Camera.from_fov(W, H, 60.0)
    scene = fs.Scene(cam, num_frames=1)
    quad = trimesh.Trimesh([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0]], [[0, 1, 2], [0, 2, 3]],
                           process=False)
    a = math.radians(tilt_deg)
    P = np.eye(4)
    P[:3, :3] = [[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]]
    P[:3, 3] = [0.0, 0.0, 4.0]
    scene.add_object(quad, P, material=material)
    scene.lights = AMBIENT
    return scene, P


def pixel_centre_points(scene: fs.Scene, P: np.ndarray) -> np.ndarray:
    """Object-frame (x, y) [m] where each pixel-centre ray meets the plane z_obj = 0 (numpy ray casting)."""
    K = scene.camera.K
    W, H = scene.camera.width, scene.camera.height
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    n, o = P[:3, 2], P[:3, 3]
    t = (o @ n) / (d @ n)
    X = d * t[..., None] - o
    return np.stack([X @ P[:3, 0], X @ P[:3, 1]], -1)


def to_linear(rgb: torch.Tensor) -> np.ndarray:
    c = rgb[0].numpy().astype(np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def test_checks_are_filtered_like_a_supersampled_reference():
    W, H = 64, 48
    colors = [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]
    mat = {"texture": "checks", "scale": 9.0, "colors": colors, "specular": 0.0}  # cells of 11 cm: 0.3-10 px
    scene, P = tilted_plane(W, H, mat)
    one = to_linear(fs.render(scene, ["rgb"], render_mode="flat")["rgb"])[0]
    ref = to_linear(fs.render(scene, ["rgb"], render_mode="flat", spp=256)["rgb"])[0]
    xy = pixel_centre_points(scene, P) * 9.0
    parity = (np.floor(xy[..., 0]).astype(int) + np.floor(xy[..., 1]).astype(int)) & 1
    point = np.where(parity == 1, 0.0, 1.0)  # the unfiltered lookup at the pixel centre (colour a where even)
    err_filtered = np.abs(one - ref).mean()
    err_point = np.abs(point - ref).mean()
    print(f"checks: |filtered - ref| {err_filtered:.4f}, |point - ref| {err_point:.4f}")
    assert err_point > 0.15  # the pattern does alias when point sampled
    assert err_filtered < 0.3 * err_point
    far = xy[..., 1] > np.percentile(xy[..., 1], 75)  # the distant quarter: sub-pixel cells
    assert np.abs(one - ref)[far].mean() < 0.3 * np.abs(point - ref)[far].mean()


@pytest.mark.parametrize("angle", [0.0, 0.7, 2.5])
def test_stripes_follow_their_angle_like_a_numpy_reference(angle):
    """Stripes rotated by the layer's ``angle`` on a plane facing the camera (flat mode, white ambient light:
    radiance = albedo) agree with numpy stripes of the rotated pixel-centre points, away from stripe edges
    (where the box filter mixes the two colours). A swapped or wrong cos/sin of the angle fails."""
    W, H, scale = 96, 72, 1.5  # 0.67 m stripes at 4 m: ~16 px wide, filter ~0.03 cycles
    mat = {"texture": "stripes", "scale": scale, "angle": angle, "colors": [[1.0] * 3, [0.0] * 3],
           "specular": 0.0}
    scene, P = tilted_plane(W, H, mat, tilt_deg=0.0)
    got = to_linear(fs.render(scene, ["rgb"], render_mode="flat")["rgb"])[0]
    q = pixel_centre_points(scene, P)
    x = (math.cos(angle) * q[..., 0] - math.sin(angle) * q[..., 1]) * scale  # the first rotated coordinate
    frac = x - np.floor(x)
    ref = np.where(frac < 0.5, 1.0, 0.0)  # colour a (white) on the first half of each period
    inner = (np.abs(frac - 0.5) > 0.05) & (np.minimum(frac, 1.0 - frac) > 0.05)
    print(f"stripes at {angle} rad: {inner.mean():.3f} of pixels away from edges, max |got - ref| there "
          f"{np.abs(got - ref)[inner].max():.2e}")
    assert inner.mean() > 0.6 and 0.2 < ref[inner].mean() < 0.8
    assert np.abs(got - ref)[inner].max() < 1e-4


def test_image_is_mip_mapped_like_a_supersampled_reference(tmp_path):
    W, H = 64, 48
    rng = np.random.default_rng(3)
    Image.fromarray(rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)).save(tmp_path / "noise.png")
    mat = {"texture": "image", "image": str(tmp_path / "noise.png"), "scale": 0.25, "specular": 0.0}
    scene, P = tilted_plane(W, H, mat, tilt_deg=30.0)  # 128 texels per 4 m: ~5-25 texels per pixel
    one = to_linear(fs.render(scene, ["rgb"], render_mode="flat")["rgb"])
    ref = to_linear(fs.render(scene, ["rgb"], render_mode="flat", spp=256)["rgb"])
    img = mip_pyramid(tmp_path / "noise.png")[0].astype(np.float64)  # linear RGB, (h, w, 3)
    xy = pixel_centre_points(scene, P) * 0.25
    cols = np.floor((xy[..., 0] % 1.0) * 128).astype(int)
    rows = np.floor((1.0 - xy[..., 1] % 1.0) * 128).astype(int) % 128
    point = img[rows, cols].transpose(2, 0, 1)  # nearest texel: what an unfiltered lookup sees
    err_filtered = np.abs(one - ref).mean()
    err_point = np.abs(point - ref).mean()
    print(f"image: |mip - ref| {err_filtered:.4f}, |point - ref| {err_point:.4f}")
    assert err_filtered < 0.3 * err_point


def test_mip_pyramid_levels_halve_and_keep_the_mean(tmp_path):
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 256, (37, 50, 3), dtype=np.uint8)).save(tmp_path / "odd.png")
    levels = mip_pyramid(tmp_path / "odd.png")
    assert [lv.shape[:2] for lv in levels][:3] == [(37, 50), (19, 25), (10, 13)] and levels[-1].shape[:2] == (1, 1)
    base = levels[0].astype(np.float64)
    np.testing.assert_allclose(levels[1][3, 4], base[6:8, 8:10].reshape(-1, 3).mean(0), rtol=1e-5)
    for lv in levels:
        assert abs(lv.mean() - base.mean()) < 0.05


def test_screen_space_materials_follow_the_pixel_size(tmp_path):
    Image.fromarray(np.zeros((30, 80, 3), np.uint8)).save(tmp_path / "flat.png")
    for fam in ("noise", "value", "cells", "stripes", "checks", "image"):
        for pixel_size in (0.002, 0.02):
            for s in range(5):
                m = sample_material(np.random.default_rng(s), [fam], tmp_path, pixel_size=pixel_size,
                                    texture_px=(2.0, 64.0))
                px = 1.0 / (m["scale"] * pixel_size)  # the pattern's period on screen [px]
                if fam in ("noise", "value", "cells"):
                    assert 0.6 * 64 <= px <= 64 and px / 2 ** (m["octaves"] - 1) >= 2.0
                    assert px / 2 ** m["octaves"] < 2.0  # octaves reach down to the smallest size
                elif fam == "image":
                    assert 0.7 * 80 <= px <= 1.4 * 80  # 0.7-1.4 px per texel: tiled, not stretched
                else:
                    assert 8.0 <= px <= 32.0
                if fam != "image":
                    assert 2.0 * 4 <= 1.0 / (m["grain_scale"] * pixel_size) <= 2.0 * 8


def test_each_room_face_is_its_own_textured_object():
    cfg = BouncingThingsConfig(width=64, height=48, num_frames=2, motion="kinematic")
    scene = sample_scene(cfg, 0, 1)
    walls = [o for o in scene.objects if o.background]
    assert len(walls) == len(ROOM_WALLS) and all(o.category == ROOM_CATEGORY for o in walls)
    assert len({repr(o.material) for o in walls}) == 6 and all(o.material["texture"] != "solid" for o in walls)
    expected = room_walls(*cfg.room_bounds)
    for o, m in zip(walls, expected):
        np.testing.assert_array_equal(o.mesh.vertices, m.vertices)
    solid = BouncingThingsConfig(width=64, height=48, num_frames=2, motion="kinematic", texture_families=("solid",))
    assert all(o.material["texture"] == "solid" for o in sample_scene(solid, 0, 1).objects)


def test_wall_distances_match_the_ray_caster():
    cfg = BouncingThingsConfig(width=64, height=48, num_frames=1, motion="static")
    scene = sample_scene(cfg, 0, 2)
    room = fs.Scene(scene.camera, num_frames=1)
    room.set_camera_poses(scene.world_T_cam)
    for m in room_walls(*cfg.room_bounds):
        room.add_object(m)
    out = fs.render(room, ["distance", "instance"])
    dist, inst = out["distance"][0, 0].numpy(), out["instance"][0, 0].numpy()
    got = wall_distances(scene.camera, scene.world_T_cam[0], *cfg.room_bounds)
    for w in range(6):
        seen = dist[inst == w + 1]
        if seen.size > 0.05 * dist.size:  # a face that fills a good share of the image
            assert got[w] == pytest.approx(float(np.median(seen)), rel=0.15), ROOM_WALLS[w]


def test_expose_lights_sets_the_median_radiance():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    nrm = np.tile([0.0, 0.0, 1.0], (3, 1))
    lights = [Light("point", (1.0, 1.0, 1.0), 2.0, position=(0.0, 0.0, 2.0)), Light("ambient", (1, 1, 1), 0.1)]
    out = expose_lights(lights, pts, nrm, 0.5)
    I = out[0].intensity
    radiance = [I * 2.0 / r ** 3 for r in (2.0, 5.0 ** 0.5, 13.0 ** 0.5)]  # I cos / r^2 with cos = 2 / r
    assert np.median(radiance) == pytest.approx(0.5) and out[1] == lights[1]


def test_default_samples_carry_texture_in_every_render_mode():
    # The measured 512x384 figures are in benchmarks/accuracy/texture.py; this small run guards the mechanism.
    for mode in ("flat", "direct"):
        cfg = BouncingThingsConfig(width=128, height=96, num_frames=1, render_mode=mode, motion="static")
        ds = fs.datasets.BouncingThings(cfg, outputs=["rgb"], seed=0)
        rgb = [ds.sample(i)["rgb"] for i in range(3)]
        flat = np.mean([textureless_fraction(x) for x in rgb])
        grey = np.mean([float(x.mean()) for x in rgb])
        print(mode, flat, grey)
        assert flat < 0.45 and 0.3 < grey < 0.7


def _hash3(x, y, seed: int) -> np.ndarray:
    """numpy port of flowsynth.kernels.texture.hash3 (lowbias32 finaliser), uint32 arithmetic."""
    u = np.uint32
    with np.errstate(over="ignore"):
        h = u(seed % 2**32) * u(0x27D4EB2F) + np.asarray(x).astype(np.int64).astype(u) * u(0x165667B1)
        h = (h ^ np.asarray(y).astype(np.int64).astype(u) * u(0x3C6EF372)) + u(0x7F4A7C15)
        h = h ^ (h >> u(16))
        h = h * u(0x7FEB352D)
        h = h ^ (h >> u(15))
        h = h * u(0x68E31DA4)
        return h ^ (h >> u(16))


def _worley(q: np.ndarray, seed: int) -> np.ndarray:
    """Brute-force Worley cells: for each point, the value of the nearest jittered lattice feature among the
    3x3 cells around it (the docstring of flowsynth.kernels.texture.cells), float64."""
    unit = lambda h: (h >> np.uint32(8)).astype(np.float64) / 16777216.0
    f = np.floor(q)
    best = np.full(q.shape[:-1], np.inf)
    value = np.zeros(q.shape[:-1])
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            cx, cy = f[..., 0] + dx, f[..., 1] + dy
            px = cx + unit(_hash3(cx, cy, seed))
            py = cy + unit(_hash3(cx, cy, seed + 1))
            d2 = (q[..., 0] - px) ** 2 + (q[..., 1] - py) ** 2
            nearer = d2 < best
            best = np.where(nearer, d2, best)
            value = np.where(nearer, unit(_hash3(cx, cy, seed + 2)), value)
    return value


def test_cells_match_a_brute_force_worley_reference():
    """One octave of "cells" on a plane facing the camera, coarse enough that the octave is not faded: flat
    mode under a white ambient light renders the pattern value itself (colours black and white). A numpy
    Worley oracle at the pixel-centre points agrees except where a pixel centre lies within float32 rounding
    of a cell border."""
    W, H, seed = 128, 96, 12345
    mat = {"texture": "cells", "octaves": 1, "scale": 2.5, "seed": seed, "colors": [[0.0] * 3, [1.0] * 3],
           "specular": 0.0}
    scene, P = tilted_plane(W, H, mat, tilt_deg=0.0)  # 0.4 m cells, ~11 px at 4 m: octave weight 1 everywhere
    got = to_linear(fs.render(scene, ["rgb"], render_mode="flat")["rgb"])[0]  # red (= green = blue)
    ref = _worley(pixel_centre_points(scene, P) * 2.5, seed)
    agree = np.abs(got - ref) < 1e-4
    print(f"cells: {agree.mean():.4f} of pixels agree, {len(np.unique(np.round(ref, 6)))} distinct cells")
    assert len(np.unique(np.round(ref, 6))) > 60
    assert agree.mean() > 0.995


def _dead_leaves(q: np.ndarray, seed: int, octaves: int) -> np.ndarray:
    """Brute-force dead leaves (the docstring of flowsynth.kernels.texture.dead_leaves), float64: per size k
    (cells of 2^-k cycles), the disc of each of the 3x3 cells around the point; the covering disc of greatest
    depth gives the value; a point no disc covers gets its Worley cell's value (seed + 104729)."""
    unit = lambda h: (h >> np.uint32(8)).astype(np.float64) / 16777216.0
    best = np.full(q.shape[:-1], -1.0)
    value = np.zeros(q.shape[:-1])
    for k in range(octaves):
        p = q * 2.0 ** k
        f = np.floor(p)
        s = seed + 7919 * k
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                cx, cy = f[..., 0] + dx, f[..., 1] + dy
                px, py = cx + unit(_hash3(cx, cy, s)), cy + unit(_hash3(cx, cy, s + 1))
                r = 0.35 + 0.4 * unit(_hash3(cx, cy, s + 2))
                depth = unit(_hash3(cx, cy, s + 3))
                on_top = ((p[..., 0] - px) ** 2 + (p[..., 1] - py) ** 2 < r * r) & (depth > best)
                best = np.where(on_top, depth, best)
                value = np.where(on_top, unit(_hash3(cx, cy, s + 4)), value)
    return np.where(best < 0, _worley(q, seed + 104729), value)


def test_dead_leaves_match_a_brute_force_reference():
    """Three sizes of "leaves" on a plane facing the camera, the finest cell (1/6 m) ~4.6 px, so no size is
    left out: flat mode under a white ambient light renders the value itself. The numpy oracle agrees except
    where a pixel centre lies within float32 rounding of a disc or cell border; most pixels are on a disc, some
    on the Worley ground, and many distinct leaves show."""
    W, H, seed, scale = 128, 96, 777, 1.5
    mat = {"texture": "leaves", "octaves": 3, "scale": scale, "seed": seed, "colors": [[0.0] * 3, [1.0] * 3],
           "specular": 0.0}
    scene, P = tilted_plane(W, H, mat, tilt_deg=0.0)
    got = to_linear(fs.render(scene, ["rgb"], render_mode="flat")["rgb"])[0]
    q = pixel_centre_points(scene, P) * scale
    ref = _dead_leaves(q, seed, 3)
    ground = _dead_leaves(q, seed, 0)  # no discs at all: the Worley ground everywhere
    agree = np.abs(got - ref) < 1e-4
    print(f"leaves: {agree.mean():.4f} of pixels agree, {len(np.unique(np.round(ref, 6)))} distinct values, "
          f"{(ref == ground).mean():.3f} on the ground")
    assert len(np.unique(np.round(ref, 6))) > 60 and 0.0 < (ref == ground).mean() < 0.5
    assert agree.mean() > 0.995


def test_leaves_is_drawn_only_when_named():
    """"leaves" is a texture family a config may name; the families drawn by default are unchanged (so every
    default sample keeps its bits: benchmarks/speed/hashes.py)."""
    from flowsynth.appearance.materials import PROCEDURAL_FAMILIES, TEXTURE_FAMILIES, sample_material

    assert "leaves" in TEXTURE_FAMILIES and "leaves" not in PROCEDURAL_FAMILIES
    assert PROCEDURAL_FAMILIES == ("solid", "noise", "value", "cells", "stripes", "checks", "blend")
    drawn = {sample_material(np.random.default_rng(i), ("leaves", "noise"))["texture"] for i in range(20)}
    assert drawn == {"leaves", "noise"}
    cfg = BouncingThingsConfig(width=64, height=48, num_frames=1, motion="static", texture_families=("leaves",))
    walls = [o for o in sample_scene(cfg, 0, 1).objects if o.background]
    assert all(o.material["texture"] == "leaves" for o in walls)
    with pytest.raises(fs.ConfigError, match="leaves"):
        BouncingThingsConfig(texture_families=("leaf",))


def _blend_mask(q: np.ndarray, seed: int, scale: float) -> np.ndarray:
    """The blend mask w = smoothstep(0.4, 0.6, 3-octave noise) at object-plane points q (..., 2) [m], evaluated
    by a kernel of this test from ``fractal`` itself (every octave fully present), not through planar_color."""
    from flowsynth.kernels import wp_runtime

    wp = wp_runtime()
    from flowsynth.kernels.texture import F_NOISE, fractal

    @wp.kernel(enable_backward=False, module="unique")
    def mask(q: wp.array[wp.vec2], seed: wp.int32, scale: wp.float32, out: wp.array[wp.float32]):
        i = wp.tid()
        out[i] = wp.smoothstep(0.4, 0.6, fractal(q[i] * scale, seed, 3, F_NOISE, 0.5, 0.0))

    pts = wp.array(q.reshape(-1, 2).astype(np.float32), dtype=wp.vec2)
    out = wp.zeros(len(pts), dtype=wp.float32)
    wp.launch(mask, len(pts), [pts, seed, scale], [out])
    return out.numpy().reshape(q.shape[:-1])


def test_blend_is_its_layers_mixed_by_the_mask():
    """A "blend" renders, at every pixel, a mix (1 - w) a + w b of what its two layers render alone (flat mode,
    white ambient light: radiance = albedo), one w for all channels; where the mask (``_blend_mask``, computed
    apart) is 0 or 1 the pixel is exactly that one layer, bit for bit (the kernel then looks up only that
    layer), and both cases are common."""
    W, H, mask_scale = 96, 72, 0.4
    a = {"texture": "stripes", "scale": 3.0, "angle": 0.4, "seed": 1, "colors": [[0.9, 0.2, 0.1], [0.6, 0.5, 0.0]]}
    b = {"texture": "value", "scale": 1.5, "octaves": 3, "seed": 2, "colors": [[0.1, 0.3, 0.9], [0.0, 0.9, 0.6]]}

    def render(mat):  # a plane facing the camera: the mask's octaves (2.5 m .. 0.6 m) span 12+ px
        scene, _ = tilted_plane(W, H, {**mat, "specular": 0.0}, tilt_deg=0.0)
        return fs.render(scene, ["rgb"], render_mode="flat")["rgb"]

    rgb = [render(m) for m in ({"texture": "blend", "layers": [a, b], "mask_scale": mask_scale, "seed": 3}, a, b)]
    got, ra, rb = (x[0].numpy() for x in rgb)  # frame 0, sRGB-encoded, (3, H, W)
    lg, la, lb = (to_linear(x) for x in rgb)
    w = _blend_mask(pixel_centre_points(*tilted_plane(W, H, a, tilt_deg=0.0)), 3, mask_scale)
    span = lb - la
    ch = np.argmax(np.abs(span), 0)  # the channel where the layers differ most gives the mix weight
    mix = np.take_along_axis((lg - la) / np.where(span == 0, 1, span), ch[None], 0)[0]
    print(f"blend: mask 0 on {(w == 0).mean():.3f}, 1 on {(w == 1).mean():.3f}; max |mix - mask| "
          f"{np.abs(mix - w).max():.2e}")
    assert (w == 0).mean() > 0.05 and (w == 1).mean() > 0.05 and ((w > 0) & (w < 1)).mean() > 0.02
    assert np.all(got[:, w == 0] == ra[:, w == 0]) and np.all(got[:, w == 1] == rb[:, w == 1])
    assert np.abs(la + mix[None] * span - lg).max() < 1e-5  # one w for all three channels
    assert np.abs(mix - w).max() < 0.02  # and it is the mask (float32 hit points against float64 centres)


# --- natural_image: textures with statistics of photographs, made without files (issue 46) -----------------------

def _amplitude_slope(grey):
    """Least-squares slope of log radial mean amplitude against log frequency, over 4-64 cycles per image."""
    n = grey.shape[0]
    amp = np.abs(np.fft.fft2(grey - grey.mean()))
    fy, fx = np.meshgrid(np.fft.fftfreq(n) * n, np.fft.fftfreq(n) * n, indexing="ij")
    r = np.hypot(fx, fy).round().astype(int)
    ks = np.arange(4, 65)
    mean = np.array([amp[r == k].mean() for k in ks])
    return np.polyfit(np.log(ks), np.log(mean), 1)[0]


def test_natural_pink_has_a_power_law_spectrum_and_is_seeded():
    from flowsynth.appearance.textures import natural_image

    slopes = []
    for seed in range(4):
        im = natural_image("pink", seed, 256)
        assert im.shape == (256, 256, 3) and im.dtype == np.float32 and np.isfinite(im).all()
        assert im.min() >= 0 and im.max() <= 1
        slopes.append(_amplitude_slope(im.mean(-1)))
    assert all(-1.8 < s < -0.6 for s in slopes), slopes  # 1/f^a, a drawn in [0.8, 1.6] (clipping bends it a little)
    assert np.array_equal(natural_image("pink", 1, 64), natural_image("pink", 1, 64))
    assert not np.array_equal(natural_image("pink", 1, 64), natural_image("pink", 2, 64))


def test_natural_leaves_cover_the_plane_with_discs_and_edges_leave_smooth_regions():
    from flowsynth.appearance.textures import natural_image

    leaves = natural_image("leaves", 0, 128)
    colours = np.unique((leaves * 255).astype(np.uint8).reshape(-1, 3), axis=0)
    assert len(colours) > 100  # many discs, each its own colour (with a faint shading)
    edges = natural_image("edges", 0, 128)
    grad = np.abs(np.diff(edges.mean(-1), axis=1))
    assert (grad < 0.01).mean() > 0.8 and grad.max() > 0.05  # mostly smooth, with sharp edges


def test_natural_image_rejects_an_unknown_kind():
    from flowsynth.errors import ConfigError
    from flowsynth.appearance.textures import natural_image

    with pytest.raises(ConfigError, match="kind"):
        natural_image("marble", 0)
