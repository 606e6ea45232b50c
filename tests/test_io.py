"""File formats: round trips against our own readers and against independent ones (OpenCV, OpenEXR,
Pillow), atomic writes, and error paths."""

from __future__ import annotations

import fcntl
import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import pytest
import torch
from PIL import Image

from flowsynth.errors import ExportError, ShapeError
from flowsynth.io.atomic import atomic_path, atomic_write_bytes
from flowsynth.io.exr import CHANNEL_NAMES, COMPRESSIONS, read_exr, read_tensor_exr, write_exr, write_tensor_exr
from flowsynth.io.flo import read_flo, read_middlebury, write_flo
from flowsynth.io.jsonio import coco_boxes, read_json, write_json
from flowsynth.io.kitti import KITTI_FLOW_MAX, KITTI_FLOW_MIN, read_kitti_flow, write_kitti_flow
from flowsynth.io.png import (
    decode_png,
    read_ppm,
    read_rgb_png,
    read_u16_png,
    write_ppm,
    write_rgb_png,
    write_u16_png,
)

H, W = 7, 11


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


def _special_floats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Random float32 with awkward values mixed in: -0, denormals, huge, inf."""
    a = (rng.standard_normal(shape) * 100).astype(np.float32)
    flat = a.reshape(-1)
    flat[:6] = [-0.0, 1e-45, -3e-39, 3.4e38, np.inf, -np.inf]
    return a


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


# ---------------------------------------------------------------- EXR


@pytest.mark.parametrize("output", sorted(CHANNEL_NAMES))
def test_exr_tensor_round_trip_bit_exact(tmp_path: Path, rng: np.random.Generator, output: str) -> None:
    names = CHANNEL_NAMES[output]
    a = _special_floats(rng, (len(names), H, W))
    path = tmp_path / f"{output}.exr"
    write_tensor_exr(path, a, names)
    back = read_tensor_exr(path, names)
    assert back.shape == a.shape and back.dtype == np.float32
    np.testing.assert_array_equal(_bits(back), _bits(a))
    # Independent reader: the OpenEXR library directly, default (grouping) mode.
    exr = OpenEXR.File(str(path))
    channels = exr.channels()
    assert sorted(channels) == sorted(names)
    for c, name in enumerate(names):
        np.testing.assert_array_equal(_bits(channels[name].pixels), _bits(a[c]))
    assert exr.header()["compression"] == OpenEXR.ZIP_COMPRESSION


@pytest.mark.parametrize("compression", sorted(COMPRESSIONS))
def test_exr_every_compression_bit_exact_and_readable(tmp_path: Path, rng: np.random.Generator,
                                                      compression: str) -> None:
    """Each offered compression is lossless: the OpenEXR library reads it back bit for bit, and the header
    names the compression asked for."""
    a = _special_floats(rng, (2, 40, 56))
    a[:, 10:30, 20:50] = 0.0  # a run the compressors do shrink
    path = tmp_path / f"{compression}.exr"
    write_tensor_exr(path, a, CHANNEL_NAMES["flow"], compression=compression)
    exr = OpenEXR.File(str(path), separate_channels=True)
    assert exr.header()["compression"] == COMPRESSIONS[compression]
    for c, name in enumerate(CHANNEL_NAMES["flow"]):
        np.testing.assert_array_equal(_bits(exr.channels()[name].pixels), _bits(a[c]))
    with pytest.raises(ValueError, match="compression"):
        write_tensor_exr(tmp_path / "x.exr", a, CHANNEL_NAMES["flow"], compression="dwaa")


def test_exr_nan_survives(tmp_path: Path) -> None:
    a = np.full((H, W), np.nan, np.float32)
    write_exr(tmp_path / "n.exr", {"Z": a})
    assert np.isnan(read_exr(tmp_path / "n.exr")["Z"]).all()


def test_exr_non_contiguous_and_caller_dict(tmp_path: Path, rng: np.random.Generator) -> None:
    wide = rng.random((H, 2 * W), dtype=np.float32)
    tall = rng.random((W, H), dtype=np.float32)
    channels = {"flow.x": wide[:, ::2], "flow.y": tall.T}
    assert not channels["flow.x"].flags.c_contiguous and not channels["flow.y"].flags.c_contiguous
    write_exr(tmp_path / "f.exr", channels)
    assert isinstance(channels["flow.x"], np.ndarray)  # OpenEXR.File would swap in Channel objects
    back = OpenEXR.File(str(tmp_path / "f.exr"), separate_channels=True).channels()
    np.testing.assert_array_equal(back["flow.x"].pixels, wide[:, ::2])
    np.testing.assert_array_equal(back["flow.y"].pixels, tall.T)
    # A channels-first tensor slice (non-contiguous planes of a torch tensor) too.
    t = torch.from_numpy(rng.random((H, W, 3), dtype=np.float32)).permute(2, 0, 1)
    write_tensor_exr(tmp_path / "n.exr", t, CHANNEL_NAMES["normals"])
    np.testing.assert_array_equal(read_tensor_exr(tmp_path / "n.exr", CHANNEL_NAMES["normals"]), t.numpy())


def test_exr_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ShapeError, match="2-D"):
        write_exr(tmp_path / "x.exr", {"flow": np.zeros((H, W, 2), np.float32)})
    with pytest.raises(ShapeError, match="shape"):
        write_exr(tmp_path / "x.exr", {"A": np.zeros((H, W), np.float32), "B": np.zeros((W, H), np.float32)})
    with pytest.raises(ShapeError, match="dtype"):
        write_exr(tmp_path / "x.exr", {"A": np.zeros((H, W), np.int64)})
    write_exr(tmp_path / "x.exr", {"Z": np.zeros((H, W), np.float32)})
    with pytest.raises(ExportError, match="no channel"):
        read_tensor_exr(tmp_path / "x.exr", CHANNEL_NAMES["flow"])
    assert not list(tmp_path.glob(".*"))


# ---------------------------------------------------------------- .flo


def test_flo_round_trip_and_opencv(tmp_path: Path, rng: np.random.Generator) -> None:
    flow = _special_floats(rng, (2, H, W))
    path = tmp_path / "a.flo"
    write_flo(path, flow)
    assert path.stat().st_size == 12 + 8 * H * W
    back = read_flo(path)
    assert back.shape == (2, H, W) and back.dtype == np.float32
    np.testing.assert_array_equal(_bits(back), _bits(flow))
    theirs = cv2.readOpticalFlow(str(path))  # (H, W, 2): u, v
    np.testing.assert_array_equal(_bits(theirs), _bits(flow.transpose(1, 2, 0)))
    # And the other way: OpenCV writes, we read.
    cv2.writeOpticalFlow(str(tmp_path / "cv.flo"), np.ascontiguousarray(flow.transpose(1, 2, 0)))
    np.testing.assert_array_equal(_bits(read_flo(tmp_path / "cv.flo")), _bits(flow))


def test_read_middlebury_layout(tmp_path: Path, rng: np.random.Generator) -> None:
    # frames written by OpenCV, flow by cv2.writeOpticalFlow: the oracle is the other library's writers
    pairs = {}
    for name in ("Venus", "Army"):
        d = tmp_path / name
        d.mkdir()
        f1, f2 = (rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(2))
        flow = rng.normal(0, 3, (H, W, 2)).astype(np.float32)
        flow[0, :3] = 1e10  # Middlebury's "unknown"
        cv2.imwrite(str(d / "frame10.png"), f1[..., ::-1])
        cv2.imwrite(str(d / "frame11.png"), f2[..., ::-1])
        cv2.writeOpticalFlow(str(d / "flow10.flo"), flow)
        pairs[name] = (f1, f2, flow)
    (tmp_path / "NoFlow").mkdir()
    (tmp_path / "NoFlow" / "frame10.png").write_bytes((tmp_path / "Venus" / "frame10.png").read_bytes())
    (tmp_path / "README.md").write_text("not a pair")
    got = read_middlebury(tmp_path)
    assert [g[0] for g in got] == ["Army", "Venus"]
    for name, img1, img2, flow, known in got:
        f1, f2, truth = pairs[name]
        np.testing.assert_array_equal(img1, f1.transpose(2, 0, 1).astype(np.float32) / 255)
        np.testing.assert_array_equal(img2, f2.transpose(2, 0, 1).astype(np.float32) / 255)
        assert known.dtype == bool and not known[0, :3].any() and known.sum() == H * W - 3
        np.testing.assert_array_equal(flow[:, known], truth.transpose(2, 0, 1)[:, known])
        assert not flow[:, ~known].any()
    assert [g[0] for g in read_middlebury(tmp_path, ("Venus", "Grove2"))] == ["Venus"]
    with pytest.raises(FileNotFoundError):
        read_middlebury(tmp_path / "missing")


def test_flo_non_contiguous(tmp_path: Path, rng: np.random.Generator) -> None:
    hw2 = rng.standard_normal((H, W, 2)).astype(np.float32)
    flow = hw2.transpose(2, 0, 1)  # a view, not C-contiguous
    write_flo(tmp_path / "a.flo", flow)
    np.testing.assert_array_equal(read_flo(tmp_path / "a.flo"), flow)


def test_flo_rejects_bad_files(tmp_path: Path) -> None:
    write_flo(tmp_path / "a.flo", np.zeros((2, H, W), np.float32))
    data = (tmp_path / "a.flo").read_bytes()
    (tmp_path / "magic.flo").write_bytes(struct.pack("<f", 1.0) + data[4:])
    with pytest.raises(ExportError, match="magic"):
        read_flo(tmp_path / "magic.flo")
    (tmp_path / "short.flo").write_bytes(data[:-4])
    with pytest.raises(ExportError, match="bytes"):
        read_flo(tmp_path / "short.flo")
    with pytest.raises(ShapeError):
        write_flo(tmp_path / "b.flo", np.zeros((H, W, 2), np.float32))


# ---------------------------------------------------------------- KITTI


def test_kitti_round_trip_and_opencv(tmp_path: Path, rng: np.random.Generator) -> None:
    flow = (rng.standard_normal((2, H, W)) * 50).astype(np.float32)
    flow[0, 0, 0], flow[1, 0, 1], flow[0, 0, 2] = 600.0, -700.0, np.nan
    valid = rng.random((H, W)) > 0.2
    valid[0, :3] = True
    path = tmp_path / "k.png"
    write_kitti_flow(path, flow, valid)
    back, back_valid = read_kitti_flow(path)
    expected_valid = valid & np.isfinite(flow).all(axis=0)
    np.testing.assert_array_equal(back_valid, expected_valid)
    clipped = np.clip(flow, KITTI_FLOW_MIN, KITTI_FLOW_MAX)
    m = expected_valid
    assert np.abs(back[:, m] - clipped[:, m]).max() <= 1 / 128 + 1e-6
    assert back[0, 0, 0] == KITTI_FLOW_MAX and back[1, 0, 1] == KITTI_FLOW_MIN
    assert (back[:, ~m] == 0).all()
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert bgr.dtype == np.uint16 and bgr.shape == (H, W, 3)
    np.testing.assert_array_equal(bgr[..., 0], expected_valid)
    u = (bgr[..., 2].astype(np.float64) - 2**15) / 64
    v = (bgr[..., 1].astype(np.float64) - 2**15) / 64
    np.testing.assert_allclose(u[m], clipped[0][m], atol=1 / 128 + 1e-6)
    np.testing.assert_allclose(v[m], clipped[1][m], atol=1 / 128 + 1e-6)
    # OpenCV (libpng, adaptive row filters) writes a KITTI file; our decoder reads it.
    cv2.imwrite(str(tmp_path / "cv.png"), bgr)
    back2, valid2 = read_kitti_flow(tmp_path / "cv.png")
    np.testing.assert_array_equal(back2, back)
    np.testing.assert_array_equal(valid2, back_valid)


def _filtered_png(image: np.ndarray, ftype: int) -> bytes:
    """Reference PNG encoder (8-bit RGB) applying one filter type to every row (PNG spec 9.2)."""
    h, w, _ = image.shape
    rows = image.reshape(h, -1).astype(np.int64)
    bpp, raw = 3, b""
    for y in range(h):
        line, prior = rows[y], rows[y - 1] if y else np.zeros_like(rows[0])
        left = np.concatenate([np.zeros(bpp, np.int64), line[:-bpp]])
        upleft = np.concatenate([np.zeros(bpp, np.int64), prior[:-bpp]])
        if ftype == 1:
            pred = left
        elif ftype == 2:
            pred = prior
        elif ftype == 3:
            pred = (left + prior) // 2
        else:
            p = left + prior - upleft
            pa, pb, pc = np.abs(p - left), np.abs(p - prior), np.abs(p - upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, prior, upleft))
        raw += bytes([ftype]) + ((line - pred) % 256).astype(np.uint8).tobytes()

    def chunk(tag: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + tag + payload + struct.pack(">I", zlib.crc32(tag + payload))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )


@pytest.mark.parametrize("ftype", [1, 2, 3, 4])
def test_png_decoder_every_filter(rng: np.random.Generator, ftype: int) -> None:
    image = rng.integers(0, 256, (5, 6, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_png(_filtered_png(image, ftype)), image)



def _filter_types(data: bytes, h: int) -> set[int]:
    """The filter-type bytes of a PNG's rows, read from its IDAT chunks."""
    pos, idat = 8, b""
    while pos < len(data):
        length, tag = struct.unpack(">I4s", data[pos : pos + 8])
        idat += data[pos + 8 : pos + 8 + length] if tag == b"IDAT" else b""
        pos += 12 + length
    raw = zlib.decompress(idat)
    return set(raw[:: len(raw) // h])


_CV_FILTERS = {0: cv2.IMWRITE_PNG_FILTER_NONE, 1: cv2.IMWRITE_PNG_FILTER_SUB, 2: cv2.IMWRITE_PNG_FILTER_UP,
               3: cv2.IMWRITE_PNG_FILTER_AVG, 4: cv2.IMWRITE_PNG_FILTER_PAETH, "all": cv2.IMWRITE_PNG_ALL_FILTERS}


@pytest.mark.parametrize("filters", list(_CV_FILTERS))
def test_png_decoder_equals_opencv_on_kitti_sized_files(rng: np.random.Generator, filters) -> None:
    """A 1242x375 16-bit RGB PNG (a KITTI flow map's size and kind) written by OpenCV (libpng) with each filter
    type, and with libpng's adaptive choice among all five per row: decode_png returns OpenCV's values bit for bit.
    The file holds smooth flow-like channels plus noise, so the Paeth and average predictors meet every case."""
    h, w = 375, 1242
    yy, xx = np.mgrid[0:h, 0:w]
    rgb = np.stack([2**15 + 64 * (5 * np.sin(xx / 90) + 3 * yy / h), 2**15 + 64 * 2 * np.cos(yy / 40),
                    rng.random((h, w)) > 0.2], axis=-1).astype(np.uint16)
    rgb[..., :2] += rng.integers(0, 3, (h, w, 2), dtype=np.uint16)
    rgb[:4, :4] = [[0, 65535, 1]]  # extremes, where a predictor's sum wraps
    ok, buf = cv2.imencode(".png", rgb[..., ::-1].copy(), [cv2.IMWRITE_PNG_FILTER, _CV_FILTERS[filters]])
    data = buf.tobytes()
    used = _filter_types(data, h)
    expected = {2, 4} if filters == "all" else {filters}  # libpng picks Paeth for most rows here, up for others
    assert used >= expected if filters == "all" else used == expected
    theirs = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)[..., ::-1]
    ours = decode_png(data)
    assert ours.dtype == np.uint16 and ours.shape == (h, w, 3)
    np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("channels", [1, 4])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_decoder_equals_opencv_grey_and_rgba(rng: np.random.Generator, channels: int, dtype) -> None:
    """Greyscale and RGBA, 8 and 16 bits, random values, libpng's adaptive filters: OpenCV's values bit for bit."""
    image = rng.integers(0, np.iinfo(dtype).max + 1, (23, 31, channels)[: 2 if channels == 1 else 3], dtype=dtype)
    for flag in (cv2.IMWRITE_PNG_FILTER_PAETH, cv2.IMWRITE_PNG_FILTER_AVG, cv2.IMWRITE_PNG_ALL_FILTERS):
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_FILTER, flag])
        theirs = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)  # B, G, R, A: reorder to the file's R, G, B, A
        theirs = theirs if channels == 1 else theirs[..., [2, 1, 0, 3]]
        np.testing.assert_array_equal(decode_png(buf.tobytes()), theirs)


