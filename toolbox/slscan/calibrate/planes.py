"""The projector as a set of light planes measured on a flat panel, refined by a global fit.

The paper's calibration (Rocchini et al. 2001, §3.3): a flat panel is placed in two or
more unknown poses; in each, its plane is known from the calibrated camera (here: from
the printed board's corners). Every measured projector feature (a hybrid green line, or a
Gray-code stripe edge between two projector columns) is seen on the panel as a curve of
camera pixels; their camera rays meet the panel's plane in 3D points that all lie on the
feature's light plane. Pooling the points of every pose, one plane is fitted per feature.
Per-pixel codes (phase shifting: a continuous projector column at every decoded pixel)
are first resampled where each camera row crosses whole projector columns
(:func:`column_crossings`), one feature per projector column.

Those raw planes are then refined by the **global fit**: a pinhole projector's column
planes all contain one line (the projector's vertical axis through its centre) and are
spaced like a pinhole camera's columns, ``u = fx tan(phi) + cx`` for the plane at angle
``phi`` about that axis. This 1-D pinhole model (7 parameters: the axis line, the angle
of the optical axis about it, ``fx`` and ``cx``) is fitted by least squares to every
point of every plane at once, so that each plane borrows strength from all the others.
Plane residuals (point-to-plane RMS, mm) are reported before and after the global fit.

What column planes cannot tell: where along the vertical axis the projector's centre is,
its vertical focal length and principal point. :class:`LightPlaneModel` places the centre
at the axis point nearest the camera's centre and takes ``fy = fx`` when a full
:class:`~slscan.rig.Projector` is asked of it.

References
----------
C. Rocchini, P. Cignoni, C. Montani, P. Pingi, R. Scopigno. "A low cost 3D scanner based
on structured light". Computer Graphics Forum 20(3) (Eurographics 2001), 299-308.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from slscan.calibrate.target import Board
from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector, _as_pose

log = logging.getLogger(__name__)

MIN_POINTS_PER_PLANE = 20
MIN_SPREAD_RATIO = 0.02
"""A light plane is measured only if its points spread across the plane: the second
singular value of its centred points must be at least this share of the first (two lines
that nearly coincide do not fix a plane). When the median plane falls below, the panel's
poses are degenerate."""

OUTLIER_SIGMAS = 4.0
"""Points farther than this many robust standard deviations from their plane are dropped."""


# --- the global model -----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LightPlaneModel:
    """The light planes of a pinhole projector's columns: a 1-D pinhole model.

    width : projector width, px
    fx : horizontal focal length, px
    cx : principal point column, px (OpenCV pixel centres)
    rig_from_projector : (4, 4) mm; its y axis is the line every plane contains, its
        origin the projector centre (placed at the point of that line nearest the camera)

    The plane of continuous column ``u`` has, in the projector frame, normal
    ``(1, 0, -(u - cx) / fx)`` (normalised) and contains the origin: exactly
    :meth:`slscan.rig.Projector.column_planes` of an undistorted projector.
    """

    width: int
    fx: float
    cx: float
    rig_from_projector: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(
            self, "rig_from_projector", _as_pose(self.rig_from_projector, "light-plane model pose")
        )
        if not self.fx > 0 or self.width <= 0:
            raise SlscanError(
                f"light-plane model: fx and width must be positive, got {self.fx}, {self.width}"
            )

    @property
    def center(self) -> np.ndarray:
        """A point (3,) of the common axis: the projector centre, mm, rig frame."""
        return self.rig_from_projector[:3, 3].copy()

    @property
    def axis(self) -> np.ndarray:
        """Direction (3,) of the line every plane contains (the projector's y axis)."""
        return self.rig_from_projector[:3, 1].copy()

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), of columns (n,) px."""
        return _model_planes(
            self.rig_from_projector[:3, :3],
            self.center,
            self.fx,
            self.cx,
            np.asarray(projector_columns, float).reshape(-1),
        )

    def projector(self, height: int, *, cy: float | None = None) -> Projector:
        """A full projector with these column planes: ``fy = fx``, ``cy`` default the centre row."""
        cy = (height - 1) / 2.0 if cy is None else float(cy)
        lens = PinholeModel(self.width, int(height), self.fx, self.fx, self.cx, cy)
        return Projector(lens, self.rig_from_projector)

    def to_dict(self) -> dict:
        return {
            "width": self.width,
            "fx": self.fx,
            "cx": self.cx,
            "rig_from_projector": self.rig_from_projector.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict, what: str = "light-plane model") -> LightPlaneModel:
        try:
            return cls(
                int(d["width"]),
                float(d["fx"]),
                float(d["cx"]),
                np.asarray(d["rig_from_projector"], float),
            )
        except KeyError as exc:
            raise SlscanError(f"{what}: missing field {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise SlscanError(f"{what}: {exc}") from None


def _model_planes(
    rot: np.ndarray, center: np.ndarray, fx: float, cx: float, u: np.ndarray
) -> np.ndarray:
    xn = (u - cx) / fx
    n_local = np.stack([np.ones_like(xn), np.zeros_like(xn), -xn], axis=1)
    n = n_local @ rot.T
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.concatenate([n, -(n @ center)[:, None]], axis=1)


class MeasuredPlanes:
    """Light planes from a measured calibration; implements :class:`~slscan.decode.samples.LightPlanes`.

    model : the globally fitted :class:`LightPlaneModel` (planes of any column)
    raw_columns, raw_planes : (m,), (m, 4) the per-feature planes as measured, optional
    use_raw : give the raw planes (linearly interpolated between measured columns,
        renormalised; the model outside them) instead of the model's
    """

    def __init__(
        self,
        model: LightPlaneModel,
        raw_columns: np.ndarray | None = None,
        raw_planes: np.ndarray | None = None,
        *,
        use_raw: bool = False,
    ) -> None:
        self.model = model
        self.raw_columns = (
            None if raw_columns is None else np.asarray(raw_columns, float).reshape(-1)
        )
        self.raw_planes = (
            None if raw_planes is None else np.asarray(raw_planes, float).reshape(-1, 4)
        )
        if use_raw and (self.raw_columns is None or len(self.raw_columns) < 2):
            raise SlscanError("MeasuredPlanes: use_raw needs at least two raw planes")
        if self.raw_columns is not None:
            if self.raw_planes is None or len(self.raw_planes) != len(self.raw_columns):
                raise SlscanError("MeasuredPlanes: raw_columns and raw_planes differ in length")
            order = np.argsort(self.raw_columns)
            self.raw_columns, self.raw_planes = self.raw_columns[order], self.raw_planes[order]
            # orient the raw planes like the model's
            flip = (
                np.einsum("ij,ij->i", self.raw_planes[:, :3], model.planes(self.raw_columns)[:, :3])
                < 0
            )
            self.raw_planes[flip] *= -1
        self.use_raw = use_raw

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), for columns (n,) px."""
        u = np.asarray(projector_columns, float).reshape(-1)
        out = self.model.planes(u)
        if not self.use_raw:
            return out
        cols, pl = self.raw_columns, self.raw_planes
        inside = (u >= cols[0]) & (u <= cols[-1])
        j = np.clip(np.searchsorted(cols, u[inside], side="right") - 1, 0, len(cols) - 2)
        t = (u[inside] - cols[j]) / (cols[j + 1] - cols[j])
        p = pl[j] * (1 - t)[:, None] + pl[j + 1] * t[:, None]
        p /= np.linalg.norm(p[:, :3], axis=1, keepdims=True)
        out[inside] = p
        return out

    def __repr__(self) -> str:
        n = 0 if self.raw_columns is None else len(self.raw_columns)
        return f"MeasuredPlanes(fx={self.model.fx:.1f}, {n} raw planes, use_raw={self.use_raw})"


