"""Textures evaluated in object-local coordinates, so a texture moves exactly with its object.

A material is one ``Material`` struct of an array (packed by field name in ``flowsynth.renderer.shading.pack_materials``
from a numpy structured array of ``Material.numpy_dtype()``, so the packer and the kernels share one definition of
every field and a misnamed one fails: numpy raises on an unknown field, Warp does not compile one). It has two
texture *layers* (``a``, ``b``, each a ``Layer``) and a blend mask; a single-layer material has layer b's family
set to ``FAMILY_NONE``.

Triplanar projection: the object-frame hit point p [m] is projected onto the planes x = 0, y = 0,
z = 0 as (p.y, p.z), (p.z, p.x), (p.x, p.y); the three 2-D lookups are blended with weights
|n_i|^4 / sum_k |n_k|^4 of the object-frame face normal n. Each layer multiplies these coordinates
by its ``scale`` [cycles / m], so a pattern period is 1 / scale metres on the object's surface.

Filtering (no aliasing at any distance): every lookup gets the pixel footprint ``fw`` [m], the width of
the surface patch one pixel (sample) covers. Fractal octaves (noise, value, cells) whose period spans fewer
than FADE_HI footprints fade out linearly, and are gone (not evaluated) below FADE_LO: the pattern keeps
its mean and loses only detail the pixel grid cannot carry. Stripes and checks are box-filtered exactly
over the footprint (closed-form integral of the square wave). Images are mip-mapped: trilinear lookup at
level log2(footprint in texels).

Images are stored in one atlas of mip pyramids: ``img_data`` (sum of w*h over all levels,) vec3 linear RGB,
rows top to bottom, and ``img_info`` (rows, 4) int32 (offset, width, height, levels), one row per level,
an image's levels in consecutive rows (a material stores its level-0 row). An image tiles with period 1
along the first texture coordinate and height / width along the second (square texels, no stretch).
"""

from __future__ import annotations

import warp as wp

__all__ = ["FAMILIES", "FAMILY_NONE", "Layer", "Material", "base_color", "layer_trig_kernel"]

# Texture families, by kernel code. "blend" is not a code: it is a material with two layers.
FAMILIES = {"solid": 0, "noise": 1, "value": 2, "cells": 3, "stripes": 4, "checks": 5, "image": 6, "leaves": 7}
FAMILY_NONE = -1
F_SOLID = wp.constant(0)
F_NOISE = wp.constant(1)
F_VALUE = wp.constant(2)
F_CELLS = wp.constant(3)
F_STRIPES = wp.constant(4)
F_CHECKS = wp.constant(5)
F_IMAGE = wp.constant(6)
F_LEAVES = wp.constant(7)



@wp.struct
class Layer:
    """One texture layer of a material."""

    color_a: wp.vec3  # linear RGB
    color_b: wp.vec3  # linear RGB
    scale: wp.float32  # [1/m]
    angle: wp.float32  # [rad]
    gain: wp.float32  # amplitude ratio of successive octaves
    grain: wp.float32  # relative amplitude of the grain
    grain_scale: wp.float32  # [1/m]
    # cos and sin of ``angle``, filled by ``layer_trig_kernel`` on the device (once per table instead of once per
    # lookup; numpy's cos would not give Warp's bits)
    cos_angle: wp.float32
    sin_angle: wp.float32
    family: wp.int32  # FAMILIES code, or FAMILY_NONE (layer b of a single-layer material)
    octaves: wp.int32
    seed: wp.int32
    image: wp.int32  # atlas row of the image's level 0 (family "image")


@wp.struct
class Material:
    """One object's material: two layers and the mask blending them, and the BRDF's parameters."""

    a: Layer
    b: Layer
    mask_scale: wp.float32  # [1/m]
    roughness: wp.float32
    specular: wp.float32
    mask_seed: wp.int32


# Gain mapping fractal noise (roughly zero-mean, std ~0.2 before gain) to a [0, 1] mix weight.
NOISE_GAIN = wp.constant(1.6)
# Triplanar weights below this are skipped (the largest weight is >= 1/9 for a unit normal).
TRIPLANAR_MIN_WEIGHT = wp.constant(1.0e-3)
# Octave fading: an octave whose period spans >= FADE_HI pixel footprints is fully present, < FADE_LO absent.
FADE_LO = wp.constant(2.0)
FADE_HI = wp.constant(4.0)
# Dead leaves: disc radii as a fraction of their lattice cell (a disc reaches at most one cell beyond its own).
LEAF_RADIUS_LO = wp.constant(0.35)
LEAF_RADIUS_HI = wp.constant(0.75)
# Box filters narrower than this [cycles] are point samples (avoids 0/0).
MIN_FILTER = wp.constant(1.0e-6)


