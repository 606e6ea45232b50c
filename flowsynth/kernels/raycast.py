"""Two-level ray casting against rigid instances of cached per-asset meshes.

Top level: one grouped ``wp.Bvh`` over instance boxes, group f = frame f, boxes in that frame's
*reference* frame (the camera frame of frame f). Bottom level: one 4-wide BVH per asset in the object frame
(``flowsynth.raycast.blas``, traversed by ``flowsynth.kernels.blas``, which also holds every face's vertices). A ray
(origin o, unit direction d, reference frame) visits the instances whose box it
crosses, is mapped into each object's frame with ``obj_T_ref`` (float32, composed in float64 on the
host) and tested against that asset's mesh. Nothing is rebuilt when objects move.

Item index of instance n in frame f is ``f * N + n``. Kernels receive the scene as one ``Instances``
struct (filled by ``flowsynth.raycast.accel.SceneAccel.instances``): a new per-instance field is one new struct
member, read wherever it is needed.

Closest hit only for primary and path rays; visibility and shadow rays ask "is anything in the way"
(any hit: the first blocker ends the ray, ``trace_any`` / ``any_from_camera``).
"""

from __future__ import annotations

import warp as wp

from flowsynth.kernels.blas import blas_any, blas_closest, eval_position, face_vertices
from flowsynth.kernels.specialise import specialised_builder

__all__ = ["Culling", "Instances", "Pinhole", "TileLists", "primary_kernel", "tile_list", "trace_any",
           "trace_closest", "visibility_kernel"]


@wp.struct
class Instances:
    """F frames of rigid instances, as every tracing kernel reads them (flowsynth.raycast.accel.SceneAccel).

    Frame f's items are ``frame_start[f] .. frame_start[f + 1] - 1``, instance n of the frame's scene at item
    ``frame_start[f] + n``: one clip of N instances (item f N + n), or a batch of clips, frame b T + t of clip b
    (``SceneAccel.batch``)."""

    bvh: wp.uint64  # grouped top-level BVH over instance boxes, group f = frame f
    roots: wp.array[wp.int32]  # (F,) root node of each group
    use_bvh: wp.array[wp.int32]  # (F,) 0: the frame's camera rays walk the near-to-far candidate lists, not the BVH
    frame_start: wp.array[wp.int32]  # (F + 1,) CSR start of each frame's items (its first item, and frame_items')
    frame_items: wp.array[wp.int32]  # (F * N,) each frame's items, nearest box first
    near: wp.array[wp.float32]  # (F * N,) distance from the frame's camera centre to the item's box [m]
    lowers: wp.array[wp.vec3]  # (F * N,) item box, reference frame [m]
    uppers: wp.array[wp.vec3]
    item_root: wp.array[wp.int32]  # (F * N,) root code of the item's asset tree in the blas_* atlas
    item_face0: wp.array[wp.int32]  # (F * N,) first blas_slot row of the item's asset (its face 0)
    blas_bounds: wp.array[wp.vec4]  # the scene's asset trees (flowsynth.raycast.blas.atlas): child boxes,
    blas_kids: wp.array[wp.vec4i]  # child codes,
    blas_tris: wp.array[wp.vec3]  # triangles in leaf order,
    blas_face: wp.array[wp.int32]  # and each one's face index; blas_slot: each face's triangle
    blas_slot: wp.array[wp.int32]
    obj_T_ref: wp.array[wp.mat44]  # (F * N,) reference (camera) frame -> object frame
    ref_T_obj: wp.array[wp.mat44]  # (F * N,) object frame -> reference frame
    item_inst: wp.array[wp.int32]  # (items,) the item's row in per-instance tables (n; clip b's from its first row)
    thin: wp.array[wp.int32]  # (F * N,) 1: the item's object-frame box is thin (a room wall); rays test it first
    obj_lo: wp.array[wp.vec3]  # (F * N,) object-frame box of the item's mesh, padded [m]
    obj_hi: wp.array[wp.vec3]


