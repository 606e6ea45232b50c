"""G-buffer ray cast on one CPU core: flowsynth vs Embree (embreex), Mitsuba 3 (llvm) and Newton's SensorCamera.

Scene: 30 icospheres (radius 1 m, 5120 faces each, random rotations) at random non-overlapping positions
4-12 m in front of a 640x480 camera (60 deg horizontal fov) at the origin, OpenCV axes, looking down +z.
Every engine casts the same pixel-centre rays (unit directions through the pixel centres of the same K)
against the same triangles and returns ray distance (or depth), the hit object and its face normal:

- flowsynth ``fs.render(scene, ["depth", "instance", "normals"])`` (cast + torch post-processing), the raw
  ``cast_gbuffer`` on a prebuilt ``SceneAccel``, and the kernel launch alone into preallocated arrays;
- Embree through ``embreex``: the 30 meshes merged into one world-space triangle soup; ``scene.run(...,
  output=1)`` returns distance, primitive id and Embree's geometric normal ("cast" level); the row
  "Embree run + numpy post" adds the numpy work to reach flowsynth's outputs (instance id from the
  primitive id, unit camera-facing normal from the hit triangle's vertices, depth) ("full" level);
- Mitsuba 3 (``mitsuba``, llvm_ad_rgb variant, Dr.Jit thread count 1): the same triangle soup as one
  ``mi.Mesh`` filled through ``mi.traverse``; ``ray_intersect`` (t, primitive, geometric normal: "cast")
  and ``ray_intersect_preliminary`` (t, primitive: "raw", beside Embree's ``run`` returning primitive
  ids and flowsynth's primary kernel without normals);
- Newton ``SensorCamera.update`` with depth (ray distance), shape index and normal images; the same ray
  directions handed over as a camera-space ray bundle (Newton's camera frame is OpenGL's: x right,
  y up, looking down -z, so directions are (x, -y, -z) and the camera pose is a half-turn about x).

Single core: the script sets OMP/MKL/OpenBLAS/numexpr thread counts to 1 and its CPU affinity to one core
before importing numpy (Embree's TBB pool sizes itself from the affinity mask), and calls
``torch.set_num_threads(1)``; Warp's CPU kernels run on the calling thread. Run it as
``taskset -c 0 python benchmarks/peers/raycast.py [--quick] [--cold-cache]``. Prints a table; writes
``benchmarks/results/raycast.json``.

Timing: all engines are set up first (``first_s``: first call, including kernel compilation or cache load
and BVH builds), then timed round-robin so load changes hit all alike. Mrays/s comes from the median
process CPU time, which on one pinned core is the work done even when other processes share the core;
wall-clock rates are reported beside it. ``x_embree`` compares with Embree's row of the same level,
``x_newton`` with Newton's update (which returns raw images, i.e. the "cast" level), ``x_mitsuba`` with
Mitsuba's row of the same level. Then, on every CPU the process may use, flowsynth's cast at ``threads`` 1
and all, and Mitsuba at Dr.Jit thread count 1 and all (wall clock; the load average is printed).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parents[1])]  # _common, and flowsynth from this checkout when not installed
from _common import (
    RAYCAST_FOV_DEG,
    RAYCAST_HEIGHT,
    RAYCAST_SPHERES,
    RAYCAST_WIDTH,
    RAYCAST_Z_RANGE,
    Timer,
    machine_info,
    pin_single_core,
    print_table,
    raycast_scene,
    save_plot,
    time_round_robin,
    write_json,
)

# One core and one thread per library, set before numpy and torch load, and only when run as a script: a script
# that imports this module must not find its own process pinned (scaling.py did, and undid it by hand).
PINNING = pin_single_core() if __name__ == "__main__" else None

import numpy as np
import torch

import flowsynth as fs
from flowsynth.raycast import SceneAccel, blas, pinhole
from flowsynth.kernels import wp_runtime
from flowsynth.plan import make_plan
from flowsynth.raycast import cast_gbuffer, scene_arrays
from flowsynth.renderer import gbuffer_outputs

WIDTH, HEIGHT, FOV_DEG = RAYCAST_WIDTH, RAYCAST_HEIGHT, RAYCAST_FOV_DEG
OUTPUTS = ["depth", "instance", "normals"]
NEWTON_NO_HIT = 0xFFFFFFFF
# Agreement target for depth between engines where both hit the same object (float32 ray casts).
DEPTH_REL_TOL = 1e-5


def pixel_dirs(camera: fs.Camera) -> np.ndarray:
    """(H*W, 3) float64 unit pixel-centre ray directions, camera frame (OpenCV)."""
    return camera.pixel_rays(torch.float64).reshape(-1, 3).numpy()


def world_triangles(scene: fs.Scene) -> tuple[np.ndarray, np.ndarray, int]:
    """All objects merged: (V (n, 3) float64 world, F (m, 3) int32, faces per object)."""
    verts, faces, offset = [], [], 0
    for obj in scene.objects:
        P = obj.poses[0]
        V = np.asarray(obj.mesh.vertices) @ P[:3, :3].T + P[:3, 3]
        verts.append(V)
        faces.append(np.asarray(obj.mesh.faces) + offset)
        offset += len(V)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int32), len(scene.objects[0].mesh.faces)


class Engine:
    """One engine, set up (first call done) and ready to time.

    ``fns`` maps a timing key to a no-argument callable; ``rows`` lists (row name, level, timing key or keys
    summed, first-call seconds); ``result`` holds its G-buffer for the agreement check (flat per pixel:
    depth [m] float64, instance (-1 = none), unit normal, ray distance [m]).
    """

    def __init__(self, fns: dict, rows: list, info: dict, result: dict) -> None:
        self.fns, self.rows, self.info, self.result = fns, rows, info, result
        self.set_threads = None  # callable(n) for engines timed again on all cores


def setup_flowsynth(scene: fs.Scene) -> Engine:
    from flowsynth.kernels.raycast import primary_kernel

    wp = wp_runtime()
    with Timer() as tm:
        out = fs.render(scene, OUTPUTS)
    first = tm.wall_s
    meshes, cam_T_world, world_T_obj = scene_arrays(scene)
    accel = SceneAccel(meshes, cam_T_world, world_T_obj)
    cam = scene.camera
    gb = cast_gbuffer(accel, cam, want_normals=True, want_points=False)
    plan = make_plan(OUTPUTS)
    # the primary kernel alone, launched into preallocated outputs: the cast without allocation or copies
    shape = (1, cam.height, cam.width)
    outs = [wp.zeros(shape, dtype=wp.float32), wp.zeros(shape, dtype=wp.int32), wp.zeros(shape, dtype=wp.int32),
            wp.zeros((1, 1, 1), dtype=wp.vec3), wp.zeros(shape, dtype=wp.vec3)]
    inputs = [accel.instances(), accel.tile_lists(cam), pinhole(cam), 1e9, 0]
    kernel = primary_kernel(True, False)
    raw_kernel = primary_kernel(False, False)  # distance, item, face only: the bare traversal
    dummy = wp.zeros((1, 1, 1), dtype=wp.vec3)
    raw_outs = outs[:3] + [dummy, dummy]
    mesh = scene.objects[0].mesh
    fns = {
        "render": lambda: fs.render(scene, OUTPUTS),
        "cast": lambda: cast_gbuffer(accel, cam, want_normals=True, want_points=False),
        "kernel": lambda: wp.launch(kernel, dim=shape[:2], inputs=inputs, outputs=outs),
        "raw": lambda: wp.launch(raw_kernel, dim=shape[:2], inputs=inputs, outputs=raw_outs),
        "scene_accel": lambda: SceneAccel(meshes, cam_T_world, world_T_obj),
        "gbuffer_outputs": lambda: gbuffer_outputs([scene], [(meshes, cam_T_world, world_T_obj)], accel, gb, plan),
        "asset_bvh_build": lambda: blas.atlas([mesh]),
    }
    rows = [("flowsynth fs.render", "full", "render", first), ("flowsynth cast_gbuffer", "cast", "cast", None),
            ("flowsynth kernel only", "cast", "kernel", None), ("flowsynth raw kernel", "raw", "raw", None)]
    result = {"depth": out["depth"][0, 0].numpy().astype(np.float64).reshape(-1),
              "instance": out["instance"][0, 0].numpy().reshape(-1).astype(np.int64) - 1,
              "normal": out["normals"][0].numpy().reshape(3, -1).T.astype(np.float64),
              "dist": gb.host().dist.reshape(-1).astype(np.float64)}
    return Engine(fns, rows, {"first_call_s": first}, result)


def setup_embree(scene: fs.Scene, dirs: np.ndarray) -> Engine:
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    V, F, faces_per = world_triangles(scene)
    V32 = V.astype(np.float32)
    origins = np.zeros((len(dirs), 3), np.float32)
    d32 = np.ascontiguousarray(dirs, dtype=np.float32)
    with Timer() as tm:
        esc = rtcore_scene.EmbreeScene()
        TriangleMesh(esc, V32, F)
        hit = esc.run(origins, d32, output=1)
    first = tm.wall_s

    def post(h: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """G-buffer from Embree's hits: depth [m], instance (-1 = none), unit camera-facing face normal."""
        prim = h["primID"]
        ok = prim >= 0
        tri = V32[F[np.where(ok, prim, 0)]]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n *= (-np.sign(np.einsum("ij,ij->i", n, d32)) / np.linalg.norm(n, axis=1))[:, None]
        n[~ok] = 0.0
        return np.where(ok, h["tfar"] * d32[:, 2], 0.0), np.where(ok, prim // faces_per, -1), n

    depth, inst, normal = post(hit)
    fns = {"embree_cast": lambda: esc.run(origins, d32, output=1), "embree_post": lambda: post(hit),
           "embree_raw": lambda: esc.run(origins, d32)}
    rows = [("Embree run + numpy post", "full", ("embree_cast", "embree_post"), None),
            ("Embree run(output=1)", "cast", "embree_cast", first),
            ("Embree run (primID only)", "raw", "embree_raw", None)]
    result = {"depth": depth.astype(np.float64), "instance": inst.astype(np.int64),
              "normal": normal.astype(np.float64), "dist": np.where(inst >= 0, hit["tfar"], 0.0).astype(np.float64)}
    return Engine(fns, rows, {"first_call_s": first, "triangles": len(F)}, result)


def setup_mitsuba(scene: fs.Scene, dirs: np.ndarray) -> Engine:
    """Mitsuba 3, llvm_ad_rgb variant: the world triangle soup as one ``mi.Mesh`` (filled through
    ``mi.traverse``), the same rays as one ``mi.Ray3f`` batch. "raw": ``ray_intersect_preliminary`` (t and
    primitive index evaluated); "cast": ``ray_intersect`` (t, primitive index and geometric normal)."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(1)
    V, F, faces_per = world_triangles(scene)
    t0 = time.perf_counter()
    mesh = mi.Mesh("spheres", vertex_count=len(V), face_count=len(F), has_vertex_normals=False,
                   has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(V.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(F.astype(np.uint32).ravel())
    params.update()
    msc = mi.load_dict({"type": "scene", "spheres": mesh})
    d32 = dirs.astype(np.float32)
    ray = mi.Ray3f(o=mi.Point3f(0.0, 0.0, 0.0), d=mi.Vector3f(*(mi.Float(d32[:, k]) for k in range(3))))
    dr.eval(ray)

    def raw():
        si = msc.ray_intersect_preliminary(ray, coherent=True)
        dr.eval(si.t, si.prim_index)
        dr.sync_thread()
        return si

    def cast():
        si = msc.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal, coherent=True)
        dr.eval(si.t, si.prim_index, si.n)
        dr.sync_thread()
        return si

    si = cast()
    first = time.perf_counter() - t0
    raw()
    t = si.t.numpy().astype(np.float64)
    ok = np.isfinite(t)
    n = si.n.numpy().reshape(3, -1).T.astype(np.float64) if si.n.numpy().shape[0] == 3 else si.n.numpy()
    n = n * -np.sign(np.einsum("ij,ij->i", n, dirs))[:, None]
    n[~ok] = 0.0
    prim = si.prim_index.numpy().astype(np.int64)
    result = {"depth": np.where(ok, t * dirs[:, 2], 0.0), "instance": np.where(ok, prim // faces_per, -1),
              "normal": n, "dist": np.where(ok, t, 0.0)}
    rows = [("Mitsuba ray_intersect", "cast", "mitsuba_cast", first),
            ("Mitsuba ray_intersect_preliminary", "raw", "mitsuba_raw", None)]
    engine = Engine({"mitsuba_cast": cast, "mitsuba_raw": raw}, rows,
                    {"first_call_s": first, "variant": mi.variant(), "mitsuba": mi.__version__}, result)
    engine.set_threads = dr.set_thread_count
    return engine


def setup_newton(scene: fs.Scene, dirs: np.ndarray) -> Engine:
    wp = wp_runtime()
    import newton
    from newton.sensors import SensorCamera

    t0 = time.perf_counter()
    builder = newton.ModelBuilder()
    mesh = scene.objects[0].mesh
    nmesh = newton.Mesh(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.int32).reshape(-1),
                        compute_inertia=False)
    for obj in scene.objects:
        P = obj.poses[0]
        xf = wp.transform(wp.vec3(*P[:3, 3]), wp.quat_from_matrix(wp.mat33(*P[:3, :3].reshape(-1))))
        builder.add_shape_mesh(-1, xform=xf, mesh=nmesh)
    model = builder.finalize(device="cpu")
    sensor = SensorCamera(model, load_textures=False)
    state = model.state()
    t_build = time.perf_counter() - t0
    H, W = HEIGHT, WIDTH
    bundle = np.zeros((H, W, 1, 2, 3), np.float32)
    bundle[:, :, 0, 1] = (dirs * np.array([1.0, -1.0, -1.0])).reshape(H, W, 3)
    rays = wp.array(bundle, dtype=wp.vec3f, device="cpu")
    cam_tf = wp.array([wp.transform(wp.vec3(0.0), wp.quat(1.0, 0.0, 0.0, 0.0))], dtype=wp.transformf, device="cpu")
    depth = sensor.allocate_image_depth(1, W, H)
    shape = sensor.allocate_image_shape_index(1, W, H)
    normal = sensor.allocate_image_normal(1, W, H)

    def update():
        sensor.update(state, cam_tf, rays, depth_image=depth, shape_index_image=shape, normal_image=normal)

    with Timer() as tm:
        update()
    first = tm.wall_s
    sid = shape.numpy().reshape(-1)
    ok = sid != NEWTON_NO_HIT
    dist = depth.numpy().reshape(-1).astype(np.float64)
    result = {"depth": np.where(ok, dist * dirs[:, 2], 0.0), "instance": np.where(ok, sid.astype(np.int64), -1),
              "normal": normal.numpy().reshape(-1, 3).astype(np.float64), "dist": np.where(ok, dist, 0.0)}
    rows = [("Newton SensorCamera.update", "cast", "newton_update", t_build + first)]
    return Engine({"newton_update": update}, rows, {"model_build_s": t_build, "first_update_s": first}, result)


def load_text() -> str:
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def all_cores(scene: fs.Scene, engines: dict, repeat: int) -> list[dict]:
    """flowsynth's cast (``threads`` = all) and Mitsuba (``dr.set_thread_count``) on every allowed core."""
    cpus = PINNING["affinity_before"]
    if len(cpus) < 2 or "flowsynth" not in engines:
        return []
    os.sched_setaffinity(0, set(cpus))
    n = len(cpus)
    meshes, cam_T_world, world_T_obj = scene_arrays(scene)
    accel = SceneAccel(meshes, cam_T_world, world_T_obj)
    fns = {("flowsynth cast_gbuffer", "cast", k): (lambda k=k: cast_gbuffer(accel, scene.camera, want_normals=True,
                                                                           want_points=False, threads=k))
           for k in (1, n)}
    mit = engines.get("mitsuba")
    for k in (1, n) if mit else ():
        def run(k=k, fn=mit.fns["mitsuba_cast"]):
            mit.set_threads(k)
            return fn()
        fns[("Mitsuba ray_intersect", "cast", k)] = run
    times = time_round_robin(fns, repeat=repeat, warmup=1)
    if mit:
        mit.set_threads(1)
    os.sched_setaffinity(0, set(PINNING["affinity"]))
    rows = [{"engine": e, "level": lv, "threads": k, "wall_ms": 1e3 * t["wall_s"],
             "Mrays_s_wall": WIDTH * HEIGHT / t["wall_s"] / 1e6} for (e, lv, k), t in times.items()]
    for r in rows:
        other = [x for x in rows if x["engine"].startswith("Mitsuba") and x["threads"] == r["threads"]]
        r["x_mitsuba"] = r["Mrays_s_wall"] / other[0]["Mrays_s_wall"] if other else None
    return rows


def _row(engine: str, level: str, t: dict, first: float | None = None) -> dict:
    rays = WIDTH * HEIGHT
    return {"engine": engine, "level": level, "first_s": first, "wall_ms": 1e3 * t["wall_s"],
            "cpu_ms": 1e3 * t["cpu_s"], "Mrays_s": rays / t["cpu_s"] / 1e6, "Mrays_s_wall": rays / t["wall_s"] / 1e6}


def compare(ref: dict, other: dict, dirs: np.ndarray) -> dict:
    """Hit-mask, id, depth and normal agreement of ``other`` against flowsynth's ``ref``."""
    h0, h1 = ref["instance"] >= 0, other["instance"] >= 0
    both = h0 & h1
    same = both & (ref["instance"] == other["instance"])
    rel = np.abs(other["depth"][same] - ref["depth"][same]) / ref["depth"][same]
    n0, n1 = ref["normal"][same], other["normal"][same]
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(n0, n1), axis=1), np.einsum("ij,ij->i", n0, n1)))
    grazing = np.abs(np.einsum("ij,ij->i", n0, dirs[same]))  # |cos| of the incidence angle
    bad = rel > DEPTH_REL_TOL
    return {
        "hit_pixels_flowsynth": int(h0.sum()), "hit_pixels_other": int(h1.sum()),
        "hit_mask_mismatch": int((h0 != h1).sum()), "instance_mismatch": int((both & ~same).sum()),
        "depth_rel_err_max": float(rel.max()), "depth_rel_err_p999": float(np.quantile(rel, 0.999)),
        "depth_rel_err_over_tol": int(bad.sum()),
        "over_tol_max_abs_cos_incidence": float(grazing[bad].max()) if bad.any() else None,
        "normal_angle_p999_deg": float(np.quantile(angle, 0.999)), "normal_angle_max_deg": float(angle.max()),
        "normal_angle_over_0.01deg": int((angle > 0.01).sum()),
    }


