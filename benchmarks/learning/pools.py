"""The RAFT judge's training pools: one function per arm of ``protocol.ARMS`` (``ARM_POOLS``), each making its arm's
pool for one seed, and ``build_arms``, which makes the pools of a run's arms. A pool is (img1, img2, flow, valid):
uint8 (n, 3, h, w) images, float32 (n, 2, h, w) flow [px] and bool (n, 1, h, w) valid, at ``protocol.RES``.
The 2D pools (the chairs2d arms and chairs2d_photos) come from the library's layers, ``fs.datasets.layers_pairs``
(``layers_pool``); a run's data records it (``LAYERS``). Decision 0023's equivalence rule relates them to the
registered runs' pools, which OpenCV drew (``sets.chairs2d_pairs``, kept as the reference).
"""

from __future__ import annotations

import dataclasses

from .protocol import POOL, RES
from .sets import NATURAL_PHOTOS, natural_folder, photo_folder, photo_sources

CHAIRS2D_ARMS = ("chairs2d", "mixture", "curriculum")  # the arms made from the chairs2d pool
# the 2D pools' generator, recorded as the run's data["layers"]: the library's layers_pairs (a run without the key
# drew them with OpenCV's sets.chairs2d_pairs, as the registered runs of decision 0023 did)
LAYERS = "flowsynth"
# torch threads drawing the 2D pools: the pairs are the same bits at any count, and one thread is the fastest on a
# loaded machine (decision 0023 gives the rates)
LAYERS_THREADS = 1


def _u8(x):
    import torch

    return (x * 255).round().clamp(0, 255).to(torch.uint8)


def flowsynth_pool(n: int, seed: int, workers: int, overrides: dict | None = None, image: str = "rgb"):
    """n flowsynth pairs at RES: (img1, img2 uint8 (n, 3, h, w), flow (n, 2, h, w), valid (n, 1, h, w) bool), and the
    config. ``overrides``: config fields of a lever (not the size); ``image``: the output the images come from
    ("rgb", or "rgb_final": the final pass). The ``workers`` render through ``fs.datasets.loader`` (forkserver), so a
    process that has initialised CUDA renders its pools at the CPU rate; the pairs are those of any start method."""
    import torch

    import flowsynth as fs

    base = fs.BouncingThingsConfig.from_dict(overrides or {})
    cfg = dataclasses.replace(base, width=RES[0], height=RES[1], num_frames=2)  # flow_px scales with the width
    ds = fs.datasets.BouncingThings(cfg, outputs=[image, "flow_fw", "valid_fw"], seed=seed, length=n)
    w, h = RES
    img1, img2 = torch.empty(n, 3, h, w, dtype=torch.uint8), torch.empty(n, 3, h, w, dtype=torch.uint8)
    flow, valid = torch.empty(n, 2, h, w), torch.empty(n, 1, h, w, dtype=torch.bool)
    o = 0
    for b in fs.datasets.loader(ds, batch_size=16, num_workers=workers, persistent_workers=False):
        k = len(b[image])
        img1[o:o + k], img2[o:o + k] = _u8(b[image][:, 0]), _u8(b[image][:, 1])
        flow[o:o + k], valid[o:o + k] = b["flow_fw"][:, 0], b["valid_fw"][:, 0]
        o += k
    return (img1, img2, flow, valid), cfg


def mean_flow(data) -> float:
    """Mean |flow| [px] over the valid pixels of an (img1, img2, flow, valid) set."""
    import torch

    return float(torch.linalg.vector_norm(data[2], dim=1)[data[3][:, 0] > 0.5].mean())


def layers_pool(n: int, seed: int, sources, motion_scale: float = 1.0) -> tuple:
    """n FlyingChairs-style pairs from ``sources`` ((m, 3, h, w) float in [0, 1]): ``fs.datasets.layers_pairs(n,
    seed, sources, motion_scale)``'s frames and forward flow as (img1, img2 float32 (n, 3, h, w) in [0, 1], flow
    float32 (n, 2, h, w) [px], valid bool (n, 1, h, w)). Valid is True everywhere, as in FlyingChairs and as the
    registered runs trained: a layer's flow is exact at every pixel, its target inside the image or not. Runs on
    ``LAYERS_THREADS`` torch threads and restores the caller's count."""
    import torch

    import flowsynth as fs

    threads = torch.get_num_threads()
    torch.set_num_threads(LAYERS_THREADS)
    try:
        out = fs.datasets.layers_pairs(n, seed, sources, motion_scale, outputs=("rgb", "flow_fw"))
    finally:
        torch.set_num_threads(threads)
    rgb, flow = out["rgb"], out["flow_fw"][:, 0]
    return rgb[:, 0], rgb[:, 1], flow, torch.ones(n, 1, *flow.shape[-2:], dtype=torch.bool)


