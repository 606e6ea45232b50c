"""Lens models (flowsynth/scene/camera.py): rays, flow, tracks and boxes through Brown-Conrady and Kannala-Brandt,
against OpenCV's cv2.projectPoints / cv2.fisheye.projectPoints (an implementation nobody here wrote) and kornia."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch
import trimesh

import flowsynth as fs
from flowsynth import cli
from flowsynth.errors import ConfigError

W, H = 64, 48
BC = ("brown_conrady", (-0.3, 0.1, 0.001, -0.002, 0.0))
BC8 = ("brown_conrady", (0.1, 0.01, 0.001, 0.002, 0.001, 0.01, 0.001, 0.0001))
KB = ("kannala_brandt", (0.1, -0.05, 0.01, -0.002))
STRONG_BC = ("brown_conrady", (-0.45, 0.0, 0.0, 0.0))  # folds at r2 = 1 / (3 * 0.45): the corners are uncovered
STRONG_KB = ("kannala_brandt", (-0.3, 0.05, 0.0, 0.0))  # a fisheye circle inside the frame
LENSES = [BC, BC8, KB, STRONG_BC, STRONG_KB]


def cv_project(model: str, dist, K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """OpenCV's projection of camera-frame points X (P, 3): the oracle."""
    if model == "brown_conrady":
        uv, _ = cv2.projectPoints(X.astype(np.float64), np.zeros(3), np.zeros(3), K, np.asarray(dist, np.float64))
    else:
        uv, _ = cv2.fisheye.projectPoints(X.astype(np.float64)[:, None], np.zeros(3), np.zeros(3), K,
                                          np.asarray(dist, np.float64))
    return uv.reshape(-1, 2)


def make_scene(model: str, dist, T: int = 3) -> fs.Scene:
    """A wall 4 m ahead (the whole view: 88 deg off axis at its edges), a sphere in front of it moving right and a
    box moving left."""
    cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
    scene = fs.Scene(camera=cam, num_frames=T)
    scene.set_camera_poses(np.tile(np.eye(4), (T, 1, 1)))
    wall = np.tile(np.eye(4), (T, 1, 1))
    wall[:, 2, 3] = 4.0
    scene.add_object(trimesh.creation.box((200.0, 200.0, 0.2)), poses=wall)
    sph = np.tile(np.eye(4), (T, 1, 1))
    sph[:, :3, 3] = [0.3, 0.1, 2.5]
    sph[:, 0, 3] += 0.15 * np.arange(T)
    scene.add_object(trimesh.creation.icosphere(3, 0.6), poses=sph)
    box = np.tile(np.eye(4), (T, 1, 1))
    box[:, :3, 3] = [-1.0, -0.4, 3.0]
    box[:, 0, 3] -= 0.1 * np.arange(T)
    scene.add_object(trimesh.creation.box((0.5, 0.5, 0.5)), poses=box)
    return scene


def pixel_grid() -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:H, 0:W]
    return u.astype(np.float64), v.astype(np.float64)


@pytest.mark.parametrize("lens", LENSES)
def test_rays_project_back_through_opencv(lens):
    """Each covered pixel's ray projects onto its own centre through OpenCV; kornia's projection agrees."""
    model, dist = lens
    cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
    rays = cam.pixel_rays_numpy()
    cov = cam.covered
    assert cov.any() and np.isfinite(rays).all()
    assert (rays[~cov] == 0).all()
    u, v = pixel_grid()
    X = rays[cov] * 3.0
    target = np.stack([u[cov], v[cov]], 1)
    assert np.abs(cv_project(model, dist, cam.K, X) - target).max() < 1e-6
    uv, ok = cam.project(X)
    assert ok.all() and np.abs(uv - target).max() < 1e-6
    if lens in (STRONG_BC, STRONG_KB):
        assert not cov.all()  # the corners lie beyond the image of the domain
        # an uncovered pixel has no preimage in the domain: the domain's edge projects inside its radius
        lim = cam.lens_limit
        if model == "brown_conrady":
            edge = np.array([[np.sqrt(lim) * (1 - 1e-9), 0.0, 1.0]])
        else:
            edge = np.array([[np.tan(lim) * (1 - 1e-9) if lim < np.pi / 2 else 1e6, 0.0, 1.0]])
        r_edge = np.abs(cam.project(edge)[0][0, 0] - cam.cx)
        r_pix = np.hypot((u - cam.cx), (v - cam.cy))
        assert (r_pix[~cov] > r_edge - 1e-6).all()