# --- per-pixel codes to features ------------------------------------------------------------

MAX_CROSSING_SLOPE = 3.0
"""Projector px per camera px: two neighbouring pixels whose columns differ by more are on
either side of a jump (a silhouette, a wrong fringe order), and no column is crossed between."""


def per_pixel(samples: StripeSamples) -> bool:
    """Whether ``samples`` are per-pixel codes (phase shifting: every decoded pixel with its
    own continuous projector column) rather than features many samples share (a hybrid
    green line, a Gray-code edge): more than half the samples have a column of their own."""
    n = len(samples)
    return n > 0 and len(np.unique(np.asarray(samples.projector_column))) > n // 2


def column_crossings(
    samples: StripeSamples, *, step: float = 1.0, max_slope: float = MAX_CROSSING_SLOPE
) -> StripeSamples:
    """Per-pixel codes resampled as features: where each camera row crosses whole projector
    columns.

    A light plane is fitted to the points of one projector column; per-pixel codes (phase
    shifting) give every pixel a column of its own, so no two share one. Along each camera
    row, between two neighbouring decoded pixels whose columns ``a`` and ``b`` straddle a
    multiple ``k step`` of ``step``, the column is ``k step`` at ``x + (k step - a) / (b -
    a)`` (linear interpolation of the decoded column, which is smooth on the flat panel):
    a sample of that column's light plane at a sub-pixel camera position, as a Gray-code
    edge is of ``c + 0.5``.

    Parameters
    ----------
    samples : per-pixel samples of one view (``x`` whole camera columns, ``row`` rows)
    step : projector px between the columns sampled
    max_slope : see :data:`MAX_CROSSING_SLOPE`

    Returns
    -------
    StripeSamples
        ``projector_column`` ``k step``, ``stripe`` ``k``, ``x`` sub-pixel on camera row
        ``row``; ``contrast`` interpolated, ``saturated`` where either pixel is.
    """
    if not step > 0:
        raise SlscanError(f"column step must be positive, got {step}")
    if len(samples) == 0:
        return samples
    rows = np.asarray(samples.row, np.int64)
    xs = np.rint(np.asarray(samples.x, np.float64)).astype(np.int64)
    x_min, row_min = int(xs.min()), int(rows.min())
    shape = (int(rows.max()) - row_min + 1, int(xs.max()) - x_min + 2)
    cols = np.full(shape, np.nan)
    contrast = np.zeros(shape, np.float32)
    saturated = np.zeros(shape, bool)
    at = (rows - row_min, xs - x_min)
    cols[at] = np.asarray(samples.projector_column, np.float64) / step
    contrast[at] = samples.contrast
    saturated[at] = samples.saturated
    a, b = cols[:, :-1], cols[:, 1:]
    with np.errstate(invalid="ignore"):
        near = np.abs(b - a) <= max_slope / step
    first, last = np.floor(np.fmin(a, b)), np.floor(np.fmax(a, b))
    count = np.where(near, last - first, 0).astype(np.int64)  # multiples of step in (min, max]
    r, c = np.nonzero(count)
    n = count[r, c]
    r, c = np.repeat(r, n), np.repeat(c, n)
    within = np.arange(len(r)) - np.repeat(np.cumsum(n) - n, n)
    k = first[r, c] + 1 + within
    t = (k - a[r, c]) / (b[r, c] - a[r, c])
    return StripeSamples(
        row=(r + row_min).astype(np.int32),
        x=(c + x_min + t).astype(np.float64),
        projector_column=k * step,
        stripe=k.astype(np.int32),
        contrast=((1 - t) * contrast[r, c] + t * contrast[r, c + 1]).astype(np.float32),
        saturated=saturated[r, c] | saturated[r, c + 1],
    )


