"""The per-(pair, pixel) Warp reprojection kernel (flowsynth.truth.flow.reproject_pixels) against a float64 numpy
reprojection of the same G-buffer (the gather/scatter code the kernel replaced, kept here as the oracle).

The scene has a moving, turning camera with a skewed K, objects leaving the image and objects passing behind
the camera, so every branch (valid, out of frame, behind the camera, occluded, visible) is taken. The
exact occlusion is compared with the visibility kernel over each frame's whole instance list
(flowsynth.truth.flow.visibility), the depth test with its numpy form.
"""

import importlib

import numpy as np
import pytest
import trimesh
from oracle import pose

import flowsynth as fs
from flowsynth.raycast.accel import SceneAccel
from flowsynth.truth.flow import DEPTH_TEST_REL_TOL, MOTION_TOL, reproject_pixels, visibility, world_points

render_mod = importlib.import_module("flowsynth.raycast.gbuffer")

W, H, T = 64, 48, 4
K = np.array([[52.0, 6.0, 30.3], [0.0, 49.0, 22.8], [0.0, 0.0, 1.0]])


def scene_arrays():
    cams = np.stack([pose((0.04 * t, -0.03 * t, 0.06 * t), (0.1 * t, -0.05 * t, 0.15 * t)) for t in range(T)])
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    objs = [
        (trimesh.creation.box((14.0, 10.0, 0.2)), [pose(t=(0, 0, 12.0))] * T),
        (trimesh.creation.box((1.0, 1.0, 1.0)), [pose(axis * 0.5 * t, (-0.8, 0.0, 5.0)) for t in range(T)]),
        (trimesh.creation.icosphere(2, radius=0.6), [pose(t=(1.5 + 1.6 * t, 0.2, 5.0)) for t in range(T)]),
        (trimesh.creation.box((0.6, 0.6, 0.6)),
         [pose((0.1 * t, 0.0, 0.0), (0.9, 0.5, z)) for t, z in enumerate((2.0, 0.2, -1.5, -2.5))]),
        (trimesh.creation.box((0.3, 0.3, 4.0)), [pose(t=(-1.2, 0.8, z)) for z in (2.5, 1.2, 0.5, -0.5)]),
        (trimesh.creation.box((0.5, 0.5, 0.5)),  # comes from behind the camera: backward pairs need it
         [pose((0.0, 0.2 * t, 0.0), (-0.3, -0.6, z)) for t, z in enumerate((-2.0, -0.5, 0.4, 1.5))]),
    ]
    scene = fs.Scene(fs.Camera(K, W, H), T)
    scene.set_camera_poses(cams)
    for mesh, poses in objs:
        scene.add_object(mesh, poses=np.stack(poses))
    return scene


def numpy_pairs(gb, cam_T_obj, src0, step, P, K=K):
    """float64 numpy: per hit pixel of frames src0 .. src0 + P - 1, X in the target frame, (u', v') by the full
    K, flow, valid, inside; plus the pixel coordinates (f, i, j) and target frames r."""
    gb = gb.host()
    H, W = gb.item.shape[1:]
    src = np.arange(P) + src0
    f, i, j = np.nonzero(gb.hit[src])
    s = src[f]
    r = s + step
    p = gb.point[s, i, j].astype(np.float64)
    M = cam_T_obj[r, gb.instance_index[s, i, j]]
    X = (M[:, :3, :3] @ p[:, :, None])[:, :, 0] + M[:, :3, 3]
    front = X[:, 2] > 0
    h = np.where(front[:, None], X, [0.0, 0.0, 1.0]) @ K.T
    uv = np.where(front[:, None], h[:, :2] / h[:, 2:], 0.0)
    inside = front & (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < H - 0.5)
    flow = np.zeros((P, 2, H, W))
    flow[f, 0, i, j] = np.where(front, uv[:, 0] - j, 0.0)
    flow[f, 1, i, j] = np.where(front, uv[:, 1] - i, 0.0)
    masks = {m: np.zeros((P, 1, H, W), bool) for m in ("valid", "oof")}
    masks["valid"][f, 0, i, j] = front
    masks["oof"][f, 0, i, j] = ~inside
    return flow, masks, (f, i, j, r, X, uv, inside)


@pytest.fixture(scope="module")
def setup():
    scene = scene_arrays()
    meshes, cam_T_world, world_T_obj = render_mod.scene_arrays(scene)
    accel = SceneAccel(meshes, cam_T_world, world_T_obj)
    gb = render_mod.cast_gbuffer(accel, scene.camera, want_normals=False, want_points=True)
    return scene, accel, gb, np.matmul(cam_T_world[:, None], world_T_obj)


