"""Object tables and boxes against independent computations from the meshes and the instance map (issue 4)."""

import numpy as np
import pytest
import torch
import trimesh
from oracle import pose, project, rigid_inverse

import flowsynth as fs

W, H = 96, 72
TABLE_KEYS = ["object_valid", "object_category", "object_asset", "world_T_obj", "box3d_corners",
              "box2d_amodal", "box2d_visible", "visible_pixels", "instance"]
IMAGE = np.array([-0.5, -0.5, W - 0.5, H - 0.5])


def off_centre_box(extents, shift) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents)
    m.apply_translation(shift)
    return m


def box_scene(offset: float = 0.0):
    """T = 2. Frame 0 / frame 1:
    1 sphere: fully in view / partly out of the left edge;  2 box: in view, rotated / far right, outside;
    3 box: straddles the camera plane / entirely behind;     4 wall: behind the others in both;
    5 box: shares object 2's mesh, in view in both frames.  Everything is shifted by ``offset`` [m]."""
    T = 2
    shift = pose(t=(offset, -0.5 * offset, 0.25 * offset))
    sphere = trimesh.creation.icosphere(2, radius=0.5)
    box = off_centre_box((1.0, 0.6, 0.4), (0.2, -0.1, 0.05))
    objs = [
        (sphere, [pose(t=(0.0, 0.0, 5.0)), pose(t=(-3.3, 0.3, 5.0))], 7),
        (box, [pose((0.3, 0.5, 0.2), (1.2, 0.6, 6.0)), pose((0.3, 0.5, 0.2), (20.0, 0.6, 6.0))], 2),
        (trimesh.creation.box((0.4, 0.4, 1.0)),
         [pose((0.0, 0.0, 0.2), (0.3, 0.2, 0.3)), pose(t=(0.3, 0.2, -3.0))], 2),
        (trimesh.creation.box((30.0, 30.0, 0.2)), [pose(t=(0.0, 0.0, 12.0))] * T, 1),
        (box, [pose((0.0, 1.0, 0.0), (-1.5, -0.9, 7.0)), pose((0.0, 1.2, 0.1), (-1.4, -0.9, 7.0))], 2),
    ]
    scene = fs.Scene(fs.Camera.from_fov(W, H, 60.0), T)
    scene.set_camera_poses(shift)
    for mesh, poses, cat in objs:
        scene.add_object(mesh, poses=shift[None] @ np.stack(poses), category=cat)
    return scene


def dense_vertices(mesh: trimesh.Trimesh, max_edge: float) -> np.ndarray:
    """Vertices of ``mesh`` subdivided until no edge is longer than ``max_edge`` [m]."""
    V, _ = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=max_edge)
    return np.asarray(V, np.float64)


def reference_amodal(V_obj: np.ndarray, cam_T_obj: np.ndarray, K: np.ndarray) -> np.ndarray:
    """xyxy of the projected dense vertices in front of the camera, clipped to the image; 0 if none
    or if the box misses the image."""
    X = V_obj @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3]
    X = X[X[:, 2] > 0]
    if len(X) == 0:
        return np.zeros(4)
    uv = project(K, X)
    lo, hi = uv.min(0), uv.max(0)
    if (hi < IMAGE[:2]).any() or (lo > IMAGE[2:]).any():
        return np.zeros(4)
    return np.concatenate([np.maximum(lo, IMAGE[:2]), np.minimum(hi, IMAGE[2:])])


@pytest.fixture(scope="module")
def rendered():
    scene = box_scene()
    return scene, fs.render(scene, TABLE_KEYS, max_objects=8)


@pytest.mark.parametrize("offset", [0.0, 1e4])
def test_box3d_corners(offset):
    scene = box_scene(offset)
    out = fs.render(scene, ["box3d_corners"], max_objects=6)
    box3d = out["box3d_corners"].double().numpy()
    assert out["box3d_corners"].shape == (2, 6, 8, 3) and out["box3d_corners"].dtype == torch.float32
    assert (box3d[:, len(scene.objects):] == 0).all()
    for n, o in enumerate(scene.objects):
        V = np.asarray(o.mesh.vertices)
        lo, hi = V.min(0), V.max(0)
        bits = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])
        corners = np.where(bits == 1, hi, lo)
        for t in range(2):
            ref = corners @ o.poses[t, :3, :3].T + o.poses[t, :3, 3]
            tol = 1e-6 + 2e-7 * np.abs(ref).max()
            np.testing.assert_allclose(box3d[t, n], ref, rtol=0, atol=tol)
            if n == 1:  # a posed box mesh: its oriented bounding box is unique and equals the 3D box
                posed = o.mesh.copy().apply_transform(o.poses[t])
                to_origin, ext = trimesh.bounds.oriented_bounds(posed)
                obb = trimesh.bounds.corners([-ext / 2, ext / 2]) @ rigid_inverse(to_origin)[:3, :3].T
                obb = obb + rigid_inverse(to_origin)[:3, 3]
                dist = np.linalg.norm(box3d[t, n][:, None] - obb[None], axis=-1)
                assert (dist.min(1) < 10 * tol).all() and (dist.min(0) < 10 * tol).all()