@wp.func
def hash3(x: wp.int32, y: wp.int32, seed: wp.int32) -> wp.uint32:
    """Integer hash of a lattice cell and a seed (lowbias32 finaliser)."""
    h = wp.uint32(seed) * wp.uint32(0x27D4EB2F) + wp.uint32(x) * wp.uint32(0x165667B1)
    h = (h ^ wp.uint32(y) * wp.uint32(0x3C6EF372)) + wp.uint32(0x7F4A7C15)
    h = h ^ (h >> wp.uint32(16))
    h = h * wp.uint32(0x7FEB352D)
    h = h ^ (h >> wp.uint32(15))
    h = h * wp.uint32(0x68E31DA4)
    h = h ^ (h >> wp.uint32(16))
    return h


@wp.func
def unit(h: wp.uint32) -> wp.float32:
    """Top 24 bits of a hash as a float in [0, 1)."""
    return wp.float32(h >> wp.uint32(8)) * (1.0 / 16777216.0)


@wp.func
def value_noise(q: wp.vec2, seed: wp.int32) -> wp.float32:
    """Smoothly interpolated lattice values in [0, 1)."""
    fx = wp.floor(q[0])
    fy = wp.floor(q[1])
    ix = wp.int32(fx)
    iy = wp.int32(fy)
    tx = q[0] - fx
    ty = q[1] - fy
    tx = tx * tx * (3.0 - 2.0 * tx)
    ty = ty * ty * (3.0 - 2.0 * ty)
    a = wp.lerp(unit(hash3(ix, iy, seed)), unit(hash3(ix + 1, iy, seed)), tx)
    b = wp.lerp(unit(hash3(ix, iy + 1, seed)), unit(hash3(ix + 1, iy + 1, seed)), tx)
    return wp.lerp(a, b, ty)


@wp.func
def cells(q: wp.vec2, seed: wp.int32) -> wp.float32:
    """Worley cells: the random value in [0, 1) of the nearest jittered lattice feature point."""
    fx = wp.floor(q[0])
    fy = wp.floor(q[1])
    ix = wp.int32(fx)
    iy = wp.int32(fy)
    best = wp.float32(1.0e9)
    bx = ix
    by = iy
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            px = fx + wp.float32(dx) + unit(hash3(ix + dx, iy + dy, seed))
            py = fy + wp.float32(dy) + unit(hash3(ix + dx, iy + dy, seed + 1))
            d2 = (q[0] - px) * (q[0] - px) + (q[1] - py) * (q[1] - py)
            if d2 < best:
                best = d2
                bx = ix + dx
                by = iy + dy
    return unit(hash3(bx, by, seed + 2))  # hashed once, for the winner only


@wp.func
def octave_weight(period: wp.float32, fw: wp.float32) -> wp.float32:
    """Weight in [0, 1] of a pattern octave of ``period`` seen through a footprint ``fw`` (same units)."""
    return wp.clamp((period / wp.max(fw, 1.0e-30) - FADE_LO) / (FADE_HI - FADE_LO), 0.0, 1.0)


@wp.func
def fractal(q: wp.vec2, seed: wp.int32, octaves: wp.int32, fam: wp.int32, gain: wp.float32,
            fw: wp.float32) -> wp.float32:
    """Fractal sum (lacunarity 2, amplitude ratio ``gain``) of Perlin gradient noise (F_NOISE), value noise
    (F_VALUE) or Worley cells (F_CELLS) at q [cycles], normalised by the root sum of squared amplitudes (so the
    contrast does not shrink with the number of octaves) and mapped to [0, 1]; octaves finer than the
    footprint ``fw`` [cycles] fade out (see the module docstring)."""
    total = wp.float32(0.0)
    norm = wp.float32(0.0)
    amp = wp.float32(1.0)
    freq = wp.float32(1.0)
    for o in range(wp.max(octaves, 1)):
        w = octave_weight(1.0 / freq, fw)
        if w > 0.0:
            n = wp.float32(0.0)
            if fam == F_NOISE:
                n = wp.noise(wp.rand_init(seed, o), q * freq)
            elif fam == F_VALUE:
                n = value_noise(q * freq, seed + 7919 * o) - 0.5
            else:
                n = cells(q * freq, seed + 7919 * o) - 0.5
            total += w * amp * n
        norm += amp * amp
        amp *= gain
        freq *= 2.0
    g = wp.where(fam == F_CELLS, 1.0, NOISE_GAIN)
    return wp.clamp(0.5 + g * total / wp.sqrt(norm), 0.0, 1.0)


