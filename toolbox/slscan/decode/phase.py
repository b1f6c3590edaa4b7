"""Decode phase-shifting captures to a sub-pixel projector column (and row) at every pixel.

Per axis (projector columns, rows) and fringe period, the N captures ``I_k = A + B cos(phi +
shift_k)`` are fitted by least squares (any N >= 3 known shifts): the wrapped phase
``phi``, the modulation ``B`` and the offset ``A`` at every pixel; with N >= 4 the fit's
residual measures the image noise (and any fringe distortion) directly. ``phi`` gives the
projector coordinate modulo the period; the fringe order comes from the set's Gray code
(the cell of one period, read against its inverse images), its complementary bit (read
mid-period, where the Gray code is certain), or from several periods together
(temporal unwrapping: the order whose coordinates best agree across all periods,
weighted by each period's precision; for periods whose beat of the beats covers the
projector this is the heterodyne answer, and more robust to noise than beats of beats).

Pixels are kept where white minus black clears ``min_contrast`` and the fringe
modulation clears both ``min_modulation`` of it and the noise; the unwrapped coordinates
are then checked against their neighbours: a pixel one period off most neighbours is
corrected by a period, one that agrees with none is rejected, and both are counted
(:class:`AxisDecode`). With several periods, each is unwrapped and those disagreeing by
more than a quarter of the shortest period are rejected; the coordinate kept is their
precision-weighted mean.

References
----------
.. [1] Srinivasan, Liu, Halioua, Applied Optics 23(18), 1984 (N-step phase shifting).
.. [2] Sansoni, Carocci, Rodella, Applied Optics 38(31), 1999 (Gray code + phase shift).
.. [3] Zhang, Su, Xiang, Liu, "Absolute phase retrieval methods for digital fringe
   projection profilometry: a review", Optics and Lasers in Engineering 107, 2018
   (complementary Gray code, multi-frequency temporal unwrapping).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from slscan.capture.session import Session, ViewRecord
from slscan.decode.family import FamilyDecode, ProjectorConstraints
from slscan.decode.masks import (
    channel_max,
    channel_mean,
    full_scale,
    lit_bounds,
    noise_sigma,
    uncrop,
)
from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError
from slscan.patterns import PatternImage
from slscan.patterns.graycode import inverse_gray
from slscan.patterns.phase import joint_period

log = logging.getLogger(__name__)

MIN_CONTRAST = 0.03
"""White minus black must exceed this fraction of full scale (shadow, background), as for Gray code."""
MIN_MODULATION = 0.15
"""The fringe amplitude ``2 B`` must exceed this share of white minus black: defocus,
subsurface scattering and global light lower it; below, the phase is mostly noise."""
NOISE_SIGMAS = 4.0
"""``B`` must exceed this many standard deviations of its own estimate (the image noise
times ``sqrt(2 / N)``): a phase error of at most about 1 / 4 radian."""
MIN_ORDER_MARGIN = 9.0
"""Temporal unwrapping: the best fringe order's chi-square must beat the runner-up's by
this much (three standard deviations), or the pixel is left out as ambiguous."""
CONSISTENCY_RADIUS = 2
"""Half-size (px) of the window whose unwrapped coordinates each pixel is checked against."""
CONSISTENCY_SLOPE = 1.5
"""Projector px per camera px that neighbouring coordinates may differ by (steep surfaces)."""
EDGE_PX = 1
"""Pixels this close to the rim of the decoded region are dropped: at a silhouette or a
depth step a pixel sees two surfaces, its phase is the lit one's but its ray is the pixel
centre's, which may miss that surface (on the virtual tile at full size 0.7 % of the
points were more than 0.5 mm off, all on the rim)."""
STEP_FACTOR = 6.0
"""A depth step: neighbouring pixels whose projector columns differ by more than this many
times the view's median difference between neighbours (and at least :data:`MIN_STEP_PX`)."""
MIN_STEP_PX = 3.0
LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114], np.float32)
GAMMA_EVIDENCE = 0.03
"""``projector_gamma="auto"`` corrects for the exponent it estimates only when that lowers
the fitted phases' N-th harmonic (0: evenly spread, 1: all alike) by more than this: a
linear rig, or fringes pre-distorted for the projector, decode exactly as without; the
kamino410 captures (3 steps, a display without gamma correction) measure 0.40-0.44 as
described and 0.01-0.03 at their estimate."""
GAMMA_SAMPLE = 25_000
"""Pixels (well-modulated, drawn evenly) ``projector_gamma="auto"`` estimates on: the
harmonic's level to about 0.006, a fifth of :data:`GAMMA_EVIDENCE`."""


# --- the pattern set ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Fringes:
    """The N images of one period along one axis.

    period, origin : projector px; ids : pattern ids in shift order; shifts : radians
    gamma : the response the fringes were pre-distorted for
    """

    period: float
    origin: float
    ids: tuple[str, ...]
    shifts: tuple[float, ...]
    gamma: float = 1.0


@dataclass(frozen=True)
class GrayCode:
    """The Gray code of one axis: ``bits`` (pattern, inverse or None), most significant first.

    cell, origin : projector px per code and where code 0 starts
    complementary : the extra bit (pattern, inverse or None) of cells ``cell / 2``, or None
    """

    bits: tuple[tuple[str, str | None], ...]
    cell: float
    origin: float
    complementary: tuple[str, str | None] | None = None


@dataclass(frozen=True)
class AxisSet:
    """What a pattern set holds along one projector axis: its fringes and its Gray code."""

    axis: str
    size: int
    fringes: tuple[Fringes, ...]
    gray: GrayCode | None

    @property
    def method(self) -> str:
        """{"complementary", "gray", "heterodyne"}: how the fringe order is found."""
        if self.gray is None:
            return "heterodyne"
        return "complementary" if self.gray.complementary is not None else "gray"

    def ids(self) -> list[str]:
        """Every pattern id the axis uses, fringes first."""
        out = [i for f in self.fringes for i in f.ids]
        if self.gray is not None:
            pairs = list(self.gray.bits) + ([self.gray.complementary] if self.gray.complementary else [])
            out += [i for pair in pairs for i in pair if i is not None]
        return out