@pytest.mark.parametrize("threads", [1, 2])
def test_world_points_and_motion_equal_numpy(setup, threads):
    """world_points_kernel (fs.render's ``position`` and the ``motion`` flags) against the numpy gather of 4x4
    matrices it replaced: world points to 1e-12 m, 0 where nothing is hit; motion flags equal wherever the
    displacement is not within 1e-9 m of the threshold. The scene has a static wall, a translating sphere and
    turning boxes, so both flag values occur."""
    scene, _, gb, _ = setup
    world_T_obj = render_mod.scene_arrays(scene)[2]
    world, moved = world_points(gb, world_T_obj, moved=True, threads=threads)
    h = gb.host()
    f, i, j = np.nonzero(h.hit)
    p = h.point[f, i, j].astype(np.float64)
    n = h.instance_index[f, i, j]

    def apply(M):
        return (M[:, :3, :3] @ p[:, :, None])[:, :, 0] + M[:, :3, 3]

    expect = np.zeros((T, H, W, 3))
    expect[f, i, j] = apply(world_T_obj[f, n])
    assert world.shape == (T, H, W, 3) and world.dtype == np.float64
    np.testing.assert_allclose(world, expect, rtol=0, atol=1e-12)
    assert not world[~h.hit].any()
    nxt = f < T - 1
    xa = expect[f, i, j][nxt]
    disp = np.linalg.norm(apply(world_T_obj[np.minimum(f + 1, T - 1), n])[nxt] - xa, axis=1)
    bound = MOTION_TOL + 1e-12 * np.linalg.norm(xa, axis=1)
    truth = np.zeros((T - 1, H, W), bool)
    truth[f[nxt], i[nxt], j[nxt]] = disp > bound
    clear = np.ones((T - 1, H, W), bool)
    clear[f[nxt], i[nxt], j[nxt]] = np.abs(disp - bound) > 1e-9
    assert moved.shape == (T - 1, H, W) and moved.dtype == bool
    assert (moved == truth)[clear].all() and clear.mean() > 0.99
    assert 0.05 < truth[h.hit[:-1]].mean() < 0.95, "both flag values must occur"
    assert world_points(gb, world_T_obj, moved=False, threads=threads)[1] is None


@pytest.mark.parametrize("gap", [1, 2])
@pytest.mark.parametrize("direction", ["fw", "bw"])
def test_kernel_equals_numpy_reprojection(setup, gap, direction):
    scene, accel, gb, cam_T_obj = setup
    P = T - gap
    src0, step = (0, gap) if direction == "fw" else (gap, -gap)
    flow, masks, (f, i, j, r, X, uv, inside) = numpy_pairs(gb, cam_T_obj, src0, step, P)
    front = X[:, 2] > 0
    assert (~front).sum() > 5, "some hit points must fall behind the target camera"
    assert (front & ~inside).sum() > 5, "some must project out of frame"
    assert K[0, 1] != 0.0
    got = reproject_pixels(gb, cam_T_obj, K, src0, step, P, accel=accel, camera=scene.camera, flow=True,
                           occlusion="exact", threads=1)
    for m in ("valid", "oof"):
        np.testing.assert_array_equal(got[m], masks[m], err_msg=m)
    # float64 in both; the kernel's flow is float32: equal to the float64 value rounded to float32
    assert got["flow"].dtype == np.float32
    np.testing.assert_allclose(got["flow"], flow, rtol=1e-6, atol=2e-6)
    assert np.abs(flow).max() > 5.0, "the motion must be visible"
    # exact occlusion: same as the visibility kernel over the frame's whole instance list
    occ = np.zeros((P, 1, H, W), bool)
    blocked = visibility(accel, [(X[inside], r[inside])], threads=1)
    hidden = ~inside
    hidden[inside] = blocked
    occ[f, 0, i, j] = hidden
    assert blocked.sum() > 5 and (~blocked).sum() > 5, "visible and hidden in-frame points"
    np.testing.assert_array_equal(got["occ"], occ)
    # depth-buffer occlusion
    dz = scene.camera.pixel_rays_numpy()[..., 2]
    jj = np.clip(np.rint(uv[inside, 0]).astype(np.int64), 0, W - 1)
    ii = np.clip(np.rint(uv[inside, 1]).astype(np.int64), 0, H - 1)
    ri = r[inside]
    h = gb.host()
    depth_blocked = ~h.hit[ri, ii, jj] | (X[inside, 2] > h.dist[ri, ii, jj] * dz[ii, jj] * (1 + DEPTH_TEST_REL_TOL))
    occ_d = np.zeros((P, 1, H, W), bool)
    hidden = ~inside
    hidden[inside] = depth_blocked
    occ_d[f, 0, i, j] = hidden
    got_d = reproject_pixels(gb, cam_T_obj, K, src0, step, P, accel=accel, camera=scene.camera,
                             occlusion="depth", threads=1)
    np.testing.assert_array_equal(got_d["occ"], occ_d)
    # any thread count: bit-identical
    again = reproject_pixels(gb, cam_T_obj, K, src0, step, P, accel=accel, camera=scene.camera, flow=True,
                             occlusion="exact", threads=3)
    for key in ("flow", "valid", "oof", "occ"):
        np.testing.assert_array_equal(again[key], got[key], err_msg=key)


