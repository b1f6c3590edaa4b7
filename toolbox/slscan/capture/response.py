"""Measure a camera's tone curve from its own Gray-code captures: linear or sRGB.

A projector showing a binary pattern and then its inverse sends, at every projector pixel,
exactly the light of its white frame plus that of its black frame (each pixel is either on
or off, so the projector's own gamma does not enter). Blur, defocus and global light only
redistribute that light linearly, so in linear light every camera pixel satisfies::

    pattern + inverse = white + black

A camera tone curve ``f`` breaks it wherever a pixel sees both stripes of a pair (a stripe
edge blurred over it, the finest stripes, light carried across by inter-reflection), and
in a level-dependent way: with ``f`` concave (sRGB) two half-lit pixels read brighter than
the white and black together, by up to a third of ``white - black``. Where a pixel lies well
inside a stripe under direct light only, ``pattern = white`` and ``inverse = black`` whatever
the curve, so those pixels say nothing and are left out.

:func:`fit_response` undoes each candidate curve (:data:`CANDIDATES`, through the decoders'
own :func:`~slscan.capture.session.linearise`) on the pixels that see both stripes of a
pair (``|pattern - inverse| < MIXED * (white - black)`` as stored, the same pixels for
every candidate) and scores it by the residual ``(pattern + inverse - white - black) /
(white - black)``: its 20 %-trimmed mean in each of 12 bins (3 of ``|pattern - inverse|``,
4 of the white level), root-mean-squared over the bins, so a curve that is right on
average but wrong at some level still scores badly. The candidate with the smaller residual
is chosen when the other's is at least :data:`MIN_RATIO` times larger and apart by
:data:`NOISE_MARGIN` standard errors; with too few such pixels (:data:`MIN_SAMPLES`:
saturated or dark captures, coarse stripes only) or residuals that do not separate, the
answer falls back to linear, and says why. The exponent of the power law ``v**gamma`` that
fits best is reported beside them (a diagnostic: sessions record only linear or sRGB).

On real captures the right curve leaves a residual of a few per cent (kamino410's linear
machine-vision cameras: 0.02-0.05 for linear against 0.17-0.40 for sRGB), the virtual rig's
about 0.001; the wrong one 0.3.

References
----------
.. [1] IEC 61966-2-1:1999, the sRGB transfer function.
.. [2] Debevec, Malik, "Recovering high dynamic range radiance maps from photographs",
   SIGGRAPH 1997: camera response from the images themselves (here from the projector's
   additivity instead of exposure series).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field

import numpy as np

from slscan.capture.session import RESPONSES, Session, linearise
from slscan.errors import SlscanError

log = logging.getLogger(__name__)

CANDIDATES = RESPONSES
"""The tone curves :func:`fit_response` chooses between (those a session can record)."""

MIXED = 0.7
"""A pixel sees both stripes of a pair when ``|pattern - inverse|`` (as stored) is under this
share of ``white - black``; pixels inside a stripe give ``pattern = white`` under any curve."""

MIN_CONTRAST = 0.08
"""``white - black`` must exceed this fraction of full scale (shadow, background)."""

MAX_WHITE = 0.95
"""The white frame must stay under this fraction of full scale (clipping breaks the sum)."""

MIN_SAMPLES = 2000
"""Fewest pixel samples (pixel x pair x channel) that decide; fewer: linear, said so."""

MIN_RATIO = 2.0
"""The rejected candidate's residual must be at least this many times the chosen one's."""

NOISE_MARGIN = 5.0
"""...and larger by this many standard errors of the residuals (noise, JPEG)."""

TARGET_SAMPLES = 150_000
"""Samples :func:`measure_response` fits on: it strides over the pixels to gather about
this many and thins what it gathered to it (the residuals' standard error stays near 0.001
of ``white - black``, far below the 0.3 between the candidates)."""

PAIRS = 2
"""Column pairs :func:`response_pairs` takes: the finest ones, where most pixels see both
stripes (blur, a couple of camera pixels per stripe)."""

_BIN_EDGES = (0.25, 0.5)  # of |pattern - inverse| / (white - black), stored
_TRIM = 0.2


@dataclass(frozen=True)
class ResponseFit:
    """What the captures say about the camera's tone curve (:func:`fit_response`).

    response : {"linear", "srgb"}, the curve chosen (linear when the evidence is weak)
    measured : the captures decided; False: too little evidence, linear by default
    reason : why, in a few words (one line)
    residuals : candidate -> residual, RMS over level bins of the trimmed mean of
        ``(pattern + inverse - white - black) / (white - black)`` in that candidate's
        linear light (0: the identity holds)
    standard_error : of a residual, from the samples' scatter (noise, JPEG)
    samples : pixel samples (pixel x pair x channel) that saw both stripes of a pair
    gamma, gamma_residual : the power law ``v**gamma`` that fits best, and its residual
        (a diagnostic; None without samples)
    views : the views measured
    """

    response: str
    measured: bool
    reason: str
    residuals: dict[str, float] = field(default_factory=dict)
    standard_error: float = 0.0
    samples: int = 0
    gamma: float | None = None
    gamma_residual: float | None = None
    views: tuple[str, ...] = ()

    def describe(self) -> str:
        """One line, e.g. ``linear (measured on capture_0, 184,910 samples: residual linear
        0.024, srgb 0.403; nearest power law gamma 0.95: 0.004)``, or ``linear (by default,
        not measured: <reason>; on ...)``."""
        where = f" on {', '.join(self.views)}," if self.views else ""
        evidence = f"{self.samples:,} samples"
        if self.residuals:
            evidence += ": residual " + ", ".join(f"{k} {v:.3f}" for k, v in self.residuals.items())
        if self.gamma is not None:
            evidence += f"; nearest power law gamma {self.gamma:.2f}: {self.gamma_residual:.3f}"
        if self.measured:
            return f"{self.response} (measured{where or ','} {evidence})"
        return f"{self.response} (by default, not measured: {self.reason};{where or ' with'} {evidence})"

    def to_dict(self) -> dict:
        return {
            "response": self.response, "measured": self.measured, "reason": self.reason,
            "residuals": {k: round(float(v), 5) for k, v in self.residuals.items()},
            "standard_error": round(float(self.standard_error), 6), "samples": int(self.samples),
            "gamma": None if self.gamma is None else round(float(self.gamma), 3),
            "gamma_residual": None if self.gamma_residual is None else round(float(self.gamma_residual), 5),
            "views": list(self.views),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ResponseFit:
        try:
            return cls(
                response=str(d["response"]), measured=bool(d["measured"]), reason=str(d.get("reason", "")),
                residuals={str(k): float(v) for k, v in d.get("residuals", {}).items()},
                standard_error=float(d.get("standard_error", 0.0)), samples=int(d.get("samples", 0)),
                gamma=None if d.get("gamma") is None else float(d["gamma"]),
                gamma_residual=None if d.get("gamma_residual") is None else float(d["gamma_residual"]),
                views=tuple(d.get("views", ())),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise SlscanError(f"camera.response_fit: not a response measurement ({exc})") from None


def mixed_samples(white: np.ndarray, black: np.ndarray, pairs: Sequence[tuple[np.ndarray, np.ndarray]],
                  *, stride: int = 1) -> np.ndarray:
    """(4, n) stored values ``(white, black, pattern, inverse)`` of the pixels that see both
    stripes of a pair, every ``stride``-th pixel along rows and columns, channels of RGB
    captures pooled (the curve acts on each).

    white, black : (h, w) or (h, w, 3) uint8 or uint16 captures as stored
    pairs : ``(pattern, inverse)`` captures like ``white``
    """
    white = np.asarray(white)
    if white.dtype not in (np.uint8, np.uint16):
        raise SlscanError(f"response fit: captures must be uint8 or uint16 as stored, got {white.dtype}")
    top = float(np.iinfo(white.dtype).max)
    sub = (slice(None, None, stride), slice(None, None, stride))

    def flat(image: np.ndarray) -> np.ndarray:
        image = np.asarray(image)
        if image.shape != white.shape or image.dtype != white.dtype:
            raise SlscanError(f"response fit: a capture is {image.shape} {image.dtype}, the white frame "
                              f"{white.shape} {white.dtype}")
        return image[sub].reshape(-1).astype(np.int32)

    w, b = flat(white), flat(black)
    contrast = w - b
    usable = (contrast > MIN_CONTRAST * top) & (w < MAX_WHITE * top)
    w, b, contrast = w[usable], b[usable], contrast[usable]
    out = []
    for pattern, inverse in pairs:
        p, q = flat(pattern)[usable], flat(inverse)[usable]
        keep = (np.abs(p - q) < MIXED * contrast) & (np.maximum(p, q) < top)
        out.append(np.stack([w[keep], b[keep], p[keep], q[keep]]))
    if not out:
        return np.zeros((4, 0), np.int32)
    return np.concatenate(out, axis=1)


def _bins(stored: np.ndarray) -> np.ndarray:
    """(n,) bin index of each sample: 3 bins of ``|p - q| / (w - b)`` times 4 quartiles of
    the white level (stored values: the same bins for every candidate)."""
    w, b, p, q = stored.astype(np.float64)
    u = np.digitize(np.abs(p - q) / (w - b), _BIN_EDGES)
    level = np.digitize(w, np.quantile(w, [0.25, 0.5, 0.75])) if len(w) else np.zeros(0, int)
    return u * 4 + level


def residual(linear: np.ndarray, bins: np.ndarray, min_bin: int = 50) -> tuple[float, float]:
    """(residual, standard error) of the identity on samples ``linear`` (4, n) = ``(white,
    black, pattern, inverse)`` in some candidate's linear light: the RMS over ``bins`` of
    the 20 %-trimmed mean of ``(p + q - w - b) / (w - b)``, weighted by the bins' sizes
    (bins under ``min_bin`` samples left out)."""
    w, b, p, q = linear.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = (p + q - w - b) / (w - b)
    ok = np.isfinite(e)
    total = n = var = 0.0
    for k in np.unique(bins[ok]):
        ek = np.sort(e[ok & (bins == k)])
        if len(ek) < min_bin:
            continue
        cut = int(_TRIM * len(ek))
        mean = float(ek[cut:len(ek) - cut].mean())
        mad = float(np.median(np.abs(ek - np.median(ek))))
        se2 = (1.4826 * mad) ** 2 / len(ek) * 1.2  # the trimmed mean's variance, about
        total += len(ek) * mean * mean
        var += len(ek) * se2
        n += len(ek)
    if not n:
        return float("nan"), float("nan")
    return float(np.sqrt(total / n)), float(np.sqrt(var / n))


def _power_law(stored: np.ndarray, bins: np.ndarray, top: float) -> tuple[float, float]:
    """(gamma, residual) of the power law ``(v / top)**gamma`` that fits best."""
    from scipy.optimize import minimize_scalar

    v = stored.astype(np.float64) / top
    logs = np.log(np.maximum(v, 0.5 / top))

    def cost(g: float) -> float:
        return residual(np.exp(g * logs), bins)[0]

    found = minimize_scalar(cost, bounds=(0.3, 4.0), method="bounded", options={"xatol": 0.005})
    return float(found.x), float(found.fun)


def fit_response(white: np.ndarray, black: np.ndarray, pairs: Sequence[tuple[np.ndarray, np.ndarray]],
                 *, stride: int = 1, views: Sequence[str] = ()) -> ResponseFit:
    """Which tone curve, linear or sRGB, the captures of one or more views were stored through.

    white, black : (h, w) or (h, w, 3) uint8/uint16 captures as stored, under full white
        and full black
    pairs : ``(pattern, inverse)`` captures of Gray-code bits (any axis), like ``white``
    stride : use every ``stride``-th pixel along rows and columns (speed)
    views : names for the result

    Several views: pass :func:`mixed_samples` of each to :func:`fit_samples` instead.
    """
    top = float(np.iinfo(np.asarray(white).dtype).max) if np.asarray(white).dtype.kind == "u" else 1.0
    return fit_samples(mixed_samples(white, black, pairs, stride=stride), top=top, views=views)


def fit_samples(stored: np.ndarray, *, top: float, views: Sequence[str] = ()) -> ResponseFit:
    """:func:`fit_response` on samples already gathered by :func:`mixed_samples` (4, n)
    of captures whose full scale is ``top`` (255 or 65535)."""
    n = stored.shape[1]
    views = tuple(views)
    if n < MIN_SAMPLES:
        return ResponseFit(
            "linear", False, f"only {n:,} pixel samples see both stripes of a pair under a clear, "
            f"unclipped white (at least {MIN_SAMPLES:,} needed)", samples=n, views=views,
        )
    dtype = np.uint8 if top <= 255 else np.uint16
    bins = _bins(stored)
    residuals, errors = {}, []
    for name in CANDIDATES:
        lin = linearise(stored.astype(dtype), name)
        if name == "linear":
            lin = lin.astype(np.float64) / top
        r, se = residual(lin, bins)
        residuals[name] = r
        errors.append(se)
    se = float(max(errors))
    gamma, gamma_residual = _power_law(stored, bins, top)
    ranked = sorted(CANDIDATES, key=lambda k: residuals[k])
    best, other = ranked[0], ranked[1]
    common = {"residuals": residuals, "standard_error": se, "samples": n, "gamma": gamma,
              "gamma_residual": gamma_residual, "views": views}
    if not np.isfinite(residuals[best]):
        return ResponseFit("linear", False, "no level bin held enough samples", **common)
    if residuals[other] < MIN_RATIO * residuals[best] or residuals[other] - residuals[best] < NOISE_MARGIN * se:
        return ResponseFit(
            "linear", False, f"{best} and {other} fit about as well (residuals within a factor "
            f"{MIN_RATIO:g} or {NOISE_MARGIN:g} standard errors)", **common,
        )
    return ResponseFit(best, True, f"{best} fits {residuals[other] / max(residuals[best], 1e-9):.0f}x "
                       f"better than {other}", **common)


def response_pairs(pairs: Sequence[tuple[Hashable, Hashable]], count: int = PAIRS) -> list[tuple[Hashable, Hashable]]:
    """The ``(pattern id, inverse id)`` pairs a response fit reads, of a set's column pairs
    (most significant first): the ``count`` finest."""
    return list(pairs[-count:])


def measure_response(
    read: Callable[[str, Hashable], np.ndarray],
    views: Sequence[str],
    white_id: Hashable,
    black_id: Hashable,
    pairs: Sequence[tuple[Hashable, Hashable]],
    *,
    max_views: int = 3,
    target: int = TARGET_SAMPLES,
) -> ResponseFit:
    """Fit the tone curve on the captures of up to ``max_views`` of ``views``, in order,
    stopping once ``target`` samples are gathered.

    read : ``read(view, image id)`` -> the capture as stored, (h, w) or (h, w, 3)
        uint8/uint16 (ids: pattern ids, file positions, whatever ``read`` takes)
    pairs : the ``(pattern id, inverse id)`` to use (:func:`response_pairs`)

    Each view is subsampled with a stride that reads about ``target`` pixels of each
    capture (every 3rd row and column of 1.3 MP, every 11th of 16 MP), and the samples
    gathered are thinned evenly to ``target``.
    """
    gathered, used = [], []
    top = 255.0
    for view in list(views)[:max_views]:
        white, black = read(view, white_id), read(view, black_id)
        top = float(np.iinfo(white.dtype).max) if white.dtype.kind == "u" else 1.0
        channels = 1 if white.ndim == 2 else white.shape[2]
        stride = max(1, int(np.ceil(np.sqrt(white.shape[0] * white.shape[1] * channels / target))))
        found = mixed_samples(white, black, [(read(view, p), read(view, q)) for p, q in pairs],
                              stride=stride)
        gathered.append(found)
        used.append(view)
        if sum(g.shape[1] for g in gathered) >= target:
            break
    stored = np.concatenate(gathered, axis=1) if gathered else np.zeros((4, 0), np.int32)
    step = max(1, stored.shape[1] // target)
    return fit_samples(stored[:, ::step], top=top, views=used)


def measure_session_response(session: Session, *, views: Sequence[str] | None = None,
                             max_views: int = 3) -> ResponseFit:
    """:func:`measure_response` on a session's Gray-code captures (as stored): of ``views``
    (default: the session's, in order), up to ``max_views``.

    Raises
    ------
    SlscanError
        The session has no white and black frames or no Gray-code column pairs.
    """
    white_id, black_id = session.flat_frame_ids("measuring the camera response")
    bits: dict[tuple[int, bool], str] = {}
    for p in session.patterns:
        if p.family == "gray" and p.axis == "columns":
            bits[(int(p.params["bit"]), bool(p.params["inverse"]))] = p.id
    pairs = [(bits[(b, False)], bits[(b, True)]) for b in sorted({b for b, _ in bits})
             if (b, False) in bits and (b, True) in bits]
    if not pairs:
        raise SlscanError(f"{session.root}: no Gray-code column pairs to measure the camera response with")

    def read(view: str, pid: str) -> np.ndarray:
        v = session.view(view)
        return session.read_image(v, v.image_for(pid))

    names = [v.name for v in session.views] if views is None else list(views)
    return measure_response(read, names, white_id, black_id, response_pairs(pairs), max_views=max_views)


def describe_response(response: str, fit: dict | None) -> str:
    """One line: a session's ``response`` and where it comes from, given its
    ``camera.response_fit`` (``fit``; empty: recorded by the capture, not measured)."""
    if not fit:
        return f"{response} (recorded with the captures; not measured)"
    if "response" not in fit:  # given, nothing measured
        return f"{response} (given; not measured)"
    measured = ResponseFit.from_dict(fit)
    if fit.get("source", "measured") != "given":
        return measured.describe()
    if not measured.measured:
        verdict = "the captures do not tell"
    elif measured.response == response:
        verdict = "the captures agree"
    else:
        verdict = f"the captures measure {measured.response}"
    return f"{response} (given; {verdict}: {measured.describe()})"


def with_response(session: Session, response: str) -> Session:
    """``session`` read through another tone curve: ``response`` in :data:`CANDIDATES`
    (recorded as given, beside what was measured), or ``"measure"`` (measured now,
    :func:`measure_session_response`). Nothing is written."""
    from dataclasses import replace

    if response == "measure":
        fit = measure_session_response(session)
        return replace(session, response=fit.response, response_fit={**fit.to_dict(), "source": "measured"})
    if response not in CANDIDATES:
        raise SlscanError(f"camera response must be measure or one of {', '.join(CANDIDATES)}, got {response!r}")
    return replace(session, response=response, response_fit={**session.response_fit, "source": "given"})


def describe_session_response(session: Session) -> str:
    """:func:`describe_response` of a session (an error names its ``session.json``)."""
    try:
        return describe_response(session.response, session.response_fit)
    except SlscanError as exc:
        raise SlscanError(f"{session.root / 'session.json'}: {exc}") from None
