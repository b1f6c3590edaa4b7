"""Camera intrinsics and lens distortion from views of a printed board, through OpenCV.

Corners are found by OpenCV's detectors (chessboard: ``findChessboardCorners`` refined by
``cornerSubPix``; ChArUco: ``CharucoDetector``) and the camera is calibrated by Zhang's
method (``calibrateCamera``). Views where the board is not found, and views whose
reprojection error stands out, are rejected one at a time with a warning naming the image.

References
----------
Z. Zhang. "A flexible new technique for camera calibration". IEEE Transactions on
Pattern Analysis and Machine Intelligence 22(11) (2000), 1330-1334.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from slscan.calibrate.options import DISTORTION_MODELS
from slscan.calibrate.target import MIN_CORNERS, Board, CornerDetection, pose_matrix
from slscan.decode.masks import channel_mean
from slscan.errors import SlscanError
from slscan.rig import PinholeModel

log = logging.getLogger(__name__)

_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


def distortion_flags(model: str) -> int:
    """OpenCV calibration flags that leave only ``model``'s coefficients free."""
    flags = {
        "none": cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K1
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3,
        "radial": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
        "radial-tangential": cv2.CALIB_FIX_K3,
        "full": 0,
    }
    if model not in flags:
        raise SlscanError(
            f"unknown distortion model {model!r}: expected one of {', '.join(DISTORTION_MODELS)}"
        )
    return flags[model]


def grey_image(image: np.ndarray) -> np.ndarray:
    """Grey float32 (h, w) in [0, 255] of an (h, w) or (h, w, 3) uint8/uint16/float image."""
    image = np.asarray(image)
    scale = {np.dtype(np.uint8): 1.0, np.dtype(np.uint16): 255.0 / 65535.0}.get(image.dtype, 255.0)
    grey = channel_mean(image)
    return grey * np.float32(scale)


def _subpix_half_window(corners: np.ndarray, board: Board) -> int:
    """Half-size of the cornerSubPix window: a fifth of the corner spacing, 3..15 px."""
    grid = corners.reshape(board.rows, board.columns, 2)
    spacing = np.concatenate(
        [
            np.linalg.norm(np.diff(grid, axis=0), axis=-1).ravel(),
            np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel(),
        ]
    )
    return int(np.clip(round(0.2 * float(np.min(spacing))), 3, 15))


def detect_corners(image: np.ndarray, board: Board, *, source: str = "") -> CornerDetection:
    """Find the inner corners of ``board`` in ``image``.

    Parameters
    ----------
    image : (h, w) or (h, w, 3) uint8/uint16 capture (RGB is read as the mean of channels)
    board : the target
    source : the image's name, carried into the result for messages

    Returns
    -------
    CornerDetection
        Sub-pixel corners and their ids; false-valued, with the reason, when the board is
        not found. A chessboard is found whole or not at all; a ChArUco board may be seen
        in part.
    """
    grey = grey_image(image)
    grey8 = np.clip(np.rint(grey), 0, 255).astype(np.uint8)
    if board.kind == "chessboard":
        size = (board.columns, board.rows)
        flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
        found, corners = cv2.findChessboardCorners(grey8, size, flags=flags)
        if not found:
            found, corners = cv2.findChessboardCornersSB(
                grey8, size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE
            )
        if not found or corners is None:
            return CornerDetection.failed(
                source, f"{board.columns}x{board.rows} chessboard not found"
            )
        corners = corners.reshape(-1, 1, 2).astype(np.float32)
        half = _subpix_half_window(corners.reshape(-1, 2), board)
        corners = cv2.cornerSubPix(grey, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
        return CornerDetection(
            source, corners.reshape(-1, 2).astype(np.float64), np.arange(board.n_corners)
        )
    detector = cv2.aruco.CharucoDetector(board.aruco_board())
    corners, ids, _, marker_ids = detector.detectBoard(grey8)
    if ids is None or len(ids) < MIN_CORNERS:
        n_markers = 0 if marker_ids is None else len(marker_ids)
        n_corners = 0 if ids is None else len(ids)
        return CornerDetection.failed(
            source, f"ChArUco board not found ({n_markers} markers, {n_corners} corners)"
        )
    ids = ids.reshape(-1).astype(int)
    order = np.argsort(ids)
    ids, corners = ids[order], corners.reshape(-1, 2)[order].astype(np.float32)
    # refine in the white gap between the corner and the markers of its two white squares
    half = _charuco_half_window(corners, ids, board)
    corners = cv2.cornerSubPix(
        grey, corners.reshape(-1, 1, 2), (half, half), (-1, -1), _SUBPIX_CRITERIA
    )
    return CornerDetection(source, corners.reshape(-1, 2).astype(np.float64), ids)


def _charuco_half_window(corners: np.ndarray, ids: np.ndarray, board: Board) -> int:
    """Half-size of the cornerSubPix window for ChArUco corners: 0.8 times the white gap
    between a corner and the nearest marker, in px (2..10)."""
    obj = board.object_points(ids)[:, :2]
    d_img = np.linalg.norm(np.diff(corners.reshape(-1, 2), axis=0), axis=1)
    d_obj = np.linalg.norm(np.diff(obj, axis=0), axis=1)
    near = np.abs(d_obj - board.square) < 1e-6  # neighbours along a row
    if not near.any():
        return 2
    px_per_mm = float(np.min(d_img[near] / d_obj[near]))
    gap = 0.5 * (board.square - board.marker_side) * px_per_mm
    return int(np.clip(round(0.8 * gap), 2, 10))


@dataclass(frozen=True)
class CameraCalibration:
    """The camera's intrinsics and the board's pose in each view used.

    lens : the calibrated camera
    rms : float, px, reprojection RMS over every corner of the views used
    views : (n,) names (sources) of the views used
    view_errors : (n,) float64 px, reprojection RMS of each view used
    camera_from_board : (n, 4, 4) float64, mm, the board's pose in each view used
    detections : the n detections used
    rejected : ``(source, reason)`` of each view left out
    std_intrinsics : (4,) float64 px, standard deviations of fx, fy, cx, cy
    """

    lens: PinholeModel
    rms: float
    views: tuple[str, ...]
    view_errors: np.ndarray
    camera_from_board: np.ndarray
    detections: tuple[CornerDetection, ...]
    rejected: tuple[tuple[str, str], ...] = ()
    std_intrinsics: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))

    def residuals(self) -> dict:
        """JSON-ready residual summary."""
        return {
            "rms_px": self.rms,
            "views": [
                {"name": name, "rms_px": float(err)}
                for name, err in zip(self.views, self.view_errors)
            ],
            "rejected": [{"name": name, "reason": reason} for name, reason in self.rejected],
            "std_fx_fy_cx_cy_px": [float(v) for v in self.std_intrinsics],
        }