def test_disparity_change_equals_numpy(setup):
    scene, accel, gb, cam_T_obj = setup
    fB = K[0, 0] * 0.1
    flow, masks, (f, i, j, r, X, uv, inside) = numpy_pairs(gb, cam_T_obj, 0, 1, T - 1)
    p = gb.host().point[f, i, j].astype(np.float64)
    M0 = cam_T_obj[f, gb.host().instance_index[f, i, j]]
    z0 = (M0[:, 2, :3] * p).sum(-1) + M0[:, 2, 3]
    front = X[:, 2] > 0
    dc = np.zeros((T - 1, 1, H, W))
    dc[f, 0, i, j] = np.where(front, fB / np.where(front, X[:, 2], 1.0) - fB / z0, 0.0)
    got = reproject_pixels(gb, cam_T_obj, K, 0, 1, T - 1, fB=fB, threads=1)
    np.testing.assert_allclose(got["dc"], dc, rtol=1e-12, atol=1e-9)
    assert np.abs(dc).max() > 1.0


@pytest.mark.parametrize("step", [2, -1])
def test_scene_flow_equals_numpy(setup, step):
    """scene_flow = cam_T_world[s] (world_T_obj[s + step, n] - world_T_obj[s, n]) p where hit (valid or not)."""
    scene, accel, gb, cam_T_obj = setup
    _, cam_T_world, world_T_obj = render_mod.scene_arrays(scene)
    src0 = max(-step, 0)
    P = T - abs(step)
    src = np.arange(P) + src0
    f, i, j = np.nonzero(gb.host().hit[src])
    s = src[f]
    n = gb.host().instance_index[s, i, j]
    p = gb.host().point[s, i, j].astype(np.float64)
    xa = (world_T_obj[s, n, :3, :3] @ p[:, :, None])[:, :, 0] + world_T_obj[s, n, :3, 3]
    xb = (world_T_obj[s + step, n, :3, :3] @ p[:, :, None])[:, :, 0] + world_T_obj[s + step, n, :3, 3]
    sf = np.zeros((P, 3, H, W))
    sf[f, :, i, j] = np.einsum("pij,pj->pi", cam_T_world[s, :3, :3], xb - xa)  # world displacement, camera s axes
    sfT = np.matmul(cam_T_world[src][:, None], world_T_obj[src + step] - world_T_obj[src])
    got = reproject_pixels(gb, cam_T_obj, K, src0, step, P, scene_flow_T=sfT, threads=1)
    assert got["scene_flow"].dtype == np.float32
    np.testing.assert_allclose(got["scene_flow"], sf, rtol=1e-6, atol=1e-6)
    assert np.abs(sf).max() > 0.5 and (~got["valid"] & gb.host().hit[src][:, None]).any()


def test_culling_bounds_hold_against_brute_force():
    """The culling data of ``SceneAccel.culling`` (flowsynth.raycast.culling._face_planes) against float64 brute force:
    every vertex behind every face plane, inside the bounding sphere, and the inner ball free of surface
    (rays from its centre, Moller-Trumbore over every triangle, first hit no nearer than the radius; every
    ray hits: the centre is enclosed). Flat meshes (room walls) get a zero-width slab, non-convex ones no ball."""
    from oracle import ray_cast

    from flowsynth.raycast.culling import _face_planes
    from flowsynth.scene.assets import get_asset, room_walls

    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    meshes = {"box": trimesh.creation.box((0.6, 0.3, 0.2)), "icosphere": trimesh.creation.icosphere(2, radius=0.6),
              "rock": get_asset("rock", 0.7).mesh, "torus": get_asset("torus", 0.5).mesh,
              "wall": room_walls((-3.0, -2.0, 0.0), (3.0, 2.0, 2.5))[2]}
    for name, mesh in meshes.items():
        b = _face_planes(mesh)
        V = np.asarray(mesh.vertices, np.float32).astype(np.float64)
        heights = V @ b["planes"][:, :3].T - b["planes"][:, 3]  # (vertices, faces)
        assert heights.max() <= 1e-12, name
        centre, radius = b["sphere"][:3], b["sphere"][3]
        assert np.linalg.norm(V - centre, axis=1).max() <= radius * (1 + 1e-12), name
        if name == "wall":
            assert b["slab"] is not None and b["slab"][3] == b["slab"][4] and b["inner"] == 0.0
            continue
        assert b["slab"] is None, name
        if name == "torus":
            assert b["inner"] == 0.0, "a non-convex mesh gets no inner ball"
            continue
        assert b["inner"] > 0.2 * radius, name
        hits = ray_cast(centre, dirs, [mesh], np.eye(4)[None])
        assert np.isfinite(hits["t"]).all(), name
        assert hits["t"].min() >= b["inner"], (name, hits["t"].min(), b["inner"])


