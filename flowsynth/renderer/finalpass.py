"""The final pass, ``rgb_final``: the clean render with camera effects, as Sintel ships "final" beside "clean".

In linear radiance, per clip (the models, their defaults and what they are not: docs/rendering.md, Final pass):

1. motion blur: the scene re-shaded with the shutter centred on the frame instant (``FinalPass.shutter``,
   ``time_samples``; ``flowsynth.renderer.shading.shade_radiance`` with ``Plan.shutter_offset = -shutter / 2``);
2. fog: L' = L exp(-sigma s) + F (1 - exp(-sigma s)), s the ray length of the pixel-centre hit (``distance``);
3. depth of field: thin-lens circle of confusion per pixel, gathered with occlusion-aware weights
   (``flowsynth.kernels.dof``);
4. exposure and white balance: a gain per frame and channel;
5. sensor noise: Poisson-Gaussian on the sensor signal x = exposure L: a Poisson(x / a) + N(0, b^2);

then the clean pass's tone mapping (``Plan.tonemap``, ``Plan.exposure``). Ground truth is not touched: it stays
that of the pinhole, mid-shutter geometry (docs/conventions.md). Every random draw comes from the plan's seed
(the scene's ``render_seed`` unless the plan sets one), so a sample's final pass re-renders from its provenance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from flowsynth.plan import FinalPass, Plan

__all__ = ["FINAL_STREAM", "SENSOR_WIDTH", "FinalDraw", "apply_dof", "apply_fog", "apply_noise", "coc_px",
           "draw_final", "render_final"]

# Width of the sensor the thin lens forms its image on [m] (full frame, 36 mm): the physical focal length is
# f = SENSOR_WIDTH * f_px / W. It enters the circle of confusion only through (d_f - f).
SENSOR_WIDTH = 0.036
# Tag mixed into the render seed so the final pass's draws are independent of every other use of that seed.
FINAL_STREAM = 0x46494E41
# Planar depth [m] given to pixels that see nothing (the thin lens's limit d -> infinity).
SKY_DEPTH = 1.0e30
# Largest Poisson mean drawn (x / a); beyond it the shot noise is below float32 resolution anyway.
MAX_POISSON_MEAN = 1.0e12


@dataclass(frozen=True)
class FinalDraw:
    """What the final pass of one clip drew from its seed (``draw_final``).

    Attributes:
        dof: the clip has depth of field.
        aperture: aperture diameter A [m] (drawn even without depth of field).
        focus: focus distance d_f [m] (planar depth); None without depth of field.
        shot_noise: Poisson gain a [linear intensity].
        read_noise: read-noise standard deviation b [linear intensity].
        gains: (T, 3) float64 linear gain of each frame and channel: 2^e_t (exp(w_R), 1, exp(w_B)).
    """

    dof: bool
    aperture: float
    focus: float | None
    shot_noise: float
    read_noise: float
    gains: np.ndarray


def _streams(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """(per-clip draws, noise) generators of the final pass for ``seed``."""
    params, noise = np.random.SeedSequence([int(seed) % (1 << 64), FINAL_STREAM]).spawn(2)
    return np.random.default_rng(params), np.random.default_rng(noise)


def _uniform(rng_u: float, lo: float, hi: float) -> float:
    return lo + (hi - lo) * rng_u


def draw_final(seed: int, fp: FinalPass, depth_mid: np.ndarray, candidates: np.ndarray,
               num_frames: int) -> FinalDraw:
    """The per-clip and per-frame values of the final pass, drawn from ``seed`` in a fixed order (so a setting
    that is off never changes what the others draw).

    Args:
        seed: the render seed.
        fp: the settings.
        depth_mid: (H, W) planar depth [m] of the middle frame T // 2, 0 where nothing is hit.
        candidates: (H, W) bool, the pixels the focus may be drawn from (objects; any hit when none).
        num_frames: T.
    """
    rng, _ = _streams(seed)
    u_dof, u_ap, u_focus, u_shot, u_read = rng.random(5)
    stops = rng.standard_normal(num_frames) * fp.exposure_jitter
    wb = rng.standard_normal((num_frames, 2)) * fp.wb_jitter
    lo, hi = fp.aperture
    aperture = math.exp(_uniform(u_ap, math.log(lo), math.log(hi))) if lo > 0 else _uniform(u_ap, lo, hi)
    pool = depth_mid[candidates] if candidates.any() else depth_mid[depth_mid > 0]
    dof = bool(u_dof < fp.dof_prob) and aperture > 0 and (fp.focus is not None or pool.size > 0)
    focus = None
    if dof:
        focus = fp.focus if fp.focus is not None else float(pool[min(int(u_focus * pool.size), pool.size - 1)])
    gains = np.exp2(stops)[:, None] * np.stack([np.exp(wb[:, 0]), np.ones(num_frames), np.exp(wb[:, 1])], 1)
    return FinalDraw(dof, float(aperture), focus, _uniform(u_shot, *fp.shot_noise), _uniform(u_read, *fp.read_noise),
                     gains)


def coc_px(depth: np.ndarray, aperture: float, focus: float, f_px: float, f_m: float) -> np.ndarray:
    """Thin-lens circle-of-confusion diameter [px] at planar depth ``depth`` [m] (0 or inf = nothing hit: the
    limit d -> infinity): c = A f_px |d - d_f| / (d (d_f - f)), with A the aperture diameter [m], d_f the focus
    distance [m], f the physical focal length [m] and f_px the focal length in pixels. Float64."""
    d = np.asarray(depth, np.float64)
    far = ~(d > 0) | ~np.isfinite(d)
    safe = np.where(far, 1.0, d)
    c = aperture * f_px * np.abs(safe - focus) / (safe * (focus - f_m))
    return np.where(far, aperture * f_px / (focus - f_m), c)


def apply_dof(radiance: np.ndarray, depth: np.ndarray, aperture: float, focus: float, f_px: float, f_m: float,
              max_coc: float, threads: int | None = None, device: str = "cpu") -> np.ndarray:
    """Depth of field of (T, H, W, 3) linear ``radiance`` with (T, H, W) planar ``depth`` [m] (0 = no hit):
    per-pixel CoC from ``coc_px`` clamped to ``max_coc`` [px], gathered by ``flowsynth.kernels.dof`` (its module
    docstring states the weights) on Warp ``device``. ``focus`` must exceed the focal length ``f_m``. Returns float32
    (T, H, W, 3) numpy."""
    from flowsynth.kernels import wp_runtime
    from flowsynth.parallel import BAND0, launch_bands

    if not focus > f_m:
        raise ValueError(f"focus {focus} m must exceed the focal length {f_m} m")
    radius = (0.5 * np.minimum(coc_px(depth, aperture, focus, f_px, f_m), max_coc)).astype(np.float32)
    search = int(math.ceil(float(radius.max()))) if radius.size else 0
    if search == 0:
        return np.asarray(radiance, np.float32)
    wp = wp_runtime()
    from flowsynth.kernels.dof import dof_gather_kernel

    T, H, W = radius.shape
    z = np.where(np.asarray(depth) > 0, depth, SKY_DEPTH).astype(np.float32)
    src = wp.array(np.ascontiguousarray(radiance, np.float32), dtype=wp.vec3, device=device)
    dst = wp.empty((T, H, W), dtype=wp.vec3, device=device)
    launch_bands(dof_gather_kernel, (T, H, W), 1,
                 [src, wp.array(radius, dtype=wp.float32, device=device), wp.array(z, dtype=wp.float32, device=device),
                  search, BAND0], [dst], device, threads, row_loop=True, cost=(2 * search + 1) ** 2)
    return dst.numpy()


def apply_fog(radiance: np.ndarray, distance: np.ndarray, density: float, color) -> np.ndarray:
    """L exp(-sigma s) + F (1 - exp(-sigma s)) for (T, H, W, 3) ``radiance`` and (T, H, W) ray length ``distance``
    [m] (0 = nothing hit: s = infinity, the fog colour F). Float32 out."""
    s = np.asarray(distance, np.float64)
    trans = np.where(s > 0, np.exp(-density * s), 0.0)[..., None]
    out = np.asarray(radiance, np.float64) * trans + np.asarray(color, np.float64) * (1.0 - trans)
    return out.astype(np.float32)


def apply_noise(signal: np.ndarray, shot: float, read: float, rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian sensor noise on a linear ``signal`` x >= 0 (any shape): y = a Poisson(x / a) + b N(0, 1),
    so E[y] = x and Var[y] = a x + b^2 (a = ``shot``, b = ``read``; a = 0: no shot noise). Float64 out, may be
    negative where read noise dominates (the display transform clamps)."""
    x = np.maximum(np.asarray(signal, np.float64), 0.0)
    y = shot * rng.poisson(np.minimum(x / shot, MAX_POISSON_MEAN)).astype(np.float64) if shot > 0 else x.copy()
    if read > 0:
        y += read * rng.standard_normal(x.shape)
    return y


