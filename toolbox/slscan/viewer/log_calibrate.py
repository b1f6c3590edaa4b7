"""Loggers for the calibrate stage: board corners, board poses, the projector, its planes, residuals.

Entity tree, continuing :mod:`slscan.viewer.log` (rig frame = camera frame, mm)::

    world/camera/image/calibrate/board         the white image the board was found in [view]
    world/camera/image/calibrate/corners       detected corners (green)               [view]
    world/camera/image/calibrate/reprojected   corners reprojected by the result (red) [view]
    world/projector/image/calibrate/corners    corners mapped into the projector      [view]
    world/projector/image/calibrate/reprojected  ... reprojected by the result        [view]
    world/boards/view_NNN                      Transform3D rig_from_board (static)
    world/boards/view_NNN/outline, corners     the board's squares area and corners (static)
    world/light_planes                         a sample of the measured light planes (static)
    plot/calibrate/camera_rms_px, projector_rms_px   per-view reprojection RMS   [view]
    plot/calibrate/plane_rms_before_mm, plane_rms_after_mm   per-plane residuals (bar charts)
    log/calibrate                              rejected views and the summary

The camera and projector frusta are :func:`slscan.viewer.log.log_rig` of the calibrated rig; what a
calibration run logs is put together by the calibrate stage (``slscan.calibrate.pipeline``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import rerun as rr

from slscan.viewer.log import _set_view, _to_uint8
from slscan.viewer.paths import (
    BOARDS_PATH,
    CALIBRATE_CAMERA_PATH,
    CALIBRATE_LOG_PATH,
    CALIBRATE_PLOT_PATH,
    CALIBRATE_PROJECTOR_PATH,
    PLANES_PATH,
    board_path,
)

if TYPE_CHECKING:
    from slscan.calibrate.planes import LightPlaneModel
    from slscan.calibrate.target import Board, CornerDetection

CAMERA_PATH = CALIBRATE_CAMERA_PATH
PROJECTOR_PATH = CALIBRATE_PROJECTOR_PATH
PLOT_PATH = CALIBRATE_PLOT_PATH
LOG_PATH = CALIBRATE_LOG_PATH
__all__ = ["BOARDS_PATH", "PLANES_PATH", "board_path"]  # re-exported from slscan.viewer.paths

CORNER_COLOR = (40, 255, 120)
REPROJECTED_COLOR = (255, 60, 60)
BOARD_COLOR = (230, 230, 230)
PLANE_COLOR = (255, 140, 0)
N_PLANES_SHOWN = 24
JPEG_QUALITY = 90


def log_board_image(
    rec: rr.RecordingStream | None,
    image: np.ndarray,
    detection: CornerDetection,
    *,
    view_index: int,
) -> None:
    """Log the image the board was looked for in, and the corners found, on the camera image.

    image : (h, w) or (h, w, 3) uint8/uint16 camera px
    detection : the corners (k, 2) px and ids; a failed one is logged as a warning
    """
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(
        f"{CAMERA_PATH}/board",
        rr.Image(_to_uint8(np.asarray(image))).compress(jpeg_quality=JPEG_QUALITY),
    )
    if detection:
        rec.log(
            f"{CAMERA_PATH}/corners",
            rr.Points2D(
                detection.corners,
                colors=CORNER_COLOR,
                radii=2.0,
                labels=[str(i) for i in detection.ids],
                show_labels=False,
            ),
        )
    else:
        rec.log(f"{CAMERA_PATH}/corners", rr.Clear(recursive=False))
        rec.log(
            LOG_PATH,
            rr.TextLog(f"view {view_index}: {detection.source}: {detection.reason}", level="WARN"),
        )


def log_reprojection(
    rec: rr.RecordingStream | None,
    path: str,
    measured: np.ndarray,
    reprojected: np.ndarray,
    *,
    view_index: int,
) -> None:
    """Log measured (green) and reprojected (red) points (k, 2) px under ``path``."""
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(
        f"{path}/corners", rr.Points2D(np.asarray(measured, float), colors=CORNER_COLOR, radii=2.0)
    )
    rec.log(
        f"{path}/reprojected",
        rr.Points2D(np.asarray(reprojected, float), colors=REPROJECTED_COLOR, radii=1.0),
    )


def log_board_pose(
    rec: rr.RecordingStream | None, board: Board, rig_from_board: np.ndarray, *, view_index: int
) -> None:
    """Log one view's board, static: its pose, the squares' outline and its corners (mm)."""
    if rec is None:
        return
    path = board_path(view_index)
    pose = np.asarray(rig_from_board, float)
    rec.log(path, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]), static=True)
    outline = board.outline()
    rec.log(
        f"{path}/outline",
        rr.LineStrips3D(
            [np.concatenate([outline, outline[:1]])],
            colors=BOARD_COLOR,
            radii=1.0,
            labels=[f"view {view_index}"],
        ),
        static=True,
    )
    rec.log(
        f"{path}/corners",
        rr.Points3D(board.object_points(), colors=CORNER_COLOR, radii=2.0),
        static=True,
    )


def plane_quads(
    model: LightPlaneModel, columns: np.ndarray, height: int, near: float, far: float
) -> list[np.ndarray]:
    """Closed outlines (5, 3) mm of the light planes of ``columns``, between ``near`` and
    ``far`` mm from the projector, over the rows ``0 .. height - 1`` (``fy = fx``)."""
    rot, centre = model.rig_from_projector[:3, :3], model.center
    quads = []
    for u in np.asarray(columns, float):
        xn = (u - model.cx) / model.fx
        corners = []
        for z, yn in ((near, -0.5), (far, -0.5), (far, 0.5), (near, 0.5)):
            y = yn * height / model.fx
            corners.append(centre + rot @ (np.array([xn, y, 1.0]) * z))
        corners.append(corners[0])
        quads.append(np.asarray(corners))
    return quads


def log_light_planes(
    rec: rr.RecordingStream | None,
    model: LightPlaneModel,
    *,
    height: int,
    near: float,
    far: float,
    n: int = N_PLANES_SHOWN,
) -> None:
    """Log ``n`` of the model's light planes, evenly over the projector's width, static."""
    if rec is None:
        return
    columns = np.linspace(0, model.width - 1, n)
    rec.log(
        PLANES_PATH,
        rr.LineStrips3D(
            plane_quads(model, columns, height, near, far),
            colors=PLANE_COLOR,
            radii=0.8,
            labels=[f"u = {u:.0f}" for u in columns],
            show_labels=False,
        ),
        static=True,
    )


def log_view_errors(
    rec: rr.RecordingStream | None, errors: dict[str, float], *, view_index: int
) -> None:
    """Log per-view scalars (px) under ``plot/calibrate/<name>``."""
    if rec is None:
        return
    _set_view(rec, view_index)
    for name, value in errors.items():
        if np.isfinite(value):
            rec.log(f"{PLOT_PATH}/{name}", rr.Scalars(float(value)))


def log_plane_residuals(
    rec: rr.RecordingStream | None, before: np.ndarray, after: np.ndarray
) -> None:
    """Log per-plane point-to-plane RMS (mm), before and after the global fit, as bar charts."""
    if rec is None:
        return
    rec.log(f"{PLOT_PATH}/plane_rms_before_mm", rr.BarChart(np.asarray(before, float)), static=True)
    rec.log(f"{PLOT_PATH}/plane_rms_after_mm", rr.BarChart(np.asarray(after, float)), static=True)
