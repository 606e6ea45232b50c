"""fs.datasets.Layers as a dataset: the same sample i in every run, worker and after a resume; its textures; Mixture
with both kinds and its preset file; export to every layout read back by torchvision's readers; the CLI, statistics
and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import tvision
from PIL import Image
from torch.utils.data import DataLoader

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.datasets import LAYERS_OUTPUTS, Exported, Layers, LayersConfig, Mixture, MixtureConfig, layers_pairs
from flowsynth.datasets import make_stream
from flowsynth.export import export_dataset

HALF_STEP = 0.5 / 64  # KITTI's flow PNGs round to 1/64 px
OUTS = ["rgb", "flow_fw", "valid_fw", "occ_fw", "instance"]


@pytest.fixture
def photos(tmp_path):
    """A folder of 3 small images (one wide, one tall, one grey) with patterns: the stream's texture_dir."""
    d = tmp_path / "photos"
    d.mkdir()
    ys, xs = np.mgrid[0:60, 0:90]
    Image.fromarray(np.stack([xs * 2, ys * 4, (xs + ys) % 256], -1).astype(np.uint8)).save(d / "a.png")
    Image.fromarray(np.stack([ys.T % 256, (xs.T * 3) % 256, xs.T * 2], -1).astype(np.uint8)).save(d / "b.png")
    Image.fromarray(((xs * ys) % 256).astype(np.uint8)).save(d / "c.png")
    return str(d)


def _cfg(photos, **kw):
    return LayersConfig(**{"width": 64, "height": 48, "texture_dir": photos, **kw})


def _equal(a: dict, b: dict, keys) -> None:
    for k in keys:
        assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k


def test_sample_i_is_the_same_in_every_run_worker_epoch_and_resume(photos):
    """Sample i is a function of (config, seed, i): two objects agree; two loader workers (forkserver) yield indices
    0..5 once each with exactly sample(i); a stream restored from state_dict continues with the uninterrupted
    stream's samples; epoch 1 of a length-4 stream holds indices 4..7; another seed gives other samples."""
    cfg = _cfg(photos)
    a, b = Layers(cfg, [*OUTS, "meta"], seed=3), Layers(cfg, [*OUTS, "provenance"], seed=3)
    _equal(a.sample(2), b.sample(2), OUTS)
    assert a.sample(2)["provenance"] == b.sample(2)["provenance"]
    assert not torch.equal(Layers(cfg, OUTS, seed=4).sample(2)["flow_fw"], a.sample(2)["flow_fw"])
    ds = Layers(cfg, OUTS, seed=3, length=6)
    got = {int(it["index"]): it for it in fs.datasets.loader(ds, batch_size=None, num_workers=2)}
    assert sorted(got) == list(range(6))
    for i, it in got.items():
        _equal(it, a.sample(i), OUTS)
    whole = Layers(cfg, OUTS, seed=3)
    it = iter(whole)
    first = [next(it) for _ in range(5)]
    part = Layers(cfg, OUTS, seed=3)
    it2 = iter(part)
    [next(it2) for _ in range(2)]
    resumed = Layers(cfg, OUTS, seed=3)
    resumed.load_state_dict(part.state_dict())
    for want, have in zip(first[2:], iter(resumed)):
        assert int(have["index"]) == int(want["index"])
        _equal(have, want, OUTS)
    ep = Layers(cfg, ["rgb"], seed=3, length=4)
    assert [int(x["index"]) for x in ep] == [0, 1, 2, 3] and [int(x["index"]) for x in ep] == [4, 5, 6, 7]
    with pytest.raises(fs.ConfigError, match="seed"):
        resumed.load_state_dict(Layers(cfg, OUTS, seed=9).state_dict())


