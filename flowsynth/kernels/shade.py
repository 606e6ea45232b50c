"""RGB shading: flat, direct (ray-traced shadows) and path-traced radiance with anti-aliasing and motion blur.

One launch of dims (T, H, W); each thread averages ``spp`` samples of its pixel into linear radiance.
Sample k of frame t:

- sub-pixel position: x = (k + xi) / spp (one sample per column stratum) and y = reverse_bits(k) XOR r
  (a digitally shifted van der Corput sequence), with r random per pixel. For spp = 4^m this is a
  (0, 2m, 2)-net: exactly one sample in every cell of the sqrt(spp) x sqrt(spp) grid (a jittered grid).
- time slice s = (k + o) mod S with o random per pixel, so every (position stratum, slice) pair is equally
  likely; the ray is traced in group t * S + s of the acceleration structure (the scene at that time).
- RNG: ``wp.rand_init(seed_t, pixel * spp + k)`` with seed_t a hash of (seed, t): bit-for-bit reproducible.
  A launch may shade a batch of scenes (frame b T + t is frame t of scene b, with scene b's seed, lights and sky).

When ``reuse`` is set (spp == 1, no motion blur) the primary hit is read from the G-buffer instead of traced.

Shading model (all quantities linear RGB; ``light_irr`` already holds pi * intensity * colour):
BRDF f = (1 - s) albedo / pi + s D G1(wi) G1(wo) / (4 (n.wi) (n.wo)), GGX with alpha = roughness^2, white
specular of weight s. Lights: directional (``light_vec`` = unit vector towards the light, camera frame of the
group) and point (``light_vec`` = position), both delta lights; the ambient sky radiance ``sky`` is the
background and, in flat/direct modes, an unshadowed ambient term sky * ((1 - s) albedo + s).

The tone mapper (radiance -> sRGB) is ``flowsynth.kernels.tonemap``.
"""

from __future__ import annotations


import warp as wp

from flowsynth.kernels import RENDER_MODES
from flowsynth.kernels.blas import eval_position, face_vertices
from flowsynth.kernels.raycast import (Instances, Pinhole, TileLists, closest_from_camera, tile_list, trace_any,
                                       trace_closest)
from flowsynth.kernels.specialise import specialised_builder
from flowsynth.kernels.texture import Material, base_color, hash3, unit

__all__ = ["LIGHT_DIRECTIONAL", "LIGHT_POINT", "ShadeGBuffer", "ShadeSampling", "ShadeScene", "lens_ray",
           "shade_kernel"]

LIGHT_DIRECTIONAL = 0
LIGHT_POINT = 1
# Secondary rays (shadow and bounce) start at x + n * max(OFFSET_REL * |x|, OFFSET_ABS): the BVH queries have
# no t_min, and float32 hit points carry ~1e-6 relative error in camera-frame coordinates.
OFFSET_REL = wp.constant(1.0e-4)
OFFSET_ABS = wp.constant(1.0e-6)
# A bounce whose sampling pdf falls below this is ended (guards the division by the pdf).
PDF_MIN = wp.constant(1.0e-6)
# Russian roulette from this bounce on; survival probability max(throughput) capped at RR_MAX_SURVIVAL.
RR_START = wp.constant(2)
RR_MAX_SURVIVAL = wp.constant(0.95)
# Each indirect contribution of a path sample (light reaching the pixel after >= 1 bounce) is scaled down
# to at most this radiance (max over channels): a biased but standard clamp against fireflies (glossy
# surfaces seen via a bounce, lit by a delta light). Direct light at the first hit is never clamped.
INDIRECT_CLAMP = wp.constant(2.0)
# Surfaces reached by a bounce shade with roughness at least this ("filter glossy", as in Blender Cycles):
# a sharp highlight seen only indirectly is a rare, very bright sample (a firefly). First hits are exact.
MIN_INDIRECT_ROUGHNESS = wp.constant(0.5)
# Texture filtering (flowsynth.kernels.texture): the pixel footprint on a surface is spread / sqrt(max(|cos|,
# MIN_FOOTPRINT_COS)), spread = ray length x ``pix_angle``; a bounce widens the spread by BOUNCE_SPREAD per metre.
MIN_FOOTPRINT_COS = wp.constant(0.05)
BOUNCE_SPREAD = wp.constant(0.1)
# Point lights closer than sqrt(this) [m] to a surface point are skipped (inverse-square singularity).
MIN_LIGHT_DIST2 = wp.constant(1.0e-12)
PI = wp.constant(3.14159265358979)