def phase_sets(descs: Sequence[PatternImage], *, where: str = "") -> dict[str, AxisSet]:
    """The phase-shifting sets of a pattern set, by axis ("columns", "rows").

    Raises
    ------
    SlscanError
        A period with fewer than 3 steps or two images of one step, a Gray bit missing or
        without its inverse, a missing complementary partner, a Gray cell that unwraps no
        period, or periods that cannot be unwrapped without Gray code (naming the patterns).
    """
    where = f"{where}: " if where else ""
    out = {}
    for axis in ("columns", "rows"):
        mine = [d for d in descs if d.family == "phase" and d.axis == axis]
        if not mine:
            continue
        size = mine[0].width if axis == "columns" else mine[0].height
        sines: dict[tuple[float, float], list[PatternImage]] = {}
        grays: dict[tuple[int, bool, bool], PatternImage] = {}
        cells = set()
        for d in mine:
            p = d.params
            try:
                if p["kind"] == "sine":
                    key3 = (float(p["period"]), float(p.get("origin", 0.0)), float(p.get("gamma", 1.0)))
                    sines.setdefault(key3, []).append(d)
                elif p["kind"] == "gray":
                    key = (int(p["bit"]), bool(p.get("inverse", False)), bool(p.get("complementary", False)))
                    if key in grays:
                        raise SlscanError(f"{where}patterns {grays[key].id!r} and {d.id!r} both show {axis} Gray "
                                          f"bit {key[0]}{' (inverse)' if key[1] else ''}")
                    grays[key] = d
                    cells.add((float(p["cell"]) * (2 if key[2] else 1), float(p.get("origin", 0.0)),
                               int(p["bits"]) - (1 if key[2] else 0)))
                else:
                    raise SlscanError(f"{where}pattern {d.id!r}: unknown phase image kind {p['kind']!r}")
            except KeyError as exc:
                raise SlscanError(f"{where}pattern {d.id!r}: phase description lacks {exc.args[0]!r}") from None
        fringes = []
        for (period, origin, _), group in sorted(sines.items(), key=lambda kv: (-kv[0][0], kv[0][2])):
            if len(group) < 3:
                raise SlscanError(
                    f"{where}{axis} fringes of period {period:g} px have {len(group)} image(s) "
                    f"({', '.join(d.id for d in group)}); N-step phase shifting needs at least 3"
                )
            group = sorted(group, key=lambda d: float(d.params["shift"]))
            shifts = [float(d.params["shift"]) for d in group]
            wrapped = np.mod(np.asarray(shifts), 2 * np.pi)
            if len(np.unique(np.round(wrapped, 6))) < len(shifts):
                raise SlscanError(f"{where}{axis} fringes of period {period:g} px repeat a phase shift "
                                  f"({', '.join(d.id for d in group)})")
            fringes.append(Fringes(period, origin, tuple(d.id for d in group), tuple(shifts),
                                   float(group[0].params.get("gamma", 1.0))))
        if not fringes:
            raise SlscanError(f"{where}the {axis} phase patterns hold Gray code but no fringes")
        gray = None
        if grays:
            if len(cells) != 1:
                raise SlscanError(f"{where}{axis} Gray-code images disagree on their cell, origin or bits: {sorted(cells)}")
            cell, origin, nbits = cells.pop()
            bits = []
            for b in range(nbits):
                pat = grays.get((b, False, False))
                if pat is None:
                    raise SlscanError(f"{where}{axis} Gray-code bit {b} of {nbits} is missing: the fringe order "
                                      "needs every bit")
                inv = grays.get((b, True, False))
                bits.append((pat.id, None if inv is None else inv.id))
            if any(i is None for _, i in bits) and not all(i is None for _, i in bits):
                raise SlscanError(f"{where}{axis} Gray-code bits come with and without inverse images: "
                                  "expected all or none")
            comp = None
            extra = [k for k in grays if k[2]]
            if extra:
                pat = grays.get((nbits, False, True))
                if pat is None:
                    raise SlscanError(f"{where}{axis} complementary Gray bit has an inverse but no pattern")
                inv = grays.get((nbits, True, True))
                if (inv is None) != (bits[0][1] is None):
                    raise SlscanError(f"{where}{axis} complementary Gray bit {pat.id!r}: its inverse is "
                                      f"{'missing' if inv is None else 'there but the other bits have none'}")
                comp = (pat.id, None if inv is None else inv.id)
            gray = GrayCode(tuple(bits), cell, origin, comp)
            first = fringes[0].period
            if not (abs(cell - first) < 1e-6 * first or cell <= first / 2):
                raise SlscanError(
                    f"{where}{axis} Gray code of {cell:g} px cells cannot unwrap fringes of {first:g} px: "
                    "the cell must be one period, or at most half of it"
                )
        elif len(fringes) == 1:
            raise SlscanError(
                f"{where}{axis} fringes of one period ({fringes[0].period:g} px) and no Gray code: no way to "
                "unwrap the phase (add Gray code, or fringes of other periods)"
            )
        elif joint_period([f.period for f in fringes]) < size:
            raise SlscanError(
                f"{where}{axis} periods {', '.join(f'{f.period:g}' for f in fringes)} repeat together every "
                f"{joint_period([f.period for f in fringes]):.0f} px, less than the projector's {size} px: "
                "no way to unwrap the phase without Gray code"
            )
        out[axis] = AxisSet(axis, size, tuple(fringes), gray)
    return out


# --- the fit -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PhaseFit:
    """The least-squares fit of ``I_k = A + B cos(phase + shift_k)`` at every pixel.

    phase : (h, w) float32 wrapped phase in [0, 2 pi); amplitude B, offset A : (h, w) float32
    residual : (h, w) float32 sum of squared residuals (0 for N = 3)
    steps : N
    """

    phase: np.ndarray
    amplitude: np.ndarray
    offset: np.ndarray
    residual: np.ndarray
    steps: int


def fit_phase(images: Iterable[np.ndarray], shifts: Sequence[float]) -> PhaseFit:
    """Fit the wrapped phase, modulation and offset of N >= 3 phase-shifted images.

    images : N (h, w) float arrays (any linear unit), in the order of ``shifts``; consumed
        one at a time (a generator keeps memory to a few frames)
    shifts : radians, at least three distinct modulo 2 pi
    """
    shifts = np.asarray(shifts, np.float64)
    m = np.stack([np.ones_like(shifts), np.cos(shifts), -np.sin(shifts)], axis=1)  # (N, 3)
    gram = m.T @ m
    if np.linalg.cond(gram) > 1e8:
        raise SlscanError(f"phase shifts {np.round(shifts, 3).tolist()} do not determine a phase")
    sums: list = [None, None, None]
    square = None
    n = 0
    for k, image in enumerate(images):
        image = np.asarray(image, np.float32)
        for j in range(3):
            term = image if m[k, j] == 1 else np.float32(m[k, j]) * image
            sums[j] = term.copy() if sums[j] is None and term is image else term if sums[j] is None \
                else np.add(sums[j], term, out=sums[j])
        square = image * image if square is None else np.add(square, image * image, out=square)
        n += 1
    if n != len(shifts):
        raise SlscanError(f"phase fit: {n} images for {len(shifts)} shifts")
    inv = np.linalg.inv(gram).astype(np.float32)
    offset, c, s = (sum(inv[i, j] * sums[j] for j in range(3)) for i in range(3))
    residual = square - (offset * sums[0] + c * sums[1] + s * sums[2])
    np.maximum(residual, 0, out=residual)
    phase = np.arctan2(s, c)
    phase[phase < 0] += np.float32(2 * np.pi)
    return PhaseFit(phase.astype(np.float32), np.hypot(c, s).astype(np.float32), offset.astype(np.float32),
                    residual.astype(np.float32), n)