def test_texture_dir_images_are_cut_to_the_frame_and_resized(tmp_path):
    """An image 4:1 with red, green, green, blue quarters is cut about its centre to 4:3, all green; a tall image
    keeps its middle rows; the bank lists the folder sorted by name; the sources are the bank's images."""
    d = tmp_path / "t"
    d.mkdir()
    wide = np.zeros((50, 200, 3), np.uint8)
    wide[:, :50, 0], wide[:, 50:150, 1], wide[:, 150:, 2] = 255, 255, 255
    Image.fromarray(wide).save(d / "0wide.png")
    tall = np.zeros((200, 50, 3), np.uint8)
    tall[:50, :, 0], tall[50:150, :, 2], tall[150:, :, 0] = 255, 255, 255
    Image.fromarray(tall).save(d / "1tall.png")
    ds = Layers(LayersConfig(width=64, height=48, texture_dir=str(d)), ["rgb"])
    assert len(ds.textures) == 2
    green, blue = ds.textures[0], ds.textures[1]
    assert green.shape == (3, 48, 64) and torch.allclose(green, torch.tensor([0.0, 1.0, 0.0]).view(3, 1, 1))
    assert torch.allclose(blue[:, 8:40], torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1), atol=1e-6)
    (d / "2bad.png").write_text("not an image")
    with pytest.raises(fs.AssetError, match="2bad.png"):
        Layers(LayersConfig(width=64, height=48, texture_dir=str(d)), ["rgb"]).textures[0]


def test_the_default_bank_is_flowsynth_frames():
    """Without texture_dir, source j is frame 0 of BouncingThings sample j at the stream's size and TEXTURE_SEED,
    in 8-bit steps; a sample's images come from those sources (frame 0's background is one of them)."""
    from flowsynth.datasets.layer_textures import TEXTURE_SEED

    cfg = LayersConfig(width=32, height=32, texture_bank=2)
    ds = Layers(cfg, ["rgb", "instance"], seed=1)
    frame = fs.datasets.BouncingThings(fs.BouncingThingsConfig(width=32, height=32, num_frames=1), ["rgb"],
                                       seed=TEXTURE_SEED).sample(1)["rgb"][0]
    assert torch.equal(ds.textures[1], (frame * 255).round() / 255)
    s, d = ds.sample(0), ds.draw(0)
    bg = s["instance"][0, 0] == 0
    assert torch.equal(s["rgb"][0][:, bg], ds.textures[d.background][:, bg])


def test_valid_means_one_thing_in_a_mixture_of_both_kinds(photos):
    """docs/conventions.md's valid_fw, the flow is defined, in both kinds of a Mixture: a pixel whose target leaves
    the image (oof_fw) is still valid where it sees a surface in front of the target camera. So in samples of either
    source some pixels are valid and out of frame at once; a layered sample is valid everywhere (every pixel sees a
    layer), a BouncingThings one never where it sees nothing (instance 0)."""
    things = fs.BouncingThingsConfig(width=64, height=48, num_frames=2, num_objects=(1, 2), render_mode="flat")
    mix = Mixture({"things": things, "chairs": _cfg(photos)}, outputs=["valid_fw", "oof_fw", "instance"], seed=0)
    both = {0: 0, 1: 0}
    for i in range(8):
        s, k = mix.sample(i), mix.source(i)
        valid, oof = s["valid_fw"][0, 0], s["oof_fw"][0, 0]
        both[k] += int((valid & oof).sum())
        if k == 1:
            assert bool(valid.all())
        else:
            assert not bool((valid & (s["instance"][0, 0] == 0)).any())
    assert both[0] > 0 and both[1] > 0, both


