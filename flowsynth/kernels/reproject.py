"""Per-pixel reprojection of the primary cast's hit points into another frame or view (float64), with the
validity, out-of-frame and occlusion tests fused in: one thread per (pair, pixel), no gather.

Definitions are those of flowsynth/flow.py's module docstring. For pair t the source frame is
s = src0 + t and the target frame r = s + step; the pixel (i, j) of frame s holding instance n at
object-frame point p (float32, promoted to float64) maps to

    X = cam_T_obj[r, n] @ p,  valid = X.z > 0,  (u', v') = (K X)[:2] / (K X)[2]   (full K, float64)

and, where requested, flow (u' - j, v' - i), occlusion (exact visibility ray, or the depth-buffer test),
disparity change fB / X.z - fB / (cam_T_obj[s, n] @ p).z and scene flow sfM[t, n] @ p.
"""

from __future__ import annotations

import warp as wp

from flowsynth.kernels.raycast import Instances, TileLists, any_in_list, trace_any

__all__ = ["OCC_DEPTH", "OCC_EXACT", "OCC_NONE", "blocked_from_camera", "pair_kernel"]

OCC_NONE, OCC_EXACT, OCC_DEPTH = 0, 1, 2


@wp.func
def blocked_from_camera(inst: Instances, tiles: TileLists, g: wp.int32, lst: wp.int32, p: wp.vec3,
                        rel_tol: wp.float32):
    """Is the segment from frame g's camera centre to camera-frame point p blocked (visibility_kernel's test)?

    Same answer as ``any_from_camera`` over the whole frame: the candidates are those of screen tile
    ``lst`` of the primary cast (the tile of the pixel nearest to p's projection), which holds every
    instance whose box projects within a pixel of that tile (flowsynth.accel._tile_lists); boxes elsewhere
    cannot meet the ray. Near to far, first blocker ends the walk.
    """
    L = wp.length(p)
    if L <= 0.0:
        return True
    d = p / L
    max_t = L * (1.0 - rel_tol)
    if inst.use_bvh != 0:
        return trace_any(inst.bvh, inst.roots[g], inst.item_mesh, inst.obj_T_ref, wp.vec3(0.0), d, max_t)
    return any_in_list(inst.near, inst.lowers, inst.uppers, inst.item_mesh, inst.obj_T_ref, tiles.items,
                       tiles.start[lst], tiles.start[lst + 1], d, max_t)


_PAIR: dict = {}


def pair_kernel(want_flow: bool, occ_mode: int, want_dc: bool, want_sf: bool = False):
    """The pair kernel, specialised so unrequested outputs are compiled out.

    Launch dims (P, rows, W) from row ``band0`` (``flowsynth.parallel``). Every pixel of every output is
    written: ``valid`` (uint8, 1 = hit and X.z > 0), ``oof`` (uint8, hit and not inside [-0.5, W - 0.5) x
    [-0.5, H - 0.5)), and when requested ``flow`` (P, 2, H, W) float32, ``occ`` (uint8, oof or blocked),
    ``dc`` float64 disparity change, ``sf`` (P, 3, H, W) float32 scene flow ``sfM[t, n] @ p`` (where hit,
    valid or not); all 0 where not hit (flow and dc also where not valid).
    """
    key = (bool(want_flow), int(occ_mode), bool(want_dc), bool(want_sf))
    if key in _PAIR:
        return _PAIR[key]

    @wp.kernel(enable_backward=False, module="unique")
    def pairs(
        item: wp.array3d[wp.int32],
        point: wp.array3d[wp.vec3],
        cam_T_obj: wp.array2d[wp.mat44d],
        n_inst: wp.int32,
        src0: wp.int32,
        step: wp.int32,
        K: wp.mat33d,
        inst: Instances,
        tiles: TileLists,
        rel_tol: wp.float32,
        dist: wp.array3d[wp.float32],
        dz: wp.array2d[wp.float64],
        depth_tol: wp.float64,
        fB: wp.float64,
        sfM: wp.array2d[wp.mat44d],
        band0: wp.int32,
        # outputs
        valid: wp.array3d[wp.uint8],
        oof: wp.array3d[wp.uint8],
        occ: wp.array3d[wp.uint8],
        flow: wp.array4d[wp.float32],
        dc: wp.array3d[wp.float64],
        sf: wp.array4d[wp.float32],
    ):
        t, i, j = wp.tid()
        i += band0
        s = src0 + t
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
            return
        n = it % n_inst
        r = s + step
        q = point[s, i, j]
        p = wp.vec3d(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]))
        if wp.static(want_sf):
            S = sfM[t, n]
            sf[t, 0, i, j] = wp.float32(S[0, 0] * p[0] + S[0, 1] * p[1] + S[0, 2] * p[2] + S[0, 3])
            sf[t, 1, i, j] = wp.float32(S[1, 0] * p[0] + S[1, 1] * p[1] + S[1, 2] * p[2] + S[1, 3])
            sf[t, 2, i, j] = wp.float32(S[2, 0] * p[0] + S[2, 1] * p[1] + S[2, 2] * p[2] + S[2, 3])
        M = cam_T_obj[r, n]
        x = M[0, 0] * p[0] + M[0, 1] * p[1] + M[0, 2] * p[2] + M[0, 3]
        y = M[1, 0] * p[0] + M[1, 1] * p[1] + M[1, 2] * p[2] + M[1, 3]
        z = M[2, 0] * p[0] + M[2, 1] * p[1] + M[2, 2] * p[2] + M[2, 3]
        H = item.shape[1]
        W = item.shape[2]
        if z <= wp.float64(0.0):
            valid[t, i, j] = wp.uint8(0)
            oof[t, i, j] = wp.uint8(1)
            if wp.static(occ_mode != 0):
                occ[t, i, j] = wp.uint8(1)
            if wp.static(want_flow):
                flow[t, 0, i, j] = 0.0
                flow[t, 1, i, j] = 0.0
            if wp.static(want_dc):
                dc[t, i, j] = wp.float64(0.0)
            return
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
            M0 = cam_T_obj[s, n]
            z0 = M0[2, 0] * p[0] + M0[2, 1] * p[1] + M0[2, 2] * p[2] + M0[2, 3]
            dc[t, i, j] = fB / z - fB / z0
        if wp.static(occ_mode == 1):
            blocked = True
            if inside:
                jj = wp.min(wp.int32(wp.floor(u + wp.float64(0.5))), W - 1)
                ii = wp.min(wp.int32(wp.floor(v + wp.float64(0.5))), H - 1)
                lst = (r * tiles.tiles_y + ii // tiles.tile) * tiles.tiles_x + jj // tiles.tile
                blocked = blocked_from_camera(inst, tiles, r, lst, wp.vec3(wp.float32(x), wp.float32(y),
                                                                          wp.float32(z)), rel_tol)
            occ[t, i, j] = wp.uint8(1) if blocked else wp.uint8(0)
        if wp.static(occ_mode == 2):
            blocked = True
            if inside:
                jj = wp.clamp(wp.int32(wp.rint(u)), 0, W - 1)
                ii = wp.clamp(wp.int32(wp.rint(v)), 0, H - 1)
                target_depth = wp.float64(dist[r, ii, jj]) * dz[ii, jj]
                blocked = item[r, ii, jj] < 0 or z > target_depth * (wp.float64(1.0) + depth_tol)
            occ[t, i, j] = wp.uint8(1) if blocked else wp.uint8(0)

    _PAIR[key] = pairs
    return pairs
