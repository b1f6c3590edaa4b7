"""Rerun logging of the live preview before a scan (``slscan preview``, ``slscan scan
--preview``): the camera's white frame with the focus tiles and the clipped pixels laid
over it, and focus, clipping and overlap as scalar plots, on the ``preview`` timeline
(the layout: :func:`slscan.viewer.layouts.preview_blueprint`)."""

from __future__ import annotations

import numpy as np
import rerun as rr

from slscan.viewer import paths

IMAGE_PATH = paths.PREVIEW_IMAGE_PATH
FOCUS_PATH = paths.PREVIEW_FOCUS_PATH
CLIPPED_PATH = paths.PREVIEW_CLIPPED_PATH
FOCUS_PLOT = paths.PREVIEW_FOCUS_PLOT
CLIPPED_PLOT = paths.PREVIEW_CLIPPED_PLOT
OVERLAP_PLOT = paths.PREVIEW_OVERLAP_PLOT
TEXT_PATH = paths.PREVIEW_TEXT_PATH
PREVIEW_TIMELINE = "preview"
CLIPPED_COLOR = (255, 40, 200, 220)  # magenta: a channel at full scale
FOCUS_ALPHA = 110


def focus_overlay(tiles: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w, 4) uint8 RGBA of the focus tiles (rows, cols) in [0, 1] stretched over an
    image of ``shape`` (h, w): red (blurred) through yellow to green (sharp); tiles
    without a value are transparent."""
    h, w = shape
    rows, cols = tiles.shape
    ys = np.minimum(np.arange(h) * rows // h, rows - 1)
    xs = np.minimum(np.arange(w) * cols // w, cols - 1)
    v = tiles[ys[:, None], xs[None, :]]
    valid = np.isfinite(v)
    v = np.clip(np.nan_to_num(v), 0.0, 1.0)
    out = np.zeros((h, w, 4), np.uint8)
    out[..., 0] = (255 * np.clip(2 - 2 * v, 0, 1)).astype(np.uint8)
    out[..., 1] = (255 * np.clip(2 * v, 0, 1)).astype(np.uint8)
    out[..., 3] = np.where(valid, FOCUS_ALPHA, 0).astype(np.uint8)
    return out


def log_preview(rec: rr.RecordingStream | None, index: int, measures) -> None:
    """Log one refresh (:class:`slscan.capture.preview.PreviewMeasures`) at ``index`` on
    the ``preview`` timeline; nothing when ``rec`` is None."""
    if rec is None:
        return
    rec.set_time(PREVIEW_TIMELINE, sequence=int(index))
    image = measures.image
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    rec.log(IMAGE_PATH, rr.Image(image))
    h, w = measures.lit.shape
    rec.log(FOCUS_PATH, rr.Image(focus_overlay(measures.focus_tiles, (h, w)), color_model="RGBA", draw_order=5.0))
    full = 255 if measures.image.dtype == np.uint8 else 65535
    top = measures.image.max(axis=2) if measures.image.ndim == 3 else measures.image
    clipped = np.zeros((h, w, 4), np.uint8)
    clipped[top >= full] = CLIPPED_COLOR
    rec.log(CLIPPED_PATH, rr.Image(clipped, color_model="RGBA", draw_order=10.0))
    if np.isfinite(measures.focus):
        rec.log(FOCUS_PLOT, rr.Scalars(float(measures.focus)))
    rec.log(CLIPPED_PLOT, rr.Scalars(100.0 * float(measures.clipped_share)))
    rec.log(OVERLAP_PLOT, rr.Scalars(100.0 * float(measures.overlap)))
    rec.log(TEXT_PATH, rr.TextLog(measures.line(), level="INFO"))