def test_mixture_of_both_kinds_and_its_preset_round_trip(photos, tmp_path):
    """A Mixture of a BouncingThings and a Layers config: sample i is its source's own sample i (the keys every
    source gives), both sources occur, a DataLoader batches them; to_preset / from_preset give the same sources and
    samples, for weights and for a curriculum."""
    things = fs.BouncingThingsConfig(width=64, height=48, num_frames=2, num_objects=(1, 2), render_mode="flat")
    chairs = _cfg(photos)
    outs = ["rgb", "flow_fw", "valid_fw"]
    mix = Mixture({"things": things, "chairs": chairs}, {"things": 1, "chairs": 2}, outputs=outs, seed=2)
    plain = [make_stream(things, outs, seed=2), Layers(chairs, outs, seed=2)]
    keys = set(outs) | {"index", "seed", "source"}
    seen = set()
    for i in range(6):
        k = mix.source(i)
        seen.add(k)
        got = mix.sample(i)
        assert set(got) == keys and int(got["source"]) == k
        _equal(got, plain[k].sample(i), outs)
    assert seen == {0, 1}
    # "meta": the metadata keys every source has: provenance (a Layers source has no camera)
    meta = Mixture({"things": things, "chairs": chairs}, outputs=[*outs, "meta"], seed=2)
    configs = (things, chairs)
    for i in range(2):
        got = meta.sample(i)
        assert set(got) == keys | {"provenance"}
        assert got["provenance"] == make_stream(configs[meta.source(i)], [*outs, "provenance"], seed=2).sample(i)[
            "provenance"]
    with pytest.raises(fs.ConfigError, match="no \\['K'\\]"):  # asked by name: every source must have it
        Mixture({"things": things, "chairs": chairs}, outputs=[*outs, "K"], seed=2)
    batch = next(iter(DataLoader(Mixture({"things": things, "chairs": chairs}, outputs=outs, seed=2, length=4),
                                 batch_size=4)))
    assert batch["rgb"].shape == (4, 2, 3, 48, 64) and batch["valid_fw"].dtype == torch.bool
    for weights in ({"things": 1, "chairs": 2}, [(3, {"chairs": 1}), (None, {"things": 1, "chairs": 1})]):
        m = Mixture({"things": things, "chairs": chairs}, weights, outputs=outs, seed=2)
        path = m.to_preset(tmp_path / "preset.json")
        text = json.loads(path.read_text())
        assert [s["kind"] for s in text["sources"]] == ["bouncing", "layers"]
        back = Mixture.from_preset(path, outputs=outs, seed=2)
        assert back.names == m.names and back.config == m.config
        assert [back.source(i) for i in range(200)] == [m.source(i) for i in range(200)]
        i = next(i for i in range(50) if m.source(i) == 1)
        _equal(back.sample(i), m.sample(i), outs)


@pytest.mark.parametrize("make,match", [
    (lambda p: LayersConfig(width=16), "width"),
    (lambda p: LayersConfig(num_frames=0), "num_frames"),
    (lambda p: LayersConfig(motion_scale=-1.0), "motion_scale"),
    (lambda p: LayersConfig(motion_scale=float("nan")), "motion_scale"),
    (lambda p: LayersConfig(texture_bank=0), "texture_bank"),
    (lambda p: LayersConfig(texture_dir=5), "texture_dir"),
    (lambda p: LayersConfig.from_dict({"fov_deg": 60.0}), "unknown LayersConfig field"),
    (lambda p: Layers(_cfg(p), ["depth"]), "Layers gives"),
    (lambda p: Layers(_cfg(p, num_frames=1), ["flow_fw"]), "num_frames >= 2"),
    (lambda p: Layers(fs.BouncingThingsConfig(), ["rgb"]), "LayersConfig"),
    (lambda p: Layers(_cfg(p), ["rgb"], seed=-1), "seed"),
    (lambda p: Layers(_cfg(p), ["rgb"]).sample(-1), "sample index"),
    (lambda p: make_stream(_cfg(p), ["rgb"], occlusion="depth"), "exact"),
    (lambda p: Layers(LayersConfig(texture_dir=p + "/missing"), ["rgb"]).sample(0), "does not exist"),
    (lambda p: Mixture({"a": _cfg(p), "b": fs.BouncingThingsConfig(width=64, height=48, num_frames=3)}), "differs"),
    (lambda p: Mixture({"a": _cfg(p), "b": fs.BouncingThingsConfig(width=64, height=48, num_frames=2)},
                       outputs=["rgb", "depth"]), "Layers gives"),
    (lambda p: Mixture.from_preset(p + "/none.json"), "does not exist"),
    (lambda p: MixtureConfig.from_dict({"format": "flowsynth-mixture", "version": 1,
                                        "sources": [{"name": "a", "kind": "blobs", "config": {}}]}), "kind"),
    (lambda p: MixtureConfig.from_dict({"sources": []}), "format"),
    (lambda p: layers_pairs(0, 0, torch.rand(2, 3, 32, 32)), "n must be"),
])
def test_bad_input_is_a_config_error_that_says_what_to_do(photos, make, match):
    with pytest.raises(fs.ConfigError, match=match):
        make(photos)


