"""The library's FlyingChairs-style layers (``flowsynth.datasets``: torch, analytic shapes) beside the learning
benchmark's helper (``learning.sets.chairs2d_pairs``: OpenCV), on one judge-like pool: how far apart they are.

    python benchmarks/accuracy/layers_equivalence.py [--quick] [--n 1200] [--seed 0] [--sources 64]
                                                     [--motion-scale 1.0]

Both draw from one generator ``default_rng(seed)`` over n pairs at 256x192 (the judge's size), with the same sources:
frame 0 of the library's default texture bank (BouncingThings frames at 256x192, 8-bit), the first ``--sources`` of
them. The draws are equal call for call (tests/test_layers2d.py); what differs is how shapes are filled and images
warped. The helper runs twice: plain, timed, and with its OpenCV calls recorded (the masks it drew and warped: its
layer maps, frame 1 and 2). The library pair by pair (``draw_pair``, ``render_layers``: what ``layers_pairs`` runs),
timed. Reported:

- layer differs: share of pixels whose layer (background or shape k) differs, frame 1, frame 2;
- flow EPE between the two [px]: all pixels, and where the frame-1 layers agree; mean |flow| of each [px];
- image mean |difference| (0..1 scale), frame 1, frame 2, and frame 2 where both frames' layers agree;
- rate of each [pairs/s] (the helper unrecorded), both on one thread (``torch.set_num_threads(1)``,
  ``cv2.setNumThreads(1)``), as in one DataLoader worker: on a loaded 2-core machine torch's two intra-op threads
  made the library 10x slower than one.

Writes benchmarks/results/layers_equivalence.json (``--quick``: 64 pairs, layers_equivalence_quick.json).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common, learning

from _common import machine_info, print_table, write_json

RES = (256, 192)  # (w, h): the learning judge's pools


def sources(m: int):
    """The first ``m`` frames of the library's default texture bank at RES, (m, 3, h, w) float32."""
    import torch

    from flowsynth.datasets import Layers, LayersConfig

    bank = Layers(LayersConfig(width=RES[0], height=RES[1], texture_bank=m), ["rgb"]).textures
    return torch.stack([bank[j] for j in range(m)])


def helper_pool(n: int, seed: int, src, motion_scale: float, record: bool):
    """``chairs2d_pairs``' (img1, img2, flow, valid) and, with ``record``, its layer maps (n, 2, h, w) uint8 from
    the masks it drew (frame 1) and warped with INTER_NEAREST (frame 2)."""
    import cv2
    import numpy as np

    from flowsynth.datasets import draw_pair
    from learning.sets import chairs2d_pairs

    if not record:
        return chairs2d_pairs(n, seed, src, motion_scale), None
    masks, real = [], {k: getattr(cv2, k) for k in ("ellipse", "fillPoly", "warpAffine")}

    def drawn(name):
        def call(mask, *args):
            out = real[name](mask, *args)
            masks.append(("drawn", mask.copy()))
            return out
        return call

    def warp(img, M, size, **kw):
        out = real["warpAffine"](img, M, size, **kw)
        if kw.get("flags") == cv2.INTER_NEAREST:
            masks.append(("warped", out))
        return out

    cv2.ellipse, cv2.fillPoly, cv2.warpAffine = drawn("ellipse"), drawn("fillPoly"), warp
    try:
        pool = chairs2d_pairs(n, seed, src, motion_scale)
    finally:
        for k, fn in real.items():
            setattr(cv2, k, fn)
    rng = np.random.default_rng(seed)
    h, w = src.shape[-2:]
    lay = np.zeros((n, 2, h, w), np.uint8)
    it = iter(masks)
    for i in range(n):
        for k in range(1, len(draw_pair(rng, w, h, len(src), motion_scale).layers) + 1):
            (a, m1), (b, m2) = next(it), next(it)
            assert (a, b) == ("drawn", "warped")
            lay[i, 0][m1.astype(bool)] = k
            lay[i, 1][m2.astype(bool)] = k
    return pool, lay


