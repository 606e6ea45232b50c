"""``--layout sintel`` read by torchvision.datasets.Sintel (flow exact to float32) and OpenCV."""

from pathlib import Path

import cv2
import numpy as np
import torch
import tvision

import flowsynth as fs
from flowsynth.datasets import BouncingThings, Exported
from flowsynth.export import export_dataset

CFG = fs.BouncingThingsConfig(width=48, height=32, num_frames=3, motion="kinematic", num_objects=(3, 4),
                              max_objects=4, min_speed=2.0, max_speed=3.0)


def test_torchvision_reads_export(tmp_path):
    export_dataset(CFG, tmp_path, 2, layout="sintel", progress=False)
    ds = tvision.datasets().Sintel(root=tmp_path, split="train", pass_name="clean")
    assert len(ds) == 4  # 2 scenes x 2 frame pairs
    stream = BouncingThings(CFG, outputs=["rgb", "flow_fw", "occ_fw"])
    occluded = 0
    for k in range(4):
        img1, img2, flow = ds[k]
        # Sintel lists scenes in os.listdir order: find which scene and frame pair ds[k] is
        first = Path(ds._image_list[k][0])
        i, t = int(first.parent.name.removeprefix("scene_")), int(first.stem.removeprefix("frame_")) - 1
        s = stream.sample(i)
        np.testing.assert_array_equal(flow, s["flow_fw"][t].numpy())
        np.testing.assert_array_equal(cv2.readOpticalFlow(ds._flow_list[k]).transpose(2, 0, 1), s["flow_fw"][t].numpy())
        for img, frame in ((img1, t), (img2, t + 1)):
            a = np.asarray(img).astype(np.float32) / 255
            assert np.abs(a - s["rgb"][frame].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6
        occ = cv2.imread(str(tmp_path / f"Sintel/training/occlusions/scene_{i:05d}/frame_{t + 1:04d}.png"),
                         cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(occ, s["occ_fw"][t, 0].numpy().astype(np.uint8) * 255)
        occluded += int(s["occ_fw"][t].sum())
    assert occluded > 0, "no occluded pixel: the occlusion maps went untested"
    back, s = Exported(tmp_path, verify=True)[0], stream.sample(0)
    assert torch.equal(back["flow_fw"], s["flow_fw"]) and torch.equal(back["occ_fw"], s["occ_fw"])


def test_torchvision_reads_final_pass(tmp_path):
    """With rgb_final among the outputs, final/ sits beside clean/: torchvision's pass_name="final" reads the
    final frames (8-bit of the stream's rgb_final) with the same flow as the clean pass; Exported reads both back."""
    outputs = ["rgb", "rgb_final", "flow_fw"]
    export_dataset(CFG, tmp_path, 1, layout="sintel", outputs=outputs, progress=False)
    tv = tvision.datasets()
    final = tv.Sintel(root=tmp_path, split="train", pass_name="final")
    clean = tv.Sintel(root=tmp_path, split="train", pass_name="clean")
    assert len(final) == len(clean) == 2
    s = BouncingThings(CFG, outputs=outputs).sample(0)
    assert not torch.equal(s["rgb_final"], s["rgb"])  # the passes differ (blur, noise, gains)
    for k in range(2):
        img1, img2, flow = final[k]
        t = int(Path(final._image_list[k][0]).stem.removeprefix("frame_")) - 1
        assert Path(final._image_list[k][0]).parent.parent.name == "final"
        np.testing.assert_array_equal(flow, s["flow_fw"][t].numpy())
        np.testing.assert_array_equal(flow, clean[k][2])
        for img, frame in ((img1, t), (img2, t + 1)):
            a = np.asarray(img).astype(np.float32) / 255
            assert np.abs(a - s["rgb_final"][frame].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6
    back = Exported(tmp_path, verify=True)[0]
    assert set(back) >= {"rgb", "rgb_final", "flow_fw"}
    assert torch.equal(back["flow_fw"], s["flow_fw"])
    assert (back["rgb_final"] - s["rgb_final"]).abs().max() <= 0.5 / 255 + 1e-6