# ---------------------------------------------------------------- PNG / PPM


def test_u16_png_round_trip_and_opencv(tmp_path: Path, rng: np.random.Generator) -> None:
    ids = rng.integers(0, 65536, (H, W)).astype(np.int32)
    ids[0, 0], ids[0, 1] = 0, 65535
    path = tmp_path / "ids.png"
    write_u16_png(path, torch.from_numpy(ids))
    back = read_u16_png(path)
    assert back.dtype == np.int32
    np.testing.assert_array_equal(back, ids)
    theirs = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert theirs.dtype == np.uint16 and theirs.shape == (H, W)
    np.testing.assert_array_equal(theirs, ids)
    mask = ids > 30000
    write_u16_png(tmp_path / "mask.png", mask[:, ::-1])
    np.testing.assert_array_equal(read_u16_png(tmp_path / "mask.png"), mask[:, ::-1])


def test_u16_png_rejects_out_of_range(tmp_path: Path) -> None:
    for bad in (np.array([[65536]]), np.array([[-1]])):
        with pytest.raises(ExportError, match="65535"):
            write_u16_png(tmp_path / "x.png", bad)
    with pytest.raises(ShapeError):
        write_u16_png(tmp_path / "x.png", np.zeros((H, W), np.float32))
    assert not list(tmp_path.iterdir())


