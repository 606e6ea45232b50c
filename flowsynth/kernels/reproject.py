"""Per-pixel reprojection of the primary cast's hit points into another frame or view (float64), with the
validity, out-of-frame and occlusion tests fused in, no gather: on the CPU one thread per (pair, row) looping over the
row's pixels (a Warp CPU thread per pixel spends more on unravelling its 3-D index than on the reprojection:
docs/decisions/0004-pair-kernel-rows-and-culls.md), on a GPU one thread per pixel; the pairs of one clip or of a batch
of clips (docs/decisions/0024-batches-on-the-device.md).

Definitions are those of flowsynth/truth/flow.py's module docstring. For pair t the source frame is
s = pair_src[t] and the target frame r = s + step; the pixel (i, j) of frame s holding instance n at
object-frame point p (float32, promoted to float64) maps to

    X = cam_T_obj[r, n] @ p,  valid = X.z > 0,  (u', v') = (K X)[:2] / (K X)[2]   (full K, float64)

(cam_T_obj[r, n]: the target item's row of ``PairTarget.cam_T_obj``)

(with a lens model, flowsynth/scene/camera.py: valid = X in the model's domain, (u', v') = the model's projection,
``lens_project``, the same equations as cv2.projectPoints / cv2.fisheye.projectPoints)

and, where requested, flow (u' - j, v' - i), occlusion (exact visibility ray, or the depth-buffer test),
disparity change fB / X.z - fB / (cam_T_obj[s, n] @ p).z and scene flow sfM[t, n] @ p.

The exact visibility ray (occlusion="exact") is the segment from the camera centre of frame r to
(1 - tol) X; it is blocked when any mesh meets it (first blocker ends the test). Exact culls spare the
mesh queries that cannot hit (``Culling``, flowsynth.raycast.accel.SceneAccel.culling), all proved on float64
planes with a margin of 1e-6 |X| + 1e-9 m (float32 rounding of the ray the mesh queries trace is ~1e-7 |X|;
|X| is taken as its float32 length L):
- own item: its mesh lies in the half-space n . x <= e of the hit face's plane (e: max of n . v over the
  asset's vertices); when the camera and the segment's end are both beyond it, no point of the segment
  is (n . x is linear along the segment);
- flat items (room walls), tested one by one: the segment stays on one side of the item's slab;
- the other items: those of the screen tile of (u', v') in the primary cast's lists without the flat
  items (every instance whose clipped hull projects within a pixel of that tile: instances elsewhere cannot
  meet the ray), near to far, down to the first whose box starts beyond the segment, box entry tested, then the
  bounding sphere, then the planes through the camera centre that bound the item's projected convex hull
  (``beyond_silhouette``: near misses of convex items need no mesh query).
The cheapest tests run first: the flat groups without the own item, and only when a test needs them the
own face plane and the ray's inverse direction (docs/decisions/0004-pair-kernel-rows-and-culls.md).
"""

from __future__ import annotations

import warp as wp

from flowsynth.kernels.blas import blas_any
from flowsynth.kernels.raycast import (Culling, Instances, TileLists, beyond_silhouette, box_entry_inv, inverse_dir,
                                       tile_list, trace_any)
from flowsynth.kernels.specialise import specialised_builder

__all__ = ["LENS_CODES", "OCC_DEPTH", "OCC_EXACT", "OCC_NONE", "PairOcclusion", "PairSource", "PairTarget",
           "lens_project", "pair_kernel", "world_points_kernel"]

OCC_NONE, OCC_EXACT, OCC_DEPTH = 0, 1, 2
# the pair kernel's lens variants (flowsynth.scene.camera.LENS_MODELS)
LENS_CODES = {"pinhole": 0, "brown_conrady": 1, "kannala_brandt": 2}


