"""Bottom level of the ray caster: a 4-wide BVH per asset mesh, built in numpy, traversed by
``flowsynth.kernels.blas``.

Why not ``wp.Mesh``: on one CPU core its ``mesh_query_ray`` is a binary-tree walk that tests child boxes one
at a time; this 4-wide tree tests a node's four child boxes as ``vec4`` slabs (SSE), keeps each stack entry's
entry distance (entries beyond the best hit are dropped on pop) and stores the triangles in leaf order.
benchmarks/speed/bvh.py measures the two side by side on the same rays (same hits;
docs/decisions/0001-per-asset-bvh4.md).

Build: binned SAH (``BINS`` bins, leaves of at most ``LEAF`` triangles) one tree level at a time (one numpy
call per level, not per node), then the binary tree is collapsed to 4 wide by opening the child of largest
surface area. The build is the expensive part (tens of ms for 5k faces), so only the tree's *topology* (node
children, leaf triangle order) is cached, keyed by the faces and the vertices up to scale: the scaled copies
``flowsynth.scene.assets.get_asset`` makes of one shape share one build. Every mesh then gets its own boxes by a
refit from its float32 vertices (exact float32 min/max, so boxes hold their triangles exactly).

Layout (one scene: the assets' trees concatenated by ``atlas``):

- ``bounds`` (6 * nodes,) vec4: rows lo_x, lo_y, lo_z, hi_x, hi_y, hi_z of node k at 6k .. 6k + 5, lane j =
  child j (an empty child: an empty box, lo 1e30 > hi -1e30);
- ``kids`` (nodes,) vec4i: child code, >= 0 an inner node, -1 empty, <= -2 a leaf: c = -2 - code, first
  triangle c >> 3, count c & 7;
- ``tris`` (3 * triangles,) vec3: the triangle's float32 vertices (a, b, c) in leaf order;
- ``face`` (triangles,) int32: the mesh's face index of each triangle, and ``slot`` the inverse (each face's
  triangle; a mesh's faces from its ``face0`` on): the kernels read a face's vertices there, no ``wp.Mesh``;
- an asset's root is a child code (a mesh of at most ``LEAF`` faces has a leaf root).
"""

from __future__ import annotations

import hashlib
import weakref
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from flowsynth.caches import register
from flowsynth.errors import AssetError
from flowsynth.scene import freeze

__all__ = ["BINS", "LEAF", "atlas", "build_topology", "topology"]

BINS = 16  # SAH bins per axis and node
LEAF = 4  # most triangles in a leaf (LEAF_BITS bits of the leaf code)
LEAF_BITS = 3
TOPOLOGY_CACHE_SIZE = 256  # distinct faces arrays kept (least recently used dropped)
_TOPOLOGY: OrderedDict = register("blas.topology", OrderedDict())


def leaf_code(first, count):
    """Child code of a leaf of ``count`` triangles from ``first`` (arrays or ints)."""
    return -2 - ((np.asarray(first, np.int64) << LEAF_BITS) | np.asarray(count, np.int64))


def _shift(code, n_nodes: int, n_tris: int) -> np.ndarray:
    """Child codes (array or int) of one tree moved into an atlas after ``n_nodes`` nodes and ``n_tris``
    triangles: inner nodes shifted by the one, leaves' first triangles by the other, empty slots kept."""
    code = np.asarray(code, np.int64)
    c = -2 - code
    moved = leaf_code((c >> LEAF_BITS) + n_tris, c & ((1 << LEAF_BITS) - 1))
    return np.where(code <= -2, moved, np.where(code >= 0, code + n_nodes, code))


@dataclass(frozen=True)
class Topology:
    """A 4-wide tree without boxes: ``kids`` (n, 4) int64 child codes (node 0 the root when n > 0), ``order``
    (M,) the mesh's face of each leaf slot, ``levels`` inner nodes grouped by depth (deepest last), ``root``
    the root's child code."""

    kids: np.ndarray
    order: np.ndarray
    levels: tuple
    root: int


def _area(lo, hi):
    d = np.maximum(hi - lo, 0.0)
    return d[..., 0] * d[..., 1] + d[..., 1] * d[..., 2] + d[..., 2] * d[..., 0]


