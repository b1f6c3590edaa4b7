"""The live preview before a scan: what the camera sees, how sharp the projected stripes
are (a focus aid), how much of the image is clipped, and how much of it the projector
lights, refreshed until the operator starts the scan.

Each refresh shows four images and captures each: black, white, fine vertical stripes
(``period_px`` projector pixels per period: 2 on, 2 off by default) and their inverse.

- **overlap**: the share of the camera image the projector lights (white brighter than
  black by 10 % of full scale), where a scan can measure anything;
- **clipped**: the share of those lit pixels with a channel at full scale in the white
  frame (saturation spoils the stripe axes, paper Fig. 9);
- **focus**: per tile of the image, the stripes' contrast ``|S - I| / (S + I)`` (stripes
  ``S``, inverse ``I``) averaged over the lit pixels: near 1 when the fine stripes are
  resolved, falling towards 0 as the camera or the projector is defocused (or the stripes
  are finer than the camera resolves). Turn the focus ring for the highest value; tiles
  show where in the image it is sharp.

Works with any :class:`~slscan.devices.base.Projector` and :class:`~slscan.devices.base.Camera`.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slscan.capture.driver import shoot_once
from slscan.devices.base import Camera, DeviceError, Projector

log = logging.getLogger(__name__)

LIT_LEVEL = 0.10  # a pixel is lit when white is brighter than black by this share of full scale
MIN_LIT_SHARE_PER_TILE = 0.05  # a tile with fewer lit pixels has no focus value (NaN)


@dataclass(frozen=True)
class PreviewMeasures:
    """One preview refresh.

    image : (h, w, 3) the camera's white frame, as captured
    focus_tiles : (rows, cols) float, stripe contrast per tile in [0, 1]; NaN where the
        projector lights too little of the tile
    focus : median of the tiles that have a value (NaN when none)
    clipped_share : share of the lit pixels with a channel at full scale (white frame)
    overlap : share of the camera image the projector lights
    lit : (h, w) bool, the pixels the projector lights
    seconds : how long the refresh took (s)
    """

    image: np.ndarray
    focus_tiles: np.ndarray
    focus: float
    clipped_share: float
    overlap: float
    lit: np.ndarray
    seconds: float

    def line(self) -> str:
        """One line for the terminal."""
        focus = "-" if math.isnan(self.focus) else f"{self.focus:.3f}"
        return (f"focus {focus}, clipped {100 * self.clipped_share:.2f} %, "
                f"projector lights {100 * self.overlap:.1f} % of the image")


def stripe_images(width: int, height: int, *, period_px: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Vertical stripes and their inverse, (height, width, 3) uint8 each: ``period_px // 2``
    white columns then as many black, and the reverse."""
    if period_px < 2 or period_px % 2:
        raise DeviceError(f"the preview's stripe period must be an even number of projector px >= 2, got {period_px}")
    on = (np.arange(width) % period_px) < period_px // 2
    stripes = np.zeros((height, width, 3), np.uint8)
    stripes[:, on] = 255
    return stripes, 255 - stripes


def _grey(image: np.ndarray) -> np.ndarray:
    full = 255.0 if image.dtype == np.uint8 else 65535.0
    grey = image.mean(axis=2) if image.ndim == 3 else image
    return grey.astype(np.float32) / np.float32(full)


def preview_measures(
    black: np.ndarray,
    white: np.ndarray,
    stripes: np.ndarray,
    inverse: np.ndarray,
    *,
    tiles: tuple[int, int] = (6, 8),
    seconds: float = 0.0,
) -> PreviewMeasures:
    """Focus, clipping and overlap from the four captures of one refresh.

    black, white, stripes, inverse : (h, w) or (h, w, 3) uint8 / uint16, one camera's frames
    tiles : (rows, cols) of the focus map
    """
    full = 255 if white.dtype == np.uint8 else 65535
    k, w_, s, i = _grey(black), _grey(white), _grey(stripes), _grey(inverse)
    lit = w_ - k > LIT_LEVEL
    overlap = float(lit.mean())
    top = white.max(axis=2) if white.ndim == 3 else white
    clipped = float((top[lit] >= full).mean()) if lit.any() else 0.0
    contrast = np.abs(s - i) / np.maximum(s + i - 2 * k, 1e-3)
    contrast = np.clip(contrast, 0.0, 1.0)
    rows, cols = tiles
    h, w = lit.shape
    focus = np.full((rows, cols), np.nan)
    for r in range(rows):
        for c in range(cols):
            y0, y1 = r * h // rows, (r + 1) * h // rows
            x0, x1 = c * w // cols, (c + 1) * w // cols
            m = lit[y0:y1, x0:x1]
            if m.size and m.mean() >= MIN_LIT_SHARE_PER_TILE:
                focus[r, c] = float(contrast[y0:y1, x0:x1][m].mean())
    valid = focus[np.isfinite(focus)]
    return PreviewMeasures(white, focus, float(np.median(valid)) if valid.size else math.nan, clipped, overlap,
                           lit, seconds)


def measure_once(
    projector: Projector,
    camera: Camera,
    *,
    period_px: int = 4,
    settle_s: float = 0.0,
    tiles: tuple[int, int] = (6, 8),
) -> PreviewMeasures:
    """Show black, white, stripes and inverse stripes, capture each, and measure."""
    w, h = projector.resolution
    stripes, inverse = stripe_images(w, h, period_px=period_px)
    white = np.full((h, w, 3), 255, np.uint8)
    t0 = time.monotonic()
    shots = []
    for name, image in (("black", None), ("white", white), ("stripes", stripes), ("inverse stripes", inverse)):
        shots.append(shoot_once(projector, camera, image, settle_s=settle_s, label=f"preview, {name}"))
    return preview_measures(*shots, tiles=tiles, seconds=time.monotonic() - t0)


def run_preview(
    projector: Projector,
    camera: Camera,
    *,
    seconds: float | None = None,
    frames: int | None = None,
    stop: Callable[[], bool] | None = None,
    on_measures: Callable[[int, PreviewMeasures], None] | None = None,
    period_px: int = 4,
    settle_s: float = 0.0,
    tiles: tuple[int, int] = (6, 8),
) -> list[PreviewMeasures]:
    """Refresh the preview until ``stop()`` is true (e.g. the operator pressed Enter),
    ``seconds`` have passed or ``frames`` refreshes were made (whichever comes first; at
    least one refresh); ``on_measures(index, measures)`` after each (logging, a line).
    Returns every refresh's measures. The projector is left dark."""
    if seconds is None and frames is None and stop is None:
        raise DeviceError("the preview needs an end: seconds, frames or a stop condition")
    if seconds is not None and not (math.isfinite(seconds) and seconds >= 0):
        raise DeviceError(f"preview seconds must be a number >= 0, got {seconds}")
    if frames is not None and frames < 1:
        raise DeviceError(f"preview frames must be at least 1, got {frames}")
    t_end = None if seconds is None else time.monotonic() + seconds
    out: list[PreviewMeasures] = []
    try:
        while True:
            measures = measure_once(projector, camera, period_px=period_px, settle_s=settle_s, tiles=tiles)
            out.append(measures)
            if on_measures is not None:
                on_measures(len(out) - 1, measures)
            if frames is not None and len(out) >= frames:
                break
            if t_end is not None and time.monotonic() >= t_end:
                break
            if stop is not None and stop():
                break
    finally:
        projector.blank()
    return out
