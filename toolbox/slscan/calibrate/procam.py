"""The projector as an inverse camera, calibrated from local homographies (Moreno & Taubin 2012).

For each view of the board, every camera pixel's projector column and row are decoded
from Gray codes. Around each board corner found in the camera, a homography from camera
pixels to projector pixels is fitted in a small window and the corner is mapped through
it: the board corners are thus "seen" by the projector with sub-pixel accuracy, although
a Gray code only gives whole projector pixels. Two kinds of correspondences
(``correspondences=``):

``"pixels"``
    Moreno & Taubin's: every decoded camera pixel with its (integer) projector column and
    row; the homography is fitted robustly (RANSAC, then least squares on the inliers).
    When camera and projector pixels are about the same size the rounding error is not
    random but a moiré pattern over the window, and biases the corner (0.14 projector px
    RMS at the virtual rig's 1:1 sampling).
``"edges"`` (default)
    the sub-pixel stripe edges of the Gray code, along camera rows for the columns and
    along camera columns for the rows (:func:`decode_gray_axes`): each edge is a point
    whose projector column (or row) is known exactly, ``c + 0.5``. The homography is fitted
    to those one-coordinate constraints by the direct linear transform, with one round of
    outlier rejection; no rounding, no moiré.

The projector is then calibrated like a camera (Zhang's method) and its pose relative to
the camera follows from a stereo calibration, which also refines both devices'
intrinsics jointly.

References
----------
D. Moreno, G. Taubin. "Simple, accurate, and robust projector-camera calibration".
Second International Conference on 3D Imaging, Modeling, Processing, Visualization and
Transmission (3DIMPVT), 2012, 464-471.

Z. Zhang. "A flexible new technique for camera calibration". IEEE TPAMI 22(11) (2000),
1330-1334.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from slscan.calibrate.camera import distortion_flags, lens_from_opencv
from slscan.calibrate.target import MIN_CORNERS, Board, CornerDetection, pose_matrix
from slscan.decode.family import ProjectorConstraints
from slscan.decode.graycode import GrayAxes, decode_gray_axes  # noqa: F401 (moved there; imported from here)
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector, Rig

log = logging.getLogger(__name__)

RANSAC_THRESHOLD_PX = 1.5
"""Decoded pixels farther than this (projector px) from the local homography are outliers."""
EDGE_OUTLIER_SIGMAS = 3.0
"""Edge constraints beyond this many robust sigmas of the first fit are dropped."""


@dataclass(frozen=True)
class ProjectorCorners:
    """Board corners of one view mapped into the projector by local homographies.

    points : (k, 2) float64 projector px of the k corners given (NaN where not mapped)
    ok : (k,) bool, mapped: enough decoded pixels around the corner
    support : (k,) int decoded pixels (inliers) the corner's homography was fitted to
    residual : (k,) float64 projector px, RMS of the inliers about the homography
    """

    points: np.ndarray
    ok: np.ndarray
    support: np.ndarray
    residual: np.ndarray

    def __bool__(self) -> bool:
        return int(self.ok.sum()) >= MIN_CORNERS


def default_half_window(detection: CornerDetection, board: Board) -> int:
    """Half-size (px) of the homography window: 0.3 corner spacings, between 4 and 30 px."""
    if not detection:
        return 8
    obj = board.object_points(detection.ids)[:, :2]
    # spacing in px from the camera's local scale: image distance per board distance
    d_img = np.linalg.norm(detection.corners[1:] - detection.corners[:-1], axis=1)
    d_obj = np.linalg.norm(obj[1:] - obj[:-1], axis=1)
    px_per_mm = float(np.median(d_img / np.maximum(d_obj, 1e-9)))
    return int(np.clip(round(0.3 * board.square * px_per_mm), 4, 30))


def projector_corners(
    column: np.ndarray,
    row: np.ndarray,
    valid: np.ndarray,
    corners: np.ndarray,
    *,
    half_window: int,
    min_support: int | None = None,
    ransac_threshold: float = RANSAC_THRESHOLD_PX,
) -> ProjectorCorners:
    """Map camera ``corners`` into the projector through local homographies.

    Parameters
    ----------
    column, row : (h, w) int projector column and row decoded at each camera pixel
    valid : (h, w) bool, where both were decoded
    corners : (k, 2) float64 camera px
    half_window : the window is ``2 half_window + 1`` px square around each corner
    min_support : fewest decoded pixels (inliers) for a corner; default a quarter of the
        window (the black squares of a board often do not decode)
    ransac_threshold : projector px

    Returns
    -------
    ProjectorCorners
        False-valued when fewer than :data:`MIN_CORNERS` corners were mapped.

    References
    ----------
    D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration",
    3DIMPVT 2012.
    """
    h, w = valid.shape
    corners = np.asarray(corners, float).reshape(-1, 2)
    k = len(corners)
    side = 2 * half_window + 1
    min_support = side * side // 4 if min_support is None else int(min_support)
    points = np.full((k, 2), np.nan)
    ok = np.zeros(k, bool)
    support = np.zeros(k, int)
    residual = np.full(k, np.nan)
    offsets = np.arange(-half_window, half_window + 1)
    for i, (cx, cy) in enumerate(corners):
        x0, y0 = round(cx), round(cy)
        xs, ys = x0 + offsets, y0 + offsets
        xs, ys = xs[(xs >= 0) & (xs < w)], ys[(ys >= 0) & (ys < h)]
        if len(xs) == 0 or len(ys) == 0:
            continue
        win = np.ix_(ys, xs)
        sel = valid[win]
        if int(sel.sum()) < max(min_support, 8):
            support[i] = int(sel.sum())
            continue
        gy, gx = np.meshgrid(ys, xs, indexing="ij")
        # camera pixels relative to the corner: better conditioned, and the corner maps from 0
        src = np.stack([gx[sel] - cx, gy[sel] - cy], axis=1).astype(np.float64)
        dst = np.stack([column[win][sel], row[win][sel]], axis=1).astype(np.float64)
        hom, inliers = cv2.findHomography(src, dst, cv2.RANSAC, ransac_threshold)
        if hom is None:
            continue
        inl = inliers.reshape(-1).astype(bool)
        if int(inl.sum()) < max(min_support, 8):
            support[i] = int(inl.sum())
            continue
        hom, _ = cv2.findHomography(src[inl], dst[inl], 0)  # least squares on the inliers
        if hom is None or abs(hom[2, 2]) < 1e-12:
            continue
        mapped = cv2.perspectiveTransform(src[inl].reshape(-1, 1, 2), hom).reshape(-1, 2)
        residual[i] = float(np.sqrt(np.mean(np.sum((mapped - dst[inl]) ** 2, axis=1))))
        points[i] = hom[:2, 2] / hom[2, 2]
        ok[i] = True
        support[i] = int(inl.sum())
    return ProjectorCorners(points, ok, support, residual)


def _dlt_homography(
    px: np.ndarray, py: np.ndarray, value: np.ndarray, is_row: np.ndarray
) -> np.ndarray | None:
    """Homography (3, 3) from one-coordinate constraints: ``u(p) = value`` where not
    ``is_row``, ``v(p) = value`` where ``is_row``; points and values pre-normalised."""
    p = np.stack([px, py, np.ones_like(px)], axis=1)
    zero = np.zeros_like(p)
    a = np.where(
        is_row[:, None],
        np.concatenate([zero, p, -value[:, None] * p], axis=1),
        np.concatenate([p, zero, -value[:, None] * p], axis=1),
    )
    # the right singular vector of the smallest singular value, from the 9 x 9 normal
    # matrix: the same vector (points and values are normalised to about unit size) at a
    # fraction of the cost of an SVD of the (n, 9) matrix when every pixel is a constraint
    try:
        eigval, eigvec = np.linalg.eigh(a.T @ a)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(eigval).all() or eigval[1] <= 1e-20 * eigval[-1]:
        return None
    return eigvec[:, 0].reshape(3, 3)


def projector_corners_from_edges(
    constraints: ProjectorConstraints,
    corners: np.ndarray,
    *,
    half_window: int,
    min_support: int | None = None,
    outlier_sigmas: float = EDGE_OUTLIER_SIGMAS,
) -> ProjectorCorners:
    """Map camera ``corners`` into the projector through local homographies fitted to the
    Gray code's sub-pixel stripe edges.

    Parameters
    ----------
    constraints : camera points with a known projector column or row: the Gray code's
        column edges (along camera rows) and row edges (along camera columns), or phase
        shifting's every decoded pixel (the family decoder's ``projector_constraints``)
    corners : (k, 2) float64 camera px
    half_window : camera px; edges within ``half_window`` of the corner (both axes) count
    min_support : fewest column edges and fewest row edges, each; default ``half_window``
    outlier_sigmas : constraints beyond this many robust sigmas (1.4826 MAD) of the first
        fit are dropped and the homography fitted again

    Returns
    -------
    ProjectorCorners
        ``support`` counts the edge constraints kept, ``residual`` is their RMS in
        projector px (along the coordinate each constrains).

    References
    ----------
    D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration",
    3DIMPVT 2012 (local homographies; here fitted to stripe edges instead of pixels).
    """
    cx_all, cy_all = constraints.x, constraints.y
    val_all, is_row_all = constraints.value, constraints.is_row
    corners = np.asarray(corners, float).reshape(-1, 2)
    k = len(corners)
    min_support = half_window if min_support is None else int(min_support)
    points = np.full((k, 2), np.nan)
    ok = np.zeros(k, bool)
    support = np.zeros(k, int)
    residual = np.full(k, np.nan)
    scale = 1.0 / max(half_window, 1)
    by_y = np.argsort(cy_all, kind="stable")  # each window is a band of rows, then a span of x
    y_sorted = cy_all[by_y]
    for i, (x0, y0) in enumerate(corners):
        band = by_y[
            np.searchsorted(y_sorted, y0 - half_window, "left") : np.searchsorted(
                y_sorted, y0 + half_window, "right"
            )
        ]
        sel = np.sort(band[np.abs(cx_all[band] - x0) <= half_window])
        is_row = is_row_all[sel]
        if min(int(is_row.sum()), int((~is_row).sum())) < max(min_support, 4):
            support[i] = len(sel)
            continue
        px, py = (cx_all[sel] - x0) * scale, (cy_all[sel] - y0) * scale
        value = val_all[sel]
        u0, v0 = float(np.median(value[~is_row])), float(np.median(value[is_row]))
        vs = np.maximum(np.ptp(value[~is_row]), np.ptp(value[is_row])) / 2 or 1.0
        norm_value = np.where(is_row, value - v0, value - u0) / vs
        keep = np.ones(len(sel), bool)
        hom = None
        for iteration in range(3):  # fit, drop outliers, fit again (at most twice)
            hom = _dlt_homography(px[keep], py[keep], norm_value[keep], is_row[keep])
            if hom is None:
                break
            q = np.stack([px, py, np.ones_like(px)], axis=1) @ hom.T
            with np.errstate(divide="ignore", invalid="ignore"):
                pred = np.where(is_row, q[:, 1], q[:, 0]) / q[:, 2]
            err = (pred - norm_value) * vs
            if iteration == 2:
                break
            sigma = 1.4826 * float(np.median(np.abs(err[keep])))
            new_keep = np.abs(err) <= max(outlier_sigmas * sigma, 1e-6)
            n_col, n_row = int((new_keep & ~is_row).sum()), int((new_keep & is_row).sum())
            if min(n_col, n_row) < max(min_support, 4) or np.array_equal(new_keep, keep):
                break
            keep = new_keep
        if hom is None or abs(hom[2, 2]) < 1e-12:
            continue
        points[i] = [u0 + vs * hom[0, 2] / hom[2, 2], v0 + vs * hom[1, 2] / hom[2, 2]]
        ok[i] = bool(np.isfinite(points[i]).all())
        support[i] = int(keep.sum())
        residual[i] = float(np.sqrt(np.mean(err[keep] ** 2)))
    return ProjectorCorners(points, ok, support, residual)


@dataclass(frozen=True)
class InverseCameraCalibration:
    """The rig from the projector calibrated as an inverse camera.

    rig : camera (jointly refined unless asked not to) and projector with its pose
    stereo_rms : px, RMS reprojection error of the stereo calibration over the corners
        in both devices
    camera_rms, projector_rms : px, of each device's own calibration before the joint one
    views : (n,) names of the views used
    view_errors : (n, 2) float64 px, per-view RMS in the camera and in the projector
    object_ids : per view, (k,) corner ids used
    camera_points, projector_points : per view, (k, 2) px of those corners
    projector_from_board : (n, 4, 4) mm, the board's pose in the projector, each view
    rejected : ``(view, reason)`` of views left out
    """

    rig: Rig
    stereo_rms: float
    camera_rms: float
    projector_rms: float
    views: tuple[str, ...]
    view_errors: np.ndarray
    object_ids: tuple[np.ndarray, ...]
    camera_points: tuple[np.ndarray, ...]
    projector_points: tuple[np.ndarray, ...]
    projector_from_board: np.ndarray
    rejected: tuple[tuple[str, str], ...] = ()

    def residuals(self) -> dict:
        return {
            "stereo_rms_px": self.stereo_rms,
            "camera_rms_px": self.camera_rms,
            "projector_rms_px": self.projector_rms,
            "views": [
                {
                    "name": name,
                    "camera_rms_px": float(e[0]),
                    "projector_rms_px": float(e[1]),
                    "corners": len(ids),
                }
                for name, e, ids in zip(self.views, self.view_errors, self.object_ids)
            ],
            "rejected": [{"name": name, "reason": reason} for name, reason in self.rejected],
        }


def calibrate_inverse_camera(
    camera: PinholeModel,
    views: Sequence[tuple[str, CornerDetection, ProjectorCorners]],
    board: Board,
    projector_size: tuple[int, int],
    *,
    distortion: str = "radial-tangential",
    camera_distortion: str = "radial-tangential",
    refine_camera: bool = True,
    min_views: int = 3,
) -> InverseCameraCalibration:
    """Calibrate the projector as an inverse camera and find its pose (Moreno & Taubin 2012).

    Parameters
    ----------
    camera : the camera, calibrated (e.g. :func:`slscan.calibrate.camera.calibrate_camera`)
    views : per view, its name, the board corners in the camera and those corners mapped
        into the projector (:func:`projector_corners`); views with too few mapped corners
        are rejected with a warning
    board : the target
    projector_size : (width, height) px
    distortion : projector lens model, {"none", "radial", "radial-tangential", "full"}
    camera_distortion : the camera's lens model, kept in the joint refinement
    refine_camera : refine camera and projector intrinsics jointly with the pose
        (``stereoCalibrate`` with the intrinsics as a guess); else keep them fixed
    min_views : fewest views

    Returns
    -------
    InverseCameraCalibration

    Raises
    ------
    SlscanError
        Fewer than ``min_views`` usable views, naming the rejected ones.

    References
    ----------
    D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration",
    3DIMPVT 2012. Z. Zhang, "A flexible new technique for camera calibration", TPAMI 2000.
    """
    proj_flags = distortion_flags(distortion)
    names, obj, cam_pts, proj_pts, ids_used = [], [], [], [], []
    rejected = []
    for name, det, pc in views:
        if not det or not pc:
            reason = (
                det.reason
                if not det
                else (
                    f"only {int(pc.ok.sum())} board corners decoded in the projector "
                    f"(need {MIN_CORNERS}); is the board lit by the projector, are there row codes?"
                )
            )
            log.warning("%s: view rejected for the projector: %s", name, reason)
            rejected.append((name, reason))
            continue
        names.append(name)
        ids_used.append(det.ids[pc.ok])
        obj.append(board.object_points(det.ids[pc.ok]).astype(np.float32))
        cam_pts.append(det.corners[pc.ok].astype(np.float32).reshape(-1, 1, 2))
        proj_pts.append(pc.points[pc.ok].astype(np.float32).reshape(-1, 1, 2))
    if len(names) < min_views:
        listed = "; ".join(f"{n}: {r}" for n, r in rejected) or "none"
        raise SlscanError(
            f"projector calibration needs at least {min_views} views with the board decoded in the "
            f"projector, {len(names)} found (rejected: {listed})"
        )
    psize = (int(projector_size[0]), int(projector_size[1]))
    try:
        p_rms, kp, dp, _, _ = cv2.calibrateCamera(
            obj, proj_pts, psize, None, None, flags=proj_flags
        )
        kc, dc = camera.K, camera.dist_array.reshape(1, 5)
        c_rms = _rms_with_fixed_intrinsics(obj, cam_pts, kc, dc)
        flags = cv2.CALIB_FIX_INTRINSIC
        if refine_camera:
            flags = (
                cv2.CALIB_USE_INTRINSIC_GUESS
                | _fixed_only(proj_flags)
                | _fixed_only(distortion_flags(camera_distortion))
            )
        result = cv2.stereoCalibrateExtended(
            obj,
            cam_pts,
            proj_pts,
            kc.copy(),
            dc.copy(),
            kp,
            dp,
            (camera.width, camera.height),
            None,
            None,
            flags=flags,
            criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-9),
        )
    except cv2.error as exc:
        raise SlscanError(
            f"projector calibration failed in OpenCV: {str(exc).strip().splitlines()[-1]}"
        ) from None
    s_rms, kc2, dc2, kp2, dp2, r, t, _, _, rvecs, tvecs, per_view = result
    cam_lens = lens_from_opencv(kc2, dc2, (camera.width, camera.height))
    proj_lens = lens_from_opencv(kp2, dp2, psize)
    projector_from_camera = np.eye(4)
    projector_from_camera[:3, :3] = r
    projector_from_camera[:3, 3] = np.asarray(t).reshape(3)
    rig_from_projector = np.linalg.inv(projector_from_camera)
    rig_from_projector[3] = [0, 0, 0, 1]
    rig = Rig(cam_lens, Projector(proj_lens, _orthonormalise(rig_from_projector)))
    cam_from_board = [pose_matrix(rv, tv) for rv, tv in zip(rvecs, tvecs)]
    projector_from_board = np.stack([projector_from_camera @ p for p in cam_from_board])
    log.info(
        "projector: fx %.2f fy %.2f cx %.2f cy %.2f px, baseline %.1f mm, stereo RMS %.3f px",
        proj_lens.fx,
        proj_lens.fy,
        proj_lens.cx,
        proj_lens.cy,
        float(np.linalg.norm(rig.projector.center)),
        s_rms,
    )
    return InverseCameraCalibration(
        rig=rig,
        stereo_rms=float(s_rms),
        camera_rms=float(c_rms),
        projector_rms=float(p_rms),
        views=tuple(names),
        view_errors=np.asarray(per_view, float).reshape(-1, 2),
        object_ids=tuple(ids_used),
        camera_points=tuple(p.reshape(-1, 2).astype(np.float64) for p in cam_pts),
        projector_points=tuple(p.reshape(-1, 2).astype(np.float64) for p in proj_pts),
        projector_from_board=projector_from_board,
        rejected=tuple(rejected),
    )


def _fixed_only(flags: int) -> int:
    """Turn "zero and keep" distortion flags into "keep at the guess" ones, so that in a
    joint refinement a coefficient left out of one device's model does not reset the
    other device's."""
    if flags & cv2.CALIB_ZERO_TANGENT_DIST:
        flags = (flags & ~cv2.CALIB_ZERO_TANGENT_DIST) | cv2.CALIB_FIX_TANGENT_DIST
    return flags


def _rms_with_fixed_intrinsics(obj, img, k, d) -> float:
    """Reprojection RMS (px) of views with the intrinsics fixed (each view's pose solved)."""
    sq, n = 0.0, 0
    for o, p in zip(obj, img):
        _, rvec, tvec = cv2.solvePnP(o, p, k, d)
        proj, _ = cv2.projectPoints(o, rvec, tvec, k, d)
        sq += float(np.sum((proj.reshape(-1, 2) - p.reshape(-1, 2)) ** 2))
        n += len(o)
    return float(np.sqrt(sq / max(n, 1)))


def _orthonormalise(pose: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(pose[:3, :3])
    out = pose.copy()
    out[:3, :3] = u @ vt
    return out