# --- unwrapping ---------------------------------------------------------------------------------


def gray_order(code_bits: Sequence[np.ndarray]) -> np.ndarray:
    """The cell index (int32) of Gray-code bits read at each pixel (most significant first)."""
    code = np.zeros(code_bits[0].shape, np.int64)
    for bit in code_bits:
        code = (code << 1) | bit.astype(np.int64)
    return inverse_gray(code).astype(np.int32)


def unwrap_with_gray(phase: np.ndarray, fringes: Fringes, gray: GrayCode, order: np.ndarray,
                     fine_order: np.ndarray | None = None) -> np.ndarray:
    """Projector coordinate (h, w) float64 from a wrapped ``phase`` and the Gray code's cell
    index ``order`` (and, for a complementary code, the index ``fine_order`` of all its
    bits: cells of half a period).

    A cell of one period: mid-period the cell index names the period; within a quarter
    period of its ends, where the cell edge and the phase wrap fall together, the
    complementary code's ``(fine_order + 1) // 2`` (which changes mid-period) does, or
    without it the cell index still does, and a pixel whose code and phase disagree there
    is left to the neighbour check. A cell of at most half a period: its centre is within
    a quarter period of the truth, and picks the period.
    """
    period = fringes.period
    frac = phase.astype(np.float64) / (2 * np.pi)
    estimate = gray.origin + gray.cell * (order + 0.5)
    if abs(gray.cell - period) < 1e-6 * period and fine_order is not None:
        shifted = gray.origin + gray.cell * ((fine_order + 1) // 2)
        # position within the cell the phase implies (the cell and the fringes share one period)
        t = np.mod(fringes.origin + period * frac - gray.origin, period) / period
        estimate = np.where((t >= 0.25) & (t < 0.75), estimate, shifted)
    k = np.rint((estimate - fringes.origin) / period - frac)
    return fringes.origin + period * (k + frac)


def unwrap_from(estimate: np.ndarray, phase: np.ndarray, fringes: Fringes) -> np.ndarray:
    """Coordinate of ``fringes``' phase in the period nearest a coarser ``estimate`` (px)."""
    frac = phase.astype(np.float64) / (2 * np.pi)
    k = np.rint((estimate - fringes.origin) / fringes.period - frac)
    return fringes.origin + fringes.period * (k + frac)


def reorder_by_periods(per: list[np.ndarray], phases: Sequence[np.ndarray], fringes: Sequence[Fringes],
                       gray: GrayCode, idx: np.ndarray, shape: tuple[int, int], *,
                       radius: int = CONSISTENCY_RADIUS) -> tuple[list[np.ndarray], int]:
    """Undo a Gray-code cell misread at a cell edge, where the periods and the neighbours say so.

    With a Gray cell of one period (the longest) and no complementary bit, the cell edges
    fall on that period's phase wraps: a camera pixel on an edge may read the next cell,
    and the longest period's coordinate is then one period off (the phase puts it near the
    far edge of the cell read); the other periods, unwrapped in turn from it, then disagree
    by a fraction of their period. Where the periods' coordinates ``per`` (each (n,) at
    the flat pixel indices ``idx`` of an image of ``shape``, the longest first) disagree by
    a quarter of the shortest period or more and the longest lies within a quarter cell of
    an edge, its order is moved by one back across that edge and the others are unwrapped
    again; the move is kept when they then agree, and the mean of the neighbours whose
    periods agree (within ``radius`` px) is nearer the moved coordinate than the unmoved
    one, by less than a quarter period. (Agreeing alone says little: two periods in a 3:2
    ratio disagree by a fraction of a period that some move always undoes.) A pixel
    mid-cell is left alone: its code is wrong, not at an edge. Returns the coordinates and
    the number of pixels moved.
    """
    shortest = min(f.period for f in fringes)
    spread = np.max(per, axis=0) - np.min(per, axis=0)
    good = spread < shortest / 4
    where = np.mod((per[0] - gray.origin) / gray.cell, 1.0)
    move = np.where(where >= 0.75, -1.0, np.where(where < 0.25, 1.0, 0.0))  # back across the edge it is near
    bad = np.flatnonzero(~good & (move != 0))
    if bad.size == 0:
        return per, 0
    moved = [per[0][bad] + move[bad] * fringes[0].period]
    for ph, f in zip(phases[1:], fringes[1:]):
        moved.append(unwrap_from(moved[-1], ph[bad], f))
    agree = (np.max(moved, axis=0) - np.min(moved, axis=0)) < shortest / 4
    values = np.zeros(shape[0] * shape[1], np.float32)
    weight = np.zeros(shape[0] * shape[1], np.float32)
    values[idx[good]] = per[0][good]
    weight[idx[good]] = 1
    size = (2 * radius + 1, 2 * radius + 1)
    total = cv2.boxFilter(values.reshape(shape), -1, size, normalize=False).ravel()[idx[bad]]
    count = cv2.boxFilter(weight.reshape(shape), -1, size, normalize=False).ravel()[idx[bad]]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count >= 3, total / count, np.nan)
    near = np.abs(moved[0] - mean)
    keep = agree & (near < np.abs(per[0][bad] - mean)) & (near < fringes[0].period / 4)
    out = [p.copy() for p in per]
    for i in range(len(out)):
        out[i][bad[keep]] = moved[i][keep]
    return out, int(keep.sum())


