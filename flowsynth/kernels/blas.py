"""Traversal of the per-asset 4-wide BVHs (layout: ``flowsynth.raycast.blas``) and their refit kernel.

``blas_closest`` and ``blas_any`` replace ``wp.mesh_query_ray`` / ``wp.mesh_query_ray_anyhit`` (and
``face_vertices`` / ``eval_position`` replace ``wp.mesh_get`` / ``wp.mesh_eval_position``): the same
watertight ray-triangle test (Woop, Benthin and Wald 2013, as Warp's ``intersect_ray_tri_woop``, with the
ray's shear computed once per ray instead of once per triangle), the same hits (t in [0, max_t)), the same
(u, v) convention (hit point u a + v b + (1 - u - v) c of the face's vertices a, b, c). What is
faster (benchmarks/speed/bvh.py, docs/decisions/0001-per-asset-bvh4.md): a node's four child boxes are tested at once
as ``vec4`` slabs, the near and far planes are picked once per ray from the direction's signs, children are visited
near first, and each stack entry keeps its entry distance so entries beyond the best hit are dropped on pop.
"""

from __future__ import annotations

import warp as wp

__all__ = ["STACK", "blas_any", "blas_closest", "eval_position", "face_vertices", "refit_kernel"]

# Stack entries per ray: a 4-wide tree of depth D needs at most 3 D + 1 (flowsynth.raycast.blas checks each tree).
STACK = 64
# Far slab distances are scaled up by 1 + 2 gamma(3) (Ize 2013, "Robust BVH ray traversal"), so float32
# rounding of the slab test never drops a box the ray touches.
SLAB_EPS = wp.constant(1.0000004)
# A zero direction component is replaced by this magnitude in the slab test only: its slabs then hold every
# origin inside them (t from -huge to +huge) and no other, with no inf * 0.
TINY_DIR = wp.constant(1.0e-30)
# Entry distance given a child the ray misses in the sort of a node's children: the largest float32, above any
# hit's entry (at most the best hit's t, below the finite max_t every caller passes).
NO_ENTRY = wp.constant(3.4028234663852886e38)

_StackI = wp.types.vector(length=STACK, dtype=wp.int32)
_StackF = wp.types.vector(length=STACK, dtype=wp.float32)


@wp.func
def ray_shear(d: wp.vec3):
    """The watertight test's per-ray constants: axes (kx, ky, kz), kz the largest |d| component, kx, ky
    swapped when d[kz] < 0 (winding kept), and shear S = (d[kx] / d[kz], d[ky] / d[kz], 1 / d[kz])."""
    ax = wp.abs(d[0])
    ay = wp.abs(d[1])
    az = wp.abs(d[2])
    kz = wp.int32(2)
    if ax > ay and ax > az:
        kz = 0
    elif ay > az:
        kz = 1
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    if d[kz] < 0.0:
        tmp = kx
        kx = ky
        ky = tmp
    return kx, ky, kz, wp.vec3(d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz])


@wp.func
def tri_hit(tris: wp.array[wp.vec3], k: wp.int32, o: wp.vec3, kx: wp.int32, ky: wp.int32, kz: wp.int32,
            S: wp.vec3, max_t: wp.float32):
    """Watertight test of triangle k (vertices tris[3k .. 3k + 2]) against o + t d (d's shear ``ray_shear``):
    (hit with t in [0, max_t), t, u, v). Edge functions that come out exactly 0 are recomputed in float64, as
    in Warp's intersect_ray_tri_woop."""
    A = tris[3 * k] - o
    B = tris[3 * k + 1] - o
    C = tris[3 * k + 2] - o
    Ax = A[kx] - S[0] * A[kz]
    Ay = A[ky] - S[1] * A[kz]
    Bx = B[kx] - S[0] * B[kz]
    By = B[ky] - S[1] * B[kz]
    Cx = C[kx] - S[0] * C[kz]
    Cy = C[ky] - S[1] * C[kz]
    U = Cx * By - Cy * Bx
    V = Ax * Cy - Ay * Cx
    W = Bx * Ay - By * Ax
    if U == 0.0 or V == 0.0 or W == 0.0:
        U = wp.float32(wp.float64(Cx) * wp.float64(By) - wp.float64(Cy) * wp.float64(Bx))
        V = wp.float32(wp.float64(Ax) * wp.float64(Cy) - wp.float64(Ay) * wp.float64(Cx))
        W = wp.float32(wp.float64(Bx) * wp.float64(Ay) - wp.float64(By) * wp.float64(Ax))
    t = wp.float32(0.0)
    u = wp.float32(0.0)
    v = wp.float32(0.0)
    hit = False
    if not ((U < 0.0 or V < 0.0 or W < 0.0) and (U > 0.0 or V > 0.0 or W > 0.0)):
        det = U + V + W
        if det != 0.0:
            r = 1.0 / det
            t = S[2] * (U * A[kz] + V * B[kz] + W * C[kz]) * r
            u = U * r
            v = V * r
            hit = t >= 0.0 and t < max_t
    return hit, t, u, v


