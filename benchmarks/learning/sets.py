"""The learning benchmark's pairs that flowsynth does not render: the OpenCV reference of the FlyingChairs-style 2D
baseline (``chairs2d_pairs``), the photographs of its photo-textured arms (``train_photos``, ``photo_sources``,
``photo_folder``) and the file-free textures of ``flowsynth_natural`` (``natural_folder``), the real judges (the
Motorcycle stereo pair, ``motorcycle_full``; the Middlebury pairs, ``middlebury_pairs``) and the small-motion
diagnostic (``small_motion_pairs``). Each set is (img1, img2, flow, valid) float32 tensors (n, C, H, W). Imports
nothing of this package.
"""

from __future__ import annotations

import zlib
from pathlib import Path

MIDDLEBURY = ("Dimetrodon", "Grove2", "Urban2", "Venus")  # the pairs looked for under --middlebury (any subset)
# the photo-textured arms take every photograph that ships with scikit-image (none needs a download; most
# are grey), as FlyingChairs textures its chairs with photographs; none is a judge's image
NATURAL_PHOTOS = ("astronaut", "brick", "camera", "cat", "cell", "chelsea", "clock", "coffee", "coins", "grass",
                  "gravel", "hubble_deep_field", "immunohistochemistry", "moon", "page", "retina", "rocket", "text")


def _affine(rng, shift_px: float, rot: float, zoom: float, size: tuple[int, int]):
    """2x3 affine map of pixel coordinates about the centre of an image of ``size`` (w, h): rotation, scale,
    translation."""
    import numpy as np

    a = rng.uniform(-rot, rot)
    s = np.exp(rng.uniform(-zoom, zoom))
    c = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2])
    R = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t = c - R @ c + rng.normal(size=2) * shift_px
    return np.concatenate([R, t[:, None]], 1)


def chairs2d_pairs(n: int, seed: int, sources, motion_scale: float = 1.0):
    """n FlyingChairs-style pairs from ``sources`` (m, 3, h, w) images (any size; shape sizes and shifts, set
    at 128 px wide, scale with w / 128): a background and 2-5 shapes, each under its own random affine map; flow exact
    for every pixel of frame 0 (all valid, as in FlyingChairs).
    ``motion_scale`` multiplies every shift, rotation and log-zoom range.

    The reference, drawn with OpenCV: the registered runs of decision 0023 trained on it. The judge's pools now come
    from the library's ``fs.datasets.layers_pairs`` (``pools.layers_pool``), which makes the same draws and renders
    them with torch; this function stays as the oracle of tests/test_layers2d.py and the helper side of
    benchmarks/accuracy/layers_equivalence.py, and no pool is made with it."""
    import cv2
    import numpy as np
    import torch

    rng = np.random.default_rng(seed)
    src = sources.permute(0, 2, 3, 1).numpy()
    H, W = src.shape[1:3]
    k = W / 128  # the shapes and shifts below are set at 128 px wide
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    grid = np.stack([xs, ys, np.ones_like(xs)], -1)  # (H, W, 3)
    out = [[], [], [], []]
    for _ in range(n):
        bg = src[rng.integers(len(src))]
        # frame 0 is the source itself (so it looks like the flowsynth frames); frame 1 = warped by A
        A = _affine(rng, 1.5 * k * motion_scale, 0.05 * motion_scale, 0.05 * motion_scale, (W, H))
        img1, img2 = bg.copy(), cv2.warpAffine(bg, A, (W, H), borderMode=cv2.BORDER_REFLECT)
        flow = grid @ A.T - grid[..., :2]
        for _shape in range(rng.integers(2, 6)):
            tex = src[rng.integers(len(src))]
            mask = np.zeros((H, W), np.uint8)
            centre = (int(rng.uniform(0.1, 0.9) * W), int(rng.uniform(0.1, 0.9) * H))
            if rng.uniform() < 0.5:
                axes = (int(k * rng.uniform(6, 30)), int(k * rng.uniform(6, 30)))
                cv2.ellipse(mask, centre, axes, rng.uniform(0, 180), 0, 360, 1, -1)
            else:
                n_pts = rng.integers(3, 8)
                ang = np.sort(rng.uniform(0, 2 * np.pi, n_pts))
                r = k * rng.uniform(6, 30, n_pts)
                pts = np.stack([centre[0] + r * np.cos(ang), centre[1] + r * np.sin(ang)], 1).astype(np.int32)
                cv2.fillPoly(mask, [pts], 1)
            B = _affine(rng, rng.uniform(1.0, 6.0) * k * motion_scale, 0.15 * motion_scale, 0.1 * motion_scale,
                        (W, H))
            m1 = mask.astype(bool)
            img1[m1] = tex[m1]
            m2 = cv2.warpAffine(mask, B, (W, H), flags=cv2.INTER_NEAREST).astype(bool)
            tex2 = cv2.warpAffine(tex, B, (W, H))
            img2[m2] = tex2[m2]
            flow[m1] = (grid @ B.T - grid[..., :2])[m1]
        valid = np.ones((H, W, 1))
        for lst, x in zip(out, (img1, img2, flow, valid)):
            lst.append(torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).permute(2, 0, 1))
    return tuple(torch.stack(x) for x in out)


