"""Decode the paper's hybrid pattern: green lines indexed by red/blue bands, with sub-pixel axes.

Pipeline for one view (:func:`decode_hybrid_images` on arrays, :func:`decode_hybrid` on a
capture session):

1. **Shadow mask** from the white and black frames (:func:`slscan.decode.masks.shadow_mask`);
   the steps after it run on the bounding box of the lit pixels (:func:`~slscan.decode.masks.lit_bounds`).
2. **Colour crosstalk** (:func:`estimate_crosstalk`): the camera's response to each
   projector primary, a (3, 3) matrix ``M`` (camera channels × primaries, unit diagonal),
   measured from the session itself. Pixels deep inside a red (blue) band of a coarse
   image see only the red (blue) primary, so their black-subtracted colour is a column of
   ``M`` times the albedo: the ratios of its channels give that column whatever the
   surface colour. The green column comes from pixels that are red in one coarse image
   and blue in another: ``(white − black) − red − blue`` is what the green primary alone
   gives there.
   With ``mixing="pixel"`` (the default) this matrix only gives the first guess of the
   bands: :func:`estimate_mixing` then measures each pixel's own response to each primary
   (paint × crosstalk) from the coarse images where it sits deep in a red or a blue band,
   and :class:`_PixelUnmixer` unmixes with it (exact also when the paint acts after the
   crosstalk, as on a real surface); :func:`separate_global` optionally takes the global
   light out (``global_light``).
3. **Unmix and normalise** (:func:`primaries`): with ``I − B = M (a ∘ p)`` (albedo ``a``,
   projected primaries ``p`` in [0, 1]), ``M⁻¹ (I − B) / M⁻¹ (W − B) = p`` per pixel and
   primary, so the surface colour cancels (the figurine's saturated red and blue paint
   otherwise reads as bands). Unmixing comes before the division, which makes the
   cancellation exact for any albedo.
4. **Signals**: every projector pixel of the pattern is exactly one primary, so
   ``p_r + p_g + p_b = 1`` and each of the green line ``g`` and the "redness" ``e`` has
   two estimates (``p_g`` or ``1 − p_r − p_b``; ``p_r`` or ``1 − p_b``); they are
   combined with weights from each channel's white-frame signal, so a line on red paint
   (little green light comes back) is measured through the red and blue channels.
5. **Progressive indexing**: a green line found in image ``k`` is indexed from the band
   bits (red 0, blue 1) of images ``1 .. k−1`` read at its sub-pixel position: the
   region ``r`` is their binary number, most significant first, and the line is
   ``params["lines"][r]`` of image ``k``.
6. **Medial axis**: local maxima of ``g`` along each camera row (after a ``[1, 2, 1] / 4``
   filter across rows) that stand above the neighbouring bands, refined to sub-pixel by
   one of :data:`ESTIMATORS`.
7. **Rejection**: with ``max_line_sigma`` > 0, lines too weak against the image noise to
   place their axis (:func:`line_axis_sigma`: the camera noise, :func:`estimate_noise`,
   carried through the unmixing; on saturated paint the line comes back faintly);
   ambiguous bits (``e`` near 0.5); low or flat peaks; a peak without red
   on its left and blue on its right; a line next to a drop of the white frame (a
   silhouette, shadow or crease truncates its profile); a line beside a paint edge that
   moves its centre (``paint_edges="shift"``: the centre read pixel by pixel and in the
   centre's paint disagree, :func:`paint_read_peaks`); samples whose projector column
   disagrees with every linear prediction from their neighbours along the row (a wrong
   index, :func:`order_consistent`).

Sub-pixel estimators (``estimator=``), on the samples ``f(c + i)`` of the line signal
around its integer maximum ``c``:

``"centroid"``
    centre of mass of ``max(f, 0)`` over a window ``± 2.5`` px re-centred on the
    estimate until it settles, counting only the line's own flanks (Fisher & Naidu 1996
    compare it with the others).
``"gaussian"``
    the vertex of the parabola through ``ln f(c − 1), ln f(c), ln f(c + 1)``: exact for a
    Gaussian profile (Naidu & Fisher 1991).
``"parabola"``
    the vertex of the parabola through ``f(c − 1), f(c), f(c + 1)``; biased towards the
    pixel centre ("pixel locking") on lines narrower than about 2 px: 0.07 px at σ 0.8.
``"blais-rioux"``
    the zero crossing, linearly interpolated, of the 4th-order FIR derivative
    ``d(i) = f(i + 1) + f(i + 2) − f(i − 1) − f(i − 2)`` (Blais & Rioux 1986).

The default, ``"gaussian"``, was the most accurate everywhere on the virtual rig at full
size (``benchmarks/stripe_axes.py``; the green lines are about 1.2 camera px wide,
Gaussian σ ≈ 0.8 px after blur): RMS axis error 0.008 px on a noise-free tile, 0.011 px
with sensor noise, 0.093 px on the noisy, painted figurine (centroid 0.010 / 0.016 /
0.107, Blais-Rioux 0.016 / 0.019 / 0.122, parabola 0.069 / 0.069 / 0.120).

References
----------
C. Rocchini, P. Cignoni, C. Montani, P. Pingi, R. Scopigno. "A low cost 3D scanner based
on structured light". Computer Graphics Forum 20(3) (Eurographics 2001), 299-308.

F. Blais, M. Rioux. "Real-time numerical peak detector". Signal Processing 11(2) (1986),
145-155.

R. B. Fisher, D. K. Naidu. "A comparison of algorithms for subpixel peak detection". In
J. Sanz (ed.), Image Technology, Springer (1996), 385-404.

D. K. Naidu, R. B. Fisher. "A comparative analysis of algorithms for determining the
peak position of a stripe to sub-pixel accuracy". Proc. British Machine Vision
Conference (1991), 217-225.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from slscan.capture.session import ImageRecord, Session, ViewRecord
from slscan.decode.family import FamilyDecode
from slscan.decode.masks import (
    DEFAULT_MIN_CONTRAST,
    SaturationReport,
    channel_max,
    full_scale,
    like_white,
    lit_bounds,
    saturation,
    saturation_report,
    shadow_mask,
    uncrop,
    warn_saturation,
)
from slscan.decode.options import DEFAULT_ESTIMATOR, ESTIMATORS
from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError
from slscan.patterns import PatternImage
from slscan.patterns import hybrid as hybrid_pattern

log = logging.getLogger(__name__)

DEFAULT_MIN_PEAK = 0.2
"""Smallest line signal kept: green relative to the white frame at the line's maximum."""

DEFAULT_MIN_PROMINENCE = 0.15
"""How far the maximum must stand above the lower of the two neighbouring band minima."""

DEFAULT_AMBIGUITY = 0.15
"""Band bits with ``|e − 0.5|`` below this (red ≈ blue) are unreadable."""

DEFAULT_MIN_POLARITY = 0.1
"""A line must be redder one pixel to its left than one pixel to its right by this much."""

DEFAULT_MIN_EDGE_RATIO = 0.6
"""Lines whose white-frame neighbourhood falls below this fraction of the line's own white
level are cut by a silhouette or shadow edge, and dropped."""

DEFAULT_MAX_LINE_SIGMA = 0.0
"""Largest expected axis standard deviation (camera px) of a kept line sample
(:func:`line_axis_sigma`); 0 keeps every sample (off)."""

NOISE_BINS = 16  # white-frame levels over which the shot-noise gain is fitted
EDGE_RADIUS = 2  # px each side checked for a white-frame edge
PROMINENCE_RADIUS = 3  # px each side searched for the neighbouring band minimum
PLATEAU_WIDTH = 7  # px, band pixels used for crosstalk must be this deep inside a band
CROSSTALK_LEVELS = 3  # coarse images whose wide bands serve the crosstalk estimate
CROSSTALK_ROWS = 240  # about this many image rows are used for it
MIN_CROSSTALK_PIXELS = 50
MAX_NEIGHBOUR_GAP = 16.0  # camera px; farther samples along a row are not compared
MAX_LONE_SLOPE = 8.0  # projector px per camera px, for a sample with a single neighbour
MIXING_MODES = ("pixel", "global")
DEFAULT_MIXING = "pixel"
"""Colour unmixing: per pixel from the session's own bands (:func:`estimate_mixing`), or one
crosstalk matrix for the view (:func:`estimate_crosstalk`, the decoder before 2026-11)."""
MIXING_LEVELS = 6  # coarse images whose bands serve the per-pixel mixing
MIXING_CONFIDENCE = 0.3  # |e − 0.5| a band pixel needs to serve the mixing estimate
MIXING_SMOOTH = 9  # px, box over which the per-pixel primary shares are averaged
GLOBAL_LEVELS = 3  # finest levels whose images give the global light (Nayar et al. 2006)
GLOBAL_WINDOW = 5  # px along x over which the smallest share is taken too
GLOBAL_SMOOTH = 15  # px, box over which the global estimate is averaged
PAINT_EDGE_FLOOR = 0.3  # channels darker than this share of the brightest are not tested
PAINT_EDGE_MODES = ("shift", "drop", "keep")
DEFAULT_PAINT_EDGES = "shift"
PAINT_EDGE_SHIFT = 0.3
"""camera px: with ``paint_edges="shift"``, a line sample at a paint edge is dropped when
reading its profile in its centre's paint instead of pixel by pixel moves its centre by more
than this. Demo at half size: 2,671 samples dropped instead of 11,475 ("drop"), fused-mesh
holes 107 (drop 201, keep 101); figurine at scale 0.5, vertices near paint edges: gross
outliers 0.63 % (drop 0.24, keep 0.98); ``benchmarks/paint_edges.py``, where
``--variant s=paint_edges:shift,paint_edge_shift:T`` sweeps it."""
PAINT_EDGE_METRIC = "paint_edge_samples_dropped"
"""The per-view metric (``range_maps.json``) counting line samples dropped at paint edges."""
MIN_DIRECT = 0.25  # line samples where less of the white frame is direct light are dropped
CENTROID_RADIUS = 2.5  # px each side of the centre of mass
CROP_MARGIN = 8  # px kept around the lit pixels: every window below fits inside
_EPS = 1e-6
_ROW_KERNEL = np.array([0.25, 0.5, 0.25], np.float32)