def test_bad_sources_are_a_shape_error():
    with pytest.raises(fs.ShapeError, match="32x32"):
        layers_pairs(1, 0, torch.rand(2, 3, 16, 64))
    with pytest.raises(fs.ShapeError, match=r"\(m, 3, H, W\)"):
        layers_pairs(1, 0, torch.rand(2, 32, 32))


def test_export_to_every_layout_read_back_by_readers_nobody_here_wrote(photos, tmp_path):
    """Two samples of 3 frames in each layout: torchvision's FlyingChairs, KittiFlow and Sintel read the pairs (flow
    bit-exact, or within KITTI's 1/64 px where valid_fw, valid = valid_fw), Exported reads native and webdataset back
    as the stream (floats bit-exact, rgb within 8-bit rounding); the manifest names the kind and no camera, and its
    statistics name the layers' categories; flyingthings3d is refused before writing; a re-run resumes."""
    cfg = _cfg(photos, num_frames=3)
    stream = Layers(cfg, [*LAYERS_OUTPUTS, "provenance"], seed=1)
    s = [stream.sample(i) for i in range(2)]
    tv = tvision.datasets()
    root = export_dataset(cfg, tmp_path / "chairs", 2, seed=1, layout="flyingchairs", progress=False)
    ds = tv.FlyingChairs(root=root, split="train")
    assert len(ds) == 4
    for k in range(4):
        _, img2, flow = ds[k]
        ref = s[k // 2]
        np.testing.assert_array_equal(flow, ref["flow_fw"][k % 2].numpy())
        assert np.abs(np.asarray(img2) / 255 - ref["rgb"][k % 2 + 1].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6
    root = export_dataset(cfg, tmp_path / "kitti", 2, seed=1, layout="kitti", progress=False)
    ds = tv.KittiFlow(root=root, split="train")
    for k in range(4):
        _, _, flow, valid = ds[k]
        ref = s[k // 2]
        np.testing.assert_array_equal(valid, ref["valid_fw"][k % 2, 0].numpy())
        assert np.abs(flow - ref["flow_fw"][k % 2].numpy())[:, valid].max() <= HALF_STEP + 1e-6
    assert all(ref["valid_fw"].all() for ref in s)  # the flow is defined everywhere: KITTI's mask holds it all
    assert any(ref["oof_fw"].any() for ref in s), "no target leaves the image: out-of-frame flow went untested"
    root = export_dataset(cfg, tmp_path / "sintel", 2, seed=1, layout="sintel", progress=False)
    ds = tv.Sintel(root=root, split="train", pass_name="clean")
    flows = sorted(ds[k][2].tobytes() for k in range(4))
    assert flows == sorted(ref["flow_fw"][t].numpy().tobytes() for ref in s for t in range(2))
    for layout in ("native", "webdataset"):
        root = export_dataset(cfg, tmp_path / layout, 2, seed=1, layout=layout, progress=False)
        manifest = json.loads((root / "manifest.json").read_text())
        assert manifest["dataset"] == "layers" and manifest["cameras"]["00000"] is None
        assert set(manifest["stats"]["category_share"]) <= {"background", "shape:ellipse", "shape:polygon"}
        back = Exported(root, verify=True)
        for i in range(2):
            a = back[i]
            assert set(a) == {*manifest["outputs"], "index", "seed", "provenance"}, layout
            assert a["provenance"] == s[i]["provenance"]
            for k in manifest["outputs"]:
                if k == "rgb":
                    assert (a[k] - s[i][k]).abs().max() <= 0.5 / 255 + 1e-6
                else:
                    assert a[k].dtype == s[i][k].dtype and torch.equal(a[k], s[i][k]), (layout, k)
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "native").rglob("*.exr")}
    export_dataset(cfg, tmp_path / "native", 2, seed=1, layout="native", progress=False)
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "native").rglob("*.exr")} == before
    with pytest.raises(fs.ConfigError, match="Layers gives|disparity"):
        export_dataset(cfg, tmp_path / "ft3d", 1, layout="flyingthings3d", progress=False)
    assert not (tmp_path / "ft3d").exists()


