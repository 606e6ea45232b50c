"""Rectified stereo (stereo_baseline) against independent float64 oracles (issue 17).

Oracles: d = fx B / Z from the depth map, and a brute-force stereo oracle: both views cast by
tests/oracle.py, the left view's world points projected into the right camera (u_L - u_R is the
disparity), visibility between the views by brute-force rays, and FlyingThings3D's disparity change from
the oracle's reprojected depth in frame t+1. None calls flowsynth's stereo code.
"""

import numpy as np
import pytest
import torch
import trimesh
from oracle import bilinear, boundary, cast_frame, pair_truth, pose, project, rigid_inverse, visible
from torch.utils.data import default_collate

import flowsynth as fs
from flowsynth.io.sampleio import read_sample, write_sample

W, H = 64, 48
B = 0.3
KEYS = ["depth", "instance", "depth_right", "disparity", "disparity_right", "disparity_change", "disparity_occ",
        "disparity_occ_right", "valid_fw"]


def stereo_clip(skew: float = 0.0):
    """T = 3: a wall, a slab close to the camera (large disparity, wide occlusions), a spinning cube, a ball
    moving in depth; the camera moves and turns."""
    T = 3
    cams = np.stack([pose((0.01 * t, -0.02 * t, 0.0), (0.05 * t, 0.02 * t, 0.15 * t)) for t in range(T)])
    objs = [
        (trimesh.creation.box((16.0, 12.0, 0.2)), np.stack([pose((0.0, 0.15, 0.0), (0.0, 0.0, 10.0))] * T)),
        (trimesh.creation.box((0.8, 1.5, 0.1)), np.stack([pose((0.0, 0.2, 0.0), (-0.6 + 0.2 * t, 0.0, 2.0))
                                                           for t in range(T)])),
        (trimesh.creation.box((1.0, 1.0, 1.0)), np.stack([pose((0.2, 0.4 + 0.5 * t, 0.0), (0.6, 0.3, 5.0))
                                                           for t in range(T)])),
        (trimesh.creation.icosphere(2, radius=0.5), np.stack([pose(t=(1.5, -0.8, 6.0 - 1.0 * t)) for t in range(T)])),
    ]
    K = np.array([[60.0, skew, 31.5], [0.0, 58.0, 23.5], [0.0, 0.0, 1.0]])
    scene = fs.Scene(fs.Camera(K, W, H), T)
    scene.set_camera_poses(cams)
    for mesh, P in objs:
        scene.add_object(mesh, poses=P)
    return scene, cams, np.stack([P for _, P in objs], 1)


