"""Flat frames: all white (texture, shadow mask) and all black (ambient level).

params: ``value`` : [r, g, b] uint8 projected everywhere.
"""

from __future__ import annotations

import numpy as np

from slscan.patterns import Family, PatternImage


def generate(width: int, height: int) -> list[PatternImage]:
    """The white and black frames for a ``width`` × ``height`` projector."""
    return [
        PatternImage("white", "flat", width, height, "none", {"value": [255, 255, 255]}),
        PatternImage("black", "flat", width, height, "none", {"value": [0, 0, 0]}),
    ]


def profile(desc: PatternImage) -> np.ndarray:
    return np.asarray([desc.params["value"]], dtype=np.uint8)


FAMILY = Family(
    name="flat",
    summary="uniform frames (white, black)",
    generate=lambda width, height: generate(width, height),
    profile=profile,
)
"""Flat frames are in every set (:func:`slscan.patterns.standard_set` puts them first);
they select no set and decode nothing by themselves."""
