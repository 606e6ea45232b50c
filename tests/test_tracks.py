"""Point tracks (target_points, occluded, query_points) against independent float64 oracles (issue 17).

Oracle: the query pixel is brute-force cast in its frame (tests/oracle.py), its object-frame point is
carried frame to frame by chaining the per-frame relative motions cam_T_obj[f+1] cam_T_obj[f]^-1 in
float64, projected, and its visibility decided by brute-force ray casting towards it. Tracks may disagree
about visibility only at silhouettes: the query pixel or the target pixel nearest to the track has
another instance in its 3x3 neighbourhood (oracle instance maps).
"""

import pickle

import numpy as np
import pytest
import torch
import trimesh
from oracle import boundary, cast_frame, pose, project, rigid_inverse, visible
from torch.utils.data import default_collate

import flowsynth as fs
from flowsynth.io.sampleio import read_sample, write_sample

W, H = 64, 48


def clip():
    """T = 5: a wall (background), a slab sliding in front of a spinning cube and a ball that leaves the
    image, a box passing close to the camera; the camera moves and turns."""
    T = 5
    cams = np.stack([pose((0.01 * t, -0.02 * t, 0.0), (0.08 * t, 0.04 * t, 0.1 * t)) for t in range(T)])
    objs = [
        (trimesh.creation.box((16.0, 12.0, 0.2)), np.stack([pose((0.0, 0.15, 0.0), (0.0, 0.0, 11.0))] * T), True),
        (trimesh.creation.box((1.2, 2.0, 0.1)), np.stack([pose((0.0, 0.2, 0.0), (-1.5 + 0.5 * t, 0.0, 3.0))
                                                           for t in range(T)]), False),
        (trimesh.creation.box((1.0, 1.0, 1.0)), np.stack([pose((0.2, 0.4 + 0.4 * t, 0.0), (-0.4, 0.3, 6.0))
                                                           for t in range(T)]), False),
        (trimesh.creation.icosphere(2, radius=0.5), np.stack([pose(t=(1.2 + 0.7 * t, -0.6, 5.5)) for t in range(T)]),
         False),
        (trimesh.creation.box((0.5, 0.5, 0.5)), np.stack([pose(t=(0.7, 0.5, z)) for z in (3.0, 2.0, 1.0, 0.2, -0.8)]),
         False),
    ]
    scene = fs.Scene(fs.Camera.from_fov(W, H, 70.0), T)
    scene.set_camera_poses(cams)
    for mesh, P, bg in objs:
        scene.add_object(mesh, poses=P, background=bg)
    return scene, cams, np.stack([P for _, P, _ in objs], 1)


@pytest.fixture(scope="module")
def rendered():
    scene, cams, world_T_obj = clip()
    out = fs.render(scene, ["tracks", "instance", "flow_fw"], num_tracks=300, seed=5)
    meshes = [o.mesh for o in scene.objects]
    casts = {f: cast_frame(scene.camera.K, W, H, cams[f], meshes, world_T_obj[f]) for f in range(scene.num_frames)}
    return scene, cams, world_T_obj, out, casts


def chained_track(K, cams, world_T_obj, n, p, tq):
    """(T, 3) camera-frame points of object point p of instance n: start in frame tq, then chain."""
    cam_T_obj = rigid_inverse(cams) @ world_T_obj[:, n]
    T = len(cams)
    X = np.zeros((T, 3))
    X[tq] = cam_T_obj[tq, :3, :3] @ p + cam_T_obj[tq, :3, 3]
    for f in list(range(tq + 1, T)) + list(range(tq - 1, -1, -1)):
        prev = f - 1 if f > tq else f + 1
        step = cam_T_obj[f] @ rigid_inverse(cam_T_obj[prev])  # the per-frame relative motion
        X[f] = step[:3, :3] @ X[prev] + step[:3, 3]
    return X


