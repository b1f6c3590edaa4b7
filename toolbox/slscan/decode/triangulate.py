"""Triangulation: camera rays through samples meet the projector's light planes, or its rays.

With the projector as a calibrated inverse camera (:class:`RigPlanes`), the whole
calibration is used, lens distortion included: a sample with only its projector column
lies where its camera ray meets the (curved, with distortion) surface of every point the
projector sends to that column; a sample with its column and row (phase shifting with
row fringes; Gray-code edges given the row interpolated from the row edges) at the depth
along its camera ray that best reprojects to both in the projector: least squares, each
axis weighted by its sensitivity (how fast its coordinate changes with depth) and its
measurement noise, so the better-conditioned axis of the rig's geometry counts most. A
light-plane model (the paper's planes, measured) intersects each ray with its column's
plane: it has no rows.

Which axes a view should use follows from the geometry (:func:`axis_conditioning`,
:func:`choose_axes`): a column plane that nearly contains the camera centre (a projector
mostly above or below the camera) is a short effective baseline, and its depth changes
by many mm per projector pixel; the rows then carry the depth.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from slscan.decode.samples import LightPlanes, StripeSamples
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector, distort

log = logging.getLogger(__name__)

MIN_RAY_PLANE_ANGLE_DEG = 0.5
"""Rays closer than this to lying in their light plane give no point (NaN)."""


class RigPlanes:
    """The projector as a calibrated inverse camera (the rig's, or a measured calibration's).

    :func:`triangulate` uses its whole model (:meth:`triangulate`: lens distortion, and the
    projector rows where the samples have them). As :class:`slscan.decode.samples.LightPlanes`
    its :meth:`planes` are :meth:`slscan.rig.Projector.column_planes`, exact when the lens
    has no distortion (with distortion, the planes of its undistorted model: the starting
    point of the solution, never the answer).
    """

    def __init__(self, projector: Projector) -> None:
        if not isinstance(projector, Projector):
            raise SlscanError(
                f"RigPlanes needs a slscan.rig.Projector, got {type(projector).__name__}"
            )
        self.projector = projector
        self.distorted = bool(any(projector.lens.dist))

    def triangulate(self, rays: np.ndarray, samples: StripeSamples, *,
                    min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG,
                    sigma: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
        """Points (k, 3) of ``samples`` along camera ``rays`` (k, 3; z = 1) through the whole
        projector model (:func:`depth_along_rays`): their column, and their row where known
        (``samples.projector_row``, NaN where not), weighted by ``sigma`` = (column, row)
        coordinate noise in projector px. A ray within ``min_angle_deg`` of every
        (undistorted) plane it uses gives NaN, as for planes."""
        return self.triangulate_depth(rays, samples, min_angle_deg=min_angle_deg, sigma=sigma)[0]

    def triangulate_depth(self, rays: np.ndarray, samples: StripeSamples, *,
                          min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG,
                          sigma: tuple[float, float] = (1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`triangulate`, and each point's expected depth standard deviation (k,) mm for
        the coordinate noise ``sigma`` (``depth_along_rays``'s second output)."""
        columns = np.asarray(samples.projector_column, np.float64)
        rows = None if samples.projector_row is None else np.asarray(samples.projector_row, np.float64)
        z, sd = depth_along_rays(rays, self.projector, columns, rows, sigma_u=sigma[0], sigma_v=sigma[1],
                                 start=plane_start(rays, self.projector, columns, rows))
        z[grazing(rays, self.projector, columns, rows, min_angle_deg)] = np.nan
        sd[~np.isfinite(z)] = np.nan
        return rays * z[:, None], sd

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
    # column by column: (k, 3) products cost several times more
    rot, c, lens = projector.rig_from_projector[:3, :3], projector.center, projector.lens
    d = [rays[:, 0] * depth - c[0], rays[:, 1] * depth - c[1], depth - c[2]]
    lx, ly, lz = (rot[0, i] * d[0] + rot[1, i] * d[1] + rot[2, i] * d[2] for i in range(3))
    with np.errstate(divide="ignore", invalid="ignore"):
        xd, yd = distort(lx / lz, ly / lz, lens.dist_array)
    uv = np.stack([lens.fx * xd + lens.cx, lens.fy * yd + lens.cy], axis=1)
    uv[lz <= 0] = np.nan
    return uv