def test_rgb_png_and_ppm_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    rgb = rng.random((3, H, W), dtype=np.float32)
    rgb[:, 0, 0] = [0.6 / 255, 0.4 / 255, 1.0]  # round, not truncate: 1, 0, 255
    view = rgb[:, :, ::-1]  # non-contiguous
    for name, write, read in (("a.png", write_rgb_png, read_rgb_png), ("a.ppm", write_ppm, read_ppm)):
        write(tmp_path / name, view)
        back = read(tmp_path / name)
        assert back.shape == (3, H, W) and back.dtype == np.float32
        assert np.abs(back - view).max() <= 0.5 / 255 + 1e-6
        with Image.open(tmp_path / name) as im:  # independent reader
            assert im.mode == "RGB" and im.size == (W, H)
            pixels = np.asarray(im)
        np.testing.assert_array_equal(pixels[0, -1], [1, 0, 255])
        np.testing.assert_array_equal(pixels, np.rint(view.transpose(1, 2, 0) * 255))
    assert (tmp_path / "a.ppm").read_bytes()[:2] == b"P6"


# ---------------------------------------------------------------- JSON and COCO


def test_json_round_trip_and_rejects_nan(tmp_path: Path) -> None:
    obj = {
        "K": np.eye(3, dtype=np.float32),
        "poses": torch.zeros(2, 4, 4),
        "seed": np.int64(7),
        "flag": np.bool_(True),
        1: (1.5, "a", None),
        "path": tmp_path,
    }
    write_json(tmp_path / "m.json", obj)
    back = read_json(tmp_path / "m.json")
    assert back["K"] == np.eye(3).tolist() and back["poses"] == torch.zeros(2, 4, 4).tolist()
    assert back["seed"] == 7 and back["flag"] is True and back["1"] == [1.5, "a", None]
    assert back["path"] == str(tmp_path)
    for bad in ({"a": [1.0, float("nan")]}, {"K": np.array([1.0, np.inf])}, {"t": torch.tensor([np.nan])}):
        with pytest.raises(ExportError, match="non-finite"):
            write_json(tmp_path / "bad.json", bad)
    assert not (tmp_path / "bad.json").exists()
    (tmp_path / "nan.json").write_text('{"a": NaN}')
    with pytest.raises(ExportError):
        read_json(tmp_path / "nan.json")


