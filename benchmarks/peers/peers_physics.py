"""Rigid-body stepping on one CPU core: flowsynth's Newton XPBD against PyBullet (Kubric's engine).

Scenes: sampled BouncingThings layouts (``flowsynth.scene.sampling.sample_layout``) of n = 5, 20, 80 objects in a
6 x 5 x 4 m room (camera zone 1 m), sizes 0.3-0.6 m, speeds 1-4 m/s, angular speeds 0-3 rad/s, 24 fps, zero
gravity, restitution 1, friction 0 (flowsynth's defaults), from two asset sets: analytic primitives (box,
sphere, cylinder, capsule, cone) and convex hulls (torus, rock, crystal, star, blob). Both engines start
from the same poses and velocities and simulate the same number of frames:

- flowsynth: ``flowsynth.scene.motion.NewtonScene`` (what ``simulate_physics`` runs: Newton XPBD, 4 iterations,
  captured substeps) at the automatic substep count (``choose_substeps``); after every substep speeds
  are clamped into [min_speed, max_speed] and angular speeds into ``angular_speed``.
- PyBullet (DIRECT mode, default solver settings: 50 iterations, no CCD) with the same colliders:
  box, sphere, cylinder and capsule as PyBullet primitives, cone and every convex hull as a convex mesh
  shape (``GEOM_MESH`` with the hull's vertices; PyBullet has no cone), the six room walls as the same
  static boxes, the same mass and inertia (hull volume x 1000 kg/m^3, inertia tensor about the object
  origin; the PyBullet body frame is its principal frame), restitution 1 on every body (Bullet multiplies
  the pair's coefficients), friction (lateral, spinning, rolling) 0, damping 0. Two step rates:
  "240 Hz" (10 steps per frame, PyBullet's and Kubric's default rate) and "same substeps" (as many steps
  per frame as flowsynth takes). ``fixedTimeStep = 1 / fps`` with ``numSubSteps``: one
  ``stepSimulation`` call per frame.

PyBullet has no speed band: collisions exchange momentum and neither engine conserves kinetic energy
exactly at restitution 1, so PyBullet's speeds drift out of [min_speed, max_speed] and spins out of
``angular_speed`` (columns ``v_out``, ``w_out``: share of object-frames outside the band; flowsynth's are
0 by construction, though its kinetic energy still falls). ``E_end/E0`` is the objects' kinetic energy
at the last frame over the first.

Per scene and engine: setup [ms] (model building; Newton's includes graph capture), step [ms/frame]
(stepping plus reading every pose and velocity back), penetration (the deepest overlap of two visual
meshes over all frames, from python-fcl contact depths through trimesh's CollisionManager, relative to
the smaller object's size -- the measure of tests/test_motion.py), wall (farthest vertex outside the
room / that object's size, 0 = inside). Run ``python benchmarks/peers/peers_physics.py [--quick]``: prints a
table, writes ``benchmarks/results/peers_physics.json`` and ``peers_physics.png`` (ms/frame vs objects).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1]), str(HERE.parents[1] / "tests")]  # _common, flowsynth, oracle
from _common import Timer, machine_info, pin_single_core, plot_curves, print_table, write_json

PINNING = pin_single_core()

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation

from flowsynth.scene import DENSITY, BouncingThingsConfig, NewtonScene, choose_substeps, sample_layout, wall_boxes
from oracle import max_penetration

SETS = {"primitives": ("box", "sphere", "cylinder", "capsule", "cone"),
        "hulls": ("torus", "rock", "crystal", "star", "blob")}
COUNTS = (5, 20, 80)
PYBULLET_HZ = 240.0  # PyBullet's default fixed time step, also Kubric's step_rate [1/s]
BAND_TOL = 1e-3  # relative slack on the speed band when counting speeds outside it (float32 Newton state)


def make_cfg(n: int, assets: tuple[str, ...], num_frames: int) -> BouncingThingsConfig:
    """The scenes of benchmarks/accuracy/physics.py: dense enough that 80 objects collide often."""
    return BouncingThingsConfig(
        room_size=(6.0, 5.0, 4.0), camera_clearance=1.0, num_objects=(n, n), max_objects=max(32, n),
        object_size=(0.3, 0.6), min_speed=1.0, max_speed=4.0, angular_speed=(0.0, 3.0),
        num_frames=num_frames, assets=assets, motion="physics")


def max_wall_excursion(cfg: BouncingThingsConfig, assets, poses: np.ndarray) -> float:
    """Farthest any mesh vertex gets outside the room over all frames / that object's size (0 = inside)."""
    lo, hi = (np.asarray(b) for b in cfg.room_bounds)
    worst = 0.0
    for i, a in enumerate(assets):
        V = np.einsum("tij,vj->tvi", poses[:, i, :3, :3], a.mesh.vertices) + poses[:, i, None, :3, 3]
        worst = max(worst, float(max((lo - V).max(), (V - hi).max())) / a.size)
    return worst


