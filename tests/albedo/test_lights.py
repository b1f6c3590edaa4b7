"""Light calibration: the virtual rig's true lights are recovered from a matte-panel session."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from slscan.albedo.lights import (
    PANEL_FILE,
    LightCalibration,
    MattePanel,
    calibrate_lights,
    panel_samples,
    read_lights,
    write_lights,
)
from slscan.capture.session import load_session
from slscan.errors import SlscanError
from slscan.virtual.device import VirtualCaptureConfig


def test_recovers_true_positions_intensities_and_ambient(panel_session, calibrated):
    rig = panel_session.calibration
    true_positions = np.array([light.position for light in rig.lights])
    true_intensity = np.array([light.intensity for light in rig.lights])
    error_mm = np.linalg.norm(calibrated.positions - true_positions, axis=1)
    assert error_mm.max() < 3.0, error_mm
    np.testing.assert_allclose(calibrated.intensities, true_intensity, rtol=0.01)
    np.testing.assert_allclose(
        calibrated.ambient, VirtualCaptureConfig().optics.ambient, atol=0.002
    )
    # the reported uncertainty is honest: errors within a few sigma, sigma sub-millimetre
    sigma = np.array(calibrated.position_sigma)
    assert np.all(sigma < 2.0) and np.all(error_mm < 5 * sigma + 0.5), (error_mm, sigma)
    assert calibrated.reference_distance == rig.working_distance
    assert calibrated.fit["rms"] < 0.02


def test_json_round_trip(tmp_path, calibrated):
    path = write_lights(tmp_path / "lights.json", calibrated)
    back = read_lights(path)
    np.testing.assert_array_equal(back.positions, calibrated.positions)
    np.testing.assert_array_equal(back.intensities, calibrated.intensities)
    assert back.ambient == calibrated.ambient
    assert back.position_sigma == pytest.approx(calibrated.position_sigma)
    assert json.loads(path.read_text())["frame"] == "rig (camera) frame, mm"


def test_bad_light_files(tmp_path, calibrated):
    with pytest.raises(SlscanError, match="not found"):
        read_lights(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(SlscanError, match="bad.json.*not an slscan light calibration"):
        read_lights(bad)
    d = calibrated.to_dict()
    del d["lights"][2]["position"]
    bad.write_text(json.dumps(d))
    with pytest.raises(SlscanError, match="bad.json.*position"):
        read_lights(bad)


def test_panel_samples_lie_on_the_panel(panel_session):
    view = panel_session.views[1]
    panel = MattePanel()
    samples = panel_samples(panel_session, view, panel, max_samples=500)
    centre, normal = panel.front_plane(view.rig_from_object)
    np.testing.assert_allclose((samples.points - centre) @ normal, 0.0, atol=1e-6)
    assert 300 <= len(samples.points) <= 700
    assert samples.values.shape == (6, len(samples.points), 3)


def test_errors_name_what_is_missing(tmp_path, panel_session):
    copy = tmp_path / "session"
    shutil.copytree(panel_session.root, copy)
    (copy / PANEL_FILE).unlink()
    with pytest.raises(SlscanError, match="light_panel.json"):
        calibrate_lights(copy)
    # a panel pose is needed
    meta = json.loads((copy / "session.json").read_text())
    for v in meta["views"]:
        v["rig_from_object"] = None
    (copy / "session.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match="view_000.*pose is unknown"):
        calibrate_lights(load_session(copy), panel=MattePanel())
    # every light needs lit images
    meta["views"] = [
        {**v, "images": [r for r in v["images"] if r.get("light") != 4]} for v in meta["views"]
    ]
    (copy / "session.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match=r"no lit image of light\(s\) \[4\]"):
        calibrate_lights(load_session(copy), panel=MattePanel())


def test_nominal_lights_from_rig(panel_session):
    nominal = LightCalibration.from_rig(panel_session.calibration)
    assert len(nominal.lights) == 6 and nominal.ambient == (0.0, 0.0, 0.0)
    assert "nominal" in nominal.fit["source"]


def test_virtual_light_calibration_run(tmp_path):
    from slscan.virtual.panels import LightPanelConfig, calibrate_virtual_lights

    lights = calibrate_virtual_lights(LightPanelConfig(poses=3, scale=0.2), tmp_path / "lights")
    assert (tmp_path / "lights" / "session" / PANEL_FILE).is_file()
    back = read_lights(tmp_path / "lights" / "lights.json")
    np.testing.assert_array_equal(back.positions, lights.positions)
    assert back.fit["session"] == str((tmp_path / "lights" / "session").resolve())
    rig = load_session(tmp_path / "lights" / "session").calibration
    true = np.array([light.position for light in rig.lights])
    assert np.linalg.norm(lights.positions - true, axis=1).max() < 5.0
    np.testing.assert_allclose(lights.intensities, 0.8, rtol=0.01)


def test_srgb_camera_panel_is_read_in_linear_light(tmp_path):
    # a camera that saves sRGB codes (the 'tone' effect): the panel's codes are turned back
    # into light before the fit, so the lights come out as a linear camera's would (codes
    # read as light put them up to 65 mm off, their intensities 17 % low)
    from dataclasses import replace

    from slscan.virtual.panels import (
        LightPanelConfig,
        capture_light_calibration,
        light_calibration_poses,
    )

    config = replace(LightPanelConfig(poses=3, scale=0.2).capture_config(), effects=("tone",))
    session = capture_light_calibration(
        tmp_path / "session", config=config, poses=light_calibration_poses(config.rig(), count=3)
    )
    assert session.response == "srgb"
    rig = session.calibration
    true = np.array([light.position for light in rig.lights])
    lights = calibrate_lights(session, initial=true + 50.0)
    assert np.linalg.norm(lights.positions - true, axis=1).max() < 3.0
    np.testing.assert_allclose(lights.intensities, [light.intensity for light in rig.lights], rtol=0.01)