# --- panel points ---------------------------------------------------------------------------


def panel_points(
    samples: StripeSamples,
    camera: PinholeModel,
    camera_from_board: np.ndarray,
    board: Board,
    *,
    margin: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """3D points where the features of ``samples`` meet the panel.

    Parameters
    ----------
    samples : k stripe samples of one view (camera pixels ``(x, row)``, projector columns)
    camera : the calibrated camera
    camera_from_board : (4, 4) the board's pose, mm
    board : the printed target on the panel; only points on its squares area grown by
        ``margin`` mm (default half a square) are kept, the rest of the scene may not be
        flat or the panel
    Returns
    -------
    columns : (j,) float64 projector column of each kept point
    points : (j, 3) float64 mm, rig (camera) frame
    """
    if len(samples) == 0:
        return np.zeros(0), np.zeros((0, 3))
    margin = 0.5 * board.square if margin is None else float(margin)
    pixels = samples.pixels()  # sub-pixel (x, y), whichever axis the edge was found along
    rays = camera.rays_local(pixels)
    r, t = camera_from_board[:3, :3], camera_from_board[:3, 3]
    normal = r[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (normal @ t) / (rays @ normal)
    points = rays * s[:, None]
    local = (points - t) @ r  # board frame
    w, h = board.size
    keep = (
        np.isfinite(s)
        & (s > 0)
        & (local[:, 0] >= -margin)
        & (local[:, 0] <= w + margin)
        & (local[:, 1] >= -margin)
        & (local[:, 1] <= h + margin)
    )
    return np.asarray(samples.projector_column, float)[keep], points[keep]


# --- per-feature planes ---------------------------------------------------------------------


@dataclass(frozen=True)
class LinePlanes:
    """One plane per measured projector feature (a hybrid line or a Gray-code edge).

    columns : (m,) float64 projector column of each feature
    planes : (m, 4) unit-normal planes, rig frame, mm
    counts : (m,) int points kept (inliers) per plane
    rms : (m,) float64 mm, point-to-plane RMS of the inliers
    spread : (m,) float64, second over first singular value of the centred points
    point_line : (k,) int index into ``columns`` of each point; -1 for outliers and for
        points of features left out
    """

    columns: np.ndarray
    planes: np.ndarray
    counts: np.ndarray
    rms: np.ndarray
    spread: np.ndarray
    point_line: np.ndarray

    def __len__(self) -> int:
        return len(self.columns)


def _fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane (4,) of ``points`` (n, 3) and the singular values (3,)."""
    c = points.mean(axis=0)
    _, s, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    return np.concatenate([n, [-n @ c]]), s


def fit_line_planes(
    columns: np.ndarray,
    points: np.ndarray,
    views: np.ndarray,
    *,
    min_points: int = MIN_POINTS_PER_PLANE,
    min_views: int = 2,
    outlier_sigmas: float = OUTLIER_SIGMAS,
) -> LinePlanes:
    """Fit one plane per projector feature to its points pooled over the panel's poses.

    Parameters
    ----------
    columns : (k,) projector column of each point (points of one feature share it exactly)
    points : (k, 3) mm
    views : (k,) int, the panel pose each point was seen in
    min_points, min_views : a feature needs this many points, from this many poses
    outlier_sigmas : points beyond this many robust sigmas (1.4826 MAD) are dropped and the
        plane refitted once

    Returns
    -------
    LinePlanes (possibly empty)
    """
    columns = np.asarray(columns, float)
    points = np.asarray(points, float)
    views = np.asarray(views, int)
    point_line = np.full(len(columns), -1, int)
    keys, inverse = np.unique(columns, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(keys) + 1))
    out_cols, out_planes, out_counts, out_rms, out_spread = [], [], [], [], []
    for k in range(len(keys)):
        idx = order[bounds[k] : bounds[k + 1]]
        if len(idx) < min_points or len(np.unique(views[idx])) < min_views:
            continue
        plane, _ = _fit_plane(points[idx])
        d = points[idx] @ plane[:3] + plane[3]
        sigma = 1.4826 * float(np.median(np.abs(d - np.median(d))))
        inl = np.abs(d) <= max(outlier_sigmas * sigma, 1e-9)
        if inl.sum() < min_points or len(np.unique(views[idx[inl]])) < min_views:
            continue
        idx = idx[inl]
        plane, s = _fit_plane(points[idx])
        d = points[idx] @ plane[:3] + plane[3]
        line = len(out_cols)
        point_line[idx] = line
        out_cols.append(keys[k])
        out_planes.append(plane)
        out_counts.append(len(idx))
        out_rms.append(float(np.sqrt(np.mean(d**2))))
        out_spread.append(float(s[1] / max(s[0], 1e-12)))
    return LinePlanes(
        columns=np.asarray(out_cols, float),
        planes=np.asarray(out_planes, float).reshape(-1, 4),
        counts=np.asarray(out_counts, int),
        rms=np.asarray(out_rms, float),
        spread=np.asarray(out_spread, float),
        point_line=point_line,
    )


# --- the global fit ---------------------------------------------------------------------


@dataclass(frozen=True)
class PlaneModelFit:
    """Result of the global fit; false-valued (with ``reason``) when it failed.

    model : the fitted model (None on failure)
    rms_before : mm, point-to-plane RMS of every inlier point about its own raw plane
    rms_after : mm, the same about the model's plane of its column
    line_rms_after : (m,) mm per feature
    """

    model: LightPlaneModel | None
    rms_before: float
    rms_after: float
    line_rms_after: np.ndarray
    reason: str = ""

    def __bool__(self) -> bool:
        return self.model is not None


def _moments(points: np.ndarray, point_line: np.ndarray, m: int, origin: np.ndarray) -> np.ndarray:
    """Per-feature (m, 4, 4) sums of ``[x; 1][x; 1]^T`` over its points, x relative to origin."""
    keep = point_line >= 0
    x = np.concatenate([points[keep] - origin, np.ones((int(keep.sum()), 1))], axis=1)
    outer = x[:, :, None] * x[:, None, :]
    moments = np.zeros((m, 4, 4))
    np.add.at(moments, point_line[keep], outer)
    return moments


def _initial_model(lines: LinePlanes, origin: np.ndarray, width: int):
    """Axis, centre, rotation, fx, cx from the raw planes (closed form)."""
    n = lines.planes[:, :3].copy()
    d = lines.planes[:, 3] + n @ origin  # planes relative to origin
    ref = n[np.argmin(np.abs(lines.columns - np.median(lines.columns)))]
    flip = n @ ref < 0
    n[flip] *= -1
    d[flip] *= -1
    axis = np.linalg.svd(n, full_matrices=False)[2][2]
    a_stack = np.concatenate([n, axis[None, :]])
    b_stack = np.concatenate([-d, [-(axis @ origin)]])
    center = np.linalg.lstsq(a_stack, b_stack, rcond=None)[0]  # relative to origin
    e1 = n.mean(axis=0) - (n.mean(axis=0) @ axis) * axis
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    phi = np.arctan2(n @ e2, n @ e1)
    slope, intercept = np.polyfit(lines.columns, phi, 1)
    if slope < 0:  # the projector's y axis points the other way
        axis, e2, phi, slope, intercept = -axis, -e2, -phi, -slope, -intercept
    fx = 1.0 / slope
    cx = (width - 1) / 2.0
    phi0 = intercept + slope * cx
    x_p = math.cos(phi0) * e1 + math.sin(phi0) * e2
    rot = np.stack([x_p, axis, np.cross(x_p, axis)], axis=1)
    return rot, center, fx, cx


def fit_plane_model(
    lines: LinePlanes,
    points: np.ndarray,
    width: int,
) -> PlaneModelFit:
    """The global fit: one 1-D pinhole projector for every measured plane (least squares).

    Parameters
    ----------
    lines : the raw planes and which points belong to each (:func:`fit_line_planes`)
    points : (k, 3) mm, the points ``lines.point_line`` indexes
    width : projector width, px

    Returns
    -------
    PlaneModelFit
        Minimises the sum of squared point-to-plane distances of every inlier point to
        the model's plane of its column, over the model's 7 degrees of freedom (plus the
        free position of the centre along the axis, pinned at the point nearest the
        camera). False-valued, with the reason, for fewer than 3 planes or a failed fit.

    References
    ----------
    C. Rocchini et al., "A low cost 3D scanner based on structured light", Eurographics
    2001, §3.3 (the global fit of the light planes).
    """
    m = len(lines)
    if m < 3:
        return PlaneModelFit(
            None,
            math.nan,
            math.nan,
            np.zeros(0),
            f"only {m} light planes measured; the global fit needs 3",
        )
    points = np.asarray(points, float)
    keep = lines.point_line >= 0
    origin = points[keep].mean(axis=0)
    moments = _moments(points, lines.point_line, m, origin)
    # factor each moment matrix so that sum_i (p . x_i)^2 = |L^T p|^2
    eye = np.eye(4) * 1e-12 * np.trace(moments, axis1=1, axis2=2)[:, None, None]
    chol = np.linalg.cholesky(moments + eye)
    lt = np.transpose(chol, (0, 2, 1))
    rot0, center0, fx0, cx0 = _initial_model(lines, origin, width)
    cols = lines.columns
    n_points = int(keep.sum())

    def unpack(theta):
        rot = rot0 @ Rotation.from_rotvec(theta[:3]).as_matrix()
        return rot, theta[3:6], theta[6] * fx0, theta[7] + cx0

    def residuals(theta):
        rot, center, fx, cx = unpack(theta)
        planes = _model_planes(rot, center, fx, cx, cols)  # relative to origin
        r = np.einsum("mij,mj->mi", lt, planes).ravel()
        gauge = (center + origin) @ rot[:, 1] * 1e-3 * math.sqrt(n_points)
        return np.concatenate([r, [gauge]])

    theta0 = np.concatenate([np.zeros(3), center0, [1.0, 0.0]])
    try:
        sol = least_squares(residuals, theta0, method="lm", x_scale="jac", max_nfev=2000)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return PlaneModelFit(None, math.nan, math.nan, np.zeros(0), f"the global fit failed: {exc}")
    rot, center, fx, cx = unpack(sol.x)
    if not (np.isfinite(sol.x).all() and fx > 0):
        return PlaneModelFit(None, math.nan, math.nan, np.zeros(0), "the global fit diverged")
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = center + origin
    model = LightPlaneModel(int(width), float(fx), float(cx), pose)

    idx = np.flatnonzero(keep)
    line = lines.point_line[idx]
    raw = lines.planes[line]
    d_before = np.einsum("ij,ij->i", points[idx], raw[:, :3]) + raw[:, 3]
    model_planes = model.planes(cols)[line]
    d_after = np.einsum("ij,ij->i", points[idx], model_planes[:, :3]) + model_planes[:, 3]
    per_line = np.sqrt(np.bincount(line, d_after**2, minlength=m) / np.maximum(lines.counts, 1))
    return PlaneModelFit(
        model,
        float(np.sqrt(np.mean(d_before**2))),
        float(np.sqrt(np.mean(d_after**2))),
        per_line,
    )


# --- the whole method -------------------------------------------------------------------


@dataclass(frozen=True)
class PanelView:
    """One pose of the panel: what was decoded on it and where it was.

    name : the view (for messages)
    samples : the decoded features (hybrid green lines or Gray-code edges), or per-pixel
        codes (phase shifting), which are measured where they cross whole projector
        columns (:func:`column_crossings`)
    camera_from_board : (4, 4) mm, the board's pose from its corners
    """

    name: str
    samples: StripeSamples
    camera_from_board: np.ndarray


@dataclass(frozen=True)
class LightPlaneCalibration:
    """Light planes measured on a panel and their global model.

    model : the fitted :class:`LightPlaneModel`
    lines : the raw per-feature planes
    rms_before, rms_after : mm, point-to-plane RMS about the raw planes and about the model
    line_rms_after : (m,) mm
    views : names of the panel poses used
    points_per_view : (n,) points kept on the panel in each pose
    pattern : {"hybrid", "gray", "phase"}, what the features were
    """

    model: LightPlaneModel
    lines: LinePlanes
    rms_before: float
    rms_after: float
    line_rms_after: np.ndarray
    views: tuple[str, ...]
    points_per_view: np.ndarray
    pattern: str

    def measured_planes(self, *, use_raw: bool = False) -> MeasuredPlanes:
        return MeasuredPlanes(self.model, self.lines.columns, self.lines.planes, use_raw=use_raw)

    def residuals(self) -> dict:
        return {
            "pattern": self.pattern,
            "planes": len(self.lines),
            "points": int(self.lines.counts.sum()),
            "rms_before_global_fit_mm": self.rms_before,
            "rms_after_global_fit_mm": self.rms_after,
            "views": [
                {"name": name, "points": int(n)}
                for name, n in zip(self.views, self.points_per_view)
            ],
        }


def calibrate_light_planes(
    panels: Sequence[PanelView],
    camera: PinholeModel,
    board: Board,
    projector_width: int,
    *,
    pattern: str = "gray",
    margin: float | None = None,
    min_points: int = MIN_POINTS_PER_PLANE,
    min_spread: float = MIN_SPREAD_RATIO,
) -> LightPlaneCalibration:
    """Measure the projector's light planes on a flat panel in ≥ 2 poses and fit the global model.

    Parameters
    ----------
    panels : the panel's poses, each with its decoded features and board pose
    camera : the calibrated camera (rays through the distorted sample pixels)
    board : the printed target on the panel (the area trusted to be flat, see
        :func:`panel_points`)
    projector_width : px
    pattern : {"hybrid", "gray", "phase"}, recorded with the result
    margin : mm around the board's squares also trusted to be panel (default half a square)
    min_points : points a feature needs to get a plane
    min_spread : see :data:`MIN_SPREAD_RATIO`

    Returns
    -------
    LightPlaneCalibration

    Raises
    ------
    SlscanError
        Fewer than 2 poses; "poses are degenerate" when the panel's poses are too similar
        for the planes to be measured; no plane measured; a failed global fit.

    References
    ----------
    C. Rocchini et al., "A low cost 3D scanner based on structured light", Eurographics
    2001, §3.3.
    """
    if len(panels) < 2:
        raise SlscanError(
            f"light-plane calibration needs the panel in at least 2 poses, got {len(panels)}"
        )
    cols, pts, views, counts = [], [], [], []
    for v, panel in enumerate(panels):
        samples = column_crossings(panel.samples) if per_pixel(panel.samples) else panel.samples
        c, p = panel_points(samples, camera, panel.camera_from_board, board, margin=margin)
        cols.append(c)
        pts.append(p)
        views.append(np.full(len(c), v))
        counts.append(len(c))
        log.info("%s: %d feature points on the panel", panel.name, len(c))
    columns, points, view_ids = np.concatenate(cols), np.concatenate(pts), np.concatenate(views)
    lines = fit_line_planes(columns, points, view_ids, min_points=min_points)
    if len(lines) == 0:
        raise SlscanError(
            "no light plane could be measured: no projector feature was seen on the panel in "
            f"two poses with {min_points} points (is the board lit by the projector?)"
        )
    median_spread = float(np.median(lines.spread))
    if median_spread < min_spread:
        raise SlscanError(
            f"poses are degenerate: the panel's poses are too similar to measure the light planes "
            f"(their lines on each plane nearly coincide: spread {median_spread:.4f} < {min_spread}); "
            "move the panel nearer or farther, or tilt it, between poses"
        )
    good = lines.spread >= min_spread
    if not good.all():
        lines = _subset(lines, good)
    fit = fit_plane_model(lines, points, projector_width)
    if not fit:
        raise SlscanError(f"light-plane calibration: {fit.reason}")
    log.info(
        "light planes: %d planes, point-to-plane RMS %.4f mm before, %.4f mm after the global fit; "
        "fx %.2f px, cx %.2f px",
        len(lines),
        fit.rms_before,
        fit.rms_after,
        fit.model.fx,
        fit.model.cx,
    )
    return LightPlaneCalibration(
        model=fit.model,
        lines=lines,
        rms_before=fit.rms_before,
        rms_after=fit.rms_after,
        line_rms_after=fit.line_rms_after,
        views=tuple(p.name for p in panels),
        points_per_view=np.asarray(counts, int),
        pattern=pattern,
    )


def _subset(lines: LinePlanes, keep: np.ndarray) -> LinePlanes:
    new_index = np.full(len(lines), -1, int)
    new_index[keep] = np.arange(np.count_nonzero(keep))
    point_line = np.where(lines.point_line >= 0, new_index[np.maximum(lines.point_line, 0)], -1)
    return LinePlanes(
        lines.columns[keep],
        lines.planes[keep],
        lines.counts[keep],
        lines.rms[keep],
        lines.spread[keep],
        point_line,
    )