def _make_query(anyhit: bool):
    @wp.func
    def query(bounds: wp.array[wp.vec4], kids: wp.array[wp.vec4i], tris: wp.array[wp.vec3], root: wp.int32,
              o: wp.vec3, d: wp.vec3, max_t: wp.float32):
        """(leaf-order triangle of the closest hit, or with ``anyhit`` the first found; -1 if none, t, u, v)"""
        idir = wp.vec3(0.0)
        for a in range(3):
            da = d[a]
            if wp.abs(da) < TINY_DIR:
                da = TINY_DIR
            idir[a] = 1.0 / da
        ox = wp.vec4(o[0])
        oy = wp.vec4(o[1])
        oz = wp.vec4(o[2])
        ix = wp.vec4(idir[0])
        iy = wp.vec4(idir[1])
        iz = wp.vec4(idir[2])
        zero4 = wp.vec4(0.0)
        nx = wp.where(idir[0] < 0.0, 3, 0)  # the rows (lo_x .. hi_z) of the near and far planes
        ny = wp.where(idir[1] < 0.0, 4, 1)
        nz = wp.where(idir[2] < 0.0, 5, 2)
        fx = (nx + 3) % 6
        fy = (ny + 3) % 6
        fz = (nz + 3) % 6
        kx, ky, kz, S = ray_shear(d)
        st = _StackI()
        stt = _StackF()
        sp = wp.int32(0)
        cur = wp.int32(root)
        best_t = wp.float32(max_t)
        best_k = wp.int32(-1)
        bu = wp.float32(0.0)
        bv = wp.float32(0.0)
        done = bool(False)  # noqa: UP018  (a dynamic variable: Warp refuses to mutate a constant in a loop)
        while not done:
            if cur >= 0:
                base = cur * 6
                tmin = wp.max(wp.max(wp.cw_mul(bounds[base + nx] - ox, ix), wp.cw_mul(bounds[base + ny] - oy, iy)),
                              wp.max(wp.cw_mul(bounds[base + nz] - oz, iz), zero4))
                tfar = wp.min(wp.min(wp.cw_mul(bounds[base + fx] - ox, ix), wp.cw_mul(bounds[base + fy] - oy, iy)),
                              wp.cw_mul(bounds[base + fz] - oz, iz))
                tmax = wp.min(tfar * SLAB_EPS, wp.vec4(best_t))
                ch = kids[cur]
                # children the ray enters, sorted near to far: a miss gets NO_ENTRY (beyond any hit's entry), then
                # odd-even transposition of the four (adjacent swaps on strictly greater: ties keep lane order,
                # the order an insertion sort gives), on scalars so nothing is indexed at run time; the swaps are
                # written out: as a @wp.func returning the pair they cost 17% of the cast (decision 0030)
                t0 = wp.where(tmin[0] <= tmax[0], tmin[0], NO_ENTRY)
                t1 = wp.where(tmin[1] <= tmax[1], tmin[1], NO_ENTRY)
                t2 = wp.where(tmin[2] <= tmax[2], tmin[2], NO_ENTRY)
                t3 = wp.where(tmin[3] <= tmax[3], tmin[3], NO_ENTRY)
                nh = wp.where(t0 < NO_ENTRY, 1, 0) + wp.where(t1 < NO_ENTRY, 1, 0) + wp.where(t2 < NO_ENTRY, 1, 0) \
                    + wp.where(t3 < NO_ENTRY, 1, 0)
                c0 = ch[0]
                c1 = ch[1]
                c2 = ch[2]
                c3 = ch[3]
                if nh == 1:  # the one child entered
                    c0 = wp.where(t0 < NO_ENTRY, c0, wp.where(t1 < NO_ENTRY, c1, wp.where(t2 < NO_ENTRY, c2, c3)))
                elif nh > 1:
                    for _r in range(2):
                        if t0 > t1:
                            tt = t0
                            t0 = t1
                            t1 = tt
                            cc = c0
                            c0 = c1
                            c1 = cc
                        if t2 > t3:
                            tt = t2
                            t2 = t3
                            t3 = tt
                            cc = c2
                            c2 = c3
                            c3 = cc
                        if t1 > t2:
                            tt = t1
                            t1 = t2
                            t2 = tt
                            cc = c1
                            c1 = c2
                            c2 = cc
                if nh > 0:
                    if nh > 3:
                        st[sp] = c3
                        stt[sp] = t3
                        sp += 1
                    if nh > 2:
                        st[sp] = c2
                        stt[sp] = t2
                        sp += 1
                    if nh > 1:
                        st[sp] = c1
                        stt[sp] = t1
                        sp += 1
                    cur = c0
                    continue
            else:
                lc = -2 - cur
                first = lc >> 3
                for k in range(first, first + (lc & 7)):
                    hit, t, u, v = tri_hit(tris, k, o, kx, ky, kz, S, best_t)
                    if hit:
                        best_t = t
                        best_k = k
                        bu = u
                        bv = v
                        if wp.static(anyhit):
                            done = True
                            break
                if wp.static(anyhit):
                    if done:
                        break
            cur = wp.int32(-1)
            while sp > 0:
                sp -= 1
                if stt[sp] <= best_t:
                    cur = st[sp]
                    break
            if cur == -1:
                done = True
        return best_k, best_t, bu, bv

    return query


