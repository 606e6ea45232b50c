"""benchmarks/learning/learning.py's network starts as a working block matcher (issue 12's protocol): untrained, it
recovers a known translation of a random texture. The oracle is the translation itself."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks" / "learning"))

import learning


def _shifted_pair(dx: int, dy: int):
    """A smooth random texture (bicubic upsampling of noise) and the same texture moved by (dx, dy) px: the
    content at pixel x of the first image is at x + (dx, dy) in the second."""
    g = torch.Generator().manual_seed(1)
    big = torch.nn.functional.interpolate(torch.rand(1, 3, 48, 64, generator=g), size=(192, 256), mode="bicubic",
                                          align_corners=False).clamp(0, 1)
    a = big[:, :, 40:136, 40:168]
    b = big[:, :, 40 - dy:136 - dy, 40 - dx:168 - dx]
    return a, b


@pytest.mark.parametrize(("dx", "dy", "tol"), [(0, 0, 0.01), (3, -2, 0.6), (7, 5, 0.4)])
def test_untrained_net_recovers_a_translation(dx, dy, tol):
    torch.manual_seed(0)
    net = learning.build_net()
    a, b = _shifted_pair(dx, dy)
    with torch.no_grad():
        flow = net(a, b)[-1][0]
    assert flow.shape == (2, 96, 128)
    inner = flow[:, 16:-16, 16:-16]  # away from the borders, where part of a window leaves the image
    err = (inner - torch.tensor([dx, dy], dtype=inner.dtype).view(2, 1, 1)).norm(dim=0)
    assert float(err.mean()) < tol
    assert torch.isfinite(flow).all()


def test_batches_stream_each_pair_once_and_pool_draws_with_replacement():
    """A pool of steps x batch pairs or more is a stream: the batches are one permutation's consecutive slices.
    A smaller pool is drawn from with replacement, the same draws as ``torch.randint`` on the same generator."""
    stream = list(learning.batches(12, 3, 4, torch.Generator().manual_seed(5)))
    assert [len(b) for b in stream] == [4, 4, 4]
    assert sorted(torch.cat(stream).tolist()) == list(range(12))
    assert torch.equal(torch.cat(stream), torch.randperm(12, generator=torch.Generator().manual_seed(5)))
    pool = list(learning.batches(11, 3, 4, torch.Generator().manual_seed(5)))
    g = torch.Generator().manual_seed(5)
    for b in pool:
        assert torch.equal(b, torch.randint(11, (4,), generator=g))


def test_too_few_steps_is_a_usage_error():
    import subprocess

    script = Path(__file__).resolve().parents[1] / "benchmarks" / "learning" / "learning.py"
    r = subprocess.run([sys.executable, str(script), "--steps", "10"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "at least 20 steps" in r.stderr


def _write_flo_by_hand(path: Path, flow) -> None:
    """The Middlebury .flo format written with numpy alone: b'PIEH', int32 width and height, then float32 (u, v)
    interleaved row by row (the oracle; flowsynth's own writer is not used)."""
    import numpy as np

    h, w = flow.shape[1:]
    body = np.ascontiguousarray(np.asarray(flow, np.float32).transpose(1, 2, 0)).tobytes()
    path.write_bytes(b"PIEH" + np.array([w, h], "<i4").tobytes() + body)


def test_middlebury_pairs_reads_frames_flow_and_unknown_marker(tmp_path):
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    h, w = 37, 53  # not multiples of 8
    img = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(2)]
    flow = rng.normal(size=(2, h, w)).astype(np.float32) * 3
    flow[:, 5, 7] = 1.5e9  # the format's marker of unknown flow
    d = tmp_path / "Venus"
    d.mkdir()
    for name, im in zip(("frame10.png", "frame11.png"), img):
        cv2.imwrite(str(d / name), im[..., ::-1])  # OpenCV writes BGR
    _write_flo_by_hand(d / "flow10.flo", flow)
    (tmp_path / "Grove2").mkdir()  # incomplete: skipped
    sets = learning.middlebury_pairs(str(tmp_path))
    assert list(sets) == ["mb_Venus"]
    a, b, f, valid = sets["mb_Venus"]
    assert a.shape == (1, 3, h, w) and f.shape == (1, 2, h, w) and valid.shape == (1, 1, h, w)
    assert torch.equal(a[0], torch.from_numpy(img[0].transpose(2, 0, 1).astype(np.float32) / 255))
    assert valid[0, 0, 5, 7] == 0 and float(valid.sum()) == h * w - 1
    known = valid[0, 0] > 0
    assert torch.equal(f[0][:, known], torch.from_numpy(flow)[:, known])
    assert torch.isfinite(f).all() and float(f[0, :, 5, 7].abs().max()) == 0
    assert learning.middlebury_pairs(None) == {} and learning.middlebury_pairs(str(tmp_path / "none")) == {}


