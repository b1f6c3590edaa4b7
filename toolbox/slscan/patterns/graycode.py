"""Plain black/white Gray-code stripes with inverse images (the paper's first version).

Column ``c`` (or row) has the reflected-binary code ``g = c ^ (c >> 1)`` written with
``bits = ceil(log2(width))`` bits, most significant first. Image ``bit`` is white where
that bit of ``g`` is 1; its inverse is white where it is 0. This is the layout of
OpenCV's ``structured_light.GrayCodePattern`` and of the procam-calibration captures.

params of each image:

- ``bit`` : int, 0 = most significant; ``bits`` : int
- ``inverse`` : bool
- ``code`` : ``"reflected-binary"``, or ``"xor"`` for Gupta's XOR codes (below)
- ``base`` : XOR codes only: the bit every other bit is XOR-ed with

XOR codes (Gupta, Agrawal, Veeraraghavan, Narasimhan, "Structured light 3D scanning in
the presence of global illumination", CVPR 2011): image ``bit < base`` shows Gray bit
``bit`` XOR Gray bit ``base``; images ``bit >= base`` show their Gray bit itself (the
base, and the bits finer than it, already high-frequency: XOR-ing the 2 px bit with the
4 px base would leave stripes 1 px wide, too fine to locate their edges). With ``base`` a
fine bit (``bits - 2``: stripes 4 projector pixels wide, "XOR-04"; ``bits - 1``: 2 px,
"XOR-02") every image is high-frequency, so global light (inter-reflections, subsurface
scattering) falls about evenly on a pattern and its inverse, and cancels in
``pattern - inverse``; plain Gray code's low bits (half the field lit) do not have that
property. Decoding reads each image's bit and XORs the coarse ones back with the base
image's bit.
"""

from __future__ import annotations

import math

import numpy as np

from slscan.errors import SlscanError
from slscan.patterns import Family, PatternImage


def n_bits(size: int) -> int:
    return max(1, math.ceil(math.log2(size)))


def gray(values: np.ndarray) -> np.ndarray:
    values = np.asarray(values, dtype=np.int64)
    return values ^ (values >> 1)


def inverse_gray(codes: np.ndarray) -> np.ndarray:
    """Binary value of reflected-binary ``codes``."""
    value = np.asarray(codes, dtype=np.int64).copy()
    shift = value >> 1
    while np.any(shift):
        value ^= shift
        shift >>= 1
    return value


CODES = ("reflected-binary", "xor")

XOR_BASE_WIDTH = 4
"""Stripe width (projector px) of the XOR codes' default base bit: Gupta's "XOR-04"."""


def xor_base(bits: int, stripe_width: int = XOR_BASE_WIDTH) -> int:
    """The bit whose stripes are ``stripe_width`` (a power of two, >= 2) projector px wide."""
    if stripe_width < 2 or stripe_width & (stripe_width - 1):
        raise SlscanError(f"XOR base stripe width must be a power of two >= 2, got {stripe_width}")
    return max(0, bits - int(np.log2(stripe_width)))


def generate(width: int, height: int, *, rows: bool = False, code: str = "reflected-binary",
             base_width: int = XOR_BASE_WIDTH) -> list[PatternImage]:
    """(pattern, inverse) pairs for the columns, most significant bit first; rows if asked.

    code : {"reflected-binary", "xor"}; ``"xor"`` XORs every coarser bit with the one whose
        stripes are ``base_width`` projector pixels wide (see the module notes)
    """
    if code not in CODES:
        raise SlscanError(f"unknown Gray-code variant {code!r}: expected one of {CODES}")
    images = []
    axes = [("columns", width, "col")] + ([("rows", height, "row")] if rows else [])
    prefix = "gray" if code == "reflected-binary" else "xor"
    for axis, size, tag in axes:
        bits = n_bits(size)
        extra = {} if code == "reflected-binary" else {"base": xor_base(bits, base_width)}
        for bit in range(bits):
            for inverse in (False, True):
                images.append(
                    PatternImage(
                        f"{prefix}-{tag}-{bit:02d}{'-inv' if inverse else ''}", "gray", width, height, axis,
                        {"bit": bit, "bits": bits, "inverse": inverse, "code": code, **extra},
                    )
                )
    return images


def bit_of(values: np.ndarray, bits: int, bit: int) -> np.ndarray:
    """Gray bit ``bit`` (0 = most significant) of columns (rows) ``values``."""
    return (gray(values) >> (bits - 1 - bit)) & 1


def profile(desc: PatternImage) -> np.ndarray:
    size = desc.width if desc.axis == "columns" else desc.height
    p = desc.params
    at = np.arange(size)
    on = bit_of(at, p["bits"], p["bit"])
    if p.get("code", "reflected-binary") == "xor" and p["bit"] < p["base"]:
        on = on ^ bit_of(at, p["bits"], p["base"])
    if p["inverse"]:
        on = 1 - on
    return np.repeat((on * 255).astype(np.uint8)[:, None], 3, axis=1)


def finest(patterns) -> PatternImage | None:
    """The column pattern with the narrowest stripes (the last bit)."""
    coded = [p for p in patterns if p.family == "gray" and p.axis == "columns"]
    return max(coded, key=lambda p: p.params["bit"], default=None)


FAMILY = Family(
    name="gray",
    summary="black/white Gray-code stripes with inverses (xor: Gupta's XOR-04 codes)",
    generate=generate,
    profile=profile,
    decoder="slscan.decode.graycode",
    sets={"gray": {}, "xor": {"code": "xor"}},
    priority=1,
    rows=True,
    finest=finest,
)