def test_unproject_against_kornia():
    """Camera.unproject inverts kornia's distort_points (Brown-Conrady) and distort_points_kannala_brandt."""
    from kornia.geometry.calibration import distort_points
    from kornia.geometry.camera import distort_points_kannala_brandt

    rng = np.random.default_rng(0)
    ab = rng.uniform(-0.6, 0.6, size=(200, 2))
    for model, dist in (BC, BC8, KB):
        cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
        K = torch.from_numpy(cam.K)
        if model == "brown_conrady":
            pix = torch.from_numpy(ab @ cam.K[:2, :2].T + cam.K[:2, 2])
            d = torch.tensor(dist, dtype=torch.float64)
            uv = distort_points(pix, K, torch.nn.functional.pad(d, (0, 8 - len(dist)))).numpy()
        else:
            params = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy, *dist], dtype=torch.float64)
            uv = distort_points_kannala_brandt(torch.from_numpy(ab), params).numpy()
        rays, ok = cam.unproject(uv)
        assert ok.all()
        np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], ab, atol=1e-10)


@pytest.mark.parametrize("lens", [BC, KB, STRONG_BC])
def test_surface_points_and_flow_against_opencv(lens):
    """position projects back onto its pixel; flow_fw (gap 1 and 2) and flow_bw equal OpenCV's projection of the
    surface point in the target frame minus the pixel, over the valid pixels; no NaN anywhere."""
    model, dist = lens
    scene = make_scene(model, dist)
    keys = ["position", "depth", "instance", "flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "oof_fw",
            "distance"]
    out = fs.render(scene, keys, flow_gaps=(1, 2))
    for k, t in out.items():
        assert torch.isfinite(t.float()).all(), k
    K = scene.camera.K
    u, v = pixel_grid()
    inst = out["instance"][:, 0].numpy()
    pos = out["position"].numpy().transpose(0, 2, 3, 1).astype(np.float64)
    cov = scene.camera.covered
    assert ((inst[0] > 0) == cov).all()  # the wall fills the view: every covered pixel hits, no other does
    assert (out["depth"][:, 0].numpy()[:, ~cov] == 0).all()
    hit = inst[0] > 0
    assert np.abs(cv_project(model, dist, K, pos[0][hit]) - np.stack([u[hit], v[hit]], 1)).max() < 1e-3
    # depth along the ray: distance x ray = the camera-frame point (camera at the origin)
    Xd = scene.camera.pixel_rays_numpy()[hit] * out["distance"][0, 0].numpy()[hit, None]
    assert np.abs(cv_project(model, dist, K, Xd) - np.stack([u[hit], v[hit]], 1)).max() < 1e-3

    def moved(s: int, r: int) -> np.ndarray:
        """Surface points of frame s carried to frame r with their objects (camera frame = world here)."""
        X = np.zeros_like(pos[s])
        for k, o in enumerate(scene.objects, 1):
            m = inst[s] == k
            p_obj = (pos[s][m] - o.poses[s][:3, 3]) @ o.poses[s][:3, :3]
            X[m] = p_obj @ o.poses[r][:3, :3].T + o.poses[r][:3, 3]
        return X

    for key, s, r in (("flow_fw", 0, 1), ("flow_fw_k2", 0, 2), ("flow_bw", 1, 0)):  # pair 0 of each
        valid = out[key.replace("flow", "valid")][0, 0].numpy()
        assert valid.sum() > 0.5 * cov.sum()
        fl = out[key][0].numpy().transpose(1, 2, 0)[valid]
        want = cv_project(model, dist, K, moved(s, r)[valid]) - np.stack([u[valid], v[valid]], 1)
        assert np.abs(fl - want).max() < 1e-3, key
    assert not out["valid_fw"][:, 0].numpy()[:, ~cov].any()


