"""Regression checks cover calibration: a baseline of a calibration recipe (three of kamino410's
real procam captures, imported, camera and projector calibrated both ways) passes when re-run unchanged and
catches a board square of 70 mm instead of 75 mm, which scales the rig (the projector's
position, the light planes' distances) and changes no intrinsic.

The baseline is made once (a module fixture) with the recorded session's images copied
as they are instead of re-encoded at the strongest PNG compression (0.4 s of CPU per
1280 x 1024 image; lossless either way, and tested on the demo baseline): a fake of the
storage step only, named here. Needs the shared real data (skips without it).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from slscan.executor import Executor
from slscan.recipe import regress as regress_module
from slscan.recipe.regress import (
    RECORDING,
    baseline_inputs,
    compare,
    failed_stages,
    format_table,
    make_baseline,
    regress,
)
from slscan.recipe.runner import load_recipe, parse_recipe, run_recipe

IN_PROCESS = Executor(workers=1)


POSES = ("capture_0", "capture_2", "capture_3")
"""Three of the five board poses (the fewest a calibration takes), for time."""


def _recipe(source: Path):
    return parse_recipe(
        {
            "recipe": {"name": "kamino410-regress", "stages": ["import", "calibrate"]},
            "import": {"source": str(source), "format": "kamino410"},
            "calibrate": {
                "method": "both",
                "planes_pattern": "gray",
                "board": {"kind": "chessboard", "columns": 9, "rows": 7, "square": 75.0},
            },
        },
        where="test recipe",
    )


@pytest.fixture(scope="module")
def calibration_baseline(shared_data, tmp_path_factory) -> tuple[Path, Path, list]:
    """The baseline, its unchanged re-run (kept) and that re-run's checks."""
    folder = tmp_path_factory.mktemp("calibration_baseline")
    sample = shared_data / "procam_graycode_kamino410" / "sample_data"
    source = folder / "sample_data"
    source.mkdir()
    for name in (*POSES, "graycode_pattern"):
        (source / name).symlink_to(sample / name, target_is_directory=True)
    patch = pytest.MonkeyPatch()
    patch.setattr(regress_module, "_reencode_png", lambda src, dst: (
        dst.parent.mkdir(parents=True, exist_ok=True), shutil.copyfile(src, dst)))
    try:
        baseline = make_baseline(_recipe(source), folder / "baseline", executor=IN_PROCESS)
    finally:
        patch.undo()
    checks = regress(baseline, work=folder / "run", executor=IN_PROCESS)
    return baseline, folder / "run", checks


def test_an_unchanged_calibration_rerun_passes_and_compares_the_calibration(calibration_baseline):
    baseline, _, checks = calibration_baseline
    assert (baseline / "calibrate" / "calibration.json").is_file()
    failed = [c for c in checks if not c.ok]
    assert not failed, format_table(failed)
    names = {c.metric for c in checks if c.stage == "calibrate"}
    assert {
        "board",
        "models",
        "camera fx px",
        "camera distortion",
        "projector cy px",
        "projector rotation deg",
        "projector position mm",
        "light planes angle deg",
        "light planes offset mm",
        "light planes centre position mm",
        "raw light planes",
        "residuals camera/rms_px",
        "residuals inverse_camera/stereo_rms_px",
    } <= names, sorted(names)


def test_a_board_square_of_70_instead_of_75_mm_is_caught(calibration_baseline, tmp_path):
    baseline, kept, _ = calibration_baseline
    run = tmp_path / "run"
    shutil.copytree(kept, run, ignore=shutil.ignore_patterns(RECORDING))
    recipe = load_recipe(baseline / "recipe.resolved.toml", overrides=["calibrate.board.square=70"])
    runs = run_recipe(recipe, run, given=baseline_inputs(baseline, recipe), executor=IN_PROCESS)
    assert [r.stage for r in runs if r.ran] == ["calibrate"]
    checks = compare(baseline, run)
    assert failed_stages(checks) == ["calibrate"], format_table([c for c in checks if not c.ok])
    failed = {c.metric: c for c in checks if not c.ok}
    assert failed["board"].baseline == "chessboard 9x7, 75.0 mm"
    assert failed["board"].current == "chessboard 9x7, 70.0 mm"
    # the rig scales by 70/75: the projector moves by a fifteenth of its distance (mm, not um)
    assert failed["projector position mm"].current > 5.0
    assert failed["light planes offset mm"].current > 1.0
    for metric in ("camera fx px", "projector fx px", "projector rotation deg"):  # intrinsics hold
        assert metric not in failed, format_table(list(failed.values()))
