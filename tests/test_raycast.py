"""G-buffer ray casting against an independent float64 brute-force oracle and analytic geometry."""

import numpy as np
import pytest
import torch
import trimesh

import flowsynth as fs
import oracle

GB = ["depth", "distance", "normals", "position", "instance", "category", "asset"]


def brute_force(cam: fs.Camera, cam_T_world: np.ndarray, meshes, world_T_objs, dirs=None):
    """Closest hit of every pixel-centre ray over all triangles (tests/oracle.py, float64), camera frame.

    Returns t (H,W) [inf = miss], instance index (H,W) [-1 = miss], unit normal (H,W,3) facing the
    camera, and the ray directions (H,W,3).
    """
    if dirs is None:
        dirs = oracle.pixel_rays(cam.K, cam.width, cam.height)
    cam_T_obj = np.stack([cam_T_world @ P for P in world_T_objs])
    res = oracle.ray_cast(np.zeros(3), dirs.reshape(-1, 3), meshes, cam_T_obj)
    n = np.zeros((len(res["t"]), 3))
    for k, mesh in enumerate(meshes):
        sel = res["obj"] == k
        tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[res["face"][sel]]] @ cam_T_obj[k, :3, :3].T
        nk = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nk /= np.linalg.norm(nk, axis=1, keepdims=True)
        n[sel] = nk * -np.sign(np.einsum("ri,ri->r", nk, dirs.reshape(-1, 3)[sel]))[:, None]
    shape = dirs.shape[:-1]
    return res["t"].reshape(shape), res["obj"].reshape(shape), n.reshape(*shape, 3), dirs