@pytest.mark.parametrize("skew", [0.0, 3.0])
def test_disparity_equals_brute_force_stereo(skew):
    scene, cams, world_T_obj = stereo_clip(skew)
    out = fs.render(scene, KEYS, stereo_baseline=B)
    K, meshes, T = scene.camera.K, [o.mesh for o in scene.objects], scene.num_frames
    right = cams @ pose(t=(B, 0.0, 0.0))
    dz = scene.camera.pixel_rays_numpy()[..., 2]
    totals = {"occ": 0, "occ_right": 0, "disagree": 0}
    for t in range(T):
        left_c = cast_frame(K, W, H, cams[t], meshes, world_T_obj[t])
        right_c = cast_frame(K, W, H, right[t], meshes, world_T_obj[t])
        disp = out["disparity"][t, 0].double().numpy()
        depth = out["depth"][t, 0].double().numpy()
        hit = depth > 0
        # d = fx B / Z, 0 where nothing is hit
        assert np.allclose(disp[hit], K[0, 0] * B / depth[hit], rtol=1e-6) and (disp[~hit] == 0).all()
        # right view: depth against brute-force casting, d_R = fx B / Z_R
        zr = np.where(right_c["hit"], right_c["t"], 0.0) * dz
        dr = out["depth_right"][t, 0].double().numpy()
        same_r = (dr > 0) == right_c["hit"]
        assert same_r[~boundary(right_c["instance"])].all()
        sel = same_r & right_c["hit"] & ~boundary(right_c["instance"])
        assert np.abs(dr - zr)[sel].max() < 1e-4 * zr[sel].max()
        drr = out["disparity_right"][t, 0].double().numpy()
        assert np.allclose(drr[sel], K[0, 0] * B / zr[sel], rtol=1e-5)
        # left pixel -> its world point -> right camera: same row, u_R = u_L - disparity
        ok = left_c["hit"] & (out["instance"][t, 0].numpy() == left_c["instance"])
        i, j = np.nonzero(ok)
        Xw = np.einsum("pij,pj->pi", world_T_obj[t, left_c["obj"][i, j], :3, :3], left_c["p"][i, j]) \
            + world_T_obj[t, left_c["obj"][i, j], :3, 3]
        Xr = Xw @ rigid_inverse(right[t])[:3, :3].T + rigid_inverse(right[t])[:3, 3]
        uv = project(K, Xr)
        assert np.abs(uv[:, 1] - i).max() < 1e-6, "rectified: the point stays on its row"
        assert np.abs((j - uv[:, 0]) - disp[i, j]).max() < 1e-3
        # occlusion between the views: brute-force visibility from the other camera, off silhouettes
        inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5)
        vis = np.zeros(len(i), bool)
        vis[inside] = visible(Xw[inside], right[t], meshes, world_T_obj[t])
        occ = out["disparity_occ"][t, 0].numpy()
        jj = np.clip(np.rint(uv[:, 0]), 0, W - 1).astype(int)
        sil = boundary(left_c["instance"])[i, j] | boundary(right_c["instance"])[i, jj]
        wrong = occ[i, j] != ~vis
        assert not (wrong & ~sil).any(), np.argwhere(wrong & ~sil)[:5]
        assert not occ[~left_c["hit"]].any()
        totals["occ"] += int((~vis & inside).sum())
        totals["disagree"] += int(wrong.sum())
        # right pixels hidden from the left camera
        ir, jr = np.nonzero(right_c["hit"] & (dr > 0))
        Xw_r = np.einsum("pij,pj->pi", world_T_obj[t, right_c["obj"][ir, jr], :3, :3], right_c["p"][ir, jr]) \
            + world_T_obj[t, right_c["obj"][ir, jr], :3, 3]
        uvl = project(K, Xw_r @ rigid_inverse(cams[t])[:3, :3].T + rigid_inverse(cams[t])[:3, 3])
        vis_l = np.zeros(len(ir), bool)
        in_l = (uvl[:, 0] >= -0.5) & (uvl[:, 0] < W - 0.5)
        vis_l[in_l] = visible(Xw_r[in_l], cams[t], meshes, world_T_obj[t])
        occ_r = out["disparity_occ_right"][t, 0].numpy()
        jl = np.clip(np.rint(uvl[:, 0]), 0, W - 1).astype(int)
        sil_r = boundary(right_c["instance"])[ir, jr] | boundary(left_c["instance"])[ir, jl]
        assert not ((occ_r[ir, jr] != ~vis_l) & ~sil_r).any()
        totals["occ_right"] += int((~vis_l & in_l).sum())
    print(f"stereo skew {skew}: {totals}")
    assert totals["occ"] > 50 and totals["occ_right"] > 50, "the slab must hide wall points from the other view"


