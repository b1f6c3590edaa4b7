"""Two calibrated cameras, one uncalibrated projector: match projector codes between cameras.

The projector only labels the surface. Each camera decodes the Gray-code column and row
of every pixel (:func:`slscan.decode.graycode.decode_gray`); a projector pixel ``(column,
row)`` seen by both cameras is one surface point. For each code, the pixels carrying it in
a camera are reduced to one sub-pixel position: their centroid, after dropping pixels
more than ``outlier_px`` from the group's median (stray wrong decodes); by default each
pixel is first moved onto its code's centre by plane fits of the decoded codes around it,
over which the rounding of the integer codes averages out. The rays through
the two undistorted centroids are triangulated at their midpoint; a match is rejected
when its symmetric epipolar distance or the gap between its rays is too large, or when
it lies behind a camera. The matched points keep their projector grid ``(row, column)``,
which meshes them into a range map like the camera-projector one, written in camera 0's
frame. No projector calibration is needed.

Everything is vectorised over codes (``np.unique``, ``np.bincount``, ``np.intersect1d``).

References
----------
.. [1] Scharstein, Szeliski, "High-accuracy stereo depth maps using structured light",
   CVPR 2003 (cameras matched through the projector's codes).
.. [2] Hartley, Zisserman, "Multiple View Geometry in Computer Vision", 2nd ed., 2004:
   12.5 (midpoint triangulation), 9.6 (essential matrix, epipolar distance).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slscan import __version__
from slscan.capture.multicam import MultiCamSession, load_multicam
from slscan.capture.session import Session
from slscan.decode.graycode import decode_gray, gray_pairs
from slscan.decode.rangemap import (
    MAX_EDGE_FACTOR,
    MAX_VIEW_ANGLE_DEG,
    RangeMap,
    _filter_faces,
    _grid_lookup,
    _median_ratio,
    _vertex_normals,
    _white_rgb,
    write_ply,
)
from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, write_json
from slscan.rig import PinholeModel

log = logging.getLogger(__name__)

MAX_EPIPOLAR_PX = 1.5
"""Default: matches whose symmetric epipolar distance exceeds this (camera px) are rejected.
A centroid of one to a few pixels is off by up to half a pixel in each camera."""

MAX_RAY_GAP_MM = 2.0
"""Default: matches whose two rays pass further apart than this (mm) are rejected."""

OUTLIER_PX = 3.0
"""Default: pixels this far (camera px) from their code's median position are left out of
its centroid (a projector pixel covers one to a few camera pixels at the paper's geometry)."""

SUBPIXEL_RADIUS = 3
"""Default half-width (camera px) of the window over which :func:`subpixel_positions`
fits the decoded codes by planes."""

STEREO_FOLDER = "stereo_{a}_{b}"
"""Folder, inside the decode output, of the range maps from camera ``a`` matched with ``b``."""


@dataclass(frozen=True)
class StereoConfig:
    """How projector codes are matched between cameras and meshed."""

    max_epipolar_px: float = MAX_EPIPOLAR_PX
    """Largest symmetric epipolar distance of a match, camera px."""
    max_ray_gap_mm: float = MAX_RAY_GAP_MM
    """Largest distance between the two rays of a match, mm."""
    outlier_px: float = OUTLIER_PX
    """Pixels further than this from their code's median position do not count, camera px."""
    subpixel: bool = True
    """Refine each pixel onto its code's centre by plane fits of the decoded codes around
    it (:func:`subpixel_positions`) before averaging; False: average the pixel centres.
    On the half-size virtual rig the refinement takes the median error from 0.34 to 0.24
    mm on the figurine and from 0.34 to 0.06 mm on the flat tile, for 10-17 % fewer
    vertices (pixels at the decoded region's border cannot be refined;
    ``benchmarks/stereo.py``)."""
    code_step: int = 1
    """Match blocks of ``code_step`` x ``code_step`` projector pixels (1: every pixel). A
    camera with fewer pixels than the projector sees each block more than once."""
    max_edge_factor: float = MAX_EDGE_FACTOR
    """Mesh edges longer than this many times the expected spacing are cut."""
    max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG
    """Triangles seen from camera 0 more obliquely than this are dropped."""
    gray_threshold: str = "adaptive"
    """Each camera's Gray-code bit thresholds, ``"adaptive"`` or ``"opencv"``
    (:func:`slscan.decode.graycode.decode_gray_images`)."""

    def __post_init__(self) -> None:
        for name in ("max_epipolar_px", "max_ray_gap_mm", "outlier_px", "max_edge_factor"):
            if not getattr(self, name) > 0:
                raise SlscanError(f"stereo {name} must be positive, got {getattr(self, name)!r}")
        if not (isinstance(self.code_step, int) and self.code_step >= 1):
            raise SlscanError(f"stereo code_step must be a whole number >= 1, got {self.code_step!r}")
        if not 0 < self.max_view_angle_deg <= 90:
            raise SlscanError(f"stereo max_view_angle_deg must be in (0, 90], got {self.max_view_angle_deg!r}")


@dataclass(frozen=True)
class CodeCentroids:
    """Where one camera sees each projector code.

    codes : (n,) int64 sorted, ``column_block * rows_per_column + row_block``
    xy : (n, 2) float64 centroid of the code's pixels, camera px (distorted, as seen)
    count : (n,) int32 pixels averaged
    """

    codes: np.ndarray
    xy: np.ndarray
    count: np.ndarray

    def __len__(self) -> int:
        return len(self.codes)


def _box(image: np.ndarray, radius: int) -> np.ndarray:
    import cv2

    size = 2 * radius + 1
    return cv2.boxFilter(image, cv2.CV_64F, (size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)


def subpixel_positions(
    column: np.ndarray,
    row: np.ndarray,
    mask: np.ndarray,
    *,
    code_step: int = 1,
    radius: int = SUBPIXEL_RADIUS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where, near each decoded pixel, its code block's centre lies: sub-pixel (x, y).

    The decoded (integer) column and row are fitted by planes ``u ≈ u0 + J (p - p0)``
    over the ``(2 radius + 1)²`` window around each pixel (least squares over the decoded
    pixels of the window: the rounding of the codes averages out), and the pixel moves by
    ``J⁻¹ (target - u0)`` onto its block's centre. Pixels whose window is less than
    half decoded, whose fit is off by more than 0.5 code rms (a depth step or a
    wrong decode in the window), or whose move exceeds the window are not refined.

    Returns x, y (h, w) float64 and ok (h, w) bool (refined).
    """
    valid = np.asarray(mask, bool) & (column >= 0) & (row >= 0)
    h, w = valid.shape
    m = valid.astype(np.float64)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    n = _box(m, radius)
    sx, sy = _box(m * gx, radius), _box(m * gy, radius)
    sxx, sxy, syy = _box(m * gx * gx, radius), _box(m * gx * gy, radius), _box(m * gy * gy, radius)
    ok = valid & (n >= (2 * radius + 1) ** 2 / 2)
    yi, xi = np.nonzero(ok)
    px, py, k = gx[ok], gy[ok], n[ok]
    # moments about each pixel
    cx, cy = sx[ok] - px * k, sy[ok] - py * k
    cxx = sxx[ok] - 2 * px * sx[ok] + px * px * k
    cyy = syy[ok] - 2 * py * sy[ok] + py * py * k
    cxy = sxy[ok] - px * sy[ok] - py * sx[ok] + px * py * k
    normal = np.stack([np.stack([k, cx, cy], -1), np.stack([cx, cxx, cxy], -1), np.stack([cy, cxy, cyy], -1)], -2)
    fits, rms = [], np.zeros(len(px))
    for code in (np.asarray(column, np.float64), np.asarray(row, np.float64)):
        mu = m * code
        su, sxu, syu, suu = _box(mu, radius)[ok], _box(mu * gx, radius)[ok], _box(mu * gy, radius)[ok], _box(mu * code, radius)[ok]
        rhs = np.stack([su, sxu - px * su, syu - py * su], -1)
        with np.errstate(invalid="ignore", divide="ignore"):
            coef = np.linalg.solve(normal + 1e-9 * np.eye(3), rhs[..., None])[..., 0]
        fits.append(coef)
        rms += np.maximum(suu - np.einsum("ij,ij->i", coef, rhs), 0) / k
    half = (code_step - 1) / 2.0
    target = np.stack([(np.asarray(column)[ok] // code_step) * code_step + half,
                       (np.asarray(row)[ok] // code_step) * code_step + half], -1)
    jac = np.stack([fits[0][:, 1:], fits[1][:, 1:]], -2)  # d(u, v) / d(x, y)
    resid = target - np.stack([fits[0][:, 0], fits[1][:, 0]], -1)
    det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        dx = (jac[:, 1, 1] * resid[:, 0] - jac[:, 0, 1] * resid[:, 1]) / det
        dy = (-jac[:, 1, 0] * resid[:, 0] + jac[:, 0, 0] * resid[:, 1]) / det
    good = (np.abs(det) > 1e-3) & (np.sqrt(rms / 2) <= 0.5) & (np.hypot(dx, dy) <= radius)
    x_out, y_out = gx.copy(), gy.copy()
    refined = np.zeros_like(valid)
    x_out[yi[good], xi[good]] = px[good] + dx[good]
    y_out[yi[good], xi[good]] = py[good] + dy[good]
    refined[yi[good], xi[good]] = True
    return x_out, y_out, refined


def code_centroids(
    column: np.ndarray,
    row: np.ndarray,
    mask: np.ndarray,
    *,
    projector_height: int,
    code_step: int = 1,
    outlier_px: float = OUTLIER_PX,
    subpixel: bool = False,
) -> CodeCentroids:
    """The centroid of the pixels carrying each projector code in one camera.

    column, row : (h, w) int decoded projector column and row (-1: none)
    mask : (h, w) bool pixels whose column and row are decoded
    projector_height : px, to pack ``(column, row)`` into one code
    code_step : projector pixels per code block along each axis
    outlier_px : pixels further than this from their code's median position are dropped
        before averaging; a code left with none is dropped
    subpixel : average each pixel's estimate of its block centre
        (:func:`subpixel_positions`) instead of the pixel centres; pixels it cannot
        refine are left out
    """
    column, row, mask = np.asarray(column), np.asarray(row), np.asarray(mask, bool)
    valid = mask & (column >= 0) & (row >= 0)
    if subpixel:
        px, py, refined = subpixel_positions(column, row, valid, code_step=code_step)
        ys, xs = np.nonzero(refined)
        code_col, code_row = column[ys, xs], row[ys, xs]
        xs, ys = px[ys, xs], py[ys, xs]
    else:
        ys, xs = np.nonzero(valid)
        code_col, code_row = column[ys, xs], row[ys, xs]
    rows_per = -(-int(projector_height) // code_step)
    code = (code_col // code_step).astype(np.int64) * rows_per + (code_row // code_step)
    codes, inv, counts = np.unique(code, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    if len(codes) == 0:
        return CodeCentroids(codes, np.zeros((0, 2)), np.zeros(0, np.int32))
    # per-code (lower) median of x and y: sort within each code, take the middle element
    start = np.cumsum(counts) - counts
    mid = start + (counts - 1) // 2
    med_x = xs[np.lexsort((xs, inv))][mid].astype(np.float64)
    med_y = ys[np.lexsort((ys, inv))][mid].astype(np.float64)
    keep = (xs - med_x[inv]) ** 2 + (ys - med_y[inv]) ** 2 <= outlier_px**2
    n = np.bincount(inv, keep, minlength=len(codes))
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = np.bincount(inv, xs * keep, minlength=len(codes)) / n
        cy = np.bincount(inv, ys * keep, minlength=len(codes)) / n
    ok = n > 0
    return CodeCentroids(codes[ok], np.stack([cx[ok], cy[ok]], axis=1), n[ok].astype(np.int32))


def triangulate_midpoint(
    c0: np.ndarray, d0: np.ndarray, c1: np.ndarray, d1: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Midpoints (k, 3) of the closest points of rays ``c0 + s d0`` and ``c1 + t d1``.

    c0, c1 : (3,) ray origins; d0, d1 : (k, 3) unit directions
    Returns points, gap (k,) distance between the rays' closest points, and s, t (k,)
    (negative: behind the origin); NaN for parallel rays.
    """
    w = np.asarray(c0, float) - np.asarray(c1, float)
    b = np.einsum("ij,ij->i", d0, d1)
    d = d0 @ w
    e = d1 @ w
    denom = 1.0 - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = np.where(denom > 1e-12, denom, np.nan)
        s = (b * e - d) / denom
        t = (e - b * d) / denom
    p0 = c0 + s[:, None] * d0
    p1 = c1 + t[:, None] * d1
    return 0.5 * (p0 + p1), np.linalg.norm(p0 - p1, axis=1), s, t


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def epipolar_distance(
    xa: np.ndarray, xb: np.ndarray, a_from_b: np.ndarray, fa: float, fb: float
) -> np.ndarray:
    """Symmetric epipolar distance (k,) px of normalised (undistorted, z = 1) points
    ``xa``, ``xb`` (k, 3) of cameras a and b, b at ``a_from_b``: the mean of each point's
    distance to the other's epipolar line, in its camera's pixels (focal ``fa``, ``fb``)."""
    e = _skew(a_from_b[:3, 3]) @ a_from_b[:3, :3]  # xa^T E xb = 0
    la = xb @ e.T  # lines in image a
    lb = xa @ e  # lines in image b
    num = np.abs(np.einsum("ij,ij->i", xa, la))
    with np.errstate(divide="ignore", invalid="ignore"):
        da = num / np.hypot(la[:, 0], la[:, 1]) * fa
        db = num / np.hypot(lb[:, 0], lb[:, 1]) * fb
    return 0.5 * (da + db)


@dataclass(frozen=True)
class StereoMatch:
    """Projector codes matched between cameras a and b and triangulated.

    points : (n, 3) float64 mm, camera a's frame
    column, row : (n,) int32 projector column and row of each point (block centre with
        ``code_step`` > 1, rounded down)
    xy_a, xy_b : (n, 2) float64 the code's centroid in each camera, px
    ray_gap : (n,) mm; epipolar : (n,) px
    stats : counts: codes seen by each camera, common to both, rejected (epipolar, ray
        gap, behind a camera), kept
    """

    points: np.ndarray
    column: np.ndarray
    row: np.ndarray
    xy_a: np.ndarray
    xy_b: np.ndarray
    ray_gap: np.ndarray
    epipolar: np.ndarray
    stats: dict[str, int] = field(default_factory=dict)


def match_codes(
    a: CodeCentroids,
    b: CodeCentroids,
    lens_a: PinholeModel,
    lens_b: PinholeModel,
    a_from_b: np.ndarray,
    *,
    projector_height: int,
    code_step: int = 1,
    max_epipolar_px: float = MAX_EPIPOLAR_PX,
    max_ray_gap_mm: float = MAX_RAY_GAP_MM,
) -> StereoMatch:
    """Triangulate the codes seen by both cameras; points in camera a's frame.

    a_from_b : (4, 4) mm, camera b's pose in camera a's frame
    """
    common, ia, ib = np.intersect1d(a.codes, b.codes, assume_unique=True, return_indices=True)
    xa = lens_a.rays_local(a.xy[ia])
    xb = lens_b.rays_local(b.xy[ib])
    da = xa / np.linalg.norm(xa, axis=1, keepdims=True)
    db = xb @ a_from_b[:3, :3].T
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    points, gap, s, t = triangulate_midpoint(np.zeros(3), da, a_from_b[:3, 3], db)
    epi = epipolar_distance(xa, xb, a_from_b, lens_a.fx, lens_b.fx)
    front = (s > 0) & (t > 0)
    epi_ok = epi <= max_epipolar_px
    gap_ok = gap <= max_ray_gap_mm
    keep = front & epi_ok & gap_ok
    rows_per = -(-int(projector_height) // code_step)
    half = (code_step - 1) // 2
    stats = {
        "codes_a": len(a), "codes_b": len(b), "common": len(common),
        "rejected_behind": int((~front).sum()),
        "rejected_epipolar": int((front & ~epi_ok).sum()),
        "rejected_ray_gap": int((front & epi_ok & ~gap_ok).sum()),
        "matched": int(keep.sum()),
    }
    code = common[keep]
    return StereoMatch(
        points=points[keep],
        column=((code // rows_per) * code_step + half).astype(np.int32),
        row=((code % rows_per) * code_step + half).astype(np.int32),
        xy_a=a.xy[ia][keep], xy_b=b.xy[ib][keep],
        ray_gap=gap[keep], epipolar=epi[keep], stats=stats,
    )


def mesh_matches(
    match: StereoMatch,
    *,
    white_image: np.ndarray,
    view: str = "",
    code_step: int = 1,
    max_edge_factor: float = MAX_EDGE_FACTOR,
    max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG,
) -> RangeMap:
    """Mesh matched points on their projector grid into a range map in camera a's frame.

    Each grid quad of four matched codes gives two triangles (one when a corner is
    missing); long-edged and grazing triangles are cut as in
    :func:`slscan.decode.rangemap.build_range_map`, and points in no triangle are left
    out (isolated matches are the least trustworthy). The range map's ``row`` and
    ``stripe`` are the projector row and column; colours come from camera a's white
    image, quality is the cosine of camera a's viewing angle.
    """
    points = match.points
    k = len(points)
    col = (match.column // code_step).astype(np.int64)
    row = (match.row // code_step).astype(np.int64)
    faces = np.zeros((0, 3), np.int64)
    if k:
        span = int(row.max()) + 2
        keys = col * span + row
        find = _grid_lookup(keys, np.ones(k, bool))
        p00 = np.arange(k)
        p10, p01, p11 = find(keys + span), find(keys + 1), find(keys + span + 1)
        # a full quad: (00, 10, 11) + (00, 11, 01); otherwise the one triangle that exists
        cand = [
            np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1),
            np.stack([p00, p10, p01], 1)[p11 < 0], np.stack([p10, p11, p01], 1)[p00 < 0],
        ]
        tri = np.concatenate(cand)
        tri = tri[(tri >= 0).all(axis=1)]
        depth = np.linalg.norm(points, axis=1)
        m_col = _median_ratio(points, depth, p00[p10 >= 0], p10[p10 >= 0])
        m_row = _median_ratio(points, depth, p00[p01 >= 0], p01[p01 >= 0])
        faces = _filter_faces(tri, points, depth, row, col, m_row, m_col, max_edge_factor, max_view_angle_deg)
    finite = np.ones(k, bool)
    normals = _vertex_normals(points, faces, finite)
    used = np.zeros(k, bool)
    used[faces.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    pts = points[used]
    cos_view = np.clip(-np.einsum("ij,ij->i", normals[used], pts / np.linalg.norm(pts, axis=1, keepdims=True)), 0, 1)
    xy = match.xy_a[used]
    h = np.asarray(white_image).shape[0]
    colors = _white_rgb(white_image, np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, h - 1), xy[:, 0])
    return RangeMap(
        vertices=pts, faces=new_index[faces].astype(np.int32), normals=normals[used].astype(np.float32),
        colors=colors, quality=cos_view.astype(np.float32),
        row=match.row[used].astype(np.int32), stripe=match.column[used].astype(np.int32), view=view,
    )


@dataclass(frozen=True)
class StereoView:
    """One view reconstructed from two cameras: the matches and their range map (camera a's frame)."""

    view: str
    cameras: tuple[str, str]
    match: StereoMatch
    range_map: RangeMap
    seconds: dict[str, float] = field(default_factory=dict)

    @property
    def metrics(self) -> dict[str, float]:
        st = self.match.stats
        out = {k: float(v) for k, v in st.items()}
        out["vertices"] = float(len(self.range_map.vertices))
        out["faces"] = float(len(self.range_map.faces))
        if len(self.match.points):
            out["median_epipolar_px"] = float(np.median(self.match.epipolar))
            out["median_ray_gap_mm"] = float(np.median(self.match.ray_gap))
        return out


def _check_gray_rows(session: Session, camera: str) -> None:
    descs = [p for p in session.patterns if p.family == "gray"]
    if not gray_pairs(descs, "columns") or not gray_pairs(descs, "rows"):
        raise SlscanError(
            f"{session.root}: camera {camera!r} has no Gray-code {'row' if gray_pairs(descs, 'columns') else 'column'} "
            "patterns; matching cameras needs Gray-code columns and rows (capture with --patterns gray "
            "or both and --gray-rows)"
        )


def reconstruct_view(
    multi: MultiCamSession,
    view: str,
    config: StereoConfig = StereoConfig(),
    *,
    pair: tuple[int, int] = (0, 1),
) -> StereoView:
    """Match the projector codes of ``view`` between cameras ``pair`` (indices) of ``multi``
    and mesh the triangulated points into a range map in the first camera's frame."""
    multi.require_calibrated()
    ia, ib = pair
    if not (0 <= ia < len(multi.cameras) and 0 <= ib < len(multi.cameras)) or ia == ib:
        raise SlscanError(f"stereo pair {pair}: expected two different cameras of {len(multi.cameras)}")
    cam_a, cam_b = multi.cameras[ia], multi.cameras[ib]
    sa, sb = multi.sessions[ia], multi.sessions[ib]
    for cam, s in ((cam_a, sa), (cam_b, sb)):
        _check_gray_rows(s, cam.name)
    height = sa.projector_size[1]
    seconds = {}
    t = time.perf_counter()
    ra = decode_gray(sa, view, threshold=config.gray_threshold)
    rb = decode_gray(sb, view, threshold=config.gray_threshold)
    seconds["decode"] = time.perf_counter() - t
    t = time.perf_counter()
    opts = {"projector_height": height, "code_step": config.code_step}
    ca, cb = (code_centroids(r.column, r.row, r.mask, outlier_px=config.outlier_px, subpixel=config.subpixel, **opts)
              for r in (ra, rb))
    a_from_b = np.linalg.inv(cam_a.rig_from_camera) @ cam_b.rig_from_camera
    match = match_codes(ca, cb, cam_a.lens, cam_b.lens, a_from_b, max_epipolar_px=config.max_epipolar_px,
                        max_ray_gap_mm=config.max_ray_gap_mm, **opts)
    seconds["match"] = time.perf_counter() - t
    t = time.perf_counter()
    rm = mesh_matches(match, white_image=ra.white, view=view, code_step=config.code_step,
                      max_edge_factor=config.max_edge_factor, max_view_angle_deg=config.max_view_angle_deg)
    seconds["mesh"] = time.perf_counter() - t
    st = match.stats
    log.info(
        "%s %s-%s: %d codes matched of %d common; rejected %d epipolar, %d ray gap, %d behind",
        view, cam_a.name, cam_b.name, st["matched"], st["common"], st["rejected_epipolar"],
        st["rejected_ray_gap"], st["rejected_behind"],
    )
    return StereoView(view, (cam_a.name, cam_b.name), match, rm, seconds)


def reconstruct_multicam(
    multi: MultiCamSession | str | os.PathLike,
    out: str | os.PathLike,
    config: StereoConfig = StereoConfig(),
    *,
    pair: tuple[int, int] = (0, 1),
    overwrite: bool = False,
    rec=None,
    progress: Callable[[str], None] | None = None,
) -> list[StereoView]:
    """Reconstruct every view of a multi-camera session from camera pair ``pair``:
    ``out/VIEW.ply`` (range maps in the first camera's frame) and ``out/range_maps.json``
    (the decode stage's format, with the match counts as metrics).

    rec : an ``rr.RecordingStream`` for the range maps and metrics, or None
    """
    from slscan.decode.pipeline import RANGE_MAPS_FORMAT, RANGE_MAPS_VERSION

    if not isinstance(multi, MultiCamSession):
        multi = load_multicam(multi)
    multi.require_calibrated()
    results, entries = [], []
    with atomic_output_dir(out, overwrite=overwrite) as tmp:
        for index, view in enumerate(multi.sessions[pair[0]].views):
            result = reconstruct_view(multi, view.name, config, pair=pair)
            if rec is not None:
                from slscan.viewer import log_decode as rlog

                rm = result.range_map
                rlog.log_range_map(rec, rm.vertices, rm.faces, rm.normals, rm.colors, view_index=index)
                rlog.log_metrics(rec, result.metrics, view_index=index)
            if progress:
                progress(view.name)
            if len(result.range_map.faces) == 0:
                log.warning("%s: no stereo matches could be meshed (%s); left out", view.name, result.match.stats)
                continue
            write_ply(result.range_map, tmp / f"{view.name}.ply")
            entries.append({
                "view": view.name, "file": f"{view.name}.ply", "method": "stereo-codes",
                "rig_from_object": None if view.rig_from_object is None else view.rig_from_object.tolist(),
                "metrics": result.metrics, "seconds": result.seconds,
            })
            results.append(result)
        if not entries:
            raise SlscanError(f"{multi.root}: no view gave stereo matches (is the object seen by both cameras?)")
        a, b = (multi.cameras[i].name for i in pair)
        write_json(tmp / "range_maps.json", {
            "format": RANGE_MAPS_FORMAT, "version": RANGE_MAPS_VERSION, "written_by": f"slscan {__version__}",
            "session": str(Path(multi.sessions[pair[0]].root).resolve()),
            "frame": f"camera {a} frame, mm", "light_planes": None,
            "stereo": {"cameras": [a, b], "multi_camera": str(Path(multi.root).resolve())},
            "config": asdict(config), "views": entries,
        })
    return results
