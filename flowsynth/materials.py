"""Materials, image textures and lights for RGB rendering: sampling from a seed, validation, defaults.

Plain numpy and Pillow: importing this module loads no Warp kernel. The material dict schema and the
light model are documented in docs/rendering.md; ``resolve_material`` is the one place that checks a
material and fills in defaults.
"""

from __future__ import annotations

import colorsys
import functools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flowsynth.caches import register
from flowsynth.errors import AssetError, ConfigError

__all__ = [
    "IMAGE_EXTENSIONS",
    "LIGHT_KINDS",
    "MAX_TEXTURE_SIZE",
    "PROCEDURAL_FAMILIES",
    "TEXTURE_FAMILIES",
    "Light",
    "check_texture_families",
    "default_lights",
    "default_material",
    "list_textures",
    "load_texture",
    "mip_pyramid",
    "resolve_lights",
    "resolve_material",
    "sample_lights",
    "sample_material",
    "srgb_to_linear",
]

TEXTURE_FAMILIES = ("solid", "noise", "value", "cells", "stripes", "checks", "blend", "image")
# The default families to draw from: every procedural one (image textures need a folder).
PROCEDURAL_FAMILIES = TEXTURE_FAMILIES[:-1]
LIGHT_KINDS = ("directional", "point", "ambient")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
# Image textures larger than this [px] along their longer side are downscaled on load (Lanczos).
MAX_TEXTURE_SIZE = 1024
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


# ---------------------------------------------------------------------------------------------- lights

@dataclass(frozen=True)
class Light:
    """A light source, static in the world.

    Attributes:
        kind: "directional" (parallel light, e.g. the sun), "point" (isotropic, inverse-square falloff)
            or "ambient" (uniform sky radiance from every direction; also the background colour).
        color: linear RGB, each >= 0.
        intensity: >= 0. A white diffuse surface facing a directional light of intensity I has radiance
            I (irradiance pi * I); at distance r [m] from a point light, I / r^2; an ambient light is a
            sky of radiance I * color.
        direction: directional only: world-frame direction the light travels (need not be unit).
        position: point only: world-frame position [m].
    """

    kind: str
    color: tuple = (1.0, 1.0, 1.0)
    intensity: float = 1.0
    direction: tuple = (0.0, 0.0, -1.0)
    position: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if self.kind not in LIGHT_KINDS:
            raise ConfigError(f"Light.kind must be one of {LIGHT_KINDS}, got {self.kind!r}")
        color = _vec3(self.color, "Light.color")
        if (color < 0).any():
            raise ConfigError(f"Light.color must be non-negative linear RGB, got {self.color!r}")
        if not (math.isfinite(self.intensity) and self.intensity >= 0):
            raise ConfigError(f"Light.intensity must be finite and >= 0, got {self.intensity!r}")
        direction = _vec3(self.direction, "Light.direction")
        norm = float(np.linalg.norm(direction))
        if self.kind == "directional" and norm == 0.0:
            raise ConfigError("Light.direction of a directional light must be a non-zero vector")
        object.__setattr__(self, "color", tuple(float(c) for c in color))
        object.__setattr__(self, "intensity", float(self.intensity))
        if abs(norm - 1.0) > 1e-12:  # a unit direction is kept bit for bit (Scene.from_meta re-renders exactly)
            direction = direction / max(norm, 1e-300)
        object.__setattr__(self, "direction", tuple(float(c) for c in direction))
        object.__setattr__(self, "position", tuple(float(c) for c in _vec3(self.position, "Light.position")))


def default_lights(world_T_cam0: np.ndarray, distance: float = 1.0) -> list[Light]:
    """Lights used when ``scene.lights`` is empty, fixed in the world relative to the first camera pose.

    - a warm directional key light travelling along camera-frame (0.4, 0.8, 0.45) (from above-left-behind
      the first camera), intensity 0.6 — it casts the shadows of open scenes;
    - a white "headlight": a point light 0.1 ``distance`` above and left of the first camera, so that a
      white surface facing it at ``distance`` [m] (the median distance the camera sees) has radiance 0.3 —
      it lights what the camera sees even inside a closed room, whose walls block the key light;
    - a pale blue ambient sky of radiance 0.2 * (0.75, 0.85, 1.0).
    """
    P = np.asarray(world_T_cam0, np.float64)
    d_cam = np.array([0.4, 0.8, 0.45])
    d = max(float(distance), 1e-6)
    head = P[:3, :3] @ np.array([-0.1 * d, -0.1 * d, 0.0]) + P[:3, 3]
    return [Light("directional", (1.0, 0.96, 0.9), 0.6, direction=tuple(P[:3, :3] @ (d_cam / np.linalg.norm(d_cam)))),
            Light("point", (1.0, 1.0, 1.0), 0.3 * d * d, position=tuple(head)),
            Light("ambient", (0.75, 0.85, 1.0), 0.2)]