def unwrap_temporal(phases: Sequence[np.ndarray], fringes: Sequence[Fringes], sigmas: Sequence[np.ndarray],
                    size: int, *, chunk: int = 1 << 16) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates from several periods' wrapped phases, without Gray code.

    Every period of the finest fringes across ``[0, size)`` is a candidate; each other
    period's phase says how far (px, wrapped to half its period) the candidate is from
    its nearest fringe of the same phase, and the candidate with the least
    ``sum(distance**2 / (sigma_finest**2 + sigma**2))`` (a chi-square) wins.

    phases : per period (n,) wrapped phases; sigmas : per period (n,) standard deviation
    (px) of its coordinate. Returns the (n,) coordinates of the finest period at the chosen
    order and the (n,) margin: the runner-up's chi-square minus the winner's (small:
    ambiguous; infinite when there is one candidate).
    """
    ref = int(np.argmin([f.period for f in fringes]))
    fr = fringes[ref]
    n = len(phases[ref])
    orders = np.arange(-1, math.ceil(size / fr.period) + 1, dtype=np.float64)
    best = np.empty(n)
    margin = np.empty(n)
    for start in range(0, n, chunk):
        sl = slice(start, min(n, start + chunk))
        cand = fr.origin + fr.period * (orders[None, :] + phases[ref][sl, None] / (2 * np.pi))  # (c, m)
        cost = np.zeros(cand.shape)
        for i, f in enumerate(fringes):
            if i == ref:
                continue
            there = (cand - f.origin) / f.period - phases[i][sl, None] / (2 * np.pi)
            dist = (there - np.rint(there)) * f.period
            cost += dist * dist / (sigmas[ref][sl, None] ** 2 + sigmas[i][sl, None] ** 2)
        inside = (cand >= -0.5) & (cand <= size - 0.5)
        cost = np.where(inside, cost, np.inf)
        two = np.argpartition(cost, 1, axis=1)[:, :2]
        c2 = np.take_along_axis(cost, two, axis=1)
        first = np.where(c2[:, 0] <= c2[:, 1], 0, 1)
        win = np.take_along_axis(two, first[:, None], axis=1)[:, 0]
        best[sl] = cand[np.arange(len(win)), win]
        with np.errstate(invalid="ignore"):
            margin[sl] = np.abs(c2[:, 1] - c2[:, 0])
    return best, margin


def _shift(a: np.ndarray, dy: int, dx: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    h, w = a.shape
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    return (ys, xs), (yd, xd)


def fix_orders(coord: np.ndarray, valid: np.ndarray, period: float, *, radius: int = CONSISTENCY_RADIUS,
               slope: float = CONSISTENCY_SLOPE, min_neighbours: int = 3) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Correct or reject pixels whose fringe order disagrees with their neighbours'.

    Each valid pixel counts its valid neighbours (up to ``radius`` px, Chebyshev) whose
    coordinate is within ``period / 4 + slope * d`` of its own, one period above or one
    below. A pixel that more neighbours put a period off than agree with it is moved by
    that period (an order misread at a cell edge); one with at least ``min_neighbours``
    valid neighbours of which none agrees and none is a period off is rejected.

    Returns the coordinates, the validity, and the numbers corrected and rejected
    (:func:`order_fixes` says which pixels).
    """
    coord = coord.copy()
    valid = valid.copy()
    corrected = rejected = 0
    for _ in range(2):
        agree = np.zeros(coord.shape, np.uint8)
        above = np.zeros(coord.shape, np.uint8)
        below = np.zeros(coord.shape, np.uint8)
        count = np.zeros(coord.shape, np.uint8)
        c = np.where(valid, coord, np.nan).astype(np.float32)
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dy == 0 and dx == 0:
                    continue
                there, here = _shift(c, dy, dx)
                tol = np.float32(min(period / 4 + slope * max(abs(dy), abs(dx)), 0.45 * period))
                diff = c[there] - c[here]
                ok = valid[there]
                count[here] += ok
                agree[here] += np.abs(diff) < tol
                above[here] += np.abs(diff - np.float32(period)) < tol
                below[here] += np.abs(diff + np.float32(period)) < tol
        up = valid & (above > agree) & (above >= below) & (above >= 2)
        down = valid & (below > agree) & (below > above) & (below >= 2)
        lone = valid & (count >= min_neighbours) & (agree == 0) & (above == 0) & (below == 0)
        coord[up] += period
        coord[down] -= period
        valid &= ~lone
        corrected += int(up.sum() + down.sum())
        rejected += int(lone.sum())
        if not (up.any() or down.any() or lone.any()):
            break
    return coord, valid, corrected, rejected


def order_fixes(before: np.ndarray, after: np.ndarray, valid: np.ndarray, period: float) -> np.ndarray:
    """What :func:`fix_orders` did at each pixel: (h, w) int8, 0 nothing (or not decoded),
    +1 / -1 moved a period up / down, 2 rejected.

    before : (h, w) its input coordinates (NaN where not decoded); after, valid : its output
    """
    decoded = np.isfinite(before)
    kept = decoded & valid
    fix = np.zeros(before.shape, np.int8)
    fix[kept] = np.sign(np.rint((after[kept] - before[kept]) / period)).astype(np.int8)
    fix[decoded & ~valid] = 2
    return fix


# --- decoding one view ---------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisDecode:
    """One projector axis decoded.

    coordinate : (h, w) float64 projector px, NaN where not decoded
    periods : per period (longest first), (h, w) float64 its own unwrapped coordinate
        (NaN where not decoded): how far the periods agree is a check of the decode
    wrapped : per period (h, w) float32 wrapped phase, radians
    modulation : (h, w) float32 ``2 B / (white - black)`` of the finest period
    method : {"complementary", "gray", "heterodyne"}
    order_fix : (h, w) int8 what the neighbour check of the fringe orders did at each pixel:
        0 nothing (or not decoded), +1 / -1 moved one period up / down, 2 rejected
    counts : pixels ``lit``, ``low_modulation`` (lit, fringes too weak), ``noisy`` (lit,
        modulation under the noise limit), ``order_corrected`` and ``order_rejected`` (the
        neighbour check), ``order_from_periods`` (Gray code of one-period cells: the
        longest period's order moved by one so that the periods agree,
        :func:`reorder_by_periods`), ``periods_disagree`` (several periods more than a
        quarter of the shortest apart), ``ambiguous`` (temporal unwrapping: two orders
        nearly as good), ``valid``
    """

    coordinate: np.ndarray
    periods: tuple[np.ndarray, ...]
    wrapped: tuple[np.ndarray, ...]
    modulation: np.ndarray
    method: str
    counts: dict[str, int]
    order_fix: np.ndarray | None = None


@dataclass(frozen=True)
class PhaseResult:
    """What one view's phase-shifting images say about each camera pixel.

    column, row : (h, w) float64 projector column / row (px), NaN where not decoded; row None
        without row fringes
    mask : (h, w) bool, the column (and the row, when there are row fringes) decoded
    contrast : (h, w) float32 white minus black, fraction of full scale
    saturated : (h, w) bool, some image of the set is clipped at this pixel
    noise : standard deviation of one capture's noise, fraction of full scale
    axes : the per-axis details
    white : the white capture as read
    dn : full scale of the captures (255 for 8-bit), for noise in digital numbers
    projector_gamma : the projector exponent the phases were corrected for (the
        descriptions' ``gamma`` when they were not, 1 when those differ)
    """

    column: np.ndarray
    row: np.ndarray | None
    mask: np.ndarray
    contrast: np.ndarray
    saturated: np.ndarray
    noise: float
    axes: dict[str, AxisDecode] = field(default_factory=dict)
    white: np.ndarray | None = None
    dn: float = 255.0
    projector_gamma: float = 1.0

    @property
    def modulation(self) -> np.ndarray:
        """(h, w) float32 the column fringes' relative modulation ``2 B / (white - black)``."""
        return self.axes["columns"].modulation


