"""Decode black/white Gray-code stripes with inverse images: per-pixel codes and sub-pixel edges.

Each bit of the projector column (and row) is read by comparing a pattern image with its
inverse: ``bit = pattern > inverse``. Comparing the pair instead of thresholding one image
makes the read independent of albedo, ambient light and the projector's black level. A
pixel is trusted only when every bit's ``|pattern - inverse|`` clears a threshold set by
the pixel's own white-minus-black signal and by the images' noise, estimated from the
data the same way for plain Gray and XOR codes (:func:`estimate_noise`): each bit's
``pattern + inverse`` against a reference showing the same light, blurred and curved
alike: ``white + black`` inside flat stripe interiors, away from the bit's edges, or the
next bit's pair where both show the same stripes (XOR codes' images coarser than the base).
The sum equals ``white + black`` in linear light everywhere, but not near edges for a camera
curve not undone (sRGB: steep in the darks, it makes blur's light leak into fine dark
stripes large).

The measured features are the stripe edges: along each camera row, where the decoded
column steps from ``c`` to ``c + 1``, exactly one Gray-code bit flips, and the zero
crossing of that bit's ``pattern - inverse`` (linearly interpolated between pixels) is the
sub-pixel camera position of the projector plane ``u = c + 0.5``. The same search runs
along camera columns, and each boundary keeps the samples of the axis that crosses it
more steeply, so a projector mounted rotated (stripes horizontal in the camera) gives as
many edges as an upright one.

Two threshold rules are offered: ``"adaptive"`` (the default, above) and ``"opencv"``,
the fixed rule of OpenCV's ``structured_light::GrayCodePattern`` [3]_: a pixel is lit
when ``|white - black| > black_threshold`` and every bit reads when
``|pattern - inverse| >= white_threshold`` (DN; OpenCV's defaults 40 and 5), on the grey
images as an OpenCV user loads them (RGB through ``cv2.cvtColor``; never linearised) and
with nothing else rejecting pixels, so the mask is OpenCV's; 16-bit captures: the same
share of full scale (thresholds times 257).

Memory: a view keeps, per column bit, both captures' grey levels (1 byte a pixel each for
8-bit grey captures) or, for float levels (float or linearised sRGB captures), only
``pattern - inverse``; row bits are folded into the row code as they are read, the noise
is estimated on a subsample while reading, and edges are searched in bands. Captures are
read as stored, one JPEG decode each, by a thread that turns each into the grey plane
kept of it while the decoder works. A 16 MP, 42-image view decodes in about 1 GB (grey
PNG, ``benchmarks/decode_memory.py``) to 2 GB (colour JPEG through an sRGB curve, lit
across the frame, ``benchmarks/decode_16mp.py``).

References
----------
.. [1] Rocchini, Cignoni, Montani, Pingi, Scopigno, "A low cost 3D scanner based on
   structured light", Computer Graphics Forum 20(3), Eurographics 2001 (first version:
   plain Gray-code stripes).
.. [2] Inokuchi, Sato, Matsuda, "Range imaging system for 3-D object recognition",
   ICPR 1984 (Gray-coded structured light).
.. [3] OpenCV, ``modules/structured_light/src/graycodepattern.cpp``
   (``computeShadowMasks``, ``getProjPixel``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Self

import numpy as np

from slscan.capture.session import Session, ViewRecord
from slscan.decode.family import FamilyDecode, ProjectorConstraints
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
from slscan.patterns.graycode import CODES, gray

log = logging.getLogger(__name__)

MAX_EDGE_GAP = 3
"""Largest gap (px) along a row between two valid pixels whose columns differ by one or
two for the edges between them to be measured; the pixels in between (usually the ones
right on an edge, where the flipping bit is too weak to read) only locate the crossing."""

THRESHOLD_MODES = ("adaptive", "opencv")
"""Threshold rules of :func:`decode_gray_images`."""

OPENCV_BLACK_THRESHOLD = 40.0
"""DN: OpenCV ``GrayCodePattern``'s default ``blackThreshold`` (``|white - black|`` must exceed it)."""

OPENCV_WHITE_THRESHOLD = 5.0
"""DN: OpenCV ``GrayCodePattern``'s default ``whiteThreshold`` (a bit whose
``|pattern - inverse|`` is below it makes the pixel invalid)."""

OPENCV_DN = 255.0
"""Full scale of the DN OpenCV's thresholds are in: ``GrayCodePattern`` reads pixels as
8-bit (``at<uchar>``). On 16-bit captures the ``"opencv"`` rule applies them as the same
share of full scale, ``* 65535 / 255 = * 257`` (40 DN -> 10280, 5 DN -> 1285), to the
16-bit grey at its full precision: what OpenCV gives on the captures rounded to 8 bit
(``v / 257``) but for pixels where the rounding decides (a difference within an 8-bit DN
of its threshold: 3.8 % of the decoded pixels of the virtual figurine)."""

EDGE_BAND = 256
"""Camera rows (columns) per band of the edge search: bounds its index arrays' memory."""

PREFETCH = 2
"""Captures :func:`decode_gray` reads ahead of the decoder (each is dropped once used)."""

_KEEP_DIFFERENCES = True
"""Keep float column levels of plain Gray codes as their differences (:class:`_BitDiffs`);
False: both captures' levels, as before (the tests compare the two)."""

SEPARATION_BITS = 3
"""How many column bits (with their inverses) split the light into direct and global
parts (Nayar et al. 2006): the finest ones the optics resolve (see
``SEPARATION_MIN_CONTRAST``), fine enough for global light to fall evenly on a pattern and
its inverse, and varied enough that every pixel sits well inside a lit and an unlit stripe
of one of them."""

SEPARATION_MIN_CONTRAST = 0.6
"""The split skips the finest bits whose median ``|pattern - inverse| / (white - black)``
over lit pixels is below this share of the best fine bit's: blur puts their direct light
into the unlit image, which would read as global light (the kamino410 captures' 2 px
stripes keep 0.50 of their 16 px stripes' contrast, the virtual rig's 0.51; their 4 px
stripes 0.76 and 0.86)."""

FLAT_RADIUS = 2
"""Camera px a pixel must lie inside a stripe (from its pattern's and inverse's own edges)
for the noise estimate to use it (:func:`estimate_noise`): camera blur of σ 0.6–1 px
leaks 0.04–2 % of the light this far."""

MIN_FLAT_RESIDUALS = 2000
"""Fewest residuals (pixels x bits inside stripes) the noise estimate takes at a radius
before it tries a smaller one: the MAD of 2000 is within about 3 % (1 sigma)."""

CONSISTENCY_RADIUS = 2
"""Half-size (px) of the window in which a decoded code must agree with most of its
valid neighbours (:func:`_inconsistent`)."""

CODE_TOLERANCE = (2.0, 2.0)
"""A neighbour ``d`` pixels away (Chebyshev) agrees when the codes differ by at most
``a + b * d`` columns (rows): surfaces steeper than ``b`` projector pixels per camera pixel
are rare, and a wrong low-order bit moves a code by 1 to 3."""


@dataclass(frozen=True)
class GrayResult:
    """What one view's Gray-code images say about each camera pixel.

    column : (h, w) int32 projector column, -1 where not decoded
    row : (h, w) int32 projector row, -1 where not decoded; None without row patterns
    mask : (h, w) bool, the column (and the row, when row patterns exist) decoded
    edges : StripeSamples, sub-pixel stripe edges (``projector_column = c + 0.5`` for the
        edge between columns ``c`` and ``c + 1``), found along camera rows and, where
        the stripes cross them more steeply, along camera columns
        (``edges.along_columns``)
    contrast : (h, w) float32 white minus black, fraction of full scale
    saturated : (h, w) bool, some image of the set is clipped at this pixel
    noise : float, estimated standard deviation of ``pattern - inverse``, fraction of
        full scale
    white : the white capture as read, when decoded from a session (:func:`decode_gray`)
    bits_used : ``{axis: (bits read, bits of the full code)}``; fewer bits read (a set
        missing some) give coarser codes: the centre of a block of ``2**missing``
        columns (rows), and edges only between blocks
    diagnostics : what limited the valid share, in camera pixels: ``pixels``; ``lit``
        (passed the contrast test); ``low_contrast`` (failed it: white - black too
        small, shadow or background); ``dark`` (the part of ``low_contrast`` that
        failed even the minimum contrast: background, shadow); ``weak_bit_noise`` and ``weak_bit_ratio`` (lit
        but some bit's ``|pattern - inverse|`` under the threshold, whose binding term
        was the noise term, or the share of ``white - black``; OpenCV's fixed
        ``white_threshold`` counts as a noise term); ``out_of_range`` (every bit read,
        code beyond the projector); ``valid`` (the mask); ``noise_dn`` (the noise in
        DN of the captures) and ``threshold_mode``. With ``robust`` decoding also
        ``unreliable_global`` (every bit readable and in range, but some bit failed
        Gupta's direct/global rule: global light may have flipped it) and
        ``inconsistent`` (the code disagrees with most valid neighbours), and
        ``global_direct_median`` (median of global / direct over lit pixels).
        ``lit = valid + weak_bit_noise + weak_bit_ratio + out_of_range +
        unreliable_global + inconsistent``.
    direct, global_light : (h, w) float32 direct and global light under full white,
        fractions of full scale, from the finest bits (:func:`separate_light`); None
        unless decoded with ``robust``
    """

    column: np.ndarray
    row: np.ndarray | None
    mask: np.ndarray
    edges: StripeSamples
    contrast: np.ndarray
    saturated: np.ndarray
    noise: float
    white: np.ndarray | None = None
    bits_used: dict[str, tuple[int, int]] = field(default_factory=dict)
    diagnostics: dict[str, float | int | str] = field(default_factory=dict)
    direct: np.ndarray | None = None
    global_light: np.ndarray | None = None

    @property
    def valid_fraction(self) -> float:
        """Share of camera pixels in ``mask``."""
        return float(self.mask.mean())


# --- pattern bookkeeping ------------------------------------------------------------------


@dataclass(frozen=True)
class GrayBits:
    """The Gray-code bits of one axis in a pattern set.

    bits : bits of the full code
    pairs : ``(pattern id, inverse id)`` of the bits decoding uses: the leading run of
        bits present, most significant first
    missing : indices of the bits absent from the set
    unused : indices of bits present after the first missing one (not used: without the
        missing bit they cannot refine the code)
    """

    bits: int
    pairs: tuple[tuple[str, str], ...]
    missing: tuple[int, ...]
    unused: tuple[int, ...]
    code: str = "reflected-binary"
    base: int | None = None
    """XOR codes: the bit the coarser ones were XOR-ed with (None: plain Gray code)."""

    @property
    def coarse(self) -> int:
        """Low bits not read: a code names a block of ``2**coarse`` columns (rows)."""
        return self.bits - len(self.pairs)


