"""Export throughput (samples/s) with 1 and 2 workers, bytes per sample per format, and the EXR compressions.

    python benchmarks/speed/export.py [--quick]

The EXR table writes the float32 EXR files of one sample of the default config (320x240, native layout's
default outputs: depth, flow_fw, flow_bw) with every lossless compression that ``--exr-compression``
offers, side by side in one run (round robin, process CPU time), checks each reads back bit-exactly, and
gives bytes and write / read times; it chose the default (flowsynth.io.layouts.base.Layout).

Writes benchmarks/results/export.json.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common

from _common import EXPORT_OUTPUTS, EXPORT_SAMPLE, Timer, machine_info, print_table, time_round_robin, write_json

OUTPUTS = list(EXPORT_OUTPUTS)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    import flowsynth as fs
    from flowsynth.export import export_dataset

    W, H = (256, 192) if args.quick else (512, 384)
    num = 12 if args.quick else 32
    cfg = fs.BouncingThingsConfig(width=W, height=H, **EXPORT_SAMPLE)
    rows, sizes = [], defaultdict(list)
    tmp = Path(tempfile.mkdtemp(prefix="fs-export-bench-"))
    try:
        export_dataset(cfg, tmp / "warm", 1, outputs=OUTPUTS, progress=False)  # compile / load kernels once
        for workers in (1, 2):
            out = tmp / f"w{workers}"
            with Timer() as tm:
                export_dataset(cfg, out, num, outputs=OUTPUTS, workers=workers, progress=False, seed=workers)
            dt = tm.wall_s
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
    exr = exr_compressions(num_frames=24, repeat=2 if args.quick else 3)  # the default config, also when quick
    write_json("export", {"machine": machine_info(), "resolution": [W, H], "outputs": OUTPUTS,
                          "throughput": rows, "bytes_per_sample": per_format, "exr_compression": exr})


def exr_compressions(num_frames: int, repeat: int) -> dict:
    """Bytes, write and read CPU time of one default sample's EXR files per lossless compression."""
    import numpy as np

    import flowsynth as fs
    from flowsynth.datasets import BouncingThings
    from flowsynth.io import CHANNEL_NAMES, read_tensor_exr, write_tensor_exr
    from flowsynth.io.layouts import EXR_COMPRESSIONS, get

    cfg = fs.BouncingThingsConfig(num_frames=num_frames)
    keys = ("depth", "flow_fw", "flow_bw")
    assert set(keys) <= set(get("native").default_outputs)
    sample = BouncingThings(cfg, outputs=list(keys)).sample(0)
    planes = [(k, t, sample[k][t].numpy()) for k in keys for t in range(sample[k].shape[0])]
    names = {"depth": CHANNEL_NAMES["depth"], "flow_fw": CHANNEL_NAMES["flow"], "flow_bw": CHANNEL_NAMES["flow"]}
    tmp = Path(tempfile.mkdtemp(prefix="fs-exr-bench-"))
    try:
        def writer(c):
            return lambda: [write_tensor_exr(tmp / c / f"{k}_{t}.exr", a, names[k], compression=c)
                            for k, t, a in planes]

        def reader(c):
            return lambda: [read_tensor_exr(tmp / c / f"{k}_{t}.exr", names[k]) for k, t, _ in planes]

        for c in EXR_COMPRESSIONS:
            (tmp / c).mkdir()
        writes = time_round_robin({c: writer(c) for c in EXR_COMPRESSIONS}, repeat=repeat)
        reads = time_round_robin({c: reader(c) for c in EXR_COMPRESSIONS}, repeat=repeat)
        raw = sum(a.nbytes for _, _, a in planes)
        rows = []
        for c in EXR_COMPRESSIONS:
            exact = all(np.array_equal(read_tensor_exr(tmp / c / f"{k}_{t}.exr", names[k]), a) for k, t, a in planes)
            size = {k: sum((tmp / c / f"{k}_{t}.exr").stat().st_size for kk, t, _ in planes if kk == k) for k in keys}
            rows.append({"compression": c, "depth MB": size["depth"] / 1e6, "flow_fw MB": size["flow_fw"] / 1e6,
                         "flow_bw MB": size["flow_bw"] / 1e6, "total MB": sum(size.values()) / 1e6,
                         "x raw": sum(size.values()) / raw, "write s": writes[c]["cpu_s"],
                         "read s": reads[c]["cpu_s"], "bit-exact": exact})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nEXR compressions, one sample at {cfg.width}x{cfg.height}, T={num_frames} ({len(planes)} files, "
          f"{raw / 1e6:.1f} MB raw float32); CPU seconds per sample, median of {repeat}; load {os.getloadavg()}")
    print_table(rows, ["compression", "depth MB", "flow_fw MB", "flow_bw MB", "total MB", "x raw", "write s",
                       "read s", "bit-exact"])
    return {"num_frames": num_frames, "raw_bytes": raw, "rows": rows}


if __name__ == "__main__":
    main()
