"""The RAFT judge's protocol, pre-registered in docs/decisions/0023-raft-judge.md: its numbers (module constants), its
judges, the score a net gets on them, and the names of the files a run writes. Trains nothing; ``pools`` renders the
arms, ``trainers`` trains and tests the nets, ``runs`` runs the whole protocol.

- Net: torchvision's ``raft_small(weights=None)`` (``flowsynth.train.nets.raft_small``, 0.99 M parameters), RAFT's
  recipe as ``flowsynth.train.steps`` implements it (the same step ``examples/train_raft.py`` runs): sequence loss
  (gamma 0.8), AdamW at ``LR`` with weight decay 1e-4 and a linear one-cycle schedule, gradient clip 1, ``UPDATES`` flow
  updates in training and ``TEST_UPDATES`` at test; ``STEPS`` steps of ``BATCH`` random ``CROP`` crops with flips and
  colour jitter, the same augmentation for every arm.
- Training pools: ``POOL`` pairs per arm rendered at ``RES`` (256x192), images kept as uint8.
  - ``flowsynth``: ``BouncingThingsConfig()`` (with ``--set`` changes: a lever) at 256x192, 2 frames; its
    ``flow_px``, stated at 512 px wide (``flow_px_width``), is scaled by the config to 1 / ``SCALE`` of it, so motion
    keeps the proportions of a 512x384 rendering (the registered runs divided it by ``SCALE`` by hand: the same
    bytes); procedural textures only.
  - ``chairs2d_photos``: the FlyingChairs-style 2D baseline (``pools.layers_pool``, the library's layers; the
    registered runs drew it with OpenCV, ``sets.chairs2d_pairs``) textured with crops of every photograph that ships
    with scikit-image (``NATURAL_PHOTOS``), as FlyingChairs is textured with photographs.
  - ``chairs2d``: the same baseline textured with flowsynth frames not trained on: it isolates what the 3D motion
    teaches. Both baselines' motion is scaled so that their mean |flow| equals the flowsynth pool's.
  - ``flowsynth_photos``: the flowsynth config with NATURAL_PHOTOS as every texture (``texture_families=("image",)``).
  - ``flowsynth_natural``: the same with 96 textures made without files, with statistics of photographs instead
    (``sets.natural_folder``: 1/f spectra, dead leaves, sparse edges over smooth regions).
  - ``flowsynth_final``: the flowsynth config's final pass (``rgb_final``: motion blur, depth of field, sensor
    noise) as the images, in place of ``rgb``; the flow is the same truth.
  - ``mixture``: a preset mixture, as FlowNet and RAFT start on chairs: half the ``flowsynth`` pool, half the
    ``chairs2d`` pool (no files).
  - ``curriculum``: chairs first, as FlowNet and RAFT train: the ``chairs2d`` pool for the first half of the steps,
    then the ``flowsynth`` pool (no files; both pools whole, so the arm holds 2 x POOL pairs; ``STAGES``).
  - ``control``: the flowsynth pool again, with another net seed (seed + ``CONTROL_SEED``): the judge's own noise.
  - ``still_natural``: the ``flowsynth`` pool with its last 15% of pairs replaced by still (half) and near-still
    (half, sub-pixel) 2D pairs textured with ``sets.natural_folder``'s images (``pools.still_natural``).
  - ``tuned``: the preset ``flowsynth tune`` wrote (``--preset FILE``), at RES, rendered as the tune renders its own
    pools (``pools.tuned``): decision 0026's judge of the tune.
- Judges (``judge_sets``): Motorcycle ("stereo": the whole stereo pair at half resolution, plain and mirrored,
  ``sets.motorcycle_full``) and, with ``--middlebury DIR``, the mean EPE over the Middlebury pairs found there
  ("middlebury", each pair also "mb_NAME"), at full resolution. Tested at step 0 and every ``EVERY`` steps; a net's
  score on a judge is the mean of its last ``JUDGED`` checkpoints (steps 2000 and 2400: ``score``).
"""

from __future__ import annotations

from pathlib import Path

from .sets import middlebury_pairs, motorcycle_full

