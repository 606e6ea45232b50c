"""Exact bounds of the instances of a clip, for culling rays: convex hulls, face planes, flat slabs, silhouettes.

Per mesh (cached per process, keyed by the mesh's content: ``flowsynth.scene.meshes.freeze`` makes it read-only first)
its convex hull's points (``hull_points``: the tight boxes of ``flowsynth.raycast.accel`` and the screen bounds of
``flowsynth.raycast.tiles``) and its face planes (``_face_planes``); per clip the ``Culling`` struct of the visibility
rays (``build_culling``: flowsynth/kernels/reproject.py tests it before a mesh query).
"""

from __future__ import annotations

import hashlib
import weakref
from collections import OrderedDict

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from trimesh.convex import QHULL_DEFAULT

from flowsynth.caches import register
from flowsynth.kernels import wp_runtime
from flowsynth.scene import freeze

__all__ = ["FLAT_REL", "MESH_CACHE_SIZE", "culling_struct", "culling_tables", "hull_points", "join_culling"]

# Maximum number of per-mesh hulls and face planes kept per process (least recently used are dropped).
MESH_CACHE_SIZE = 512
# A mesh is "flat" when it lies between two parallel planes (one of its face planes) closer than this
# fraction of its extent: visibility rays then test that slab (exact) before its box and mesh (room walls).
FLAT_REL = 1e-2
# Face planes' offsets e = max of n . v over every vertex cost faces x vertices (~3 ns each): above this
# product (built-in assets: <= 2.1e6) the bounding sphere's n . c + r stands in (an 82k-face icosphere:
# 9.2 s -> 0.05 s, measured once by hand).
FACE_PLANES_BUDGET = 2e7

_KEYS: weakref.WeakKeyDictionary = register("culling.mesh_keys", weakref.WeakKeyDictionary())


def _mesh_key(mesh: trimesh.Trimesh) -> bytes:
    """Content hash of a mesh, computed once per mesh object, which is frozen first (``flowsynth.scene.meshes.freeze``:
    changing it afterwards raises instead of reusing the hash)."""
    key = _KEYS.get(mesh)
    if key is None:
        freeze(mesh)
        h = hashlib.blake2b(digest_size=16)
        h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float32).tobytes())
        h.update(np.ascontiguousarray(mesh.faces, dtype=np.int32).tobytes())
        key = _KEYS[mesh] = h.digest()
    return key


def _cached(cache: OrderedDict, key, make):
    """``cache[key]``, made by ``make()`` on a miss: a per-process LRU cache of at most ``MESH_CACHE_SIZE``
    entries (hull points, face planes)."""
    hit = cache.get(key)
    if hit is None:
        hit = cache[key] = make()
        while len(cache) > MESH_CACHE_SIZE:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return hit



