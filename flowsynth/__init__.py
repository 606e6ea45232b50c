"""flowsynth: synthetic optical-flow and geometry ground truth, ray-cast with NVIDIA Warp on the CPU.

Importing flowsynth compiles nothing; Warp kernels load on first use.
"""

from flowsynth.camera import Camera
from flowsynth.errors import AssetError, ConfigError, ExportError, FlowsynthError, ShapeError
from flowsynth.render import render
from flowsynth.scene import Scene, SceneObject

__version__ = "0.1.0"

__all__ = [
    "AssetError",
    "BouncingThingsConfig",
    "Camera",
    "ConfigError",
    "ExportError",
    "FlowsynthError",
    "Scene",
    "SceneObject",
    "ShapeError",
    "datasets",
    "render",
]


def __getattr__(name: str):
    # Lazy imports keep `import flowsynth` cheap (no Warp initialisation, no kernel compilation).
    if name == "BouncingThingsConfig":
        from flowsynth.config import BouncingThingsConfig
        return BouncingThingsConfig
    if name == "datasets":
        import importlib

        return importlib.import_module("flowsynth.datasets")
    raise AttributeError(f"module 'flowsynth' has no attribute {name!r}")
