"""Two calibrated cameras, one uncalibrated projector: match projector codes between cameras.

The projector only labels the surface. Each camera decodes the projector column and row of
every pixel with the pattern family that gives them (:func:`slscan.decode.codes.codes_family`:
Gray code, integer codes; phase shifting, sub-pixel codes); the projector plane is cut into
cells (one projector pixel, or blocks of ``code_step``), and a cell seen by both cameras is
one surface point. In each camera a cell is reduced to one sub-pixel position: every pixel
voting for it (its decoded code falls in the cell) is moved onto the cell's centre by plane
fits of the decoded column and row maps around it (over which the rounding of integer codes
averages out; phase codes are fitted as they are), and the moved pixels are averaged, after
dropping those far from the cell's median position (stray wrong decodes). Where the fits are
degenerate, because a code covers a block of camera pixels wider than the fit's window
(long focal lengths, Gray-code bits dropped), the cell falls back to the centroid of its
pixels. The rays through the two undistorted positions are triangulated at their midpoint;
a match is rejected when its symmetric epipolar distance (by default limited from the
view's own distribution of it, so a calibration's residual is measured, not assumed) or
the gap between its rays is too large, or when it lies behind a camera. The matched points
keep their projector grid ``(row, column)``, which meshes them into a range map like the
camera-projector one, following the codes' real step (2 or 4 projector pixels where bits
were dropped), written in camera 0's frame. No projector calibration is needed.

Everything is vectorised over pixels and cells (box filters, ``np.unique``, ``np.bincount``,
``np.intersect1d``); the plane fits run in bands of camera rows, so a 16 MP camera costs a
few hundred MB beyond its decoded maps.

References
----------
.. [1] Scharstein, Szeliski, "High-accuracy stereo depth maps using structured light",
   CVPR 2003 (cameras matched through the projector's codes).
.. [2] Hartley, Zisserman, "Multiple View Geometry in Computer Vision", 2nd ed., 2004:
   12.5 (midpoint triangulation), 9.6 (essential matrix, epipolar distance).
.. [3] Herakleous, Poullis, "3DUNDERWORLD-SLS: An Open-Source Structured-Light Scanning
   System for Rapid Geometry Acquisition", arXiv:1406.6595, 2014 (two cameras matched
   through Gray-code cells, per-cell centroids, ray midpoints).
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from slscan import __version__
from slscan.capture.multicam import MultiCamSession, load_multicam
from slscan.capture.session import Session
from slscan.decode.rangemap import (
    MAX_EDGE_FACTOR,
    MAX_VIEW_ANGLE_DEG,
    RangeMap,
    _filter_faces,
    _vertex_normals,
    _white_rgb,
    write_ply,
)
from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, write_json
from slscan.rig import PinholeModel

log = logging.getLogger(__name__)

MAX_EPIPOLAR_PX = 1.5
"""The fixed epipolar limit slscan used before ``"auto"`` (camera px): a centroid of one to a
few pixels is off by up to half a pixel in each camera, with an exact calibration."""

EPIPOLAR_FLOOR_PX = 1.0
"""``"auto"`` epipolar limit: never below this (camera px), however exact the calibration."""

EPIPOLAR_SIGMAS = 4.0
"""``"auto"`` epipolar limit: the median of the view's epipolar distances plus this many
robust standard deviations of them (1.4826 MAD): the calibration's residual, measured on
the matches themselves (for a half-normal distribution, the 99.8th percentile)."""

MAX_RAY_GAP_MM = 2.0
"""The fixed ray-gap limit slscan used before ``"auto"``, and the floor of ``"auto"`` (mm):
matches whose two rays pass further apart than this are rejected."""

OUTLIER_PX = 3.0
"""Default: pixels this far (camera px) from their cell's median position are left out of
its centroid (a projector pixel covers one to a few camera pixels at the paper's geometry)..."""

OUTLIER_SPREAD = 3.0
"""...or, for a cell covering a block of pixels, this many times the median distance of its
pixels from that median position, when larger (a square block of side s: 1.15 s, the whole
block; a stray decode is further)."""

SUBPIXEL_RADIUS = 3
"""Default half-width (camera px) of the window over which :func:`subpixel_positions`
fits the decoded codes by planes."""

MIN_BLOCK_PIXELS = 9
"""A cell covering a block of at least this many pixels (3 x 3) takes the centroid of its
pixels when fewer than :data:`MIN_REFINED_SHARE` of them could be plane-fitted: the fit
is degenerate where a code covers a block wider than the window (constant codes, no
gradient), and a block's centroid is sub-pixel by itself. A smaller cell takes the mean of
its fitted pixels, and is dropped when none could be fitted (the decoded region's border,
a depth step, a wrong decode)."""

MIN_REFINED_SHARE = 0.5
"""See :data:`MIN_BLOCK_PIXELS`."""

REFINE_BAND = 128
"""Camera rows per band of :func:`subpixel_positions`' plane fits (bounds their memory)."""

STEREO_FOLDER = "stereo_{a}_{b}"
"""Folder, inside the decode output, of the range maps from camera ``a`` matched with ``b``."""


@dataclass(frozen=True)
class StereoConfig:
    """How projector codes are matched between cameras and meshed."""

    max_epipolar_px: float | str = "auto"
    """Largest symmetric epipolar distance of a match, camera px; ``"auto"`` (default): the
    median of the view's epipolar distances plus :data:`EPIPOLAR_SIGMAS` robust deviations,
    at least :data:`EPIPOLAR_FLOOR_PX`: a calibration whose residual is 1.8 px (a real
    two-camera set) is not held to a limit for an exact one. The limit used is reported in
    the match counts (``epipolar_limit_px``)."""
    max_ray_gap_mm: float | str = "auto"
    """Largest distance between the two rays of a match, mm; ``"auto"`` (default): the same
    rule on the view's ray gaps, at least :data:`MAX_RAY_GAP_MM` (the gap is the epipolar
    distance in mm at the point's depth: a calibration residual widens both)."""
    outlier_px: float = OUTLIER_PX
    """Pixels further than this from their cell's median position do not count, camera px
    (cells covering a block of pixels allow :data:`OUTLIER_SPREAD` times their spread)."""
    subpixel: bool = True
    """Refine each pixel onto its cell's centre by plane fits of the decoded codes around
    it (:func:`subpixel_positions`) before averaging; a cell covering a block of at least
    ``min_block_pixels`` whose fits are degenerate (fewer than ``min_refined_share`` of its
    pixels fitted) takes the centroid of its pixels; a smaller cell none of whose pixels
    fitted is dropped. False: every cell its centroid. On the half-size virtual rig the refinement takes the
    median error from 0.31 to 0.25 mm on the figurine; with 4 x 4 camera pixels per
    projector pixel, from 0.30 to 0.065 mm on the flat tile (``tests/decode/test_stereo.py``,
    ``benchmarks/stereo.py``)."""
    min_refined_share: float = MIN_REFINED_SHARE
    """See ``subpixel``."""
    min_block_pixels: int = MIN_BLOCK_PIXELS
    """See ``subpixel``."""
    code_step: int = 1
    """Match blocks of ``code_step`` x ``code_step`` projector pixels (1: every pixel). A
    camera with fewer pixels than the projector sees each block more than once."""
    mesh_step: int | str = "auto"
    """The mesh's grid step, projector px: ``"auto"`` (default) follows the codes' real
    step around each point (``code_step`` times 1, 2, 4, ... up to the bits dropped or
    missing: Gray-code pixels with dropped bits carry codes 2 or 4 apart); a number: one
    fixed step (a multiple of ``code_step``)."""
    max_edge_factor: float = MAX_EDGE_FACTOR
    """Mesh edges longer than this many times the expected spacing are cut."""
    max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG
    """Triangles seen from camera 0 more obliquely than this are dropped."""
    gray_threshold: str = "adaptive"
    """Each camera's Gray-code bit thresholds, ``"adaptive"`` or ``"opencv"``
    (:func:`slscan.decode.graycode.decode_gray_images`)."""
    gray_drop_bits: int = 0
    """Gray code: a pixel whose finest bits are washed out keeps the code of its leading
    reliable bits when at most this many are missing (``decode_gray``'s ``drop_bits``);
    its code then marks a block of 2 or 4 projector pixels."""

    def __post_init__(self) -> None:
        for name in ("outlier_px", "max_edge_factor"):
            if not getattr(self, name) > 0:
                raise SlscanError(f"stereo {name} must be positive, got {getattr(self, name)!r}")
        for name, unit in (("max_epipolar_px", "px"), ("max_ray_gap_mm", "mm")):
            v = getattr(self, name)
            if not (v == "auto" or (isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0)):
                raise SlscanError(f"stereo {name} must be 'auto' or a positive number of {unit}, got {v!r}")
        if not (isinstance(self.code_step, int) and self.code_step >= 1):
            raise SlscanError(f"stereo code_step must be a whole number >= 1, got {self.code_step!r}")
        step = self.mesh_step
        if not (step == "auto" or (isinstance(step, int) and not isinstance(step, bool) and step >= 1
                                   and step % self.code_step == 0)):
            raise SlscanError(
                f"stereo mesh_step must be 'auto' or a whole multiple of code_step ({self.code_step}), got {step!r}")
        if not (isinstance(self.min_block_pixels, int) and self.min_block_pixels >= 1):
            raise SlscanError(f"stereo min_block_pixels must be a whole number >= 1, got {self.min_block_pixels!r}")
        if not 0 <= self.min_refined_share <= 1:
            raise SlscanError(f"stereo min_refined_share must be in [0, 1], got {self.min_refined_share!r}")
        if not 0 < self.max_view_angle_deg <= 90:
            raise SlscanError(f"stereo max_view_angle_deg must be in (0, 90], got {self.max_view_angle_deg!r}")
        if not (isinstance(self.gray_drop_bits, int) and self.gray_drop_bits >= 0):
            raise SlscanError(f"stereo gray_drop_bits must be a whole number >= 0, got {self.gray_drop_bits!r}")


@dataclass(frozen=True)
class CodeCentroids:
    """Where one camera sees each projector cell.

    codes : (n,) int64 sorted, ``column_cell * rows_per_column + row_cell``
    xy : (n, 2) float64 the cell's position, camera px (distorted, as seen)
    count : (n,) int32 pixels averaged
    refined : (n,) bool the position is the mean of plane-fitted pixels (else the centroid
        of the cell's pixels)
    """

    codes: np.ndarray
    xy: np.ndarray
    count: np.ndarray
    refined: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.codes)

    @property
    def refined_count(self) -> int:
        return 0 if self.refined is None else int(self.refined.sum())


