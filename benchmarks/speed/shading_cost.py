"""What shading costs, on one pinned core: texture lookups, texture families, and the shading kernel's camera rays.

    python benchmarks/speed/shading_cost.py [--quick]

Shading is most of a default sample (flat mode, 320x240, 24 frames: the radiance kernel is about half of its
CPU time), and in flat mode most of the shading is texture lookups. Three tables:

(A "blend" material looks up only the layers its mask shows since 2026-11-24: where the mask weight is exactly 0
or 1, one layer; the families table run at the revision before and after shows what that saves.)

1. **Lookups** (``lookups``): a kernel evaluates one pattern at N random points, 5 octaves each (the frequency
   doubling as in ``fractal``), once per variant, round-robin:
   - ``cells`` as the library has it (the winning feature's value hashed once, after the 3x3 search) beside
     ``cells_per_improvement`` (the form before 2026-11-24, in this file: the value hashed every time a nearer
     feature is found); the outputs must be identical;
   - ``wp.noise`` (Perlin, the "noise" family) and ``value_noise`` for scale.
2. **Shading** (``families``): process CPU of ``flowsynth.renderer.shading.shade_radiance`` per 2-frame 512x384
   sample (flat mode, 20 objects, edge_spp 1, seed 0) with every object and wall given one texture family,
   beside "solid" (x_solid: its time over solid's, the cost of the texture), and the default mix; and the
   default config's whole sample with the radiance share.
3. **Camera rays** (``camera_rays``): the shading kernel traces rays of its own from the camera for the extra
   samples of edge pixels (``edge_spp``) and for spp > 1. Without motion blur they walk the G-buffer cast's
   screen-tile lists near to far (``flowsynth.renderer.shading.CAMERA_RAY_TILES``, since 2026-11-24) instead of the
   top-level BVH; shade_radiance per sample both ways, round-robin, with the images compared (identical).
   Settings: the default config (flat, edge_spp 4), issue 13's full sample (512x384, 2 frames, direct, 20
   objects, edge_spp 4) and the same with spp 4.

4. **Parts** (``parts``): the full sample's own shading (512x384, 2 frames, 20 objects, direct light, edge_spp 4,
   the default texture mix, every output) beside variants that each leave one part out: the shadow rays (flat
   mode), the textures (every surface solid), the extra samples of silhouette pixels (edge_spp 1), and the shadow
   rays and textures together; shade_radiance per sample and what each part costs. Issue 63 reads the full
   sample against Cycles (benchmarks/peers/cycles.py), and this is what holds its shading where it is.

Writes benchmarks/results/shading_cost.json (quick: shading_cost_quick.json; a subset of ``--tables``:
shading_cost_<tables>.json).
"""

from __future__ import annotations

import argparse
import sys
import time
from contextlib import contextmanager
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]
from _common import (FULL_SAMPLE_OUTPUTS, Timer, full_sample_config, machine_info, pin_single_core, print_table,
                     time_round_robin, write_json)

PINNING = pin_single_core()

import numpy as np

from flowsynth.kernels import wp_runtime

wp = wp_runtime()

from flowsynth.kernels.texture import cells, hash3, unit, value_noise

OCTAVES = 5
FAMILIES = ("solid", "stripes", "checks", "value", "noise", "cells", "blend")


@wp.func
def cells_per_improvement(q: wp.vec2, seed: wp.int32) -> wp.float32:
    """``flowsynth.kernels.texture.cells`` before 2026-11-24: the same cells, the value hashed on every
    improvement."""
    fx = wp.floor(q[0])
    fy = wp.floor(q[1])
    ix = wp.int32(fx)
    iy = wp.int32(fy)
    best = wp.float32(1.0e9)
    value = wp.float32(0.0)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            h = hash3(ix + dx, iy + dy, seed)
            px = fx + wp.float32(dx) + unit(h)
            py = fy + wp.float32(dy) + unit(hash3(ix + dx, iy + dy, seed + 1))
            d2 = (q[0] - px) * (q[0] - px) + (q[1] - py) * (q[1] - py)
            if d2 < best:
                best = d2
                value = unit(hash3(ix + dx, iy + dy, seed + 2))
    return value


