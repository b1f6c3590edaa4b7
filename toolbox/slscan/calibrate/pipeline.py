"""The calibrate stage end to end: a capture session of a board in, a calibration file out.

Per view: find the board's corners in the white image; calibrate the camera (Zhang);
decode the projected patterns. Then the projector, by either or both methods:

- ``"inverse-camera"`` (Moreno & Taubin 2012): board corners mapped into the projector by
  local homographies of the decoded columns and rows (phase shifting's at every pixel, or
  the Gray code's stripe edges), the projector calibrated as a camera, its pose by a
  stereo calibration that also refines the camera (:mod:`slscan.calibrate.procam`);
- ``"planes"`` (Rocchini et al. 2001): the board as the flat panel, one light plane per
  hybrid green line, Gray-code edge or (phase shifting) whole projector column, then the
  global fit (:mod:`slscan.calibrate.planes`).

With both, the camera jointly refined by the inverse-camera method is the one the planes
are measured with and the one written, so the two projector models share one camera.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from slscan.calibrate.camera import (
    CameraCalibration,
    calibrate_camera,
    detect_corners,
)
from slscan.calibrate.io import Calibration
from slscan.calibrate.options import (
    CORRESPONDENCES,
    DISTORTION_MODELS,
    INVERSE_PATTERNS,
    METHODS,
    PLANE_PATTERNS,
)
from slscan.calibrate.planes import LightPlaneCalibration, PanelView, calibrate_light_planes
from slscan.calibrate.procam import (
    InverseCameraCalibration,
    ProjectorCorners,
    calibrate_inverse_camera,
    default_half_window,
    projector_corners,
    projector_corners_from_edges,
)
from slscan.calibrate.target import Board, CornerDetection, board_image_id, board_pose
from slscan.capture.session import Session, load_session
from slscan.decode.family import decoder_function
from slscan.decode.pipeline import DecodeConfig
from slscan.errors import SlscanError
from slscan.patterns import Family, families_in, family

log = logging.getLogger(__name__)

Progress = Callable[[int, int, str], None]


@dataclass(frozen=True)
class CalibrationConfig:
    """How the calibrate stage measures the rig."""

    board: Board = field(default_factory=Board)
    """The printed target every view shows."""
    method: str = "both"
    """{"planes", "inverse-camera", "both"}: the projector's model(s)."""
    planes_pattern: str = "auto"
    """{"auto", "phase", "hybrid", "gray"}: features whose planes are measured; "auto" takes
    the first family the session has in the pattern registry's "auto" order (phase shifting,
    hybrid green lines, Gray-code edges)."""
    camera_distortion: str = "radial-tangential"
    """Camera lens model: {"none", "radial", "radial-tangential", "full"}."""
    projector_distortion: str = "radial-tangential"
    """Projector lens model (inverse camera), as ``camera_distortion``."""
    refine_camera: bool = True
    """Refine the camera jointly with the projector in the stereo calibration."""
    inverse_pattern: str = "auto"
    """{"auto", "phase", "gray"}: the codes (columns and rows) that map the board corners
    into the projector for the inverse camera; "auto" takes the first family with rows the
    session has in the pattern registry's "auto" order (phase shifting, Gray code)."""
    correspondences: str = "edges"
    """{"edges", "pixels"}: what the local homographies are fitted to: one-coordinate
    constraints (the Gray code's sub-pixel stripe edges; phase shifting's every decoded
    pixel, once with its column and once with its row) or Moreno & Taubin's decoded pixels
    with both coordinates (see ``calibrate.procam``)."""
    window: int = 0
    """Half-size (camera px) of the local-homography windows; 0: 0.3 board squares."""
    min_views: int = 3
    """Fewest usable views of the board."""
    panel_margin: float | None = None
    """mm around the board's squares trusted to be the flat panel; None: half a square."""
    keep_raw_planes: bool = True
    """Write the measured per-feature planes into the calibration file too."""

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SlscanError(
                f"unknown calibration method {self.method!r}: expected one of {', '.join(METHODS)}"
            )
        if self.planes_pattern not in PLANE_PATTERNS:
            raise SlscanError(
                f"unknown planes pattern {self.planes_pattern!r}: expected one of {', '.join(PLANE_PATTERNS)}"
            )
        for name in ("camera_distortion", "projector_distortion"):
            if getattr(self, name) not in DISTORTION_MODELS:
                raise SlscanError(
                    f"unknown {name.replace('_', ' ')} model {getattr(self, name)!r}: "
                    f"expected one of {', '.join(DISTORTION_MODELS)}"
                )
        if self.inverse_pattern not in INVERSE_PATTERNS:
            raise SlscanError(
                f"unknown inverse-camera pattern {self.inverse_pattern!r}: "
                f"expected one of {', '.join(INVERSE_PATTERNS)}"
            )
        if self.correspondences not in CORRESPONDENCES:
            raise SlscanError(
                f"unknown correspondences {self.correspondences!r}: expected one of {', '.join(CORRESPONDENCES)}"
            )
        if self.window < 0 or self.min_views < 2:
            raise SlscanError("window must be >= 0 and min_views >= 2")

    @property
    def methods(self) -> tuple[str, ...]:
        return ("inverse-camera", "planes") if self.method == "both" else (self.method,)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["board"] = self.board.to_dict()
        return d


