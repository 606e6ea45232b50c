"""Independent float64 numpy oracles for the ground-truth tests, ``benchmarks/accuracy/accuracy.py`` and
``benchmarks/peers/peers_physics.py``.

Nothing here calls flowsynth's ray caster, flow or annotation code. Conventions (docs/conventions.md):
OpenCV camera axes (x right, y down, z forward), ``a_T_b`` maps b-frame points into frame a, the centre of
pixel (row i, col j) is (u, v) = (j, i), and a camera point (x, y, z) projects to
u = (fx x + s y) / z + cx, v = fy y / z + cy.

Ray casting is brute force: Moller-Trumbore against every triangle of every posed mesh, in world
coordinates, float64. A per-object bounding-sphere test only skips rays that cannot hit that object.
Mesh penetration comes from python-fcl contact depths (trimesh's CollisionManager), not from Newton.
"""

from __future__ import annotations

import numpy as np
import trimesh
from trimesh.collision import CollisionManager

# Slack on the barycentric inside test: rays through a shared edge or vertex hit at least one triangle.
BARY_EPS = 1e-12
# Rays to test against one object's triangles at a time (bounds the (rays, faces) temporaries).
CHUNK = 1 << 21
# Relative tolerance of the oracle's visibility test: the point is hidden when a surface is hit closer
# than (1 - VIS_TOL) times its distance from the target camera centre.
VIS_TOL = 1e-6
# Oracle motion threshold [m] on the world displacement of the surface point.
MOTION_TOL = 1e-7


def rotation(rotvec) -> np.ndarray:
    """(3, 3) rotation matrix of an axis-angle vector [rad] (Rodrigues)."""
    r = np.asarray(rotvec, np.float64)
    a = np.linalg.norm(r)
    if a == 0.0:
        return np.eye(3)
    k = r / a
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(a) * Kx + (1.0 - np.cos(a)) * Kx @ Kx


