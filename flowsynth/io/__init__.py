"""File formats: one module per format, writer and reader side by side.

Arrays are channels-first numpy arrays (CPU torch tensors are accepted by the writers). Every writer
is atomic (:mod:`flowsynth.io.atomic`): a crash never leaves a partial file under the final name.

- ``exr``: ``.exr`` named float32 channels (depth, flow, normals, ...); lossless, bit-exact.
- ``flo``: Middlebury ``.flo`` flow (2, H, W); bit-exact float32.
- ``kitti``: KITTI 16-bit flow PNG with valid mask; 1/64 px steps, range [-512, 512) px.
- ``pfm``: PFM float maps (FlyingThings3D's disparity and disparity change); bit-exact float32.
- ``png``: 8-bit RGB PNG and PPM; 16-bit greyscale PNG for ids and masks, exact up to 65535; 8-bit
  0 / 255 mask PNG (Sintel's occlusions).
- ``layouts``: export layouts (native, flyingchairs, kitti, sintel, flyingthings3d, webdataset) as
  plug-ins, found by name (``flowsynth.io.layouts``; README, Export, lists each one's tree).
- ``jsonio``: JSON metadata and COCO-style boxes; finite numbers only.
"""

from flowsynth.io.atomic import atomic_path, atomic_write_bytes
from flowsynth.io.exr import CHANNEL_NAMES, read_exr, read_tensor_exr, write_exr, write_tensor_exr
from flowsynth.io.flo import read_flo, write_flo
from flowsynth.io.jsonio import coco_boxes, read_json, to_jsonable, write_json
from flowsynth.io.kitti import read_kitti_flow, write_kitti_flow
from flowsynth.io.png import (
    decode_png,
    encode_png16,
    read_mask_png,
    read_ppm,
    read_rgb_png,
    read_u16_png,
    write_mask_png,
    write_ppm,
    write_rgb_png,
    write_u16_png,
)

__all__ = [
    "CHANNEL_NAMES",
    "atomic_path",
    "atomic_write_bytes",
    "coco_boxes",
    "decode_png",
    "encode_png16",
    "read_exr",
    "read_flo",
    "read_json",
    "read_kitti_flow",
    "read_mask_png",
    "read_ppm",
    "read_rgb_png",
    "read_tensor_exr",
    "read_u16_png",
    "to_jsonable",
    "write_exr",
    "write_flo",
    "write_json",
    "write_kitti_flow",
    "write_mask_png",
    "write_ppm",
    "write_rgb_png",
    "write_tensor_exr",
    "write_u16_png",
]
