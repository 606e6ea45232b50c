"""Flow, validity, out-of-frame and motion masks against independent float64 numpy oracles (issue 4).

Oracles: the plane-induced homography for a planar quad, and brute-force ray casting + reprojection
(tests/oracle.py). Neither calls flowsynth's flow code.
"""

import numpy as np
import pytest
import torch
import trimesh
from oracle import (
    bilinear,
    boundary,
    homography_flow,
    look_at,
    pair_truth,
    plane_homography,
    pose,
    quad,
    rigid_inverse,
)

import flowsynth as fs

W, H = 64, 48
FLOW_KEYS = ["flow_fw", "flow_bw", "valid_fw", "valid_bw", "oof_fw", "oof_bw", "instance"]


def make_scene(cam, world_T_cam, objects):
    """Scene from camera poses (T, 4, 4) and (mesh, world_T_obj (T, 4, 4)) pairs."""
    scene = fs.Scene(cam, len(world_T_cam))
    scene.set_camera_poses(world_T_cam)
    for mesh, poses in objects:
        scene.add_object(mesh, poses=poses)
    return scene


def epe(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=-1)


def chw(x: torch.Tensor) -> np.ndarray:
    """(C, H, W) tensor -> (H, W, C) float64 array."""
    return x.double().permute(1, 2, 0).numpy()


# (object motion, camera motion) per frame pair; "offset" shifts the whole scene [m].
PLANE_CASES = {
    "object": {"obj": ((0.04, -0.06, 0.05), (0.15, -0.08, 0.3)), "cam": ((0, 0, 0), (0, 0, 0)),
               "offset": 0.0},
    "camera": {"obj": ((0, 0, 0), (0, 0, 0)), "cam": ((0.03, -0.04, 0.02), (0.2, 0.1, -0.3)), "offset": 0.0},
    "both": {"obj": ((-0.05, 0.03, 0.08), (-0.1, 0.12, 0.25)),
             "cam": ((0.02, 0.05, -0.03), (0.15, -0.1, 0.2)), "offset": 0.0},
    "both_at_1e4m": {"obj": ((-0.05, 0.03, 0.08), (-0.1, 0.12, 0.25)),
                     "cam": ((0.02, 0.05, -0.03), (0.15, -0.1, 0.2)), "offset": 1e4},
}


def plane_scene(case: dict, K: np.ndarray):
    """A tilted 12 m quad ~5 m in front of the camera, covering the image in both frames."""
    shift = pose(t=np.array([1.0, -0.7, 0.5]) * case["offset"] / np.linalg.norm([1.0, -0.7, 0.5]))
    cam0 = pose((0.01, -0.02, 0.0), (0.0, 0.0, 0.0))
    obj0 = pose((0.35, -0.25, 0.1), (0.1, -0.2, 5.0))
    world_T_cam = shift @ np.stack([cam0, cam0 @ pose(*case["cam"])])
    world_T_obj = shift @ np.stack([obj0, pose(*case["obj"]) @ obj0])
    cam = fs.Camera(K, W, H)
    return make_scene(cam, world_T_cam, [(quad(6.0), world_T_obj)]), world_T_cam, world_T_obj


def plane_errors(K: np.ndarray, case: dict) -> dict:
    scene, world_T_cam, world_T_obj = plane_scene(case, K)
    out = fs.render(scene, FLOW_KEYS)
    cam_T_obj = rigid_inverse(world_T_cam) @ world_T_obj
    res = {}
    for name, s, r in (("fw", 0, 1), ("bw", 1, 0)):
        truth = homography_flow(plane_homography(K, cam_T_obj[s], cam_T_obj[r]), W, H)
        valid = out[f"valid_{name}"][0, 0].numpy()
        assert valid.all(), f"{name}: the quad covers the image, every pixel must be valid"
        v, u = np.mgrid[0:H, 0:W]
        tu, tv = u + truth[..., 0], v + truth[..., 1]
        oof = (tu < -0.5) | (tu >= W - 0.5) | (tv < -0.5) | (tv >= H - 0.5)
        err = epe(chw(out[f"flow_{name}"][0]), truth)[valid]
        wrong_oof = int((out[f"oof_{name}"][0, 0].numpy() != oof).sum())
        res[name] = (float(err.mean()), float(err.max()), float(np.abs(truth).max()), wrong_oof)
    return res


