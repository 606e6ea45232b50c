"""Flow across frame gaps (``flow_gaps``) and scene flow against independent float64 oracles (issue 17).

Oracles: composed plane-induced homographies (the per-frame reprojections chained in float64), brute-force
ray casting + reprojection between frames t and t+k (tests/oracle.py ``pair_truth``), and rigid motions
whose 3D displacement is known in closed form. None calls flowsynth's flow code.
"""

import numpy as np
import pytest
import torch
import trimesh
from oracle import (
    apply,
    cast_frame,
    homography_flow,
    pair_truth,
    plane_homography,
    pose,
    quad,
    rigid_inverse,
    silhouette,
)
from torch.utils.data import default_collate

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.io.sampleio import read_sample, write_sample

W, H = 64, 48


def plane_clip(T: int, offset: float = 0.0):
    """A tilted 14 m quad ~6 m away; object and camera move and turn every frame."""
    shift = pose(t=np.array([1.0, -0.7, 0.5]) * offset / np.linalg.norm([1.0, -0.7, 0.5]))
    cams = np.stack([shift @ pose((0.01 * t, -0.02 * t, 0.005 * t), (0.08 * t, -0.05 * t, 0.1 * t)) for t in range(T)])
    objs = np.stack([shift @ pose((0.35 - 0.03 * t, -0.25 + 0.04 * t, 0.1), (0.1 - 0.1 * t, -0.2, 6.0 + 0.15 * t))
                     for t in range(T)])
    scene = fs.Scene(fs.Camera(np.array([[58.0, 0.0, 30.7], [0.0, 54.0, 24.2], [0, 0, 1]]), W, H), T)
    scene.set_camera_poses(cams)
    scene.add_object(quad(7.0), poses=objs)
    return scene, cams, objs


@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_gap_flow_equals_composed_homographies(offset):
    """flow_fw_kK[t] = H_{t+K-1 -> t+K} ... H_{t -> t+1} (per-frame homographies chained in float64);
    flow_bw_kK[t] the inverse chain; the gap-1 keys stay exactly what they were without flow_gaps."""
    T, gaps = 5, (1, 2, 4)
    scene, cams, objs = plane_clip(T, offset)
    keys = ["flow_fw", "flow_bw", "valid_fw", "valid_bw", "oof_fw"]
    out = fs.render(scene, keys, flow_gaps=gaps)
    plain = fs.render(scene, keys)
    for k in keys:
        assert torch.equal(out[k], plain[k]), k
    K = scene.camera.K
    cam_T_obj = rigid_inverse(cams) @ objs
    step = [plane_homography(K, cam_T_obj[t], cam_T_obj[t + 1]) for t in range(T - 1)]
    worst = 0.0
    for k in gaps:
        fw, bw = fs.plan.gap_key("flow_fw", k), fs.plan.gap_key("flow_bw", k)
        assert out[fw].shape == (T - k, 2, H, W) and out[fs.plan.gap_key("valid_bw", k)].shape == (T - k, 1, H, W)
        for t in range(T - k):
            Hm = np.eye(3)
            for s in range(t, t + k):
                Hm = step[s] @ Hm
            for key, truth in ((fw, homography_flow(Hm, W, H)), (bw, homography_flow(np.linalg.inv(Hm), W, H))):
                assert np.abs(truth).max() > 2.0 * k, "the motion must be visible"
                err = np.linalg.norm(out[key][t].double().permute(1, 2, 0).numpy() - truth, axis=-1)
                worst = max(worst, float(err.max()))
                assert err.mean() < 1e-3 and err.max() < 1e-2, (k, t, key, err.mean(), err.max())
    print(f"gap flow vs composed homographies, offset {offset:g} m: max EPE {worst:.2e} px")