def pose(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) rigid transform [R(rotvec) t; 0 1]."""
    T = np.eye(4)
    T[:3, :3] = rotation(rotvec)
    T[:3, 3] = t
    return T


def quad(half: float) -> trimesh.Trimesh:
    """Two-triangle square in the object plane z = 0, side 2 * half [m], normal +z."""
    V = np.array([[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]])
    return trimesh.Trimesh(V, np.array([[0, 1, 2], [0, 2, 3]]), process=False)


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """world_T_cam (4, 4) of an OpenCV camera at ``eye`` looking at ``target``; ``up`` is roughly -y_cam."""
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, np.float64), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4)."""
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def apply(T: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Apply (4, 4) or per-point (P, 4, 4) transforms to points (P, 3)."""
    if T.ndim == 2:
        return X @ T[:3, :3].T + T[:3, 3]
    return np.einsum("pij,pj->pi", T[:, :3, :3], X) + T[:, :3, 3]


def project(K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixel coordinates (P, 2) of camera-frame points (P, 3) with z != 0 (skew included)."""
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    return np.stack([(K[0, 0] * x + K[0, 1] * y) / z + K[0, 2], K[1, 1] * y / z + K[1, 2]], 1)


def pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Unit camera-frame directions (H, W, 3) through the pixel centres (u, v) = (j, i)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = (u - K[0, 2] - K[0, 1] * y) / K[0, 0]
    d = np.stack([x, y, np.ones_like(x)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def ray_cast(origins: np.ndarray, dirs: np.ndarray, meshes, world_T_obj: np.ndarray) -> dict:
    """Closest hit with t > 0 of rays o + t d (world frame, unit d) over all posed meshes.

    Args:
        origins: (R, 3) or (3,) world points; dirs: (R, 3) unit world directions.
        meshes: N trimesh meshes (object frame); world_T_obj: (N, 4, 4) their poses.
    Returns:
        dict with ``t`` (R,) [inf = miss], ``obj`` (R,) 0-based object [-1 = miss], ``face`` (R,),
        ``bary`` (R, 2) barycentric (u, v) of the hit, ``p`` (R, 3) object-frame hit point.
    """
    R = len(dirs)
    o_all = np.broadcast_to(np.asarray(origins, np.float64), (R, 3))
    best_t = np.full(R, np.inf)
    best_obj = np.full(R, -1)
    best_face = np.full(R, -1)
    best_uv = np.zeros((R, 2))
    for n, (mesh, P) in enumerate(zip(meshes, world_T_obj)):
        V = apply(P, np.asarray(mesh.vertices, np.float64))
        tri = V[np.asarray(mesh.faces)]
        centre = 0.5 * (V.min(0) + V.max(0))
        radius = np.linalg.norm(V - centre, axis=1).max() * (1 + 1e-9) + 1e-9
        oc = centre - o_all
        tc = np.einsum("ri,ri->r", oc, dirs)
        miss2 = np.einsum("ri,ri->r", oc, oc) - tc * tc
        cand = np.nonzero((miss2 <= radius * radius) & (tc + radius > 0))[0]
        v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        step = max(1, CHUNK // len(tri))
        for s in range(0, len(cand), step):
            idx = cand[s:s + step]
            t, f, uv = _moller_trumbore(o_all[idx], dirs[idx], v0, e1, e2)
            better = t < best_t[idx]
            k = idx[better]
            best_t[k], best_obj[k], best_face[k], best_uv[k] = t[better], n, f[better], uv[better]
    p = np.zeros((R, 3))
    for n, mesh in enumerate(meshes):
        sel = best_obj == n
        if sel.any():
            tri = np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.faces)[best_face[sel]]]
            u, v = best_uv[sel, 0:1], best_uv[sel, 1:2]
            p[sel] = (1 - u - v) * tri[:, 0] + u * tri[:, 1] + v * tri[:, 2]
    return {"t": best_t, "obj": best_obj, "face": best_face, "bary": best_uv, "p": p}


def _moller_trumbore(o, d, v0, e1, e2):
    """Closest t > 0 per ray over triangles (v0, e1, e2): (t [inf = miss], face, (u, v))."""
    dx, dy, dz = (d[:, None, k] for k in range(3))
    px = dy * e2[None, :, 2] - dz * e2[None, :, 1]
    py = dz * e2[None, :, 0] - dx * e2[None, :, 2]
    pz = dx * e2[None, :, 1] - dy * e2[None, :, 0]
    det = px * e1[None, :, 0] + py * e1[None, :, 1] + pz * e1[None, :, 2]
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    ok = np.abs(det) > 1e-14 * scale[None]
    inv = 1.0 / np.where(ok, det, 1.0)
    sx, sy, sz = (o[:, None, k] - v0[None, :, k] for k in range(3))
    u = (sx * px + sy * py + sz * pz) * inv
    qx = sy * e1[None, :, 2] - sz * e1[None, :, 1]
    qy = sz * e1[None, :, 0] - sx * e1[None, :, 2]
    qz = sx * e1[None, :, 1] - sy * e1[None, :, 0]
    v = (dx * qx + dy * qy + dz * qz) * inv
    t = (qx * e2[None, :, 0] + qy * e2[None, :, 1] + qz * e2[None, :, 2]) * inv
    hit = ok & (u >= -BARY_EPS) & (v >= -BARY_EPS) & (u + v <= 1 + BARY_EPS) & (t > 0)
    t = np.where(hit, t, np.inf)
    f = t.argmin(1)
    r = np.arange(len(f))
    return t[r, f], f, np.stack([u[r, f], v[r, f]], 1)


def cast_frame(K: np.ndarray, width: int, height: int, world_T_cam: np.ndarray, meshes,
               world_T_obj: np.ndarray) -> dict:
    """Primary cast of one frame: ``ray_cast`` results reshaped to (H, W, ...), plus ``instance``
    (H, W) 1-based id (0 = nothing) and ``hit`` (H, W) bool."""
    d = pixel_rays(K, width, height).reshape(-1, 3) @ world_T_cam[:3, :3].T
    res = ray_cast(world_T_cam[:3, 3], d, meshes, world_T_obj)
    out = {k: v.reshape(height, width, *v.shape[1:]) for k, v in res.items()}
    out["instance"] = out["obj"] + 1
    out["hit"] = out["obj"] >= 0
    return out


def visible(X_world: np.ndarray, world_T_cam: np.ndarray, meshes, world_T_obj: np.ndarray) -> np.ndarray:
    """(P,) True where the segment from the camera centre to each world point X (P, 3) is unobstructed:
    the closest hit along the ray towards X is at least (1 - VIS_TOL) |X - c| away."""
    c = world_T_cam[:3, 3]
    d = X_world - c
    L = np.linalg.norm(d, axis=1)
    res = ray_cast(c, d / L[:, None], meshes, world_T_obj)
    return res["t"] >= L * (1.0 - VIS_TOL)


def pair_truth(K, width, height, world_T_cam, meshes, world_T_obj, src: int, dst: int,
               casts: dict | None = None, occlusion: bool = True) -> dict:
    """Flow-family ground truth of frame ``src`` towards frame ``dst`` (definitions of flowsynth/truth/flow.py).

    Args:
        world_T_cam: (T, 4, 4); world_T_obj: (T, N, 4, 4); casts: optional cache {frame: cast_frame(...)}.
    Returns (H, W, ...) float64 / bool arrays: ``flow`` (H, W, 2) [px] (0 where not valid), ``uv`` target
    pixel coordinates, ``z`` target depth [m], ``hit``, ``valid``, ``oof``, ``occ`` (when ``occlusion``),
    ``motion`` (only meaningful for dst = src + 1), ``disp`` world displacement [m], ``instance``,
    ``X_world`` the moved world point.
    """
    casts = {} if casts is None else casts
    for f in (src, dst):
        if f not in casts:
            casts[f] = cast_frame(K, width, height, world_T_cam[f], meshes, world_T_obj[f])
    c = casts[src]
    hit = c["hit"]
    i, j = np.nonzero(hit)
    n = c["obj"][i, j]
    p = c["p"][i, j]
    Xw_src = apply(world_T_obj[src, n], p)
    Xw = apply(world_T_obj[dst, n], p)
    X = apply(rigid_inverse(world_T_cam[dst]), Xw)
    front = X[:, 2] > 0
    uv = np.where(front[:, None], project(K, np.where(front[:, None], X, 1.0)), 0.0)
    inside = (front & (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5)
              & (uv[:, 1] >= -0.5) & (uv[:, 1] < height - 0.5))
    out = {"hit": hit, "instance": c["instance"]}
    shape2 = (height, width, 2)
    for key, val, fill in (("uv", uv, 0.0), ("z", X[:, 2], 0.0), ("valid", front, False),
                           ("oof", ~inside, False), ("X_world", Xw, 0.0)):
        a = np.full((height, width) + val.shape[1:], fill, dtype=val.dtype)
        a[i, j] = val
        out[key] = a
    flow = np.zeros(shape2)
    flow[i, j] = np.where(front[:, None], uv - np.stack([j, i], 1), 0.0)
    out["flow"] = flow
    disp = np.zeros((height, width))
    disp[i, j] = np.linalg.norm(Xw - Xw_src, axis=1)
    out["disp"] = disp
    out["motion"] = disp > MOTION_TOL
    if occlusion:
        vis = np.zeros(len(i), bool)
        k = np.nonzero(inside)[0]
        if len(k):
            vis[k] = visible(Xw[k], world_T_cam[dst], meshes, world_T_obj[dst])
        occ = np.zeros((height, width), bool)
        occ[i, j] = ~vis
        out["occ"] = occ
    return out


def boundary(inst: np.ndarray) -> np.ndarray:
    """(H, W) True where the 3x3 neighbourhood of a pixel in the id map ``inst`` holds more than one id."""
    pad = np.pad(inst, 1, mode="edge")
    H, W = inst.shape
    out = np.zeros((H, W), bool)
    for di in range(3):
        for dj in range(3):
            out |= pad[di:di + H, dj:dj + W] != inst
    return out


def silhouette(inst_src: np.ndarray, inst_dst: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Silhouette pixels of a frame pair (H, W) bool: the pixel's 3x3 neighbourhood in the source
    instance map holds more than one id, or the 3x3 neighbourhood of the target pixel nearest to its
    projection ``uv`` (H, W, 2) (clamped into the image) does in the target instance map."""
    H, W = inst_src.shape
    jj = np.clip(np.rint(uv[..., 0]), 0, W - 1).astype(int)
    ii = np.clip(np.rint(uv[..., 1]), 0, H - 1).astype(int)
    return boundary(inst_src) | boundary(inst_dst)[ii, jj]


def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample (H, W, C) ``img`` at pixel coordinates uv (P, 2) bilinearly (pixel centres at integers)."""
    H, W = img.shape[:2]
    u = np.clip(uv[:, 0], 0, W - 1)
    v = np.clip(uv[:, 1], 0, H - 1)
    j0 = np.minimum(np.floor(u).astype(int), W - 2)
    i0 = np.minimum(np.floor(v).astype(int), H - 2)
    a = (u - j0)[:, None]
    b = (v - i0)[:, None]
    return ((1 - a) * (1 - b) * img[i0, j0] + a * (1 - b) * img[i0, j0 + 1]
            + (1 - a) * b * img[i0 + 1, j0] + a * b * img[i0 + 1, j0 + 1])


def plane_homography(K: np.ndarray, src_cam_T_obj: np.ndarray, dst_cam_T_obj: np.ndarray,
                     normal_obj=(0.0, 0.0, 1.0), offset_obj: float = 0.0) -> np.ndarray:
    """Homography (3, 3) mapping source pixels to target pixels for the object plane n_o . p = d_o.

    In the source camera frame the plane is n . X = d with n = R_s n_o and d = d_o + n . t_s. A point
    moves as X' = A X + a with [A | a] = dst_cam_T_obj @ inv(src_cam_T_obj); on the plane 1 = n . X / d, so
    X' = (A + a n^T / d) X and H = K (A + a n^T / d) K^-1. (With the plane written n . X + d' = 0,
    d' = -d, this is the textbook K (R - t n^T / d') K^-1.)
    """
    n = src_cam_T_obj[:3, :3] @ np.asarray(normal_obj, np.float64)
    d = offset_obj + n @ src_cam_T_obj[:3, 3]
    M = dst_cam_T_obj @ rigid_inverse(src_cam_T_obj)
    return K @ (M[:3, :3] + np.outer(M[:3, 3], n) / d) @ np.linalg.inv(K)


def homography_flow(Hm: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 2) flow [px] of the homography ``Hm`` at every pixel centre."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = np.stack([u, v, np.ones_like(u)], -1) @ Hm.T
    return x[..., :2] / x[..., 2:3] - np.stack([u, v], -1)


def max_penetration(assets, poses: np.ndarray) -> float:
    """Deepest overlap of two visual meshes over all frames / smaller size (python-fcl contact depths)."""
    sizes = [a.size for a in assets]
    cm = CollisionManager()
    for i, a in enumerate(assets):
        cm.add_object(str(i), a.mesh)
    worst = 0.0
    for t in range(poses.shape[0]):
        for i in range(len(assets)):
            cm.set_transform(str(i), poses[t, i])
        _, contacts = cm.in_collision_internal(return_data=True)
        for c in contacts:
            i, j = (int(name) for name in c.names)
            worst = max(worst, c.depth / min(sizes[i], sizes[j]))
    return worst
