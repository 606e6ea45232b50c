"""RGB rendering: time per frame against error, for each render mode and spp.

Scene: a closed, textured 10 x 8 x 6 m room (+z up, floor at z = 0) holding 16 objects (icospheres of
1280 faces, boxes, 48-sided cylinders, tori) with sampled materials and 1-3 sampled point lights, seen
from one end of the room. Times are wall time per frame of ``fs.render(scene, ["rgb"])`` (primary cast
included; kernels compiled beforehand) at the timing resolution on one core. Errors are the RMS difference
of the sRGB output [0, 1] from a high-spp ``path`` reference at the (lower) error resolution; the
reference's own noise is estimated from its two halves and reported. ``rmse_vs_own_ref`` is the error
against the same mode at the reference spp (the anti-aliasing / Monte Carlo error alone, without the
difference in light transport between modes). A second table sets spp 1 with ``edge_spp`` 4 (extra samples at
silhouettes only, BouncingThingsConfig's default) beside spp 1 and spp 4.

    python benchmarks/accuracy/rgb.py            # timing 512x384, errors 128x96 vs path 2x256 spp  (~7 min)
    python benchmarks/accuracy/rgb.py --quick    # timing 256x192, errors 96x72 vs path 2x128 spp   (< 2 min)

``rmse_corrected`` removes the reference noise n in quadrature: sqrt(max(rmse^2 - n^2, 0)).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]  # _common, and flowsynth from this checkout when not installed
from _common import RESULTS_DIR, Timer, machine_info, pin_single_core, print_table, write_json

MODES = ("flat", "direct", "path")
EDGE_SPP = 4  # BouncingThingsConfig's default edge_spp


def room_scene(width: int, height: int, num_objects: int = 16, seed: int = 0, num_frames: int = 1):
    import numpy as np
    import trimesh

    import flowsynth as fs
    from flowsynth.appearance import sample_lights, sample_material

    rng = np.random.default_rng(seed)
    scene = fs.Scene(fs.Camera.from_fov(width, height, 60.0), num_frames)
    size = np.array([10.0, 8.0, 6.0])
    cam = np.eye(4)
    cam[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # looks along +x, image down = -z
    cam[:3, 3] = [-4.5, 0.0, 2.0]
    scene.set_camera_poses(cam)
    for axis in range(3):
        for side in (-1.0, 1.0):
            ext = size + 0.2
            ext[axis] = 0.1
            pose = np.eye(4)
            pose[axis, 3] = side * (size[axis] / 2 + 0.05)
            pose[2, 3] += size[2] / 2
            scene.add_object(trimesh.creation.box(ext), pose, material=sample_material(rng, size=float(size.max())))
    shapes = [trimesh.creation.icosphere(3, 0.5), trimesh.creation.box((0.9, 0.6, 0.7)),
              trimesh.creation.cylinder(0.35, 1.0, sections=48), trimesh.creation.torus(0.45, 0.15)]
    for k in range(num_objects):
        pose = np.eye(4)
        pose[:3, :3] = trimesh.transformations.random_rotation_matrix(rng.uniform(size=3))[:3, :3]
        pose[:3, 3] = [rng.uniform(-2.0, 4.0), rng.uniform(-3.0, 3.0), rng.uniform(0.5, 4.5)]
        scene.add_object(shapes[k % 4], pose, material=sample_material(rng, size=1.0))
    scene.lights = sample_lights(rng, size, center=(0.0, 0.0, size[2] / 2))
    return scene


def render_rgb(scene, mode: str, spp: int, seed: int = 0, shutter: float = 0.0, edge_spp: int = 1):
    import flowsynth as fs

    return fs.render(scene, ["rgb"], render_mode=mode, spp=spp, seed=seed, shutter=shutter,
                     edge_spp=edge_spp)["rgb"].numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smaller images and reference (< 2 min)")
    args = ap.parse_args()
    pinning = pin_single_core()
    import numpy as np

    time_res, err_res, ref_half, spps = ((256, 192), (96, 72), 128, (1, 4, 16)) if args.quick else \
        ((512, 384), (128, 96), 256, (1, 4, 16, 64))
    scene_t, scene_e = room_scene(*time_res), room_scene(*err_res)
    with Timer() as tm:
        for mode in MODES:  # compile every kernel variant outside the timings
            render_rgb(room_scene(16, 12), mode, 2)
            render_rgb(room_scene(16, 12, num_frames=2), mode, 2, shutter=0.5)
    compile_s = tm.wall_s

    import flowsynth as fs

    with Timer() as tm:
        fs.render(scene_t, ["depth"])
    gbuffer_s = tm.wall_s
    with Timer() as tm:
        ref_a = render_rgb(scene_e, "path", ref_half, seed=1001)
        ref_b = render_rgb(scene_e, "path", ref_half, seed=1002)
    ref_s = tm.wall_s
    ref = 0.5 * (ref_a + ref_b)
    ref_noise = float(np.sqrt(np.mean((ref_a - ref_b) ** 2)) / 2.0)

    own = {mode: render_rgb(scene_e, mode, 2 * ref_half, seed=1003) for mode in MODES if mode != "path"}
    own["path"] = ref
    def row(mode: str, spp: int, edge_spp: int = 1) -> dict:
        with Timer() as tm:
            render_rgb(scene_t, mode, spp, edge_spp=edge_spp)
        seconds = tm.wall_s
        img = render_rgb(scene_e, mode, spp, edge_spp=edge_spp)
        rmse = float(np.sqrt(np.mean((img - ref) ** 2)))
        print(f"{mode:6s} spp {spp:3d} edge_spp {edge_spp:2d}: {seconds:8.3f} s/frame, rmse {rmse:.4f}", flush=True)
        return {"mode": mode, "spp": spp, "seconds_per_frame": seconds,
                "us_per_sample": seconds / (time_res[0] * time_res[1] * spp) * 1e6,
                "rmse_vs_path_ref": rmse, "rmse_corrected": math.sqrt(max(rmse**2 - ref_noise**2, 0.0)),
                "psnr_db": -20.0 * math.log10(max(rmse, 1e-12)),
                "rmse_vs_own_ref": float(np.sqrt(np.mean((img - own[mode]) ** 2)))}

    rows = [row(mode, spp) for mode in MODES for spp in spps]
    # edge_spp (BouncingThingsConfig's default 4): extra samples at silhouettes only, against spp 1 and spp 4
    edge_rows = []
    for mode in MODES:
        base = {r["spp"]: r for r in rows if r["mode"] == mode}
        e = row(mode, 1, EDGE_SPP)
        for name, r in (("spp 1", base[1]), (f"spp 1, edge_spp {EDGE_SPP}", e), ("spp 4", base[4])):
            edge_rows.append({"mode": mode, "samples": name, "seconds_per_frame": r["seconds_per_frame"],
                              "time_vs_spp1": r["seconds_per_frame"] / base[1]["seconds_per_frame"],
                              "rmse_vs_path_ref": r["rmse_vs_path_ref"], "rmse_vs_own_ref": r["rmse_vs_own_ref"]})
    blur_spp = 4
    two = room_scene(*time_res, num_frames=2)
    blur = {}
    for shutter in (0.0, 0.5):
        with Timer() as tm:
            render_rgb(two, "direct", blur_spp, shutter=shutter)
        blur[f"shutter_{shutter}"] = tm.wall_s / 2

    print(f"\nRGB at {time_res[0]}x{time_res[1]}, errors at {err_res[0]}x{err_res[1]} against path "
          f"{2 * ref_half} spp (reference noise ~{ref_noise:.4f} rms); G-buffer alone {gbuffer_s:.3f} s/frame")
    print_table(rows, ["mode", "spp", "seconds_per_frame", "us_per_sample", "rmse_vs_path_ref", "rmse_corrected",
                       "psnr_db", "rmse_vs_own_ref"])
    print(f"\nSilhouette anti-aliasing (edge_spp {EDGE_SPP}: max(spp, {EDGE_SPP}) samples where a 4-neighbour sees "
          "another instance), same scenes")
    print_table(edge_rows, list(edge_rows[0]))
    print(f"motion blur, direct spp {blur_spp}, per frame: shutter 0 {blur['shutter_0.0']:.3f} s, "
          f"shutter 0.5 {blur['shutter_0.5']:.3f} s")
    result = {
        "machine": machine_info(), "pinning": pinning, "quick": args.quick,
        "scene": "closed 10x8x6 m room, 16 objects (icosphere 1280 faces, box, cylinder, torus), "
                 "sampled materials and point lights",
        "timing_resolution": time_res, "error_resolution": err_res, "reference": {
            "mode": "path", "spp": 2 * ref_half, "seconds": ref_s, "noise_rms": ref_noise},
        "error_metric": "RMS difference of sRGB output in [0, 1] from the reference",
        "gbuffer_seconds_per_frame": gbuffer_s, "compile_seconds": compile_s,
        "rows": rows, "edge_spp_rows": edge_rows,
        "motion_blur_seconds_per_frame": {"mode": "direct", "spp": blur_spp, **blur},
    }
    path = write_json("rgb", result)
    png = plot(rows, RESULTS_DIR / "rgb.png",
               f"rgb {time_res[0]}x{time_res[1]}: time vs error to path {2 * ref_half} spp", ref_noise)
    print(f"wrote {path} and {png}")


def plot(rows: list[dict], path: Path, title: str, floor: float) -> Path:
    """Log-log plot of seconds per frame (x) against rmse (y), one line per mode; Pillow-drawn."""
    from PIL import Image, ImageDraw

    W, H, L, R, T, B = 760, 500, 70, 130, 60, 50
    img = Image.new("RGB", (W, H), "white")
    dr = ImageDraw.Draw(img)
    xs = [math.log10(r["seconds_per_frame"]) for r in rows]
    ys = [math.log10(max(r[k], 1e-6)) for r in rows for k in ("rmse_vs_path_ref", "rmse_vs_own_ref")]
    ys.append(math.log10(max(floor, 1e-6)))
    x0, x1 = math.floor(min(xs)), math.ceil(max(xs))
    y0, y1 = math.floor(min(ys) * 2) / 2, math.ceil(max(ys) * 2) / 2

    def px(lx, ly):
        return (L + (lx - x0) / max(x1 - x0, 1e-9) * (W - L - R), H - B - (ly - y0) / max(y1 - y0, 1e-9) * (H - T - B))

    dr.rectangle([L, T, W - R, H - B], outline="black")
    for d in range(x0, x1 + 1):
        x, _ = px(d, y0)
        dr.line([x, H - B, x, H - B + 5], fill="black")
        dr.text((x - 12, H - B + 8), f"1e{d}", fill="black")
    y = y0
    while y <= y1 + 1e-9:
        _, yy = px(x0, y)
        dr.line([L - 5, yy, L, yy], fill="black")
        dr.text((8, yy - 6), f"{10 ** y:.3g}", fill="black")
        y += 0.5
    dr.text((L + (W - L - R) // 2 - 60, H - 22), "seconds per frame (log)", fill="black")
    dr.text((8, T - 22), "rmse vs reference (log)", fill="black")
    dr.text((L + 10, 8), title, fill="black")
    _, yf = px(x0, math.log10(max(floor, 1e-6)))
    dr.line([L, yf, W - R, yf], fill=(160, 160, 160))
    dr.text((W - R + 6, yf - 6), "ref. noise", fill=(120, 120, 120))
    colors = {"flat": (31, 119, 180), "direct": (255, 127, 14), "path": (44, 160, 44)}
    legend = [(mode, "rmse_vs_path_ref", mode) for mode in MODES]
    legend += [(mode, "rmse_vs_own_ref", f"{mode} vs own") for mode in MODES if mode != "path"]
    for k, (mode, key, label) in enumerate(legend):
        pts = [(px(math.log10(r["seconds_per_frame"]), math.log10(max(r[key], 1e-6))), r["spp"])
               for r in rows if r["mode"] == mode]
        own = key == "rmse_vs_own_ref"
        dr.line([p for p, _ in pts], fill=colors[mode], width=1 if own else 2)
        for (x, y), spp in pts:
            dr.ellipse([x - 4, y - 4, x + 4, y + 4], outline=colors[mode], fill="white" if own else colors[mode])
            dr.text((x + 6, y - 14), str(spp), fill=colors[mode])
        yk = T + 20 + 20 * k
        dr.line([W - R + 10, yk, W - R + 30, yk], fill=colors[mode], width=1 if own else 3)
        dr.text((W - R + 36, yk - 6), label, fill="black")
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    img.save(path)
    return path


if __name__ == "__main__":
    main()
