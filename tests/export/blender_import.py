"""Run inside Blender: ``blender -b --factory-startup -P blender_import.py -- JOB.json``, or
``... -- FILE.bvh --png OUT.png [--frame N]`` to render one frame of a BVH (N counts from 0).

Imports each BVH of the job with Blender's own importer (``import_anim.bvh``, Y up,
forward -Z: Blender's default) and writes what Blender made of it to the job's ``out``
JSON: per file, the armature's rest-pose bone heads and tails (by bone name) and, at the
job's sampled frames, every bone's world head position. With ``render`` it also renders
one frame of the first file to a PNG (Cycles on the CPU: spheres at the joints, rods
along the bones, a floor, a camera). No numpy here: Blender's Python has none; the
checking is done by check.py outside.

Debian's Blender 3.4 importer opens files with mode "rU", which Python 3.11 refuses;
the importer's module gets an ``open`` that drops the "U".
"""

import builtins
import json
import math
import sys

import bpy
from mathutils import Vector

import io_anim_bvh.import_bvh as import_bvh


def _open_without_u(file, mode="r", *args, **kwargs):
    return builtins.open(file, mode.replace("U", ""), *args, **kwargs)


import_bvh.open = _open_without_u  # module global: shadows the builtin for the importer only


def clear_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)


def import_bvh_file(path):
    before = set(bpy.data.objects)
    bpy.ops.import_anim.bvh(filepath=path, axis_forward="-Z", axis_up="Y", rotate_mode="NATIVE",
                            update_scene_fps=True, update_scene_duration=True)
    new = [o for o in bpy.data.objects if o not in before and o.type == "ARMATURE"]
    assert len(new) == 1, f"expected one armature from {path}, got {new}"
    return new[0]


def world_heads(arm):
    mw = arm.matrix_world
    return {pb.name: list(mw @ pb.head) for pb in arm.pose.bones}


def render(arm, frame, png):
    scene = bpy.context.scene
    scene.frame_set(frame)
    heads = world_heads(arm)
    tails = {pb.name: arm.matrix_world @ pb.tail for pb in arm.pose.bones}
    names = [b.name for b in arm.data.bones]
    floor = min(v[2] for v in heads.values()) - 0.03
    skin = bpy.data.materials.new("skin")
    skin.diffuse_color = (0.85, 0.45, 0.2, 1.0)
    skin.use_nodes = True
    skin.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.85, 0.45, 0.2, 1.0)
    for name in names:
        h = Vector(heads[name])
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.035, location=h, segments=16, ring_count=8)
        bpy.context.object.data.materials.append(skin)
        bone = arm.data.bones[name]
        ends = [Vector(heads[c.name]) for c in bone.children] or [tails[name]]
        for e in ends:
            d = e - h
            if d.length < 1e-4:
                continue
            bpy.ops.mesh.primitive_cylinder_add(radius=0.02, depth=d.length, location=h + d / 2, vertices=12)
            rod = bpy.context.object
            rod.rotation_mode = "QUATERNION"
            rod.rotation_quaternion = Vector((0, 0, 1)).rotation_difference(d.normalized())
            rod.data.materials.append(skin)
    bpy.ops.mesh.primitive_plane_add(size=8, location=(heads["pelvis"][0], heads["pelvis"][1], floor))
    center = Vector(heads["pelvis"])
    bpy.ops.object.light_add(type="SUN", location=(center.x + 2, center.y - 3, center.z + 4))
    bpy.context.object.data.energy = 4.0
    bpy.context.object.rotation_euler = (math.radians(40), 0, math.radians(30))
    bpy.ops.object.camera_add(location=(center.x + 2.2, center.y - 3.6, center.z + 0.6))
    cam = bpy.context.object
    track = cam.constraints.new("TRACK_TO")
    target = bpy.data.objects.new("target", None)
    scene.collection.objects.link(target)
    target.location = center + Vector((0, 0, -0.1))
    track.target = target
    scene.camera = cam
    world = bpy.data.worlds.new("world")
    world.color = (0.6, 0.7, 0.8)
    scene.world = world
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.cycles.use_denoising = False
    scene.render.resolution_x, scene.render.resolution_y = 640, 480
    scene.render.filepath = png
    bpy.ops.render.render(write_still=True)


def main():
    args = sys.argv[sys.argv.index("--") + 1:]
    if not args[0].endswith(".json"):  # blender_import.py -- FILE.bvh --png OUT.png [--frame N]
        clear_scene()
        arm = import_bvh_file(args[0])
        start, end = arm.animation_data.action.frame_range  # the file's frames 0.. at start..
        frame = int(args[args.index("--frame") + 1]) if "--frame" in args else int(end - start) // 2
        render(arm, 1 + frame, args[args.index("--png") + 1])
        print(f"blender_import: rendered frame {frame} of {args[0]}")
        return
    job = json.load(open(args[0]))
    out = {}
    for item in job["files"]:
        clear_scene()
        arm = import_bvh_file(item["bvh"])
        rest = {b.name: {"head": list(arm.matrix_world @ b.head_local), "tail": list(arm.matrix_world @ b.tail_local)}
                for b in arm.data.bones}
        frames = {}
        for i in item["frames"]:
            bpy.context.scene.frame_set(1 + i)  # the importer puts the file's frame i at frame_start + i
            frames[str(i)] = world_heads(arm)
        out[item["bvh"]] = {"rest": rest, "frames": frames, "fps": bpy.context.scene.render.fps / bpy.context.scene.render.fps_base,
                            "frame_end": bpy.context.scene.frame_end}
    if job.get("render"):
        r = job["render"]
        clear_scene()
        arm = import_bvh_file(r["bvh"])
        render(arm, 1 + r["frame"], r["png"])
    with open(job["out"], "w") as f:
        json.dump(out, f)
    print(f"blender_import: {len(out)} files imported")


main()
