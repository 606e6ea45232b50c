"""Lens models (flowsynth/camera.py): rays, flow, tracks and boxes through Brown-Conrady and Kannala-Brandt, against
OpenCV's cv2.projectPoints / cv2.fisheye.projectPoints (an implementation nobody here wrote) and kornia."""

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
    from flowsynth.sampleio import write_sample
    from flowsynth.scene import provenance_json

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
    from flowsynth.sampling import sample_layout, sample_scene

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