@wp.struct
class ShadeScene:
    """Everything a shading thread reads besides its pixel's G-buffer entry."""

    inst: Instances
    max_t: wp.float32
    mats: wp.array[Material]  # one per instance (``flowsynth.renderer.shading.pack_materials``)
    img_data: wp.array[wp.vec3]
    img_info: wp.array2d[wp.int32]
    n_lights: wp.array[wp.int32]  # (B,) delta lights of each scene (clip) of the launch
    light_kind: wp.array2d[wp.int32]  # (B, L)
    light_vec: wp.array2d[wp.vec3]  # (groups, L) per group (frame, or time slice), camera frame
    light_irr: wp.array2d[wp.vec3]  # (B, L)
    sky: wp.array[wp.vec3]  # (B,) ambient sky radiance of each scene
    pix_angle: wp.float32
    tiles: TileLists  # the G-buffer cast's per-tile candidate lists (when use_tiles)
    use_tiles: wp.int32  # 1: camera rays walk ``tiles`` near to far (no motion blur: group g is frame g)
    smooth: wp.int32  # 1: shading normals interpolated from ``corner_n`` (smooth shading); 0: face normals
    corner_n: wp.array[wp.vec3]  # corner normals, 3 per atlas face (SceneAccel.corner_normals; a dummy when off)


@wp.struct
class ShadeGBuffer:
    """The G-buffer of the pixel-centre rays as the shading kernel reads it (a (1, 1, 1) dummy where it does not)."""

    item: wp.array3d[wp.int32]  # (T, H, W) hit item, -1: none (the edge test, and the reused hit)
    face: wp.array3d[wp.int32]  # (T, H, W) hit face (the reused hit)
    dist: wp.array3d[wp.float32]  # (T, H, W) ray length [m] (the reused hit)
    point: wp.array3d[wp.vec3]  # (T, H, W) object-frame hit point [m] (the reused hit)
    reuse: wp.int32  # 1: the pixel-centre sample shades the G-buffer's hit instead of tracing (spp 1, no blur)


@wp.struct
class ShadeSampling:
    """How many samples a pixel takes, their time slices, seed and path length."""

    spp: wp.int32  # samples per pixel
    edge_spp: wp.int32  # samples of a silhouette pixel when > spp (else no pixel gets extra samples)
    slices: wp.int32  # motion-blur time slices per frame (1: none); group t * slices + s of ``ShadeScene.inst``
    seeds: wp.array[wp.int32]  # (B,) render seed of each scene (int32)
    frames: wp.int32  # frames per scene: launch frame t is frame t - b T of scene b = t // T
    bounces: wp.int32  # path-traced bounces ("path" mode)


@wp.func
def reverse_bits(x: wp.uint32) -> wp.uint32:
    x = ((x >> wp.uint32(1)) & wp.uint32(0x55555555)) | ((x & wp.uint32(0x55555555)) << wp.uint32(1))
    x = ((x >> wp.uint32(2)) & wp.uint32(0x33333333)) | ((x & wp.uint32(0x33333333)) << wp.uint32(2))
    x = ((x >> wp.uint32(4)) & wp.uint32(0x0F0F0F0F)) | ((x & wp.uint32(0x0F0F0F0F)) << wp.uint32(4))
    x = ((x >> wp.uint32(8)) & wp.uint32(0x00FF00FF)) | ((x & wp.uint32(0x00FF00FF)) << wp.uint32(8))
    return (x >> wp.uint32(16)) | (x << wp.uint32(16))