@pytest.mark.parametrize("case", list(PLANE_CASES))
def test_plane_flow_equals_homography(case):
    K = np.array([[58.0, 0.0, 30.7], [0.0, 54.0, 24.2], [0.0, 0.0, 1.0]])
    res = plane_errors(K, PLANE_CASES[case])
    for name, (mean, mx, mag, wrong_oof) in res.items():
        print(f"plane {case} {name}: EPE mean {mean:.2e} max {mx:.2e} px (|flow| up to {mag:.1f} px)")
        assert mag > 2.0, "the motion must be visible"
        assert mean < 1e-3 and mx < 1e-2, (case, name, mean, mx)
        assert wrong_oof == 0, (case, name, wrong_oof)


def test_plane_flow_equals_homography_skewed_intrinsics():
    """Camera accepts a skew K[0, 1]; primary rays honour it, so the reprojection must too."""
    K = np.array([[58.0, 4.0, 30.7], [0.0, 54.0, 24.2], [0.0, 0.0, 1.0]])
    res = plane_errors(K, PLANE_CASES["both"])
    for name, (mean, mx, _, wrong_oof) in res.items():
        assert mean < 1e-3 and mx < 1e-2, f"{name}: EPE mean {mean:.3g} max {mx:.3g} px"
        assert wrong_oof == 0, (name, wrong_oof)


def tumbling_scene(offset: float = 0.0):
    """T = 3: a spinning cube, a sphere leaving the image, a cube and a long bar passing behind the
    camera, a back wall; the camera moves and turns. ``offset`` shifts everything [m]."""
    T = 3
    shift = pose(t=np.array([0.6, -1.0, 0.8]) * offset / np.linalg.norm([0.6, -1.0, 0.8]))
    cams = np.stack([shift @ pose((0.0, 0.03 * t, 0.01 * t), (0.05 * t, -0.02 * t, 0.1 * t))
                     for t in range(T)])
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    objs = [
        (trimesh.creation.box((14.0, 10.0, 0.2)), np.stack([pose(t=(0, 0, 12.0))] * T)),
        (cube, np.stack([pose(axis * 0.5 * t, (-0.8, 0.0, 5.0)) for t in range(T)])),
        (trimesh.creation.icosphere(2, radius=0.6),
         np.stack([pose(t=(1.5 + 1.8 * t, 0.2, 5.0)) for t in range(T)])),
        (trimesh.creation.box((0.6, 0.6, 0.6)),
         np.stack([pose((0.1 * t, 0.0, 0.0), (0.9, 0.5, z)) for t, z in enumerate((2.0, 0.2, -1.5))])),
        (trimesh.creation.box((0.3, 0.3, 4.0)), np.stack([pose(t=(-1.2, 0.8, z)) for z in (2.5, 1.2, 0.5)])),
    ]
    objs = [(m, shift[None] @ P) for m, P in objs]
    cam = fs.Camera.from_fov(W, H, 60.0)
    return make_scene(cam, cams, objs), cams, np.stack([P for _, P in objs], 1)


def compare_pairs(scene, cams, world_T_obj, keys) -> list[tuple]:
    """Render ``keys``; (pair t, direction, rendered dict, oracle truth, instance agreement mask) per
    (pair, direction)."""
    out = fs.render(scene, keys)
    K = scene.camera.K
    meshes = [o.mesh for o in scene.objects]
    casts: dict = {}
    cases = []
    for t in range(scene.num_frames - 1):
        for name, s, r in (("fw", t, t + 1), ("bw", t + 1, t)):
            truth = pair_truth(K, W, H, cams, meshes, world_T_obj, s, r, casts=casts, occlusion=False)
            inst = out["instance"][s, 0].numpy()
            agree = inst == truth["instance"]
            cases.append((t, name, out, truth, agree))
    return cases


def check_against_oracle(cases, mean_tol=1e-3, max_tol=1e-2) -> list[str]:
    report = []
    for t, name, out, truth, agree in cases:
        assert not (~agree & ~boundary(truth["instance"])).any(), "instance maps differ off silhouettes"
        flow = chw(out[f"flow_{name}"][t])
        valid = out[f"valid_{name}"][t, 0].numpy()
        oof = out[f"oof_{name}"][t, 0].numpy()
        assert np.isfinite(flow).all()
        assert (flow[~valid] == 0).all()
        z, uv = truth["z"], truth["uv"]
        near_plane = np.abs(z) < 1e-6
        edge = ((np.abs(uv[..., 0] + 0.5) < 1e-4) | (np.abs(uv[..., 0] - (W - 0.5)) < 1e-4)
                | (np.abs(uv[..., 1] + 0.5) < 1e-4) | (np.abs(uv[..., 1] - (H - 0.5)) < 1e-4))
        assert (valid == truth["valid"])[agree & ~near_plane].all(), (t, name)
        assert (oof == truth["oof"])[agree & ~near_plane & ~edge].all(), (t, name)
        sel = agree & truth["valid"] & ~truth["oof"]
        err = epe(flow, truth["flow"])
        mean, mx = err[sel].mean(), err[sel].max()
        assert mean < mean_tol and mx < max_tol, (t, name, mean, mx)
        far = agree & truth["valid"] & truth["oof"]
        rel = err[far] / np.maximum(1.0, np.linalg.norm(truth["flow"][far], axis=-1))
        assert (rel < 1e-3).all(), (t, name, rel.max(initial=0))
        behind = (~truth["valid"] & truth["hit"]).sum()
        report.append(f"pair {t} {name}: {sel.sum()} in-frame px EPE mean {mean:.2e} max {mx:.2e}; "
                      f"{far.sum()} out-of-frame px rel err max {rel.max(initial=0):.1e}; "
                      f"{behind} behind camera; {(~agree).sum()} silhouette px skipped")
    return report


