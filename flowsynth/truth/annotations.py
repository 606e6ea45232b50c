"""Per-object tables: categories, poses, 3D and 2D boxes, visible pixel counts, padded to max_objects.

Box conventions (image coordinates, pixel (row i, col j) centred at (u, v) = (j, i)):

- ``box3d_corners`` (T, N, 8, 3) world [m]: corners of the object-frame axis-aligned bounding box,
  corner c = (lo + b * (hi - lo)) with bits b = ((c >> 2) & 1, (c >> 1) & 1, c & 1) over (x, y, z),
  mapped by world_T_obj of the frame — the object's oriented box.
- ``box2d_amodal`` (T, N, 4) xyxy [px]: extent of the whole projected mesh (occluded parts included),
  edges crossing the near plane z = NEAR are cut there, then clipped to the image rectangle
  [-0.5, W - 0.5] x [-0.5, H - 0.5]. Objects entirely behind the camera or outside the image: all 0.
  With a lens model (flowsynth/scene/camera.py) the edges are curves in the image: the box bounds the projections
  of the vertices and of ``LENS_EDGE_SAMPLES`` - 1 evenly spaced points inside each edge that lie in the
  model's domain (the outline of a projected mesh is made of projected edges), so it can fall short of the
  true extent by the edge's bulge between two samples.
- ``box2d_visible`` (T, N, 4) xyxy [px]: extent of the pixels showing the object in the instance map,
  pixel edges included: (j_min - 0.5, i_min - 0.5, j_max + 0.5, i_max + 0.5); all 0 when not visible.
- ``visible_pixels`` (T, N) int32: pixels of the instance map showing the object.

Rows list the scene's non-background objects in instance order (BouncingThings: row n is instance
n + 1); background objects such as the room are rendered but have no row.
"""

from __future__ import annotations

import numpy as np
import torch

from flowsynth.errors import ConfigError

__all__ = ["LENS_EDGE_SAMPLES", "NEAR", "amodal_box", "object_tables"]

# Near plane [m] at which mesh edges crossing behind the camera are cut for the amodal box.
NEAR = 1e-6
# Intervals per mesh edge sampled for the amodal box of a lens camera.
LENS_EDGE_SAMPLES = 16
_BITS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)], np.float64)


def amodal_box(V_cam: np.ndarray, edges: np.ndarray, K: np.ndarray, W: int, H: int, camera=None) -> np.ndarray:
    """xyxy box of camera-frame mesh vertices ``V_cam`` (V, 3) with ``edges`` (E, 2), clipped to the image;
    through ``camera``'s lens model when it has one (module docstring)."""
    if camera is not None and not camera.is_pinhole:
        s = np.linspace(0.0, 1.0, LENS_EDGE_SAMPLES + 1)[:, None, None]
        a, b = V_cam[edges[:, 0]], V_cam[edges[:, 1]]
        uv, ok = camera.project(np.concatenate([V_cam, (a + s * (b - a)).reshape(-1, 3)]))
        if not ok.any():
            return np.zeros(4)
        return _clip_box(uv[ok], W, H)
    front = V_cam[:, 2] > NEAR
    pts = [V_cam[front]]
    a, b = V_cam[edges[:, 0]], V_cam[edges[:, 1]]
    cross = (a[:, 2] > NEAR) != (b[:, 2] > NEAR)
    if cross.any():
        a, b = a[cross], b[cross]
        s = (NEAR - a[:, 2]) / (b[:, 2] - a[:, 2])
        pts.append(a + s[:, None] * (b - a))
    P = np.concatenate(pts)
    if len(P) == 0:
        return np.zeros(4)
    uvw = P @ K.T
    return _clip_box(uvw[:, :2] / uvw[:, 2:3], W, H)


def _clip_box(uv: np.ndarray, W: int, H: int) -> np.ndarray:
    x0, y0 = uv.min(0)
    x1, y1 = uv.max(0)
    if x1 < -0.5 or y1 < -0.5 or x0 > W - 0.5 or y0 > H - 0.5:
        return np.zeros(4)
    return np.array([max(x0, -0.5), max(y0, -0.5), min(x1, W - 0.5), min(y1, H - 0.5)])