VARIANTS = ("cells", "cells_per_improvement", "wp.noise", "value_noise", "empty loop")


@wp.kernel(enable_backward=False)
def lookup_kernel(q: wp.array[wp.vec2], variant: wp.int32, out: wp.array[wp.float32]):
    i = wp.tid()
    p = q[i]
    acc = wp.float32(0.0)
    for o in range(OCTAVES):
        seed = 7 + o
        r = wp.float32(0.0)
        if variant == 0:
            r = cells(p, seed)
        elif variant == 1:
            r = cells_per_improvement(p, seed)
        elif variant == 2:
            r = wp.noise(wp.rand_init(seed, o), p)
        elif variant == 3:
            r = value_noise(p, seed)
        acc += r
        p = p * 2.0
    out[i] = acc


def lookups(n: int, rounds: int) -> list[dict]:
    rng = np.random.default_rng(0)
    q = wp.array(rng.uniform(-50.0, 50.0, (n, 2)).astype(np.float32), dtype=wp.vec2)
    outs = {v: wp.zeros(n, dtype=wp.float32) for v in VARIANTS}

    def run(k):
        return lambda: wp.launch(lookup_kernel, n, [q, k], [outs[VARIANTS[k]]])

    t = time_round_robin({v: run(k) for k, v in enumerate(VARIANTS)}, repeat=rounds, warmup=1)
    same = np.array_equal(outs["cells"].numpy(), outs["cells_per_improvement"].numpy())
    empty = t["empty loop"]["cpu_s"]
    rows = []
    for v in VARIANTS:
        cpu = t[v]["cpu_s"]
        rows.append({"variant": v, "cpu_ms": cpu * 1e3,
                     "ns_per_octave": max(cpu - empty, 0.0) / (n * OCTAVES) * 1e9 if v != "empty loop" else None})
    rows[0]["x_before"] = rows[1]["ns_per_octave"] / max(rows[0]["ns_per_octave"], 1e-12)
    rows[0]["note"] = f"outputs identical to cells_per_improvement: {same}"
    if not same:
        raise SystemExit("cells differs from cells_per_improvement")
    return rows


@contextmanager
def radiance_timer():
    """Wraps ``flowsynth.renderer.shading.shade_radiance`` (which ``render_rgb`` calls) for the ``with`` block: yields a
    dict whose "s" the wrapper adds each call's process CPU time to; the original is put back on exit."""
    from flowsynth.renderer import shading

    orig = shading.shade_radiance
    spent = {"s": 0.0}

    def timed(*a, **k):
        with Timer() as tm:
            out = orig(*a, **k)
        spent["s"] += tm.cpu_s
        return out

    shading.shade_radiance = timed
    try:
        yield spent
    finally:
        shading.shade_radiance = orig


def stream_rounds(streams: dict, indices: range, rounds: int, rotate: bool = False) -> dict:
    """Each stream's samples ``indices`` once a round, round-robin (``time_round_robin``: one untimed warm-up round,
    then ``rounds``; ``rotate``: each round starts with another stream): {name: fn} with ``fn.radiance_s`` and
    ``fn.sample_s``, the shade_radiance and whole-sample process CPU seconds a sample of each timed round."""
    def run(name, spent):
        def go():
            spent["s"] = 0.0
            with Timer() as tm:
                for i in indices:
                    streams[name].sample(i)
            go.sample_s.append(tm.cpu_s / len(indices))
            go.radiance_s.append(spent["s"] / len(indices))
        go.sample_s, go.radiance_s = [], []
        return go

    with radiance_timer() as spent:
        fns = {name: run(name, spent) for name in streams}
        time_round_robin(fns, repeat=rounds, warmup=1, rotate=rotate)
    for fn in fns.values():  # the warm-up round appended too: drop it
        del fn.radiance_s[0], fn.sample_s[0]
    return fns


