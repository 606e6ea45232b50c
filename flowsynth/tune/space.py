"""The search space of ``flowsynth tune``: a few of the generator's own knobs, each with a handful of values.

``SPACE`` is the table (docs/tune.md shows the same one). A point is one label per knob; its key,
``"motion=small,objects=default,..."``, names it in the state and the report. A point makes a ``Mixture``'s sources
(``sources``): "things", a ``BouncingThingsConfig`` whose fields the knobs set (each knob but ``layers`` sets one
field), and, where the ``layers`` knob's share is above 0, "layers", a ``LayersConfig`` (FlyingChairs-style 2D
layers) of the same size, weighted by that share. Each knob's default label holds the generator's default, so the
all-default point is ``BouncingThingsConfig()`` alone (at the preset's size).

Motion is given at ``REFERENCE_WIDTH`` (512 px, FlyingChairs' width: every config's ``flow_px_width``), and each
config scales it to the width a tune renders at; the preset a tune writes is at ``PRESET_SIZE`` with the motion as
given. The 2D layers follow the same knob: their ``motion_scale`` is ``LAYERS_MOTION_SCALE`` (their mean |flow| then
matches the default 3D stream's, as the learning judge matched its 2D pools) times the knob's largest flow over the
default's.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from flowsynth.errors import ConfigError
from flowsynth.scene import FLOW_PX_WIDTH, BouncingThingsConfig

__all__ = ["LAYERS", "LAYERS_MOTION_SCALE", "PRESET_SIZE", "REFERENCE_WIDTH", "SPACE", "Knob", "default_point",
           "draw_candidates", "grid", "key_of", "point_of", "preset", "sources"]

REFERENCE_WIDTH = FLOW_PX_WIDTH  # [px] the image width the motion knob's flow_px values are given at
PRESET_SIZE = (512, 384)  # (width, height) [px] of the preset a tune writes
PRESET_FRAMES = 2  # frames per clip of the preset: one flow pair, as a tune trains on
LAYERS = "layers"  # the knob (and the mixture source) of the 2D layers' share
# LayersConfig.motion_scale at which the 2D layers' mean |flow| matches the default 3D stream's: the learning judge's
# pilot-matched scale was 1.48-1.52 over seeds 0-2 (docs/decisions/0023-raft-judge.md)
LAYERS_MOTION_SCALE = 1.5
_DEFAULT_FAMILIES = BouncingThingsConfig().texture_families


@dataclass(frozen=True)
class Knob:
    """One knob of the search space: a config field and the values a tune tries."""

    name: str
    """The knob's name in keys and reports."""
    field: str
    """The ``BouncingThingsConfig`` field it sets (``LAYERS``: the 2D layers' share of the mixture)."""
    values: dict[str, Any]
    """label -> the field's value (for ``flow_px``: at ``REFERENCE_WIDTH``)."""
    default: str
    """The label whose value is the field's default."""
    what: str
    """What it changes, one line for the docs."""


SPACE: tuple[Knob, ...] = (
    Knob("motion", "flow_px", {"small": (1.0, 16.0), "default": (2.0, 48.0), "large": (4.0, 96.0)}, "default",
         "per-frame flow the objects and camera aim at, (min, max) [px] at 512 px width"),
    Knob("objects", "num_objects", {"few": (2, 6), "default": (4, 12), "many": (8, 16)}, "default",
         "flying objects per scene, (min, max) [count]"),
    Knob("camera", "camera_motion", {"moving": "moving", "static": "static"}, "moving",
         "whether the camera moves (translation, look-at target, pan, tilt, roll)"),
    Knob("still", "rest_fraction", {"0": 0.0, "0.3": 0.3}, "0",
         "chance that an object starts at rest, and, once per clip, that the camera holds still"),
    Knob("textures", "texture_families",
         {"procedural": _DEFAULT_FAMILIES, "natural": (*_DEFAULT_FAMILIES, "solid", "leaves")}, "procedural",
         "texture families: the default procedural ones, or those plus flat colours and dead leaves"),
    Knob(LAYERS, LAYERS, {"0": 0.0, "0.5": 0.5}, "0",
         "share of the training pairs that are FlyingChairs-style 2D layers (fs.datasets.Layers)"),
)


