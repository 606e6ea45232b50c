"""RGB rendering: brightness constancy along the flow, anti-aliasing convergence, motion blur, shadows,
determinism, textures and their validation. Small images; the file runs in well under 90 s on 2 cores."""

from __future__ import annotations

import math

import kornia
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

import flowsynth as fs
from flowsynth.appearance.lights import Light, sample_lights
from flowsynth.appearance.materials import resolve_material, sample_material
from flowsynth.appearance.textures import list_textures, srgb_to_linear
from flowsynth.kernels.tonemap import SrgbPow, srgb_pow, srgb_pow_tables
from flowsynth.renderer.shading import poses_at, tonemap_frames, tonemap_srgb

LIGHT_DIR = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])  # travel direction, world frame
LIGHTS = [Light("directional", (1.0, 0.95, 0.9), 0.7, direction=tuple(LIGHT_DIR)),
          Light("ambient", (0.8, 0.9, 1.0), 0.2)]
SMOOTH = {"texture": "noise", "octaves": 2, "specular": 0.0}


def to_linear(c) -> np.ndarray:
    """sRGB-encoded values (any shape) -> linear, by kornia: the oracle is not flowsynth's srgb_to_linear."""
    x = torch.from_numpy(np.ascontiguousarray(c, np.float32)).reshape(1, 1, -1).expand(3, 1, -1)
    return kornia.color.rgb_to_linear_rgb(x)[0].reshape(np.shape(c)).numpy()


def rot(axis, angle: float) -> np.ndarray:
    return trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]


