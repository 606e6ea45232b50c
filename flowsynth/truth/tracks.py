"""Long-range point tracks (TAP-Vid layout) from the primary cast's object-frame hit points.

Q = ``num_tracks`` query pixels are drawn from the pixels of all T frames that see a surface (with a seeded
generator: a pure function of the sample's seed), by ``track_sampling``:

- ``"uniform"``: every such pixel equally likely;
- ``"objects"``: only pixels of objects that are not background (BouncingThings: not the room);
- ``"edges"``: only pixels within one pixel of a depth edge: their 3x3 neighbourhood holds another
  instance, no hit, or a depth differing by more than ``EDGE_REL_DEPTH`` relative.

Draws are without replacement while the pool holds at least Q pixels, with replacement otherwise; an
empty pool of "objects" or "edges" falls back to "uniform". A query pixel (row i, column j) of frame t_q
sees instance n at object-frame point p; in every frame f the track is

    X_f = cam_T_world[f] world_T_obj[f, n] p                          (float64)
    target_points[q, f] = pi(X_f) = (u, v) [px]   (0 where X_f.z <= 0)
    occluded[q, f] = X_f.z <= 0  or  pi(X_f) outside [-0.5, W - 0.5) x [-0.5, H - 0.5)
                     or the ray from camera f towards X_f hits a surface closer than
                     (1 - VISIBILITY_REL_TOL) |X_f|                  (the visibility rays of occlusion)
    query_points[q] = (t_q, i, j)   (TAP-Vid order (t, y, x))

where pi is the camera's projection, through its lens model if it has one (flowsynth/scene/camera.py; "X_f.z <= 0"
then reads "X_f outside the model's domain"),
so target_points[q, t_q] = (j, i) and occluded[q, t_q] is False. Pixel coordinates follow flowsynth's
convention (pixel centres at integers); TAP-Vid's Kubric data puts them at +0.5 (``flowsynth.io.sampleio``
converts when it writes ``tapvid.pkl``). If no pixel of the clip sees anything, every track is occluded
in every frame and all coordinates are 0.
"""

from __future__ import annotations

import numpy as np
import torch

from flowsynth.raycast import HostGBuffer
from flowsynth.truth.flow import reproject, visibility

__all__ = ["EDGE_REL_DEPTH", "track_outputs"]

# "edges" sampling: a depth step larger than this fraction of the pixel's depth counts as an edge.
EDGE_REL_DEPTH = 0.05


def _edge_mask(gb: HostGBuffer, dz: np.ndarray) -> np.ndarray:
    """(T, H, W) True where a hit pixel's 3x3 neighbourhood holds another instance, a miss or a depth step."""
    idx = gb.instance_index
    depth = gb.dist.astype(np.float64) * dz
    T, H, W = depth.shape
    pi = np.pad(idx, ((0, 0), (1, 1), (1, 1)), mode="edge")
    pd = np.pad(depth, ((0, 0), (1, 1), (1, 1)), mode="edge")
    edge = np.zeros((T, H, W), bool)
    for di in range(3):
        for dj in range(3):
            ni, nd = pi[:, di:di + H, dj:dj + W], pd[:, di:di + H, dj:dj + W]
            edge |= (ni != idx) | (np.abs(nd - depth) > EDGE_REL_DEPTH * depth)
    return edge & gb.hit


def _pool(scene, gb: HostGBuffer, sampling: str) -> np.ndarray:
    """(P, 3) candidate (frame, row, column) of the sampling rule (uniform when the rule finds none)."""
    hit = gb.hit
    if sampling == "objects":
        fg = np.array([not o.background for o in scene.objects] + [False])
        mask = hit & fg[gb.instance_index]
    elif sampling == "edges":
        mask = _edge_mask(gb, scene.camera.pixel_rays_numpy()[..., 2])
    else:
        mask = hit
    if not mask.any():
        mask = hit
    return np.argwhere(mask)


def track_outputs(scene, accel, gb, plan, world_T_obj: np.ndarray, cam_T_world: np.ndarray) -> dict:
    """``target_points`` (Q, T, 2) float32 [px], ``occluded`` (Q, T) bool, ``query_points`` (Q, 3) float32
    (t, y, x) for the plan's ``num_tracks`` Q and ``track_sampling``, seeded by ``plan.seed``."""
    T, H, W = gb.shape
    Q = plan.num_tracks
    host = gb.host()  # the hand-over: tracks are sampled and reprojected on the host (sparse points)
    pool = _pool(scene, host, plan.track_sampling)
    target = np.zeros((Q, T, 2), np.float32)
    occluded = np.ones((Q, T), bool)
    query = np.zeros((Q, 3), np.float32)
    if len(pool):
        rng = np.random.default_rng([plan.seed, 17])
        pick = pool[rng.choice(len(pool), Q, replace=len(pool) < Q)]
        fq, i, j = pick[:, 0], pick[:, 1], pick[:, 2]
        n = host.instance_index[fq, i, j]
        p = np.repeat(host.point[fq, i, j].astype(np.float64), T, axis=0)  # (Q*T, 3), track-major
        f = np.tile(np.arange(T), Q)
        M = np.matmul(cam_T_world[f], world_T_obj[f, np.repeat(n, T)])
        X, uv = reproject(p, M, scene.camera.K)
        front = X[:, 2] > 0
        if not scene.camera.is_pinhole:  # through the lens model: in its domain only (flowsynth/scene/camera.py)
            uv, front = scene.camera.project(X)
        inside = front & (uv[:, 0] >= -0.5) & (uv[:, 0] < W - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < H - 0.5)
        occ = ~inside
        occ[inside] = visibility(accel, [(X[inside], f[inside])], plan.threads)
        target = uv.reshape(Q, T, 2).astype(np.float32)
        occluded = occ.reshape(Q, T)
        query = np.stack([fq, i, j], 1).astype(np.float32)
    out = {"target_points": torch.from_numpy(target), "occluded": torch.from_numpy(occluded),
           "query_points": torch.from_numpy(query)}
    return {k: v for k, v in out.items() if k in plan.outputs}
