"""Blender side of benchmarks/peers/cycles.py: build an exported flowsynth scene in Blender and render it with Cycles.

    blender -b --factory-startup -noaudio -P benchmarks/peers/_cycles_scene.py -- SCENE.json OUT_DIR CONFIG [REPEAT]

Runs inside Blender's own Python (``bpy``, standard library only: a distribution's Blender may run on a
system Python without numpy), never imported by flowsynth. ``SCENE.json`` is written by
``benchmarks/peers/cycles.py`` (``export_scene``): per object the object-frame mesh, the (T, 4, 4) world_T_obj
poses, the instance id and a base colour; the camera K, size and (T, 4, 4) world_T_cam (OpenCV axes); the
lights. CONFIG is "direct" (light paths max_bounces = 0: camera ray, then
one shadow ray per light sample, like flowsynth's "direct" mode) or "path" (Cycles' default light paths).

Cycles: CPU, 1 sample, no denoising or adaptive sampling, FIXED 1 thread, box pixel filter of width 0.01
px (so the one sample goes through the pixel centre, like flowsynth's ground truth), compositing and
sequencer off, passes Combined, Z, Normal, Vector and IndexOB (object index = flowsynth instance id).
Frame t of the scene is Blender frame t + 1; every object and the camera carry one keyframe per frame, so
Cycles' Vector pass sees the same motion. Each frame is rendered ``REPEAT`` times (``bpy.ops.render.render``,
timed with wall clock and process CPU time; each call syncs the scene and builds the BVH anew, persistent
data off), and the last render of each frame is saved as a 32-bit multilayer EXR (not timed).

Writes OUT_DIR/cycles_<CONFIG>.json: start-up (``t_script`` = time.time() when this script starts, for the
caller to subtract its launch time), scene build time, per-frame render times, Blender and Cycles details.
"""

import json
import math
import os
import sys
import time

T_SCRIPT = time.time()

import bpy
from mathutils import Matrix

SENSOR_WIDTH = 36.0  # [mm]; any value works, the focal length is set relative to it


def _args():
    argv = sys.argv[sys.argv.index("--") + 1:]
    return argv[0], argv[1], argv[2], int(argv[3]) if len(argv) > 3 else 1


def _clear():
    for coll in (bpy.data.objects, bpy.data.meshes, bpy.data.lights, bpy.data.cameras, bpy.data.materials):
        for item in list(coll):
            coll.remove(item)


def _material(name, rgb, roughness, specular):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*[float(c) for c in rgb], 1.0)
    bsdf.inputs["Roughness"].default_value = float(roughness)
    bsdf.inputs["Specular"].default_value = float(specular)
    return mat


def _keyframe_pose(obj, poses):
    """One keyframe per frame: Blender frame t + 1 holds world_T_obj[t] (rigid: location + quaternion)."""
    obj.rotation_mode = "QUATERNION"
    for t, pose in enumerate(poses):
        loc, rot, _ = Matrix(pose).decompose()
        obj.location = loc
        obj.rotation_quaternion = rot
        obj.keyframe_insert("location", frame=t + 1)
        obj.keyframe_insert("rotation_quaternion", frame=t + 1)