@wp.func
def camera_ray(v: wp.float32, u: wp.float32, cam: Pinhole):
    """Unit camera-frame direction through image point (u, v) [px]."""
    y = (v - cam.intr[3]) / cam.intr[1]
    x = (u - cam.intr[2] - cam.skew * y) / cam.intr[0]
    return wp.normalize(wp.vec3(x, y, 1.0))


@wp.func
def lens_ray(v: wp.float32, u: wp.float32, rays: wp.array2d[wp.vec3], pad: wp.int32):
    """Unit camera-frame direction through image point (u, v) [px] of a lens camera: the bilinear blend of the
    unit rays of the four pixel centres around it, renormalised. ``rays`` holds the centres of rows and columns
    -pad .. H - 1 + pad (``flowsynth.scene.camera.Camera.ray_grid``, z < 0: uncovered), pad >= 1, so every point within
    half a pixel of the image has its four. (0, 0, -1) when one of them is uncovered (the sample is black)."""
    y = v + wp.float32(pad)
    x = u + wp.float32(pad)
    i0 = wp.clamp(wp.int32(wp.floor(y)), 0, rays.shape[0] - 2)
    j0 = wp.clamp(wp.int32(wp.floor(x)), 0, rays.shape[1] - 2)
    fy = y - wp.float32(i0)
    fx = x - wp.float32(j0)
    r00 = rays[i0, j0]
    r01 = rays[i0, j0 + 1]
    r10 = rays[i0 + 1, j0]
    r11 = rays[i0 + 1, j0 + 1]
    if r00[2] <= 0.0 or r01[2] <= 0.0 or r10[2] <= 0.0 or r11[2] <= 0.0:
        return wp.vec3(0.0, 0.0, -1.0)
    d = (r00 * (1.0 - fx) + r01 * fx) * (1.0 - fy) + (r10 * (1.0 - fx) + r11 * fx) * fy
    return wp.normalize(d)


@wp.func
def offset_origin(x: wp.vec3, n: wp.vec3):
    return x + n * wp.max(OFFSET_REL * wp.length(x), OFFSET_ABS)


@wp.func
def tangent_frame(n: wp.vec3):
    """Two unit vectors completing n to an orthonormal basis (Duff et al. 2017)."""
    s = wp.where(n[2] >= 0.0, 1.0, -1.0)
    a = -1.0 / (s + n[2])
    b = n[0] * n[1] * a
    return wp.vec3(1.0 + s * n[0] * n[0] * a, s * b, -s * n[0]), wp.vec3(b, s + n[1] * n[1] * a, -n[1])


@wp.func
def ggx_d(nh: wp.float32, a2: wp.float32) -> wp.float32:
    k = nh * nh * (a2 - 1.0) + 1.0
    return a2 / wp.max(PI * k * k, 1.0e-30)


@wp.func
def smith_g1(nv: wp.float32, a2: wp.float32) -> wp.float32:
    return 2.0 * nv / (nv + wp.sqrt(a2 + (1.0 - a2) * nv * nv))


@wp.func
def brdf(n: wp.vec3, wi: wp.vec3, wo: wp.vec3, albedo: wp.vec3, spec: wp.float32, rough: wp.float32):
    ni = wp.dot(n, wi)
    no = wp.dot(n, wo)
    if ni <= 0.0 or no <= 0.0:
        return wp.vec3(0.0)
    f = albedo * ((1.0 - spec) / PI)
    if spec > 0.0:
        a = rough * rough
        a2 = a * a
        nh = wp.max(wp.dot(n, wp.normalize(wi + wo)), 0.0)
        fs = spec * ggx_d(nh, a2) * smith_g1(ni, a2) * smith_g1(no, a2) / (4.0 * ni * no)
        f = f + wp.vec3(fs)
    return f