@dataclass(frozen=True)
class HybridResult:
    """What :func:`decode_hybrid` finds in one view.

    samples : the green lines' sub-pixel centres; ``projector_column`` is the line's
        projector column (its centre, pixel centres at integers), ``stripe`` its index
        ``0 .. 2**levels − 2``; sorted by row, then x
    mask : (h, w) bool pixels lit by the projector
    codes : (h, w) int32 region code after all levels (the band bits, most significant
        first), −1 outside the mask and where a bit is unreadable; for display
    crosstalk : (3, 3) float64 camera channel (rows) response to projector primaries
        (columns), unit diagonal, as estimated (or given)
    saturation : per-image saturation, white, black, then the pattern images in level order
    white : (h, w, 3) the white capture as given (for colour and saturation downstream)
    rejected : line maxima dropped, by reason ("sub-pixel fit", "ambiguous bit", "edge",
        "polarity", "global": too little direct light, "weak line": the line's contrast
        against the noise cannot place its axis, "paint edge": a paint edge moves its
        centre, "order": inconsistent index)
    level_samples : line samples kept per level, coarsest first (before the order test);
        each level has twice the lines of the one before (on the virtual marble bust under
        subsurface scattering every level keeps about a ninth of its direct-light count)
    axis_sigma : (k,) float64 expected standard deviation (camera px) of each sample's
        axis from the line's signal against the image noise (:func:`line_axis_sigma`, the
        noise from :func:`estimate_noise`), in the order of ``samples``; None unless asked
        for (``axis_sigma=True``) or computed anyway (``max_line_sigma`` > 0)
    """

    samples: StripeSamples
    mask: np.ndarray
    codes: np.ndarray
    crosstalk: np.ndarray
    saturation: tuple[SaturationReport, ...]
    white: np.ndarray | None = None
    rejected: Mapping[str, int] = field(default_factory=dict)
    level_samples: tuple[int, ...] = ()
    axis_sigma: np.ndarray | None = None


# --- sub-pixel medial axis ----------------------------------------------------------------


def _window(signal: np.ndarray, rows: np.ndarray, cols: np.ndarray, half: int) -> np.ndarray:
    """Values (k, 2 half + 1) of ``signal[rows, cols + i]``, i = −half .. half (edges clamped)."""
    offsets = np.arange(-half, half + 1)
    idx = np.clip(cols[:, None] + offsets[None, :], 0, signal.shape[1] - 1)
    return signal[rows[:, None], idx]


def _centroid(
    f: np.ndarray, half: int, *, radius: float = CENTROID_RADIUS, iterations: int = 10
) -> tuple[np.ndarray, np.ndarray]:
    """Centre of mass of ``max(f, 0)`` over a window ``± radius`` px centred on the estimate.

    f : (k, 2 half + 1) samples at offsets ``−half .. half`` from the integer maximum
    Returns offsets (k,) and validity (k,). Only the line's own flanks count (samples
    beyond the first rise on either side belong to a neighbour); pixels count by the share
    of their width inside the window; re-centring the window (``iterations`` times) removes
    the bias a fixed window has when the line is not centred on a pixel.
    """
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    # only the line's own flanks: stop at the first rise on either side (a neighbouring line)
    falling_left = np.cumprod(f[:, half - 1 :: -1] <= f[:, half:0:-1], axis=1)[:, ::-1]
    falling_right = np.cumprod(f[:, half + 1 :] <= f[:, half:-1], axis=1)
    flank = np.concatenate([falling_left, np.ones((len(f), 1)), falling_right], axis=1)
    w = np.maximum(f, 0.0) * flank
    centre = np.zeros(len(f))
    total = np.ones(len(f))
    for _ in range(iterations):
        lo = centre[:, None] - radius
        hi = centre[:, None] + radius
        share = np.clip(np.minimum(offsets + 0.5, hi) - np.maximum(offsets - 0.5, lo), 0.0, 1.0)
        ws = w * share
        total = ws.sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            centre = np.clip((ws * offsets).sum(axis=1) / total, -1.0, 1.0)
        centre = np.where(total > _EPS, centre, 0.0)
    return centre, total > _EPS


def subpixel_peaks(
    signal: np.ndarray, rows: np.ndarray, cols: np.ndarray, *, estimator: str = DEFAULT_ESTIMATOR
) -> tuple[np.ndarray, np.ndarray]:
    """Refine integer maxima of a line signal to sub-pixel positions along x.

    signal : (h, w) float line signal (a 1-D profile works as ``signal[None]``)
    rows, cols : (k,) int position of each local maximum
    estimator : {"centroid", "gaussian", "parabola", "blais-rioux"} (module docstring)

    Returns ``x`` (k,) float64 camera px (pixel centres at integers) and ``ok`` (k,) bool,
    False where the estimate failed (flat or non-concave profile, a maximum too close to
    the image border, or an offset beyond one pixel).
    """
    if estimator not in ESTIMATORS:
        raise SlscanError(
            f"unknown line estimator {estimator!r}: expected one of {', '.join(ESTIMATORS)}"
        )
    signal = np.asarray(signal)
    if signal.ndim == 1:
        signal = signal[None]
    rows = np.asarray(rows, dtype=np.intp)
    cols = np.asarray(cols, dtype=np.intp)
    half = _half_window(estimator)
    return _refine(_window(signal, rows, cols, half).astype(np.float64), cols, signal.shape[1], estimator)


def _half_window(estimator: str) -> int:
    """Samples each side of the integer maximum that ``estimator`` reads."""
    return 2 if estimator in ("gaussian", "parabola") else 3