@wp.struct
class TileLists:
    """Per (frame, TILE x TILE screen tile) candidate lists of the primary cast, near to far (CSR)."""

    start: wp.array[wp.int32]  # (F * tiles_y * tiles_x + 1,)
    items: wp.array[wp.int32]
    tiles_x: wp.int32
    tiles_y: wp.int32
    tile_shift: wp.int32  # log2 of the tile size [px] (a power of two: a shift, not an integer division)


@wp.func
def tile_list(tiles_x: wp.int32, tiles_y: wp.int32, tile_shift: wp.int32, f: wp.int32, i: wp.int32, j: wp.int32):
    """Index of the ``TileLists`` list of frame f's tile holding pixel (row i, col j), from the struct's scalars (a
    variant taking the struct whole costs the same: docs/decisions/0021-instances-struct-convention.md)."""
    return (f * tiles_y + (i >> tile_shift)) * tiles_x + (j >> tile_shift)


@wp.struct
class Culling:
    """Exact culling data of visibility rays (flowsynth.raycast.accel.SceneAccel.culling), float64.

    A mesh lying in a half-space (or slab) that the segment from the camera to the target point does not
    enter cannot block it: no mesh query is needed.
    """

    face_plane: wp.array[wp.vec4d]  # (faces of all assets,) (n, e): the asset's mesh lies in n . x <= e (object frame)
    face_off: wp.array[wp.int32]  # (N,) first face_plane row of instance n's asset
    slab_n: wp.array[wp.vec3d]  # (F * N,) flat items: slab normal, camera frame of the item's frame
    slab_lh: wp.array[wp.vec2d]  # (F * N,) slab (lo, hi) of n . x; lo > hi: not flat (no slab test)
    sphere: wp.array[wp.vec4d]  # (F * N,) (centre in the frame's camera frame, radius): holds the item's mesh
    inner: wp.array[wp.float64]  # (F * N,) radius of a ball about the same centre inside the closed mesh, or 0
    grp_off: wp.array[wp.int32]  # (F + 1,) frame f's flat-item groups are grp_off[f] .. grp_off[f + 1] - 1
    grp_n: wp.array[wp.vec3d]  # per group: the members' slab normal (one sign)
    grp_ab: wp.array[wp.vec2d]  # per group: (A, B), n . x in (A, B) is beyond every member's slab
    grp_item: wp.array[wp.vec2i]  # per group: the single member bounding A (B), else -2
    mem_start: wp.array[wp.int32]  # (groups + 1,) CSR of the groups' members
    mem_items: wp.array[wp.int32]  # members' global item indices
    sil: wp.array[wp.vec4d]  # (F * N * SIL_K,) (n, h): planes through the camera centre, unit n, hull in n . x <= h
    sil_z: wp.array[wp.float64]  # (F * N,) least depth z of the item's hull; <= 0: not wholly in front, no planes


# Planes per (frame, item) bounding the item's projected convex hull (SceneAccel.culling): their 16 directions
# in the image cut a 16-gon at most 1 / cos(pi / 16) - 1 = 2 % wider than the hull.
SIL_K = 16


@wp.func
def beyond_silhouette(sil: wp.array[wp.vec4d], sil_z: wp.array[wp.float64], item: wp.int32, X: wp.vec3d,
                      margin: wp.float64):
    """Does the segment from the camera centre to X (X.z > 0; any part of it up to X) stay farther than
    ``margin`` from item ``item``'s convex hull? Its points nearer than the hull's least depth z0 are (z < z0 -
    margin); beyond, along a plane (n, h) of ``Culling.sil``, n . (s X) is least at s0 = (z0 - margin) / X.z
    when n . X > 0, so s0 n . X > h + margin clears the rest."""
    z0 = sil_z[item] - margin
    if z0 <= wp.float64(0.0):
        return False
    for k in range(SIL_K):
        P = sil[item * SIL_K + k]
        nx = P[0] * X[0] + P[1] * X[1] + P[2] * X[2]
        if nx > wp.float64(0.0) and z0 * nx > (P[3] + margin) * X[2]:
            return True
    return False


