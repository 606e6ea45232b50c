"""Deterministic BouncingThings scenes from (config, seed, index).

``sample_scene(cfg, seed, index)`` draws everything from ``np.random.default_rng(SeedSequence([seed,
index]))`` in a fixed order (below), runs the motion and returns a :class:`flowsynth.Scene`:

- instances 1..n: the flying objects, category ``OBJECT_CATEGORY_OFFSET + a`` where ``a`` is the index
  of the object's asset in ``resolve_assets(cfg.assets)`` (globs expanded);
- instances n + 1 .. n + 6: the room, a box seen from inside spanning ``cfg.room_bounds``, one object per
  face in ``flowsynth.scene.assets.ROOM_WALLS`` order (floor, ceiling, walls), each with its own material,
  category ``ROOM_CATEGORY``, identity pose, ``background=True`` (rendered, but no row in the object tables).

Materials, lights and the render seed are resolved here, so the scene is the whole description of what is
rendered (``Scene.to_meta``). Texture detail is set in screen terms: each surface's material is drawn with
``pixel_size`` = expected viewing distance / focal length (``flowsynth.appearance.materials.sample_material``), the
distance being the object's centre from the first camera, or for a wall the median length of a 16 x 12
grid of first-frame camera rays that end on it (the wall centre's distance when none does).

World frame: +z up, floor at z = 0, room centred on x = y = 0. The camera sits in the camera zone
(the first ``cfg.camera_clearance`` metres along +x from the wall x = -room_x / 2), which objects never
enter, and looks at a point near the centre of the objects' region; OpenCV axes (x right, y down,
z forward) with world +z pointing up in the image. A moving camera translates, follows a moving look-at
target and pans, tilts and rolls (flowsynth/scene/camerapath.py). Objects start inside the objects' region
with disjoint bounding spheres, preferably inside the camera's view frustum (aimed at the image inset by
``cfg.spawn_margin``, at a distance drawn log-uniformly along the ray, so near objects are common).
With ``cfg.flow_px`` set, the camera's path and every object's speed are scaled to per-frame flow
targets in pixels, drawn from ``cfg.flow_px_scaled`` (flow_px at the rendered width: config docstring); the
targets drawn are kept in ``scene.meta["motion"]``, in the rendered image's pixels.

Draw order (changing it changes every dataset): n, asset indices, size levels, camera path
(flowsynth.scene.camerapath.sample_camera_motion), camera flow target, object positions (rejection sampling),
orientations, linear velocity directions and speeds, object flow targets, angular velocities, texture
seeds (n objects, then the six room faces); then each surface's material from its own seed, the lights
from ``SeedSequence([seed, index, 2])`` and the render seed (``sample_seed``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from flowsynth.appearance import Light, sample_lights, sample_material
from flowsynth.errors import ConfigError
from flowsynth.options import check_int
from flowsynth.scene.assets import ROOM_WALLS, Asset, get_asset, resolve_assets, room_walls
from flowsynth.scene.camera import Camera
from flowsynth.scene.camerapath import camera_poses, look_at, sample_camera_motion, scale_to_flow
from flowsynth.scene.config import BouncingThingsConfig
from flowsynth.scene.motion import InitialState, Trajectory, quat_to_rotation, simulate
from flowsynth.scene.scene import Scene

__all__ = [
    "EXPOSURE",
    "OBJECT_CATEGORY_OFFSET",
    "ROOM_CATEGORY",
    "WALL_NORMALS",
    "SceneLayout",
    "build_scene",
    "expose_lights",
    "look_at",
    "make_rng",
    "sample_layout",
    "sample_scene",
    "sample_seed",
    "simulation_config",
    "size_levels",
    "view_grid",
    "wall_distances",
]

ROOM_CATEGORY = 1
"""Category id of the room (walls, floor, ceiling)."""
OBJECT_CATEGORY_OFFSET = 2
"""Category of an object = OBJECT_CATEGORY_OFFSET + index of its asset in resolve_assets(cfg.assets)."""
SPAWN_GAP_FRACTION = 0.02
"""Initial clearance between bounding spheres (and to the walls), as a fraction of the smallest size."""
FRUSTUM_TRIES = 200
"""Placement attempts per object inside the camera's view before trying the whole region [count]."""
REGION_TRIES = 5000
"""Further placement attempts per object anywhere in the objects' region [count]."""
MIN_SIN_SIGHT = 0.5
"""Floor of sin(angle between velocity and line of sight) when deriving speeds from ``flow_px``: motion
along the line of sight moves few pixels, and its speed must stay finite."""


