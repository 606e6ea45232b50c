"""Ground truth of the geometry, from the G-buffer and the poses: flow, occlusion, motion and scene flow by exact
float64 reprojection (``flow``), stereo disparity (``stereo``), point tracks (``tracks``), object tables and boxes
(``annotations``). Never an image effect: the final pass changes pixels, not these."""

from flowsynth.truth.annotations import object_tables
from flowsynth.truth.flow import flow_outputs, pair_arrays, reproject, world_point_arrays, world_points
from flowsynth.truth.stereo import right_view, stereo_outputs
from flowsynth.truth.tracks import track_outputs

__all__ = ["flow_outputs", "object_tables", "pair_arrays", "reproject", "right_view", "stereo_outputs", "track_outputs",
           "world_point_arrays", "world_points"]