@wp.struct
class Pinhole:
    """Pinhole intrinsics: intr = (fx, fy, cx, cy) [px], skew = K[0, 1]; for a lens model (flowsynth.scene.camera)
    ``rays`` (H, W) holds each pixel centre's unit ray (z < 0: uncovered pixel), read by ``primary_kernel``'s
    lens variant only."""

    intr: wp.vec4
    skew: wp.float32
    rays: wp.array2d[wp.vec3]


@wp.func
def thin_skip(thin: wp.array[wp.int32], obj_lo: wp.array[wp.vec3], obj_hi: wp.array[wp.vec3], item: wp.int32,
              o_obj: wp.vec3, d_obj: wp.vec3, max_t: wp.float32):
    """True when ``item`` is thin (``Instances.thin``: a wall, whose reference-frame box is loose) and the
    object-frame ray o_obj + t d_obj does not enter its padded object-frame box before max_t: no mesh query."""
    if thin[item] == 0:
        return False
    te = box_entry(obj_lo[item] - o_obj, obj_hi[item] - o_obj, d_obj)
    return te < 0.0 or te >= max_t


@wp.func
def trace_closest(inst: Instances, root: wp.int32, o: wp.vec3, d: wp.vec3, max_t: wp.float32):
    """Closest hit along o + t d, t in [0, max_t), below BVH node ``root`` (a frame's group root) of ``inst``'s
    top-level BVH. Returns (item or -1, t, face, u, v). A thin instance is mesh-queried only when the ray enters
    its object-frame box first (``thin_skip``). Takes ``Instances`` whole (docs/decisions/0021)."""
    best_t = max_t
    best_item = wp.int32(-1)
    best_face = wp.int32(-1)
    best_u = wp.float32(0.0)
    best_v = wp.float32(0.0)
    query = wp.bvh_query_ray(inst.bvh, o, d, root)
    item = wp.int32(0)
    while wp.bvh_query_next(query, item, best_t):
        X = inst.obj_T_ref[item]
        o_obj = wp.transform_point(X, o)
        d_obj = wp.transform_vector(X, d)
        if thin_skip(inst.thin, inst.obj_lo, inst.obj_hi, item, o_obj, d_obj, best_t):
            continue
        face, t, u, v = blas_closest(inst.blas_bounds, inst.blas_kids, inst.blas_tris, inst.blas_face,
                                     inst.item_root[item], o_obj, d_obj, best_t)
        if face >= 0:
            best_t = t
            best_item = item
            best_face = face
            best_u = u
            best_v = v
    return best_item, best_t, best_face, best_u, best_v


@wp.func
def trace_any(inst: Instances, root: wp.int32, o: wp.vec3, d: wp.vec3, max_t: wp.float32):
    """True when anything below BVH node ``root`` of ``inst``'s top-level BVH is hit along o + t d with t in
    [0, max_t) (first blocker ends the ray), skipping thin instances as ``trace_closest`` does."""
    query = wp.bvh_query_ray(inst.bvh, o, d, root)
    item = wp.int32(0)
    while wp.bvh_query_next(query, item, max_t):
        X = inst.obj_T_ref[item]
        o_obj = wp.transform_point(X, o)
        d_obj = wp.transform_vector(X, d)
        if thin_skip(inst.thin, inst.obj_lo, inst.obj_hi, item, o_obj, d_obj, max_t):
            continue
        if blas_any(inst.blas_bounds, inst.blas_kids, inst.blas_tris, inst.item_root[item], o_obj, d_obj, max_t):
            return True
    return False