def near_silhouette(cam, cam_T_world, meshes, poses, eps_px=1e-3):
    """Pixels whose ray, moved by eps_px in any direction, changes which object it hits."""
    H, W = cam.height, cam.width
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ref = None
    out = np.zeros((H, W), bool)
    for du, dv in [(0, 0), (eps_px, 0), (-eps_px, 0), (0, eps_px), (0, -eps_px)]:
        d = np.stack([u + du, v + dv, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        _, k, _, _ = brute_force(cam, cam_T_world, meshes, poses, d)
        ref = k if ref is None else ref
        out |= k != ref
    return out


def random_pose(rng, center, scale=1.0):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    P = np.eye(4)
    P[:3, :3] = trimesh.transformations.quaternion_matrix(q)[:3, :3]
    P[:3, 3] = center + scale * rng.uniform(-1, 1, 3)
    return P


def build_scene(seed=0, offset=np.zeros(3), T=2, W=48, H=36):
    rng = np.random.default_rng(seed)
    cam = fs.Camera.from_fov(W, H, 60)
    scene = fs.Scene(cam, T)
    cams = np.stack([oracle.look_at(offset + [0.1 * t, 0.05 * t, -6.0], offset) for t in range(T)])
    scene.set_camera_poses(cams)
    meshes = [trimesh.creation.box((1.0, 0.6, 0.8)), trimesh.creation.icosphere(2, radius=0.7),
              trimesh.creation.box((6.0, 6.0, 0.05)), trimesh.creation.box((1.5, 0.3, 1.0))]
    poses = []
    for k, m in enumerate(meshes):
        if k == 2:
            P = np.tile(np.eye(4), (T, 1, 1))
            P[:, :3, 3] = offset + [0, 0, 2.5]
        else:
            P = np.stack([random_pose(rng, offset + [0, 0, 0], 1.2) for _ in range(T)])
        scene.add_object(m, P, category=10 + k)
        poses.append(P)
    return scene, meshes, poses, cams


@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_gbuffer_matches_brute_force_oracle(offset):
    scene, meshes, poses, cams = build_scene(seed=1, offset=np.full(3, offset))
    out = fs.render(scene, GB)
    for t in range(scene.num_frames):
        cam_T_world = np.linalg.inv(cams[t])
        tt, kk, nn, dirs = brute_force(scene.camera, cam_T_world, meshes, [P[t] for P in poses])
        sil = near_silhouette(scene.camera, cam_T_world, meshes, [P[t] for P in poses])
        hit_ref = kk >= 0
        hit = out["instance"][t, 0].numpy() > 0
        assert not (hit != hit_ref)[~sil].any()
        both = hit & hit_ref & ~sil
        assert both.sum() > 0.5 * hit_ref.size
        dist = out["distance"][t, 0].numpy()
        rel = np.abs(dist[both] - tt[both]) / tt[both]
        assert rel.max() <= 1e-5
        depth = out["depth"][t, 0].numpy()
        depth_ref = tt * dirs[..., 2]
        assert (np.abs(depth[both] - depth_ref[both]) / depth_ref[both]).max() <= 1e-5
        np.testing.assert_array_equal(out["instance"][t, 0].numpy()[both], kk[both] + 1)
        np.testing.assert_array_equal(out["category"][t, 0].numpy()[both], kk[both] + 10)
        n = out["normals"][t].numpy().transpose(1, 2, 0)
        assert np.abs(n[both] - nn[both]).max() < 1e-4
        pos_ref = (cams[t][:3, :3] @ (tt[..., None] * dirs)[both].T).T + cams[t][:3, 3]
        pos = out["position"][t].numpy().transpose(1, 2, 0)[both]
        # float32 positions: error relative to |position|
        assert np.abs(pos - pos_ref).max() <= 1e-5 * (np.abs(pos_ref).max() + 1.0)
        # no hit -> zeros everywhere
        miss = ~hit
        for key in ("depth", "distance", "normals", "position", "instance", "category", "asset"):
            assert (out[key][t][:, miss] == 0).all()


def test_shared_asset_ids():
    scene, *_ = build_scene()
    m = scene.objects[0].mesh
    k = scene.add_object(m, np.eye(4))
    assert scene.objects[k - 1].asset != scene.objects[0].asset  # cleaned copy is a new mesh object
    box = trimesh.creation.box()
    a = scene.add_object(box, np.eye(4))
    b = scene.add_object(box, np.eye(4))
    assert scene.objects[a - 1].asset == scene.objects[b - 1].asset


def test_planar_depth_is_distance_times_cos():
    cam = fs.Camera.from_fov(40, 30, 70)
    scene = fs.Scene(cam, 1)
    P = np.eye(4)
    P[:3, 3] = [0, 0, 3]
    scene.add_object(trimesh.creation.box((20, 20, 0.01)), P)
    out = fs.render(scene, ["depth", "distance", "normals"])
    d = cam.pixel_rays().numpy()
    depth, dist = out["depth"][0, 0].numpy(), out["distance"][0, 0].numpy()
    np.testing.assert_allclose(depth, dist * d[..., 2], rtol=2e-7)
    np.testing.assert_allclose(depth, 3 - 0.005, rtol=1e-6)
    n = out["normals"][0].numpy().transpose(1, 2, 0)
    np.testing.assert_allclose(n, np.broadcast_to([0, 0, -1], n.shape), atol=1e-6)


def test_normals_unit_and_facing_camera():
    scene, *_ = build_scene(seed=3)
    out = fs.render(scene, ["normals", "instance"])
    d = scene.camera.pixel_rays().numpy()
    for t in range(scene.num_frames):
        n = out["normals"][t].numpy().transpose(1, 2, 0)
        hit = out["instance"][t, 0].numpy() > 0
        np.testing.assert_allclose(np.linalg.norm(n[hit], axis=-1), 1.0, atol=1e-6)
        assert (np.einsum("ij,ij->i", n[hit], d[hit]) < 0).all()


def test_posed_object_renders_like_pretransformed_mesh():
    rng = np.random.default_rng(7)
    cam = fs.Camera.from_fov(48, 36, 50)
    mesh = trimesh.creation.icosphere(2)
    mesh.vertices[:, 0] *= 1.7
    P = random_pose(rng, np.array([0.0, 0.0, 4.0]), 0.3)
    a = fs.Scene(cam, 1)
    a.add_object(mesh, P)
    b = fs.Scene(cam, 1)
    b.add_object(trimesh.Trimesh(mesh.vertices @ P[:3, :3].T + P[:3, 3], mesh.faces, process=False), np.eye(4))
    oa, ob = fs.render(a, GB), fs.render(b, GB)
    hit = (oa["instance"] > 0) & (ob["instance"] > 0)
    assert (oa["instance"] != ob["instance"]).sum() <= 2  # silhouette pixels only
    # equal up to float32 rounding of the pre-transformed vertices (a few ulps)
    np.testing.assert_allclose(oa["depth"][hit], ob["depth"][hit], rtol=4e-6)
    assert (oa["normals"] - ob["normals"]).abs().amax(1, keepdim=True)[hit].max() < 1e-5


def test_rays_through_shared_vertices_and_edges_never_miss():
    # A tessellated plane whose vertices and edge midpoints project exactly onto pixel centres.
    cam = fs.Camera(np.array([[16.0, 0, 16], [0, 16.0, 16], [0, 0, 1]]), 33, 33)
    grid = trimesh.creation.box((1, 1, 1))
    n = 8
    xs = np.arange(-n, n + 1) * 0.5  # vertices at u = 16 + 4 x / z * ... -> integer pixel centres at z = 2
    X, Y = np.meshgrid(xs, xs)
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 2.0)], 1)
    F = []
    m = len(xs)
    for i in range(m - 1):
        for j in range(m - 1):
            a, b, c, d = i * m + j, i * m + j + 1, (i + 1) * m + j, (i + 1) * m + j + 1
            F += [[a, b, d], [a, d, c]]
    grid = trimesh.Trimesh(V, np.array(F), process=False)
    closed = trimesh.creation.box((2.0, 2.0, 2.0))  # a corner aimed at the principal point
    R = trimesh.transformations.rotation_matrix(np.arctan(np.sqrt(0.5)), [1, -1, 0]) @ \
        trimesh.transformations.rotation_matrix(np.pi / 4, [0, 0, 1])
    for mesh, pose in [(grid, np.eye(4)), (closed, R)]:
        scene = fs.Scene(cam, 1)
        P = pose.copy()
        if mesh is closed:
            P[:3, 3] = [0, 0, 6.0]
        scene.add_object(mesh, P)
        out = fs.render(scene, ["instance", "depth"])
        ref_t, ref_k, _, _ = brute_force(cam, np.eye(4), [mesh], [P])
        got = out["instance"][0, 0].numpy() > 0
        assert not (got & (ref_k < 0)).any()
        missed = (ref_k >= 0) & ~got
        assert not missed.any(), f"{missed.sum()} vertex/edge-aimed rays missed"