def _fmt_items(d: dict) -> str:
    return ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in d.items())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 timed rounds instead of 9")
    ap.add_argument("--skip", nargs="*", default=[], choices=["embree", "newton", "mitsuba"],
                    help="engines to leave out")
    ap.add_argument("--cold-cache", action="store_true",
                    help="compile Warp kernels into an empty kernel cache, so first_s includes compilation")
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.cold_cache:
        import atexit
        import shutil
        import tempfile

        import warp

        warp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="warp-cache-")
        atexit.register(shutil.rmtree, warp.config.kernel_cache_dir, ignore_errors=True)
    repeat = 3 if args.quick else 9
    t_start = time.perf_counter()
    scene = raycast_scene()
    dirs = pixel_dirs(scene.camera)
    engines, rows, errors = {}, [], {}
    setups = {"flowsynth": lambda: setup_flowsynth(scene), "embree": lambda: setup_embree(scene, dirs),
              "newton": lambda: setup_newton(scene, dirs), "mitsuba": lambda: setup_mitsuba(scene, dirs)}
    for name, setup in setups.items():
        if name in args.skip:
            continue
        try:
            engines[name] = setup()
        except Exception as exc:
            errors[name] = f"{type(exc).__name__}: {exc}"
            rows.append({"engine": name, "note": f"failed: {errors[name]}"})
    fns = {k: f for e in engines.values() for k, f in e.fns.items()}
    times = time_round_robin(fns, repeat=repeat, warmup=1)
    for e in engines.values():
        for engine, level, keys, first in e.rows:
            keys = keys if isinstance(keys, tuple) else (keys,)
            rows.insert(len(rows) - len(errors), _row(engine, level, {c: sum(times[k][c] for k in keys)
                                                                      for c in ("wall_s", "cpu_s")}, first))
        e.info.update({f"{k}_cpu_ms": 1e3 * times[k]["cpu_s"] for k in e.fns})

    # Ratios compare like with like: "full" rows end in depth/instance/normal arrays ready to use, "cast"
    # rows in raw hits (distance, primitive or shape id, normal). Newton's update is a cast-level row.
    ref = {(r["level"], r["engine"].split()[0]): r["Mrays_s"] for r in rows if r.get("Mrays_s")}
    newton_rate = ref.get(("cast", "Newton"))
    for r in rows:
        if r.get("Mrays_s"):
            embree_rate = ref.get((r["level"], "Embree"))
            r["x_embree"] = r["Mrays_s"] / embree_rate if embree_rate else None
            r["x_newton"] = r["Mrays_s"] / newton_rate if newton_rate else None
            mitsuba_rate = ref.get((r["level"], "Mitsuba"))
            r["x_mitsuba"] = r["Mrays_s"] / mitsuba_rate if mitsuba_rate else None
    names = {"x_embree": "Embree (same level)", "x_newton": "Newton", "x_mitsuba": "Mitsuba (same level)"}
    ratios = {f"{r['engine']} / {names[k]}": r[k]
              for r in rows if r["engine"].startswith("flowsynth") for k in names if r.get(k)}
    multi = all_cores(scene, engines, repeat)
    ours = engines.get("flowsynth")
    agreement = {k: compare(ours.result, engines[k].result, dirs) for k in ("embree", "newton", "mitsuba")
                 if ours and k in engines}
    hit_frac = float((ours.result["instance"] >= 0).mean()) if ours else float("nan")

    info = machine_info(extra_packages=("embreex", "mitsuba"))
    print(f"G-buffer cast (depth + instance + normals): {RAYCAST_SPHERES} icospheres x "
          f"{len(scene.objects[0].mesh.faces)} faces, {WIDTH}x{HEIGHT} = {WIDTH * HEIGHT} rays, "
          f"hit fraction {hit_frac:.3f}; medians of {repeat} round-robin rounds; Mrays/s from process CPU time")
    print(f"{info['cpu_model']} ({info['cpu_count']} CPUs), affinity {PINNING['affinity']}, torch threads "
          f"{torch.get_num_threads()}, warp {info['warp-lang']}, newton {info['newton']}, embreex {info['embreex']}")
    print_table(rows, ["engine", "level", "first_s", "wall_ms", "cpu_ms", "Mrays_s", "Mrays_s_wall",
                       "x_embree", "x_newton", "x_mitsuba", "note"])
    if multi:
        print(f"\nAll {len(PINNING['affinity_before'])} allowed cores (wall-clock medians; Embree's TBB pool "
              f"was sized at import on one core, so it is not in this table); {load_text()}")
        print_table(multi, ["engine", "level", "threads", "wall_ms", "Mrays_s_wall", "x_mitsuba"])
    for name, e in engines.items():
        print(f"{name}: {_fmt_items(e.info)}")
    for name, a in agreement.items():
        print(f"flowsynth vs {name}: {_fmt_items(a)}")
    total = time.perf_counter() - t_start
    print(f"total {total:.1f} s")
    path = write_json("raycast", {
        "machine": info, "pinning": PINNING, "torch_threads": torch.get_num_threads(),
        "setup": {"width": WIDTH, "height": HEIGHT, "fov_deg": FOV_DEG, "K": scene.camera.K,
                  "spheres": RAYCAST_SPHERES, "faces_per_sphere": len(scene.objects[0].mesh.faces),
                  "z_range_m": RAYCAST_Z_RANGE, "hit_fraction": hit_frac, "repeat": repeat, "quick": args.quick,
                  "cold_cache": args.cold_cache, "rate_clock": "process CPU time (median)"},
        "rows": rows, "ratios": ratios, "details": {k: e.info for k, e in engines.items()}, "errors": errors,
        "agreement": agreement, "timings": times, "total_s": total, "all_cores": multi,
        "loadavg_1_5_15": os.getloadavg(),
    })
    timed = [r for r in rows if r.get("Mrays_s")]
    save_plot("raycast", [r["engine"] for r in timed], [r["Mrays_s"] for r in timed], "Mrays/s (1 core)",
              "G-buffer cast, 640x480, 30 x 5120 triangles")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