def families(width: int, height: int, samples: int, rounds: int) -> list[dict]:
    import torch

    import flowsynth as fs

    torch.set_num_threads(1)
    sets = {"default mix": None, **{f: (f,) for f in FAMILIES}}
    streams = {}
    for name, fam in sets.items():
        kw = {} if fam is None else {"texture_families": fam}
        cfg = full_sample_config(width=width, height=height, render_mode="flat", edge_spp=1, **kw)
        streams[name] = fs.datasets.BouncingThings(cfg, outputs=["rgb"], seed=0, threads=1)
    default = fs.datasets.BouncingThings(fs.BouncingThingsConfig(), seed=0, threads=1)
    streams["default config, whole sample"] = default

    fns = stream_rounds(streams, range(samples), rounds)
    solid = float(np.median(fns["solid"].radiance_s))
    rows = []
    for name, fn in fns.items():
        rad = float(np.median(fn.radiance_s))
        smp = float(np.median(fn.sample_s))
        whole = name.startswith("default config")
        rows.append({"textures": name, "radiance_cpu_ms": rad * 1e3, "x_solid": None if whole else rad / solid,
                     "sample_cpu_ms": smp * 1e3, "radiance_share": rad / smp})
    return rows


def _tiles_vs_bvh(ds, scenes: list, rounds: int) -> tuple[float, float, bool]:
    """Median shade_radiance CPU per scene [s] with camera rays through the tile lists and through the BVH,
    alternating each round (one untimed warm-up round), and whether every image came out identical."""
    import torch

    from flowsynth.renderer import render_plan, shading

    per = {True: [], False: []}
    images = {}
    with radiance_timer() as spent:
        try:
            for r in range(rounds + 1):
                for tiles in (True, False):
                    shading.CAMERA_RAY_TILES = tiles
                    spent["s"] = 0.0
                    images[tiles] = [render_plan(sc, ds.plan)["rgb"] for sc in scenes]
                    if r:
                        per[tiles].append(spent["s"] / len(scenes))
        finally:
            shading.CAMERA_RAY_TILES = True
    same = all(torch.equal(a, b) for a, b in zip(images[True], images[False]))
    return float(np.median(per[True])), float(np.median(per[False])), same


def camera_rays(samples: int, rounds: int, quick: bool) -> list[dict]:
    import torch

    import flowsynth as fs

    torch.set_num_threads(1)
    W, H = (256, 192) if quick else (512, 384)
    settings = {"default config (flat, edge_spp 4)": fs.BouncingThingsConfig(),
                f"full sample {W}x{H} direct, edge_spp 4": full_sample_config(width=W, height=H),
                f"full sample {W}x{H} direct, spp 4": full_sample_config(width=W, height=H, spp=4)}
    rows = []
    for name, cfg in settings.items():
        ds = fs.datasets.BouncingThings(cfg, outputs=["rgb"], seed=0, threads=1)
        t, b, same = _tiles_vs_bvh(ds, [ds.scene(i) for i in range(samples)], rounds)
        if not same:
            raise SystemExit(f"{name}: the tile walk and the BVH walk rendered different images")
        rows.append({"setting": name, "bvh_radiance_ms": b * 1e3, "tiles_radiance_ms": t * 1e3, "x_bvh": b / t,
                     "images_identical": same})
    return rows


# The full sample's shading with one part of it left out at a time (``parts``): (label, config overrides).
PARTS = (("full sample (direct, edge_spp 4, default textures)", {}),
         ("no shadow rays (flat)", {"render_mode": "flat"}),
         ("solid textures", {"texture_families": ("solid",)}),
         ("no extra edge samples (edge_spp 1)", {"edge_spp": 1}),
         ("flat and solid", {"render_mode": "flat", "texture_families": ("solid",)}))