@wp.func
def dead_leaves(q: wp.vec2, seed: wp.int32, octaves: wp.int32, fw: wp.float32) -> wp.float32:
    """Dead leaves, the occlusion model of natural images (Matheron; Lee, Mumford and Huang 2001): discs of
    ``octaves`` sizes, the cells of size k halving from 1 cycle, one disc per lattice cell of each size (centre
    anywhere in the cell, radius LEAF_RADIUS_LO-LEAF_RADIUS_HI of the cell), each with a random depth. q [cycles]
    takes the value in [0, 1) of the uppermost disc covering it, or, where none does, of its Worley cell of the
    largest size. Sizes whose cell spans fewer than FADE_LO footprints ``fw`` [cycles] are left out: those leaves
    fall below the pixel grid, and the leaves under them show."""
    best = wp.float32(-1.0)
    val = wp.float32(0.0)
    freq = wp.float32(1.0)
    for o in range(wp.max(octaves, 1)):
        if 1.0 / freq >= FADE_LO * fw:
            p = q * freq
            fx = wp.floor(p[0])
            fy = wp.floor(p[1])
            ix = wp.int32(fx)
            iy = wp.int32(fy)
            s = seed + 7919 * o
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    cx = fx + wp.float32(dx) + unit(hash3(ix + dx, iy + dy, s))
                    cy = fy + wp.float32(dy) + unit(hash3(ix + dx, iy + dy, s + 1))
                    r = LEAF_RADIUS_LO + (LEAF_RADIUS_HI - LEAF_RADIUS_LO) * unit(hash3(ix + dx, iy + dy, s + 2))
                    if (p[0] - cx) * (p[0] - cx) + (p[1] - cy) * (p[1] - cy) < r * r:
                        depth = unit(hash3(ix + dx, iy + dy, s + 3))
                        if depth > best:
                            best = depth
                            val = unit(hash3(ix + dx, iy + dy, s + 4))
        freq *= 2.0
    if best < 0.0:
        val = cells(q, seed + 104729)
    return val


@wp.func
def stripe_integral(x: wp.float32) -> wp.float32:
    """Integral from 0 to x of the square wave that is 1 where frac(x) >= 1/2, else 0."""
    fx = wp.floor(x)
    return 0.5 * fx + wp.max(x - fx - 0.5, 0.0)


@wp.func
def box_stripes(x: wp.float32, w: wp.float32) -> wp.float32:
    """Mean of that square wave over [x - w/2, x + w/2] (w [cycles]): exactly box-filtered stripes."""
    if w < MIN_FILTER:
        return wp.where(x - wp.floor(x) < 0.5, 0.0, 1.0)
    return (stripe_integral(x + 0.5 * w) - stripe_integral(x - 0.5 * w)) / w


@wp.func
def image_level(img_data: wp.array[wp.vec3], img_info: wp.array2d[wp.int32], row: wp.int32, q: wp.vec2):
    """Bilinear, tiling lookup of one mip level (atlas row ``row``) at texture coordinates q."""
    off = img_info[row, 0]
    w = img_info[row, 1]
    h = img_info[row, 2]
    x = wp.frac(q[0]) * wp.float32(w) - 0.5
    y = (1.0 - wp.frac(q[1])) * wp.float32(h) - 0.5
    fx = wp.floor(x)
    fy = wp.floor(y)
    tx = x - fx
    ty = y - fy
    x0 = (wp.int32(fx) % w + w) % w
    y0 = (wp.int32(fy) % h + h) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    a = wp.lerp(img_data[off + y0 * w + x0], img_data[off + y0 * w + x1], tx)
    b = wp.lerp(img_data[off + y1 * w + x0], img_data[off + y1 * w + x1], tx)
    return wp.lerp(a, b, ty)


@wp.func
def image_sample(img_data: wp.array[wp.vec3], img_info: wp.array2d[wp.int32], k: wp.int32, q: wp.vec2,
                 fw: wp.float32):
    """Trilinear (mip-mapped), tiling lookup of the image whose level 0 is atlas row k, at q [tiles along
    the width], footprint fw [tiles]."""
    w0 = wp.float32(img_info[k, 1])
    levels = img_info[k, 3]
    qq = wp.vec2(q[0], q[1] * w0 / wp.float32(img_info[k, 2]))
    lod = wp.clamp(wp.log2(wp.max(fw * w0, 1.0)), 0.0, wp.float32(levels - 1))
    l0 = wp.min(wp.int32(lod), levels - 1)
    a = image_level(img_data, img_info, k + l0, qq)
    t = lod - wp.float32(l0)
    if t > 0.0 and l0 + 1 < levels:
        a = wp.lerp(a, image_level(img_data, img_info, k + l0 + 1, qq), t)
    return a