@wp.func
def inverse_dir(d: wp.vec3):
    """(1 / d[a]) per axis, 0 where d[a] == 0 (``box_entry_inv`` tests those axes apart)."""
    inv = wp.vec3(0.0)
    for a in range(3):
        if d[a] != 0.0:
            inv[a] = 1.0 / d[a]
    return inv


@wp.func
def box_entry_inv(lo: wp.vec3, hi: wp.vec3, d: wp.vec3, inv: wp.vec3):
    """Entry distance of the ray 0 + t d (t >= 0) into box [lo, hi]; -1 when it misses. ``inv`` = inverse_dir(d),
    computed once per ray (no division per box)."""
    t0 = wp.float32(0.0)
    t1 = wp.float32(1.0e30)
    for a in range(3):
        if d[a] == 0.0:
            if lo[a] > 0.0 or hi[a] < 0.0:
                return wp.float32(-1.0)
        else:
            ta = lo[a] * inv[a]
            tb = hi[a] * inv[a]
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    if t0 > t1:
        return wp.float32(-1.0)
    return t0


@wp.func
def box_entry(lo: wp.vec3, hi: wp.vec3, d: wp.vec3):
    """Entry distance of the ray 0 + t d (t >= 0) into box [lo, hi]; -1 when it misses."""
    return box_entry_inv(lo, hi, d, inverse_dir(d))


@wp.func
def closest_from_camera(inst: Instances, g: wp.int32, start: wp.array[wp.int32], items: wp.array[wp.int32],
                        lst: wp.int32, d: wp.vec3, max_t: wp.float32):
    """``trace_closest`` for a ray leaving the camera centre of frame g, same result.

    With few instances (``use_bvh[g]`` = 0) the candidates of list ``lst`` of the CSR lists (start, items)
    (all the frame's instances, or those whose clipped hull projects onto the ray's screen tile) are visited near
    to far (sorted by ``near``) and the walk stops at the first box farther than the best hit: ~1.2 mesh
    queries per ray instead of one per box crossed.
    """
    if inst.use_bvh[g] != 0:
        return trace_closest(inst, inst.roots[g], wp.vec3(0.0), d, max_t)
    best_t = max_t
    best_item = wp.int32(-1)
    best_face = wp.int32(-1)
    best_u = wp.float32(0.0)
    best_v = wp.float32(0.0)
    inv = inverse_dir(d)
    for k in range(start[lst], start[lst + 1]):
        item = items[k]
        if inst.near[item] >= best_t:
            break
        X = inst.obj_T_ref[item]
        o = wp.vec3(X[0, 3], X[1, 3], X[2, 3])
        d_obj = wp.vec3(0.0)
        query = False
        if inst.thin[item] != 0:  # a wall's camera-frame box is loose, its object-frame box tight
            d_obj = wp.transform_vector(X, d)
            query = not thin_skip(inst.thin, inst.obj_lo, inst.obj_hi, item, o, d_obj, best_t)
        else:
            te = box_entry_inv(inst.lowers[item], inst.uppers[item], d, inv)
            if te >= 0.0 and te < best_t:
                d_obj = wp.transform_vector(X, d)
                query = True
        if query:
            face, t, u, v = blas_closest(inst.blas_bounds, inst.blas_kids, inst.blas_tris, inst.blas_face,
                                         inst.item_root[item], o, d_obj, best_t)
            if face >= 0:
                best_t = t
                best_item = item
                best_face = face
                best_u = u
                best_v = v
    return best_item, best_t, best_face, best_u, best_v


