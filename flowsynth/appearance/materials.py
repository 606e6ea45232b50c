"""Materials for RGB rendering: the material dict format, sampling from a seed, validation, defaults.

Plain numpy: importing this module loads no Warp kernel. The material dict schema is documented in
docs/rendering.md; ``resolve_material`` is the one place that checks a material and fills in defaults. Lights
are in ``flowsynth.appearance.lights``, image files and their mip pyramids in ``flowsynth.appearance.textures``.
"""

from __future__ import annotations

import colorsys
import math
from pathlib import Path

import numpy as np

from flowsynth.appearance.textures import list_textures, load_texture
from flowsynth.errors import ConfigError

__all__ = [
    "PROCEDURAL_FAMILIES",
    "TEXTURE_FAMILIES",
    "check_texture_families",
    "default_material",
    "resolve_material",
    "sample_material",
]

TEXTURE_FAMILIES = ("solid", "noise", "value", "cells", "stripes", "checks", "blend", "image", "leaves")
# The default families to draw from (image textures need a folder; "leaves", dead-leaves discs, is drawn when named).
PROCEDURAL_FAMILIES = ("solid", "noise", "value", "cells", "stripes", "checks", "blend")
# Fallback roughness / specular weight for material dicts that leave them out.
DEFAULT_ROUGHNESS = 0.5
DEFAULT_SPECULAR = 0.0
DEFAULT_OCTAVES = 4
DEFAULT_GAIN = 0.5
# Default pattern frequency: this many cycles across an object's longest side.
DEFAULT_CYCLES_PER_OBJECT = 4.0
# A random palette's two colours differ by at least this in grey level (mean of the sRGB channels).
MIN_PALETTE_CONTRAST = 0.25
# Screen-space sampling (sample_material with pixel_size): feature sizes [px] at the expected distance.
DEFAULT_TEXTURE_PX = (2.0, 64.0)
# Octaves of a fractal layer at most (each costs one noise evaluation per lookup).
MAX_OCTAVES = 8

_LAYER_KEYS = {"texture", "colors", "scale", "angle", "octaves", "gain", "grain", "grain_scale", "seed", "image"}
_MATERIAL_KEYS = _LAYER_KEYS | {"layers", "mask_scale", "roughness", "specular"}
# Shorthand: {"texture_seed": s} (optionally with the families and folder) is sample_material(default_rng(s)).
_SEEDED_KEYS = {"texture_seed", "texture_families", "texture_dir"}


# ------------------------------------------------------------------------------------------- materials

def sample_material(rng: np.random.Generator, texture_families=PROCEDURAL_FAMILIES, texture_dir=None, *,
                    size: float = 1.0, pixel_size: float | None = None,
                    texture_px: tuple[float, float] = DEFAULT_TEXTURE_PX) -> dict:
    """A random material dict (schema: docs/rendering.md).

    Args:
        rng: numpy Generator (the scene's seeded RNG).
        texture_families: names to draw the texture family from, uniformly; see ``TEXTURE_FAMILIES``.
            "blend" mixes two layers drawn from the other listed families.
        texture_dir: folder of image textures; required when "image" is among the families.
        size: the object's size [m] (longest side); without ``pixel_size``, pattern periods are drawn
            relative to it (1-12 cycles per object).
        pixel_size: the width [m] one pixel covers on the surface at its expected viewing distance
            (distance / focal length in px). When given, pattern frequencies are set in screen terms: fractal
            layers (noise, value, cells, leaves) span ``texture_px`` over several octaves (largest features
            60-100% of ``texture_px[1]``, octaves down to ``texture_px[0]``), stripes and checks have periods
            log-uniform in [max(4 texture_px[0], 8), texture_px[1] / 2] px, every procedural layer but
            "solid" gets a fine grain (amplitude 0.25-0.5, periods 4-8 ``texture_px[0]`` and two octaves
            finer), an image shows 0.7-1.4 px per texel (tiled, not stretched) and a blend's mask has
            features 2-6 times ``texture_px[1]``.
        texture_px: (min, max) feature size on screen [px] (screen terms only).
    """
    families = check_texture_families(texture_families, texture_dir)
    files = list_textures(texture_dir) if texture_dir is not None else []  # a texture_dir given must hold images
    files = files if "image" in families else []
    family = str(rng.choice(families))
    px = None if pixel_size is None else (float(pixel_size), float(texture_px[0]), float(texture_px[1]))
    mat: dict = {}
    if family == "blend":
        simple = [f for f in families if f != "blend"] or ["noise", "cells"]
        mat["texture"] = "blend"
        mat["layers"] = [_sample_layer(rng, str(rng.choice(simple)), files, size, px) for _ in range(2)]
        mat["mask_scale"] = float(rng.uniform(0.5, 2.0) / size if px is None else
                                  1.0 / (rng.uniform(2.0, 6.0) * px[2] * px[0]))
        mat["seed"] = int(rng.integers(0, 2**31 - 1))
    else:
        mat.update(_sample_layer(rng, family, files, size, px))
    mat["roughness"] = float(rng.uniform(0.15, 0.9))
    mat["specular"] = float(rng.uniform(0.0, 0.4)) if rng.uniform() < 0.6 else 0.0
    return mat