def lens_from_opencv(k: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> PinholeModel:
    """A :class:`PinholeModel` from OpenCV's camera matrix (3, 3) and distortion (>= 5,)."""
    d = np.zeros(5)
    dist = np.asarray(dist, float).ravel()
    d[: min(5, len(dist))] = dist[:5]
    return PinholeModel(
        int(size[0]),
        int(size[1]),
        float(k[0, 0]),
        float(k[1, 1]),
        float(k[0, 2]),
        float(k[1, 2]),
        tuple(float(v) for v in d),
    )


def reprojection_errors(
    lens: PinholeModel, object_points: np.ndarray, image_points: np.ndarray, pose: np.ndarray
) -> np.ndarray:
    """Distances (n,) px between ``image_points`` (n, 2) and ``object_points`` (n, 3) seen
    by ``lens`` with the object at ``pose`` (4, 4, camera_from_object)."""
    local = object_points @ pose[:3, :3].T + pose[:3, 3]
    return np.linalg.norm(lens.project_local(local) - image_points, axis=1)


def calibrate_camera(
    detections: Sequence[CornerDetection],
    board: Board,
    image_size: tuple[int, int],
    *,
    distortion: str = "radial-tangential",
    min_views: int = 3,
    outlier_factor: float = 3.0,
    outlier_floor: float = 0.5,
) -> CameraCalibration:
    """Calibrate a camera from board corners found in several views (Zhang 2000).

    Parameters
    ----------
    detections : one per view; false-valued ones are rejected with a warning
    board : the target the corners belong to
    image_size : (width, height) px
    distortion : {"none", "radial", "radial-tangential", "full"}
    min_views : fewest views to calibrate from
    outlier_factor, outlier_floor : a view whose reprojection RMS exceeds both
        ``outlier_factor`` times the median view's and ``outlier_floor`` px is rejected
        (the worst first, then the camera is calibrated again)

    Returns
    -------
    CameraCalibration

    Raises
    ------
    SlscanError
        Fewer than ``min_views`` views left, naming the rejected ones.

    References
    ----------
    Z. Zhang. "A flexible new technique for camera calibration". IEEE TPAMI 22(11)
    (2000), 1330-1334.
    """
    flags = distortion_flags(distortion)
    used = []
    rejected: list[tuple[str, str]] = []
    for det in detections:
        if det:
            used.append(det)
        else:
            reason = det.reason or f"only {len(det.ids)} corners found"
            log.warning("%s: view rejected: %s", det.source, reason)
            rejected.append((det.source, reason))
    while True:
        if len(used) < max(min_views, 1):
            names = "; ".join(f"{s}: {r}" for s, r in rejected) or "none"
            raise SlscanError(
                f"camera calibration needs at least {min_views} views of the {board.describe()}, "
                f"{len(used)} left (rejected: {names})"
            )
        obj = [board.object_points(d.ids).astype(np.float32) for d in used]
        img = [d.corners.astype(np.float32).reshape(-1, 1, 2) for d in used]
        try:
            rms, k, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
                obj, img, tuple(int(v) for v in image_size), None, None, flags=flags
            )
        except cv2.error as exc:
            raise SlscanError(
                f"camera calibration failed in OpenCV: {str(exc).strip().splitlines()[-1]}"
            ) from None
        per_view = np.asarray(per_view, float).reshape(-1)
        worst = int(np.argmax(per_view))
        limit = max(outlier_factor * float(np.median(per_view)), outlier_floor)
        if per_view[worst] > limit and len(used) > min_views:
            reason = f"outlier: reprojection RMS {per_view[worst]:.3f} px (limit {limit:.3f} px)"
            log.warning("%s: view rejected: %s", used[worst].source, reason)
            rejected.append((used[worst].source, reason))
            del used[worst]
            continue
        break
    lens = lens_from_opencv(k, dist, image_size)
    poses = np.stack([pose_matrix(r, t) for r, t in zip(rvecs, tvecs)])
    log.info(
        "camera: fx %.2f fy %.2f cx %.2f cy %.2f px, RMS %.3f px over %d views",
        lens.fx,
        lens.fy,
        lens.cx,
        lens.cy,
        rms,
        len(used),
    )
    return CameraCalibration(
        lens=lens,
        rms=float(rms),
        views=tuple(d.source for d in used),
        view_errors=per_view,
        camera_from_board=poses,
        detections=tuple(used),
        rejected=tuple(rejected),
        std_intrinsics=np.asarray(std_in, float).reshape(-1)[:4],
    )