@wp.func
def any_in_list(near: wp.array[wp.float32], lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3],
                item_root: wp.array[wp.int32], bb: wp.array[wp.vec4], bk: wp.array[wp.vec4i], bt: wp.array[wp.vec3],
                obj_T_ref: wp.array[wp.mat44], items: wp.array[wp.int32],
                a: wp.int32, b: wp.int32, d: wp.vec3, max_t: wp.float32):
    """Any hit before ``max_t`` along the camera-centre ray ``d`` among ``items[a:b]`` (sorted nearest box
    first, so the walk stops at the first box that starts beyond ``max_t``). Takes the Instances arrays it
    reads, not the struct: a struct argument is copied per call."""
    for k in range(a, b):
        item = items[k]
        if near[item] >= max_t:
            break
        te = box_entry(lowers[item], uppers[item], d)
        if te >= 0.0 and te < max_t:
            X = obj_T_ref[item]
            if blas_any(bb, bk, bt, item_root[item], wp.vec3(X[0, 3], X[1, 3], X[2, 3]), wp.transform_vector(X, d),
                        max_t):
                return True
    return False


@wp.func
def any_from_camera(inst: Instances, g: wp.int32, d: wp.vec3, max_t: wp.float32):
    """``trace_any`` for a ray leaving the camera centre of frame g: the frame's instances near to far,
    first blocker ends the walk (any-hit mesh queries)."""
    if inst.use_bvh[g] != 0:
        return trace_any(inst, inst.roots[g], wp.vec3(0.0), d, max_t)
    return any_in_list(inst.near, inst.lowers, inst.uppers, inst.item_root, inst.blas_bounds, inst.blas_kids,
                       inst.blas_tris, inst.obj_T_ref, inst.frame_items,
                       inst.frame_start[g], inst.frame_start[g + 1], d, max_t)


@wp.func
def pixel_ray(i: wp.int32, j: wp.int32, cam: Pinhole):
    """Unit camera-frame direction through the centre of pixel (row i, col j)."""
    y = (wp.float32(i) - cam.intr[3]) / cam.intr[1]
    x = (wp.float32(j) - cam.intr[2] - cam.skew * y) / cam.intr[0]
    return wp.normalize(wp.vec3(x, y, 1.0))


@specialised_builder
def primary_kernel(want_normals: bool, want_points: bool, lens: bool = False, per_pixel: bool = False):
    """The primary G-buffer kernel, specialised so unrequested channels are compiled out.

    ``lens``: the pixel rays come from ``cam.rays`` (H, W) (a lens model's unprojected pixel centres,
    flowsynth.scene.camera; a ray with z < 0 marks an uncovered pixel: no hit) instead of the pinhole ``cam``.

    Two launch shapes of one body (``flowsynth.parallel.pixel_threads``): ``per_pixel`` False, dims (F, rows) from
    row ``band0`` (``row_loop=True``), each thread casting the W pixels of its row (a Warp CPU thread per pixel
    spends ~35 ns unravelling its 3-D index: docs/decisions/0004-pair-kernel-rows-and-culls.md); ``per_pixel``
    True, dims (F, rows, W), a thread per pixel (the GPU's shape). F counts every frame of a batch of clips
    (``SceneAccel.batch``). Outputs per pixel (every pixel written): ``dist``
    ray length [m] (0 = no hit), ``item`` (-1 = no hit), ``face`` (-1 = no hit), and when requested ``point``
    (object-frame hit point [m], 0 = no hit) and ``normal`` (unit, reference/camera frame, facing the camera;
    0 = no hit).
    """
    @wp.kernel(enable_backward=False, module="unique")
    def primary(
        inst: Instances,
        tiles: TileLists,
        cam: Pinhole,
        max_t: wp.float32,
        band0: wp.int32,
        # outputs
        dist: wp.array3d[wp.float32],
        item_out: wp.array3d[wp.int32],
        face_out: wp.array3d[wp.int32],
        point: wp.array3d[wp.vec3],
        normal: wp.array3d[wp.vec3],
    ):
        if wp.static(per_pixel):
            f, i, j0 = wp.tid()
            j1 = j0 + 1
        else:
            f, i = wp.tid()
            j0 = wp.int32(0)
            j1 = dist.shape[2]
        i += band0
        for j in range(j0, j1):
            d = pixel_ray(i, j, cam)
            if wp.static(lens):
                d = cam.rays[i, j]
            lst = tile_list(tiles.tiles_x, tiles.tiles_y, tiles.tile_shift, f, i, j)
            item, t, face, u, v = closest_from_camera(inst, f, tiles.start, tiles.items, lst, d, max_t)
            if wp.static(lens):
                if d[2] < 0.0:  # uncovered pixel
                    item = wp.int32(-1)
            if item < 0:
                item_out[f, i, j] = -1
                face_out[f, i, j] = -1
                dist[f, i, j] = 0.0
                if wp.static(want_points):
                    point[f, i, j] = wp.vec3(0.0)
                if wp.static(want_normals):
                    normal[f, i, j] = wp.vec3(0.0)
                continue
            item_out[f, i, j] = item
            face_out[f, i, j] = face
            dist[f, i, j] = t
            if wp.static(want_points):
                point[f, i, j] = eval_position(inst.blas_tris, inst.blas_slot, inst.item_face0[item], face, u, v)
            if wp.static(want_normals):
                a, b, c = face_vertices(inst.blas_tris, inst.blas_slot, inst.item_face0[item], face)
                n = wp.normalize(wp.transform_vector(inst.ref_T_obj[item], wp.cross(b - a, c - a)))
                if wp.dot(n, d) > 0.0:
                    n = -n
                normal[f, i, j] = n

    return primary


