"""Headless entry points slscan runs in a background Blender: import summary and preview render.

Run as a script, with bpy (``python batch.py -- ARGS``) or in Blender
(``blender -b --factory-startup --python batch.py -- ARGS``)::

    summary TEXTURE_JSON OUT_JSON
    preview TEXTURE_JSON OUT_PNG --width W --height H --samples N

Both register the add-on, import the result through ``bpy.ops.import_scene.slscan`` and
write their output file; errors go to stderr and the exit status is non-zero.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys

if __name__ == "__main__":  # run as a script: make the add-on importable as a package
    _here = os.path.dirname(os.path.abspath(__file__))
    sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _here]
    sys.path.insert(0, os.path.dirname(_here))

import bpy
import numpy as np  # Blender's own numpy (< 2)
from mathutils import Matrix, Vector

import slscan_blender


def _fresh_scene() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)


def _import(texture_json: str) -> None:
    slscan_blender.register()
    try:
        bpy.ops.import_scene.slscan(filepath=texture_json)
    except RuntimeError as exc:  # the operator's self.report({'ERROR'}, ...)
        raise SystemExit(f"slscan import failed: {exc}") from None


def _material_summary(mat) -> dict:
    out = {"name": mat.name, "image_texture": False, "image": None}
    if mat.node_tree is None:
        return out
    for node in mat.node_tree.nodes:
        if node.type == "TEX_IMAGE" and node.image is not None:
            out["image_texture"] = True
            out["image"] = {"name": node.image.name, "size": list(node.image.size)}
            break
    return out


def summary() -> dict:
    """What the scene holds after an import: objects, meshes, materials, cameras."""
    scene = bpy.context.scene
    objects, meshes, cameras = [], [], []
    for obj in scene.objects:
        objects.append(
            {
                "name": obj.name,
                "type": obj.type,
                "collections": [c.name for c in obj.users_collection],
            }
        )
        if obj.type == "MESH":
            mesh = obj.data
            meshes.append(
                {
                    "name": obj.name,
                    "vertices": len(mesh.vertices),
                    "faces": len(mesh.polygons),
                    "triangles": sum(len(p.vertices) - 2 for p in mesh.polygons),
                    "uv_layers": [uv.name for uv in mesh.uv_layers],
                    "materials": [_material_summary(m) for m in mesh.materials if m is not None],
                    "matrix_world": [list(r) for r in obj.matrix_world],
                }
            )
        elif obj.type == "CAMERA" and "slscan_width" in obj.data:
            cam = obj.data
            bg = [b.image for b in cam.background_images if b.image is not None]
            cameras.append(
                {
                    "name": obj.name,
                    "view": cam["slscan_view"],
                    "matrix_world": [list(r) for r in obj.matrix_world],
                    "lens": cam.lens,
                    "sensor_width": cam.sensor_width,
                    "sensor_fit": cam.sensor_fit,
                    "shift_x": cam.shift_x,
                    "shift_y": cam.shift_y,
                    "resolution": [cam["slscan_width"], cam["slscan_height"]],
                    "pixel_aspect": [cam["slscan_pixel_aspect_x"], cam["slscan_pixel_aspect_y"]],
                    "background_image": (
                        {
                            "name": bg[0].name,
                            "size": list(bg[0].size),
                            "filepath": bpy.path.abspath(bg[0].filepath),
                        }
                        if bg
                        else None
                    ),
                }
            )
    return {
        "blender": bpy.app.version_string,
        "objects": objects,
        "meshes": meshes,
        "cameras": cameras,
        "scene_camera": scene.camera.name if scene.camera else None,
        "resolution": [scene.render.resolution_x, scene.render.resolution_y],
    }


def _look_at(eye: Vector, target: Vector, up: Vector) -> Matrix:
    """Camera matrix_world at ``eye`` looking at ``target`` (Blender camera: -z forward, y up)."""
    forward = (target - eye).normalized()
    right = forward.cross(up)
    if right.length < 1e-6:  # up parallel to the view: any perpendicular will do
        right = forward.orthogonal()
    right.normalize()
    true_up = right.cross(forward)
    rot = Matrix((right, true_up, -forward)).transposed()
    out = rot.to_4x4()
    out.translation = eye
    return out


def _world_vertices(objs) -> np.ndarray:
    """(n, 3) float64 vertex positions of the mesh objects, Blender world frame (m)."""
    out = []
    for obj in objs:
        co = np.empty(3 * len(obj.data.vertices), np.float32)
        obj.data.vertices.foreach_get("co", co)
        m = np.array(obj.matrix_world, np.float64)
        out.append(co.reshape(-1, 3).astype(np.float64) @ m[:3, :3].T + m[:3, 3])
    return np.concatenate(out) if out else np.zeros((0, 3))


def _framing_distance(
    points: np.ndarray, centre, direction, up, tan_x: float, tan_y: float
) -> float:
    """Smallest distance from ``centre`` along ``direction`` at which a camera looking back at
    ``centre`` sees every point within the half-angles' tangents ``tan_x``, ``tan_y``."""
    forward = -np.asarray(direction)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    rel = points - np.asarray(centre)
    along = rel @ np.asarray(direction)
    need = np.maximum(along + np.abs(rel @ right) / tan_x, along + np.abs(rel @ true_up) / tan_y)
    return float(need.max())


