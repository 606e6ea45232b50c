"""Where a RAFT judge's net fails: ``--stats`` (flow magnitude and texture of the arms' pools beside the real judges),
``--diagnose`` (EPE on smooth or textured pixels with small or large true motion, with the small-motion diagnostic's
pairs) and ``--figures`` (each saved net's predicted flow beside the truth).
"""

from __future__ import annotations

from pathlib import Path

from _common import RESULTS_DIR

from .pools import build_arms
from .protocol import TEST_UPDATES, judge_sets
from .sets import small_motion_pairs

SMOOTH = 0.02  # a pixel is "smooth" when the mean |grey-level gradient| over its 9x9 window is below this (of 1)
SMALL = 4.0  # [px] "small" true motion


def texture_map(img):
    """(B, 1, H, W) mean |grey-level gradient| over each pixel's 9x9 window (images (B, 3, H, W) in [0, 1])."""
    from torch.nn import functional as F

    grey = img.float().mean(1, keepdim=True)
    grad = (grey[..., :, 1:] - grey[..., :, :-1]).abs()[..., :-1, :] + \
        (grey[..., 1:, :] - grey[..., :-1, :]).abs()[..., :, :-1]
    return F.avg_pool2d(F.pad(grad, (4, 5, 4, 5), mode="replicate"), 9, 1)


def pool_stats(names: list, n: int, workers: int, overrides: dict, middlebury_dir: str | None = None) -> list[dict]:
    """Per arm, over ``n`` training pairs of seed 0 at RES: |flow| percentiles and the share of valid pixels moving
    less than 0.5, 1 and 2 px, and the textureless share (``SMOOTH``); the real judges beside them."""
    import torch

    arms, _, _ = build_arms(names, 0, workers, overrides, n)
    sets = {**{k: (v[0].float() / 255, v[1], v[2], v[3]) for k, v in arms.items()}, **judge_sets(middlebury_dir)}
    rows = []
    for name, (img1, _, flow, valid) in sets.items():
        mag = torch.linalg.vector_norm(flow, dim=1)[valid[:, 0] > 0.5]
        q = torch.quantile(mag[torch.randperm(len(mag))[:1_000_000]], torch.tensor([0.1, 0.5, 0.9]))
        rows.append({"set": name, "mean |flow|": float(mag.mean()), "p10": float(q[0]), "p50": float(q[1]),
                     "p90": float(q[2]), "< 0.5 px": float((mag < 0.5).float().mean()),
                     "< 1 px": float((mag < 1).float().mean()), "< 2 px": float((mag < 2).float().mean()),
                     "textureless": float((texture_map(img1) < SMOOTH).float().mean())})
    return rows


def diagnose(nets: list[str], middlebury_dir: str | None) -> list[dict]:
    """Per saved net and real pair, the EPE over four kinds of valid pixel: smooth (low texture, ``SMOOTH``) or
    textured, crossed with small (|flow| < ``SMALL``) or large true motion; the share of each kind; and zero flow's
    EPE. Where a net "sees motion everywhere", its error on smooth pixels with small motion stands out. The pairs:
    the real judges and the small-motion diagnostic (``small_motion_pairs``: the judges' photographs moved by at
    most 0, 1 and 3 px; on a still pair the EPE is the motion the net invents)."""
    import torch

    from flowsynth.train.nets import raft_small
    from flowsynth.train.steps import predict

    tests = judge_sets(middlebury_dir)
    tests.update(small_motion_pairs({k: v for k, v in tests.items() if k.startswith("mb_")}))
    rows = []
    for path in nets:
        net = raft_small()
        net.load_state_dict(torch.load(path, map_location="cpu"))
        for pair, (img1, img2, flow, valid) in tests.items():
            texture = texture_map(img1[:1])
            err = torch.linalg.vector_norm(predict(net, img1[:1], img2[:1], TEST_UPDATES) - flow[:1], dim=1,
                                           keepdim=True)
            small = torch.linalg.vector_norm(flow[:1], dim=1, keepdim=True) < SMALL
            v = valid[:1] > 0.5
            row = {"net": Path(path).stem, "pair": pair, "all": float(err[v].mean()),
                   "zero flow": float(torch.linalg.vector_norm(flow[:1], dim=1, keepdim=True)[v].mean())}
            for tname, tmask in (("smooth", texture < SMOOTH), ("textured", texture >= SMOOTH)):
                for mname, mmask in (("small", small), ("large", ~small)):
                    m = v & tmask & mmask
                    row[f"{tname}/{mname}"] = float(err[m].mean()) if m.any() else None
                    row[f"share {tname}/{mname}"] = float(m.sum() / v.sum())
            rows.append(row)
    return rows


def figures(name: str, middlebury_dir: str | None, nets: list[str]) -> list:
    """One PNG per real pair and per still pair of the small-motion diagnostic (results/NAME_PAIR.png): frame 1, the
    ground truth and, per saved net (``nets``: paths of .pt files from ``train``), its predicted flow and its
    end-point error, on one colour scale per pair (at least 1 px)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import torch

    from flowsynth.train.nets import raft_small
    from flowsynth.train.steps import predict
    from flowsynth.viz import flow_to_color

    tests = judge_sets(middlebury_dir)
    still = small_motion_pairs({k: v for k, v in tests.items() if k.startswith("mb_")}, magnitudes=(0.0,))
    tests.update(still)  # the still pairs of the small-motion diagnostic: the motion a net invents
    loaded = {}
    for p in nets:
        net = raft_small()
        net.load_state_dict(torch.load(p, map_location="cpu"))
        loaded[Path(p).stem] = net
    paths = []
    for pair, (img1, img2, flow, valid) in tests.items():
        gt = flow[:1]
        scale = max(float(torch.linalg.vector_norm(gt, dim=1)[valid[:1, 0] > 0.5].max()), 1.0)
        cols = 2 + len(loaded)
        fig, ax = plt.subplots(2, cols, figsize=(3.2 * cols, 5.6))
        ax[0, 0].imshow(img1[0].permute(1, 2, 0).numpy())
        ax[0, 0].set_title(f"{pair}: frame 1")
        ax[0, 1].imshow(flow_to_color(gt[0], max_flow=scale))
        ax[0, 1].set_title(f"ground truth (max {scale:.1f} px)")
        ax[1, 0].imshow(valid[0, 0].numpy(), cmap="gray", vmin=0, vmax=1)
        ax[1, 0].set_title("valid")
        ax[1, 1].axis("off")
        for k, (label, net) in enumerate(loaded.items(), 2):
            pred = predict(net, img1[:1], img2[:1], TEST_UPDATES)
            err = torch.linalg.vector_norm(pred - gt, dim=1)[0] * (valid[0, 0] > 0.5)
            epe = float(err.sum() / (valid[0, 0] > 0.5).sum())
            ax[0, k].imshow(flow_to_color(pred[0], max_flow=scale))
            ax[0, k].set_title(f"{label}")
            im = ax[1, k].imshow(err.numpy(), cmap="magma", vmin=0, vmax=max(scale, 1.0))
            ax[1, k].set_title(f"error, EPE {epe:.2f} px")
        if loaded:
            fig.colorbar(im, ax=ax[1, -1], fraction=0.046)
        for a in ax.flat:
            a.set_xticks([])
            a.set_yticks([])
        fig.tight_layout()
        out = RESULTS_DIR / f"{name}_{pair}.png"
        RESULTS_DIR.mkdir(parents=True, exist_ok=True)
        fig.savefig(out, dpi=80)
        plt.close(fig)
        paths.append(out)
    return paths
