"""Loggers for the albedo stage: lit images, shadow and highlight masks, un-shaded image.

Entity tree, continuing :mod:`slscan.viewer.log`::

    world/camera/image/albedo/lit          each lit image                   [view, frame]
    world/camera/image/albedo/shadow       its light's shadow mask (blue overlay)   [view, frame]
    world/camera/image/albedo/highlight    its light's rejected highlights (yellow overlay)  [view, frame]
    world/camera/image/albedo/unshaded     the un-shaded (albedo) image, sRGB  [view]
    world/camera/image/albedo/normal       normals used, RGB of (n + 1) / 2  [view]
    world/camera/image/albedo/error        |albedo - truth| / |truth|, Turbo (virtual rig)  [view]
    world/albedo/view_NNN                  Mesh3D of the range map coloured by albedo  [view]
    world/lights/calibrated                Points3D of the calibrated lights (static)
    log/albedo                             TextLog naming each lit frame  [view, frame]
    plot/albedo/<metric>                   per-view scalars  [view]

Each function takes the recording stream first and returns at once when it is ``None``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import rerun as rr

from slscan.colour import srgb8
from slscan.errors import SlscanError
from slscan.viewer.log import (
    JPEG_QUALITY,
    LIGHT_RADIUS_MM,
    _check_image,
    _overlay,
    _png,
    _set_view,
    _to_uint8,
)
from slscan.viewer.log_decode import colormap
from slscan.viewer.paths import (
    ALBEDO_LOG_PATH,
    ALBEDO_PATH,
    ALBEDO_PLOT_PATH,
    CALIBRATED_LIGHTS_PATH,
    albedo_mesh_path,
)
from slscan.viewer.recording import first_static

if TYPE_CHECKING:
    from slscan.albedo.lights import LightCalibration

LIGHTS_PATH = CALIBRATED_LIGHTS_PATH
SHADOW_COLOR = (40, 90, 255, 150)
HIGHLIGHT_COLOR = (255, 230, 0, 190)
CALIBRATED_LIGHT_COLOR = (255, 80, 200)
ERROR_RANGE = 0.10
"""Relative albedo error shown at the top of the error colour map (10 %)."""


def log_lit_image(
    rec: rr.RecordingStream | None,
    image: np.ndarray,
    *,
    view_index: int,
    frame_index: int,
    light: int,
    shadow: np.ndarray | None = None,
    highlight: np.ndarray | None = None,
) -> None:
    """One lit image (JPEG) with its light's shadow and highlight masks as overlays.

    image : (h, w) or (h, w, 3) uint8 / uint16 camera pixels, RGB
    shadow, highlight : (h, w) bool, where this light was left out as shadowed / rejected
        as a highlight
    frame_index : the image's frame in its view (its place in ``session.json``)
    light : the ring light's index, or -1 for the projector as the light (the white frame)
    """
    if rec is None:
        return
    source = "the projector (white frame)" if light < 0 else f"light {light}"  # -1: the projector as light
    image = _check_image(image, f"lit image of {source}")
    for name, mask in (("shadow", shadow), ("highlight", highlight)):
        if mask is not None and mask.shape != image.shape[:2]:
            raise SlscanError(
                f"{name} mask of {source} is {mask.shape}, the image {image.shape[:2]}"
            )
    _set_view(rec, view_index, frame_index)
    rec.log(f"{ALBEDO_PATH}/lit", rr.Image(_to_uint8(image)).compress(jpeg_quality=JPEG_QUALITY))
    if shadow is not None:
        rec.log(f"{ALBEDO_PATH}/shadow", _overlay(shadow, SHADOW_COLOR))
    if highlight is not None:
        rec.log(f"{ALBEDO_PATH}/highlight", _overlay(highlight, HIGHLIGHT_COLOR))
    rec.log(
        ALBEDO_LOG_PATH,
        rr.TextLog(f"view {view_index} · frame {frame_index} · {source}", level="INFO"),
    )


def log_unshaded(
    rec: rr.RecordingStream | None,
    albedo: np.ndarray,
    valid: np.ndarray,
    *,
    view_index: int,
    normal: np.ndarray | None = None,
) -> None:
    """The un-shaded image (linear albedo shown as sRGB; invalid pixels black) and normals.

    albedo : (h, w, 3) float linear RGB; valid : (h, w) bool
    normal : (h, w, 3) float unit normals, NaN where none
    """
    if rec is None:
        return
    if albedo.shape[:2] != valid.shape:
        raise SlscanError(f"albedo image is {albedo.shape[:2]}, its validity mask {valid.shape}")
    _set_view(rec, view_index)
    rec.log(f"{ALBEDO_PATH}/unshaded", _png(srgb8(np.where(valid[..., None], albedo, 0.0))))
    if normal is not None:
        rgb = (
            np.round((np.nan_to_num(normal, nan=-1.0) + 1.0) * 127.5).clip(0, 255).astype(np.uint8)
        )
        rec.log(f"{ALBEDO_PATH}/normal", _png(rgb))


def albedo_error_image(
    albedo: np.ndarray, truth: np.ndarray, valid: np.ndarray, max_error: float = ERROR_RANGE
) -> np.ndarray:
    """Turbo colours (h, w, 3) uint8 of ``|albedo - truth| / |truth|`` over [0, max_error].

    Black where the albedo is invalid or the truth unknown.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.linalg.norm(albedo - truth, axis=-1) / np.linalg.norm(truth, axis=-1)
    err = np.where(valid & np.isfinite(err), err, np.nan)
    return colormap(err, max_error)