def preview(out_png: str, width: int, height: int, samples: int) -> None:
    """Render a lit 3/4 view of the imported model with Cycles on the CPU, framed to fit."""
    scene = bpy.context.scene
    meshes = [o for o in scene.objects if o.type == "MESH"]
    if not meshes:
        raise SystemExit("slscan preview: the result has no mesh to render")
    for obj in meshes:  # a glb without normals imports flat-shaded: smooth it for the picture
        if not obj.data.has_custom_normals:
            obj.data.shade_smooth()
    points = _world_vertices(meshes)
    if len(points) == 0:
        raise SystemExit("slscan preview: the result's mesh has no vertices")
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, radius = Vector((lo + hi) / 2), max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    views = [o for o in scene.objects if o.type == "CAMERA" and "slscan_width" in o.data]
    if views:  # look from the first scanner view's side, turned 30 deg and raised 20 deg
        ref = views[0].matrix_world
        back, up = ref.col[2].to_3d().normalized(), ref.col[1].to_3d().normalized()
    else:  # glTF's Y-up is Blender's Z-up: a classic 3/4 view
        back, up = Vector((0.0, -1.0, 0.0)), Vector((0.0, 0.0, 1.0))
    side = up.cross(back).normalized()
    direction = Matrix.Rotation(math.radians(30), 3, up) @ back
    direction = (Matrix.Rotation(math.radians(-20), 3, side) @ direction).normalized()

    cam = bpy.data.cameras.new("slscan preview")
    cam.sensor_fit = "AUTO"
    cam.lens = 50.0
    tan_long = cam.sensor_width / 2 / cam.lens  # AUTO fit: the sensor spans the longer side
    tan_x, tan_y = (
        (tan_long, tan_long * height / width)
        if width >= height
        else (tan_long * width / height, tan_long)
    )
    margin = 0.9  # the model fills 90% of the frame
    distance = _framing_distance(points, centre, direction, up, margin * tan_x, margin * tan_y)
    cam.clip_start, cam.clip_end = distance / 100, distance + 4 * radius
    cam_obj = bpy.data.objects.new("slscan preview", cam)
    scene.collection.objects.link(cam_obj)
    cam_obj.matrix_world = _look_at(centre + direction * distance, centre, up)
    scene.camera = cam_obj

    # Lighting: a key sun from over the camera's shoulder plus a soft grey world.
    sun = bpy.data.lights.new("slscan key", type="SUN")
    sun.energy = 3.0
    sun.angle = math.radians(10)
    sun_obj = bpy.data.objects.new("slscan key", sun)
    scene.collection.objects.link(sun_obj)
    key_dir = Matrix.Rotation(math.radians(-35), 3, up) @ direction
    key_dir = (Matrix.Rotation(math.radians(-25), 3, side) @ key_dir).normalized()
    sun_obj.matrix_world = _look_at(centre + key_dir, centre, up)
    world = bpy.data.worlds.new("slscan preview")
    world.use_nodes = True
    bg = world.node_tree.nodes.get("Background")
    bg.inputs["Color"].default_value = (0.8, 0.8, 0.8, 1.0)
    bg.inputs["Strength"].default_value = 0.6
    scene.world = world

    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = max(1, int(samples))
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 4
    render.resolution_x, render.resolution_y = int(width), int(height)
    render.resolution_percentage = 100
    render.pixel_aspect_x = render.pixel_aspect_y = 1.0
    render.film_transparent = False
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGB"
    render.image_settings.color_depth = "8"
    scene.view_settings.view_transform = "Standard"  # texture colours as they are, not filmic
    render.filepath = out_png
    bpy.ops.render.render(write_still=True)
    if not os.path.isfile(out_png) or os.path.getsize(out_png) == 0:
        raise SystemExit(f"slscan preview: Blender wrote no image at {out_png}")


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="slscan_blender.batch")
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("summary")
    p.add_argument("texture_json")
    p.add_argument("out_json")
    p = sub.add_parser("preview")
    p.add_argument("texture_json")
    p.add_argument("out_png")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--samples", type=int, default=16)
    args = parser.parse_args(argv)
    _fresh_scene()
    _import(args.texture_json)
    if args.command == "summary":
        with open(args.out_json, "w", encoding="utf-8") as f:
            json.dump(summary(), f, indent=1)
    else:
        preview(os.path.abspath(args.out_png), args.width, args.height, args.samples)


def script_args(argv: list[str]) -> list[str]:
    """The arguments after ``--`` (Blender's convention), else all but the script name."""
    return argv[argv.index("--") + 1 :] if "--" in argv else argv[1:]


if __name__ == "__main__":
    main(script_args(sys.argv))