def test_coco_boxes_hand_computed() -> None:
    # T = 2 frames, N = 3 slots: object 0 visible in both, object 1 only in frame 1, slot 2 padding. Boxes in
    # flowsynth's pixel-centre coordinates (pixels j0..j1 span j0 - 1/2 .. j1 + 1/2); COCO's start at the pixel edge
    # x = j0: object 0 in frame 0 covers columns 1..4 and rows 2..3, COCO [1, 2, 4, 2].
    boxes = np.array(
        [
            [[0.5, 1.5, 4.5, 3.5], [0.0, 0.0, 0.0, 0.0], [np.nan] * 4],
            [[1.5, 1.5, 5.5, 4.5], [2.5, 0.5, 3.5, 8.5], [np.nan] * 4],
        ]
    )
    coco = coco_boxes(
        torch.from_numpy(boxes),
        np.array([True, True, False]),
        np.array([3, 1, 0]),
        np.array([[12, 0, 0], [15, 4, 0]]),
        width=W,
        height=H,
        file_names=["rgb_0000.png", "rgb_0001.png"],
        category_names={1: "cube"},
    )
    assert coco["images"] == [
        {"id": 1, "file_name": "rgb_0000.png", "width": W, "height": H, "frame": 0},
        {"id": 2, "file_name": "rgb_0001.png", "width": W, "height": H, "frame": 1},
    ]
    common = {"iscrowd": 0}
    assert coco["annotations"] == [
        {"id": 1, "image_id": 1, "category_id": 3, "bbox": [1.0, 2.0, 4.0, 2.0], "area": 8.0,
         "instance_id": 1, "frame": 0, "visible_pixels": 12, **common},
        {"id": 2, "image_id": 2, "category_id": 3, "bbox": [2.0, 2.0, 4.0, 3.0], "area": 12.0,
         "instance_id": 1, "frame": 1, "visible_pixels": 15, **common},
        {"id": 3, "image_id": 2, "category_id": 1, "bbox": [3.0, 1.0, 1.0, 8.0], "area": 8.0,
         "instance_id": 2, "frame": 1, "visible_pixels": 4, **common},
    ]  # fmt: skip
    assert coco["categories"] == [
        {"id": 1, "name": "cube", "supercategory": "object"},
        {"id": 3, "name": "category_3", "supercategory": "object"},
    ]
    with pytest.raises(ShapeError):
        coco_boxes(
            boxes, np.ones(2, bool), np.ones(3), np.ones((2, 3)), width=W, height=H, file_names=["a", "b"]
        )


