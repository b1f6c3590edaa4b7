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

The camera and projector frusta are :func:`slscan.viewer.log.log_rig` of the calibrated rig.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from slscan.viewer.layouts import stage_blueprint
from slscan.viewer.log import _set_view, _to_uint8, log_rig

if TYPE_CHECKING:
    from slscan.calibrate.pipeline import CalibrationRun
    from slscan.calibrate.planes import LightPlaneModel
    from slscan.calibrate.target import Board, CornerDetection
    from slscan.capture.session import Session

CAMERA_PATH = "world/camera/image/calibrate"
PROJECTOR_PATH = "world/projector/image/calibrate"
BOARDS_PATH = "world/boards"
PLANES_PATH = "world/light_planes"
PLOT_PATH = "plot/calibrate"
LOG_PATH = "log/calibrate"

CORNER_COLOR = (40, 255, 120)
REPROJECTED_COLOR = (255, 60, 60)
BOARD_COLOR = (230, 230, 230)
PLANE_COLOR = (255, 140, 0)
N_PLANES_SHOWN = 24
JPEG_QUALITY = 90


def board_path(view_index: int) -> str:
    return f"{BOARDS_PATH}/view_{view_index:03d}"


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


def log_calibration(rec: rr.RecordingStream | None, run: CalibrationRun, session: Session) -> None:
    """Log a calibration's results: the rig, board poses, reprojections, planes, residuals."""
    if rec is None:
        return
    from slscan.calibrate.target import board_pose

    cal = run.calibration
    old = session.calibration
    rig = cal.rig(
        lights=old.lights if old is not None else (),
        working_distance=old.working_distance if old is not None else 1300.0,
    )
    log_rig(rec, rig)
    board = cal.board
    index = {
        str(session.image_path(v, v.image_for(_white_id(session)))): i
        for i, v in enumerate(session.views)
    }
    inverse = run.inverse_camera
    distances = []
    for det in run.camera.detections:
        i = index.get(det.source)
        if i is None:
            continue
        pose = board_pose(cal.camera, det, board)
        distances.append(pose[2, 3])
        log_board_pose(rec, board, pose, view_index=i)
        local = board.object_points(det.ids) @ pose[:3, :3].T + pose[:3, 3]
        log_reprojection(
            rec, CAMERA_PATH, det.corners, cal.camera.project_local(local), view_index=i
        )
        errors = {
            "camera_rms_px": float(
                np.sqrt(
                    np.mean(np.sum((cal.camera.project_local(local) - det.corners) ** 2, axis=1))
                )
            )
        }
        view_name = session.views[i].name
        if inverse is not None and view_name in inverse.views:
            k = inverse.views.index(view_name)
            pts = inverse.projector_points[k]
            obj = board.object_points(inverse.object_ids[k])
            pose_p = inverse.projector_from_board[k]
            reproj = cal.projector.lens.project_local(obj @ pose_p[:3, :3].T + pose_p[:3, 3])
            log_reprojection(rec, PROJECTOR_PATH, pts, reproj, view_index=i)
            errors["projector_rms_px"] = float(inverse.view_errors[k, 1])
        log_view_errors(rec, errors, view_index=i)
    if cal.light_planes is not None and distances:
        near, far = 0.8 * min(distances), 1.1 * max(distances)
        log_light_planes(rec, cal.light_planes, height=cal.projector_size[1], near=near, far=far)
    if run.light_planes is not None:
        lp = run.light_planes
        log_plane_residuals(rec, lp.lines.rms, lp.line_rms_after)
    summary = [f"camera RMS {run.camera.rms:.3f} px over {len(run.camera.views)} views"]
    if inverse is not None:
        summary.append(f"stereo RMS {inverse.stereo_rms:.3f} px")
    if run.light_planes is not None:
        summary.append(
            f"planes RMS {run.light_planes.rms_before:.4f} mm -> {run.light_planes.rms_after:.4f} mm (global fit)"
        )
    rec.log(LOG_PATH, rr.TextLog("; ".join(summary), level="INFO"), static=True)


def _white_id(session: Session) -> str:
    from slscan.calibrate.target import board_image_id

    return board_image_id(session)


def calibrate_blueprint() -> rrb.Blueprint:
    """Calibrate stage: the boards, rig and light planes in 3D beside the corners in 2D.

    Left: 3D view of ``world`` — board poses, camera and projector frusta, a sample of
    light planes (images left out). Right: the board image with detected (green) and
    reprojected (red) corners; the projector's image with the corners mapped into it;
    per-view reprojection errors and per-plane residuals; the calibration log. Time panel
    on the view timeline.
    """
    scene = rrb.Spatial3DView(
        origin="world",
        contents=[
            "+ $origin/**",
            "- $origin/camera/image/**",
            "- $origin/projector/image/calibrate/**",
        ],
        name="Boards, rig and light planes",
    )
    camera = rrb.Spatial2DView(
        origin="world/camera/image",
        contents=["+ $origin/calibrate/**"],
        name="Board corners (camera)",
    )
    projector = rrb.Spatial2DView(
        origin="world/projector/image",
        contents=["+ $origin/calibrate/**"],
        name="Board corners (projector)",
    )
    errors = rrb.TimeSeriesView(
        origin=PLOT_PATH,
        contents=["+ $origin/camera_rms_px", "+ $origin/projector_rms_px"],
        name="Reprojection RMS per view (px)",
    )
    planes = rrb.Tabs(
        rrb.BarChartView(
            origin=f"{PLOT_PATH}/plane_rms_after_mm", name="Plane RMS after global fit (mm)"
        ),
        rrb.BarChartView(
            origin=f"{PLOT_PATH}/plane_rms_before_mm", name="Plane RMS, raw planes (mm)"
        ),
        name="Light-plane residuals",
    )
    log = rrb.TextLogView(origin="log/calibrate", name="Calibration log")
    return stage_blueprint(
        rrb.Horizontal(
            scene,
            rrb.Vertical(
                rrb.Horizontal(camera, projector),
                rrb.Horizontal(errors, planes),
                log,
                row_shares=[3, 2, 1],
            ),
            column_shares=[1, 1],
            name="Calibrate",
        ),
    )