@dataclass(frozen=True)
class SceneLayout:
    """Everything drawn for one scene before motion (``sample_layout``); not an export layout
    (``flowsynth.io.layouts.base.Layout``).

    Attributes:
        asset_keys: the resolved asset list (built-in names and absolute paths).
        asset_index: (n,) int index into ``asset_keys`` per object.
        assets: the n objects' scaled assets.
        initial: objects' state at t = 0.
        world_T_cam: (T, 4, 4) float64 camera poses, OpenCV axes.
        texture_seeds: (n + 6,) int texture seeds, objects then the room's faces (``ROOM_WALLS`` order).
        motion: what ``cfg.flow_px`` resolved to (empty without it): "camera_flow_px" (target),
            "camera_flow_px_achieved" (median room flow, frames 0-1), "object_flow_px" (targets) [px];
            with ``cfg.rest_fraction`` > 0 also "objects_at_rest" (count) and "camera_at_rest" (when it is);
            with ``cfg.camera_dist_max`` set, "camera_dist": the drawn lens coefficients.
    """

    asset_keys: tuple[str, ...]
    asset_index: np.ndarray
    assets: tuple[Asset, ...]
    initial: InitialState
    world_T_cam: np.ndarray
    texture_seeds: np.ndarray
    motion: dict = field(default_factory=dict)


def make_rng(seed: int, index: int) -> np.random.Generator:
    """The generator of sample ``index`` of a dataset with ``seed`` (both non-negative integers)."""
    seed, index = check_int("seed", seed, 0), check_int("index", index, 0)
    return np.random.default_rng(np.random.SeedSequence([seed, index]))


def sample_scene(cfg: BouncingThingsConfig, seed: int, index: int) -> Scene:
    """Sample, simulate and assemble scene ``index`` of the dataset ``(cfg, seed)``, bit for bit
    reproducible."""
    layout = sample_layout(cfg, seed, index)
    trajectory = simulate(simulation_config(cfg, layout), layout.assets, layout.initial)
    scene = build_scene(cfg, layout, trajectory)
    light_rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 2]))
    lights = sample_lights(light_rng, cfg.room_size)
    points, face, _ = view_grid(scene.camera, scene.world_T_cam[0], *cfg.room_bounds)
    scene.lights = expose_lights(lights, points, WALL_NORMALS[face], float(light_rng.uniform(*EXPOSURE)))
    scene.render_seed = sample_seed(seed, index)
    scene.meta.update(config=cfg.to_dict(), seed=int(seed), index=int(index), substeps=trajectory.substeps)
    if layout.motion:
        scene.meta["motion"] = layout.motion
    return scene


def simulation_config(cfg: BouncingThingsConfig, layout: SceneLayout) -> BouncingThingsConfig:
    """The config a layout's motion is simulated with: with ``flow_px`` and physics, the speed band narrowed to the
    drawn speeds (physics keeps speeds in that band); else ``cfg``."""
    if cfg.flow_px is not None and cfg.motion == "physics" and len(layout.assets):
        speed = np.linalg.norm(layout.initial.velocity, axis=1)
        return replace(cfg, min_speed=float(speed.min()), max_speed=float(speed.max()))
    return cfg


def sample_seed(seed: int, index: int) -> int:
    """The 32-bit render seed of sample ``index`` (the renderer's noise: anti-aliasing, path tracing, motion
    blur); scene sampling uses ``SeedSequence([seed, index])`` directly."""
    return int(np.random.SeedSequence([seed, index, 1]).generate_state(1)[0])