@wp.struct
class PairSource:
    """The pair kernel's G-buffer and frames: pair t maps frame s = pair_src[t] into frame s + step."""

    item: wp.array3d[wp.int32]  # (F, H, W) item of each pixel's hit (``Instances``' numbering), -1: none
    point: wp.array3d[wp.vec3]  # (F, H, W) object-frame hit point [m]
    face: wp.array3d[wp.int32]  # (F, H, W) hit face (the own item's cull, occlusion="exact")
    dist: wp.array3d[wp.float32]  # (F, H, W) ray length [m] (the depth test, occlusion="depth"; else a dummy)
    frame_start: wp.array[wp.int32]  # (F + 1,) frame f's first item (``Instances.frame_start``)
    item_inst: wp.array[wp.int32]  # (items,) the item's row in per-instance tables (``Instances.item_inst``)
    pair_src: wp.array[wp.int32]  # (P,) source frame of each pair (src0 + t; a batch's clip b from frame b T)
    step: wp.int32


@wp.struct
class PairTarget:
    """The target view's poses and projection, the stereo baseline and the scene-flow transforms."""

    cam_T_obj: wp.array[wp.mat44d]  # (items,) target view from each item's object in its frame, float64
    K: wp.mat33d  # intrinsics, skew included
    lens_k: wp.array[wp.float64]  # lens coefficients (``lens_project``; 8 entries, 0 when unused)
    lens_lim: wp.float64  # the lens model's domain bound
    fB: wp.float64  # focal length x baseline (disparity change ``dc``)
    sfM: wp.array[wp.mat44d]  # (items,) scene-flow transform of each source item (``sf``; a dummy when not asked)


@wp.struct
class PairOcclusion:
    """What the occlusion tests read: the target view's scene (exact) or depth rays (depth)."""

    inst: Instances  # the target view's instances (occlusion="exact")
    tiles: TileLists  # its tile lists without flat items (occlusion="exact")
    cull: Culling  # its culling tables (occlusion="exact")
    rel_tol: wp.float32  # the visibility ray stops at (1 - rel_tol) X
    dz: wp.array2d[wp.float64]  # (H, W) z of each pixel's unit ray (occlusion="depth")
    depth_tol: wp.float64  # relative depth tolerance of the depth test


