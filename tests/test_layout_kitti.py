"""``--layout kitti`` read by torchvision.datasets.KittiFlow (flow within KITTI's 1/64 px steps) and OpenCV."""

import cv2
import numpy as np
import torch
import tvision

from flowsynth.datasets import BouncingThings, Exported
from flowsynth.export import export_dataset
from flowsynth.io import layouts

HALF_STEP = 0.5 / 64  # the writer rounds to the nearest 1/64 px


def test_torchvision_reads_export(tmp_path, layout_config):
    export_dataset(layout_config, tmp_path, 2, layout="kitti", progress=False)
    ds = tvision.datasets().KittiFlow(root=tmp_path, split="train")
    assert len(ds) == 4  # 2 samples x 2 frame pairs
    stream = BouncingThings(layout_config, outputs=["rgb", "flow_fw", "valid_fw", "occ_fw"])
    occluded = 0
    for k in range(4):
        img1, img2, flow, valid = ds[k]
        s, t = stream.sample(k // 2), k % 2
        ref_valid = s["valid_fw"][t, 0].numpy()
        np.testing.assert_array_equal(valid, ref_valid)  # flow_occ: occluded pixels count as valid
        assert np.abs(flow - s["flow_fw"][t].numpy())[:, valid].max() <= HALF_STEP + 1e-6
        for img, frame in ((img1, t), (img2, t + 1)):
            a = np.asarray(img).astype(np.float32) / 255
            assert np.abs(a - s["rgb"][frame].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6
        # flow_noc, read by OpenCV (B, G, R = valid, v, u): valid and visible in the next frame
        noc = cv2.imread(str(tmp_path / f"KittiFlow/training/flow_noc/{k:06d}_10.png"), cv2.IMREAD_UNCHANGED)
        occ = s["occ_fw"][t, 0].numpy()
        np.testing.assert_array_equal(noc[..., 0] > 0, ref_valid & ~occ)
        occluded += int((ref_valid & occ).sum())
    assert occluded > 0, "no occluded pixel: the flow_occ / flow_noc distinction went untested"
    back = Exported(tmp_path, verify=True)[1]
    s = stream.sample(1)
    assert torch.equal(back["valid_fw"], s["valid_fw"])
    assert (back["flow_fw"] - s["flow_fw"]).abs().max() <= HALF_STEP + 1e-6


def test_out_of_range_flow_is_invalid_not_clipped(tmp_path):
    h, w = 4, 5
    flow = torch.zeros(1, 2, h, w)
    flow[0, 0, 1, 2] = 600.0  # beyond KITTI's +-512 px
    flow[0, 1, 2, 3] = -513.0
    sample = {"rgb": torch.rand(2, 3, h, w), "flow_fw": flow, "valid_fw": torch.ones(1, 1, h, w, dtype=torch.bool)}
    files = layouts.get("kitti").write(sample, 0, tmp_path)
    assert sorted(files.values()) == ["flow_fw", "rgb", "rgb"]
    bgr = cv2.imread(str(tmp_path / "KittiFlow/training/flow_occ/000000_10.png"), cv2.IMREAD_UNCHANGED)
    expected = np.ones((h, w), bool)
    expected[1, 2] = expected[2, 3] = False
    np.testing.assert_array_equal(bgr[..., 0] > 0, expected)
