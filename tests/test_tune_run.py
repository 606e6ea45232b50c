"""flowsynth tune end to end: validation pairs written under tmp_path (Middlebury's layout, an exact affine warp of a
smooth synthetic image, flow by flowsynth's .flo writer), the trainer with a stand-in net resumed bit for bit after
an interruption, the `--quick` command with RAFT-small, and the command's named errors (exit status 2)."""

import sys

import numpy as np
import pytest
import torch

import flowsynth as fs
from flowsynth import tune
from flowsynth.cli import main
from flowsynth.io import read_json, read_rgb_png, write_flo, write_rgb_png
from flowsynth.tune import TWIN, EnsembleTrainer, Recipe, plan_rungs, search


def _texture(x, y):
    """A smooth colour image (3, H, W) in [0, 1] at real coordinates x, y [px]."""
    return np.stack([0.5 + 0.3 * np.sin(0.21 * x + 0.13 * y) + 0.15 * np.cos(0.05 * x * y / 40),
                     0.5 + 0.35 * np.cos(0.17 * x - 0.11 * y),
                     0.5 + 0.2 * np.sin(0.09 * x) * np.cos(0.23 * y) + 0.2 * np.sin(0.31 * y)]).clip(0, 1)


def affine_pair(h=128, w=160, a=((1.03, 0.02), (-0.01, 0.98)), t=(2.5, -1.5)):
    """Frame 2 of a scene that moves pixel p of frame 1 to M(p) = A p + t: img2(q) = img1(M^-1(q)); flow = M(p) - p."""
    a, t = np.array(a), np.array(t)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    p = np.stack([xs, ys])
    src = np.einsum("ij,jhw->ihw", np.linalg.inv(a), p - t[:, None, None])
    flow = np.einsum("ij,jhw->ihw", a, p) + t[:, None, None] - p
    return _texture(xs, ys).astype(np.float32), _texture(*src).astype(np.float32), flow.astype(np.float32)


def write_middlebury(root, names=("Alpha", "Beta"), h=128, w=160):
    for k, name in enumerate(names):
        img1, img2, flow = affine_pair(h, w, t=(1.5 + k, -1.0 - 0.5 * k))
        (root / name).mkdir(parents=True)
        write_rgb_png(root / name / "frame10.png", img1)
        write_rgb_png(root / name / "frame11.png", img2)
        write_flo(root / name / "flow10.flo", flow)
    return root


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # one torch thread: tests/conftest.py