def test_outside_domain_is_out_of_frame():
    """A point beyond the fold of a strong barrel lens projects nowhere: valid False, oof True, flow 0."""
    model, dist = STRONG_BC
    cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
    r = np.sqrt(cam.lens_limit)
    X = np.array([[0.5 * r, 0.0, 1.0], [1.5 * r, 0.0, 1.0], [0.0, 0.0, -1.0]])
    uv, ok = cam.project(X)
    assert ok.tolist() == [True, False, False] and (uv[1:] == 0).all()
    # the scene: an object moving from the centre to beyond the fold
    T = 2
    scene = fs.Scene(camera=cam, num_frames=T)
    scene.set_camera_poses(np.tile(np.eye(4), (T, 1, 1)))
    P = np.tile(np.eye(4), (T, 1, 1))
    P[:, 2, 3] = 2.0
    P[1, 0, 3] = 2.0 * 1.5 * r
    scene.add_object(trimesh.creation.box((0.3, 0.3, 0.1)), poses=P)
    out = fs.render(scene, ["instance", "valid_fw", "oof_fw", "occ_fw", "flow_fw"])
    hit = out["instance"][0, 0].numpy() > 0
    assert hit.any()
    assert not out["valid_fw"][0, 0].numpy()[hit].any()
    assert out["oof_fw"][0, 0].numpy()[hit].all() and out["occ_fw"][0, 0].numpy()[hit].all()
    assert (out["flow_fw"][0].numpy()[:, hit] == 0).all()


@pytest.mark.parametrize("lens", [BC, KB])
def test_tracks_and_boxes_through_the_model(lens):
    """Tracks equal OpenCV's projection of the query point carried by its object; the amodal box bounds OpenCV's
    projection of the mesh vertices; visible boxes and counts come from the distorted instance map."""
    model, dist = lens
    scene = make_scene(model, dist)
    out = fs.render(scene, ["instance", "position", "target_points", "occluded", "query_points", "box2d_amodal",
                            "box2d_visible", "visible_pixels"], num_tracks=64, track_sampling="objects")
    K = scene.camera.K
    q = out["query_points"].numpy().astype(int)
    pos = out["position"].numpy().transpose(0, 2, 3, 1).astype(np.float64)
    inst = out["instance"][:, 0].numpy()
    tp = out["target_points"].numpy()
    for n, (tq, i, j) in enumerate(q):
        o = scene.objects[inst[tq, i, j] - 1]
        p_obj = (pos[tq, i, j] - o.poses[tq][:3, 3]) @ o.poses[tq][:3, :3]
        X = p_obj @ np.swapaxes(o.poses[:, :3, :3], 1, 2) + o.poses[:, :3, 3]
        assert np.abs(tp[n] - cv_project(model, dist, K, X)).max() < 1e-3
        assert not out["occluded"][n, tq]
    for t in range(scene.num_frames):
        for n, o in enumerate(scene.objects):
            V = np.asarray(o.mesh.vertices) @ o.poses[t][:3, :3].T + o.poses[t][:3, 3]
            uv = cv_project(model, dist, K, V)
            x0, y0, x1, y1 = out["box2d_amodal"][t, n].numpy()
            inside = (uv[:, 0] > -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < H - 0.5)
            assert (uv[inside, 0] >= x0 - 1e-3).all() and (uv[inside, 0] <= x1 + 1e-3).all()
            assert (uv[inside, 1] >= y0 - 1e-3).all() and (uv[inside, 1] <= y1 + 1e-3).all()
            m = inst[t] == n + 1
            assert out["visible_pixels"][t, n] == m.sum()
            if m.any():
                rows, cols = np.nonzero(m)
                np.testing.assert_array_equal(out["box2d_visible"][t, n].numpy(),
                                              [cols.min() - 0.5, rows.min() - 0.5, cols.max() + 0.5, rows.max() + 0.5])