def test_rotating_leaving_and_behind_camera():
    scene, cams, world_T_obj = tumbling_scene()
    cases = compare_pairs(scene, cams, world_T_obj, FLOW_KEYS)
    for line in check_against_oracle(cases):
        print(line)
    # the scene exercises what it claims: points leave the image and pass behind the camera
    behind = sum(int((tr["hit"] & ~tr["valid"]).sum()) for *_, tr, _ in cases)
    leaving = sum(int((tr["valid"] & tr["oof"]).sum()) for *_, tr, _ in cases)
    assert behind > 20 and leaving > 20, (behind, leaving)


@pytest.mark.parametrize("offset", [1e4, 1e5])
def test_large_coordinates(offset):
    """Camera and objects 1e4 m (and 1e5 m) from the world origin: flow still within 1e-3 px of the
    float64 oracle, everywhere in frame."""
    scene, cams, world_T_obj = tumbling_scene(offset)
    cases = compare_pairs(scene, cams, world_T_obj, FLOW_KEYS)
    for line in check_against_oracle(cases, mean_tol=1e-4, max_tol=1e-3):
        print(f"offset {offset:g} m: {line}")


def test_forward_backward_consistency():
    """flow_fw + flow_bw(x + flow_fw) ~ 0 for pixels visible in both frames, away from boundaries.

    flow_bw is sampled bilinearly. Used pixels: visible in both frames (valid_fw, not occ_fw), a 3x3
    neighbourhood of one instance in frame t, and a target inside the grid of pixel centres whose 2x2
    bilinear footprint in frame t+1 is one instance, all valid_bw, on one planar face (equal normals),
    so the interpolant only sees one smooth homography.
    """
    T = 2
    cams = np.stack([pose(), pose((0.02, -0.03, 0.01), (0.12, 0.05, 0.15))])
    objs = [
        (trimesh.creation.box((14.0, 10.0, 0.2)), np.stack([pose((0.1, 0.2, 0), (0, 0, 12.0))] * T)),
        (trimesh.creation.box((1.6, 1.2, 1.0)),
         np.stack([pose((0.3, 0.5, 0.1), (-0.8, 0.1, 5.0)), pose((0.35, 0.45, 0.15), (-0.6, 0.15, 5.2))])),
        (trimesh.creation.box((1.0, 2.0, 0.8)),
         np.stack([pose((-0.2, 0.7, 0.0), (1.2, -0.2, 6.0)), pose((-0.2, 0.75, 0.05), (1.1, -0.3, 5.8))])),
    ]
    scene = make_scene(fs.Camera.from_fov(W, H, 60.0), cams, objs)
    out = fs.render(scene, ["flow_fw", "flow_bw", "valid_fw", "occ_fw", "valid_bw", "instance", "normals"])
    fw, bw = chw(out["flow_fw"][0]), chw(out["flow_bw"][0])
    inst0, inst1 = out["instance"][0, 0].numpy(), out["instance"][1, 0].numpy()
    nrm1 = chw(out["normals"][1])
    ok = out["valid_fw"][0, 0].numpy() & ~out["occ_fw"][0, 0].numpy() & ~boundary(inst0)
    i, j = np.nonzero(ok)
    x1 = np.stack([j, i], 1) + fw[i, j]
    j0 = np.clip(np.floor(x1[:, 0]).astype(int), 0, W - 2)
    i0 = np.clip(np.floor(x1[:, 1]).astype(int), 0, H - 2)
    valid_bw = out["valid_bw"][0, 0].numpy()
    keep = (x1[:, 0] >= 0) & (x1[:, 0] <= W - 1) & (x1[:, 1] >= 0) & (x1[:, 1] <= H - 1)
    for di in (0, 1):
        for dj in (0, 1):
            keep &= (inst1[i0 + di, j0 + dj] == inst0[i, j]) & valid_bw[i0 + di, j0 + dj]
            keep &= np.abs(nrm1[i0 + di, j0 + dj] - nrm1[i0, j0]).max(1) < 1e-4
    resid = np.linalg.norm(fw[i, j] + bilinear(bw, x1), axis=1)[keep]
    print(f"fw/bw consistency over {keep.sum()} px: mean {resid.mean():.2e} max {resid.max():.2e} px")
    assert keep.sum() > 0.3 * H * W
    assert resid.max() < 0.01


