"""CPU against CUDA: every main output of a few default samples, held to the tolerances of ``TOLERANCES``.

    python benchmarks/device/device_agreement.py [--quick] [--samples N] [--device cuda]

Renders samples 0..N-1 of ``fs.datasets.BouncingThings(BouncingThingsConfig(), outputs=MAIN_OUTPUTS, seed=0)`` (the
default config: 320x240, 24 frames, flat shading) and sample 0 of the same config with ``render_mode="direct"``
(shadow rays), once with ``device="cpu"`` and once with ``device`` (default "cuda"), and compares them key by key
(``compare``), with these tolerances (``TOLERANCES``):

- ids and masks identical: instance, occ_fw, occ_bw, valid_fw (and the scene's K and cam_T_world);
- flow_fw, flow_bw within 1e-3 px (largest absolute difference of any component);
- depth within 1e-4 relative (|a - b| / max(a, b) where either is non-zero);
- rgb within 0.02 (largest absolute difference of any channel);
- normals: no tolerance in the issue; the largest difference is reported.

Each row gives the largest difference over every sample, the number of elements beyond the tolerance, and the
99.9th percentile of the absolute difference. The first CUDA sample's time includes compiling (or loading) every
kernel. Exit status 1 when any tolerance is broken, else 0; where Warp finds no CUDA device the script says
"no CUDA", writes nothing and exits 0. ``--quick``: one sample, 4 frames.

Writes benchmarks/results/device_agreement.json after every sample (``_quick`` with --quick), with the machine and
versions. tests/test_device_agreement.py holds ``compare`` to the tolerances and runs a small scene through it on
every device Warp finds.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import machine_info, print_table, write_json

MAIN_OUTPUTS = ("rgb", "depth", "flow_fw", "flow_bw", "occ_fw", "occ_bw", "valid_fw", "instance", "normals", "K",
                "cam_T_world")
TOLERANCES: dict[str, tuple[str, float | None]] = {
    "instance": ("equal", 0), "occ_fw": ("equal", 0), "occ_bw": ("equal", 0), "valid_fw": ("equal", 0),
    "K": ("equal", 0), "cam_T_world": ("equal", 0),
    "flow_fw": ("abs", 1e-3), "flow_bw": ("abs", 1e-3),
    "depth": ("rel", 1e-4),
    "rgb": ("abs", 0.02),
    "normals": ("abs", None),
}
"""key -> (kind, tolerance): "equal" (every element identical), "abs" (largest absolute difference <= tolerance),
"rel" (largest relative difference <= tolerance); None: reported, not held to a tolerance."""


def compare(ref: dict, got: dict, keys=None) -> list[dict]:
    """One row per key of ``keys`` (default: every key of ``TOLERANCES`` in both dicts): kind, tolerance, ``max``
    (largest absolute or relative difference; for "equal" the number of differing elements), ``over`` (elements
    beyond the tolerance), ``p999`` (99.9th percentile of the absolute difference), ``elements`` and ``ok`` (None
    where no tolerance applies). A shape or dtype mismatch is a row with ``ok`` False."""
    import torch

    keys = [k for k in TOLERANCES if k in ref and k in got] if keys is None else list(keys)
    rows = []
    for k in keys:
        kind, tol = TOLERANCES[k]
        a, b = ref[k], got[k]
        row = {"key": k, "kind": kind, "tolerance": tol, "elements": a.numel()}
        if a.shape != b.shape or a.dtype != b.dtype:
            rows.append({**row, "max": None, "over": None, "p999": None, "ok": False,
                         "error": f"{tuple(a.shape)} {a.dtype} against {tuple(b.shape)} {b.dtype}"})
            continue
        if kind == "equal":
            differ = int((a != b).sum())
            diff = (a.double() - b.double()).abs() if a.dtype != torch.bool else (a != b).double()
            rows.append({**row, "max": differ, "over": differ, "p999": _p999(diff), "ok": differ == 0})
            continue
        a64, b64 = a.double(), b.double()
        diff = (a64 - b64).abs()
        if kind == "rel":
            scale = torch.maximum(a64.abs(), b64.abs())
            err = torch.where(scale > 0, diff / scale.clamp_min(1e-300), torch.zeros_like(diff))
        else:
            err = diff
        nan = int(torch.isnan(a64).sum() + torch.isnan(b64).sum())
        worst = float(err.max()) if err.numel() else 0.0
        over = int((err > tol).sum()) if tol is not None else None
        rows.append({**row, "max": worst, "over": over, "p999": _p999(diff), "nan": nan,
                     "ok": None if tol is None else (over == 0 and nan == 0)})
    return rows


def _p999(diff) -> float:
    import torch

    if diff.numel() == 0:
        return 0.0
    flat = diff.flatten().double()
    k = max(1, int(round(0.999 * flat.numel())))
    return float(torch.kthvalue(flat, k).values)


def merge(total: dict[str, dict], rows: list[dict]) -> None:
    """Fold a sample's rows into ``total`` (largest max and p999, summed over and elements, ok of all)."""
    for r in rows:
        t = total.get(r["key"])
        if t is None:
            total[r["key"]] = dict(r)
            continue
        for f in ("max", "p999"):
            if r[f] is not None and (t[f] is None or r[f] > t[f]):
                t[f] = r[f]
        for f in ("over", "elements", "nan"):
            if r.get(f) is not None:
                t[f] = (t.get(f) or 0) + r[f]
        if t["ok"] is not None or r["ok"] is not None:
            t["ok"] = bool(t["ok"] is not False and r["ok"] is not False)
        if "error" in r:
            t["error"] = r["error"]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="one sample of 4 frames")
    p.add_argument("--samples", type=int, default=None, help="samples of the default config (default 3; quick 1)")
    p.add_argument("--device", default="cuda", help="the device compared with the CPU (default cuda)")
    args = p.parse_args()

    import flowsynth as fs
    from flowsynth.raycast import resolve_device
    from flowsynth.kernels import wp_runtime

    wp = wp_runtime()
    if args.device.startswith("cuda") and wp.get_cuda_device_count() == 0:
        print(f"no CUDA: Warp finds no CUDA device, so no {args.device!r}; skipped, nothing written")
        return 0
    resolve_device(args.device)  # a ConfigError naming what Warp finds, for any other device it lacks
    n = args.samples if args.samples is not None else (1 if args.quick else 3)
    base = fs.BouncingThingsConfig(num_frames=4) if args.quick else fs.BouncingThingsConfig()
    runs = [("default", base, i) for i in range(n)]
    runs.append(("default, direct", replace(base, render_mode="direct"), 0))

    name = "device_agreement" + ("_quick" if args.quick else "")
    result: dict = {"device": args.device, "cuda_name": wp.get_device(args.device).name,
                    "tolerances": {k: {"kind": v[0], "tolerance": v[1]} for k, v in TOLERANCES.items()},
                    "outputs": list(MAIN_OUTPUTS), "size": [base.width, base.height], "num_frames": base.num_frames,
                    "machine": machine_info(extra_packages=("kornia",)), "samples": [], "rows": []}
    total: dict[str, dict] = {}
    for label, cfg, i in runs:
        t = time.perf_counter()
        ref = fs.datasets.BouncingThings(cfg, outputs=MAIN_OUTPUTS, seed=0).sample(i)
        t_cpu = time.perf_counter() - t
        t = time.perf_counter()
        got = fs.datasets.BouncingThings(cfg, outputs=MAIN_OUTPUTS, seed=0, device=args.device).sample(i)
        t_dev = time.perf_counter() - t
        rows = compare(ref, got)
        merge(total, rows)
        broken = [r["key"] for r in rows if r["ok"] is False]
        result["samples"].append({"config": label, "render_mode": cfg.render_mode, "index": i, "cpu_s": t_cpu,
                                  "device_s": t_dev, "broken": broken, "rows": rows})
        result["rows"] = list(total.values())
        result["ok"] = all(r["ok"] is not False for r in total.values())
        write_json(name, result)
        print(f"{label} sample {i}: cpu {t_cpu:.2f} s, {args.device} {t_dev:.2f} s; "
              f"{'broken: ' + ', '.join(broken) if broken else 'within every tolerance'}", flush=True)

    print(f"\nCPU against {args.device} ({result['cuda_name']}), {len(runs)} samples of {base.width}x{base.height}, "
          f"T={base.num_frames}:")
    print_table([{"key": r["key"], "kind": r["kind"], "tolerance": r["tolerance"], "max diff": r["max"],
                  "p99.9 abs": r["p999"], "over": r["over"], "elements": r["elements"],
                  "ok": "-" if r["ok"] is None else ("yes" if r["ok"] else "NO")} for r in total.values()],
                ["key", "kind", "tolerance", "max diff", "p99.9 abs", "over", "elements", "ok"])
    path = write_json(name, result)
    print(f"{'every tolerance holds' if result['ok'] else 'A TOLERANCE IS BROKEN'}; wrote {path}")
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