def gray_bits(descs: Sequence[PatternImage], axis: str) -> GrayBits:
    """The Gray-code bits along ``axis`` of a pattern set (``bits == 0``: none).

    Raises
    ------
    SlscanError
        When a bit has its pattern but not its inverse (or the reverse), two patterns
        claim the same bit, or the bit counts disagree.
    """
    found: dict[tuple[int, bool], str] = {}
    bits_seen = set()
    codes_seen = set()
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
        code = d.params.get("code", "reflected-binary")
        if code not in CODES:
            raise SlscanError(
                f"pattern {d.id!r}: unsupported code {code!r}, expected one of {', '.join(CODES)}"
            )
        if code == "xor":
            if "base" not in d.params:
                raise SlscanError(f"pattern {d.id!r}: XOR-code description lacks 'base'")
            codes_seen.add((code, int(d.params["base"])))
        else:
            codes_seen.add((code, None))
        key = (bit, inverse)
        if key in found:
            raise SlscanError(
                f"patterns {found[key]!r} and {d.id!r} both claim {axis} bit {bit} "
                f"(inverse={inverse})"
            )
        found[key] = d.id
        bits_seen.add(bits)
    if not found:
        return GrayBits(0, (), (), ())
    if len(bits_seen) != 1:
        raise SlscanError(
            f"Gray-code {axis} patterns disagree on the number of bits: {sorted(bits_seen)}"
        )
    if len(codes_seen) != 1:
        raise SlscanError(
            f"Gray-code {axis} patterns mix codes: {sorted(codes_seen, key=str)}"
        )
    code, base = codes_seen.pop()
    bits = bits_seen.pop()
    if base is not None and not 0 <= base < bits:
        raise SlscanError(f"XOR-code {axis} patterns: base bit {base} outside 0..{bits - 1}")
    present = []
    for bit in range(bits):
        have = [(bit, inverse) in found for inverse in (False, True)]
        if have[0] != have[1]:
            inverse = not have[1]
            what = "inverse" if inverse else "pattern"
            raise SlscanError(
                f"Gray-code {axis} bit {bit} has no {what} image (its partner is "
                f"{found[(bit, not inverse)]!r}); decoding needs every bit as a "
                "(pattern, inverse) pair"
            )
        if have[0]:
            present.append(bit)
    missing = tuple(b for b in range(bits) if b not in present)
    if base is not None and base in missing:
        raise SlscanError(
            f"XOR-code {axis} patterns lack their base bit {base}: no bit can be read without it"
        )
    lead = next(iter(missing), bits)
    if base is not None and base >= lead:  # the leading run must hold the base
        missing_after = [b for b in missing if b > base]
        lead = next(iter(missing_after), bits)
    pairs = tuple((found[(b, False)], found[(b, True)]) for b in range(lead) if b not in missing)
    if len(pairs) != lead:  # a bit before the base is missing: nothing coarser decodes
        raise SlscanError(
            f"XOR-code {axis} patterns lack bit(s) {', '.join(map(str, [b for b in missing if b < lead]))}: "
            "an XOR set decodes only with every bit down to its base"
        )
    return GrayBits(bits, pairs, missing, tuple(b for b in present if b > lead), code, base)


def gray_pairs(descs: Sequence[PatternImage], axis: str) -> list[tuple[str, str]]:
    """The ``(pattern id, inverse id)`` of the bits along ``axis`` that decoding uses, most
    significant first: every bit, or the leading run of bits present when some are missing
    (see :func:`gray_bits`).

    Returns an empty list when the set has no Gray code along ``axis`` (or lacks its
    most significant bit).

    Raises
    ------
    SlscanError
        When a bit has its pattern but not its inverse (or the reverse), or the bit
        counts disagree.
    """
    return list(gray_bits(descs, axis).pairs)


LUMA_WEIGHTS = (77, 150, 29)
"""Integer weights (sum 256) of R, G, B in the luma read of lossy captures: ITU-R BT.601's
0.299, 0.587, 0.114, the Y that JPEG keeps at full resolution (its chroma is halved)."""


@dataclass(frozen=True)
class _Read:
    """One capture already read into what :class:`_Reader` keeps of it (by the thread that
    reads ahead, :func:`decode_gray`): its levels and clipping over the whole frame, and the
    capture's own shape and pixel type (checked against the white frame's)."""

    levels: np.ndarray
    clipped: np.ndarray
    shape: tuple[int, ...]
    dtype: np.dtype


class _Reader:
    """Reads captures of one view: grey levels, their fractions of full scale and clipping.

    luma : RGB captures are read as their luma (:data:`LUMA_WEIGHTS`) instead of the mean
        of their channels: for lossy (JPEG) captures, whose 4:2:0 chroma is half resolution
        and whose colour errors the channel mean would add to the stripes.
    opencv : read as OpenCV ``GrayCodePattern`` users do (:func:`opencv_grey`): RGB
        captures through ``cv2.cvtColor`` to grey of the same depth, rounded; grey ones as
        they are. The levels are then the grey DN themselves.
    response : the integer captures' tone curve (``Session.response``): other than
        ``"linear"``, each capture is read (as stored) straight into the float32 grey of
        its linearised channels, exactly what :func:`~slscan.capture.session.linearise`
        then the channel mean (or luma) give, through one lookup table per channel: no
        float RGB copy of a capture is made, and clipping is found on the stored values."""

    def __init__(self, white: np.ndarray, where: str, luma: bool = False, opencv: bool = False,
                 response: str = "linear") -> None:
        self.white, self.where = white, where
        self.clip = self.scale = full_scale(np.empty(0, white.dtype), where)
        self.channels = 1 if white.ndim == 2 else white.shape[2]
        self.opencv = opencv and self.channels == 3
        self.weights = LUMA_WEIGHTS if luma and self.channels == 3 and not opencv else None
        self.saturated = np.zeros(white.shape[:2], bool)
        self.box = (slice(None), slice(None))  # the part of each image returned
        self.curve = None
        if response != "linear" and white.dtype in (np.uint8, np.uint16):
            from slscan.capture.session import linearise

            # the linearised captures are float fractions of full scale: read as such
            self.curve = linearise(np.arange(int(self.clip) + 1, dtype=white.dtype), response)
            self.scale = 1.0
            if self.weights is not None:
                total = float(sum(self.weights))
                self.channel_curves = [self.curve * np.float32(w / total) for w in self.weights]
            else:
                self.channel_curves = [self.curve] * self.channels
        # integer captures are kept as levels (the channel sum, or the weighted sum for
        # luma, in the smallest integer type that holds it: 1 byte a pixel for 8-bit grey)
        # and turned into the same float32 fractions as channel_mean (or the luma) gives
        # through a lookup table; float (and linearised) captures are kept as their float32
        # fractions (lut None)
        self.lut = None
        self.level_dtype = np.float32
        integer = white.dtype not in (np.float32, np.float64) and self.curve is None
        self.dn = self.scale if integer else 255.0
        if integer and white.dtype in (np.uint8, np.uint16):
            per_level = sum(self.weights) if self.weights else 1 if self.opencv else self.channels
            self.per_level = per_level
            top = int(self.scale) * per_level
            self.level_dtype = next(t for t in (np.uint8, np.uint16, np.uint32) if top <= np.iinfo(t).max)
            lut = np.arange(top + 1, dtype=np.float32)
            if per_level > 1:
                lut *= np.float32(1.0 / per_level)
            lut *= np.float32(1.0 / self.scale)
            self.lut = lut

    def _grey(self, image: np.ndarray) -> np.ndarray:
        """float32 channel mean (or luma, or OpenCV's grey) of a checked capture."""
        if self.curve is not None:  # linearised channels, weighted, summed in channel order
            if image.ndim == 2:
                return self.curve[image]
            if image.dtype == np.uint8:  # OpenCV's lookup and add: the same float32 sums, faster
                import cv2

                planes = cv2.split(np.ascontiguousarray(image))
                grey = cv2.LUT(planes[0], self.channel_curves[0])
                for c in range(1, len(planes)):
                    cv2.add(grey, cv2.LUT(planes[c], self.channel_curves[c]), dst=grey)
            else:
                grey = self.channel_curves[0][image[..., 0]]
                for c in range(1, image.shape[2]):
                    grey += self.channel_curves[c][image[..., c]]
            if self.weights is None:
                grey *= np.float32(1.0 / image.shape[2])
            return grey
        if self.opencv and image.ndim == 3:
            return opencv_grey(image).astype(np.float32)
        if self.weights is None or image.ndim == 2:
            return channel_mean(image)
        total = float(sum(self.weights))
        grey = image[..., 0].astype(np.float32) * np.float32(self.weights[0] / total)
        for c in (1, 2):
            grey += image[..., c].astype(np.float32) * np.float32(self.weights[c] / total)
        return grey

    def check(self, image: np.ndarray | _Read, name: str) -> np.ndarray | _Read:
        """``image`` cropped to the box, its clipping recorded (an error naming it when
        it does not match the white frame); a :class:`_Read` capture as it is."""
        if isinstance(image, _Read):
            like_white(np.broadcast_to(np.zeros((), image.dtype), image.shape), self.white, name, self.where)
            self.saturated[self.box] |= image.clipped[self.box]
            return image
        image = like_white(image, self.white, name, self.where)[self.box]
        self.saturated[self.box] |= channel_max(image) >= self.clip
        return image

    def read_ahead(self, image: np.ndarray) -> _Read | np.ndarray:
        """``image`` read into its levels over the whole frame, and its clipping (what
        :meth:`levels` and :meth:`check` take from it later, on any box); an image unlike
        the white frame as it is (for :meth:`check` to name)."""
        image = np.asarray(image)
        if image.shape != self.white.shape or image.dtype != self.white.dtype:
            return image
        return _Read(self._levels(image), channel_max(image) >= self.clip, image.shape, image.dtype)

    def __call__(self, image: np.ndarray | _Read, name: str) -> np.ndarray:
        """Grey float32 image in fractions of full scale."""
        if isinstance(image, _Read):
            return np.array(self.fraction(self.levels(image, name)), np.float32)
        grey = self._grey(self.check(image, name))
        grey *= np.float32(1.0 / self.scale)
        return grey

    def levels(self, image: np.ndarray | _Read, name: str) -> np.ndarray:
        """Levels of a capture on the box: channel sums (integer captures, ``level_dtype``)
        or grey fractions (float captures); :meth:`fraction` turns them into fractions."""
        image = self.check(image, name)
        if isinstance(image, _Read):
            return image.levels[self.box]
        return self._levels(image)

    def _levels(self, image: np.ndarray) -> np.ndarray:
        """:meth:`levels` of a checked capture."""
        if self.lut is None:
            grey = self._grey(image)
            grey *= np.float32(1.0 / self.scale)
            return grey
        if image.ndim == 2:
            return np.array(image, self.level_dtype)
        if self.opencv:
            return opencv_grey(image)
        if self.weights is not None:
            out = image[..., 0].astype(self.level_dtype) * self.level_dtype(self.weights[0])
            for c in (1, 2):
                out += image[..., c].astype(self.level_dtype) * self.level_dtype(self.weights[c])
            return out
        out = image[..., 0].astype(self.level_dtype)
        for c in range(1, image.shape[2]):
            out += image[..., c]
        return out

    def fraction(self, levels: np.ndarray) -> np.ndarray:
        """Grey float32 fractions of full scale of ``levels``, exactly as ``__call__``."""
        return levels if self.lut is None else self.lut[levels]

    def level_threshold(self, dn: float) -> float:
        """A threshold in 8-bit DN of the grey captures (:data:`OPENCV_DN`), in level units:
        for 16-bit captures the same share of full scale (``dn * 257``); for float ones a
        fraction (``dn / 255``)."""
        if self.lut is None:
            return dn / OPENCV_DN
        return dn * (self.scale / OPENCV_DN) * self.per_level