def row_planes(projector: Projector, rows: np.ndarray) -> np.ndarray:
    """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), of continuous projector
    rows (n,) px: the plane through the centre and every ray of row ``v`` (exact without
    distortion), as :meth:`slscan.rig.Projector.column_planes` for columns."""
    v = np.asarray(rows, float).reshape(-1)
    yn = (v - projector.lens.cy) / projector.lens.fy
    rot = projector.rig_from_projector[:3, :3]
    n = [rot[i, 1] - yn * rot[i, 2] for i in range(3)]  # (0, 1, -yn) in the projector frame
    scale = 1.0 / np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    n = [c * scale for c in n]
    c = projector.center
    return np.stack([*n, -(n[0] * c[0] + n[1] * c[1] + n[2] * c[2])], axis=1)


def _ray_plane_sin(rays: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(k,) sine of the angle between each ray and its plane."""
    r_norm = np.linalg.norm(rays, axis=1)
    return np.abs(np.einsum("ij,ij->i", rays, planes[:, :3])) / np.maximum(r_norm, 1e-300)


def plane_start(rays: np.ndarray, projector: Projector, u: np.ndarray | None,
                v: np.ndarray | None = None) -> np.ndarray:
    """(k,) first depths for :func:`depth_along_rays`: where each ray meets the undistorted
    plane of its column or of its row, whichever it crosses more steeply (NaN: neither)."""
    k = len(rays)
    best, best_sin = np.full(k, np.nan), np.zeros(k)
    for values, planes_of in ((u, projector.column_planes), (v, lambda vv: row_planes(projector, vv))):
        if values is None:
            continue
        values = np.asarray(values, np.float64)
        known = np.isfinite(values)
        pl = np.full((k, 4), np.nan)
        pl[known] = planes_of(values[known])
        z = intersect_rays_planes(rays, pl, min_angle_deg=0.0)[:, 2]
        sin = np.where(np.isfinite(z), _ray_plane_sin(rays, pl), 0.0)
        better = sin > best_sin
        best, best_sin = np.where(better, z, best), np.where(better, sin, best_sin)
    return best


def grazing(rays: np.ndarray, projector: Projector, u: np.ndarray | None, v: np.ndarray | None,
            min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG) -> np.ndarray:
    """(k,) bool: the ray lies within ``min_angle_deg`` of the undistorted plane of every
    projector coordinate it has (its column, its row where known): no depth."""
    k = len(rays)
    limit = math.sin(math.radians(min_angle_deg))
    steep = np.zeros(k, bool)
    for values, planes_of in ((u, projector.column_planes), (v, lambda vv: row_planes(projector, vv))):
        if values is None:
            continue
        values = np.asarray(values, np.float64)
        known = np.isfinite(values)
        sin = np.zeros(k)
        sin[known] = _ray_plane_sin(rays[known], planes_of(values[known]))
        steep |= sin > limit
    return ~steep


def depth_gains(rays: np.ndarray, projector: Projector, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How fast the projector coordinates of the points ``depth * rays`` change with depth:
    ``(|du/dz|, |dv/dz|)``, each (k,) projector px per mm (lens distortion included).
    ``1 / gain`` is the depth change one projector pixel of that coordinate makes (mm/px)."""
    z = np.asarray(depth, np.float64)
    h = np.maximum(1e-4 * np.abs(z), 1e-3)
    p0 = _project_depth(projector, rays, z)
    p1 = _project_depth(projector, rays, z + h)
    d = (p1 - p0) / h[:, None]
    return np.abs(d[:, 0]), np.abs(d[:, 1])


def depth_along_rays(
    rays: np.ndarray,
    projector: Projector,
    u: np.ndarray | None,
    v: np.ndarray | None = None,
    *,
    sigma_u: float | np.ndarray = 1.0,
    sigma_v: float | np.ndarray = 1.0,
    start: np.ndarray | None = None,
    iterations: int = 8,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (z, mm) along camera ``rays`` (k, 3; z = 1) of the points the projector sends
    to column ``u`` and/or row ``v`` (each (k,) px, NaN where a sample lacks it, or None),
    its lens distortion included.

    One coordinate: Newton's method on ``u(z) = u`` (the exact curved column surface), or
    on ``v(z) = v``. Both: Gauss-Newton on ``((u(z) - u) / sigma_u)**2 + ((v(z) - v) /
    sigma_v)**2``, so each axis counts by how fast its coordinate changes with depth
    (the rig's geometry) and by how well it was measured (``sigma_u``, ``sigma_v``:
    coordinate noise, projector px, scalars or (k,)). ``start`` (k,) is a first depth
    (e.g. :func:`plane_start`, the undistorted planes' intersection).

    Returns the depth (k,) (NaN where it does not converge or lies behind a device) and its
    expected standard deviation (k,) mm at the solution, ``1 / sqrt((du/dz / sigma_u)**2 +
    (dv/dz / sigma_v)**2)`` over the coordinates each sample has: with the default unit
    sigmas, the depth change per projector pixel (mm/px; columns only ``1 / |du/dz|``).
    """
    k = len(rays)
    z = np.full(k, 1000.0) if start is None else np.where(np.isfinite(start) & (start > 0), start, 1000.0)
    nan = np.full(k, np.nan)
    tu = nan if u is None else np.asarray(u, np.float64)
    tv = nan if v is None else np.asarray(v, np.float64)
    has_u, has_v = np.isfinite(tu), np.isfinite(tv)
    wu = np.where(has_u, 1.0 / np.square(sigma_u), 0.0)
    wv = np.where(has_v, 1.0 / np.square(sigma_v), 0.0)
    for _ in range(iterations):
        h = np.maximum(1e-4 * z, 1e-3)
        p0 = _project_depth(projector, rays, z)
        p1 = _project_depth(projector, rays, z + h)
        du, dv = (p1[:, 0] - p0[:, 0]) / h, (p1[:, 1] - p0[:, 1]) / h
        ru = np.where(has_u, p0[:, 0] - tu, 0.0)
        rv = np.where(has_v, p0[:, 1] - tv, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.clip((wu * du * ru + wv * dv * rv) / (wu * du * du + wv * dv * dv), -0.5 * z, 0.5 * z)
        z = z - step
        moving = np.isfinite(step) & (np.abs(step) > 1e-8 * np.abs(z))
        if not moving.any():  # converged (from the planes' start, in two or three steps)
            break
    p0 = _project_depth(projector, rays, z)
    h = np.maximum(1e-4 * z, 1e-3)
    p1 = _project_depth(projector, rays, z + h)
    du, dv = (p1[:, 0] - p0[:, 0]) / h, (p1[:, 1] - p0[:, 1]) / h
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma = 1.0 / np.sqrt(wu * du * du + wv * dv * dv)
        miss_u = np.where(has_u, np.abs(p0[:, 0] - tu), 0.0)
        miss_v = np.where(has_v, np.abs(p0[:, 1] - tv), 0.0)
    both = has_u & has_v
    # one coordinate: the ray must meet its surface exactly; two: they must agree within 1 px
    miss = np.where(both, np.hypot(miss_u, miss_v) / np.sqrt(2.0), miss_u + miss_v)
    bad = ~np.isfinite(z) | (z <= 0) | ~np.isfinite(miss) | ~(has_u | has_v)
    bad |= np.where(both, miss > 1.0, miss > 1e-3)
    z = np.where(bad, np.nan, z)
    return z, np.where(bad, np.nan, sigma)


AXES = ("auto", "columns", "both")
"""Which projector coordinates triangulate a view (``DecodeConfig.projector_axes``)."""

ROWS_WORTH = 1.25
"""``choose_axes``: rows are used when the median depth noise per projector pixel with
columns alone is at least this many times that with both axes (the rows' decode costs a
second pass over the captures). The paper's rig (projector beside the camera): 1.00;
kamino410's boards (projector 624 mm below the camera, 90 mm aside): about 7."""


@dataclass(frozen=True)
class AxisConditioning:
    """How well each projector axis pins depth in one view: median over its samples of the
    depth change per projector pixel (mm/px) with the columns alone, the rows alone and
    both (least squares, equal noise per projector px). NaN where not known."""

    columns: float
    rows: float
    both: float

    @property
    def rows_gain(self) -> float:
        """How many times less depth noise both axes give than the columns alone."""
        return self.columns / self.both if self.both > 0 else float("nan")

    def to_dict(self) -> dict[str, float]:
        return {"columns": self.columns, "rows": self.rows, "both": self.both}


def axis_conditioning(rays: np.ndarray, projector: Projector, depth: np.ndarray) -> AxisConditioning:
    """The depth change per projector pixel (mm/px) of the points ``depth * rays`` (rays (k, 3)
    with z = 1, depth (k,) mm; NaN ignored) by axis: medians of ``1 / |du/dz|``,
    ``1 / |dv/dz|`` and ``1 / |d(u, v)/dz|`` (:func:`depth_gains`)."""
    ok = np.isfinite(depth) & (np.asarray(depth) > 0)
    if not ok.any():
        return AxisConditioning(float("nan"), float("nan"), float("nan"))
    gu, gv = depth_gains(rays[ok], projector, np.asarray(depth, np.float64)[ok])
    with np.errstate(divide="ignore"):
        return AxisConditioning(float(np.median(1.0 / gu)), float(np.median(1.0 / gv)),
                                float(np.median(1.0 / np.hypot(gu, gv))))


def choose_axes(conditioning: AxisConditioning, wanted: str = "auto") -> str:
    """"columns" or "both": the axes ``wanted``, or with "auto" both where the rows make the
    median depth noise at least :data:`ROWS_WORTH` times smaller than the columns alone."""
    if wanted not in AXES:
        raise SlscanError(f"unknown projector axes {wanted!r}: expected one of {', '.join(AXES)}")
    if wanted != "auto":
        return wanted
    return "both" if conditioning.rows_gain >= ROWS_WORTH else "columns"


def triangulate(
    samples: StripeSamples,
    camera: PinholeModel,
    planes: LightPlanes,
    *,
    min_angle_deg: float = MIN_RAY_PLANE_ANGLE_DEG,
    sigma: tuple[float, float] = (1.0, 1.0),
) -> np.ndarray:
    """3D points of stripe samples: the camera ray through each sample meets its light plane
    (with :class:`RigPlanes` and lens distortion or projector rows: the whole projector
    model, :meth:`RigPlanes.triangulate`).

    Parameters
    ----------
    samples : StripeSamples, k samples at camera pixels ``samples.pixels()`` (distorted,
        as seen): ``(x, row)``, or ``(x, y)`` for samples found along camera columns
    camera : the camera's lens; rays go through the undistorted pixel
    planes : the projector's light planes (e.g. :class:`RigPlanes`)
    min_angle_deg : float, degrees
        Rays closer than this to lying in their plane give NaN.
    sigma : (column, row) coordinate noise, projector px: how the two axes are weighted
        where the samples have rows and the projector is an inverse camera

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
        return planes.triangulate(rays, samples, min_angle_deg=min_angle_deg, sigma=sigma)
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


@dataclass(frozen=True)
class TriangulationReport:
    """What triangulated one view and how well its geometry pins depth.

    model : {"inverse camera", "light planes"}: the projector model used
    axes : {"columns", "both"}: the projector coordinates used ("both": least squares,
        each axis weighted by its noise)
    conditioning : depth change per projector pixel (mm/px) by axis, medians over the
        view's points (:func:`axis_conditioning`; the geometry, whatever was used)
    noise_px : (columns, rows) measured coordinate noise, projector px (NaN: not measured)
    depth_noise_mm : median expected depth standard deviation of the points as
        triangulated, mm (the axes used, each with its measured noise; NaN: unknown)
    rows_share : share of the samples that have a projector row (0 with "columns")
    rows_missing : share of the decoded samples left out for want of a row (Gray code with
        "both": a column edge alone would be triangulated by the axis turned away from)
    """

    model: str
    axes: str
    conditioning: AxisConditioning
    noise_px: tuple[float, float] = (float("nan"), float("nan"))
    depth_noise_mm: float = float("nan")
    rows_share: float = 0.0
    rows_missing: float = 0.0

    def metrics(self) -> dict[str, float]:
        """Numbers for ``range_maps.json``'s per-view metrics."""
        c = self.conditioning
        found = {
            "rows_used": float(self.axes == "both"),
            "rows_share": self.rows_share,
            "rows_missing_share": self.rows_missing,
            "depth_mm_per_px_columns": c.columns,
            "depth_mm_per_px_rows": c.rows,
            "depth_mm_per_px_both": c.both,
            "expected_depth_noise_mm": self.depth_noise_mm,
        }
        return {k: float(v) for k, v in found.items() if np.isfinite(v)}  # NaN: not known, left out

    def to_dict(self) -> dict:
        """JSON-ready (None where not known)."""
        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        return {
            "model": self.model, "axes": self.axes,
            "depth_mm_per_px": {k: num(v) for k, v in self.conditioning.to_dict().items()},
            "noise_px": {"columns": num(self.noise_px[0]), "rows": num(self.noise_px[1])},
            "expected_depth_noise_mm": num(self.depth_noise_mm), "rows_share": self.rows_share,
            "rows_missing_share": self.rows_missing,
        }

    def describe(self) -> str:
        """One line for the decode summary."""
        c = self.conditioning
        used = {"columns": "columns", "both": "rows and columns"}[self.axes]
        why = ""
        if self.model == "light planes":
            why = " (light planes have no rows)"
        elif self.axes == "both" and self.rows_missing > 0:
            why = f" ({self.rows_missing:.0%} of the column samples left out: no row)"
        elif self.axes == "both" and self.rows_share < 1:
            why = f" ({self.rows_share:.0%} of the samples with a row)"
        noise = "" if not np.isfinite(self.depth_noise_mm) else f"; expected depth noise {self.depth_noise_mm:.2f} mm"
        return (f"{used}, {self.model}{why}; mm of depth per projector px: columns {c.columns:.2f}, "
                f"rows {c.rows:.2f}, both {c.both:.2f}{noise}")


def triangulation_report(
    samples: StripeSamples,
    points: np.ndarray,
    camera: PinholeModel,
    projector: Projector | None,
    planes: LightPlanes,
    *,
    sigma: tuple[float, float] = (float("nan"), float("nan")),
    rows_missing: float = 0.0,
    max_points: int = 20000,
) -> TriangulationReport:
    """The :class:`TriangulationReport` of samples triangulated to ``points`` (k, 3) with
    ``planes``: the axes used and, at (up to ``max_points`` of) the points' depths, the
    depth change per projector pixel of each axis for ``projector`` (the rig's; None: not
    known) and the expected depth noise for the measured coordinate noise ``sigma``
    (columns, rows; projector px); ``rows_missing`` is passed on (the decoder's
    ``rows_missing_share``)."""
    model = "inverse camera" if isinstance(planes, RigPlanes) else "light planes"
    rows = None if samples.projector_row is None else np.asarray(samples.projector_row, np.float64)
    has_row = np.zeros(len(samples), bool) if rows is None or model != "inverse camera" else np.isfinite(rows)
    axes = "both" if has_row.any() else "columns"
    nan = float("nan")
    if projector is None and isinstance(planes, RigPlanes):
        projector = planes.projector
    ok = np.flatnonzero(np.isfinite(points[:, 2]))
    if projector is None or len(ok) == 0:
        return TriangulationReport(model, axes, AxisConditioning(nan, nan, nan), tuple(sigma), nan,
                                   float(has_row.mean()) if len(samples) else 0.0, rows_missing)
    take = ok[np.linspace(0, len(ok) - 1, min(len(ok), max_points)).astype(np.int64)]
    rays = camera.rays_local(samples.subset(take).pixels())
    depth = points[take, 2]
    conditioning = axis_conditioning(rays, projector, depth)
    gu, gv = depth_gains(rays, projector, depth)
    su, sv = sigma
    with np.errstate(divide="ignore", invalid="ignore"):
        wu = (gu / su) ** 2 if np.isfinite(su) else np.zeros(len(take))
        wv = np.where(has_row[take], (gv / sv) ** 2, 0.0) if np.isfinite(sv) else np.zeros(len(take))
        sd = 1.0 / np.sqrt(wu + wv)
    sd = sd[np.isfinite(sd)]
    return TriangulationReport(model, axes, conditioning, (float(su), float(sv)),
                               float(np.median(sd)) if len(sd) else nan, float(has_row.mean()), rows_missing)


def rig_conditioning(camera: PinholeModel, projector: Projector, depth: float = 1300.0,
                     grid: int = 16) -> AxisConditioning:
    """:func:`axis_conditioning` of a rig for a fronto-parallel plane ``depth`` mm from the
    camera, over a ``grid`` x ``grid`` of camera pixels spanning the central 80 % of the
    image: the axes' conditioning before anything is decoded. Its ratios hardly depend on
    ``depth`` (each axis's depth per pixel grows as depth squared over its effective baseline)."""
    gx, gy = np.meshgrid(np.linspace(0.1, 0.9, grid) * (camera.width - 1),
                         np.linspace(0.1, 0.9, grid) * (camera.height - 1))
    rays = camera.rays_local(np.stack([gx.ravel(), gy.ravel()], axis=1))
    return axis_conditioning(rays, projector, np.full(len(rays), float(depth)))
