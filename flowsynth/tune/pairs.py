"""A tune's validation pairs: image pairs with true flow, read from a folder in one of four layouts, detected.

::

    middlebury     NAME/frame10.png, frame11.png, flow10.flo        (other-color-twoframes + other-gt-flow)
    flyingchairs   NNNNN_img1.ppm, NNNNN_img2.ppm, NNNNN_flow.flo    pair NNNNN
    kitti          image_2/NNNNNN_10.png, NNNNNN_11.png, flow_occ/NNNNNN_10.png    pair NNNNNN
    sintel         clean|final/SCENE/frame_NNNN.png, flow/SCENE/frame_NNNN.flo    pair PASS/SCENE/frame_NNNN

The layout's root is the folder given, or found below it: in ``training/`` or ``data/``, or one folder down (as the
downloads unpack: ``data_scene_flow/training``, ``MPI-Sintel-complete/training``, ``FlyingChairs_release/data``, or
what ``flowsynth export --layout`` writes). Flow files are read by ``flowsynth.io`` (``read_flo``,
``read_middlebury``, ``read_kitti_flow``); a pixel's flow is valid where the format says it is known (KITTI's mask,
Middlebury's unknown-flow marker) and finite, and is 0 elsewhere.
"""

from __future__ import annotations

import fnmatch
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from flowsynth.errors import ConfigError, ExportError
from flowsynth.io import read_flo, read_kitti_flow, read_ppm, read_rgb_png
from flowsynth.tune.trainer import Pair

__all__ = ["LAYOUTS", "find_pairs", "image_size", "load_pairs", "read_pairs"]

UNKNOWN = 1e9  # [px] a .flo component above this marks unknown flow (Middlebury's convention)


def _middlebury(root: Path) -> dict[str, tuple]:
    return {d.name: (d / "frame10.png", d / "frame11.png", d / "flow10.flo") for d in sorted(root.iterdir())
            if d.is_dir() and (d / "flow10.flo").is_file()}


def _chairs(root: Path) -> dict[str, tuple]:
    return {f.name[:-len("_flow.flo")]: (f.with_name(f.name.replace("_flow.flo", "_img1.ppm")),
                                        f.with_name(f.name.replace("_flow.flo", "_img2.ppm")), f)
            for f in sorted(root.glob("*_flow.flo"))}


def _kitti(root: Path) -> dict[str, tuple]:
    return {f.name[:-len("_10.png")]: (root / "image_2" / f.name, root / "image_2" / f.name.replace("_10.", "_11."), f)
            for f in sorted((root / "flow_occ").glob("*_10.png"))}


def _sintel(root: Path) -> dict[str, tuple]:
    out = {}
    for pss in ("clean", "final"):
        for f in sorted((root / "flow").glob("*/frame_*.flo")) if (root / pss).is_dir() else []:
            n = int(f.stem.split("_")[1])
            scene = root / pss / f.parent.name
            out[f"{pss}/{f.parent.name}/{f.stem}"] = (scene / f"{f.stem}.png", scene / f"frame_{n + 1:04d}.png", f)
    return out


LAYOUTS: dict[str, tuple[Callable[[Path], bool], Callable[[Path], dict]]] = {
    "middlebury": (lambda p: any((d / "flow10.flo").is_file() and (d / "frame10.png").is_file()
                                 for d in p.iterdir() if d.is_dir()), _middlebury),
    "flyingchairs": (lambda p: next(p.glob("*_flow.flo"), None) is not None, _chairs),
    "kitti": (lambda p: (p / "image_2").is_dir() and (p / "flow_occ").is_dir(), _kitti),
    "sintel": (lambda p: (p / "flow").is_dir() and ((p / "clean").is_dir() or (p / "final").is_dir()), _sintel),
}
"""name -> (whether a folder is that layout's root, its pairs {name: (image 1, image 2, flow file)})."""


def _roots(root: Path) -> list[Path]:
    found = []
    for d in [root] + sorted(d for d in root.iterdir() if d.is_dir()):
        found += [d] + [d / s for s in ("training", "data") if (d / s).is_dir()]
    return list(dict.fromkeys(found))


def _detect(root: Path) -> tuple[str, Path]:
    hits = [(name, r) for r in _roots(root) for name, (test, _) in LAYOUTS.items() if test(r)]
    if not hits:
        raise ConfigError(f"{root}: no validation pairs found; expected one of the layouts {list(LAYOUTS)} there or "
                          "one folder down (flowsynth/tune/pairs.py shows each tree)")
    if len(hits) > 1:
        raise ConfigError(f"{root}: several layouts found ({', '.join(f'{n} in {r}' for n, r in hits)}); point the "
                          "validation folder at one of them")
    return hits[0][0], hits[0][1]