def test_tracks_match_chained_reprojection_and_brute_force_visibility(rendered):
    scene, cams, world_T_obj, out, casts = rendered
    K, meshes, T = scene.camera.K, [o.mesh for o in scene.objects], scene.num_frames
    target, occluded, query = (out[k].numpy() for k in ("target_points", "occluded", "query_points"))
    assert target.shape == (300, T, 2) and occluded.shape == (300, T) and query.shape == (300, 3)
    assert target.dtype == np.float32 and occluded.dtype == bool and query.dtype == np.float32
    counts = {"hidden": 0, "oof": 0, "visible": 0, "disagree": 0, "skipped": 0}
    worst = 0.0
    tracks = []  # (q, uv (T, 2), front (T,), inside (T,), world points (T, 3))
    for q, (tq, i, j) in enumerate(query.astype(int)):
        c = casts[tq]
        assert c["hit"][i, j], "query points lie on surfaces"
        assert not occluded[q, tq] and np.abs(target[q, tq] - (j, i)).max() < 1e-3
        if c["instance"][i, j] != out["instance"][tq, 0, i, j] or boundary(c["instance"])[i, j]:
            counts["skipped"] += 1
            continue
        X = chained_track(K, cams, world_T_obj, c["obj"][i, j], c["p"][i, j], tq)
        front = X[:, 2] > 0
        uv = np.where(front[:, None], project(K, np.where(front[:, None], X, 1.0)), 0.0)
        inside = front & (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < H - 0.5)
        Xw = np.einsum("fij,fj->fi", cams[:, :3, :3], X) + cams[:, :3, 3]
        tracks.append((q, uv, front, inside, Xw))
    vis = np.zeros((len(tracks), T), bool)  # brute-force visibility, one batch per frame
    for f in range(T):
        rows = [k for k, tr in enumerate(tracks) if tr[3][f]]
        if rows:
            pts = np.stack([tracks[k][4][f] for k in rows])
            vis[rows, f] = visible(pts, cams[f], meshes, world_T_obj[f])
    for (q, uv, front, inside, _), v in zip(tracks, vis):
        err = np.abs(target[q] - uv).max(1)
        worst = max(worst, float(err[inside].max(initial=0.0)))
        assert (err[inside] < 2e-3).all(), (q, err)
        # out of frame (possibly near the camera plane, |uv| huge): float32 relative precision
        far = front & ~inside
        assert (err[far] < 1e-3 * np.maximum(1.0, np.abs(uv[far]).max(1))).all(), (q, err, uv)
        assert (target[q][~front] == 0).all()
        for f in np.nonzero(occluded[q] == v)[0]:
            ii, jj = int(np.clip(np.rint(uv[f, 1]), 0, H - 1)), int(np.clip(np.rint(uv[f, 0]), 0, W - 1))
            assert boundary(casts[f]["instance"])[ii, jj], (q, f, "visibility differs off a silhouette")
            counts["disagree"] += 1
        counts["hidden"] += int((inside & ~v).sum())
        counts["oof"] += int((~inside).sum())
        counts["visible"] += int(v.sum())
    print(f"tracks vs chained oracle: max error {worst:.1e} px, {counts}")
    assert counts["hidden"] > 30 and counts["oof"] > 30 and counts["visible"] > 300
    assert counts["disagree"] <= 0.01 * 300 * T


def test_tracks_agree_with_flow_where_visible(rendered):
    """Between consecutive frames a visible track moves by the flow of the pixel it sits on (sampled at the
    nearest pixel, so off by at most the flow's change over half a pixel)."""
    _, _, _, out, _ = rendered
    target, occ = out["target_points"].numpy(), out["occluded"].numpy()
    flow = out["flow_fw"].numpy()
    checked = 0
    for q in range(len(target)):
        for f in range(target.shape[1] - 1):
            if occ[q, f] or occ[q, f + 1]:
                continue
            u, v = target[q, f]
            i, j = int(round(v)), int(round(u))
            if abs(u - j) > 1e-3 or abs(v - i) > 1e-3:
                continue  # only tracks sitting on a pixel centre: flow there is exact
            d = target[q, f + 1] - target[q, f]
            assert np.abs(d - flow[f, :, i, j]).max() < 1e-3
            checked += 1
    assert checked >= 150, checked  # a track sits on a pixel centre in its query frame


