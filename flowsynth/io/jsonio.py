"""JSON files (metadata, camera parameters, COCO-style 2-D boxes), strict about non-finite numbers.

:func:`write_json` accepts numpy arrays and scalars and torch tensors anywhere in the object and
stores them as (nested) lists and plain numbers. JSON has no NaN or infinity (Python's ``json``
writes the non-standard ``NaN`` token by default, which most other parsers reject), so a non-finite
value raises :class:`~flowsynth.errors.ExportError` naming where it is.
"""

from __future__ import annotations

import enum
import json
import math
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from flowsynth.errors import ExportError, ShapeError
from flowsynth.io.atomic import atomic_write_bytes

__all__ = ["coco_boxes", "json_differences", "read_json", "to_jsonable", "write_json"]


def _finite(value: float, where: str) -> float:
    if not math.isfinite(value):
        raise ExportError(f"JSON cannot store the non-finite value {value} at {where}")
    return value


def to_jsonable(obj: Any, where: str = "obj") -> Any:
    """Convert ``obj`` to plain JSON types: dict (str keys), list, str, int, float, bool, None.

    numpy arrays / torch tensors -> nested lists; numpy scalars -> int / float / bool; tuples ->
    lists; integer dict keys -> strings; ``os.PathLike`` -> str; enums -> their value.

    Args:
        obj: the object to convert.
        where: name of ``obj`` used in error messages (``obj['a'][2]``).

    Raises:
        ExportError: a NaN / inf value, or a type JSON cannot represent; the message says where.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return _finite(float(obj), where)
    if isinstance(obj, enum.Enum):
        return to_jsonable(obj.value, where)
    if hasattr(obj, "detach") and hasattr(obj, "numpy"):  # torch.Tensor, without importing torch
        t = obj.detach().cpu()
        try:
            obj = t.numpy()
        except TypeError:  # bfloat16 and other dtypes numpy lacks
            obj = t.float().numpy()
    if isinstance(obj, np.generic):
        obj = np.asarray(obj)
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f":
            bad = ~np.isfinite(obj)
            if bad.any():
                index = tuple(int(i) for i in np.argwhere(bad)[0])
                raise ExportError(
                    f"JSON cannot store the non-finite value {obj[index]} at {where}{list(index)}"
                )
        elif obj.dtype.kind not in "biu":
            return [to_jsonable(x, f"{where}[{i}]") for i, x in enumerate(obj.tolist())]
        return obj.tolist()
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
                key = str(int(key))
            elif not isinstance(key, str):
                raise ExportError(f"JSON object keys must be str or int, got {type(key).__name__} at {where}")
            out[key] = to_jsonable(value, f"{where}[{key!r}]")
        return out
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(x, f"{where}[{i}]") for i, x in enumerate(obj)]
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise ExportError(f"JSON cannot store a {type(obj).__name__} at {where}")


def write_json(path: str | os.PathLike[str], obj: Any, *, indent: int | None = 2) -> None:
    """Write ``obj`` as UTF-8 JSON (converted with :func:`to_jsonable`), atomically.

    Raises:
        ExportError: a NaN / inf value or unsupported type, or the file cannot be written.
    """
    text = json.dumps(to_jsonable(obj), indent=indent, allow_nan=False, ensure_ascii=False)
    atomic_write_bytes(path, (text + "\n").encode("utf-8"))


def _reject_constant(token: str) -> Any:
    raise ValueError(f"non-standard JSON constant {token}")


def read_json(path: str | os.PathLike[str]) -> Any:
    """Read a JSON file; arrays come back as lists.

    Raises:
        ExportError: invalid JSON, or the non-standard ``NaN`` / ``Infinity`` tokens.
        FileNotFoundError: the file does not exist.
    """
    with open(path, encoding="utf-8") as fh:
        text = fh.read()
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except ValueError as exc:
        raise ExportError(f"{path} is not valid JSON: {exc}") from exc


def coco_boxes(
    box2d_visible: Any,
    object_valid: Any,
    category: Any,
    visible_pixels: Any,
    *,
    width: int,
    height: int,
    file_names: Sequence[str],
    category_names: Mapping[int, str] | None = None,
    first_image_id: int = 1,
    first_annotation_id: int = 1,
) -> dict[str, list[dict[str, Any]]]:
    """Build a COCO detection dict from one sample's per-frame visible boxes.

    Object slot n of the sample's object tables is instance id n + 1 in its ``instance`` map.
    One image per frame; one annotation per (frame, valid object with at least one visible pixel).
    Boxes follow COCO's pixel-edge convention: the image's left and top edges are x = 0 and y = 0, so
    a box is flowsynth's (pixel centres at integers, edges at -1/2) shifted by +1/2.

    Args:
        box2d_visible: (T, N, 4) float xyxy [px], the sample's ``box2d_visible`` (flowsynth's pixel-centre
            coordinates: a box of the pixels j0..j1 spans x0 = j0 - 1/2 .. x1 = j1 + 1/2).
        object_valid: (N,) bool, padding mask of the object tables.
        category: (N,) int, category id per object (COCO ids, > 0).
        visible_pixels: (T, N) int, visible pixel count per frame and object.
        width, height: image size [px].
        file_names: T image file names, frame order.
        category_names: optional id -> name; missing names become ``"category_<id>"``.
        first_image_id, first_annotation_id: ids to start from, to merge samples into one file.

    Returns:
        ``{"images": [...], "annotations": [...], "categories": [...]}`` with plain Python values.
        images: ``id, file_name, width, height, frame``. annotations: ``id, image_id, category_id,
        bbox = [x0 + 1/2, y0 + 1/2, x1 - x0, y1 - y0]`` (COCO's [x, y, w, h]: the pixels j0..j1 give
        x = j0, w = j1 - j0 + 1), ``area`` (bbox w * h),
        ``iscrowd = 0, instance_id, frame, visible_pixels``. categories: ``id, name,
        supercategory = "object"`` for every category of a valid object (and of ``category_names``).

    Raises:
        ShapeError: inconsistent shapes.
        ExportError: a kept box has non-finite coordinates.
    """
    boxes = np.asarray(box2d_visible, dtype=np.float64)
    valid = np.asarray(object_valid).astype(bool)
    cats = np.asarray(category).astype(np.int64)
    pixels = np.asarray(visible_pixels).astype(np.int64)
    if boxes.ndim != 3 or boxes.shape[2] != 4:
        raise ShapeError(f"box2d_visible must be (T, N, 4), got {boxes.shape}")
    t_count, n_count = boxes.shape[:2]
    if valid.shape != (n_count,) or cats.shape != (n_count,) or pixels.shape != (t_count, n_count):
        raise ShapeError(
            f"with box2d_visible {boxes.shape}: object_valid and category must be ({n_count},), "
            f"visible_pixels ({t_count}, {n_count}); got {valid.shape}, {cats.shape}, {pixels.shape}"
        )
    if len(file_names) != t_count:
        raise ShapeError(f"file_names has {len(file_names)} entries, box2d_visible has {t_count} frames")
    names = dict(category_names or {})
    images, annotations = [], []
    ann_id = first_annotation_id
    for t in range(t_count):
        image_id = first_image_id + t
        images.append(
            {
                "id": image_id,
                "file_name": str(file_names[t]),
                "width": int(width),
                "height": int(height),
                "frame": t,
            }
        )
        for n in np.flatnonzero(valid & (pixels[t] > 0)):
            x0, y0, x1, y1 = (float(v) for v in boxes[t, n])
            if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
                raise ExportError(f"box2d_visible[{t}, {n}] = {boxes[t, n].tolist()} is not finite")
            w, h = x1 - x0, y1 - y0
            annotations.append(
                {
                    "id": ann_id,
                    "image_id": image_id,
                    "category_id": int(cats[n]),
                    "bbox": [x0 + 0.5, y0 + 0.5, w, h],
                    "area": w * h,
                    "iscrowd": 0,
                    "instance_id": int(n) + 1,
                    "frame": t,
                    "visible_pixels": int(pixels[t, n]),
                }
            )
            ann_id += 1
    ids = sorted({int(c) for c in cats[valid]} | {int(c) for c in names})
    categories = [{"id": c, "name": names.get(c, f"category_{c}"), "supercategory": "object"} for c in ids]
    return {"images": images, "annotations": annotations, "categories": categories}


def json_differences(old: Any, new: Any, where: str = "") -> list[tuple[str, Any, Any]]:
    """Where two JSON-like values differ: ``[(path, old value, new value)]``, paths such as ``config.width`` or
    ``config.sources[1].config.texture_bank``, in order. Dicts are compared key by key (a key one side lacks has the
    value None there), lists of one length item by item; anything else whole. What a refusal to resume names, so a
    user sees which setting to change (``flowsynth export``'s manifest identity, a tune's)."""
    if isinstance(old, Mapping) and isinstance(new, Mapping):
        out = []
        for k in [*old, *(k for k in new if k not in old)]:
            out += json_differences(old.get(k), new.get(k), f"{where}.{k}" if where else str(k))
        return out
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new) and old != new:
        return [d for n, (a, b) in enumerate(zip(old, new)) for d in json_differences(a, b, f"{where}[{n}]")]
    return [] if old == new else [(where, old, new)]