def resolve_lights(lights, world_T_cam0: np.ndarray, distance: float = 1.0) -> list[Light]:
    """``scene.lights`` as Light objects (dicts are accepted as Light keyword arguments); when empty,
    ``default_lights(world_T_cam0, distance)``."""
    if not lights:
        return default_lights(world_T_cam0, distance)
    out = []
    for i, light in enumerate(lights):
        if isinstance(light, dict):
            try:
                light = Light(**light)
            except TypeError as e:
                raise ConfigError(f"scene.lights[{i}]: {e}; fields are kind, color, intensity, direction, "
                                  "position") from e
        if not isinstance(light, Light):
            raise ConfigError(f"scene.lights[{i}] must be a flowsynth.materials.Light or a dict, "
                              f"got {type(light).__name__}")
        out.append(light)
    return out


def sample_lights(rng: np.random.Generator, room_size, *, center=None, up=(0.0, 0.0, 1.0),
                  num_point: tuple[int, int] = (1, 3), num_directional: tuple[int, int] = (0, 0)) -> list[Light]:
    """Random lights for a box-shaped room.

    Args:
        rng: numpy Generator (the scene's seeded RNG).
        room_size: room extents [m], a float (cube) or (3,) along the world axes; the room is the box of
            that size centred at ``center``.
        center: room centre, world frame [m]; None means the BouncingThings room (x and y centred on 0,
            floor at z = 0): (0, 0, room_size[2] / 2).
        up: world up direction (the ceiling side).
        num_point: inclusive range of the number of point lights; placed in the room's upper half, at
            least 20% of the room's extent away from the walls and 25% from the ceiling (hot spots near
            a light make path tracing noisy), tinted between warm and cool white, with intensities chosen so a white
            surface at the room centre facing the lights gets radiance ~0.5 to 1.2 in total.
        num_directional: inclusive range of the number of directional (sun) lights, falling from above
            at 20 to 60 degrees off vertical. Only useful when the room is open to the sky: a closed
            room's walls shadow them completely in "direct" and "path" modes.

    Returns:
        list of Light, always ending with one ambient (sky) light of radiance 0.05 to 0.2.
    """
    size = np.broadcast_to(np.asarray(room_size, np.float64), (3,)).copy()
    if not (np.isfinite(size).all() and (size > 0).all()):
        raise ConfigError(f"room_size must be positive and finite, got {room_size!r}")
    up = _vec3(up, "up")
    up = up / max(float(np.linalg.norm(up)), 1e-300)
    center = np.array([0.0, 0.0, size[2] / 2]) if center is None else _vec3(center, "center")
    lights = []
    n_point = int(rng.integers(num_point[0], num_point[1] + 1))
    n_dir = int(rng.integers(num_directional[0], num_directional[1] + 1))
    total = rng.uniform(0.5, 1.2)
    for _ in range(n_point):
        offset = rng.uniform(-0.3, 0.3, 3) * size
        height = float(abs(up) @ size)
        offset += up * (rng.uniform(0.05, 0.25) * height - offset @ up)
        position = center + offset
        r2 = float(offset @ offset)
        lights.append(Light("point", _white(rng), total / max(n_point, 1) * r2 * rng.uniform(0.7, 1.3),
                            position=tuple(position)))
    for _ in range(n_dir):
        tilt = math.radians(rng.uniform(20.0, 60.0))
        side = _perpendicular(up, rng)
        direction = -math.cos(tilt) * up + math.sin(tilt) * side
        lights.append(Light("directional", _white(rng), rng.uniform(0.3, 0.8), direction=tuple(direction)))
    sky = np.array(colorsys.hsv_to_rgb(rng.uniform(0.52, 0.62), rng.uniform(0.05, 0.3), 1.0))
    lights.append(Light("ambient", tuple(sky), rng.uniform(0.05, 0.2)))
    return lights


def _white(rng: np.random.Generator) -> tuple:
    warm, cool = np.array([1.0, 0.82, 0.62]), np.array([0.72, 0.82, 1.0])
    c = warm + rng.uniform() * (cool - warm)
    return tuple(c / c.max())


