"""How cost grows: time per sample against pixels, objects, triangles per object and frames per clip.

    python benchmarks/scaling.py [--quick]

Hand-built scenes (icospheres of chosen resolution in front of a wall, random rigid motion) rendered with
the ground-truth request depth + flow_fw + occ_fw + instance. Each curve is fitted with cost ~ x^k and
the exponent k reported. Writes benchmarks/results/scaling.json and scaling_<axis>.png.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import fit_exponent, machine_info, pin_single_core, plot_curves, print_table, write_json

OUTPUTS = ["depth", "flow_fw", "occ_fw", "instance"]


def make_scene(W: int, H: int, n_obj: int, faces: int, T: int, seed: int = 0):
    import numpy as np
    import trimesh

    import flowsynth as fs

    rng = np.random.default_rng(seed)
    sub = max(0, int(round(np.log(faces / 20) / np.log(4))))  # icosphere: 20 * 4^s faces
    mesh = trimesh.creation.icosphere(sub, radius=0.3)
    scene = fs.Scene(fs.Camera.from_fov(W, H, 60), T)
    for _ in range(n_obj):
        p0 = rng.uniform([-3, -2, 4], [3, 2, 10])
        v = rng.uniform(-0.1, 0.1, 3)
        P = np.tile(np.eye(4), (T, 1, 1))
        for t in range(T):
            a = 0.05 * t
            P[t, :3, :3] = trimesh.transformations.rotation_matrix(a, [0, 1, 0])[:3, :3]
            P[t, :3, 3] = p0 + t * v
        scene.add_object(mesh, P)
    wall = np.eye(4)
    wall[2, 3] = 12
    scene.add_object(trimesh.creation.box((40, 40, 0.1)), wall)
    return scene, len(mesh.faces)


def time_render(scene, repeat: int) -> float:
    import flowsynth as fs

    fs.render(scene, OUTPUTS)
    best = float("inf")
    for _ in range(repeat):
        t = time.process_time()
        fs.render(scene, OUTPUTS)
        best = min(best, time.process_time() - t)
    return best


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    pin = pin_single_core()
    rep = 2 if args.quick else 3
    axes = {
        "pixels": [(w, h) for w, h in [(64, 48), (128, 96), (256, 192), (512, 384), (1024, 768)]],
        "objects": [5, 10, 20, 40, 80, 160],
        "triangles": [80, 320, 1280, 5120, 20480, 81920],
        "frames": [2, 4, 8, 16, 32],
    }
    if args.quick:
        axes["pixels"] = axes["pixels"][:4]
        axes["frames"] = axes["frames"][:4]
    base = dict(W=256, H=192, n_obj=20, faces=1280, T=2)
    results, fits = {}, []
    for axis, values in axes.items():
        rows = []
        for v in values:
            kw = dict(base)
            if axis == "pixels":
                kw["W"], kw["H"] = v
                x = v[0] * v[1]
            elif axis == "objects":
                kw["n_obj"] = x = v
            elif axis == "triangles":
                kw["faces"] = v
            else:
                kw["T"] = x = v
            scene, faces = make_scene(**kw)
            if axis == "triangles":
                x = faces
            s = time_render(scene, rep)
            rows.append({"axis": axis, "x": x, "s/sample": s, "ms/frame": 1e3 * s / kw["T"]})
        k = fit_exponent([r["x"] for r in rows], [r["s/sample"] for r in rows])
        fits.append({"axis": axis, "exponent": k, "range": f"{rows[0]['x']}..{rows[-1]['x']}"})
        results[axis] = rows
        print_table(rows, ["axis", "x", "s/sample", "ms/frame"])
        plot_curves(f"scaling_{axis}", {"depth+flow_fw+occ_fw": ([r["x"] for r in rows],
                                                                   [r["s/sample"] for r in rows])},
                    axis, "CPU s per sample", title=f"cost vs {axis} (exponent {k:.2f})")
    print("\nFitted exponents (cost ~ x^k), others at 256x192, 20 objects, 1280 faces, T=2:")
    print_table(fits, ["axis", "exponent", "range"])
    write_json("scaling", {"machine": machine_info(), "pinning": pin, "base": base, "curves": results,
                           "exponents": fits})


if __name__ == "__main__":
    main()