def test_grazing_rays_and_camera_inside_object_are_finite():
    cam = fs.Camera.from_fov(32, 24, 90)
    scene = fs.Scene(cam, 2)
    # plane containing the optical axis (pure grazing) and a box around the camera
    scene.add_object(trimesh.creation.box((0.0001, 10, 10)), np.eye(4))
    scene.add_object(trimesh.creation.box((3, 3, 3)), np.eye(4))
    out = fs.render(scene, GB)
    for v in out.values():
        assert torch.isfinite(v.float()).all()
    assert (out["instance"] > 0).all()  # inside a closed box every ray hits something
    assert (out["depth"] > 0).all()


def test_empty_scene_renders_zeros():
    scene = fs.Scene(fs.Camera.from_fov(16, 12), 3)
    out = fs.render(scene, GB + ["flow_fw", "occ_fw", "valid_fw", "motion"])
    for k, v in out.items():
        assert not v.any(), k
    assert out["flow_fw"].shape == (2, 2, 12, 16)


def test_single_pixel_image():
    scene = fs.Scene(fs.Camera.from_fov(1, 1, 10), 1)
    P = np.eye(4)
    P[2, 3] = 5
    scene.add_object(trimesh.creation.box(), P)
    out = fs.render(scene, ["depth", "instance"])
    assert out["depth"].shape == (1, 1, 1, 1)
    assert out["depth"].item() == pytest.approx(4.5, rel=1e-6)


@pytest.mark.parametrize("K,W,H", [
    (np.diag([0.0, 1.0, 1.0]), 4, 4),
    (np.diag([1.0, -1.0, 1.0]), 4, 4),
    (np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, np.nan]]), 4, 4),
    (np.eye(3), 0, 4),
    (np.eye(3), 4, -1),
])
def test_bad_camera(K, W, H):
    with pytest.raises(fs.ConfigError):
        fs.Camera(K, W, H)


def test_bad_fov_and_shape():
    with pytest.raises(fs.ConfigError):
        fs.Camera.from_fov(10, 10, 180.0)
    with pytest.raises(fs.ShapeError):
        fs.Camera(np.eye(4), 4, 4)