def test_predict_pads_any_size_and_recovers_a_translation():
    """At a size that is not a multiple of the coarsest stride the padded prediction has the image's size and the
    untrained matcher still recovers the translation away from the padded border."""
    torch.manual_seed(0)
    net = learning.build_net()
    a, b = _shifted_pair(3, -2)
    a, b = a[..., :90, :121], b[..., :90, :121]
    with torch.no_grad():
        flow = learning.predict(net, a, b)[0]
    assert flow.shape == (2, 90, 121)
    inner = flow[:, 16:-16, 16:-16]
    err = (inner - torch.tensor([3.0, -2.0]).view(2, 1, 1)).norm(dim=0)
    assert float(err.mean()) < 0.6
    test = (a, b, torch.tensor([3.0, -2.0]).view(1, 2, 1, 1).expand(1, 2, 90, 121), torch.ones(1, 1, 90, 121))
    with torch.no_grad():
        full = learning.evaluate(net, test)
    assert full == pytest.approx(float((flow - test[2][0]).norm(dim=0).mean()), rel=1e-5)


def test_with_means_and_same_protocol():
    assert learning.with_means({"stereo": 2.0, "mb_A": 1.0, "mb_B": 3.0})["middlebury"] == 2.0
    assert "middlebury" not in learning.with_means({"stereo": 2.0})
    base = {k: 1 for k in learning.PROTOCOL} | {"flowsynth_config": {"width": 128}}
    newer = dict(base, flowsynth_config={"width": 128, "rest_fraction": 0.0})  # a field added at its default
    assert learning.same_protocol(base, newer)
    assert not learning.same_protocol(base, dict(base, flowsynth_config={"width": 128, "rest_fraction": 0.1}))
    assert not learning.same_protocol(base, dict(base, steps=2))
    assert not learning.same_protocol(base, dict(base, flowsynth_config={"width": 96}))


def test_final_ratios_need_both_arms_and_screen_excludes_photo_arms(monkeypatch):
    """A ``--screen`` run has the flowsynth arm alone: no ratio to the baseline is made up for it; and a screen
    with photo arms is a usage error (exit 2)."""
    end = lambda epe: {"curve": [{"step": 0, "stereo": 2.0}, {"step": 10, "stereo": epe}]}
    both = [{"results": {"flowsynth": end(1.5), "chairs2d": end(2.0)}}]
    assert learning.final_ratios(both) == {"stereo": [0.75]}
    assert learning.final_ratios([{"results": {"flowsynth": end(1.5)}}]) == {}
    monkeypatch.setattr(sys, "argv", ["learning.py", "--screen", "--photo-arms", "--quick"])
    with pytest.raises(SystemExit) as e:
        learning.main()
    assert e.value.code == 2


def test_mixture_argument_names_presets_and_weights():
    import argparse

    assert learning._mixture("chairs=1,default=2.5") == {"chairs": 1.0, "default": 2.5}
    for bad in ("chair=1", "chairs", "chairs=1,"):
        with pytest.raises(argparse.ArgumentTypeError):
            learning._mixture(bad)


