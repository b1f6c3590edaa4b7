"""Import an slscan texture result (``texture.json``) into Blender: model, view cameras, images.

Frames and conventions (the texture stage's ``texture.json``):

- slscan's world frame is in mm. ``gltf_from_world`` (4x4) maps it to the glb's frame
  (metres, glTF Y-up); Blender's glTF importer turns glTF (x, y, z) into Blender
  (x, -z, y). A point therefore reaches Blender as ``GLTF_TO_BLENDER @ gltf_from_world @ p``.
- A view's ``world_from_camera`` maps OpenCV camera coordinates (x right, y down, z forward)
  to the world; a Blender camera looks down its local -z with y up, hence
  ``OPENCV_TO_BLENDER_CAMERA = diag(1, -1, -1)`` on the camera side.
- Intrinsics are OpenCV's (pixel centres at integer coordinates). Blender's camera has one
  focal length, a horizontal or vertical sensor fit and a shift measured in units of the
  fitted image side; ``fx != fy`` becomes the scene's pixel aspect, which is a scene
  setting, so each camera keeps its view's intrinsics as custom properties and
  :func:`use_view` applies them to the scene (resolution, pixel aspect, active camera).

This module must not import slscan: it runs in Blender's own Python.
"""

from __future__ import annotations

import json
import math
import os

import bpy
from mathutils import Matrix

FORMAT = "slscan-texture"
VERSION = 1
VIEWS_COLLECTION = "slscan views"
SENSOR_WIDTH_MM = 36.0

# glTF (x, y, z) -> Blender (x, -z, y), as Blender's glTF importer does.
GLTF_TO_BLENDER = Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))
# OpenCV camera axes (x right, y down, z forward) -> Blender camera axes (x right, y up, -z forward).
OPENCV_TO_BLENDER_CAMERA = Matrix.Diagonal((1, -1, -1, 1))


class ResultError(Exception):
    """The result folder is not one this add-on can import; the message says why."""


# --- reading texture.json -----------------------------------------------------------------


def _matrix4(value, what: str) -> Matrix:
    try:
        rows = [[float(x) for x in row] for row in value]
    except (TypeError, ValueError):
        raise ResultError(f"{what} must be a 4x4 matrix of numbers") from None
    if (
        len(rows) != 4
        or any(len(r) != 4 for r in rows)
        or not all(math.isfinite(x) for r in rows for x in r)
    ):
        raise ResultError(f"{what} must be a finite 4x4 matrix")
    return Matrix(rows)


def read_result(filepath: str) -> dict:
    """Read and check ``texture.json``; return it with absolute paths and parsed matrices.

    The returned dict has ``folder``, ``glb`` (absolute path), ``gltf_from_world`` (Matrix)
    and ``views``: a list of dicts with ``name``, ``image`` (absolute path), ``width``,
    ``height``, ``fx``, ``fy``, ``cx``, ``cy`` (px) and ``world_from_camera`` (Matrix, mm).
    Raises :class:`ResultError` naming the file and what was expected.
    """
    path = os.path.abspath(bpy.path.abspath(filepath))
    if not os.path.isfile(path):
        raise ResultError(f"{path}: file not found")
    try:
        with open(path, encoding="utf-8") as f:
            doc = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ResultError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise ResultError(
            f"{path}: not an slscan texture result (format {found!r}, expected {FORMAT!r})"
        )
    version = doc.get("version")
    if not isinstance(version, int) or version < 1:
        raise ResultError(f"{path}: bad version {version!r} (expected {VERSION})")
    if version > VERSION:
        raise ResultError(
            f"{path}: written by a newer slscan (format version {version}; this add-on reads "
            f"version {VERSION}): update the add-on"
        )
    if doc.get("units", "mm") != "mm":
        raise ResultError(f"{path}: units {doc.get('units')!r}, expected 'mm'")
    folder = os.path.dirname(path)
    model = doc.get("model")
    if not isinstance(model, dict) or not isinstance(model.get("glb"), str):
        raise ResultError(f"{path}: no model.glb entry")
    glb = os.path.join(folder, model["glb"])
    if not os.path.isfile(glb):
        raise ResultError(f"{glb}: model file named in {os.path.basename(path)} not found")
    gltf_from_world = _matrix4(doc.get("gltf_from_world"), f"{path}: gltf_from_world")
    views = []
    for i, v in enumerate(doc.get("views") or []):
        where = f"{path}: views[{i}]"
        try:
            view = {
                "name": str(v["name"]),
                "image": os.path.join(folder, str(v["image"])),
                "width": int(v["width"]),
                "height": int(v["height"]),
                **{k: float(v[k]) for k in ("fx", "fy", "cx", "cy")},
            }
        except (KeyError, TypeError, ValueError) as exc:
            raise ResultError(f"{where}: missing or bad field {exc}") from None
        if view["width"] <= 0 or view["height"] <= 0 or view["fx"] <= 0 or view["fy"] <= 0:
            raise ResultError(f"{where}: width, height, fx and fy must be positive")
        view["world_from_camera"] = _matrix4(
            v.get("world_from_camera"), f"{where} world_from_camera"
        )
        views.append(view)
    return {
        "path": path,
        "folder": folder,
        "glb": glb,
        "gltf_from_world": gltf_from_world,
        "views": views,
        "preview": doc.get("preview"),
    }