def test_sampling_modes_and_determinism():
    scene, *_ = clip()
    base = dict(num_tracks=128, seed=3)
    a = fs.render(scene, ["tracks", "instance", "depth"], **base)
    b = fs.render(scene, ["tracks"], **base)
    for k in ("target_points", "occluded", "query_points"):
        assert torch.equal(a[k], b[k]), "tracks are a pure function of the scene and seed"
    c = fs.render(scene, ["query_points"], num_tracks=128, seed=4)
    assert not torch.equal(a["query_points"], c["query_points"])
    assert len({tuple(x) for x in a["query_points"].tolist()}) == 128, "no repeats while the pool is large"
    assert len(set(a["query_points"][:, 0].int().tolist())) == scene.num_frames, "queries come from every frame"
    inst = a["instance"][:, 0].numpy()
    obj = fs.render(scene, ["query_points"], track_sampling="objects", **base)["query_points"].int().numpy()
    assert (inst[obj[:, 0], obj[:, 1], obj[:, 2]] >= 2).all(), "objects: never the background wall"
    edge = fs.render(scene, ["query_points"], track_sampling="edges", **base)["query_points"].int().numpy()
    z = a["depth"][:, 0].double().numpy()
    zp, ip = np.pad(z, ((0, 0), (1, 1), (1, 1)), mode="edge"), np.pad(inst, ((0, 0), (1, 1), (1, 1)), mode="edge")
    for t, i, j in edge:
        win_z, win_i = zp[t, i:i + 3, j:j + 3], ip[t, i:i + 3, j:j + 3]
        assert (win_i != inst[t, i, j]).any() or (np.abs(win_z - z[t, i, j]) > 0.05 * z[t, i, j]).any()
    small = fs.render(scene, ["tracks"], num_tracks=40000, seed=1)  # more queries than surface pixels
    assert small["query_points"].shape == (40000, 3) and not small["occluded"][
        torch.arange(40000), small["query_points"][:, 0].long()].any()
    empty = fs.Scene(fs.Camera.from_fov(W, H, 60.0), 3)
    e = fs.render(empty, ["tracks"], num_tracks=8)
    assert e["occluded"].all() and not e["target_points"].any() and e["query_points"].shape == (8, 3)
    for bad in (dict(num_tracks=0), dict(track_sampling="corners")):
        with pytest.raises(fs.ConfigError):
            fs.render(scene, ["tracks"], **bad)


def test_dataset_collate_export_and_tapvid_file(tmp_path):
    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=4, motion="kinematic", num_objects=(2, 3),
                                  num_tracks=50, track_sampling="objects")
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "tracks", "meta"], seed=2)
    a, b = ds.sample(0), ds.sample(1)
    batch = default_collate([a, b])
    assert batch["target_points"].shape == (2, 50, 4, 2) and batch["occluded"].shape == (2, 50, 4)
    write_sample(a, tmp_path)
    back = read_sample(tmp_path)
    assert back.pop("provenance") == a.pop("provenance")  # the scene record (tests/test_provenance.py)
    for k, v in a.items():
        assert back[k].dtype == v.dtype and back[k].shape == v.shape, k
    for k in ("target_points", "occluded", "query_points"):
        assert torch.equal(back[k], a[k]), k
    with open(tmp_path / "tapvid.pkl", "rb") as f:
        tv = pickle.load(f)
    # TAP-Vid Kubric conventions: raster coordinates, query (t, y, x) equals the track at its frame (x, y)
    q = tv["query_points"]
    t = q[:, 0].astype(int)
    assert np.allclose(tv["target_points"][np.arange(50), t], q[:, :0:-1], atol=1e-4)
    assert np.allclose(tv["target_points"], a["target_points"].numpy() + 0.5)
    assert np.array_equal(tv["occluded"], a["occluded"].numpy())
    assert np.allclose(tv["points"], tv["target_points"] / np.array([32, 24]))
    assert tv["video"].shape == (4, 24, 32, 3) and tv["video"].dtype == np.uint8
    png = tmp_path / "preview.png"
    from flowsynth.cli import main

    assert main(["preview", "--out", str(png), "--width", "32", "--height", "24", "--num-frames", "3",
                 "--num-objects", "1,2", "--motion", "kinematic", "--outputs", "rgb,tracks"]) == 0
    assert png.stat().st_size > 0
