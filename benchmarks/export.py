"""Export throughput (samples/s) with 1 and 2 workers, and bytes per sample per format.

    python benchmarks/export.py [--quick]

Writes benchmarks/results/export.json.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine_info, print_table, write_json

OUTPUTS = ["rgb", "depth", "normals", "flow_fw", "flow_bw", "occ_fw", "instance", "box2d_visible"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    import flowsynth as fs
    from flowsynth.export import export

    W, H = (256, 192) if args.quick else (512, 384)
    num = 12 if args.quick else 32
    cfg = fs.BouncingThingsConfig(width=W, height=H, num_frames=2, render_mode="direct")
    rows, sizes = [], defaultdict(list)
    tmp = Path(tempfile.mkdtemp(prefix="fs-export-bench-"))
    try:
        export(cfg, tmp / "warm", 1, outputs=OUTPUTS, progress=False)  # compile / load kernels once
        for workers in (1, 2):
            out = tmp / f"w{workers}"
            t = time.perf_counter()
            export(cfg, out, num, outputs=OUTPUTS, workers=workers, progress=False, seed=workers)
            dt = time.perf_counter() - t
            rows.append({"workers": workers, "samples": num, "seconds": dt, "samples/s": num / dt})
            if workers == 1:
                for f in out.glob("[0-9]*/*"):
                    key = f.name.rsplit("_", 1)[0] if f.name[-9:-4].lstrip("_").isdigit() else f.stem
                    sizes[f"{key} ({f.suffix[1:]})"].append(f.stat().st_size)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    per_format = [{"file": k, "bytes/sample": sum(v) / num} for k, v in sorted(sizes.items())]
    total = sum(r["bytes/sample"] for r in per_format)
    per_format.append({"file": "total", "bytes/sample": total})
    print(f"Export throughput at {W}x{H}, T=2, render_mode=direct, outputs={','.join(OUTPUTS)}; wall time "
          "includes starting the worker processes (spawn: each imports torch, Warp and Newton)")
    print_table(rows, ["workers", "samples", "seconds", "samples/s"])
    print("\nBytes per sample per file kind (T=2: 2 frames, 1 pair)")
    print_table(per_format, ["file", "bytes/sample"])
    write_json("export", {"machine": machine_info(), "resolution": [W, H], "outputs": OUTPUTS,
                          "throughput": rows, "bytes_per_sample": per_format})


if __name__ == "__main__":
    main()