@wp.func
def lens_project(model: wp.int32, k: wp.array[wp.float64], lim: wp.float64, K: wp.mat33d, X: wp.vec3d):
    """(u, v, ok) of camera-frame X through lens ``model`` (1 Brown-Conrady, k = (k1, k2, p1, p2, k3, k4, k5, k6);
    2 Kannala-Brandt, k = (k1, k2, k3, k4)), float64, flowsynth/scene/camera.py's equations (OpenCV's); ``ok``: X
    lies in the domain (z > 0 and r2 < lim, resp. atan(r) < lim); u, v = 0 where not."""
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    if X[2] <= zero:
        return zero, zero, False
    a = X[0] / X[2]
    b = X[1] / X[2]
    r2 = a * a + b * b
    ad = a
    bd = b
    if model == 1:
        if r2 >= lim:
            return zero, zero, False
        q = (one + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))) / (one + r2 * (k[5] + r2 * (k[6] + r2 * k[7])))
        two = wp.float64(2.0)
        ad = a * q + two * k[2] * a * b + k[3] * (r2 + two * a * a)
        bd = b * q + k[2] * (r2 + two * b * b) + two * k[3] * a * b
    else:
        r = wp.sqrt(r2)
        th = wp.atan(r)
        if th >= lim:
            return zero, zero, False
        if r > wp.float64(1.0e-8):
            t2 = th * th
            thd = th * (one + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
            ad = a * thd / r
            bd = b * thd / r
    return K[0, 0] * ad + K[0, 1] * bd + K[0, 2], K[1, 1] * bd + K[1, 2], True


@wp.func
def group_holds(grp_n: wp.array[wp.vec3d], grp_ab: wp.array[wp.vec2d], grp_item: wp.array[wp.vec2i], g: wp.int32,
                X: wp.vec3d, keep: wp.float64, margin: wp.float64, skip: wp.int32):
    """Do both ends of the segment from the camera centre to keep X lie strictly inside flat group ``g``'s
    interval (A, B) along its normal (by ``margin``)? Then the segment meets none of its members. A bound set
    by item ``skip`` alone is dropped (``skip`` = -1: none)."""
    ab = grp_ab[g]
    gi = grp_item[g]
    lo = ab[0] + margin
    hi = ab[1] - margin
    if gi[0] == skip:
        lo = wp.float64(-1.0e300)
    if gi[1] == skip:
        hi = wp.float64(1.0e300)
    hg = keep * wp.dot(grp_n[g], X)
    return wp.min(hg, wp.float64(0.0)) > lo and wp.max(hg, wp.float64(0.0)) < hi


@wp.func
def groups_hold(grp_n: wp.array[wp.vec3d], grp_ab: wp.array[wp.vec2d], g0: wp.int32, g1: wp.int32, X: wp.vec3d,
                keep: wp.float64, margin: wp.float64):
    """``group_holds`` for every group g0 .. g1 - 1 with no item left out: no flat item can block the segment
    (room walls seen from inside: three tests, no per-item data)."""
    for g in range(g0, g1):
        ab = grp_ab[g]
        hg = keep * wp.dot(grp_n[g], X)
        if wp.min(hg, wp.float64(0.0)) <= ab[0] + margin or wp.max(hg, wp.float64(0.0)) >= ab[1] - margin:
            return False
    return True


@wp.func
def own_skip(face_plane: wp.vec4d, M: wp.mat44d, p: wp.vec3d, keep: wp.float64, margin: wp.float64, me: wp.int32):
    """``me`` when the own item provably cannot block the segment, else -1: its mesh lies in n . x <= e
    (``face_plane`` (n, e) of the hit face, object frame) and the camera centre (at -R^T t there, M = cam_T_obj)
    and the segment's end keep p + (1 - keep) camera are both beyond that plane by ``margin``."""
    cx = -(M[0, 0] * M[0, 3] + M[1, 0] * M[1, 3] + M[2, 0] * M[2, 3])
    cy = -(M[0, 1] * M[0, 3] + M[1, 1] * M[1, 3] + M[2, 1] * M[2, 3])
    cz = -(M[0, 2] * M[0, 3] + M[1, 2] * M[1, 3] + M[2, 2] * M[2, 3])
    hc = face_plane[0] * cx + face_plane[1] * cy + face_plane[2] * cz - face_plane[3]
    hp = face_plane[0] * p[0] + face_plane[1] * p[1] + face_plane[2] * p[2] - face_plane[3]
    if hc > margin and keep * hp + (wp.float64(1.0) - keep) * hc > margin:
        return me
    return wp.int32(-1)


@wp.func
def flat_blocks(near: wp.array[wp.float32], lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3],
                item_root: wp.array[wp.int32], bb: wp.array[wp.vec4], bk: wp.array[wp.vec4i], bt: wp.array[wp.vec3],
                obj_T_ref: wp.array[wp.mat44], slab_n: wp.array[wp.vec3d],
                slab_lh: wp.array[wp.vec2d], grp_n: wp.array[wp.vec3d], grp_ab: wp.array[wp.vec2d],
                grp_item: wp.array[wp.vec2i], mem_start: wp.array[wp.int32], mem_items: wp.array[wp.int32],
                g0: wp.int32, g1: wp.int32, d: wp.vec3, inv: wp.vec3, max_t: wp.float32, X: wp.vec3d,
                keep: wp.float64, margin: wp.float64, skip: wp.int32):
    """Does a flat item of groups g0 .. g1 - 1 (``Culling``) other than ``skip`` block the segment from the
    camera centre to keep X (float32 ray ``d``, ``max_t``)? Along a slab normal n, n . x is 0 at the camera
    and keep n . X at the end, linear between: a segment beyond a slab at both ends (by ``margin``) cannot
    meet it. A group whose interval (A, B) holds both ends misses all its members (room walls: three tests;
    a bound set by ``skip`` alone is dropped); otherwise each member's own slab is tested, then its box and
    mesh as in ``any_in_list``."""
    for g in range(g0, g1):
        if group_holds(grp_n, grp_ab, grp_item, g, X, keep, margin, skip):
            continue
        for k in range(mem_start[g], mem_start[g + 1]):
            item = mem_items[k]
            if item == skip:
                continue
            lh = slab_lh[item]
            he = keep * wp.dot(slab_n[item], X)
            if wp.min(he, wp.float64(0.0)) > lh[1] + margin or wp.max(he, wp.float64(0.0)) < lh[0] - margin:
                continue
            if near[item] < max_t:
                te = box_entry_inv(lowers[item], uppers[item], d, inv)
                if te >= 0.0 and te < max_t:
                    M = obj_T_ref[item]
                    if blas_any(bb, bk, bt, item_root[item], wp.vec3(M[0, 3], M[1, 3], M[2, 3]),
                                wp.transform_vector(M, d), max_t):
                        return True
    return False


