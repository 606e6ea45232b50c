"""flowsynth.stats against brute-force numpy on the same rendered samples, and the `flowsynth stats` command."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.errors import ConfigError, ShapeError
from flowsynth.stats import HIST_BIN_PX, dataset_stats, dis_check, textureless_fraction

CFG = fs.BouncingThingsConfig(width=64, height=48, num_frames=3, motion="kinematic", num_objects=(3, 5))


def _textureless_loops(img: np.ndarray) -> float:
    """Oracle: (3, H, W) -> share of 8x8 tiles with grey std < 0.02, tile by tile."""
    grey = 0.299 * img[0] + 0.587 * img[1] + 0.114 * img[2]
    flat = total = 0
    for i in range(0, img.shape[1] - 7, 8):
        for j in range(0, img.shape[2] - 7, 8):
            flat += float(np.std(grey[i:i + 8, j:j + 8])) < 0.02
            total += 1
    return flat / total


def test_textureless_fraction_matches_tile_loops():
    rng = np.random.default_rng(0)
    img = np.full((3, 35, 50), 0.5)
    img[:, :16, :24] += rng.normal(0, 0.1, (3, 16, 24))  # 2 x 3 textured tiles of the 4 x 6 grid
    img[:, 16:24, :] += np.linspace(0, 0.01, 50)  # a gentle ramp: std far below 0.02
    assert textureless_fraction(torch.tensor(img)) == pytest.approx(_textureless_loops(img)) == 1 - 6 / 24
    noisy = rng.uniform(0, 1, (2, 3, 48, 64))
    assert textureless_fraction(noisy) == 0.0
    assert textureless_fraction(np.full((3, 8, 8), 0.3)) == 1.0
    with pytest.raises(ShapeError):
        textureless_fraction(np.zeros((1, 8, 8)))


@pytest.fixture(scope="module")
def stats_and_samples():
    ds = fs.datasets.BouncingThings(CFG, outputs=["rgb", "flow_fw", "valid_fw", "occ_fw", "oof_fw", "category"],
                                    seed=3)
    return dataset_stats(CFG, 2, seed=3, dis=True), [ds.sample(i) for i in range(2)]


def test_dataset_stats_match_numpy_on_the_same_samples(stats_and_samples):
    st, samples = stats_and_samples
    valid = np.concatenate([s["valid_fw"][:, 0].numpy().ravel() for s in samples])
    mag = np.concatenate([s["flow_fw"].double().norm(dim=1).numpy().ravel() for s in samples])[valid]
    occ = np.concatenate([s["occ_fw"].numpy().ravel() for s in samples])[valid]
    oof = np.concatenate([s["oof_fw"].numpy().ravel() for s in samples])[valid]
    assert st["valid_pixels"] == valid.sum()
    assert st["flow"]["mean"] == pytest.approx(mag.mean(), rel=1e-9)
    for q in (50, 90, 99):  # the histogram's percentile is the smallest value whose CDF reaches q
        assert abs(st["flow"][f"p{q}"] - np.percentile(mag, q, method="inverted_cdf")) <= HIST_BIN_PX
    assert st["flow"]["zero_fraction"] == pytest.approx((mag < 0.1).mean())
    assert st["occluded_fraction"] == pytest.approx(occ.mean())
    assert st["out_of_frame_fraction"] == pytest.approx(oof.mean())
    rgb = [s["rgb"][t].numpy() for s in samples for t in range(CFG.num_frames)]
    assert st["textureless_fraction"] == pytest.approx(np.mean([_textureless_loops(x) for x in rgb]))
    cat = np.concatenate([s["category"].numpy().ravel() for s in samples])
    assert st["category_share"]["room"] == pytest.approx((cat == 1).mean())
    assert sum(st["category_share"].values()) == pytest.approx(1.0)
    assert st["seconds_per_sample"]["min"] > 0


def test_dis_check_counts_visible_room_and_object_pixels(stats_and_samples):
    st, samples = stats_and_samples
    one = dis_check(samples[0])
    vis = samples[0]["valid_fw"][:, 0].numpy() & ~samples[0]["occ_fw"][:, 0].numpy()
    cat = samples[0]["category"][:-1, 0].numpy()
    assert one["room"]["pixels"] == (vis & (cat == 1)).sum()
    assert one["objects"]["pixels"] == (vis & (cat >= 2)).sum()
    gt = samples[0]["flow_fw"].double().norm(dim=1).numpy()
    assert one["room"]["zero_epe_sum"] == pytest.approx(gt[vis & (cat == 1)].sum())
    assert set(st["dis"]) == {"room", "objects"} and st["dis"]["objects"]["dis_epe"] >= 0


def test_stats_rejects_single_frames_and_bad_num():
    with pytest.raises(ConfigError):
        dataset_stats(fs.BouncingThingsConfig(num_frames=1), 1)
    with pytest.raises(ConfigError):
        dataset_stats(CFG, 0)


def test_stats_cli_prints_and_writes_json(tmp_path, capsys):
    out = tmp_path / "stats.json"
    rc = main(["stats", "--num", "1", "--width", "48", "--height", "32", "--num-frames", "2", "--motion", "static",
               "--json", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "|flow| [px]" in text and "textureless" in text
    st = json.loads(out.read_text())
    assert st["num_samples"] == 1 and st["config"]["width"] == 48 and 0 <= st["flow"]["zero_fraction"] <= 1


def test_export_manifest_carries_the_same_statistics(tmp_path):
    from flowsynth.export import export_dataset

    root = export_dataset(CFG, tmp_path / "ds", 2, seed=3, outputs=["rgb", "flow_fw", "occ_fw"], progress=False)
    manifest = json.loads((root / "manifest.json").read_text())
    want = dataset_stats(CFG, 2, seed=3)
    got = manifest["stats"]
    for key in ("valid_pixels", "flow", "occluded_fraction", "out_of_frame_fraction", "textureless_fraction",
                "category_share"):
        assert got[key] == pytest.approx(want[key]), key
    written = {p.name.rsplit("_", 1)[0] for p in (root / "00000").iterdir()}
    assert written == {"rgb", "flow_fw", "occ_fw", "meta.json"}  # the statistics' extra inputs are not written
    # resume: a no-op
    export_dataset(CFG, tmp_path / "ds", 2, seed=3, outputs=["rgb", "flow_fw", "occ_fw"], progress=False)
    assert json.loads((root / "manifest.json").read_text())["stats"] == got
