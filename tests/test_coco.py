"""The native export's COCO file, read and evaluated by pycocotools (a second library): one file for the dataset,
category names from the assets, boxes in COCO's pixel-edge convention, and a resume that gives the same file."""

from __future__ import annotations

import json

import numpy as np
import pycocotools.coco as coco_api
import pycocotools.cocoeval as cocoeval
import pycocotools.mask as mask_utils
import pytest

import flowsynth as fs
from flowsynth.datasets import Exported
from flowsynth.export import export_dataset
from flowsynth.scene import OBJECT_CATEGORY_OFFSET, resolve_assets


CFG = fs.BouncingThingsConfig(width=64, height=48, num_frames=2, motion="kinematic", num_objects=(3, 5),
                              max_objects=5)
NUM = 3


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    return export_dataset(CFG, tmp_path_factory.mktemp("coco") / "ds", NUM, seed=1, progress=False)


def _evaluate(gt, dets: list[dict]) -> np.ndarray:
    """COCOeval's 12 summary numbers of ``dets`` against ``gt`` (stats[0]: AP over IoU 0.5:0.95, stats[1]: AP50)."""
    ev = cocoeval.COCOeval(gt, gt.loadRes(dets), "bbox")
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    return ev.stats


def test_one_file_named_categories_and_pixel_edge_boxes(export):
    """One boxes_coco.json at the root (none in the sample folders) with an image per (sample, frame); category
    names are the config's assets (category OBJECT_CATEGORY_OFFSET + a is asset a); every box is what pycocotools
    gives for the object's mask in the exported instance map (COCO's [x, y, w, h], the image's left edge at x = 0),
    and its visible_pixels is the mask's area."""
    assert not list(export.glob("0*/boxes_coco.json"))
    gt = coco_api.COCO(str(export / "boxes_coco.json"))
    assets = dict(enumerate(resolve_assets(CFG.assets), OBJECT_CATEGORY_OFFSET))
    cats = gt.loadCats(gt.getCatIds())
    assert cats and all(c["name"] == assets[c["id"]] for c in cats)
    assert len(gt.getImgIds()) == NUM * CFG.num_frames
    ex = Exported(export)
    anns = gt.loadAnns(gt.getAnnIds())
    assert len(anns) >= NUM
    for ann in anns:
        img = gt.loadImgs(ann["image_id"])[0]
        assert (img["width"], img["height"]) == (CFG.width, CFG.height)
        instance = ex[img["sample"]]["instance"][img["frame"], 0].numpy()
        rle = mask_utils.encode(np.asfortranarray(instance == ann["instance_id"], dtype=np.uint8))
        assert ann["bbox"] == mask_utils.toBbox(rle).tolist(), ann
        assert ann["visible_pixels"] == int(mask_utils.area(rle)) and ann["area"] == ann["bbox"][2] * ann["bbox"][3]
        x, y, w, h = ann["bbox"]
        assert 0 <= x and x + w <= CFG.width and 0 <= y and y + h <= CFG.height


def test_cocoeval_of_the_truth_and_of_shifted_boxes(export):
    """The ground truth as its own detections has AP 1; boxes shifted right by a tenth of their width overlap
    their truth by IoU (0.9 w h) / (1.1 w h) = 9/11 (pycocotools' iou agrees), so they count at the IoU thresholds
    0.5 .. 0.8 and miss at 0.85 .. 0.95: AP = 7/10, AP50 = 1; shifted by half their width, IoU 1/3: AP 0."""
    gt = coco_api.COCO(str(export / "boxes_coco.json"))
    anns = gt.loadAnns(gt.getAnnIds())

    def dets(shift: float) -> list[dict]:
        return [{"image_id": a["image_id"], "category_id": a["category_id"], "score": 1.0,
                 "bbox": [a["bbox"][0] + shift * a["bbox"][2], *a["bbox"][1:]]} for a in anns]

    assert _evaluate(gt, dets(0.0))[:2] == pytest.approx([1.0, 1.0])
    shifted = dets(0.1)
    iou = mask_utils.iou([d["bbox"] for d in shifted], [a["bbox"] for a in anns], [0] * len(anns))
    np.testing.assert_allclose(np.diag(iou), 9 / 11, rtol=1e-9)
    assert _evaluate(gt, shifted)[:2] == pytest.approx([0.7, 1.0])
    assert _evaluate(gt, dets(0.5))[:2] == pytest.approx([0.0, 0.0])


def test_a_resume_writes_the_file_of_the_whole_export(export, tmp_path):
    """An export of 2 samples resumed to NUM writes the COCO file that an export of NUM in one run writes, byte for
    byte, and the manifest records it."""
    root = export_dataset(CFG, tmp_path / "ds", 2, seed=1, progress=False)
    assert len(json.loads((root / "boxes_coco.json").read_text())["images"]) == 2 * CFG.num_frames
    export_dataset(CFG, root, NUM, seed=1, progress=False)
    assert (root / "boxes_coco.json").read_bytes() == (export / "boxes_coco.json").read_bytes()
    assert "boxes_coco.json" in json.loads((root / "manifest.json").read_text())["index"]
