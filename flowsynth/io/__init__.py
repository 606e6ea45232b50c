"""Files: one module per format (``exr``, ``flo``, ``kitti``, ``pfm``, ``png``, ``jsonio``), a sample's files
(``sampleio``), an export's manifest checks (``integrity``) and the export layouts as plug-ins (``layouts``: native,
flyingchairs, kitti, sintel, flyingthings3d, webdataset). Every writer is atomic: no crash leaves a partial file."""

from flowsynth.io import layouts
from flowsynth.io.atomic import atomic_path, atomic_write_bytes
from flowsynth.io.exr import CHANNEL_NAMES, read_exr, read_tensor_exr, write_exr, write_tensor_exr
from flowsynth.io.flo import read_flo, read_middlebury, write_flo
from flowsynth.io.integrity import VERIFY_MODES, file_records, foreign_files, read_manifest, sample_problem
from flowsynth.io.jsonio import coco_boxes, json_differences, read_json, to_jsonable, write_json
from flowsynth.io.kitti import KITTI_FLOW_SCALE, read_kitti_flow, write_kitti_flow
from flowsynth.io.png import (
    ZLIB_LEVEL,
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
    "KITTI_FLOW_SCALE",
    "VERIFY_MODES",
    "ZLIB_LEVEL",
    "atomic_path",
    "atomic_write_bytes",
    "coco_boxes",
    "decode_png",
    "encode_png16",
    "file_records",
    "foreign_files",
    "json_differences",
    "layouts",
    "read_exr",
    "read_flo",
    "read_json",
    "read_kitti_flow",
    "read_manifest",
    "read_mask_png",
    "read_middlebury",
    "read_ppm",
    "read_rgb_png",
    "read_tensor_exr",
    "read_u16_png",
    "sample_problem",
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
