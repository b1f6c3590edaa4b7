"""The result every decoder returns: sub-pixel camera positions of known projector planes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

CONTINUITY_PX = 2.0
"""Camera px: a feature in the next row counts as the same line if it is this close in x."""


@dataclass(frozen=True)
class StripeSamples:
    """Where the camera saw each measured projector feature, one entry per (camera row, feature).

    row : (k,) int32 camera row
    x : (k,) float64 sub-pixel camera column of the feature's centre (OpenCV pixel centres)
    projector_column : (k,) float64 continuous projector column ``u`` of the light plane the
        feature lies on (a hybrid green line: its column; a Gray-code edge: ``c + 0.5``
        between columns ``c`` and ``c + 1``)
    stripe : (k,) int32 feature index along the projector (hybrid line index 0..2**L-2,
        Gray-code edge index c); samples with consecutive ``stripe`` are neighbours
    contrast : (k,) float32 signal of the feature relative to the white frame, for quality
    saturated : (k,) bool, the feature's pixels were clipped in some image
    """

    row: np.ndarray
    x: np.ndarray
    projector_column: np.ndarray
    stripe: np.ndarray
    contrast: np.ndarray
    saturated: np.ndarray

    def __len__(self) -> int:
        return len(self.row)

    def subset(self, keep: np.ndarray) -> StripeSamples:
        return StripeSamples(*(getattr(self, f)[keep] for f in
                               ("row", "x", "projector_column", "stripe", "contrast", "saturated")))

    def continuity(self, max_dx: float = CONTINUITY_PX) -> np.ndarray:
        """(k,) int8: how many of the rows just above and below carry the same feature
        within ``max_dx`` camera px of each sample (2 inside a line, 1 at its ends, 0 for a
        lone sample).

        Line ends are where the decoder's checks failed in the next row (a shadow or
        silhouette edge, an unreadable band, a lost maximum); the same cause spoils the
        last sample: on the full-size virtual figurine the camera-x error of samples with
        one neighbour is 3.2x (hybrid) and 2.0x (Gray code) that of samples with two
        (``benchmarks/line_ends.py``).
        """
        n = len(self)
        out = np.zeros(n, np.int8)
        if n == 0:
            return out
        rows = np.asarray(self.row, np.int64)
        stripes = np.asarray(self.stripe, np.int64) - int(np.min(self.stripe))
        span = int(stripes.max()) + 1
        keys = rows * span + stripes
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        x = np.asarray(self.x, np.float64)
        for step in (-span, span):
            wanted = keys + step
            first = np.searchsorted(sorted_keys, wanted)
            near = np.zeros(n, bool)
            for extra in (0, 1):  # a row may cross one plane twice: look at two candidates
                at = np.minimum(first + extra, n - 1)
                near |= (sorted_keys[at] == wanted) & (np.abs(x[order[at]] - x) <= max_dx)
            out += near
        return out

    def trim_line_ends(self, rows: int) -> StripeSamples:
        """The samples without the last ``rows`` samples at either end of every line run
        (lone samples go with the first)."""
        samples = self
        for _ in range(rows):
            samples = samples.subset(samples.continuity() == 2)
        return samples

    def shifted(self, rows: int, cols: int) -> StripeSamples:
        """The same samples with camera positions moved by ``rows`` and ``cols`` px (crop to image)."""
        return StripeSamples((self.row + rows).astype(np.int32), self.x + cols, self.projector_column,
                             self.stripe, self.contrast, self.saturated)


class LightPlanes(Protocol):
    """Light planes of the projector, from the rig's known calibration or a measured one."""

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), ``a x + b y + c z + d = 0``,
        for continuous projector columns (n,)."""