def _box(image: np.ndarray, radius: int) -> np.ndarray:
    import cv2

    size = 2 * radius + 1
    return cv2.boxFilter(image, cv2.CV_64F, (size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)


def _valid_codes(column: np.ndarray, row: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Pixels whose column and row decoded: int maps -1, float maps NaN where not."""
    valid = np.asarray(mask, bool).copy()
    for m in (column, row):
        valid &= np.isfinite(m) if np.issubdtype(m.dtype, np.floating) else m >= 0
    return valid


def _cells(values: np.ndarray, step: int) -> np.ndarray:
    """The cell index (int64) of decoded codes: integer codes ``c // step``; sub-pixel codes
    (projector pixel centres at whole numbers) the cell ``[k step - 0.5, (k + 1) step - 0.5)``."""
    if np.issubdtype(values.dtype, np.integer):
        return values.astype(np.int64) // step
    return np.floor((values + 0.5) / step).astype(np.int64)


def _refine(
    column: np.ndarray, row: np.ndarray, valid: np.ndarray, *, code_step: int, radius: int, band: int = REFINE_BAND
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Plane-fit refinement of every ``valid`` pixel (in ``np.nonzero`` order), band by band.

    Returns ys, xs (k,) int the pixels, x, y (k,) float64 their refined positions (the
    pixel centre where not refined) and ok (k,) bool refined.
    """
    h = valid.shape[0]
    ys, xs = np.nonzero(valid)
    x_out, y_out = xs.astype(np.float64), ys.astype(np.float64)
    ok_out = np.zeros(len(ys), bool)
    if not len(ys):
        return ys, xs, x_out, y_out, ok_out
    first = np.searchsorted(ys, np.arange(h + 1))  # index of each row's first valid pixel
    half = (code_step - 1) / 2.0
    need = (2 * radius + 1) ** 2 / 2
    for y0 in range(int(ys[0]) // band * band, int(ys[-1]) + 1, band):
        y1 = min(h, y0 + band)
        i0, i1 = first[y0], first[y1]
        if i0 == i1:
            continue
        a0, a1 = max(0, y0 - radius), min(h, y1 + radius)
        cols = np.flatnonzero(valid[a0:a1].any(axis=0))
        c0, c1 = int(cols[0]), int(cols[-1]) + 1
        v = valid[a0:a1, c0:c1]
        m = v.astype(np.float64)
        gx = np.arange(c1 - c0, dtype=np.float64)[None, :]
        gy = np.arange(a1 - a0, dtype=np.float64)[:, None]
        py, px = ys[i0:i1] - a0, xs[i0:i1] - c0  # this band's pixels, band coordinates
        at = (py, px)
        k = _box(m, radius)[at]
        ok = k >= need
        mx, my = m * gx, m * gy
        sx, sy = _box(mx, radius)[at], _box(my, radius)[at]
        sxx, sxy, syy = _box(mx * gx, radius)[at], _box(mx * gy, radius)[at], _box(my * gy, radius)[at]
        fx, fy = px.astype(np.float64), py.astype(np.float64)
        # moments about each pixel, and the normal matrix [[k, cx, cy], [cx, cxx, cxy], [cy, cxy, cyy]]
        cx, cy = sx - fx * k, sy - fy * k
        cxx = sxx - 2 * fx * sx + fx * fx * k
        cyy = syy - 2 * fy * sy + fy * fy * k
        cxy = sxy - fx * sy - fy * sx + fx * fy * k
        a, b, c, d, e, f = k + 1e-9, cx, cy, cxx + 1e-9, cxy, cyy + 1e-9
        adj = (d * f - e * e, c * e - b * f, b * e - c * d, a * f - c * c, b * c - a * e, a * d - b * b)
        det3 = a * adj[0] + b * adj[1] + c * adj[2]
        fits, rms = [], np.zeros(len(px))
        for code in (column, row):
            u = np.where(v, code[a0:a1, c0:c1], 0).astype(np.float64)
            mu = m * u
            su, sxu, syu = _box(mu, radius)[at], _box(mu * gx, radius)[at], _box(mu * gy, radius)[at]
            suu = _box(mu * u, radius)[at]
            r0, r1, r2 = su, sxu - fx * su, syu - fy * su
            with np.errstate(invalid="ignore", divide="ignore"):
                coef = [(adj[0] * r0 + adj[1] * r1 + adj[2] * r2) / det3,
                        (adj[1] * r0 + adj[3] * r1 + adj[4] * r2) / det3,
                        (adj[2] * r0 + adj[4] * r1 + adj[5] * r2) / det3]
            fits.append(coef)
            rms += np.maximum(suu - (coef[0] * r0 + coef[1] * r1 + coef[2] * r2), 0) / k
            del u, mu
        # each pixel's target: the centre of the cell its own code falls in
        tu = _cells(column[ys[i0:i1], xs[i0:i1]], code_step) * code_step + half
        tv = _cells(row[ys[i0:i1], xs[i0:i1]], code_step) * code_step + half
        (u0, ux, uy), (v0, vx, vy) = fits
        det = ux * vy - uy * vx
        ru, rv = tu - u0, tv - v0
        with np.errstate(invalid="ignore", divide="ignore"):
            dx = (vy * ru - uy * rv) / det
            dy = (-vx * ru + ux * rv) / det
            good = ok & (np.abs(det) > 1e-3) & (np.sqrt(rms / 2) <= 0.5) & (np.hypot(dx, dy) <= radius)
        x_out[i0:i1][good] += dx[good]
        y_out[i0:i1][good] += dy[good]
        ok_out[i0:i1] = good
    return ys, xs, x_out, y_out, ok_out


def subpixel_positions(
    column: np.ndarray,
    row: np.ndarray,
    mask: np.ndarray,
    *,
    code_step: int = 1,
    radius: int = SUBPIXEL_RADIUS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where, near each decoded pixel, the centre of its code's cell lies: sub-pixel (x, y).

    column, row : (h, w) decoded projector column and row: int (-1: none) or float
        (sub-pixel codes, NaN: none)

    The decoded column and row are fitted by planes ``u ≈ u0 + J (p - p0)`` over the
    ``(2 radius + 1)²`` window around each pixel (least squares over the decoded pixels of
    the window: the rounding of integer codes averages out), and the pixel moves by
    ``J⁻¹ (target - u0)`` onto its cell's centre (the cell of ``code_step`` projector
    pixels its code falls in). Pixels whose window is less than half decoded, whose fit is
    off by more than 0.5 code rms (a depth step or a wrong decode in the window), whose
    fit is degenerate (``|det J| <= 1e-3``: a code constant over the window) or whose move
    exceeds the window are not refined.

    Returns x, y (h, w) float64 and ok (h, w) bool (refined).
    """
    column, row = np.asarray(column), np.asarray(row)
    valid = _valid_codes(column, row, mask)
    h, w = valid.shape
    ys, xs, x, y, ok = _refine(column, row, valid, code_step=code_step, radius=radius)
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    refined = np.zeros_like(valid)
    gx[ys[ok], xs[ok]] = x[ok]
    gy[ys[ok], xs[ok]] = y[ok]
    refined[ys[ok], xs[ok]] = True
    return gx, gy, refined


def _group_median(values: np.ndarray, inv: np.ndarray, start: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Per group (lower) median of ``values``; groups given by ``inv`` (each non-empty)."""
    return values[np.lexsort((values, inv))][start + (counts - 1) // 2]


def _robust_centroids(
    xs: np.ndarray, ys: np.ndarray, inv: np.ndarray, groups: int, outlier_px: float, spread: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group: mean x, y of its members within ``max(outlier_px, spread * median
    distance)`` of the group's median position, and how many they are (0: none; NaN mean)."""
    counts = np.bincount(inv, minlength=groups)
    cx = np.full(groups, np.nan)
    cy = np.full(groups, np.nan)
    n = np.zeros(groups, np.int64)
    if not len(inv):
        return cx, cy, n
    # renumber the non-empty groups so that every group has members
    present = np.flatnonzero(counts)
    dense = np.searchsorted(present, inv)
    c = counts[present]
    start = np.cumsum(c) - c
    med_x = _group_median(xs, dense, start, c)
    med_y = _group_median(ys, dense, start, c)
    dist = np.hypot(xs - med_x[dense], ys - med_y[dense])
    limit = np.full(len(present), float(outlier_px))
    if spread:
        limit = np.maximum(limit, spread * _group_median(dist, dense, start, c))
    keep = dist <= limit[dense]
    k = np.bincount(dense, keep, minlength=len(present))
    with np.errstate(invalid="ignore", divide="ignore"):
        cx[present] = np.bincount(dense, xs * keep, minlength=len(present)) / k
        cy[present] = np.bincount(dense, ys * keep, minlength=len(present)) / k
    n[present] = k.astype(np.int64)
    return cx, cy, n


def code_centroids(
    column: np.ndarray,
    row: np.ndarray,
    mask: np.ndarray,
    *,
    projector_height: int,
    code_step: int = 1,
    outlier_px: float = OUTLIER_PX,
    subpixel: bool = False,
    min_refined_share: float = MIN_REFINED_SHARE,
    min_block_pixels: int = MIN_BLOCK_PIXELS,
    radius: int = SUBPIXEL_RADIUS,
) -> CodeCentroids:
    """The position of each projector cell seen by one camera.

    column, row : (h, w) decoded projector column and row, int32 (-1: none; Gray code) or
        float (NaN: none; phase shifting, sub-pixel)
    mask : (h, w) bool pixels whose column and row are decoded
    projector_height : px, to pack ``(column, row)`` cells into one code
    code_step : projector pixels per cell along each axis; a pixel's cell is the one its
        code falls in (:func:`_cells`)
    outlier_px : pixels further than this from their cell's median position are dropped
        before averaging (cells covering a block of pixels: :data:`OUTLIER_SPREAD` times
        their median distance from it, when larger); a cell left with none is dropped
    subpixel : each cell the mean of its pixels' estimates of the cell's centre
        (:func:`subpixel_positions`); a cell of at least ``min_block_pixels`` (a block)
        of which fewer than ``min_refined_share`` could be refined (the fits degenerate)
        the centroid of its pixels; a smaller cell none of whose pixels could be refined
        is dropped. False: every cell the centroid of its pixels
    """
    column, row = np.asarray(column), np.asarray(row)
    valid = _valid_codes(column, row, mask)
    if subpixel:
        ys, xs, rx, ry, ok = _refine(column, row, valid, code_step=code_step, radius=radius)
    else:
        ys, xs = np.nonzero(valid)
    rows_per = -(-int(projector_height) // code_step)
    ci = np.maximum(_cells(column[ys, xs], code_step), 0)
    ri = np.clip(_cells(row[ys, xs], code_step), 0, rows_per - 1)
    code = ci * rows_per + ri
    codes, inv = np.unique(code, return_inverse=True)
    inv = inv.reshape(-1)
    if len(codes) == 0:
        return CodeCentroids(codes, np.zeros((0, 2)), np.zeros(0, np.int32), np.zeros(0, bool))
    fx, fy = xs.astype(np.float64), ys.astype(np.float64)
    cx, cy, n = _robust_centroids(fx, fy, inv, len(codes), outlier_px, OUTLIER_SPREAD)
    refined = np.zeros(len(codes), bool)
    if subpixel:
        total = np.bincount(inv, minlength=len(codes))
        fitted = np.bincount(inv[ok], minlength=len(codes))
        rxc, ryc, rn = _robust_centroids(rx[ok], ry[ok], inv[ok], len(codes), outlier_px, 0.0)
        block = n >= min_block_pixels
        refined = (rn > 0) & ((fitted >= min_refined_share * total) | ~block)
        cx, cy, n = np.where(refined, rxc, cx), np.where(refined, ryc, cy), np.where(refined, rn, np.where(block, n, 0))
    good = n > 0
    return CodeCentroids(codes[good], np.stack([cx[good], cy[good]], axis=1), n[good].astype(np.int32),
                         refined[good])


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


def epipolar_limit(distances: np.ndarray, *, floor: float = EPIPOLAR_FLOOR_PX,
                   sigmas: float = EPIPOLAR_SIGMAS) -> float:
    """The ``"auto"`` epipolar limit, camera px, from the matches' own epipolar distances
    (k,): ``max(floor, median + sigmas * 1.4826 * MAD)`` over the finite ones (``floor``
    when there are none). A calibration's residual shows as a shift of the whole
    distribution (the good matches' median), wrong matches as its far tail. (The
    ``"auto"`` ray-gap limit is the same rule on the ray gaps, mm.)"""
    d = np.asarray(distances, float)
    d = d[np.isfinite(d)]
    if not len(d):
        return float(floor)
    med = float(np.median(d))
    mad = float(np.median(np.abs(d - med)))
    return max(float(floor), med + sigmas * 1.4826 * mad)


@dataclass(frozen=True)
class StereoMatch:
    """Projector cells matched between cameras a and b and triangulated.

    points : (n, 3) float64 mm, camera a's frame
    column, row : (n,) int32 projector column and row of each point (the cell's centre,
        rounded down, with ``code_step`` > 1)
    xy_a, xy_b : (n, 2) float64 the cell's position in each camera, px
    ray_gap : (n,) mm; epipolar : (n,) px
    stats : counts: cells seen by each camera (``codes_a``, ``codes_b``) and how many of
        them were plane-fitted (``refined_a``, ``refined_b``; the others are centroids),
        common to both, rejected (``rejected_epipolar``, ``rejected_ray_gap``,
        ``rejected_behind``), kept (``matched``); the epipolar limit used
        (``epipolar_limit_px``) and the median epipolar distance of the common cells in
        front of both cameras (``epipolar_median_px``, absent when none), px; the ray-gap
        limit used (``ray_gap_limit_mm``)
    """

    points: np.ndarray
    column: np.ndarray
    row: np.ndarray
    xy_a: np.ndarray
    xy_b: np.ndarray
    ray_gap: np.ndarray
    epipolar: np.ndarray
    stats: dict[str, float] = field(default_factory=dict)


def match_codes(
    a: CodeCentroids,
    b: CodeCentroids,
    lens_a: PinholeModel,
    lens_b: PinholeModel,
    a_from_b: np.ndarray,
    *,
    projector_height: int,
    code_step: int = 1,
    max_epipolar_px: float | str = "auto",
    max_ray_gap_mm: float | str = "auto",
) -> StereoMatch:
    """Triangulate the cells seen by both cameras; points in camera a's frame.

    a_from_b : (4, 4) mm, camera b's pose in camera a's frame
    max_epipolar_px : px, or ``"auto"`` (:func:`epipolar_limit` of the common cells in
        front of both cameras)
    max_ray_gap_mm : mm, or ``"auto"`` (the same rule on their ray gaps, at least
        :data:`MAX_RAY_GAP_MM`)
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
    limit = epipolar_limit(epi[front]) if max_epipolar_px == "auto" else float(max_epipolar_px)
    gap_limit = (epipolar_limit(gap[front], floor=MAX_RAY_GAP_MM) if max_ray_gap_mm == "auto"
                 else float(max_ray_gap_mm))
    epi_ok = epi <= limit
    gap_ok = gap <= gap_limit
    keep = front & epi_ok & gap_ok
    rows_per = -(-int(projector_height) // code_step)
    half = (code_step - 1) // 2
    stats = {
        "codes_a": len(a), "codes_b": len(b), "refined_a": a.refined_count, "refined_b": b.refined_count,
        "common": len(common),
        "rejected_behind": int((~front).sum()),
        "rejected_epipolar": int((front & ~epi_ok).sum()),
        "rejected_ray_gap": int((front & epi_ok & ~gap_ok).sum()),
        "matched": int(keep.sum()),
        "epipolar_limit_px": float(limit),
        "ray_gap_limit_mm": float(gap_limit),
    }
    if front.any():
        stats["epipolar_median_px"] = float(np.median(epi[front]))
    code = common[keep]
    return StereoMatch(
        points=points[keep],
        column=((code // rows_per) * code_step + half).astype(np.int32),
        row=((code % rows_per) * code_step + half).astype(np.int32),
        xy_a=a.xy[ia][keep], xy_b=b.xy[ib][keep],
        ray_gap=gap[keep], epipolar=epi[keep], stats=stats,
    )


def _axis_links(major: np.ndarray, minor: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Each point's next neighbour along ``minor`` on its ``major`` line (-1: none), kept
    when their distance is one of ``steps`` and at most the larger of the two points' own
    spacing on the line (the nearer of their two neighbours): a region whose codes step by
    4 links by 4, but a missing code in a region stepping by 1 stays a hole."""
    k = len(major)
    order = np.lexsort((minor, major))
    mj, mn = major[order], minor[order]
    same = mj[1:] == mj[:-1]
    gap = np.where(same, mn[1:] - mn[:-1], np.iinfo(np.int64).max)
    after = np.concatenate([gap, [np.iinfo(np.int64).max]])  # to the next point on the line
    before = np.concatenate([[np.iinfo(np.int64).max], gap])  # to the previous one
    own = np.minimum(after, before)
    nxt_own = np.concatenate([own[1:], [np.iinfo(np.int64).max]])
    ok = np.concatenate([same, [False]])
    ok &= np.isin(after, steps) & (after <= np.maximum(own, nxt_own))
    link = np.full(k, -1, np.int64)
    link[order[ok]] = order[np.flatnonzero(ok) + 1]
    return link


def mesh_matches(
    match: StereoMatch,
    *,
    white_image: np.ndarray,
    view: str = "",
    code_step: int = 1,
    steps: tuple[int, ...] | None = None,
    max_edge_factor: float = MAX_EDGE_FACTOR,
    max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG,
) -> RangeMap:
    """Mesh matched points on their projector grid into a range map in camera a's frame.

    steps : the grid steps the codes may take, projector px (default: ``code_step``
        alone). Each point links to its next neighbour along its projector row (column)
        when they are one of ``steps`` apart and no further apart than the nearer
        neighbour of either (:func:`_axis_links`), so codes 2 or 4 apart (Gray-code bits
        dropped) mesh at their own step while a missing code among codes 1 apart stays a
        hole. A point, its right and lower neighbours and their common neighbour give two
        triangles (a full grid square); with the right, lower or far corner missing, the
        one triangle that is left.
    Long-edged and grazing triangles are cut as in
    :func:`slscan.decode.rangemap.build_range_map` (edge lengths expected from the median
    length per projector pixel of the links), and points in no triangle are left out
    (isolated matches are the least trustworthy). The range map's ``row`` and ``stripe``
    are the projector row and column; colours come from camera a's white image, quality
    is the cosine of camera a's viewing angle.
    """
    return _mesh(match, white_image=white_image, view=view, steps=tuple(steps) if steps else (code_step,),
                 max_edge_factor=max_edge_factor, max_view_angle_deg=max_view_angle_deg)[0]


def _mesh(
    match: StereoMatch,
    *,
    white_image: np.ndarray,
    view: str,
    steps: tuple[int, ...],
    max_edge_factor: float,
    max_view_angle_deg: float,
) -> tuple[RangeMap, dict[str, object]]:
    """:func:`mesh_matches`, and what it found (see :class:`StereoView`'s ``mesh``)."""
    points = match.points
    k = len(points)
    col = match.column.astype(np.int64)
    row = match.row.astype(np.int64)
    allowed = np.asarray(steps, np.int64)
    faces = np.zeros((0, 3), np.int64)
    info: dict[str, object] = {"links": 0, "triangles": 0, "spacing_px": math.nan, "steps": tuple(steps)}
    if k:
        right = _axis_links(row, col, allowed)
        down = _axis_links(col, row, allowed)
        has_r, has_d = right >= 0, down >= 0
        r_of_d = np.where(has_d, right[np.where(has_d, down, 0)], -1)  # the far corner, two ways
        d_of_r = np.where(has_r, down[np.where(has_r, right, 0)], -1)
        both = has_r & has_d
        corner = np.where(both, np.where(r_of_d == d_of_r, r_of_d, -1), np.maximum(r_of_d, d_of_r))
        p00 = np.arange(k)
        has_c = corner >= 0
        # a grid square's two triangles, or with one corner missing the one left
        tri = np.concatenate([
            np.stack([p00, right, corner], 1)[has_r & has_c], np.stack([p00, corner, down], 1)[has_d & has_c],
            np.stack([p00, right, down], 1)[both & ~has_c],
        ])
        depth = np.linalg.norm(points, axis=1)

        def per_px(a: np.ndarray, b: np.ndarray, n: np.ndarray) -> float:
            if not len(a):
                return math.nan
            length = np.linalg.norm(points[a] - points[b], axis=1)
            return float(np.median(length / (0.5 * (depth[a] + depth[b]) * n)))

        m_col = per_px(p00[has_r], right[has_r], (col[right[has_r]] - col[has_r]).astype(np.float64))
        m_row = per_px(p00[has_d], down[has_d], (row[down[has_d]] - row[has_d]).astype(np.float64))
        faces = _filter_faces(tri, points, depth, row, col, m_row, m_col, max_edge_factor, max_view_angle_deg)
        info.update(links=int(has_r.sum() + has_d.sum()), triangles=len(tri), spacing_px=_row_spacing(col, row))
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
    rm = RangeMap(
        vertices=pts, faces=new_index[faces].astype(np.int32), normals=normals[used].astype(np.float32),
        colors=colors, quality=cos_view.astype(np.float32),
        row=match.row[used].astype(np.int32), stripe=match.column[used].astype(np.int32), view=view,
    )
    return rm, info


@dataclass(frozen=True)
class StereoView:
    """One view reconstructed from two cameras: the matches and their range map (camera a's frame).

    mesh : how the matches meshed: ``links`` (grid neighbours found), ``triangles``
        (formed from them), ``faces`` (kept after the edge-length and viewing-angle cuts),
        ``spacing_px`` (median projector distance between a match and its nearest
        neighbour on its projector row, NaN without any), ``steps`` (the grid steps allowed)
    """

    view: str
    cameras: tuple[str, str]
    match: StereoMatch
    range_map: RangeMap
    seconds: dict[str, float] = field(default_factory=dict)
    mesh: dict[str, object] = field(default_factory=dict)

    @property
    def metrics(self) -> dict[str, float]:
        st = self.match.stats
        out = {k: float(v) for k, v in st.items() if isinstance(v, (int, float)) and math.isfinite(v)}
        out["vertices"] = float(len(self.range_map.vertices))
        out["faces"] = float(len(self.range_map.faces))
        if len(self.match.points):
            out["median_epipolar_px"] = float(np.median(self.match.epipolar))
            out["median_ray_gap_mm"] = float(np.median(self.match.ray_gap))
        return out

    def describe(self) -> str:
        """One line: what each camera saw, what each test rejected, what meshed."""
        st, (a, b) = self.match.stats, self.cameras
        parts = [f"{self.view}: cells seen {a} {st['codes_a']:,} ({st['refined_a']:,} plane-fitted), "
                 f"{b} {st['codes_b']:,} ({st['refined_b']:,}), both {st['common']:,}"]
        if st["common"]:
            median = st.get("epipolar_median_px")
            med = f"; median {median:.2f} px" if median is not None else ""
            parts.append(
                f"rejected {st['rejected_epipolar']:,} by the epipolar limit ({st['epipolar_limit_px']:.2f} px{med}), "
                f"{st['rejected_ray_gap']:,} by the ray gap ({st['ray_gap_limit_mm']:.2f} mm), "
                f"{st['rejected_behind']:,} behind a camera; "
                f"{st['matched']:,} matched")
        if st["matched"]:
            m = self.mesh
            spacing = m.get("spacing_px", math.nan)
            apart = f"matches {spacing:g} projector px apart" if math.isfinite(spacing) else "no two on a projector row"
            parts.append(
                f"{m.get('triangles', 0):,} triangles from {m.get('links', 0):,} grid links "
                f"({apart}, mesh steps {', '.join(map(str, m.get('steps', ())))} px), "
                f"{len(self.range_map.faces):,} faces kept")
        return ", ".join(parts[:1]) + "".join(f"; {p}" for p in parts[1:])


def _rejections_hint(results: list[StereoView]) -> str:
    """Which step lost the most cells, from the counts of ``results``: a test, or meshing."""
    count = {k: sum(r.match.stats[k] for r in results) for k in
             ("common", "rejected_epipolar", "rejected_ray_gap", "rejected_behind", "matched")}
    if not count["common"]:
        return "no projector cell was decoded by both cameras"
    lost = {
        "the epipolar test rejected the most matches (--stereo-epipolar)": count["rejected_epipolar"],
        "the ray-gap test rejected the most matches (--stereo-ray-gap)": count["rejected_ray_gap"],
        "the most matches lay behind a camera (is camera 1's pose in cameras.json right?)": count["rejected_behind"],
        "the matches did not mesh: no grid neighbours at the mesh steps (--stereo-mesh-step)": count["matched"],
    }
    what = max(lost, key=lost.get)
    return f"{what}: {lost[what]:,} of {count['common']:,} cells both cameras saw"


def _check_codes(session: Session, camera: str):
    """The family giving ``session``'s projector codes; an error when it has none, or no rows."""
    from slscan.decode.codes import codes_family

    fam = codes_family(session)
    if fam is None:
        found = sorted({p.family for p in session.patterns}) or ["none"]
        raise SlscanError(
            f"{session.root}: camera {camera!r} has no patterns that give projector codes ({', '.join(found)}); "
            "matching cameras needs Gray-code or phase-shifting columns and rows")
    axes = {p.axis for p in session.patterns if p.family == fam.name}
    for axis in ("columns", "rows"):
        if axis not in axes:
            raise SlscanError(
                f"{session.root}: camera {camera!r} has no {fam.name} {axis[:-1]} patterns; matching cameras "
                f"needs projector columns and rows (capture with --patterns gray or both and --gray-rows)")
    return fam


def _decode(session: Session, view: str, config: StereoConfig):
    """One camera's :class:`~slscan.decode.codes.ProjectorCodes`, by the family that gives them."""
    from slscan.decode.codes import decode_codes
    from slscan.decode.pipeline import DecodeConfig

    return decode_codes(session, view, DecodeConfig(gray_threshold=config.gray_threshold,
                                                    gray_drop_bits=config.gray_drop_bits))


def _bits_read(session: Session) -> tuple[int, int] | None:
    """The Gray-code bits a camera's set lets decoding read per axis (its leading run of
    bits present), or None without Gray code. Sub-pixel codes (phase shifting) report no
    bits read (``ProjectorCodes.bits`` 0), so :func:`coarsened` leaves them as they are."""
    from slscan.decode.graycode import gray_pairs

    bits = len(gray_pairs(session.patterns, "columns")), len(gray_pairs(session.patterns, "rows"))
    return bits if bits[0] else None


def coarsened(codes, bits: tuple[int, int]):
    """``codes`` (:class:`~slscan.decode.codes.ProjectorCodes` of Gray code) read to
    ``bits`` per axis at most: a finer code is replaced by the centre of its block of
    ``2**(read - bits)`` columns (rows), as a set missing those bits decodes it, so that a
    camera whose set lacks bits the other has is matched on the bits both have."""
    from dataclasses import replace

    from slscan.decode.graycode import _block_centres

    maps = {}
    for name, value, read, want in (("column", codes.column, codes.bits[0], bits[0]),
                                    ("row", codes.row, codes.bits[1], bits[1])):
        if value is None or read <= want:
            continue
        ok = value >= 0
        drop = np.full(value.shape, read - want, np.uint8)
        maps[name] = np.where(ok, _block_centres(np.where(ok, value, 0), drop), value).astype(value.dtype)
    if not maps:
        return codes
    return replace(codes, **maps, bits=tuple(min(r, w) for r, w in zip(codes.bits, bits)))


def _row_spacing(column: np.ndarray, row: np.ndarray) -> float:
    """Median distance, projector px, between a point and the next one on its projector row
    (NaN when no row has two)."""
    col, row = np.asarray(column, np.int64), np.asarray(row, np.int64)
    order = np.lexsort((col, row))
    same = row[order][1:] == row[order][:-1]
    gaps = (col[order][1:] - col[order][:-1])[same]
    return float(np.median(gaps)) if len(gaps) else math.nan


def mesh_steps(config: StereoConfig, bits: tuple[int, int], projector_size: tuple[int, int],
               spacing_px: float = math.nan) -> tuple[int, ...]:
    """The grid steps (projector px) the mesh may follow: ``config.mesh_step`` when fixed;
    "auto": ``code_step`` times 1, 2, 4, ... up to the codes' real step: the bits dropped per
    pixel (``gray_drop_bits``) and missing from the set (``bits`` read per axis, against the
    projector's size; 0: sub-pixel codes, none missing), or the matches' median spacing
    along projector rows ``spacing_px`` (the finest Gray-code stripes lost in camera blur
    leave every other code), whichever is larger."""
    if config.mesh_step != "auto":
        return (int(config.mesh_step),)
    missing = max((math.ceil(math.log2(max(size, 2))) - b if b > 0 else 0) for b, size in zip(bits, projector_size))
    levels = max(missing, 0) + config.gray_drop_bits
    if math.isfinite(spacing_px) and spacing_px > config.code_step:
        levels = max(levels, math.ceil(math.log2(spacing_px / config.code_step)))
    return tuple(config.code_step * 2**j for j in range(levels + 1))


def reconstruct_view(
    multi: MultiCamSession,
    view: str,
    config: StereoConfig = StereoConfig(),
    *,
    pair: tuple[int, int] = (0, 1),
) -> StereoView:
    """Match the projector cells of ``view`` between cameras ``pair`` (indices) of ``multi``
    and mesh the triangulated points into a range map in the first camera's frame.

    Each camera is decoded by the family that gives projector codes
    (:func:`slscan.decode.codes.codes_family`: phase shifting, then Gray code), one camera
    at a time (only its cells are kept)."""
    multi.require_calibrated()
    ia, ib = pair
    if not (0 <= ia < len(multi.cameras) and 0 <= ib < len(multi.cameras)) or ia == ib:
        raise SlscanError(f"stereo pair {pair}: expected two different cameras of {len(multi.cameras)}")
    cam_a, cam_b = multi.cameras[ia], multi.cameras[ib]
    sa, sb = multi.sessions[ia], multi.sessions[ib]
    for cam, s in ((cam_a, sa), (cam_b, sb)):
        _check_codes(s, cam.name)
    height = sa.projector_size[1]
    opts = {"projector_height": height, "code_step": config.code_step}
    seconds = {"decode": 0.0, "match": 0.0}
    centroids, bits = [], []
    read = [_bits_read(s) for s in (sa, sb)]
    common = tuple(map(min, *read)) if None not in read else None  # a camera missing bits the other has
    # codes missing low bits name blocks of 2**missing projector pixels: every such cell is a
    # block by construction, whose plane fits degenerate, so it falls back to its centroid
    # whatever its size in the camera
    full = tuple(max(1, math.ceil(math.log2(n))) for n in sa.projector_size)
    min_block = 1 if common is not None and any(c < f for c, f in zip(common, full)) else config.min_block_pixels
    for s in (sa, sb):
        t = time.perf_counter()
        codes = _decode(s, view, config)
        if common is not None:
            codes = coarsened(codes, common)
        seconds["decode"] += time.perf_counter() - t
        t = time.perf_counter()
        centroids.append(code_centroids(codes.column, codes.row, codes.mask, outlier_px=config.outlier_px,
                                        subpixel=config.subpixel, min_refined_share=config.min_refined_share,
                                        min_block_pixels=min_block, **opts))
        bits.append(codes.bits)
        seconds["match"] += time.perf_counter() - t
        del codes
    t = time.perf_counter()
    a_from_b = np.linalg.inv(cam_a.rig_from_camera) @ cam_b.rig_from_camera
    match = match_codes(*centroids, cam_a.lens, cam_b.lens, a_from_b, max_epipolar_px=config.max_epipolar_px,
                        max_ray_gap_mm=config.max_ray_gap_mm, **opts)
    seconds["match"] += time.perf_counter() - t
    t = time.perf_counter()
    steps = mesh_steps(config, tuple(min(x, y) for x, y in zip(*bits)), sa.projector_size,
                       _row_spacing(match.column, match.row))
    white_id, _ = sa.flat_frame_ids("stereo matching")
    record = sa.view(view)
    white = sa.read_image(record, record.image_for(white_id))
    rm, mesh = _mesh(match, white_image=white, view=view, steps=steps, max_edge_factor=config.max_edge_factor,
                     max_view_angle_deg=config.max_view_angle_deg)
    seconds["mesh"] = time.perf_counter() - t
    result = StereoView(view, (cam_a.name, cam_b.name), match, rm, seconds, mesh)
    log.info("%s", result.describe())
    return result


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

    Raises
    ------
    SlscanError
        No view meshed: one line with each view's counts (cells each camera saw, common,
        rejected by each test, matched, meshed) and the test that rejected the most.
    """
    from slscan.decode.pipeline import RANGE_MAPS_FORMAT, RANGE_MAPS_VERSION

    if not isinstance(multi, MultiCamSession):
        multi = load_multicam(multi)
    multi.require_calibrated()
    results, entries, failed = [], [], []
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
                log.warning("no stereo range map, left out: %s", result.describe())
                failed.append(result)
                continue
            write_ply(result.range_map, tmp / f"{view.name}.ply")
            entries.append({
                "view": view.name, "file": f"{view.name}.ply", "method": "stereo-codes",
                "rig_from_object": None if view.rig_from_object is None else view.rig_from_object.tolist(),
                "metrics": result.metrics, "seconds": result.seconds,
            })
            results.append(result)
        if not entries:
            shown = failed[:3]
            more = f"; and {len(failed) - len(shown)} more view(s)" if len(failed) > len(shown) else ""
            raise SlscanError(
                f"{multi.root}: no view gave a stereo range map ({_rejections_hint(failed)}): "
                + "; ".join(r.describe() for r in shown) + more)
        a, b = (multi.cameras[i].name for i in pair)
        write_json(tmp / "range_maps.json", {
            "format": RANGE_MAPS_FORMAT, "version": RANGE_MAPS_VERSION, "written_by": f"slscan {__version__}",
            "session": str(Path(multi.sessions[pair[0]].root).resolve()),
            "frame": f"camera {a} frame, mm", "light_planes": None,
            "stereo": {"cameras": [a, b], "multi_camera": str(Path(multi.root).resolve())},
            "config": asdict(config), "views": entries,
        })
    return results