def parts(width: int, height: int, samples: int, rounds: int) -> list[dict]:
    """shade_radiance CPU ms per sample of the full sample (``full_sample_config``: direct light, edge_spp 4, the
    default texture mix) and of each ``PARTS`` variant that leaves one part of the work out, on the same indices
    (from 5000), round-robin with a rotating start; each variant's saving against the full sample, and the full
    sample's whole CPU ms (the share shading is of it)."""
    import torch

    import flowsynth as fs

    torch.set_num_threads(1)
    streams = {label: fs.datasets.BouncingThings(full_sample_config(width=width, height=height, **kw),
                                                 outputs=list(FULL_SAMPLE_OUTPUTS), seed=0, threads=1)
               for label, kw in PARTS}

    fns = stream_rounds(streams, range(5000, 5000 + samples), rounds, rotate=True)
    full = PARTS[0][0]
    full_rad = float(np.median(fns[full].radiance_s))
    rows = []
    for name, fn in fns.items():
        rad = float(np.median(fn.radiance_s))
        rows.append({"shading": name, "radiance_cpu_ms": rad * 1e3, "saved_ms": (full_rad - rad) * 1e3,
                     "x_full": rad / full_rad, "sample_cpu_ms": float(np.median(fn.sample_s)) * 1e3,
                     "radiance_min_ms": float(np.min(fn.radiance_s)) * 1e3,
                     "radiance_max_ms": float(np.max(fn.radiance_s)) * 1e3})
    return rows


TABLES = ("lookups", "families", "camera_rays", "parts")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--tables", default=",".join(TABLES),
                   help="comma-separated subset of " + ",".join(TABLES) + " (the families table alone also runs "
                        "against an older flowsynth: a before/after of the texture kernels)")
    args = p.parse_args()
    tables = args.tables.split(",")
    if set(tables) - set(TABLES):
        raise SystemExit(f"--tables: unknown {sorted(set(tables) - set(TABLES))}; choose from {TABLES}")
    n, rounds, (W, H), samples = (100_000, 3, (256, 192), 2) if args.quick else (400_000, 5, (512, 384), 3)
    t0 = time.perf_counter()
    out = {"machine": machine_info(), "pinning": PINNING, "octaves": OCTAVES, "points": n, "rounds": rounds,
           "resolution": [W, H]}
    if "lookups" in tables:
        out["lookups"] = lookups(n, rounds)
        print(f"\nOne lookup of {OCTAVES} octaves at {n} random points, one pinned core (affinity "
              f"{PINNING['affinity']}); medians of {rounds} round-robin rounds of process CPU time; ns_per_octave net "
              "of the empty loop; x_before: the previous form's time over this one's")
        print_table(out["lookups"], ["variant", "cpu_ms", "ns_per_octave", "x_before", "note"])
    if "families" in tables:
        out["families"] = families(W, H, samples, rounds)
        print(f"\nshade_radiance per 2-frame {W}x{H} sample (flat, 20 objects, edge_spp 1, seed 0, {samples} "
              f"samples a round, medians of {rounds} rounds), every surface one family; last row: "
              "BouncingThingsConfig() (320x240, 24 frames, flat, edge_spp 4), whole sample")
        print_table(out["families"], ["textures", "radiance_cpu_ms", "x_solid", "sample_cpu_ms", "radiance_share"])
    if "camera_rays" in tables:
        out["camera_rays"] = camera_rays(samples, rounds, args.quick)
        print(f"\nshade_radiance per sample [ms], camera rays through the top-level BVH vs the tile lists "
              f"({samples} samples a round, medians of {rounds} round-robin rounds, process CPU); x_bvh: BVH time "
              "over tiles time")
        print_table(out["camera_rays"], ["setting", "bvh_radiance_ms", "tiles_radiance_ms", "x_bvh",
                                         "images_identical"])
    if "parts" in tables:
        out["parts"] = parts(W, H, samples, rounds)
        print(f"\nThe full sample's shading ({W}x{H}, 2 frames, 20 objects, every output) with one part left out: "
              f"shade_radiance process CPU ms a sample ({samples} samples a round from index 5000, medians of "
              f"{rounds} rotating round-robin rounds, min and max); saved_ms: the full sample's minus the row's; "
              "sample_cpu_ms: the whole sample")
        print_table(out["parts"], ["shading", "radiance_cpu_ms", "saved_ms", "x_full", "sample_cpu_ms",
                                   "radiance_min_ms", "radiance_max_ms"])
    out["seconds"] = time.perf_counter() - t0
    write_json(("shading_cost_quick" if args.quick else "shading_cost") + ("" if tables == list(TABLES) else
                                                                         "_" + "_".join(tables)), out)


if __name__ == "__main__":
    main()