def object_tables(scene, gb, plan, world_T_obj: np.ndarray, cam_T_world: np.ndarray) -> dict:
    """Padded object tables (see module docstring) for the keys the plan asks for."""
    T, H, W = gb.shape
    rows = [n for n, o in enumerate(scene.objects) if not o.background]  # table row r <- scene object rows[r]
    objects = [scene.objects[n] for n in rows]
    N = len(rows)
    Nmax = N if plan.max_objects is None else plan.max_objects
    if N > Nmax:
        raise ConfigError(f"scene has {N} objects but max_objects={Nmax}; raise max_objects")
    world_T_obj = world_T_obj[:, rows]
    want = set(plan.outputs)
    out = {
        "object_valid": np.zeros(Nmax, bool),
        "object_category": np.zeros(Nmax, np.int32),
        "object_asset": np.zeros(Nmax, np.int32),
        "world_T_obj": np.zeros((T, Nmax, 4, 4), np.float32),
    }
    out["object_valid"][:N] = True
    out["object_category"][:N] = [o.category for o in objects]
    out["object_asset"][:N] = [o.asset for o in objects]
    out["world_T_obj"][:, :N] = world_T_obj
    if "box3d_corners" in want:
        box = np.zeros((T, Nmax, 8, 3), np.float32)
        for n, o in enumerate(objects):
            lo, hi = o.mesh.bounds
            c = lo + _BITS * (hi - lo)
            box[:, n] = np.einsum("tij,kj->tki", world_T_obj[:, n, :3, :3], c) + world_T_obj[:, n, None, :3, 3]
        out["box3d_corners"] = box
    if "box2d_amodal" in want:
        amodal = np.zeros((T, Nmax, 4), np.float32)
        K = scene.camera.K
        for n, o in enumerate(objects):
            V = np.asarray(o.mesh.vertices, np.float64)
            edges = np.asarray(o.mesh.edges_unique)
            cam_T_obj = np.einsum("tij,tjk->tik", cam_T_world, world_T_obj[:, n])
            for t in range(T):
                Vc = V @ cam_T_obj[t, :3, :3].T + cam_T_obj[t, :3, 3]
                amodal[t, n] = amodal_box(Vc, edges, K, W, H, scene.camera)
        out["box2d_amodal"] = amodal
    if "box2d_visible" in want or "visible_pixels" in want:
        row_of = np.full(len(scene.objects) + 1, -1)  # scene object index -> table row, -1 -> -1
        row_of[rows] = np.arange(N)
        out["box2d_visible"], out["visible_pixels"] = _visible(row_of[gb.host().instance_index], Nmax)  # on the host
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items() if k in want}


def _visible(idx: np.ndarray, Nmax: int) -> tuple[np.ndarray, np.ndarray]:
    T, _, W = idx.shape
    boxes = np.zeros((T, Nmax, 4), np.float32)
    counts = np.zeros((T, Nmax), np.int32)
    for t in range(T):
        lab = idx[t].reshape(-1)
        hit = lab >= 0
        if not hit.any():
            continue
        lab_h = lab[hit]
        rows, cols = np.divmod(np.nonzero(hit)[0], W)
        counts[t] = np.bincount(lab_h, minlength=Nmax)[:Nmax]
        big = np.iinfo(np.int64).max
        for arr, k0, k1 in ((cols, 0, 2), (rows, 1, 3)):
            mn = np.full(Nmax, big)
            mx = np.full(Nmax, -1)
            np.minimum.at(mn, lab_h, arr)
            np.maximum.at(mx, lab_h, arr)
            seen = counts[t] > 0
            boxes[t, seen, k0] = mn[seen] - 0.5
            boxes[t, seen, k1] = mx[seen] + 0.5
    return boxes, counts