def _room(num_frames: int):
    """BouncingThings room scene 3 at 80x60 (flat): scene, its SceneAccel, G-buffer with points, cam_T_obj."""
    from flowsynth.scene.sampling import sample_scene

    cfg = fs.BouncingThingsConfig(width=80, height=60, num_frames=num_frames, render_mode="flat")
    scene = sample_scene(cfg, 0, 3)
    meshes, cam_T_world, world_T_obj = render_mod.scene_arrays(scene)
    accel = SceneAccel(meshes, cam_T_world, world_T_obj)
    gb = render_mod.cast_gbuffer(accel, scene.camera, want_normals=False, want_points=True)
    return scene, accel, gb, np.matmul(cam_T_world[:, None], world_T_obj)


def _assert_culled_occ_is_the_full_walk(scene, accel, gb, cam_T_obj, src0: int, step: int, P: int) -> None:
    """The pair kernel's culled occlusion equals out-of-frame or the visibility kernel's full walk."""
    _, _, (f, i, j, r, X, uv, inside) = numpy_pairs(gb, cam_T_obj, src0, step, P, scene.camera.K)
    got = reproject_pixels(gb, cam_T_obj, scene.camera.K, src0, step, P, accel=accel, camera=scene.camera,
                           occlusion="exact", threads=2)
    blocked = visibility(accel, [(X[inside], r[inside])], threads=1)
    assert blocked.sum() > 20 and (~blocked).sum() > 1000
    occ = np.zeros((P, 1, scene.camera.height, scene.camera.width), bool)
    hidden = ~inside
    hidden[inside] = blocked
    occ[f, 0, i, j] = hidden
    np.testing.assert_array_equal(got["occ"], occ)


@pytest.mark.parametrize("gap", [1, 2])
def test_culled_visibility_equals_the_full_walk_in_a_room(gap):
    """In a BouncingThings room (six flat walls, convex and non-convex objects), the pair kernel's culled
    visibility (own face plane, wall slabs, bounding and inner balls, tile lists without walls) gives
    exactly the visibility kernel's answer over every instance of the frame, in both directions."""
    scene, accel, gb, cam_T_obj = _room(5)
    cull = accel.culling()
    assert (np.diff(cull.grp_off.numpy()) == 3).all(), "the room's walls: three groups per frame"
    assert (cull.inner.numpy() > 0).any() and (cull.inner.numpy() == 0).any()
    P = scene.num_frames - gap
    for src0, step in ((0, gap), (gap, -gap)):
        _assert_culled_occ_is_the_full_walk(scene, accel, gb, cam_T_obj, src0, step, P)


def test_sphere_bounded_face_planes_keep_visibility_exact(monkeypatch):
    """Above ``FACE_PLANES_BUDGET`` (faces x vertices) a face plane's offset is the bounding sphere's
    n . c + r instead of the max over the vertices: it must still hold every vertex (float64 brute force),
    give no inner ball, and leave the culled visibility equal to the visibility kernel's full walk."""
    from collections import OrderedDict

    import flowsynth.raycast.culling as culling_mod

    monkeypatch.setattr(culling_mod, "FACE_PLANES_BUDGET", 0)
    monkeypatch.setattr(culling_mod, "_PLANES", OrderedDict())
    for mesh in (trimesh.creation.icosphere(2, radius=0.6), trimesh.creation.torus(0.5, 0.15)):
        b = culling_mod._face_planes(mesh)
        V = np.asarray(mesh.vertices, np.float32).astype(np.float64)
        assert (V @ b["planes"][:, :3].T - b["planes"][:, 3]).max() <= 0.0
        assert b["inner"] == 0.0
    scene, accel, gb, cam_T_obj = _room(4)
    assert (accel.culling().inner.numpy() == 0).all()
    _assert_culled_occ_is_the_full_walk(scene, accel, gb, cam_T_obj, 0, 1, scene.num_frames - 1)