def _sample_layer(rng: np.random.Generator, family: str, files: list, size: float, px) -> dict:
    colors = _palette(rng)
    if family == "solid":
        colors = [list(map(float, colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.1, 0.8),
                                                       rng.uniform(0.3, 0.95))))] * 2
    layer = {"texture": family, "colors": colors, "seed": int(rng.integers(0, 2**31 - 1)),
             "angle": float(rng.uniform(0.0, math.pi)), "octaves": int(rng.integers(3, 7))}
    if family == "image":
        layer["image"] = str(files[int(rng.integers(0, len(files)))])
    if px is None:
        cycles = {"noise": (1.0, 4.0), "value": (2.0, 8.0), "cells": (3.0, 12.0), "leaves": (1.0, 4.0),
                  "stripes": (2.0, 10.0), "checks": (2.0, 8.0), "image": (0.5, 2.0), "solid": (1.0, 1.0)}[family]
        layer["scale"] = float(rng.uniform(*cycles) / size)
        return layer
    metres, lo, hi = px
    if family not in ("image", "solid"):  # fine grain: 3 octaves of value noise from 2-4 texture_px[0] down
        layer["grain"] = float(rng.uniform(0.25, 0.5))
        layer["grain_scale"] = 1.0 / (rng.uniform(4.0, 8.0) * lo * metres)
    if family in ("noise", "value", "cells", "leaves"):
        largest = hi * rng.uniform(0.6, 1.0)  # [px]
        layer["octaves"] = int(np.clip(math.floor(math.log2(largest / lo)) + 1, 1, MAX_OCTAVES))
        layer["gain"] = float(rng.uniform(0.7, 0.9))
        layer["scale"] = 1.0 / (largest * metres)
    elif family == "image":
        width = load_texture(layer["image"]).shape[1]
        layer["scale"] = 1.0 / (width * rng.uniform(0.7, 1.4) * metres)
    else:  # stripes, checks, solid
        top = max(hi / 2.0, lo)
        period = math.exp(rng.uniform(math.log(min(max(4.0 * lo, 8.0), top)), math.log(top)))
        layer["scale"] = 1.0 / (period * metres)
    return layer


def _palette(rng: np.random.Generator) -> list:
    """Two sRGB colours whose grey levels (channel means) differ by at least MIN_PALETTE_CONTRAST."""
    h1 = rng.uniform()
    h2 = (h1 + (0.5 if rng.uniform() < 0.3 else rng.uniform(-0.15, 0.15))) % 1.0
    c1 = np.array(colorsys.hsv_to_rgb(h1, rng.uniform(0.15, 0.9), rng.uniform(0.6, 0.95)))
    c2 = np.array(colorsys.hsv_to_rgb(h2, rng.uniform(0.15, 0.9), rng.uniform(0.08, 0.45)))
    c2 *= min(1.0, (c1.mean() - MIN_PALETTE_CONTRAST) / max(c2.mean(), 1e-6))  # grey levels differ clearly
    pair = [list(map(float, c1)), list(map(float, np.maximum(c2, 0.0)))]
    return pair[::-1] if rng.uniform() < 0.5 else pair


def default_material(instance: int, size: float = 1.0) -> dict:
    """The material of an object whose material dict is empty: a procedural texture drawn from the
    instance id (so a hand-built scene is textured and repeatable), purely diffuse."""
    rng = np.random.default_rng([0x5EED, int(instance)])
    mat = sample_material(rng, ("noise", "value", "cells", "stripes", "checks"), size=size)
    mat["specular"] = 0.0
    return mat


