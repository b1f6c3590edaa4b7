"""Triangulation: camera rays through samples meet the projector's light planes, or its rays.

With the projector as a calibrated inverse camera (:class:`RigPlanes`), the whole
calibration is used, lens distortion included: a sample with only its projector column
lies where its camera ray meets the (curved, with distortion) surface of every point the
projector sends to that column; a sample with its column and row (phase shifting with
row fringes) at the depth along its camera ray that best reprojects to both in the
projector (least squares, which weights each axis by how sharply it pins the depth: the
better-conditioned axis of the rig's geometry counts most). A light-plane model (the
paper's planes, measured) intersects each ray with its column's plane.
"""

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
        self.distorted = bool(any(projector.lens.dist))

    def triangulate(self, rays: np.ndarray, samples: StripeSamples, *,
                    min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG) -> np.ndarray:
        """Points (k, 3) of ``samples`` along camera ``rays`` (k, 3; z = 1) through the whole
        projector model (:func:`depth_along_rays`): their column, and their row when known.
        Rays within ``min_angle_deg`` of their undistorted column plane give NaN, as for planes."""
        columns = np.asarray(samples.projector_column, np.float64)
        first = intersect_rays_planes(rays, self.planes(columns), min_angle_deg=min_angle_deg)
        rows = None if samples.projector_row is None else np.asarray(samples.projector_row, np.float64)
        if rows is None:
            grazing = ~np.isfinite(first[:, 2])
        else:  # both axes: a ray in its column plane is still pinned by the row
            grazing = np.zeros(len(rays), bool)
        z, _ = depth_along_rays(rays, self.projector, columns, rows, start=first[:, 2])
        z[grazing] = np.nan
        return rays * z[:, None]

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


def _project_depth(projector: Projector, rays: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Projector pixels (k, 2) of the points ``depth * rays`` (rays with z = 1), NaN behind it."""
    pts = rays * depth[:, None]
    local = (pts - projector.center) @ projector.rig_from_projector[:3, :3]
    uv = projector.lens.project_local(local)
    uv[local[:, 2] <= 0] = np.nan
    return uv


def depth_along_rays(
    rays: np.ndarray,
    projector: Projector,
    u: np.ndarray,
    v: np.ndarray | None = None,
    *,
    start: np.ndarray | None = None,
    iterations: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (z, mm) along camera ``rays`` (k, 3; z = 1) of the points the projector sends
    to column ``u`` (and row ``v``), its lens distortion included.

    Columns only: Newton's method on ``u(z) = u`` (the exact curved column surface).
    Column and row: Gauss-Newton on ``|(u(z), v(z)) - (u, v)|**2``, so each axis counts by
    how fast its coordinate changes with depth. ``start`` (k,) is a first depth (e.g. the
    undistorted plane's intersection).

    Returns the depth (k,) (NaN where it does not converge or lies behind a device) and the
    depth change per projector pixel (k,) mm/px at the solution: the depth noise one
    projector pixel of coordinate noise gives (columns only: ``1 / |du/dz|``; both:
    ``1 / |d(u, v)/dz|``).
    """
    k = len(rays)
    z = np.full(k, 1000.0) if start is None else np.where(np.isfinite(start) & (start > 0), start, 1000.0)
    target = np.asarray(u, np.float64)
    both = v is not None
    for _ in range(iterations):
        h = np.maximum(1e-4 * z, 1e-3)
        p0 = _project_depth(projector, rays, z)
        p1 = _project_depth(projector, rays, z + h)
        du = (p1[:, 0] - p0[:, 0]) / h
        ru = p0[:, 0] - target
        if both:
            dv = (p1[:, 1] - p0[:, 1]) / h
            rv = p0[:, 1] - v
            with np.errstate(divide="ignore", invalid="ignore"):
                step = (du * ru + dv * rv) / (du * du + dv * dv)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                step = ru / du
        z = z - np.clip(step, -0.5 * z, 0.5 * z)
    p0 = _project_depth(projector, rays, z)
    h = np.maximum(1e-4 * z, 1e-3)
    p1 = _project_depth(projector, rays, z + h)
    du = (p1[:, 0] - p0[:, 0]) / h
    gain = np.hypot(du, (p1[:, 1] - p0[:, 1]) / h) if both else np.abs(du)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = 1.0 / gain
    miss = np.abs(p0[:, 0] - target)
    if both:
        miss = np.hypot(miss, p0[:, 1] - v) / np.sqrt(2.0)
    bad = ~np.isfinite(z) | (z <= 0) | ~np.isfinite(miss) | (miss > np.maximum(1.0, 3 * sigma * 0))
    if not both:
        bad |= miss > 1e-3  # a column's surface the ray never meets
    z = np.where(bad, np.nan, z)
    return z, np.where(bad, np.nan, sigma)


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
    if isinstance(planes, RigPlanes) and (samples.projector_row is not None or planes.distorted):
        return planes.triangulate(rays, samples, min_angle_deg=min_angle_deg)
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