def occluding_clip():
    """T = 4: a back wall, a slab sliding across objects, a spinning cube, a ball leaving the image."""
    T = 4
    cams = np.stack([pose((0.01 * t, -0.03 * t, 0.0), (0.1 * t, 0.05 * t, 0.1 * t)) for t in range(T)])
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    ball = trimesh.creation.icosphere(2, radius=0.5)
    objs = [
        (trimesh.creation.box((16.0, 12.0, 0.2)), np.stack([pose((0.0, 0.15, 0.0), (0.0, 0.0, 11.0))] * T)),
        (trimesh.creation.box((1.2, 2.0, 0.1)), np.stack([pose((0.0, 0.2, 0.0), (-1.2 + 0.5 * t, 0.0, 3.0))
                                                           for t in range(T)])),
        (cube, np.stack([pose((0.2, 0.4 + 0.5 * t, 0.0), (-0.4, 0.3, 6.0 - 0.2 * t)) for t in range(T)])),
        (ball, np.stack([pose(t=(1.6 + 0.9 * t, -0.6, 5.5)) for t in range(T)])),
    ]
    scene = fs.Scene(fs.Camera.from_fov(W, H, 70.0), T)
    scene.set_camera_poses(cams)
    for mesh, P in objs:
        scene.add_object(mesh, poses=P)
    return scene, cams, np.stack([P for _, P in objs], 1)


