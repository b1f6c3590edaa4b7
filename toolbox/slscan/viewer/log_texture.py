"""Loggers for the texture stage: the textured model, the atlas and how many views fed each texel.

Entity tree (the upright object frame of the aligned set, mm, y up)::

    object/model/textured          Mesh3D with texcoords and the baked albedo texture   (static)
    object/views/<name>            Transform3D object_from_camera + Pinhole of each view (static)
    object/views/<name>/albedo     the view's un-shaded image (sRGB)                      (static)
    texture/atlas                 the baked atlas (sRGB image)                           (static)
    texture/view_count            views blended per texel, coloured, named on hover        (static)
    plot/texture/<metric>         coverage, observed share, seam error, seconds           [stage = textured]
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import rerun as rr

from slscan.colour import view_count_legend
from slscan.viewer.log_register import (
    MAX_LOGGED_FACES,
    MODEL_PATH,
    STAGES,
    _set_stage,
    log_object_frame,
)

from slscan.viewer.paths import ATLAS_PATH, TEXTURE_PLOT_PATH, VIEW_COUNT_PATH, VIEWS_PATH

TEXTURED_STAGE = "textured"
STAGES.setdefault(TEXTURED_STAGE, len(STAGES))
MAX_LOGGED_TEXTURE = 4096


def log_texture_views(rec: rr.RecordingStream | None, entries: Sequence[Mapping], images: Sequence[np.ndarray]) -> None:
    """Each view as a camera at its pose with its exported (undistorted, sRGB) un-shaded
    image; ``entries`` as in ``texture.json`` (name, width, height, fx, fy, cx, cy,
    world_from_camera)."""
    if rec is None:
        return
    log_object_frame(rec)
    for entry, image in zip(entries, images):
        path = f"{VIEWS_PATH}/{entry['name']}"
        m = np.asarray(entry["world_from_camera"], float)
        rec.log(path, rr.Transform3D(translation=m[:3, 3], mat3x3=m[:3, :3]), static=True)
        rec.log(path, rr.Pinhole(focal_length=[entry["fx"], entry["fy"]],
                                 principal_point=[entry["cx"] + 0.5, entry["cy"] + 0.5],
                                 resolution=[entry["width"], entry["height"]], image_plane_distance=50.0),
                static=True)
        rec.log(f"{path}/albedo", rr.Image(image).compress(jpeg_quality=90), static=True)


def log_texture_result(rec: rr.RecordingStream | None, folder) -> None:
    """Log a texture-stage output folder from disk (``texture.json``, the OBJ, the views)."""
    from pathlib import Path
    from types import SimpleNamespace

    from slscan.fsio import read_json, read_png
    from slscan.meshes import read_obj_atlas

    if rec is None:
        return
    folder = Path(folder)
    manifest = read_json(folder / "texture.json", "texture manifest")
    atlas, texture = read_obj_atlas(folder / manifest["model"]["obj"])
    count = read_png(folder / manifest["model"]["view_count"])  # the raw counts
    entries = manifest.get("views", [])
    log_texture_views(rec, entries, [read_png(folder / e["image"]) for e in entries])
    log_textured_model(rec, SimpleNamespace(**atlas), texture, None, count, manifest.get("metrics", {}),
                       max_views=max(len(entries), int(count.max(initial=0))))


def log_textured_model(rec: rr.RecordingStream | None, atlas, texture: np.ndarray, normals: np.ndarray | None,
                       view_count: np.ndarray, metrics: Mapping[str, float], *,
                       covered: np.ndarray | None = None, max_views: int | None = None) -> None:
    """The textured mesh, the atlas image, the per-texel view count and the metrics.

    view_count : (size, size) int, views blended per texel; shown in the colours of
        :func:`slscan.colour.view_count_image` (as ``view_count.png``), each named on hover
        (``3 views``) by an annotation context
    covered : (size, size) bool, texels inside the charts (None: those with a count)
    max_views : the top of the colour ramp; None: the largest count
    """
    if rec is None:
        return
    log_object_frame(rec)
    _set_stage(rec, TEXTURED_STAGE)
    faces = np.asarray(atlas.faces)
    if len(faces) > MAX_LOGGED_FACES:
        faces = faces[:: int(np.ceil(len(faces) / MAX_LOGGED_FACES))]
    shown = texture
    if texture.shape[0] > MAX_LOGGED_TEXTURE:
        step = int(np.ceil(texture.shape[0] / MAX_LOGGED_TEXTURE))
        shown = texture[::step, ::step]
    # Rerun's texcoords put (0, 0) at the image's top-left corner, as glTF and our atlas do.
    rec.log(f"{MODEL_PATH}/textured", rr.Mesh3D(
        vertex_positions=np.asarray(atlas.vertices, np.float32),
        triangle_indices=faces.astype(np.uint32),
        vertex_normals=None if normals is None else np.asarray(normals, np.float32),
        vertex_texcoords=np.asarray(atlas.uvs, np.float32),
        albedo_texture=shown,
    ), static=True)  # the stage's one result: shown whatever timeline the viewer is on
    rec.log(ATLAS_PATH, rr.Image(shown), static=True)
    # classes: 0 outside the charts, k + 1 for a texel blended from k views
    count = np.asarray(view_count).astype(np.int64)
    top = int(max_views) if max_views else max(int(count.max(initial=0)), 1)
    inside = count > 0 if covered is None else np.asarray(covered, bool)
    classes = np.where(inside, np.clip(count, 0, top) + 1, 0).astype(np.uint16)
    legend = list(view_count_legend(top).items())
    rec.log(VIEW_COUNT_PATH, rr.AnnotationContext(
        [rr.AnnotationInfo(id=k, label=label, color=colour) for k, (label, colour) in enumerate(legend)]
    ), static=True)
    rec.log(VIEW_COUNT_PATH, rr.SegmentationImage(classes, opacity=1.0), static=True)
    for name, value in metrics.items():
        if value is not None and np.isfinite(value):
            rec.log(f"{TEXTURE_PLOT_PATH}/{name}", rr.Scalars(float(value)))