@wp.func
def list_blocks(near: wp.array[wp.float32], lowers: wp.array[wp.vec3], uppers: wp.array[wp.vec3],
                item_root: wp.array[wp.int32], bb: wp.array[wp.vec4], bk: wp.array[wp.vec4i], bt: wp.array[wp.vec3],
                obj_T_ref: wp.array[wp.mat44], sphere: wp.array[wp.vec4d],
                inner: wp.array[wp.float64], sil: wp.array[wp.vec4d], sil_z: wp.array[wp.float64],
                items: wp.array[wp.int32], a: wp.int32, b: wp.int32, d: wp.vec3,
                inv: wp.vec3, max_t: wp.float32, X: wp.vec3d, inv_xx: wp.float64, keep: wp.float64,
                margin: wp.float64, skip: wp.int32):
    """``any_in_list`` over ``items[a:b]`` (nearest box first) leaving out item ``skip``, for the segment
    from the camera centre to keep X, with three exact shortcuts before each mesh query: the segment misses
    the item's bounding sphere (no hit), or its point nearest the sphere's centre lies inside the item's
    inner ball while the camera is outside the sphere (the segment enters the closed mesh before keep X:
    blocked), or it stays beyond one of the item's silhouette planes (no hit)."""
    for k in range(a, b):
        item = items[k]
        if near[item] >= max_t:
            break
        if item != skip:
            te = box_entry_inv(lowers[item], uppers[item], d, inv)
            if te >= 0.0 and te < max_t:
                S = sphere[item]
                c = wp.vec3d(S[0], S[1], S[2])
                s = wp.dot(c, X) * inv_xx  # parameter of the point of the line 0 + s X nearest the centre
                e = c - wp.clamp(s, wp.float64(0.0), keep) * X
                dd = wp.dot(e, e)
                out = S[3] + margin
                if dd > out * out:
                    continue
                rho = inner[item] - margin
                if rho > wp.float64(0.0) and s > wp.float64(0.0) and s < keep and dd < rho * rho:
                    if wp.dot(c, c) > out * out:
                        return True
                if beyond_silhouette(sil, sil_z, item, X, margin):
                    continue
                M = obj_T_ref[item]
                if blas_any(bb, bk, bt, item_root[item], wp.vec3(M[0, 3], M[1, 3], M[2, 3]), wp.transform_vector(M, d),
                            max_t):
                    return True
    return False


@wp.func
def affine_point(M: wp.mat44d, p: wp.vec3d):
    """M p for a 4x4 affine M: each coordinate r0 p0 + r1 p1 + r2 p2 + r3 of a row r, summed in that order."""
    return wp.vec3d(M[0, 0] * p[0] + M[0, 1] * p[1] + M[0, 2] * p[2] + M[0, 3],
                    M[1, 0] * p[0] + M[1, 1] * p[1] + M[1, 2] * p[2] + M[1, 3],
                    M[2, 0] * p[0] + M[2, 1] * p[1] + M[2, 2] * p[2] + M[2, 3])


