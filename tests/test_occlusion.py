"""Occlusion masks against a brute-force float64 visibility oracle (tests/oracle.py), issue 4.

Silhouette pixels (where the exact method and the oracle may legitimately disagree, because a
visibility ray grazes an edge): pixels whose 3x3 neighbourhood in frame s's instance map holds more
than one id, or whose projection's nearest target pixel has a 3x3 neighbourhood in frame r's instance
map holding more than one id (``oracle.silhouette``). Instance maps are the oracle's.
"""

import numpy as np
import pytest
import trimesh
from oracle import pair_truth, pose, silhouette

import flowsynth as fs

W, H = 96, 72
KEYS = ["flow_fw", "flow_bw", "valid_fw", "valid_bw", "occ_fw", "occ_bw", "oof_fw", "oof_bw", "instance"]


def occluding_scene():
    """T = 3: a back wall, a slab sliding across two objects behind it, a spinning cube (self-occlusion),
    a sphere leaving the image, a cube passing behind the camera; the camera moves and turns."""
    T = 3
    cams = np.stack([pose((0.01 * t, -0.03 * t, 0.0), (0.1 * t, 0.05 * t, 0.1 * t)) for t in range(T)])
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    ball = trimesh.creation.icosphere(2, radius=0.5)
    objs = [
        (trimesh.creation.box((16.0, 12.0, 0.2)), np.stack([pose((0.0, 0.15, 0.0), (0.0, 0.0, 11.0))] * T)),
        (trimesh.creation.box((1.2, 2.0, 0.1)), np.stack([pose((0.0, 0.2, 0.0), (-1.0 + 0.6 * t, 0.0, 3.0))
                                                           for t in range(T)])),
        (cube, np.stack([pose((0.2, 0.4 + 0.6 * t, 0.0), (-0.4, 0.3, 6.0 - 0.2 * t)) for t in range(T)])),
        (ball, np.stack([pose(t=(0.3 - 0.3 * t, -0.4, 5.5)) for t in range(T)])),
        (cube, np.stack([pose((0.0, 0.6 * t, 0.3 * t), (1.8, -0.8, 7.0)) for t in range(T)])),
        (ball, np.stack([pose(t=(2.6 + 1.2 * t, 1.2, 6.0)) for t in range(T)])),
        (trimesh.creation.box((0.5, 0.5, 0.5)),
         np.stack([pose(t=(-0.6, -0.6, z)) for z in (1.5, 0.3, -1.0)])),
    ]
    scene = fs.Scene(fs.Camera.from_fov(W, H, 70.0), T)
    scene.set_camera_poses(cams)
    for mesh, P in objs:
        scene.add_object(mesh, poses=P)
    return scene, cams, np.stack([P for _, P in objs], 1)


@pytest.fixture(scope="module")
def rendered():
    scene, cams, world_T_obj = occluding_scene()
    exact = fs.render(scene, KEYS)
    depth = fs.render(scene, KEYS, occlusion="depth")
    K, meshes, casts = scene.camera.K, [o.mesh for o in scene.objects], {}
    truths = {}
    for t in range(scene.num_frames - 1):
        for name, s, r in (("fw", t, t + 1), ("bw", t + 1, t)):
            truths[t, name] = pair_truth(K, W, H, cams, meshes, world_T_obj, s, r, casts=casts)
            truths[t, name]["inst_dst"] = casts[r]["instance"]
    return exact, depth, truths


def test_exact_occlusion_matches_oracle_off_silhouettes(rendered):
    exact, _, truths = rendered
    totals = np.zeros(4, int)
    for (t, name), tr in truths.items():
        occ = exact[f"occ_{name}"][t, 0].numpy()
        oof = exact[f"oof_{name}"][t, 0].numpy()
        sil = silhouette(tr["instance"], tr["inst_dst"], tr["uv"])
        wrong = occ != tr["occ"]
        print(f"pair {t} {name}: {occ.sum()} occluded ({(occ & ~oof).sum()} hidden, {oof.sum()} out of "
              "frame); "
              f"{wrong.sum()} disagree with the oracle, {(wrong & ~sil).sum()} off silhouettes "
              f"({sil.sum()} silhouette px)")
        assert not (wrong & ~sil).any(), np.argwhere(wrong & ~sil)[:10]
        assert not (occ & ~tr["hit"]).any(), "occlusion is only defined where the pixel sees a surface"
        assert (occ[oof]).all(), "out-of-frame points count as occluded"
        totals += [(occ & ~oof).sum(), oof.sum(), wrong.sum(), (wrong & ~sil).sum()]
    assert totals[0] > 200 and totals[1] > 100, "the scene must exercise hidden and out-of-frame points"
    assert totals[2] < 0.005 * sum(int(tr["hit"].sum()) for tr in truths.values())