def compare(n: int, seed: int, src, motion_scale: float, pool, lay) -> tuple[dict, float]:
    """The differences (module docstring) and the library's seconds for the n pairs."""
    import numpy as np
    import torch

    from flowsynth.datasets import draw_pair, render_layers

    img1, img2, flow, _ = pool
    h, w = src.shape[-2:]
    rng = np.random.default_rng(seed)
    s = {k: 0.0 for k in ("lay1", "lay2", "epe", "epe_agree", "agree", "mag_h", "mag_l", "mad1", "mad2",
                          "mad2_agree", "agree2")}
    seconds = 0.0
    for i in range(n):
        t = time.perf_counter()
        out = render_layers(draw_pair(rng, w, h, len(src), motion_scale), src.__getitem__, w, h, 2,
                            ("rgb", "flow_fw", "instance"))
        seconds += time.perf_counter() - t
        inst = out["instance"][:, 0].numpy()
        same1, same2 = inst[0] == lay[i, 0], inst[1] == lay[i, 1]
        epe = torch.linalg.vector_norm(out["flow_fw"][0] - flow[i], dim=0).numpy()
        d1 = (out["rgb"][0] - img1[i]).abs().mean(0).numpy()
        d2 = (out["rgb"][1] - img2[i]).abs().mean(0).numpy()
        both = same1 & same2
        s["lay1"] += float((~same1).sum())
        s["lay2"] += float((~same2).sum())
        s["epe"] += float(epe.sum())
        s["epe_agree"] += float(epe[same1].sum())
        s["agree"] += float(same1.sum())
        s["mag_h"] += float(torch.linalg.vector_norm(flow[i], dim=0).sum())
        s["mag_l"] += float(torch.linalg.vector_norm(out["flow_fw"][0], dim=0).sum())
        s["mad1"] += float(d1.sum())
        s["mad2"] += float(d2.sum())
        s["mad2_agree"] += float(d2[both].sum())
        s["agree2"] += float(both.sum())
    px = n * h * w
    return {"layer_differs_frame1": s["lay1"] / px, "layer_differs_frame2": s["lay2"] / px,
            "flow_epe_all_px": s["epe"] / px, "flow_epe_where_layers_agree_px": s["epe_agree"] / s["agree"],
            "mean_flow_helper_px": s["mag_h"] / px, "mean_flow_library_px": s["mag_l"] / px,
            "image_mad_frame1": s["mad1"] / px, "image_mad_frame2": s["mad2"] / px,
            "image_mad_frame2_where_layers_agree": s["mad2_agree"] / s["agree2"]}, seconds


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="64 pairs, 16 sources [flag]")
    p.add_argument("--n", type=int, default=1200, help="pairs [default 1200, the judge's pool]")
    p.add_argument("--seed", type=int, default=0, help="the generator's seed [default 0]")
    p.add_argument("--sources", type=int, default=64, help="texture-bank frames both use [default 64]")
    p.add_argument("--motion-scale", type=float, default=1.0, help="both generators' motion_scale [default 1.0]")
    args = p.parse_args()
    n, m = (64, 16) if args.quick else (args.n, args.sources)
    import cv2
    import torch

    t = time.perf_counter()
    src = sources(m)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    bank_s = time.perf_counter() - t
    t = time.perf_counter()
    helper_pool(n, args.seed, src, args.motion_scale, record=False)
    helper_s = time.perf_counter() - t
    pool, lay = helper_pool(n, args.seed, src, args.motion_scale, record=True)
    diff, library_s = compare(n, args.seed, src, args.motion_scale, pool, lay)
    rates = {"helper_pairs_per_s": n / helper_s, "library_pairs_per_s": n / library_s}
    print(f"{n} pairs at {RES[0]}x{RES[1]}, seed {args.seed}, {m} sources (bank {bank_s:.0f} s), motion_scale "
          f"{args.motion_scale}; torch threads {torch.get_num_threads()}, OpenCV threads {cv2.getNumThreads()}")
    print_table([{"measure": k, "value": v} for k, v in {**diff, **rates}.items()], ["measure", "value"])
    write_json("layers_equivalence" + ("_quick" if args.quick else ""),
               {"machine": machine_info(("opencv-python", "opencv-python-headless", "kornia")),
                "n": n, "seed": args.seed, "sources": m, "size": list(RES), "motion_scale": args.motion_scale,
                "bank_seconds": bank_s, "helper_seconds": helper_s, "library_seconds": library_s,
                "torch_threads": torch.get_num_threads(), "opencv_threads": cv2.getNumThreads(), **diff, **rates})


if __name__ == "__main__":
    main()
