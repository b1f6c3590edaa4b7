"""``slscan scan`` on the virtual rig: resume, exposure, calibration captures, bad input."""

from __future__ import annotations

import json

import pytest

from slscan.capture.session import load_session
from slscan.cli import main

QUICK = ["--scale", "0.25", "--levels", "6", "--quiet"]


def test_scan_resumes_with_the_next_view_and_keeps_the_first(tmp_path, capsys):
    out = tmp_path / "scan"
    assert main(["scan", "--camera", "virtual", "--views", "1", "--out", str(out), *QUICK]) == 0
    first = {p.name: p.read_bytes() for p in (out / "view_000").iterdir()}
    assert main(["scan", "--camera", "virtual", "--views", "2", "--out", str(out), *QUICK]) == 2
    assert "pass --resume to continue it" in capsys.readouterr().err
    assert main(["scan", "--camera", "virtual", "--views", "2", "--out", str(out), "--resume", *QUICK]) == 0
    session = load_session(out)
    assert [v.name for v in session.views] == ["view_000", "view_001"]
    assert {p.name: p.read_bytes() for p in (out / "view_000").iterdir()} == first
    assert session.views[1].rig_from_object is not None  # the turntable turned: a different pose
    assert abs(session.views[1].rig_from_object[0, 0] - session.views[0].rig_from_object[0, 0]) > 0.5
    err = capsys.readouterr().err
    assert "1 from before" in err and "covered" in err


def test_auto_exposure_brings_a_saturating_camera_down(tmp_path, capsys):
    out = tmp_path / "scan"
    assert main(["scan", "--camera", "virtual", "--exposure", "6", "--check-exposure", "--out", str(out),
                 *QUICK]) == 2
    err = capsys.readouterr().err
    assert "saturated" in err and "--auto-exposure searches for one" in err and not out.exists()
    assert main(["scan", "--camera", "virtual", "--check-exposure", *QUICK]) == 0  # no --out needed
    assert "clipped" in capsys.readouterr().err
    assert main(["scan", "--camera", "virtual", "--exposure", "6", "--auto-exposure", "--out", str(out),
                 *QUICK]) == 0
    meta = json.loads((out / "session.json").read_text())
    assert meta["views"][0]["exposure"]["camera"]["exposure"] < 6
    assert "clipped" in capsys.readouterr().err


def test_board_capture_goes_on_to_a_calibration(tmp_path, capsys):
    out = tmp_path / "board"
    assert main(["scan", "--camera", "virtual", "--board", "9x7", "--square", "50", "--views", "5",
                 "--out", str(out), "--scale", "0.5", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert err.count("board found: 63 corners") == 5 and "slscan calibrate" in err
    session = load_session(out)
    assert all(not v.lit_images() for v in session.views)
    assert {"hybrid", "gray"} <= {p.family for p in session.patterns}
    assert main(["calibrate", str(out), "--out", str(tmp_path / "rig.json"), "--board", "9x7", "--square", "50",
                 "--quiet"]) == 0
    rig = json.loads((tmp_path / "rig.json").read_text())
    truth = session.calibration.camera
    assert rig["camera"]["fx"] == pytest.approx(truth.fx, rel=0.01)


@pytest.mark.parametrize("argv, message", [
    (["--camera", "nikon"], "unknown camera 'nikon'"),
    (["--camera", "virtual", "--views", "0"], "--views must be at least 1"),
    (["--camera", "virtual", "--settle", "soon"], "--settle must be a number of seconds or auto"),
    (["--camera", "virtual", "--lit-exposure", "nan"], "--lit-exposure must be positive"),
    (["--camera", "virtual", "--levels", "12"], "--levels must be in 1..7 for a 256 px wide projector"),
    (["--camera", "virtual", "--resume", "--overwrite"], "contradict"),
    (["--camera", "folder:/nonexistent/dir", "--projector", "virtual"], "not a real projector"),
    (["--camera", "virtual", "--projector", "screen:0"], "--camera virtual sees the virtual projector only"),
    (["--camera", "virtual", "--calibration", "rig.json"], "--calibration is for real rigs"),
    (["--camera", "virtual", "--lights", "manual"], "--lights manual is for real rigs"),
])
def test_bad_scan_options_are_one_line_errors(tmp_path, capsys, argv, message):
    out = tmp_path / "s"
    assert main(["scan", *argv, "--out", str(out), "--scale", "0.25", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_the_scan_recording_fills_every_view_of_the_scan_layout(tmp_path):
    from tests.viewer.test_log import entity_paths

    rrd = tmp_path / "scan.rrd"
    assert main(["scan", "--camera", "virtual", "--out", str(tmp_path / "s"), "--save", str(rrd), *QUICK]) == 0
    paths = entity_paths(rrd)
    for wanted in ("/world/camera/image/capture", "/world/projector/image/pattern", "/world/camera/image/scan/holes",
                   "/plot/scan/coverage", "/world/scans/view_000/range_map", "/world/camera/image/decode/codes",
                   "/log/scan"):
        assert any(p == wanted or p.startswith(wanted + "/") for p in paths), (wanted, sorted(paths))
