"""The final pass (rgb_final, flowsynth/renderer/finalpass.py) against its models: each effect alone on a known scene,
checked against an oracle written here (kornia's sRGB decoding, analytic ray lengths, the thin-lens formula,
a brute-force numpy gather, the Poisson-Gaussian moments); the ground truth untouched; determinism."""

from __future__ import annotations

import dataclasses

import kornia
import numpy as np
import pytest
import torch
import trimesh

import flowsynth as fs
from flowsynth.errors import ConfigError
from flowsynth.renderer.finalpass import apply_dof, draw_final
from flowsynth.appearance.lights import Light
from flowsynth.plan import FinalPass
from flowsynth.renderer.shading import poses_at

# Every effect off: the final pass must equal the clean pass bit for bit.
OFF = dict(final_shutter=0.0, final_dof_prob=0.0, final_shot_noise=(0.0, 0.0), final_read_noise=(0.0, 0.0),
           final_exposure_jitter=0.0, final_wb_jitter=0.0, final_fog_density=0.0)
WALL_Z = 5.9  # the wall's front face [m], camera frame
CFG = fs.BouncingThingsConfig(width=64, height=48, num_frames=3, motion="kinematic", num_objects=(3, 4),
                              max_objects=4)


def to_linear(rgb: torch.Tensor) -> np.ndarray:
    """sRGB-encoded (..., 3, H, W) -> linear, decoded by kornia (not flowsynth's own transfer function)."""
    return kornia.color.rgb_to_linear_rgb(rgb.reshape(-1, *rgb.shape[-3:])).reshape(rgb.shape).numpy()


def pose(t=(0.0, 0.0, 0.0)) -> np.ndarray:
    P = np.eye(4)
    P[:3, 3] = t
    return P


def wall_scene(T: int = 2, W: int = 96, H: int = 72, solid=None, lights=None) -> fs.Scene:
    """Camera at the origin looking down +z at a static wall whose front face is at z = WALL_Z."""
    scene = fs.Scene(fs.Camera.from_fov(W, H, 60.0), T)
    scene.lights = lights or [Light("directional", (1.0, 0.95, 0.9), 0.5, direction=(0.2, 0.3, 1.0)),
                              Light("ambient", (0.8, 0.9, 1.0), 0.2)]
    material = ({"texture": "solid", "colors": [solid, solid], "specular": 0.0} if solid is not None else
                {"texture": "noise", "octaves": 2, "specular": 0.0, "scale": 0.5, "seed": 11,
                 "colors": [[0.85, 0.8, 0.7], [0.25, 0.3, 0.35]]})
    scene.add_object(trimesh.creation.box((12.0, 9.0, 0.2)), pose((0.0, 0.0, WALL_Z + 0.1)), material=material)
    return scene


def final(scene, **effects) -> dict[str, torch.Tensor]:
    return fs.render(scene, ["rgb", "rgb_final", "distance", "depth"], **{**OFF, **effects})


def test_all_effects_off_equals_clean():
    scene = wall_scene(3)
    box = trimesh.creation.box((1.0, 0.8, 0.9))
    scene.add_object(box, np.stack([pose((-0.8 + 0.3 * t, 0.1, 3.5)) for t in range(3)]))
    out = final(scene, edge_spp=4)
    assert torch.equal(out["rgb_final"], out["rgb"])
    alone = fs.render(scene, ["rgb"], edge_spp=4)["rgb"]
    assert torch.equal(out["rgb"], alone)  # asking for rgb_final changes nothing in rgb


def test_noise_statistics_match_poisson_gaussian():
    """A flat patch of known linear value x: mean x and variance a x + b^2 per channel (within 5 standard errors
    of the mean and 6% of the variance, ~6 standard errors of the sample variance at n = 18432)."""
    a, b = 0.004, 0.01
    scene = wall_scene(2, W=128, H=72, solid=[0.6, 0.5, 0.4], lights=[Light("ambient", (1, 1, 1), 1.0)])
    out = final(scene, final_shot_noise=(a, a), final_read_noise=(b, b))
    clean, noisy = to_linear(out["rgb"]), to_linear(out["rgb_final"])
    for c in range(3):
        x = clean[:, c]
        assert np.ptp(x) < 1e-6  # the patch is flat
        x = float(x.mean())
        y = noisy[:, c].astype(np.float64).ravel()
        var = a * x + b * b
        assert 0.05 < x < 0.8 and y.min() > 0.0 and y.max() < 1.0  # no clipping biases the moments
        assert abs(y.mean() - x) < 5 * np.sqrt(var / y.size), (c, y.mean(), x)
        assert abs(y.var() / var - 1.0) < 0.06, (c, y.var(), var)
    assert not np.array_equal(noisy[0], noisy[1])  # every frame draws its own noise