def test_cli_export_preview_stats(photos, tmp_path, capsys):
    """``--dataset layers``: export, preview and stats run (exit 0) from its flags; a scene flag with layers, a
    layers flag without, a preset with layers and an output layers lack exit 2 naming the flag."""
    size = ["--dataset", "layers", "--width", "64", "--height", "48", "--texture-dir", photos, "--motion-scale", "2"]
    assert main(["export", "--out", str(tmp_path / "e"), "--num", "2", "--layout", "flyingchairs", "--no-progress",
                 *size]) == 0
    assert len(list((tmp_path / "e" / "FlyingChairs" / "data").glob("*_flow.flo"))) == 2
    manifest = json.loads((tmp_path / "e" / "manifest.json").read_text())
    assert manifest["config"]["motion_scale"] == 2.0 and manifest["dataset"] == "layers"
    assert main(["preview", "--out", str(tmp_path / "p.png"), *size]) == 0
    with Image.open(tmp_path / "p.png") as im:
        assert im.text["flowsynth:dataset"] == "layers"
        assert json.loads(im.text["flowsynth:config"]) == manifest["config"]
    capsys.readouterr()
    assert main(["stats", "--num", "2", "--json", str(tmp_path / "s.json"), *size]) == 0
    out = capsys.readouterr().out
    assert "background" in out and "occluded" in out
    assert json.loads((tmp_path / "s.json").read_text())["config"]["width"] == 64
    for argv, needle in ((["--fov-deg", "30"], "--fov-deg"), (["--preset", "chairs"], "--preset"),
                         (["--outputs", "rgb,depth"], "Layers gives")):
        assert main(["preview", "--out", str(tmp_path / "q.png"), *size, *argv]) == 2
        assert needle in capsys.readouterr().err
    assert main(["preview", "--out", str(tmp_path / "q.png"), "--motion-scale", "2"]) == 2
    assert "--dataset layers" in capsys.readouterr().err


def test_stats_of_a_layers_stream(photos):
    """fs.stats over Layers: flow statistics over valid pixels, some occlusion, the layers' categories."""
    from flowsynth.stats import dataset_stats

    st = dataset_stats(_cfg(photos), 4, seed=0)
    assert st["flow"]["mean"] > 0.5 and 0 < st["occluded_fraction"] < 1
    # valid everywhere (the flow is defined), so the share out of frame is oof_fw's share of all pixels
    stream = Layers(_cfg(photos), ["valid_fw", "oof_fw"], seed=0)
    masks = [stream.sample(i) for i in range(4)]
    assert all(m["valid_fw"].all() for m in masks)
    oof = sum(int(m["oof_fw"].sum()) for m in masks) / sum(m["oof_fw"].numel() for m in masks)
    assert 0 < oof < 1 and st["out_of_frame_fraction"] == pytest.approx(oof, rel=1e-12)
    assert "background" in st["category_share"] and abs(sum(st["category_share"].values()) - 1) < 1e-9
