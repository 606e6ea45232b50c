"""One sample dict <-> one folder of standard files (the ``native`` export layout).

Per-frame keys are written one file per frame, per-pair keys one file per pair (index t = pair
(t, t+1)); everything that is not an image (cameras, object tables, index, seed, provenance) goes to
``meta.json``:

| key                                   | file                    | format                              |
|---------------------------------------|-------------------------|-------------------------------------|
| rgb, rgb_right, rgb_final             | KEY_TTTT.png            | 8-bit sRGB PNG                      |
| depth, distance, normals, position    | KEY_TTTT.exr            | float32 EXR (channels: io.exr)      |
| depth_right                           | KEY_TTTT.exr            | float32 EXR, channel Z              |
| disparity, disparity_right,           | KEY_TTTT.exr            | float32 EXR, channel disparity      |
| disparity_change                      |                         |                                     |
| flow_fw, flow_bw                      | KEY_TTTT.exr            | float32 EXR, channels flow.x/flow.y |
| scene_flow_fw, scene_flow_bw          | KEY_TTTT.exr            | float32 EXR, channels SF.X/Y/Z      |
| instance, category, asset             | KEY_TTTT.png            | 16-bit greyscale PNG                |
| valid_*, occ_*, oof_*, motion,        | KEY_TTTT.png            | 16-bit greyscale PNG, 0/1           |
| disparity_occ, disparity_occ_right    |                         |                                     |
| any of these per-pair keys at gap K   | KEY_kK_TTTT.*           | as the key at gap 1 (TTTT = pair t) |
| K, cam_T_world, object tables, index, | meta.json               | JSON (float32 values, exact)        |
| seed, source (a mixture's)            |                         |                                     |
| provenance                            | meta.json               | JSON object (Scene.from_meta reads) |
| a lens camera's model, coefficients  | meta.json               | camera_model, camera_dist (OpenCV)  |
| target_points, occluded, query_points | tracks.npz              | numpy .npz, the tensors as they are |
| all three track keys (when requested) | tapvid.pkl              | TAP-Vid (Kubric) dict, see below    |

``tapvid.pkl`` is what TAP-Vid loaders read: a pickled dict of numpy arrays with TAP-Vid's Kubric keys,
``query_points`` (Q, 3) float32 (t, y, x), ``target_points`` (Q, T, 2) float32 (x, y) and ``occluded``
(Q, T) bool, in TAP-Vid's raster pixel coordinates (flowsynth's + 0.5: the top-left image corner is (0, 0));
``points`` (Q, T, 2) the same positions divided by (W, H), as in the TAP-Vid DAVIS / Kinetics pickles
(when the sample has an image-sized key that gives W and H);
and, when rgb was requested, ``video`` (T, H, W, 3) uint8 (Kubric's loader gives it scaled to [-1, 1]:
``video / 127.5 - 1``). ``{name: pickle.load(f)}`` over samples is the TAP-Vid DAVIS file layout.

The boxes of the whole export go to one COCO file at its root, ``boxes_coco.json`` (``write_coco``), written
when the export ends from every sample's ``meta.json``.

A key that is in none of these rows raises :class:`flowsynth.errors.ExportError`: a new output needs its
own row here (a file format, or a place in ``META_KEYS``) before it can be exported.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import json
from pathlib import Path

import numpy as np
import torch

from flowsynth.errors import ExportError
from flowsynth.io.atomic import atomic_write_bytes
from flowsynth.io.exr import CHANNEL_NAMES, read_tensor_exr, write_tensor_exr
from flowsynth.io.jsonio import coco_boxes, read_json, write_json
from flowsynth.io.png import read_rgb_png, read_u16_png, write_rgb_png, write_u16_png
from flowsynth.plan import CAMERA_KEYS, FLOW_KEYS, GBUFFER_KEYS, TABLE_KEYS, TRACK_KEYS, split_gap_key

__all__ = ["COCO_FILE", "COCO_KEYS", "META_KEYS", "PROVENANCE_KEY", "file_digest", "read_sample", "tapvid_dict",
           "write_coco", "write_sample"]

_EXR = {"depth": "depth", "distance": "distance", "normals": "normals", "position": "position",
        "flow_fw": "flow", "flow_bw": "flow", "scene_flow_fw": "scene_flow", "scene_flow_bw": "scene_flow",
        "depth_right": "depth", "disparity": "disparity", "disparity_right": "disparity",
        "disparity_change": "disparity"}
_RGB = ("rgb", "rgb_right", "rgb_final")
_U16 = (("instance", "category", "asset") + tuple(k for k in FLOW_KEYS if not k.startswith("flow_"))
        + ("disparity_occ", "disparity_occ_right"))
# Keys stored as JSON arrays in meta.json: cameras, object tables, the sample's index and seed, and a mixture sample's
# source (int64, the position of its config in the preset).
META_KEYS = CAMERA_KEYS + TABLE_KEYS + ("index", "seed", "source")
# The sample's provenance (flowsynth.scene.scene.provenance_json: a JSON string), stored in meta.json as a JSON object.
PROVENANCE_KEY = "provenance"
COCO_FILE = "boxes_coco.json"
"""The export's COCO detection file (``write_coco``), at its root."""
COCO_KEYS = ("box2d_visible", "visible_pixels", "object_valid", "object_category")
"""The outputs a sample needs for its boxes to be in ``COCO_FILE``."""


