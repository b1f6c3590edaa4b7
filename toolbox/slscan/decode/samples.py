"""The result every decoder returns: sub-pixel camera positions of known projector planes."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


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

    def shifted(self, rows: int, cols: int) -> StripeSamples:
        """The same samples with camera positions moved by ``rows`` and ``cols`` px (crop to image)."""
        return StripeSamples((self.row + rows).astype(np.int32), self.x + cols, self.projector_column,
                             self.stripe, self.contrast, self.saturated)


class LightPlanes(Protocol):
    """Light planes of the projector, from the rig's known calibration or a measured one."""

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), ``a x + b y + c z + d = 0``,
        for continuous projector columns (n,)."""
