"""Calibration from phase shifting with rows on small virtual-rig board sessions: known answers,
the ``slscan scan --board --patterns phase`` path end to end, and what is refused."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session
from slscan.calibrate.procam import projector_corners_from_edges
from slscan.calibrate.target import Board
from slscan.capture.session import load_session
from slscan.cli import main
from slscan.decode.phase import decode_phase, projector_constraints
from slscan.errors import SlscanError

BOARD = Board(columns=9, rows=7, square=50.0)
BOARD_ARGS = ["--board", "9x7", "--square", "50", "--quiet"]


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    """``slscan scan --board 9x7 --patterns phase`` on the virtual rig: four board poses
    under phase shifting with rows (camera 504x336, projector 358x269), and what it said."""
    out = tmp_path_factory.mktemp("board") / "session"
    code, err = _main_with_stderr(["scan", "--camera", "virtual", "--patterns", "phase", "--views", "4",
                                   "--out", str(out), "--scale", "0.35", *BOARD_ARGS])
    assert code == 0, err
    return load_session(out), err


def _main_with_stderr(argv: list[str]) -> tuple[int, str]:
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(argv)
    return code, err.getvalue()


@pytest.fixture(scope="module")
def session(scanned):
    return scanned[0]


@pytest.fixture(scope="module")
def run(session):
    return calibrate_session(session, CalibrationConfig(board=BOARD))


def normal_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a[:, :3], b[:, :3])), 0, 1)))


def true_corners(session, view):
    """The board's corners in the rig frame, and their true camera and projector pixels."""
    pose = view.rig_from_object
    points = BOARD.object_points() @ pose[:3, :3].T + pose[:3, 3]
    truth = session.calibration
    return truth.camera.project_local(points), truth.projector.project(points)


def test_the_session_holds_phase_with_rows_only(session):
    assert {p.family for p in session.patterns} == {"flat", "phase"}
    assert {p.axis for p in session.patterns if p.family == "phase"} == {"columns", "rows"}


def test_phase_maps_the_true_corners_into_the_projector(session):
    """Every decoded pixel of a window is a constraint: the local homography maps the true
    camera corners to within hundredths of a projector pixel of their true projections
    (measured: 0.006 px RMS, 0.015 px max; the Gray code's edges: 0.03 px RMS at 0.5 scale)."""
    errors, decoded = [], []
    for view in session.views:
        cam, proj = true_corners(session, view)
        constraints = projector_constraints(session, view)
        assert len(constraints) == 2 * int(decode_phase(session, view).mask.sum())
        pc = projector_corners_from_edges(constraints, cam, half_window=8)
        assert pc.ok.all()
        errors.append(np.linalg.norm(pc.points - proj, axis=1))
        decoded.append(pc.support / (2 * 17 * 17))
    errors = np.concatenate(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.015 and errors.max() < 0.05, errors.max()
    # the black squares are below the decoder's contrast floor: about half of each window
    # decodes, and the outlier rejection drops a tenth of that (the squares' blurred rims)
    assert 0.3 < np.median(np.concatenate(decoded)) < 0.7


def test_a_phase_board_session_calibrates_to_the_truth(session, run):
    """Both projector models from phase alone. Measured at this size: projector focal
    lengths within 0.65 px (0.1 %), principal point within 0.5 px, rotation 0.026 deg,
    centre 0.8 mm; light-plane normals within 0.041 deg, the model's fx 0.7 px."""
    truth = session.calibration
    cal = run.calibration
    assert cal.methods == ("inverse-camera", "planes")
    lens, true = cal.projector.lens, truth.projector.lens
    assert abs(lens.fx / true.fx - 1) < 0.002 and abs(lens.fy / true.fy - 1) < 0.002
    assert abs(lens.cx - true.cx) < 1.0 and abs(lens.cy - true.cy) < 1.0
    rot = cal.projector.rig_from_projector[:3, :3].T @ truth.projector.rig_from_projector[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))) < 0.05
    assert np.linalg.norm(cal.projector.center - truth.projector.center) < 1.5  # of 450 mm
    inv = cal.residuals["inverse_camera"]
    assert inv["stereo_rms_px"] < 0.06 and not inv["rejected"]
    assert all(v["corners"] == 63 for v in inv["views"])
    planes = run.light_planes
    assert planes.pattern == "phase" and len(planes.lines) > 220  # one per projector column
    assert planes.lines.columns.tolist() == np.round(planes.lines.columns).tolist()
    model = cal.light_planes
    assert abs(model.fx / true.fx - 1) < 0.002 and abs(model.cx - true.cx) < 1.5
    u = np.linspace(0, true.width - 1, 50)
    assert normal_angles(model.planes(u), truth.projector.column_planes(u)).max() < 0.1
    raw = normal_angles(cal.raw_planes, truth.projector.column_planes(cal.raw_columns))
    assert np.median(raw) < 0.06 and raw.max() < 0.2