@wp.func
def surface(sc: ShadeScene, item: wp.int32, face: wp.int32, p_obj: wp.vec3, d: wp.vec3, spread: wp.float32):
    """Shading normal (camera frame, facing against d), albedo, specular weight, roughness at a hit; the
    texture is filtered over the footprint of a ray cone of width ``spread`` [m] at the hit."""
    a, b, c = face_vertices(sc.inst.blas_tris, sc.inst.blas_slot, sc.inst.item_face0[item], face)
    n_obj = wp.normalize(wp.cross(b - a, c - a))
    n = wp.normalize(wp.transform_vector(sc.inst.ref_T_obj[item], n_obj))
    cos = wp.dot(n, d)
    if cos > 0.0:
        n = -n
    if sc.smooth != 0:  # the corner normals at the hit's barycentric coordinates, on the face's side facing d
        n = smooth_normal(sc, item, face, a, b, c, p_obj, n)
    inst = sc.inst.item_inst[item]
    fw = spread / wp.sqrt(wp.max(wp.abs(cos), MIN_FOOTPRINT_COS))
    albedo = base_color(sc.mats, sc.img_data, sc.img_info, inst, p_obj, n_obj, fw)
    return n, albedo, sc.mats[inst].specular, sc.mats[inst].roughness


@wp.func
def smooth_normal(sc: ShadeScene, item: wp.int32, face: wp.int32, a: wp.vec3, b: wp.vec3, c: wp.vec3, p: wp.vec3,
                  n_face: wp.vec3):
    """Smooth shading: the corner normals of ``face`` blended at object-frame point p's barycentric coordinates
    (u a + v b + (1 - u - v) c = p, as ``eval_position``), in the camera frame, flipped to the side of ``n_face``
    (the face normal facing the ray). Falls back to ``n_face`` on a degenerate face."""
    e0 = a - c
    e1 = b - c
    r = p - c
    d00 = wp.dot(e0, e0)
    d01 = wp.dot(e0, e1)
    d11 = wp.dot(e1, e1)
    det = d00 * d11 - d01 * d01
    if det <= 0.0:
        return n_face
    d20 = wp.dot(r, e0)
    d21 = wp.dot(r, e1)
    u = (d11 * d20 - d01 * d21) / det
    v = (d00 * d21 - d01 * d20) / det
    k = 3 * (sc.inst.item_face0[item] + face)
    m = u * sc.corner_n[k] + v * sc.corner_n[k + 1] + (1.0 - u - v) * sc.corner_n[k + 2]
    if wp.length(m) <= 1.0e-12:
        return n_face
    ns = wp.normalize(wp.transform_vector(sc.inst.ref_T_obj[item], m))
    if wp.dot(ns, n_face) < 0.0:
        ns = -ns
    return ns


@wp.func
def direct_light(sc: ShadeScene, clip: wp.int32, g: wp.int32, x: wp.vec3, n: wp.vec3, wo: wp.vec3, albedo: wp.vec3,
                 spec: wp.float32, rough: wp.float32, shadows: wp.bool):
    """Radiance towards wo from the delta lights of scene ``clip`` at x (group g); with ``shadows``, one shadow ray
    per lit light."""
    L = wp.vec3(0.0)
    o = offset_origin(x, n)
    for l in range(sc.n_lights[clip]):
        v = sc.light_vec[g, l]
        E = sc.light_irr[clip, l]
        wi = v
        t_max = sc.max_t
        if sc.light_kind[clip, l] == LIGHT_POINT:
            dv = v - x
            r2 = wp.dot(dv, dv)
            if r2 <= MIN_LIGHT_DIST2:
                continue
            r = wp.sqrt(r2)
            wi = dv / r
            E = E / r2
            t_max = r
        ci = wp.dot(n, wi)
        if ci <= 0.0:
            continue
        if shadows:
            if trace_any(sc.inst, sc.inst.roots[g], o, wi, t_max):
                continue
        L += wp.cw_mul(brdf(n, wi, wo, albedo, spec, rough), E) * ci
    return L