@specialised_builder
def pair_kernel(want_flow: bool, occ_mode: int, want_dc: bool, want_sf: bool = False, lens: int = 0,
                per_pixel: bool = False):
    """The pair kernel, specialised so unrequested outputs are compiled out.

    ``lens`` (``LENS_CODES``): 0 the pinhole K, else the target view's lens model, coefficients ``lens_k`` and
    domain bound ``lens_lim`` (``lens_project``); a point outside the domain is treated as one behind the camera.

    Two launch shapes of one body (``flowsynth.parallel.pixel_threads``): ``per_pixel`` False, dims (P, rows) from
    row ``band0`` (``row_loop=True``), each thread doing the W pixels of its row; ``per_pixel`` True, dims (P, rows,
    W), a thread per pixel (the GPU's shape). P counts every pair of a batch of clips. Every pixel of every output
    is written: ``valid`` (uint8, 1 = hit and
    X.z > 0), ``oof`` (uint8, hit and not inside [-0.5, W - 0.5) x [-0.5, H - 0.5)), and when requested
    ``flow`` (P, 2, H, W) float32, ``occ`` (uint8, oof or blocked), ``dc`` float64 disparity change, ``sf``
    (P, 3, H, W) float32 scene flow ``sfM[t, n] @ p`` (where hit, valid or not); all 0 where not hit (flow
    and dc also where not valid). The item of the same instance in target frame r is ``it - frame_start[s] +
    frame_start[r]`` (f N + n in one clip). For occlusion="exact", ``tiles`` are the lists without flat items
    (``SceneAccel.tile_lists(camera, flat=False)``). Inputs: the parameter blocks ``PairSource``, ``PairTarget``
    and ``PairOcclusion`` (fields documented there), then ``band0``.
    """
    @wp.kernel(enable_backward=False, module="unique")
    def pairs(
        src: PairSource,
        tgt: PairTarget,
        occl: PairOcclusion,
        band0: wp.int32,
        # outputs
        valid: wp.array3d[wp.uint8],
        oof: wp.array3d[wp.uint8],
        occ: wp.array3d[wp.uint8],
        flow: wp.array4d[wp.float32],
        dc: wp.array3d[wp.float64],
        sf: wp.array4d[wp.float32],
    ):
        item = src.item
        point = src.point
        face = src.face
        dist = src.dist
        frame_start = src.frame_start
        item_inst = src.item_inst
        step = src.step
        cam_T_obj = tgt.cam_T_obj
        K = tgt.K
        lens_k = tgt.lens_k
        lens_lim = tgt.lens_lim
        fB = tgt.fB
        sfM = tgt.sfM
        inst = occl.inst
        tiles = occl.tiles
        cull = occl.cull
        rel_tol = occl.rel_tol
        dz = occl.dz
        depth_tol = occl.depth_tol
        if wp.static(per_pixel):
            t, i, j0 = wp.tid()
            j1 = j0 + 1
        else:
            t, i = wp.tid()
            j0 = wp.int32(0)
            j1 = item.shape[2]
        i += band0
        s = src.pair_src[t]
        r = s + step
        H = item.shape[1]
        W = item.shape[2]
        for j in range(j0, j1):
            it = item[s, i, j]
            if it < 0:
                valid[t, i, j] = wp.uint8(0)
                oof[t, i, j] = wp.uint8(0)
                if wp.static(occ_mode != 0):
                    occ[t, i, j] = wp.uint8(0)
                if wp.static(want_flow):
                    flow[t, 0, i, j] = 0.0
                    flow[t, 1, i, j] = 0.0
                if wp.static(want_dc):
                    dc[t, i, j] = wp.float64(0.0)
                if wp.static(want_sf):
                    sf[t, 0, i, j] = 0.0
                    sf[t, 1, i, j] = 0.0
                    sf[t, 2, i, j] = 0.0
                continue
            ri = it - frame_start[s] + frame_start[r]  # the same instance's item in frame r
            q = point[s, i, j]
            p = wp.vec3d(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]))
            if wp.static(want_sf):
                Y = affine_point(sfM[it], p)
                sf[t, 0, i, j] = wp.float32(Y[0])
                sf[t, 1, i, j] = wp.float32(Y[1])
                sf[t, 2, i, j] = wp.float32(Y[2])
            M = cam_T_obj[ri]
            X = affine_point(M, p)
            x = X[0]
            y = X[1]
            z = X[2]
            behind = z <= wp.float64(0.0)
            u = wp.float64(0.0)
            v = wp.float64(0.0)
            if wp.static(lens != 0):
                u, v, ok = lens_project(wp.static(lens), lens_k, lens_lim, K, X)
                behind = not ok
            if behind:
                valid[t, i, j] = wp.uint8(0)
                oof[t, i, j] = wp.uint8(1)
                if wp.static(occ_mode != 0):
                    occ[t, i, j] = wp.uint8(1)
                if wp.static(want_flow):
                    flow[t, 0, i, j] = 0.0
                    flow[t, 1, i, j] = 0.0
                if wp.static(want_dc):
                    dc[t, i, j] = wp.float64(0.0)
                continue
            if wp.static(lens == 0):
                # full K (skew included), dehomogenised as kornia's convert_points_from_homogeneous does
                h0 = K[0, 0] * x + K[0, 1] * y + K[0, 2] * z
                h1 = K[1, 0] * x + K[1, 1] * y + K[1, 2] * z
                h2 = K[2, 0] * x + K[2, 1] * y + K[2, 2] * z
                sc = wp.float64(1.0)
                if wp.abs(h2) > wp.float64(1.0e-8):
                    sc = wp.float64(1.0) / h2
                u = sc * h0
                v = sc * h1
            inside = (u >= wp.float64(-0.5) and u < wp.float64(W) - wp.float64(0.5) and v >= wp.float64(-0.5)
                      and v < wp.float64(H) - wp.float64(0.5))
            valid[t, i, j] = wp.uint8(1)
            oof[t, i, j] = wp.uint8(0) if inside else wp.uint8(1)
            if wp.static(want_flow):
                flow[t, 0, i, j] = wp.float32(u - wp.float64(j))
                flow[t, 1, i, j] = wp.float32(v - wp.float64(i))
            if wp.static(want_dc):
                M0 = cam_T_obj[it]
                z0 = M0[2, 0] * p[0] + M0[2, 1] * p[1] + M0[2, 2] * p[2] + M0[2, 3]
                dc[t, i, j] = fB / z - fB / z0
            if wp.static(occ_mode == 1):
                blocked = True
                if inside:
                    pf = wp.vec3(wp.float32(x), wp.float32(y), wp.float32(z))
                    L = wp.length(pf)
                    if L > 0.0:
                        d = pf / L
                        max_t = L * (1.0 - rel_tol)
                        if inst.use_bvh[r] != 0:
                            blocked = trace_any(inst, inst.roots[r], wp.vec3(0.0), d, max_t)
                        else:
                            # cheapest first: the flat groups without the own item (room walls: three dot
                            # products), then the own item's plane and the ray's inverse direction only when a
                            # test needs them
                            X = wp.vec3d(x, y, z)
                            keep = wp.float64(1.0) - wp.float64(rel_tol)
                            margin = wp.float64(1.0e-6) * wp.float64(L) + wp.float64(1.0e-9)
                            g0 = cull.grp_off[r]
                            g1 = cull.grp_off[r + 1]
                            skip = wp.int32(-1)
                            have_skip = False
                            blocked = False
                            if not groups_hold(cull.grp_n, cull.grp_ab, g0, g1, X, keep, margin):
                                skip = own_skip(cull.face_plane[cull.face_off[item_inst[it]] + face[s, i, j]], M, p,
                                                keep, margin, ri)
                                have_skip = True
                                blocked = flat_blocks(inst.near, inst.lowers, inst.uppers, inst.item_root,
                                                      inst.blas_bounds, inst.blas_kids, inst.blas_tris, inst.obj_T_ref,
                                                      cull.slab_n, cull.slab_lh, cull.grp_n, cull.grp_ab, cull.grp_item,
                                                      cull.mem_start, cull.mem_items, g0, g1, d, inverse_dir(d), max_t,
                                                      X, keep, margin, skip)
                            if not blocked:
                                jj = wp.min(wp.int32(wp.floor(u + wp.float64(0.5))), W - 1)
                                ii = wp.min(wp.int32(wp.floor(v + wp.float64(0.5))), H - 1)
                                lst = tile_list(tiles.tiles_x, tiles.tiles_y, tiles.tile_shift, r, ii, jj)
                                a = tiles.start[lst]
                                b = tiles.start[lst + 1]
                                # the lists run near to far: nothing to test when the first box starts beyond the end
                                if a < b and inst.near[tiles.items[a]] < max_t:
                                    if not have_skip:
                                        skip = own_skip(cull.face_plane[cull.face_off[item_inst[it]] + face[s, i, j]],
                                                        M, p, keep, margin, ri)
                                    blocked = list_blocks(inst.near, inst.lowers, inst.uppers, inst.item_root,
                                                          inst.blas_bounds, inst.blas_kids, inst.blas_tris,
                                                          inst.obj_T_ref, cull.sphere, cull.inner, cull.sil,
                                                          cull.sil_z, tiles.items, a, b, d, inverse_dir(d), max_t,
                                                          X, wp.float64(1.0) / wp.dot(X, X), keep, margin, skip)
                occ[t, i, j] = wp.uint8(1) if blocked else wp.uint8(0)
            if wp.static(occ_mode == 2):
                blocked = True
                if inside:
                    jj = wp.clamp(wp.int32(wp.rint(u)), 0, W - 1)
                    ii = wp.clamp(wp.int32(wp.rint(v)), 0, H - 1)
                    target_depth = wp.float64(dist[r, ii, jj]) * dz[ii, jj]
                    blocked = item[r, ii, jj] < 0 or z > target_depth * (wp.float64(1.0) + depth_tol)
                occ[t, i, j] = wp.uint8(1) if blocked else wp.uint8(0)

    return pairs


