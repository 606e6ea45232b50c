"""``--layout flyingthings3d`` (FlyingThings3D "subset" tree) read back by OpenCV, an independent PFM/.flo/PNG
reader: disparity, disparity change and flow exact to float32, masks exact, images to 8 bits."""

import dataclasses

import cv2
import numpy as np
import pytest

import flowsynth as fs
from flowsynth.datasets import BouncingThings, Exported
from flowsynth.export import export_dataset

ROOT = "FlyingThings3D_subset/train"


def test_opencv_reads_export(tmp_path, layout_config):
    CFG = dataclasses.replace(layout_config, stereo_baseline=0.25)
    export_dataset(CFG, tmp_path, 2, layout="flyingthings3d", progress=False)
    stream = BouncingThings(CFG, outputs=list(fs.io.layouts.get("flyingthings3d").default_outputs))
    T = CFG.num_frames
    for i in range(2):
        s = stream.sample(i)
        assert s["disparity"].max() > 1.0 and s["disparity_occ"].any()
        for t in range(T):
            n = i * T + t
            for key, sub in (("disparity", "disparity/left"), ("disparity_right", "disparity/right")):
                d = cv2.imread(str(tmp_path / f"{ROOT}/{sub}/{n:07d}.pfm"), cv2.IMREAD_UNCHANGED)
                np.testing.assert_array_equal(d, s[key][t, 0].numpy())
            for key, sub in (("disparity_occ", "disparity_occlusions/left"),
                             ("disparity_occ_right", "disparity_occlusions/right")):
                m = cv2.imread(str(tmp_path / f"{ROOT}/{sub}/{n:07d}.png"), cv2.IMREAD_UNCHANGED)
                np.testing.assert_array_equal(m, s[key][t, 0].numpy().astype(np.uint8) * 255)
            for key, sub in (("rgb", "image_clean/left"), ("rgb_right", "image_clean/right")):
                img = cv2.imread(str(tmp_path / f"{ROOT}/{sub}/{n:07d}.png"))[..., ::-1] / 255.0
                assert np.abs(img - s[key][t].permute(1, 2, 0).numpy()).max() <= 0.5 / 255 + 1e-6
        for t in range(T - 1):
            dc = cv2.imread(str(tmp_path / f"{ROOT}/disparity_change/left/into_future/{i * T + t:07d}.pfm"),
                            cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(dc, s["disparity_change"][t, 0].numpy())
            fw = cv2.readOpticalFlow(str(tmp_path / f"{ROOT}/flow/left/into_future/{i * T + t:07d}.flo"))
            np.testing.assert_array_equal(fw.transpose(2, 0, 1), s["flow_fw"][t].numpy())
            bw = cv2.readOpticalFlow(str(tmp_path / f"{ROOT}/flow/left/into_past/{i * T + t + 1:07d}.flo"))
            np.testing.assert_array_equal(bw.transpose(2, 0, 1), s["flow_bw"][t].numpy())
    back, s = Exported(tmp_path, verify=True)[1], stream.sample(1)
    for k, v in back.items():
        if k.startswith("rgb"):
            assert (v - s[k]).abs().max() <= 0.5 / 255 + 1e-6
        elif k in s:
            assert v.dtype == s[k].dtype and np.array_equal(v.numpy(), s[k].numpy()), k


def test_needs_a_right_camera(tmp_path):
    cfg = fs.BouncingThingsConfig(width=48, height=32, num_frames=2, motion="kinematic", num_objects=(1, 2))
    with pytest.raises(fs.ConfigError, match="stereo"):
        export_dataset(cfg, tmp_path, 1, layout="flyingthings3d", progress=False)