_walk_closest = _make_query(False)
_walk_any = _make_query(True)


@wp.func
def blas_closest(bounds: wp.array[wp.vec4], kids: wp.array[wp.vec4i], tris: wp.array[wp.vec3],
                 face: wp.array[wp.int32], root: wp.int32, o: wp.vec3, d: wp.vec3, max_t: wp.float32):
    """Closest hit of o + t d, t in [0, max_t), in the tree whose root code is ``root``: (face or -1, t, u, v)."""
    k, t, u, v = _walk_closest(bounds, kids, tris, root, o, d, max_t)
    if k < 0:
        return wp.int32(-1), t, u, v
    return face[k], t, u, v


@wp.func
def blas_any(bounds: wp.array[wp.vec4], kids: wp.array[wp.vec4i], tris: wp.array[wp.vec3], root: wp.int32,
             o: wp.vec3, d: wp.vec3, max_t: wp.float32):
    """Is o + t d hit with t in [0, max_t) in the tree whose root code is ``root``? (the first hit ends it)"""
    k, t, u, v = _walk_any(bounds, kids, tris, root, o, d, max_t)
    return k >= 0


@wp.func
def face_vertices(tris: wp.array[wp.vec3], slot: wp.array[wp.int32], face0: wp.int32, face: wp.int32):
    """Vertices (a, b, c) of face ``face`` of the mesh whose faces start at ``face0`` in the atlas
    (``slot``: each face's triangle in leaf order)."""
    k = 3 * slot[face0 + face]
    return tris[k], tris[k + 1], tris[k + 2]


@wp.func
def eval_position(tris: wp.array[wp.vec3], slot: wp.array[wp.int32], face0: wp.int32, face: wp.int32,
                  u: wp.float32, v: wp.float32):
    """Point (u, v) of a face, u a + v b + (1 - u - v) c, as ``wp.mesh_eval_position`` computes it."""
    a, b, c = face_vertices(tris, slot, face0, face)
    return a * u + b * v + c * (1.0 - u - v)


@wp.kernel(enable_backward=False)
def refit_kernel(kids: wp.array[wp.vec4i], tris: wp.array[wp.vec3],
                 # outputs
                 bounds: wp.array[wp.vec4]):
    """Child boxes of every node of an atlas (one thread): nodes from last to first, since a child's index is
    larger than its parent's; a leaf child's box is its triangles' vertices' min / max, an inner child's the
    union of its own four boxes, an empty child's lo 1e30 > hi -1e30 (flowsynth.raycast.blas layout)."""
    for back in range(kids.shape[0]):
        n = kids.shape[0] - 1 - back
        ch = kids[n]
        lx = wp.vec4(1.0e30)
        ly = wp.vec4(1.0e30)
        lz = wp.vec4(1.0e30)
        hx = wp.vec4(-1.0e30)
        hy = wp.vec4(-1.0e30)
        hz = wp.vec4(-1.0e30)
        for j in range(4):
            c = ch[j]
            blo = wp.vec3(1.0e30)
            bhi = wp.vec3(-1.0e30)
            if c >= 0:
                for a in range(3):
                    blo[a] = wp.min(bounds[6 * c + a])
                    bhi[a] = wp.max(bounds[6 * c + 3 + a])
            elif c <= -2:
                lc = -2 - c
                for k in range(3 * (lc >> 3), 3 * ((lc >> 3) + (lc & 7))):
                    blo = wp.min(blo, tris[k])
                    bhi = wp.max(bhi, tris[k])
            lx[j] = blo[0]
            ly[j] = blo[1]
            lz[j] = blo[2]
            hx[j] = bhi[0]
            hy[j] = bhi[1]
            hz[j] = bhi[2]
        bounds[6 * n + 0] = lx
        bounds[6 * n + 1] = ly
        bounds[6 * n + 2] = lz
        bounds[6 * n + 3] = hx
        bounds[6 * n + 4] = hy
        bounds[6 * n + 5] = hz
