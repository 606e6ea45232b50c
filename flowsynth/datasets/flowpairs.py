"""``FlowPairs``: (img1, img2, flow, valid) items exactly as torchvision's optical-flow datasets return them."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from PIL import Image
from torch.utils.data import Dataset

from flowsynth.datasets.kinds import config_kind, make_stream
from flowsynth.errors import ConfigError

__all__ = ["MASKS", "FlowPairs"]

MASKS = ("valid", "visible")
"""FlowPairs masks: flow defined (occluded pixels included), or defined and visible in both frames."""


class FlowPairs(Dataset):
    """Map-style dataset of image pairs with forward flow, like ``torchvision.datasets.FlyingChairs``.

    Item i is frames (0, 1) of sample i of ``cfg``'s stream (``flowsynth.datasets.make_stream``: BouncingThings,
    Layers or Mixture): ``(img1, img2, flow, valid_flow_mask)`` with img1/img2 ``PIL.Image`` RGB, flow
    ``np.ndarray`` (2, H, W) float32 [px] (dx, dy), valid ``np.ndarray`` (H, W) bool — the torchvision convention
    (KITTI-style 4-tuple). When ``transforms`` is given it is called as ``transforms(img1, img2, flow, valid)`` and
    its result returned, as in torchvision.

    Which mask. ``mask="valid"`` (default) is ``valid_fw``: every pixel whose flow is defined, occluded
    and out-of-frame pixels included. This is what torchvision-style training expects: FlyingChairs,
    FlyingThings3D and Sintel supervise every pixel (torchvision returns no mask for them, meaning all
    valid), KITTI's ``flow_occ`` ground truth that ``torchvision.datasets.KittiFlow`` reads includes
    occluded pixels, and torchvision's RAFT reference recipe drops only invalid pixels and |flow| above
    ``max_flow``. ``mask="visible"`` is ``valid_fw & ~occ_fw``: the pixels whose surface is seen in both
    frames, for evaluation in the style of KITTI "noc" or Sintel "matched" EPE, or to train on matched
    pixels only. It costs the visibility rays of exact occlusion. For a Layers sample (a mixture's included)
    ``valid_fw`` is True at every pixel (its flow is defined everywhere, out of frame too), and ``occ_fw`` comes
    from the layer order.

    Args:
        cfg: a BouncingThingsConfig (default config when None), LayersConfig or MixtureConfig (a preset file:
            ``MixtureConfig.from_file(path)``), with num_frames >= 2.
        seed: dataset seed.
        length: number of pairs (len()).
        transforms: optional callable (img1, img2, flow, valid) -> anything.
        mask: "valid" (flow defined, occluded included) or "visible" (defined and not occluded).
    """

    def __init__(self, cfg=None, seed: int = 0, length: int = 10000,
                 transforms: Callable | None = None, *, mask: str = "valid") -> None:
        if mask not in MASKS:
            raise ConfigError(f"mask must be one of {list(MASKS)}, got {mask!r}")
        outputs = ("rgb", "flow_fw", "valid_fw") + (("occ_fw",) if mask == "visible" else ())
        if cfg is None:
            from flowsynth.scene import BouncingThingsConfig

            cfg = BouncingThingsConfig()
        config_kind(cfg)  # a ConfigError for anything but a dataset config
        if cfg.num_frames < 2:
            raise ConfigError("FlowPairs needs num_frames >= 2")
        self.stream = make_stream(cfg, outputs, seed, length)
        self.transforms, self.mask = transforms, mask

    def __len__(self) -> int:
        return self.stream.length

    def __getitem__(self, i: int):
        if not 0 <= i < len(self):
            raise IndexError(f"index {i} out of range for FlowPairs of length {len(self)}")
        s = self.stream.sample(i)
        imgs = [Image.fromarray(np.ascontiguousarray(
            (s["rgb"][t].permute(1, 2, 0).numpy() * 255.0 + 0.5).clip(0, 255).astype(np.uint8))) for t in (0, 1)]
        flow = s["flow_fw"][0].numpy()
        valid = s["valid_fw"][0, 0].numpy()
        if self.mask == "visible":
            valid = valid & ~s["occ_fw"][0, 0].numpy()
        if self.transforms is not None:
            return self.transforms(imgs[0], imgs[1], flow, valid)
        return imgs[0], imgs[1], flow, valid