def test_fog_matches_exponential_attenuation():
    """L' = L exp(-sigma s) + F (1 - exp(-sigma s)) with s the analytic ray length to the plane z = WALL_Z."""
    sigma, fog = 0.15, (0.3, 0.4, 0.5)
    scene = wall_scene(2)
    out = final(scene, final_fog_density=sigma, final_fog_color=fog)
    W, H = scene.camera.width, scene.camera.height
    K = scene.camera.K
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    s = WALL_Z * np.linalg.norm(ray, axis=-1)  # distance along the ray to z = WALL_Z
    np.testing.assert_allclose(out["distance"][0, 0].numpy(), s, rtol=1e-5)
    trans = np.exp(-sigma * s)[None, None]
    clean = to_linear(out["rgb"])
    want = clean * trans + np.asarray(fog)[None, :, None, None] * (1 - trans)
    ok = (clean < 0.999) & (want < 0.999)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(to_linear(out["rgb_final"])[ok], want[ok], atol=3e-5)


def test_exposure_and_white_balance_apply_the_drawn_gains():
    ej, wj = 0.3, 0.1
    scene = wall_scene(3)
    out = final(scene, final_exposure_jitter=ej, final_wb_jitter=wj)
    gains = draw_final(scene.render_seed, FinalPass(**{**{k.removeprefix("final_"): v for k, v in OFF.items()},
                                                       "exposure_jitter": ej, "wb_jitter": wj}),
                       np.zeros((72, 96)), np.zeros((72, 96), bool), 3).gains
    clean, graded = to_linear(out["rgb"]), to_linear(out["rgb_final"])
    for t in range(3):
        for c in range(3):
            x, y = clean[t, c], graded[t, c]
            ok = (x > 0.02) & (y < 0.999)
            ratio = y[ok] / x[ok]
            assert ok.sum() > 1000 and np.ptp(ratio) < 2e-3, (t, c)  # one gain per frame and channel
            assert abs(np.median(ratio) - gains[t, c]) < 1e-4
    assert np.ptp(gains[:, 1]) > 0.01 and np.ptp(gains[:, 0] / gains[:, 1]) > 0.01  # they change between frames


def test_dof_leaves_the_focus_plane_unchanged():
    scene = wall_scene(2)
    out = final(scene, final_dof_prob=1.0, final_aperture=(0.05, 0.05), final_focus=WALL_Z)
    assert torch.equal(out["rgb_final"], out["rgb"])
    blurred = final(scene, final_dof_prob=1.0, final_aperture=(0.05, 0.05), final_focus=0.5)
    assert (blurred["rgb_final"] - blurred["rgb"]).abs().mean() > 1e-3  # out of focus, the texture blurs


def thin_lens_coc(d: float, A: float, d_f: float, f_px: float, f_m: float) -> float:
    """c = A f |d - d_f| / (d (d_f - f)) on the sensor, in pixels: times f_px / f."""
    return A * f_m * abs(d - d_f) / (d * (d_f - f_m)) * f_px / f_m


