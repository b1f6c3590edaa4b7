"""Loggers for the capture stage: the rig, the scene, captures, patterns and ground truth.

One ``log_*`` function per thing logged. Each takes the recording stream first and
returns at once when it is ``None``, before any array work, so logging off costs nothing.

Entity tree (rig frame = camera frame, mm, OpenCV axes x right / y down / z forward)::

    world                              ViewCoordinates RDF (static)
    world/camera                       Transform3D, identity (static)
    world/camera/image                 Pinhole of the camera (static)
    world/camera/image/capture         captured frames            [view, frame]
    world/camera/image/truth/...       depth, normal, albedo,
                                       projector_column, visibility  [view]
    world/projector                    Transform3D rig_from_projector (static)
    world/projector/image              Pinhole of the projector lens (static)
    world/projector/image/pattern      projected image            [view, frame]
    world/lights                       Points3D of the ring lights (static)
    world/scene/mesh                   Mesh3D of the scanned object  [view]
    world/scans/view_NNN/truth_points  Points3D of the true surface  [view]
    log/capture                        TextLog naming each frame  [view, frame]

View-level data (mesh, truth) is logged at ``frame = 0`` of its view, so it also shows
when the frame timeline is selected.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
import rerun as rr

from slscan.colour import srgb8
from slscan.errors import SlscanError
from slscan.meshes import vertex_normals
from slscan.viewer.paths import (
    CAMERA_IMAGE_PATH,
    CAMERA_PATH,
    CAPTURE_LOG_PATH,
    CAPTURE_PATH,
    LIGHTS_PATH,
    MESH_PATH,
    PATTERN_PATH,
    PROJECTOR_IMAGE_PATH,
    PROJECTOR_PATH,
    TRUTH_PATH,
    WORLD_PATH,
    scan_path,
)
from slscan.viewer.recording import FRAME_TIMELINE, LOSSLESS_ATTR, VIEW_TIMELINE, first_static

if TYPE_CHECKING:  # imported lazily: capture modules import these loggers
    from slscan.capture.session import GroundTruth
    from slscan.rig import PinholeModel, Rig

CAMERA_IMAGE_PLANE_MM = 300.0
"""Where the camera frustum's image plane is drawn: visible at the rig's scale."""
PROJECTOR_COLOR = (255, 140, 0)
CAMERA_COLOR = (90, 170, 255)
LIGHT_RADIUS_MM = 10.0
TRUTH_POINT_STRIDE = 4
JPEG_QUALITY = 90

VISIBILITY_COLORS = ((0, 0, 0), (60, 60, 150), (255, 210, 60))
"""Display colours of the visibility labels background, projector shadow, lit."""



# --- small helpers --------------------------------------------------------------------------


def _set_view(rec: rr.RecordingStream, view_index: int, frame_index: int = 0) -> None:
    rec.set_time(VIEW_TIMELINE, sequence=int(view_index))
    rec.set_time(FRAME_TIMELINE, sequence=int(frame_index))


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """uint8 pixels of a uint8 or uint16 image (16-bit: the top 8 bits)."""
    if image.dtype == np.uint8:
        return image
    return (image >> 8).astype(np.uint8)


def _check_image(image: np.ndarray, what: str) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16):
        raise SlscanError(f"{what}: expected uint8 or uint16 pixels, got {image.dtype}")
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (1, 3))):
        raise SlscanError(f"{what}: expected an (h, w) or (h, w, 3) image, got shape {image.shape}")
    return image[..., 0] if image.ndim == 3 and image.shape[2] == 1 else image


def _png(image: np.ndarray, *, draw_order: float | None = None) -> rr.EncodedImage:
    """Lossless PNG of an (h, w), (h, w, 3) RGB or (h, w, 4) RGBA uint8 image."""
    if image.ndim == 3:
        image = image[..., [2, 1, 0, 3]] if image.shape[2] == 4 else image[..., ::-1]
    ok, data = cv2.imencode(".png", np.ascontiguousarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise SlscanError("could not PNG-encode an image for Rerun")
    return rr.EncodedImage(contents=data.tobytes(), media_type="image/png", draw_order=draw_order)


def _overlay(mask: np.ndarray, color: tuple[int, int, int, int], *, draw_order: float = 10.0) -> rr.EncodedImage:
    """A mask drawn in ``color`` (RGBA) over a camera frame, transparent elsewhere.

    PNG-encoded: Rerun 0.41 draws no JPEG frame (:func:`log_capture`) under a raw RGBA
    ``rr.Image`` in the same 2D view, but blends encoded images as expected.
    """
    rgba = np.zeros(mask.shape + (4,), np.uint8)
    rgba[mask] = color
    return _png(rgba, draw_order=draw_order)


def _colors_u8(colors: np.ndarray) -> np.ndarray:
    colors = np.asarray(colors)
    if colors.dtype == np.uint8:
        return colors
    return np.round(np.clip(colors, 0.0, 1.0) * 255).astype(np.uint8)


def _pinhole(
    lens: PinholeModel, image_plane_distance: float, color: tuple[int, int, int]
) -> rr.Pinhole:
    return rr.Pinhole(
        image_from_camera=lens.K,
        resolution=[lens.width, lens.height],
        camera_xyz=rr.ViewCoordinates.RDF,
        image_plane_distance=float(image_plane_distance),
        color=color,
    )


# --- loggers ----------------------------------------------------------------------------------


def log_rig(rec: rr.RecordingStream | None, rig: Rig) -> None:
    """Log the rig, static: world axes, camera and projector frusta, ring lights.

    Once per recording (and per session subtree): the same rig again is not re-sent; a
    different rig (a calibrated one) replaces it.

    The camera frustum is drawn to :data:`CAMERA_IMAGE_PLANE_MM`; the projector's reaches
    ``rig.working_distance`` so it meets the object. Light positions are mm, rig frame.
    """
    if rec is None:
        return
    # static, once per recording: a second stage logging the same rig changes nothing
    lenses = (rig.camera.K, rig.camera.width, rig.camera.height, rig.projector.rig_from_projector,
              rig.projector.lens.K, rig.projector.lens.width, rig.projector.lens.height, rig.working_distance)
    key = tuple(np.asarray(v, float).round(9).tobytes() for v in lenses)
    if not first_static(rec, CAMERA_IMAGE_PATH, key):
        return
    if first_static(rec, WORLD_PATH):
        rec.log(WORLD_PATH, rr.ViewCoordinates.RDF, static=True)
    identity = rr.Transform3D(translation=[0.0, 0.0, 0.0], mat3x3=np.eye(3))
    rec.log(CAMERA_PATH, identity, static=True)
    rec.log(
        CAMERA_IMAGE_PATH,
        _pinhole(rig.camera, CAMERA_IMAGE_PLANE_MM, CAMERA_COLOR),
        static=True,
    )
    pose = rig.projector.rig_from_projector
    rig_from_projector = rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3])
    rec.log(PROJECTOR_PATH, rig_from_projector, static=True)
    rec.log(
        PROJECTOR_IMAGE_PATH,
        _pinhole(rig.projector.lens, rig.working_distance, PROJECTOR_COLOR),
        static=True,
    )
    if rig.lights:
        positions = np.array([light.position for light in rig.lights], float)
        intensity = np.array([light.intensity for light in rig.lights], float)
        colors = intensity / np.maximum(intensity.max(axis=1, keepdims=True), 1e-9)
        rec.log(
            LIGHTS_PATH,
            rr.Points3D(
                positions,
                radii=LIGHT_RADIUS_MM,
                colors=_colors_u8(colors),
                labels=[f"light {i}" for i in range(len(rig.lights))],
            ),
            static=True,
        )


def log_scene_mesh(
    rec: rr.RecordingStream | None,
    vertices: np.ndarray,
    triangles: np.ndarray,
    vertex_colors: np.ndarray | None = None,
    *,
    view_index: int,
) -> None:
    """Log the scene's mesh as placed for one view at ``world/scene/mesh``.

    vertices : (n, 3) float, mm, rig frame
    triangles : (m, 3) int, vertex indices
    vertex_colors : (n, 3) float in [0, 1] or uint8, display colours; None for grey
    """
    if rec is None:
        return
    vertices = np.asarray(vertices)
    triangles = np.asarray(triangles)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise SlscanError(f"scene mesh: expected (n, 3) vertices, got shape {vertices.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise SlscanError(f"scene mesh: expected (m, 3) triangles, got shape {triangles.shape}")
    if vertex_colors is not None and np.shape(vertex_colors) != vertices.shape:
        raise SlscanError(
            f"scene mesh: vertex colours have shape {np.shape(vertex_colors)}, "
            f"vertices {vertices.shape}"
        )
    tri = triangles.astype(np.uint32)
    _set_view(rec, view_index)
    rec.log(
        MESH_PATH,
        rr.Mesh3D(
            vertex_positions=vertices.astype(np.float32),
            triangle_indices=tri,
            vertex_normals=vertex_normals(vertices, tri) if len(tri) else None,
            vertex_colors=None if vertex_colors is None else _colors_u8(vertex_colors),
        ),
    )


def log_capture(
    rec: rr.RecordingStream | None,
    image: np.ndarray,
    *,
    view_index: int,
    frame_index: int,
    label: str,
    compress: bool | None = None,
) -> None:
    """Log one captured camera frame at ``world/camera/image/capture``, and its name.

    image : (h, w) or (h, w, 3) uint8 or uint16, camera pixels, RGB
    compress : JPEG (quality 90) for display, 16-bit frames reduced to 8 bits; False logs
        the pixels losslessly as they are; None (default): JPEG unless the stream was
        opened with ``lossless_images``
    label : the frame's name (e.g. the pattern id), written to ``log/capture``
    """
    if rec is None:
        return
    image = _check_image(image, f"capture {label!r}")
    _set_view(rec, view_index, frame_index)
    if compress is None:
        compress = not getattr(rec, LOSSLESS_ATTR, False)
    if compress:
        archetype = rr.Image(_to_uint8(image)).compress(jpeg_quality=JPEG_QUALITY)
    else:
        archetype = rr.Image(image)
    rec.log(CAPTURE_PATH, archetype)
    text = f"view {view_index} · frame {frame_index} · {label}"
    rec.log(CAPTURE_LOG_PATH, rr.TextLog(text, level="INFO"))


def log_pattern(
    rec: rr.RecordingStream | None,
    pattern_image: np.ndarray,
    *,
    view_index: int,
    frame_index: int,
) -> None:
    """Log the projected image of one frame at ``world/projector/image/pattern`` (PNG).

    pattern_image : (h, w, 3) uint8, projector pixels, RGB (see :func:`slscan.patterns.render`)
    """
    if rec is None:
        return
    pattern_image = _check_image(pattern_image, "pattern image")
    _set_view(rec, view_index, frame_index)
    rec.log(PATTERN_PATH, _png(_to_uint8(pattern_image)))


def projector_column_image(column: np.ndarray, projector_width: float) -> np.ndarray:
    """Turbo colour map (h, w, 3) uint8 RGB of projector columns over [0, width]; NaN black.

    column : (h, w) float, continuous projector column (px)
    """
    valid = np.isfinite(column)
    scaled = np.clip(np.where(valid, column, 0.0) / max(float(projector_width), 1e-9), 0.0, 1.0)
    bgr = cv2.applyColorMap(np.round(scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = bgr[..., ::-1].copy()
    rgb[~valid] = 0
    return rgb


def log_ground_truth(
    rec: rr.RecordingStream | None,
    gt: GroundTruth,
    *,
    view_index: int,
    projector_width: float | None = None,
) -> None:
    """Log a virtual view's per-pixel truth under ``world/camera/image/truth/``.

    Layers: ``depth`` (z, mm), ``normal`` (RGB of (n + 1) / 2), ``albedo`` (sRGB),
    ``projector_column`` (Turbo over [0, projector_width]), ``visibility`` (segmentation
    with labels). Also ``world/scans/view_NNN/truth_points``: every
    :data:`TRUTH_POINT_STRIDE`-th pixel's true surface point (mm, rig frame) coloured by
    albedo, so it overlays the scene mesh.

    gt : :class:`GroundTruth` over (h, w) camera pixels, NaN on background
    projector_width : px; default: the largest column seen, rounded up
    """
    if rec is None:
        return
    from slscan.capture.session import VISIBILITY_LABELS

    h, w = gt.visibility.shape[:2]
    for name in ("point", "normal", "albedo", "projector_uv"):
        if getattr(gt, name).shape[:2] != (h, w):
            raise SlscanError(
                f"ground truth: {name} is {getattr(gt, name).shape[:2]}, visibility is {(h, w)}"
            )
    _set_view(rec, view_index)

    z = gt.point[..., 2].astype(np.float32)
    finite = z[np.isfinite(z)]
    depth_range = [float(finite.min()), float(finite.max())] if finite.size else None
    if depth_range is not None and depth_range[1] <= depth_range[0]:
        depth_range[1] = depth_range[0] + 1.0
    rec.log(
        f"{TRUTH_PATH}/depth",
        rr.DepthImage(
            np.nan_to_num(z, nan=0.0), meter=1000.0, colormap="Viridis", depth_range=depth_range
        ),
    )

    normal = (np.nan_to_num(gt.normal, nan=-1.0) + 1.0) * 127.5
    normal = np.round(normal).clip(0, 255).astype(np.uint8)
    rec.log(f"{TRUTH_PATH}/normal", _png(normal))

    albedo = srgb8(gt.albedo)
    rec.log(f"{TRUTH_PATH}/albedo", _png(albedo))

    column = gt.projector_uv[..., 0]
    if projector_width is None:
        finite = column[np.isfinite(column)]
        projector_width = float(np.ceil(finite.max())) if finite.size else 1.0
    rec.log(f"{TRUTH_PATH}/projector_column", _png(projector_column_image(column, projector_width)))

    if first_static(rec, f"{TRUTH_PATH}/visibility"):
        rec.log(
            f"{TRUTH_PATH}/visibility",
            rr.AnnotationContext(
                [
                    rr.AnnotationInfo(id=k, label=VISIBILITY_LABELS[k], color=VISIBILITY_COLORS[k])
                    for k in VISIBILITY_LABELS
                ]
            ),
            static=True,
        )
    rec.log(f"{TRUTH_PATH}/visibility", rr.SegmentationImage(gt.visibility.astype(np.uint8)))

    step = TRUTH_POINT_STRIDE
    grid = gt.point[::step, ::step]
    valid = np.all(np.isfinite(grid), axis=-1)
    if valid.any():
        spacing = np.linalg.norm(np.diff(grid, axis=1), axis=-1)
        spacing = spacing[np.isfinite(spacing)]
        radius = 0.5 * float(np.median(spacing)) if spacing.size else 1.0
        rec.log(
            f"{scan_path(view_index)}/truth_points",
            rr.Points3D(grid[valid], colors=srgb8(gt.albedo[::step, ::step][valid]), radii=radius),
        )