class _Grey:
    """Captures as grey float32 fractions of full scale (channel mean, or luma for lossy RGB),
    cropped to ``box`` once it is set; clipping is collected from the images asked."""

    def __init__(self, luma: bool) -> None:
        self.luma = luma
        self.scale: float | None = None
        self.saturated: np.ndarray | None = None
        self.box: tuple[slice, slice] | None = None

    def _check(self, image: np.ndarray, name: str) -> np.ndarray:
        image = np.asarray(image)
        top = full_scale(image, name)
        if self.scale is None:
            self.scale = top
        elif top != self.scale:
            raise SlscanError(f"{name}: pixels are {image.dtype}, unlike the white frame's")
        return image if self.box is None else image[self.box]

    def __call__(self, image: np.ndarray, name: str = "image") -> np.ndarray:
        image = self._check(image, name)
        clipped = channel_max(image) >= self.scale
        self.saturated = clipped if self.saturated is None else self.saturated | clipped
        if image.ndim == 3 and image.shape[2] == 3 and self.luma:
            grey = np.tensordot(image.astype(np.float32), LUMA_WEIGHTS, axes=([2], [0]))
        else:
            grey = channel_mean(image)
        grey *= np.float32(1.0 / self.scale)
        return grey

    def raw(self, image: np.ndarray, name: str = "image") -> np.ndarray:
        """A grey level in the captures' own units, only to compare two captures (a Gray
        bit against its inverse): the channel sum (or the luma), no clipping collected."""
        image = self._check(image, name)
        if image.ndim == 2:
            return image
        if self.luma and image.shape[2] == 3:
            return np.tensordot(image.astype(np.float32), LUMA_WEIGHTS, axes=([2], [0]))
        wide = np.uint32 if image.dtype == np.uint16 else np.uint16 if image.dtype == np.uint8 else np.float32
        out = image[..., 0].astype(wide)
        for c in range(1, image.shape[2]):
            out += image[..., c]
        return out


def decode_phase_images(
    images: Mapping[str, np.ndarray],
    descs: Sequence[PatternImage],
    white: np.ndarray,
    black: np.ndarray,
    *,
    min_contrast: float = MIN_CONTRAST,
    min_modulation: float = MIN_MODULATION,
    noise_sigmas: float = NOISE_SIGMAS,
    consistency_radius: int = CONSISTENCY_RADIUS,
    edge: int = EDGE_PX,
    projector_gamma: float | str | None = "auto",
    luma: bool = False,
    where: str = "",
) -> PhaseResult:
    """Decode one view's phase-shifting captures into projector columns (and rows).

    Parameters
    ----------
    images : pattern id -> (h, w) or (h, w, 3) captures (uint8, uint16, or float in [0, 1]);
        each is read once, axis by axis, fringes then Gray code, so a mapping that reads
        on demand and forgets keeps memory to a few frames
    descs : the session's pattern descriptions; the ``family == "phase"`` ones are used
    white, black : captures under full white and full black
    min_contrast : white - black must exceed this fraction of full scale
    min_modulation : ``2 B`` must exceed this share of white - black...
    noise_sigmas : ...and ``B`` this many standard deviations of its estimate
    consistency_radius : px of the neighbour check of the fringe orders (0: none)
    edge : px dropped around the rim of the decoded region (0: none), see :data:`EDGE_PX`
    projector_gamma : the projector's response exponent (``slscan response``): the phase of
        fringes pre-distorted for another value is corrected for the harmonics that leaves
        (:func:`slscan.decode.phase_gamma.phase_correction`); "auto" (the default): the
        exponent estimated from these captures (:func:`slscan.decode.phase_gamma.gamma_from_phases`),
        used when it levels the phases by more than :data:`GAMMA_EVIDENCE`; None: taken as
        described
    luma : read RGB captures as their luma (lossy sessions) instead of the channel mean

    Raises
    ------
    SlscanError
        The set cannot be decoded (see :func:`phase_sets`), or an image is missing or of
        another size or type (naming the pattern).
    """
    sets = phase_sets(descs, where=where)
    if "columns" not in sets:
        raise SlscanError(f"{where + ': ' if where else ''}the pattern set has no phase-shifting column fringes")
    read = _Grey(luma)
    w_full = read(white, "white")
    b_full = read(black, "black")
    shape = w_full.shape
    contrast_full = w_full - b_full
    # quantisation floor: one digital number of the captures (linearised sRGB ones come as
    # fractions of full scale, from 8-bit files)
    dn = 255.0 if read.scale == 1.0 else float(read.scale)
    noise = max(noise_sigma(np.asarray(black)) / (read.scale or 1.0), 1.0 / dn / math.sqrt(12))
    # work on the lit region's bounding box only (windows around a lit pixel stay inside)
    box = lit_bounds(contrast_full > min_contrast, consistency_radius + edge + 2)
    read.box, read.saturated = box, read.saturated[box]
    w_img, b_img, contrast = w_full[box], b_full[box], contrast_full[box]
    lit = contrast > min_contrast

    def get(pid: str, raw: bool = False) -> np.ndarray:
        if pid not in images:
            raise SlscanError(f"{where + ': ' if where else ''}no captured image of phase pattern {pid!r}")
        image = np.asarray(images[pid])
        if image.shape[:2] != shape:
            raise SlscanError(f"{where + ': ' if where else ''}{pid}: {image.shape[1]}x{image.shape[0]} px, "
                              f"unlike the white frame's {shape[1]}x{shape[0]}")
        return read.raw(image, pid) if raw else read(image, pid)

    first: list[np.ndarray] = []  # one fringe image kept: its residual measures the noise

    def fringes(f: Fringes, keep: bool):
        for k, i in enumerate(f.ids):
            image = get(i)
            if keep and k == 0:
                first.append(image)
            yield image

    fits = {axis: [fit_phase(fringes(f, not first), f.shifts) for f in s.fringes] for axis, s in sets.items()}
    gamma = _projector_gamma(projector_gamma, sets, fits, contrast, lit, min_modulation, where)
    if gamma is not None:
        from slscan.decode.phase_gamma import phase_correction

        fits = {axis: [replace(fit, phase=phase_correction(fit.phase, f.shifts, gamma / f.gamma))
                       for fit, f in zip(fl, sets[axis].fringes)] for axis, fl in fits.items()}
    axis0 = next(iter(sets))
    noise = max(noise, fit_noise(first[0], fits[axis0][0], sets[axis0].fringes[0].shifts, lit))
    axes = {}
    for axis, s in sets.items():
        axes[axis] = _decode_axis(s, fits[axis], get, w_img, b_img, contrast, lit, noise, min_modulation,
                                  noise_sigmas, consistency_radius)
    axes = {axis: _uncrop_axis(a, box, shape) for axis, a in axes.items()}
    mask = np.isfinite(axes["columns"].coordinate)
    if "rows" in axes:
        mask &= np.isfinite(axes["rows"].coordinate)
    if edge:  # mixed pixels: a pixel on the rim of the decoded region, or beside a depth step, sees two surfaces
        mask &= ~depth_steps(axes["columns"].coordinate, mask)
        mask = cv2.erode(mask.view(np.uint8), np.ones((2 * edge + 1, 2 * edge + 1), np.uint8)).view(bool)
    row = None
    if "rows" in axes:
        row = np.where(mask, axes["rows"].coordinate, np.nan)
    column = np.where(mask, axes["columns"].coordinate, np.nan)
    own = {f.gamma for s in sets.values() for f in s.fringes}
    used = gamma if gamma is not None else (own.pop() if len(own) == 1 else 1.0)
    return PhaseResult(column, row, mask, contrast_full, uncrop(read.saturated, box, shape, False), float(noise),
                       axes, dn=dn, projector_gamma=float(used))


