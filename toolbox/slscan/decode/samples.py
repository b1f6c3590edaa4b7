"""The result every decoder returns: sub-pixel camera positions of known projector planes."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

CONTINUITY_PX = 2.0
"""Camera px: a feature in the next row counts as the same line if it is this close in x."""


@dataclass(frozen=True)
class StripeSamples:
    """Where the camera saw each measured projector feature, one entry per (camera row, feature)
    (or per (camera column, feature) for samples found along columns).

    row : (k,) int32 camera row
    x : (k,) float64 sub-pixel camera column of the feature's centre (OpenCV pixel centres)
    projector_column : (k,) float64 continuous projector column ``u`` of the light plane the
        feature lies on (a hybrid green line: its column; a Gray-code edge: ``c + 0.5``
        between columns ``c`` and ``c + 1``)
    stripe : (k,) int32 feature index along the projector (hybrid line index 0..2**L-2,
        Gray-code edge index c); samples with consecutive ``stripe`` are neighbours
    contrast : (k,) float32 signal of the feature relative to the white frame, for quality
    saturated : (k,) bool, the feature's pixels were clipped in some image
    y : (k,) float64 sub-pixel camera row, or None: every sample lies on its pixel row
        ``row`` (found along camera rows)
    along_columns : (k,) bool, or None (all False): the sample was found along camera
        column ``x`` (a whole number) at sub-pixel row ``y`` (``row`` is ``y`` rounded),
        where the stripes cross camera columns more steeply than rows
    projector_row : (k,) float64 continuous projector row ``v`` at the sample as well, or
        None: only the column is known (phase shifting with row fringes knows both, and
        triangulates ray to ray)

    Use :attr:`camera_y` (or :meth:`pixels`) for the sample's camera position, which
    works either way.
    """

    row: np.ndarray
    x: np.ndarray
    projector_column: np.ndarray
    stripe: np.ndarray
    contrast: np.ndarray
    saturated: np.ndarray
    y: np.ndarray | None = None
    along_columns: np.ndarray | None = None
    projector_row: np.ndarray | None = None

    FIELDS = ("row", "x", "projector_column", "stripe", "contrast", "saturated", "y",
              "along_columns", "projector_row")

    def __len__(self) -> int:
        return len(self.row)

    @property
    def camera_y(self) -> np.ndarray:
        """(k,) float64 sub-pixel camera row of each sample."""
        return np.asarray(self.row, np.float64) if self.y is None else np.asarray(self.y, np.float64)

    def pixels(self) -> np.ndarray:
        """(k, 2) float64 camera pixel ``(x, y)`` of each sample (OpenCV pixel centres)."""
        return np.stack([np.asarray(self.x, np.float64), self.camera_y], axis=1)

    def lines(self) -> tuple[np.ndarray, np.ndarray]:
        """The search line of each sample and its position along it: ``(row, x)`` for
        samples found along rows, ``(offset + x, y)`` for those found along columns, with
        ``offset`` keeping the two kinds of lines apart (never adjacent). (k,) int64, (k,)
        float64."""
        line = np.asarray(self.row, np.int64)
        pos = np.asarray(self.x, np.float64)
        if self.along_columns is None or not np.any(self.along_columns):
            return line, pos
        along = np.asarray(self.along_columns, bool)
        offset = int(line.max()) + 3
        line = np.where(along, np.rint(pos).astype(np.int64) + offset, line)
        return line, np.where(along, self.camera_y, pos)

    def subset(self, keep: np.ndarray) -> StripeSamples:
        return StripeSamples(*(None if getattr(self, f) is None else getattr(self, f)[keep]
                               for f in self.FIELDS))

    def with_y(self) -> StripeSamples:
        """The same samples with ``y`` and ``along_columns`` filled in."""
        return replace(
            self, y=self.camera_y,
            along_columns=np.zeros(len(self), bool) if self.along_columns is None
            else np.asarray(self.along_columns, bool),
        )

    @staticmethod
    def concatenate(parts: Sequence[StripeSamples]) -> StripeSamples:
        """The samples of ``parts`` one after another (``y`` and ``along_columns`` filled in
        when some part has them)."""
        if not parts:
            return StripeSamples(np.zeros(0, np.int32), np.zeros(0), np.zeros(0),
                                 np.zeros(0, np.int32), np.zeros(0, np.float32), np.zeros(0, bool))
        full = any(p.y is not None or p.along_columns is not None for p in parts)
        if full:
            parts = [p.with_y() for p in parts]
        if any(p.projector_row is None for p in parts):  # rows known only where every part knows them
            parts = [replace(p, projector_row=None) for p in parts]
        return StripeSamples(*(None if getattr(parts[0], f) is None
                               else np.concatenate([getattr(p, f) for p in parts])
                               for f in StripeSamples.FIELDS))

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
        previous, following = self._along_feature(max_dx)
        return (np.isfinite(previous).astype(np.int8) + np.isfinite(following)).astype(np.int8)

    def _along_feature(self, max_dx: float) -> tuple[np.ndarray, np.ndarray]:
        """(k,) positions along their lines (``lines()``) of the same feature on the line
        before and after each sample, the nearer of up to two within ``max_dx`` px (a line
        may cross one plane twice); NaN where there is none."""
        n = len(self)
        if n == 0:
            return np.zeros(0), np.zeros(0)
        rows, x = self.lines()  # rows and x, or columns and y for samples found along columns
        stripes = np.asarray(self.stripe, np.int64) - int(np.min(self.stripe))
        span = int(stripes.max()) + 1
        keys = rows * span + stripes
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        found = []
        for step in (-span, span):
            wanted = keys + step
            first = np.searchsorted(sorted_keys, wanted)
            best = np.full(n, np.nan)
            for extra in (0, 1):
                at = np.minimum(first + extra, n - 1)
                cand = x[order[at]]
                ok = (sorted_keys[at] == wanted) & (np.abs(cand - x) <= max_dx)
                best = np.where(ok & ~(np.abs(best - x) <= np.abs(cand - x)), cand, best)
            found.append(best)
        return found[0], found[1]

    def smoothed(self, max_dx: float = CONTINUITY_PX) -> StripeSamples:
        """The samples with each position averaged along its feature, ``[1, 2, 1] / 4``
        over the previous, own and next line (row, or column for samples found along
        columns), where both neighbouring lines carry the same feature within ``max_dx``
        px; elsewhere (line ends, depth steps) the position is kept. A straight feature,
        slanted or not, keeps its position (the neighbours sit symmetrically about it), and
        independent noise of the positions drops to 0.61 of itself (``sqrt(6) / 4``).

        For Gray-code edges, where each row's crossing is found from that row alone; the
        hybrid decoder filters its line signal across rows before finding maxima instead.
        """
        if len(self) == 0:
            return self
        _, x = self.lines()
        near_x = self._along_feature(max_dx)
        both = np.isfinite(near_x[0]) & np.isfinite(near_x[1])
        pos = np.where(both, 0.5 * x + 0.25 * (near_x[0] + near_x[1]), x)
        if self.along_columns is None or not np.any(self.along_columns):
            return replace(self, x=pos)
        along = np.asarray(self.along_columns, bool)
        y = np.where(along, pos, self.camera_y)
        return replace(self, x=np.where(along, self.x, pos), y=y,
                       row=np.where(along, np.rint(y), self.row).astype(np.int32))

    def trim_line_ends(self, rows: int) -> StripeSamples:
        """The samples without the last ``rows`` samples at either end of every line run
        (lone samples go with the first)."""
        samples = self
        for _ in range(rows):
            samples = samples.subset(samples.continuity() == 2)
        return samples

    def sampled_share(self, mask: np.ndarray) -> float:
        """Share of the ``mask`` pixels (a view's lit pixels) with a sample in their row
        within the median gap between consecutive samples along rows (at least 2 px): about
        how much of the lit surface the samples reach, without meshing them. 1.0 for an
        empty mask. On the virtual marble bust: 0.95 under direct light for the hybrid
        pattern, 0.13 under subsurface scattering, which washes out its lines."""
        mask = np.asarray(mask, bool)
        if not mask.any():
            return 1.0
        h, w = mask.shape
        rows = np.asarray(self.row, np.int64)
        cols = np.rint(np.asarray(self.x, np.float64)).astype(np.int64)
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        rows, cols = rows[inside], cols[inside]
        if len(rows) == 0:
            return 0.0
        order = np.lexsort((cols, rows))
        rows, cols = rows[order], cols[order]
        same = rows[1:] == rows[:-1]
        reach = max(2, int(np.ceil(np.median(np.diff(cols)[same])))) if same.any() else 2
        import cv2

        hits = np.zeros((h, w), np.uint8)
        hits[rows, cols] = 1
        near = cv2.dilate(hits, np.ones((1, 2 * reach + 1), np.uint8)).astype(bool)
        return float(near[mask].mean())

    def shifted(self, rows: int, cols: int) -> StripeSamples:
        """The same samples with camera positions moved by ``rows`` and ``cols`` px (crop to image)."""
        return replace(self, row=(self.row + rows).astype(np.int32), x=self.x + cols,
                       y=None if self.y is None else self.y + rows)


class LightPlanes(Protocol):
    """Light planes of the projector, from the rig's known calibration or a measured one."""

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        """Planes (n, 4) ``[a, b, c, d]``, unit normal, rig frame (mm), ``a x + b y + c z + d = 0``,
        for continuous projector columns (n,)."""