def culling_tables(meshes: list[trimesh.Trimesh], cam_T_obj: np.ndarray, threads: int | None = None,
                   device: str = "cpu") -> dict:
    """The visibility rays' exact culling data of one clip of N instances in F frames (``cam_T_obj`` (F, N, 4, 4)
    float64) in numpy: the ``Culling`` struct's fields (flowsynth.kernels.raycast; items f N + n), and ``flat``, the
    (N,) bool flags of the flat instances. ``culling_struct`` uploads them (``join_culling`` joins a batch's first).

    Per face of every asset, its plane (unit normal n, e = max over the asset's vertices of n . v): the
    whole mesh lies in n . x <= e. The flat instances (``FLAT_REL``: room walls), and per (frame, item)
    of a flat instance the slab lo <= n . x <= hi holding it, in the frame's camera frame; per (frame, item)
    the ``SIL_K`` planes through the camera centre that bound its convex hull (``_silhouette_planes``). All float64,
    from the float32 vertices the mesh queries use. Visibility rays test the flat instances of their
    frame first, then walk ``SceneAccel.tile_lists(camera, flat=False)``. ``threads``: those of the face planes'
    kernel on a mesh not yet cached (``_face_planes``, on ``device``; the result does not depend on it).
    """
    bounds = [_face_planes(m, threads, device) for m in meshes]
    planes, slabs = [b["planes"] for b in bounds], [b["slab"] for b in bounds]
    offsets = np.cumsum([0] + [len(p) for p in planes])[:-1]
    flat = np.array([s is not None for s in slabs], bool)
    n_obj = np.array([s[:3] if s is not None else np.zeros(3) for s in slabs]).reshape(-1, 3)  # (N, 3)
    lh = np.array([s[3:] if s is not None else (1.0, 0.0) for s in slabs]).reshape(-1, 2)  # (N, 2); lo > hi: not flat
    F, N = cam_T_obj.shape[:2]
    R, t = cam_T_obj[..., :3, :3], cam_T_obj[..., :3, 3]  # (F, N, 3, 3), (F, N, 3)
    n_cam = np.einsum("fnij,nj->fni", R, n_obj)
    shift = np.einsum("fni,fni->fn", n_cam, t)
    lh_cam = np.where(flat[None, :, None], lh[None] + shift[..., None], lh[None])
    sph = np.array([b["sphere"] for b in bounds]).reshape(-1, 4)  # (N, 4)
    centre = np.einsum("fnij,nj->fni", R, sph[:, :3]) + t
    g_off, g_n, g_ab, g_item, m_start, m_items = _flat_groups(n_cam, lh_cam, np.flatnonzero(flat))
    sil, sil_z = _silhouette_planes(meshes, cam_T_obj)
    return {"face_plane": np.concatenate(planes) if planes else np.zeros((0, 4)),
            "face_off": np.asarray(offsets, np.int32), "slab_n": n_cam.reshape(-1, 3), "slab_lh": lh_cam.reshape(-1, 2),
            "sphere": np.concatenate([centre, np.broadcast_to(sph[:, 3], (F, N))[..., None]], -1).reshape(-1, 4),
            "inner": np.tile(np.array([b["inner"] for b in bounds], np.float64), F),
            "grp_off": g_off, "grp_n": g_n, "grp_ab": g_ab, "grp_item": g_item, "mem_start": m_start,
            "mem_items": m_items, "sil": sil.reshape(-1, 4), "sil_z": sil_z.reshape(-1), "flat": flat}


def join_culling(tables: list[dict], item0: np.ndarray, frames: int) -> dict:
    """The ``culling_tables`` of a batch's clips (without ``flat``) as one: per-item and per-face rows one clip after
    another, per-frame and CSR offsets and the items they name shifted (clip b's items by its first item
    ``item0[b]``; -2, no item, stays). One clip is returned as it is."""
    if len(tables) == 1:
        return tables[0]
    out = {k: np.concatenate([t[k] for t in tables]) for k in ("face_plane", "slab_n", "slab_lh", "sphere", "inner",
                                                               "sil", "sil_z")}
    planes = np.cumsum([0] + [len(t["face_plane"]) for t in tables])
    out["face_off"] = np.concatenate([t["face_off"] + planes[b] for b, t in enumerate(tables)]).astype(np.int32)
    g_off, g_n, g_ab, g_item, m_start, m_items = [], [], [], [], [], []
    groups = members = 0
    for b, t in enumerate(tables):
        G, Mn = int(t["grp_off"][-1]), int(t["mem_start"][-1])
        g_off.append(t["grp_off"][:-1] + groups)
        g_n.append(t["grp_n"][:G])
        g_ab.append(t["grp_ab"][:G])
        g_item.append(np.where(t["grp_item"][:G] >= 0, t["grp_item"][:G] + item0[b], t["grp_item"][:G]))
        m_start.append(t["mem_start"][:-1] + members)
        m_items.append(t["mem_items"][:Mn] + item0[b])
        groups, members = groups + G, members + Mn
    out["grp_off"] = np.concatenate(g_off + [[groups]]).astype(np.int32)
    out["mem_start"] = np.concatenate(m_start + [[members]]).astype(np.int32)
    out["grp_n"] = np.concatenate(g_n) if groups else np.zeros((1, 3))
    out["grp_ab"] = np.concatenate(g_ab) if groups else np.zeros((1, 2))
    out["grp_item"] = np.concatenate(g_item).astype(np.int32) if groups else np.zeros((1, 2), np.int32)
    out["mem_items"] = np.concatenate(m_items).astype(np.int32) if members else np.zeros(1, np.int32)
    if not len(out["face_plane"]):
        out["face_plane"] = np.zeros((1, 4))
    return out