@pytest.mark.parametrize("d", [2.0, 9.0])
def test_dof_blurs_a_step_edge_to_the_thin_lens_width(d):
    """A step edge on a plane at depth d: the edge profile's derivative is the disc's chord profile, a semicircle
    of radius r = c / 2 whose variance is r^2 / 4; the transition spans |x - edge| < r + 1 and nothing more."""
    A, d_f, f_px, f_m = 0.5, 4.0, 100.0, 0.03
    c = thin_lens_coc(d, A, d_f, f_px, f_m)
    H, W, edge = 40, 90, 45
    rad = np.zeros((1, H, W, 3), np.float32)
    rad[:, :, edge:] = 1.0
    out = apply_dof(rad, np.full((1, H, W), d), A, d_f, f_px, f_m, max_coc=64.0, threads=1)
    prof = out[0, H // 2, :, 0].astype(np.float64)
    dp = np.diff(prof)
    x = np.arange(W - 1) + 0.5
    mean = (x * dp).sum() / dp.sum()
    sd = np.sqrt(((x - mean) ** 2 * dp).sum() / dp.sum())
    r = c / 2
    assert 3.0 < r < 20.0
    assert abs(mean - (edge - 0.5)) < 0.05
    assert abs(2 * sd - r) < 0.06 * r, (2 * sd, r)
    inside = np.nonzero((prof > 1e-6) & (prof < 1 - 1e-6))[0]
    assert inside.min() >= edge - r - 1 and inside.max() <= edge + r


def brute_force_gather(rad, depth, coc):
    """The documented gather rule, written out: q's disc (radius max(c_q/2, 1/2)) covers p, and q is not behind
    p unless p's own disc reaches q; weights 1 / r_q^2."""
    T, H, W, _ = rad.shape
    r = np.maximum(coc / 2, 0.5)
    depth = np.where(depth > 0, depth, np.inf)  # nothing hit: infinitely far
    out = np.zeros_like(rad, dtype=np.float64)
    for t in range(T):
        for i in range(H):
            for j in range(W):
                acc, wsum = np.zeros(3), 0.0
                for qi in range(H):
                    for qj in range(W):
                        d2 = (qi - i) ** 2 + (qj - j) ** 2
                        rq = r[t, qi, qj]
                        if d2 <= rq * rq and (depth[t, qi, qj] <= depth[t, i, j] or d2 <= r[t, i, j] ** 2):
                            acc += rad[t, qi, qj] / rq**2
                            wsum += 1 / rq**2
                out[t, i, j] = acc / wsum
    return out


def test_dof_gather_matches_brute_force_and_respects_occlusion():
    rng = np.random.default_rng(0)
    T, H, W = 1, 18, 22
    A, d_f, f_px, f_m = 0.3, 3.0, 60.0, 0.03
    depth = np.full((T, H, W), 8.0)
    depth[:, 5:12, 6:14] = d_f  # a sharp foreground square at the focus distance
    depth[:, 14:, 17:] = 1.2  # a blurred corner nearer than focus, its CoC radius (4.5 px) off the square
    depth[:, :3, :3] = 0.0  # sky
    rad = rng.random((T, H, W, 3)).astype(np.float32)
    out = apply_dof(rad, depth, A, d_f, f_px, f_m, max_coc=10.0, threads=2)
    coc = np.array([[[min(thin_lens_coc(z if z > 0 else 1e30, A, d_f, f_px, f_m), 10.0) for z in row]
                     for row in frame] for frame in depth])
    np.testing.assert_allclose(out, brute_force_gather(rad, depth, coc), rtol=2e-5, atol=2e-6)
    sharp = depth == d_f
    np.testing.assert_array_equal(out[sharp], rad[sharp])  # no background bleeds onto the sharp foreground


def test_dof_blurred_foreground_spreads_over_a_sharp_background():
    """Everything in focus but a near square: exactly the pixels within the square's CoC radius change."""
    rng = np.random.default_rng(1)
    A, d_f, f_px, f_m = 0.3, 3.0, 60.0, 0.03
    depth = np.full((1, 30, 30), d_f)
    depth[:, 10:16, 12:18] = 1.2
    r = thin_lens_coc(1.2, A, d_f, f_px, f_m) / 2
    rad = rng.random((1, 30, 30, 3)).astype(np.float32)
    out = apply_dof(rad, depth, A, d_f, f_px, f_m, max_coc=20.0, threads=1)
    ii, jj = np.mgrid[:30, :30]
    gap = np.hypot(np.maximum(np.maximum(10 - ii, ii - 15), 0), np.maximum(np.maximum(12 - jj, jj - 17), 0))
    changed = np.abs(out[0] - rad[0]).max(-1) > 0
    assert 3.0 < r < 6.0
    np.testing.assert_array_equal(changed[depth[0] == d_f], (gap <= r)[depth[0] == d_f])


def blur_scene(times) -> fs.Scene:
    """A textured box translating across the wall, posed at the given (fractional) frame times."""
    scene = wall_scene(len(times))
    P = np.stack([pose((-1.0 + 0.25 * t, 0.2 * t, 3.5)) for t in range(3)])
    scene.add_object(trimesh.creation.box((1.2, 1.0, 0.8)), poses_at(P, np.asarray(times, float)),
                     material={"texture": "checks", "scale": 0.3, "seed": 2, "specular": 0.0,
                               "colors": [[0.9, 0.7, 0.2], [0.1, 0.2, 0.6]]})
    return scene


def test_motion_blur_is_centred_on_the_frame_instant():
    """Frame t integrates [t - s/2, t + s/2]: the mean of sharp renders at the K slice times (frame 0's earlier
    half extrapolated backwards), and the ground truth stays that of the frame instant."""
    s, K = 0.8, 8
    scene = blur_scene([0, 1, 2])
    out = fs.render(scene, ["rgb", "rgb_final", "depth", "flow_fw"], **{**OFF, "final_shutter": s,
                                                                        "final_time_samples": K})
    sharp = fs.render(scene, ["depth", "flow_fw"])
    assert torch.equal(out["depth"], sharp["depth"]) and torch.equal(out["flow_fw"], sharp["flow_fw"])
    for t in range(3):
        times = t + s * ((np.arange(K) + 0.5) / K - 0.5)
        ref = np.mean([to_linear(fs.render(blur_scene([x]), ["rgb"], spp=16, seed=k)["rgb"][0])
                       for k, x in enumerate(times)], 0)
        err = np.abs(to_linear(out["rgb_final"][t]) - ref)
        err_clean = np.abs(to_linear(out["rgb"][t]) - ref)
        assert err.mean() < 0.004 and np.quantile(err, 0.99) < 0.08, (t, err.mean())
        assert err_clean.mean() > 3 * err.mean()
    opened = 1 + s * (np.arange(K) + 0.5) / K  # a shutter opening at the instant instead: further off
    ref = np.mean([to_linear(fs.render(blur_scene([x]), ["rgb"], spp=16, seed=k)["rgb"][0])
                   for k, x in enumerate(opened)], 0)
    assert np.abs(to_linear(out["rgb_final"][1]) - ref).mean() > 3 * err.mean()


def test_ground_truth_is_byte_identical_with_and_without_final():
    gt = ["flow_fw", "flow_bw", "depth", "distance", "occ_fw", "valid_fw", "instance", "normals"]
    a = fs.datasets.BouncingThings(CFG, outputs=gt, seed=4).sample(1)
    b = fs.datasets.BouncingThings(CFG, outputs=gt + ["rgb_final"], seed=4).sample(1)
    for k in gt:
        assert a[k].dtype == b[k].dtype and a[k].numpy().tobytes() == b[k].numpy().tobytes(), k


def test_finite_in_range_deterministic_and_reproducible_from_provenance():
    cfg = dataclasses.replace(CFG, final_dof_prob=1.0, final_aperture=(0.05, 0.08), final_fog_density=0.1,
                              final_shot_noise=(0.01, 0.02), final_read_noise=(0.02, 0.05), final_exposure_jitter=1.0)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "rgb_final"], seed=2)
    s = ds.sample(0)
    x = s["rgb_final"]
    assert x.shape == s["rgb"].shape and x.dtype == torch.float32
    assert torch.isfinite(x).all() and x.min() >= 0 and x.max() <= 1
    again = fs.datasets.BouncingThings(cfg, outputs=["rgb_final"], seed=2).sample(0)["rgb_final"]
    assert x.numpy().tobytes() == again.numpy().tobytes()
    assert not torch.equal(x, ds.sample(1)["rgb_final"])
    meta = ds.scene(0).to_meta()
    back = fs.render(fs.Scene.from_meta(meta), ["rgb_final"], **cfg.plan_options())["rgb_final"]
    assert torch.equal(back, x)
    other = fs.render(fs.Scene.from_meta(meta), ["rgb_final"], seed=12345, **cfg.plan_options())["rgb_final"]
    assert not torch.equal(other, x)  # the plan's seed, when set, is the final pass's seed too


def test_config_validates_final_fields():
    with pytest.raises(ConfigError, match="final_aperture"):
        fs.BouncingThingsConfig(final_aperture=(0.05, 0.01))
    with pytest.raises(ConfigError, match="final_shutter"):
        fs.BouncingThingsConfig(final_shutter=1.5)
    with pytest.raises(ConfigError, match="final_fog_color"):
        fs.BouncingThingsConfig(final_fog_color=(1.0, -1.0, 0.0))
    cfg = fs.BouncingThingsConfig(final_max_coc=8, final_focus=3)
    assert cfg.final_max_coc == 8.0 and isinstance(cfg.final_max_coc, float)
    assert fs.BouncingThingsConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.plan_options()["final_focus"] == 3.0