@wp.func
def clamp_indirect(c: wp.vec3):
    m = wp.max(c[0], wp.max(c[1], c[2]))
    if m > INDIRECT_CLAMP:
        return c * (INDIRECT_CLAMP / m)
    return c


@wp.func
def path_radiance(sc: ShadeScene, clip: wp.int32, g: wp.int32, x0: wp.vec3, n0: wp.vec3, wo0: wp.vec3, albedo0: wp.vec3,
                  spec0: wp.float32, rough0: wp.float32, bounces: wp.int32, rng: wp.uint32, spread0: wp.float32):
    """Path-traced radiance towards wo0 from hit x0: next-event estimation at every vertex, ``bounces``
    BRDF-sampled bounces (one-sample mixture of cosine and GGX half-vector sampling), Russian roulette,
    roughness at least MIN_INDIRECT_ROUGHNESS after a bounce, indirect contributions clamped to
    INDIRECT_CLAMP."""
    x = x0
    n = n0
    wo = wo0
    albedo = albedo0
    spec = spec0
    rough = rough0
    L = direct_light(sc, clip, g, x, n, wo, albedo, spec, rough, True)
    beta = wp.vec3(1.0)
    spread = spread0
    for b in range(bounces):
        p_spec = wp.where(spec <= 0.0, 0.0, wp.where(spec >= 1.0, 1.0, wp.clamp(spec, 0.1, 0.9)))
        u1 = wp.randf(rng)
        u2 = wp.randf(rng)
        u3 = wp.randf(rng)
        e1, e2 = tangent_frame(n)
        phi = 2.0 * PI * u2
        a = rough * rough
        a2 = a * a
        wi = wp.vec3(0.0)
        if u3 < p_spec:
            c2 = (1.0 - u1) / (1.0 + (a2 - 1.0) * u1)
            st = wp.sqrt(wp.max(1.0 - c2, 0.0))
            h = e1 * (st * wp.cos(phi)) + e2 * (st * wp.sin(phi)) + n * wp.sqrt(c2)
            wi = 2.0 * wp.dot(wo, h) * h - wo
        else:
            r = wp.sqrt(u1)
            wi = e1 * (r * wp.cos(phi)) + e2 * (r * wp.sin(phi)) + n * wp.sqrt(wp.max(1.0 - u1, 0.0))
        wi = wp.normalize(wi)
        ci = wp.dot(n, wi)
        if ci <= 0.0:
            break
        pdf = (1.0 - p_spec) * ci / PI
        if p_spec > 0.0:
            h = wp.normalize(wi + wo)
            nh = wp.max(wp.dot(n, h), 0.0)
            pdf += p_spec * ggx_d(nh, a2) * nh / wp.max(4.0 * wp.dot(wo, h), 1.0e-30)
        if pdf < PDF_MIN:
            break
        beta = wp.cw_mul(beta, brdf(n, wi, wo, albedo, spec, rough)) * (ci / pdf)
        if b >= RR_START:
            q = wp.min(wp.max(beta[0], wp.max(beta[1], beta[2])), RR_MAX_SURVIVAL)
            if wp.randf(rng) >= q:
                break
            beta = beta / q
        o = offset_origin(x, n)
        item, dist, face, bu, bv = trace_closest(sc.inst, sc.inst.roots[g], o, wi, sc.max_t)
        if item < 0:
            L += clamp_indirect(wp.cw_mul(beta, sc.sky[clip]))
            break
        x = o + wi * dist
        wo = -wi
        spread += dist * BOUNCE_SPREAD
        p_hit = eval_position(sc.inst.blas_tris, sc.inst.blas_slot, sc.inst.item_face0[item], face, bu, bv)
        n, albedo, spec, rough = surface(sc, item, face, p_hit, wi, spread)
        rough = wp.max(rough, MIN_INDIRECT_ROUGHNESS)
        L += clamp_indirect(wp.cw_mul(beta, direct_light(sc, clip, g, x, n, wo, albedo, spec, rough, True)))
    return L


FLT_MAX = wp.constant(wp.float32(3.4028234663852886e38))  # largest finite float32


