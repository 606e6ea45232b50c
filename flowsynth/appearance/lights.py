"""Lights for RGB rendering: the ``Light`` type, the default lights, and random lights for a room.

Plain numpy: importing this module loads no Warp kernel. The light model is documented in docs/rendering.md
(Lights); ``resolve_lights`` is the one place that turns ``scene.lights`` into ``Light`` objects.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import numpy as np

from flowsynth.errors import ConfigError

__all__ = ["LIGHT_KINDS", "Light", "default_lights", "resolve_lights", "sample_lights"]

LIGHT_KINDS = ("directional", "point", "ambient")


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
            raise ConfigError(f"scene.lights[{i}] must be a flowsynth.appearance.lights.Light or a dict, "
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



def _vec3(v, name: str) -> np.ndarray:
    a = np.asarray(v, np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ConfigError(f"{name} must be 3 finite numbers, got {v!r}")
    return a
