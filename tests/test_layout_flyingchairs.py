"""``--layout flyingchairs`` read by torchvision.datasets.FlyingChairs and OpenCV's .flo reader."""

import dataclasses

import cv2
import numpy as np
import pytest
import tvision

from flowsynth.cli import main
from flowsynth.datasets import BouncingThings
from flowsynth.export import export_dataset



def check_pairs(ds, stream, pairs_per_sample, indices):
    """ds[k] for k in indices is pair (t, t+1) of sample k // pairs_per_sample, t = k % pairs_per_sample."""
    for n, k in enumerate(indices):
        img1, img2, flow = ds[n]
        s = stream.sample(k // pairs_per_sample)
        t = k % pairs_per_sample
        np.testing.assert_array_equal(flow, s["flow_fw"][t].numpy())
        for img, frame in ((img1, t), (img2, t + 1)):
            a = np.asarray(img).astype(np.float32) / 255
            assert np.abs(a - s["rgb"][frame].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6


@pytest.mark.parametrize("num", [1, 3])
def test_torchvision_reads_any_num(tmp_path, num, capsys, small_config, small_flags):
    """--num 1 used to write a one-line split file, which np.loadtxt turns into an unindexable 0-d array."""
    assert main(["export", "--out", str(tmp_path), "--num", str(num), "--layout", "flyingchairs", "--no-progress",
                 *small_flags]) == 0
    assert f"torchvision.datasets.FlyingChairs(root='{tmp_path}')" in capsys.readouterr().out
    ds = tvision.datasets().FlyingChairs(root=tmp_path, split="train")
    assert len(ds) == num and len(tvision.datasets().FlyingChairs(root=tmp_path, split="val")) == 0
    stream = BouncingThings(small_config, outputs=["rgb", "flow_fw"])
    check_pairs(ds, stream, 1, range(num))
    for i, flo in enumerate(sorted((tmp_path / "FlyingChairs" / "data").glob("*.flo"))):
        np.testing.assert_array_equal(cv2.readOpticalFlow(str(flo)).transpose(2, 0, 1),
                                      stream.sample(i)["flow_fw"][0].numpy())


def test_every_frame_pair_is_a_sample(tmp_path, small_config):
    """num_frames 6 and 2 samples: 10 pairs, the 10th in the val split, nothing dropped."""
    cfg = dataclasses.replace(small_config, num_frames=6)
    export_dataset(cfg, tmp_path, 2, layout="flyingchairs", progress=False)
    assert len(list((tmp_path / "FlyingChairs" / "data").glob("*_flow.flo"))) == 10
    train = tvision.datasets().FlyingChairs(root=tmp_path, split="train")
    val = tvision.datasets().FlyingChairs(root=tmp_path, split="val")
    assert len(train) == 9 and len(val) == 1
    stream = BouncingThings(cfg, outputs=["rgb", "flow_fw"])
    check_pairs(train, stream, 5, range(9))
    check_pairs(val, stream, 5, [9])  # pair 10 = frames 4, 5 of sample 1
