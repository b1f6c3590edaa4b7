"""Ray-plane triangulation: camera rays through stripe samples meet the projector's light planes."""

from __future__ import annotations

import logging
import math

import numpy as np

from slscan.decode.samples import LightPlanes, StripeSamples
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector

log = logging.getLogger(__name__)

MIN_RAY_PLANE_ANGLE_DEG = 0.5
"""Rays closer than this to lying in their light plane give no point (NaN)."""


class RigPlanes:
    """Light planes from the rig's known calibration: the projector as an inverse pinhole.

    Implements :class:`slscan.decode.samples.LightPlanes` with
    :meth:`slscan.rig.Projector.column_planes` (exact when the projector lens has no
    distortion; with distortion a projector column is not a plane and this is the plane
    of its undistorted model).
    """

    def __init__(self, projector: Projector) -> None:
        if not isinstance(projector, Projector):
            raise SlscanError(
                f"RigPlanes needs a slscan.rig.Projector, got {type(projector).__name__}"
            )
        self.projector = projector
        if any(projector.lens.dist):
            log.warning("the projector lens has distortion: its columns are approximated by planes")

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), for columns (n,) px."""
        return self.projector.column_planes(np.asarray(projector_columns, dtype=np.float64))

    def __repr__(self) -> str:
        lens = self.projector.lens
        return f"RigPlanes(projector {lens.width}x{lens.height})"


def intersect_rays_planes(
    rays: np.ndarray, planes: np.ndarray, *, min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG
) -> np.ndarray:
    """Points (k, 3) where rays from the origin along ``rays`` (k, 3) meet ``planes`` (k, 4).

    NaN where the ray is within ``min_angle_deg`` of lying in its plane, or meets it
    behind the origin.
    """
    rays = np.asarray(rays, dtype=np.float64)
    planes = np.asarray(planes, dtype=np.float64)
    # column by column: (k, 3) row-wise norms and dot products cost several times more
    r = [rays[:, i] for i in range(3)]
    n = [planes[:, i] for i in range(3)]
    n_norm2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
    r_norm2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    denom = n[0] * r[0] + n[1] * r[1] + n[2] * r[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        sin_angle = np.abs(denom) / np.sqrt(n_norm2 * r_norm2)
        t = -planes[:, 3] / denom
    ok = (sin_angle > math.sin(math.radians(min_angle_deg))) & (t > 0) & np.isfinite(t)
    t = np.where(ok, t, np.nan)
    return np.stack([r[0] * t, r[1] * t, r[2] * t], axis=1)


def triangulate(
    samples: StripeSamples,
    camera: PinholeModel,
    planes: LightPlanes,
    *,
    min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG,
) -> np.ndarray:
    """3D points of stripe samples: the camera ray through each sample meets its light plane.

    Parameters
    ----------
    samples : StripeSamples, k samples at camera pixels ``samples.pixels()`` (distorted,
        as seen): ``(x, row)``, or ``(x, y)`` for samples found along camera columns
    camera : the camera's lens; rays go through the undistorted pixel
    planes : the projector's light planes (e.g. :class:`RigPlanes`)
    min_angle_deg : float, degrees
        Rays closer than this to lying in their plane give NaN.

    Returns
    -------
    points : (k, 3) float64, mm, rig frame (camera frame); NaN where the ray is (nearly)
        parallel to its plane or meets it behind the camera.
    """
    k = len(samples)
    if k == 0:
        return np.zeros((0, 3))
    pixels = samples.pixels()  # (x, row), or (column, sub-pixel y) along columns
    rays = camera.rays_local(pixels)
    pl = np.asarray(
        planes.planes(np.asarray(samples.projector_column, np.float64)), dtype=np.float64
    )
    if pl.shape != (k, 4):
        raise SlscanError(
            f"light planes: expected ({k}, 4) planes for {k} samples, got shape {pl.shape}"
        )
    points = intersect_rays_planes(rays, pl, min_angle_deg=min_angle_deg)
    bad = int(np.isnan(points[:, 0]).sum())
    if bad:
        log.debug("triangulate: %d of %d samples have no intersection (grazing or behind)", bad, k)
    return points