def test_motion_mask():
    """motion is True exactly where the seen surface point moves in world space between t and t+1."""
    T = 3
    cams = np.stack([pose((0.0, 0.02 * t, 0.0), (0.1 * t, 0.0, 0.05 * t)) for t in range(T)])
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    objs = [
        (trimesh.creation.box((14.0, 10.0, 0.2)), np.stack([pose(t=(0, 0, 12.0))] * T)),
        (cube, np.stack([pose((0.2, 0.3, 0.0), (-1.2, -0.5, 5.0))] * T)),
        (cube, np.stack([pose((0.0, 0.0, 0.4 * t), (1.0, 0.5, 6.0)) for t in range(T)])),
        (trimesh.creation.icosphere(2, radius=0.7),
         np.stack([pose(t=(0.2 * t, 0.9, 4.0)) for t in range(T)])),
        (cube, np.stack([pose(t=(-1.0, 1.0, 6.0 - 2.0 * (t == 2))) for t in range(T)])),
    ]
    world_T_obj = np.stack([P for _, P in objs], 1)
    scene = make_scene(fs.Camera.from_fov(W, H, 60.0), cams, objs)
    out = fs.render(scene, ["motion", "instance"])
    assert out["motion"].shape == (T - 1, 1, H, W) and out["motion"].dtype == torch.bool
    K, meshes, casts = scene.camera.K, [m for m, _ in objs], {}
    for t in range(T - 1):
        truth = pair_truth(K, W, H, cams, meshes, world_T_obj, t, t + 1, casts=casts, occlusion=False)
        motion = out["motion"][t, 0].numpy()
        agree = out["instance"][t, 0].numpy() == truth["instance"]
        assert (motion == truth["motion"])[agree].all()
        assert not motion[~truth["hit"] & agree].any()
        print(f"motion pair {t}: {motion.sum()} moving px, {(~agree).sum()} silhouette px skipped")
        assert 0 < motion.sum() < truth["hit"].sum()

    static = make_scene(fs.Camera.from_fov(W, H, 60.0), cams, [(m, np.stack([P[0]] * T)) for m, P in objs])
    assert not fs.render(static, ["motion"])["motion"].any(), "camera-only motion moves no surface"


def test_pair_indexing_and_dtypes():
    """Index t of every per-pair key is the pair (t, t+1); flow_bw[t] starts from frame t+1."""
    T = 3
    cams = np.stack([look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0))] * T)
    poses = np.stack([pose(t=(0.3 * t * t, 0.0, 5.0)) for t in range(T)])
    scene = make_scene(fs.Camera.from_fov(W, H, 60.0), cams, [(trimesh.creation.box((4.0, 2.0, 0.5)), poses)])
    keys = ["flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw"]
    out = fs.render(scene, keys)
    for k, v in out.items():
        assert v.shape == ((T - 1, 2, H, W) if k.startswith("flow") else (T - 1, 1, H, W)), k
        assert v.dtype == (torch.float32 if k.startswith("flow") else torch.bool), k
    f = scene.camera.fx
    centre = (H // 2, W // 2)
    for t in range(T - 1):
        dx = f * (poses[t + 1, 0, 3] - poses[t, 0, 3]) / 4.75  # front face at z = 4.75 m
        assert out["flow_fw"][t, 0][centre].item() == pytest.approx(dx, abs=1e-3)
        assert out["flow_bw"][t, 0][centre].item() == pytest.approx(-dx, abs=1e-3)


def test_single_frame_and_empty_scene():
    """T = 1 gives empty per-pair tensors; a scene without objects gives zero flow and all-False masks."""
    keys = ["flow_fw", "flow_bw", "valid_fw", "occ_bw", "oof_fw", "motion"]
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    one = make_scene(fs.Camera.from_fov(W, H, 60.0), pose()[None], [(cube, pose(t=(0, 0, 4))[None])])
    for k, v in fs.render(one, keys).items():
        assert v.shape[0] == 0, k
    empty = make_scene(fs.Camera.from_fov(W, H, 60.0), np.stack([pose(), pose(t=(0.1, 0, 0))]), [])
    for k, v in fs.render(empty, keys).items():
        assert v.shape[0] == 1 and not v.any(), k