def _base(key: str) -> str:
    """The key whose file format ``key`` uses: per-pair keys at any frame gap use the gap-1 key's."""
    split = split_gap_key(key)
    return split[0] if split else key


def file_digest(path: Path) -> str:
    """sha256 hex digest of a file."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def write_sample(sample: dict[str, torch.Tensor], folder: Path, *, exr_compression: str = "zip") -> list[str]:
    """Write every key of ``sample`` into ``folder`` (which must exist). Returns the file names written.

    ``exr_compression`` is a lossless EXR compression, a key of ``flowsynth.io.exr.COMPRESSIONS``.

    Raises ExportError, before writing anything, when a key has no file format (see the module table).
    """
    folder = Path(folder)
    unknown = [k for k in sample if k not in _RGB and _base(k) not in _EXR and _base(k) not in _U16
               and k not in META_KEYS and k not in TRACK_KEYS and k != PROVENANCE_KEY]
    if unknown:
        raise ExportError(f"no export format for key(s) {unknown}; known keys are rgb, {', '.join(_EXR)}, "
                          f"{', '.join(_U16)}, {', '.join(META_KEYS)} (add a format in flowsynth/io/sampleio.py)")
    names: list[str] = []
    meta: dict = {"keys": list(sample)}
    for key, value in sample.items():
        if key == PROVENANCE_KEY:
            meta[key] = json.loads(value)
            cam = meta[key].get("camera", {})
            if "model" in cam:  # a lens camera: its model and coefficients beside K (pinhole files unchanged)
                meta["camera_model"], meta["camera_dist"] = cam["model"], cam["dist"]
            continue
        a = value.numpy()
        if key in _RGB:
            for t in range(a.shape[0]):
                names.append(f"{key}_{t:04d}.png")
                write_rgb_png(folder / names[-1], a[t])
        elif _base(key) in _EXR:
            for t in range(a.shape[0]):
                names.append(f"{key}_{t:04d}.exr")
                write_tensor_exr(folder / names[-1], a[t], CHANNEL_NAMES[_EXR[_base(key)]],
                                 compression=exr_compression)
        elif key in TRACK_KEYS:
            continue  # tracks.npz below
        elif _base(key) in _U16:
            for t in range(a.shape[0]):
                names.append(f"{key}_{t:04d}.png")
                write_u16_png(folder / names[-1], a[t, 0].astype(np.int64))
        else:  # META_KEYS
            meta[key] = {"shape": list(a.shape), "dtype": str(value.dtype).replace("torch.", ""),
                         "data": a.reshape(-1).tolist()}
    tracks = {k: sample[k].numpy() for k in TRACK_KEYS if k in sample}
    if tracks:
        buf = io.BytesIO()
        np.savez(buf, **tracks)
        atomic_write_bytes(folder / "tracks.npz", buf.getvalue())
        names.append("tracks.npz")
    if len(tracks) == len(TRACK_KEYS):
        atomic_write_bytes(folder / "tapvid.pkl", pickle.dumps(tapvid_dict(sample), protocol=4))
        names.append("tapvid.pkl")
    write_json(folder / "meta.json", meta)
    names.append("meta.json")
    return names


def write_coco(root: Path, folders: list[str]) -> list[str]:
    """Write ``root/COCO_FILE``: one COCO detection file of the samples in ``root/FOLDER`` for each of ``folders``
    (sample folders of ``write_sample`` with ``index`` and ``provenance``, in order), from their ``meta.json``.
    Returns ``[COCO_FILE]``, or [] (and writes nothing) when no sample holds ``COCO_KEYS``.

    One image per (sample, frame), ids 1, 2, ... in that order, ``file_name`` ``FOLDER/rgb_TTTT.png`` and
    ``sample`` its index; one annotation per visible object and frame (``flowsynth.io.coco_boxes``: COCO's
    pixel-edge boxes). Categories: every object category the samples hold, named by the asset their provenance
    names (``box``; where two assets share an id, as in a mixture, their names joined by "|"), ``category_<id>``
    for an object without one. A folder without ``meta.json`` is left out (a dry run writes sample 0 only)."""
    root = Path(root)
    images: list[dict] = []
    annotations: list[dict] = []
    names: dict[int, list[str]] = {}
    for folder in folders:
        path = root / folder / "meta.json"
        if not path.is_file():
            continue
        meta = read_json(path)
        if not all(k in meta for k in COCO_KEYS):
            continue
        tables = {k: np.asarray(meta[k]["data"]).reshape(meta[k]["shape"]) for k in COCO_KEYS}
        for o in meta[PROVENANCE_KEY].get("objects", []):
            asset = (o.get("mesh") or {}).get("asset")
            if not o.get("background") and asset is not None and asset not in names.setdefault(o["category"], []):
                names[o["category"]].append(asset)
        camera = meta[PROVENANCE_KEY]["camera"]
        frames = [f"{folder}/rgb_{t:04d}.png" for t in range(tables["box2d_visible"].shape[0])]
        part = coco_boxes(tables["box2d_visible"], tables["object_valid"], tables["object_category"],
                          tables["visible_pixels"], width=camera["width"], height=camera["height"],
                          file_names=frames, first_image_id=len(images) + 1,
                          first_annotation_id=len(annotations) + 1)
        images += [{**im, "sample": int(meta["index"]["data"][0])} for im in part["images"]]
        annotations += part["annotations"]
        for c in part["categories"]:
            names.setdefault(c["id"], [])
    if not images:
        return []
    categories = [{"id": c, "name": "|".join(v) or f"category_{c}", "supercategory": "object"}
                  for c, v in sorted(names.items())]
    write_json(root / COCO_FILE, {"info": {"description": "flowsynth export: visible boxes"}, "images": images,
                                  "annotations": annotations, "categories": categories})
    return [COCO_FILE]


def tapvid_dict(sample: dict) -> dict[str, np.ndarray]:
    """The TAP-Vid (Kubric) dict of a sample with ``target_points``, ``occluded``, ``query_points`` (and
    optionally ``rgb``): raster coordinates (+ 0.5 px), see the module docstring."""
    target = sample["target_points"].numpy().astype(np.float64)
    occ = sample["occluded"].numpy().astype(bool)
    H, W = _image_size(sample)
    raster = target + 0.5
    out = {"query_points": (sample["query_points"].numpy() + np.array([0.0, 0.5, 0.5])).astype(np.float32),
           "target_points": raster.astype(np.float32), "occluded": occ}
    if H and W:
        out["points"] = (raster / np.array([W, H])).astype(np.float32)
    if "rgb" in sample:
        rgb = sample["rgb"].numpy().transpose(0, 2, 3, 1)
        out["video"] = np.rint(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)
    return out


def _image_size(sample: dict) -> tuple[int, int]:
    for k in ("rgb",) + GBUFFER_KEYS + FLOW_KEYS:
        if k in sample:
            return int(sample[k].shape[-2]), int(sample[k].shape[-1])
    return 0, 0


def read_sample(folder: Path) -> dict[str, torch.Tensor]:
    """Read a folder written by ``write_sample`` back into a sample dict (same keys, shapes, dtypes; the
    ``provenance`` string is the one written, character for character)."""
    folder = Path(folder)
    meta = read_json(folder / "meta.json")
    out: dict[str, torch.Tensor] = {}
    tracks: dict = {}
    if (folder / "tracks.npz").exists():
        with np.load(folder / "tracks.npz") as z:
            tracks = {k: z[k] for k in z.files}
    for key in meta["keys"]:
        if key == PROVENANCE_KEY:
            out[key] = json.dumps(meta[key], separators=(",", ":"))
            continue
        if key in TRACK_KEYS:
            out[key] = torch.from_numpy(tracks[key])
            continue
        if key in meta:
            m = meta[key]
            dtype = getattr(torch, m["dtype"])
            np_dtype = torch.empty(0, dtype=dtype).numpy().dtype
            out[key] = torch.from_numpy(np.asarray(m["data"], dtype=np_dtype).reshape(m["shape"]))
            continue
        files = sorted(folder.glob(f"{key}_[0-9][0-9][0-9][0-9].*"))
        if key in _RGB:
            arr = np.stack([read_rgb_png(f) for f in files]).astype(np.float32)
        elif _base(key) in _EXR:
            arr = np.stack([read_tensor_exr(f, CHANNEL_NAMES[_EXR[_base(key)]]) for f in files]).astype(np.float32)
        else:
            arr = np.stack([read_u16_png(f) for f in files])[:, None]
            arr = arr.astype(bool) if key not in ("instance", "category", "asset") else arr.astype(np.int32)
        out[key] = torch.from_numpy(np.ascontiguousarray(arr))
    return out
