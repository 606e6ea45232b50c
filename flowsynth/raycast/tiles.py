"""Screen tiles: the primary cast's and the visibility rays' per-(frame, tile) candidate lists, near to far.

Below ``flowsynth.raycast.accel.ORDERED_MAX`` instances a camera ray walks the list of its TILE x TILE pixel screen tile
instead of the top-level BVH: the instances whose convex hull, clipped to z >= ``CLIP_Z``, projects within a pixel
of the tile (``_screen_bounds``; a lens camera bounds its rays' normalised coordinates instead, ``_lens_tile_mask``).
"""

from __future__ import annotations

import numpy as np
import trimesh

from flowsynth.kernels import wp_runtime
from flowsynth.raycast.culling import hull_points

__all__ = ["CLIP_Z", "LENS_TILE_BOUNDS", "TILE", "join_tiles", "posed_hull", "tile_struct", "tile_tables"]

# Primary rays take their candidate list from their TILE x TILE pixel screen tile (benchmarks/speed/tiles.py:
# 1.30 Mrays/s with one list per frame, 1.48 with 16 px tiles, same hits; docs/decisions/0002-screen-tiles-16px.md).
TILE = 16  # a power of two: the kernels find a pixel's tile by a shift


def tile_tables(meshes: list[trimesh.Trimesh], cam_T_obj: np.ndarray, order: np.ndarray | None, camera,
                bounds: dict, posed: list | None = None) -> tuple[np.ndarray, np.ndarray, int, int] | None:
    """The per-(frame, screen tile) candidate lists of one clip of N instances in F frames (``cam_T_obj`` (F, N, 4,
    4)) in numpy: CSR (start (F ty tx + 1,), items) int32 and the tile grid (tx, ty), holding per tile the items of
    ``order`` (F, N') (the clip's items f N + n near to far: all N, or those that are not flat) whose hull, clipped
    to z >= ``CLIP_Z``, projects within a pixel of the tile (``_screen_bounds``), near to far. ``order`` None: None
    (the rays walk the BVH). ``bounds``: the caller's memo of screen bounds per camera (keyed by its size, K and
    lens). ``posed``: each instance's hull points already posed by ``posed_hull`` (the accel's), or None."""
    if TILE <= 0 or TILE & (TILE - 1):
        raise ValueError(f"flowsynth.raycast.tiles.TILE must be a power of two, got {TILE}")
    if order is None:
        return None
    kb = (camera.width, camera.height, camera.K.tobytes(), camera.model, camera.dist)
    if camera.is_pinhole:
        if kb not in bounds:
            bounds[kb] = _screen_bounds(meshes, cam_T_obj, camera.K, posed)
        return _tile_lists(bounds[kb], order, camera.width, camera.height, TILE)
    # a lens model: rays' normalised coordinates per tile against the hulls' (_lens_tile_mask)
    if kb not in bounds:
        bounds[kb] = _screen_bounds(meshes, cam_T_obj, np.eye(3), posed)
    mask = _lens_tile_mask(bounds[kb], order, camera, TILE)
    start, items = _csr_lists(mask, order)
    ty, tx = mask.shape[2:]
    return start, items, tx, ty


def join_tiles(lists: list, item0: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The lists of a batch of clips (``tile_tables`` of each, None where a clip's rays walk the BVH) as one CSR
    over the batch's frames, clip b's items shifted by its first item ``item0[b]``; a clip without lists gets empty
    ones. One clip is returned as it is (no lists at all: one empty list on a 1 x 1 grid)."""
    grids = {(x[2], x[3]) for x in lists if x is not None}
    if not grids:
        return np.zeros(2, np.int32), np.zeros(1, np.int32), 1, 1
    if len(lists) == 1:
        return lists[0]
    tx, ty = grids.pop()
    starts, items, total = [], [], 0
    for b, x in enumerate(lists):
        if x is None:
            starts.append(np.full(frames * ty * tx, total, np.int64))
            continue
        starts.append(x[0][:-1].astype(np.int64) + total)
        items.append(x[1][:x[0][-1]].astype(np.int64) + item0[b])
        total += int(x[0][-1])
    start = np.concatenate(starts + [np.array([total])]).astype(np.int32)
    return start, (np.concatenate(items).astype(np.int32) if total else np.zeros(1, np.int32)), tx, ty


def tile_struct(lists: tuple[np.ndarray, np.ndarray, int, int], device: str = "cpu"):
    """The ``TileLists`` struct (flowsynth.kernels.raycast) of CSR lists (start, items, tx, ty) on ``device``."""
    from flowsynth.kernels.raycast import TileLists

    wp = wp_runtime()
    start, items, tx, ty = lists
    t = TileLists()
    t.start = wp.array(start, dtype=wp.int32, device=device)
    t.items = wp.array(items if len(items) else np.zeros(1, np.int32), dtype=wp.int32, device=device)
    t.tiles_x, t.tiles_y, t.tile_shift = tx, ty, TILE.bit_length() - 1
    return t


# Screen bounds of an instance's hull clip it at this depth [m]: the part nearer the camera plane is not seen.
CLIP_Z = 1e-9
# Hulls of up to this many points are clipped at CLIP_Z pair by pair (V^2 per frame); a larger hull reaching
# behind the camera plane gets every tile.
CLIP_MAX_POINTS = 64


def posed_hull(hull: np.ndarray, cam_T_obj: np.ndarray) -> np.ndarray:
    """Hull points (K, 3) in the camera frames of one instance's ``cam_T_obj`` (F, 4, 4): (F, K, 3) float64."""
    return np.matmul(hull, np.swapaxes(cam_T_obj[:, :3, :3], 1, 2)) + cam_T_obj[:, None, :3, 3]


def _screen_bounds(meshes: list[trimesh.Trimesh], cam_T_obj: np.ndarray, K: np.ndarray,
                   posed: list | None = None) -> np.ndarray:
    """(F, N, 4) float64 (u_min, u_max, v_min, v_max) [px] of the projection of each instance's convex hull
    clipped to z >= ``CLIP_Z`` (camera frame of ``cam_T_obj`` (F, N, 4, 4)), NaN where nothing of it lies
    there. The clipped hull is the convex hull of its points with z >= CLIP_Z and of the points where the
    segments between a point in front and one behind cross z = CLIP_Z; perspective projection keeps convex
    sets convex, so the bounds of those points' projections bound every hit a camera ray can make. A hull
    of more than ``CLIP_MAX_POINTS`` points reaching behind the plane gets infinite bounds (every tile).
    ``posed``: the instances' hull points posed by ``posed_hull`` where the caller has them."""
    F, N = cam_T_obj.shape[:2]
    out = np.full((F, N, 4), np.nan)
    for n, m in enumerate(meshes):
        P = posed_hull(hull_points(m), cam_T_obj[:, n]) if posed is None else posed[n]
        z = P[..., 2]
        front = z >= CLIP_Z  # (F, V)
        if front.all():  # every point in front (the common case): the same values without the masks
            u = (K[0, 0] * P[..., 0] + K[0, 1] * P[..., 1]) / z + K[0, 2]
            v = K[1, 1] * P[..., 1] / z + K[1, 2]
            out[:, n] = np.stack([u.min(1), u.max(1), v.min(1), v.max(1)], -1)
            continue
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
