"""Flat frames: all white (texture, shadow mask) and all black (ambient level).

params: ``value`` : [r, g, b] uint8 projected everywhere.
"""

from __future__ import annotations

import numpy as np

from slscan.patterns import PatternImage


def generate(width: int, height: int) -> list[PatternImage]:
    """The white and black frames for a ``width`` × ``height`` projector."""
    return [
        PatternImage("white", "flat", width, height, "none", {"value": [255, 255, 255]}),
        PatternImage("black", "flat", width, height, "none", {"value": [0, 0, 0]}),
    ]


def profile(desc: PatternImage) -> np.ndarray:
    return np.asarray([desc.params["value"]], dtype=np.uint8)
