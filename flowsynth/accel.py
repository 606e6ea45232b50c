"""Host side of the two-level ray caster: per-clip instance BVH over the assets' own trees (``flowsynth.blas``).

``SceneAccel`` takes F "frames" (camera pose + one pose per instance); frames need not be the clip's
frames (motion blur passes sub-frame times). All poses are composed in float64 here and handed to the
kernels as float32 ``obj_T_ref`` matrices relative to the frame's camera, so the float32 kernels only
ever see camera-relative coordinates: precision does not depend on the distance from the world origin.
"""

from __future__ import annotations

import hashlib
import weakref
from collections import OrderedDict

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError
from trimesh.convex import QHULL_DEFAULT

from flowsynth.blas import atlas
from flowsynth.caches import register
from flowsynth.errors import ConfigError
from flowsynth.kernels import wp_runtime
from flowsynth.meshes import freeze

# Up to this many instances per frame, camera rays walk candidate lists near to far instead of the BVH.
ORDERED_MAX = 64
# Primary rays take their candidate list from their TILE x TILE pixel screen tile (benchmarks/tiles.py:
# 1.30 Mrays/s with one list per frame, 1.48 with 16 px tiles, same hits; docs/decisions/0002-screen-tiles-16px.md).
TILE = 16  # a power of two: the kernels find a pixel's tile by a shift

__all__ = ["BOX_PAD_REL", "MESH_CACHE_SIZE", "SceneAccel", "pinhole", "resolve_device"]

# Maximum number of per-mesh hulls and face planes kept per process (least recently used are dropped).
MESH_CACHE_SIZE = 512
# A mesh is "flat" when it lies between two parallel planes (one of its face planes) closer than this
# fraction of its extent: visibility rays then test that slab (exact) before its box and mesh (room walls).
FLAT_REL = 1e-2
# Face planes' offsets e = max of n . v over every vertex cost faces x vertices (~3 ns each): above this
# product (built-in assets: <= 2.1e6) the bounding sphere's n . c + r stands in (an 82k-face icosphere:
# 9.2 s -> 0.05 s, measured once by hand).
FACE_PLANES_BUDGET = 2e7
# Instance boxes are inflated by this fraction of their size (plus the same fraction of their distance
# to the camera) so float32 rounding of the ray never culls a true hit.
BOX_PAD_REL = 1e-4

_KEYS: weakref.WeakKeyDictionary = register("accel.mesh_keys", weakref.WeakKeyDictionary())


def resolve_device(device) -> str:
    """The Warp device ``device`` names ("cpu", "cuda", "cuda:1", or a ``warp.Device``) as Warp's alias
    ("cpu", "cuda:0", ...). Raises ConfigError naming the device and the devices Warp finds when it has none such
    (e.g. "cuda" on a machine without a CUDA driver)."""
    wp = wp_runtime()
    try:
        return wp.get_device(device).alias
    except (RuntimeError, ValueError, TypeError) as e:
        found = [d.alias for d in wp.get_devices()]
        raise ConfigError(f"device {device!r} is not available: Warp finds {found} "
                          f"({wp.get_cuda_device_count()} CUDA device(s); {e}). Use device='cpu' or one of "
                          f"those") from None