def test_screen_report_applies_rule_3(tmp_path):
    """Rule 3 (docs/decisions/0019): promising when the candidate's Middlebury EPE is below 0.95 of the default's
    and its Motorcycle EPE not above 1.05 of it; the ratios are the final curve points', seed by seed; runs of
    different protocols are refused."""
    import json

    def run(path, stereo, mb, steps=1200):
        end = {"step": steps, "stereo": stereo, "middlebury": mb}
        path.write_text(json.dumps({"steps": steps, "batch": 8, "pool": 9600, "resolution": [128, 96],
                                    "test_pairs": 100, "net": "ncc-v2",
                                    "runs": [{"seed": 0, "results": {"flowsynth": {"curve": [end]}}}]}))
        return str(path)

    default = run(tmp_path / "d.json", 2.0, 1.5)
    rows = learning.screen_report(run(tmp_path / "a.json", 2.1, 1.35), default)
    assert [r["judge"] for r in rows] == ["stereo", "middlebury"]
    assert rows[0]["ratio"] == pytest.approx(1.05) and rows[1]["ratio"] == pytest.approx(0.9)
    assert all(r["promising (rule 3)"] for r in rows)
    assert not learning.screen_report(run(tmp_path / "b.json", 2.2, 1.35), default)[0]["promising (rule 3)"]
    assert not learning.screen_report(run(tmp_path / "c.json", 1.0, 1.45), default)[0]["promising (rule 3)"]
    with pytest.raises(SystemExit, match="steps"):
        learning.screen_report(run(tmp_path / "e.json", 1.0, 1.0, steps=800), default)


def test_plot_judge_curves_draws_each_judge(tmp_path, monkeypatch):
    """--plot hands one plot per real judge, every arm and seed of the matched files a series, to the shared
    plot_curves (matplotlib, the bench extra, draws it; the PNG itself is checked where matplotlib is installed)."""
    import json

    import _common

    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    drawn = {}

    def record(name, series, *args, **kwargs):
        drawn[name] = series
        return tmp_path / f"{name}.png"

    monkeypatch.setattr(_common, "plot_curves", record)
    curve = [{"step": s, "stereo": 2.0 - s / 1000, "middlebury": 1.6 - s / 2000} for s in (0, 400, 800)]
    (tmp_path / "learning_x_s0.json").write_text(json.dumps(
        {"runs": [{"seed": 0, "results": {"flowsynth": {"curve": curve}, "chairs2d": {"curve": curve[:2]}}}]}))
    (tmp_path / "learning_y_s0.json").write_text("{}")  # not matched by the pattern
    paths = learning.plot_judge_curves("curves", "learning_x_*.json")
    assert sorted(p.name for p in paths) == ["curves_middlebury.png", "curves_stereo.png"]
    assert drawn["curves_stereo"] == {"x_s0 flowsynth s0": ((0, 400, 800), (2.0, 1.6, 1.2)),
                                      "x_s0 chairs2d s0": ((0, 400), (2.0, 1.6))}
    steps = (0, 400, 800)
    assert drawn["curves_middlebury"]["x_s0 flowsynth s0"] == (steps, tuple(1.6 - s / 2000 for s in steps))


def test_plot_judge_curves_writes_png(tmp_path, monkeypatch):
    """With matplotlib (the bench extra) the plots are PNG files."""
    import json

    import _common

    pytest.importorskip("matplotlib", reason="plots need the bench extra (bash scripts/setup.sh --bench)")
    monkeypatch.setattr(_common, "RESULTS_DIR", tmp_path)
    curve = [{"step": s, "stereo": 2.0 - s / 1000} for s in (0, 400)]
    runs = [{"seed": 0, "results": {"a": {"curve": curve}}}]
    (tmp_path / "learning_x_s0.json").write_text(json.dumps({"runs": runs}))
    paths = learning.plot_judge_curves("curves", "learning_x_*.json")
    assert [p.name for p in paths] == ["curves_stereo.png"]
    assert paths[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
