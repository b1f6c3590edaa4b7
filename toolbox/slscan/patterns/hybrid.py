"""The paper's hybrid pattern: recursive subdivision with one-pixel green lines.

At level ``k`` (1-based) the projector width is cut into ``2**(k-1)`` regions; each region
is split in two by a one-pixel green line in its middle, with red on its left and blue
on its right. The bands give every pixel one bit per level (red 0, blue 1), so after
levels ``1..k-1`` a pixel knows its region and a line new in image ``k`` is indexed from
those bits; the green lines are the measured features (sub-pixel medial axis). ``L``
levels give ``2**L - 1`` lines; 9 levels on a 1024-pixel projector give 511 lines, two
projector pixels apart.

Line ``i`` (0-based, left to right, all levels) sits in projector column
``floor((i + 1) * width / 2**L)``; its light plane passes through that column's centre.

params of each image:

- ``level`` : int, 1-based; ``levels`` : int, total levels of the set
- ``lines`` : list of ``[line_index, column]`` for the green lines of this image
- ``regions`` : list of ``[start, stop)`` projector columns, one per line, same order
- ``colors`` : ``{"left": [255, 0, 0], "line": [0, 255, 0], "right": [0, 0, 255]}``

References
----------
C. Rocchini, P. Cignoni, C. Montani, P. Pingi, R. Scopigno. "A low cost 3D scanner based
on structured light". Computer Graphics Forum 20(3) (Eurographics 2001), 299-308.
"""

from __future__ import annotations

import numpy as np

from slscan.errors import SlscanError
from slscan.patterns import Family, PatternImage

RED = [255, 0, 0]
GREEN = [0, 255, 0]
BLUE = [0, 0, 255]
COLORS = {"left": RED, "line": GREEN, "right": BLUE}


def line_columns(width: int, levels: int) -> np.ndarray:
    """Projector column (n,) of every line ``i = 0 .. 2**levels - 2``, left to right."""
    m = np.arange(1, 2**levels, dtype=np.int64)
    return (m * width) // (2**levels)


def line_levels(levels: int) -> np.ndarray:
    """Level (1-based) at which each line appears, (n,) int."""
    m = np.arange(1, 2**levels, dtype=np.int64)
    trailing = np.zeros_like(m)
    mm = m.copy()
    while np.any(mm % 2 == 0):
        even = mm % 2 == 0
        trailing[even] += 1
        mm[even] //= 2
    return levels - trailing


def generate(width: int, height: int, *, levels: int = 9) -> list[PatternImage]:
    """Descriptions of the ``levels`` images of the hybrid pattern, coarse to fine."""
    if levels < 1:
        raise SlscanError(f"hybrid pattern: levels must be >= 1, got {levels}")
    if width < 2 ** (levels + 1):
        raise SlscanError(
            f"hybrid pattern: {levels} levels need a projector at least {2 ** (levels + 1)} px wide "
            f"(two pixels per line), got {width}"
        )
    columns = line_columns(width, levels)
    level_of = line_levels(levels)
    images = []
    for k in range(1, levels + 1):
        idx = np.flatnonzero(level_of == k)
        n_regions = 2 ** (k - 1)
        starts = (np.arange(n_regions) * width) // n_regions
        stops = (np.arange(1, n_regions + 1) * width) // n_regions
        images.append(
            PatternImage(
                f"hybrid-{k:02d}", "hybrid", width, height, "columns",
                {
                    "level": k,
                    "levels": levels,
                    "lines": [[int(i), int(columns[i])] for i in idx],
                    "regions": [[int(a), int(b)] for a, b in zip(starts, stops)],
                    "colors": COLORS,
                },
            )
        )
    return images


def band_labels(desc: PatternImage) -> np.ndarray:
    """Per projector column (width,) int8: 0 red (left), 1 blue (right), 2 green (line)."""
    labels = np.empty(desc.width, dtype=np.int8)
    for (_, col), (start, stop) in zip(desc.params["lines"], desc.params["regions"]):
        labels[start:col] = 0
        labels[col] = 2
        labels[col + 1 : stop] = 1
    return labels


def profile(desc: PatternImage) -> np.ndarray:
    colors = desc.params["colors"]
    table = np.array([colors["left"], colors["right"], colors["line"]], dtype=np.uint8)
    return table[band_labels(desc)]


def column_codes(images: list[PatternImage]) -> np.ndarray:
    """The code of every projector column after all ``images`` (levels in order).

    Returns (width,) int64: the binary number formed by the band bits (red 0, blue 1),
    most significant first. Columns that are green at some level get that line's
    ``-(line_index + 1)`` instead, since they carry a line, not a band.
    """
    width = images[0].width
    code = np.zeros(width, dtype=np.int64)
    line_of = np.zeros(width, dtype=np.int64)
    for desc in sorted(images, key=lambda d: d.params["level"]):
        labels = band_labels(desc)
        code = code * 2 + (labels == 1)
        for i, col in desc.params["lines"]:
            line_of[col] = -(i + 1)
    return np.where(line_of < 0, line_of, code)


def finest(patterns) -> PatternImage | None:
    """The level with the most lines (the last)."""
    coded = [p for p in patterns if p.family == "hybrid"]
    return max(coded, key=lambda p: p.params["level"], default=None)


FAMILY = Family(
    name="hybrid",
    summary="the paper's pattern: one-pixel green lines between red and blue bands",
    generate=generate,
    profile=profile,
    decoder="slscan.decode.hybrid",
    sets={"hybrid": {}},
    priority=2,
    lossy=False,
    finest=finest,
)