def _perpendicular(up: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    return math.cos(phi) * e1 + math.sin(phi) * e2


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
            layers (noise, value, cells) span ``texture_px`` over several octaves (largest features 60-100% of
            ``texture_px[1]``, octaves down to ``texture_px[0]``), stripes and checks have periods
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
        cycles = {"noise": (1.0, 4.0), "value": (2.0, 8.0), "cells": (3.0, 12.0), "stripes": (2.0, 10.0),
                  "checks": (2.0, 8.0), "image": (0.5, 2.0), "solid": (1.0, 1.0)}[family]
        layer["scale"] = float(rng.uniform(*cycles) / size)
        return layer
    metres, lo, hi = px
    if family not in ("image", "solid"):  # fine grain: 3 octaves of value noise from 2-4 texture_px[0] down
        layer["grain"] = float(rng.uniform(0.25, 0.5))
        layer["grain_scale"] = 1.0 / (rng.uniform(4.0, 8.0) * lo * metres)
    if family in ("noise", "value", "cells"):
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
        raise ConfigError(f"material {where}texture must be one of {TEXTURE_FAMILIES[:-2] + ('image',)}"
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


# -------------------------------------------------------------------------------------- image textures

def list_textures(texture_dir) -> list[Path]:
    """The image files (``IMAGE_EXTENSIONS``) directly inside ``texture_dir``, sorted by name.

    Raises ConfigError when the folder does not exist or holds no images.
    """
    root = Path(texture_dir)
    if not root.is_dir():
        raise ConfigError(f"texture_dir {str(root)!r} does not exist or is not a folder; "
                          "pass a folder of pictures (png, jpg, ...) or leave it unset")
    files = sorted(p for p in root.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise ConfigError(f"texture_dir {str(root)!r} holds no images with extensions {IMAGE_EXTENSIONS}")
    return files


def load_texture(path) -> np.ndarray:
    """An image texture as (h, w, 3) float32 linear RGB (sRGB decoded), at most MAX_TEXTURE_SIZE px a side.

    Cached per process by path, size and modification time. Raises AssetError if Pillow cannot read it.
    """
    return _load_texture(*_texture_key(path))


@register("materials.textures")
@functools.lru_cache(maxsize=64)
def _load_texture(path: str, _size: int, _mtime: int) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            if max(im.size) > MAX_TEXTURE_SIZE:
                k = MAX_TEXTURE_SIZE / max(im.size)
                im = im.resize((max(1, round(im.width * k)), max(1, round(im.height * k))), Image.LANCZOS)
            srgb = np.asarray(im, np.float32) / 255.0
    except (OSError, UnidentifiedImageError) as e:
        raise AssetError(f"image texture {path!r} cannot be decoded by Pillow: {e}") from e
    return srgb_to_linear(srgb)


def mip_pyramid(path) -> list[np.ndarray]:
    """Mip levels of an image texture: level 0 is ``load_texture(path)`` (h, w, 3) float32 linear RGB; level
    l + 1 averages 2x2 texels of level l (an odd side wraps around, as the texture tiles), down to 1 x 1.
    Cached with the texture."""
    return _pyramid(*_texture_key(path))


def _texture_key(path) -> tuple[str, int, int]:
    p = Path(path)
    try:
        st = p.stat()
    except OSError as e:
        raise AssetError(f"image texture {str(p)!r} cannot be read: {e}") from e
    return str(p.resolve()), st.st_size, st.st_mtime_ns


@register("materials.mip_pyramids")
@functools.lru_cache(maxsize=64)
def _pyramid(path: str, size: int, mtime: int) -> list[np.ndarray]:
    levels = [_load_texture(path, size, mtime)]
    while max(levels[-1].shape[:2]) > 1:
        a = levels[-1].astype(np.float64)
        if a.shape[0] % 2 and a.shape[0] > 1:
            a = np.concatenate([a, a[:1]], 0)
        if a.shape[1] % 2 and a.shape[1] > 1:
            a = np.concatenate([a, a[:, :1]], 1)
        h, w = max(a.shape[0] // 2, 1), max(a.shape[1] // 2, 1)
        a = a.reshape(h, a.shape[0] // h, w, a.shape[1] // w, 3).mean(axis=(1, 3))
        levels.append(a.astype(np.float32))
    return levels


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear (IEC 61966-2-1)."""
    c = np.asarray(c, np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _vec3(v, name: str) -> np.ndarray:
    a = np.asarray(v, np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ConfigError(f"{name} must be 3 finite numbers, got {v!r}")
    return a
