"""Depth of field of the final pass: a gather over each pixel's neighbours with occlusion-aware weights.

Every pixel q spreads its linear radiance uniformly over a disc of radius r_q (half its circle of confusion,
at least 1/2 px, so a sharp pixel covers only itself). Output pixel p gathers, from every q within the
launch's search radius R, the radiance of those whose disc covers p, weighted by 1 / r_q^2 (a disc's radiance
per unit area), and divides by the sum of the weights:

    out(p) = sum_q w(p, q) L(q) / sum_q w(p, q),   w(p, q) = [|p - q| <= r_q] [z_q <= z_p or |p - q| <= r_p] / r_q^2

The second bracket is the occlusion rule: a sample behind p (z_q > z_p) reaches p only where p's own disc
reaches q, so a sharp foreground never takes on the blur of the background behind it, while a blurred
foreground spreads over whatever lies behind it. p itself always has weight 1 / r_p^2 > 0.
flowsynth/renderer/finalpass.py launches it; docs/rendering.md (Final pass) states the model and its limits.
"""

from __future__ import annotations

import warp as wp

__all__ = ["MIN_COC_RADIUS", "dof_gather_kernel"]

# Smallest disc radius [px]: a pixel in focus covers its own centre and no neighbour's.
MIN_COC_RADIUS = 0.5


@wp.kernel(enable_backward=False)
def dof_gather_kernel(
    src: wp.array3d[wp.vec3],
    radius: wp.array3d[wp.float32],
    depth: wp.array3d[wp.float32],
    search: wp.int32,
    band0: wp.int32,
    # outputs
    dst: wp.array3d[wp.vec3],
):
    """One thread per (frame t, row i), looping over the columns. ``radius``: CoC radius [px] per pixel;
    ``depth``: planar depth [m] per pixel (a large value where nothing is hit); ``search``: R [px], at least
    the largest radius of the frame rounded up."""
    t, i = wp.tid()
    i += band0
    H = src.shape[1]
    W = src.shape[2]
    for j in range(W):
        rp = wp.max(radius[t, i, j], MIN_COC_RADIUS)
        zp = depth[t, i, j]
        acc = wp.vec3(0.0)
        wsum = wp.float32(0.0)
        for qi in range(wp.max(i - search, 0), wp.min(i + search + 1, H)):
            di = float(qi - i)
            for qj in range(wp.max(j - search, 0), wp.min(j + search + 1, W)):
                dj = float(qj - j)
                d2 = di * di + dj * dj
                rq = wp.max(radius[t, qi, qj], MIN_COC_RADIUS)
                if d2 <= rq * rq and (depth[t, qi, qj] <= zp or d2 <= rp * rp):
                    w = 1.0 / (rq * rq)
                    acc += w * src[t, qi, qj]
                    wsum += w
        dst[t, i, j] = acc / wsum
