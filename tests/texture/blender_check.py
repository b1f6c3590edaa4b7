"""Run inside Blender (bpy) by test_blender.py: exercise the add-on, report what Blender sees.

    python blender_check.py -- TEXTURE_JSON OUT_JSON [--pixel ROW COL ...] [--bad TEXTURE_JSON ...]

Writes OUT_JSON with: registration checks; per view camera the projection of every
imported mesh vertex through ``world_to_camera_view`` in OpenCV pixel coordinates (pixel
centres integer, v down); the mesh vertices in Blender's world frame; the base-colour
texture's size and the requested pixels (row, col from the top, 0-255); the error each
``--bad`` result gives; and, with ``--render``, a render through each view camera.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import bpy
from bpy_extras.object_utils import world_to_camera_view
from mathutils import Vector

# The driver sets PYTHONPATH, which a Blender executable ignores: add toolbox/ here too.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "toolbox"))

import slscan_blender
from slscan_blender.importer import use_view


def registration() -> dict:
    out = {}
    slscan_blender.register()
    out["registered_operator"] = hasattr(bpy.types, "IMPORT_SCENE_OT_slscan")
    out["menu_entry"] = any(
        getattr(f, "__name__", "") == "menu_func_import"
        and f.__module__.startswith("slscan_blender")
        for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    )
    slscan_blender.unregister()
    out["operator_after_unregister"] = hasattr(bpy.types, "IMPORT_SCENE_OT_slscan")
    out["menu_after_unregister"] = any(
        getattr(f, "__module__", "").startswith("slscan_blender")
        for f in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    )
    slscan_blender.register()  # a second cycle must work too (add-on disabled and enabled again)
    slscan_blender.unregister()
    slscan_blender.register()
    return out


def texture_image():
    for obj in bpy.context.scene.objects:
        if obj.type != "MESH":
            continue
        for mat in obj.data.materials:
            for node in mat.node_tree.nodes:
                if node.type == "TEX_IMAGE" and node.image is not None:
                    # the image must feed the Principled BSDF's Base Color
                    linked = any(
                        link.to_socket.name == "Base Color"
                        for link in mat.node_tree.links
                        if link.from_node == node
                    )
                    return node.image, linked
    return None, False


def render_silhouettes(scene, folder: str) -> None:
    """Render each view camera at its view's resolution: Cycles, a uniform white world (so
    a diffuse convex model shows its albedo), transparent film, Standard view transform."""
    world = bpy.data.worlds.new("white")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    scene.world = world
    scene.view_settings.view_transform = "Standard"
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.cycles.use_denoising = False
    scene.render.film_transparent = True
    scene.render.filter_size = 0.01  # no pixel filter: alpha is coverage of the pixel centre
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    for cam in [o for o in scene.objects if o.type == "CAMERA"]:
        use_view(scene, cam)
        scene.render.filepath = os.path.join(folder, cam.data["slscan_view"] + ".png")
        bpy.ops.render.render(write_still=True)


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("texture_json")
    parser.add_argument("out_json")
    parser.add_argument("--pixel", nargs=2, type=int, action="append", default=[])
    parser.add_argument("--bad", action="append", default=[])
    parser.add_argument(
        "--render", help="folder for a silhouette render (RGBA PNG) per view camera"
    )
    args = parser.parse_args(argv)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    out = {"registration": registration()}
    bpy.ops.import_scene.slscan(filepath=args.texture_json)
    scene = bpy.context.scene

    meshes = [o for o in scene.objects if o.type == "MESH"]
    verts = [list(o.matrix_world @ v.co) for o in meshes for v in o.data.vertices]
    out["vertices_blender"] = verts

    image, linked = texture_image()
    out["texture"] = None
    if image is not None:
        w, h = image.size
        px = image.pixels[:]  # float RGBA, rows from the bottom
        out["texture"] = {
            "size": [w, h],
            "base_color_linked": linked,
            "pixels": [
                [round(255 * px[((h - 1 - r) * w + c) * 4 + k]) for k in range(3)]
                for r, c in args.pixel
            ],
        }

    out["cameras"] = {}
    for cam in [o for o in scene.objects if o.type == "CAMERA"]:
        use_view(scene, cam)
        w, h = scene.render.resolution_x, scene.render.resolution_y
        uv = []
        for co in verts:
            ndc = world_to_camera_view(scene, cam, Vector(co))
            uv.append([ndc.x * w - 0.5, (1.0 - ndc.y) * h - 0.5, ndc.z])
        out["cameras"][cam.data["slscan_view"]] = {
            "object": cam.name,
            "collections": [c.name for c in cam.users_collection],
            "resolution": [w, h],
            "uvz": uv,
        }

    if args.render:
        render_silhouettes(scene, args.render)

    out["bad"] = {}
    for bad in args.bad:
        try:
            bpy.ops.import_scene.slscan(filepath=bad)
            out["bad"][bad] = None
        except RuntimeError as exc:
            out["bad"][bad] = str(exc)

    with open(args.out_json, "w", encoding="utf-8") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1 :] if "--" in sys.argv else sys.argv[1:])