def render_final(scene, accel, gb, plan: Plan, device: str = "cpu") -> torch.Tensor:
    """``rgb_final``: (T, 3, H, W) float32 sRGB in [0, 1] (the module docstring lists the steps).

    Args:
        scene: the scene (camera, objects, lights, render seed).
        accel: the G-buffer's acceleration structure.
        gb: the G-buffer of the pixel-centre rays at the frame instants (``dist``, ``item``).
        plan: the plan; ``plan.final_pass`` holds the settings, ``plan.seed`` (None: ``scene.render_seed``) seeds
            every draw.
        device: Warp device of the shading.
    """
    from flowsynth.renderer.shading import shade_radiance, tonemap_frames

    fp = plan.final_pass
    seed = int(scene.render_seed if plan.seed is None else plan.seed)
    plan = replace(plan, seed=seed)
    if fp.shutter > 0:
        plan = replace(plan.with_options(shutter=fp.shutter, spp=max(plan.spp, fp.time_samples)),
                       shutter_offset=-0.5 * fp.shutter)
    radiance = shade_radiance([scene], accel, gb, plan, device=device).numpy()  # the draws below compute on the host
    T, H, W = radiance.shape[:3]
    dz = scene.camera.pixel_rays_numpy()[..., 2]
    host = gb.host()  # the final pass's draws, fog, gains and noise compute on the host
    hit = host.hit
    depth = np.where(hit, host.dist.astype(np.float64) * dz, 0.0)
    distance = np.where(hit, host.dist, 0.0)
    idx = host.instance_index[T // 2]
    objects = np.array([not o.background for o in scene.objects] + [False])
    draw = draw_final(seed, fp, depth[T // 2], objects[idx], T)
    if fp.fog_density > 0:
        radiance = apply_fog(radiance, distance, fp.fog_density, fp.fog_color)
    if draw.dof:
        f_px = float(scene.camera.K[0, 0])
        f_m = SENSOR_WIDTH * f_px / W
        radiance = apply_dof(radiance, depth, draw.aperture, max(draw.focus, 2.0 * f_m), f_px, f_m, fp.max_coc,
                             plan.threads, device=device)
    if fp.exposure_jitter > 0 or fp.wb_jitter > 0:
        radiance = (radiance * draw.gains[:, None, None, :]).astype(np.float32)
    if (draw.shot_noise > 0 or draw.read_noise > 0) and plan.exposure > 0:
        _, rng = _streams(seed)
        x = apply_noise(plan.exposure * np.asarray(radiance, np.float64), draw.shot_noise, draw.read_noise, rng)
        radiance = (np.maximum(x, 0.0) / plan.exposure).astype(np.float32)
    return torch.from_numpy(tonemap_frames(np.ascontiguousarray(radiance, np.float32), plan.tonemap, plan.exposure,
                                           plan.threads, device=device))