@wp.func
def edge_pixel(item: wp.array3d[wp.int32], t: wp.int32, i: wp.int32, j: wp.int32) -> wp.bool:
    """True at a silhouette: a 4-neighbour of pixel (i, j) sees another instance (or the sky) at its centre."""
    c = item[t, i, j]
    e = False
    if i > 0:
        e = e or item[t, i - 1, j] != c
    if i + 1 < item.shape[1]:
        e = e or item[t, i + 1, j] != c
    if j > 0:
        e = e or item[t, i, j - 1] != c
    if j + 1 < item.shape[2]:
        e = e or item[t, i, j + 1] != c
    return e


@wp.func
def finite_nonneg1(x: wp.float32):
    if x > 0.0 and x < FLT_MAX:
        return x
    return wp.float32(0.0)


@wp.func
def finite_nonneg(c: wp.vec3):
    """c with each component that is not finite and > 0 (NaN, +-inf, negative, -0) set to +0: what
    ``np.nan_to_num(np.maximum(c, 0), nan=0, posinf=0)`` gives, in the kernel instead of a pass over the frames."""
    return wp.vec3(finite_nonneg1(c[0]), finite_nonneg1(c[1]), finite_nonneg1(c[2]))


@specialised_builder
def shade_kernel(mode: str, lens: bool = False, per_pixel: bool = False):
    """The shading kernel for render mode "flat", "direct" or "path" (other modes' code compiled out).

    Two launch shapes of one body (``flowsynth.parallel.pixel_threads``): ``per_pixel`` False, dims (T, rows) from
    row ``band0`` (``row_loop=True``), each thread shading the W pixels of its row; True, dims (T, rows, W), a thread
    per pixel. Output ``radiance`` (T, H, W) vec3: mean linear radiance of the pixel's samples.

    ``lens``: a lens camera (flowsynth/scene/camera.py); ``cam.rays`` holds ``Camera.ray_grid(pad)`` (rows and columns
    -pad .. H - 1 + pad, pad = (rows - H) / 2 >= 1). The pixel-centre sample takes its centre's ray (the ray the
    G-buffer cast, so it still reuses that hit); a sub-pixel sample at (u, v) takes ``lens_ray``, the
    bilinear blend of the four surrounding centres' rays (tests/test_lens.py bounds how far it projects from
    (u, v) through OpenCV). A sample whose ray is uncovered (or whose blend touches an uncovered centre)
    contributes black (0): an uncovered pixel is black, a pixel at the edge of the lens's image is dimmed by
    the share of its samples there. The pinhole variant's code is that of before (the lens lines are
    ``wp.static`` branches).

    Inputs: ``ShadeScene``, ``ShadeGBuffer``, ``Pinhole``, ``ShadeSampling`` (fields documented there), ``band0``.
    """
    if mode not in RENDER_MODES:
        raise ValueError(f"unknown render mode {mode!r}; choose from {RENDER_MODES}")
    path = mode == "path"
    shadows = mode == "direct"

    @wp.kernel(enable_backward=False, module="unique")
    def shade(
        sc: ShadeScene,
        gb: ShadeGBuffer,
        cam: Pinhole,
        smp: ShadeSampling,
        band0: wp.int32,
        # outputs
        radiance: wp.array3d[wp.vec3],
    ):
        gb_item = gb.item
        gb_face = gb.face
        gb_dist = gb.dist
        gb_point = gb.point
        reuse = gb.reuse
        spp = smp.spp
        edge_spp = smp.edge_spp
        slices = smp.slices
        bounces = smp.bounces
        if wp.static(per_pixel):
            t, i, j0 = wp.tid()
            j1 = j0 + 1
        else:
            t, i = wp.tid()
            j0 = wp.int32(0)
            j1 = radiance.shape[2]
        i += band0
        clip = t // smp.frames  # frame t - clip T of scene clip
        seed = smp.seeds[clip]
        seed_t = wp.int32(hash3(t - clip * smp.frames, 0, seed))
        seed_p = wp.int32(hash3(t - clip * smp.frames, 1, seed))
        seed_e = wp.int32(hash3(t - clip * smp.frames, 2, seed))
        if wp.static(lens):
            pad = (cam.rays.shape[0] - radiance.shape[1]) // 2
        for j in range(j0, j1):
            pix = wp.uint32(i * radiance.shape[2] + j)
            prng = wp.rand_init(seed_p, wp.int32(pix))
            scramble = wp.uint32(wp.randi(prng))
            t_off = wp.randi(prng, 0, slices)
            acc = wp.vec3(0.0)
            ns = spp
            own = reuse  # 1: shade the G-buffer's pixel-centre hit
            seed_k = seed_t
            pix_angle = sc.pix_angle
            if edge_spp > spp:
                if edge_pixel(gb_item, t, i, j):
                    ns = edge_spp
                    own = 0
                    seed_k = seed_e
                    pix_angle = sc.pix_angle * wp.sqrt(wp.float32(spp) / wp.float32(edge_spp))
            for k in range(ns):
                rng = wp.rand_init(seed_k, wp.int32(pix * wp.uint32(ns) + wp.uint32(k)))
                g = t * slices + (k + t_off) % slices
                item = wp.int32(-1)
                face = wp.int32(-1)
                dist = wp.float32(0.0)
                p_obj = wp.vec3(0.0)
                d = wp.vec3(0.0)
                if own != 0:
                    d = camera_ray(wp.float32(i), wp.float32(j), cam)
                    if wp.static(lens):
                        d = cam.rays[i + pad, j + pad]
                        if d[2] <= 0.0:  # uncovered: black
                            continue
                    item = gb_item[t, i, j]
                    face = gb_face[t, i, j]
                    dist = gb_dist[t, i, j]
                    p_obj = gb_point[t, i, j]
                else:
                    du = (wp.float32(k) + wp.randf(rng)) / wp.float32(ns)
                    dv = unit(reverse_bits(wp.uint32(k)) ^ scramble)
                    d = camera_ray(wp.float32(i) + dv - 0.5, wp.float32(j) + du - 0.5, cam)
                    if wp.static(lens):
                        d = lens_ray(wp.float32(i) + dv - 0.5, wp.float32(j) + du - 0.5, cam.rays, pad)
                        if d[2] <= 0.0:  # uncovered: black
                            continue
                    bu = wp.float32(0.0)
                    bv = wp.float32(0.0)
                    if sc.use_tiles != 0:  # the primary cast's walk: candidates of the pixel's tile, near to far
                        lst = tile_list(sc.tiles.tiles_x, sc.tiles.tiles_y, sc.tiles.tile_shift, g, i, j)
                        item, dist, face, bu, bv = closest_from_camera(sc.inst, g, sc.tiles.start, sc.tiles.items, lst,
                                                                       d, sc.max_t)
                    else:
                        item, dist, face, bu, bv = trace_closest(sc.inst, sc.inst.roots[g], wp.vec3(0.0), d,
                                                                 sc.max_t)
                    if item >= 0:
                        p_obj = eval_position(sc.inst.blas_tris, sc.inst.blas_slot, sc.inst.item_face0[item], face,
                                              bu, bv)
                if item < 0:
                    acc += sc.sky[clip]
                    continue
                spread = dist * pix_angle
                n, albedo, spec, rough = surface(sc, item, face, p_obj, d, spread)
                x = d * dist
                L = wp.vec3(0.0)
                if wp.static(path):
                    L = path_radiance(sc, clip, g, x, n, -d, albedo, spec, rough, bounces, rng, spread)
                else:
                    L = wp.cw_mul(sc.sky[clip], albedo * (1.0 - spec) + wp.vec3(spec))
                    L += direct_light(sc, clip, g, x, n, -d, albedo, spec, rough, wp.static(shadows))
                if wp.isfinite(L):
                    acc += L
            radiance[t, i, j] = finite_nonneg(acc / wp.float32(ns))

    return shade