def test_meta_round_trip_and_native_files(tmp_path):
    """Provenance records the lens; Scene.from_meta re-renders bit for bit; the native layout writes model and
    coefficients beside K."""
    from flowsynth.io.sampleio import write_sample
    from flowsynth.scene.scene import provenance_json

    scene = make_scene(*KB, T=2)
    meta = scene.to_meta()
    assert meta["camera"]["model"] == "kannala_brandt" and meta["camera"]["dist"] == list(KB[1])
    again = fs.Scene.from_meta(json.loads(json.dumps(meta)))
    assert again.camera.model == "kannala_brandt" and again.camera.dist == KB[1]
    keys = ["depth", "flow_fw", "instance", "K"]
    a, b = fs.render(scene, keys), fs.render(again, keys)
    for k in keys:
        assert torch.equal(a[k], b[k]), k
    sample = dict(a)
    sample["provenance"] = provenance_json(scene)
    write_sample(sample, tmp_path)
    written = json.loads((tmp_path / "meta.json").read_text())
    assert written["camera_model"] == "kannala_brandt" and written["camera_dist"] == list(KB[1])
    assert "K" in written
    pin = fs.Camera.from_fov(W, H, 60.0)
    assert pin.lens_meta() == {}  # pinhole files and provenance keep their old form


def test_config_draws_and_validation():
    cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, camera_model="brown_conrady",
                                  camera_dist=(-0.2, 0.0, 0.0, 0.0), camera_dist_max=(-0.1, 0.05, 0.001, 0.001))
    from flowsynth.scene.sampling import sample_layout, sample_scene

    s1, s2 = sample_scene(cfg, 0, 0), sample_scene(cfg, 0, 1)
    for s in (s1, s2):
        d = np.array(s.camera.dist)
        assert s.camera.model == "brown_conrady"
        assert (d >= cfg.camera_dist).all() and (d <= cfg.camera_dist_max).all()
    assert s1.camera.dist != s2.camera.dist
    # the lens draw leaves every other draw as it was
    base = fs.BouncingThingsConfig(width=W, height=H, num_frames=2)
    la, lb = sample_layout(cfg, 0, 1), sample_layout(base, 0, 1)
    np.testing.assert_array_equal(la.world_T_cam, lb.world_T_cam)
    np.testing.assert_array_equal(la.initial.position, lb.initial.position)
    bad = [dict(camera_model="fisheye"), dict(camera_model="brown_conrady", camera_dist=(0.1, 0.2)),
           dict(camera_model="kannala_brandt", camera_dist=(0.1, 0.2, 0.3, 0.4, 0.5)),
           dict(camera_model="pinhole", camera_dist=(0.1, 0.0, 0.0, 0.0)),
           dict(camera_model="kannala_brandt", camera_dist=(0.1, 0, 0, 0), camera_dist_max=(0.0, 0, 0, 0)),
           dict(camera_model="kannala_brandt", camera_dist=(0.1, 0, 0, 0), camera_dist_max=(0.2, 0, 0)),
           dict(camera_model="brown_conrady", camera_dist=(float("nan"), 0, 0, 0))]
    for kw in bad:
        with pytest.raises(ConfigError):
            fs.BouncingThingsConfig(**kw)
    with pytest.raises(ConfigError, match="skew"):
        fs.Camera(np.array([[50.0, 1.0, 30.0], [0, 50.0, 20.0], [0, 0, 1]]), W, H, model=KB[0], dist=KB[1])
    with pytest.raises(ConfigError, match="not available"):
        fs.render(make_scene(*BC, T=2), ["disparity"], stereo_baseline=0.1)


def test_cli_flags(tmp_path, capsys):
    """The new fields are flags; a bad value is exit status 2 with the ConfigError's message."""
    args = ["preview", "--out", str(tmp_path / "p.png"), "--width", "32", "--height", "24", "--num-frames", "2",
            "--camera-model", "kannala_brandt", "--camera-dist", "0.1,0.2"]
    assert cli.main(args) == 2
    assert "kannala_brandt camera takes 4" in capsys.readouterr().err
    assert cli.main(args[:-2] + ["--camera-model", "fisheye"]) == 2
    assert "camera model must be one of" in capsys.readouterr().err
    assert cli.main(args[:-1] + ["0.1,abc,0,0"]) == 2  # does not parse: argparse names the flag
    assert "--camera-dist" in capsys.readouterr().err
    ns = cli._parser().parse_args(["export", "--out", str(tmp_path / "x"), "--num", "1", "--camera-model",
                                   "brown_conrady", "--camera-dist=-0.1,0.01,0,0",  # '=': a value may start with -
                                   "--camera-dist-max", "0.0,0.02,0,0"])
    cfg = cli.build_config(ns)
    assert cfg.camera_model == "brown_conrady" and cfg.camera_dist_max == (0.0, 0.02, 0.0, 0.0)


