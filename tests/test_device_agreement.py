"""Every device Warp finds renders what the CPU renders, within issue 47's tolerances
(benchmarks/device/device_agreement.py): ids and occlusion identical, flow within 1e-3 px, depth within 1e-4
relative, rgb within 0.02.

The comparison itself is checked on made-up outputs first (each tolerance fails just beyond its bound), then a
small scene is rendered on the CPU and on each CUDA device and compared; here, without CUDA, the CPU against itself.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

import flowsynth as fs
from flowsynth.kernels import wp_runtime

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "device"))

import device_agreement as da  # noqa: E402


def _outputs(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {"instance": torch.randint(0, 5, (2, 1, 6, 8), generator=g, dtype=torch.int32),
            "occ_fw": torch.rand((1, 1, 6, 8), generator=g) > 0.5,
            "flow_fw": torch.randn((1, 2, 6, 8), generator=g) * 10,
            "depth": torch.rand((2, 1, 6, 8), generator=g) * 8 + 1,
            "rgb": torch.rand((2, 3, 6, 8), generator=g)}


def _ok(rows) -> dict[str, bool]:
    return {r["key"]: r["ok"] for r in rows}


def test_compare_passes_identical_outputs():
    ref = _outputs()
    rows = da.compare(ref, {k: v.clone() for k, v in ref.items()})
    assert [r["key"] for r in rows] == ["instance", "occ_fw", "flow_fw", "depth", "rgb"]
    assert all(r["ok"] and r["max"] == 0 and r["over"] == 0 for r in rows)


@pytest.mark.parametrize("key,change,ok", [
    ("flow_fw", 0.9e-3, True), ("flow_fw", 1.1e-3, False),
    ("rgb", 0.019, True), ("rgb", 0.021, False),
    ("depth", 0.9e-4, True), ("depth", 1.1e-4, False),  # relative: times the depth
])
def test_compare_holds_each_tolerance(key, change, ok):
    ref = _outputs()
    got = {k: v.clone() for k, v in ref.items()}
    if key == "depth":
        got[key][0, 0, 2, 3] *= 1 + change
    else:
        got[key][0, 0, 2, 3] += change
    rows = {r["key"]: r for r in da.compare(ref, got)}
    assert rows[key]["ok"] is ok and rows[key]["over"] == (0 if ok else 1)
    assert all(r["ok"] for k, r in rows.items() if k != key)


@pytest.mark.parametrize("key", ["instance", "occ_fw"])
def test_compare_counts_any_id_or_mask_change(key):
    ref = _outputs()
    got = {k: v.clone() for k, v in ref.items()}
    got[key][0, 0, 1, 1] = ~got[key][0, 0, 1, 1] if key == "occ_fw" else got[key][0, 0, 1, 1] + 1
    rows = {r["key"]: r for r in da.compare(ref, got)}
    assert rows[key]["ok"] is False and rows[key]["max"] == 1


def test_compare_refuses_a_shape_or_dtype_change_and_nan():
    ref = _outputs()
    got = {**ref, "depth": ref["depth"][:1], "rgb": ref["rgb"].double()}
    rows = {r["key"]: r for r in da.compare(ref, got)}
    assert rows["depth"]["ok"] is False and rows["rgb"]["ok"] is False and "error" in rows["depth"]
    nan = {**ref, "flow_fw": ref["flow_fw"].clone()}
    nan["flow_fw"][0, 1, 0, 0] = float("nan")
    assert _ok(da.compare(ref, nan))["flow_fw"] is False


def test_merge_keeps_the_worst_of_every_sample():
    ref = _outputs()
    a = {k: v.clone() for k, v in ref.items()}
    b = {k: v.clone() for k, v in ref.items()}
    a["rgb"][0, 0, 0, 0] += 0.01
    b["rgb"][1, 2, 5, 7] += 0.05
    total: dict = {}
    da.merge(total, da.compare(ref, a))
    da.merge(total, da.compare(ref, b))
    assert total["rgb"]["ok"] is False and total["rgb"]["over"] == 1
    assert total["rgb"]["max"] == pytest.approx(0.05, abs=1e-6)
    assert total["rgb"]["elements"] == 2 * ref["rgb"].numel() and total["flow_fw"]["ok"] is True


def _devices() -> list[str]:
    wp = wp_runtime()
    n = wp.get_cuda_device_count()
    return [f"cuda:{i}" for i in range(n)] or ["cpu"]


@pytest.mark.parametrize("device", _devices())
def test_a_small_scene_agrees_with_the_cpu(device):
    cfg = fs.BouncingThingsConfig(width=64, height=48, num_frames=3, num_objects=(3, 5), render_mode="direct")
    ref = fs.datasets.BouncingThings(cfg, outputs=da.MAIN_OUTPUTS, seed=3).sample(1)
    got = fs.datasets.BouncingThings(cfg, outputs=da.MAIN_OUTPUTS, seed=3, device=device).sample(1)
    rows = da.compare(ref, got)
    assert {r["key"] for r in rows} >= set(da.MAIN_OUTPUTS)
    broken = [r for r in rows if r["ok"] is False]
    assert broken == [], broken
    if device == "cpu":
        assert all(r["max"] == 0 for r in rows)
