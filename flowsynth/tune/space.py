"""The search space of ``flowsynth tune``: a few of the generator's own knobs, each with a handful of values.

``SPACE`` is the table (docs/tune.md shows the same one): each knob sets one ``BouncingThingsConfig`` field, and
one of its values, labelled ``"default"`` or named in ``Knob.default``, is the field's default, so the all-default
point is ``BouncingThingsConfig()`` (at the preset's size). A point is one label per knob; its key,
``"motion=small,objects=default,..."``, names it in the state, the report and the preset's provenance.

Motion is given at ``REFERENCE_WIDTH`` (512 px, FlyingChairs' width, as the learning judge gives ``flow_px``) and
scaled to the width a tune renders at; the preset a tune writes is at ``PRESET_SIZE`` with the motion as given.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np

from flowsynth.errors import ConfigError
from flowsynth.scene import BouncingThingsConfig

__all__ = ["PRESET_SIZE", "REFERENCE_WIDTH", "SPACE", "Knob", "default_point", "draw_candidates", "grid", "key_of",
           "point_of", "preset_config", "training_config"]

REFERENCE_WIDTH = 512  # [px] the image width at which the motion knob's flow_px values are given
PRESET_SIZE = (512, 384)  # (width, height) [px] of the preset a tune writes
PRESET_FRAMES = 2  # frames per clip of the preset: one flow pair, as a tune trains on
_DEFAULT_FAMILIES = BouncingThingsConfig().texture_families


@dataclass(frozen=True)
class Knob:
    """One knob of the search space: a config field and the values a tune tries."""

    name: str
    """The knob's name in keys and reports."""
    field: str
    """The ``BouncingThingsConfig`` field it sets."""
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


def preset_config(key: str) -> BouncingThingsConfig:
    """The config of point ``key`` as a preset: ``PRESET_SIZE``, ``PRESET_FRAMES`` frames, each knob's field set to
    its label's value, every other field at its default."""
    point = point_of(key)
    fields = {k.field: k.values[point[k.name]] for k in SPACE}
    return BouncingThingsConfig(width=PRESET_SIZE[0], height=PRESET_SIZE[1], num_frames=PRESET_FRAMES, **fields)


def training_config(key: str, res: tuple[int, int]) -> BouncingThingsConfig:
    """The config a tune renders point ``key``'s training pairs from: ``preset_config(key)`` at ``res`` = (width,
    height) [px], its ``flow_px`` scaled by width / ``REFERENCE_WIDTH`` (so motion keeps its share of the image)."""
    cfg = preset_config(key)
    scale = res[0] / REFERENCE_WIDTH
    return dataclasses.replace(cfg, width=res[0], height=res[1], flow_px=tuple(x * scale for x in cfg.flow_px))
