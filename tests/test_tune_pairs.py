"""flowsynth.tune.read_pairs: the four layouts detected and read, checked against torchvision's dataset classes reading
the same folders (readers nobody here wrote), and the named errors for folders that hold no usable pairs."""

import numpy as np
import pytest
import torch
import tvision

import flowsynth as fs
from flowsynth.io import layouts, write_flo, write_ppm, write_rgb_png
from flowsynth.tune import read_pairs

H, W = 24, 32


def _sample(seed: int, frames: int = 3) -> dict:
    g = torch.Generator().manual_seed(seed)
    valid = torch.rand(frames - 1, 1, H, W, generator=g) > 0.2
    return {"rgb": torch.rand(frames, 3, H, W, generator=g), "flow_fw": 20 * torch.randn(frames - 1, 2, H, W,
                                                                                           generator=g),
            "valid_fw": valid}


def _same_images(ours, theirs):
    for a, b in zip(ours, theirs):  # our images are the files' 8 bits
        assert a.dtype == torch.uint8
        np.testing.assert_array_equal(a[0].numpy(), np.asarray(b).transpose(2, 0, 1))


def test_flyingchairs_as_torchvision_reads_it(tmp_path):
    lay = layouts.get("flyingchairs")
    lay.write(_sample(0), 0, tmp_path)
    lay.finish(tmp_path, 1, fs.BouncingThingsConfig(num_frames=3))
    layout, pairs = read_pairs(tmp_path)  # the layout's root, FlyingChairs/data, is found two folders down
    theirs = tvision.datasets().FlyingChairs(root=tmp_path, split="train")
    assert layout == "flyingchairs" and list(pairs) == ["00001", "00002"] and len(theirs) == 2
    for (img1, img2, flow, valid), (t1, t2, tflow) in zip(pairs.values(), theirs):
        _same_images((img1, img2), (t1, t2))
        assert np.array_equal(flow[0].numpy(), tflow) and valid.all()


def test_kitti_as_torchvision_reads_it(tmp_path):
    layouts.get("kitti").write(_sample(1), 0, tmp_path)
    layout, pairs = read_pairs(tmp_path)
    theirs = tvision.datasets().KittiFlow(root=tmp_path, split="train")
    assert layout == "kitti" and list(pairs) == ["000000", "000001"] and len(theirs) == 2
    for (img1, img2, flow, valid), (t1, t2, tflow, tvalid) in zip(pairs.values(), theirs):
        _same_images((img1, img2), (t1, t2))
        np.testing.assert_array_equal(valid[0, 0].numpy(), tvalid)
        assert not valid.all() and (flow[0].numpy() == np.where(tvalid, tflow, 0)).all()


def test_sintel_as_torchvision_reads_it_with_globs(tmp_path):
    for i in range(2):
        layouts.get("sintel").write(_sample(2 + i), i, tmp_path)
    layout, pairs = read_pairs(tmp_path)
    theirs = tvision.datasets().Sintel(root=tmp_path, split="train", pass_name="clean")
    assert layout == "sintel" and len(pairs) == len(theirs) == 4
    assert list(pairs)[:2] == ["clean/scene_00000/frame_0001", "clean/scene_00000/frame_0002"]
    for k, (t1, t2, tflow) in enumerate(theirs):  # torchvision lists scenes in os.listdir's order: match by path
        path = theirs._image_list[k][0]
        img1, img2, flow, valid = pairs[f"clean/{path.split('/')[-2]}/{path.split('/')[-1][:-4]}"]
        _same_images((img1, img2), (t1, t2))
        assert np.array_equal(flow[0].numpy(), tflow) and valid.all()
    _, some = read_pairs(tmp_path, ["clean/scene_00001/*"])
    assert list(some) == ["clean/scene_00001/frame_0001", "clean/scene_00001/frame_0002"]


def test_unknown_flow_and_non_finite_values_are_invalid_and_zero(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    flow = np.ones((2, H, W), np.float32)
    flow[0, 1, 2], flow[1, 3, 4], flow[0, 5, 6] = np.nan, np.inf, 1e10  # Middlebury marks unknown flow by > 1e9
    write_flo(data / "a_flow.flo", flow)
    for k in (1, 2):
        write_ppm(data / f"a_img{k}.ppm", np.full((3, H, W), 0.5, np.float32))
    _, pairs = read_pairs(tmp_path)
    _, _, got, valid = pairs["a"]
    assert torch.isfinite(got).all() and int((~valid).sum()) == 3
    assert got[0, :, 1, 2].tolist() == [0, 0] and got[0, :, 0, 0].tolist() == [1, 1]


def _middlebury(root, name="Venus", h=H, w=W):
    (root / name).mkdir(parents=True)
    for k in (10, 11):
        write_rgb_png(root / name / f"frame{k}.png", np.zeros((3, h, w), np.float32))
    write_flo(root / name / "flow10.flo", np.zeros((2, H, W), np.float32))


@pytest.mark.parametrize("case, match", [
    ("empty", "no validation pairs found"),
    ("not a folder", "not a folder"),
    ("two layouts", "several layouts"),
    ("missing image", "frame11.png is missing"),
    ("sizes differ", "sizes differ"),
    ("unknown everywhere", "known at no pixel"),
    ("bad png", "cannot read its images"),
])
def test_unusable_folders_are_named_errors(tmp_path, case, match):
    root = tmp_path / "val"
    root.mkdir()
    if case == "not a folder":
        root = tmp_path / "nothing"
    elif case == "two layouts":
        _middlebury(root / "a")
        (root / "b").mkdir()
        write_flo(root / "b" / "x_flow.flo", np.zeros((2, H, W), np.float32))  # FlyingChairs' names
    elif case == "missing image":
        _middlebury(root)
        (root / "Venus" / "frame11.png").unlink()
    elif case == "sizes differ":
        _middlebury(root, h=H + 8)
    elif case == "unknown everywhere":
        _middlebury(root)
        write_flo(root / "Venus" / "flow10.flo", np.full((2, H, W), 2e9, np.float32))
    elif case == "bad png":
        _middlebury(root)
        (root / "Venus" / "frame10.png").write_bytes(b"not a png")
    with pytest.raises(fs.ConfigError, match=match):
        read_pairs(root)
