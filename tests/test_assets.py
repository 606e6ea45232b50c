"""Built-in and user assets: closed meshes, normalised size, colliders that contain the mesh, caching."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from flowsynth.scene.assets import (
    BUILTIN_ASSETS,
    PRIMITIVE_ASSETS,
    get_asset,
    load_user_mesh,
    resolve_assets,
    ROOM_WALLS,
    room_walls,
    unit_mesh,
)
from flowsynth.errors import AssetError

# Collider containment is checked on the mesh vertices with this slack [fraction of size] (float64 round-off).
CONTAIN_TOL = 1e-9


@pytest.mark.parametrize("name", BUILTIN_ASSETS)
def test_builtin_meshes_are_closed_and_normalised(name):
    m = unit_mesh(name)
    assert m.is_watertight and m.is_winding_consistent, name
    assert m.volume > 0, f"{name}: inward-facing triangles"
    assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(0.5, abs=1e-12)
    a = get_asset(name, 0.7)
    assert a.size == 0.7
    assert np.linalg.norm(a.mesh.vertices, axis=1).max() == pytest.approx(0.35, abs=1e-12)


@pytest.mark.parametrize("name", BUILTIN_ASSETS)
def test_collider_contains_the_visual_mesh(name):
    a = get_asset(name, 0.8)
    c = a.collider
    V = np.asarray(a.mesh.vertices)
    x, y, z = V.T
    tol = CONTAIN_TOL * a.size
    assert c.kind == (name if name in PRIMITIVE_ASSETS else "convex")
    if c.kind == "box":
        assert (np.abs(V) <= np.asarray(c.params) + tol).all()
    elif c.kind == "sphere":
        assert (np.linalg.norm(V, axis=1) <= c.params[0] + tol).all()
    elif c.kind == "cylinder":
        r, h = c.params
        assert (np.hypot(x, y) <= r + tol).all() and (np.abs(z) <= h + tol).all()
    elif c.kind == "capsule":
        r, h = c.params
        axis_point = np.stack([np.zeros_like(z), np.zeros_like(z), np.clip(z, -h, h)], 1)
        assert (np.linalg.norm(V - axis_point, axis=1) <= r + tol).all()
    elif c.kind == "cone":
        r, h = c.params
        assert (np.abs(z) <= h + tol).all()
        assert (np.hypot(x, y) <= r * (h - z) / (2 * h) + tol).all()
    hull = c.hull
    assert hull.is_watertight and hull.volume > 0
    # Every vertex lies behind every face plane of the (convex) hull.
    plane_offsets = np.einsum("ij,ij->i", hull.face_normals, hull.vertices[hull.faces[:, 0]])
    assert (V @ hull.face_normals.T - plane_offsets).max() <= tol


def test_assets_are_cached_per_name_and_size():
    a, b = get_asset("rock", 0.5), get_asset("rock", 0.5)
    assert a is b and a.mesh is b.mesh
    assert get_asset("rock", 0.6).mesh is not a.mesh
    assert unit_mesh("torus") is unit_mesh("torus")


def test_primitive_collider_dimensions_scale_with_size():
    small, big = get_asset("box", 0.5), get_asset("box", 1.0)
    np.testing.assert_allclose(np.asarray(big.collider.params), 2 * np.asarray(small.collider.params))


def test_user_mesh_is_normalised_and_cached(tmp_path):
    path = tmp_path / "long.ply"
    trimesh.creation.box(extents=(4.0, 1.0, 1.0)).apply_translation((10.0, 0, 0)).export(path)
    m = load_user_mesh(str(path))
    assert m is load_user_mesh(str(path))
    np.testing.assert_allclose((m.vertices.min(0) + m.vertices.max(0)) / 2, 0.0, atol=1e-12)
    assert np.linalg.norm(m.vertices, axis=1).max() == pytest.approx(0.5)
    a = get_asset(str(path), 0.4)
    assert a.collider.kind == "convex"


def test_resolve_assets_expands_globs_in_sorted_order(tmp_path):
    for name in ("b.obj", "a.obj"):
        trimesh.creation.icosphere(subdivisions=1).export(tmp_path / name)
    keys = resolve_assets(("cone", str(tmp_path / "*.obj")))
    assert keys == ("cone", str(tmp_path / "a.obj"), str(tmp_path / "b.obj"))


@pytest.mark.parametrize("entry, match", [("teapot", "unknown asset"),
                                          ("/no/such/file.obj", "does not exist"),
                                          ("/no/such/*.stl", "matches no files")])
def test_resolve_assets_errors(entry, match):
    with pytest.raises(AssetError, match=match):
        resolve_assets((entry,))


def test_unloadable_file_raises_asset_error(tmp_path):
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"\x00\x01 definitely not an stl")
    with pytest.raises(AssetError, match="bad.stl"):
        load_user_mesh(str(bad))


def test_room_walls_tile_the_box_and_face_inward():
    lo, hi = (-2.0, -1.5, 0.0), (2.0, 1.5, 3.0)
    walls = room_walls(lo, hi)
    assert len(walls) == len(ROOM_WALLS) == 6
    room = trimesh.util.concatenate(list(walls))
    np.testing.assert_allclose(room.bounds, [lo, hi])
    assert room.area == pytest.approx(2 * (4 * 3 + 4 * 3 + 3 * 3))  # the box's surface, each face once
    centre = (np.asarray(lo) + np.asarray(hi)) / 2
    to_centre = centre - room.triangles_center
    assert (np.einsum("ij,ij->i", room.face_normals, to_centre) > 0).all()
    floor = walls[ROOM_WALLS.index("floor")]
    np.testing.assert_allclose(floor.vertices[:, 2], 0.0)
    np.testing.assert_allclose(floor.face_normals, [[0, 0, 1]] * 2, atol=1e-12)
    assert walls is room_walls(lo, hi)


def test_library_meshes_are_cleaned_once_and_shared():
    """Scenes share one cleaned copy of a library mesh (equal to cleaning it afresh); a user's mesh with the
    same content is cleaned on its own, so editing it never touches the library's copy."""
    from flowsynth.scene.camera import Camera
    from flowsynth.scene.scene import Scene, clean_mesh

    mesh = get_asset("rock", 0.5).mesh
    wall = room_walls((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0))[0]
    scenes = [Scene(Camera.from_fov(8, 6, 60.0), 1) for _ in range(2)]
    for s in scenes:
        s.add_object(mesh)
        s.add_object(wall, background=True)
    assert scenes[0].objects[0].mesh is scenes[1].objects[0].mesh
    assert scenes[0].objects[1].mesh is scenes[1].objects[1].mesh
    fresh = clean_mesh(mesh)
    np.testing.assert_array_equal(scenes[0].objects[0].mesh.vertices, fresh.vertices)
    np.testing.assert_array_equal(scenes[0].objects[0].mesh.faces, fresh.faces)
    user = trimesh.Trimesh(np.array(mesh.vertices), np.array(mesh.faces), process=False)
    scenes[0].add_object(user)
    assert scenes[0].objects[2].mesh is not scenes[0].objects[0].mesh


def test_voxel_solids_are_their_cells():
    """chair and frame are the closed surfaces of their unit-cube cells: volume = the cell count, area = the faces
    between a filled and an empty cell (counted from the grid), watertight, and wholly inside their convex hull
    collider (test_collider_contains_the_visual_mesh)."""
    from flowsynth.scene.assets import _CHAIR, _FRAME, _voxel_solid

    for cells in (_CHAIR, _FRAME, np.ones((2, 3, 1), bool)):
        m = _voxel_solid(cells)
        padded = np.pad(cells, 1).astype(int)
        exposed = sum(np.abs(np.diff(padded, axis=a)).sum() for a in range(3))
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume == pytest.approx(cells.sum(), rel=1e-12)
        assert m.area == pytest.approx(exposed, rel=1e-12)