def baseline_pool(n: int, seed: int, sources, target_flow: float):
    """n 2D pairs (``layers_pool``) from ``sources`` (float (m, 3, h, w) in [0, 1]) whose mean |flow| matches
    ``target_flow`` [px] (the motion scale measured on 64 pilot pairs of seed + 1): (the pool, the motion scale)."""
    scale = target_flow / mean_flow(layers_pool(64, seed + 1, sources))
    img1, img2, flow, valid = layers_pool(n, seed, sources, scale)
    return (_u8(img1), _u8(img2), flow, valid), scale


@dataclasses.dataclass
class SeedPools:
    """What the arms of one seed share: ``n`` pairs an arm, the flowsynth ``pool`` (its first ``n`` pairs of
    ``rendered``, which holds n / 2 more, the chairs2d pool's textures, when an arm of CHAIRS2D_ARMS is built), its
    mean |flow| ``target`` [px] (the baselines' motion is scaled to it), ``info``, the facts recorded for the
    results (motion scales), and the ``tuned`` arm's ``preset`` file. ``chairs2d()`` makes the chairs2d pool on first
    use."""

    n: int
    seed: int
    workers: int
    overrides: dict
    rendered: tuple
    info: dict
    chairs: tuple | None = None
    preset: str | None = None

    @property
    def pool(self) -> tuple:
        return tuple(x[:self.n] for x in self.rendered)

    @property
    def target(self) -> float:
        return self.info["flowsynth_mean_flow"]

    def chairs2d(self) -> tuple:
        """The chairs2d pool (n pairs textured with the flowsynth frames not trained on), made once for the arms of
        CHAIRS2D_ARMS: a pure function of n and the seed."""
        if self.chairs is None:
            textures = self.rendered[0][self.n:].float() / 255
            self.chairs, self.info["chairs2d_motion_scale"] = baseline_pool(self.n, self.seed, textures, self.target)
            self.info["layers"] = LAYERS
        return self.chairs


def flowsynth(s: SeedPools) -> tuple:
    """The flowsynth pool: the config under test (with the run's ``--set`` changes)."""
    return s.pool


def control(s: SeedPools) -> tuple:
    """The flowsynth pool again (the control differs in its net seed: ``protocol.CONTROL_SEED``)."""
    return s.pool


def chairs2d(s: SeedPools) -> tuple:
    """The 2D baseline textured with flowsynth frames not trained on."""
    return s.chairs2d()