def _binary_sah(tlo: np.ndarray, thi: np.ndarray):
    """Binned-SAH binary tree over triangle boxes (tlo, thi) (M, 3), built level by level. Returns (left,
    right, start, count, perm, lo, hi): children (-1 for leaves), leaves' slot ranges, the face of each slot
    and the node boxes."""
    M = len(tlo)
    cen = 0.5 * (tlo + thi)
    B = BINS
    cap = 2 * M + 1
    left = np.full(cap, -1, np.int64)
    right = np.full(cap, -1, np.int64)
    start = np.zeros(cap, np.int64)
    count = np.zeros(cap, np.int64)
    lo, hi = np.empty((cap, 3)), np.empty((cap, 3))
    perm = np.arange(M, dtype=np.int64)
    seg_node, seg_start, seg_end = np.array([0]), np.array([0]), np.array([M])
    n_nodes = 1
    while len(seg_node):
        lens = seg_end - seg_start
        at = np.concatenate([[0], np.cumsum(lens)[:-1]])
        elems = perm[np.arange(int(lens.sum())) - np.repeat(at - seg_start, lens)]
        lo[seg_node] = np.minimum.reduceat(tlo[elems], at, axis=0)
        hi[seg_node] = np.maximum.reduceat(thi[elems], at, axis=0)
        leaf = lens <= LEAF
        start[seg_node[leaf]], count[seg_node[leaf]] = seg_start[leaf], lens[leaf]
        s_idx = np.nonzero(~leaf)[0]
        if not len(s_idx):
            break
        S = len(s_idx)
        lens2, st, en = lens[s_idx], seg_start[s_idx], seg_end[s_idx]
        offs = np.concatenate([[0], np.cumsum(lens2)[:-1]])
        e_seg = np.repeat(np.arange(S), lens2)
        e_pos = np.arange(int(lens2.sum())) - offs[e_seg] + st[e_seg]
        e_el = perm[e_pos]
        c = cen[e_el]
        cmin = np.minimum.reduceat(c, offs, axis=0)
        cmax = np.maximum.reduceat(c, offs, axis=0)
        ext = cmax - cmin
        scale = np.where(ext > 0, B * (1.0 - 1e-9) / np.where(ext > 0, ext, 1.0), 0.0)
        bins = np.clip(((c - cmin[e_seg]) * scale[e_seg]).astype(np.int64), 0, B - 1)  # (n, 3)
        key = ((e_seg[:, None] * 3 + np.arange(3)) * B + bins).ravel()
        nk = S * 3 * B
        cnt = np.bincount(key, minlength=nk).reshape(S, 3, B)
        blo = np.full((nk, 3), np.inf)
        bhi = np.full((nk, 3), -np.inf)
        np.minimum.at(blo, key, np.repeat(tlo[e_el], 3, axis=0))
        np.maximum.at(bhi, key, np.repeat(thi[e_el], 3, axis=0))
        blo, bhi = blo.reshape(S, 3, B, 3), bhi.reshape(S, 3, B, 3)
        # split k (1 .. B-1): bins [0, k) go left
        llo = np.minimum.accumulate(blo, axis=2)[:, :, :-1]
        lhi = np.maximum.accumulate(bhi, axis=2)[:, :, :-1]
        lcnt = np.cumsum(cnt, axis=2)[:, :, :-1]
        rlo = np.minimum.accumulate(blo[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1:]
        rhi = np.maximum.accumulate(bhi[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1:]
        rcnt = np.cumsum(cnt[:, :, ::-1], axis=2)[:, :, ::-1][:, :, 1:]
        with np.errstate(invalid="ignore"):
            cost = lcnt * np.where(lcnt > 0, _area(llo, lhi), 0.0) + rcnt * np.where(rcnt > 0, _area(rlo, rhi), 0.0)
        cost = np.where((lcnt > 0) & (rcnt > 0), cost, np.inf).reshape(S, -1)
        best = np.argmin(cost, axis=1)
        axis, ksplit = best // (B - 1), best % (B - 1) + 1
        goes_right = bins[np.arange(len(e_seg)), axis[e_seg]] >= ksplit[e_seg]
        stuck = ~np.isfinite(cost[np.arange(S), best])  # every centroid in one bin: split the slots in half
        if stuck.any():
            rank = np.arange(len(e_seg)) - offs[e_seg]
            goes_right = np.where(stuck[e_seg], rank >= lens2[e_seg] // 2, goes_right)
        perm[e_pos] = e_el[np.argsort(e_seg * 2 + goes_right, kind="stable")]
        n_left = np.bincount(e_seg, weights=~goes_right, minlength=S).astype(np.int64)
        lid = n_nodes + 2 * np.arange(S)
        n_nodes += 2 * S
        left[seg_node[s_idx]], right[seg_node[s_idx]] = lid, lid + 1
        mid = st + n_left
        seg_node = np.concatenate([lid, lid + 1])
        seg_start, seg_end = np.concatenate([st, mid]), np.concatenate([mid, en])
    n = n_nodes
    return left[:n], right[:n], start[:n], count[:n], perm, lo[:n], hi[:n]


def build_topology(vertices: np.ndarray, faces: np.ndarray) -> Topology:
    """The 4-wide tree of a mesh (vertices (V, 3), faces (M, 3), M >= 1), without boxes."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    tlo, thi = tri.min(1), tri.max(1)
    L, R, start, count, perm, lo, hi = _binary_sah(tlo, thi)
    if L[0] < 0:
        return Topology(np.zeros((0, 4), np.int64), perm, (), int(leaf_code(0, count[0])))
    area = _area(lo, hi)  # which child to open when collapsing
    nodes, kids4, depth = [], {}, {0: 0}
    stack = [0]
    while stack:  # depth-first: a node's children get larger indices than the node
        n = stack.pop()
        ch = [L[n], R[n]]
        while len(ch) < 4:
            inner = [(area[c], i) for i, c in enumerate(ch) if L[c] >= 0]
            if not inner:
                break
            i = max(inner)[1]
            c = ch.pop(i)
            ch[i:i] = [L[c], R[c]]
        kids4[n] = ch
        nodes.append(n)
        for c in reversed(ch):
            if L[c] >= 0:
                depth[c] = depth[n] + 1
                stack.append(c)
    index = {n: i for i, n in enumerate(nodes)}
    kids = np.full((len(nodes), 4), -1, np.int64)
    for i, n in enumerate(nodes):
        for j, c in enumerate(kids4[n]):
            kids[i, j] = index[c] if L[c] >= 0 else int(leaf_code(start[c], count[c]))
    d = np.array([depth[n] for n in nodes])
    levels = tuple(np.nonzero(d == k)[0] for k in range(d.max() + 1))
    return Topology(kids, perm, levels, 0)


def topology(vertices: np.ndarray, faces: np.ndarray) -> Topology:
    """The cached tree of a mesh's shape (built on a miss): a mesh whose faces equal a cached one's and whose
    vertices, over their largest |coordinate|, agree with its within 1e-5 shares its tree (the scaled copies
    ``flowsynth.scene.assets.get_asset`` makes of one shape). Refitting (``atlas``) makes any shared tree exact."""
    v = np.asarray(vertices, np.float64)
    f = np.ascontiguousarray(faces, np.int64).reshape(-1, 3)
    if not len(f):
        raise AssetError("a BVH needs at least one face")
    s = np.abs(v).max()
    unit = v / (s if s > 0 else 1.0)
    key = hashlib.blake2b(f.tobytes(), digest_size=16).digest()
    for cand, top in _TOPOLOGY.get(key, ()):
        if cand.shape == unit.shape and np.allclose(cand, unit, rtol=0.0, atol=1e-5):
            _TOPOLOGY.move_to_end(key)
            return top
    from flowsynth.kernels.blas import STACK

    top = build_topology(v, f)
    if 3 * len(top.levels) + 1 > STACK:
        raise AssetError(f"a mesh of {len(f)} faces gives a BVH of depth {len(top.levels)}: more than the "
                         f"ray stack of {STACK} entries holds")
    _TOPOLOGY.setdefault(key, []).append((unit, top))
    _TOPOLOGY.move_to_end(key)
    while len(_TOPOLOGY) > TOPOLOGY_CACHE_SIZE:
        _TOPOLOGY.popitem(last=False)
    return top


_OF_MESH: weakref.WeakKeyDictionary = register("blas.topology_of_mesh", weakref.WeakKeyDictionary())


def _topology_of(mesh, v: np.ndarray, f: np.ndarray) -> Topology:
    """``topology(v, f)`` of ``mesh`` (its float32 vertices and faces), remembered per mesh object: a mesh object
    seen in an earlier scene skips the face hash and vertex comparison. The mesh is frozen when it is remembered
    (``flowsynth.scene.meshes.freeze``: changing it afterwards raises instead of reusing a stale tree); objects that
    take no weak reference are not remembered."""
    return _per_mesh(_OF_MESH, mesh, lambda: topology(v, f))


def _per_mesh(cache: weakref.WeakKeyDictionary, mesh, make):
    """``make()`` remembered in ``cache`` per mesh object, the mesh frozen when remembered
    (``flowsynth.scene.meshes.freeze``); an object that takes no weak reference is not remembered."""
    try:
        got = cache.get(mesh)
    except TypeError:
        return make()
    if got is None:
        got = cache[freeze(mesh)] = make()
    return got


def atlas(meshes: list, device: str = "cpu") -> dict:
    """The trees of a scene's distinct meshes (trimesh or anything with ``vertices`` and ``faces``) in one set
    of Warp arrays (module docstring layout): each mesh's cached topology, its inner-node codes shifted by its
    node offset and its leaf codes by its triangle offset, its triangles gathered from its float32 vertices,
    and every box refitted (``refit_kernel``). Returns {"bounds", "kids", "tris", "face", "slot"} Warp arrays
    ("slot": each face's triangle in leaf order, faces of mesh m from "face0"[m] on) and numpy int32 "roots"
    (the root code of each mesh's tree) and "face0"."""
    from flowsynth.kernels import wp_runtime
    from flowsynth.kernels.blas import refit_kernel

    wp = wp_runtime()
    kids, tris, face, roots, face0 = [], [], [], [], []
    n_nodes = n_tris = 0
    for m in meshes:
        v = np.asarray(m.vertices, np.float32)
        f = np.asarray(m.faces, np.int64).reshape(-1, 3)
        top = _topology_of(m, v, f)
        kids.append(_shift(top.kids, n_nodes, n_tris))
        roots.append(int(_shift(top.root, n_nodes, n_tris)))
        tris.append(v[f[top.order]].reshape(-1, 3))
        face.append(top.order)
        face0.append(n_tris)
        n_nodes += len(top.kids)
        n_tris += len(top.order)
    if n_tris >= 1 << (31 - LEAF_BITS):
        raise AssetError(f"a scene of {n_tris} triangles is more than a leaf code holds")
    k = np.concatenate(kids).astype(np.int32) if n_nodes else np.zeros((0, 4), np.int32)
    slot = np.empty(n_tris, np.int32)
    for f0, order in zip(face0, face):
        slot[f0 + order] = f0 + np.arange(len(order), dtype=np.int32)
    out = {"kids": wp.array(k, dtype=wp.vec4i, device=device),
           "tris": wp.array(np.concatenate(tris), dtype=wp.vec3, device=device),
           "face": wp.array(np.concatenate(face).astype(np.int32), dtype=wp.int32, device=device),
           "slot": wp.array(slot, dtype=wp.int32, device=device),
           "bounds": wp.empty(6 * n_nodes, dtype=wp.vec4, device=device), "roots": np.asarray(roots, np.int32),
           "face0": np.asarray(face0, np.int32)}
    if n_nodes:
        wp.launch(refit_kernel, dim=1, inputs=[out["kids"], out["tris"]], outputs=[out["bounds"]], device=device)
    return out


SMOOTH_CREASE_DEG = 60.0
"""Corner normals (smooth shading) average the faces around a vertex whose normals are within this angle [deg] of
the corner's own face: a box's 90-degree edges stay sharp, a sphere or a cylinder's side of 8 or more segments
shades round."""
_CORNERS: weakref.WeakKeyDictionary = register("blas.corner_normals_of_mesh", weakref.WeakKeyDictionary())


def corner_normals(mesh, crease_deg: float = SMOOTH_CREASE_DEG) -> np.ndarray:
    """(F, 3, 3) float32 unit normal at each corner k of each face f of ``mesh`` (the corner at vertex
    ``faces[f, k]``): the area-weighted mean of the normals of the faces that share the corner's position (vertices
    at one position count as one, so a mesh split at seams still shades smooth) and lie within ``crease_deg`` of
    face f's normal. A face of zero area joins no mean; its corners get the mean of nothing near, (0, 0, 1).
    Remembered per mesh object (``_per_mesh``) at the default crease; another crease is computed afresh."""
    if crease_deg != SMOOTH_CREASE_DEG:
        return _corner_normals(mesh, crease_deg)
    return _per_mesh(_CORNERS, mesh, lambda: _corner_normals(mesh, crease_deg))


def _corner_normals(mesh, crease_deg: float) -> np.ndarray:
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int64).reshape(-1, 3)
    F = len(f)
    _, pos = np.unique(np.round(v, 9), axis=0, return_inverse=True)  # one id per position
    pos = pos.reshape(-1)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # twice the area times the unit normal
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    unit = np.divide(fn, length, out=np.zeros_like(fn), where=length > 0)
    corner_pos = pos[f].reshape(-1)  # (3F,) the position id of every corner
    face_of = np.repeat(np.arange(F), 3)
    order = np.argsort(corner_pos, kind="stable")
    sorted_pos = corner_pos[order]
    start = np.searchsorted(sorted_pos, sorted_pos, "left")  # each sorted corner's group start
    count = np.bincount(corner_pos)[sorted_pos]
    acc = np.zeros((3 * F, 3))
    cos_crease = np.cos(np.radians(crease_deg))
    for d in range(int(count.max(initial=0))):  # the d-th corner of each corner's group
        ok = d < count
        ci, cj = order[ok], order[start[ok] + d]
        fi, fj = face_of[ci], face_of[cj]
        near = np.einsum("ij,ij->i", unit[fi], unit[fj]) >= cos_crease
        acc[ci[near]] += fn[fj[near]]  # each corner appears once per d: no repeated index
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    out = np.where(norm > 0, acc / np.where(norm > 0, norm, 1.0), np.repeat(unit, 3, axis=0))
    out[np.linalg.norm(out, axis=1) == 0] = (0.0, 0.0, 1.0)
    return out.reshape(F, 3, 3).astype(np.float32)
