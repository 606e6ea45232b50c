"""Export: round trip against the stream, crash safety under SIGKILL, layouts, CLI errors."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

import flowsynth as fs
from flowsynth.cli import main
from flowsynth.datasets import BouncingThings, Exported
from flowsynth.sampleio import file_digest

SMALL = ["--width", "32", "--height", "24", "--num-frames", "2", "--motion", "kinematic",
         "--num-objects", "2,3", "--max-objects", "4"]
CFG = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 3),
                              max_objects=4)
FLOAT_OUTS = ["depth", "distance", "normals", "position", "flow_fw", "flow_bw", "valid_fw", "occ_fw", "oof_bw",
              "motion", "instance", "category", "asset", "object_valid", "object_category", "world_T_obj",
              "box3d_corners", "box2d_amodal", "box2d_visible", "visible_pixels"]


def check_manifest(root: Path, num: int):
    manifest = json.loads((root / "manifest.json").read_text())
    assert sorted(manifest["samples"]) == [f"{i:05d}" for i in range(num)]
    for name, files in manifest["samples"].items():
        on_disk = sorted(p.name for p in (root / name).iterdir())
        assert on_disk == sorted(files)
        for f, digest in files.items():
            assert file_digest(root / name / f) == digest
    assert not list(root.glob(".tmp-*")) and not list(root.rglob(".*.tmp-*"))
    return manifest


def test_exported_equals_stream(tmp_path):
    from flowsynth.export import export

    root = export(CFG, tmp_path / "ds", 3, seed=4, outputs=FLOAT_OUTS, progress=False)
    manifest = check_manifest(root, 3)
    assert manifest["seed"] == 4 and manifest["layout"] == "native" and manifest["versions"]["warp-lang"]
    ds = BouncingThings(CFG, outputs=FLOAT_OUTS, seed=4)
    ex = Exported(root, verify=True)
    assert len(ex) == 3
    for i in range(3):
        a, b = ex[i], ds.sample(i)
        assert set(a) == set(b)
        for k in b:
            assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k


def test_exported_rgb_within_quantisation(tmp_path):
    from flowsynth.export import export

    root = export(CFG, tmp_path / "ds", 1, outputs=["rgb", "flow_fw"], progress=False)
    a, b = Exported(root)[0], BouncingThings(CFG, outputs=["rgb", "flow_fw"]).sample(0)
    assert (a["rgb"] - b["rgb"]).abs().max() <= 0.5 / 255 + 1e-6
    assert torch.equal(a["flow_fw"], b["flow_fw"])


def test_sigkill_then_resume(tmp_path):
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "flowsynth.cli", "export", "--out", str(out), "--num", "8", "--no-progress",
           "--outputs", "depth,flow_fw,instance", *SMALL]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not (out.exists() and len([p for p in out.iterdir() if p.name.isdigit()]) >= 2):
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done_before = sorted(p.name for p in out.iterdir() if p.name.isdigit())
    assert 2 <= len(done_before) < 8, "the export finished before it could be killed; make it longer"
    mtimes = {n: (out / n / "meta.json").stat().st_mtime_ns for n in done_before}
    assert subprocess.run(cmd, capture_output=True).returncode == 0
    check_manifest(out, 8)
    for n, m in mtimes.items():  # finished samples were not regenerated
        assert (out / n / "meta.json").stat().st_mtime_ns == m


def test_two_workers_match_one(tmp_path):
    from flowsynth.export import export

    a = export(CFG, tmp_path / "a", 4, outputs=["depth", "instance"], workers=2, progress=False)
    b = export(CFG, tmp_path / "b", 4, outputs=["depth", "instance"], workers=1, progress=False)
    ma, mb = (json.loads((r / "manifest.json").read_text())["samples"] for r in (a, b))
    assert ma == mb


def test_flyingchairs_layout_loads_like_torchvision(tmp_path):
    from PIL import Image

    root = tmp_path / "fc"
    assert main(["export", "--out", str(root), "--num", "3", "--layout", "flyingchairs", "--no-progress",
                 *SMALL]) == 0
    # what torchvision.datasets.FlyingChairs does on construction
    images = sorted((root / "data").glob("*.ppm"))
    flows = sorted((root / "data").glob("*.flo"))
    split = np.loadtxt(root / "FlyingChairs_train_val.txt", dtype=np.int32)
    assert len(flows) == len(split) == 3 and len(images) == 6
    ds = BouncingThings(CFG, outputs=["rgb", "flow_fw"], seed=0)
    for i in range(3):
        s = ds.sample(i)
        np.testing.assert_array_equal(cv2.readOpticalFlow(str(flows[i])).transpose(2, 0, 1), s["flow_fw"][0].numpy())
        img = np.asarray(Image.open(images[2 * i])).astype(np.float32) / 255
        assert np.abs(img - s["rgb"][0].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6


def test_cli_bad_inputs(tmp_path, capsys):
    assert main(["export", "--out", str(tmp_path / "a"), "--num", "1", "--outputs", "depht", *SMALL]) == 2
    assert "valid outputs" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["export", "--out", str(tmp_path / "b"), "--num", "1", "--config", str(bad)]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("widht = 3\n")
    assert main(["export", "--out", str(tmp_path / "b"), "--num", "1", "--config", str(wrong)]) == 2
    assert "unknown BouncingThingsConfig field" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "c"), "--num", "1", "--no-progress", "--outputs", "depth",
                 *SMALL]) == 0
    assert main(["export", "--out", str(tmp_path / "c"), "--num", "1", "--no-progress", "--outputs", "depth",
                 "--seed", "9", *SMALL]) == 2
    assert "different config" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "c"), "--num", "1", "--no-progress", "--outputs", "depth",
                 "--seed", "9", "--overwrite", *SMALL]) == 0
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["export", "--out", str(blocker / "sub"), "--num", "1", "--no-progress", *SMALL]) == 2
    assert "cannot write" in capsys.readouterr().err
    assert main(["export", "--out", str(tmp_path / "d"), "--num", "1", "--width", "-3"]) == 2
    assert "width" in capsys.readouterr().err


def test_cli_entry_point_exit_codes(tmp_path):
    r = subprocess.run([sys.executable, "-m", "flowsynth.cli", "export", "--out", str(tmp_path), "--num", "0"],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "num must be" in r.stderr


def test_preview_writes_png(tmp_path):
    out = tmp_path / "p.png"
    assert main(["preview", "--out", str(out), *SMALL]) == 0
    from PIL import Image

    assert Image.open(out).size[0] > CFG.width
    assert os.path.getsize(out) > 1000