@dataclass(frozen=True)
class CalibrationRun:
    """Everything the calibrate stage measured.

    calibration : what is written to the calibration file
    detections : the board corners of every view (false-valued where not found)
    camera : the camera calibration (Zhang) before any joint refinement
    inverse_camera, light_planes : each method's result, or None
    projector_corners : per view name, the corners mapped into the projector
    """

    calibration: Calibration
    detections: tuple[CornerDetection, ...]
    camera: CameraCalibration
    inverse_camera: InverseCameraCalibration | None
    light_planes: LightPlaneCalibration | None
    projector_corners: dict[str, ProjectorCorners]


def plane_pattern(session: Session, wanted: str = "auto") -> str:
    """The family whose features the planes method measures in ``session`` ("hybrid",
    "gray", "phase"): the one asked, or with "auto" the first present in "auto" order."""
    present = families_in(session.patterns)
    if wanted == "auto":
        if not present:
            raise SlscanError(f"{session.root}: the session has no coded patterns to measure light planes with")
        return present[0].name
    if wanted not in {f.name for f in present}:
        raise SlscanError(f"{session.root}: the session has no {wanted} patterns")
    return wanted


def row_family(session: Session, wanted: str = "auto") -> Family:
    """The family that gives the projector rows the inverse-camera method needs: the one
    asked ("phase", "gray"), or with "auto" the first present in "auto" order that codes
    rows and has them in this session."""

    def has_rows(fam: Family) -> bool:
        return fam.rows and any(p.family == fam.name and p.axis == "rows" for p in session.patterns)

    if wanted != "auto":
        if wanted not in {f.name for f in families_in(session.patterns)}:
            raise SlscanError(
                f"{session.root}: the session has no {wanted} patterns for the inverse camera"
            )
        fam = family(wanted)
        if not has_rows(fam):
            raise SlscanError(
                f"{session.root}: the session's {wanted} patterns code the projector columns "
                "only; the inverse-camera method needs the rows too (capture with --gray-rows, "
                "or slscan scan --board)"
            )
        return fam
    for fam in families_in(session.patterns):
        if has_rows(fam):
            return fam
    raise SlscanError(
        f"{session.root}: the inverse-camera method needs projector row patterns (Gray code or phase "
        "shifting with rows), the session has none (capture with row codes, or use --method planes)"
    )


PLANE_DECODE = DecodeConfig(gray_smooth=False, projector_axes="columns")
"""The decode settings the planes method measures features with: the decode stage's
defaults, but Gray-code edges as found in each row (not averaged along the edge), as the
light planes were fitted before edge averaging existed, and the columns only (planes have
no rows)."""