def size_levels(cfg: BouncingThingsConfig) -> np.ndarray:
    """(cfg.size_levels,) float64 object sizes [m], log-spaced from object_size min to max."""
    lo, hi = cfg.object_size
    if cfg.size_levels == 1:
        return np.array([lo])
    return np.geomspace(lo, hi, cfg.size_levels)


def sample_layout(cfg: BouncingThingsConfig, seed: int, index: int) -> SceneLayout:
    """Draw objects, sizes, camera path, initial states and texture seeds (no motion)."""
    rng = make_rng(seed, index)
    keys = resolve_assets(cfg.assets)
    n = int(rng.integers(cfg.num_objects[0], cfg.num_objects[1] + 1))
    asset_index = rng.integers(len(keys), size=n)
    sizes = size_levels(cfg)[rng.integers(cfg.size_levels, size=n)]
    assets = tuple(get_asset(keys[a], float(s)) for a, s in zip(asset_index, sizes))
    camera = Camera.from_fov(cfg.width, cfg.height, cfg.fov_deg)
    path = sample_camera_motion(cfg, rng)
    motion: dict = {}
    if cfg.flow_px is not None:
        motion["camera_flow_px"] = _log_uniform(rng, cfg.flow_px_scaled)
        if cfg.camera_motion == "moving":
            path, motion["camera_flow_px_achieved"] = scale_to_flow(cfg, path, motion["camera_flow_px"])
    world_T_cam = camera_poses(cfg, path)
    position = _place_objects(cfg, rng, sizes, camera, world_T_cam[0])
    quat = rng.normal(size=(n, 4))
    rotation = quat_to_rotation(quat)  # normal 4-vectors: uniform random rotations
    direction = _unit(rng.normal(size=(n, 3)))
    if cfg.planar_motion:
        forward = world_T_cam[0, :3, 2]
        direction = _unit(direction - (direction @ forward)[:, None] * forward)
    speed = rng.uniform(cfg.min_speed, cfg.max_speed, size=(n, 1))
    if cfg.flow_px is not None:
        u = np.array([_log_uniform(rng, cfg.flow_px_scaled) for _ in range(n)])
        motion["object_flow_px"] = u.tolist()
        speed = np.clip(_speed_for_flow(cfg, camera, world_T_cam[0], position, direction, u),
                        cfg.min_speed, cfg.max_speed)[:, None]
    velocity = direction * speed
    w_lo, w_hi = cfg.angular_speed
    angular = _unit(rng.normal(size=(n, 3))) * rng.uniform(w_lo, w_hi, size=(n, 1))
    seeds = rng.integers(0, 2**31 - 1, size=n + len(ROOM_WALLS))
    if cfg.rest_fraction > 0:  # drawn last, so that a config without it keeps every other draw
        rest = rng.uniform(size=n + 1) < cfg.rest_fraction
        velocity[rest[:n]] = 0.0
        angular[rest[:n]] = 0.0
        motion["objects_at_rest"] = int(rest[:n].sum())
        if rest[n]:
            world_T_cam = np.repeat(world_T_cam[:1], len(world_T_cam), axis=0)
            motion["camera_at_rest"] = True
    if cfg.camera_dist_max is not None:  # its own generator: every other draw stays as without it
        lens_rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 3]))
        motion["camera_dist"] = tuple(float(x) for x in lens_rng.uniform(cfg.camera_dist, cfg.camera_dist_max))
    return SceneLayout(keys, asset_index, assets, InitialState(position, rotation, velocity, angular), world_T_cam,
                  seeds, motion)


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    lo, hi = bounds
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _speed_for_flow(cfg: BouncingThingsConfig, camera: Camera, world_T_cam: np.ndarray, position: np.ndarray,
                    direction: np.ndarray, flow_px: np.ndarray) -> np.ndarray:
    """(n,) speeds [m/s] that move objects at ``position`` (n, 3) along unit ``direction`` (n, 3) by
    ``flow_px`` (n,) pixels per frame, seen from ``world_T_cam`` (pinhole, small-motion approximation)."""
    sight = position - world_T_cam[:3, 3]
    dist = np.linalg.norm(sight, axis=1)
    cos = np.abs(np.sum(direction * sight, axis=1)) / np.maximum(dist, 1e-9)
    sin = np.sqrt(np.clip(1.0 - cos**2, 0.0, 1.0))
    return flow_px * dist * cfg.fps / (camera.fx * np.maximum(sin, MIN_SIN_SIGHT))


