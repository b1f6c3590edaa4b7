"""Regression checks against the stored demo baseline (tests/data/baselines/demo)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import slscan.decode.pipeline as pipeline
from slscan.cli import main
from slscan.errors import SlscanError
from slscan.recipe.regress import collect_metrics, regress

BASELINE = Path(__file__).parents[1] / "data" / "baselines" / "demo"


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


def test_the_demo_baseline_passes_and_is_not_written():
    before = _snapshot(BASELINE)
    checks = regress(BASELINE)
    assert checks and all(c.ok for c in checks), [c for c in checks if not c.ok]
    assert {"decode/view_000.ply distance mm", "decode/view_000/vertices"} <= {c.name for c in checks}
    assert _snapshot(BASELINE) == before


def test_a_deliberate_change_in_a_stage_is_caught(monkeypatch, capsys):
    real = pipeline.triangulate

    def shifted(samples, camera, planes, **kw):  # a 'bug': points 0.05 mm further away
        points = real(samples, camera, planes, **kw)
        return points * (1 + 0.05 / np.linalg.norm(points, axis=1, keepdims=True))

    monkeypatch.setattr(pipeline, "triangulate", shifted)
    checks = regress(BASELINE)
    failed = {c.name for c in checks if not c.ok}
    assert "decode/view_000.ply distance mm" in failed
    # the command line says so and exits non-zero
    assert main(["regress", str(BASELINE), "--quiet"]) == 1
    assert "REGRESSION" in capsys.readouterr().out


def test_dropped_samples_are_caught(monkeypatch):
    real = pipeline.decode_hybrid

    def lossy(*args, **kw):
        result = real(*args, **kw)
        keep = np.arange(len(result.samples)) % 10 != 0  # a 'bug' losing a tenth of the lines
        return type(result)(**{**result.__dict__, "samples": result.samples.subset(keep)})

    monkeypatch.setattr(pipeline, "decode_hybrid", lossy)
    failed = {c.name for c in regress(BASELINE) if not c.ok}
    assert {"decode/view_000/samples", "decode/view_000/vertices"} <= failed


def test_broken_baselines_are_refused(tmp_path):
    copy = tmp_path / "demo"
    shutil.copytree(BASELINE, copy)
    meta = json.loads((copy / "baseline.json").read_text())
    meta["version"] = 99
    (copy / "baseline.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match="baseline version 99"):
        regress(copy)
    (copy / "recording.rrd").unlink()
    with pytest.raises(SlscanError, match="lacks recording.rrd"):
        regress(copy)
    with pytest.raises(SlscanError, match="not found"):
        regress(tmp_path / "nowhere")
    with pytest.raises(SlscanError, match="never writes into its baseline"):
        regress(BASELINE, work=BASELINE)


def test_texture_metrics_are_collected(tmp_path):
    (tmp_path / "texture").mkdir()
    (tmp_path / "texture" / "texture.json").write_text(json.dumps({"metrics": {"charts": 12, "seam_error_mean": 0.9}}))
    assert collect_metrics(tmp_path) == {"texture/charts": 12.0, "texture/seam_error_mean": 0.9}