def build(json_path):
    with open(json_path) as f:
        d = json.load(f)
    scene = bpy.context.scene
    T = int(d["num_frames"])
    W, H = int(d["width"]), int(d["height"])
    K = d["K"]
    meshes = {}
    for i, inst in enumerate(d["instances"]):
        asset = int(d["assets"][i])
        if asset not in meshes:
            V, F = d["meshes"][str(asset)]
            me = bpy.data.meshes.new(f"asset{asset}")
            me.vertices.add(len(V))
            me.vertices.foreach_set("co", [x for v in V for x in v])
            me.loops.add(3 * len(F))
            me.loops.foreach_set("vertex_index", [x for f in F for x in f])
            me.polygons.add(len(F))
            me.polygons.foreach_set("loop_start", range(0, 3 * len(F), 3))
            me.polygons.foreach_set("loop_total", [3] * len(F))
            me.update(calc_edges=True)
            me.validate()
            me.materials.append(None)  # one slot, filled per object below
            meshes[asset] = me
        ob = bpy.data.objects.new(f"inst{inst}", meshes[asset])
        ob.pass_index = int(inst)
        # Per-object material on the object's slot (instances sharing a mesh keep their own colours).
        ob.material_slots[0].link = "OBJECT"
        ob.material_slots[0].material = _material(f"mat{inst}", d["colors"][i], d["roughness"][i],
                                                  d["specular"][i])
        scene.collection.objects.link(ob)
        _keyframe_pose(ob, d["poses"][i])
    # Camera: OpenCV axes (x right, y down, z forward) -> Blender camera axes (x right, y up, looking down -z).
    cam_data = bpy.data.cameras.new("cam")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.sensor_width = SENSOR_WIDTH
    cam_data.lens = float(K[0][0]) * SENSOR_WIDTH / W
    # flowsynth puts pixel centres at integer coordinates, so the image centre is ((W-1)/2, (H-1)/2); Blender's
    # shift is in units of the larger image side, positive shift_x moves the optical axis left in the image.
    cam_data.shift_x = -(float(K[0][2]) - (W - 1) / 2) / max(W, H)
    cam_data.shift_y = (float(K[1][2]) - (H - 1) / 2) / max(W, H)
    cam_data.clip_start, cam_data.clip_end = 1e-3, 1e4
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    flip = Matrix.Diagonal((1.0, -1.0, -1.0, 1.0))
    _keyframe_pose(cam, [Matrix(P) @ flip for P in d["world_T_cam"]])
    scene.camera = cam
    # Lights (flowsynth units -> Blender): point intensity I (white diffuse at r has radiance I / r^2) ->
    # power 4 pi^2 I [W]; directional intensity I (radiance I) -> sun strength pi I [W/m^2]; ambient -> the
    # world background colour (uniform sky radiance). Point lights are hard (radius 0), suns have angle 0.
    for j, (kind, color, intensity, direction, position) in enumerate(zip(
            d["light_kind"], d["light_color"], d["light_intensity"], d["light_direction"],
            d["light_position"])):
        if kind == "ambient":
            world = bpy.data.worlds.new("world")
            world.use_nodes = True
            bg = world.node_tree.nodes["Background"]
            bg.inputs["Color"].default_value = (*[float(c) for c in color], 1.0)
            bg.inputs["Strength"].default_value = float(intensity)
            scene.world = world
            continue
        ld = bpy.data.lights.new(f"light{j}", "POINT" if kind == "point" else "SUN")
        ld.color = [float(c) for c in color]
        if kind == "point":
            ld.energy = float(4 * math.pi ** 2 * intensity)
            ld.shadow_soft_size = 0.0
        else:
            ld.energy = float(math.pi * intensity)
            ld.angle = 0.0
        lo = bpy.data.objects.new(f"light{j}", ld)
        if kind == "point":
            lo.location = [float(x) for x in position]
        else:  # a sun shines along its local -z
            lo.rotation_mode = "QUATERNION"
            from mathutils import Vector
            lo.rotation_quaternion = Vector([-float(x) for x in direction]).to_track_quat("Z", "Y")
        scene.collection.objects.link(lo)
    scene.frame_start, scene.frame_end = 1, T
    scene.render.fps = int(round(float(d["fps"])))
    scene.render.resolution_x, scene.render.resolution_y = W, H
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    return T


def settings(config):
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    cy = scene.cycles
    cy.device = "CPU"
    cy.samples = 1
    cy.preview_samples = 1
    cy.use_denoising = False
    cy.use_adaptive_sampling = False
    cy.pixel_filter_type = "BOX"
    cy.filter_width = 0.01
    cy.seed = 0
    if config == "direct":
        cy.max_bounces = 0
    elif config != "path":
        raise SystemExit(f"unknown config {config!r}")
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 1
    scene.render.use_persistent_data = False
    scene.render.use_motion_blur = False
    scene.render.use_compositing = False
    scene.render.use_sequencer = False
    scene.render.dither_intensity = 0.0
    scene.view_settings.view_transform = "Standard"
    vl = scene.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = True
    vl.use_pass_normal = True
    vl.use_pass_vector = True
    vl.use_pass_object_index = True
    im = scene.render.image_settings
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"
    im.exr_codec = "NONE"


def main():
    scene_path, out_dir, config, repeat = _args()
    t0 = time.perf_counter()
    _clear()
    T = build(scene_path)
    settings(config)
    t_build = time.perf_counter() - t0
    scene = bpy.context.scene
    frames = []
    for t in range(T):
        scene.frame_set(t + 1)
        wall, cpu = [], []
        for _ in range(repeat):
            w0, c0 = time.perf_counter(), time.process_time()
            bpy.ops.render.render(write_still=False)
            cpu.append(time.process_time() - c0)
            wall.append(time.perf_counter() - w0)
        path = os.path.join(out_dir, f"cycles_{config}_{t}.exr")
        bpy.data.images["Render Result"].save_render(filepath=path)
        frames.append({"frame": t, "wall_s": wall, "cpu_s": cpu, "exr": path})
    info = {"config": config, "t_script": T_SCRIPT, "build_s": t_build, "frames": frames, "repeat": repeat,
            "blender": bpy.app.version_string, "threads": scene.render.threads,
            "max_bounces": scene.cycles.max_bounces, "samples": scene.cycles.samples,
            "objects": len([o for o in scene.objects if o.type == "MESH"])}
    with open(os.path.join(out_dir, f"cycles_{config}.json"), "w") as f:
        json.dump(info, f, indent=1)


main()
