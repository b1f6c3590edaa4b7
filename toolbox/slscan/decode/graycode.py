"""Decode black/white Gray-code stripes with inverse images: per-pixel codes and sub-pixel edges.

Each bit of the projector column (and row) is read by comparing a pattern image with its
inverse: ``bit = pattern > inverse``. Comparing the pair instead of thresholding one image
makes the read independent of albedo, ambient light and the projector's black level. A
pixel is trusted only when every bit's ``|pattern - inverse|`` clears a threshold set by
the pixel's own white-minus-black signal and by the images' noise, estimated from the
data (see :func:`estimate_noise`).

The measured features are the stripe edges: along each camera row, where the decoded
column steps from ``c`` to ``c + 1``, exactly one Gray-code bit flips, and the zero
crossing of that bit's ``pattern - inverse`` (linearly interpolated between pixels) is the
sub-pixel camera position of the projector plane ``u = c + 0.5``.

References
----------
.. [1] Rocchini, Cignoni, Montani, Pingi, Scopigno, "A low cost 3D scanner based on
   structured light", Computer Graphics Forum 20(3), Eurographics 2001 (first version:
   plain Gray-code stripes).
.. [2] Inokuchi, Sato, Matsuda, "Range imaging system for 3-D object recognition",
   ICPR 1984 (Gray-coded structured light).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from slscan.capture.session import Session, ViewRecord
from slscan.decode.masks import (
    channel_max,
    channel_mean,
    full_scale,
    like_white,
    lit_bounds,
    uncrop,
)
from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError
from slscan.patterns import PatternImage
from slscan.patterns.graycode import gray, inverse_gray

log = logging.getLogger(__name__)

MAX_EDGE_GAP = 3
"""Largest gap (px) along a row between two valid pixels whose columns differ by one or
two for the edges between them to be measured; the pixels in between (usually the ones
right on an edge, where the flipping bit is too weak to read) only locate the crossing."""


@dataclass(frozen=True)
class GrayResult:
    """What one view's Gray-code images say about each camera pixel.

    column : (h, w) int32 projector column, -1 where not decoded
    row : (h, w) int32 projector row, -1 where not decoded; None without row patterns
    mask : (h, w) bool, the column (and the row, when row patterns exist) decoded
    edges : StripeSamples, sub-pixel stripe edges along camera rows (``stripe = c``,
        ``projector_column = c + 0.5`` for the edge between columns ``c`` and ``c + 1``)
    contrast : (h, w) float32 white minus black, fraction of full scale
    saturated : (h, w) bool, some image of the set is clipped at this pixel
    noise : float, estimated standard deviation of ``pattern - inverse``, fraction of
        full scale
    white : the white capture as read, when decoded from a session (:func:`decode_gray`)
    """

    column: np.ndarray
    row: np.ndarray | None
    mask: np.ndarray
    edges: StripeSamples
    contrast: np.ndarray
    saturated: np.ndarray
    noise: float
    white: np.ndarray | None = None

    @property
    def valid_fraction(self) -> float:
        """Share of camera pixels in ``mask``."""
        return float(self.mask.mean())


# --- pattern bookkeeping ------------------------------------------------------------------


def gray_pairs(descs: Sequence[PatternImage], axis: str) -> list[tuple[str, str]]:
    """The ``(pattern id, inverse id)`` of each bit along ``axis``, most significant first.

    Returns an empty list when the set has no Gray code along ``axis``.

    Raises
    ------
    SlscanError
        When a bit lacks its pattern or its inverse, or the bit counts disagree.
    """
    found: dict[tuple[int, bool], str] = {}
    bits_seen = set()
    for d in descs:
        if d.family != "gray" or d.axis != axis:
            continue
        try:
            bit, bits, inverse = (
                int(d.params["bit"]),
                int(d.params["bits"]),
                bool(d.params["inverse"]),
            )
        except KeyError as exc:
            raise SlscanError(
                f"pattern {d.id!r}: Gray-code description lacks {exc.args[0]!r}"
            ) from None
        if d.params.get("code", "reflected-binary") != "reflected-binary":
            raise SlscanError(
                f"pattern {d.id!r}: unsupported code {d.params['code']!r}, "
                "expected reflected-binary"
            )
        key = (bit, inverse)
        if key in found:
            raise SlscanError(
                f"patterns {found[key]!r} and {d.id!r} both claim {axis} bit {bit} "
                f"(inverse={inverse})"
            )
        found[key] = d.id
        bits_seen.add(bits)
    if not found:
        return []
    if len(bits_seen) != 1:
        raise SlscanError(
            f"Gray-code {axis} patterns disagree on the number of bits: {sorted(bits_seen)}"
        )
    bits = bits_seen.pop()
    pairs = []
    for bit in range(bits):
        for inverse in (False, True):
            if (bit, inverse) not in found:
                other = found.get((bit, not inverse), "?")
                what = "inverse" if inverse else "pattern"
                raise SlscanError(
                    f"Gray-code {axis} bit {bit} has no {what} image (its partner is {other!r}); "
                    "decoding needs every bit as a (pattern, inverse) pair"
                )
        pairs.append((found[(bit, False)], found[(bit, True)]))
    return pairs


class _Reader:
    """Turns captures into grey float32 images in fractions of full scale, tracking clipping."""

    def __init__(self, white: np.ndarray, where: str) -> None:
        self.white, self.where = white, where
        self.scale = full_scale(np.empty(0, white.dtype), where)
        self.saturated = np.zeros(white.shape[:2], bool)
        self.box = (slice(None), slice(None))  # the part of each image returned

    def __call__(self, image: np.ndarray, name: str) -> np.ndarray:
        image = like_white(image, self.white, name, self.where)
        image = image[self.box]
        self.saturated[self.box] |= channel_max(image) >= self.scale
        grey = channel_mean(image)
        grey *= np.float32(1.0 / self.scale)
        return grey


# --- decoding -------------------------------------------------------------------------------


def estimate_noise(pattern_sums: np.ndarray, flat_sum: np.ndarray, where: np.ndarray) -> float:
    """Standard deviation of ``pattern - inverse`` from how far ``pattern + inverse``
    departs from ``white + black`` (equal in expectation for binary patterns, blur or not).

    pattern_sums : (bits, h, w) float32 ``pattern + inverse`` per bit
    flat_sum : (h, w) float32 ``white + black``
    where : (h, w) bool pixels to use (lit ones)

    The residual has about twice the variance of ``pattern - inverse``; a median absolute
    deviation keeps camera non-linearity at mid-grey pixels from inflating it.
    """
    if not where.any():
        return 0.0
    # 200 000 residuals fix the MAD to about 0.3 %
    step = max(1, int(where.sum()) * len(pattern_sums) // 200_000)
    idx = np.flatnonzero(where)[::step]
    resid = pattern_sums.reshape(len(pattern_sums), -1)[:, idx] - flat_sum.reshape(-1)[idx]
    mad = float(np.median(np.abs(resid - np.median(resid))))
    return 1.4826 * mad / np.sqrt(2.0)


def _decode_axis(
    diffs: np.ndarray, size: int, lit: np.ndarray, threshold: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Values (h, w) int32 (-1 where unread) and validity from bit differences (bits, h, w)."""
    bits = len(diffs)
    code = np.zeros(diffs.shape[1:], np.int64)
    valid = lit.copy()
    for k in range(bits):
        code |= (diffs[k] > 0).astype(np.int64) << (bits - 1 - k)
        valid &= np.abs(diffs[k]) > threshold
    value = inverse_gray(code)
    valid &= value < size
    return np.where(valid, value, -1).astype(np.int32), valid