def log_albedo_error(
    rec: rr.RecordingStream | None,
    albedo: np.ndarray,
    truth: np.ndarray,
    valid: np.ndarray,
    *,
    view_index: int,
    max_error: float = ERROR_RANGE,
) -> None:
    """Relative albedo error against ground truth (virtual rig), Turbo over [0, max_error]."""
    if rec is None:
        return
    if albedo.shape != truth.shape:
        raise SlscanError(f"albedo image is {albedo.shape}, the ground-truth albedo {truth.shape}")
    _set_view(rec, view_index)
    rec.log(f"{ALBEDO_PATH}/error", _png(albedo_error_image(albedo, truth, valid, max_error)))


def log_albedo_mesh(
    rec: rr.RecordingStream | None,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None,
    vertex_albedo: np.ndarray,
    *,
    view_index: int,
) -> None:
    """The range map coloured by its per-vertex albedo (sRGB; unknown vertices grey)."""
    if rec is None:
        return
    if len(vertex_albedo) != len(vertices):
        raise SlscanError(f"{len(vertex_albedo)} vertex albedos for {len(vertices)} vertices")
    known = np.all(np.isfinite(vertex_albedo), axis=1)
    colors = srgb8(vertex_albedo)
    colors[~known] = 96
    _set_view(rec, view_index)
    rec.log(
        albedo_mesh_path(view_index),
        rr.Mesh3D(
            vertex_positions=np.asarray(vertices, np.float32),
            triangle_indices=np.asarray(faces, np.uint32),
            vertex_normals=None if normals is None else np.asarray(normals, np.float32),
            vertex_colors=colors,
        ),
    )


def log_lights(rec: rr.RecordingStream | None, lights: LightCalibration) -> None:
    """The calibrated light positions (mm, rig frame), static, beside the rig's nominal ones;
    once per recording (the same lights again are not re-sent)."""
    if rec is None:
        return
    positions = np.asarray(lights.positions, float)
    if not first_static(rec, LIGHTS_PATH, positions.round(9).tobytes()):
        return  # logged by an earlier view
    rec.log(
        LIGHTS_PATH,
        rr.Points3D(
            positions,
            radii=LIGHT_RADIUS_MM * 0.6,
            colors=CALIBRATED_LIGHT_COLOR,
            labels=[f"light {i} (calibrated)" for i in range(len(lights.lights))],
        ),
        static=True,
    )


def log_albedo_metrics(
    rec: rr.RecordingStream | None, metrics: dict[str, float], *, view_index: int
) -> None:
    """Per-view scalars under ``plot/albedo/``."""
    if rec is None:
        return
    _set_view(rec, view_index)
    for name, value in metrics.items():
        if value is not None and np.isfinite(value):
            rec.log(f"{ALBEDO_PLOT_PATH}/{name}", rr.Scalars(float(value)))
