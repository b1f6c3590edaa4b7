"""The phase layout as the user sees it: the real viewer renders it headless.

A phase decode of known constant maps (a wrapped phase of a quarter turn on the columns
and three quarters on the rows, projector column and row at 20 % and 80 %, modulation
0.6, two blocks of corrected and rejected fringe orders) goes through the phase
decoder's display maps and the decode loggers into an .rrd; ``rerun`` opens it with the
phase layout (``viewer_layouts/phase.rbl`` as built by ``slscan.viewer.layouts``) on a
private Xvfb with Mesa's Vulkan rasteriser (lavapipe), and takes a screenshot. Every map's
colour must then cover a good part of the picture: each view shows its entity with its
colormap, and the corrections are drawn over the capture.

Needs Xvfb (``xvfb-run``) and Mesa's Vulkan driver (Debian ``mesa-vulkan-drivers``), which
``.ci/setup`` installs: skipped without them, failed when ``CI`` is set. About 15 s.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from slscan.decode.phase import ORDER_FIX_LABELS, AxisDecode, PhaseResult, display_maps, phase_stats
from slscan.patterns import standard_set
from slscan.rig import default_rig
from slscan.viewer.layouts import phase_blueprint
from slscan.viewer.log import log_capture, log_rig
from slscan.viewer.log_decode import colormap_range, log_display_maps, log_metrics
from slscan.viewer.recording import open_recording

WINDOW = (1000, 640)  # logical points; the screenshot is at the viewer's pixel density
TOLERANCE = 6  # per channel, 8-bit
MIN_SHARE = 0.002  # of the screenshot's pixels, for each expected colour (a view's image is ~2 %)
MARK_SHADING = (0.5, 1.05)  # the viewer shades 2D points: a mark's colour times 0.7-0.75 in Rerun 0.41


def _requirements() -> tuple[str, str]:
    xvfb_run = shutil.which("xvfb-run")
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    vulkan = glob.glob("/usr/share/vulkan/icd.d/lvp_icd*.json")
    missing = [name for name, found in (("xvfb-run (xvfb)", xvfb_run), ("rerun (rerun-sdk)", rerun),
                                        ("Mesa's Vulkan driver lavapipe (mesa-vulkan-drivers)", vulkan)) if not found]
    if missing:
        message = f"rendering the viewer needs {', '.join(missing)}: run .ci/setup"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return xvfb_run, rerun


def _phase_recording(path: Path) -> dict[str, np.ndarray]:
    """Log a phase decode of constant maps; return the colour each map should show."""
    rig = default_rig(scale=0.2, projector_scale=0.25)
    w, h = rig.camera.width, rig.camera.height
    pw, ph = rig.projector.lens.width, rig.projector.lens.height
    session = SimpleNamespace(projector_size=(pw, ph), patterns=standard_set("phase", width=pw, height=ph, rows=True))
    fix = np.zeros((h, w), np.int8)
    fix[h // 10: h // 2 - 2, w // 10: 9 * w // 10] = 1  # a block moved a period up
    fix[h // 2 + 2: 9 * h // 10, w // 10: 9 * w // 10] = 2  # ... and one rejected
    values = {"columns": (np.pi / 2, 0.2 * (pw - 1), 0.6, fix), "rows": (3 * np.pi / 2, 0.8 * (ph - 1), 0.3, 0 * fix)}
    axes = {
        axis: AxisDecode(np.full((h, w), coord), (np.full((h, w), coord),), (np.full((h, w), phase, np.float32),),
                         np.full((h, w), mod, np.float32), "complementary",
                         {"lit": w * h, "low_modulation": 0, "noisy": 0, "order_corrected": int((f == 1).sum()),
                          "order_rejected": int((f == 2).sum()), "periods_disagree": 0, "ambiguous": 0,
                          "out_of_range": 0, "valid": w * h}, f)
        for axis, (phase, coord, mod, f) in values.items()
    }
    full = np.ones((h, w), bool)
    result = PhaseResult(axes["columns"].coordinate, axes["rows"].coordinate, full, np.full((h, w), 0.5, np.float32),
                         ~full, 0.001, axes)
    # the layout travels in the recording, as ``slscan decode --save`` sends it (a layout
    # given beside the .rrd on the command line is applied or not, by a race in the viewer)
    with open_recording(save=path, recording_name="phase render", blueprint=phase_blueprint()) as rec:
        log_rig(rec, rig)
        log_capture(rec, np.full((h, w, 3), 128, np.uint8), view_index=0, frame_index=0, label="white",
                    compress=False)
        log_display_maps(rec, display_maps(result, session), view_index=0)
        stats = phase_stats(result)
        log_metrics(rec, stats, view_index=0, marked=stats)

    def colour(value, lo, hi, name):
        return colormap_range(np.array([[value]]), (lo, hi), name)[0, 0]

    return {
        "wrapped phase (columns), twilight": colour(np.pi / 2, 0, 2 * np.pi, "twilight"),
        "wrapped phase (rows), twilight": colour(3 * np.pi / 2, 0, 2 * np.pi, "twilight"),
        "projector column, turbo": colour(0.2 * (pw - 1), 0, pw - 1, "turbo"),
        "projector row, turbo": colour(0.8 * (ph - 1), 0, ph - 1, "turbo"),
        "modulation (columns), viridis": colour(0.6, 0, 1, "viridis"),
        "capture under the corrections": np.array([128, 128, 128]),
    }


MARKS = {"orders corrected up (marks)": np.array(ORDER_FIX_LABELS[1][1][:3]),
         "orders rejected (marks)": np.array(ORDER_FIX_LABELS[3][1][:3])}


def _share(picture: np.ndarray, rgb: np.ndarray, *, shaded: bool = False) -> float:
    """Share of ``picture``'s pixels showing ``rgb`` (or, ``shaded``, ``rgb`` darkened as the
    viewer shades a point)."""
    rgb = rgb.astype(np.float64)
    scale = picture @ rgb / (rgb @ rgb) if shaded else np.ones(picture.shape[:2])
    close = np.abs(picture - scale[..., None] * rgb).max(axis=-1) <= TOLERANCE
    return float((close & (scale >= MARK_SHADING[0]) & (scale <= MARK_SHADING[1])).mean())


def test_phase_layout_renders_every_map(tmp_path):
    xvfb_run, rerun = _requirements()
    rrd, shot = tmp_path / "phase.rrd", tmp_path / "phase.png"
    expected = _phase_recording(rrd)
    w, h = WINDOW
    # the X screen is made large so that the pointer, at its centre, is off the window: no tooltip
    cmd = [xvfb_run, "-a", "-s", f"-screen 0 {5 * w}x{5 * h}x24", rerun, str(rrd),
           "--renderer", "vulkan", "--window-size", f"{w}x{h}", "--screenshot-to", str(shot)]
    # RUST_LOG=error: no toasts (software rasteriser, container) over the views
    run = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=180,
                         env={**os.environ, "RUST_LOG": "error"})
    assert run.returncode == 0 and shot.is_file(), (run.stdout + run.stderr)[-3000:]
    picture = cv2.imread(str(shot))[..., ::-1].astype(np.float64)
    shares = {name: _share(picture, rgb) for name, rgb in expected.items()}
    shares |= {name: _share(picture, rgb, shaded=True) for name, rgb in MARKS.items()}
    missing = {name: f"{share:.4f}" for name, share in shares.items() if share < MIN_SHARE}
    assert not missing, f"colours hardly on screen: {missing} (kept {shot})"