def build_scene(cfg: BouncingThingsConfig, layout: SceneLayout, trajectory: Trajectory) -> Scene:
    """Assemble a Scene: objects (ids 1..n) with ``trajectory.poses``, then the room's six faces (ids n + 1 ..
    n + 6, marked ``background``: rendered, not in the object tables), each with a resolved material drawn in
    screen terms (module docstring)."""
    camera = Camera.from_fov(cfg.width, cfg.height, cfg.fov_deg, model=cfg.camera_model,
                             dist=layout.motion.get("camera_dist", cfg.camera_dist))
    scene = Scene(camera, num_frames=cfg.num_frames, fps=cfg.fps)
    scene.set_camera_poses(layout.world_T_cam)
    focal = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    eye = layout.world_T_cam[0, :3, 3]

    def material(i: int, size: float, distance: float) -> dict:
        rng = np.random.default_rng(int(layout.texture_seeds[i]))
        return sample_material(rng, cfg.texture_families, cfg.texture_dir, size=size,
                               pixel_size=max(distance, 1e-3) / focal, texture_px=cfg.texture_px)

    n = len(layout.assets)
    for i, asset in enumerate(layout.assets):
        distance = float(np.linalg.norm(trajectory.poses[0, i, :3, 3] - eye))
        scene.add_object(asset.mesh, trajectory.poses[:, i], material=material(i, asset.size, distance),
                         category=OBJECT_CATEGORY_OFFSET + int(layout.asset_index[i]),
                         source={"asset": asset.name, "size": asset.size})
    lo, hi = cfg.room_bounds
    distances = wall_distances(camera, layout.world_T_cam[0], lo, hi)
    for w, mesh in enumerate(room_walls(lo, hi)):
        size = float(np.ptp(np.asarray(mesh.vertices), axis=0).max())
        scene.add_object(mesh, None, category=ROOM_CATEGORY, material=material(n + w, size, distances[w]),
                         background=True)
    return scene


WALL_NORMALS = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], np.float64)
"""Inward unit normals of the room's faces, ``ROOM_WALLS`` order."""
EXPOSURE = (0.5, 0.8)
"""Range of the radiance [linear] a white diffuse surface gets from the point and directional lights (no
shadows) at the median of the room points the first camera sees; the lights are scaled to a value drawn
from it (``expose_lights``), so images have natural brightness whatever the room and light positions."""