def opencv_grey(image: np.ndarray) -> np.ndarray:
    """(h, w) grey of an (h, w, 3) RGB capture as OpenCV users read it:
    ``cv2.cvtColor(..., COLOR_RGB2GRAY)`` (BT.601 luma 0.299 R + 0.587 G + 0.114 B in
    OpenCV's own fixed point, rounded to the capture's depth), which equals
    ``cvtColor(cv2.imread(file), COLOR_BGR2GRAY)`` on the BGR image ``cv2.imread`` gives. A
    grey (h, w) capture is returned as it is."""
    image = np.asarray(image)
    if image.ndim == 2:
        return image
    import cv2

    image = np.ascontiguousarray(image[..., :3], np.float32 if image.dtype == np.float64 else None)
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


class _BitDiffs:
    """``pattern - inverse`` of each bit, fractions of full scale, indexed like a (bits, h,
    w) array (``d[k, rows, cols]``) but stored as the two captures' levels.

    XOR codes (``base`` set): the difference of bit ``k < base`` comes with the sign of
    the Gray bit it encodes, ``(pattern - inverse) * sign(base pattern - base inverse)``:
    positive where the Gray bit is 1, zero crossings only at that bit's own boundaries
    (the base bit is constant across them, so the crossing is the captured one).

    Float levels of plain Gray codes are stored as the differences themselves (half the
    memory): ``pattern`` holds ``pattern - inverse`` and ``inverse`` zeros (a broadcast
    view, no memory), which every use (bits, thresholds, reliability, edges) reads exactly
    as before; ``sums`` then holds each bit's ``pattern + inverse`` on the noise subsample
    (:func:`estimate_noise`)."""

    def __init__(self, read: _Reader, pattern: np.ndarray, inverse: np.ndarray,
                 base: int | None = None, sums: list[np.ndarray] | None = None) -> None:
        self.read, self.pattern, self.inverse, self.base = read, pattern, inverse, base
        self.sums = sums

    def __len__(self) -> int:
        return len(self.pattern)

    def __getitem__(self, index) -> np.ndarray:
        f = self.read.fraction
        d = f(self.pattern[index]) - f(self.inverse[index])
        if self.base is None:
            return d
        k, *rest = index if isinstance(index, tuple) else (index,)
        b = (self.base, *rest)
        flip = (self.pattern[b] <= self.inverse[b]) & (np.asarray(k) < self.base)
        return np.where(flip, -d, d)

    def rows(self, sl: slice) -> _BitDiffs:
        return _BitDiffs(self.read, self.pattern[:, sl], self.inverse[:, sl], self.base)

    @property
    def T(self) -> _BitDiffs:
        return _BitDiffs(self.read, self.pattern.transpose(0, 2, 1), self.inverse.transpose(0, 2, 1),
                         self.base)


# --- decoding -------------------------------------------------------------------------------


def _mad_sigma(resid: np.ndarray) -> float:
    mad = float(np.median(np.abs(resid - np.median(resid))))
    return 1.4826 * mad / np.sqrt(2.0)