def _mesh_key(mesh: trimesh.Trimesh) -> bytes:
    """Content hash of a mesh, computed once per mesh object, which is frozen first (``flowsynth.meshes.freeze``:
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


class SceneAccel:
    """Ray-casting structure for F frames of N instances.

    Args:
        meshes: N object-frame meshes (instances may share a mesh).
        cam_T_world: (F, 4, 4) float64.
        world_T_obj: (F, N, 4, 4) float64.
        device: Warp device ("cpu", the default; "cuda", "cuda:1", ... where Warp finds one: ``resolve_device``).
            Every array of the accel lives there.
    """

    def __init__(self, meshes: list[trimesh.Trimesh], cam_T_world: np.ndarray, world_T_obj: np.ndarray,
                 device: str = "cpu") -> None:
        """Build the per-frame instance boxes (camera frame), their near-to-far order and the grouped BVH."""
        wp = wp_runtime()
        F = cam_T_world.shape[0]
        N = len(meshes)
        device = resolve_device(device)
        self.F, self.N, self.device = F, N, device
        self.empty = N == 0
        if self.empty:
            return
        # cam_T_obj per (frame, instance), float64
        cam_T_obj = np.einsum("fij,fnjk->fnik", cam_T_world, world_T_obj)
        obj_T_cam = _rigid_inverse(cam_T_obj)
        lo = np.empty((F, N, 3))
        hi = np.empty((F, N, 3))
        scale = np.empty((F, N, 1))
        v_lo, v_hi = np.empty((N, 3)), np.empty((N, 3))  # object-frame boxes: those of the hull points
        for n, m in enumerate(meshes):  # tight boxes: the posed hull vertices, not the posed local box
            hull = _hull_points(m)
            v_lo[n], v_hi[n] = hull.min(0), hull.max(0)
            pts = np.matmul(hull, np.swapaxes(cam_T_obj[:, n, :3, :3], 1, 2)) + cam_T_obj[:, n, None, :3, 3]
            lo[:, n], hi[:, n] = pts.min(1), pts.max(1)
            scale[:, n, 0] = (hi[:, n] - lo[:, n]).max(-1) + np.abs(pts).max((1, 2))
        pad = BOX_PAD_REL * scale + 1e-30
        lowers = (lo - pad).reshape(-1, 3).astype(np.float32)
        uppers = (hi + pad).reshape(-1, 3).astype(np.float32)
        # distance from each frame's camera centre to each box, and the near-to-far visiting order
        near = np.linalg.norm(np.maximum(lo - pad, 0.0) + np.maximum(-(hi + pad), 0.0), axis=-1)
        order = np.argsort(near, axis=1, kind="stable") + (np.arange(F) * N)[:, None]
        self.near = wp.array((near * (1.0 - 1e-6)).reshape(-1).astype(np.float32), dtype=wp.float32, device=device)
        self._order_np, self._lo, self._hi = order, lo - pad, hi + pad
        self.frame_start = wp.array(np.arange(F + 1, dtype=np.int32) * N, dtype=wp.int32, device=device)
        self.frame_items = wp.array(order.reshape(-1).astype(np.int32), dtype=wp.int32, device=device)
        self.use_bvh = int(N > ORDERED_MAX)
        self._tiles: dict = {}
        self._bounds: dict = {}  # (W, H, K bytes) -> _screen_bounds
        groups = np.repeat(np.arange(F, dtype=np.int32), N)
        self.lowers = wp.array(lowers, dtype=wp.vec3, device=device)  # (F * N,) padded instance boxes, camera frame
        self.uppers = wp.array(uppers, dtype=wp.vec3, device=device)
        self._groups = wp.array(groups, dtype=wp.int32, device=device)
        self.bvh = wp.Bvh(self.lowers, self.uppers, constructor="sah" if wp.get_device(device).is_cpu else None,
                          groups=self._groups)
        roots = _group_roots(self.bvh, F, device)
        self.roots = roots
        distinct = {id(m): m for m in meshes}  # instances sharing a mesh share its tree
        slot = {k: i for i, k in enumerate(distinct)}
        self.blas = atlas(list(distinct.values()), device)
        which = [slot[id(m)] for m in meshes]
        self.item_root = wp.array(np.tile(self.blas["roots"][which], F), dtype=wp.int32, device=device)
        self.item_face0 = wp.array(np.tile(self.blas["face0"][which], F), dtype=wp.int32, device=device)
        self.obj_T_ref = wp.array(obj_T_cam.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=device)
        self.ref_T_obj = wp.array(cam_T_obj.reshape(-1, 4, 4).astype(np.float32), dtype=wp.mat44, device=device)
        self._meshes, self._cam_T_obj, self._cull = meshes, cam_T_obj, None
        # object-frame boxes, padded like the camera-frame ones (size plus the camera's farthest distance);
        # per item (tiled over the frames), so the kernels index them by item like every other array
        ext = v_hi - v_lo
        far = np.abs(obj_T_cam[..., :3, 3]).max((0, 2)) + np.abs(np.concatenate([v_lo, v_hi], 1)).max(1)
        o_pad = (BOX_PAD_REL * (ext.max(1) + far) + 1e-30)[:, None]
        thin = (ext.min(1) <= FLAT_REL * ext.max(1)).astype(np.int32)
        self.thin = wp.array(np.tile(thin, F), dtype=wp.int32, device=device)
        self.obj_lo = wp.array(np.tile((v_lo - o_pad).astype(np.float32), (F, 1)), dtype=wp.vec3, device=device)
        self.obj_hi = wp.array(np.tile((v_hi + o_pad).astype(np.float32), (F, 1)), dtype=wp.vec3, device=device)

    def instances(self):
        """The kernels' ``Instances`` struct (flowsynth.kernels.raycast) over this accel's arrays (no copy):
        every tracing kernel reads the scene from it."""
        from flowsynth.kernels.raycast import Instances

        inst = Instances()
        inst.bvh, inst.roots, inst.use_bvh = self.bvh.id, self.roots, self.use_bvh
        inst.frame_start, inst.frame_items, inst.near = self.frame_start, self.frame_items, self.near
        inst.lowers, inst.uppers = self.lowers, self.uppers
        inst.obj_T_ref, inst.ref_T_obj, inst.n_inst = self.obj_T_ref, self.ref_T_obj, self.N
        inst.thin, inst.obj_lo, inst.obj_hi = self.thin, self.obj_lo, self.obj_hi
        inst.item_root, inst.item_face0 = self.item_root, self.item_face0
        inst.blas_bounds, inst.blas_kids = self.blas["bounds"], self.blas["kids"]
        inst.blas_tris, inst.blas_face, inst.blas_slot = self.blas["tris"], self.blas["face"], self.blas["slot"]
        return inst

    def culling(self, threads: int | None = None):
        """The visibility rays' exact culling data: a ``Culling`` struct (flowsynth.kernels.raycast).

        Per face of every asset, its plane (unit normal n, e = max over the asset's vertices of n . v): the
        whole mesh lies in n . x <= e. The flat instances (``FLAT_REL``: room walls), and per (frame, item)
        of a flat instance the slab lo <= n . x <= hi holding it, in the frame's camera frame; per (frame, item)
        the ``SIL_K`` planes through the camera centre that bound its convex hull (``_silhouette_planes``). All float64,
        from the float32 vertices the mesh queries use. Visibility rays test the flat instances of their
        frame first, then walk ``tile_lists(camera, flat=False)``. ``threads``: those of the face planes'
        kernel on a mesh not yet cached (``_face_planes``; the result does not depend on it).
        """
        if self._cull is None:
            from flowsynth.kernels.raycast import Culling

            wp = wp_runtime()
            bounds = [_face_planes(m, threads, self.device) for m in self._meshes]
            planes, slabs = [b["planes"] for b in bounds], [b["slab"] for b in bounds]
            offsets = np.cumsum([0] + [len(p) for p in planes])[:-1]
            flat = np.array([s is not None for s in slabs])
            n_obj = np.array([s[:3] if s is not None else np.zeros(3) for s in slabs])  # (N, 3)
            lh = np.array([s[3:] if s is not None else (1.0, 0.0) for s in slabs])  # (N, 2); lo > hi: not flat
            F, N = self.F, self.N
            R, t = self._cam_T_obj[..., :3, :3], self._cam_T_obj[..., :3, 3]  # (F, N, 3, 3), (F, N, 3)
            n_cam = np.einsum("fnij,nj->fni", R, n_obj)
            shift = np.einsum("fni,fni->fn", n_cam, t)
            lh_cam = np.where(flat[None, :, None], lh[None] + shift[..., None], lh[None])
            c = Culling()
            c.face_plane = wp.array(np.concatenate(planes), dtype=wp.vec4d, device=self.device)
            c.face_off = wp.array(np.asarray(offsets, np.int32), dtype=wp.int32, device=self.device)
            c.slab_n = wp.array(n_cam.reshape(-1, 3), dtype=wp.vec3d, device=self.device)
            c.slab_lh = wp.array(lh_cam.reshape(-1, 2), dtype=wp.vec2d, device=self.device)
            sph = np.array([b["sphere"] for b in bounds])  # (N, 4)
            centre = np.einsum("fnij,nj->fni", R, sph[:, :3]) + t
            c.sphere = wp.array(np.concatenate([centre, np.broadcast_to(sph[:, 3], (F, N))[..., None]], -1)
                                .reshape(-1, 4), dtype=wp.vec4d, device=self.device)
            c.inner = wp.array(np.tile([b["inner"] for b in bounds], F), dtype=wp.float64, device=self.device)
            g_off, g_n, g_ab, g_item, m_start, m_items = _flat_groups(n_cam, lh_cam, np.flatnonzero(flat))
            c.grp_item = wp.array(g_item, dtype=wp.vec2i, device=self.device)
            c.grp_off = wp.array(g_off, dtype=wp.int32, device=self.device)
            c.grp_n = wp.array(g_n, dtype=wp.vec3d, device=self.device)
            c.grp_ab = wp.array(g_ab, dtype=wp.vec2d, device=self.device)
            c.mem_start = wp.array(m_start, dtype=wp.int32, device=self.device)
            c.mem_items = wp.array(m_items, dtype=wp.int32, device=self.device)
            sil, sil_z = _silhouette_planes(self._meshes, self._cam_T_obj)
            c.sil = wp.array(sil.reshape(-1, 4), dtype=wp.vec4d, device=self.device)
            c.sil_z = wp.array(sil_z.reshape(-1), dtype=wp.float64, device=self.device)
            self._cull, self._flat = c, flat
        return self._cull

    def tile_lists(self, camera, flat: bool = True, threads: int | None = None):
        """The primary cast's per-(frame, screen tile) candidate lists: a ``TileLists`` struct
        (flowsynth.kernels.raycast) holding the instances whose hull, clipped to z >= ``CLIP_Z``, projects within
        a pixel of each tile (``_screen_bounds``), near to far;
        ``flat=False``: without the flat instances of ``culling()`` (visibility rays test those apart; ``threads``:
        those of ``culling``)."""
        from flowsynth.kernels.raycast import TileLists

        wp = wp_runtime()
        key = (camera.width, camera.height, camera.K.tobytes(), flat, camera.model, camera.dist)
        if key not in self._tiles:
            if TILE <= 0 or TILE & (TILE - 1):
                raise ValueError(f"flowsynth.accel.TILE must be a power of two, got {TILE}")
            if self.use_bvh:
                start, items, tx, ty = np.zeros(2, np.int32), np.zeros(1, np.int32), 1, 1
            else:
                order = self._order_np
                if not flat:
                    self.culling(threads)
                    local = order - (np.arange(self.F) * self.N)[:, None]
                    keep = ~self._flat[local]  # (F, N): the same instances are flat in every frame
                    order = order[keep].reshape(self.F, -1)
                kb = key[:3] + key[4:]
                if camera.is_pinhole:
                    if kb not in self._bounds:
                        self._bounds[kb] = _screen_bounds(self._meshes, self._cam_T_obj, camera.K)
                    start, items, tx, ty = _tile_lists(self._bounds[kb], order, camera.width, camera.height, TILE)
                else:  # a lens model: rays' normalised coordinates per tile against the hulls' (_lens_tile_mask)
                    if kb not in self._bounds:
                        self._bounds[kb] = _screen_bounds(self._meshes, self._cam_T_obj, np.eye(3))
                    mask = _lens_tile_mask(self._bounds[kb], order, camera, TILE)
                    start, items = _csr_lists(mask, order)
                    ty, tx = mask.shape[2:]
            t = TileLists()
            t.start = wp.array(start, dtype=wp.int32, device=self.device)
            t.items = wp.array(items if len(items) else np.zeros(1, np.int32), dtype=wp.int32, device=self.device)
            t.tiles_x, t.tiles_y, t.tile_shift = tx, ty, TILE.bit_length() - 1
            self._tiles[key] = t
        return self._tiles[key]


_HULLS: OrderedDict = register("accel.hulls", OrderedDict())


def _hull_points(mesh: trimesh.Trimesh) -> np.ndarray:
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
        hull = _hull_points(m).astype(np.float32).astype(np.float64)
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


_PLANES: OrderedDict = register("accel.face_planes", OrderedDict())


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


# Screen bounds of an instance's hull clip it at this depth [m]: the part nearer the camera plane is not seen.
CLIP_Z = 1e-9
# Hulls of up to this many points are clipped at CLIP_Z pair by pair (V^2 per frame); a larger hull reaching
# behind the camera plane gets every tile.
CLIP_MAX_POINTS = 64


def _screen_bounds(meshes: list[trimesh.Trimesh], cam_T_obj: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(F, N, 4) float64 (u_min, u_max, v_min, v_max) [px] of the projection of each instance's convex hull
    clipped to z >= ``CLIP_Z`` (camera frame of ``cam_T_obj`` (F, N, 4, 4)), NaN where nothing of it lies
    there. The clipped hull is the convex hull of its points with z >= CLIP_Z and of the points where the
    segments between a point in front and one behind cross z = CLIP_Z; perspective projection keeps convex
    sets convex, so the bounds of those points' projections bound every hit a camera ray can make. A hull
    of more than ``CLIP_MAX_POINTS`` points reaching behind the plane gets infinite bounds (every tile)."""
    F, N = cam_T_obj.shape[:2]
    out = np.full((F, N, 4), np.nan)
    for n, m in enumerate(meshes):
        P = np.matmul(_hull_points(m), np.swapaxes(cam_T_obj[:, n, :3, :3], 1, 2)) + cam_T_obj[:, n, None, :3, 3]
        z = P[..., 2]
        front = z >= CLIP_Z  # (F, V)
        pts, ok = P, front
        if not front.all() and P.shape[1] <= CLIP_MAX_POINTS:
            za, zb = z[:, :, None], z[:, None, :]
            cross = front[:, :, None] & ~front[:, None, :]  # (F, V, V): a in front, b behind
            s = np.where(cross, (za - CLIP_Z) / np.where(cross, za - zb, 1.0), 0.0)
            X = P[:, :, None] + s[..., None] * (P[:, None] - P[:, :, None])
            X[..., 2] = CLIP_Z
            pts = np.concatenate([P, X.reshape(F, -1, 3)], 1)
            ok = np.concatenate([front, cross.reshape(F, -1)], 1)
        zz = np.where(ok, pts[..., 2], 1.0)
        u = (K[0, 0] * pts[..., 0] + K[0, 1] * pts[..., 1]) / zz + K[0, 2]
        v = K[1, 1] * pts[..., 1] / zz + K[1, 2]
        b = np.stack([np.where(ok, u, np.inf).min(1), np.where(ok, u, -np.inf).max(1),
                      np.where(ok, v, np.inf).min(1), np.where(ok, v, -np.inf).max(1)], -1)
        if not front.all() and P.shape[1] > CLIP_MAX_POINTS:
            b[~front.all(1)] = (-np.inf, np.inf, -np.inf, np.inf)
        out[:, n] = np.where(ok.any(1)[:, None], b, np.nan)
    return out


def _tile_lists(bounds: np.ndarray, order: np.ndarray, W: int, H: int,
                tile: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """CSR lists (start, items) of the instances whose screen ``bounds`` (F, N, 4) (``_screen_bounds``, one
    pixel of margin) touch each screen tile, in near-to-far ``order`` (F, N) of global item indices."""
    F, N, _ = bounds.shape
    tx, ty = -(-W // tile), -(-H // tile)
    seen = ~np.isnan(bounds[..., 0])
    b = np.where(seen[..., None], bounds, 0.0)
    j0 = (np.floor(b[..., 0]) - 1).clip(0, W - 1).astype(np.int64) // tile
    j1 = (np.ceil(b[..., 1]) + 1).clip(0, W - 1).astype(np.int64) // tile
    i0 = (np.floor(b[..., 2]) - 1).clip(0, H - 1).astype(np.int64) // tile
    i1 = (np.ceil(b[..., 3]) + 1).clip(0, H - 1).astype(np.int64) // tile
    offscreen = ~seen | (b[..., 1] < -1) | (b[..., 0] > W) | (b[..., 3] < -1) | (b[..., 2] > H)
    local = order - (np.arange(F) * N)[:, None]  # (F, N) instance index, near to far
    i0, i1, j0, j1, offscreen = (np.take_along_axis(a, local, axis=1)[..., None, None]
                                 for a in (i0, i1, j0, j1, offscreen))
    ti = np.arange(ty)[None, None, :, None]
    tj = np.arange(tx)[None, None, None, :]
    mask = (ti >= i0) & (ti <= i1) & (tj >= j0) & (tj <= j1) & ~offscreen  # (F, N near to far, ty, tx)
    start, items = _csr_lists(mask, order)
    return start, items, tx, ty


def _csr_lists(mask: np.ndarray, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists (start, items) of ``mask`` (F, N near to far, ty, tx): per (frame, tile) row-major, the global
    item indices ``order`` (F, N) of the instances it holds, near to far."""
    F, _, ty, tx = mask.shape
    f, y, x, k = np.nonzero(mask.transpose(0, 2, 3, 1))  # row-major: near to far within each tile
    items = order[f, k].astype(np.int32)
    counts = np.bincount((f * ty + y) * tx + x, minlength=F * ty * tx)
    start = np.zeros(F * ty * tx + 1, np.int32)
    start[1:] = np.cumsum(counts)
    return start, items


# Lens cameras: candidate lists from the rays' normalised coordinates (``_lens_tile_mask``); False gives every
# instance to every tile (the brute-force lists tests/test_lens.py compares against).
LENS_TILE_BOUNDS = True
# Rings of pixel centres around a tile whose rays bound its box (``_lens_tile_mask``): one for the shading
# kernel's sub-pixel stencils, one for visibility rays that land within half a pixel of a centre.
LENS_TILE_RING = 2


def _lens_tile_mask(nbounds: np.ndarray, order: np.ndarray, camera, tile: int) -> np.ndarray:
    """(F, N' near to far, ty, tx) bool: instance ``order[f, k]`` may be hit by a ray of tile (y, x) of a lens
    camera.

    A ray from the camera centre that hits an instance has its normalised coordinates (a, b) = (x / z, y / z) in
    the box ``nbounds`` (F, N, 4) of the instance's clipped hull (``_screen_bounds`` with K = I: a pinhole of unit
    focal length, exact for any ray with z > 0). A tile's box bounds (a, b) of the covered rays of its pixel
    centres and of ``LENS_TILE_RING`` rings around them (``Camera.ray_grid``), padded by the largest step of (a, b)
    between adjacent centres there: the rays the kernels cast for a tile are the pixel centres' (the primary
    cast: inside by construction), convex combinations of four neighbouring centres' rays (the shading kernel's
    sub-pixel samples: a bilinear blend of rays keeps (a, b) in the convex hull of theirs) and rays through
    points within half a pixel of a centre (the pair kernel's visibility rays: the image of a pixel cell bows out
    of its corners' box by far less than one step unless the lens folds there). A tile whose rings hold both
    covered and uncovered centres (the edge of the lens's image, where the unprojection's slope is unbounded)
    gets every instance; one that holds only uncovered centres gets none (no ray there hits anything)."""
    from scipy.ndimage import maximum_filter, minimum_filter

    F, N = nbounds.shape[:2]
    H, W = camera.height, camera.width
    p = LENS_TILE_RING
    R = camera.ray_grid(p)
    cov = R[..., 2] > 0
    z = np.where(cov, R[..., 2], 1.0)
    ab = [np.where(cov, R[..., c] / z, np.nan) for c in (0, 1)]
    step = np.zeros(cov.shape)
    for c in (0, 1):
        for axis in (0, 1):
            d = np.abs(np.diff(ab[c], axis=axis))
            d = np.where(np.isnan(d), 0.0, d)
            lo = [slice(None), slice(None)]
            lo[axis] = slice(0, -1)
            step[tuple(lo)] = np.maximum(step[tuple(lo)], d)
            hi = [slice(None), slice(None)]
            hi[axis] = slice(1, None)
            step[tuple(hi)] = np.maximum(step[tuple(hi)], d)
    size = 2 * p + 1
    ty, tx = -(-H // tile), -(-W // tile)

    def blocks(x: np.ndarray, fill: float, reduce) -> np.ndarray:
        """(ty, tx) ``reduce`` over each tile of (H, W) ``x`` (the image padded to whole tiles with ``fill``)."""
        full = np.full((ty * tile, tx * tile), fill)
        full[:H, :W] = x
        return reduce(reduce(full.reshape(ty, tile, tx, tile), axis=3), axis=1)

    inner = (slice(p, p + H), slice(p, p + W))
    box = []
    for c in (0, 1):
        box.append(blocks(minimum_filter(np.where(cov, ab[c], np.inf), size, mode="nearest")[inner], np.inf, np.min))
        box.append(blocks(maximum_filter(np.where(cov, ab[c], -np.inf), size, mode="nearest")[inner], -np.inf,
                          np.max))
    pad = blocks(maximum_filter(step, size, mode="nearest")[inner], 0.0, np.max)
    some = blocks(maximum_filter(cov, size, mode="nearest")[inner], False, np.max)
    edge = some & blocks(maximum_filter(~cov, size, mode="nearest")[inner], False, np.max)
    a0, a1, b0, b1 = box[0] - pad, box[1] + pad, box[2] - pad, box[3] + pad
    a0, b0 = np.where(edge, -np.inf, a0), np.where(edge, -np.inf, b0)
    a1, b1 = np.where(edge, np.inf, a1), np.where(edge, np.inf, b1)
    if not LENS_TILE_BOUNDS:
        a0, b0, a1, b1 = (np.full((ty, tx), v) for v in (-np.inf, -np.inf, np.inf, np.inf))
        some = np.ones((ty, tx), bool)
    local = order - (np.arange(F) * N)[:, None]
    nb = np.take_along_axis(nbounds, local[..., None], axis=1)[..., None, None, :]  # (F, N', 1, 1, 4)
    seen = ~np.isnan(nb[..., 0])
    return (seen & some & (nb[..., 0] <= a1) & (nb[..., 1] >= a0) & (nb[..., 2] <= b1) & (nb[..., 3] >= b0))


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def _group_roots(bvh, F: int, device: str):
    from flowsynth.kernels.raycast import group_roots_kernel

    wp = wp_runtime()
    roots = wp.zeros(F, dtype=wp.int32, device=device)
    wp.launch(group_roots_kernel, dim=F, inputs=[bvh.id], outputs=[roots], device=device)
    return roots


def pinhole(camera, device: str = "cpu", pad: int = 0):
    """The kernels' ``Pinhole`` struct of a camera's K (and a lens model's per-pixel rays, on ``device``; with
    ``pad`` > 0 those of ``Camera.ray_grid(pad)``, rows and columns -pad .. H - 1 + pad, for the shading kernel)."""
    from flowsynth.kernels.raycast import Pinhole

    wp = wp_runtime()
    K = camera.K
    p = Pinhole()
    p.intr = wp.vec4(K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    p.skew = float(K[0, 1])
    if not camera.is_pinhole:  # a lens model's rays, uploaded once per camera, pad and device (cached)
        key = (str(device), K.tobytes(), camera.width, camera.height, camera.model, camera.dist, int(pad))
        rays = _RAYS.get(key)
        if rays is None:
            rays = _RAYS[key] = _ray_array(camera, device, pad)
            while len(_RAYS) > RAY_CACHE_SIZE:
                _RAYS.popitem(last=False)
        _RAYS.move_to_end(key)
        p.rays = rays
    return p


# Lens cameras' ray arrays kept per process (per camera, pad and device; least recently used dropped), as
# flowsynth.camera keeps their numpy rays.
RAY_CACHE_SIZE = 16
_RAYS: OrderedDict = register("accel.lens_ray_arrays", OrderedDict())


def _ray_array(camera, device: str, pad: int):
    """A lens camera's ``ray_grid(pad)`` as a float32 vec3 Warp array on ``device``; uncovered pixels get
    (0, 0, -1): no hit."""
    wp = wp_runtime()
    rays = camera.ray_grid(pad).astype(np.float32)
    rays[rays[..., 2] <= 0] = (0.0, 0.0, -1.0)
    return wp.array(rays, dtype=wp.vec3, device=device)