class BulletScene:
    """The same objects and walls in a PyBullet DIRECT world, stepped one frame at a time."""

    def __init__(self, cfg: BouncingThingsConfig, assets, initial, steps_per_frame: int) -> None:
        import pybullet as pb

        self.pb = pb
        self.cid = pb.connect(pb.DIRECT)
        c = self.cid
        pb.setGravity(*cfg.gravity, physicsClientId=c)
        pb.setPhysicsEngineParameter(fixedTimeStep=1.0 / cfg.fps, numSubSteps=steps_per_frame,
                                     physicsClientId=c)
        s_max = max(a.size for a in assets)
        for centre, half in wall_boxes(cfg, s_max):
            shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=c)
            body = pb.createMultiBody(0.0, shape, basePosition=centre.tolist(), physicsClientId=c)
            self._material(body, cfg)
        self.bodies, self.R_principal = [], []
        for i, a in enumerate(assets):
            inertia = DENSITY * np.asarray(a.collider.hull.moment_inertia_frame(np.eye(4)), dtype=np.float64)
            diag, R = np.linalg.eigh(inertia)  # body frame = principal frame: obj_R_body = R
            if np.linalg.det(R) < 0:
                R[:, 0] = -R[:, 0]
            body_q_obj = Rotation.from_matrix(R.T).as_quat().tolist()  # obj frame's orientation in body frame
            shape = self._shape(a, body_q_obj)
            world_R_body = initial.rotation[i] @ R
            body = pb.createMultiBody(DENSITY * float(a.collider.hull.volume), shape,
                                      basePosition=initial.position[i].tolist(),
                                      baseOrientation=Rotation.from_matrix(world_R_body).as_quat().tolist(),
                                      physicsClientId=c)
            pb.changeDynamics(body, -1, localInertiaDiagonal=diag.tolist(), linearDamping=0.0,
                              angularDamping=0.0, physicsClientId=c)
            self._material(body, cfg)
            pb.resetBaseVelocity(body, initial.velocity[i].tolist(), initial.angular_velocity[i].tolist(),
                                 physicsClientId=c)
            self.bodies.append(body)
            self.R_principal.append(R)
        self.R_principal = np.stack(self.R_principal)

    def _shape(self, asset, body_q_obj: list[float]) -> int:
        pb, c, col = self.pb, self.cid, asset.collider
        frame = {"collisionFrameOrientation": body_q_obj, "physicsClientId": c}
        if col.kind == "box":
            return pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(col.params), **frame)
        if col.kind == "sphere":
            return pb.createCollisionShape(pb.GEOM_SPHERE, radius=col.params[0], **frame)
        if col.kind == "cylinder":
            return pb.createCollisionShape(pb.GEOM_CYLINDER, radius=col.params[0], height=2 * col.params[1],
                                           **frame)
        if col.kind == "capsule":  # PyBullet's height is the distance between the cap centres
            return pb.createCollisionShape(pb.GEOM_CAPSULE, radius=col.params[0], height=2 * col.params[1],
                                           **frame)
        # convex hulls, and the cone (no PyBullet primitive): the hull of the visual mesh
        return pb.createCollisionShape(pb.GEOM_MESH, vertices=np.asarray(col.hull.vertices).tolist(), **frame)

    def _material(self, body: int, cfg: BouncingThingsConfig) -> None:
        self.pb.changeDynamics(body, -1, restitution=cfg.restitution, lateralFriction=cfg.friction,
                               spinningFriction=0.0, rollingFriction=0.0, physicsClientId=self.cid)

    def advance_frame(self) -> None:
        self.pb.stepSimulation(physicsClientId=self.cid)

    def read(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(world_T_obj (N, 4, 4), velocity (N, 3), angular velocity (N, 3))."""
        pb, c = self.pb, self.cid
        pos = [pb.getBasePositionAndOrientation(b, physicsClientId=c) for b in self.bodies]
        vel = [pb.getBaseVelocity(b, physicsClientId=c) for b in self.bodies]
        P = np.zeros((len(self.bodies), 4, 4))
        world_R_body = Rotation.from_quat([q for _, q in pos]).as_matrix()
        P[:, :3, :3] = world_R_body @ np.swapaxes(self.R_principal, 1, 2)
        P[:, :3, 3] = [p for p, _ in pos]
        P[:, 3, 3] = 1.0
        return P, np.array([v for v, _ in vel]), np.array([w for _, w in vel])

    def close(self) -> None:
        self.pb.disconnect(physicsClientId=self.cid)


def run(engine: str, cfg: BouncingThingsConfig, seed: int, steps: int) -> dict:
    """Simulate cfg.num_frames frames of layout (cfg, seed) with one engine; times and accuracy."""
    layout = sample_layout(cfg, seed, 0)
    with Timer() as tm:
        sim = (NewtonScene if engine == "flowsynth" else BulletScene)(cfg, layout.assets, layout.initial, steps)
        frames = [sim.read()]
        sim.advance_frame()  # frame 1, in setup: Newton captures its substep graph here
        frames.append(sim.read())
    setup = tm.wall_s
    timed = cfg.num_frames - 2
    with Timer() as tm:
        for _ in range(timed):
            sim.advance_frame()
            frames.append(sim.read())
    wall, cpu = tm.wall_s / timed, tm.cpu_s / timed
    if engine != "flowsynth":
        sim.close()
    poses = np.stack([f[0] for f in frames])
    vel, ang = np.stack([f[1] for f in frames]), np.stack([f[2] for f in frames])
    speed, spin = np.linalg.norm(vel, axis=-1), np.linalg.norm(ang, axis=-1)
    v_out = (speed < cfg.min_speed * (1 - BAND_TOL)) | (speed > cfg.max_speed * (1 + BAND_TOL))
    w_out = (spin < cfg.angular_speed[0] * (1 - BAND_TOL)) | (spin > cfg.angular_speed[1] * (1 + BAND_TOL))
    energy = kinetic_energy(layout.assets, poses, vel, ang)
    return {"setup_ms": 1e3 * setup, "step_ms": 1e3 * cpu, "step_wall_ms": 1e3 * wall,
            "penetration": max_penetration(layout.assets, poses),
            "wall": max_wall_excursion(cfg, layout.assets, poses),
            "v_out": float(v_out.mean()), "w_out": float(w_out.mean()), "v_max": float(speed.max()),
            "E_end/E0": float(energy[-1] / energy[0])}


def kinetic_energy(assets, poses: np.ndarray, vel: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """(T,) total kinetic energy [J] of the objects: translation plus rotation about the object origin."""
    mass = np.array([DENSITY * float(a.collider.hull.volume) for a in assets])
    I_obj = np.stack([DENSITY * np.asarray(a.collider.hull.moment_inertia_frame(np.eye(4))) for a in assets])
    R = poses[:, :, :3, :3]
    I_world = R @ I_obj[None] @ np.swapaxes(R, -1, -2)
    rot = np.einsum("tni,tnij,tnj->t", ang, I_world, ang)
    return 0.5 * (np.einsum("n,tni,tni->t", mass, vel, vel) + rot)


def summarise(set_name: str, n: int, label: str, steps: int, res: list[dict]) -> dict:
    """One table row from the runs of all seeds: median times, worst accuracy."""
    def med(key: str) -> float:
        return float(np.median([r[key] for r in res]))

    return {"set": set_name, "n": n, "engine": label, "steps/frame": steps, "setup_ms": med("setup_ms"),
            "step_ms": med("step_ms"), "step_wall_ms": med("step_wall_ms"),
            "penetration": max(r["penetration"] for r in res), "wall": max(r["wall"] for r in res),
            "v_out": float(np.mean([r["v_out"] for r in res])),
            "w_out": float(np.mean([r["w_out"] for r in res])), "v_max": max(r["v_max"] for r in res),
            "E_end/E0": med("E_end/E0")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="24 frames, one seed (else 96 frames, three seeds)")
    args = ap.parse_args()
    wp.config.quiet = True
    t_start = time.perf_counter()
    T = 24 if args.quick else 96
    seeds = [0] if args.quick else [0, 1, 2]
    fps = make_cfg(5, SETS["hulls"], T).fps
    steps_240 = round(PYBULLET_HZ / fps)
    for assets in SETS.values():  # compile / load Newton's kernels untimed
        run("flowsynth", make_cfg(5, assets, 3), 0, 2)

    rows = []
    for set_name, assets in SETS.items():
        for n in COUNTS:
            cfg = make_cfg(n, assets, T)
            auto = choose_substeps(cfg, [a.size for a in sample_layout(cfg, 0, 0).assets])
            variants = [("flowsynth (Newton XPBD)", "flowsynth", auto),
                        (f"PyBullet {PYBULLET_HZ:.0f} Hz", "pybullet", steps_240),
                        ("PyBullet same substeps", "pybullet", auto)]
            for label, engine, steps in variants:
                row = summarise(set_name, n, label, steps, [run(engine, cfg, s, steps) for s in seeds])
                if engine == "flowsynth":  # first of the variants: the reference
                    base = row["step_ms"]
                row["x_time"] = row["step_ms"] / base
                rows.append(row)
                print(f"{set_name} n={n} {label}: {row['step_ms']:.2f} ms/frame, penetration "
                      f"{row['penetration']:.3g}", flush=True)
    info = machine_info(extra_packages=("pybullet",))
    print(f"\nRigid-body stepping, flowsynth (Newton XPBD) vs PyBullet, same bodies; {T} frames at {fps:g} "
          f"fps, seeds {seeds}. step_ms: process CPU per frame (median over seeds); x_time: step_ms / "
          "flowsynth's; "
          "penetration: max visual-mesh overlap / smaller size (fcl); wall: max excursion / size; "
          "v_out, w_out: share of object-frames with speed outside [1, 4] m/s, spin outside [0, 3] rad/s; "
          "v_max [m/s]; E_end/E0: kinetic energy at the last frame / at the first (median over seeds)")
    print(f"{info['cpu_model']}, affinity {PINNING['affinity']}, newton {info['newton']}, "
          f"warp {info['warp-lang']}, pybullet {info['pybullet']}")
    print_table(rows, ["set", "n", "engine", "steps/frame", "setup_ms", "step_ms", "step_wall_ms", "x_time",
                       "penetration", "wall", "v_out", "w_out", "v_max", "E_end/E0"])
    series = {}
    for set_name in SETS:
        for label in dict.fromkeys(r["engine"] for r in rows):
            pts = [(r["n"], r["step_ms"]) for r in rows if r["set"] == set_name and r["engine"] == label]
            series[f"{label}, {set_name}"] = ([p[0] for p in pts], [p[1] for p in pts])
    plot_curves("peers_physics", series, "objects", "CPU time per frame [ms] (1 core)",
                title=f"Rigid-body stepping, {T} frames at {fps:g} fps")
    total = time.perf_counter() - t_start
    path = write_json("peers_physics", {
        "machine": info, "pinning": PINNING, "loadavg_1_5_15": os.getloadavg(), "quick": args.quick,
        "frames": T, "fps": fps, "seeds": seeds, "pybullet_hz": PYBULLET_HZ, "rows": rows,
        "notes": "flowsynth clamps linear speeds into [min_speed, max_speed] and angular speeds into "
                 "angular_speed after every substep; PyBullet has no such band (v_out, w_out).",
        "total_s": total})
    print(f"total {total:.1f} s; wrote {path}")


if __name__ == "__main__":
    main()