def resolve_material(material: dict | None, *, instance: int = 1, size: float = 1.0) -> dict:
    """Validate a material dict and fill in defaults. Returns a new dict in canonical form.

    An empty or None material becomes ``default_material(instance, size)``; ``{"texture_seed": s}``
    (optionally with "texture_families" and "texture_dir") becomes ``sample_material`` drawn from
    ``np.random.default_rng(s)`` with those arguments and the object's size. Raises ConfigError naming the
    offending key for unknown keys and out-of-range values.
    """
    if not material:
        material = default_material(instance, size)
    if not isinstance(material, dict):
        raise ConfigError(f"material must be a dict, got {type(material).__name__}")
    if "texture_seed" in material:
        extra = set(material) - _SEEDED_KEYS
        if extra:
            raise ConfigError(f"a material with 'texture_seed' takes only {sorted(_SEEDED_KEYS)}, got {sorted(extra)}")
        rng = np.random.default_rng(int(material["texture_seed"]))
        material = sample_material(rng, material.get("texture_families", PROCEDURAL_FAMILIES),
                                   material.get("texture_dir"), size=size)
    unknown = set(material) - _MATERIAL_KEYS
    if unknown:
        raise ConfigError(f"unknown material key(s) {sorted(unknown)}; valid keys: {sorted(_MATERIAL_KEYS)}")
    out = {"roughness": _number(material, "roughness", DEFAULT_ROUGHNESS, 0.02, 1.0),
           "specular": _number(material, "specular", DEFAULT_SPECULAR, 0.0, 1.0),
           "seed": int(material.get("seed", instance))}
    if material.get("texture", "noise") == "blend":
        layers = material.get("layers")
        if not (isinstance(layers, (list, tuple)) and len(layers) == 2):
            raise ConfigError("a 'blend' material needs 'layers': a list of two layer dicts")
        out["texture"] = "blend"
        out["layers"] = [_resolve_layer(layer, out["seed"] + 1 + i, size, f"layers[{i}].")
                         for i, layer in enumerate(layers)]
        out["mask_scale"] = _number(material, "mask_scale", 1.0 / size, 0.0, math.inf)
    else:
        out.update(_resolve_layer({k: v for k, v in material.items() if k in _LAYER_KEYS}, out["seed"], size, ""))
    return out


def _resolve_layer(layer: dict, seed: int, size: float, where: str) -> dict:
    if not isinstance(layer, dict) or set(layer) - _LAYER_KEYS:
        raise ConfigError(f"material {where or 'layer '}must be a dict with keys {sorted(_LAYER_KEYS)}")
    family = layer.get("texture", "noise")
    if family not in TEXTURE_FAMILIES or family == "blend":
        layers = tuple(f for f in TEXTURE_FAMILIES if f != "blend")
        raise ConfigError(f"material {where}texture must be one of {layers}"
                          f"{' or blend' if not where else ''}, got {family!r}")
    colors = np.asarray(layer.get("colors", [[0.8, 0.8, 0.8], [0.2, 0.2, 0.2]]), np.float64)
    if colors.shape in ((3,), (1, 3)):
        colors = np.stack([colors.reshape(3)] * 2)
    if colors.shape != (2, 3) or not np.isfinite(colors).all() or colors.min() < 0 or colors.max() > 1:
        raise ConfigError(f"material {where}colors must be one or two sRGB triples in [0, 1], "
                          f"got {layer.get('colors')!r}")
    out = {"texture": family, "colors": colors.tolist(),
           "scale": _number(layer, "scale", DEFAULT_CYCLES_PER_OBJECT / size, 0.0, math.inf, where),
           "angle": _number(layer, "angle", 0.0, -math.inf, math.inf, where),
           "octaves": int(_number(layer, "octaves", DEFAULT_OCTAVES, 1, MAX_OCTAVES, where)),
           "gain": _number(layer, "gain", DEFAULT_GAIN, 0.0, 1.0, where),
           "grain": _number(layer, "grain", 0.0, 0.0, 1.0, where),
           "grain_scale": _number(layer, "grain_scale", 0.0, 0.0, math.inf, where),
           "seed": int(layer.get("seed", seed)), "image": None}
    if family == "image":
        if "image" not in layer:
            raise ConfigError(f"material {where}texture 'image' needs {where}image: the path of a picture")
        path = Path(layer["image"])
        if not path.is_file():
            raise ConfigError(f"material {where}image: no such file {str(path)!r}")
        out["image"] = str(path)
    return out


def _number(d: dict, key: str, default: float, lo: float, hi: float, where: str = "") -> float:
    v = d.get(key, default)
    try:
        v = float(v)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"material {where}{key} must be a number, got {v!r}") from e
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ConfigError(f"material {where}{key} must be in [{lo}, {hi}], got {v!r}")
    return v


def check_texture_families(families, texture_dir) -> list[str]:
    """The texture families as a list, checked by name (reads no file: ``list_textures`` reads ``texture_dir``).
    Raises ConfigError for an unknown family, or for "image" without a ``texture_dir``."""
    families = [families] if isinstance(families, str) else list(families)
    bad = [f for f in families if f not in TEXTURE_FAMILIES]
    if not families or bad:
        raise ConfigError(f"texture families must be a non-empty subset of {TEXTURE_FAMILIES}, got {families!r}")
    if "image" in families and texture_dir is None:
        raise ConfigError("texture family 'image' needs texture_dir: a folder of pictures (png, jpg, ...)")
    return families
