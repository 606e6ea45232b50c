"""Tone mapping: linear radiance to sRGB-encoded float32, in float64 steps, on the render device.

``tonemap_kernel`` is ``flowsynth.renderer.shading.tonemap_srgb`` (numpy) per pixel: exposure, the optional extended
Reinhard operator, the sRGB transfer function with its power from a table (``srgb_pow``, no libm call), the same
float32 values bit for bit (docs/decisions/0013-tonemap-kernel.md).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from flowsynth.kernels.specialise import specialised_builder

__all__ = ["SrgbPow", "srgb_encode", "srgb_pow", "srgb_pow_tables", "tonemap_kernel"]


# sRGB power x^(1/2.4) on x in (0.0031308, 1] (``srgb_pow``): x = m 2^-k, m in [1, 2) split into SRGB_POW_BINS
# bins, each a degree-4 Taylor polynomial of m^(1/2.4) about the bin centre (truncation < 1e-15 relative), times
# 2^(-k / 2.4) from a table of k = 0 .. 10 (``srgb_pow_tables``).
SRGB_POW_BINS = 256
SRGB_POW_SHIFT = wp.constant(wp.int64(44))  # 52 mantissa bits - log2(SRGB_POW_BINS)
# ``srgb_encode`` rounds the fast value to float32 only when every value within this of it rounds alike; the
# fast value is within 2e-15 of the exact float64 steps (truncation, table and rounding errors), so the result
# is theirs bit for bit, and about 1 value in 1,000 (near a float32 rounding boundary) takes the exact path.
SRGB_POW_DELTA = wp.constant(wp.float64(1.0e-11))
MANTISSA = wp.constant(wp.int64(0xFFFFFFFFFFFFF))
ONE_BITS = wp.constant(wp.int64(0x3FF0000000000000))


@wp.struct
class SrgbPow:
    coef: wp.array2d[wp.float64]  # (SRGB_POW_BINS, 5) Taylor coefficients of m^(1/2.4) about bin centres
    scale: wp.array[wp.float64]  # (11,) 2^(-k / 2.4)


@wp.func
def srgb_pow(x: wp.float64, tab: SrgbPow) -> wp.float64:
    """x^(1/2.4) for x in (2^-10, 1] to ~1e-15 relative, from the float64 bits of x (no libm call)."""
    b = wp.cast(x, wp.int64)
    k = wp.int32(wp.int64(1023) - (b >> wp.int64(52)))  # x = m 2^-k
    mant = b & MANTISSA
    i = wp.int32(mant >> SRGB_POW_SHIFT)
    t = wp.cast(mant | ONE_BITS, wp.float64) - wp.float64(2 * SRGB_POW_BINS + 1 + 2 * i) / wp.float64(
        2 * SRGB_POW_BINS)
    p = tab.coef[i, 0] + t * (tab.coef[i, 1] + t * (tab.coef[i, 2] + t * (tab.coef[i, 3] + t * tab.coef[i, 4])))
    return p * tab.scale[k]


@wp.func
def srgb_encode(c: wp.float32, exposure: wp.float64, reinhard: wp.int32, white2: wp.float64,
                tab: SrgbPow) -> wp.float32:
    """flowsynth.renderer.shading.tonemap_srgb of one linear value, in the same float64 steps: x = exposure c (NaN -> 0,
    +inf -> 1e30, < 0 -> 0), extended Reinhard x (1 + x / white^2) / (1 + x) when asked, min(x, 1), then the
    sRGB transfer function, clipped to [0, 1] and rounded to float32. The power comes from ``srgb_pow`` unless
    the float32 rounding is in doubt (then from ``wp.pow``, as before): rounding to float32 is monotonic, so
    when both ends of [e - SRGB_POW_DELTA, e + SRGB_POW_DELTA] round to one value, so does the exact e."""
    x = wp.float64(c) * exposure
    if wp.isnan(x):
        x = wp.float64(0.0)
    x = wp.max(wp.min(x, wp.float64(1.0e30)), wp.float64(0.0))
    if reinhard != 0:
        x = x * (wp.float64(1.0) + x / white2) / (wp.float64(1.0) + x)
    x = wp.min(x, wp.float64(1.0))
    e = wp.float64(12.92) * x
    if x > wp.float64(0.0031308):
        fast = wp.float64(1.055) * srgb_pow(x, tab) - wp.float64(0.055)
        lo = wp.float32(wp.clamp(fast - SRGB_POW_DELTA, wp.float64(0.0), wp.float64(1.0)))
        if lo == wp.float32(wp.clamp(fast + SRGB_POW_DELTA, wp.float64(0.0), wp.float64(1.0))):
            return lo
        e = wp.float64(1.055) * wp.pow(x, wp.float64(1.0) / wp.float64(2.4)) - wp.float64(0.055)
    return wp.float32(wp.clamp(e, wp.float64(0.0), wp.float64(1.0)))


@specialised_builder
def tonemap_kernel(per_pixel: bool = False):
    """(F, H, W) vec3 linear radiance -> (F, 3, H, W) float32 sRGB (``srgb_encode``). Two launch shapes of one body
    (``flowsynth.parallel.pixel_threads``): ``per_pixel`` False, dims (F, rows) from row ``band0``, each thread one
    row (``row_loop=True``); True, dims (F, rows, W), a thread per pixel."""
    @wp.kernel(enable_backward=False, module="unique")
    def tonemap(radiance: wp.array3d[wp.vec3], exposure: wp.float64, reinhard: wp.int32, white2: wp.float64,
                tab: SrgbPow, band0: wp.int32, rgb: wp.array4d[wp.float32]):
        if wp.static(per_pixel):
            t, i, j0 = wp.tid()
            j1 = j0 + 1
        else:
            t, i = wp.tid()
            j0 = wp.int32(0)
            j1 = radiance.shape[2]
        i += band0
        for j in range(j0, j1):
            c = radiance[t, i, j]
            for k in range(3):
                rgb[t, k, i, j] = srgb_encode(c[k], exposure, reinhard, white2, tab)

    return tonemap


def srgb_pow_tables(device: str = "cpu") -> SrgbPow:
    """The tables of ``srgb_pow`` on ``device`` (flowsynth.renderer.shading.srgb_tables keeps one per device): Taylor
    coefficients binom(a, n) c^(a - n), n = 0 .. 4, of m^a, a = 1/2.4, about each bin centre c, and 2^(-k a) for
    k = 0 .. 10."""
    a = 1.0 / 2.4
    c = (2 * SRGB_POW_BINS + 1 + 2 * np.arange(SRGB_POW_BINS)) / (2 * SRGB_POW_BINS)
    coef = np.stack([math.prod(a - j for j in range(n)) / math.factorial(n) * c ** (a - n) for n in range(5)], 1)
    tab = SrgbPow()
    tab.coef = wp.array(coef, dtype=wp.float64, device=device)
    tab.scale = wp.array(2.0 ** (-a * np.arange(11)), dtype=wp.float64, device=device)
    return tab