def pose(R=None, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    P = np.eye(4)
    P[:3, :3] = np.eye(3) if R is None else R
    P[:3, 3] = t
    return P


def wall_scene(T: int, W: int = 96, H: int = 72, wall: dict | None = None) -> fs.Scene:
    """Camera at the origin looking down +z at a static textured wall 6 m away."""
    scene = fs.Scene(fs.Camera.from_fov(W, H, 60.0), T)
    scene.lights = list(LIGHTS)
    material = wall or dict(SMOOTH, scale=0.5, colors=[[0.85, 0.8, 0.7], [0.25, 0.3, 0.35]], seed=11)
    scene.add_object(trimesh.creation.box((12.0, 9.0, 0.2)), pose(t=(0.0, 0.0, 6.0)), material=material)
    return scene


def moving_boxes(T: int, *, rotate_axis=LIGHT_DIR, camera_motion: bool = True, **kw) -> fs.Scene:
    """Two textured boxes translating and spinning about ``rotate_axis`` in front of the wall."""
    scene = wall_scene(T, **kw)
    if camera_motion:
        scene.set_camera_poses(np.stack([pose(rot([0, 1, 0], 0.01 * t), (0.05 * t, 0.02 * t, 0.0))
                                         for t in range(T)]))
    specs = [((1.2, 1.0, 1.1), (-1.1, 0.2, 4.0), (0.15, 0.05, 0.1), 0.12, "noise"),
             ((0.9, 1.1, 0.8), (1.0, -0.3, 3.6), (-0.1, 0.08, -0.05), -0.1, "value")]
    for k, (size, p0, v, w, family) in enumerate(specs):
        R0 = rot([1, 2, 3], 0.7 + k)
        poses = [pose(rot(rotate_axis, w * t) @ R0, np.add(p0, np.multiply(v, t))) for t in range(T)]
        scene.add_object(trimesh.creation.box(size), np.stack(poses),
                         material=dict(SMOOTH, texture=family, scale=1.0, seed=k,
                                       colors=[[0.9, 0.6, 0.3], [0.2, 0.3, 0.6]]))
    return scene


def smooth_region(inst: np.ndarray, normals: np.ndarray, r: int) -> np.ndarray:
    """(H, W) pixels whose (2r+1)^2 window sees one instance and one face orientation (no edges)."""
    H, W = inst.shape
    pad_i = np.pad(inst, r, constant_values=-1)
    pad_n = np.pad(normals, ((0, 0), (r, r), (r, r)), constant_values=9.0)
    ok = inst > 0
    for di in range(2 * r + 1):
        for dj in range(2 * r + 1):
            ok &= pad_i[di:di + H, dj:dj + W] == inst
            ok &= np.abs(pad_n[:, di:di + H, dj:dj + W] - normals).max(0) < 1e-3
    return ok


def warp_back(img_next: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of frame t+1 at x + flow_fw(x): (3, H, W)."""
    H, W = flow.shape[-2:]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32),
                          indexing="ij")
    mx, my = (u + flow[0])[None], (v + flow[1])[None]
    return kornia.geometry.transform.remap(img_next[None], mx, my, mode="bilinear", align_corners=True)[0]


def constancy_errors(scene: fs.Scene, mode: str, r: int = 2, flow_scale: float = 1.0) -> np.ndarray:
    """|rgb_t - rgb_{t+1}(x + flow)| on mutually visible, edge-free (and, for direct, shadow-edge-free) pixels."""
    keys = ["rgb", "flow_fw", "occ_fw", "valid_fw", "instance", "normals"]
    out = fs.render(scene, keys, render_mode=mode)
    shadow = None
    if mode == "direct":
        flat = fs.render(scene, ["rgb"], render_mode="flat")["rgb"]
        shadow = ((flat - out["rgb"]).amax(1) > 1e-4).numpy()
    errs = []
    for t in range(scene.num_frames - 1):
        inst = out["instance"][:, 0].numpy()
        nrm = out["normals"].numpy()
        ok = (out["valid_fw"][t, 0] & ~out["occ_fw"][t, 0]).numpy() & smooth_region(inst[t], nrm[t], r)
        smooth1 = smooth_region(inst[t + 1], nrm[t + 1], r)
        flow = out["flow_fw"][t] * flow_scale
        H, W = inst.shape[1:]
        i, j = np.nonzero(ok)
        ti = np.clip(np.rint(i + flow[1, i, j].numpy()).astype(int), 0, H - 1)
        tj = np.clip(np.rint(j + flow[0, i, j].numpy()).astype(int), 0, W - 1)
        keep = smooth1[ti, tj] & (inst[t + 1][ti, tj] == inst[t][i, j])
        if shadow is not None:
            still0 = smooth_region(shadow[t].astype(np.int32) + 1, nrm[t] * 0, r)
            still1 = smooth_region(shadow[t + 1].astype(np.int32) + 1, nrm[t] * 0, r)
            keep &= still0[i, j] & still1[ti, tj] & (shadow[t][i, j] == shadow[t + 1][ti, tj])
        warped = warp_back(out["rgb"][t + 1], flow).numpy()
        diff = np.abs(warped - out["rgb"][t].numpy()).max(0)
        errs.append(diff[i[keep], j[keep]])
    return np.concatenate(errs)


@pytest.mark.parametrize("mode", ["flat", "direct"])
def test_brightness_constancy(mode):
    # Diffuse materials, a static directional light and rotations about the light direction: n . l is
    # constant on every face, so the radiance of a surface point is the same in both frames.
    errs = constancy_errors(moving_boxes(3), mode)
    assert errs.size > 2000
    mean, p95 = float(errs.mean()), float(np.quantile(errs, 0.95))
    print(f"{mode}: brightness constancy over {errs.size} px: mean {mean:.5f}, p95 {p95:.5f}, max {errs.max():.4f}")
    assert mean < 0.004 and p95 < 0.012


def test_brightness_constancy_has_teeth():
    # Ignoring the motion (zero flow) breaks the same check by far: it does measure texture motion.
    scene = moving_boxes(3)
    assert constancy_errors(scene, "flat", flow_scale=0.0).mean() > 5 * constancy_errors(scene, "flat").mean()


def test_shadows_match_geometric_oracle():
    scene = wall_scene(1)
    c, h = np.array([0.5, -0.6, 4.5]), 0.5
    scene.add_object(trimesh.creation.box((1.0, 1.0, 1.0)), pose(t=c), material=dict(SMOOTH, seed=3))
    keys = ["rgb", "instance", "position"]
    direct = fs.render(scene, keys, render_mode="direct")
    flat = fs.render(scene, ["rgb"], render_mode="flat")["rgb"]
    d, f = direct["rgb"][0].numpy(), flat[0].numpy()
    assert np.isfinite(d).all() and d.min() >= 0 and d.max() <= 1
    assert (d <= f + 1e-6).all()  # shadows only darken; elsewhere direct == flat
    observed = (f - d).max(0) > 1e-3
    # Oracle: a wall point is in shadow when the ray towards the light crosses the box (slab test).
    P = direct["position"][0].numpy().reshape(3, -1).T
    to_light = -LIGHT_DIR
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (c - h - P) / to_light
        t2 = (c + h - P) / to_light
    tn, tf = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
    expected = ((tn <= tf) & (tf > 0)).reshape(observed.shape)
    wall = direct["instance"][0, 0].numpy() == 1
    edge = smooth_region(expected.astype(np.int32) + 1, np.zeros((3,) + expected.shape), 1)
    assert expected[wall].sum() > 150
    assert (observed[wall & edge] == expected[wall & edge]).mean() > 0.995
    assert (observed[wall] != expected[wall]).sum() < 0.05 * expected[wall].sum()
    assert not observed[~wall].any()  # the box's own faces are lit or facing away in both modes


def test_antialiasing_converges():
    def errors(material: dict) -> dict:
        scene = moving_boxes(1, W=64, H=48, camera_motion=False)
        for obj in scene.objects:
            obj.material.update(material)
        lin = {spp: to_linear(fs.render(scene, ["rgb"], render_mode="flat", spp=spp, edge_spp=1, seed=spp)["rgb"]
                              .numpy()) for spp in (1, 4, 16, 256)}  # edge_spp=1: spp samples in every pixel
        return {spp: float(np.sqrt(np.mean((lin[spp] - lin[256]) ** 2))) for spp in (1, 4, 16)}

    # Silhouettes only (solid colours): only more samples anti-alias them.
    err = errors({"texture": "solid"})
    print("AA rms error vs spp 256, solid:", err)
    assert err[4] < 0.6 * err[1] and err[16] < 0.6 * err[4]
    # Checks: the texture is also pre-filtered over each sample's footprint (tests/test_texture.py), so
    # spp 1 is already close; more samples still converge.
    err = errors({"texture": "checks", "scale": 2.0})
    print("AA rms error vs spp 256, checks:", err)
    assert err[4] < err[1] < 0.02 and err[16] < 0.6 * err[4]


def test_edge_spp_antialiases_silhouettes_only():
    """edge_spp: pixels at a silhouette (a 4-neighbour sees another instance; found here in numpy from the
    ``instance`` output) get more samples and approach the spp 256 reference; every other pixel, the creases
    between a box's faces included, is the spp 1 render bit for bit."""
    scene = moving_boxes(1, W=64, H=48, camera_motion=False)
    for obj in scene.objects:
        obj.material.update({"texture": "solid"})
    one = fs.render(scene, ["rgb", "instance"], render_mode="flat", spp=1, seed=1)
    edge = fs.render(scene, ["rgb"], render_mode="flat", spp=1, edge_spp=16, seed=1)["rgb"].numpy()
    ref = to_linear(fs.render(scene, ["rgb"], render_mode="flat", spp=256, seed=256)["rgb"].numpy())
    inst = one["instance"][0, 0].numpy()
    border = np.zeros(inst.shape, bool)
    every = slice(None)
    for a, b in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):
        for ia, ib in (((a, every), (b, every)), ((every, a), (every, b))):  # neighbour above/below, left/right
            border[ia] |= inst[ia] != inst[ib]
    assert 0.05 < border.mean() < 0.5
    rgb1 = one["rgb"].numpy()
    assert np.array_equal(edge[0][:, ~border], rgb1[0][:, ~border])
    assert (np.abs(edge[0] - rgb1[0]).max(0) > 0)[border].mean() > 0.5

    def rms(x):
        return float(np.sqrt(np.mean((to_linear(x)[0][:, border] - ref[0][:, border]) ** 2)))
    print("silhouette rms vs spp 256: spp 1", rms(rgb1), "edge_spp 16", rms(edge))
    assert rms(edge) < 0.4 * rms(rgb1)


@pytest.mark.parametrize("mode", ["flat", "path"])
def test_camera_rays_find_the_same_hits_through_tiles_as_through_the_bvh(monkeypatch, mode):
    """Without motion blur the shading kernel's own camera rays (edge_spp, spp > 1) walk the G-buffer cast's
    screen-tile lists; the top-level BVH (``CAMERA_RAY_TILES = False``, what motion blur uses) is an independent
    walk to the same closest hits, so both render the same image bit for bit."""
    from flowsynth.renderer import shading

    scene = moving_boxes(3, W=64, H=48, camera_motion=True)
    opts = {"render_mode": mode, "spp": 4, "edge_spp": 16, "seed": 7}
    tiles = fs.render(scene, ["rgb"], **opts)["rgb"].numpy()
    monkeypatch.setattr(shading, "CAMERA_RAY_TILES", False)
    bvh = fs.render(scene, ["rgb"], **opts)["rgb"].numpy()
    assert np.array_equal(tiles, bvh)
    assert tiles.std() > 0.05  # a real image, not an empty one


def test_motion_blur_equals_mean_of_sharp_frames():
    # Constant linear and angular velocity, so the slerp/linear interpolation between frames (and the
    # extrapolation past the last frame) reproduces the true motion; the reference poses are analytic.
    T, W, H, shutter, K = 2, 64, 48, 0.8, 16
    axis, w, v = np.array([0.2, 1.0, 0.3]), 0.5, np.array([0.6, 0.15, 0.0])
    R0, p0 = rot([1, 0, 1], 0.4), np.array([-0.8, 0.0, 4.0])

    def obj_pose(tau):
        return pose(rot(axis, w * tau) @ R0, p0 + v * tau)

    def cam_pose(tau):
        return pose(rot([0, 1, 0], 0.05 * tau), (0.1 * tau, 0.0, 0.0))

    def build(times):
        s = wall_scene(len(times), W, H)
        s.set_camera_poses(np.stack([cam_pose(x) for x in times]))
        s.add_object(trimesh.creation.box((1.0, 0.8, 0.9)), np.stack([obj_pose(x) for x in times]),
                     material=dict(SMOOTH, texture="checks", scale=2.5))
        return s

    blurred = fs.render(build(np.arange(T)), ["rgb", "depth"], render_mode="flat", spp=64, shutter=shutter)
    sharp = fs.render(build(np.arange(T)), ["rgb", "depth"], render_mode="flat", spp=64)
    assert torch.equal(blurred["depth"], sharp["depth"])  # ground truth stays that of the frame instant
    for t in range(T):
        times = t + shutter * (np.arange(K) + 0.5) / K
        ref = np.mean([to_linear(fs.render(build([x]), ["rgb"], render_mode="flat", spp=16, seed=k)["rgb"][0]
                                 .numpy()) for k, x in enumerate(times)], 0)
        err = np.abs(to_linear(blurred["rgb"][t].numpy()) - ref)
        err_sharp = np.abs(to_linear(sharp["rgb"][t].numpy()) - ref)
        print(f"frame {t}: blurred vs mean of {K} sharp: mean {err.mean():.5f} p99 {np.quantile(err, 0.99):.4f};"
              f" unblurred vs it: mean {err_sharp.mean():.5f}")
        assert err.mean() < 0.003 and np.quantile(err, 0.99) < 0.05
        assert err_sharp.mean() > 5 * err.mean()


def test_pose_interpolation_matches_constant_motion():
    axis, w, v = np.array([0.3, -1.0, 0.5]), 1.1, np.array([1.0, -2.0, 0.5])
    P = np.stack([pose(rot(axis, w * t), v * t) for t in range(3)])
    times = np.array([0.0, 0.25, 1.5, 2.0, 2.7])
    expect = np.stack([pose(rot(axis, w * x), v * x) for x in times])
    assert np.abs(poses_at(P, times) - expect).max() < 1e-12
    assert np.abs(poses_at(P[:1], times) - P[0]).max() == 0.0


@pytest.mark.parametrize("mode", ["flat", "direct", "path"])
def test_rgb_finite_in_range_and_deterministic(mode):
    scene = moving_boxes(2, W=48, H=36)
    scene.objects[1].material.update(specular=0.6, roughness=0.1)
    a = fs.render(scene, ["rgb"], render_mode=mode, spp=4, shutter=0.5, seed=7)["rgb"]
    b = fs.render(scene, ["rgb"], render_mode=mode, spp=4, shutter=0.5, seed=7)["rgb"]
    assert a.shape == (2, 3, 36, 48) and a.dtype == torch.float32
    assert torch.isfinite(a).all() and a.min() >= 0 and a.max() <= 1
    assert torch.equal(a, b)
    c = fs.render(scene, ["rgb"], render_mode=mode, spp=4, shutter=0.5, seed=8)["rgb"]
    assert not torch.equal(a, c)


def test_reused_and_traced_primary_hits_agree():
    # spp 1 without blur shades the G-buffer's pixel-centre hit; with a (negligible) shutter the primary ray
    # is traced anew at a jittered sub-pixel position. On a uniformly coloured plate both must agree.
    scene = fs.Scene(fs.Camera.from_fov(32, 24, 40.0), 1)
    scene.lights = list(LIGHTS)
    scene.add_object(trimesh.creation.box((6.0, 6.0, 0.1)), pose(rot([1, 0, 0], 0.3), (0, 0, 3.0)),
                     material={"texture": "solid", "colors": [[0.7, 0.5, 0.3]]})
    for mode in ("flat", "direct"):
        a = fs.render(scene, ["rgb"], render_mode=mode)["rgb"]
        b = fs.render(scene, ["rgb"], render_mode=mode, spp=1, shutter=1e-9)["rgb"]
        assert (a - b).abs().max() < 1e-5 and torch.equal(a, a[..., :1, :1].expand_as(a))


def test_path_tracer_matches_analytic_furnace():
    # A convex diffuse object under a uniform sky only: every bounce escapes, radiance = albedo * sky;
    # flat mode's ambient term gives the same value exactly.
    scene = fs.Scene(fs.Camera.from_fov(48, 36, 50.0), 1)
    scene.lights = [Light("ambient", (1.0, 1.0, 1.0), 0.7)]
    scene.add_object(trimesh.creation.icosphere(2, 1.0), pose(t=(0, 0, 4.0)),
                     material={"texture": "solid", "colors": [[0.8, 0.6, 0.4]], "specular": 0.0})
    hit = fs.render(scene, ["instance"])["instance"][0, 0].numpy() > 0
    flat = to_linear(fs.render(scene, ["rgb"], render_mode="flat", edge_spp=1)["rgb"][0].numpy())  # pixel centres
    path = to_linear(fs.render(scene, ["rgb"], render_mode="path", spp=64)["rgb"][0].numpy())
    expect = 0.7 * to_linear(np.array([0.8, 0.6, 0.4]))[:, None]
    assert np.abs(flat[:, hit] - expect).max() < 1e-3
    assert np.abs(path[:, hit].mean(1) - expect[:, 0]).max() < 0.01
    assert np.abs(flat[:, ~hit] - 0.7).max() < 1e-3  # background = sky radiance


def ggx_oracle(n: np.ndarray, wo: np.ndarray, albedo: np.ndarray, s: float, r: float, m: int = 20000):
    """Hemispherical integral of the documented BRDF times cos, per pixel, by a Fibonacci lattice (numpy)."""
    k = np.arange(m) + 0.5
    z, phi = 1.0 - k / m, math.pi * (1.0 + 5.0**0.5) * k  # uniform on the upper hemisphere
    local = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
    a2 = (r * r) ** 2
    out = []
    for nn, oo in zip(n, wo):
        e1 = np.cross(nn, [1.0, 0.0, 0.0] if abs(nn[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        wi = local @ np.stack([e1, np.cross(nn, e1), nn])
        ni, no = wi @ nn, float(oo @ nn)
        h = wi + oo
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        nh = h @ nn
        D = a2 / (math.pi * (nh * nh * (a2 - 1) + 1) ** 2)
        g1 = lambda c: 2 * c / (c + np.sqrt(a2 + (1 - a2) * c * c))
        spec = s * D * g1(ni) * g1(no) / (4 * ni * no)
        out.append(((1 - s) * albedo[None] / math.pi + spec[:, None]) * ni[:, None])
    return np.stack([o.mean(0) * 2 * math.pi for o in out])


def test_path_tracer_glossy_furnace_matches_numpy_integral():
    # Checks the BRDF importance sampling (cosine + GGX mixture) and its pdf: a glossy convex object under
    # a uniform sky has radiance L_sky * integral of f cos over the hemisphere, integrated here by brute force.
    s, r, sky = 0.6, 0.6, 0.5
    scene = fs.Scene(fs.Camera.from_fov(64, 48, 40.0), 1)
    scene.lights = [Light("ambient", (1.0, 1.0, 1.0), sky)]
    scene.add_object(trimesh.creation.icosphere(1, 1.0), pose(t=(0, 0, 4.0)),
                     material={"texture": "solid", "colors": [[0.6, 0.6, 0.6]], "specular": s, "roughness": r})
    out = fs.render(scene, ["rgb", "normals", "instance"], render_mode="path", spp=256, seed=3)
    inner = smooth_region(out["instance"][0, 0].numpy(), out["normals"][0].numpy(), 1)
    n = out["normals"][0].numpy()[:, inner].T.astype(np.float64)
    wo = -scene.camera.pixel_rays().numpy()[inner]
    expect = sky * ggx_oracle(n, wo, to_linear(np.full(3, 0.6)).astype(np.float64), s, r)
    got = to_linear(out["rgb"][0].numpy())[:, inner].T
    print(f"glossy furnace over {inner.sum()} px: path {got.mean():.5f}, numpy integral {expect.mean():.5f}")
    assert inner.sum() > 300
    assert abs(got.mean() - expect.mean()) < 0.01 * expect.mean()


def test_direct_light_units():
    # A white diffuse plate facing a directional light at angle a: radiance = I cos(a) (+ ambient).
    scene = fs.Scene(fs.Camera.from_fov(32, 24, 30.0), 1)
    a, I = 0.6, 0.5
    scene.lights = [Light("directional", (1.0, 1.0, 1.0), I, direction=(math.sin(a), 0.0, math.cos(a)))]
    scene.add_object(trimesh.creation.box((4.0, 4.0, 0.1)), pose(t=(0, 0, 3.0)),
                     material={"texture": "solid", "colors": [[1.0, 1.0, 1.0]]})
    for mode in ("flat", "direct", "path"):
        lin = to_linear(fs.render(scene, ["rgb"], render_mode=mode, spp=1)["rgb"].numpy())
        assert np.abs(lin - I * math.cos(a)).max() < 2e-3, mode


def test_no_objects_renders_sky_and_defaults_render():
    scene = fs.Scene(fs.Camera.from_fov(16, 12), 2)
    rgb = fs.render(scene, ["rgb"], render_mode="path")["rgb"]
    assert rgb.shape == (2, 3, 12, 16) and torch.equal(rgb, rgb[..., :1, :1].expand_as(rgb))
    scene.add_object(trimesh.creation.icosphere(1, 0.5), pose(t=(0, 0, 2.0)))  # no material, no lights
    rgb = fs.render(scene, ["rgb"], render_mode="direct", spp=4)["rgb"]
    assert torch.isfinite(rgb).all() and rgb.std() > 0.02


def test_image_textures(tmp_path):
    red = np.zeros((8, 8, 3), np.uint8)
    red[..., 0] = 220
    check = (np.indices((32, 32)).sum(0) // 8 % 2 * 200 + 30).astype(np.uint8)
    Image.fromarray(red).save(tmp_path / "red.png")
    Image.fromarray(np.stack([check] * 3, -1)).save(tmp_path / "check.jpg")
    (tmp_path / "notes.txt").write_text("not an image")
    assert [p.name for p in list_textures(tmp_path)] == ["check.jpg", "red.png"]
    mats = [sample_material(np.random.default_rng(s), ["image"], tmp_path, size=1.0) for s in range(6)]
    assert {m["image"] for m in mats} == {str(tmp_path / "check.jpg"), str(tmp_path / "red.png")}
    scene = wall_scene(1, 48, 36, wall={"texture": "image", "image": str(tmp_path / "red.png"), "scale": 0.3})
    scene.add_object(trimesh.creation.box((1.5, 1.5, 1.5)), pose(rot([1, 1, 0], 0.5), (0, 0, 4.0)),
                     material={"texture": "image", "image": str(tmp_path / "check.jpg"), "scale": 1.0})
    out = fs.render(scene, ["rgb", "instance"], render_mode="flat", edge_spp=1)  # one sample a pixel: its own hit
    rgb, inst = out["rgb"][0].numpy(), out["instance"][0, 0].numpy()
    wall, box = rgb[:, inst == 1], rgb[:, inst == 2]
    assert (wall[0] > 4 * wall[1] + 0.05).all() and (wall[1] == wall[2]).all()  # red picture
    assert box.std(1).min() > 0.1 and np.abs(box[0] - box[1]).max() < 0.06  # grey checks


def test_texture_and_material_errors(tmp_path):
    with pytest.raises(fs.ConfigError, match="holds no images"):
        list_textures(tmp_path)
    with pytest.raises(fs.ConfigError, match="does not exist"):
        sample_material(np.random.default_rng(0), ["image"], tmp_path / "missing")
    with pytest.raises(fs.ConfigError, match="needs texture_dir"):
        sample_material(np.random.default_rng(0), ["noise", "image"])
    with pytest.raises(fs.ConfigError, match="unknown material key"):
        resolve_material({"colour": [1, 0, 0]})
    with pytest.raises(fs.ConfigError, match="roughness"):
        resolve_material({"roughness": 3.0})
    with pytest.raises(fs.ConfigError, match="Light.kind"):
        Light("spot")
    with pytest.raises(fs.ConfigError, match="tonemap"):
        tonemap_srgb(np.zeros((1, 3)), "filmic")


def test_sampled_materials_and_lights_render():
    rng = np.random.default_rng(3)
    scene = wall_scene(1, 48, 36)
    scene.lights = sample_lights(rng, (12.0, 9.0, 14.0), center=(0, 0, 0), up=(0, -1, 0), num_directional=(1, 1))
    assert sum(light.kind == "ambient" for light in scene.lights) == 1
    for k in range(4):
        scene.add_object(trimesh.creation.box((0.6, 0.6, 0.6)), pose(rot([0, 1, 1], k), (k - 1.5, 0, 4.0)),
                         material=sample_material(rng, size=0.6) if k else sample_material(rng, ["blend"]))
    for mode in ("flat", "direct", "path"):
        rgb = fs.render(scene, ["rgb"], render_mode=mode, spp=2)["rgb"]
        assert torch.isfinite(rgb).all() and 0 <= rgb.min() and rgb.max() <= 1 and rgb.std() > 0.01


def test_material_shorthand_and_tone_maps():
    m = resolve_material({"texture_seed": 5}, size=2.0)
    assert m == resolve_material(sample_material(np.random.default_rng(5), size=2.0), size=2.0)
    L = np.array([0.0, 1e-4, 0.2, 0.9, 1.0, 4.0, 1e9, np.nan, np.inf, -1.0])[:, None].repeat(3, 1)
    for method in ("clamp", "reinhard"):
        c = tonemap_srgb(L, method)
        assert c.dtype == np.float32 and np.isfinite(c).all() and c.min() >= 0 and c.max() <= 1
        assert (np.diff(c[:7, 0]) >= 0).all() and c[6, 0] == 1.0
    assert np.abs(to_linear(tonemap_srgb(L[:5], "clamp")) - L[:5]).max() < 1e-6


@pytest.mark.parametrize("method", ["clamp", "reinhard"])
@pytest.mark.parametrize("exposure", [1.0, 0.37, 0.0])
def test_tonemap_kernel_equals_numpy_tonemap(method, exposure):
    """The renderer's one-pass tone-mapping kernel (``tonemap_frames``) gives numpy's ``tonemap_srgb`` bit for
    bit, frame by frame, channels first: radiance across the sRGB knee, past white, NaN, +-inf, negative."""
    rng = np.random.default_rng(3)
    L = rng.uniform(0.0, 1.5, size=(3, 7, 11, 3)).astype(np.float32) ** 3
    L[0, 0, :6, 0] = [0.0, 0.0031308, 0.0031309, np.nan, np.inf, -np.inf]
    L[1, 2, :3, 1] = [-0.5, 4.0, 1e30]
    got = tonemap_frames(L, method, exposure, threads=2)
    with np.errstate(invalid="ignore"):  # inf * 0 exposure: NaN, mapped to 0 by both
        want = np.stack([tonemap_srgb(L[t], method, exposure).transpose(2, 0, 1) for t in range(len(L))])
    assert got.dtype == np.float32 and got.shape == (3, 3, 7, 11)
    np.testing.assert_array_equal(got, want)
    c = np.linspace(0.0, 1.0, 1001)
    assert np.abs(srgb_to_linear(c) - to_linear(c)).max() < 1e-6


def test_srgb_power_table_matches_numpy_and_the_kernel_rounds_like_numpy():
    """``srgb_pow`` (the tone-mapping kernel's table-driven x^(1/2.4), no libm call) is within 1e-14 relative of
    numpy's float64 power over its whole domain, and the kernel, which keeps it only where float32 rounding
    cannot tell the two apart, equals numpy's ``tonemap_srgb`` bit for bit on a million values: random ones,
    every float32 near the sRGB knee and a dense run from 0.5 up."""
    import warp as wp

    @wp.kernel(enable_backward=False, module="unique")
    def pw(x: wp.array[wp.float64], tab: SrgbPow, out: wp.array[wp.float64]):
        i = wp.tid()
        out[i] = srgb_pow(x[i], tab)

    rng = np.random.default_rng(7)
    x = np.concatenate([np.exp(rng.uniform(np.log(0.0031308), 0.0, 200_000)), [0.0031309, 0.5, 1.0 - 2**-53, 1.0],
                        2.0 ** -np.arange(9.0)])
    out = wp.zeros(len(x), dtype=wp.float64, device="cpu")  # the tables live on the CPU
    wp.launch(pw, len(x), [wp.array(x, dtype=wp.float64, device="cpu"), srgb_pow_tables()], [out], device="cpu")
    rel = np.abs(out.numpy() / x ** (1.0 / 2.4) - 1.0)
    print(f"srgb_pow: max relative error {rel.max():.2e}")
    assert rel.max() < 1e-14

    f32 = np.float32
    knee = np.arange(f32(0.0030).view(np.int32), f32(0.0033).view(np.int32), dtype=np.int32).view(f32)
    run = np.arange(f32(0.5).view(np.int32), f32(0.5).view(np.int32) + 300_000, dtype=np.int32).view(f32)
    L = np.concatenate([rng.uniform(0.0, 1.2, 600_000).astype(f32), knee, run])
    L = L[: len(L) // 3 * 3].reshape(1, -1, 1, 3)
    for method, exposure in (("clamp", 1.0), ("reinhard", 0.37)):
        got = tonemap_frames(L, method, exposure, threads=2)[0, :, :, 0].T
        np.testing.assert_array_equal(got, tonemap_srgb(L[0, :, 0], method, exposure))


def test_radiance_clamp_in_kernel_equals_numpy_clamp():
    """The shading kernel's last step (``finite_nonneg``) gives what ``render_radiance`` computed in numpy before
    it moved into the kernel, bit for bit, sign of zero included: NaN, +-inf, negatives and -0 -> +0."""
    import warp as wp

    from flowsynth.kernels.shade import finite_nonneg

    @wp.kernel(enable_backward=False)
    def clamp(x: wp.array[wp.vec3], y: wp.array[wp.vec3]):
        k = wp.tid()
        y[k] = finite_nonneg(x[k])

    special = [np.nan, np.inf, -np.inf, -0.0, 0.0, -1e-30, 1e-45, 3.4e38, -2.0, 0.5]
    x = np.array(np.meshgrid(special, special, special[::-1])).reshape(3, -1).T.astype(np.float32)
    got = wp.empty(len(x), dtype=wp.vec3, device="cpu")
    wp.launch(clamp, len(x), inputs=[wp.array(x, dtype=wp.vec3, device="cpu")], outputs=[got], device="cpu")
    with np.errstate(invalid="ignore"):
        want = np.nan_to_num(np.maximum(x, 0.0), nan=0.0, posinf=0.0)
    assert want.dtype == np.float32
    np.testing.assert_array_equal(got.numpy().view(np.uint32), want.view(np.uint32))
    assert (want > 0).sum() > 100  # the finite positives pass through, not everything is zeroed


def _lambert_sphere(smooth: bool, subdivisions: int = 2):
    """A white diffuse icosphere (radius 1, 4 m ahead) under one directional light from the camera's side, flat
    mode (no shadows, no ambient), rendered with or without smooth shading: its linear radiance, the analytic
    radiance I max(n . l, 0) of the true sphere's normal at each hit point (from the ray distance), the hit mask
    and the ``normals`` output."""
    W, H, I = 96, 72, 0.8
    light = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])  # travel direction
    scene = fs.Scene(fs.Camera.from_fov(W, H, 45.0), 1)
    scene.lights = [Light("directional", (1.0, 1.0, 1.0), I, direction=tuple(light))]
    centre = np.array([0.0, 0.0, 4.0])
    scene.add_object(trimesh.creation.icosphere(subdivisions, 1.0), pose(rot([0.2, 1.0, 0.3], 0.7), centre),
                     material={"texture": "solid", "colors": [[1.0, 1.0, 1.0]], "specular": 0.0})
    out = fs.render(scene, ["rgb", "distance", "instance", "normals"], render_mode="flat", edge_spp=1,
                    smooth_shading=smooth)
    lin = to_linear(out["rgb"][0].numpy())[0]
    hit = out["instance"][0, 0].numpy() > 0
    X = scene.camera.pixel_rays_numpy() * out["distance"][0, 0].numpy()[..., None]
    n_true = (X - centre) / np.linalg.norm(X - centre, axis=-1, keepdims=True)
    want = I * np.clip(n_true @ -light, 0.0, None)
    return lin, want, hit, out["normals"][0].numpy()


def test_smooth_shading_matches_the_true_sphere():
    """Smooth shading lights a tessellated sphere (320 faces) as the true sphere would be lit at each hit point:
    its radiance is within 0.02 of I max(n . l, 0) on 99% of the sphere's pixels, where flat face normals are off
    by several times more (the facets). The ``normals`` output stays the faces' own either way."""
    lin_s, want, hit, nrm_s = _lambert_sphere(True)
    lin_f, _, _, nrm_f = _lambert_sphere(False)
    inner = hit & (want > 0.05)
    err_s, err_f = np.abs(lin_s - want)[inner], np.abs(lin_f - want)[inner]
    print(f"smooth: p50 {np.median(err_s):.4f} p99 {np.quantile(err_s, 0.99):.4f}; "
          f"flat: p50 {np.median(err_f):.4f} p99 {np.quantile(err_f, 0.99):.4f}")
    assert inner.sum() > 1000
    assert np.quantile(err_s, 0.99) < 0.02 and np.median(err_f) > 3 * np.median(err_s)
    np.testing.assert_array_equal(nrm_s, nrm_f)


def test_smooth_shading_keeps_creases_and_defaults_off():
    """A box's 90-degree edges are creases: smooth shading renders it as flat shading does (to float32 rounding
    of the interpolated normal), and ``smooth_shading`` is off unless asked for (config and RenderOptions)."""
    from flowsynth.raycast.blas import corner_normals

    box = trimesh.creation.box((1.0, 2.0, 0.5))
    faces = np.cross(*(box.vertices[box.faces[:, k]] - box.vertices[box.faces[:, 0]] for k in (1, 2)))
    faces /= np.linalg.norm(faces, axis=1, keepdims=True)
    np.testing.assert_allclose(corner_normals(box), np.repeat(faces[:, None], 3, 1), atol=1e-6)
    sphere = trimesh.creation.icosphere(3, 1.0)
    corners = corner_normals(sphere)
    radial = sphere.vertices[sphere.faces] / np.linalg.norm(sphere.vertices[sphere.faces], axis=-1, keepdims=True)
    assert np.degrees(np.arccos(np.clip((corners * radial).sum(-1), -1, 1))).max() < 1.0
    scene = fs.Scene(fs.Camera.from_fov(48, 36, 50.0), 1)
    scene.lights = list(LIGHTS)
    scene.add_object(box, pose(rot([0.3, 1.0, 0.2], 0.6), (0.0, 0.0, 3.0)), material=dict(SMOOTH, seed=4))
    a, b = (fs.render(scene, ["rgb"], render_mode="direct", smooth_shading=s)["rgb"].numpy() for s in (False, True))
    assert np.abs(a.astype(np.float64) - b).max() < 1e-4 and (a != 0).any()
    assert not fs.BouncingThingsConfig().smooth_shading and not fs.RenderOptions().smooth_shading
    with pytest.raises(fs.ConfigError, match="smooth_shading"):
        fs.RenderOptions(smooth_shading=1)