def test_box2d_amodal(rendered):
    scene, out = rendered
    amodal = out["box2d_amodal"].double().numpy()
    K = scene.camera.K
    cam_T_world = rigid_inverse(scene.world_T_cam)
    expected_cases = {(0, 0): "inside", (1, 0): "clipped", (0, 1): "inside", (1, 1): "outside",
                      (0, 2): "straddles", (1, 2): "behind", (0, 4): "inside", (1, 4): "inside"}
    for (t, n), case in expected_cases.items():
        o = scene.objects[n]
        cam_T_obj = cam_T_world[t] @ o.poses[t]
        V = dense_vertices(o.mesh, 0.02)
        ref = reference_amodal(V, cam_T_obj, K)
        got = amodal[t, n]
        print(f"amodal t={t} object {n + 1} ({case}): {np.round(got, 3)} vs {np.round(ref, 3)}")
        if case == "inside":
            unclipped = project(K, V @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3])
            assert (unclipped.min(0) > IMAGE[:2]).all() and (unclipped.max(0) < IMAGE[2:]).all()
        if case in ("outside", "behind"):
            assert (got == 0).all()
        if case == "clipped":
            assert ref[0] == -0.5 and ref[2] > 0
        if case == "straddles":
            assert (ref[:2] == IMAGE[:2]).any() or (ref[2:] == IMAGE[2:]).any()
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-3)
    # frame 1 of the wall: larger than the image, so clipped to it
    np.testing.assert_allclose(amodal[1, 3], IMAGE, atol=1e-6)


def test_box2d_visible_and_pixel_counts(rendered):
    _, out = rendered
    inst = out["instance"][:, 0].numpy()
    for t in range(2):
        for n in range(8):
            i, j = np.nonzero(inst[t] == n + 1)
            assert out["visible_pixels"][t, n].item() == len(i)
            ref = np.zeros(4)
            if len(i):
                ref = np.array([j.min() - 0.5, i.min() - 0.5, j.max() + 0.5, i.max() + 0.5])
            np.testing.assert_array_equal(out["box2d_visible"][t, n].numpy(), ref)
    assert out["visible_pixels"].dtype == torch.int32
    vis, amodal = out["box2d_visible"].numpy(), out["box2d_amodal"].numpy()
    seen = out["visible_pixels"].numpy() > 0
    # the visible box lies inside the amodal box (up to half a pixel: visible boxes cover whole pixels)
    assert (vis[seen][:, :2] >= amodal[seen][:, :2] - 0.5 - 1e-4).all()
    assert (vis[seen][:, 2:] <= amodal[seen][:, 2:] + 0.5 + 1e-4).all()


def test_object_tables_are_padded(rendered):
    scene, out = rendered
    N = len(scene.objects)
    assert out["object_valid"].tolist() == [True] * N + [False] * (8 - N)
    assert out["object_category"].tolist() == [7, 2, 2, 1, 2, 0, 0, 0]
    assert out["object_asset"][:N].tolist() == [o.asset for o in scene.objects]
    assert out["object_asset"][1] == out["object_asset"][4] and (out["object_asset"][N:] == 0).all()
    world_T_obj = np.stack([o.poses for o in scene.objects], 1)
    np.testing.assert_allclose(out["world_T_obj"][:, :N].double().numpy(), world_T_obj, atol=1e-6)
    assert (out["world_T_obj"][:, N:] == 0).all()
    for k, shape in (("world_T_obj", (2, 8, 4, 4)), ("box2d_amodal", (2, 8, 4)), ("box2d_visible", (2, 8, 4)),
                     ("visible_pixels", (2, 8)), ("object_valid", (8,)), ("object_category", (8,))):
        assert tuple(out[k].shape) == shape, k
    for k in ("box2d_amodal", "box2d_visible", "visible_pixels"):
        assert (out[k][:, N:] == 0).all(), k


def test_max_objects_too_small_raises():
    with pytest.raises(fs.ConfigError, match="max_objects"):
        fs.render(box_scene(), ["object_valid"], max_objects=2)