# --- RGB through the lens (flowsynth/kernels/shade.py's lens variant) ---------------------------------------------

# How far a sub-pixel sample's ray (the renormalised bilinear blend of its four surrounding centres' rays,
# kernels/shade.lens_ray) may project from its image point through OpenCV, at W x H with a 100 deg field of view
# [px]: measured 0.018 (BC), 0.007 (BC8), 0.009 (KB); near the fold of the strong lenses the unprojection's slope
# grows without bound and so does the blend's error (0.073 and 0.048). At 640 x 480 each is ~10x smaller.
SUBPIXEL_TOL = {BC: 0.03, BC8: 0.03, KB: 0.03, STRONG_BC: 0.15, STRONG_KB: 0.15}


def _subpixel_rays(cam: fs.Camera, uv: np.ndarray) -> np.ndarray:
    """kernels/shade.lens_ray at image points uv (P, 2), on the ray grid the shading kernel reads."""
    import warp as wp

    from flowsynth.raycast.accel import pinhole
    from flowsynth.kernels import wp_runtime
    from flowsynth.kernels.shade import lens_ray
    from flowsynth.renderer.shading import LENS_RAY_PAD

    wp_runtime()

    @wp.kernel(enable_backward=False, module="unique")
    def rays_at(uv: wp.array[wp.vec2], rays: wp.array2d[wp.vec3], pad: wp.int32, out: wp.array[wp.vec3]):
        k = wp.tid()
        out[k] = lens_ray(uv[k][1], uv[k][0], rays, pad)

    out = wp.empty(len(uv), dtype=wp.vec3, device="cpu")
    wp.launch(rays_at, len(uv), [wp.array(uv.astype(np.float32), dtype=wp.vec2, device="cpu"),
                                 pinhole(cam, "cpu", pad=LENS_RAY_PAD).rays, LENS_RAY_PAD], [out], device="cpu")
    return out.numpy().astype(np.float64)


