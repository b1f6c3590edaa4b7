"""Both calibration methods on a small virtual-rig session of a board: known answers, end to end."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from slscan.calibrate.command import add_command
from slscan.calibrate.io import apply_calibration, calibration_planes, load_calibration
from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session
from slscan.calibrate.target import Board
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.errors import SlscanError
from slscan.virtual.boards import capture_calibration_session
from slscan.virtual.device import VirtualCaptureConfig

BOARD = Board(columns=9, rows=7, square=50.0)
SMALL = VirtualCaptureConfig(
    patterns="both",
    gray_rows=True,
    lit_images=False,
    camera_scale=0.4,
    projector_scale=0.4,
    levels=7,
)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return capture_calibration_session(
        tmp_path_factory.mktemp("board") / "session", BOARD, config=SMALL, n_poses=4
    )


@pytest.fixture(scope="module")
def parser():
    parser = argparse.ArgumentParser(prog="slscan")
    add_command(parser.add_subparsers(dest="command"))
    return parser


@pytest.fixture(scope="module")
def outputs(session, parser, tmp_path_factory):
    """``slscan calibrate`` on the session, both methods, with a recording and an XML export."""
    tmp = tmp_path_factory.mktemp("out")
    out, rrd, xml = tmp / "rig.json", tmp / "cal.rrd", tmp / "rig.xml"
    args = parser.parse_args(
        [
            "calibrate",
            str(session.root),
            "--out",
            str(out),
            "--square",
            "50",
            "--export-xml",
            str(xml),
            "--save",
            str(rrd),
            "--quiet",
        ]
    )
    assert args.func(args) == 0
    return out, rrd, xml


@pytest.fixture(scope="module")
def cal(outputs):
    return load_calibration(outputs[0])


def normal_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a[:, :3], b[:, :3])), 0, 1)))


def test_both_methods_recover_the_true_rig(session, cal):
    truth = session.calibration
    assert cal.methods == ("inverse-camera", "planes") and cal.board == BOARD
    assert cal.residuals["camera"]["rms_px"] < 0.1 and not cal.residuals["camera"]["rejected"]
    for est, true in ((cal.camera, truth.camera), (cal.projector.lens, truth.projector.lens)):
        assert abs(est.fx / true.fx - 1) < 0.01 and abs(est.fy / true.fy - 1) < 0.01
        assert abs(est.cx - true.cx) < 3 and abs(est.cy - true.cy) < 3
    assert (
        np.linalg.norm(cal.projector.center - truth.projector.center) < 2.0
    )  # of a 450 mm baseline
    assert cal.residuals["inverse_camera"]["stereo_rms_px"] < 0.15
    model = cal.light_planes
    assert (
        abs(model.fx / truth.projector.lens.fx - 1) < 0.01
        and abs(model.cx - truth.projector.lens.cx) < 3
    )
    u = np.linspace(0, truth.projector.lens.width - 1, 50)
    assert normal_angles(model.planes(u), truth.projector.column_planes(u)).max() < 0.1
    assert (
        normal_angles(
            calibration_planes(cal, source="inverse-camera").planes(u),
            truth.projector.column_planes(u),
        ).max()
        < 0.1
    )
    raw = normal_angles(cal.raw_planes, truth.projector.column_planes(cal.raw_columns))
    assert np.median(raw) < 0.1 and len(raw) > 60  # hybrid green lines
    lp = cal.residuals["light_planes"]
    assert lp["pattern"] == "hybrid" and 0 < lp["rms_before_global_fit_mm"] < 0.2
    assert lp["rms_after_global_fit_mm"] < 0.2


@pytest.mark.parametrize("source", ["planes", "raw-planes", "inverse-camera"])
def test_a_measured_calibration_decodes_end_to_end(session, cal, source):
    view = session.views[0]
    result = decode_view(
        apply_calibration(session, cal),
        view,
        DecodeConfig(method="gray"),
        planes=calibration_planes(cal, source=source),
    )
    points = result.range_map.vertices
    pose = view.rig_from_object  # the board's printed face is its z = 0 plane
    distance = np.abs((points - pose[:3, 3]) @ pose[:3, 2])
    assert len(points) > 10_000
    # 0.1 % of the 1.3 m working distance: what a few board poses leave of the scale
    assert np.median(distance) < 1.3 and np.percentile(distance, 95) < 2.5, np.median(distance)
    true = decode_view(session, view, DecodeConfig(method="gray")).range_map.vertices
    assert np.median(np.abs((true - pose[:3, 3]) @ pose[:3, 2])) < 0.2


def test_light_planes_of_the_gray_code_edges(session):
    run = calibrate_session(
        session, CalibrationConfig(board=BOARD, method="planes", planes_pattern="gray")
    )
    assert run.calibration.methods == ("planes",)
    truth = session.calibration.projector
    u = np.linspace(0, truth.lens.width - 1, 50)
    assert run.inverse_camera is None and run.calibration.projector is None
    assert normal_angles(run.calibration.light_planes.planes(u), truth.column_planes(u)).max() < 0.1
    assert len(run.light_planes.lines) > 200  # one per Gray-code edge on the board


def test_calibrate_command_writes_xml_and_recording(session, parser, outputs, cal, tmp_path):
    from rerun.chunk import RrdReader

    out, rrd, xml = outputs
    assert "<roration" in xml.read_text()
    paths = {c.entity_path for c in RrdReader(rrd).stream().to_chunks()}
    for expected in (
        "/world/camera/image/calibrate/corners",
        "/world/boards/view_000",
        "/world/projector/image/calibrate/corners",
        "/world/light_planes",
        "/plot/calibrate/camera_rms_px",
        "/plot/calibrate/plane_rms_after_mm",
    ):
        assert expected in paths, sorted(paths)
    # importing the exported XML gives the same calibration back
    args = parser.parse_args(
        [
            "calibrate",
            str(session.root),
            "--out",
            str(tmp_path / "imported.json"),
            "--import-xml",
            str(xml),
            "--quiet",
        ]
    )
    assert args.func(args) == 0
    imported = load_calibration(tmp_path / "imported.json")
    assert imported.camera == cal.camera and imported.projector.lens == cal.projector.lens
    with pytest.raises(SlscanError, match="exists"):
        args = parser.parse_args(
            ["calibrate", str(session.root), "--out", str(out), "--square", "50"]
        )
        args.func(args)
    with pytest.raises(SlscanError, match="--square"):
        args = parser.parse_args(
            ["calibrate", str(session.root), "--out", str(tmp_path / "x.json")]
        )
        args.func(args)


def test_no_row_codes_no_inverse_camera(session, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(session.root, copy)
    meta = json.loads((copy / "session.json").read_text())
    meta["patterns"] = [p for p in meta["patterns"] if p.get("axis") != "rows"]
    for v in meta["views"]:
        v["images"] = [r for r in v["images"] if "gray-row" not in r.get("pattern", "")]
    (copy / "session.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match="needs projector row patterns"):
        calibrate_session(copy, CalibrationConfig(board=BOARD, method="inverse-camera"))
