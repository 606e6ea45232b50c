"""examples/train_raft.py runs: a few steps of torchvision's RAFT-small on a tiny stream, a checkpoint that a second
run resumes from, and EPE on a folder of real-layout pairs that the test writes (a known translation of a random
image), checked against the EPE the test computes itself from the saved weights."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))


@pytest.fixture(scope="module")
def example():
    if importlib.util.find_spec("torchvision") is None:
        pytest.skip("torchvision is not installed (scripts/setup.sh installs it for the tests)")
    import tvision

    tvision.datasets()  # this CPU torch needs the shim before torchvision's models import
    spec = importlib.util.spec_from_file_location("train_raft", REPO / "examples" / "train_raft.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _pair_folder(root: Path, dx: int = 3, dy: int = -2) -> Path:
    """root/Shift/frame10.png, frame11.png, flow10.flo: a smooth random image moved by (dx, dy) px; one pixel's flow
    marked unknown (1e10)."""
    from PIL import Image

    from flowsynth.io.flo import write_flo

    rng = np.random.default_rng(0)
    big = torch.nn.functional.interpolate(torch.from_numpy(rng.random((1, 3, 40, 50), dtype=np.float32)),
                                          size=(160, 200), mode="bicubic", align_corners=False)[0].clamp(0, 1)
    a, b = big[:, 10:140, 10:180], big[:, 10 - dy:140 - dy, 10 - dx:180 - dx]
    d = root / "Shift"
    d.mkdir(parents=True)
    for name, im in (("frame10.png", a), ("frame11.png", b)):
        Image.fromarray((im.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(d / name)
    flow = np.zeros((2, 130, 170), np.float32)
    flow[0], flow[1] = dx, dy
    flow[:, 0, 0] = 1e10
    write_flo(d / "flow10.flo", flow)
    return root


def test_train_raft_runs_checkpoints_resumes_and_evaluates(example, tmp_path):
    pairs = example.middlebury_pairs(str(_pair_folder(tmp_path / "pairs")))
    assert [p[0] for p in pairs] == ["Shift"] and not bool(pairs[0][4][0, 0, 0])
    ckpt = tmp_path / "raft.pt"
    first = example.train(2, width=160, height=128, crop=(128, 128), batch=2, workers=0, checkpoint=str(ckpt),
                          save_every=1, pairs=pairs, progress=False)
    assert len(first["losses"]) == 2 and all(np.isfinite(first["losses"]))
    assert torch.load(ckpt)["step"] == 2
    second = example.train(3, width=160, height=128, crop=(128, 128), batch=2, workers=0, checkpoint=str(ckpt),
                           pairs=pairs, progress=False)
    assert len(second["losses"]) == 1 and torch.load(ckpt)["step"] == 3  # resumed at step 2, ran step 3 only
    # the reported EPE is the mean |prediction - (3, -2)| over the known pixels, computed here from the saved net
    net = example.build_raft()
    net.load_state_dict(torch.load(ckpt)["model"])
    net.eval()
    _, a, b, _, _ = pairs[0]
    with torch.no_grad():
        x1 = torch.nn.functional.pad(a[None], (0, 6, 0, 6), mode="replicate") * 2 - 1
        x2 = torch.nn.functional.pad(b[None], (0, 6, 0, 6), mode="replicate") * 2 - 1
        pred = net(x1, x2, num_flow_updates=12)[-1][0, :, :130, :170].numpy()
    err = np.hypot(pred[0] - 3, pred[1] + 2)
    err[0, 0] = np.nan
    assert second["after"]["Shift"] == pytest.approx(float(np.nanmean(err)), rel=1e-4)


def test_no_pairs_is_exit_code_3(example, tmp_path):
    (tmp_path / "empty").mkdir()
    assert example.main(["--steps", "1", "--eval", str(tmp_path / "empty")]) == example.EXIT_NO_PAIRS


@pytest.mark.parametrize("args", [["--steps", "-5"], ["--steps", "0"], ["--batch", "0"], ["--workers", "-1"],
                                  ["--lr", "0"], ["--lr", "nan"], ["--save-every", "0"], ["--width", "64"],
                                  ["--seed", "-1"], ["--eval-limit", "0"], ["--crop", "64", "64"],
                                  ["--precision", "fp8"], ["--precision", "fp16", "--device", "cpu"]])
def test_bad_arguments_exit_2_before_any_work(example, args, capsys):
    """As in the CLI: a bad argument is exit status 2 with a message naming it, before a net is built."""
    with pytest.raises(SystemExit) as e:
        example.main(args)
    assert e.value.code == 2
    assert args[0] in capsys.readouterr().err


def test_bf16_channels_last_trains(example, tmp_path):
    """--precision bf16 --channels-last: a finite loss, the net's convolution weights in channels_last memory, and a
    checkpoint that records no gradient scaler (bf16 needs none)."""
    ckpt = tmp_path / "raft.pt"
    out = example.train(1, width=160, height=128, crop=(128, 128), batch=1, workers=0, checkpoint=str(ckpt),
                        progress=False, precision="bf16", channels_last=True)
    assert len(out["losses"]) == 1 and np.isfinite(out["losses"][0])
    conv = out["net"].feature_encoder.convnormrelu[0].weight
    assert conv.is_contiguous(memory_format=torch.channels_last) and not conv.is_contiguous()
    assert torch.load(ckpt)["scaler"] is None and torch.load(ckpt)["step"] == 1


def test_stream_workers_start_without_fork(example, monkeypatch):
    """The example's stream takes its workers from fs.datasets.loader (forkserver: the net may already be on a
    GPU); the batches are the stream's samples, whatever the start method."""
    import flowsynth as fs

    seen = {}
    real = fs.datasets.loader

    def spy(ds, **kw):
        seen["loader"] = real(ds, **kw)
        return seen["loader"]

    monkeypatch.setattr(fs.datasets, "loader", spy)
    cfg = example.stream_config(64, 48)
    img1, img2, flow, valid = next(example.stream(cfg, 0, 2, 1))
    assert seen["loader"].multiprocessing_context.get_start_method() in ("forkserver", "spawn")
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "valid_fw"], seed=0)
    first = [ds.sample(i) for i in (0, 1)]
    assert torch.equal(img1, torch.stack([s["rgb"][0] for s in first]))
    assert torch.equal(flow, torch.stack([s["flow_fw"][0] for s in first]))