def culling_struct(tables: dict, device: str = "cpu"):
    """The ``Culling`` struct (flowsynth.kernels.raycast) of ``culling_tables`` (or ``join_culling``) on ``device``."""
    from flowsynth.kernels.raycast import Culling

    wp = wp_runtime()
    types = {"face_plane": wp.vec4d, "face_off": wp.int32, "slab_n": wp.vec3d, "slab_lh": wp.vec2d,
             "sphere": wp.vec4d, "inner": wp.float64, "grp_item": wp.vec2i, "grp_off": wp.int32, "grp_n": wp.vec3d,
             "grp_ab": wp.vec2d, "mem_start": wp.int32, "mem_items": wp.int32, "sil": wp.vec4d, "sil_z": wp.float64}
    c = Culling()
    for name, dtype in types.items():
        setattr(c, name, wp.array(tables[name], dtype=dtype, device=device))
    return c


_HULLS: OrderedDict = register("culling.hulls", OrderedDict())


def hull_points(mesh: trimesh.Trimesh) -> np.ndarray:
    """Vertices of the convex hull of a mesh (cached per process): its posed box is the tight box.

    Qhull's hull vertices (with trimesh's options ``QHULL_DEFAULT``) in the order of the mesh's vertices: the
    rows of ``mesh.convex_hull.vertices`` on the built-in assets (tests/test_raycast.py), without building and
    repairing that hull mesh. Any set of the mesh's vertices holding every extreme point bounds the mesh
    exactly."""
    def hull():
        V = np.asarray(mesh.vertices, np.float64)
        if len(V) <= 64:
            return V
        try:
            return V[np.sort(ConvexHull(V, qhull_options=str(QHULL_DEFAULT)).vertices)]
        except (ValueError, IndexError, QhullError):  # flat/degenerate point sets: all vertices are exact too
            return V

    return _cached(_HULLS, _mesh_key(mesh), hull)


