"""Import phase-shifting captures (N-step fringes, Gray code) made by other tools.

Other tools project sinusoidal fringes (and usually a Gray code to unwrap them) in their
own order, with their own conventions for the phase (cosine or sine, shifts, its sign),
and save the photographs under their own names. An *order spec* says what each
photograph shows, in the natural sort order of the file names, with the grammar of the
Gray-code order spec (:mod:`slscan.capture.graycode_import`) extended by fringe blocks::

    white,black,cols:sine:period=16:steps=4,cols:gray:cell=16:pairs,cols:comp:pairs

Grammar (items separated by commas, one item per image or block of images)::

    ITEM   := "white" | "black" | "skip" | AXIS ":" KIND (":" OPTION)*
    AXIS   := "cols" | "rows"          projector columns (vertical fringes) or rows
    KIND   := "sine"                   N phase-shifted fringe images of one period
            | "gray"                   a Gray code of cells of ``cell`` px
            | "comp"                   the complementary Gray bit (cells of cell / 2 px)

    sine options:
      period=LEN    projector px per fringe: a number or a fraction (200/3)
      count=N       instead of period: N fringes across the projector, period = size // N
                    (integer px, as OpenCV's SinusoidalPattern)
      steps=N       N >= 3 images, shifted by 360/N degrees each from ``shift``
      shift=DEG     the first image's phase shift in degrees (default 0)
      shifts=D/D/.. every image's shift in degrees, instead of steps and shift
      origin=LEN    the projector px where the phase is 0 (default 0)
      decreasing    the phase falls along the axis (the image is f(-2 pi (x - origin) / P + shift))
      sin           the image is 0.5 + 0.5 sin(...) rather than 0.5 + 0.5 cos(...)
      gamma=G       the values were raised to 1 / G (pre-distorted for a projector of response G)
    gray options:
      cell=LEN      projector px per code (default: the axis's longest period)
      bits=N or N   number of bits (default ceil(log2(size / cell)))
      pairs | split | plain, msb | lsb, origin=LEN   as in the Gray-code order spec
    comp options:
      pairs | plain the extra bit's pattern and inverse (default), or the pattern alone

so the ``k``-th image of a ``sine`` block, at projector coordinate ``x`` (pixel centres at
whole numbers), is ``(0.5 + 0.5 f(s 2 pi (x - origin) / period + shift_k)) ** (1 / gamma)``
with ``f`` cos (or sin) and ``s`` +1 (or -1, ``decreasing``). Every block becomes slscan
phase descriptions (:mod:`slscan.patterns.phase`; a sine block's shifts rewritten for
the cosine of the increasing phase), and the whole set is checked as the decoder will
read it (:func:`slscan.decode.phase.phase_sets`): every order needs one ``white``, one
``black`` and a ``cols:sine`` block, and a way to unwrap each axis (Gray code, or several
periods whose joint period covers the projector). Named presets (:data:`PRESETS`) hold
the layouts of known tools; those of kamino410/phase-shifting read the display size and
step from the ``config.xml`` the tool writes beside the captures. Images are copied byte
for byte (BMP converted to PNG), as the Gray-code importer does.

References
----------
.. [1] kamino410/phase-shifting (MIT licence), ``phase_shifting.py`` and
   ``gamma_correction.py``: the image orders of the ``kamino410-phase`` and
   ``kamino410-gamma`` presets.
.. [2] OpenCV ``structured_light.SinusoidalPattern`` (opencv_contrib,
   ``sinusoidalpattern.cpp``): ``generate`` gives 3 images ``127.5 + 127.5 sin(2 pi j /
   period + i shiftValue)``, ``period = width / nbrOfPeriods`` (integer division; height
   with ``horizontal``), ``shiftValue`` 2 pi / 3 by default; optional cross markers are
   drawn into those images.
.. [3] Hoang, Pan, Nguyen, Wang, "Generic gamma correction for accuracy enhancement in
   fringe-projection profilometry", Optics Letters 35(12), 2010 (the gamma set).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from slscan.capture.graycode_import import (
    LAYOUTS,
    _image_format,
    _numbering,
    _place,
    _refuse_overlap,
    _short,
    choose_response,
    copy_views,
    find_views,
    flat_item,
    measure_placed_response,
    order_items,
)
from slscan.capture.session import RESPONSES, ROTATIONS, Session, SessionWriter
from slscan.errors import SlscanError
from slscan.patterns import PatternImage, flat

logger = logging.getLogger(__name__)

AXIS_NAMES = {"cols": "columns", "rows": "rows"}
KINDS = ("sine", "gray", "comp")
_TAGS = {"columns": "col", "rows": "row"}
_SYNTAX = ("expected white, black, skip, cols:sine:period=P:steps=N[:...], cols:gray[:cell=C][:...], "
           "cols:comp[:pairs|plain] or the same with rows")


# --- the order spec ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SineBlock:
    """N phase-shifted fringe images of one period along one projector axis.

    axis : {"columns", "rows"}
    period : projector px per fringe, or None when ``count`` gives it
    count : fringes across the projector (period = size // count), or None
    shifts : each image's shift (degrees) as the tool wrote it, in file order
    origin : projector px where the phase is 0
    decreasing : the phase falls along the axis
    form : {"cos", "sin"}
    gamma : the values were raised to ``1 / gamma``
    """

    axis: str
    period: float | None
    count: int | None
    shifts: tuple[float, ...]
    origin: float = 0.0
    decreasing: bool = False
    form: str = "cos"
    gamma: float = 1.0

    def period_px(self, size: int) -> float:
        return float(size // self.count) if self.count is not None else float(self.period)

    def description_shifts(self) -> list[float]:
        """Each image's shift (radians) in slscan's form ``cos(2 pi (x - origin) / P + shift)``:
        ``sin(u) = cos(u - pi / 2)``, and ``cos(-u + d) = cos(u - d)``."""
        out = []
        for deg in self.shifts:
            d = math.radians(deg) - (math.pi / 2 if self.form == "sin" else 0.0)
            out.append(-d if self.decreasing else d)
        return out


@dataclass(frozen=True)
class GrayBlock:
    """A Gray code along one axis (as :class:`~slscan.capture.graycode_import.CodeBlock`,
    with the code's cell and origin): ``cell`` None takes the axis's longest period."""

    axis: str
    cell: float | None = None
    bits: int | None = None
    layout: str = "pairs"
    msb_first: bool = True
    origin: float = 0.0


@dataclass(frozen=True)
class CompBlock:
    """The complementary Gray bit of an axis: its pattern and (``pairs``) its inverse."""

    axis: str
    layout: str = "pairs"


Block = SineBlock | GrayBlock | CompBlock


@dataclass(frozen=True)
class PhaseSlot:
    """What one image of the order shows: a flat frame, a skipped image, or one phase
    pattern (``desc``), with a phrase naming it for errors."""

    kind: str
    desc: PatternImage | None = None
    what: str = ""
    block: int = -1

    @property
    def pattern_id(self) -> str | None:
        if self.kind in ("white", "black"):
            return self.kind
        return None if self.desc is None else self.desc.id

    def describe(self) -> str:
        if self.kind in ("white", "black"):
            return f"the {self.kind} image"
        return self.what or "a skipped image"


@dataclass(frozen=True)
class PhaseOrder:
    """A parsed phase order spec (:func:`parse_phase_order`): what each image shows."""

    text: str
    items: tuple[str | Block, ...]

    def slots(self, projector_size: tuple[int, int]) -> list[PhaseSlot]:
        """One :class:`PhaseSlot` per image for a ``(width, height)`` projector; raise
        naming the block when a period or code does not fit it, or the set cannot be
        decoded (:func:`slscan.decode.phase.phase_sets`)."""
        from slscan.decode.phase import phase_sets

        pw, ph = projector_size
        sizes = {"columns": pw, "rows": ph}
        longest: dict[str, float] = {}
        for item in self.items:
            if isinstance(item, SineBlock):
                period = self._period(item, sizes[item.axis])
                longest[item.axis] = max(longest.get(item.axis, 0.0), period)
        grays = {item.axis: item for item in self.items if isinstance(item, GrayBlock)}
        cells = {axis: (g.cell if g.cell is not None else longest.get(axis)) for axis, g in grays.items()}
        out: list[PhaseSlot] = []
        counter: dict[str, int] = {}
        for block, item in enumerate(self.items):
            if isinstance(item, str):
                made = [PhaseSlot(item)]
            elif isinstance(item, SineBlock):
                index = counter[item.axis] = counter.get(item.axis, -1) + 1
                made = self._sine_slots(item, index, pw, ph)
            elif isinstance(item, GrayBlock):
                made = self._gray_slots(item, cells[item.axis], pw, ph)
            else:
                gray = grays[item.axis]
                made = self._comp_slots(item, gray, cells[gray.axis], pw, ph)
            out += [replace(slot, block=block) for slot in made]
        phase_sets([s.desc for s in out if s.desc is not None], where=f"order {self.text!r}")
        return out

    def summary(self, slots: list[PhaseSlot]) -> str:
        """What the order's ``slots`` show, e.g. ``"3 column fringes of 66.67 px, ...,
        10 column Gray, white, black"``."""
        parts = []
        for block, item in enumerate(self.items):
            mine = [s for s in slots if s.block == block]
            if isinstance(item, str):
                parts.append(item)
            elif isinstance(item, SineBlock):
                parts.append(f"{len(mine)} {item.axis[:-1]} fringes of {mine[0].desc.params['period']:.4g} px")
            else:
                kind = "Gray" if isinstance(item, GrayBlock) else "complementary Gray"
                parts.append(f"{len(mine)} {item.axis[:-1]} {kind}")
        return ", ".join(parts)

    def _period(self, item: SineBlock, size: int) -> float:
        period = item.period_px(size)
        if item.count is not None and period < 3:
            raise SlscanError(
                f"order {self.text!r}: count={item.count} fringes across the projector's {size} px "
                f"{item.axis} leaves {period:g} px per fringe; expected at least 3"
            )
        if not (2 < period <= size):
            raise SlscanError(
                f"order {self.text!r}: period={period:g} px does not fit the projector's {size} px "
                f"{item.axis}; expected more than 2 and at most {size} px (or give --projector)"
            )
        return period

    def _bits(self, item: GrayBlock, cell: float, size: int) -> int:
        needed = max(1, math.ceil(math.log2(size / cell))) if cell < size else 1
        bits = item.bits if item.bits is not None else needed
        if bits < needed:
            raise SlscanError(
                f"order {self.text!r}: {bits} {item.axis[:-1]} Gray bits of {cell:g} px cells cover "
                f"{cell * 2 ** bits:g} px, less than the projector's {size} px {item.axis}; expected at "
                f"least {needed} bits (or give --projector)"
            )
        return bits

    def _sine_slots(self, item: SineBlock, index: int, pw: int, ph: int) -> list[PhaseSlot]:
        size = pw if item.axis == "columns" else ph
        period = self._period(item, size)
        tag, name = _TAGS[item.axis], item.axis[:-1]
        n = len(item.shifts)
        return [
            PhaseSlot("sine", PatternImage(
                f"phase-{tag}-p{index}-s{k}", "phase", pw, ph, item.axis,
                {"kind": "sine", "period": period, "step": k, "steps": n, "shift": shift,
                 "origin": item.origin, "gamma": item.gamma},
            ), f"the {name} fringe of period {period:.6g} px, step {k + 1} of {n}")
            for k, shift in enumerate(item.description_shifts())
        ]

    def _gray_slots(self, item: GrayBlock, cell: float | None, pw: int, ph: int) -> list[PhaseSlot]:
        size = pw if item.axis == "columns" else ph
        if cell is None:
            raise SlscanError(f"order {self.text!r}: {_TOKENS[item.axis]}:gray has no cell=C and the "
                              f"{item.axis} have no fringes to take it from")
        if not (0 < cell <= size):
            raise SlscanError(f"order {self.text!r}: Gray cell={cell:g} px does not fit the projector's "
                              f"{size} px {item.axis}; expected more than 0 and at most {size} px")
        bits = self._bits(item, cell, size)
        order = range(bits) if item.msb_first else range(bits - 1, -1, -1)
        if item.layout == "pairs":
            keys = [(b, inv) for b in order for inv in (False, True)]
        elif item.layout == "split":
            keys = [(b, inv) for inv in (False, True) for b in order]
        else:
            keys = [(b, False) for b in order]
        return [self._gray_slot(item.axis, b, bits, cell, item.origin, inv, pw, ph) for b, inv in keys]

    def _comp_slots(self, item: CompBlock, gray: GrayBlock, cell: float, pw: int, ph: int) -> list[PhaseSlot]:
        size = pw if item.axis == "columns" else ph
        bits = self._bits(gray, cell, size)
        invs = (False, True) if item.layout == "pairs" else (False,)
        return [self._gray_slot(item.axis, bits, bits + 1, cell / 2, gray.origin, inv, pw, ph, comp=True)
                for inv in invs]

    @staticmethod
    def _gray_slot(axis: str, bit: int, bits: int, cell: float, origin: float, inverse: bool, pw: int, ph: int,
                   comp: bool = False) -> PhaseSlot:
        tag, name = _TAGS[axis], axis[:-1]
        what = (f"the {'inverse of the ' if inverse else ''}{'complementary ' if comp else ''}{name} Gray bit "
                f"{bit} ({'the extra bit of ' + format(cell, 'g') + ' px cells' if comp else '0 = most significant'}"
                f" of {bits})")
        return PhaseSlot("gray", PatternImage(
            f"phase-{tag}-gray-{bit:02d}{'-inv' if inverse else ''}", "phase", pw, ph, axis,
            {"kind": "gray", "bit": bit, "bits": bits, "cell": cell, "origin": origin, "inverse": inverse,
             **({"complementary": True} if comp else {})},
        ), what)


_TOKENS = {v: k for k, v in AXIS_NAMES.items()}


def _length(text: str, what: str, spec: str) -> float:
    """A length in px: a number or a fraction ``A/B``; raise naming the option."""
    try:
        if "/" in text:
            num, den = text.split("/")
            value = float(num) / float(den)
        else:
            value = float(text)
    except (ValueError, ZeroDivisionError):
        value = math.nan
    if not math.isfinite(value):
        raise SlscanError(f"order {spec!r}: {what}={text!r} is not a number; expected e.g. 16, 66.667 or 200/3")
    return value


def _number(text: str, what: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise SlscanError(f"order {spec!r}: {what}={text!r} is not a number")
    return value


def _whole(text: str, what: str, spec: str, least: int) -> int:
    if not text.isdigit() or int(text) < least:
        raise SlscanError(f"order {spec!r}: {what}={text!r}; expected a whole number >= {least}")
    return int(text)


_BARE = {**{layout: "layout" for layout in LAYOUTS}, "msb": "msb", "lsb": "msb", "decreasing": "decreasing",
         "sin": "sin"}
"""Options written as a bare word, by the key they set (a bare number is ``bits``)."""
_KEYED = ("period", "count", "steps", "shift", "shifts", "origin", "gamma", "cell", "bits")
"""Options written ``key=value``."""


def _options(spec: str, head: str, options: list[str], allowed: tuple[str, ...]) -> dict[str, str]:
    """``key=value`` and bare words of one block, each at most once and of the allowed ones."""
    out: dict[str, str] = {}
    for opt in options:
        key, eq, value = opt.partition("=")
        if not eq:
            key, value = ("bits" if opt.isdigit() else _BARE.get(opt, "")), opt
        if key not in allowed or key in out or (eq and key not in _KEYED):
            raise SlscanError(
                f"order {spec!r}: bad or repeated option {opt!r} of {head!r}; expected "
                f"{', '.join(_OPTION_HELP[a] for a in allowed)}"
            )
        out[key] = value
    return out


_OPTION_HELP = {
    "period": "period=LEN", "count": "count=N", "steps": "steps=N", "shift": "shift=DEG",
    "shifts": "shifts=DEG/DEG/...", "origin": "origin=LEN", "decreasing": "decreasing", "sin": "sin",
    "gamma": "gamma=G", "cell": "cell=LEN", "bits": "bits=N", "layout": "pairs|split|plain",
    "msb": "msb|lsb",
}
_SINE_OPTIONS = ("period", "count", "steps", "shift", "shifts", "origin", "decreasing", "sin", "gamma")
_GRAY_OPTIONS = ("cell", "bits", "layout", "msb", "origin")


def _sine_block(spec: str, head: str, axis: str, opts: dict[str, str]) -> SineBlock:
    if ("period" in opts) == ("count" in opts):
        raise SlscanError(f"order {spec!r}: {head} needs period=LEN (projector px per fringe) or count=N "
                          "(fringes across the projector), one of them")
    if "shifts" in opts:
        if "steps" in opts or "shift" in opts:
            raise SlscanError(f"order {spec!r}: {head}: give shifts=DEG/DEG/... or steps=N[:shift=DEG], not both")
        shifts = tuple(_number(v, "shifts", spec) for v in opts["shifts"].split("/"))
    elif "steps" in opts:
        steps = _whole(opts["steps"], "steps", spec, 1)
        first = _number(opts.get("shift", "0"), "shift", spec)
        shifts = tuple(first + 360.0 * k / steps for k in range(steps))
    else:
        raise SlscanError(f"order {spec!r}: {head} needs steps=N (phase-shifted images) or shifts=DEG/DEG/...")
    if len(shifts) < 3:
        raise SlscanError(f"order {spec!r}: {head} has {len(shifts)} phase step(s); N-step phase shifting "
                          "needs at least 3")
    wrapped = {round(s % 360.0, 6) % 360.0 for s in shifts}
    if len(wrapped) < len(shifts):
        raise SlscanError(f"order {spec!r}: {head} repeats a phase shift ({'/'.join(f'{s:g}' for s in shifts)} "
                          "degrees); expected distinct shifts")
    gamma = _number(opts.get("gamma", "1"), "gamma", spec)
    if not 0.2 <= gamma <= 5:
        raise SlscanError(f"order {spec!r}: {head}: gamma={gamma:g}; expected 0.2 .. 5")
    period = count = None
    if "period" in opts:
        period = _length(opts["period"], "period", spec)
    else:
        count = _whole(opts["count"], "count", spec, 1)
    return SineBlock(axis, period, count, shifts, _length(opts.get("origin", "0"), "origin", spec),
                     "decreasing" in opts, "sin" if "sin" in opts else "cos", gamma)


def is_phase_order(text: str) -> bool:
    """Whether an order spec has a phase block (``cols:sine``, ``:gray``, ``:comp``), so
    that it is this grammar's and not the Gray-code importer's."""
    return any(part.strip().lower().split(":")[1:2] in ([k] for k in KINDS) for part in text.split(","))


def parse_phase_order(text: str) -> PhaseOrder:
    """Parse a phase order spec (grammar in the module docstring); raise naming the bad item."""
    items: list[str | Block] = []
    seen: set[str] = set()
    for raw, head, options in order_items(text):
        if flat_item(text, head, options, seen):
            items.append(head)
            continue
        if head not in AXIS_NAMES or not options or options[0] not in KINDS:
            raise SlscanError(f"order {text!r}: unknown item {raw!r}; {_SYNTAX}")
        kind, options = options[0], options[1:]
        axis = AXIS_NAMES[head]
        name = f"{head}:{kind}"
        if kind == "sine":
            items.append(_sine_block(text, name, axis, _options(text, name, options, _SINE_OPTIONS)))
        elif kind == "gray":
            if name in seen:
                raise SlscanError(f"order {text!r}: {name!r} appears twice; expected one Gray code per axis")
            opts = _options(text, name, options, _GRAY_OPTIONS)
            cell = _length(opts["cell"], "cell", text) if "cell" in opts else None
            bits = _whole(opts["bits"], "bits", text, 1) if "bits" in opts else None
            items.append(GrayBlock(axis, cell, bits, opts.get("layout", "pairs"), opts.get("msb", "msb") == "msb",
                                   _length(opts.get("origin", "0"), "origin", text)))
        else:
            if name in seen:
                raise SlscanError(f"order {text!r}: {name!r} appears twice; expected one complementary bit per axis")
            opts = _options(text, name, options, ("layout",))
            layout = opts.get("layout", "pairs")
            if layout == "split":
                raise SlscanError(f"order {text!r}: {name}:split; the complementary bit is one image or a pair "
                                  "(pairs or plain)")
            items.append(CompBlock(axis, layout))
        seen.add(name)
    for needed, why in (("white", "decoding needs a white image"), ("black", "decoding needs a black image"),
                        ("cols:sine", "decoding needs column fringes")):
        if needed not in seen:
            raise SlscanError(f"order {text!r}: no {needed!r}; {why}")
    for item in items:
        if isinstance(item, CompBlock):
            gray = next((g for g in items if isinstance(g, GrayBlock) and g.axis == item.axis), None)
            tag = _TOKENS[item.axis]
            if gray is None:
                raise SlscanError(f"order {text!r}: {tag}:comp without {tag}:gray; the complementary bit "
                                  "completes a Gray code")
            if (gray.layout == "plain") != (item.layout == "plain"):
                raise SlscanError(
                    f"order {text!r}: {tag}:comp:{item.layout} with {tag}:gray:{gray.layout}; the complementary "
                    "bit needs its inverse exactly when the other bits have theirs (pairs with pairs or split, "
                    "plain with plain)"
                )
    return PhaseOrder(text, tuple(items))


# --- presets ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PhasePreset:
    """The capture layout of a known phase-shifting tool.

    order : the order spec; ``{name}`` fields are filled from ``values``
    projector_size : (width, height) px, or None to read it from ``config``
    pattern, views, first : as the Gray-code presets (capture file glob, view folder
        glob, number of the first image)
    tool : what ``device.tool`` of the session says
    config : a file beside the captures (in the view folder, else ``src``) holding the
        tool's settings as OpenCV FileStorage, or None
    keys : the numeric keys read from ``config`` (all required)
    values : the fields of ``order`` (and ``width``, ``height``) from the keys read
    """

    order: str
    projector_size: tuple[int, int] | None = None
    pattern: str = "*"
    views: str = "*"
    first: int | None = None
    tool: str = "phase"
    config: str | None = None
    keys: tuple[str, ...] = ()
    values: Callable[[dict[str, float]], dict[str, Any]] = field(default=lambda cfg: {})


def _kamino410_phase(cfg: dict[str, float]) -> dict[str, Any]:
    step = int(cfg["step"])  # the tool writes it as an int
    return {"width": int(cfg["disp_width"]), "height": int(cfg["disp_height"]), "step": step,
            "cell": int(step / 2)}


def _kamino410_gamma(cfg: dict[str, float]) -> dict[str, Any]:
    width = int(cfg["disp_width"])
    return {"width": width, "height": int(cfg["disp_height"]), "step": int(cfg["step"]),
            "period": int(width / 8), "g1": repr(float(cfg["gamma_p1"])), "g2": repr(float(cfg["gamma_p2"]))}


_KAMINO_SINE = "sine:period={p}:steps=3:shift=-120"
PRESETS: dict[str, PhasePreset] = {
    "kamino410-phase": PhasePreset(
        ",".join([f"{a}:{_KAMINO_SINE.format(p=p)}" for a in ("cols", "rows") for p in ("{step}/3", "{step}/2")]
                 + ["cols:gray:cell={cell}:pairs", "rows:gray:cell={cell}:pairs", "white", "black"]),
        pattern="pat[0-9]*", first=0, tool="kamino410/phase-shifting", config="config.xml",
        keys=("disp_width", "disp_height", "step"), values=_kamino410_phase,
    ),
    "kamino410-gamma": PhasePreset(
        ",".join([f"{a}:{_KAMINO_SINE.format(p='{period}')}:gamma={{{g}}}" for a in ("cols", "rows")
                  for g in ("g1", "g2")]
                 + ["cols:gray:cell={step}:pairs", "rows:gray:cell={step}:pairs", "white", "black"]),
        pattern="pat[0-9]*", first=0, tool="kamino410/phase-shifting gamma_correction", config="config.xml",
        keys=("disp_width", "disp_height", "gamma_p1", "gamma_p2", "step"), values=_kamino410_gamma,
    ),
    "opencv-sinusoidal": PhasePreset(
        "cols:sine:count=20:steps=3:sin,cols:gray:pairs,white,black", projector_size=(800, 600),
        tool="OpenCV structured_light.SinusoidalPattern + GrayCodePattern",
    ),
}
"""Named layouts.

``kamino410-phase``: kamino410/phase-shifting's ``phase_shifting.py gen W H STEP``:
``pat00``-``pat02`` column fringes of period STEP / 3, 3 steps shifted by 2 pi (k - 2) / 3
(k = 1, 2, 3), ``pat03``-``pat05`` period STEP / 2, ``pat06``-``pat11`` the same along
rows, then OpenCV ``GrayCodePattern`` images of ``int(STEP / 2)``-px cells (column then
row (pattern, inverse) pairs, most significant bit first), white, black; W, H and STEP
from ``config.xml`` (``disp_width``, ``disp_height``, ``step``); the tool's ``-gamma``
option is not recorded there, so the fringes are taken as generated with the default 1.

``kamino410-gamma``: its ``gamma_correction.py gen W H G1 G2 -step S``: column fringes of
period ``int(W / 8)`` raised to 1 / G1 (``pat00``-``02``) and to 1 / G2 (``pat03``-``05``),
the same along rows (period ``int(W / 8)`` too, ``pat06``-``11``), the Gray code of S-px
cells, white, black; W, H, G1, G2, S from ``config.xml``. (The tool truncates the row
fringes to 8 bits instead of rounding them: a bias of half a digital number, described
here as rounded.)

``opencv-sinusoidal``: OpenCV's ``SinusoidalPattern`` with its default parameters
(800 x 600, 20 periods, so 40 px, shift 2 pi / 3, vertical fringes, sine form) followed by
what slscan needs to unwrap and mask them, from OpenCV's other generator:
``GrayCodePattern`` column (pattern, inverse) pairs of one-period cells, then the white and
black images of ``getImagesForShadowMasks``. OpenCV unwraps its fringes spatially
(relative phase, absolute only through the markers); slscan does not, so the three
images alone are refused (no way to unwrap). Markers (``setMarkers``) are 5-px crosses
drawn into the fringe images: they are not read, and the few camera pixels that see them
get a wrong phase (mostly rejected by the decoder's neighbour check). Other
``nbrOfPeriods``, ``shiftValue`` or ``horizontal`` settings: an order spec
(``cols:sine:count=N:steps=3:sin``, ``shifts=...``, ``rows:...``).
"""


def get_phase_preset(name: str) -> PhasePreset:
    """The phase preset called ``name``; raise listing the presets."""
    try:
        return PRESETS[name]
    except KeyError:
        raise SlscanError(
            f"unknown phase-shifting preset {name!r}; expected one of {', '.join(PRESETS)} "
            "(or give the order with --order)"
        ) from None


def read_tool_config(path: Path, keys: tuple[str, ...]) -> dict[str, float]:
    """The numbers ``keys`` of an OpenCV FileStorage file (a tool's ``config.xml``);
    raise naming the file and the keys missing."""
    import cv2

    if not path.is_file():
        raise SlscanError(f"{path}: not found; expected the tool's settings ({', '.join(keys)})")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        fs = None
    if fs is None or not fs.isOpened():
        raise SlscanError(f"{path}: not a readable OpenCV FileStorage file; expected {', '.join(keys)}")
    try:
        values, missing = {}, []
        for key in keys:
            node = fs.getNode(key)
            if node.empty() or not (node.isInt() or node.isReal()):
                missing.append(key)
            else:
                values[key] = float(node.real())
    finally:
        fs.release()
    if missing:
        raise SlscanError(f"{path}: no number {', '.join(missing)}; expected {', '.join(keys)}")
    return values


@dataclass(frozen=True)
class _Plan:
    """What one view folder's images show: the order (a preset's filled from its config
    file), the projector size, one slot per image and each file's position."""

    text: str
    size: tuple[int, int]
    slots: list[PhaseSlot]
    placed: dict[int, Path]


def _plan(chosen: PhasePreset, preset: str | None, src: Path, folder: Path, files: list[Path],
          projector_size: tuple[int, int] | None) -> _Plan:
    """Read the view's config (a preset's: in the view folder, else ``src``), parse the
    order, check it against the projector and place the files; raise naming what is wrong."""
    values: dict[str, Any] = {}
    if chosen.config is not None:
        path = folder / chosen.config if (folder / chosen.config).is_file() else src / chosen.config
        values = chosen.values(read_tool_config(path, chosen.keys))
    text = chosen.order.format(**values) if preset is not None else chosen.order
    spec = parse_phase_order(text)
    size = projector_size or chosen.projector_size
    if size is None:
        size = (values["width"], values["height"]) if "width" in values else (1024, 768)
    pw, ph = (int(v) for v in size)
    if pw <= 0 or ph <= 0:
        raise SlscanError(f"projector size must be positive, got {pw}x{ph}")
    slots = spec.slots((pw, ph))
    return _Plan(text, (pw, ph), slots, _place_all(folder, files, slots, chosen.first, text, spec.summary(slots)))


def _plans(chosen: PhasePreset, preset: str | None, src: Path, found: dict[Path, list[Path]],
           projector_size: tuple[int, int] | None) -> dict[Path, _Plan]:
    """Each view's plan. ``src`` itself as the one view must fit; of its sub-folders, those
    that do not (another tool's set, a folder of notes) are not views: skipped, named with
    the reason in one warning, as the Gray-code importer does. The views kept must share
    one pattern set (order and projector)."""
    if list(found) == [src]:
        return {src: _plan(chosen, preset, src, src, found[src], projector_size)}
    plans: dict[Path, _Plan] = {}
    skipped: list[tuple[Path, SlscanError]] = []
    for folder, files in found.items():
        try:
            plans[folder] = _plan(chosen, preset, src, folder, files, projector_size)
        except SlscanError as exc:
            skipped.append((folder, exc))
    if not plans:
        raise skipped[0][1]
    if skipped:
        logger.warning("%s: %d sub-folder(s) skipped, not views of this layout: %s", src, len(skipped),
                       "; ".join(f"{folder.name}/ ({_short(exc, folder)})" for folder, exc in skipped))
    (first, one), *others = plans.items()
    for folder, other in others:
        if (other.text, other.size) != (one.text, one.size):
            raise SlscanError(
                f"{folder}: its images show order {other.text!r} on a {other.size[0]}x{other.size[1]} projector, "
                f"{first.name} {one.text!r} on {one.size[0]}x{one.size[1]}; expected one pattern set for every "
                "view (import the folders one at a time)"
            )
    return plans


# --- the import -------------------------------------------------------------------------------


def import_phase(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    preset: str | None = None,
    order: str | None = None,
    projector_size: tuple[int, int] | None = None,
    rotation: int | None = None,
    pattern: str | None = None,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    tool: str | None = None,
    response: str | None = None,
) -> Session:
    """Turn a folder of phase-shifting captures into an slscan capture session.

    ``src`` (one folder of captures, or one sub-folder per view), ``out``, ``overwrite``,
    ``progress``, ``tool`` and ``response`` are as for
    :func:`~slscan.capture.graycode_import.import_graycode` (default ``tool``: the
    preset's, else "phase").

    Parameters
    ----------
    preset : {"kamino410-phase", "kamino410-gamma", "opencv-sinusoidal"}, optional
        A named layout (:data:`PRESETS`); its order, projector size (or the tool's config
        file) and file globs are the defaults of the options below.
    order : str, optional
        The phase order spec (module docstring), instead of a preset's.
    projector_size : (width, height) px, optional
        Default: the preset's (or its config file's), else 1024 x 768.
    rotation : {0, 90, 180, 270}, optional
        Degrees the projector is mounted turned relative to the camera (default 0).
    pattern : glob, optional
        Which files of a folder are captures (default: the preset's, else every PNG, JPEG,
        TIFF and BMP file), taken in natural sort order.

    Returns
    -------
    Session
        Family ``phase`` descriptions (and ``white``, ``black``), one image per file named
        ``NN_<pattern id>.<ext>``; ``calibration`` None, no poses; ``device`` records the
        tool, the source and the order.

    Raises
    ------
    SlscanError
        One line naming the file, folder or option and what was expected: an unknown
        preset, a bad order item, a period or Gray code that does not fit the projector, a
        set with no way to unwrap, a missing or extra image (what it shows), a wrong image
        count, images of different sizes or formats, a missing or incomplete config file.
        Nothing is left at ``out`` then.
    """
    if (preset is None) == (order is None):
        raise SlscanError("give either a phase-shifting preset or an order spec (not both, not neither)")
    chosen = get_phase_preset(preset) if preset is not None else PhasePreset(order)
    rotation = 0 if rotation is None else int(rotation)
    if rotation not in ROTATIONS:
        raise SlscanError(f"projector rotation {rotation} is not one of {ROTATIONS} (degrees)")
    if response == "auto":
        response = None
    if response is not None and response not in RESPONSES:
        raise SlscanError(f"camera response must be auto or one of {', '.join(RESPONSES)}, got {response!r}")
    src = Path(src).resolve()
    out_path = Path(out)
    found = find_views(src, pattern=pattern or chosen.pattern, views=chosen.views)
    _refuse_overlap(out_path.resolve(), src, list(found))
    plans = _plans(chosen, preset, src, found, projector_size)
    plan = next(iter(plans.values()))
    text, (pw, ph), slots = plan.text, plan.size, plan.slots
    placed = {folder: p.placed for folder, p in plans.items()}
    fmt, (cw, ch, channels, depth), lossy = _image_format(placed)
    response, response_fit = choose_response(src, response, _measure_response(placed, slots))
    patterns = flat.generate(pw, ph) + [s.desc for s in slots if s.desc is not None]
    device = {"kind": "import", "tool": tool or chosen.tool, "source": str(src), "order": text}
    if preset is not None:
        device["preset"] = preset
    logger.info(
        "importing %d view(s) of phase-shifting captures from %s: order %r, %s (%s response), camera %dx%d, "
        "projector %dx%d", len(placed), src, text, fmt.upper(), response, cw, ch, pw, ph,
    )
    with SessionWriter(
        out_path, camera_size=(cw, ch), projector_size=(pw, ph), channels=3 if channels == 4 else channels,
        bit_depth=depth, patterns=patterns, calibration=None, device=device, overwrite=overwrite, lossy=lossy,
        projector_rotation=rotation, response=response, response_fit=response_fit,
    ) as writer:
        copy_views(writer, placed, [s.pattern_id for s in slots], progress)
        session = writer.session()
    logger.info("wrote capture session %s (%d views)", out_path, len(placed))
    return session


def _measure_response(placed: dict[Path, dict[int, Path]], slots: list[PhaseSlot]):
    """The camera's tone curve measured as the Gray-code importer does, on the column Gray
    code's (pattern, inverse) pairs against white and black (not measured, linear, without
    them: fringes alone do not tell)."""
    at = {slot.pattern_id: i for i, slot in enumerate(slots) if slot.pattern_id is not None}
    bits = sorted({s.desc.params["bit"] for s in slots if s.kind == "gray" and s.desc.axis == "columns"
                   and not s.desc.params.get("complementary")})
    pairs = [(at[f"phase-col-gray-{b:02d}"], at[f"phase-col-gray-{b:02d}-inv"]) for b in bits
             if f"phase-col-gray-{b:02d}-inv" in at]
    return measure_placed_response(placed, at["white"], at["black"], pairs)


def _place_all(folder: Path, files: list[Path], slots: list[PhaseSlot], first: int | None, text: str,
               needs: str) -> dict[int, Path]:
    """Each file's position in the order; a missing one is an error naming the file and
    what it shows (a phase set has no bits to drop)."""
    placed = _place(folder, files, len(slots), first, text, needs, drop=True)
    missing = [i for i in range(len(slots)) if i not in placed]
    if missing:
        i = missing[0]
        numbering = _numbering(files)  # without numbered names _place refuses a short folder
        name = f"image {i}"
        if numbering is not None:
            prefix, suffix, digits, numbers = numbering
            start = first if first is not None else min(numbers)
            name = f"{prefix}{start + i:0{digits}d}{suffix}"
        others = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise SlscanError(
            f"{folder / name}: image not found; expected {slots[i].describe()} (position {i} of the order "
            f"{text!r}: {len(slots)} images, {needs}){others}; found {len(files)}"
        )
    return placed