def test_occluder_one_centimetre_in_front():
    """A plate 1 cm in front of a wall 10 m away (1e-3 relative, 10x the exact method's tolerance)
    slides sideways: the wall points it covers in the target frame are occluded."""
    T = 2
    scene = fs.Scene(fs.Camera.from_fov(64, 48, 60.0), T)
    scene.add_object(trimesh.creation.box((20.0, 20.0, 0.02)), poses=pose(t=(0.0, 0.0, 10.01)))
    plate = np.stack([pose(t=(x, 0.0, 9.99 - 0.001)) for x in (-1.0, 1.0)])
    scene.add_object(trimesh.creation.box((3.0, 3.0, 0.002)), poses=plate)
    out = fs.render(scene, ["occ_fw", "occ_bw", "oof_fw", "instance"])
    K, meshes = scene.camera.K, [o.mesh for o in scene.objects]
    cams = np.stack([np.eye(4)] * T)
    world_T_obj = np.stack([o.poses for o in scene.objects], 1)
    casts: dict = {}
    for name, s, r in (("fw", 0, 1), ("bw", 1, 0)):
        tr = pair_truth(K, 64, 48, cams, meshes, world_T_obj, s, r, casts=casts)
        occ = out[f"occ_{name}"][0, 0].numpy()
        sil = silhouette(tr["instance"], casts[r]["instance"], tr["uv"])
        hidden_wall = tr["occ"] & (tr["instance"] == 1)
        print(f"1 cm occluder {name}: {hidden_wall.sum()} wall px hidden, "
              f"{(occ != tr['occ']).sum()} disagree")
        assert hidden_wall.sum() > 50
        assert not ((occ != tr["occ"]) & ~sil).any()


def test_self_occlusion_of_spinning_cube(rendered):
    """Faces of the tumbling cube (instance 5, nothing in front of it) that turn away are hidden by
    the cube itself: occluded pixels of instance 5 whose target pixel also shows instance 5."""
    exact, _, truths = rendered
    hidden = 0
    for (t, name), tr in truths.items():
        occ = exact[f"occ_{name}"][t, 0].numpy() & ~exact[f"oof_{name}"][t, 0].numpy()
        ii = np.clip(np.rint(tr["uv"][..., 1]).astype(int), 0, H - 1)
        jj = np.clip(np.rint(tr["uv"][..., 0]).astype(int), 0, W - 1)
        own = (tr["instance"] == 5) & (tr["inst_dst"][ii, jj] == 5)
        assert (occ == tr["occ"])[own & ~silhouette(tr["instance"], tr["inst_dst"], tr["uv"])].all()
        hidden += int((occ & own).sum())
    print(f"self-occluded px of the tumbling cube: {hidden}")
    assert hidden > 20


def test_depth_occlusion_agrees_with_exact_on_most_pixels(rendered):
    exact, depth, truths = rendered
    for k in KEYS:
        if not k.startswith("occ"):
            assert (exact[k] == depth[k]).all(), f"occlusion='depth' changes {k}"
    hits = disagree = wrong_e = wrong_d = 0
    for (t, name), tr in truths.items():
        e, d = exact[f"occ_{name}"][t, 0].numpy(), depth[f"occ_{name}"][t, 0].numpy()
        hits += int(tr["hit"].sum())
        disagree += int((e != d).sum())
        wrong_e += int((e != tr["occ"]).sum())
        wrong_d += int((d != tr["occ"]).sum())
    frac = disagree / hits
    print(f"depth vs exact occlusion: {disagree}/{hits} px differ ({100 * frac:.2f}%); wrong vs oracle: "
          f"exact {wrong_e}, depth {wrong_d}")
    assert frac < 0.05