@wp.func
def layer_color(lay: Layer, img_data: wp.array[wp.vec3], img_info: wp.array2d[wp.int32], q: wp.vec2,
                fw: wp.float32):
    """Linear RGB of one texture layer at object-plane coordinates q [m], footprint fw [m]."""
    fam = lay.family
    ca = lay.color_a
    if fam == F_SOLID:
        return ca
    cb = lay.color_b
    s = lay.scale
    c = lay.cos_angle
    sn = lay.sin_angle
    r = wp.vec2(c * q[0] - sn * q[1], sn * q[0] + c * q[1]) * s
    fc = fw * s  # footprint [cycles]
    seed = lay.seed
    if fam == F_IMAGE:
        return image_sample(img_data, img_info, lay.image, r, fc)
    v = wp.float32(0.0)
    if fam == F_STRIPES:
        v = box_stripes(r[0], fc)
    elif fam == F_CHECKS:  # cells of side 1: parity of floor(x) + floor(y) = XOR of two period-2 square waves
        a = box_stripes(0.5 * r[0], 0.5 * fc)
        b = box_stripes(0.5 * r[1], 0.5 * fc)
        v = a + b - 2.0 * a * b
    elif fam == F_LEAVES:
        v = dead_leaves(r, seed, lay.octaves, fc)
    else:
        v = fractal(r, seed, lay.octaves, fam, lay.gain, fc)
    col = wp.lerp(ca, cb, v)
    grain = lay.grain
    if grain > 0.0:  # fine value-noise grain multiplying the colour: 3 octaves from 1 / grain scale down
        gs = lay.grain_scale
        col = col * wp.max(1.0 + 2.0 * grain * (fractal(q * gs, seed + 1, 3, F_VALUE, 0.7, fw * gs) - 0.5), 0.0)
    return col


@wp.func
def planar_color(mat: Material, img_data: wp.array[wp.vec3], img_info: wp.array2d[wp.int32], q: wp.vec2,
                 fw: wp.float32):
    """Material colour at object-plane coordinates q [m], footprint fw [m]: layer a, or a noise-masked blend
    of a and b."""
    if mat.b.family == FAMILY_NONE:
        return layer_color(mat.a, img_data, img_info, q, fw)
    ms = mat.mask_scale
    w = wp.smoothstep(0.4, 0.6, fractal(q * ms, mat.mask_seed, 3, F_NOISE, 0.5, fw * ms))
    # Only the layers the mask shows are looked up: where it is exactly 0 or 1, lerp(a, b, w) is a or b exactly
    # (a (1 - 0) + b 0 = a), so skipping the other changes no bit and saves a layer on most pixels.
    if w <= 0.0:
        return layer_color(mat.a, img_data, img_info, q, fw)
    if w >= 1.0:
        return layer_color(mat.b, img_data, img_info, q, fw)
    return wp.lerp(layer_color(mat.a, img_data, img_info, q, fw), layer_color(mat.b, img_data, img_info, q, fw), w)


@wp.func
def base_color(mats: wp.array[Material], img_data: wp.array[wp.vec3], img_info: wp.array2d[wp.int32], m: wp.int32,
               p: wp.vec3, n: wp.vec3, fw: wp.float32):
    """Triplanar base colour (linear RGB) of material m at object-frame point p [m] with object-frame normal n,
    filtered over a pixel footprint fw [m]."""
    mat = mats[m]
    w = wp.vec3(n[0] * n[0], n[1] * n[1], n[2] * n[2])
    w = wp.cw_mul(w, w)
    w = w / wp.max(w[0] + w[1] + w[2], 1.0e-30)
    col = wp.vec3(0.0)
    total = wp.float32(0.0)
    if w[0] > TRIPLANAR_MIN_WEIGHT:
        col += w[0] * planar_color(mat, img_data, img_info, wp.vec2(p[1], p[2]), fw)
        total += w[0]
    if w[1] > TRIPLANAR_MIN_WEIGHT:
        col += w[1] * planar_color(mat, img_data, img_info, wp.vec2(p[2], p[0]), fw)
        total += w[1]
    if w[2] > TRIPLANAR_MIN_WEIGHT:
        col += w[2] * planar_color(mat, img_data, img_info, wp.vec2(p[0], p[1]), fw)
        total += w[2]
    return col / wp.max(total, 1.0e-30)


@wp.kernel(enable_backward=False)
def layer_trig_kernel(mats: wp.array[Material]):
    """Fill each layer's ``cos_angle`` and ``sin_angle`` from its ``angle`` (one thread per material): the same
    ``wp.cos`` / ``wp.sin`` of the same float32 angle that ``layer_color`` evaluated per lookup before, so the
    texture bits do not change (docs/decisions/0014-texture-lookups.md)."""
    m = wp.tid()
    mats[m].a.cos_angle = wp.cos(mats[m].a.angle)
    mats[m].a.sin_angle = wp.sin(mats[m].a.angle)
    mats[m].b.cos_angle = wp.cos(mats[m].b.angle)
    mats[m].b.sin_angle = wp.sin(mats[m].b.angle)