def _silhouette_planes(meshes: list[trimesh.Trimesh], cam_T_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per (frame, instance) of ``cam_T_obj`` (F, N, 4, 4): ``SIL_K`` planes through the camera centre, (unit n,
    h) with every point of the instance's convex hull in n . x <= h, and the hull's least depth z0.

    The planes' image lines take ``SIL_K`` directions a_k around the circle in normalised image coordinates
    (x / z, y / z), each touching the projected hull: n ~ (a_k, -c_k) with c_k the hull's largest a_k . (x /
    z, y / z); h is then recomputed as the largest n . x over the hull in float64 (~0). The hull is that of
    the float32 vertices the mesh queries use, posed in float64. An instance not wholly in front of the
    camera (z0 <= 0) gets z0 = -1 and planes that bound nothing (h = 1e300): no test (``beyond_silhouette``).
    Returns (F, N, SIL_K, 4) and (F, N) float64.
    """
    from flowsynth.kernels.raycast import SIL_K

    F, N = cam_T_obj.shape[:2]
    ang = 2.0 * np.pi * np.arange(SIL_K) / SIL_K
    A = np.stack([np.cos(ang), np.sin(ang)], 1)  # (K, 2)
    sil = np.zeros((F, N, SIL_K, 4))
    sil[..., 3] = 1e300
    z0 = np.full((F, N), -1.0)
    for n, m in enumerate(meshes):
        hull = hull_points(m).astype(np.float32).astype(np.float64)
        P = np.matmul(hull, np.swapaxes(cam_T_obj[:, n, :3, :3], 1, 2)) + cam_T_obj[:, n, None, :3, 3]  # (F, V, 3)
        zmin = P[..., 2].min(1)
        ok = zmin > 0
        if not ok.any():
            continue
        P = P[ok]
        c = np.matmul(P[..., :2] / P[..., 2:3], A.T).max(1)  # (f, K)
        nv = np.concatenate([np.broadcast_to(A, c.shape + (2,)), -c[..., None]], -1)
        nv /= np.linalg.norm(nv, axis=-1, keepdims=True)
        h = np.matmul(P, np.swapaxes(nv, 1, 2)).max(1)  # (f, K)
        sil[ok, n] = np.concatenate([nv, h[..., None]], -1)
        z0[ok, n] = zmin[ok]
    return sil, z0


_PLANES: OrderedDict = register("culling.face_planes", OrderedDict())


def _face_planes(mesh: trimesh.Trimesh, threads: int | None = None, device: str = "cpu") -> dict:
    """Exact bounds of a mesh for culling visibility rays, float64 from the float32 vertices the mesh
    queries use; cached per process like the asset BVHs. Keys:

    - ``planes`` (faces, 4): per face (unit normal n, e) with every vertex v in n . v <= e
      (``face_planes_kernel``, on the accel's device: e the max; above ``FACE_PLANES_BUDGET`` faces x vertices the
      bounding sphere's n . c + r); a degenerate face gets n = 0, e = 1e30 (never culls);
    - ``slab``: (n, lo, hi) with every vertex in lo <= n . v <= hi when the mesh is flat (``FLAT_REL``), else None;
    - ``sphere``: (centre, radius) holding every vertex;
    - ``inner``: radius of a ball about the same centre inside the solid, or 0: only for a closed,
      consistently outward-wound mesh whose every face plane has every vertex behind it (convex; the
      solid is then the intersection of the face half-spaces, and the ball the largest one in it, less
      the vertices' worst excess over their face planes).
    """
    return _cached(_PLANES, (str(device), _mesh_key(mesh)), lambda: _face_planes_of(mesh, threads, device))


def _face_planes_of(mesh: trimesh.Trimesh, threads: int | None = None, device: str = "cpu") -> dict:
    """``_face_planes``, computed (not cached); the face planes' kernel runs on ``device`` in bands over ``threads``
    threads (bit-identical for any count, ``flowsynth.parallel``); the planes come back to the host (numpy)."""
    from flowsynth.kernels.raycast import face_planes_kernel
    from flowsynth.parallel import BAND0, launch_bands

    wp = wp_runtime()
    V = np.asarray(mesh.vertices, np.float32)
    fc = np.asarray(mesh.faces, np.int32)
    V64 = V.astype(np.float64)
    centre = (V64.min(0) + V64.max(0)) / 2 if len(V64) else np.zeros(3)
    radius = float(np.linalg.norm(V64 - centre, axis=1).max()) if len(V64) else 0.0
    nrm = np.cross(V64[fc[:, 1]] - V64[fc[:, 0]], V64[fc[:, 2]] - V64[fc[:, 0]])
    area = np.linalg.norm(nrm, axis=1)
    if len(fc) * len(V) <= FACE_PLANES_BUDGET:
        out = wp.empty(len(fc), dtype=wp.vec4d, device=device)
        if len(fc):
            launch_bands(face_planes_kernel, (len(fc),), 0, [wp.array(V, dtype=wp.vec3, device=device),
                         wp.array(fc.reshape(-1), dtype=wp.int32, device=device), BAND0], [out], device, threads,
                         cost=len(V))
        planes = out.numpy()
    else:  # the sphere's bound n . c + r >= n . v for every vertex: looser (fewer culls), as exact
        n = nrm / np.where(area > 0, area, 1.0)[:, None]
        e = np.where(area > 0, n @ centre + radius * (1 + 1e-9), 1e30)
        planes = np.concatenate([n, e[:, None]], 1)
    res = {"planes": planes, "slab": None, "sphere": np.array([*centre, radius]), "inner": 0.0}
    if len(fc):
        f = int(np.argmax(area))
        if area[f] > 0:  # flat: within the slab of its largest face's plane (the float64 extent of n . v)
            n = nrm[f] / area[f]
            h = V64 @ n
            if h.max() - h.min() <= FLAT_REL * float(np.ptp(V64, axis=0).max()):
                res["slab"] = np.array([*n, h.min(), h.max()])
        ok = planes[:, 3] < 1e29
        own = np.einsum("fi,fi->f", planes[ok, :3], V64[fc[ok, 0]])  # each face's own offset n . a
        excess = float((planes[ok, 3] - own).max()) if ok.any() else np.inf
        if (res["slab"] is None and excess <= 1e-6 * radius and mesh.is_watertight and mesh.is_winding_consistent
                and mesh.volume > 0):
            res["inner"] = max(0.0, float((own - planes[ok, :3] @ centre).min()) - excess)
    return res


def _flat_groups(n_cam: np.ndarray, lh_cam: np.ndarray, flat_inst: np.ndarray):
    """The flat items of each frame grouped by slab normal (bitwise equal up to sign, camera frame): room
    walls make three groups of two. Per group g (normal n, sign chosen so its first non-zero component is
    positive) the interval (A, B) of n . x beyond every member's slab on the camera's side: A = max hi of
    the members the camera is above, B = min lo of those it is below (A = 1e300 when the camera is inside
    a member's slab: no shortcut). A segment from the camera (n . x = 0) to keep X with A + m < n . x < B - m
    at both ends misses every member. ``grp_item``: the one member above (below) the camera, else -2; a ray
    that leaves that member out (its own item) drops the bound A (B). Returns (grp_off (F + 1,), grp_n,
    grp_ab, grp_item, mem_start, mem_items) (CSR over groups, then over their members' global item indices)."""
    F, N = n_cam.shape[:2]
    g_off, g_n, g_ab, g_item, m_start, m_items = [0], [], [], [], [0], []
    for f in range(F):
        groups: dict[bytes, list] = {}
        for k in flat_inst:
            n, (lo, hi) = n_cam[f, k], lh_cam[f, k]
            nz = n[np.flatnonzero(n)]
            if len(nz) and nz[0] < 0:  # exact: negation commutes with rounding
                n, lo, hi = -n, -hi, -lo
            g = groups.setdefault(n.tobytes(), [n, -1e300, 1e300, [], [], []])
            item = f * N + int(k)
            if hi < 0:
                g[1] = max(g[1], hi)
                g[3].append(item)
            elif lo > 0:
                g[2] = min(g[2], lo)
                g[4].append(item)
            else:
                g[1] = 1e300
                g[3].extend((-2, -2))  # never a single member: no bound is dropped
            g[5].append(item)
        for n, a, b, above, below, members in groups.values():
            g_n.append(n)
            g_ab.append((a, b))
            g_item.append((above[0] if len(above) == 1 else -2, below[0] if len(below) == 1 else -2))
            m_items.extend(members)
            m_start.append(len(m_items))
        g_off.append(len(g_n))
    g_n = np.array(g_n) if g_n else np.zeros((1, 3))
    g_ab = np.array(g_ab) if g_ab else np.zeros((1, 2))
    g_item = np.array(g_item, np.int32) if g_item else np.zeros((1, 2), np.int32)
    m_items = np.array(m_items, np.int32) if m_items else np.zeros(1, np.int32)
    return np.array(g_off, np.int32), g_n, g_ab, g_item, np.array(m_start, np.int32), m_items