@wp.kernel(enable_backward=False)
def visibility_kernel(
    inst: Instances,
    target: wp.array[wp.vec3],
    pair_frame: wp.array[wp.int32],
    rel_tol: wp.float32,
    band0: wp.int32,
    # outputs
    blocked: wp.array[wp.int8],
):
    """Is the straight segment from a target camera centre to a point blocked?

    ``target[r]`` is the point in the camera frame of frame ``pair_frame[r]`` [m]. The ray from the
    camera centre towards it counts as blocked when it hits a surface closer than (1 - rel_tol) times
    the point's distance (any hit: the first blocker ends the ray). Launch dims (rays,) from ray ``band0``.
    """
    r = wp.tid() + band0
    p = target[r]
    L = wp.length(p)
    if L <= 0.0:
        blocked[r] = wp.int8(1)
        return
    hit = any_from_camera(inst, pair_frame[r], p / L, L * (1.0 - rel_tol))
    blocked[r] = wp.int8(1) if hit else wp.int8(0)


@wp.kernel(enable_backward=False)
def group_roots_kernel(bvh: wp.uint64, roots: wp.array[wp.int32]):
    """roots[f] = root node of group f (frame f) of a grouped BVH."""
    f = wp.tid()
    roots[f] = wp.bvh_get_group_root(bvh, f)


@wp.kernel(enable_backward=False)
def face_planes_kernel(points: wp.array[wp.vec3], indices: wp.array[wp.int32], band0: wp.int32,
                       planes: wp.array[wp.vec4d]):
    """planes[f] = (n, e) for face f of a mesh: n its unit normal (float64 from the float32 vertices),
    e = max over every vertex v of n . v (float64), so the whole mesh lies in n . x <= e; a degenerate face
    gets n = 0, e = 1e30. Faces band0 + thread index (row bands, ``flowsynth.parallel``)."""
    f = wp.tid() + band0
    a = wp.vec3d(points[indices[3 * f + 0]])
    b = wp.vec3d(points[indices[3 * f + 1]])
    c = wp.vec3d(points[indices[3 * f + 2]])
    nrm = wp.cross(b - a, c - a)
    length = wp.length(nrm)
    if length <= wp.float64(0.0):
        planes[f] = wp.vec4d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(1.0e30))
        return
    n = nrm / length
    e = wp.dot(n, a)
    for k in range(points.shape[0]):
        e = wp.max(e, wp.dot(n, wp.vec3d(points[k])))
    planes[f] = wp.vec4d(n[0], n[1], n[2], e)