def view_grid(camera: Camera, world_T_cam: np.ndarray, lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays of a 16 x 12 pixel grid of a camera inside the box [lo, hi] leave it.

    Returns points (192, 3) [m] world frame, face (192,) int index into ``ROOM_WALLS``, distance (192,) [m]."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    u, v = np.meshgrid((np.arange(16) + 0.5) / 16 * camera.width - 0.5,
                       (np.arange(12) + 0.5) / 12 * camera.height - 0.5)
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    d = pix @ np.linalg.inv(camera.K).T @ world_T_cam[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = world_T_cam[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d > 0, (hi - o) / d, np.where(d < 0, (lo - o) / d, np.inf))  # exit distance per axis
    rows = np.arange(len(t))
    axis = np.argmin(t, axis=1)
    dist = t[rows, axis]
    face = np.array([[2, 3], [4, 5], [0, 1]])[axis, (d[rows, axis] > 0).astype(int)]
    return o + d * dist[:, None], face, dist


def wall_distances(camera: Camera, world_T_cam: np.ndarray, lo, hi) -> np.ndarray:
    """(6,) expected viewing distance [m] of each face of the room box [lo, hi] (``ROOM_WALLS`` order) from a
    camera inside it: the median length of the ``view_grid`` rays that end on the face, or the distance to
    the face's centre when none does."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    _, face, dist = view_grid(camera, world_T_cam, lo, hi)
    out = np.zeros(6)
    for w in range(6):
        centre = (lo + hi) / 2
        axis = int(np.argmax(np.abs(WALL_NORMALS[w])))
        centre[axis] = (lo if WALL_NORMALS[w, axis] > 0 else hi)[axis]
        out[w] = float(np.median(dist[face == w])) if (face == w).any() else \
            float(np.linalg.norm(centre - world_T_cam[:3, 3]))
    return out


def expose_lights(lights: list[Light], points: np.ndarray, normals: np.ndarray, target: float) -> list[Light]:
    """``lights`` with the point and directional intensities scaled by one factor so that a white diffuse
    surface at ``points`` (M, 3) [m] with unit ``normals`` (M, 3) has median radiance ``target`` from them
    (unshadowed; radiance of a light = intensity x mean colour x cos / r^2 for a point light). Ambient lights
    are kept; unchanged when no point sees a light."""
    radiance = np.zeros(len(points))
    for light in lights:
        c = float(np.mean(light.color)) * light.intensity
        if light.kind == "point":
            v = np.asarray(light.position) - points
            r2 = np.maximum(np.einsum("ij,ij->i", v, v), 1e-12)
            radiance += c * np.maximum(np.einsum("ij,ij->i", v, normals), 0.0) / r2 ** 1.5
        elif light.kind == "directional":
            radiance += c * np.maximum(normals @ -np.asarray(light.direction), 0.0)
    median = float(np.median(radiance)) if len(radiance) else 0.0
    if median <= 0.0:
        return list(lights)
    k = target / median
    return [x if x.kind == "ambient" else replace(x, intensity=x.intensity * k) for x in lights]


def _place_objects(cfg: BouncingThingsConfig, rng: np.random.Generator, sizes: np.ndarray, camera: Camera,
                   world_T_cam: np.ndarray) -> np.ndarray:
    """Centres (n, 3) [m] with disjoint bounding spheres inside the objects' region, largest first."""
    n = len(sizes)
    position = np.zeros((n, 3))
    if n == 0:
        return position
    gap = SPAWN_GAP_FRACTION * float(sizes.min())
    olo, ohi = (np.asarray(b, np.float64) for b in cfg.object_bounds)
    K_inv = np.linalg.inv(camera.K)
    eye, R = world_T_cam[:3, 3], world_T_cam[:3, :3]
    placed: list[int] = []
    for i in np.argsort(-sizes, kind="stable"):
        r = sizes[i] / 2.0 + gap
        lo, hi = olo + r, ohi - r
        for attempt in range(FRUSTUM_TRIES + REGION_TRIES):
            if attempt < FRUSTUM_TRIES:
                u = rng.uniform(cfg.spawn_margin, 1.0 - cfg.spawn_margin, size=2)
                u = u * [camera.width - 1, camera.height - 1]
                ray = R @ (K_inv @ np.array([u[0], u[1], 1.0]))
                span = _ray_box(eye, ray, lo, hi)
                if span is None:
                    continue
                near = max(span[0], 1e-3)
                p = eye + ray * float(np.exp(rng.uniform(np.log(near), np.log(max(span[1], near)))))
            else:
                p = rng.uniform(lo, hi)
            others = position[placed]
            if not placed or np.all(np.linalg.norm(others - p, axis=1) >= sizes[placed] / 2 + r + gap):
                position[i] = p
                placed.append(int(i))
                break
        else:
            raise ConfigError(f"could not place {n} objects of sizes up to {sizes.max():.3g} m "
                              "without overlap; "
                              "lower num_objects or object_size, or enlarge room_size")
    return position


def _ray_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[float, float] | None:
    """Parameter interval (t0, t1), t0 >= 0, where o + t d lies inside the box [lo, hi]; None if empty."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a, b = (lo - o) / d, (hi - o) / d
    t0 = float(np.nanmax(np.minimum(a, b)))
    t1 = float(np.nanmin(np.maximum(a, b)))
    t0 = max(t0, 0.0)
    return (t0, t1) if t1 > t0 else None


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)
