"""Calibration of the real kamino410/procam-calibration captures, against that tool's result."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.calibrate.io import import_opencv_xml
from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session
from slscan.calibrate.target import Board
from slscan.capture.kamino410 import import_kamino410


def test_kamino410_captures_calibrate(shared_data, tmp_path):
    src = shared_data / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        pytest.skip(f"kamino410 captures not found at {src}")
    session = import_kamino410(src, tmp_path / "session")
    board = Board(columns=9, rows=7, square=75.0)
    run = calibrate_session(
        session, CalibrationConfig(board=board, method="both", planes_pattern="gray")
    )
    cal = run.calibration
    assert len(run.camera.views) == 5 and run.camera.rms < 0.5
    # the tool reports a stereo RMS of 0.857 px for these captures
    assert run.inverse_camera.stereo_rms < 0.857
    assert all(len(ids) == 63 for ids in run.inverse_camera.object_ids)
    ref = import_opencv_xml(
        src / "calibration_result.xml", projector_size=(1024, 768), projector_scale=0.5
    )
    assert abs(cal.camera.fx / ref.camera.fx - 1) < 0.01
    # the file's projector pixels are half the patterns' (graycode_step 2); halved, its focal
    # length is within 5 % of ours; the light-plane model, an independent measurement from the
    # same images, agrees with the inverse camera to 1 %
    assert abs(cal.projector.lens.fx / ref.projector.lens.fx - 1) < 0.05
    assert abs(cal.light_planes.fx / cal.projector.lens.fx - 1) < 0.01
    assert (
        abs(np.linalg.norm(cal.projector.center) / np.linalg.norm(ref.projector.center) - 1) < 0.1
    )
    # the projector sits about 0.63 m below the camera
    assert 550 < cal.projector.center[1] < 700