def test_the_family_is_chosen_and_refused_by_name(session):
    with pytest.raises(SlscanError, match="has no gray patterns for the inverse camera"):
        calibrate_session(
            session, CalibrationConfig(board=BOARD, method="inverse-camera", inverse_pattern="gray")
        )
    with pytest.raises(SlscanError, match="unknown inverse-camera pattern 'hybrid'"):
        CalibrationConfig(inverse_pattern="hybrid")


def test_inverse_pattern_option_is_what_the_stage_accepts():
    """``--inverse-pattern``'s choices and default (built without the stage's modules) are
    exactly what :class:`CalibrationConfig` accepts and its default."""
    import argparse

    from slscan.calibrate.command import add_command

    calibrate = add_command(argparse.ArgumentParser().add_subparsers())
    action = next(a for a in calibrate._actions if "--inverse-pattern" in a.option_strings)
    assert action.default == CalibrationConfig().inverse_pattern
    for choice in action.choices:
        assert CalibrationConfig(inverse_pattern=choice).inverse_pattern == choice


def columns_only(session, out):
    """A copy of ``session`` with the phase row fringes and their Gray code taken out."""
    shutil.copytree(session.root, out)
    meta = json.loads((out / "session.json").read_text())
    meta["patterns"] = [p for p in meta["patterns"] if p.get("axis") != "rows"]
    for view in meta["views"]:
        view["images"] = [r for r in view["images"] if "phase-row" not in r.get("pattern", "")]
    (out / "session.json").write_text(json.dumps(meta))
    return out


@pytest.mark.parametrize(
    "options, message",
    [
        (["--method", "inverse-camera"], "the inverse-camera method needs projector row patterns"),
        ([], "the inverse-camera method needs projector row patterns"),
        (["--inverse-pattern", "phase"], "phase patterns code the projector columns only"),
    ],
)
def test_phase_without_rows_is_refused_in_one_line(session, tmp_path, capsys, options, message):
    copy = columns_only(session, tmp_path / "columns")
    out = tmp_path / "rig.json"
    assert main(["calibrate", str(copy), "--out", str(out), *BOARD_ARGS, *options]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0] and "Traceback" not in err, err
    assert not out.exists()


def test_phase_without_rows_still_gives_light_planes(session, tmp_path):
    copy = load_session(columns_only(session, tmp_path / "columns"))
    run = calibrate_session(copy, CalibrationConfig(board=BOARD, method="planes"))
    truth = session.calibration.projector
    u = np.linspace(0, truth.lens.width - 1, 50)
    assert run.light_planes.pattern == "phase"
    assert normal_angles(run.calibration.light_planes.planes(u), truth.column_planes(u)).max() < 0.1


def test_scan_board_with_phase_then_calibrate(scanned, tmp_path):
    """``slscan scan --board 9x7 --patterns phase`` captured a board session (no lit images,
    the board found in every pose) that ``slscan calibrate`` calibrates by both methods from
    the phase patterns alone (measured at this size: projector fx 0.6 px, cx 0.5 px off
    the truth; the light-plane model's fx 0.7 px)."""
    session, err = scanned
    assert err.count("board found: 63 corners") == 4 and "slscan calibrate" in err
    assert all(not v.lit_images() for v in session.views)
    rig = tmp_path / "rig.json"
    assert main(["calibrate", str(session.root), "--out", str(rig), *BOARD_ARGS]) == 0
    cal = json.loads(rig.read_text())
    truth = session.calibration.projector.lens
    assert cal["projector"]["lens"]["fx"] == pytest.approx(truth.fx, rel=0.002)
    assert cal["projector"]["lens"]["cx"] == pytest.approx(truth.cx, abs=1.0)
    assert cal["light_planes"]["model"]["fx"] == pytest.approx(truth.fx, rel=0.002)
    assert cal["residuals"]["light_planes"]["pattern"] == "phase"
    assert cal["residuals"]["inverse_camera"]["stereo_rms_px"] < 0.06
