"""Rerun logging for live scans (``slscan scan``): every frame as it arrives, the quick
decode after each view (range map, holes, coverage), exposure and latency, and the
board corners of calibration captures (the ``scan`` layout: :func:`slscan.viewer.layouts.scan_blueprint`)."""

from __future__ import annotations

import numpy as np
import rerun as rr

from slscan.viewer.log import _overlay, _png, _set_view, log_capture, log_pattern
from slscan.viewer.paths import COVERAGE_PATH, DECODE_PATH, HOLES_PATH, SCAN_LOG_PATH
HOLE_COLOR = (255, 40, 200, 160)  # magenta: lit but no range-map triangle


def frame_logger(rec):
    """An ``on_frame`` callback for :func:`slscan.capture.driver.scan` logging each frame
    and the image projected for it; None when ``rec`` is None."""
    if rec is None:
        return None

    def on_frame(f) -> None:
        label = f.record.pattern or f"lit {f.record.light}"
        log_capture(rec, f.image, view_index=f.view_index, frame_index=f.frame_index, label=label)
        if f.projected is not None:
            log_pattern(rec, f.projected, view_index=f.view_index, frame_index=f.frame_index)

    return on_frame


def log_scan_text(rec: rr.RecordingStream | None, text: str, *, level: str = "INFO") -> None:
    """One line in the scan's log panel (exposure, latency, each view's coverage)."""
    if rec is not None:
        rec.log(SCAN_LOG_PATH, rr.TextLog(text, level=level))


def log_holes(
    rec: rr.RecordingStream | None, holes: np.ndarray, coverage: float, *, view_index: int
) -> None:
    """Overlay the decodable pixels that no range-map triangle covers, and plot coverage.

    holes : (h, w) bool camera px; coverage : covered share of the decodable pixels
    """
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(HOLES_PATH, _overlay(holes, HOLE_COLOR))
    rec.log(COVERAGE_PATH, rr.Scalars(float(coverage)))


def log_code_map(rec: rr.RecordingStream | None, image: np.ndarray, *, view_index: int) -> None:
    """The decoded code map of a view without calibration (no range map to show)."""
    if rec is None:
        return
    _set_view(rec, view_index)
    rec.log(f"{DECODE_PATH}/codes", _png(image))