# --- conversions --------------------------------------------------------------------------


def camera_matrix_world(gltf_from_world: Matrix, world_from_camera: Matrix) -> Matrix:
    """Blender ``matrix_world`` (metres, rigid) of a view camera.

    gltf_from_world : 4x4, world (mm) -> glTF; must be a uniform scale times a rotation
        plus a translation (no mirror)
    world_from_camera : 4x4, OpenCV camera -> world (mm)
    """
    m = GLTF_TO_BLENDER @ gltf_from_world @ world_from_camera @ OPENCV_TO_BLENDER_CAMERA
    m3 = m.to_3x3()
    det = m3.determinant()
    if det <= 0:
        raise ResultError(
            "gltf_from_world and world_from_camera must not mirror (determinant <= 0)"
        )
    scale = det ** (1.0 / 3.0)
    rot = m3 * (1.0 / scale)
    err = max(
        abs(x - y) for a, b in zip(rot @ rot.transposed(), Matrix.Identity(3)) for x, y in zip(a, b)
    )
    if err > 1e-5:  # mathutils works in float32
        raise ResultError(
            "gltf_from_world @ world_from_camera is not a uniform scale, rotation and translation"
        )
    out = rot.to_4x4()
    out.translation = m.translation
    return out


def camera_intrinsics(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> dict:
    """Blender camera and scene settings reproducing an OpenCV pinhole camera exactly.

    Returns ``lens`` (mm, for ``sensor_width`` 36 mm and a horizontal sensor fit),
    ``shift_x``, ``shift_y`` (fractions of the image width) and ``pixel_aspect_x``,
    ``pixel_aspect_y`` (both >= 1, their ratio fy / fx).

    Derivation: with a horizontal fit Blender maps a camera ray (x/d, y/d) to the pixel
    edge coordinate u = fx x/d + w/2 - shift_x w (from the left) and
    v = fy y/d + h/2 - shift_y w fy/fx (from the bottom), with fx = lens w / sensor_width
    and fy = fx pixel_aspect_x / pixel_aspect_y; OpenCV's u is that minus 0.5 and its v
    counts from the top.
    """
    lens = fx * SENSOR_WIDTH_MM / width
    if fy >= fx:
        aspect_x, aspect_y = fy / fx, 1.0
    else:
        aspect_x, aspect_y = 1.0, fx / fy
    shift_x = (width / 2.0 - (cx + 0.5)) / width
    shift_y = (cy + 0.5 - height / 2.0) * (fx / fy) / width
    return {
        "lens": lens,
        "sensor_width": SENSOR_WIDTH_MM,
        "shift_x": shift_x,
        "shift_y": shift_y,
        "pixel_aspect_x": aspect_x,
        "pixel_aspect_y": aspect_y,
    }


# --- building the scene -------------------------------------------------------------------


def use_view(scene, camera_object) -> None:
    """Make ``camera_object`` (an imported view camera) the scene camera, with its view's
    resolution and pixel aspect, so renders and camera view match the scanner's image."""
    data = camera_object.data
    if "slscan_width" not in data:
        raise ResultError(f"{camera_object.name}: not an slscan view camera")
    scene.camera = camera_object
    render = scene.render
    render.resolution_x = int(data["slscan_width"])
    render.resolution_y = int(data["slscan_height"])
    render.resolution_percentage = 100
    render.pixel_aspect_x = float(data["slscan_pixel_aspect_x"])
    render.pixel_aspect_y = float(data["slscan_pixel_aspect_y"])


def _views_collection(scene):
    coll = bpy.data.collections.new(VIEWS_COLLECTION)  # Blender renames it if taken
    scene.collection.children.link(coll)
    return coll


def add_view_camera(
    view: dict,
    gltf_from_world: Matrix,
    collection,
    *,
    background: bool,
    background_alpha: float = 0.5,
):
    """Create the camera object for one view (and its background image when asked)."""
    intr = camera_intrinsics(
        view["width"], view["height"], view["fx"], view["fy"], view["cx"], view["cy"]
    )
    cam = bpy.data.cameras.new(view["name"])
    cam.sensor_fit = "HORIZONTAL"
    cam.sensor_width = intr["sensor_width"]
    cam.lens = intr["lens"]
    cam.shift_x = intr["shift_x"]
    cam.shift_y = intr["shift_y"]
    cam.clip_start = 0.01
    cam.clip_end = 1000.0
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        cam[f"slscan_{key}"] = view[key]
    cam["slscan_view"] = view["name"]
    cam["slscan_pixel_aspect_x"] = intr["pixel_aspect_x"]
    cam["slscan_pixel_aspect_y"] = intr["pixel_aspect_y"]
    obj = bpy.data.objects.new(view["name"], cam)
    obj.matrix_world = camera_matrix_world(gltf_from_world, view["world_from_camera"])
    collection.objects.link(obj)
    if background:
        image = bpy.data.images.load(view["image"], check_existing=True)
        cam.show_background_images = True
        bg = cam.background_images.new()
        bg.image = image
        bg.frame_method = "STRETCH"  # the image is exactly the camera frame
        bg.display_depth = "FRONT"  # over the model, half transparent: alignment shows at a glance
        bg.alpha = background_alpha
    return obj


def import_result(
    context,
    filepath: str,
    *,
    import_model: bool = True,
    import_cameras: bool = True,
    camera_backgrounds: bool = True,
    background_alpha: float = 0.5,
    set_scene_camera: bool = True,
) -> dict:
    """Import ``texture.json``'s model and views into ``context.scene``.

    Returns ``{"model": [objects], "cameras": [objects], "collection": collection or None}``.
    Raises :class:`ResultError` before changing the scene when the folder is not importable.
    """
    result = read_result(filepath)
    if import_cameras and camera_backgrounds:
        missing = [v["image"] for v in result["views"] if not os.path.isfile(v["image"])]
        if missing:
            raise ResultError(
                f"{missing[0]}: view image named in {result['path']} not found"
                + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
            )
    scene = context.scene
    model = []
    if import_model:
        before = set(bpy.data.objects)
        status = bpy.ops.import_scene.gltf(filepath=result["glb"])
        if "FINISHED" not in status:
            raise ResultError(f"{result['glb']}: Blender's glTF importer failed")
        model = [o for o in bpy.data.objects if o not in before]
    cameras, collection = [], None
    if import_cameras and result["views"]:
        collection = _views_collection(scene)
        for view in result["views"]:
            cameras.append(
                add_view_camera(
                    view,
                    result["gltf_from_world"],
                    collection,
                    background=camera_backgrounds,
                    background_alpha=background_alpha,
                )
            )
        if set_scene_camera:
            use_view(scene, cameras[0])
    return {"model": model, "cameras": cameras, "collection": collection}
