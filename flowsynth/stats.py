"""Dataset statistics: what a config actually produces, measured on rendered samples.

``dataset_stats(cfg, num)`` renders ``num`` samples of ``cfg``'s stream (BouncingThings, Layers or Mixture) and reports,
over every frame pair and every valid pixel (``valid_fw``):

- ``flow``: mean and 50/90/99th percentiles of |flow_fw| [px], and ``zero_fraction``, the share of
  valid pixels with |flow| < ``ZERO_FLOW_PX``;
- ``occluded_fraction`` (``occ_fw``) and ``out_of_frame_fraction`` (``oof_fw``) of valid pixels;
- ``textureless_fraction``: share of 8x8 patches of the RGB frames whose grey intensity has standard
  deviation below 0.02 (:func:`textureless_fraction`, the one definition used across flowsynth);
- ``category_share``: pixel share of each category ("nothing", "room", "object:<asset>"; a Layers stream's
  "background", "shape:ellipse", "shape:polygon"; a mixture's names of one id joined by "|") over all frames;
- ``seconds_per_sample``: wall-clock time of the stream's ``sample`` (mean, min, max);
- with ``dis=True``: OpenCV DIS optical-flow EPE beside the zero-flow EPE on room and object pixels
  (:func:`dis_check`), which says whether the pixels carry the motion a flow network must learn.

Percentiles come from a histogram of |flow| with ``HIST_BIN_PX`` wide bins (exact to that width) so memory
stays flat for any ``num``. docs/statistics.md puts the figures beside FlyingChairs, FlyingThings3D and Sintel.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

from flowsynth.errors import ConfigError, ShapeError
from flowsynth.options import check_int

__all__ = ["GREY_WEIGHTS", "HIST_BIN_PX", "STATS_OUTPUTS", "TEXTURELESS_STD", "ZERO_FLOW_PX", "cheap_stats_outputs",
           "dataset_stats",
           "dis_check", "format_stats", "sample_record", "summarize", "textureless_fraction"]

ZERO_FLOW_PX = 0.1
"""|flow| below this counts as zero flow [px]."""
TEXTURELESS_STD = 0.02
"""An 8x8 patch is textureless when the standard deviation of its grey intensity (0..1) is below this."""
GREY_WEIGHTS = (0.299, 0.587, 0.114)
"""Grey = these weights of the sRGB-encoded R, G, B (ITU-R BT.601 luma, as OpenCV's cvtColor)."""
HIST_BIN_PX = 0.01
"""Bin width of the |flow| histogram behind the percentiles [px]."""
HIST_MAX_PX = 4096.0
"""Flow magnitudes above this land in the last bin [px]."""
STATS_OUTPUTS = ("rgb", "flow_fw", "valid_fw", "occ_fw", "oof_fw", "category")
"""The outputs every statistic needs."""


def textureless_fraction(rgb: torch.Tensor | np.ndarray, patch: int = 8, threshold: float = TEXTURELESS_STD
                         ) -> float:
    """Share of ``patch`` x ``patch`` tiles whose grey intensity has standard deviation < ``threshold``.

    Args:
        rgb: (..., 3, H, W) float in [0, 1], sRGB-encoded (as the ``rgb`` output). Tiles are the
            non-overlapping grid from the top-left corner; a remainder narrower than ``patch`` is dropped.
        patch: tile side [px].
        threshold: population standard deviation (ddof 0) of grey, in 0..1 units.

    Returns:
        fraction in [0, 1] over all tiles of all leading indices.
    """
    x = torch.as_tensor(rgb)
    if x.ndim < 3 or x.shape[-3] != 3:
        raise ShapeError(f"rgb must have shape (..., 3, H, W), got {tuple(x.shape)}")
    H, W = x.shape[-2] // patch * patch, x.shape[-1] // patch * patch
    if H == 0 or W == 0:
        raise ShapeError(f"rgb of {tuple(x.shape[-2:])} px holds no {patch}x{patch} patch")
    w = torch.tensor(GREY_WEIGHTS, dtype=torch.float64).view(3, 1, 1)
    grey = (x[..., :H, :W].to(torch.float64) * w).sum(-3).reshape(-1, H // patch, patch, W // patch, patch)
    std = grey.std(dim=(2, 4), unbiased=False)
    return float((std < threshold).double().mean())


def cheap_stats_outputs(outputs) -> tuple[str, ...]:
    """``outputs`` plus the statistics' inputs that cost almost nothing beside them: ``category`` always,
    ``valid_fw`` and ``oof_fw`` when ``flow_fw`` is requested (same reprojection)."""
    extra = ("category",) + (("valid_fw", "oof_fw") if "flow_fw" in outputs else ())
    return tuple(dict.fromkeys((*outputs, *extra)))


def sample_record(sample: dict, seconds: float = 0.0) -> dict:
    """Small JSON-compatible sums of one sample, pooled by :func:`summarize`.

    Uses the keys the sample has: ``flow_fw`` with ``valid_fw`` (flow histogram, zero flow, and with
    ``occ_fw`` / ``oof_fw`` the occlusion shares), ``rgb`` (textureless tiles), ``category`` (pixel shares).
    ``seconds`` is the time the sample took to generate.
    """
    rec: dict = {"seconds": float(seconds)}
    if "flow_fw" in sample and "valid_fw" in sample:
        valid = sample["valid_fw"][:, 0].numpy()
        mag = sample["flow_fw"].to(torch.float64).norm(dim=1).numpy()[valid]
        bins, counts = np.unique(np.minimum(mag / HIST_BIN_PX, HIST_MAX_PX / HIST_BIN_PX).astype(np.int64),
                                 return_counts=True)
        rec.update(valid=int(valid.sum()), flow_sum=float(mag.sum()), zero=int((mag < ZERO_FLOW_PX).sum()),
                   hist=[bins.tolist(), counts.tolist()])
        for key in ("occ", "oof"):
            if f"{key}_fw" in sample:
                rec[key] = int(sample[f"{key}_fw"][:, 0].numpy()[valid].sum())
    if "rgb" in sample:
        rgb = sample["rgb"]
        tiles = rgb.shape[0] * (rgb.shape[-2] // 8) * (rgb.shape[-1] // 8)
        rec.update(tiles=tiles, flat_tiles=round(textureless_fraction(rgb) * tiles))
    if "category" in sample:
        ids, n = np.unique(sample["category"].numpy(), return_counts=True)
        rec["category"] = {str(k): v for k, v in zip(ids.tolist(), n.tolist())}
    return rec


def _percentile(hist: np.ndarray, q: float) -> float:
    """q-th percentile [px] of a |flow| histogram: centre of the bin holding it."""
    cum = np.cumsum(hist)
    if cum[-1] == 0:
        return 0.0
    return (int(np.searchsorted(cum, q / 100.0 * cum[-1], side="left")) + 0.5) * HIST_BIN_PX


def summarize(records: list[dict], cfg) -> dict:
    """Pool :func:`sample_record` results into the statistics dict (module docstring); a statistic whose
    inputs no record has is None."""
    def total(key: str) -> int | None:
        have = [r[key] for r in records if key in r]
        return sum(have) if have else None

    out: dict = {"num_samples": len(records), "width": cfg.width, "height": cfg.height,
                 "num_frames": cfg.num_frames, "valid_pixels": total("valid")}
    valid = out["valid_pixels"]
    if valid:
        hist = np.zeros(int(HIST_MAX_PX / HIST_BIN_PX) + 1, dtype=np.int64)
        for r in records:
            if "hist" in r:
                np.add.at(hist, np.asarray(r["hist"][0], np.int64), np.asarray(r["hist"][1], np.int64))
        out["flow"] = {"mean": total("flow_sum") / valid, "p50": _percentile(hist, 50),
                       "p90": _percentile(hist, 90), "p99": _percentile(hist, 99),
                       "zero_fraction": total("zero") / valid}
    else:
        out["flow"] = None
    for name, key in (("occluded_fraction", "occ"), ("out_of_frame_fraction", "oof")):
        n = total(key)
        out[name] = n / valid if n is not None and valid else None
    tiles = total("tiles")
    out["textureless_fraction"] = total("flat_tiles") / tiles if tiles else None
    names = _category_names(cfg)
    cats: dict[int, int] = {}
    for r in records:
        for k, v in r.get("category", {}).items():
            cats[int(k)] = cats.get(int(k), 0) + v
    pixels = sum(cats.values())
    out["category_share"] = {names.get(k, f"category:{k}"): v / pixels for k, v in sorted(cats.items())} or None
    sec = [r["seconds"] for r in records]
    out["seconds_per_sample"] = {"mean": float(np.mean(sec)), "min": float(np.min(sec)),
                                 "max": float(np.max(sec))} if sec else None
    return out


def _category_names(cfg) -> dict[int, str]:
    """category id -> name for ``cfg``'s samples; a mixture's id that its sources name differently gets their names
    joined by "|" ("room|background")."""
    from flowsynth.datasets import LAYER_CATEGORIES, config_kind
    from flowsynth.scene import OBJECT_CATEGORY_OFFSET, ROOM_CATEGORY, resolve_assets

    if config_kind(cfg) == "mixture":
        names: dict[int, list[str]] = {}
        for _, c in cfg.sources:
            for k, name in _category_names(c).items():
                if name not in names.setdefault(k, []):
                    names[k].append(name)
        return {k: "|".join(v) for k, v in names.items()}
    if config_kind(cfg) == "layers":
        return dict(LAYER_CATEGORIES)
    names = {0: "nothing", ROOM_CATEGORY: "room"}
    for a, key in enumerate(resolve_assets(cfg.assets)):
        names[OBJECT_CATEGORY_OFFSET + a] = "object:" + key
    return names


def dataset_stats(cfg=None, num: int = 16, *, seed: int = 0, start: int = 0, occlusion: str = "exact",
                  dis: bool = False, progress: Callable[[int], None] | None = None) -> dict:
    """Statistics of samples ``start .. start + num - 1`` of ``cfg``'s stream (``flowsynth.datasets.make_stream``).

    Args:
        cfg: BouncingThingsConfig (defaults when None), LayersConfig or MixtureConfig, with num_frames >= 2.
        num: number of samples, >= 1.
        seed, start: which samples.
        occlusion: "exact" or "depth" (flowsynth.truth.flow; a Layers stream's is exact).
        dis: also run :func:`dis_check` on every frame pair (needs opencv-python).
        progress: called with the number of samples done after each one.

    Returns:
        JSON-compatible dict; see the module docstring for the keys. Fractions are in [0, 1].
    """
    from flowsynth.datasets import make_stream
    from flowsynth.scene import BouncingThingsConfig

    cfg = BouncingThingsConfig() if cfg is None else cfg
    num = check_int("num", num, 1)
    if cfg.num_frames < 2:
        raise ConfigError("statistics need flow: num_frames >= 2")
    ds = make_stream(cfg, STATS_OUTPUTS, seed, start=start, occlusion=occlusion)
    records, dis_rows = [], []
    for k in range(num):
        t = time.perf_counter()
        s = ds.sample(start + k)
        records.append(sample_record(s, time.perf_counter() - t))
        if dis:
            dis_rows.append(dis_check(s))
        if progress is not None:
            progress(k + 1)
    out = dict(summarize(records, cfg), seed=seed, start=start)
    if dis:
        out["dis"] = _pool_dis(dis_rows)
    return out


def dis_check(sample: dict) -> dict:
    """OpenCV DIS flow (preset MEDIUM, grey uint8 frames) against ground truth, on every frame pair.

    Counts visible pixels only (``valid_fw`` and not ``occ_fw``), split by category: "room" and "objects".
    Returns {region: {"pixels", "dis_epe_sum", "zero_epe_sum"}} [px summed over pixels]; the zero-flow EPE
    of a pixel is its |flow|. A flow method beats zero flow on a region when its EPE is the smaller.
    """
    import cv2

    from flowsynth.scene import OBJECT_CATEGORY_OFFSET, ROOM_CATEGORY

    w = np.asarray(GREY_WEIGHTS, dtype=np.float64)[:, None, None]
    grey = [np.clip((f.numpy() * w).sum(0) * 255.0 + 0.5, 0, 255).astype(np.uint8) for f in sample["rgb"]]
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    out = {r: {"pixels": 0, "dis_epe_sum": 0.0, "zero_epe_sum": 0.0} for r in ("room", "objects")}
    for t in range(len(grey) - 1):
        est = dis.calc(grey[t], grey[t + 1], None).transpose(2, 0, 1).astype(np.float64)
        gt = sample["flow_fw"][t].numpy().astype(np.float64)
        vis = sample["valid_fw"][t, 0].numpy() & ~sample["occ_fw"][t, 0].numpy()
        cat = sample["category"][t, 0].numpy()
        epe = np.linalg.norm(est - gt, axis=0)
        zero = np.linalg.norm(gt, axis=0)
        for region, m in (("room", vis & (cat == ROOM_CATEGORY)), ("objects", vis & (cat >= OBJECT_CATEGORY_OFFSET))):
            out[region]["pixels"] += int(m.sum())
            out[region]["dis_epe_sum"] += float(epe[m].sum())
            out[region]["zero_epe_sum"] += float(zero[m].sum())
    return out


def _pool_dis(rows: list[dict]) -> dict:
    out = {}
    for region in ("room", "objects"):
        n = sum(r[region]["pixels"] for r in rows)
        d = sum(r[region]["dis_epe_sum"] for r in rows) / max(n, 1)
        z = sum(r[region]["zero_epe_sum"] for r in rows) / max(n, 1)
        out[region] = {"pixels": n, "dis_epe": d, "zero_epe": z, "dis_beats_zero": bool(n > 0 and d < z)}
    return out


def format_stats(st: dict) -> str:
    """Human-readable multi-line summary of a :func:`dataset_stats` (or :func:`summarize`) result."""
    f = st["flow"]
    lines = [f"{st['num_samples']} samples, {st['width']}x{st['height']}, {st['num_frames']} frames "
             f"({st['valid_pixels']} valid flow pixels)"]
    if f:
        lines += [f"|flow| [px]: mean {f['mean']:.2f}  p50 {f['p50']:.2f}  p90 {f['p90']:.2f}  p99 {f['p99']:.2f}",
                  f"zero flow (< {ZERO_FLOW_PX} px): {f['zero_fraction']:.1%}"]
    for label, key in (("occluded", "occluded_fraction"), ("out of frame", "out_of_frame_fraction"),
                       (f"textureless 8x8 patches (grey std < {TEXTURELESS_STD})", "textureless_fraction")):
        if st.get(key) is not None:
            lines.append(f"{label}: {st[key]:.1%}")
    if st.get("category_share"):
        lines.append("pixel share: " + ", ".join(f"{k} {v:.1%}" for k, v in st["category_share"].items()))
    if st.get("seconds_per_sample"):
        lines.append("seconds per sample: mean {mean:.3f}  min {min:.3f}  max {max:.3f}".format(
            **st["seconds_per_sample"]))
    for region, d in st.get("dis", {}).items():
        lines.append(f"DIS EPE on {region}: {d['dis_epe']:.2f} px vs zero flow {d['zero_epe']:.2f} px "
                     f"({d['pixels']} px) -> {'DIS better' if d['dis_beats_zero'] else 'zero flow better'}")
    return "\n".join(lines)
