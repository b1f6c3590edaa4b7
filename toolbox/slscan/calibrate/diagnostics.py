"""Calibration diagnostics: how well the data pins each parameter, and refits with some held.

Small functions on an :class:`~slscan.calibrate.procam.InverseCameraCalibration`'s own
corner matches, for judging a calibration rather than making one:

- :func:`intrinsics_uncertainty`: one device's intrinsics and their standard deviations
  from the Jacobian of its reprojection (OpenCV ``calibrateCameraExtended``), with the
  residual scaled to the fit's RMS;
- :func:`refit_inverse_camera`: the stereo calibration again with the projector's principal
  point held at a given value (e.g. another tool's), so that the two values can be compared
  on the same corners by reprojection and by what they reconstruct;
- :func:`held_out_errors`: how well a calibration predicts a pose it was not made from: the
  board's pose from the camera's corners, its corners projected into the projector and
  compared with where the projector saw them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slscan.calibrate.camera import distortion_flags, lens_from_opencv
from slscan.calibrate.procam import InverseCameraCalibration, _fixed_only, _orthonormalise
from slscan.calibrate.target import Board
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector, Rig

INTRINSIC_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class IntrinsicsUncertainty:
    """One device calibrated alone from its corner matches.

    lens : the intrinsics found
    std : standard deviation of each of :data:`INTRINSIC_NAMES` (px for fx..cy; 0 for a
        coefficient the model holds)
    rms : px, reprojection RMS
    view_rms : (n,) px per view
    """

    lens: PinholeModel
    std: dict[str, float]
    rms: float
    view_rms: np.ndarray


def intrinsics_uncertainty(
    object_points: list[np.ndarray],
    image_points: list[np.ndarray],
    size: tuple[int, int],
    *,
    distortion: str = "radial-tangential",
) -> IntrinsicsUncertainty:
    """Calibrate one device from board points (per view (k, 3) mm) and their images (per view
    (k, 2) px) and give the intrinsics' standard deviations (OpenCV's, from the Jacobian at
    the solution and the residual variance: they hold if the corner errors are independent;
    a bias common to the views, or too few poses, is not in them).

    Raises SlscanError when OpenCV fails."""
    obj = [np.asarray(o, np.float32).reshape(-1, 3) for o in object_points]
    img = [np.asarray(p, np.float32).reshape(-1, 1, 2) for p in image_points]
    try:
        rms, k, dist, _, _, std, _, per_view = cv2.calibrateCameraExtended(
            obj, img, (int(size[0]), int(size[1])), None, None, flags=distortion_flags(distortion))
    except cv2.error as exc:
        raise SlscanError(f"calibration failed in OpenCV: {str(exc).strip().splitlines()[-1]}") from None
    std = np.asarray(std, float).reshape(-1)
    return IntrinsicsUncertainty(
        lens=lens_from_opencv(k, dist, size),
        std={name: float(std[i]) for i, name in enumerate(INTRINSIC_NAMES)},
        rms=float(rms),
        view_rms=np.asarray(per_view, float).reshape(-1),
    )


@dataclass(frozen=True)
class Refit:
    """A stereo calibration redone on the same corners with some parameters held.

    rig : camera and projector
    stereo_rms : px over both devices
    view_errors : (n, 2) px per view, camera and projector
    """

    rig: Rig
    stereo_rms: float
    view_errors: np.ndarray


def refit_inverse_camera(
    inverse: InverseCameraCalibration,
    board: Board,
    *,
    projector_principal_point: tuple[float, float] | None = None,
    distortion: str = "radial-tangential",
    camera_distortion: str = "radial-tangential",
) -> Refit:
    """The stereo calibration of ``inverse`` redone from its own corner matches, starting from
    its rig, with the projector's principal point held at ``projector_principal_point``
    (px; None: free, as calibrated). OpenCV's ``CALIB_FIX_PRINCIPAL_POINT`` holds the
    camera's too (at its calibrated value, within a few px of any other estimate).

    Raises SlscanError when OpenCV fails."""
    cam, proj = inverse.rig.camera, inverse.rig.projector.lens
    kc, dc = cam.K, cam.dist_array.reshape(1, 5)
    kp, dp = proj.K, proj.dist_array.reshape(1, 5)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | _fixed_only(distortion_flags(distortion)) \
        | _fixed_only(distortion_flags(camera_distortion))
    if projector_principal_point is not None:
        kp[0, 2], kp[1, 2] = projector_principal_point
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
    obj = [board.object_points(ids).astype(np.float32) for ids in inverse.object_ids]
    cam_pts = [p.astype(np.float32).reshape(-1, 1, 2) for p in inverse.camera_points]
    proj_pts = [p.astype(np.float32).reshape(-1, 1, 2) for p in inverse.projector_points]
    try:
        result = cv2.stereoCalibrateExtended(
            obj, cam_pts, proj_pts, kc.copy(), dc.copy(), kp.copy(), dp.copy(), (cam.width, cam.height),
            None, None, flags=flags, criteria=(cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-9))
    except cv2.error as exc:
        raise SlscanError(f"stereo refit failed in OpenCV: {str(exc).strip().splitlines()[-1]}") from None
    s_rms, kc2, dc2, kp2, dp2, r, t = result[:7]
    projector_from_camera = np.eye(4)
    projector_from_camera[:3, :3] = r
    projector_from_camera[:3, 3] = np.asarray(t).reshape(3)
    rig = Rig(lens_from_opencv(kc2, dc2, (cam.width, cam.height)),
              Projector(lens_from_opencv(kp2, dp2, (proj.width, proj.height)),
                        _orthonormalise(np.linalg.inv(projector_from_camera))))
    return Refit(rig, float(s_rms), np.asarray(result[-1], float).reshape(-1, 2))


def held_out_errors(
    rig: Rig,
    object_points: np.ndarray,
    camera_points: np.ndarray,
    projector_points: np.ndarray,
) -> tuple[float, float]:
    """How well ``rig`` predicts one pose of the board: its pose from the camera's corners
    (``solvePnP`` with ``rig.camera``), then the corners ``object_points`` (k, 3) projected
    into the projector and compared with ``projector_points`` (k, 2) px, where the projector
    saw them. Returns the camera's and the projector's RMS, px."""
    cam = rig.camera
    obj = np.asarray(object_points, np.float64).reshape(-1, 3)
    ok, rvec, tvec = cv2.solvePnP(obj, np.asarray(camera_points, np.float64).reshape(-1, 1, 2), cam.K,
                                  cam.dist_array)
    if not ok:
        return float("nan"), float("nan")
    r, _ = cv2.Rodrigues(rvec)
    in_camera = obj @ r.T + np.asarray(tvec).reshape(3)
    cam_err = cam.project_local(in_camera) - np.asarray(camera_points).reshape(-1, 2)
    proj_err = rig.projector.project(in_camera) - np.asarray(projector_points).reshape(-1, 2)
    return (float(np.sqrt(np.mean(np.sum(cam_err**2, axis=1)))),
            float(np.sqrt(np.mean(np.sum(proj_err**2, axis=1)))))