def default_point() -> dict[str, str]:
    """The point of the generator's defaults: {knob name: its default label}."""
    return {k.name: k.default for k in SPACE}


def key_of(point: dict[str, str]) -> str:
    """A point's key, ``"motion=small,objects=default,..."`` in ``SPACE``'s order; raises ConfigError for a point
    that is not one label of each knob."""
    if set(point) != {k.name for k in SPACE}:
        raise ConfigError(f"a point names one label of each knob {[k.name for k in SPACE]}, got {sorted(point)}")
    for k in SPACE:
        if point[k.name] not in k.values:
            raise ConfigError(f"knob {k.name}: unknown label {point[k.name]!r}; labels: {list(k.values)}")
    return ",".join(f"{k.name}={point[k.name]}" for k in SPACE)


def point_of(key: str) -> dict[str, str]:
    """The point of a key (``key_of``'s inverse); raises ConfigError for a malformed key."""
    try:
        point = dict(item.split("=", 1) for item in key.split(","))
    except ValueError:
        raise ConfigError(f"malformed point key {key!r}: expected knob=label,... ") from None
    key_of(point)
    return point


def grid() -> list[dict[str, str]]:
    """Every point of the space, in ``SPACE``'s order (the last knob varies fastest)."""
    return [dict(zip((k.name for k in SPACE), labels)) for labels in itertools.product(*(k.values for k in SPACE))]


def draw_candidates(n: int, seed: int) -> list[str]:
    """``n`` distinct points' keys: the default point first, then ``n - 1`` others drawn without replacement from
    ``grid()`` by a generator seeded ``seed``. Raises ConfigError unless 2 <= n <= the grid's size."""
    points = grid()
    if not 2 <= n <= len(points):
        raise ConfigError(f"candidates must be between 2 and {len(points)} (the grid's size), got {n}")
    default = key_of(default_point())
    others = [key_of(p) for p in points if key_of(p) != default]
    picked = np.random.default_rng(seed).choice(len(others), size=n - 1, replace=False)
    return [default, *(others[int(i)] for i in picked)]


def sources(key: str, res: tuple[int, int] = PRESET_SIZE) -> tuple[dict, dict]:
    """Point ``key``'s ``Mixture`` arguments (configs, weights) at ``res`` = (width, height) [px], ``PRESET_FRAMES``
    frames: {"things": its ``BouncingThingsConfig``, and "layers": a ``LayersConfig`` of the same size where its share
    is above 0}, {name: weight}. Motion (``flow_px``, at ``REFERENCE_WIDTH``) is scaled to the width by the config."""
    from flowsynth.datasets import LayersConfig

    point = point_of(key)
    fields = {k.field: k.values[point[k.name]] for k in SPACE if k.field != LAYERS}
    things = BouncingThingsConfig(width=res[0], height=res[1], num_frames=PRESET_FRAMES, **fields)
    share = next(k.values[point[k.name]] for k in SPACE if k.field == LAYERS)
    if share == 0:
        return {"things": things}, {"things": 1.0}
    motion = next(k for k in SPACE if k.field == "flow_px")
    scale = LAYERS_MOTION_SCALE * motion.values[point[motion.name]][1] / motion.values[motion.default][1]
    layers = LayersConfig(width=res[0], height=res[1], num_frames=PRESET_FRAMES, motion_scale=scale)
    return {"things": things, LAYERS: layers}, {"things": 1.0 - share, LAYERS: share}


def preset(key: str):
    """Point ``key``'s preset at ``PRESET_SIZE``: a ``fs.datasets.MixtureConfig`` (one source, or two with the 2D
    layers); its ``to_file`` writes the preset file."""
    from flowsynth.datasets import MixtureConfig

    return MixtureConfig(*sources(key))