def _plane_samples(session: Session, view, pattern: str):
    return family(pattern).decode_module().decode(session, view, PLANE_DECODE).samples


def calibration_steps(session: Session, config: CalibrationConfig) -> int:
    """Units of work :func:`calibrate_session` reports to its ``progress`` callback."""
    return 2 * len(session.views) + len(config.methods) + 1


def calibrate_session(
    session: Session | str | os.PathLike,
    config: CalibrationConfig = CalibrationConfig(),
    *,
    rec=None,
    progress: Progress | None = None,
) -> CalibrationRun:
    """Calibrate camera and projector from a capture session of a board in several poses.

    Parameters
    ----------
    session : the capture session (or its folder): every view shows ``config.board``
        under the white frame and the coded patterns (phase shifting or Gray code with
        rows for the inverse-camera method; phase shifting, hybrid or Gray code for the
        planes method)
    config : what to measure and how
    rec : an ``rr.RecordingStream`` for corners, board poses, the projector and its
        planes, and residuals (see :mod:`slscan.viewer.log_calibrate`), or None
    progress : called as ``progress(done, total, label)`` after each unit of work

    Returns
    -------
    CalibrationRun

    Raises
    ------
    SlscanError
        Too few views of the board; patterns missing for the method; degenerate panel
        poses; any image that does not match the session (naming the file).

    References
    ----------
    Z. Zhang, TPAMI 2000; D. Moreno, G. Taubin, 3DIMPVT 2012; C. Rocchini et al.,
    Eurographics 2001 (see the modules of :mod:`slscan.calibrate`).
    """
    from slscan.viewer import log_calibrate as rlog

    if not isinstance(session, Session):
        session = load_session(session)
    board = config.board
    methods = config.methods
    total, done = calibration_steps(session, config), 0

    def step(label: str) -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total, label)

    rows_from = row_family(session, config.inverse_pattern) if "inverse-camera" in methods else None
    pattern = plane_pattern(session, config.planes_pattern) if "planes" in methods else None

    # 1. corners and the camera
    white_id = board_image_id(session)
    detections = []
    for index, view in enumerate(session.views):
        rec_img = view.image_for(white_id)
        # as stored, tone curve and all: a monotone curve keeps a chessboard's saddle points
        # (an sRGB camera's corners, full size: 0.023 px RMS as stored, 0.028 px with the curve undone;
        # benchmarks/calibration.py --response), while the codes are decoded in linear light
        image = session.read_image(view, rec_img)
        det = detect_corners(image, board, source=str(session.image_path(view, rec_img)))
        detections.append(det)
        rlog.log_board_image(rec, image, det, view_index=index)
        step(f"corners {view.name}")
    camera = calibrate_camera(
        detections,
        board,
        session.camera_size,
        distortion=config.camera_distortion,
        min_views=config.min_views,
    )
    step("camera")
    used = set(camera.views)
    views = [
        (i, v, d) for i, (v, d) in enumerate(zip(session.views, detections)) if d.source in used
    ]

    # 2. decode each view
    codes = {}
    samples = {}
    for _, view, _ in views:
        if rows_from is not None and config.correspondences == "edges":
            find = decoder_function(rows_from, "projector_constraints", "projector constraints")
            codes[view.name] = find(session, view)
        elif rows_from is not None:
            find = decoder_function(rows_from, "projector_codes", "per-pixel projector codes")
            codes[view.name] = find(session, view)
        if pattern is not None:
            samples[view.name] = _plane_samples(session, view, pattern)
        step(f"decode {view.name}")

    # 3. the projector as an inverse camera
    lens = camera.lens
    inverse = None
    pcs: dict[str, ProjectorCorners] = {}
    if "inverse-camera" in methods:
        entries = []
        for _, view, det in views:
            found = codes[view.name]
            half = config.window or default_half_window(det, board)
            if config.correspondences == "edges":
                pc = projector_corners_from_edges(found, det.corners, half_window=half)
            else:
                pc = projector_corners(found.column, found.row, found.mask, det.corners, half_window=half)
            pcs[view.name] = pc
            entries.append((view.name, det, pc))
        inverse = calibrate_inverse_camera(
            lens,
            entries,
            board,
            session.projector_size,
            distortion=config.projector_distortion,
            camera_distortion=config.camera_distortion,
            refine_camera=config.refine_camera,
            min_views=config.min_views,
        )
        lens = inverse.rig.camera
        step("inverse camera")

    # 4. the light planes
    planes = None
    if "planes" in methods:
        panels = [
            PanelView(view.name, samples[view.name], board_pose(lens, det, board))
            for _, view, det in views
        ]
        planes = calibrate_light_planes(
            panels,
            lens,
            board,
            session.projector_size[0],
            pattern=pattern,
            margin=config.panel_margin,
        )
        step("light planes")

    residuals: dict = {"camera": camera.residuals()}
    if inverse is not None:
        residuals["inverse_camera"] = inverse.residuals()
    if planes is not None:
        residuals["light_planes"] = planes.residuals()
    calibration = Calibration(
        camera=lens,
        projector_size=session.projector_size,
        projector=None if inverse is None else inverse.rig.projector,
        light_planes=None if planes is None else planes.model,
        raw_columns=None if planes is None or not config.keep_raw_planes else planes.lines.columns,
        raw_planes=None if planes is None or not config.keep_raw_planes else planes.lines.planes,
        residuals=residuals,
        board=board,
        source={
            "session": str(Path(session.root).resolve()),
            "views": [v.name for _, v, _ in views],
            "method": config.method,
            "config": config.to_dict(),
        },
    )
    run = CalibrationRun(calibration, tuple(detections), camera, inverse, planes, pcs)
    _log_calibration(rec, run, session)
    return run