@pytest.mark.parametrize("with_flow", [True, False], ids=["fw-pass", "own-pass"])
def test_disparity_change_is_flyingthings_definition(with_flow):
    """disparity_change[t] = fx B / z_{t+1} - fx B / z_t of the point seen at the left pixel of frame t,
    z_{t+1} its depth in frame t+1 by brute-force reprojection; 0 where not valid_fw. Asked for beside
    valid_fw it comes from the flow stage's fw pass, alone from stereo's own pass: both must hold."""
    scene, cams, world_T_obj = stereo_clip()
    keys = KEYS if with_flow else [k for k in KEYS if k != "valid_fw"]
    out = fs.render(scene, keys, stereo_baseline=B)
    if not with_flow:
        out["valid_fw"] = fs.render(scene, ["valid_fw"])["valid_fw"]
    K, meshes, casts = scene.camera.K, [o.mesh for o in scene.objects], {}
    moving = 0
    for t in range(scene.num_frames - 1):
        tr = pair_truth(K, W, H, cams, meshes, world_T_obj, t, t + 1, casts=casts, occlusion=False)
        dc = out["disparity_change"][t, 0].double().numpy()
        agree = out["instance"][t, 0].numpy() == tr["instance"]
        ok = agree & tr["valid"]
        z0 = out["depth"][t, 0].double().numpy()
        truth = K[0, 0] * B / np.where(ok, tr["z"], 1.0) - K[0, 0] * B / np.where(ok, z0, 1.0)
        assert np.abs(dc - truth)[ok].max() < 1e-4
        assert (dc[~out["valid_fw"][t, 0].numpy()] == 0).all()
        moving += int((np.abs(truth[ok]) > 0.05).sum())
    assert moving > 100, "the camera and the ball move in depth"


def test_rgb_right_sees_the_left_view_shifted_by_the_disparity():
    """Flat shading is view-independent: the right image sampled at (u - d, v) reproduces the left image
    where the point is visible in both views (texture interpolation error only), much better than unshifted."""
    scene, _, _ = stereo_clip()
    out = fs.render(scene, ["rgb", "rgb_right", "disparity", "disparity_occ", "instance"], stereo_baseline=B,
                    render_mode="flat")
    for t in range(scene.num_frames):
        left, right = (out[k][t].double().permute(1, 2, 0).numpy() for k in ("rgb", "rgb_right"))
        d = out["disparity"][t, 0].double().numpy()
        keep = (d > 0) & ~out["disparity_occ"][t, 0].numpy() & ~boundary(out["instance"][t, 0].numpy())
        i, j = np.nonzero(keep)
        shifted = bilinear(right, np.stack([j - d[i, j], i], 1))
        plain = right[i, j]
        e_shift, e_plain = np.abs(shifted - left[i, j]).mean(), np.abs(plain - left[i, j]).mean()
        print(f"frame {t}: |rgb_left - rgb_right(u - d)| {e_shift:.4f}, unshifted {e_plain:.4f}")
        assert e_shift < 0.03 and e_shift < 0.5 * e_plain


def test_validation_dataset_and_export(tmp_path):
    scene, *_ = stereo_clip()
    with pytest.raises(fs.ConfigError, match="stereo_baseline"):
        fs.render(scene, ["disparity"])
    with pytest.raises(fs.ConfigError, match="stereo_baseline"):
        fs.render(scene, ["disparity"], stereo_baseline=-1.0)
    with pytest.raises(fs.ConfigError, match="stereo_baseline"):
        fs.BouncingThingsConfig(stereo_baseline=float("nan"))
    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 3),
                                  stereo_baseline=0.2)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "rgb_right", "disparity", "disparity_change",
                                                  "disparity_occ", "meta"], seed=1)
    a, b = ds.sample(0), ds.sample(1)
    batch = default_collate([a, b])
    assert batch["rgb_right"].shape == (2, 2, 3, 24, 32) and batch["disparity_change"].shape == (2, 1, 1, 24, 32)
    write_sample(a, tmp_path)
    back = read_sample(tmp_path)
    assert back.pop("provenance") == a.pop("provenance")  # the scene record (tests/test_provenance.py)
    for k, v in a.items():
        assert back[k].dtype == v.dtype and back[k].shape == v.shape, k
        if k not in ("rgb", "rgb_right"):
            assert torch.equal(back[k], v), k
    png = tmp_path / "preview.png"
    from flowsynth.cli import main

    assert main(["preview", "--out", str(png), "--width", "32", "--height", "24", "--num-frames", "2",
                 "--num-objects", "1,2", "--motion", "kinematic", "--stereo-baseline", "0.2",
                 "--outputs", "rgb,rgb_right,disparity,disparity_occ"]) == 0
    assert png.stat().st_size > 0