def _edges(
    column: np.ndarray,
    valid: np.ndarray,
    lit: np.ndarray,
    diffs: np.ndarray,
    white: np.ndarray,
    saturated: np.ndarray,
    max_gap: int,
) -> StripeSamples:
    """Sub-pixel stripe edges along rows between valid pixels whose columns differ.

    For consecutive valid pixels of a row at most ``max_gap`` apart, with lit pixels
    between them, whose columns ``c0 -> c1`` differ by 1 or 2 (at most the gap): each
    boundary ``c | c + 1`` in between is located at the first sign change, walking from
    the first pixel, of the bit that flips there (a different bit for each of two
    consecutive boundaries), interpolated linearly between the two pixels around it.
    """
    w = column.shape[1]
    bits = len(diffs)
    rows, xs = np.nonzero(valid)  # row-major: sorted by row, then x
    same_row = rows[1:] == rows[:-1]
    gap = xs[1:] - xs[:-1]
    c0, c1 = column[rows[:-1], xs[:-1]], column[rows[1:], xs[1:]]
    step = np.abs(c1 - c0)
    pair = same_row & (gap <= max_gap) & (step >= 1) & (step <= np.minimum(gap, 2))
    for between in range(1, max_gap):  # the pixels between the two must be lit
        inside = pair & (between < gap)
        xi = np.minimum(xs[:-1] + between, w - 1)
        pair &= ~inside | lit[rows[:-1], xi]
    # one entry per boundary: (pair, low + j) for j < step
    n = step[pair].astype(np.int64)
    idx = np.repeat(np.flatnonzero(pair), n)
    j = np.arange(len(idx)) - np.repeat(np.cumsum(n) - n, n)
    r, x0, g = rows[:-1][idx], xs[:-1][idx], gap[idx]
    low = np.minimum(c0[idx], c1[idx]).astype(np.int64) + j
    flip = gray(low) ^ gray(low + 1)  # a single bit
    k = (bits - 1 - np.log2(flip).round().astype(np.int64)).astype(np.intp)

    # walk from x0 towards x0 + g to the first sign change of the flipping bit's difference
    sign0 = diffs[k, r, x0] > 0
    seg = np.zeros(len(r), np.int64)  # the crossing lies in [x0 + seg, x0 + seg + 1]
    found = np.zeros(len(r), bool)
    for offset in range(1, max_gap + 1):
        xi = np.minimum(x0 + offset, w - 1)
        change = ~found & (offset <= g) & ((diffs[k, r, xi] > 0) != sign0)
        seg[change] = offset - 1
        found |= change
    xa = np.minimum(x0 + seg, w - 2)
    da, db = diffs[k, r, xa], diffs[k, r, xa + 1]
    denom = da - db
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(denom != 0, da / denom, 0.5)
    x = xa + np.clip(frac, 0.0, 1.0)

    edge_signal = np.abs(da) + np.abs(db)
    white_sum = white[r, xa] + white[r, xa + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(white_sum > 0, edge_signal / white_sum, 0.0)
    sat = saturated[r, xa] | saturated[r, xa + 1]
    keep = np.flatnonzero(found & np.isfinite(x))
    keep = keep[np.lexsort((x[keep], r[keep]))]
    return StripeSamples(
        row=r[keep].astype(np.int32),
        x=x[keep].astype(np.float64),
        projector_column=low[keep].astype(np.float64) + 0.5,
        stripe=low[keep].astype(np.int32),
        contrast=np.clip(rel[keep], 0.0, 1.0).astype(np.float32),
        saturated=sat[keep],
    )


def decode_gray_images(
    images: Mapping[str, np.ndarray],
    descs: Sequence[PatternImage],
    white: np.ndarray,
    black: np.ndarray,
    *,
    min_contrast: float = 0.03,
    min_bit_ratio: float = 0.1,
    noise_sigmas: float = 3.0,
    noise: float | None = None,
    max_edge_gap: int = MAX_EDGE_GAP,
    where: str = "",
) -> GrayResult:
    """Decode one view's Gray-code captures into projector columns (rows) and stripe edges.

    Parameters
    ----------
    images : mapping of pattern id to (h, w) or (h, w, 3) uint8/uint16 captures
        At least every Gray-code pattern of ``descs``; other entries are ignored. RGB
        captures are read as the mean of their channels.
    descs : the session's pattern descriptions; only ``family == "gray"`` ones are used
    white, black : (h, w) or (h, w, 3) captures under full white and full black
    min_contrast : float
        ``white - black`` must exceed this fraction of full scale (shadow, background).
    min_bit_ratio : float
        Every bit's ``|pattern - inverse|`` must exceed this fraction of ``white - black``...
    noise_sigmas : float
        ...and this many standard deviations of the noise of ``pattern - inverse``.
    noise : float, optional
        That standard deviation, fraction of full scale; default: estimated from the
        images (:func:`estimate_noise`), at least the quantisation noise.
    max_edge_gap : int, px
        Measure the edges between valid pixels up to this far apart along a row whose
        columns differ by one or two (the pixels between must pass ``min_contrast``);
        pixels right on an edge are often invalid, their flipping bit being too weak.
    where : str
        Prefix for error messages (e.g. the view folder).

    Returns
    -------
    GrayResult
        Decoded columns (and rows when the set has row codes), the validity mask and the
        sub-pixel stripe edges (one sample per camera row and column boundary crossed,
        sorted by row then x; a row that crosses the same boundary twice gives two).
        ``contrast`` of an edge sample is ``|d(xa)| + |d(xa + 1)|`` over
        ``white(xa) + white(xa + 1)``, with ``d`` the flipping bit's ``pattern - inverse``
        at the two pixels around the crossing (1 for a step right between two pixels
        with no black level; blur and black lower it); ``saturated`` marks a clipped
        image at either pixel.

    Raises
    ------
    SlscanError
        A Gray-code pattern or its inverse missing from ``descs`` or ``images``, or
        images of mismatched size or pixel type (naming the pattern).
    """
    where = f"{where}: " if where and not where.endswith(": ") else where
    col_pairs = gray_pairs(descs, "columns")
    row_pairs = gray_pairs(descs, "rows")
    if not col_pairs:
        raise SlscanError(f"{where}the pattern set has no Gray-code column patterns to decode")
    width = height = None
    for d in descs:
        if d.family == "gray":
            width, height = d.width, d.height
            break
    for pid in (p for pair in col_pairs + row_pairs for p in pair):
        if pid not in images:
            raise SlscanError(f"{where}no captured image of Gray-code pattern {pid!r}")
    white = np.asarray(white)
    if white.ndim not in (2, 3) or (white.ndim == 3 and white.shape[2] not in (1, 3)):
        raise SlscanError(
            f"{where}white: expected an (h, w) or (h, w, 3) image, got shape {white.shape}"
        )
    full_scale(white, f"{where}white")
    read = _Reader(white, where)
    w_img, b_img = read(white, "white"), read(black, "black")
    full_contrast = w_img - b_img
    full_lit = full_contrast > min_contrast
    # the rest runs on the lit pixels' bounding box: outside it nothing decodes
    read.box = box = lit_bounds(full_lit, max_edge_gap + 2)
    y0, x0 = box[0].start, box[1].start
    w_img, b_img, contrast, lit = w_img[box], b_img[box], full_contrast[box], full_lit[box]

    def load(pairs: list[tuple[str, str]]) -> tuple[np.ndarray, np.ndarray]:
        diffs = np.empty((len(pairs),) + contrast.shape, np.float32)
        sums = np.empty_like(diffs)
        for k, (pid, inv) in enumerate(pairs):
            p, q = read(images[pid], pid), read(images[inv], inv)
            np.subtract(p, q, out=diffs[k])
            np.add(p, q, out=sums[k])
        return diffs, sums

    col_diffs, col_sums = load(col_pairs)
    if noise is not None:
        sigma = float(noise)
    else:  # at least the quantisation noise of a difference of two images (0.41 DN)
        sigma = max(estimate_noise(col_sums, w_img + b_img, lit), np.sqrt(2 / 12) / read.scale)
    del col_sums
    threshold = np.maximum(min_bit_ratio * contrast, np.float32(noise_sigmas * sigma))
    lit &= contrast > threshold  # a pixel must at least carry a readable signal
    column, col_valid = _decode_axis(col_diffs, width, lit, threshold)
    row = None
    mask = col_valid
    if row_pairs:
        row_diffs, _ = load(row_pairs)
        row, row_valid = _decode_axis(row_diffs, height, lit, threshold)
        mask = col_valid & row_valid
        del row_diffs
    edges = _edges(column, col_valid, lit, col_diffs, w_img, read.saturated[box], max_edge_gap)
    edges = edges.shifted(y0, x0)
    column, mask = uncrop(column, box, full_lit.shape, -1), uncrop(mask, box, full_lit.shape, False)
    row = None if row is None else uncrop(row, box, full_lit.shape, -1)
    log.debug(
        "%sGray code: %.1f%% pixels decoded, %d edges, noise %.4f of full scale",
        where,
        100 * mask.mean(),
        len(edges),
        sigma,
    )
    return GrayResult(
        column=column,
        row=row,
        mask=mask,
        edges=edges,
        contrast=full_contrast,
        saturated=read.saturated,
        noise=sigma,
    )


def decode_gray(session: Session, view: ViewRecord | str, **options) -> GrayResult:
    """Read and decode the Gray-code images of ``view`` in ``session``.

    ``options`` are passed to :func:`decode_gray_images`.

    Raises
    ------
    SlscanError
        The view lacks the white or black image or a Gray-code pattern or inverse, or an
        image does not match the session (naming the file).
    """
    if isinstance(view, str):
        view = session.view(view)
    descs = [p for p in session.patterns if p.family == "gray"]
    where = str(session.root / view.name)

    white_id, black_id = session.flat_frame_ids("Gray-code decoding")
    # the order decoding uses them: flat frames, then column and row (pattern, inverse) pairs
    pairs = gray_pairs(descs, "columns") + gray_pairs(descs, "rows")
    ids = [white_id, black_id, *(p for pair in pairs for p in pair)]
    records = [view.image_for(pid) for pid in ids]
    # read in the background while the images already read are decoded
    with session.prefetch_images(view, records) as images:
        result = decode_gray_images(
            images, descs, images[white_id], images[black_id], where=where, **options
        )
        return replace(result, white=images[white_id])