# ---------------------------------------------------------------- atomic writes and unwritable paths

_WRITERS = {
    "exr": lambda p: write_exr(p, {"Z": np.zeros((H, W), np.float32)}),
    "flo": lambda p: write_flo(p, np.zeros((2, H, W), np.float32)),
    "kitti": lambda p: write_kitti_flow(p, np.zeros((2, H, W), np.float32), np.ones((H, W), bool)),
    "png": lambda p: write_rgb_png(p, np.zeros((3, H, W), np.float32)),
    "ppm": lambda p: write_ppm(p, np.zeros((3, H, W), np.float32)),
    "u16": lambda p: write_u16_png(p, np.zeros((H, W), np.int32)),
    "json": lambda p: write_json(p, {"a": 1}),
}


@pytest.mark.parametrize("fmt", sorted(_WRITERS))
def test_writers_atomic_and_unwritable(tmp_path: Path, fmt: str) -> None:
    path = tmp_path / f"out.{fmt}"
    _WRITERS[fmt](path)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary left behind
    missing = tmp_path / "no" / "such" / "dir" / f"out.{fmt}"
    with pytest.raises(ExportError, match=str(missing)):
        _WRITERS[fmt](missing)
    with pytest.raises(ExportError):  # parent is a file
        _WRITERS[fmt](path / "child.bin")