def _projector_gamma(option: float | str | None, sets: dict[str, AxisSet], fits: dict[str, list[PhaseFit]],
                     contrast: np.ndarray, lit: np.ndarray, min_modulation: float, where: str) -> float | None:
    """The projector exponent to correct the phases for, or None to leave them as fitted."""
    if option is None:
        return None
    if option != "auto":
        if isinstance(option, bool) or not (isinstance(option, (int, float)) and 0.2 <= option <= 5):
            raise SlscanError(f"projector_gamma must be 'auto', None or a number in [0.2, 5], got {option!r}")
        return float(option)
    from slscan.decode.phase_gamma import gamma_from_phases, unevenness

    ok = lit.copy()
    swing = np.maximum(contrast, np.float32(1e-6))
    for fl in fits.values():
        for fit in fl:
            ok &= 2 * fit.amplitude >= min_modulation * swing
    idx = np.flatnonzero(ok.ravel())
    if idx.size < 1000:
        return None
    idx = idx[:: max(1, idx.size // GAMMA_SAMPLE)]
    fringes = [f for s in sets.values() for f in s.fringes]
    phases = [fit.phase.ravel()[idx] for fl in fits.values() for fit in fl]
    own = {f.gamma for f in fringes}
    if len(own) == 1 and unevenness(phases, fringes, own.pop()) <= GAMMA_EVIDENCE:
        return None  # already as even as any correction could make them better than the evidence asks
    gamma, after, before = gamma_from_phases(phases, fringes)
    if before - after <= GAMMA_EVIDENCE:
        return None
    log.info("%sprojector gamma %.2f estimated from the fringes (phase unevenness %.3f -> %.3f); phases "
             "corrected for it", f"{where}: " if where else "", gamma, before, after)
    return gamma


def depth_steps(coord: np.ndarray, valid: np.ndarray, *, factor: float = STEP_FACTOR,
                min_step: float = MIN_STEP_PX) -> np.ndarray:
    """(h, w) bool: pixels beside a depth step, where the decoded coordinate jumps between
    neighbours by more than ``factor`` times the view's median jump (and ``min_step`` px):
    the arm in front of the body, a fold. Each such pixel integrates light from both
    surfaces (the camera's blur spreads it over a pixel or two), and its phase, a mixture
    of two fringes, is neither's; meshed, a band of them floats between the surfaces (the
    phase demo's fused figurine: 115 specks). Taken out with the rim, one pixel each side."""
    c = np.where(valid, coord, np.nan)
    dx = np.abs(np.diff(c, axis=1))
    dy = np.abs(np.diff(c, axis=0))
    both = np.concatenate([dx[np.isfinite(dx)], dy[np.isfinite(dy)]])
    if both.size == 0:
        return np.zeros(valid.shape, bool)
    limit = max(min_step, factor * float(np.median(both)))
    step = np.zeros(valid.shape, bool)
    jx, jy = dx > limit, dy > limit
    step[:, :-1] |= jx
    step[:, 1:] |= jx
    step[:-1] |= jy
    step[1:] |= jy
    return step


def _uncrop_axis(a: AxisDecode, box: tuple[slice, slice], shape: tuple[int, int]) -> AxisDecode:
    """An axis decoded on ``box`` as whole-image maps."""
    return replace(
        a, coordinate=uncrop(a.coordinate, box, shape, np.nan),
        periods=tuple(uncrop(p, box, shape, np.nan) for p in a.periods),
        wrapped=tuple(uncrop(w, box, shape, np.float32(np.nan)) for w in a.wrapped),
        modulation=uncrop(a.modulation, box, shape, np.float32(0)),
        order_fix=None if a.order_fix is None else uncrop(a.order_fix, box, shape, np.int8(0)),
    )


def fit_noise(image: np.ndarray, fit: PhaseFit, shifts: Sequence[float], where: np.ndarray) -> float:
    """Standard deviation of one capture's noise (its own unit) from the residual of the
    N-step fit of its first image (N >= 4; 0 for N = 3, which leaves no residual).

    A projector's gamma or clipping leaves a residual too, but one that follows the phase,
    smooth along the fringes; noise does not. So the residual's differences between
    neighbouring pixels along the fringes (rows or columns, whichever changes less) are
    taken, their robust spread (1.4826 MAD / sqrt(2)), over the pixels ``where``, corrected
    for the fit's own leverage (the residual of N images and 3 parameters keeps
    ``1 - 3 / N`` of the noise's variance).
    """
    n = fit.steps
    if n <= 3:
        return 0.0
    # the first image's model: A + B cos(phase + shift_0)
    resid = image - (fit.offset + fit.amplitude * np.cos(fit.phase + np.float32(shifts[0])))
    spreads = []
    for axis in (0, 1):
        d = np.diff(resid, axis=axis)
        ok = np.diff(where.astype(np.int8), axis=axis) == 0
        ok &= np.take(where, range(d.shape[axis]), axis=axis)
        values = d[ok]
        if values.size > 100:
            spreads.append(1.4826 * float(np.median(np.abs(values - np.median(values)))) / math.sqrt(2))
    if not spreads:
        return 0.0
    return min(spreads) / math.sqrt(1 - 3 / n)


def _decode_axis(s: AxisSet, fits: list[PhaseFit], get, w_img, b_img, contrast, lit, noise, min_modulation,
                 noise_sigmas, radius) -> AxisDecode:
    swing = np.maximum(contrast, np.float32(1e-6))
    ok = lit.copy()
    counts = {"lit": int(lit.sum())}
    mods = []
    for fit in fits:
        mod = 2 * fit.amplitude / swing
        strong = mod >= min_modulation
        clear = fit.amplitude >= noise_sigmas * noise * math.sqrt(2.0 / fit.steps)
        counts["low_modulation"] = counts.get("low_modulation", 0) + int((ok & ~strong).sum())
        counts["noisy"] = counts.get("noisy", 0) + int((ok & strong & ~clear).sum())
        ok &= strong & clear
        mods.append(mod)
    # each period's coordinate's standard deviation (px): period * noise / (2 pi B sqrt(N / 2))
    sigmas = [f.period * noise / (2 * np.pi * np.maximum(fit.amplitude, 1e-9) * math.sqrt(fit.steps / 2))
              for fit, f in zip(fits, s.fringes)]
    weights = [1.0 / (sg * sg) for sg in sigmas]
    idx = np.flatnonzero(ok.ravel())
    phases = [fit.phase.ravel()[idx] for fit in fits]
    per = []
    counts["ambiguous"] = counts["order_from_periods"] = 0
    if s.gray is not None:
        threshold = None if s.gray.bits[0][1] is not None else 0.5 * (w_img + b_img).ravel()[idx]

        def bit(pair) -> np.ndarray:
            if pair[1] is not None:  # against the inverse: in the captures' own units
                return get(pair[0], raw=True).ravel()[idx] > get(pair[1], raw=True).ravel()[idx]
            return get(pair[0]).ravel()[idx] > threshold

        main = [bit(pair) for pair in s.gray.bits]
        order = gray_order(main)
        fine = gray_order(main + [bit(s.gray.complementary)]) if s.gray.complementary is not None else None
        first = unwrap_with_gray(phases[0], s.fringes[0], s.gray, order, fine)
        per.append(first)
        for ph, f in zip(phases[1:], s.fringes[1:]):
            per.append(unwrap_from(per[-1], ph, f))
        first_set = s.fringes[0]
        edges_on_wraps = (abs(s.gray.cell - first_set.period) < 1e-6 * first_set.period
                          and abs(math.remainder(s.gray.origin - first_set.origin, first_set.period)) < 1e-6)
        if len(per) > 1 and fine is None and edges_on_wraps:
            per, counts["order_from_periods"] = reorder_by_periods(per, phases, s.fringes, s.gray, idx, ok.shape,
                                                                   radius=max(radius, 1))
        unwrap_period = s.fringes[0].period
    else:
        finest, margin = unwrap_temporal(phases, s.fringes, [sg.ravel()[idx] for sg in sigmas], s.size)
        ambiguous = margin < MIN_ORDER_MARGIN
        counts["ambiguous"] = int(ambiguous.sum())
        ref = int(np.argmin([f.period for f in s.fringes]))
        for i, (ph, f) in enumerate(zip(phases, s.fringes)):
            per.append(finest if i == ref else unwrap_from(finest, ph, f))
        keep = ~ambiguous
        idx, per = idx[keep], [p[keep] for p in per]
        unwrap_period = min(f.period for f in s.fringes)
    shortest = min(f.period for f in s.fringes)
    w_sel = [wt.ravel()[idx] for wt in weights]
    if len(per) > 1:
        spread = np.max(per, axis=0) - np.min(per, axis=0)
        agree = spread < shortest / 4
        counts["periods_disagree"] = int((~agree).sum())
        coord = sum(wi * pi for wi, pi in zip(w_sel, per)) / np.maximum(sum(w_sel), 1e-30)
        coord = np.where(agree, coord, np.nan)
    else:
        counts["periods_disagree"] = 0
        coord = per[0]
    full = np.full(ok.size, np.nan)
    full[idx] = coord
    full = full.reshape(ok.shape)
    valid = np.isfinite(full)
    corrected = rejected = 0
    order_fix = np.zeros(ok.shape, np.int8)
    if radius:
        before = full
        full, valid, corrected, rejected = fix_orders(before, valid, unwrap_period, radius=radius)
        order_fix = order_fixes(before, full, valid, unwrap_period)
    inside = valid & (full >= -0.5) & (full <= s.size - 0.5)
    counts["out_of_range"] = int((valid & ~inside).sum())
    full = np.where(inside, full, np.nan)
    counts.update(order_corrected=corrected, order_rejected=rejected, valid=int(inside.sum()))
    periods = []
    for p in per:
        m = np.full(ok.size, np.nan)
        m[idx] = p
        periods.append(m.reshape(ok.shape))
    finest_i = int(np.argmin([f.period for f in s.fringes]))
    return AxisDecode(full, tuple(periods), tuple(f.phase for f in fits), mods[finest_i].astype(np.float32),
                      s.method, counts, order_fix)


def phase_pattern_ids(session: Session) -> list[str]:
    """Every phase pattern id of ``session``'s set, in decoding order: every axis's
    fringes, then every axis's Gray code."""
    sets = phase_sets(session.patterns, where=str(session.root)).values()
    fringes = [i for s in sets for f in s.fringes for i in f.ids]
    return fringes + [i for s in sets for i in s.ids() if i not in set(fringes)]


def decode_phase(session: Session, view: ViewRecord | str, **options) -> PhaseResult:
    """Read and decode the phase-shifting images of ``view`` in ``session``.

    ``options`` go to :func:`decode_phase_images`. The captures are read in linear light
    (an sRGB camera's curve undone) by a background thread a couple ahead of the decoder,
    and dropped once used.
    """
    from slscan.decode.graycode import _Streamed

    view = session.view(view) if isinstance(view, str) else view
    where = str(session.root / view.name)
    white_id, black_id = session.flat_frame_ids("phase decoding")
    ids = [white_id, black_id, *phase_pattern_ids(session)]
    records = {pid: view.image_for(pid) for pid in ids}
    with _Streamed(lambda pid: session.read_image(view, records[pid], linear=True), ids) as images:
        white, black = images[white_id], images[black_id]
        options.setdefault("luma", session.lossy)
        result = decode_phase_images(images, session.patterns, white, black, where=where, **options)
    if session.response != "linear":  # colour downstream from the capture as the camera saved it
        white = session.read_image(view, records[white_id])
    return replace(result, white=white)


# --- the phase family's decoder (slscan.patterns.phase.FAMILY) -------------------------------------


def pixel_samples(result: PhaseResult) -> StripeSamples:
    """Every decoded pixel as a sample at its pixel centre, with its projector column (and
    row); ``stripe`` is the camera column, so the range map meshes the pixel grid."""
    ys, xs = np.nonzero(result.mask)
    contrast = np.clip(result.modulation[ys, xs], 0, 1).astype(np.float32)
    return StripeSamples(
        row=ys.astype(np.int32), x=xs.astype(np.float64), projector_column=result.column[ys, xs],
        stripe=xs.astype(np.int32), contrast=contrast, saturated=result.saturated[ys, xs],
        projector_row=None if result.row is None else result.row[ys, xs],
    )


def _options(config) -> dict:
    if config is None:
        return {}
    return {"min_modulation": config.phase_min_modulation, "projector_gamma": config.projector_gamma}


def _valid_share(result: PhaseResult):
    from slscan.decode.codes import ValidShare

    c = result.axes["columns"].counts
    pixels = result.mask.size
    lit = max(c["lit"], 1)
    return ValidShare(
        decoded=float(result.mask.mean()), lit=c["lit"] / pixels, noise_dn=result.noise * result.dn,
        low_contrast=(c["low_modulation"] + c["noisy"]) / lit, weak_bits=0.0,
        out_of_range=c["out_of_range"] / lit, source="decoder",
        unreliable=(c["order_rejected"] + c["periods_disagree"] + c["ambiguous"]) / lit,
    )


def codes_of(result: PhaseResult, session: Session, view: str):
    """The :class:`~slscan.decode.codes.ProjectorCodes` of a phase decode (float maps, NaN
    where not decoded)."""
    from slscan.decode.codes import ProjectorCodes

    return ProjectorCodes(view=view, column=result.column, row=result.row, mask=result.mask,
                          projector_size=tuple(session.projector_size), bits=(0, 0),
                          valid_share=_valid_share(result))


def decode(session: Session, view: ViewRecord | str, config) -> FamilyDecode:
    """The phase family's decode for a range map (:mod:`slscan.decode.family`): a sample at
    every decoded pixel, meshed on the pixel grid."""
    view = session.view(view) if isinstance(view, str) else view
    res = decode_phase(session, view, **_options(config))
    return FamilyDecode(
        samples=pixel_samples(res), mask=res.mask, codes=res.column, code_max=session.projector_size[0],
        saturated=res.saturated, white=res.white, max_gap_columns=None, features=False,
        projector_codes=codes_of(res, session, view.name), valid_share=_valid_share(res),
        maps=display_maps(res, session), stats=phase_stats(res),
    )


ORDER_FIX_LABELS = {
    1: ("fringe order corrected: one period up", (40, 255, 40, 255)),
    2: ("fringe order corrected: one period down", (0, 230, 255, 255)),
    3: ("rejected: fringe order agrees with no neighbour", (255, 0, 255, 255)),
}
"""The viewer's classes of :attr:`AxisDecode.order_fix` (+1, -1, 2 as 1, 2, 3; 0 transparent)."""


def display_maps(result: PhaseResult, session: Session) -> dict:
    """What the viewer shows of a phase decode, per axis (``columns``, ``rows``), by entity
    path under ``world/camera/image/decode`` (:class:`~slscan.decode.family.DisplayMap`):

    ``phase/wrapped/<axis>/period_<P>``
        each period's wrapped phase (radians, cyclic colours), on the lit pixels; the
        finest period drawn on top
    ``phase/unwrapped/<axis>``
        the axis's unwrapped projector coordinate (Turbo over the projector's width or
        height), before the axes' masks are joined and the rim dropped
    ``phase/modulation/<axis>``
        the finest period's relative modulation ``2 B / (white - black)`` on [0, 1], the
        per-pixel quality the decoder thresholds (``min_modulation``)
    ``phase/order_fix/<axis>``
        the pixels whose fringe order the neighbour check moved a period up or down, or
        rejected (a label map: marks at those pixels)
    """
    from slscan.decode.family import DisplayMap

    lit = result.contrast > MIN_CONTRAST
    sizes = {"columns": session.projector_size[0], "rows": session.projector_size[1]}
    sets = phase_sets(session.patterns)
    maps = {}
    for axis, a in result.axes.items():
        periods = [f.period for f in sets[axis].fringes]
        for rank, (period, wrapped) in enumerate(sorted(zip(periods, a.wrapped), key=lambda pw: -pw[0])):
            maps[f"phase/wrapped/{axis}/period_{period:g}"] = DisplayMap(
                np.where(lit, wrapped, np.float32(np.nan)), "twilight", (0.0, 2 * np.pi), draw_order=float(rank))
        maps[f"phase/unwrapped/{axis}"] = DisplayMap(a.coordinate.astype(np.float32), "turbo",
                                                     (0.0, sizes[axis] - 1.0))
        maps[f"phase/modulation/{axis}"] = DisplayMap(np.where(lit, a.modulation, np.float32(np.nan)),
                                                      "viridis", (0.0, 1.0))
        if a.order_fix is not None:
            classes = np.zeros(a.order_fix.shape, np.uint8)
            for fix, label in ((1, 1), (-1, 2), (2, 3)):
                classes[a.order_fix == fix] = label
            maps[f"phase/order_fix/{axis}"] = DisplayMap(classes, labels=ORDER_FIX_LABELS)
    return maps


def phase_stats(result: PhaseResult) -> dict[str, float]:
    """Per axis, shares of its lit pixels: ``phase/<axis>/<what>_share`` with <what> one of
    ``low_modulation`` (fringes too weak or noisy), ``order_corrected`` and
    ``order_rejected`` (the neighbour check), ``unwrap_rejected`` (periods disagreeing, or
    an ambiguous order) and ``out_of_range`` (the decoded share is the view's ``mask_share``)."""
    stats = {}
    for axis, a in result.axes.items():
        c = a.counts
        lit = max(c["lit"], 1)
        shares = {
            "low_modulation": c["low_modulation"] + c["noisy"],
            "order_corrected": c["order_corrected"],
            "order_rejected": c["order_rejected"],
            "unwrap_rejected": c["periods_disagree"] + c["ambiguous"],
            "out_of_range": c["out_of_range"],
        }
        stats.update({f"phase/{axis}/{k}_share": v / lit for k, v in shares.items()})
    return stats


def projector_codes(session: Session, view: ViewRecord | str, config=None):
    """The projector column and row at every decoded pixel (float, sub-pixel)."""
    view = session.view(view) if isinstance(view, str) else view
    return codes_of(decode_phase(session, view, **_options(config)), session, view.name)


def projector_constraints(session: Session, view: ViewRecord | str) -> ProjectorConstraints:
    """Every decoded pixel, once with its column and once with its row, as one-coordinate
    constraints for mapping board corners into the projector."""
    res = decode_phase(session, view)
    if res.row is None:
        raise SlscanError(f"{session.root}: the phase patterns have no row fringes; the projector's "
                          "rows are unknown (capture with rows)")
    ys, xs = np.nonzero(res.mask)
    x, y = xs.astype(np.float64), ys.astype(np.float64)
    return ProjectorConstraints(
        x=np.concatenate([x, x]), y=np.concatenate([y, y]),
        value=np.concatenate([res.column[ys, xs], res.row[ys, xs]]),
        is_row=np.concatenate([np.zeros(len(x), bool), np.ones(len(x), bool)]),
    )
