"""The preview layout as the operator sees it: the real viewer renders it headless.

One refresh of known measures (a grey camera frame; focus tiles 0 on the left half, 1 on
the right; a clipped block) goes through :func:`slscan.viewer.log_preview.log_preview` into
an .rrd with the preview layout; ``rerun`` takes a screenshot on a private Xvfb with Mesa's
Vulkan rasteriser. The overlay must show red (blurred) and green (sharp) tiles and the
magenta clipped block over the frame. Needs Xvfb and lavapipe (``.ci/setup``), as
tests/viewer/test_render_phase.py. About 15 s.
"""

from __future__ import annotations

import os
import subprocess

import cv2
import numpy as np

from slscan.capture.preview import PreviewMeasures
from slscan.viewer.layouts import preview_blueprint
from slscan.viewer.log_preview import log_preview
from slscan.viewer.recording import open_recording

from .test_render_phase import _requirements

WINDOW = (1000, 640)


def _shares(picture: np.ndarray) -> dict[str, float]:
    r, g, b = (picture[..., k].astype(int) for k in range(3))
    return {
        "red (blurred tiles)": float(((r > g + 40) & (r > b + 40) & (b < 110)).mean()),
        "green (sharp tiles)": float(((g > r + 40) & (g > b + 40)).mean()),
        "magenta (clipped)": float(((r > g + 80) & (b > g + 80)).mean()),
    }


def test_preview_layout_renders_focus_and_clipping(tmp_path):
    xvfb_run, rerun = _requirements()
    h, w = 240, 360
    image = np.full((h, w, 3), 128, np.uint8)
    image[20:60, 200:260] = 255
    tiles = np.zeros((6, 8))
    tiles[:, 4:] = 1.0
    measures = PreviewMeasures(image, tiles, 0.5, 0.01, 1.0, np.ones((h, w), bool), 0.1)
    rrd, shot = tmp_path / "preview.rrd", tmp_path / "preview.png"
    with open_recording(save=rrd, recording_name="preview render", blueprint=preview_blueprint()) as rec:
        log_preview(rec, 0, measures)
    ww, wh = WINDOW
    cmd = [xvfb_run, "-a", "-s", f"-screen 0 {5 * ww}x{5 * wh}x24", rerun, str(rrd),
           "--renderer", "vulkan", "--window-size", f"{ww}x{wh}", "--screenshot-to", str(shot)]
    run = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=180,
                         env={**os.environ, "RUST_LOG": "error"})
    assert run.returncode == 0 and shot.is_file(), (run.stdout + run.stderr)[-3000:]
    picture = cv2.imread(str(shot))[..., ::-1]
    shares = _shares(picture)
    assert shares["red (blurred tiles)"] > 0.03 and shares["green (sharp tiles)"] > 0.03, shares
    assert shares["magenta (clipped)"] > 0.001, shares
