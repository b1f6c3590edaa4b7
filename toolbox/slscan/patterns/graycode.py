"""Plain black/white Gray-code stripes with inverse images (the paper's first version).

Column ``c`` (or row) has the reflected-binary code ``g = c ^ (c >> 1)`` written with
``bits = ceil(log2(width))`` bits, most significant first. Image ``bit`` is white where
that bit of ``g`` is 1; its inverse is white where it is 0. This is the layout of
OpenCV's ``structured_light.GrayCodePattern`` and of the procam-calibration captures.

params of each image:

- ``bit`` : int, 0 = most significant; ``bits`` : int
- ``inverse`` : bool
- ``code`` : ``"reflected-binary"``
"""

from __future__ import annotations

import math

import numpy as np

from slscan.patterns import PatternImage


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


def generate(width: int, height: int, *, rows: bool = False) -> list[PatternImage]:
    """(pattern, inverse) pairs for the columns, most significant bit first; rows if asked."""
    images = []
    axes = [("columns", width, "col")] + ([("rows", height, "row")] if rows else [])
    for axis, size, tag in axes:
        bits = n_bits(size)
        for bit in range(bits):
            for inverse in (False, True):
                images.append(
                    PatternImage(
                        f"gray-{tag}-{bit:02d}{'-inv' if inverse else ''}", "gray", width, height, axis,
                        {"bit": bit, "bits": bits, "inverse": inverse, "code": "reflected-binary"},
                    )
                )
    return images


def profile(desc: PatternImage) -> np.ndarray:
    size = desc.width if desc.axis == "columns" else desc.height
    p = desc.params
    on = (gray(np.arange(size)) >> (p["bits"] - 1 - p["bit"])) & 1
    if p["inverse"]:
        on = 1 - on
    return np.repeat((on * 255).astype(np.uint8)[:, None], 3, axis=1)