def test_silhouette_planes_hold_every_vertex_and_clear_only_missing_segments():
    """``_silhouette_planes`` and ``beyond_silhouette`` (flowsynth.kernels.raycast) against float64 brute force:
    every vertex (float32, posed in float64) lies behind every plane and no nearer than the least depth; a
    segment the test clears never meets the mesh (Moller-Trumbore over every triangle, ``oracle.ray_cast``);
    the test clears most near misses of convex meshes (it is not vacuous); an instance reaching behind the
    camera gets no planes."""
    import warp as wp
    from oracle import ray_cast

    from flowsynth.raycast.culling import _silhouette_planes
    from flowsynth.scene.assets import get_asset
    from flowsynth.kernels.raycast import SIL_K, beyond_silhouette

    @wp.kernel(enable_backward=False)
    def clears(sil: wp.array[wp.vec4d], sil_z: wp.array[wp.float64], item: wp.array[wp.int32],
               X: wp.array[wp.vec3d], margin: wp.float64, out: wp.array[wp.int32]):
        k = wp.tid()
        out[k] = wp.int32(1) if beyond_silhouette(sil, sil_z, item[k], X[k], margin) else wp.int32(0)

    rng = np.random.default_rng(1)
    meshes = [get_asset(a, 0.8).mesh for a in ("box", "cone", "crystal", "star", "torus")]
    F = 3
    cam_T_obj = np.stack([[pose(rng.normal(size=3), (rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 0.5),
                                                     rng.uniform(1.5, 4.0))) for _ in meshes] for _ in range(F)])
    cam_T_obj[2, 4] = pose((0.3, 0.2, 0.1), (0.0, 0.0, 0.1))  # reaches behind the camera
    sil, z0 = _silhouette_planes(meshes, cam_T_obj)
    assert sil.shape == (F, len(meshes), SIL_K, 4)
    assert z0[2, 4] == -1.0 and (sil[2, 4, :, 3] >= 1e299).all()
    margin = 1e-6 * 8.0 + 1e-9
    cleared_misses, misses = {}, {}
    for f in range(F):
        for n, m in enumerate(meshes):
            if (f, n) == (2, 4):
                continue
            V = np.asarray(m.vertices, np.float32).astype(np.float64) @ cam_T_obj[f, n, :3, :3].T
            V += cam_T_obj[f, n, :3, 3]
            assert V[:, 2].min() >= z0[f, n] > 0
            heights = V @ sil[f, n, :, :3].T - sil[f, n, :, 3]
            assert heights.max() <= 1e-12, (f, n)
            # segments from the camera to points behind the mesh, aimed around its silhouette
            c = V.mean(0)
            r = np.linalg.norm(V - c, axis=1).max()
            aim = c + rng.uniform(-1.3 * r, 1.3 * r, size=(3000, 3))
            X = aim / np.linalg.norm(aim, axis=1, keepdims=True) * rng.uniform(0.3, 8.0, size=(3000, 1))
            item = np.full(len(X), f * len(meshes) + n, np.int32)
            out = wp.zeros(len(X), dtype=wp.int32, device="cpu")
            wp.launch(clears, len(X), inputs=[wp.array(sil.reshape(-1, 4), dtype=wp.vec4d, device="cpu"),
                                              wp.array(z0.reshape(-1), dtype=wp.float64, device="cpu"),
                                              wp.array(item, dtype=wp.int32, device="cpu"),
                                              wp.array(X, dtype=wp.vec3d, device="cpu"), margin],
                      outputs=[out], device="cpu")
            cleared = out.numpy().astype(bool)
            L = np.linalg.norm(X, axis=1)
            hit = ray_cast(np.zeros(3), X / L[:, None], [m], cam_T_obj[f, n][None])["t"] <= L
            assert not (cleared & hit).any(), (f, n, "a cleared segment meets the mesh")
            if n < 3:  # convex: a near miss reaching past the mesh's least depth is cleared
                far = X[:, 2] > z0[f, n] + 2 * r
                cleared_misses[(f, n)] = (cleared & ~hit & far).sum()
                misses[(f, n)] = (~hit & far).sum()
    assert sum(misses.values()) > 2000
    assert sum(cleared_misses.values()) > 0.9 * sum(misses.values()), (cleared_misses, misses)