class TinyFlow(torch.nn.Module):
    """RAFT's calling convention around one 3x3 convolution of the two frames: fast enough to train in a test."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(6, 2, 3, padding=1)

    def forward(self, img1, img2, num_flow_updates=12):
        flow = self.conv(torch.cat([img1, img2], 1))
        return [flow * (i + 1) / num_flow_updates for i in range(num_flow_updates)]


def test_the_val_pairs_hold_the_affine_flow(tmp_path):
    layout, pairs = tune.read_pairs(write_middlebury(tmp_path / "mb"))
    assert layout == "middlebury" and list(pairs) == ["Alpha", "Beta"]
    img1, img2 = pairs["Alpha"].images()
    flow, valid = pairs["Alpha"].flow, pairs["Alpha"].valid
    assert pairs["Alpha"].img1.dtype == torch.uint8 and pairs["Alpha"].img1.shape == (1, 3, 128, 160)
    assert img1.shape == (1, 3, 128, 160) and flow.shape == (1, 2, 128, 160) and valid.all()
    assert torch.equal(img1[0], torch.from_numpy(read_rgb_png(tmp_path / "mb" / "Alpha" / "frame10.png")))
    want1, want2, want_flow = affine_pair(t=(1.5, -1.0))
    assert torch.equal(flow[0], torch.from_numpy(want_flow))  # .flo is float32, bit for bit
    assert np.abs(img1[0].numpy() - want1).max() <= 0.5 / 255 + 1e-6  # 8-bit PNG rounding
    assert np.abs(img2[0].numpy() - want2).max() <= 0.5 / 255 + 1e-6
    # the flow is the motion: M^-1 of where it sends each pixel is the pixel
    a, t = np.array(((1.03, 0.02), (-0.01, 0.98))), np.array((1.5, -1.0))
    p = np.stack(np.mgrid[0:128, 0:160][::-1]).astype(np.float64)
    back = np.einsum("ij,jhw->ihw", np.linalg.inv(a), p + flow[0].double().numpy() - t[:, None, None])
    assert np.abs(back - p).max() < 1e-4


def _memo(render):
    cache = {}

    def memo(cfg, seed, n, out=None):
        key = (repr(cfg), seed, n)
        if key not in cache:
            cache[key] = render(cfg, seed, n)
        if out is None:
            return cache[key]
        for dst, x in zip(out, cache[key]):
            dst.copy_(x)
        return out
    return memo


class Interrupt(Exception):
    pass


def test_the_trainer_resumes_bit_for_bit_at_any_checkpoint(tmp_path):
    """Rendered pools, the stand-in net, three candidates over two rungs: a search cut after its k-th saved state and
    continued from it (a new trainer, as a new process) ends with exactly the curves of the uninterrupted one."""
    _, pairs = tune.read_pairs(write_middlebury(tmp_path / "mb", h=40, w=48))
    recipe = Recipe(res=(48, 32), crop=(16, 24), batch=2, updates=2, test_updates=2, pool=3)
    keys = tune.draw_candidates(3, 0)
    settings = {k: (tune.sources(k, recipe.res), 0) for k in keys}
    settings[keys[0] + TWIN] = (tune.sources(keys[0], recipe.res), 100)
    rungs = plan_rungs(3, tune.plan_cost(3, 4))
    render = _memo(tune.render_pool)

    def trainer():
        return EnsembleTrainer(settings, pairs, recipe, rungs[-1].end, net=TinyFlow, render=render)

    whole = search(trainer(), keys, rungs)
    assert len({whole["curves"][k][0]["mean"] for k in keys}) == 1  # one initialisation for every candidate
    assert whole["curves"][keys[0] + TWIN][0]["mean"] != whole["curves"][keys[0]][0]["mean"]  # the twin's own
    assert len({whole["curves"][k][-1]["mean"] for k in keys[:2]}) == 2  # their data differ
    for cut in (1, 3, 4, 5):  # after the untrained test; rung 0's last checkpoint; its survivors chosen; mid-rung 1
        saved = []

        def save(st, saved=saved, cut=cut):
            saved.append(st)
            if len(saved) == cut:
                raise Interrupt
        with pytest.raises(Interrupt):
            search(trainer(), keys, rungs, save=save)
        state = torch.load(_roundtrip(saved[-1], tmp_path), weights_only=True)
        resumed = search(trainer(), keys, rungs, state=state)
        assert resumed["curves"] == whole["curves"] and resumed["winner"] == whole["winner"], cut


def _roundtrip(state, tmp_path):
    path = tmp_path / "state.pt"
    torch.save(state, path)
    return path


def test_quick_tune_command_end_to_end(tmp_path, capsys):
    """`flowsynth tune --quick` with RAFT-small: exit 0, a preset the config loads, the report's numbers recomputed
    from its own curves, and the same command again continues from the finished state (nothing retrained)."""
    val = write_middlebury(tmp_path / "mb")
    out = tmp_path / "preset.json"
    argv = ["tune", "--val", str(val), "--out", str(out), "--quick", "--pairs", "Alpha"]
    assert main(argv) == 0
    rep = read_json(tmp_path / "preset.tune" / "report.json")
    mix = fs.datasets.Mixture.from_preset(out)
    assert mix.configs == tune.sources(rep["winner"])[0]
    assert rep["settings"]["pairs"] == ["Alpha"]
    rungs = rep["plan"]
    steps = [0, *(s for r in rungs for s in r["checkpoints"])]
    for net in rep["nets"]:  # every net's curve, and its rung scores as the mean of the rung's two checkpoints
        curve = {c["step"]: c["mean"] for c in net["curve"]}
        assert list(curve) == steps[:len(curve)] and all(np.isfinite(v) for v in curve.values())
        for r, score in enumerate(net["rungs"]):
            assert score == pytest.approx(np.mean([curve[s] for s in rungs[r]["checkpoints"]]))
    last = {n["key"]: n["rungs"][-1] for n in rep["nets"] if len(n["rungs"]) == len(rungs)}
    assert rep["noise"] == pytest.approx(abs(last[rep["reference"] + TWIN] - last[rep["reference"]]))
    assert rep["winner"] == min((k for k in last if not k.endswith(TWIN)), key=last.get)
    assert (tmp_path / "preset.tune" / "report.md").read_text().count("\n| ") == 1 + len(rep["nets"])
    printed = capsys.readouterr().out
    assert f"wrote {out}" in printed
    last_rung = len(rungs) - 1  # the log names the rungs as the report does, from 0
    assert f"rung {last_rung} [px]" in (tmp_path / "preset.tune" / "report.md").read_text()
    assert f"rung {last_rung} (of 0-{last_rung}) done" in printed and f"rung {last_rung + 1} " not in printed
    out.unlink()
    assert main(argv) == 0  # finished: rewrites the preset and the report from the state
    assert "continuing" in capsys.readouterr().out and read_json(tmp_path / "preset.tune" / "report.json") == rep
    assert fs.datasets.Mixture.from_preset(out).configs == mix.configs
    assert main([*argv, "--seed", "1"]) == 2  # the folder holds another tune: refused, naming what differs
    err = capsys.readouterr().err
    assert "differ in ['candidates', 'seed']" in err and "seed: 0 there, 1 here" in err, err


def _run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr().err


def test_bad_input_is_a_named_error_with_exit_status_2(tmp_path, capsys, monkeypatch):
    val = write_middlebury(tmp_path / "mb")
    out = str(tmp_path / "p.json")
    empty = tmp_path / "empty"
    empty.mkdir()
    code, err = _run(["tune", "--val", str(empty), "--out", out, "--quick"], capsys)
    assert code == 2 and "no validation pairs found" in err
    code, err = _run(["tune", "--val", str(val), "--out", out, "--quick", "--pairs", "Gamma"], capsys)
    assert code == 2 and "no validation pair named ['Gamma']" in err
    code, err = _run(["tune", "--val", str(val), "--out", out, "--budget", "5", "--candidates", "3"], capsys)
    assert code == 2 and "too small for 3 candidates" in err
    code, err = _run(["tune", "--val", str(val), "--out", out, "--quick", "--precision", "fp16"], capsys)
    assert code == 2 and "fp16" in err
    (val / "Beta" / "flow10.flo").write_bytes(b"PIEH not a flow")
    code, err = _run(["tune", "--val", str(val), "--out", out, "--quick"], capsys)
    assert code == 2 and "cannot read its flow" in err and "flow10.flo" in err
    monkeypatch.setitem(sys.modules, "torchvision.models.optical_flow", None)  # as if torchvision were missing
    code, err = _run(["tune", "--val", str(val), "--out", out, "--quick", "--pairs", "Alpha"], capsys)
    assert code == 2 and "needs torchvision" in err
    assert not (tmp_path / "p.json").exists()
