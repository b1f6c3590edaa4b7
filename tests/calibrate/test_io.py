"""Calibration files: JSON round trip and its errors, OpenCV XML import and export, use in decoding."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slscan.calibrate.io import (
    Calibration,
    calibration_planes,
    export_opencv_xml,
    import_opencv_xml,
    load_calibration,
    save_calibration,
)
from slscan.calibrate.planes import LightPlaneModel, MeasuredPlanes
from slscan.calibrate.target import Board
from slscan.decode.triangulate import RigPlanes
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, Projector, default_rig


@pytest.fixture
def calibration() -> Calibration:
    rig = default_rig()
    proj = Projector(
        PinholeModel(1024, 768, 1850.5, 1851.5, 515.0, 390.0, (0.01, -0.02, 0.001, 0.0005, 0.003)),
        rig.projector.rig_from_projector,
    )
    model = LightPlaneModel(1024, 1856.0, 512.0, rig.projector.rig_from_projector)
    cols = np.arange(0.5, 1023, 64.0)
    return Calibration(
        camera=rig.camera,
        projector_size=(1024, 768),
        projector=proj,
        light_planes=model,
        raw_columns=cols,
        raw_planes=model.planes(cols),
        board=Board(kind="charuco", square=40.0),
        residuals={"camera": {"rms_px": 0.05}, "inverse_camera": {"stereo_rms_px": 0.1}},
        source={"session": "board-session"},
    )


def test_json_round_trip(tmp_path, calibration):
    path = save_calibration(calibration, tmp_path / "rig.json")
    back = load_calibration(path)
    assert back.camera == calibration.camera
    assert back.projector == calibration.projector
    np.testing.assert_array_equal(
        back.light_planes.rig_from_projector, calibration.light_planes.rig_from_projector
    )
    assert (back.light_planes.fx, back.light_planes.cx) == (1856.0, 512.0)
    np.testing.assert_array_equal(back.raw_planes, calibration.raw_planes)
    assert back.board == calibration.board and back.residuals == calibration.residuals
    assert back.methods == ("inverse-camera", "planes")
    d = json.loads(path.read_text())
    assert d["format"] == "slscan.calibration" and d["version"] == 1 and d["units"] == "mm"
    assert not list(tmp_path.glob(".rig.json.partial-*"))  # atomic write leaves nothing behind


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda d: d.update(version=7), "version 7 is not supported"),
        (lambda d: d.update(format="something"), "not an slscan calibration"),
        (lambda d: d.pop("camera"), "missing field 'camera'"),
        (lambda d: d["camera"].pop("fx"), "camera: missing field 'fx'"),
        (
            lambda d: d["projector"].pop("rig_from_projector"),
            "missing field 'projector.rig_from_projector'",
        ),
        (lambda d: d["light_planes"]["model"].pop("cx"), "light_planes.model: missing field 'cx'"),
        (
            lambda d: d.update(projector=None, light_planes=None),
            "missing field 'projector' or 'light_planes'",
        ),
        (lambda d: d.update(projector_size="big"), "projector_size"),
    ],
)
def test_bad_files_are_refused_naming_the_field(tmp_path, calibration, edit, message):
    path = save_calibration(calibration, tmp_path / "rig.json")
    d = json.loads(path.read_text())
    edit(d)
    path.write_text(json.dumps(d))
    with pytest.raises(SlscanError, match=message):
        load_calibration(path)
    with pytest.raises(SlscanError, match="not found"):
        load_calibration(tmp_path / "none.json")


def test_opencv_xml_round_trip(tmp_path, calibration):
    path = export_opencv_xml(calibration, tmp_path / "result.xml")
    text = path.read_text()
    assert "<roration" in text and "<cam_int" in text and "<img_shape" in text
    back = import_opencv_xml(path, projector_size=(1024, 768))
    assert back.camera == calibration.camera
    assert back.projector.lens == calibration.projector.lens
    np.testing.assert_allclose(
        back.projector.rig_from_projector, calibration.projector.rig_from_projector, atol=1e-9
    )
    assert back.residuals["imported"]["stereo_rms_px"] == pytest.approx(0.1)
    half = import_opencv_xml(path, projector_size=(1024, 768), projector_scale=0.5, units_mm=10.0)
    assert half.projector.lens.fx == pytest.approx(calibration.projector.lens.fx / 2)
    np.testing.assert_allclose(half.projector.center, 10 * calibration.projector.center, rtol=1e-9)
    planes_only = Calibration(
        calibration.camera, (1024, 768), light_planes=calibration.light_planes
    )
    with pytest.raises(SlscanError, match="needs the projector as an inverse camera"):
        export_opencv_xml(planes_only, tmp_path / "x.xml")
    text = text.replace("proj_dist", "projector_distortion")
    (tmp_path / "bad.xml").write_text(text)
    with pytest.raises(SlscanError, match="missing key 'proj_dist'"):
        import_opencv_xml(tmp_path / "bad.xml", projector_size=(1024, 768))


def test_calibration_planes_choose_the_model(calibration):
    assert isinstance(calibration_planes(calibration), MeasuredPlanes)
    assert isinstance(calibration_planes(calibration, source="inverse-camera"), RigPlanes)
    raw = calibration_planes(calibration, source="raw-planes")
    np.testing.assert_allclose(
        raw.planes(calibration.raw_columns), calibration.raw_planes, atol=1e-12
    )
    only_inverse = Calibration(calibration.camera, (1024, 768), projector=calibration.projector)
    assert isinstance(calibration_planes(only_inverse), RigPlanes)
    with pytest.raises(SlscanError, match="no light-plane model"):
        calibration_planes(only_inverse, source="planes")
    rig = Calibration(calibration.camera, (1024, 768), light_planes=calibration.light_planes).rig()
    np.testing.assert_allclose(
        rig.projector.column_planes([100.0]), calibration.light_planes.planes([100.0])
    )


def test_kamino410_reference_imports(shared_data):
    path = shared_data / "procam_graycode_kamino410" / "sample_data" / "calibration_result.xml"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    cal = import_opencv_xml(path, projector_size=(1024, 768))
    assert (cal.camera.width, cal.camera.height) == (1280, 1024)
    assert cal.camera.fx == pytest.approx(3452.39, abs=0.01)
    assert cal.projector.lens.fx == pytest.approx(3953.67, abs=0.01)
    assert cal.residuals["imported"]["stereo_rms_px"] == pytest.approx(0.8566, abs=1e-4)
    # translation (85.7, -630.5, -100.8) takes camera to projector points: the projector is below
    assert cal.projector.center[1] > 600 and 600 < np.linalg.norm(cal.projector.center) < 700


def test_auto_takes_the_inverse_camera_where_rows_pin_depth(calibration):
    from dataclasses import replace

    from slscan.virtual.rigs import RigParams

    # the paper's rig (projector beside the camera): the light planes, as before
    assert isinstance(calibration_planes(calibration), MeasuredPlanes)
    # the projector mostly above the camera: its rows pin depth ~5x better than the columns
    # that are all light planes have, so "auto" takes the inverse camera (explicit choices stay)
    above = RigParams(baseline_direction_deg=80.0).rig()
    vertical = replace(calibration, projector=Projector(calibration.projector.lens,
                                                        above.projector.rig_from_projector))
    assert isinstance(calibration_planes(vertical), RigPlanes)
    assert isinstance(calibration_planes(vertical, source="planes"), MeasuredPlanes)