def _read(layout: str, name: str, files: tuple[Path, Path, Path]) -> Pair:
    for f in files:
        if not f.is_file():
            raise ConfigError(f"validation pair {name} ({layout}): {f} is missing")
    try:
        images = [read_ppm(f) if f.suffix == ".ppm" else read_rgb_png(f) for f in files[:2]]
    except (OSError, ValueError) as e:
        raise ConfigError(f"validation pair {name}: cannot read its images {files[0]}, {files[1]}: {e}") from e
    try:
        if layout == "kitti":
            flow, valid = read_kitti_flow(files[2])
        else:
            flow = read_flo(files[2])
            valid = (np.abs(flow) <= UNKNOWN).all(0)
    except (ExportError, OSError, ValueError) as e:
        raise ConfigError(f"validation pair {name}: cannot read its flow {files[2]}: {e}") from e
    valid = valid & np.isfinite(flow).all(0)
    if images[0].shape != images[1].shape or images[0].shape[1:] != flow.shape[1:]:
        raise ConfigError(f"validation pair {name}: sizes differ: images {images[0].shape[1:]} and "
                          f"{images[1].shape[1:]}, flow {flow.shape[1:]} (H, W)")
    if not valid.any():
        raise ConfigError(f"validation pair {name}: its flow {files[2]} is known at no pixel")
    flow = np.where(valid[None], flow, np.float32(0))
    images = [(x * np.float32(255)).round().astype(np.uint8) for x in images]  # exact: the files hold 8 bits
    return Pair(*(torch.from_numpy(np.ascontiguousarray(x))[None] for x in (*images, flow, valid[None])))


def image_size(layout: str, name: str, files: tuple[Path, Path, Path]) -> tuple[int, int]:
    """(H, W) [px] of a pair's first image, from its header (no pixel is decoded); ConfigError when it is missing or
    Pillow cannot open it."""
    from PIL import Image

    if not files[0].is_file():
        raise ConfigError(f"validation pair {name} ({layout}): {files[0]} is missing")
    try:
        with Image.open(files[0]) as im:
            return im.height, im.width
    except OSError as e:
        raise ConfigError(f"validation pair {name}: cannot read its image {files[0]}: {e}") from e


def load_pairs(layout: str, files: dict[str, tuple[Path, Path, Path]]) -> dict[str, Pair]:
    """The pairs ``find_pairs`` found, read (``read_pairs``'s values and errors)."""
    return {name: _read(layout, name, f) for name, f in files.items()}


def read_pairs(root: str | os.PathLike[str], names: list[str] | None = None) -> tuple[str, dict[str, Pair]]:
    """The validation pairs under ``root`` (layouts: module docstring): ``load_pairs`` of ``find_pairs``.

    Returns:
        (layout name, {pair name: ``Pair``}): images (1, 3, H, W) uint8, as the files hold them, flow (1, 2, H, W)
        float32 [px], 0 where not valid, valid (1, 1, H, W) bool.

    Raises:
        ConfigError: as ``find_pairs``, or a pair's file is missing or unreadable, its sizes differ or its flow is
            known nowhere.
    """
    layout, files = find_pairs(root, names)
    return layout, load_pairs(layout, files)


def find_pairs(root: str | os.PathLike[str], names: list[str] | None = None) -> tuple[str, dict[str, tuple]]:
    """The files of the validation pairs under ``root``, none read.

    Args:
        root: the folder (or a folder one level above the layout's root).
        names: only the pairs whose names match one of these (exactly, or as a glob: ``clean/alley_1/*``); None:
            every pair, sorted by name.

    Returns:
        (layout name, {pair name: (image 1, image 2, flow file)}).

    Raises:
        ConfigError: ``root`` is not a folder, holds no pairs or several layouts, or a name matches no pair.
    """
    base = Path(root)
    if not base.is_dir():
        raise ConfigError(f"{base}: not a folder of validation pairs")
    layout, found = _detect(base)
    pairs = LAYOUTS[layout][1](found)
    if names is not None:
        missing = [n for n in names if not any(fnmatch.fnmatchcase(k, n) for k in pairs)]
        if missing:
            shown = ", ".join(list(pairs)[:12]) + (", ..." if len(pairs) > 12 else "")
            raise ConfigError(f"no validation pair named {missing} in {found} ({layout}); pairs: {shown}")
        pairs = {k: v for k, v in pairs.items() if any(fnmatch.fnmatchcase(k, n) for n in names)}
    if not pairs:
        raise ConfigError(f"{found}: the {layout} layout holds no pairs")
    return layout, pairs
