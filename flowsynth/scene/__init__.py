"""Scene: the whole description of a sample as plain data. The config (``BouncingThingsConfig``), assets and meshes, the
camera and its path, motion (kinematic, static, or rigid-body physics on Newton) and ``Scene`` itself, which
``sample_scene`` builds from a config and a seed; ``physics`` is exported for its switches (``SCENE_REUSE``...)."""

from flowsynth.scene import physics
from flowsynth.scene.assets import resolve_assets
from flowsynth.scene.camera import Camera, check_lens_outputs
from flowsynth.scene.config import FLOW_PX_WIDTH, PRESETS, BouncingThingsConfig, config_from_dict
from flowsynth.scene.meshes import freeze
from flowsynth.scene.motion import simulate
from flowsynth.scene.physics import DENSITY, SUBSTEP_FRACTION, NewtonScene, choose_substeps, wall_boxes
from flowsynth.scene.sampling import OBJECT_CATEGORY_OFFSET, ROOM_CATEGORY, sample_layout, sample_scene, sample_seed
from flowsynth.scene.scene import Scene, SceneObject, provenance_json

__all__ = [
    "DENSITY",
    "FLOW_PX_WIDTH",
    "OBJECT_CATEGORY_OFFSET",
    "PRESETS",
    "ROOM_CATEGORY",
    "SUBSTEP_FRACTION",
    "BouncingThingsConfig",
    "Camera",
    "NewtonScene",
    "Scene",
    "SceneObject",
    "check_lens_outputs",
    "choose_substeps",
    "config_from_dict",
    "freeze",
    "physics",
    "provenance_json",
    "resolve_assets",
    "sample_layout",
    "sample_scene",
    "sample_seed",
    "simulate",
    "wall_boxes",
]