def test_gap_flow_and_occlusion_match_brute_force():
    """Every key at gaps 2 and 3 against brute-force casting of frames t and t+k (float64, exact
    visibility); occlusion may differ only on silhouettes, as for gap 1 (tests/test_occlusion.py)."""
    scene, cams, world_T_obj = occluding_clip()
    T = scene.num_frames
    keys = ["flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "instance"]
    out = fs.render(scene, keys, flow_gaps=(2, 3))
    assert "flow_fw" not in out and "flow_fw_k2" in out and "flow_bw_k3" in out
    K, meshes, casts = scene.camera.K, [o.mesh for o in scene.objects], {}
    hidden = 0
    for k in (2, 3):
        for t in range(T - k):
            for name, s, r in (("fw", t, t + k), ("bw", t + k, t)):
                tr = pair_truth(K, W, H, cams, meshes, world_T_obj, s, r, casts=casts)
                agree = out["instance"][s, 0].numpy() == tr["instance"]
                sel = agree & tr["valid"]
                flow = out[f"flow_{name}_k{k}"][t].double().permute(1, 2, 0).numpy()
                err = np.linalg.norm(flow - tr["flow"], axis=-1)[sel & ~tr["oof"]]
                assert err.max() < 1e-2 and err.mean() < 1e-3, (k, t, name, err.max())
                assert (out[f"valid_{name}_k{k}"][t, 0].numpy() == tr["valid"])[agree].all()
                assert (out[f"oof_{name}_k{k}"][t, 0].numpy() == tr["oof"])[agree].all()
                occ = out[f"occ_{name}_k{k}"][t, 0].numpy()
                sil = silhouette(tr["instance"], casts[r]["instance"], tr["uv"])
                assert not ((occ != tr["occ"]) & ~sil).any(), (k, t, name)
                hidden += int((occ & ~tr["oof"]).sum())
    assert hidden > 100, "the clip must hide points across the gaps"


def test_scene_flow_of_known_rigid_motion():
    """A translating box (displacement d per frame, known) and a box spinning about its own centre c
    by R per frame, seen by a moving, turning camera: scene_flow_fw = R_cam[t] d on the first,
    R_cam[t] (R - I)(X - c) on the second, 0 on the static wall; scene_flow_bw the motion back in the
    camera frame of t+1."""
    T = 3
    d = np.array([0.3, -0.1, 0.2])
    R = pose((0.0, 0.25, 0.1))
    c0 = np.array([0.9, 0.2, 5.0])
    cams = np.stack([pose((0.02 * t, 0.05 * t, 0.0), (0.2 * t, -0.1 * t, 0.05 * t)) for t in range(T)])
    objs = [
        (trimesh.creation.box((20.0, 20.0, 0.2)), np.stack([pose(t=(0.0, 0.0, 12.0))] * T)),
        (trimesh.creation.box((1.0, 1.0, 1.0)), np.stack([pose((0.3, 0.2, 0.0), (-1.0, 0.0, 5.0) + t * d)
                                                           for t in range(T)])),
        (trimesh.creation.box((1.0, 0.8, 0.6)), np.stack([pose(t=c0) @ np.linalg.matrix_power(R, t)
                                                           for t in range(T)])),
    ]
    scene = fs.Scene(fs.Camera.from_fov(W, H, 70.0), T)
    scene.set_camera_poses(cams)
    for mesh, P in objs:
        scene.add_object(mesh, poses=P)
    out = fs.render(scene, ["scene_flow_fw", "scene_flow_bw", "instance", "position", "depth"])
    world_T_obj = np.stack([P for _, P in objs], 1)
    for t in range(T - 1):
        for name, s in (("fw", t), ("bw", t + 1)):
            sf = out[f"scene_flow_{name}"][t].double().permute(1, 2, 0).numpy()
            inst = out["instance"][s, 0].numpy()
            Rc = rigid_inverse(cams[s])[:3, :3]
            # translating box: a constant vector, the world displacement in camera axes
            sign = 1 if name == "fw" else -1
            assert (inst == 2).sum() > 50
            assert np.abs(sf[inst == 2] - Rc @ (sign * d)).max() < 1e-6
            # spinning box: from the oracle's world point of the pixel (position) and the closed form
            X = out["position"][s].double().permute(1, 2, 0).numpy()[inst == 3]
            Rw = R[:3, :3] if name == "fw" else R[:3, :3].T
            truth = ((X - c0) @ (Rw - np.eye(3)).T) @ Rc.T
            assert (inst == 3).sum() > 50
            assert np.abs(sf[inst == 3] - truth).max() < 1e-5
            assert (sf[inst == 1] == 0).all() and (sf[inst == 0] == 0).all()
    # brute-force cross-check of one pair, gap 2 included: oracle hit point moved by the object poses
    out2 = fs.render(scene, ["scene_flow_fw", "instance"], flow_gaps=(2,))
    oc = cast_frame(scene.camera.K, W, H, cams[0], [m for m, _ in objs], world_T_obj[0])
    i, j = np.nonzero(oc["hit"] & (out2["instance"][0, 0].numpy() == oc["instance"]))
    n, p = oc["obj"][i, j], oc["p"][i, j]
    truth = apply(rigid_inverse(cams[0])[None].repeat(len(n), 0) @ (world_T_obj[2, n] - world_T_obj[0, n]), p)
    got = out2["scene_flow_fw_k2"][0].double().permute(1, 2, 0).numpy()[i, j]
    assert np.abs(got - truth).max() < 1e-4


def test_scene_flow_is_consistent_with_depth_flow_and_pose():
    """The point seen at (u, v) with depth z, moved by its scene flow and seen from camera t+1, projects
    to (u, v) + flow_fw and lies at the reprojected depth: scene flow, flow, depth and poses agree."""
    scene, cams, _ = occluding_clip()
    out = fs.render(scene, ["scene_flow_fw", "flow_fw", "valid_fw", "depth"])
    K = scene.camera.K
    rays = scene.camera.pixel_rays_numpy()
    for t in range(scene.num_frames - 1):
        valid = out["valid_fw"][t, 0].numpy()
        z = out["depth"][t, 0].double().numpy()
        X = rays / rays[..., 2:3] * z[..., None]
        Y = X + out["scene_flow_fw"][t].double().permute(1, 2, 0).numpy()
        M = rigid_inverse(cams[t + 1]) @ cams[t]
        Yr = Y[valid] @ M[:3, :3].T + M[:3, 3]
        uv = np.stack([(K[0, 0] * Yr[:, 0]) / Yr[:, 2] + K[0, 2], K[1, 1] * Yr[:, 1] / Yr[:, 2] + K[1, 2]], 1)
        v, u = np.nonzero(valid)
        flow = out["flow_fw"][t].double().permute(1, 2, 0).numpy()[valid]
        err = np.linalg.norm(uv - np.stack([u, v], 1) - flow, axis=1)
        assert err.max() < 2e-3, err.max()  # float32 depth and scene flow: ~1e-7 relative


def test_plan_validation_and_skipping():
    plan = fs.plan.make_plan(["flow_fw", "occ_bw"], flow_gaps=(1, 3))
    assert plan.outputs == ("flow_fw", "flow_fw_k3", "occ_bw", "occ_bw_k3")
    assert plan.pair_jobs == (("fw", 1), ("bw", 1), ("fw", 3), ("bw", 3))
    assert fs.plan.make_plan(["scene_flow_bw_k2"]).pair_jobs == (("bw", 2),)
    assert fs.plan.make_plan(["motion"]).pair_jobs == (("fw", 1),)
    assert not fs.plan.make_plan(["depth"]).flow_stage
    for bad in (["flow_fw_k1"], ["flow_fw_k0"], ["motion_k2"], ["flow_fw_k02"]):
        with pytest.raises(fs.ConfigError, match="unknown output"):
            fs.plan.make_plan(bad)
    for gaps in ((), (0,), 2, (1.5,), (True,)):
        with pytest.raises(fs.ConfigError, match="flow_gaps"):
            fs.plan.make_plan(["flow_fw"], flow_gaps=gaps)
    scene, _, _ = plane_clip(3)
    assert fs.render(scene, ["flow_fw", "scene_flow_bw"], flow_gaps=(3,))["flow_fw_k3"].shape == (0, 2, H, W)
    with pytest.raises(fs.ConfigError, match="flow_gaps"):
        fs.BouncingThingsConfig(flow_gaps=(0, 1))
    with pytest.raises(fs.ConfigError, match="gap 4"):
        fs.datasets.BouncingThings(fs.BouncingThingsConfig(num_frames=4, flow_gaps=(4,)), outputs=["flow_fw"])


def test_dataset_collate_and_native_export_of_gaps(tmp_path):
    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=4, motion="kinematic", num_objects=(2, 3),
                                  flow_gaps=(1, 2))
    ds = fs.datasets.BouncingThings(cfg, outputs=["flow_fw", "occ_fw", "scene_flow_bw", "meta"], seed=3)
    a, b = ds.sample(0), ds.sample(1)
    assert a["flow_fw_k2"].shape == (2, 2, 24, 32) and a["scene_flow_bw_k2"].shape == (2, 3, 24, 32)
    batch = default_collate([a, b])
    assert batch["occ_fw_k2"].shape == (2, 2, 1, 24, 32)
    write_sample(a, tmp_path)
    back = read_sample(tmp_path)
    assert list(back) == list(a)
    assert back.pop("provenance") == a.pop("provenance")  # the scene record (tests/test_provenance.py)
    for k, v in a.items():
        assert back[k].dtype == v.dtype and torch.equal(back[k], v), k
    exp = tmp_path / "exp"
    assert main(["export", "--out", str(exp), "--num", "1", "--width", "32", "--height", "24", "--num-frames", "3",
                 "--flow-gaps", "1,2", "--num-objects", "1,2", "--motion", "kinematic",
                 "--outputs", "flow_fw,scene_flow_fw", "--no-progress"]) == 0
    got = read_sample(exp / "00000")
    assert {"flow_fw", "flow_fw_k2", "scene_flow_fw", "scene_flow_fw_k2"} <= set(got)
    assert got["flow_fw_k2"].shape == (1, 2, 24, 32)
    png = tmp_path / "preview.png"
    assert main(["preview", "--out", str(png), "--width", "32", "--height", "24", "--num-frames", "3",
                 "--flow-gaps", "1,2", "--num-objects", "1,2", "--motion", "kinematic",
                 "--outputs", "rgb,flow_fw,scene_flow_fw"]) == 0
    assert png.stat().st_size > 0