def _refine(f: np.ndarray, cols: np.ndarray, width: int, estimator: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`subpixel_peaks` on the windows ``f`` (k, 2 half + 1) float64 around the
    integer maxima ``cols`` (k,) of rows ``width`` px wide."""
    half = _half_window(estimator)
    ok = (cols >= half) & (cols < width - half)
    mid = half
    with np.errstate(divide="ignore", invalid="ignore"):
        if estimator == "centroid":
            offset, good = _centroid(f, half)
            ok &= good
        elif estimator in ("gaussian", "parabola"):
            t = f[:, mid - 1 : mid + 2]
            if estimator == "gaussian":
                t = np.log(np.maximum(t, _EPS))
            denom = t[:, 0] - 2 * t[:, 1] + t[:, 2]
            offset = 0.5 * (t[:, 0] - t[:, 2]) / denom
            ok &= denom < -_EPS
        else:  # blais-rioux
            # d(i) for i = c − 1, c, c + 1: rising flank positive, falling flank negative
            d_m1 = f[:, mid] + f[:, mid + 1] - f[:, mid - 2] - f[:, mid - 3]
            d_0 = f[:, mid + 1] + f[:, mid + 2] - f[:, mid - 1] - f[:, mid - 2]
            d_p1 = f[:, mid + 2] + f[:, mid + 3] - f[:, mid] - f[:, mid - 1]
            right = d_0 > 0  # crossing between c and c + 1
            a = np.where(right, d_0, d_m1)
            b = np.where(right, d_p1, d_0)
            base = np.where(right, 0.0, -1.0)
            offset = base + a / (a - b)
            ok &= (a > 0) & (b <= 0) & (a - b > _EPS)
    ok &= np.isfinite(offset) & (np.abs(offset) <= 1.0)
    x = cols + np.where(ok, offset, 0.0)
    return x, ok


def paint_read_peaks(
    signal: np.ndarray,
    lit: np.ndarray,
    readout: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    *,
    estimator: str = DEFAULT_ESTIMATOR,
    smooth_rows: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`subpixel_peaks` on the line's profile read in the paint of its centre pixel.

    signal : (h, w) float32 line signal ``g`` before the filter across rows (a share of
        each pixel's own white: the paint divided out pixel by pixel)
    lit : (h, w, 3) float32 the white frame minus the black, per camera channel
    readout : (3, k) how ``g`` reads each camera channel at each maximum (``∂g / ∂I``,
        ``_PixelUnmixer.line_readout``)
    rows, cols : (k,) int the maxima (of ``signal`` filtered across rows when ``smooth_rows``)

    Returns ``x`` (k,) float64 camera px and ``ok`` (k,) bool, as :func:`subpixel_peaks`.

    The camera blurs paint × light. Divided pixel by pixel by the white ``k * a``, a line
    ``L`` on paint ``a`` reads ``(k * (a L)) / (k * a)``; where ``a`` is constant over the
    blur this is ``k * L``, but across a paint edge the two estimates of the centre that
    bracket the truth part: the ratio (right when the line is wider than the blur) and the
    profile in the centre's paint, ``g`` times each pixel's white relative to the centre's
    (right when the line is narrower than the blur; each channel weighted by how much the
    line signal reads it, ``|readout| · lit``). For a locally linear paint gradient ``β``
    the ratio's centre is off by ``−β σ_k²`` and the other's by ``+β σ_L²`` (camera and
    line widths): their difference bounds the paint's bias. 1-D with a step 1 -> 0.2 at
    0.6 px from a line of σ 0.3 px under a camera blur of σ 0.6 px: ratio +0.28 px, centre's
    paint −0.005 px; on the virtual rig's figurine neither is better on its own (the rig
    samples the paint at pixel centres), but samples where they differ are the worst.
    Where the paint is uniform the factor is the white frame's smooth variation (shading),
    which the ratio is right to divide out: use this at paint edges only.
    """
    rows = np.asarray(rows, dtype=np.intp)
    cols = np.asarray(cols, dtype=np.intp)
    h, w = signal.shape
    half = _half_window(estimator)
    idx = np.clip(cols[:, None] + np.arange(-half, half + 1)[None, :], 0, w - 1)
    f = np.zeros(idx.shape, np.float64)
    weights = np.abs(readout)
    centre = np.maximum(sum(weights[j] * lit[rows, cols, j] for j in range(3)), _EPS)
    taps = zip((-1, 0, 1), _ROW_KERNEL) if smooth_rows else ((0, 1.0),)
    for dr, weight in taps:
        r = rows + dr
        inside = ((r >= 0) & (r < h))[:, None]
        r = np.clip(r, 0, h - 1)[:, None]
        relative = sum(weights[j][:, None] * lit[r, idx, j] for j in range(3)) / centre[:, None]
        f += float(weight) * np.where(inside, signal[r, idx] * relative, 0.0)
    return _refine(f, cols, w, estimator)


def find_line_peaks(
    signal: np.ndarray,
    *,
    min_peak: float = DEFAULT_MIN_PEAK,
    min_prominence: float = DEFAULT_MIN_PROMINENCE,
    radius: int = PROMINENCE_RADIUS,
) -> tuple[np.ndarray, np.ndarray]:
    """Integer local maxima along x of a line signal that stand above the bands beside them.

    signal : (h, w) float line signal, 0 where nothing is lit
    min_peak : smallest signal at the maximum
    min_prominence : the maximum minus the higher of the minima over the ``radius`` pixels
        on its left and on its right must reach this

    Returns ``rows, cols`` (k,) intp, row-major order.
    """
    g = np.asarray(signal, dtype=np.float32)
    w = g.shape[1]
    if w < 2 * radius + 3:
        return np.empty(0, np.intp), np.empty(0, np.intp)
    centre = g[:, 1:-1]
    peak = (centre >= g[:, :-2]) & (centre > g[:, 2:]) & (centre >= min_peak)
    rows, cols = np.nonzero(peak)
    cols += 1
    # minima over [x − radius, x − 1] and [x + 1, x + radius] (beyond the border: +inf),
    # at the candidate maxima only (a few % of the pixels)
    value = g[rows, cols]
    left = np.full(len(rows), np.inf, np.float32)
    right = np.full(len(rows), np.inf, np.float32)
    for o in range(1, radius + 1):
        np.minimum(left, np.where(cols >= o, g[rows, np.maximum(cols - o, 0)], np.inf), out=left)
        np.minimum(right, np.where(cols + o < w, g[rows, np.minimum(cols + o, w - 1)], np.inf), out=right)
    keep = value - np.maximum(left, right) >= min_prominence
    return rows[keep], cols[keep]


# --- colour ---------------------------------------------------------------------------------


def _plateau(band: np.ndarray) -> np.ndarray:
    """Pixels (h, w) bool of ``band`` with ``PLATEAU_WIDTH // 2`` band pixels either side along x."""
    # a minimum over PLATEAU_WIDTH pixels along x, outside the image counting as no band
    eroded = cv2.erode(band.astype(np.uint8), np.ones((1, PLATEAU_WIDTH), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return eroded.astype(bool)


def estimate_crosstalk(
    white: np.ndarray,
    black: np.ndarray,
    coarse: Sequence[np.ndarray],
    *,
    mask: np.ndarray | None = None,
    saturated: np.ndarray | None = None,
    bit_depth: int | None = None,
    row_step: int | None = None,
) -> np.ndarray:
    """The projector → camera colour crosstalk (3, 3), measured from a view's own captures.

    white, black : (h, w, 3) captures under projector white and black
    coarse : (h, w, 3) captures of coarse hybrid images (wide red and blue bands), e.g. the
        first three levels
    mask : (h, w) bool lit pixels (default: :func:`~slscan.decode.masks.shadow_mask`)
    saturated : (h, w) bool pixels clipped in any of the images (default: computed)
    row_step : use every ``row_step``-th row (default: about ``CROSSTALK_ROWS`` rows)

    Returns ``M`` (3, 3) float64, camera channel (rows) response to projector primary
    (columns), each column scaled to a unit diagonal (the scale cancels in the
    normalisation by the white frame).

    Red and blue columns: the mean black-subtracted colour of pixels at least
    ``PLATEAU_WIDTH // 2`` px inside a red (blue) band, classified by their normalised
    colour; albedo scales all channels of one primary alike, so it drops out of the
    channel ratios. Green column: at pixels that are inside a red band in one coarse image
    and inside a blue band in another, ``(white − black) − red − blue`` is the green
    primary's response alone. Saturated pixels are left out. A column without enough
    pixels (fewer than ``MIN_CROSSTALK_PIXELS``) is assumed free of crosstalk, with a
    warning: the green one when a view has a single level.
    """
    white, black = np.asarray(white), np.asarray(black)
    if mask is None:
        mask = shadow_mask(white, black, bit_depth=bit_depth)
    if saturated is None:
        saturated = np.logical_or.reduce(
            [saturation(a, bit_depth=bit_depth) for a in (white, *coarse)]
        )
    # a few hundred rows hold plenty of band pixels
    step = row_step or max(1, white.shape[0] // CROSSTALK_ROWS)
    black_f = black[::step].astype(np.float32)
    lit = white[::step].astype(np.float32) - black_f
    mask = mask[::step]
    usable = mask & ~saturated[::step]
    floor = 1e-3 * full_scale(np.asarray(white), "white image", bit_depth=bit_depth)
    with np.errstate(divide="ignore"):
        inv = np.where(lit > floor, 1.0 / lit, 0.0).astype(np.float32)
    red_resp = np.zeros(lit.shape, np.float32)
    blue_resp = np.zeros(lit.shape, np.float32)
    has_red = np.zeros(mask.shape, bool)
    has_blue = np.zeros(mask.shape, bool)
    red_sum = np.zeros(3)
    blue_sum = np.zeros(3)
    n_red = n_blue = 0
    for image in coarse:
        d = np.asarray(image)[::step].astype(np.float32) - black_f
        diff = d[..., 0] * inv[..., 0] - d[..., 2] * inv[..., 2]
        red_here = _plateau((diff > 0.4) & usable)
        blue_here = _plateau((diff < -0.4) & usable)
        for here, resp, has in ((red_here, red_resp, has_red), (blue_here, blue_resp, has_blue)):
            np.copyto(resp, d, where=(here & ~has)[..., None])  # the first band a pixel is in
            has |= here
        red_sum += d[red_here].sum(axis=0, dtype=np.float64)
        blue_sum += d[blue_here].sum(axis=0, dtype=np.float64)
        n_red += int(red_here.sum())
        n_blue += int(blue_here.sum())
    both = has_red & has_blue
    green_sum = (lit[both] - red_resp[both] - blue_resp[both]).sum(axis=0, dtype=np.float64)
    m = np.eye(3)
    for k, (total, count, what) in enumerate(
        ((red_sum, n_red, "red"), (green_sum, int(both.sum()), "green"), (blue_sum, n_blue, "blue"))
    ):
        if count < MIN_CROSSTALK_PIXELS or total[k] <= 0:
            log.warning(
                "crosstalk: only %d pixels show the %s primary alone; assuming it reaches only the "
                "%s camera channel",
                count,
                what,
                what,
            )
            continue
        column = np.clip(total / total[k], 0.0, 0.95)
        column[k] = 1.0
        m[:, k] = column
    return m


@dataclass(frozen=True)
class _Unmixer:
    """Turns raw captures into the line signal ``g`` and the band "redness" ``e``.

    With ``U = M⁻¹ (I − B)`` and ``W = M⁻¹ (white − black)`` per pixel (``M``: crosstalk),
    the primaries seen are ``p_c = U_c / W_c``, each with relative inverse noise variance
    ``w_c = W_c²``. The line signal combines the green primary with the complement of red
    and blue, ``1 − p_r − p_b``, weighted by ``w_rb = w_r w_b / (w_r + w_b)``::

        g = (w_g p_g + w_rb (1 − p_r − p_b)) / (w_g + w_rb)
        e = (w_r p_r + w_b (1 − p_b)) / (w_r + w_b)

    Both are affine in the raw capture ``I``, so they are folded once per view into
    per-pixel coefficients: ``g = g0 + Σ_c G_c I_c`` and ``e = e0 + Σ_c E_c I_c``. Pixels
    outside the mask, or where the white frame gives no light, get ``g = 0`` and
    ``e = 0.5`` (an unreadable bit).
    """

    g0: np.ndarray  # (h, w) float32
    gc: tuple[np.ndarray, np.ndarray, np.ndarray]  # (h, w) float32 per camera channel
    e0: np.ndarray
    ec: tuple[np.ndarray, np.ndarray, np.ndarray]

    @classmethod
    def build(
        cls, white: np.ndarray, black: np.ndarray, crosstalk: np.ndarray, mask: np.ndarray
    ) -> _Unmixer:
        try:
            unmix = np.linalg.inv(crosstalk).T  # row vectors: U = d @ unmix
        except np.linalg.LinAlgError:
            raise SlscanError(f"crosstalk matrix is singular:\n{crosstalk}") from None
        # plane by plane in float32 (an (n, 3) @ (3, 3) product per pixel is several times
        # slower); pixels outside the mask get the "nothing there" coefficients at the end
        f32 = np.float32
        black = [np.asarray(black[..., j], f32) for j in range(3)]
        lit = [np.asarray(white[..., j], f32) - black[j] for j in range(3)]

        def mix(planes: list[np.ndarray], m: np.ndarray, c: int) -> np.ndarray:
            """Σ_j planes[j] m[j, c]"""
            out = planes[0] * f32(m[0, c])
            for j in (1, 2):
                out += planes[j] * f32(m[j, c])
            return out

        wr, wg, wb = (np.maximum(mix(lit, unmix, c), 0.0) for c in range(3))
        del lit
        sq_r, sq_g, sq_b = wr * wr, wg * wg, wb * wb
        zero = np.zeros_like(wr)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            w_rb = np.where((sq_r > 0) & (sq_b > 0), sq_r * sq_b / (sq_r + sq_b), zero)
            # g as a function of the primaries' signals U: a + Σ_c k_c U_c
            den_g = sq_g + w_rb
            a = np.where(den_g > 0, w_rb / den_g, zero)
            k_u = [
                np.where(sq_r > 0, -a / wr, zero),
                np.where(den_g > 0, wg / den_g, zero),
                np.where(sq_b > 0, -a / wb, zero),
            ]
            den_e = sq_r + sq_b
            ok_e = den_e > 0
            b = np.where(ok_e, sq_b / den_e, f32(0.5))
            j_u = [np.where(ok_e, wr / den_e, zero), zero, np.where(ok_e, -wb / den_e, zero)]
        # U = (I − B) @ unmix, so Σ_c k_c U_c = Σ_j (unmix @ k)_j (I_j − B_j)
        outside = ~np.asarray(mask, bool)
        k_i = tuple(mix(k_u, unmix.T, j) for j in range(3))
        j_i = tuple(mix(j_u, unmix.T, j) for j in range(3))
        g0, e0 = a, b
        for j in range(3):
            g0 -= k_i[j] * black[j]
            e0 -= j_i[j] * black[j]
        for plane in (*k_i, *j_i, g0):
            plane[outside] = 0.0
        e0[outside] = 0.5
        return cls(g0, k_i, e0, j_i)

    def signals(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Line signal ``g`` and redness ``e``, (h, w) float32, from a raw capture (h, w, 3)."""
        channels = [np.asarray(image[..., j], np.float32) for j in range(3)]
        g, e = self.g0.copy(), self.e0.copy()
        for j, c in enumerate(channels):
            g += self.gc[j] * c
            e += self.ec[j] * c
        return g, e


def primaries(
    image: np.ndarray, white: np.ndarray, black: np.ndarray, crosstalk: np.ndarray
) -> np.ndarray:
    """The projected primaries (h, w, 3) float32 seen at each pixel, in [0, 1] up to noise.

    image, white, black : (h, w, 3) captures under a pattern, projector white and black
    crosstalk : (3, 3) camera channel × projector primary response (:func:`estimate_crosstalk`)

    ``M⁻¹ (I − B) / M⁻¹ (W − B)`` per pixel and primary: the surface colour cancels. NaN
    where the white frame gives no light in a primary.
    """
    unmix = np.linalg.inv(crosstalk).T.astype(np.float32)
    b = np.asarray(black, np.float32)
    u = (np.asarray(image, np.float32) - b) @ unmix
    w = (np.asarray(white, np.float32) - b) @ unmix
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(w > 0, u / w, np.nan).astype(np.float32)


# --- per-pixel mixing and global light ------------------------------------------------------


NETWORK_MEDIAN_MAX = 8  # up to this many values, nan_median sorts by min/max exchanges


def nan_median(stack: np.ndarray) -> np.ndarray:
    """Median over axis 0 of ``stack`` ignoring NaN; NaN where every value is NaN."""
    stack = np.asarray(stack)
    finite = np.isfinite(stack)
    n = finite.sum(axis=0)
    if len(stack) <= NETWORK_MEDIAN_MAX and np.issubdtype(stack.dtype, np.floating):
        ordered = np.where(finite, stack, np.inf).astype(stack.dtype)
        return _short_median(ordered.reshape(len(stack), -1), n.reshape(-1)).reshape(n.shape)
    ordered = np.sort(stack, axis=0)  # NaN sorts last
    lo = np.maximum((n - 1) // 2, 0)[None]
    hi = np.minimum(n // 2, len(stack) - 1)[None]
    mid = 0.5 * (np.take_along_axis(ordered, lo, 0)[0] + np.take_along_axis(ordered, hi, 0)[0])
    return np.where(n > 0, mid, np.nan)


def _short_median(values: np.ndarray, n: np.ndarray) -> np.ndarray:
    """:func:`nan_median` of ``values`` (k, m), missing values +inf, ``n`` (m,) the count of
    the others; sorted in place row by row with element-wise min/max exchanges (for a
    short ``k``, several times faster than ``np.sort`` along it; the same result for
    finite and NaN input: a −inf would count as missing here)."""
    k = len(values)
    for top in range(k - 1, 0, -1):  # bubble the largest left up to row ``top``
        for i in range(top):
            a = values[i].copy()
            np.minimum(a, values[i + 1], out=values[i])
            np.maximum(a, values[i + 1], out=values[i + 1])
    lo, hi = values[0], values[0]  # the sorted rows (n - 1) // 2 and n // 2
    for t in range(1, k):
        if 2 * t + 1 <= k:
            lo = np.where(n >= 2 * t + 1, values[t], lo)
        hi = np.where(n >= 2 * t, values[t], hi)
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _masked_box(values: np.ndarray, valid: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (h, w, c) over the valid pixels of a ``size`` box; and the count."""
    weight = valid.astype(np.float32)
    total = cv2.boxFilter(np.where(valid[..., None], values, 0.0).astype(np.float32), -1,
                          (size, size), normalize=False, borderType=cv2.BORDER_CONSTANT)
    count = cv2.boxFilter(weight, -1, (size, size), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    with np.errstate(divide="ignore", invalid="ignore"):
        return total / count[..., None], count


def estimate_mixing(
    white: np.ndarray,
    black: np.ndarray,
    coarse: Sequence[np.ndarray],
    redness: Sequence[np.ndarray],
    *,
    mask: np.ndarray,
    saturated: Sequence[np.ndarray] | None = None,
    confidence: float = MIXING_CONFIDENCE,
    smooth: int = MIXING_SMOOTH,
) -> np.ndarray:
    """Each pixel's camera response to each projector primary, (h, w, 3, 3) float32.

    white, black : (h, w, 3) captures under projector white and black
    coarse : (h, w, 3) captures of hybrid images with wide bands (the first levels)
    redness : (h, w) the band redness ``e`` of each of ``coarse`` from a first decode
        (1 red, 0 blue; e.g. with one global crosstalk matrix)
    mask : (h, w) bool lit pixels
    saturated : (h, w) bool clipped pixels of each of ``coarse`` (left out)
    confidence : a pixel serves as red (blue) in an image where ``|e − 0.5|`` reaches this
        and the band goes on ``PLATEAU_WIDTH // 2`` px either side
    smooth : box (px) over which the per-pixel fractions are averaged

    Returns ``A`` with ``A[y, x, c, k]``: camera channel ``c`` (black subtracted) under
    projector primary ``k`` alone, so that ``I − B = A p`` for projected primaries ``p``.

    Every lit pixel is inside a red band in some coarse image and inside a blue one in
    another: there ``I − B`` is the red (blue) column of ``A`` — paint × crosstalk, as the
    surface returns it (the paint acts after the crosstalk on a real surface, so one
    global matrix cannot undo it). Per pixel, the median over those images of the column
    divided by the white frame's ``W − B`` (per channel) is the primary's share of the
    white in that channel; the shares are averaged over ``smooth`` px (noise) and, where a
    pixel never sits in a confident band, taken from the view's median. The green column
    is the rest of the white: ``W − B − red − blue``.
    """
    lit, bands = _mixing_fractions(white, black, coarse, redness, mask=mask, saturated=saturated,
                                   confidence=confidence, smooth=smooth)
    red, blue = (np.where(has[..., None], mean, fallback).astype(np.float32) for mean, has, fallback in bands)
    green = 1.0 - red - blue
    mixing = np.stack([red, green, blue], axis=-1) * np.stack(lit, axis=-1)[..., None]  # (h, w, c, k)
    return mixing.astype(np.float32)


def _mixing_fractions(
    white: np.ndarray,
    black: np.ndarray,
    coarse: Sequence[np.ndarray],
    redness: Sequence[np.ndarray],
    *,
    mask: np.ndarray,
    saturated: Sequence[np.ndarray] | None = None,
    confidence: float = MIXING_CONFIDENCE,
    smooth: int = MIXING_SMOOTH,
    wanted: np.ndarray | None = None,
) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """:func:`estimate_mixing`'s white frame ``W − B`` (3 planes (h, w) float32) and, for
    the red and the blue primary, the per-pixel share of the white averaged over the band
    pixels within ``smooth`` (h, w, 3) float32, where there are any (h, w) bool, and the
    view's median share (3,) float32 for the pixels that have none: taken only when a
    pixel of ``wanted`` (h, w) bool (default: every pixel) needs it, else zeros."""
    white, black = np.asarray(white), np.asarray(black)
    lit = [np.asarray(white[..., c], np.float32) - np.asarray(black[..., c], np.float32) for c in range(3)]
    h, w = mask.shape
    floor = 1e-3 * max(max(float(p.max()) for p in lit), _EPS)
    good = mask & (lit[0] > floor) & (lit[1] > floor) & (lit[2] > floor)
    # the band pixels are lit pixels: work on those alone (row-major), one channel at a time
    at = np.flatnonzero(good)
    inv = [(1.0 / np.maximum(p.reshape(-1).take(at), floor)).astype(np.float32) for p in lit]
    black_g = [np.asarray(black[..., c]).reshape(-1).take(at).astype(np.float32) for c in range(3)]
    n = len(coarse)
    m = len(at)
    in_band = np.zeros((2, m), np.uint8)  # images where a pixel is in a band
    shares = np.full((2, n, 3 * m), np.inf, np.float32)  # band, image, (channel, pixel); inf: none
    for i, (image, e) in enumerate(zip(coarse, redness)):
        image = np.asarray(image)
        usable = good if saturated is None else good & ~saturated[i]
        d = [(image[..., c].reshape(-1).take(at).astype(np.float32) - black_g[c]) * inv[c] for c in range(3)]
        for j, band in enumerate((e > 0.5 + confidence, e < 0.5 - confidence)):
            here = _plateau(band & usable).reshape(-1).take(at)
            in_band[j] += here
            for c in range(3):
                np.copyto(shares[j, i, c * m:(c + 1) * m], d[c], where=here)
    bands = []
    for j in range(2):
        share = _short_median(shares[j], np.tile(in_band[j], 3)).reshape(3, m)
        known = np.isfinite(share[0])
        values = np.zeros((3, h * w), np.float32)
        valid = np.zeros(h * w, bool)
        values[:, at] = share  # NaN where unknown: _masked_box leaves the invalid out
        valid[at] = known
        mean, count = _masked_box(np.moveaxis(values.reshape(3, h, w), 0, -1), valid.reshape(h, w), smooth)
        has = count > 0
        if known.sum() < MIN_CROSSTALK_PIXELS:
            log.warning("mixing: only %d pixels sit in a confident %s band; assuming no "
                        "crosstalk there", int(known.sum()), ("red", "blue")[j])
            fallback = np.eye(3, dtype=np.float32)[2 * j]
        elif wanted is not None and not np.any(wanted & ~has):
            fallback = np.zeros(3, np.float32)  # no wanted pixel needs the view's median
        else:
            fallback = np.array([np.median(v[known]) for v in share], np.float32)
        bands.append((mean, has, fallback))
    return lit, bands


def _inverse3(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses (..., 3, 3) of ``a`` by cofactors, and where they exist (|det| > 0)."""
    a = np.asarray(a, np.float64)
    inverse, ok = _inverse3_planes([[a[..., i, j] for j in range(3)] for i in range(3)])
    return np.stack([np.stack(row, axis=-1) for row in inverse], axis=-2), ok


def _inverse3_planes(a: list[list[np.ndarray]]) -> tuple[list[list[np.ndarray]], np.ndarray]:
    """:func:`_inverse3` on the entries ``a[i][j]`` (...) float64 of 3 × 3 matrices; the
    inverses' entries likewise (0 where there is none), and where they exist."""
    a = [[np.ascontiguousarray(v, np.float64) for v in row] for row in a]
    cof = [[None] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(3):
            r = [k for k in range(3) if k != i]
            c = [k for k in range(3) if k != j]
            cof[i][j] = (-1) ** (i + j) * (a[r[0]][c[0]] * a[r[1]][c[1]] - a[r[0]][c[1]] * a[r[1]][c[0]])
    det = 0.0 + a[0][0] * cof[0][0] + a[0][1] * cof[0][1] + a[0][2] * cof[0][2]
    largest = np.abs(a[0][0])
    for v in (v for row in a for v in row):
        np.maximum(largest, np.abs(v), out=largest)
    ok = np.abs(det) > _EPS * largest**3
    with np.errstate(divide="ignore", invalid="ignore"):
        det = np.where(ok, det, 1.0)
        inverse = [[np.where(ok, cof[j][i] / det, 0.0) for j in range(3)] for i in range(3)]
    return inverse, ok


def pattern_shares(desc: PatternImage) -> np.ndarray:
    """Share (3,) of the projector's columns lit red, green and blue in one hybrid image."""
    labels = hybrid_pattern.band_labels(desc)
    return np.array([(labels == 0).mean(), (labels == 2).mean(), (labels == 1).mean()])


def separate_global(
    primaries_seen: Sequence[np.ndarray], shares: Sequence[np.ndarray], *, window: int = 1
) -> np.ndarray:
    """Global (indirect) light per pixel and primary (h, w, 3) from high-frequency images.

    primaries_seen : (h, w, 3) primaries ``A⁻¹ (I − B)`` seen in fine hybrid images
        (normalised to the white frame: 1 is the white's direct plus global light)
    shares : (3,) the share of the projector lit by each primary in each image
        (:func:`pattern_shares`)

    Nayar et al. (2006): under a high-frequency pattern lighting a share ``α`` of the
    scene, a pixel that is not lit directly sees only ``α G`` (``G``: the global light
    under full illumination), and every pixel is unlit in some of the fine images. Per
    primary, the smallest ``p / α`` over the images is ``G`` (a share of the white frame);
    the direct share is ``1 − G``. Some pixels are lit by a primary in all the images
    given (with the three finest hybrid levels, 1 in 16): ``window`` > 1 takes the
    smallest over that many px along x too (the global light is smooth).
    """
    ratios = [np.asarray(p, np.float32) / np.maximum(np.asarray(s, np.float32), _EPS)
              for p, s in zip(primaries_seen, shares)]
    lowest = np.min(ratios, axis=0).astype(np.float32)
    if window > 1:
        lowest = cv2.erode(lowest, np.ones((1, window), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return np.clip(lowest, 0.0, 1.0)


@dataclass(frozen=True)
class _PixelUnmixer:
    """The line signal and redness from per-pixel mixing (:func:`estimate_mixing`).

    The unconstrained primaries ``p = A⁻¹ (I − B)`` are cleaned of the global light
    (``q = (p − α G) / (1 − G)``, per primary, ``α`` the image's share of it) and then
    projected onto ``q_r + q_g + q_b = 1`` (every projector pixel shows one primary) with
    the weights of their noise (covariance ``A⁻¹ A⁻ᵀ`` for equal noise in the camera
    channels): ``q̂ = q − c (Σ q − 1)``, ``c = Σ 1 / 1ᵀ Σ 1``. Then ``g = q̂_g`` and
    ``e = (1 + q̂_r − q̂_b) / 2``.
    """

    inverse: np.ndarray  # (3, 3, h, w) float32: primary k, camera channel j
    offset: np.ndarray  # (3, h, w) float32: −A⁻¹ B
    weights: np.ndarray  # (3, h, w) float32: c
    inside: np.ndarray  # (h, w) bool, mask & invertible
    global_light: np.ndarray | None = None  # (3, h, w) float32, share of the white

    @classmethod
    def build(cls, black: np.ndarray, mixing: np.ndarray, mask: np.ndarray) -> _PixelUnmixer:
        """From the mixing (h, w, 3, 3) of :func:`estimate_mixing`."""
        mask = np.asarray(mask, bool)
        at = np.flatnonzero(mask)
        picked = np.ascontiguousarray(mixing, np.float32).reshape(mask.size, 9).take(at, axis=0)
        return cls._from_entries(black, [[picked[:, 3 * c + k] for k in range(3)] for c in range(3)], mask, at)

    @classmethod
    def from_fractions(cls, black: np.ndarray, lit: list[np.ndarray],
                       bands: list[tuple[np.ndarray, np.ndarray, np.ndarray]], mask: np.ndarray) -> _PixelUnmixer:
        """From :func:`_mixing_fractions` (its ``wanted``: ``mask``), as :meth:`build` from
        :func:`estimate_mixing`, working on the mask's pixels alone."""
        mask = np.asarray(mask, bool)
        at = np.flatnonzero(mask)
        red, blue = (
            np.where(has.reshape(-1).take(at)[:, None], mean.reshape(-1, 3).take(at, axis=0), fallback)
            .astype(np.float32)
            for mean, has, fallback in bands
        )
        green = 1.0 - red - blue
        lit = [p.reshape(-1).take(at) for p in lit]
        entries = [[share[:, c] * lit[c] for share in (red, green, blue)] for c in range(3)]
        return cls._from_entries(black, entries, mask, at)

    @classmethod
    def _from_entries(cls, black: np.ndarray, mixing: list[list[np.ndarray]], mask: np.ndarray,
                      at: np.ndarray) -> _PixelUnmixer:
        """``mixing[c][k]`` (n,) at the mask's pixels ``at`` (flat indices, row-major); the
        rest keep the "nothing there" values."""
        h, w = mask.shape
        a, ok = _inverse3_planes(mixing)
        # the rows of A⁻¹ A⁻ᵀ summed, each entry summed in matmul's order
        s = [sum((a[k][m] * a[i][m] for m in range(1, 3)), a[k][0] * a[i][0])
             for k in range(3) for i in range(3)]
        s = [s[3 * k] + s[3 * k + 1] + s[3 * k + 2] for k in range(3)]
        total = s[0] + s[1] + s[2]
        b = [np.asarray(black[..., j], np.float64).reshape(-1).take(at) for j in range(3)]
        inverse = np.zeros((3, 3, h * w), np.float32)
        offset = np.zeros((3, h * w), np.float32)
        weights = np.full((3, h * w), 1.0 / 3.0, np.float32)
        inside = np.zeros(h * w, bool)
        inside[at] = ok
        with np.errstate(divide="ignore", invalid="ignore"):
            for k in range(3):
                for j in range(3):
                    inverse[k, j, at] = a[k][j]
                offset[k, at] = -(a[k][0] * b[0] + a[k][1] * b[1] + a[k][2] * b[2])
                weights[k, at] = np.where(ok, s[k] / total, 1.0 / 3.0)
        return cls(inverse.reshape(3, 3, h, w), offset.reshape(3, h, w), weights.reshape(3, h, w),
                   inside.reshape(h, w))

    def primaries(self, image: np.ndarray) -> np.ndarray:
        """Unconstrained primaries (3, h, w) float32 ``A⁻¹ (I − B)``; 0 outside."""
        channels = [np.asarray(image[..., j], np.float32) for j in range(3)]
        out = self.offset.copy()
        for k in range(3):
            for j in range(3):
                out[k] += self.inverse[k, j] * channels[j]
        return out

    def with_global(self, global_light: np.ndarray | None) -> _PixelUnmixer:
        return replace(self, global_light=global_light)

    def line_readout(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """How the line signal ``g`` at the pixels ``(rows, cols)`` (k,) reads each camera
        channel: ``∂g / ∂I_j``, (3, k) float64 (the unmixing, global-light scaling and
        projection of :meth:`signals`, which are affine in ``I``)."""
        inverse = self.inverse[:, :, rows, cols].astype(np.float64)  # (primary, channel, k)
        if self.global_light is not None:
            inverse = inverse / np.maximum(1.0 - self.global_light[:, rows, cols], MIN_DIRECT)[:, None, :]
        weight = self.weights[1, rows, cols].astype(np.float64)
        return inverse[1] - weight * inverse.sum(axis=0)

    def signals(
        self, image: np.ndarray, shares: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Line signal ``g`` and redness ``e`` (h, w) float32 of a raw capture (h, w, 3)."""
        q = self.primaries(image)
        if self.global_light is not None and shares is not None:
            for k in range(3):
                q[k] = (q[k] - np.float32(shares[k]) * self.global_light[k]) / np.maximum(
                    1.0 - self.global_light[k], np.float32(MIN_DIRECT)
                )
        excess = q[0] + q[1] + q[2] - 1.0
        q -= self.weights * excess
        g = np.where(self.inside, q[1], 0.0).astype(np.float32)
        e = np.where(self.inside, 0.5 + 0.5 * (q[0] - q[2]), 0.5).astype(np.float32)
        return g, e


# --- line reliability ----------------------------------------------------------------------


def estimate_noise(
    white: np.ndarray, black: np.ndarray, mask: np.ndarray, *, row_step: int = 1
) -> tuple[float, float]:
    """Noise model of one capture from the view itself: ``σ²(I) = a + b (I − B)`` (DN²).

    white, black : (h, w, 3) the projector-white and -black captures (integer captures add
        the quantisation's 1/12 DN² to ``a``)
    mask : (h, w) bool lit pixels
    row_step : use every ``row_step``-th row

    ``a`` is the black frame's noise per channel (as :func:`~slscan.decode.masks.noise_sigma`,
    which measures it on the channels' maximum), squared; ``b`` (DN² per DN) the shot-noise gain, fitted through the origin to ``σ² − a`` of the
    white frame in ``NOISE_BINS`` bins of its black-subtracted level (all channels pooled),
    ``σ²`` from the median absolute deviation of horizontal neighbour differences (a
    paint edge moves the median little). Returns ``(a, b)``.
    """
    dark = np.diff(np.asarray(black[::row_step], np.float32), axis=1).ravel()
    a = float((1.4826 * np.median(np.abs(dark - np.median(dark)))) ** 2 / 2.0) if dark.size else 0.0
    w = np.asarray(white[::row_step], np.float32)
    level = w - np.asarray(black[::row_step], np.float32)
    both = (mask[::row_step, 1:] & mask[::row_step, :-1])[..., None]
    both = np.broadcast_to(both, level[:, 1:].shape)
    lv = (0.5 * (level[:, 1:] + level[:, :-1]))[both]
    diff = np.diff(w, axis=1)[both]
    if lv.size < 10 * NOISE_BINS:
        return a, 0.0
    edges = np.quantile(lv, np.linspace(0.0, 1.0, NOISE_BINS + 1))
    bins = np.clip(np.searchsorted(edges, lv, side="right") - 1, 0, NOISE_BINS - 1)
    centres, variances = [], []
    for i in range(NOISE_BINS):
        d = diff[bins == i]
        if d.size < 10:
            continue
        mad = np.median(np.abs(d - np.median(d)))
        centres.append(float(np.median(lv[bins == i])))
        variances.append(float((1.4826 * mad) ** 2 / 2.0))
    c, v = np.array(centres), np.array(variances)
    b = float(np.sum((v - a) * c) / np.sum(c * c)) if np.sum(c * c) > 0 else 0.0
    if np.issubdtype(np.asarray(black).dtype, np.integer):
        a += 1.0 / 12.0  # quantisation, 1 DN steps (a clean black frame's jitter misses it)
    return a, max(b, 0.0)


def signal_gains(signals, black: np.ndarray, *, step: float = 256.0) -> np.ndarray:
    """``∂g/∂I_c`` (3, h, w) float32: how the line signal moves with each camera channel.

    signals : ``image -> (g, e)``, affine in the image (both unmixers are)
    black : (h, w, 3) a capture to linearise about (any, the map is affine)
    """
    base = np.asarray(black, np.float32)
    g0 = signals(base)[0]
    out = np.empty((3, *g0.shape), np.float32)
    for c in range(3):
        probe = base.copy()
        probe[..., c] += np.float32(step)
        out[c] = (signals(probe)[0] - g0) / np.float32(step)
    return out


def line_axis_sigma(
    g: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
    g_sigma: np.ndarray,
    *,
    radius: int = PROMINENCE_RADIUS,
) -> np.ndarray:
    """Expected standard deviation (camera px) of each line sample's sub-pixel axis.

    g : (h, w) the line signal the maxima were found in
    rows, cols : (k,) integer maxima
    g_sigma : (h, w) the noise standard deviation of ``g`` (same units)

    The line is modelled as a Gaussian ``f(i) = A exp(−(i − δ)² / (2 s²))`` above the
    higher of the band minima within ``radius`` px either side (as :func:`find_line_peaks`),
    fitted through the three samples around the maximum: width ``s`` (px) from the
    curvature of ``ln f`` (clipped to 0.5..3 px), offset ``δ`` from the maximum ``c``, and
    amplitude ``A``. The three-point Gaussian estimator's offset is
    ``½ (t₋₁ − t₁) / (t₋₁ − 2 t₀ + t₁)`` with ``tᵢ = ln f(c + i)``; to first order in the
    noise ``σᵢ`` of each sample this gives
    ``σ_x² = s⁴ [(δ − ½)² σ₋₁² / f₋₁² + 4 δ² σ₀² / f₀² + (δ + ½)² σ₁² / f₁²]``; for a
    centred line (``δ = 0``, equal noise) ``σ_x = s² σ / (√2 A e^(−1/(2 s²)))``, about
    ``σ / A`` px for ``s`` 0.6..1 px (width over SNR). The other estimators are within a
    small factor of it. Non-positive amplitudes give ``inf``.
    """
    rows = np.asarray(rows, np.intp)
    cols = np.asarray(cols, np.intp)
    f = _window(g, rows, cols, radius).astype(np.float64)
    floor = np.maximum(f[:, :radius].min(axis=1), f[:, radius + 1 :].min(axis=1))
    amp = f[:, radius] - floor
    t = np.log(np.maximum(f[:, radius - 1 : radius + 2] - floor[:, None], _EPS))
    curvature = t[:, 0] - 2.0 * t[:, 1] + t[:, 2]
    noise = _window(g_sigma, rows, cols, 1).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        fitted = curvature < -_EPS
        s = np.where(fitted, 1.0 / np.sqrt(np.maximum(-curvature, _EPS)), 3.0)
        s = np.clip(s, 0.5, 3.0)
        delta = np.where(fitted, np.clip(0.5 * (t[:, 0] - t[:, 2]) / curvature, -1.0, 1.0), 0.0)
        i = np.arange(-1.0, 2.0)[None, :]
        # the model's samples over its amplitude, and each one's weight in the offset
        shape = np.exp(-((i - delta[:, None]) ** 2 - delta[:, None] ** 2) / (2.0 * (s * s)[:, None]))
        weight = np.stack([delta - 0.5, -2.0 * delta, delta + 0.5], axis=1)
        sigma = s * s * np.sqrt(((weight * noise / shape) ** 2).sum(axis=1)) / amp
    return np.where(amp > 0, sigma, np.inf)


# --- indexing ------------------------------------------------------------------------------


def _interp_row(values: np.ndarray, rows: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Linear interpolation of ``values`` (h, w) along x at (rows, x), clamped to the image."""
    w = values.shape[1]
    x = np.clip(x, 0.0, w - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.intp), w - 2) if w > 1 else np.zeros(len(x), np.intp)
    t = (x - x0).astype(np.float32)
    v0 = values[rows, x0]
    v1 = values[rows, np.minimum(x0 + 1, w - 1)]
    return v0 + t * (v1 - v0)


def _region_lines(desc: PatternImage) -> tuple[np.ndarray, np.ndarray]:
    """Line index and projector column (n_regions,) of each region of ``desc``, left to right."""
    level = int(desc.params["level"])
    try:
        regions = sorted((int(a), int(b)) for a, b in desc.params["regions"])
        lines = [(int(i), int(c)) for i, c in desc.params["lines"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise SlscanError(f"pattern {desc.id!r}: malformed hybrid description ({exc})") from None
    if len(regions) != 2 ** (level - 1) or len(lines) != len(regions):
        raise SlscanError(
            f"pattern {desc.id!r}: level {level} needs {2 ** (level - 1)} regions and lines, "
            f"the description has {len(regions)} regions and {len(lines)} lines"
        )
    index = np.full(len(regions), -1, np.int64)
    column = np.full(len(regions), -1, np.int64)
    starts = np.array([a for a, _ in regions])
    for i, c in lines:
        r = int(np.searchsorted(starts, c, side="right")) - 1
        if r < 0 or not regions[r][0] <= c < regions[r][1] or index[r] >= 0:
            raise SlscanError(
                f"pattern {desc.id!r}: line {i} at column {c} is not alone in a region"
            )
        index[r], column[r] = i, c
    return index, column


def order_consistent(
    row: np.ndarray,
    x: np.ndarray,
    column: np.ndarray,
    *,
    tolerance: float,
    max_gap: float = MAX_NEIGHBOUR_GAP,
) -> np.ndarray:
    """Which samples agree with their neighbours along the row, (k,) bool.

    row, x, column : (k,) samples sorted by row, then x; ``column`` in projector px
    tolerance : projector px a sample may miss the prediction by
    max_gap : camera px beyond which samples of a row are not compared

    Along a row the projector column is a smooth, increasing function of x. Each sample is
    predicted linearly from pairs of its neighbours (two before, one before and one after,
    two after); it is kept when one prediction lands within ``tolerance``, so a wrongly
    indexed neighbour cannot condemn a good sample. A sample with a single neighbour is
    kept when the two increase together at a plausible slope; one with none is dropped.
    """
    k = len(row)
    if k == 0:
        return np.zeros(0, bool)
    row = np.asarray(row)
    x = np.asarray(x, np.float64)
    column = np.asarray(column, np.float64)
    idx = np.arange(k)

    def neighbour(offset: int) -> tuple[np.ndarray, np.ndarray]:
        j = np.clip(idx + offset, 0, k - 1)
        ok = (
            (idx + offset >= 0)
            & (idx + offset < k)
            & (row[j] == row)
            & (np.abs(x[j] - x) <= max_gap)
        )
        return j, ok

    near = {o: neighbour(o) for o in (-2, -1, 1, 2)}
    near[-2] = (near[-2][0], near[-2][1] & near[-1][1])
    near[2] = (near[2][0], near[2][1] & near[1][1])
    keep = np.zeros(k, bool)
    checked = np.zeros(k, bool)
    for a, b in ((-2, -1), (-1, 1), (1, 2)):
        (ja, oka), (jb, okb) = near[a], near[b]
        dx = x[jb] - x[ja]
        ok = oka & okb & (dx > 0.5) & (column[jb] > column[ja])
        with np.errstate(divide="ignore", invalid="ignore"):
            pred = column[ja] + (column[jb] - column[ja]) * (x - x[ja]) / dx
        checked |= ok
        keep |= ok & (np.abs(pred - column) <= tolerance)
    # samples with a single comparable neighbour: monotonic, plausible slope
    lone = ~checked
    for o in (-1, 1):
        j, ok = near[o]
        dcol = (column[j] - column) * np.sign(x[j] - x)
        slope = dcol / np.maximum(np.abs(x[j] - x), 1e-9)
        keep |= lone & ok & (dcol > 0) & (slope < MAX_LONE_SLOPE)
    return keep


# --- decoding ------------------------------------------------------------------------------


def _check_inputs(
    white: np.ndarray,
    black: np.ndarray,
    images: Sequence[np.ndarray] | Mapping[str, np.ndarray],
    descs: Sequence[PatternImage],
    names: Sequence[str] | None,
    where: str,
) -> tuple[list[int], list[str]]:
    """Validate the descriptions, levels and flat frames; return the level order (indices
    into ``descs``) and the images' names in that order. The pattern images themselves are
    checked as they are used (:func:`~slscan.decode.masks.like_white`), so they may still be loading."""
    if isinstance(images, Mapping):
        missing = [d.id for d in descs if d.id not in images]
        if missing:
            raise SlscanError(f"{where}no image of hybrid pattern(s) {', '.join(missing)}")
    elif len(images) != len(descs):
        raise SlscanError(
            f"{where}{len(images)} hybrid images for {len(descs)} pattern descriptions"
        )
    names = list(names) if names is not None else [d.id for d in descs]
    if len(names) != len(descs):
        raise SlscanError(f"{where}{len(names)} names for {len(descs)} pattern descriptions")
    if not descs:
        raise SlscanError(f"{where}no hybrid pattern images to decode")
    white = np.asarray(white)
    if white.ndim != 3 or white.shape[2] != 3:
        raise SlscanError(
            f"{where}white image is {white.shape}: the hybrid pattern is colour-coded and needs "
            "(h, w, 3) RGB captures"
        )
    like_white(black, white, "black image", where)
    for d, name in zip(descs, names):
        if d.family != "hybrid":
            raise SlscanError(
                f"{where}{name}: pattern {d.id!r} is {d.family!r}, not a hybrid pattern"
            )
        if "level" not in d.params or "lines" not in d.params or "regions" not in d.params:
            raise SlscanError(
                f"{where}pattern {d.id!r}: hybrid description lacks level, lines or regions"
            )
    order = sorted(range(len(descs)), key=lambda i: int(descs[i].params["level"]))
    levels = [int(descs[i].params["level"]) for i in order]
    total = int(descs[order[0]].params.get("levels", len(descs)))
    if levels != list(range(1, total + 1)):
        seen = set(levels)
        missing = [k for k in range(1, total + 1) if k not in seen]
        extra = sorted({k for k in levels if levels.count(k) > 1 or not 1 <= k <= total})
        raise SlscanError(
            f"{where}hybrid images must cover levels 1..{total} once each"
            + (f"; missing level(s) {missing}" if missing else "")
            + (f"; duplicate or unexpected level(s) {extra}" if extra else "")
            + f" (got {', '.join(names[i] for i in order)})"
        )
    width = descs[order[0]].width
    for i in order:
        if descs[i].width != width:
            raise SlscanError(
                f"{where}pattern {descs[i].id!r} is {descs[i].width} px wide, expected {width}"
            )
    return order, [names[i] for i in order]


def paint_edge_mode(value: bool | str) -> str:
    """The ``paint_edges`` setting as one of :data:`PAINT_EDGE_MODES` (the booleans of
    earlier recipes: True "drop", False "keep")."""
    if isinstance(value, bool):
        return "drop" if value else "keep"
    if value not in PAINT_EDGE_MODES:
        raise SlscanError(
            f"unknown paint_edges {value!r}: expected one of {', '.join(PAINT_EDGE_MODES)} (or true: drop, "
            "false: keep)"
        )
    return value


def _keep(ok: np.ndarray, cond: np.ndarray, rejected: dict[str, int], reason: str) -> np.ndarray:
    """``ok & cond``, counting under ``reason`` the samples ``cond`` rejects."""
    rejected[reason] += int(np.count_nonzero(ok & ~cond))
    return ok & cond


def _line_noise(
    gains: np.ndarray,
    image: np.ndarray,
    white: np.ndarray,
    black: np.ndarray,
    noise: tuple[float, float],
    smooth_rows: bool,
) -> np.ndarray:
    """Standard deviation (h, w) of the line signal of ``image``: the camera noise
    (``noise``, :func:`estimate_noise`) of the capture and of the white and black frames
    through the unmixing gains (:func:`signal_gains`) and the row filter.

    The line signal is a combination of ``r_c = (I_c − B_c) / (W_c − B_c)`` per camera
    channel (the white frame normalises each channel), so with ``∂g/∂I_c = G_c``:
    ``∂g/∂W_c = −G_c r_c`` and ``∂g/∂B_c = −G_c (1 − r_c)``, and
    ``σ_g² = Σ_c G_c² (σ²(I_c) + r_c² σ²(W_c) + (1 − r_c)² σ²(B_c))``. This is exact for
    the per-pixel unmixing; with one crosstalk matrix (``mixing="global"``) the white's
    term holds where the crosstalk is small."""
    a, b = noise
    a, b = np.float32(a), np.float32(b)
    var = np.zeros(gains.shape[1:], np.float32)
    for c in range(3):
        dark = np.asarray(black[..., c], np.float32)
        level = np.maximum(np.asarray(image[..., c], np.float32) - dark, 0.0)
        lit = np.maximum(np.asarray(white[..., c], np.float32) - dark, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(lit > 0, level / lit, 0.0).astype(np.float32)
        var += gains[c] * gains[c] * ((a + b * level) + r * r * (a + b * lit) + (1 - r) * (1 - r) * a)
    if smooth_rows:
        var = cv2.filter2D(var, -1, (_ROW_KERNEL * _ROW_KERNEL)[:, None], borderType=cv2.BORDER_CONSTANT)
    return np.sqrt(var)


def decode_hybrid_images(
    white: np.ndarray,
    black: np.ndarray,
    images: Sequence[np.ndarray] | Mapping[str, np.ndarray],
    descs: Sequence[PatternImage],
    *,
    estimator: str = DEFAULT_ESTIMATOR,
    min_contrast: float = DEFAULT_MIN_CONTRAST,
    min_peak: float = DEFAULT_MIN_PEAK,
    min_prominence: float = DEFAULT_MIN_PROMINENCE,
    ambiguity: float = DEFAULT_AMBIGUITY,
    min_polarity: float = DEFAULT_MIN_POLARITY,
    min_edge_ratio: float = DEFAULT_MIN_EDGE_RATIO,
    smooth_rows: bool = True,
    mixing: str = DEFAULT_MIXING,
    global_light: bool = False,
    paint_edges: bool | str = DEFAULT_PAINT_EDGES,
    paint_edge_shift: float = PAINT_EDGE_SHIFT,
    max_line_sigma: float = DEFAULT_MAX_LINE_SIGMA,
    axis_sigma: bool = False,
    crosstalk: np.ndarray | None = None,
    bit_depth: int | None = None,
    names: Sequence[str] | None = None,
    flat_names: tuple[str, str] = ("white", "black"),
    where: str = "",
) -> HybridResult:
    """Decode one view of the hybrid pattern from arrays.

    white, black : (h, w, 3) captures under projector white and black, uint8, uint16 or
        float in [0, 1]
    images : (h, w, 3) captures of the hybrid images, one per level (any order), or a
        mapping of pattern id to capture (e.g. :meth:`Session.prefetch_images
        <slscan.capture.session.Session.prefetch_images>`, still loading: each image is
        taken when its level is decoded, so decoding overlaps the reading)
    descs : their pattern descriptions (:func:`slscan.patterns.hybrid.generate`), in the
        order of ``images`` when it is a sequence
    estimator : {"centroid", "gaussian", "parabola", "blais-rioux"}, the sub-pixel line
        centre (module docstring)
    min_contrast : shadow-mask threshold, fraction of full scale
        (:func:`~slscan.decode.masks.shadow_mask`)
    min_peak, min_prominence : line detection thresholds on the normalised line signal
        (fraction of the white frame), :func:`find_line_peaks`
    ambiguity : band bits whose redness is within this of 0.5 are unreadable
    min_polarity : a line's redness one pixel left minus one pixel right must reach this
    min_edge_ratio : lines are dropped where the white frame within ``EDGE_RADIUS`` px
        along the row, or in the rows above and below, falls below this fraction of its
        value at the line (silhouette and shadow edges)
    smooth_rows : filter the line signal across rows with ``[1, 2, 1] / 4`` before finding
        maxima; a straight line keeps its centre on the middle row, the noise drops by
        about 1.6× (full-size noisy figurine, Gaussian estimator: RMS axis error 0.115 →
        0.093 px)
    mixing : {"pixel", "global"}: colour unmixing per pixel from the view's own bands
        (:func:`estimate_mixing`; holds on saturated paint), or with one crosstalk matrix
        for the view (the decoder before 2026-11)
    global_light : with ``mixing="pixel"``, estimate the global (indirect) light per pixel
        from the finest levels (:func:`separate_global`), take it out of the line signal
        and the band redness, and drop line samples where less than ``MIN_DIRECT`` of the
        white frame is direct light (off by default: without global light it costs
        accuracy, see the CHANGELOG and ``benchmarks/colour_blur.py --tables axes``)
    paint_edges : {"shift", "drop", "keep"} (True: "drop", False: "keep"), with
        ``mixing="pixel"``: what becomes of line samples where a camera channel carrying
        at least ``PAINT_EDGE_FLOOR`` of the white changes by more than ``min_edge_ratio``
        within ``EDGE_RADIUS`` px (a paint edge beside the line). "shift": dropped only
        where the paint moves the centre, i.e. where the centre read in the centre pixel's
        paint (:func:`paint_read_peaks`) is more than ``paint_edge_shift`` px from the
        ratio's; "drop": all dropped (the decoder before issue #35: every paint boundary
        costs surface); "keep": all kept. Dropped samples are counted as "paint edge"
    paint_edge_shift : camera px, the "shift" test's tolerance
    max_line_sigma : drop line samples whose expected axis standard deviation
        (:func:`line_axis_sigma`, camera px; the noise from :func:`estimate_noise`
        carried through the unmixing) exceeds this: a line the paint returns too little of
        to place (rejected as "weak line"); 0 keeps every sample
    axis_sigma : return that expected axis standard deviation of every kept sample
        (:attr:`HybridResult.axis_sigma`; costs the noise estimate and its propagation
        through the unmixing), e.g. to compare the measured error with its noise floor
    crosstalk : (3, 3) camera × projector-primary response; None estimates it from the
        captures (:func:`estimate_crosstalk`); the first guess of the bands with
        ``mixing="pixel"``
    bit_depth : {8, 16} when the values do not use their dtype's full range
    names : names of ``images`` for messages and the saturation report (default: pattern ids)
    flat_names : names of the white and black captures in the saturation report
    where : prefix for messages, e.g. the view folder

    Returns
    -------
    HybridResult

    Raises
    ------
    SlscanError
        Images of different sizes or dtypes, grey captures, or levels missing or repeated.
    """
    if estimator not in ESTIMATORS:
        raise SlscanError(
            f"unknown line estimator {estimator!r}: expected one of {', '.join(ESTIMATORS)}"
        )
    if mixing not in MIXING_MODES:
        raise SlscanError(
            f"unknown colour mixing {mixing!r}: expected one of {', '.join(MIXING_MODES)}"
        )
    if not max_line_sigma >= 0:
        raise SlscanError(f"max_line_sigma must be >= 0 camera px, got {max_line_sigma!r}")
    paint_mode = paint_edge_mode(paint_edges)
    if not paint_edge_shift >= 0:
        raise SlscanError(f"paint_edge_shift must be >= 0 camera px, got {paint_edge_shift!r}")
    prefix = f"{where}: " if where else ""
    order, names = _check_inputs(white, black, images, descs, names, prefix)
    descs = [descs[i] for i in order]
    white, black = np.asarray(white), np.asarray(black)
    full_shape = white.shape[:2]
    full_mask = shadow_mask(white, black, min_contrast=min_contrast, bit_depth=bit_depth)
    # everything below runs on the lit pixels' bounding box (outside it every signal is 0)
    crosstalk_step = max(1, full_shape[0] // CROSSTALK_ROWS)
    box = lit_bounds(full_mask, CROP_MARGIN, row_step=crosstalk_step)
    y0, x0 = box[0].start, box[1].start
    full_white = white
    white, black, mask = white[box], black[box], full_mask[box]
    h, w = mask.shape
    clipped = {
        name: saturation(image, bit_depth=bit_depth)
        for name, image in zip(flat_names, (white, black))
    }

    def image(k: int) -> np.ndarray:
        """The level-``k + 1`` capture, checked and cropped; its clipped pixels recorded.
        (``images`` may be a :class:`~slscan.fsio.Prefetched` still reading: take each
        image only when it is needed.)"""
        i = order[k]
        raw = images[descs[k].id] if isinstance(images, Mapping) else images[i]
        cropped = like_white(raw, full_white, names[k], prefix)[box]
        if names[k] not in clipped:
            clipped[names[k]] = saturation(cropped, bit_depth=bit_depth)
        return cropped

    sat_white = clipped[flat_names[0]]
    if crosstalk is None:
        coarse = [image(k) for k in range(min(CROSSTALK_LEVELS, len(descs)))]
        crosstalk = estimate_crosstalk(
            white,
            black,
            coarse,
            mask=mask,
            bit_depth=bit_depth,
            row_step=crosstalk_step,
            saturated=np.logical_or.reduce(
                [sat_white, *(clipped[n] for n in names[:CROSSTALK_LEVELS])]
            ),
        )
        del coarse
    crosstalk = np.asarray(crosstalk, np.float64)
    if crosstalk.shape != (3, 3):
        raise SlscanError(f"{prefix}crosstalk must be a (3, 3) matrix, got shape {crosstalk.shape}")

    unmixer: _Unmixer | _PixelUnmixer = _Unmixer.build(white, black, crosstalk, mask)
    shares = [pattern_shares(d) for d in descs]
    direct = None
    if mixing == "pixel":
        n_mix = min(MIXING_LEVELS, len(descs))
        coarse = [image(k) for k in range(n_mix)]
        lit, bands = _mixing_fractions(
            white, black, coarse, [unmixer.signals(c)[1] for c in coarse], mask=mask,
            saturated=[clipped[n] | sat_white for n in names[:n_mix]], wanted=mask,
        )
        del coarse
        unmixer = _PixelUnmixer.from_fractions(black, lit, bands, mask)
        del lit, bands
        if global_light and len(descs) > GLOBAL_LEVELS:
            fine = range(len(descs) - GLOBAL_LEVELS, len(descs))
            estimate = separate_global(
                [np.moveaxis(unmixer.primaries(image(k)), 0, -1) for k in fine],
                [shares[k] for k in fine],
                window=GLOBAL_WINDOW,
            )
            estimate, _ = _masked_box(estimate, unmixer.inside, GLOBAL_SMOOTH)
            estimate = np.where(unmixer.inside[..., None], np.nan_to_num(estimate), 0.0)
            unmixer = unmixer.with_global(np.ascontiguousarray(np.moveaxis(estimate, -1, 0), np.float32))
            direct = 1.0 - estimate[..., 1]
    lit = white.astype(np.float32) - black.astype(np.float32)
    white_level = np.where(mask, channel_max(lit), 0.0).astype(np.float32)
    # the edge tests below per pixel, once for every level: the white frame's lowest
    # value within EDGE_RADIUS px along the row and in the rows above and below; and where
    # no paint edge crosses a line's profile (mixing="pixel", paint_edges)
    along = np.ones((1, 2 * EDGE_RADIUS + 1), np.uint8)
    lowest_white = np.minimum(
        cv2.erode(white_level, along, borderType=cv2.BORDER_REPLICATE),
        np.minimum(white_level[np.r_[0, : h - 1]], white_level[np.r_[1:h, h - 1]]),
    )
    no_paint_edge = np.ones((h, w), bool)
    if mixing == "pixel" and paint_mode != "keep":
        for c in range(3):
            plane = np.where(mask, lit[..., c], 0.0).astype(np.float32)
            top = cv2.dilate(plane, along, borderType=cv2.BORDER_REPLICATE)
            bottom = cv2.erode(plane, along, borderType=cv2.BORDER_REPLICATE)
            no_paint_edge &= (top < PAINT_EDGE_FLOOR * white_level) | (bottom >= min_edge_ratio * top)
    if not (mixing == "pixel" and paint_mode == "shift"):
        del lit
    all_columns = np.concatenate([_region_lines(d)[1] for d in descs])
    spacing = (
        float(np.min(np.diff(np.sort(all_columns))))
        if len(all_columns) > 1
        else float(descs[0].width)
    )

    redness: list[np.ndarray] = []
    parts: list[tuple[np.ndarray, ...]] = []
    line_maps: dict[str, np.ndarray] = {}
    rejected = dict.fromkeys(
        ("sub-pixel fit", "weak line", "ambiguous bit", "edge", "polarity", "paint edge", "global"), 0
    )
    want_sigma = max_line_sigma > 0 or axis_sigma
    noise = estimate_noise(white, black, mask, row_step=crosstalk_step) if want_sigma else None
    gains: dict[tuple, np.ndarray] = {}
    n_peaks = 0
    level_samples: list[int] = []
    for k, (desc, name) in enumerate(zip(descs, names), start=1):
        raw = image(k - 1)

        def signals(im: np.ndarray, k: int = k) -> tuple[np.ndarray, np.ndarray]:
            if isinstance(unmixer, _PixelUnmixer):
                return unmixer.signals(im, shares[k - 1])
            return unmixer.signals(im)

        g_own, e = signals(raw)
        g = g_own  # g_own: before the filter across rows (paint_read_peaks filters its own windows)
        if smooth_rows:
            g = cv2.filter2D(g_own, -1, _ROW_KERNEL[:, None], borderType=cv2.BORDER_CONSTANT)
        rows, cols = find_line_peaks(g, min_peak=min_peak, min_prominence=min_prominence)
        n_peaks += len(rows)
        x, ok = subpixel_peaks(g, rows, cols, estimator=estimator)
        stays = np.ones(len(rows), bool)  # the paint does not move the centre
        if mixing == "pixel" and paint_mode == "shift":
            at = np.flatnonzero(~no_paint_edge[rows, cols])
            x_paint, ok_paint = paint_read_peaks(
                g_own, lit, unmixer.line_readout(rows[at], cols[at]), rows[at], cols[at],
                estimator=estimator, smooth_rows=smooth_rows,
            )
            stays[at] = ok_paint & (np.abs(x_paint - x[at]) <= paint_edge_shift)
        rejected["sub-pixel fit"] += int((~ok).sum())
        sigma = np.full(len(rows), np.nan)
        if noise is not None:
            key = tuple(np.round(shares[k - 1], 6)) if direct is not None else ()
            if key not in gains:
                gains[key] = signal_gains(signals, black)
            sigma = line_axis_sigma(g, rows, cols, _line_noise(gains[key], raw, white, black, noise, smooth_rows))
            if max_line_sigma > 0:
                ok = _keep(ok, sigma <= max_line_sigma, rejected, "weak line")
        lines = np.zeros((h, w), bool)  # every maximum, kept or not, for the saturation report
        for o in (-1, 0, 1):
            lines[rows, np.clip(cols + o, 0, w - 1)] = True
        line_maps[name] = lines

        region = np.zeros(len(rows), np.int64)
        for j, e_j in enumerate(redness):
            v = _interp_row(e_j, rows, x)
            ok = _keep(ok, np.abs(v - 0.5) >= ambiguity, rejected, "ambiguous bit")
            region |= (v < 0.5).astype(np.int64) << (k - 2 - j)
        # the white frame must not fall off around the line: a silhouette or shadow edge
        # truncates the line's profile and drags its centre
        ok = _keep(ok, lowest_white[rows, cols] >= min_edge_ratio * white_level[rows, cols], rejected, "edge")
        if mixing == "pixel" and paint_mode == "drop":
            # a paint edge within EDGE_RADIUS px of the line, whether it moves the centre or not
            ok = _keep(ok, no_paint_edge[rows, cols], rejected, "paint edge")
        elif mixing == "pixel" and paint_mode == "shift":
            # a paint edge across the line's profile that moves its centre (paint_read_peaks)
            ok = _keep(ok, stays, rejected, "paint edge")
        # red on the left, blue on the right
        polarity = _interp_row(e, rows, x - 1.0) - _interp_row(e, rows, x + 1.0)
        ok = _keep(ok, polarity >= min_polarity, rejected, "polarity")
        if direct is not None:
            ok = _keep(ok, direct[rows, cols] >= MIN_DIRECT, rejected, "global")
        line_index, line_column = _region_lines(desc)
        rows, cols, x, region, sigma = rows[ok], cols[ok], x[ok], region[ok], sigma[ok]
        level_samples.append(len(rows))
        sat_image = clipped[name] | sat_white
        around = _window(sat_image, rows, cols, 1).any(axis=1)
        parts.append(
            (
                rows.astype(np.int32),
                x,
                line_column[region].astype(np.float64),
                line_index[region].astype(np.int32),
                g[rows, cols].astype(np.float32),
                around,
                sigma,
            )
        )
        redness.append(e)

    row, x, column, stripe, contrast, saturated, sigma = (np.concatenate(f) for f in zip(*parts))
    order = np.lexsort((x, row))
    samples = StripeSamples(
        row[order], x[order], column[order], stripe[order], contrast[order], saturated[order]
    ).shifted(y0, x0)
    consistent = order_consistent(
        samples.row, samples.x, samples.projector_column, tolerance=spacing
    )
    rejected["order"] = int((~consistent).sum())
    log.debug(
        "%shybrid decode: %d line maxima, %d samples kept; rejected: %s",
        prefix,
        n_peaks,
        int(consistent.sum()),
        ", ".join(f"{v} {k}" for k, v in rejected.items()),
    )
    samples = samples.subset(consistent)
    sigma = sigma[order][consistent] if want_sigma else None

    codes = np.zeros((h, w), np.int64)
    readable = mask.copy()
    levels = len(redness)
    for j, e_j in enumerate(redness):
        codes |= (e_j < 0.5).astype(np.int64) << (levels - 1 - j)
        readable &= np.abs(e_j - 0.5) >= ambiguity

    report = saturation_report(clipped, mask, line_maps)
    warn_saturation(report, where=where)
    return HybridResult(
        samples=samples,
        mask=full_mask,
        codes=uncrop(np.where(readable, codes, -1).astype(np.int32), box, full_shape, -1),
        crosstalk=crosstalk,
        saturation=report,
        white=full_white,
        rejected=rejected,
        level_samples=tuple(level_samples),
        axis_sigma=sigma,
    )


def hybrid_pattern_ids(session: Session) -> tuple[str, str, list[PatternImage]]:
    """The white and black frames' ids and the hybrid descriptions (level order) of ``session``."""
    white, black = session.flat_frame_ids("hybrid decoding")
    descs = sorted(
        (p for p in session.patterns if p.family == "hybrid"),
        key=lambda p: p.params.get("level", 0),
    )
    if not descs:
        raise SlscanError(f"{session.root}: the pattern set has no hybrid patterns")
    return white, black, descs


def decode_hybrid(
    session: Session,
    view: ViewRecord | str,
    *,
    estimator: str = DEFAULT_ESTIMATOR,
    min_contrast: float = DEFAULT_MIN_CONTRAST,
    **options,
) -> HybridResult:
    """Read and decode the hybrid-pattern images of ``view`` in ``session``.

    estimator : {"centroid", "gaussian", "parabola", "blais-rioux"}
    min_contrast : shadow-mask threshold, fraction of full scale
    options : further keywords of :func:`decode_hybrid_images`

    Raises
    ------
    SlscanError
        Grey captures; the view lacks the white, black or a hybrid image or has two images
        of one pattern; an image does not match the session (naming the file).
    """
    if isinstance(view, str):
        view = session.view(view)
    where = str(session.root / view.name)
    if session.channels != 3:
        raise SlscanError(
            f"{where}: the session's captures have {session.channels} channel(s); the hybrid "
            "pattern is colour-coded and needs RGB captures"
        )
    white_id, black_id, descs = hybrid_pattern_ids(session)

    def record(pid: str) -> ImageRecord:
        recs = [r for r in view.images if r.kind == "pattern" and r.pattern == pid]
        if not recs:
            raise SlscanError(
                f"{where}: no image of pattern {pid!r}; hybrid decoding needs one per pattern"
            )
        if len(recs) > 1:
            raise SlscanError(
                f"{where}: {len(recs)} images of pattern {pid!r} "
                f"({', '.join(r.file for r in recs)}); expected one"
            )
        return recs[0]

    flat = record(white_id), record(black_id)
    recs = [record(d.id) for d in descs]
    # read in the order decoding uses them, in the background: level k is decoded while
    # level k + 1 loads
    # in linear light: an sRGB camera's curve undone (float fractions of full scale then)
    linear = session.response != "linear"
    with session.prefetch_images(view, [*flat, *recs], linear=linear) as images:
        result = decode_hybrid_images(
            images[white_id],
            images[black_id],
            images,
            descs,
            estimator=estimator,
            min_contrast=min_contrast,
            bit_depth=None if linear else session.bit_depth,
            names=[r.file for r in recs],
            flat_names=(flat[0].file, flat[1].file),
            where=where,
            **options,
        )
    if linear:  # colour and clipping downstream from the capture as the camera saved it
        result = replace(result, white=session.read_image(view, flat[0]))
    return result


def decode(session: Session, view: ViewRecord | str, config) -> FamilyDecode:
    """The hybrid family's decode for a range map (:mod:`slscan.decode.family`): the green
    lines' sub-pixel axes, with ``config``'s estimator, colour unmixing, global-light and
    paint-edge settings."""
    res = decode_hybrid(
        session, view, estimator=config.estimator, mixing=config.mixing, global_light=config.global_light,
        paint_edges=config.paint_edges, paint_edge_shift=config.paint_edge_shift,
        max_line_sigma=config.max_line_sigma,
    )
    levels = len(hybrid_pattern_ids(session)[2])
    return FamilyDecode(samples=res.samples, mask=res.mask, codes=res.codes, code_max=2**levels,
                        saturated=saturation(res.white), white=res.white,
                        stats={PAINT_EDGE_METRIC: float(res.rejected.get("paint edge", 0))})
