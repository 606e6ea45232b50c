"""flowsynth: synthetic optical-flow and geometry ground truth, ray-cast with NVIDIA Warp on the CPU.

Importing flowsynth compiles nothing; Warp kernels load on first use.

Every public name is an attribute of this package (``fs.render``, ``fs.render_plan``, ``fs.clear_caches``...);
no function shares its name with a module: ``fs.render`` comes from the folder ``flowsynth.renderer``.
"""

from flowsynth.caches import clear_caches
from flowsynth.errors import (AssetError, ConfigError, DependencyError, ExportError, FlowsynthError, ForkError,
                              ShapeError, StorageError)
from flowsynth.options import RenderOptions
from flowsynth.plan import Plan, make_plan
from flowsynth.renderer import render, render_batch, render_plan
from flowsynth.scene import Camera, Scene, SceneObject

__version__ = "0.2.0"

__all__ = [
    "AssetError",
    "BouncingThingsConfig",
    "Camera",
    "ConfigError",
    "DependencyError",
    "ExportError",
    "FlowsynthError",
    "ForkError",
    "Plan",
    "RenderOptions",
    "Scene",
    "SceneObject",
    "ShapeError",
    "StorageError",
    "clear_caches",
    "datasets",
    "make_plan",
    "render",
    "render_batch",
    "render_plan",
]


def __getattr__(name: str):
    # Lazy imports keep `import flowsynth` cheap (no Warp initialisation, no kernel compilation).
    if name == "BouncingThingsConfig":
        from flowsynth.scene import BouncingThingsConfig
        return BouncingThingsConfig
    if name == "datasets":
        import importlib

        return importlib.import_module("flowsynth.datasets")
    raise AttributeError(f"module 'flowsynth' has no attribute {name!r}")