def test_bad_poses_and_meshes():
    scene = fs.Scene(fs.Camera.from_fov(8, 8), 2)
    box = trimesh.creation.box()
    scaled = np.eye(4)
    scaled[0, 0] = 2.0
    with pytest.raises(fs.ConfigError, match="orthonormal"):
        scene.add_object(box, scaled)
    with pytest.raises(fs.ConfigError, match="NaN"):
        scene.add_object(box, np.full((4, 4), np.nan))
    with pytest.raises(fs.ConfigError, match="one pose per frame"):
        scene.add_object(box, np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(fs.ShapeError):
        scene.add_object(box, np.eye(3))
    refl = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(fs.ConfigError, match="reflection"):
        scene.set_camera_poses(refl)
    with pytest.raises(fs.AssetError, match="no faces"):
        scene.add_object(trimesh.Trimesh(np.zeros((3, 3)), np.zeros((0, 3), int)))
    bad = box.copy()
    bad.vertices[0, 0] = np.inf
    with pytest.raises(fs.AssetError, match="non-finite"):
        scene.add_object(bad)
    with pytest.raises(fs.AssetError):
        scene.add_object("box.obj")
    with pytest.raises(fs.ConfigError):
        scene.add_object(box, category=-1)


def test_degenerate_triangles_dropped_with_warning():
    box = trimesh.creation.box()
    V = np.vstack([box.vertices, [[0, 0, 0], [1, 1, 1]]])
    F = np.vstack([box.faces, [[8, 9, 9], [0, 0, 1]]])
    scene = fs.Scene(fs.Camera.from_fov(8, 8), 1)
    with pytest.warns(UserWarning, match="degenerate"):
        scene.add_object(trimesh.Trimesh(V, F, process=False))
    assert len(scene.objects[0].mesh.faces) == 12


def test_unknown_output_key_lists_valid_ones():
    scene = fs.Scene(fs.Camera.from_fov(8, 8), 1)
    with pytest.raises(fs.ConfigError, match="valid outputs are:.*depth"):
        fs.render(scene, ["depht"])


def test_camera_inside_room_and_mesh_across_camera_plane_match_brute_force():
    """Screen tiles list an instance by the projection of its hull clipped to the camera plane
    (``tiles._screen_bounds``): walls around the camera and a box reaching behind it must still be found
    wherever the float64 brute-force oracle hits them; the bounds hold every hit pixel and every sampled
    point of the clipped hull, and are tight enough to matter (a wall behind the camera is in no tile)."""
    from flowsynth.raycast.tiles import CLIP_Z, _screen_bounds
    from flowsynth.scene.assets import room_walls

    cam = fs.Camera.from_fov(64, 48, 70)
    scene = fs.Scene(cam, 2)
    cams = np.stack([oracle.look_at([-3.0 + 0.2 * t, 0.3, 1.2], [2.0, -0.5 + 0.3 * t, 0.8], up=(0, 0, 1))
                     for t in range(2)])
    scene.set_camera_poses(cams)
    meshes = list(room_walls((-4.0, -3.0, 0.0), (4.0, 3.0, 2.5)))
    meshes += [trimesh.creation.box((0.6, 0.8, 0.5)), trimesh.creation.icosphere(1, radius=0.4)]
    poses = [np.tile(np.eye(4), (2, 1, 1)) for _ in range(6)]
    straddle = oracle.pose((0.3, 0.2, 0.1), (-2.75, -0.55, 1.1))  # reaches behind camera 0, at the image edge
    poses += [np.stack([straddle, straddle]), np.stack([oracle.pose(t=(1.5, 0.2, 1.0))] * 2)]
    for m, P in zip(meshes, poses):
        scene.add_object(m, P)
    out = fs.render(scene, ["instance", "distance"])
    for t in range(2):
        cam_T_world = np.linalg.inv(cams[t])
        tt, kk, _, _ = brute_force(cam, cam_T_world, meshes, [P[t] for P in poses])
        sil = near_silhouette(cam, cam_T_world, meshes, [P[t] for P in poses])
        inst = out["instance"][t, 0].numpy() - 1
        assert (inst == kk)[~sil].all() and (kk >= 0).all()
        assert np.isin([0, 1, 3, 4, 5, 7] + [6] * (t == 0), kk).all()  # all but the wall behind; the box in frame 0
        dist = out["distance"][t, 0].numpy()
        assert (np.abs(dist - tt) / tt)[~sil].max() <= 1e-5

        cam_T_obj = np.stack([cam_T_world @ P[t] for P in poses])[None]
        b = _screen_bounds(meshes, cam_T_obj, cam.K)[0]  # (N, 4) u_min, u_max, v_min, v_max
        v, u = np.mgrid[0:48, 0:64]
        for n in range(8):
            hit = kk == n
            if hit.any():
                assert b[n, 0] - 1e-6 <= u[hit].min() and u[hit].max() <= b[n, 1] + 1e-6
                assert b[n, 2] - 1e-6 <= v[hit].min() and v[hit].max() <= b[n, 3] + 1e-6
            # random points of the hull in front of the clip plane project inside the bounds
            V = oracle.apply(cam_T_obj[0, n], np.asarray(meshes[n].vertices, np.float64))
            w = np.random.default_rng(n).dirichlet(np.full(len(V), 0.3), 4000)
            X = w @ V
            X = X[X[:, 2] >= CLIP_Z]
            if len(X):
                p = oracle.project(cam.K, X)
                assert (p[:, 0] >= b[n, 0] - 1e-6).all() and (p[:, 0] <= b[n, 1] + 1e-6).all()
                assert (p[:, 1] >= b[n, 2] - 1e-6).all() and (p[:, 1] <= b[n, 3] + 1e-6).all()
        behind = [n for n in range(6) if (oracle.apply(cam_T_obj[0, n], meshes[n].vertices)[:, 2] < 0).all()]
        assert behind and np.isnan(b[behind]).all()  # the wall behind the camera: no tile
        crossing = [n for n in range(7) if n not in behind and not np.isinf(b[n]).any()
                    and (oracle.apply(cam_T_obj[0, n], meshes[n].vertices)[:, 2] < 0).any()]
        assert len(crossing) >= 4  # floor, ceiling, side walls and the box: finite bounds, not every tile
        assert 0 < b[0, 2] < 47 and 0 < b[1, 3] < 47  # floor below the horizon, ceiling above: rows without them


def test_more_than_ordered_max_instances_take_the_bvh_and_match_the_oracle(monkeypatch):
    """Above ``ORDERED_MAX`` instances camera rays traverse the top-level BVH (``trace_closest`` /
    ``trace_any``, with the thin-instance box test) instead of the tile lists: same hits as the brute-force
    oracle, and the same G-buffer and exact occlusion as the list walk forced on the same scene."""
    import flowsynth.raycast.accel as accel

    rng = np.random.default_rng(5)
    cam = fs.Camera.from_fov(40, 30, 60)
    scene = fs.Scene(cam, 2)
    cams = np.stack([oracle.look_at([0.1 * t, 0.0, -7.0], [0.0, 0.0, 0.0]) for t in range(2)])
    scene.set_camera_poses(cams)
    meshes = [trimesh.creation.box((6.0, 5.0, 0.02))]  # a thin plate behind everything
    poses = [np.tile(oracle.pose(t=(0.0, 0.0, 2.0)), (2, 1, 1))]
    for _ in range(66):
        meshes.append(trimesh.creation.icosphere(1, radius=rng.uniform(0.15, 0.35)))
        c = rng.uniform([-2.5, -2.0, -1.5], [2.5, 2.0, 1.5])
        poses.append(np.stack([oracle.pose(t=c), oracle.pose(t=c + rng.normal(0, 0.05, 3))]))
    for m, P in zip(meshes, poses):
        scene.add_object(m, P)
    assert len(meshes) > accel.ORDERED_MAX
    keys = ["instance", "distance", "normals", "flow_fw", "occ_fw"]
    via_bvh = fs.render(scene, keys)
    monkeypatch.setattr(accel, "ORDERED_MAX", 1000)
    via_lists = fs.render(scene, keys)
    for k in keys:
        np.testing.assert_array_equal(via_bvh[k].numpy(), via_lists[k].numpy())
    for t in range(2):
        cam_T_world = np.linalg.inv(cams[t])
        tt, kk, _, _ = brute_force(cam, cam_T_world, meshes, [P[t] for P in poses])
        sil = near_silhouette(cam, cam_T_world, meshes, [P[t] for P in poses])
        inst = via_bvh["instance"][t, 0].numpy() - 1
        assert (inst == kk)[~sil].all() and (kk == 0).sum() > 50 and len(np.unique(kk)) > 30
        hit = (kk >= 0) & ~sil
        assert (np.abs(via_bvh["distance"][t, 0].numpy() - tt)[hit] / tt[hit]).max() <= 1e-5
    assert via_bvh["occ_fw"].any()


def test_hull_points_are_the_convex_hull_vertices():
    """The tight boxes' and silhouettes' hull points (Qhull called directly) are the rows of trimesh's
    ``mesh.convex_hull.vertices`` on every built-in asset at two sizes, and every mesh vertex lies within them
    along random directions (the support over the hull points equals that over all vertices)."""
    from flowsynth.raycast.culling import hull_points
    from flowsynth.scene.assets import BUILTIN_ASSETS, get_asset

    dirs = np.random.default_rng(1).normal(size=(64, 3))
    big = fewer = 0
    for name in BUILTIN_ASSETS:
        for size in (0.37, 1.3):
            mesh = get_asset(name, size).mesh
            hull = hull_points(mesh)
            V = np.asarray(mesh.vertices, np.float64)
            if len(V) > 64:
                big += 1
                assert np.array_equal(hull, np.asarray(mesh.convex_hull.vertices, np.float64)), (name, size)
                fewer += len(hull) < len(V)
            np.testing.assert_array_equal((hull @ dirs.T).max(0), (V @ dirs.T).max(0))
    assert big >= 10 and fewer >= 6  # most assets take the Qhull path; the non-convex ones lose vertices
