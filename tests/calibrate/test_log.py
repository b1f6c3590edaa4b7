"""Calibrate-stage loggers: nothing happens without a recording; the layout builds and saves."""

from __future__ import annotations

import numpy as np
import rerun.blueprint as rrb

from slscan.calibrate.pipeline import _log_calibration
from slscan.calibrate.planes import LightPlaneModel
from slscan.calibrate.target import Board, CornerDetection
from slscan.rig import default_rig
from slscan.viewer import log_calibrate as rlog
from slscan.viewer.layouts import calibrate_blueprint


def test_loggers_do_nothing_without_a_recording():
    det = CornerDetection.failed("a.png", "not found")
    rlog.log_board_image(None, np.zeros((4, 4), np.uint8), det, view_index=0)
    rlog.log_board_pose(None, Board(), np.eye(4), view_index=0)
    rlog.log_plane_residuals(None, np.ones(3), np.ones(3))
    _log_calibration(None, None, None)


def test_plane_outlines_lie_in_their_planes():
    proj = default_rig().projector
    model = LightPlaneModel(1024, proj.lens.fx, proj.lens.cx, proj.rig_from_projector)
    cols = np.array([0.0, 511.5, 1023.0])
    quads = rlog.plane_quads(model, cols, 768, 1000.0, 1600.0)
    for quad, plane in zip(quads, model.planes(cols)):
        assert quad.shape == (5, 3)
        np.testing.assert_allclose(quad @ plane[:3] + plane[3], 0.0, atol=1e-9)


def test_calibrate_blueprint_saves(tmp_path):
    blueprint = calibrate_blueprint()
    assert isinstance(blueprint, rrb.Blueprint)
    blueprint.save("slscan", tmp_path / "calibrate.rbl")
    assert (tmp_path / "calibrate.rbl").stat().st_size > 100