def mixture(s: SeedPools) -> tuple:
    """Half the flowsynth pool, then half the chairs2d pool."""
    import torch

    n = s.n
    return tuple(torch.cat([f[:n // 2], c[:n - n // 2]]) for f, c in zip(s.pool, s.chairs2d()))


def curriculum(s: SeedPools) -> tuple:
    """The chairs2d pool, then the flowsynth pool: the two blocks of ``protocol.STAGES``, in order."""
    import torch

    return tuple(torch.cat([c, f]) for c, f in zip(s.chairs2d(), s.pool))


def flowsynth_final(s: SeedPools) -> tuple:
    """The flowsynth pool's samples with the final pass (``rgb_final``) as the images."""
    return flowsynth_pool(s.n, s.seed, s.workers, s.overrides, image="rgb_final")[0]


def chairs2d_photos(s: SeedPools) -> tuple:
    """The 2D baseline textured with crops of NATURAL_PHOTOS."""
    sources = photo_sources(max(s.n // 2, 8), s.seed, RES, NATURAL_PHOTOS)
    pool, s.info["chairs2d_photos_motion_scale"] = baseline_pool(s.n, s.seed, sources, s.target)
    s.info["layers"] = LAYERS
    return pool


def flowsynth_photos(s: SeedPools) -> tuple:
    """The flowsynth config with NATURAL_PHOTOS as every texture."""
    return _textured(s, photo_folder(NATURAL_PHOTOS))


def flowsynth_natural(s: SeedPools) -> tuple:
    """The flowsynth config with file-free textures of natural statistics (``sets.natural_folder``) as every
    texture."""
    return _textured(s, natural_folder())


def _textured(s: SeedPools, folder) -> tuple:
    return flowsynth_pool(s.n, s.seed, s.workers, {**s.overrides, "texture_dir": str(folder),
                                                   "texture_families": ["image"]})[0]


# still_natural: the share of the default pool's pairs replaced, the near-still half's motion scale, and the seeds of
# its two layers pools (offsets from the run's seed, apart from every other arm's draws)
STILL_SHARE, NEAR_STILL_SCALE = 0.15, 0.05
STILL_SEED, NEAR_STILL_SEED = 40_000, 41_000


def natural_sources():
    """The textures of ``sets.natural_folder()`` (96 PNGs of 512x512, in name order) as layers sources at ``RES``:
    each image's centred 4:3 crop, averaged over 2x2 blocks (512x384 -> 256x192); float32 (96, 3, h, w) in [0, 1]."""
    import cv2
    import torch
    import torch.nn.functional as F

    w, h = RES
    out = []
    for f in sorted(natural_folder().glob("*.png")):
        im = torch.from_numpy(cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255
        H, W = im.shape[-2:]
        ch, cw = min(H, W * 3 // 4), min(W, H * 4 // 3)
        y0, x0 = (H - ch) // 2, (W - cw) // 2
        out.append(F.interpolate(im[None, :, y0:y0 + ch, x0:x0 + cw], size=(h, w), mode="area")[0])
    return torch.stack(out)


def still_natural(s: SeedPools, sources=None) -> tuple:
    """The default pool with its last ``STILL_SHARE`` of pairs replaced by still and near-still FlyingChairs-style
    pairs with natural image statistics (decision 0023's ``still_natural`` lever, against the default as W): half at
    motion scale 0 (zero flow everywhere), half at ``NEAR_STILL_SCALE`` (sub-pixel motion), textured with
    ``natural_sources()`` (or ``sources``), valid everywhere as every 2D pool. ``info["still_natural"]`` records the
    counts."""
    import torch

    n = s.n
    k = round(STILL_SHARE * n)
    still, near = k // 2, k - k // 2
    src = natural_sources() if sources is None else sources
    parts = [layers_pool(m, seed + s.seed, src, scale) for m, seed, scale in
             ((still, STILL_SEED, 0.0), (near, NEAR_STILL_SEED, NEAR_STILL_SCALE)) if m]
    tail = tuple(torch.cat(x) for x in zip(*parts)) if parts else None
    s.info["still_natural"] = {"replaced": k, "still": still, "near_still": near, "near_still_scale": NEAR_STILL_SCALE,
                               "layers": LAYERS}
    if tail is None:
        return s.pool
    tail = (_u8(tail[0]), _u8(tail[1]), tail[2], tail[3])
    return tuple(torch.cat([f[:n - k], t]) for f, t in zip(s.pool, tail))


def preset_sources(path) -> tuple[dict, dict]:
    """A preset file's (``fs.datasets.MixtureConfig.from_file``) ``Mixture`` arguments at ``RES``: {name: config with
    width and height set to RES}, its weights. Each config scales its own motion to the width (``flow_px`` is stated at
    ``flow_px_width``; the layers' shifts scale with width / 128), as docs/tune.md says of a preset rendered at another
    size."""
    from flowsynth.datasets import MixtureConfig

    mix = MixtureConfig.from_file(path)
    w, h = RES
    return {k: dataclasses.replace(c, width=w, height=h) for k, c in mix.configs.items()}, mix.weights


def tuned(s: SeedPools) -> tuple:
    """``flowsynth tune``'s preset (``--preset FILE``, docs/decisions/0026) at RES: pairs 0 .. n-1 of its ``Mixture``
    seeded with the run's seed, rendered as the tune renders its own pools (``flowsynth.tune.pools.render_pool``: the
    same bits as the tune's pool of that point and seed). ``info["preset"]`` records the file's name, its SHA-256
    and its contents."""
    import hashlib
    import json
    from pathlib import Path

    from flowsynth.tune import render_pool

    if s.preset is None:
        raise SystemExit("the tuned arm needs --preset FILE (the preset flowsynth tune wrote)")
    raw = Path(s.preset).read_bytes()
    s.info["preset"] = {"file": Path(s.preset).name, "sha256": hashlib.sha256(raw).hexdigest(),
                        "preset": json.loads(raw)}
    return render_pool(preset_sources(s.preset), s.seed, s.n, s.workers)


ARM_POOLS = {f.__name__: f for f in (flowsynth, chairs2d_photos, chairs2d, flowsynth_photos, flowsynth_natural,
                                     flowsynth_final, mixture, curriculum, control, still_natural,
                                     tuned)}  # ARMS' makers


def build_arms(names: list, seed: int, workers: int, overrides: dict, n: int = POOL,
               preset: str | None = None) -> tuple[dict, dict, object]:
    """The pools (``n`` pairs each) of the arms ``names`` (of ``protocol.ARMS``) for ``seed``: ({arm: pool}, info,
    the flowsynth config); ``preset``: the ``tuned`` arm's preset file. ``info``: the flowsynth pool's mean |flow|
    [px], the baselines' motion scales, the 2D pools' generator ("layers": ``LAYERS``, when a 2D arm is built), the
    tuned arm's preset, and per arm its mean |flow| [px] and the share of valid pixels moving less than 0.5 px
    ("still_share")."""
    import torch

    extra = n // 2 if set(CHAIRS2D_ARMS) & set(names) else 0
    rendered, cfg = flowsynth_pool(n + extra, seed, workers, overrides)
    s = SeedPools(n, seed, workers, overrides, rendered, {}, preset=preset)
    s.info["flowsynth_mean_flow"] = mean_flow(s.pool)
    arms = {name: ARM_POOLS[name](s) for name in names}
    info = s.info
    info["mean_flow"] = {k: mean_flow(v) for k, v in arms.items()}
    info["still_share"] = {k: float((torch.linalg.vector_norm(v[2], dim=1) < 0.5)[v[3][:, 0]].float().mean())
                           for k, v in arms.items()}
    return arms, info, cfg