def train_photos(names: tuple = NATURAL_PHOTOS) -> list:
    """The scikit-image images ``names`` as (h, w, 3) float32 arrays in [0, 1] (grey ones
    repeated over 3 channels)."""
    import numpy as np
    import skimage.data

    out = []
    for name in names:
        im = getattr(skimage.data, name)()
        im = np.stack([im] * 3, -1) if im.ndim == 2 else im[..., :3]
        out.append(im.astype(np.float32) / 255.0)
    return out


def photo_folder(names: tuple = NATURAL_PHOTOS) -> Path:
    """A folder (.cache/learning_photos_N under the repository, N photographs) holding the scikit-image images ``names``
    as PNG: the texture_dir of the flowsynth_photos arm."""
    import cv2
    import numpy as np

    root = Path(__file__).resolve().parents[2] / ".cache" / f"learning_photos_{len(names)}"
    root.mkdir(parents=True, exist_ok=True)
    for name, im in zip(names, train_photos(names)):
        f = root / f"{name}.png"
        if not f.exists():
            cv2.imwrite(str(f), cv2.cvtColor((im * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR))
    return root


def natural_folder(kinds: tuple = ("pink", "leaves", "edges"), per_kind: int = 32) -> Path:
    """A folder (.cache/learning_natural_KINDS under the repository) of ``per_kind`` PNG textures of each of
    ``kinds`` (``flowsynth.appearance.natural_image``, 512x512, seeds 0..per_kind-1): made without any file, with the
    statistics of photographs; the texture_dir of the flowsynth_natural arm."""
    import cv2
    import numpy as np

    from flowsynth.appearance import natural_image

    root = Path(__file__).resolve().parents[2] / ".cache" / f"learning_natural_{'_'.join(kinds)}_{per_kind}"
    root.mkdir(parents=True, exist_ok=True)
    for kind in kinds:
        for seed in range(per_kind):
            f = root / f"{kind}_{seed:03d}.png"
            if not f.exists():
                im = (natural_image(kind, seed) * 255).round().astype(np.uint8)
                cv2.imwrite(str(f.with_suffix(".tmp.png")), cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
                f.with_suffix(".tmp.png").replace(f)
    return root


def photo_sources(n: int, seed: int, size: tuple[int, int], names: tuple = NATURAL_PHOTOS):
    """n (3, h, w) crops (``size`` = (w, h)) of the scikit-image images ``names`` at random scales (0.25-1 of the
    largest crop that fits): the backgrounds and shape textures of the chairs2d_photos arm."""
    import cv2
    import numpy as np
    import torch

    rng = np.random.default_rng(30_000 + seed)
    photos = train_photos(names)
    w0, h0 = size
    out = []
    for _ in range(n):
        im = photos[int(rng.integers(len(photos)))]
        s = rng.uniform(0.25, 1.0) * min(im.shape[0] / h0, im.shape[1] / w0)
        h, w = max(int(h0 * s), 1), max(int(w0 * s), 1)
        y0, x0 = rng.integers(0, im.shape[0] - h + 1), rng.integers(0, im.shape[1] - w + 1)
        crop = cv2.resize(im[y0:y0 + h, x0:x0 + w], (w0, h0), interpolation=cv2.INTER_AREA)
        out.append(torch.from_numpy(np.ascontiguousarray(crop)).permute(2, 0, 1))
    return torch.stack(out)


def _append_horizontal(out: list, a, b, fx) -> None:
    """Append to the four lists of ``out`` the pair (a, b) ((h, w, 3) float) with horizontal flow ``fx`` (h, w) [px],
    as (C, h, w) float32 tensors: valid where ``fx`` is finite and the target lands inside the image (else flow 0)."""
    import numpy as np
    import torch

    h, w = fx.shape
    xs = np.arange(w)[None, :]
    valid = np.isfinite(fx) & (xs + fx >= 0) & (xs + fx <= w - 1)
    flow = np.stack([np.where(valid, fx, 0.0), np.zeros((h, w))], -1)
    for lst, x in zip(out, (a, b, flow, valid[..., None])):
        lst.append(torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).permute(2, 0, 1))


def motorcycle_full(factor: int = 2) -> tuple:
    """The whole Motorcycle stereo pair (scikit-image's ``stereo_motorcycle``, 741x500) downsampled by ``factor``
    (INTER_AREA; 370x250 at 2), left -> right flow (-d / factor, 0), and the same pair mirrored left-right (flow
    (+d / factor, 0)): two pairs (2, C, h, w). Valid: the disparity is known (finite) and the target lands inside
    the image. Disparity is read at the source pixel nearest each downsampled pixel's centre."""
    import cv2
    import numpy as np
    import torch

    left, right, disp = skimage_stereo()
    h, w = disp.shape[0] // factor, disp.shape[1] // factor
    a, b = (cv2.resize(x[:h * factor, :w * factor], (w, h), interpolation=cv2.INTER_AREA) for x in (left, right))
    d = disp[factor // 2::factor, factor // 2::factor][:h, :w].astype(np.float64) / factor
    out = [[], [], [], []]
    for x1, x2, fx in ((a, b, -d), (a[:, ::-1], b[:, ::-1], d[:, ::-1])):
        _append_horizontal(out, x1, x2, fx)
    return tuple(torch.stack(x) for x in out)


def skimage_stereo() -> tuple:
    """scikit-image's Motorcycle pair: left, right (float32 in [0, 1]) and the left view's disparity [px]."""
    import numpy as np
    import skimage.data

    left, right, disp = skimage.data.stereo_motorcycle()
    return left.astype(np.float32) / 255.0, right.astype(np.float32) / 255.0, disp


def middlebury_pairs(root: str | None) -> dict:
    """The Middlebury flow training pairs under ``root`` (``NAME/frame10.png``, ``frame11.png``, ``flow10.flo``
    for NAME in MIDDLEBURY; the others are skipped) at full resolution: {"mb_NAME": (img1, img2, flow, valid)},
    each (1, C, H, W) float32. Valid: the ground truth is known (|u| and |v| <= 1e9, the format's marker of unknown
    flow), wherever the target lands (Middlebury's own convention). Empty, with a message, when ``root`` is None
    or holds none of the pairs. Download: https://vision.middlebury.edu/flow/data/ (other-color-twoframes.zip and
    other-gt-flow.zip; unpack both into one folder)."""
    import torch

    from flowsynth.io import read_middlebury

    if root is None:
        print("middlebury: no --middlebury DIR given; the Middlebury judge is skipped")
        return {}
    if not Path(root).is_dir():
        print(f"middlebury: {root} is not a folder; the Middlebury judge is skipped")
        return {}
    out = {f"mb_{name}": tuple(torch.from_numpy(x)[None] for x in (img1, img2, flow, known[None].astype("float32")))
           for name, img1, img2, flow, known in read_middlebury(root, MIDDLEBURY)}
    if not out:
        print(f"middlebury: none of {MIDDLEBURY} (frame10.png, frame11.png, flow10.flo) under {root}; skipped")
    return out


SMALL_MOTION = (0.0, 1.0, 3.0)  # [px] the largest |flow| of the small-motion diagnostic's pairs (0: a still pair)


def small_motion_pair(img, seed: int, magnitude: float) -> tuple:
    """A real photograph ``img`` ((h, w, 3) float in [0, 1]) as frame 1 and the same photograph moved by a small affine
    motion as frame 2: flow(x) = t + B (x - c) about the centre c, with rotation, zoom and shear in B and the
    translation t drawn from ``seed`` and scaled so that the largest |flow| over the image is ``magnitude`` [px] (0:
    frame 2 is frame 1, the flow is 0). Frame 2 at y is frame 1 at the inverse map c + (I + B)^-1 (y - c - t)
    (bilinear; where that lies outside frame 1, by reflection). Valid: the target x + flow(x) lands inside the
    image. Returns (img1, img2, flow, valid), each (1, C, h, w) float32: what a net that "sees motion everywhere"
    gets wrong over the smooth regions of a real image."""
    import cv2
    import numpy as np
    import torch

    h, w = img.shape[:2]
    rng = np.random.default_rng(seed)
    a, z, sh = rng.uniform(-1, 1, 3)
    B = np.array([[z + sh, -a], [a, z - sh]]) / max(w, h)  # a small rotation, zoom and shear per pixel from c
    t = rng.normal(size=2)
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    d = np.stack([xs - c[0], ys - c[1]], -1)  # (h, w, 2)
    flow = t + d @ B.T
    peak = np.linalg.norm(flow, axis=-1).max()
    k = magnitude / peak if peak > 0 else 0.0
    B, t, flow = B * k, t * k, flow * k
    src = c + (d - t) @ np.linalg.inv(np.eye(2) + B).T  # where frame 2's pixel y comes from in frame 1
    img2 = img if magnitude == 0 else cv2.remap(img.astype(np.float32), src[..., 0].astype(np.float32),
                                                src[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                                                borderMode=cv2.BORDER_REFLECT)
    target = np.stack([xs, ys], -1) + flow
    valid = (target[..., 0] >= 0) & (target[..., 0] <= w - 1) & (target[..., 1] >= 0) & (target[..., 1] <= h - 1)
    return tuple(torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)).permute(2, 0, 1)[None]
                 for x in (img, img2, flow, valid[..., None]))


def small_motion_pairs(middlebury: dict, seed: int = 0, magnitudes: tuple = SMALL_MOTION) -> dict:
    """The small-motion diagnostic: each real photograph the judges use (Motorcycle's left view at half
    resolution, frame 1 of each pair in ``middlebury``: middlebury_pairs' dict) moved by ``small_motion_pair`` at
    each of ``magnitudes``: {"sm_NAME_M": (img1, img2, flow, valid)}, each photograph's motion drawn from ``seed``
    and its name. No net trains on these photographs."""
    photos = {"stereo": motorcycle_full(2)[0][0]}
    photos.update({k[3:]: v[0][0] for k, v in middlebury.items()})
    return {f"sm_{name}_{m:g}": small_motion_pair(x.permute(1, 2, 0).numpy(), seed + zlib.crc32(name.encode()), m)
            for name, x in photos.items() for m in magnitudes}