NET = "raft_small"
RES = (256, 192)  # (w, h) the training pairs are rendered at [px]
CROP = (128, 160)  # (h, w) of the training crops [px]: RAFT's correlation pyramid needs 128 or more a side
BATCH = 6
STEPS = 2400
EVERY = 400  # test every this many steps
JUDGED = 2  # a net's score: the mean of its last JUDGED checkpoints
LR = 4e-4  # RAFT's peak learning rate (AdamW, one-cycle)
UPDATES, TEST_UPDATES = 8, 12
POOL = 1200  # training pairs per arm
SCALE = 512 // RES[0]  # the pools are 1 / SCALE of the 512x384 scale that flow_px is stated at
ARMS = ("flowsynth", "chairs2d_photos", "chairs2d", "flowsynth_photos", "flowsynth_natural", "flowsynth_final",
        "mixture", "curriculum", "control", "still_natural", "tuned")
STAGES = {"curriculum": 2}  # arms trained in stages: the pool's k-th of n equal blocks feeds the k-th n-th of steps
CONTROL_SEED = 100  # the control's net seed is the run's seed + this
JUDGES = ("stereo", "middlebury")
CACHE = Path(__file__).resolve().parents[2] / ".cache" / "learning_raft"  # the trained nets' weights
RESULTS = "learning_raft"  # the stem of every results file of this judge (``results_name``)


def judge_sets(middlebury_dir: str | None) -> dict:
    """The real judges: {"stereo": ``motorcycle_full(2)``, "mb_NAME": ... for each Middlebury pair under
    ``middlebury_dir`` (none when it is None)}, each (img1, img2, flow, valid) float32 (n, C, H, W)."""
    return {"stereo": motorcycle_full(2), **middlebury_pairs(middlebury_dir)}


def with_means(epe: dict) -> dict:
    """``epe`` ({judge set: EPE [px]}) plus "middlebury", the mean over its mb_* entries, when there are any."""
    mb = [v for k, v in epe.items() if k.startswith("mb_")]
    return {**epe, "middlebury": sum(mb) / len(mb)} if mb else dict(epe)


def zero_flow(tests: dict) -> dict:
    """The EPE [px] of predicting zero flow on each of ``tests`` (``judge_sets``' dict), with the Middlebury mean."""
    import torch

    from flowsynth.train.steps import epe

    return with_means({k: epe(torch.zeros_like(v[2]), v[2], v[3]) for k, v in tests.items()})


def score(curve: list, judge: str) -> float:
    """A net's score on ``judge``: the mean EPE [px] of the last JUDGED checkpoints of ``curve`` (a net's list of
    {"step": ..., judge: EPE} entries, the untrained step 0 first and never counted). The pre-registered rule."""
    pts = [c[judge] for c in curve[1:] if judge in c][-JUDGED:]
    return sum(pts) / len(pts)


def results_name(kind: str = "", tag: str = "") -> str:
    """The stem of a results/ file of this judge: ``learning_raft[_KIND][_TAG]`` (``kind`` "" for a run's results,
    e.g. "summary_ARM_AGAINST", "screens", "stats", "diagnose", "diagnose_checkpoints", "ensemble_rate")."""
    return "_".join(x for x in (RESULTS, kind, tag) if x)


def results_tag(stem: str) -> str:
    """The TAG of a run's results stem ``learning_raft[_TAG]`` (``results_name("", TAG)``); "" for none."""
    return stem.removeprefix(RESULTS).removeprefix("_")


def net_stem(tag: str, arm: str, seed: int) -> str:
    """The file stem of the net a run tagged ``tag`` trains for ``arm`` and ``seed``: TAG_ARM_sSEED ("default" for no
    tag), its weights CACHE/STEM.pt and its progress curve results/learning_raft_progress/STEM.json."""
    return f"{tag or 'default'}_{arm}_s{seed}"


def checkpoint_path(save: str, step: int) -> str:
    """Where the weights of a net's checkpoint at ``step`` lie beside its final weights at ``save``:
    STEM_stepSTEP.pt."""
    return str(Path(save).with_name(f"{Path(save).stem}_step{step}.pt"))