def _noise_index(where: np.ndarray, bits: int) -> np.ndarray:
    """Flat indices of the ``where`` pixels the noise estimate uses (about 200 000 pixel-bits,
    of which :func:`estimate_noise` keeps those with a reference showing the same light)."""
    # 200 000 residuals fix the MAD to about 0.3 % (the 60-95 % kept: 0.4 %)
    step = max(1, int(where.sum()) * bits // 200_000)
    return np.flatnonzero(where)[::step]


def _grid_bits(diffs: _BitDiffs, iy: np.ndarray, ix: np.ndarray, radius: int) -> np.ndarray:
    """(bits, 9, n) bool: each image pair's bit (``pattern > inverse``) at ``(iy, ix)`` and
    at the 8 points ``radius`` px away on a 3 x 3 grid around it (clipped to the image);
    the pixel itself is grid point 4."""
    h, w = diffs.pattern.shape[1:]
    ys = np.stack([np.clip(iy + dy, 0, h - 1) for dy in (-radius, 0, radius) for _ in range(3)])
    xs = np.stack([np.clip(ix + dx, 0, w - 1) for _ in range(3) for dx in (-radius, 0, radius)])
    return np.stack([diffs.pattern[k][ys, xs] > diffs.inverse[k][ys, xs] for k in range(len(diffs))])


def _same_light(a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Whether grid bits ``a`` (9, n) show the same stripes as ``b`` or their inverse (None:
    as white and black, i.e. no stripe edge) around each pixel: the relation of the bits is
    the same at all 9 grid points (:func:`_grid_bits`), so no straight edge of one that the
    other lacks is nearer than the grid's radius (an edge at distance ``t < radius`` leaves
    a grid point on its far side)."""
    rel = a if b is None else a == b
    return (rel == rel[4]).all(axis=0)


def estimate_noise(diffs: _BitDiffs, flat_sum: np.ndarray, iy: np.ndarray, ix: np.ndarray,
                   radius: int = FLAT_RADIUS, min_residuals: int = MIN_FLAT_RESIDUALS) -> float:
    """Standard deviation of ``pattern - inverse`` (fraction of full scale) from how far
    each bit's ``pattern + inverse`` departs from that of a reference showing the same
    light, on the subsample ``(iy, ix)`` (:func:`_noise_index`); plain Gray and XOR codes
    alike.

    diffs : every column bit's pattern and inverse (the captured images; the XOR
        decoding is not used)
    flat_sum : ``white + black`` on the subsample, fractions of full scale

    In linear light every ``pattern + inverse`` equals ``white + black`` in expectation,
    blur and global light or not, but a camera curve not undone (an sRGB camera, steep in
    the darks) turns the light blur leaks into a fine stripe's dark half from 3 % into
    19 %, which near every edge outweighs the noise. So each bit is compared only where a
    reference shows the same light, blurred and curved alike: ``white + black`` where the
    pixel lies at least ``radius`` px inside a stripe of the bit (a flat stripe interior),
    or the next bit's ``pattern + inverse`` where the two show the same stripes or their
    inverse (:func:`_same_light`), whichever holds at more pixels (the next bit for XOR
    codes' images coarser than the base, which all show the base stripes away from their
    own rare boundaries; white and black for the rest). The residual has about twice the
    variance of ``pattern - inverse``; a median absolute deviation keeps odd pixels from
    inflating it. The radius shrinks (to 0: every pixel against ``white + black``) while
    fewer than ``min_residuals`` residuals qualify (stripes a couple of camera px wide).
    """
    if not len(iy):
        return 0.0
    f = diffs.read.fraction
    sums = diffs.sums or [f(diffs.pattern[k, iy, ix]) + f(diffs.inverse[k, iy, ix]) for k in range(len(diffs))]
    for r in range(radius, 0, -1):
        grid = _grid_bits(diffs, iy, ix, r)
        resid = []
        for k, s in enumerate(sums):
            flat = _same_light(grid[k])
            alike = _same_light(grid[k], grid[k + 1]) if k + 1 < len(sums) else flat[:0]
            if alike.sum() > flat.sum():
                resid.append((s - sums[k + 1])[alike])
            else:
                resid.append((s - flat_sum)[flat])
        resid = np.concatenate(resid)
        if len(resid) >= min_residuals:
            return _mad_sigma(resid)
    return _mad_sigma(np.concatenate([s - flat_sum for s in sums]))


class _FineExtremes:
    """The per-pixel maximum and minimum of the captures of every column bit the
    direct/global split may use (:func:`_separation_bits`: the ``count`` finest, or the
    ``count`` before the finest), gathered while the bits are read when only their
    differences are kept: the planes :func:`separate_light` gives the same split from."""

    def __init__(self, bits: int, count: int) -> None:
        self.last = bits - 1
        self.common = range(max(0, bits - count), bits - 1)  # in both candidates
        self.early = bits - count - 1 if bits > count else None  # only when the finest is skipped
        self.hi = self.lo = self.early_hi = self.early_lo = None

    def add(self, k: int, p: np.ndarray, q: np.ndarray) -> None:
        if k in self.common:
            if self.hi is None:
                self.hi, self.lo = np.maximum(p, q), np.minimum(p, q)
            else:
                for v in (p, q):
                    np.maximum(self.hi, v, out=self.hi)
                    np.minimum(self.lo, v, out=self.lo)
        elif k == self.early:
            self.early_hi, self.early_lo = np.maximum(p, q), np.minimum(p, q)

    def planes(self, fine: range, p_last: np.ndarray, q_last: np.ndarray) -> list[np.ndarray]:
        """Planes whose per-pixel maximum and minimum are those of bits ``fine``'s captures
        (``p_last``, ``q_last``: the finest bit's)."""
        out = [] if self.hi is None else [self.hi, self.lo]
        if self.last in fine:
            out += [p_last, q_last]
        if self.early is not None and self.early in fine:
            out += [self.early_hi, self.early_lo]
        return out


def separate_light(highs: Sequence[np.ndarray], black: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Direct and global light at each pixel from high-frequency binary captures.

    highs : captures (fractions of full scale) of high-frequency half-on patterns and their
        inverses; black : the capture under full black

    With ``L_max`` and ``L_min`` the per-pixel maximum and minimum over ``highs``: the
    pixel is lit in the image giving ``L_max`` and unlit in the one giving ``L_min``, and
    global light, spread from a wide surface area, is about half its full-white value in
    both (Nayar, Krishnan, Grossberg, Raskar, SIGGRAPH 2006). So ``direct = L_max -
    L_min`` (the global halves and the black level cancel) and ``global = 2 (L_min -
    black)`` (the unlit image carries only global light over the black level). The
    global estimate comes from ``L_min`` rather than ``white - direct`` so that it is
    independent of the white frame, which clips first; blur puts some direct light into
    ``L_min``, so both estimates err on the side of more global light, which makes the
    reliability rule stricter, not looser.
    """
    lmax = lmin = None
    for v in highs:
        if lmax is None:
            lmax, lmin = np.array(v, np.float32), np.array(v, np.float32)
        else:
            np.maximum(lmax, v, out=lmax)
            np.minimum(lmin, v, out=lmin)
    direct = lmax - lmin
    lmin -= black
    np.maximum(lmin, 0, out=lmin)
    lmin *= 2
    return direct, lmin


def bit_reliable(p: np.ndarray, q: np.ndarray, direct: np.ndarray, global_light: np.ndarray,
                 min_direct: float) -> np.ndarray:
    """Whether ``p > q`` reads a bit correctly whatever share of the global light each
    image got (Gupta et al., CVPR 2011; Xu and Aliaga's rule, made exact).

    A pixel the bit's pattern lights sees ``p = direct + a global`` and ``q = (1 - a)
    global`` (plus the same black level), for an unknown ``0 <= a <= 1``: low-frequency
    patterns light half the scene, so on concave or translucent surfaces ``a`` is far from
    1/2. So ``p - q`` lies in ``[direct - global, direct + global]`` when the bit is 1
    and in the mirror interval when it is 0; the two overlap on ``|p - q| <= global -
    direct``. The read is certain where ``|p - q| > global - direct`` (always where
    ``direct > global``, Gupta's condition), and uncertain where ``direct`` itself is
    under ``min_direct``. Gupta's second condition (the darker image below ``direct``,
    the brighter above ``global``) implies this one.
    """
    margin = np.abs(p - q)
    margin -= global_light
    margin += direct
    ok = margin > 0
    ok &= direct > min_direct
    return ok


def _inconsistent(value: np.ndarray, valid: np.ndarray, radius: int = CONSISTENCY_RADIUS,
                  tolerance: tuple[float, float] = CODE_TOLERANCE, min_neighbours: int = 3) -> np.ndarray:
    """Valid pixels whose code disagrees with most of their valid neighbours.

    A neighbour ``d`` pixels away (Chebyshev, up to ``radius``) agrees when the codes
    differ by at most ``tolerance[0] + tolerance[1] * d``. A pixel with at least
    ``min_neighbours`` valid neighbours of which fewer than half agree read a wrong
    bit (a global-light flip, a speck of noise): its 3D point would be an outlier.
    """
    h, w = value.shape
    count = np.zeros((h, w), np.uint8)
    agree = np.zeros((h, w), np.uint8)
    a, b = tolerance
    v = value.astype(np.int32)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy == 0 and dx == 0:
                continue
            ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
            xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
            there = valid[ys, xs]
            close = np.abs(v[ys, xs] - v[yd, xd]) <= a + b * max(abs(dy), abs(dx))
            close &= there
            count[yd, xd] += there
            agree[yd, xd] += close
    return valid & (count >= min_neighbours) & (2 * agree.astype(np.int16) < count)


def _separation_bits(diffs: _BitDiffs, contrast: np.ndarray, iy: np.ndarray, ix: np.ndarray,
                     xor: bool, count: int) -> range:
    """The column bits (indices into ``diffs``) the direct/global split uses: for XOR codes
    all (every image is high-frequency; the more phases, the closer the per-pixel maximum
    and minimum come to fully lit and unlit), else the ``count`` finest that blur leaves
    their contrast: the finest bit is skipped when its median ``|pattern - inverse|
    / (white - black)`` on the subsample ``(iy, ix)`` stays under
    ``SEPARATION_MIN_CONTRAST`` times the best of the ``count + 2`` finest bits' (global
    light lowers every high-frequency bit's contrast alike, blur the finest most)."""
    n = len(diffs)
    if xor:
        return range(n)
    c = contrast[iy, ix]
    keep = c > 0
    medians = {}
    for k in range(max(0, n - count - 2), n):
        if not keep.any():
            break
        d = diffs.read.fraction(diffs.pattern[k, iy, ix]) - diffs.read.fraction(diffs.inverse[k, iy, ix])
        medians[k] = float(np.median(np.abs(d[keep]) / c[keep]))
    last = n
    if medians:
        best = max(medians.values())
        # at most the finest bit: a coarser one losing contrast is global light acting at
        # the stripes' scale (subsurface scattering), which no finer bit would separate
        if medians[n - 1] < SEPARATION_MIN_CONTRAST * best and n > count:
            last = n - 1
    return range(max(0, last - count), last)


def _both(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
    """``a & b`` where None stands for all true."""
    if a is None or b is None:
        return b if a is None else a
    return a & b


def _fold_xor(code: np.ndarray, n: int, base: int | None) -> np.ndarray:
    """XOR codes: the Gray bits of ``n``-bit captured ``code`` (in place), each bit coarser
    than ``base`` XOR-ed back with the base bit (the finer ones are captured plain)."""
    if base is None:
        return code
    shift = n - 1 - base
    base_bit = (code >> shift) & 1
    code ^= base_bit * np.int32(((1 << n) - 1) ^ ((1 << (shift + 1)) - 1))
    return code


def _gray_to_value(code: np.ndarray) -> np.ndarray:
    """Binary values of reflected-binary ``code`` (int32), in place."""
    shift = code >> 1
    while shift.any():
        code ^= shift
        shift >>= 1
    return code


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
    ``diffs`` : (bits, h, w) ``pattern - inverse``, fractions of full scale (an array or
    :class:`_BitDiffs`). Run on transposed arrays, it searches along camera columns.
    """
    w = column.shape[1]
    bits = len(diffs)
    rows, xs = np.nonzero(valid)  # row-major: sorted by row, then x
    same_row = rows[1:] == rows[:-1]
    gap = xs[1:] - xs[:-1]
    c0, c1 = column[rows[:-1], xs[:-1]], column[rows[1:], xs[1:]]
    step = np.abs(c1 - c0)
    pair = same_row & (gap <= max_gap) & (step >= 1) & (step <= np.minimum(gap, 2))
    wide = np.flatnonzero(pair & (gap > 1))  # the pixels between the two must be lit
    for between in range(1, max_gap):
        wide = wide[gap[wide] > between]
        dark = ~lit[rows[wide], np.minimum(xs[wide] + between, w - 1)]
        pair[wide[dark]] = False
        wide = wide[~dark]
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
    pending = np.arange(len(r))  # not found yet, offset within the gap
    for offset in range(1, max_gap + 1):
        pending = pending[offset <= g[pending]]
        p_r, p_k = r[pending], k[pending]
        xi = np.minimum(x0[pending] + offset, w - 1)
        change = (diffs[p_k, p_r, xi] > 0) != sign0[pending]
        seg[pending[change]] = offset - 1
        found[pending[change]] = True
        pending = pending[~change]
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


def _edges_banded(column, valid, lit, diffs: _BitDiffs, white, saturated, max_gap, band=EDGE_BAND):
    """:func:`_edges` band by band of rows (each row's edges depend on that row alone)."""
    parts = []
    for r0 in range(0, column.shape[0], band):
        r1 = min(column.shape[0], r0 + band)
        s = _edges(column[r0:r1], valid[r0:r1], lit[r0:r1], diffs.rows(slice(r0, r1)),
                   white[r0:r1], saturated[r0:r1], max_gap)
        parts.append(s.shifted(r0, 0))
    return StripeSamples.concatenate(parts)


def _nearest_on(line: np.ndarray, pos: np.ndarray, stripe: np.ndarray,
                q_lines: Sequence[np.ndarray], q_pos: np.ndarray, q_stripe: np.ndarray) -> list[np.ndarray]:
    """(q,) distances along the line from each query ``(q_line, q_pos, q_stripe)`` to the
    nearest sample ``(line, pos, stripe)`` of the same stripe on line ``q_line`` (inf:
    none), one array for each of ``q_lines`` (the samples and positions ranked and sorted
    once for all of them)."""
    if len(line) == 0 or len(q_pos) == 0:
        return [np.full(len(q_pos), np.inf) for _ in q_lines]
    q_lines = [np.asarray(q, np.int64) for q in q_lines]
    lo = min(int(np.min(line)), *(int(np.min(q)) for q in q_lines)) - 1
    s_lo = min(int(np.min(stripe)), int(np.min(q_stripe)))
    span = max(int(np.max(line)), *(int(np.max(q)) for q in q_lines)) - lo + 2
    key = (np.asarray(stripe, np.int64) - s_lo) * span + (np.asarray(line, np.int64) - lo)
    n = len(line) + len(q_pos)
    rank = np.empty(n, np.int64)  # positions by rank, shared by samples and queries
    rank[np.argsort(np.concatenate([pos, q_pos]), kind="stable")] = np.arange(n)
    comp = key * n + rank[: len(line)]
    order = np.argsort(comp)
    sorted_comp, sorted_key = comp[order], key[order]
    found = []
    for q_line in q_lines:
        q_key = (np.asarray(q_stripe, np.int64) - s_lo) * span + (q_line - lo)
        at = np.searchsorted(sorted_comp, q_key * n + rank[len(line):])
        best = np.full(len(q_pos), np.inf)
        for cand in (at - 1, at):
            c = np.clip(cand, 0, len(line) - 1)
            same = (cand >= 0) & (cand < len(line)) & (sorted_key[c] == q_key)
            np.minimum(best, np.where(same, np.abs(pos[order[c]] - q_pos), np.inf), out=best)
        found.append(best)
    return found


def _nearest_shifted(line: np.ndarray, pos: np.ndarray, stripe: np.ndarray,
                     offsets: Sequence[int]) -> list[np.ndarray]:
    """:func:`_nearest_on` for each sample's own position and stripe on the lines
    ``line + d``, for each ``d`` in ``offsets`` (non-zero): (n,) distances (inf: none) per
    offset, the samples ranked and sorted once for all of them."""
    n = len(line)
    if n == 0:
        return [np.full(0, np.inf) for _ in offsets]
    line, stripe = np.asarray(line, np.int64), np.asarray(stripe, np.int64)
    lo = int(line.min()) + min(offsets) - 1
    span = int(line.max()) + max(offsets) - lo + 2  # every line + d in (lo, lo + span)
    key = (stripe - int(stripe.min())) * span + (line - lo)
    rank = np.empty(n, np.int64)  # positions by rank; a query's is its own sample's
    rank[np.argsort(pos, kind="stable")] = np.arange(n)
    comp = key * n + rank
    order = np.argsort(comp)
    sorted_comp, sorted_key = comp[order], key[order]
    found = []
    for d in offsets:
        # the query (key + d, rank) is no sample's (that sample's key is key): the samples
        # before it in order are at or left of it, those after at or right of it
        q_key = key + d
        at = np.searchsorted(sorted_comp, q_key * n + rank)
        best = np.full(n, np.inf)
        for cand in (at - 1, at):
            c = np.clip(cand, 0, n - 1)
            same = (cand >= 0) & (cand < n) & (sorted_key[c] == q_key)
            np.minimum(best, np.where(same, np.abs(pos[order[c]] - pos), np.inf), out=best)
        found.append(best)
    return found


def _both_axes(rows_found: StripeSamples, cols_found: StripeSamples) -> StripeSamples:
    """Edges found along rows and along columns (``cols_found`` with ``row`` the camera
    column, ``x`` the sub-pixel camera row), each boundary by the axis crossing it more
    steeply: along rows where the same boundary's nearest samples in the rows just above
    or below are within 1 px in x, along columns where those in the columns just left or
    right are within less than 1 px in y (at 45 degrees, rows win). A sample with no
    neighbour on either side stays unless the other axis has a sample of the same
    boundary within 1 px of it."""
    def steep(s: StripeSamples) -> np.ndarray:
        return np.minimum(*_nearest_shifted(s.row, s.x, s.stripe, (-1, 1)))

    def keep_lone(s: StripeSamples, near: np.ndarray, keep: np.ndarray, other: StripeSamples) -> None:
        """Lone samples of ``s`` stay unless ``other`` has the same boundary right there."""
        lone = np.flatnonzero(np.isinf(near))
        line = np.floor(s.x[lone]).astype(np.int64)
        there = np.minimum(*_nearest_on(other.row, other.x, other.stripe, [line, line + 1],
                                        s.row[lone].astype(float), s.stripe[lone]))
        keep[lone] = there > 1.0

    h_near, v_near = steep(rows_found), steep(cols_found)
    h_keep, v_keep = h_near <= 1.0, v_near < 1.0
    keep_lone(rows_found, h_near, h_keep, cols_found)
    keep_lone(cols_found, v_near, v_keep, rows_found)
    rows_found, cols_found = rows_found.subset(h_keep), cols_found.subset(v_keep)
    if len(cols_found) == 0:
        return rows_found
    y = cols_found.x
    turned = StripeSamples(
        row=np.floor(y + 0.5).astype(np.int32), x=cols_found.row.astype(np.float64),
        projector_column=cols_found.projector_column, stripe=cols_found.stripe,
        contrast=cols_found.contrast, saturated=cols_found.saturated, y=y,
        along_columns=np.ones(len(y), bool),
    )
    both = StripeSamples.concatenate([rows_found.with_y(), turned])
    return both.subset(np.lexsort((both.x, both.row)))


def decode_gray_images(
    images: Mapping[str, np.ndarray],
    descs: Sequence[PatternImage],
    white: np.ndarray,
    black: np.ndarray,
    *,
    threshold: str = "adaptive",
    min_contrast: float = 0.03,
    min_bit_ratio: float = 0.1,
    noise_sigmas: float = 3.0,
    noise: float | None = None,
    black_threshold: float = OPENCV_BLACK_THRESHOLD,
    white_threshold: float = OPENCV_WHITE_THRESHOLD,
    max_edge_gap: int = MAX_EDGE_GAP,
    edge_axes: str = "both",
    robust: bool | None = None,
    separation_bits: int = SEPARATION_BITS,
    consistency_radius: int = CONSISTENCY_RADIUS,
    drop_bits: int = 0,
    luma: bool = False,
    response: str = "linear",
    where: str = "",
) -> GrayResult:
    """Decode one view's Gray-code captures into projector columns (rows) and stripe edges.

    Parameters
    ----------
    images : mapping of pattern id to (h, w) or (h, w, 3) uint8/uint16 captures
        At least every Gray-code pattern of ``descs`` that is used; other entries are
        ignored, and each is read once, in the order column bits then row bits (pattern,
        inverse), so a mapping that reads on demand and forgets keeps memory bounded
        (:func:`decode_gray`'s also turns each capture into the grey plane kept of it as
        it reads ahead).
        RGB captures are read as the mean of their channels (or their luma: ``luma``;
        with ``threshold="opencv"`` as OpenCV's grey, :func:`opencv_grey`).
    descs : the session's pattern descriptions; only ``family == "gray"`` ones are used.
        A set missing some bits decodes with the leading run of bits present (a warning
        names the missing ones; see ``GrayResult.bits_used``).
    white, black : (h, w) or (h, w, 3) captures under full white and full black
    threshold : {"adaptive", "opencv"}
        ``"adaptive"``: ``white - black`` must exceed ``min_contrast`` and every bit's
        ``|pattern - inverse|`` both ``min_bit_ratio`` of ``white - black`` and
        ``noise_sigmas`` noise deviations. ``"opencv"``: OpenCV ``GrayCodePattern``'s
        fixed rule [3]_, ``|white - black| > black_threshold`` and every bit's
        ``|pattern - inverse| >= white_threshold`` (a bit is set where ``pattern >
        inverse``; codes beyond the projector are invalid), on the grey images as OpenCV
        users load them (:func:`opencv_grey`: RGB through ``cv2.cvtColor``, rounded) and
        in their DN: pass the captures as stored, never linearised (:func:`decode_gray`
        does). 16-bit captures: the thresholds times 257 (:data:`OPENCV_DN`); float
        captures: divided by 255.
    min_contrast : float
        ``white - black`` must exceed this fraction of full scale (shadow, background).
    min_bit_ratio : float
        Every bit's ``|pattern - inverse|`` must exceed this fraction of ``white - black``...
    noise_sigmas : float
        ...and this many standard deviations of the noise of ``pattern - inverse``.
    noise : float, optional
        That standard deviation, fraction of full scale; default: estimated from the
        column images (:func:`estimate_noise`), at least the quantisation noise.
    black_threshold, white_threshold : float, DN
        The ``"opencv"`` rule's thresholds (OpenCV's defaults 40 and 5).
    max_edge_gap : int, px
        Measure the edges between valid pixels up to this far apart along a row whose
        columns differ by one or two (the pixels between must pass ``min_contrast``);
        pixels right on an edge are often invalid, their flipping bit being too weak.
    edge_axes : {"both", "rows"}
        Search edges along camera rows and columns (each boundary keeps the samples of
        the axis crossing it more steeply), or along rows only (as before).
    robust : bool, optional
        Default: True with ``"adaptive"`` thresholds, False with ``"opencv"`` (OpenCV's
        rule alone, so the mask equals what OpenCV decodes).
        Reject codes global light may have corrupted instead of giving wrong 3D points:
        split each pixel's light into direct and global parts from the finest
        ``separation_bits`` column bits (:func:`separate_light`), drop pixels where a
        bit fails Gupta's rule (:func:`bit_reliable`; ``unreliable_global``), then
        pixels whose code disagrees with most valid neighbours within
        ``consistency_radius`` px (``inconsistent``; 0: no such test). False: the
        decoder as it was before (no separation, no rejection).
    separation_bits, consistency_radius : int
        See ``robust``.
    drop_bits : int
        Per-pixel bit dropping (Gray codes; XOR codes ignore it): a pixel whose finest
        column (row) bits are weak or unreliable but whose leading run of at least
        ``bits - drop_bits`` bits is readable (and reliable, with ``robust``) keeps the
        code of that run, the centre of its block of ``2**dropped`` columns (rows), as a
        set missing those bits would give it (``bits_used``); its edges are found only
        between such blocks, where both sides have the coarse bits. Subsurface
        scattering washes out the finest stripes first. 0: every bit or none.
    luma : bool
        Read RGB captures as their luma (BT.601 weights, :data:`LUMA_WEIGHTS`) instead of
        the mean of their channels: what :func:`decode_gray` does for lossy (JPEG) sessions,
        whose chroma is stored at half resolution. (``"opencv"`` reads OpenCV's grey.)
    response : {"linear", "srgb"}
        The integer captures' tone curve (``Session.response``): ``"srgb"`` captures,
        passed as stored, are linearised as they are read, giving exactly what decoding
        :func:`~slscan.capture.session.linearise`-d captures gives, without a float copy of
        each (:func:`decode_gray` does this). Float captures are taken as linear.
    where : str
        Prefix for error messages (e.g. the view folder).

    Returns
    -------
    GrayResult
        Decoded columns (and rows when the set has row codes), the validity mask, what
        limited it (``diagnostics``) and the sub-pixel stripe edges (sorted by row then
        x; a row that crosses the same boundary twice gives two). ``contrast`` of an
        edge sample is ``|d(xa)| + |d(xa + 1)|`` over ``white(xa) + white(xa + 1)``,
        with ``d`` the flipping bit's ``pattern - inverse`` at the two pixels around the
        crossing (1 for a step right between two pixels with no black level; blur and
        black lower it); ``saturated`` marks a clipped image at either pixel.

    Raises
    ------
    SlscanError
        A Gray-code pattern or its inverse missing from ``descs`` or ``images``, or
        images of mismatched size or pixel type (naming the pattern).
    """
    where = f"{where}: " if where and not where.endswith(": ") else where
    if threshold not in THRESHOLD_MODES:
        raise SlscanError(
            f"{where}unknown Gray-code threshold {threshold!r}: expected one of "
            f"{', '.join(THRESHOLD_MODES)}"
        )
    if edge_axes not in ("both", "rows"):
        raise SlscanError(f"{where}edge_axes must be 'both' or 'rows', got {edge_axes!r}")
    if not isinstance(drop_bits, (int, np.integer)) or isinstance(drop_bits, bool) or drop_bits < 0:
        raise SlscanError(f"{where}drop_bits must be an integer >= 0, got {drop_bits!r}")
    if separation_bits < 1 or consistency_radius < 0:
        raise SlscanError(
            f"{where}separation_bits must be at least 1 and consistency_radius at least 0, "
            f"got {separation_bits} and {consistency_radius}"
        )
    col_bits, row_bits = gray_bits(descs, "columns"), gray_bits(descs, "rows")
    if not col_bits.pairs:
        if col_bits.bits:
            raise SlscanError(
                f"{where}the Gray-code column patterns lack their most significant bit 0: "
                "nothing to decode"
            )
        raise SlscanError(f"{where}the pattern set has no Gray-code column patterns to decode")
    for axis, b in (("column", col_bits), ("row", row_bits)):
        if b.missing:
            log.warning(
                "%sGray-code %s bit(s) %s missing: decoding the %d leading bits of %d, "
                "%ss to blocks of %d%s", where, axis, ", ".join(map(str, b.missing)),
                len(b.pairs), b.bits, axis, 2**b.coarse,
                f" (bits {', '.join(map(str, b.unused))} left unused)" if b.unused else "",
            )
    width = height = None
    for d in descs:
        if d.family == "gray":
            width, height = d.width, d.height
            break
    col_pairs, row_pairs = list(col_bits.pairs), list(row_bits.pairs)
    for pid in (p for pair in col_pairs + row_pairs for p in pair):
        if pid not in images:
            raise SlscanError(f"{where}no captured image of Gray-code pattern {pid!r}")
    white = np.asarray(white)
    if white.ndim not in (2, 3) or (white.ndim == 3 and white.shape[2] not in (1, 3)):
        raise SlscanError(
            f"{where}white: expected an (h, w) or (h, w, 3) image, got shape {white.shape}"
        )
    full_scale(white, f"{where}white")
    read = _Reader(white, where, luma, opencv=threshold == "opencv", response=response)
    if robust is None:
        robust = threshold == "adaptive"
    w_img, b_img = read(white, "white"), read(black, "black")
    full_contrast = w_img - b_img
    if threshold == "opencv":  # on the levels: no rounding at ties (white - black = 40 DN)
        wl, bl = read.levels(white, "white"), read.levels(black, "black")
        if read.lut is not None:
            wl, bl = wl.astype(np.int64), bl.astype(np.int64)
        full_lit = np.abs(wl - bl) > read.level_threshold(black_threshold)
        del wl, bl
    else:
        full_lit = full_contrast > min_contrast
    n_dark = int(full_lit.size) - int(full_lit.sum())  # before `lit` (a view of it) narrows
    # the rest runs on the lit pixels' bounding box: outside it nothing decodes
    read.box = box = lit_bounds(full_lit, max_edge_gap + 2)
    y0, x0 = box[0].start, box[1].start
    w_img, b_img, contrast, lit = w_img[box], b_img[box], full_contrast[box], full_lit[box]
    # the noise estimate's subsample of lit pixels
    idx = _noise_index(lit, len(col_pairs))
    iy, ix = np.divmod(idx, lit.shape[1])
    flat_sub = w_img[iy, ix] + b_img[iy, ix]
    black_box = b_img if robust else None  # for the direct/global split
    del b_img

    # column bits: both captures' levels kept (1 byte a pixel each for 8-bit grey), for
    # the thresholds once the noise is known, for the noise estimate and for the edges;
    # float levels of plain Gray codes (float or linearised captures) as their difference,
    # with what the noise estimate and the direct/global split take from each capture
    shape = (len(col_pairs),) + contrast.shape
    as_diff = _KEEP_DIFFERENCES and read.lut is None and col_bits.base is None
    split = extremes = None
    if as_diff:
        col_diffs = _BitDiffs(read, np.empty(shape, np.float32), np.broadcast_to(np.float32(0), shape), None, [])
        extremes = _FineExtremes(len(col_pairs), separation_bits) if robust else None
    else:
        col_diffs = _BitDiffs(read, np.empty(shape, read.level_dtype), np.empty(shape, read.level_dtype),
                              col_bits.base)
    for k, (pid, inv) in enumerate(col_pairs):
        if not as_diff:
            col_diffs.pattern[k] = read.levels(images[pid], pid)
            col_diffs.inverse[k] = read.levels(images[inv], inv)
            continue
        p, q = read.levels(images[pid], pid), read.levels(images[inv], inv)
        np.subtract(p, q, out=col_diffs.pattern[k])
        col_diffs.sums.append(p[iy, ix] + q[iy, ix])
        if extremes is not None:
            extremes.add(k, p, q)
            if k == len(col_pairs) - 1:  # every bit read: split the light now, the finest in hand
                fine = _separation_bits(col_diffs, contrast, iy, ix, False, separation_bits)
                split = separate_light(extremes.planes(fine, p, q), black_box)
                extremes = black_box = None
        del p, q
    estimated = estimate_noise(col_diffs, flat_sub, iy, ix)
    del flat_sub
    if noise is not None:
        sigma = float(noise)
    else:  # at least the quantisation noise of a difference of two images (0.41 DN;
        # float captures count 255 DN to full scale, as ``read.dn`` says)
        sigma = max(estimated, np.sqrt(2 / 12) / read.dn)

    ratio_binds = None
    if threshold == "opencv":
        level_threshold = read.level_threshold(white_threshold)

        def strong(pattern: np.ndarray, inverse: np.ndarray, fractions=None) -> np.ndarray:
            if read.lut is None:
                return np.abs(pattern - inverse) >= level_threshold
            return np.abs(pattern.astype(np.int64) - inverse) >= level_threshold
    else:
        noise_term = np.float32(noise_sigmas * sigma)
        ratio_term = min_bit_ratio * contrast
        ratio_binds = ratio_term > noise_term
        bit_threshold = np.maximum(ratio_term, noise_term)
        del ratio_term
        lit &= contrast > bit_threshold  # a pixel must at least carry a readable signal

        def strong(pattern: np.ndarray, inverse: np.ndarray, fractions=None) -> np.ndarray:
            p, q = fractions or (read.fraction(pattern), read.fraction(inverse))
            return np.abs(p - q) > bit_threshold

    direct = global_light = None
    if robust:  # direct/global split from the finest column bits (Nayar et al. 2006)
        # XOR codes: every image is high-frequency, and the more phases the closer the
        # per-pixel maximum and minimum come to fully lit and fully unlit under blur
        if split is not None:
            direct, global_light = split
        else:
            fine = _separation_bits(col_diffs, contrast, iy, ix, col_bits.base is not None, separation_bits)
            direct, global_light = separate_light(
                (read.fraction(lv[k]) for k in fine for lv in (col_diffs.pattern, col_diffs.inverse)), black_box)
        del split
        min_direct = float(noise_sigmas * sigma)

    def start(bits: GrayBits) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        # XOR codes need no reliability rule: every image is high-frequency, so global
        # light falls evenly on pattern and inverse and cancels in their difference
        rule = robust and bits.base is None
        return (np.zeros(contrast.shape, np.int32), np.ones(contrast.shape, bool),
                np.ones(contrast.shape, bool) if rule else None)

    def add_bit(code: np.ndarray, ok: np.ndarray, reliable: np.ndarray | None,
                pattern: np.ndarray, inverse: np.ndarray, run: tuple | None = None) -> None:
        code <<= 1
        np.bitwise_or(code, pattern > inverse, out=code)  # the same sign as the fractions'
        # the captures' fractions, once for both tests
        fractions = (read.fraction(pattern), read.fraction(inverse)) if reliable is not None else None
        good = strong(pattern, inverse, fractions)
        ok &= good
        if reliable is not None:
            rel = bit_reliable(*fractions, direct, global_light, min_direct)
            reliable &= rel
            good &= rel
        if run is not None:  # the leading run of readable (reliable) bits
            so_far, lead = run
            so_far &= good
            lead += so_far

    def new_run(bits: GrayBits) -> tuple | None:
        if not drop_bits or bits.base is not None:
            return None
        return np.ones(contrast.shape, bool), np.zeros(contrast.shape, np.uint8)

    col_code, col_strong, col_rel = start(col_bits)
    col_run = new_run(col_bits)
    for k in range(len(col_pairs)):
        add_bit(col_code, col_strong, col_rel, col_diffs.pattern[k], col_diffs.inverse[k], col_run)
    col_value = _gray_to_value(_fold_xor(col_code, len(col_pairs), col_bits.base))
    col_in = col_value < -(-width // 2**col_bits.coarse)
    col_valid = lit & col_strong & col_in
    all_strong, in_range, all_rel = col_strong, col_in, col_rel
    row_value = row_valid = row_run = None
    if row_pairs:  # row bits: folded into the code as they are read
        row_code, row_strong, row_rel = start(row_bits)
        row_run = new_run(row_bits)
        for pid, inv in row_pairs:
            add_bit(row_code, row_strong, row_rel, read.levels(images[pid], pid),
                    read.levels(images[inv], inv), row_run)
        row_value = _gray_to_value(_fold_xor(row_code, len(row_pairs), row_bits.base))
        row_in = row_value < -(-height // 2**row_bits.coarse)
        row_valid = lit & row_strong & row_in
        all_strong, in_range = col_strong & row_strong, col_in & row_in
        if robust:
            all_rel = _both(col_rel, row_rel)
    mask = lit & all_strong & in_range
    n_unreliable = n_inconsistent = 0
    if robust:
        if all_rel is None:
            all_rel = np.ones_like(mask)
        n_unreliable = int((mask & ~all_rel).sum())
        if col_rel is not None:
            col_valid &= col_rel
        if row_valid is not None and row_rel is not None:
            row_valid &= row_rel
        if consistency_radius:
            col_valid &= ~_inconsistent(col_value, col_valid, consistency_radius)
            if row_valid is not None:
                row_valid &= ~_inconsistent(row_value, row_valid, consistency_radius)
        new_mask = col_valid if row_valid is None else col_valid & row_valid
        n_inconsistent = int((mask & all_rel).sum()) - int(new_mask.sum())
        mask = new_mask

    # per-pixel bit dropping: pixels whose leading run of good bits is long enough
    col_drop = row_drop = None
    n_dropped = 0
    if col_run is not None or row_run is not None:
        col_value, col_drop, col_extra = _drop_codes(col_value, col_valid, col_run, lit, len(col_pairs),
                                                     drop_bits, -(-width // 2**col_bits.coarse))
        extra = col_extra
        if row_value is not None:
            row_value, row_drop, row_extra = _drop_codes(row_value, row_valid, row_run, lit, len(row_pairs),
                                                         drop_bits, -(-height // 2**row_bits.coarse))
            extra = (col_valid | col_extra) & (row_valid | row_extra) & ~(col_valid & row_valid)
            row_valid = row_valid | row_extra
        col_valid = col_valid | col_extra
        if robust and consistency_radius:  # the coarse codes against their neighbours
            centre = _block_centres(col_value, col_drop)
            col_valid &= ~(_inconsistent(centre, col_valid, consistency_radius) & (col_drop > 0))
            if row_value is not None:
                centre = _block_centres(row_value, row_drop)
                row_valid &= ~(_inconsistent(centre, row_valid, consistency_radius) & (row_drop > 0))
        new_mask = col_valid if row_valid is None else col_valid & row_valid
        extra &= new_mask
        n_dropped = int(extra.sum())
        mask = mask | extra

    weak = lit & ~all_strong
    n_lit = int(lit.sum())
    n_weak = int(weak.sum())
    n_weak_ratio = 0 if ratio_binds is None else int((weak & ratio_binds).sum())
    diagnostics = {
        "threshold_mode": threshold,
        "noise_dn": float(sigma * read.dn),
        "pixels": int(full_lit.size),
        "lit": n_lit,
        "low_contrast": int(full_lit.size) - n_lit,
        "dark": n_dark,
        "weak_bit_noise": n_weak - n_weak_ratio,
        "weak_bit_ratio": n_weak_ratio,
        "out_of_range": int((lit & all_strong & ~in_range).sum()),
        "valid": int(mask.sum()),
    }
    if drop_bits:
        diagnostics["bits_dropped"] = n_dropped
    if robust:
        diagnostics["unreliable_global"] = n_unreliable
        diagnostics["inconsistent"] = n_inconsistent
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = global_light[lit] / direct[lit]
        ratio = ratio[np.isfinite(ratio)]
        diagnostics["global_direct_median"] = float(np.median(ratio)) if len(ratio) else 0.0
    del weak, all_strong, in_range, ratio_binds, black_box

    saturated = read.saturated[box]
    levels = []  # edges between blocks of 2**d columns among pixels with at least bits - d bits
    for d in range(1 if col_drop is None else int(col_drop[col_valid].max(initial=0)) + 1):
        valid_d = col_valid if col_drop is None else col_valid & (col_drop <= d)
        value_d = col_value >> d
        diffs_d = col_diffs if not d else _BitDiffs(read, col_diffs.pattern[: len(col_pairs) - d],
                                                    col_diffs.inverse[: len(col_pairs) - d], col_bits.base)
        found = _edges_banded(value_d, valid_d, lit, diffs_d, w_img, saturated, max_edge_gap)
        if edge_axes == "both":
            across = _edges_banded(value_d.T, valid_d.T, lit.T, diffs_d.T, w_img.T, saturated.T,
                                   max_edge_gap)
            found = _both_axes(found, across)
        if d:  # stripe: the boundary's low column; a boundary a finer level has is kept there
            stripe = (found.stripe.astype(np.int64) + 1) * 2**d - 1
            found = replace(found, stripe=stripe.astype(np.int32),
                            projector_column=stripe.astype(np.float64) + 0.5)
            found = found.subset(~np.isin(_edge_keys(found), np.concatenate([_edge_keys(f) for f in levels])))
        levels.append(found)
    edges = levels[0]
    if len(levels) > 1:
        edges = StripeSamples.concatenate([e.with_y() for e in levels])
        edges = edges.subset(np.lexsort((edges.x, edges.row)))
    del col_diffs, diffs_d  # the column planes, before the maps are put together
    edges = _coarse_edges(edges, col_bits.coarse).shifted(y0, x0)

    def to_map(value: np.ndarray, valid: np.ndarray, coarse: int, size: int) -> np.ndarray:
        if coarse:  # the centre of the block of 2**coarse
            value = np.minimum((value << coarse) + (1 << (coarse - 1)), size - 1)
        return uncrop(np.where(valid, value, -1).astype(np.int32), box, full_lit.shape, -1)

    if col_drop is not None:  # dropped bits: the centre of the block, in the set's units
        col_value = np.where(col_valid, _block_centres(col_value, col_drop), col_value)
    if row_drop is not None:
        row_value = np.where(row_valid, _block_centres(row_value, row_drop), row_value)
    column = to_map(col_value, col_valid, col_bits.coarse, width)
    row = None if row_value is None else to_map(row_value, row_valid, row_bits.coarse, height)
    mask = uncrop(mask, box, full_lit.shape, False)
    if robust:
        direct = uncrop(direct, box, full_lit.shape, 0.0)
        global_light = uncrop(global_light, box, full_lit.shape, 0.0)
    log.debug(
        "%sGray code: %.1f%% pixels decoded, %d edges (%d along columns), noise %.2f DN",
        where,
        100 * mask.mean(),
        len(edges),
        0 if edges.along_columns is None else int(edges.along_columns.sum()),
        sigma * read.scale,
    )
    bits_used = {"columns": (len(col_pairs), col_bits.bits)}
    if row_bits.bits:
        bits_used["rows"] = (len(row_pairs), row_bits.bits)
    return GrayResult(
        column=column,
        row=row,
        mask=mask,
        edges=edges,
        contrast=full_contrast,
        saturated=read.saturated,
        noise=sigma,
        bits_used=bits_used,
        diagnostics=diagnostics,
        direct=direct,
        global_light=global_light,
    )


def _drop_codes(value: np.ndarray, valid: np.ndarray, run: tuple | None, lit: np.ndarray, bits: int,
                drop_bits: int, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel bit dropping: ``(value, dropped, extra)`` with ``dropped`` the finest
    bits each pixel lacks (0 where ``valid`` already holds), ``extra`` the pixels not in
    ``valid`` whose leading run of good bits (``run``) is at least ``bits - drop_bits``
    long and whose block (``value >> dropped``; the leading bits of a Gray code decode to
    the leading bits of its value) starts inside the ``size`` columns (rows)."""
    if run is None:
        return value, np.zeros(value.shape, np.uint8), np.zeros(value.shape, bool)
    _, lead = run
    dropped = (bits - lead.astype(np.int32)).astype(np.uint8)
    dropped[valid] = 0
    extra = lit & ~valid & (dropped >= 1) & (dropped <= min(drop_bits, bits - 1))
    extra &= ((value >> dropped) << dropped) < size
    dropped[~valid & ~extra] = 0
    return value, dropped, extra


def _block_centres(value: np.ndarray, dropped: np.ndarray | None) -> np.ndarray:
    """``value`` with its ``dropped`` finest bits replaced by the centre of their block."""
    if dropped is None or not dropped.any():
        return value
    d = dropped.astype(np.int32)
    half = np.where(d > 0, np.left_shift(1, np.maximum(d - 1, 0)), 0)
    return ((value >> d) << d) + half


def _edge_keys(edges: StripeSamples) -> np.ndarray:
    """One int64 key per sample: its line (camera row, or column for samples found along
    columns), axis and boundary."""
    along = np.zeros(len(edges), bool) if edges.along_columns is None else edges.along_columns
    line = np.where(along, np.round(edges.x), edges.row).astype(np.int64)
    return (np.asarray(edges.stripe, np.int64) * 2 + along) * (1 << 24) + line


def _coarse_edges(edges: StripeSamples, coarse: int) -> StripeSamples:
    """Edges between blocks of ``2**coarse`` columns: ``stripe`` stays the block index (so
    neighbouring edges have consecutive stripes), ``projector_column`` the plane between
    the blocks' outer columns."""
    if not coarse:
        return edges
    return replace(edges, projector_column=(edges.stripe.astype(np.float64) + 1) * 2**coarse - 0.5)


class _Streamed(Mapping):
    """Captures by pattern id, read by a background thread in the order given, at most
    ``ahead`` waiting; each is handed out once and then forgotten, so a view's images are
    never all in memory. Use it in a ``with`` block."""

    def __init__(self, read: Callable[[Hashable], np.ndarray], keys: Sequence[Hashable],
                 ahead: int = PREFETCH) -> None:
        self._read, self._keys, self._ahead = read, list(dict.fromkeys(keys)), max(1, ahead)
        self._known = set(self._keys)
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="slscan-read")
        self._futures: dict[Hashable, Future] = {}
        self._next = 0
        self._fill()

    def _fill(self) -> None:
        while self._next < len(self._keys) and len(self._futures) < self._ahead:
            key = self._keys[self._next]
            self._futures[key] = self._pool.submit(self._read, key)
            self._next += 1

    def __getitem__(self, key: Hashable) -> np.ndarray:
        future = self._futures.pop(key, None)
        if future is None:
            if key not in self._known:
                raise KeyError(key)
            value = self._read(key)  # asked out of order, or again: read it now
        else:
            value = future.result()
        self._fill()
        return value

    def __contains__(self, key: object) -> bool:
        return key in self._known

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self._keys)

    def __len__(self) -> int:
        return len(self._keys)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        for future in self._futures.values():
            future.cancel()
        self._pool.shutdown(wait=True)
        self._futures.clear()


def decode_gray(session: Session, view: ViewRecord | str, **options) -> GrayResult:
    """Read and decode the Gray-code images of ``view`` in ``session``.

    ``options`` are passed to :func:`decode_gray_images`. The images are read as stored
    (a JPEG decoded once) by a background thread a couple ahead of the decoder, and
    dropped once used; the decoder reads each into the grey plane it keeps in linear light
    (the camera's curve, ``session.response``, undone through lookup tables), but as
    stored for ``threshold="opencv"``, whose DN thresholds apply to the images as OpenCV
    users load them.

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
    records = {pid: view.image_for(pid) for pid in ids}
    # read as stored; in linear light (an sRGB camera's curve undone as the decoder reads
    # each capture), but for OpenCV's rule
    opencv = options.get("threshold", "adaptive") == "opencv"
    if not opencv:
        options.setdefault("response", session.response)
    options.setdefault("luma", session.lossy)
    ahead: list[_Reader] = []  # the reading thread's reader, made from the white frame

    def read(pid: str) -> np.ndarray | _Read:
        image = session.read_image(view, records[pid])
        if pid == white_id:
            ahead.append(_Reader(image, where, options["luma"], opencv=opencv,
                                 response=options.get("response", "linear")))
        if pid in (white_id, black_id) or not ahead:
            return image
        return ahead[0].read_ahead(image)  # the pattern's levels, made while the decoder works

    with _Streamed(read, ids) as images:
        white, black = images[white_id], images[black_id]
        result = decode_gray_images(images, descs, white, black, where=where, **options)
    return replace(result, white=white)  # colour downstream from the capture as saved


# --- the Gray-code family's decoder (slscan.patterns.graycode.FAMILY) ---------------------------


@dataclass(frozen=True)
class GrayAxes:
    """One view's Gray code decoded along both camera axes.

    columns : the usual decode: projector column and row per camera pixel, and the column
        edges along camera rows
    rows : edges of the projector rows, as (k,) arrays ``x``, ``y`` (camera px; one of the two
        sub-pixel, whichever axis crossed the stripes) and ``value`` (projector row ``r + 0.5``)
    """

    columns: GrayResult
    row_x: np.ndarray
    row_y: np.ndarray
    row_value: np.ndarray


def decode_gray_axes(session: Session, view: ViewRecord) -> GrayAxes:
    """Decode a view's Gray code (with row codes), and the row edges along camera columns.

    The row edges come from decoding the transposed images with rows and columns swapped
    in the pattern descriptions (:func:`slscan.decode.graycode.decode_gray_images`). The
    captures are read in linear light (:meth:`Session.read_image` ``linear=True``: an sRGB
    camera's curve undone), as :func:`~slscan.decode.graycode.decode_gray` reads them, so
    the column decode is the decode stage's and the thresholds and the direct/global split
    see light, not tone-curve codes.

    Raises
    ------
    SlscanError
        The session has no row codes, or an image is missing or does not match.
    """
    descs = [p for p in session.patterns if p.family == "gray"]
    if not any(d.axis == "rows" for d in descs):
        raise SlscanError(f"{session.root}: the session has no Gray-code row patterns")
    where = str(session.root / view.name)
    flat = {tuple(p.params.get("value", [])): p.id for p in session.patterns if p.family == "flat"}
    if (255, 255, 255) not in flat or (0, 0, 0) not in flat:
        raise SlscanError(f"{session.root}: the pattern set needs all-white and all-black frames")

    def read(pid: str) -> np.ndarray:
        return session.read_image(view, view.image_for(pid), linear=True)

    images = {d.id: read(d.id) for d in descs}
    white, black = read(flat[(255, 255, 255)]), read(flat[(0, 0, 0)])
    # lossy (JPEG) RGB captures read as luma, as decode_gray reads them
    columns = decode_gray_images(images, descs, white, black, where=where, luma=session.lossy)
    rows = decode_gray_images(
        {k: _transposed(v) for k, v in images.items()},
        _swap_axes(descs),
        _transposed(white),
        _transposed(black),
        where=where,
        noise=columns.noise,
        luma=session.lossy,
    )
    e = rows.edges
    return GrayAxes(
        # the transposed decode's (x, y) are the camera's (y, x); its samples may have been
        # found along either axis, so take the sub-pixel position either way
        columns, e.camera_y, e.x.astype(float), e.projector_column.astype(float)
    )


def _transposed(image: np.ndarray) -> np.ndarray:
    """A capture transposed (camera rows for columns), channels and values as they are, so
    the decoder reads it as it read the capture."""
    return np.ascontiguousarray(np.swapaxes(image, 0, 1))


def _swap_axes(descs: Sequence[PatternImage]) -> list[PatternImage]:
    """Pattern descriptions with rows and columns swapped, for the transposed captures."""
    swap = {"rows": "columns", "columns": "rows"}
    return [replace(d, axis=swap[d.axis], width=d.height, height=d.width) for d in descs]


def decode_gray_transposed(session: Session, view: ViewRecord | str, **options) -> GrayResult:
    """:func:`decode_gray` on the transposed captures with rows and columns swapped: its
    ``edges`` are the sub-pixel edges of the projector **rows** (``projector_column`` is the
    row ``r + 0.5``), in the transposed frame: a sample's ``row`` is a camera column and ``x``
    a camera row (found along camera columns), or, with ``along_columns``, ``x`` a camera
    row and ``y`` a camera column (found along camera rows). Read as :func:`decode_gray`
    reads (in linear light unless ``threshold="opencv"``), streamed."""
    if isinstance(view, str):
        view = session.view(view)
    descs = [p for p in session.patterns if p.family == "gray"]
    if not any(d.axis == "rows" for d in descs):
        raise SlscanError(f"{session.root}: the session has no Gray-code row patterns")
    white_id, black_id = session.flat_frame_ids("Gray-code decoding")
    pairs = gray_pairs(descs, "rows") + gray_pairs(descs, "columns")  # read in the transposed decode's order
    ids = [white_id, black_id, *(p for pair in pairs for p in pair)]
    records = {pid: view.image_for(pid) for pid in ids}
    linear = options.get("threshold", "adaptive") != "opencv"
    with _Streamed(lambda pid: _transposed(session.read_image(view, records[pid], linear=linear)), ids) as images:
        white, black = images[white_id], images[black_id]
        options.setdefault("luma", session.lossy)
        return decode_gray_images(images, _swap_axes(descs), white, black,
                                  where=str(session.root / view.name), **options)


EDGE_BIAS_PX = 0.034
"""Camera px: the error of a stripe edge located by linear interpolation of the blurred
pattern - inverse, which depends on the edge's sub-pixel phase (virtual tile, noise-free:
RMS 0.034 px, up to 0.045; ``tests/decode/test_triangulate.py``). It changes slowly along
an edge, so neighbouring rows do not show it (:func:`edge_noise`) and averaging along the
edge does not remove it: the floor of an edge's error in the axis weights."""
SMOOTHED_NOISE = 0.612
"""Noise left in an edge position averaged ``[1, 2, 1] / 4`` along its edge (``sqrt(6) / 4``)."""
INTERPOLATED_NOISE = 0.816
"""Noise left in a value interpolated linearly between two edges, each with unit noise, at
a uniformly random place between them (``sqrt(2 / 3)``)."""


def edge_noise(edges: StripeSamples) -> tuple[float, float]:
    """The position noise of stripe edges and their spacing, camera px: the robust standard
    deviation (1.4826 MAD) of each edge's position about the mean of its neighbours on the
    lines before and after it, over ``sqrt(1.5)`` (independent noise; a straight or slanted
    edge cancels), and the median distance between consecutive edges along a line. The
    noise over the spacing is the edges' noise in projector px. NaN where too few."""
    if len(edges) < 10:
        return float("nan"), float("nan")
    before, after = edges._along_feature(2.0)
    line, pos = edges.lines()
    inner = np.isfinite(before) & np.isfinite(after)
    resid = pos[inner] - 0.5 * (before[inner] + after[inner])
    noise = 1.4826 * float(np.median(np.abs(resid))) / np.sqrt(1.5) if len(resid) >= 10 else float("nan")
    order = np.lexsort((pos, line))
    same = (line[order][1:] == line[order][:-1]) & (np.abs(np.diff(edges.stripe[order].astype(np.int64))) == 1)
    gaps = np.diff(pos[order])[same]
    spacing = float(np.median(gaps)) if len(gaps) else float("nan")
    return noise, spacing


def _bracket(line: np.ndarray, pos: np.ndarray, value: np.ndarray, q_line: np.ndarray, q_pos: np.ndarray,
             max_step: float) -> np.ndarray:
    """(q,) the value at ``q_pos`` on line ``q_line``, interpolated linearly between the edges
    ``(line, pos, value)`` (sorted by line, then pos) just before and after it, where those
    are 1 or 2 rows apart and at most ``max_step`` px per row apart; NaN elsewhere."""
    n = len(line)
    out = np.full(len(q_pos), np.nan)
    if n < 2 or len(q_pos) == 0:
        return out
    span = float(max(np.max(pos), np.max(q_pos)) + 2.0)
    key = line * span + pos
    i = np.searchsorted(key, q_line * span + q_pos, side="right")
    a, b = np.clip(i - 1, 0, n - 1), np.clip(i, 0, n - 1)
    dv, dp = value[b] - value[a], pos[b] - pos[a]
    ok = (i > 0) & (i < n) & (line[a] == q_line) & (line[b] == q_line)
    ok &= (np.abs(dv) > 0.5) & (np.abs(dv) < 2.5) & (dp > 0) & (dp <= max_step * np.abs(dv))
    with np.errstate(divide="ignore", invalid="ignore"):
        v = value[a] + (q_pos - pos[a]) / dp * dv
    out[ok] = v[ok]
    return out


def _between_lines(line, pos, value, q_across, q_along, max_step) -> np.ndarray:
    """The value at ``(q_across, q_along)`` from the lines ``floor(q_across)`` and the next,
    weighted linearly (one line alone where the other has none and it is the nearer)."""
    base = np.floor(q_across)
    t = q_across - base
    v0 = _bracket(line, pos, value, base, q_along, max_step)
    v1 = _bracket(line, pos, value, base + 1, q_along, max_step)
    both = (1 - t) * v0 + t * v1
    return np.where(np.isfinite(both), both, np.where(t <= 0.5, v0, v1))


def rows_at(row_edges: StripeSamples, x: np.ndarray, y: np.ndarray, *, max_step: float) -> np.ndarray:
    """(k,) the continuous projector row at camera points ``(x, y)`` (k,) px, interpolated
    between the row edges (:func:`decode_gray_transposed`'s, transposed frame) on the camera
    columns (rows) either side: first from the edges found along camera columns, else from
    those found along camera rows; NaN where no two consecutive edges bracket the point
    within ``max_step`` camera px per projector row."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    e = row_edges
    along_rows = np.zeros(len(e), bool) if e.along_columns is None else np.asarray(e.along_columns, bool)
    value = np.asarray(e.projector_column, np.float64)
    out = np.full(len(x), np.nan)
    for sel, across, along in ((~along_rows, x, y), (along_rows, y, x)):
        if not sel.any():
            continue
        if along is x:  # found along camera rows: line = the camera row, pos = the camera x
            line, pos = np.rint(np.asarray(e.x, np.float64)[sel]), e.camera_y[sel]
        else:  # along camera columns: line = the camera column, pos = the camera y
            line, pos = np.asarray(e.row, np.float64)[sel], np.asarray(e.x, np.float64)[sel]
        order = np.lexsort((pos, line))
        todo = ~np.isfinite(out)
        out[todo] = _between_lines(line[order], pos[order], value[sel][order], across[todo], along[todo], max_step)
    return out


def decode(session: Session, view: ViewRecord | str, config) -> FamilyDecode:
    """The Gray-code family's decode for a range map (:mod:`slscan.decode.family`): the
    sub-pixel stripe edges, averaged along their edge when ``config.gray_smooth``, with the
    mesh's bridge widened for sets missing low bits or pixels dropping them.

    With row codes and a calibrated projector whose rows pin depth better than its columns
    (``config.projector_axes``, :func:`slscan.decode.triangulate.choose_axes`), each column
    edge also gets its continuous projector row, interpolated from the row edges
    (:func:`rows_at`; the captures decoded a second time, transposed), so triangulation
    uses both axes, each weighted by its noise (``stats``: ``column_noise_px``,
    ``row_noise_px``, projector px: the edges' noise measured along them, :func:`edge_noise`,
    with the estimator's bias :data:`EDGE_BIAS_PX` as a floor, over the edges' spacing);
    column edges whose row cannot be interpolated are left out
    (``stats["rows_missing_share"]``)."""
    from slscan.decode.codes import codes_from_gray, valid_share

    view = session.view(view) if isinstance(view, str) else view
    options = {"threshold": config.gray_threshold, "robust": config.gray_robust_applied,
               "drop_bits": config.gray_drop_bits}
    res = decode_gray(session, view, **options)
    samples = res.edges.smoothed() if config.gray_smooth else res.edges
    factor = SMOOTHED_NOISE if config.gray_smooth else 1.0
    noise, spacing = edge_noise(res.edges)
    stats = {"column_noise_px": float(np.hypot(factor * np.nan_to_num(noise), EDGE_BIAS_PX) / spacing)}
    axes = _axes_for(session, res, samples, getattr(config, "projector_axes", "auto"))
    if axes == "both":
        rows = decode_gray_transposed(session, view, noise=res.noise, **options)
        row_edges = rows.edges.smoothed() if config.gray_smooth else rows.edges
        r_noise, r_spacing = edge_noise(rows.edges)
        if not np.isfinite(r_spacing):
            log.warning("%s: too few projector row edges (%d) to use the rows; triangulating the columns",
                        session.root / view.name, len(rows.edges))
            axes = "columns"
    if axes == "both":
        v = rows_at(row_edges, samples.x, samples.camera_y, max_step=2.0 * r_spacing)
        # a column edge without its row would fall back on the column alone, the axis the
        # geometry (or the user) turned away from: left out (kamino410 capture_0: those 6 %
        # of the samples were 5.8 mm RMS from the board's plane, the others 0.47 mm)
        has_row = np.isfinite(v)
        samples = replace(samples, projector_row=v).subset(has_row)
        stats["row_noise_px"] = float(INTERPOLATED_NOISE * np.hypot(factor * np.nan_to_num(r_noise), EDGE_BIAS_PX) / r_spacing)
        stats["rows_missing_share"] = float(1.0 - has_row.mean()) if len(has_row) else 0.0
    used, bits = res.bits_used.get("columns", (0, 0))
    # a set missing low bits has edges 2**missing columns apart, and pixels with dropped bits
    # 2**dropped: bridge one such spacing and a half (the default 6 columns already span blocks of 4)
    gap = max(config.max_gap_columns, 1.5 * 2**config.gray_drop_bits) * 2 ** (bits - used)
    return FamilyDecode(
        samples=samples, mask=res.mask, codes=res.column, code_max=session.projector_size[0],
        saturated=res.saturated, white=res.white, max_gap_columns=gap,
        projector_codes=codes_from_gray(res, session, view.name), valid_share=valid_share(res),
        stats=stats,
    )


def _axes_for(session: Session, res: GrayResult, samples: StripeSamples, wanted: str) -> str:
    """"both" when the view has row codes, the session a projector and ``wanted`` asks for
    rows ("both", or "auto" where they pin depth better: :func:`choose_axes` at the depths
    of the decoded rows' planes), else "columns"."""
    from slscan.decode.triangulate import axis_conditioning, choose_axes, plane_start

    rig = session.calibration
    if wanted == "columns" or res.row is None or len(samples) == 0:
        return "columns"
    if wanted == "both":
        return "both"
    if rig is None:
        return "columns"
    take = np.linspace(0, len(samples) - 1, min(len(samples), 4000)).astype(np.int64)
    pick = samples.subset(take)
    h, w = res.row.shape
    r = res.row[np.clip(pick.row, 0, h - 1), np.clip(np.rint(pick.x).astype(np.int64), 0, w - 1)]
    rays = rig.camera.rays_local(pick.pixels())
    depth = plane_start(rays, rig.projector, pick.projector_column, np.where(r >= 0, r, np.nan))
    return choose_axes(axis_conditioning(rays, rig.projector, depth), wanted)


def projector_codes(session: Session, view: ViewRecord | str, config=None):
    """The projector column and row at every decoded pixel (:class:`~slscan.decode.codes.ProjectorCodes`)."""
    from slscan.decode.codes import codes_from_gray

    view = session.view(view) if isinstance(view, str) else view
    options = {} if config is None else {"threshold": config.gray_threshold, "robust": config.gray_robust_applied,
                                         "drop_bits": config.gray_drop_bits}
    return codes_from_gray(decode_gray(session, view, **options), session, view.name)


def projector_constraints(session: Session, view: ViewRecord | str) -> ProjectorConstraints:
    """The column edges (along camera rows) and row edges (along camera columns) as
    one-coordinate constraints, for mapping board corners into the projector."""
    view = session.view(view) if isinstance(view, str) else view
    axes = decode_gray_axes(session, view)
    e = axes.columns.edges
    return ProjectorConstraints(
        x=np.concatenate([np.asarray(e.x, np.float64), axes.row_x.astype(np.float64)]),
        y=np.concatenate([e.camera_y, axes.row_y.astype(np.float64)]),
        value=np.concatenate([np.asarray(e.projector_column, np.float64), axes.row_value]),
        is_row=np.concatenate([np.zeros(len(e), bool), np.ones(len(axes.row_x), bool)]),
    )