@pytest.mark.parametrize("lens", LENSES)
def test_subpixel_rays_project_back_through_opencv(lens):
    """A sub-pixel sample's ray projects back onto its image point through OpenCV within SUBPIXEL_TOL; it is
    uncovered (0, 0, -1) exactly when one of the four pixel centres around it is."""
    model, dist = lens
    cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
    rng = np.random.default_rng(3)
    uv = np.stack([rng.uniform(-0.5, W - 0.5, 4000), rng.uniform(-0.5, H - 0.5, 4000)], 1)
    uv[:4] = [[-0.5, -0.5], [W - 0.501, H - 0.501], [cam.cx, cam.cy], [0.0, 0.0]]  # corners, the axis, a centre
    rays = _subpixel_rays(cam, uv)
    assert np.isfinite(rays).all()
    grid = cam.ray_grid(2)[..., 2] > 0  # rows and columns -2 .. H + 1
    i0, j0 = np.floor(uv[:, 1]).astype(int) + 2, np.floor(uv[:, 0]).astype(int) + 2
    four = grid[i0, j0] & grid[i0 + 1, j0] & grid[i0, j0 + 1] & grid[i0 + 1, j0 + 1]
    ok = rays[:, 2] > 0
    np.testing.assert_array_equal(ok, four)
    assert (rays[~ok] == [0.0, 0.0, -1.0]).all()
    assert ok.mean() > 0.2
    np.testing.assert_allclose(np.linalg.norm(rays[ok], axis=1), 1.0, atol=1e-6)
    err = np.abs(cv_project(model, dist, cam.K, rays[ok]) - uv[ok]).max()
    assert err < SUBPIXEL_TOL[lens], err
    # a pixel centre's blend is its own ray (float32)
    c = np.array([[W // 2 + 3.0, H // 2 - 2.0]])
    np.testing.assert_allclose(_subpixel_rays(cam, c)[0], cam.pixel_rays_numpy()[H // 2 - 2, W // 2 + 3], atol=1e-6)


@pytest.mark.parametrize("lens", [STRONG_BC, STRONG_KB])
def test_rgb_uncovered_black_and_finite(lens):
    """rgb of a lens camera: finite, exactly 0 at uncovered pixels, lit elsewhere; the same with spp > 1,
    edge_spp > 1 and motion blur, and rgb_final; stereo stays refused."""
    scene = make_scene(*lens)
    cov = scene.camera.covered
    assert (~cov).any()
    runs = [dict(), dict(edge_spp=8), dict(spp=4, edge_spp=16, shutter=0.5), dict(spp=2, render_mode="direct")]
    for kw in runs:
        out = fs.render(scene, ["rgb", "instance"], **kw)
        rgb = out["rgb"].numpy()
        assert np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.max() <= 1, kw
        assert (rgb[:, :, ~cov] == 0).all(), kw
        assert (rgb[:, :, cov].max(1) > 0.02).mean() > 0.95, kw  # the wall fills the covered view
    fin = fs.render(scene, ["rgb_final"])["rgb_final"].numpy()
    assert np.isfinite(fin).all() and fin.max() > 0
    with pytest.raises(ConfigError, match="not available"):
        fs.render(scene, ["depth_right"], stereo_baseline=0.1)


def _textured_scene(cam: fs.Camera) -> fs.Scene:
    """One frame of make_scene's wall, sphere and box, textured with smooth one-octave value noise (no grain, no
    specular) under a white sky only: a pixel's colour is the albedo at its surface point, the same seen through
    any camera (flat shading)."""
    scene = fs.Scene(camera=cam, num_frames=1)
    scene.set_camera_poses(np.eye(4)[None])
    for mesh, pos, scale in ((trimesh.creation.box((200.0, 200.0, 0.2)), (0.0, 0.0, 4.0), 0.35),
                             (trimesh.creation.icosphere(4, 0.6), (0.3, 0.1, 2.5), 1.5),
                             (trimesh.creation.box((0.5, 0.5, 0.5)), (-1.0, -0.4, 3.0), 1.0)):
        P = np.eye(4)
        P[:3, 3] = pos
        scene.add_object(mesh, poses=P[None], material={
            "texture": "value", "octaves": 1, "scale": scale, "specular": 0.0,
            "colors": [[0.95, 0.75, 0.1], [0.1, 0.25, 0.9]]})
    scene.lights = [{"kind": "ambient", "color": (1.0, 1.0, 1.0), "intensity": 1.0}]
    return scene


def _oracle_pinhole(width: int = 384, height: int = 288) -> fs.Camera:
    """A pinhole camera that sees every ray within ORACLE_DEG of the axis (2 px inside its edges)."""
    f = (height / 2 - 2) / np.tan(np.radians(ORACLE_DEG))
    K = np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    return fs.Camera(K, width, height)


# The rgb comparison covers the rays within this angle of the axis [deg]: farther out the wall is seen so obliquely
# that a lens pixel's texture footprint spans a good part of a texture period, and the texture filter (which
# fades octaves by footprint, kernels/texture.py) blurs differently in the two cameras.
ORACLE_DEG = 50.0


def _interior(inst: np.ndarray) -> np.ndarray:
    """(H, W) pixels whose 8 neighbours see the same instance (away from silhouettes), image border excluded."""
    m = np.zeros(inst.shape, bool)
    c = inst[1:-1, 1:-1]
    m[1:-1, 1:-1] = np.all([inst[1 + di:inst.shape[0] - 1 + di, 1 + dj:inst.shape[1] - 1 + dj] == c
                            for di in (-1, 0, 1) for dj in (-1, 0, 1)], axis=0)
    return m & (inst > 0)


@pytest.mark.parametrize("lens", [BC, KB])
def test_rgb_is_the_distorted_pinhole_image(lens):
    """The lens render is the pinhole render warped by the lens model.

    Oracle 1: cv2.remap of a finer pinhole render of the same scene by OpenCV's undistortion of each lens pixel
    (cv2.undistortPoints / cv2.fisheye.undistortPoints, 200 iterations, into the pinhole's pixels). Oracle 2
    (hit consistency): where the lens render's instance map says object k, the pinhole render sees object k at
    the projection of the lens pixel's surface point (G-buffer position) and has its colour there. Both over
    pixels away from silhouettes and within ORACLE_DEG of the axis.

    Tolerance: the colour is the albedo of a smooth texture (one octave, >= ~8 lens pixel footprints per
    period), so the residual is the bilinear interpolation of the ~4x finer pinhole image and the texture
    filter's different footprints: 0.02 (sRGB, [0, 1]) at the worst pixel and 0.001 on average (measured 0.008
    and 4e-5); a warp that ignores the distortion is ~1000x worse on average, asserted 20x (the check can fail).
    With spp 16 the lens pixel is box-filtered, the oracle point-sampled: 0.06 and 0.003 (measured 0.032 and
    6e-4)."""
    model, dist = lens
    cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
    pin = _oracle_pinhole()
    keys = ["rgb", "instance", "position"]
    lens_out = fs.render(_textured_scene(cam), keys, render_mode="flat")
    pin_out = fs.render(_textured_scene(pin), keys, render_mode="flat")
    rgb = lens_out["rgb"][0].numpy().transpose(1, 2, 0)
    inst = lens_out["instance"][0, 0].numpy()
    prgb = np.ascontiguousarray(pin_out["rgb"][0].numpy().transpose(1, 2, 0))
    pinst = pin_out["instance"][0, 0].numpy()
    u, v = pixel_grid()
    src = np.stack([u.ravel(), v.ravel()], 1)[:, None].astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    if model == "brown_conrady":
        und = cv2.undistortPoints(src, cam.K, np.asarray(dist), R=np.eye(3), P=pin.K, criteria=crit)
    else:
        und = cv2.fisheye.undistortPoints(src, cam.K, np.asarray(dist), R=np.eye(3), P=pin.K, criteria=crit)
    mx, my = (und.reshape(H, W, 2)[..., c].astype(np.float32) for c in (0, 1))

    def warp(img, interp=cv2.INTER_LINEAR):
        return cv2.remap(img, mx, my, interp, borderMode=cv2.BORDER_REPLICATE)

    # pixels inside objects on both sides: the warped pinhole instance map agrees around the sample point
    same = np.all([cv2.remap(pinst.astype(np.float32), mx + dx, my + dy, cv2.INTER_NEAREST) == inst
                   for dx in (-1.5, 0, 1.5) for dy in (-1.5, 0, 1.5)], axis=0)
    rays = cam.pixel_rays_numpy()
    mask = _interior(inst) & same & (rays[..., 2] > np.cos(np.radians(ORACLE_DEG - 1)))
    assert mask.sum() > 0.3 * W * H and len(np.unique(inst[mask])) == 3
    err = np.abs(rgb - warp(prgb))[mask]
    assert err.max() < 0.02 and err.mean() < 0.001, (err.max(), err.mean())
    # a pinhole of the lens's own K (the distortion ignored) is far off: the comparison sees the lens
    plain = np.stack([u * pin.fx / cam.fx + pin.cx - cam.cx * pin.fx / cam.fx,
                      v * pin.fy / cam.fy + pin.cy - cam.cy * pin.fy / cam.fy], -1).astype(np.float32)
    wrong = np.abs(rgb - cv2.remap(prgb, plain[..., 0], plain[..., 1], cv2.INTER_LINEAR))[mask]
    assert wrong.mean() > 20 * err.mean(), (wrong.mean(), err.mean())

    # oracle 2: the surface point of each lens pixel, seen by the pinhole
    X = lens_out["position"][0].numpy().transpose(1, 2, 0).astype(np.float64)  # camera = world here
    hit = inst > 0
    uvp = np.zeros((H, W, 2), np.float32)
    uvp[hit] = (X[hit] @ pin.K.T)[:, :2] / X[hit][:, 2:]
    near = cv2.remap(pinst.astype(np.float32), uvp[..., 0], uvp[..., 1], cv2.INTER_NEAREST)
    inner = _interior(inst) & (rays[..., 2] > np.cos(np.radians(ORACLE_DEG - 1)))
    assert (near[inner] == inst[inner]).all()
    err2 = np.abs(rgb - cv2.remap(prgb, uvp[..., 0], uvp[..., 1], cv2.INTER_LINEAR))[mask]
    assert err2.max() < 0.02 and err2.mean() < 0.001, (err2.max(), err2.mean())
    # and with sub-pixel samples (spp 16 box-filters each lens pixel: a smooth texture barely changes)
    blur = fs.render(_textured_scene(cam), ["rgb"], render_mode="flat", spp=16)["rgb"][0].numpy().transpose(1, 2, 0)
    err3 = np.abs(blur - warp(prgb))[mask]
    assert err3.max() < 0.06 and err3.mean() < 0.003, (err3.max(), err3.mean())


def test_project_equals_kornia():
    """Camera.project (numpy, kornia's equations) equals kornia's distort_points / distort_points_kannala_brandt."""
    from kornia.geometry.calibration import distort_points
    from kornia.geometry.camera import distort_points_kannala_brandt

    rng = np.random.default_rng(5)
    ab = rng.uniform(-0.8, 0.8, size=(500, 2))
    ab[0], ab[1] = 0.0, (1e-9, -2e-9)  # the axis and next to it
    for model, dist in LENSES:
        cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
        uv, ok = cam.project(np.concatenate([ab, np.ones((len(ab), 1))], 1))
        K = torch.from_numpy(cam.K)
        if model == "brown_conrady":
            d = torch.nn.functional.pad(torch.tensor(dist, dtype=torch.float64), (0, 8 - len(dist)))
            ref = distort_points(torch.from_numpy(ab @ cam.K[:2, :2].T + cam.K[:2, 2]), K, d).numpy()
        else:
            params = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy, *dist], dtype=torch.float64)
            ref = distort_points_kannala_brandt(torch.from_numpy(ab), params).numpy()
        assert ok.sum() > 400
        np.testing.assert_allclose(uv[ok], ref[ok], rtol=0, atol=1e-9)


@pytest.mark.parametrize("lens", [BC, KB, STRONG_BC, STRONG_KB])
def test_lens_tile_lists_match_brute_force(lens, monkeypatch):
    """The lens tile lists (tiles._lens_tile_mask) change no bit against every instance in every tile
    (tiles.LENS_TILE_BOUNDS = False): G-buffer, flow with exact occlusion (visibility rays walk the tile of their
    target pixel) and rgb with sub-pixel samples at silhouettes (their blended rays walk their pixel's tile), on
    random rooms with objects; and the lists are shorter."""
    from flowsynth.raycast import accel, tiles
    from flowsynth.raycast.gbuffer import cast_gbuffer, scene_arrays

    model, dist = lens
    cfg = fs.BouncingThingsConfig(width=80, height=60, num_frames=2, camera_model=model, camera_dist=dist)
    ds = fs.datasets.BouncingThings(cfg, outputs=["depth"], seed=7)
    keys = ["instance", "depth", "normals", "flow_fw", "valid_fw", "occ_fw", "flow_bw", "occ_bw", "rgb"]
    for i in range(3):
        scene = ds.scene(i)
        got = {}
        for brute in (False, True):
            monkeypatch.setattr(tiles, "LENS_TILE_BOUNDS", not brute)
            acc = accel.SceneAccel(*scene_arrays(scene))
            gb = cast_gbuffer(acc, scene.camera, want_normals=True, want_points=True)
            out = fs.render(scene, keys, edge_spp=8)
            got[brute] = (gb, out, len(acc.tile_lists(scene.camera).items.numpy()))
        (g0, o0, n0), (g1, o1, n1) = got[False], got[True]
        for name in ("dist", "item", "face", "point", "normal"):
            np.testing.assert_array_equal(getattr(g0.host(), name), getattr(g1.host(), name), err_msg=name)
        for k in keys:
            assert torch.equal(o0[k], o1[k]), k
        assert n0 < n1
        assert (g0.host().item >= 0).any() and o0["occ_fw"].any()