def _log_calibration(rec, run: CalibrationRun, session: Session) -> None:
    """Log a calibration's results to ``rec`` (an ``rr.RecordingStream``): the rig, board poses,
    reprojections, planes, residuals, through the loggers of :mod:`slscan.viewer.log_calibrate`."""
    if rec is None:
        return
    import numpy as np
    import rerun as rr

    from slscan.viewer import log_calibrate as rlog
    from slscan.viewer.log import log_rig

    cal = run.calibration
    old = session.calibration
    rig = cal.rig(
        lights=old.lights if old is not None else (),
        working_distance=old.working_distance if old is not None else 1300.0,
    )
    log_rig(rec, rig)
    board = cal.board
    index = {
        str(session.image_path(v, v.image_for(board_image_id(session)))): i
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
        rlog.log_board_pose(rec, board, pose, view_index=i)
        local = board.object_points(det.ids) @ pose[:3, :3].T + pose[:3, 3]
        rlog.log_reprojection(
            rec, rlog.CAMERA_PATH, det.corners, cal.camera.project_local(local), view_index=i
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
            rlog.log_reprojection(rec, rlog.PROJECTOR_PATH, pts, reproj, view_index=i)
            errors["projector_rms_px"] = float(inverse.view_errors[k, 1])
        rlog.log_view_errors(rec, errors, view_index=i)
    if cal.light_planes is not None and distances:
        near, far = 0.8 * min(distances), 1.1 * max(distances)
        rlog.log_light_planes(rec, cal.light_planes, height=cal.projector_size[1], near=near, far=far)
    if run.light_planes is not None:
        lp = run.light_planes
        rlog.log_plane_residuals(rec, lp.lines.rms, lp.line_rms_after)
    summary = [f"camera RMS {run.camera.rms:.3f} px over {len(run.camera.views)} views"]
    if inverse is not None:
        summary.append(f"stereo RMS {inverse.stereo_rms:.3f} px")
    if run.light_planes is not None:
        summary.append(
            f"planes RMS {run.light_planes.rms_before:.4f} mm -> {run.light_planes.rms_after:.4f} mm (global fit)"
        )
    rec.log(rlog.LOG_PATH, rr.TextLog("; ".join(summary), level="INFO"), static=True)