@specialised_builder
def world_points_kernel(per_pixel: bool = False):
    """The primary cast's hit points in the world frame, and whether they move to the next frame (float64).

    Two launch shapes of one body (``flowsynth.parallel.pixel_threads``): ``per_pixel`` False, dims (frames, rows)
    from row ``band0`` (``row_loop=True``), each thread walking its row; True, dims (frames, rows, W), a thread per
    pixel. Pixel (i, j) of frame f (frame t = f - b T of clip b, ``frames`` T per clip) holding item k (-1: no hit)
    at object-frame point p (float32, promoted) gets ``world`` x = world_T_obj[k] p (0 where not hit). With
    ``want_moved`` != 0, ``moved`` (B (T-1), H, W) gets, for the frames t = 0 .. T-2 of each clip (row b (T-1) + t),
    1 where the next frame's pose moves the same point by more than motion_tol + 1e-12 |x|: |world_T_obj[k'] p - x|
    with k' = k - frame_start[f] + frame_start[f + 1] (the ``motion`` output, flowsynth/truth/flow.py).
    """
    @wp.kernel(enable_backward=False, module="unique")
    def world_points(
        item: wp.array3d[wp.int32],
        point: wp.array3d[wp.vec3],
        world_T_obj: wp.array[wp.mat44d],
        frame_start: wp.array[wp.int32],
        frames: wp.int32,
        want_moved: wp.int32,
        motion_tol: wp.float64,
        band0: wp.int32,
        # outputs
        world: wp.array3d[wp.vec3d],
        moved: wp.array3d[wp.uint8],
    ):
        if wp.static(per_pixel):
            f, i, j0 = wp.tid()
            j1 = j0 + 1
        else:
            f, i = wp.tid()
            j0 = wp.int32(0)
            j1 = item.shape[2]
        i += band0
        b = f // frames
        t = f - b * frames
        last = t + 1 >= frames  # no next frame in the clip
        for j in range(j0, j1):
            k = item[f, i, j]
            x = wp.vec3d()
            m = wp.uint8(0)
            if k >= 0:
                q = point[f, i, j]
                p = wp.vec3d(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]))
                x = affine_point(world_T_obj[k], p)
                if want_moved != 0 and not last:
                    y = affine_point(world_T_obj[k - frame_start[f] + frame_start[f + 1]], p)
                    if wp.length(y - x) > motion_tol + wp.float64(1.0e-12) * wp.length(x):
                        m = wp.uint8(1)
            world[f, i, j] = x
            if want_moved != 0 and not last:
                moved[f - b, i, j] = m

    return world_points
