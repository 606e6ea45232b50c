"""Does a flow network learn from flowsynth? Same net, same budget, two training sets, real photos as the test.

    python benchmarks/learning/learning.py [--quick] [--seeds 0,1,2] [--steps 1200] [--jobs 2] [--middlebury DIR]
                                  [--photo-arms]

The judges (issue 38; protocol and rules pre-registered in docs/decisions/0019-learning-judge-real-flow.md) are
real footage with true motion: the Motorcycle stereo pair ("stereo") and, with ``--middlebury DIR``, the mean EPE
over the Middlebury flow pairs in DIR at full resolution ("middlebury"; each pair also as "mb_NAME"). Get them from
https://vision.middlebury.edu/flow/data/ (other-color-twoframes.zip and other-gt-flow.zip, unpacked into one
folder: DIR/Venus/frame10.png, frame11.png, flow10.flo, ...). Without DIR that judge is skipped, and said so.
The homography tests stay as diagnostic columns. A net must beat zero flow and its own untrained start on a real
set before its ratio to the baseline means anything; the report says, per real set and arm, in how many seeds it
does.

Training sets (each a pool of pre-generated pairs at 128x96, the same size for both):

- flowsynth: the default config (``BouncingThingsConfig()``) at 1/4 of the 512x384 size issue 12 measures it at
  (its own default size is 320x240): ``flow_px`` divided by 4, so motion and image size keep the proportions of
  a 512x384 rendering. Procedural textures only (no ``texture_dir``): no evaluation photo can reach the training
  data.
- chairs2d: a FlyingChairs-style 2D baseline built from the same textures: frame 0 of other flowsynth
  samples as backgrounds, ellipses and polygons cut from yet other flowsynth frames as foreground
  "chairs"; background and every shape move by their own random affine map (exact flow, painter's order).
  Its motion ranges are scaled so that its mean |flow| equals the flowsynth pool's: the two sets differ in
  what the motion looks like, not in how large it is.

Network (``NET`` = "ncc-v2"): a small coarse-to-fine cost-volume flow net (PWC-Net-like: a 3-level feature pyramid
at strides 2, 4 and 8; at strides 8, 4 and 2 a local cost volume of radius 3 after warping; output upsampled from
stride 2; ~0.24 M parameters). As issue 12 asks, the untrained net is a *working* coarse-to-fine block matcher:
each level's cost volume is the normalised cross-correlation (NCC) of 9x9 grey-level patches, a fixed part without
parameters, plus the cosine cost volume of the learned features times a weight that starts at 0; the level's flow
update is the soft-argmax of the cost volume over the 7x7 offsets (learned sharpness) plus a residual flow
estimator whose output layer starts at zero. Untrained, it is at 2.1-2.6 px on the resampled homography test and
2.0-2.1 px on the stereo test (zero flow: 4.7-5.0 and 9.4-10.5 px; seeds 0-5), so training can make it better or
worse, and the learning curve shows which. (The first version, "random-v1", until 2026-11-25: the same matcher on
random learned features at strides 16, 8 and 4, 0.37 M parameters; untrained it was at 25 px, far worse than zero
flow, so training mostly repaired the initialisation; its results are in docs/decisions/notebook-2026-11.md.) Trained
with Adam on a multi-scale EPE loss over valid pixels.

Test sets (made in benchmarks/learning/learning_sets.py, with the 2D baseline; every net is tested on all three; images
that ship with scikit-image, none of them a texture of
either training set), EPE over pixels whose flow lands inside the image:
- "resampled", "symmetric" (``photo_pairs``): photographs (``skimage.data``), random 128x96 crops warped by
  random homographies with exact ground truth (cv2.warpPerspective); two ways of making the second frame.
  Issue 12 judged here; since issue 38 a diagnostic column only.
- "stereo" (``stereo_pairs``): a real 3D scene, the Middlebury 2014 Motorcycle stereo pair with its measured
  disparity, downsampled crops: depth edges, occlusions and real lighting, which a homography has none of.

Budget: 1200 steps of batch 8 per net, tested every 400 steps, so the learning curve shows what a shorter budget
would have said (random-v1: 1800 steps, every 600; a step of ncc-v2 costs about 2.3x one of random-v1, mostly its
stride-2 level). Each set is a stream: its pool holds steps x batch = 9600 pairs and every pair is trained on
once, in a random order (``batches``), as a net fed by ``fs.datasets.BouncingThings`` would see them. Until
2026-11-25 (results/learning_ncc*.json) the pools held 768 pairs drawn with replacement (~12.5 epochs); a
pre-registered 5-seed comparison made the stream the default
(docs/decisions/0017-learning-benchmark-protocol.md); ``--pool 768`` still runs that protocol. A stream seed
renders 14,400 flowsynth pairs (7-10 min on 2 cores) and holds ~10 GB while it trains. The two nets of a seed
train at once, each in a process of its own (``--jobs``). Reports the test EPE
of zero flow, of the untrained net, of the net trained on each set along the curve, and the ratio
flowsynth / chairs2d (< 1: flowsynth trains the better flow network), per seed. Writes results/learning.json.

``--summarize`` trains nothing: it pools the seeds of the results/learning*.json files (``--files``) of one loss
mask (runs of further seeds written with ``--tag``) that share the first file's protocol (steps, batch, pool,
resolution, test pairs, net and the flowsynth config; the others are named and left out), and prints per test the
ratio of each seed, their geometric mean with a 95% confidence interval, how many seeds favour flowsynth, a
one-sample t-test of the log ratios and a Wilcoxon signed-rank test (scipy). Writes
results/learning_summary[_visible][_TAG].json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path[:0] = [str(Path(__file__).resolve().parent), str(Path(__file__).resolve().parents[1])]  # siblings, _common

from _common import machine_info, print_table, write_json
from learning_sets import (PHOTOS, TESTS, H, W, chairs2d_pairs, middlebury_pairs,
                           photo_folder, photo_sources, test_sets)

SCALE = 512 // W  # issue 12's 512x384 measurement size over the training size
LR = 2e-3  # peak learning rate of the one-cycle schedule (Adam)
# the real judges of issue 38: Motorcycle ("stereo") and, with --middlebury DIR, the mean EPE over the Middlebury
# flow pairs found there ("middlebury", each pair also under "mb_NAME")
JUDGES = ("stereo", "middlebury")
# pixels the training loss covers (--mask): flow defined (every pixel of chairs2d), or seen in both frames
MASKS = ("valid", "visible")
# the frames the flowsynth arm trains on (--pass): the clean render, the final pass (blur, depth of field, noise,
# exposure and white balance; docs/rendering.md), or each pair one of the two
PASSES = ("clean", "final", "mix")


# -- network ----------------------------------------------------------------------------------------------
NET = "ncc-v2"  # the network's design (JSON field "net"; files written before it have none and hold "random-v1")
R = 3  # correlation radius at every level [px of that level]
PATCH = 9  # side of the grey-level patches the fixed matcher compares (NCC) [px of the level]
LEVELS = (2, 1, 0)  # pyramid levels whose stride (2 ** (level + 1): 8, 4, 2) estimates flow, coarse to fine


def build_net():
    import torch
    from torch import nn
    from torch.nn import functional as F

    def conv(cin, cout, stride=1):
        return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.LeakyReLU(0.1))

    def correlate(f1, f2):
        """(B, (2R+1)^2, h, w) channel sums of products of f1 with f2 shifted by (dx, dy) in [-R, R]^2."""
        h, w = f1.shape[-2:]
        p = F.pad(f2, (R, R, R, R))
        return torch.cat([(f1 * p[:, :, dy:dy + h, dx:dx + w]).sum(1, keepdim=True)
                          for dy in range(2 * R + 1) for dx in range(2 * R + 1)], 1)

    def warp(x, flow):
        """x (B, C, h, w) sampled at pixel + flow (B, 2, h, w) [px of x]; zeros outside."""
        b, _, h, w = x.shape
        ys, xs = torch.meshgrid(torch.arange(h, dtype=x.dtype, device=x.device),
                                torch.arange(w, dtype=x.dtype, device=x.device), indexing="ij")
        gx = (xs + flow[:, 0]) / max(w - 1, 1) * 2 - 1
        gy = (ys + flow[:, 1]) / max(h - 1, 1) * 2 - 1
        return F.grid_sample(x, torch.stack([gx, gy], -1), align_corners=True, padding_mode="zeros")

    def patches(img, stride):
        """(B, PATCH^2, h, w) zero-mean PATCH x PATCH patches (edges replicated) of the grey image average-pooled
        by ``stride``: the cosine of two is their normalised cross-correlation (NCC), a block matcher's cost."""
        g = F.avg_pool2d(img.mean(1, keepdim=True), stride)
        p = F.unfold(F.pad(g, (PATCH // 2,) * 4, mode="replicate"), PATCH).view(g.shape[0], PATCH * PATCH,
                                                                                 *g.shape[-2:])
        return F.normalize(p - p.mean(1, keepdim=True), dim=1)

    class FlowNet(nn.Module):
        def __init__(self):
            super().__init__()
            chans = (16, 32, 48)  # features at strides 2, 4, 8; flow estimated at 8, 4, 2 (LEVELS)
            self.pyramid = nn.ModuleList()
            cin = 3
            for c in chans:
                self.pyramid.append(nn.Sequential(conv(cin, c, 2), conv(c, c)))
                cin = c
            d = torch.arange(-R, R + 1, dtype=torch.float32)
            dy, dx = torch.meshgrid(d, d, indexing="ij")
            self.register_buffer("offsets", torch.stack([dx.flatten(), dy.flatten()], 1))  # ((2R+1)^2, 2)
            self.sharpness = nn.Parameter(torch.full((len(LEVELS),), 40.0))
            self.learned = nn.Parameter(torch.zeros(len(LEVELS)))  # weight of the learned features' cost
            self.estimators = nn.ModuleList()
            for k in LEVELS:
                w = 64 if k > 0 else 32  # the stride-2 estimator is half as wide: it sees 4x the pixels
                head = nn.Conv2d(w // 2, 2, 3, 1, 1)
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)  # starts as the block matcher's flow
                self.estimators.append(nn.Sequential(conv((2 * R + 1) ** 2 + chans[k] + 2, w), conv(w, w // 2),
                                                     conv(w // 2, w // 2), head))

        def forward(self, img1, img2):
            """img (B, 3, H, W) in [0, 1] -> list of flows (B, 2, h, w) [full-res px], coarse to fine."""
            feats = []
            a, b = img1 * 2 - 1, img2 * 2 - 1
            for level in self.pyramid:
                a, b = level(a), level(b)
                feats.append((a, b))
            flow, out = None, []
            for n, k in enumerate(LEVELS):
                f1, f2 = feats[k]
                s = 2 ** (k + 1)  # this level's stride
                if flow is None:
                    flow = torch.zeros(f1.shape[0], 2, *f1.shape[-2:], dtype=f1.dtype, device=f1.device)
                else:
                    flow = F.interpolate(flow, size=f1.shape[-2:], mode="bilinear", align_corners=False)
                with torch.no_grad():  # the fixed matcher: NCC of image patches, no parameters, flow taken as given
                    ncc = correlate(patches(img1, s), warp(patches(img2, s), flow / s))
                cost = ncc + self.learned[n] * correlate(F.normalize(f1, dim=1),
                                                         F.normalize(warp(f2, flow / s), dim=1))
                # block matching: soft-argmax of the cost volume over the (2R+1)^2 offsets
                prob = torch.softmax(cost * self.sharpness[n], 1)
                match = torch.einsum("bkhw,kc->bchw", prob, self.offsets)
                flow = flow + (match + self.estimators[n](torch.cat([cost, f1, flow / s], 1))) * s
                out.append(flow)
            out.append(F.interpolate(flow, size=img1.shape[-2:], mode="bilinear", align_corners=False))
            return out

    return FlowNet()


def multiscale_loss(preds, flow, valid):
    """Mean EPE over valid pixels at every scale (ground truth average-pooled), finest weighted most."""
    import torch
    from torch.nn import functional as F

    total = 0.0
    for k, p in enumerate(preds):
        weight = 2.0 ** (k - len(preds) + 1)
        if p.shape[-1] != flow.shape[-1]:
            f = F.adaptive_avg_pool2d(flow, p.shape[-2:])
            v = F.adaptive_avg_pool2d(valid, p.shape[-2:]) > 0.99
        else:
            f, v = flow, valid > 0.5
        err = torch.linalg.vector_norm(p - f, dim=1, keepdim=True)
        total = total + weight * (err * v).sum() / v.sum().clamp(min=1)
    return total


# -- data ---------------------------------------------------------------------------------------------------
def flowsynth_pairs(n: int, seed: int, workers: int, flow_px: tuple[float, float] | None = None,
                    overrides: dict | None = None, render_pass: str = "clean", mixture: dict | None = None):
    """n flowsynth pairs: (img1, img2, flow, valid, visible, clean1) tensors (n, C, H, W), and the config used.
    ``valid`` is ``valid_fw`` (occluded and out-of-frame pixels included), ``visible`` is ``valid_fw & ~occ_fw``
    (as ``FlowPairs(mask="visible")``); a net trains on (img1, img2, flow, one of the two). ``flow_px``: another
    ``BouncingThingsConfig.flow_px`` at the 512x384 scale than the default's (to try a candidate default);
    ``overrides``: other config fields of a candidate default (``--set``), resolution-free ones only.
    ``render_pass`` (PASSES): the frames are ``rgb`` ("clean"), ``rgb_final`` ("final"), or per pair one of the two
    with equal chance ("mix", drawn from ``seed``); ``clean1`` is always the clean first frame (the baseline's
    textures). ``mixture`` (preset name -> weight): the pairs come from ``fs.datasets.Mixture`` of those presets
    (each with ``overrides``, scaled as above; ``flow_px`` overrides each preset's own), and the config returned is
    the first preset's."""
    import torch
    from torch.utils.data import DataLoader

    import flowsynth as fs

    def scaled(base):
        return dataclasses.replace(base, width=W, height=H, num_frames=2,
                                   flow_px=tuple(x / SCALE for x in (flow_px or base.flow_px)))

    outputs = ["rgb", "flow_fw", "valid_fw", "occ_fw"] + (["rgb_final"] if render_pass != "clean" else [])
    if mixture:
        configs = {name: scaled(fs.BouncingThingsConfig.preset(name, **(overrides or {}))) for name in mixture}
        ds = fs.datasets.Mixture(configs, dict(mixture), outputs=outputs, seed=seed, length=n)
        cfg = next(iter(configs.values()))
    else:
        cfg = scaled(fs.BouncingThingsConfig.from_dict(overrides or {}))
        ds = fs.datasets.BouncingThings(cfg, outputs=outputs, seed=seed, length=n)
    # filled batch by batch (each array once in memory: a final or mix pool of 14,400 pairs, collected whole and
    # then concatenated, held ~24 GB and was killed for memory on a 24 GiB machine)
    frames = torch.empty(n, 2, 3, H, W)
    clean1 = frames[:, 0] if render_pass == "clean" else torch.empty(n, 3, H, W)
    flow, valid, visible = torch.empty(n, 2, H, W), torch.empty(n, 1, H, W), torch.empty(n, 1, H, W)
    pick = (torch.ones(n, dtype=torch.bool) if render_pass == "final" else
            torch.rand(n, generator=torch.Generator().manual_seed(40_000 + seed)) < 0.5)
    o = 0
    for b in DataLoader(ds, batch_size=16, num_workers=workers):
        k = len(b["rgb"])
        rgb = b["rgb"]
        if render_pass != "clean":
            frames[o:o + k] = torch.where(pick[o:o + k, None, None, None, None], b["rgb_final"], rgb)
            clean1[o:o + k] = rgb[:, 0]
        else:
            frames[o:o + k] = rgb
        flow[o:o + k] = b["flow_fw"][:, 0]
        valid[o:o + k] = b["valid_fw"][:, 0]
        visible[o:o + k] = b["valid_fw"][:, 0] & ~b["occ_fw"][:, 0]
        o += k
    return (frames[:, 0], frames[:, 1], flow, valid, visible, clean1), cfg


def base_families() -> tuple:
    """The default config's texture families."""
    import flowsynth as fs

    return fs.BouncingThingsConfig().texture_families


def with_means(epe: dict) -> dict:
    """``epe`` (test -> EPE) plus "middlebury", the mean over its mb_* pairs, when there are any."""
    mb = [v for k, v in epe.items() if k.startswith("mb_")]
    return {**epe, "middlebury": sum(mb) / len(mb)} if mb else dict(epe)


def mean_flow(data) -> float:
    """Mean |flow| [px] over the valid pixels of an (img1, img2, flow, valid) set."""
    import torch

    return float(torch.linalg.vector_norm(data[2], dim=1)[data[3][:, 0] > 0.5].mean())


# -- train and test -----------------------------------------------------------------------------------------
def predict(net, img1, img2):
    """The net's full-resolution flow (B, 2, H, W) for any H, W: images whose sides are not multiples of the
    coarsest stride (8) are padded on the bottom and right by edge replication and the flow is cropped back.
    Sides that are multiples of 8 (the 128x96 tests) go through unpadded."""
    from torch.nn import functional as F

    h, w = img1.shape[-2:]
    ph, pw = -h % 8, -w % 8
    if ph or pw:
        img1, img2 = (F.pad(x, (0, pw, 0, ph), mode="replicate") for x in (img1, img2))
    return net(img1, img2)[-1][..., :h, :w]


def evaluate(net, test) -> float:
    """Mean EPE [px] of ``net`` over the valid pixels of ``test`` (img1, img2, flow, valid), on the net's device."""
    import torch

    dev = next(net.parameters()).device
    img1, img2, flow, valid = (x.to(dev) for x in test)
    with torch.no_grad():
        err = sum(float((torch.linalg.vector_norm(predict(net, img1[i:i + 16], img2[i:i + 16]) - flow[i:i + 16],
                                                  dim=1, keepdim=True) * valid[i:i + 16]).sum())
                  for i in range(0, len(img1), 16))
    return err / float(valid.sum())


def batches(n: int, steps: int, batch: int, g):
    """The pool indices of each training step's batch (a generator of ``steps`` int64 tensors), drawn with torch
    generator ``g``: from a pool of at least ``steps`` x ``batch`` pairs, a stream (one random permutation, each
    pair once, the default protocol); from a smaller pool, with replacement (the protocol until 2026-11-25)."""
    import torch

    order = torch.randperm(n, generator=g) if n >= steps * batch else None
    for step in range(steps):
        yield torch.randint(n, (batch,), generator=g) if order is None else order[step * batch:(step + 1) * batch]


def train(data, tests: dict, steps: int, batch: int, seed: int, every: int, threads: int = 0,
          device: str = "cpu") -> dict:
    """Train a fresh net (seed) on ``data``; test EPE on every set of ``tests`` at step 0, every ``every`` steps
    and at the end. ``threads`` > 0 sets torch's thread count (for a training process of its own). ``device``: where
    the net trains and tests (the net is initialised on the CPU first, so its start is the same everywhere; the data
    stay on the CPU and each batch is moved)."""
    import torch

    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    net = build_net().to(device)
    opt = torch.optim.Adam(net.parameters(), lr=LR)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=LR, total_steps=steps, pct_start=0.1)
    img1, img2, flow, valid = data
    draws = batches(len(img1), steps, batch, torch.Generator().manual_seed(seed))
    t = time.perf_counter()
    curve = [{"step": 0, "train_loss": None, **with_means({k: evaluate(net, v) for k, v in tests.items()})}]
    for step, idx in enumerate(draws, 1):
        loss = multiscale_loss(net(img1[idx].to(device), img2[idx].to(device)), flow[idx].to(device),
                               valid[idx].to(device))
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % every == 0 or step == steps:
            curve.append({"step": step, "train_loss": loss.item(),
                          **with_means({k: evaluate(net, v) for k, v in tests.items()})})
    return {"curve": curve, "train_s": time.perf_counter() - t,
            "parameters": sum(p.numel() for p in net.parameters())}


def test_keys(runs: list) -> list:
    """The tests every run's final curve point has, in a stable order: TESTS, "middlebury", then the mb_* pairs."""
    common = set.intersection(*(set(r["results"]["flowsynth"]["curve"][-1]) for r in runs)) - {"step", "train_loss"}
    order = list(TESTS) + ["middlebury"]
    return [k for k in order if k in common] + sorted(k for k in common if k not in order)


def epe_means(runs: list, kind: str, arms) -> dict:
    """Mean over ``runs`` of test ``kind``'s EPE: zero flow, the untrained net (step 0 of the first arm) and each
    arm's net at the end of training."""
    import numpy as np

    zero = [with_means(r["zero_flow_epe"])[kind] for r in runs]
    return {"zero_flow": float(np.mean(zero)),
            "untrained": float(np.mean([r["results"][arms[0]]["curve"][0][kind] for r in runs])),
            **{a: float(np.mean([r["results"][a]["curve"][-1][kind] for r in runs])) for a in arms}}


def train_arms(arms: dict, setting: tuple, res: dict, mags: dict, trained: dict) -> None:
    """Train the nets of ``arms`` (name -> data) at once, each in a process of its own; put each arm's curve into
    ``res``, its mean |flow| into ``mags`` and its share of pixels trained on into ``trained``. ``setting``: (tests,
    steps, batch, seed, every, jobs, threads, multiprocessing context, torch device); ``jobs`` 0 trains them one
    after another in this process."""
    tests, steps, batch, seed, every, jobs, threads, ctx, device = setting
    if jobs == 0:  # one after another in this process (no shared memory needed)
        res.update({name: train(data, tests, steps, batch, seed, every, 0, device) for name, data in arms.items()})
    else:
        _train_in_processes(arms, setting, res)
    mags.update({name: mean_flow(d) for name, d in arms.items()})
    trained.update({name: float(d[3].mean()) for name, d in arms.items()})


def _train_in_processes(arms: dict, setting: tuple, res: dict) -> None:
    """train_arms' nets, ``jobs`` at once, each in a spawned process of its own."""
    from concurrent.futures import ProcessPoolExecutor

    tests, steps, batch, seed, every, jobs, threads, ctx, device = setting
    jobs = max(1, min(jobs, len(arms)))
    with ProcessPoolExecutor(jobs, mp_context=ctx) as ex:
        futs = {name: ex.submit(train, data, tests, steps, batch, seed, every, max(1, threads // jobs), device)
                for name, data in arms.items()}
        res.update({name: f.result() for name, f in futs.items()})


def final_ratios(runs: list, arm: str = "flowsynth", against: str = "chairs2d") -> dict:
    """Per test, each seed's ``arm`` / ``against`` test EPE at the end of training ({} when a run lacks either arm,
    as a ``--screen`` run does)."""
    if not all(arm in r["results"] and against in r["results"] for r in runs):
        return {}
    return {kind: [r["results"][arm]["curve"][-1][kind] / r["results"][against]["curve"][-1][kind] for r in runs]
            for kind in test_keys(runs)}


PROTOCOL = ("steps", "batch", "pool", "resolution", "test_pairs", "photos", "net", "flowsynth_config", "render_pass",
            "mixture")
# what a file written before a PROTOCOL field existed ran under
PROTOCOL_BEFORE = {"net": "random-v1", "render_pass": "clean", "mixture": None}


def same_protocol(a: dict, b: dict) -> bool:
    """Two runs' PROTOCOL fields are equal; in the flowsynth config, a field that only one of them has (a field added
    to the library between the runs) counts as equal when it holds the field's default, which leaves the samples
    unchanged (benchmarks/speed/hashes.py checks that for each new field)."""
    import flowsynth as fs

    defaults = fs.BouncingThingsConfig().to_dict()
    if any(a[k] != b[k] for k in PROTOCOL if k != "flowsynth_config"):
        return False
    ca, cb = a["flowsynth_config"] or {}, b["flowsynth_config"] or {}
    return all(ca.get(k) == cb.get(k) if k in ca and k in cb else
               (ca if k in ca else cb)[k] == defaults.get(k, object()) for k in set(ca) | set(cb))


def summarize(mask: str, pattern: str = "learning*.json", arm: str = "flowsynth", against: str = "chairs2d") -> dict:
    """Pool the seeds of the results/ files matching ``pattern`` written with loss mask ``mask`` (module
    docstring): per test the ratio ``arm`` / ``against``, and the mean EPE of zero flow, of the untrained net and
    of each arm's trained net (a net must beat zero flow and its untrained start before its ratio means
    anything: issue 38)."""
    import numpy as np
    from scipy import stats

    from _common import RESULTS_DIR

    files = sorted(f for f in RESULTS_DIR.glob(pattern) if not f.stem.startswith("learning_summary"))
    runs, protocol, used, library, raw = {}, None, [], {}, []
    for f in files:
        d = json.loads(f.read_text())
        if d.get("mask", "valid") != mask or any(x not in d["runs"][0]["results"] for x in (arm, against)):
            continue
        proto = {k: d.get(k, PROTOCOL_BEFORE.get(k)) for k in PROTOCOL}
        if protocol is None:
            protocol = proto
        elif not same_protocol(proto, protocol):
            diff = sorted(k for k in PROTOCOL if proto[k] != protocol[k])
            print(f"not pooled: {f.name}, run under another protocol than {used[0]} (differs in {diff})")
            continue
        used.append(f.name)
        m = d.get("machine", {})  # the library the run imported (recorded since 583a881)
        library[f.name] = {k: m.get(k) for k in ("flowsynth_commit", "flowsynth_modified")}
        for r in d["runs"]:
            if r["seed"] in runs:
                raise SystemExit(f"seed {r['seed']} is in {f.name} and in an earlier file")
            runs[r["seed"]] = r
            raw.append(r)
    if len(runs) < 2:
        raise SystemExit(f"need runs of at least 2 seeds with mask {mask!r} in {RESULTS_DIR}, found {len(runs)}")
    seeds = sorted(runs)
    ratios = final_ratios([runs[s] for s in seeds], arm, against)
    rows, out = [], {}
    for kind, rs in ratios.items():
        r = np.array(rs)
        logs = np.log(r)
        n = len(logs)
        half = stats.t.ppf(0.975, n - 1) * logs.std(ddof=1) / np.sqrt(n)
        t = stats.ttest_1samp(logs, 0.0)
        w = stats.wilcoxon(logs)
        out[kind] = {"ratios": dict(zip(seeds, r.tolist())), "geometric_mean": float(np.exp(logs.mean())),
                     "ci95": [float(np.exp(logs.mean() - half)), float(np.exp(logs.mean() + half))],
                     "flowsynth_better": int((r < 1).sum()), "t": float(t.statistic), "t_p": float(t.pvalue),
                     "wilcoxon_p": float(w.pvalue), **epe_means([runs[s] for s in seeds], kind, (arm, against))}
        o = out[kind]
        rows.append({"test": kind, "seeds": n, f"{arm} better": f"{o['flowsynth_better']} of {n}",
                     "geo. mean": o["geometric_mean"], "95% CI": f"{o['ci95'][0]:.3f}-{o['ci95'][1]:.3f}",
                     "p (t)": o["t_p"], "zero flow": o["zero_flow"], "untrained": o["untrained"],
                     arm: o[arm], against: o[against]})
    print(f"{arm} / {against} test EPE after {protocol['steps']} steps, loss mask {mask!r}, seeds {seeds} from "
          f"{', '.join(used)} (< 1: {arm} trains the better net; t-test of the log ratios, two-sided); mean EPE "
          f"[px] of zero flow, the untrained net and each trained net")
    print_table(rows, list(rows[0]))
    for name, lib in library.items():
        commit = (lib["flowsynth_commit"] or "not recorded")[:12]
        print(f"{name}: flowsynth {commit}" + (" with uncommitted changes" if lib["flowsynth_modified"] else ""))
    return {"mask": mask, "files": used, "library": library, "seeds": seeds, "protocol": protocol, "tests": out}


def screen_report(candidate: str, default: str) -> list[dict]:
    """Rule 3 of docs/decisions/0019 for a lever's screen: per seed both files hold and per judge, the flowsynth
    net's final test EPE in ``candidate`` and in ``default`` (results/ JSON paths), their ratio, and the verdict
    (promising: Middlebury ratio < 0.95 and Motorcycle ratio <= 1.05). Both runs must share steps, batch, pool,
    resolution, test pairs and net."""
    from _common import RESULTS_DIR

    runs = []
    for f in (candidate, default):
        path = Path(f) if Path(f).exists() else RESULTS_DIR / f
        runs.append(json.loads(path.read_text()))
    diff = [k for k in ("steps", "batch", "pool", "resolution", "test_pairs", "net") if runs[0][k] != runs[1][k]]
    if diff:
        raise SystemExit(f"--screen-report: the two runs differ in {diff}; a screen compares like with like")
    seeds = {r["seed"]: r for r in runs[1]["runs"]}
    rows = []
    for r in runs[0]["runs"]:
        if r["seed"] not in seeds:
            continue
        a, b = r["results"]["flowsynth"]["curve"][-1], seeds[r["seed"]]["results"]["flowsynth"]["curve"][-1]
        ratio = {k: a[k] / b[k] for k in JUDGES if k in a and k in b}
        promising = ratio.get("middlebury", 1.0) < 0.95 and ratio.get("stereo", 1.0) <= 1.05
        for k in ratio:
            rows.append({"seed": r["seed"], "judge": k, "candidate": a[k], "default": b[k], "ratio": ratio[k],
                         "promising (rule 3)": promising})
    return rows


def plot_judge_curves(name: str, pattern: str) -> list:
    """One plot per real judge (results/NAME_JUDGE.png): test EPE against training step of every arm and seed of
    the results files matching ``pattern``, each line labelled by its file's tag, arm and seed; the untrained start
    is the step-0 point. Returns the paths written (none without matplotlib)."""
    from _common import RESULTS_DIR, plot_curves

    files = sorted(RESULTS_DIR.glob(pattern))
    paths = []
    for judge in JUDGES:
        series, zero = {}, {}
        for f in files:
            d = json.loads(f.read_text())
            tag = f.stem.removeprefix("learning_")
            for r in d.get("runs", []):
                for arm, res in r["results"].items():
                    pts = [(c["step"], c[judge]) for c in res["curve"] if judge in c]
                    if pts:
                        series[f"{tag} {arm} s{r['seed']}"] = tuple(zip(*pts))
                        if judge in r.get("zero_flow_epe", {}):
                            zero[r["zero_flow_epe"][judge]] = max(zero.get(r["zero_flow_epe"][judge], 0), pts[-1][0])
        for z, last in zero.items():  # zero flow's EPE: a net above this line is worse than predicting nothing
            series[f"zero flow ({z:.2f})"] = ((0, last), (z, z))
        if series:
            path = plot_curves(f"{name}_{judge}", series, "training step", f"{judge} test EPE [px]", logx=False,
                               logy=True, title=f"{judge}: the learning curves ({pattern})")
            paths += [path] if path else []
    return paths


def _mixture(text: str) -> dict:
    """``--mixture``'s PRESET=WEIGHT,... as a dict (argparse type: a bad one is a usage error)."""
    from flowsynth.scene import PRESETS

    out = {}
    for item in text.split(","):
        name, _, w = item.partition("=")
        if name not in PRESETS or not w:
            raise argparse.ArgumentTypeError(f"{item!r}: give PRESET=WEIGHT with a preset of {sorted(PRESETS)}")
        out[name] = float(w)
    return out


def main() -> None:
    net = argparse.ArgumentParser(add_help=False)
    net.add_argument("--net", choices=("raft", NET), default="raft")
    known, _ = net.parse_known_args()
    if known.net == "raft":
        import learning_raft

        return learning_raft.main(sys.argv[1:])
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--net", choices=("raft", NET), default="raft")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=None, help="training steps per net (default 1200; --quick 100)")
    p.add_argument("--every", type=int, default=400, help="test every this many steps (the learning curve)")
    p.add_argument("--workers", type=int, default=2, help="DataLoader workers generating flowsynth pairs")
    p.add_argument("--threads", type=int, default=2, help="torch threads in all (split between --jobs)")
    p.add_argument("--jobs", type=int, default=2, help="nets trained at once, each in a process of "
                   "its own; 0: one after another in this process")
    p.add_argument("--device", default="cpu", help="torch device the nets train and test on (e.g. cuda); the "
                   "pairs are rendered on the CPU either way")
    p.add_argument("--mask", choices=MASKS, default="valid",
                   help="pixels the loss covers in both training sets: 'valid' (flowsynth's valid_fw, every "
                        "chairs2d pixel) or 'visible' (seen in both frames); a run with 'visible' writes "
                        "results/learning_visible.json")
    p.add_argument("--tag", default="", help="appended to the JSON's name (results/learning[_visible]_TAG.json), "
                                             "e.g. for a run of further seeds beside the main one")
    p.add_argument("--flow-px", type=lambda v: tuple(float(x) for x in v.split(",")), default=None,
                   metavar="LO,HI", help="train flowsynth on this flow_px (at 512x384, as the config field) instead "
                                         "of the default's: a candidate default; use with --tag")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=JSON",
                   help="train flowsynth on the default config with this field changed (a JSON value, e.g. "
                        "num_objects=[2,8]); repeatable; a candidate default: use with --tag. Not width, height, "
                        "num_frames or flow_px (set by the benchmark; --flow-px)")
    p.add_argument("--pool", type=int, default=None,
                   help="training pairs per set (default steps x batch, a stream: each pair trained on once; "
                        "--quick 128): a smaller pool is drawn from with replacement (768: the protocol until "
                        "2026-11-25); flowsynth renders 1.5x this many pairs; use with --tag")
    p.add_argument("--files", default="learning*.json",
                   help="--summarize: the results/ files to pool (a glob; default every learning JSON)")
    p.add_argument("--middlebury", default=None, metavar="DIR",
                   help="a folder of Middlebury flow pairs (NAME/frame10.png, frame11.png, flow10.flo; e.g. "
                        "../shared/data/middlebury): every net is also tested on them at full resolution; without "
                        "it the Middlebury judge is skipped (said so)")
    p.add_argument("--photo-arms", action="store_true",
                   help="also train chairs2d_photos (the baseline textured with scikit-image photographs that no "
                        "test uses, TRAIN_PHOTOS) and flowsynth_photos (the flowsynth config with those photographs "
                        "in texture_dir and 'image' among its texture families): four nets a seed")
    p.add_argument("--pass", dest="render_pass", choices=PASSES, default="clean",
                   help="frames the flowsynth arm trains on: 'clean' (rgb), 'final' (rgb_final) or 'mix' (each pair "
                        "one of the two); the baseline keeps clean flowsynth frames as textures; use with --tag")
    p.add_argument("--arm", default="flowsynth", help="--summarize: the numerator arm (default flowsynth)")
    p.add_argument("--against", default="chairs2d", help="--summarize: the denominator arm (default chairs2d)")
    p.add_argument("--mixture", type=_mixture, default=None, metavar="PRESET=W,...",
                   help="the flowsynth arm's pairs from fs.datasets.Mixture of these presets at these weights (e.g. "
                   "chairs=1,default=1), each scaled as the default is")
    p.add_argument("--screen", action="store_true",
                   help="a lever's screen: train the flowsynth arm alone (no 2D baseline: its pairs are neither "
                   "rendered nor trained), to compare with the default's net of the same seed (rule 3 of "
                   "docs/decisions/0019)")
    p.add_argument("--plot", default=None, metavar="NAME",
                   help="trains nothing: per real judge, results/NAME_JUDGE.png, the learning curves of every arm "
                   "and seed in the results files matching --files")
    p.add_argument("--screen-report", nargs=2, metavar=("CANDIDATE", "DEFAULT"), default=None,
                   help="trains nothing: rule 3 of docs/decisions/0019 for a lever's screen, from two results JSONs "
                   "(paths, or names in benchmarks/results): per seed and judge, flowsynth's final EPE in each, "
                   "their ratio and the verdict")
    p.add_argument("--summarize", action="store_true",
                   help="train nothing: pool the seeds of every results/learning*.json of --mask and test the ratios")
    args = p.parse_args()
    if args.plot:
        for path in plot_judge_curves(args.plot, args.files):
            print(f"wrote {path}")
        return
    if args.screen_report:
        rows = screen_report(*args.screen_report)
        print_table(rows, ["seed", "judge", "candidate", "default", "ratio", "promising (rule 3)"])
        return
    if args.summarize:
        name = "learning_summary" + ("" if args.mask == "valid" else f"_{args.mask}")
        write_json(name + (f"_{args.tag}" if args.tag else ""),
                   summarize(args.mask, args.files, args.arm, args.against))
        return
    import numpy as np
    import torch

    import torch.multiprocessing as tmp

    torch.set_num_threads(args.threads)
    pool, steps, batch, n_test = (128, 100, 4, 40) if args.quick else (None, 1200, 8, 100)
    steps = args.steps or steps
    if steps < 20:  # the one-cycle schedule's warm-up (10% of the steps) must span at least 2 steps
        p.error(f"--steps {steps}: give at least 20 steps")
    pool = args.pool or pool or steps * batch  # full runs: a stream
    every = min(args.every, steps)
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    rows, runs = [], []
    if args.screen and args.photo_arms:
        p.error("--screen trains the flowsynth arm alone: leave out --photo-arms")
    names = ("flowsynth",) if args.screen else (
        ("flowsynth", "chairs2d") + (("flowsynth_photos", "chairs2d_photos") if args.photo_arms else ()))
    middlebury = middlebury_pairs(args.middlebury)
    ctx = tmp.get_context("spawn")
    cfg = None

    def save(end_load: str | None) -> None:
        """Write the seeds done so far (after every seed, so a crash or a stop loses at most the one running);
        ``complete`` is false until the last planned seed is in."""
        ratios = final_ratios(runs)
        write_json("learning" + ("" if args.mask == "valid" else f"_{args.mask}") + (f"_{args.tag}" if args.tag
                                                                                    else ""), {
            "complete": end_load is not None, "seeds_planned": seeds,
            "mask": args.mask, "machine": machine_info(), "load": load, "end_load": end_load, "resolution": [W, H],
            "steps": steps, "every": every, "batch": batch, "pool": pool, "test_pairs": n_test,
            "render_pass": args.render_pass, "train_device": args.device, "screen": args.screen,
            "mixture": args.mixture,
            "photos": list(PHOTOS), "net": NET, "flowsynth_config": cfg.to_dict(), "runs": runs, "ratios_final": ratios,
            "mean_ratio": {k: float(np.mean(v)) for k, v in ratios.items()}})

    seeds = [int(s) for s in args.seeds.split(",")]
    overrides = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key in ("width", "height", "num_frames", "flow_px") or not value:
            p.error(f"--set {item!r}: give FIELD=JSON for a field other than width, height, num_frames, flow_px")
        try:
            overrides[key] = json.loads(value)
        except json.JSONDecodeError:
            p.error(f"--set {item!r}: the value must be JSON, e.g. num_objects=[2,8] or motion=\"kinematic\"")
    for seed in seeds:
        t = time.perf_counter()
        synth, cfg = flowsynth_pairs(pool + (0 if args.screen else pool // 2), seed, args.workers, args.flow_px,
                                     overrides, args.render_pass, args.mixture)
        gen_s = time.perf_counter() - t
        fs_valid = tuple(x[:pool] for x in synth[:4])
        fs_train = fs_valid if args.mask == "valid" else tuple(x[:pool] for x in synth[:3] + synth[4:5])
        arms, motion_scale = {"flowsynth": fs_train}, None
        if not args.screen:
            sources = synth[5][pool:]  # textures from (clean) flowsynth frames not trained on
            pilot = chairs2d_pairs(64, seed + 1, sources)
            motion_scale = mean_flow(fs_valid) / mean_flow(pilot)  # same mean |flow| as the flowsynth pool
            arms["chairs2d"] = chairs2d_pairs(pool, seed, sources, motion_scale, visible=args.mask == "visible")
            del sources
        tests = test_sets(n_test, seed, middlebury)
        zero = {k: float((torch.linalg.vector_norm(v[2], dim=1, keepdim=True) * v[3]).sum() / v[3].sum())
                for k, v in tests.items()}
        mags = {name: mean_flow(d) for name, d in [("photos (test)", tests["resampled"]),
                                                    ("motorcycle (test)", tests["stereo"]),
                                                    *((k, v) for k, v in tests.items() if k.startswith("mb_"))]}
        res, trained = {}, {}
        setting = (tests, steps, batch, seed, every, args.jobs, args.threads, ctx, args.device)
        train_arms(arms, setting, res, mags, trained)
        # the next pools are made once these are freed: a stream seed's two arms hold ~10 GB
        del synth, fs_valid, fs_train, arms
        if args.photo_arms:  # the same pool sizes, motion scale and loss mask as the two arms above
            synth_p, _ = flowsynth_pairs(pool, seed, args.workers, args.flow_px, {
                **overrides, "texture_dir": str(photo_folder()),
                "texture_families": list(overrides.get("texture_families", base_families())) + ["image"]},
                args.render_pass)
            fs_p = tuple(x[:pool] for x in (synth_p[:4] if args.mask == "valid" else synth_p[:3] + synth_p[4:5]))
            del synth_p
            train_arms({"flowsynth_photos": fs_p, "chairs2d_photos": chairs2d_pairs(
                pool, seed, photo_sources(pool // 2, seed), motion_scale, visible=args.mask == "visible")},
                setting, res, mags, trained)
            del fs_p
        runs.append({"seed": seed, "zero_flow_epe": zero, "results": {n: res[n] for n in names},
                     "mean_flow_px": mags, "trained_pixel_fraction": trained,
                     "chairs2d_motion_scale": motion_scale, "flowsynth_generation_s": gen_s})
        save(None)
        for kind in test_keys(runs[-1:]):
            row = {"seed": seed, "test": kind, "zero-flow": with_means(zero)[kind],
                   "untrained": res["flowsynth"]["curve"][0][kind]}
            if args.screen:
                row.update({f"fs @{c['step']}": f"{c[kind]:.3f}" for c in res["flowsynth"]["curve"][1:]})
            for c_fs, c_ch in zip(res["flowsynth"]["curve"][1:], res.get("chairs2d", {"curve": []})["curve"][1:]):
                row[f"fs/chairs @{c_fs['step']}"] = (f"{c_fs[kind]:.3f}/{c_ch[kind]:.3f} = "
                                                     f"{c_fs[kind] / c_ch[kind]:.3f}")
            rows.append(row)
    end_load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print(f"\nTest EPE [px] on {n_test} pairs per test set ({W}x{H}): homography-warped scikit-image photos (test "
          f"frames 'resampled' and 'symmetric', see photo_pairs) and crops of a real stereo pair ('stereo', "
          f"stereo_pairs) during {steps} steps of batch {batch} from pools of {pool} pairs; net of "
          f"{runs[0]['results']['flowsynth']['parameters']} parameters. Load at the start: {load}; at the end: "
          f"{end_load}")
    print_table(rows, list(rows[0]))
    ratios = final_ratios(runs)
    for kind in (k for k in JUDGES if k in test_keys(runs)):  # issue 38: a useful net beats zero flow and its start
        for name in names:
            end = [r["results"][name]["curve"][-1][kind] for r in runs]
            beats = sum(e < min(with_means(r["zero_flow_epe"])[kind], r["results"][name]["curve"][0][kind])
                        for e, r in zip(end, runs))
            print(f"{kind}: the {name} net beats zero flow and its untrained start in {beats} of {len(runs)} seeds")
    for kind, rs in ratios.items():
        m = float(np.mean(rs))
        verdict = ("flowsynth better in every seed" if max(rs) < 1 else
                   "baseline better in every seed" if min(rs) > 1 else "seeds disagree")
        print(f"{kind} test, after {steps} steps: ratio flowsynth / chairs2d mean {m:.3f} "
              f"(min {min(rs):.3f}, max {max(rs):.3f}; {verdict})")
    print("mean |flow| [px] over the pixels trained on: " + ", ".join(f"{k} {v:.2f}" for k, v in
                                                                   runs[0]["mean_flow_px"].items()))
    print(f"loss mask {args.mask!r}; share of pixels trained on (seed {runs[0]['seed']}): " + ", ".join(
        f"{k} {v:.3f}" for k, v in runs[0]["trained_pixel_fraction"].items()))
    save(end_load)


if __name__ == "__main__":
    main()
