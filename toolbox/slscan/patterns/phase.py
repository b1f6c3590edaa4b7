"""Phase shifting: N-step sinusoidal fringes, with Gray code or several periods to unwrap them.

A fringe image along projector columns shows, at column ``x`` (pixel centres at whole
numbers, as everywhere in slscan),

    I(x) = (0.5 + 0.5 cos(2 pi (x - origin) / period + shift)) ** (1 / gamma)

in [0, 1] (255 is full white), for ``N >= 3`` shifts ``shift = 2 pi k / N``. The phase
``2 pi (x - origin) / period`` decoded at a camera pixel gives its projector column to a
fraction of a pixel, but only modulo ``period``: the fringe order (which period) comes from

``"gray"``
    a Gray code whose cell is one period: ``bits = ceil(log2(size / period))`` (pattern,
    inverse) pairs; the code names the period directly;
``"complementary"`` (default)
    the same Gray code and one more bit, the least significant of the code of cells half a
    period wide: near a period's ends, where the Gray code's edge and the phase's wrap both
    fall and either may be off by a camera pixel, the order is read from the extra bit,
    whose own edges lie mid-period (Zhang et al. 2018), so orders never jump by one;
``"heterodyne"``
    two or three periods and no Gray code: the periods' phases together fix the column over
    the whole projector when their joint period (the beat of the beats) covers it.

``gamma`` pre-distorts the fringes for a projector whose emitted light is ``value **
gamma`` (1: a linear projector; :mod:`slscan.decode.phase` estimates it). Descriptions
carry every number decoding needs; rows are coded the same way along ``"rows"``.

params of each image:

- ``kind`` : {"sine", "gray"}
- sine: ``period`` (projector px), ``step`` k and ``steps`` N, ``shift`` (radians; the
  k-th of N equal shifts here, any values in imported sets), ``origin`` (px where the
  phase is 0) and ``gamma``
- gray: ``bit`` (0 = most significant) of ``bits``, ``cell`` (projector px per code),
  ``origin``, ``inverse``; ``complementary``: the extra bit of the complementary Gray code
  (bit ``bits - 1`` of the code of cells ``cell`` wide, half the others')

References
----------
.. [1] Srinivasan, Liu, Halioua, "Automated phase-measuring profilometry of 3-D diffuse
   objects", Applied Optics 23(18), 1984 (N-step phase shifting).
.. [2] Sansoni, Carocci, Rodella, "Three-dimensional vision based on a combination of
   gray-code and phase-shift light projection", Applied Optics 38(31), 1999.
.. [3] Zhang, Su, Xiang, Liu, "Absolute phase retrieval methods for digital fringe
   projection profilometry: a review", Optics and Lasers in Engineering 107, 2018
   (complementary Gray code; multi-frequency heterodyne).
.. [4] Reich, Ritter, Thesing, "White light heterodyne principle for 3D-measurement",
   SPIE 3100, 1997.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from slscan.errors import SlscanError
from slscan.patterns import Family, Option, PatternImage
from slscan.patterns.graycode import gray

UNWRAP_METHODS = ("complementary", "gray", "heterodyne")
DEFAULT_PERIOD = 8.0
"""Projector px per fringe of the default set: 128 fringes across the paper's 1024 px
projector, about 5.6 mm and 8 camera px at the paper's rig. Coarser than the Gray code's
and the hybrid's finest detail (1-2 px), fine enough that on the virtual flat tile at full
size, 4 steps put the points 0.018 mm from the plane (period 16: 0.030 mm; Gray code
0.038, hybrid 0.019; ``benchmarks/phase.py``)."""
DEFAULT_STEPS = 4
DEFAULT_HETERODYNE = (16.0, 17.0, 18.0)
"""Periods of the default heterodyne set: all fine (so global light falls evenly on every
image), with a joint period of 2448 px, more than twice a 1024 px projector."""
TAGS = {"columns": "col", "rows": "row"}


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"expected comma-separated numbers, got {text!r}") from None
    return values


def joint_period(periods: Sequence[float]) -> float:
    """The period (px) over which fringes of ``periods`` repeat together, as the heterodyne
    principle finds it: the beats of neighbouring periods, then the beats of those, down to
    one (16, 17, 18 px: beats of 272 and 306 px, and of those 2448 px); infinite when two
    periods are equal."""
    level = sorted(float(p) for p in periods)
    while len(level) > 1:
        beats = []
        for a, b in itertools.pairwise(level):
            if abs(b - a) < 1e-9 * b:
                return math.inf
            beats.append(a * b / abs(b - a))
        level = sorted(beats)
    return level[0]


def check_set(size: int, periods: Sequence[float], steps: int, unwrap: str, axis: str = "columns") -> None:
    """Raise naming the option when the fringes cannot be decoded over ``size`` px."""
    if unwrap not in UNWRAP_METHODS:
        raise SlscanError(f"phase unwrapping {unwrap!r}: expected one of {', '.join(UNWRAP_METHODS)}")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 3:
        raise SlscanError(f"phase steps must be a whole number >= 3, got {steps!r}")
    if not periods:
        raise SlscanError("phase periods: give at least one period (projector px)")
    for p in periods:
        if not (isinstance(p, (int, float)) and math.isfinite(p) and 4 <= p <= size):
            raise SlscanError(
                f"phase period {p!r} px does not fit a {size} px projector {axis[:-1]} axis: "
                f"expected 4 .. {size} px"
            )
    if unwrap == "heterodyne":
        if len(periods) < 2:
            raise SlscanError("phase unwrapping 'heterodyne' needs two or three periods, got one")
        joint = joint_period(periods)
        if joint < size:
            raise SlscanError(
                f"phase periods {', '.join(f'{p:g}' for p in periods)} repeat together every {joint:.0f} px, "
                f"less than the projector's {size} px {axis}: the fringe order cannot be unwrapped "
                "(choose periods whose beat of the beats covers it, e.g. 16,17,18)"
            )
    elif len(periods) > 1 and max(periods) != periods[0]:
        raise SlscanError(
            f"phase unwrapping {unwrap!r}: the Gray code's cell is the first period, which must be the "
            f"longest, got {', '.join(f'{p:g}' for p in periods)}"
        )


def generate(
    width: int,
    height: int,
    *,
    rows: bool = False,
    periods: Sequence[float] | None = None,
    steps: int = DEFAULT_STEPS,
    unwrap: str = "complementary",
    gamma: float = 1.0,
    inverse: bool = True,
    gammas: Sequence[float] | None = None,
    cell: float | None = None,
    response: bool = False,
) -> list[PatternImage]:
    """Descriptions of a phase-shifting set along the columns (and rows).

    periods : projector px per fringe; default (8,) for Gray-code unwrapping,
        :data:`DEFAULT_HETERODYNE` for heterodyne. With Gray code the first (longest) is the
        code's cell and further periods are unwrapped from it.
    steps : N >= 3 phase shifts per period
    unwrap : {"complementary", "gray", "heterodyne"} (see the module notes)
    gamma : the projector's response the fringes are pre-distorted for (1: none)
    inverse : Gray code: (pattern, inverse) pairs (True) or patterns alone, read against
        the mean of white and black
    gammas : several pre-distortions: every period's fringes once for each (a response capture)
    cell : the Gray code's cell, px (default: the first period); at most half the shortest
        period, it gives every pixel's coordinate to a cell, whatever the phase says
    response : the projector-response capture (:data:`RESPONSE`): fringes of an eighth of
        the projector pre-distorted for 0.75 and 1.25, and a Gray code of 2 px cells, from
        which ``slscan response`` measures the projector's gamma
        (:func:`slscan.decode.phase_gamma.estimate_gamma`)
    """
    if response:
        unwrap, cell = "gray", 2.0 if cell is None else cell
        gammas = RESPONSE_GAMMAS if gammas is None else gammas
    elif periods is None:
        periods = DEFAULT_HETERODYNE if unwrap == "heterodyne" else (DEFAULT_PERIOD,)
    gammas = (gamma,) if gammas is None else tuple(float(g) for g in gammas)
    for g in gammas:
        if not (isinstance(g, (int, float)) and 0.2 <= g <= 5):
            raise SlscanError(f"phase gamma must be in [0.2, 5], got {g!r}")
    images = []
    for axis, size in [("columns", width)] + ([("rows", height)] if rows else []):
        axis_periods = (size / 8,) if response and periods is None else periods
        axis_periods = tuple(float(p) for p in (axis_periods if isinstance(axis_periods, Sequence)
                                                else (axis_periods,)))
        check_set(size, axis_periods, steps, unwrap, axis)
        tag = TAGS[axis]
        for i, period in enumerate(axis_periods):
            for j, g in enumerate(gammas):
                suffix = f"-g{j}" if len(gammas) > 1 else ""
                for k in range(steps):
                    images.append(PatternImage(
                        f"phase-{tag}-p{i}{suffix}-s{k}", "phase", width, height, axis,
                        {"kind": "sine", "period": period, "step": k, "steps": int(steps),
                         "shift": 2 * math.pi * k / steps, "origin": 0.0, "gamma": g},
                    ))
        if unwrap == "heterodyne":
            continue
        width_px = axis_periods[0] if cell is None else float(cell)
        if width_px > min(axis_periods) / 2 and abs(width_px - axis_periods[0]) > 1e-9:
            raise SlscanError(f"phase Gray cell {width_px:g} px: expected the first period or at most half "
                              f"the shortest ({min(axis_periods):g} px)")
        bits = max(1, math.ceil(math.log2(size / width_px)))
        codes = [(b, bits, width_px, False) for b in range(bits)]
        if unwrap == "complementary":
            codes.append((bits, bits + 1, width_px / 2, True))
        for bit, nbits, cell_px, extra in codes:
            for inv in (False, True) if inverse else (False,):
                images.append(PatternImage(
                    f"phase-{tag}-gray-{bit:02d}{'-inv' if inv else ''}", "phase", width, height, axis,
                    {"kind": "gray", "bit": bit, "bits": nbits, "cell": cell_px, "origin": 0.0,
                     "inverse": inv, **({"complementary": True} if extra else {})},
                ))
    return images


RESPONSE_GAMMAS = (0.75, 1.25)
"""Pre-distortions of the response capture's fringes (kamino410's gamma tool uses these)."""


def sine_values(desc: PatternImage, at: np.ndarray) -> np.ndarray:
    """Fringe intensity in [0, 1] at projector coordinates ``at`` (px), before any gamma."""
    p = desc.params
    return 0.5 + 0.5 * np.cos(2 * np.pi * (at - p.get("origin", 0.0)) / p["period"] + p["shift"])


def gray_values(desc: PatternImage, at: np.ndarray) -> np.ndarray:
    """0/1 (int) of a Gray-code image at projector coordinates ``at`` (px)."""
    p = desc.params
    cell = np.floor((np.asarray(at, np.float64) - p.get("origin", 0.0)) / p["cell"]).astype(np.int64)
    on = (gray(np.maximum(cell, 0)) >> (p["bits"] - 1 - p["bit"])) & 1
    return 1 - on if p.get("inverse") else on


def profile(desc: PatternImage) -> np.ndarray:
    size = desc.width if desc.axis == "columns" else desc.height
    at = np.arange(size, dtype=np.float64)
    if desc.params["kind"] == "sine":
        value = sine_values(desc, at) ** (1.0 / desc.params.get("gamma", 1.0))
        grey = np.rint(255 * value).astype(np.uint8)
    elif desc.params["kind"] == "gray":
        grey = (gray_values(desc, at) * 255).astype(np.uint8)
    else:
        raise SlscanError(f"pattern {desc.id!r}: unknown phase image kind {desc.params['kind']!r}")
    return np.repeat(grey[:, None], 3, axis=1)


def finest(patterns) -> PatternImage | None:
    """The column fringe of the shortest period."""
    sines = [p for p in patterns if p.family == "phase" and p.axis == "columns" and p.params.get("kind") == "sine"]
    return min(sines, key=lambda p: (p.params["period"], p.params["step"]), default=None)


FAMILY = Family(
    name="phase",
    summary="N-step sinusoidal fringes unwrapped by (complementary) Gray code or several periods",
    generate=generate,
    profile=profile,
    decoder="slscan.decode.phase",
    sets={"phase": {}, "phase-response": {"response": True}},
    options=(
        Option("periods", _floats, f"{DEFAULT_PERIOD:g} (heterodyne: 16,17,18)",
               "projector px per fringe, comma-separated; several: heterodyne, or finer periods unwrapped "
               "from the first"),
        Option("steps", int, DEFAULT_STEPS, "phase shifts per period (N >= 3)"),
        Option("unwrap", str, "complementary", f"fringe order from: {', '.join(UNWRAP_METHODS)}"),
        Option("gamma", float, 1.0, "pre-distort the fringes for this projector response (value ** gamma)"),
    ),
    priority=3,
    rows=True,
    finest=finest,
)