# Linux ioctls of the file attribute flags (linux/fs.h): the immutable flag stops even root from creating files.
_FS_IOC_GETFLAGS, _FS_IOC_SETFLAGS, _FS_IMMUTABLE_FL = 0x80086601, 0x40086602, 0x10


def _set_immutable(path: Path, on: bool) -> None:
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        flags = struct.unpack("i", fcntl.ioctl(fd, _FS_IOC_GETFLAGS, struct.pack("i", 0)))[0]
        flags = flags | _FS_IMMUTABLE_FL if on else flags & ~_FS_IMMUTABLE_FL
        fcntl.ioctl(fd, _FS_IOC_SETFLAGS, struct.pack("i", flags))
    finally:
        os.close(fd)


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_read_only_directory(tmp_path: Path) -> None:
    # Root ignores the permission bits, so as root the directory is made immutable instead.
    if os.geteuid() == 0:
        try:
            _set_immutable(tmp_path, True)
        except OSError as e:
            pytest.skip(f"running as root and this filesystem has no immutable flag ({e})")
        undo = lambda: _set_immutable(tmp_path, False)
    else:
        tmp_path.chmod(0o500)
        undo = lambda: tmp_path.chmod(0o700)
    try:
        with pytest.raises(ExportError, match="not writable"):
            atomic_write_bytes(tmp_path / "x.bin", b"x")
    finally:
        undo()
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_temp_name_failure_and_permissions(tmp_path: Path) -> None:
    final = tmp_path / "depth_0003.exr"
    final.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(final) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".depth_0003.tmp-") and tmp.suffix == ".exr"
        tmp.write_bytes(b"partial")
        raise RuntimeError("crash mid-write")
    assert final.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == [final.name]
    atomic_write_bytes(final, b"new")
    assert final.read_bytes() == b"new"
    umask = os.umask(0)
    os.umask(umask)
    assert final.stat().st_mode & 0o777 == 0o666 & ~umask


def test_exr_write_failure_from_the_file_system_is_a_storage_error(tmp_path: Path, monkeypatch) -> None:
    # OpenEXR reports a full disk as a RuntimeError carrying the OS text (seen on a full tmpfs);
    # that is an I/O failure (CLI exit 3), not bad input, and no temporary file stays behind.
    import errno
    import types

    import flowsynth.io.exr as exr_mod
    from flowsynth.errors import StorageError

    class FullDisk:
        def __init__(self, *args):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *args):
            return False

        def write(self, name):
            raise RuntimeError(f'Failed to write pixel data to image file "{name}". No space left on device.')

    fake = types.SimpleNamespace(File=FullDisk, scanlineimage=OpenEXR.scanlineimage)
    monkeypatch.setattr(exr_mod, "OpenEXR", fake)
    with pytest.raises(StorageError) as info:
        write_exr(tmp_path / "a.exr", {"Z": np.zeros((4, 5), np.float32)})
    assert info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []
