"""Regression checks against the stored whole-pipeline demo baseline (tests/data/baselines/demo).

The baseline is re-run once (a module fixture). Each deliberate change then re-runs, on a
copy of that re-run and in this process (so that monkeypatches apply), only the changed
stage and those after it: the runner skips every stage whose settings and inputs are
unchanged. A change must fail its own stage, may fail the stages after it, and must fail
none before it.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from slscan import fuse
from slscan.cli import main
from slscan.decode import pipeline
from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.meshes import vertex_normals
from slscan.recipe.regress import (
    RECORDING,
    Check,
    baseline_inputs,
    collect_metrics,
    compare,
    failed_stages,
    format_table,
    make_baseline,
    regress,
)
from slscan.recipe.runner import load_recipe, parse_recipe, run_recipe
from slscan.register import multiview

BASELINE = Path(__file__).parents[1] / "data" / "baselines" / "demo"
IN_PROCESS = Executor(workers=1)
AFTER = {
    "decode": {"albedo", "register", "fuse", "simplify", "texture"},
    "albedo": {"texture"},
    "register": {"fuse", "simplify", "texture"},
    "fuse": {"simplify", "texture"},
    "simplify": {"texture"},
    "texture": set(),
}
"""The stages a change in each stage may also fail (those that use its results)."""


def _regenerate() -> str:
    command = json.loads((BASELINE / "baseline.json").read_text()).get("command")
    return (
        "If the change is intended (or the baseline format changed), regenerate the baseline "
        f"from the repository root (tests/data/baselines/README.md):\n  {command}"
    )


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*")}


@pytest.fixture(scope="module")
def rerun(tmp_path_factory) -> tuple[list[Check], Path, bool]:
    """The baseline re-run once: its checks, its folder, and whether the baseline stayed unwritten."""
    before = _snapshot(BASELINE)
    work = tmp_path_factory.mktemp("regress") / "run"
    try:
        checks = regress(BASELINE, work=work)
    except SlscanError as exc:  # e.g. an outdated baseline: it says how to regenerate it
        pytest.fail(f"{exc}\n{_regenerate()}")
    return checks, work, _snapshot(BASELINE) == before


def _rerun(
    rerun, tmp_path: Path, *, again: tuple[str, ...] = (), overrides: tuple[str, ...] = ()
) -> list[Check]:
    """Re-run on a copy of the shared re-run: the stages in ``again`` (and those whose
    settings or inputs change), in this process; compare with the baseline."""
    run = tmp_path / "run"
    shutil.copytree(rerun[1], run, ignore=shutil.ignore_patterns(RECORDING))
    for stage in again:
        (run / f"{stage}.stage.json").unlink()
    recipe = load_recipe(BASELINE / "recipe.resolved.toml", overrides=list(overrides))
    runs = run_recipe(recipe, run, given=baseline_inputs(BASELINE, recipe), executor=IN_PROCESS)
    changed = {o.split(".")[0] for o in overrides}
    assert {r.stage for r in runs if r.ran} <= {
        *again,
        *changed,
        *(s for c in changed for s in AFTER[c]),
    }
    return compare(BASELINE, run)


def _caught(checks: list[Check], stage: str) -> dict[str, Check]:
    """Assert ``stage`` failed and no stage before it did; its failed checks by metric."""
    failed = failed_stages(checks)
    assert stage in failed, format_table(checks)
    assert set(failed) <= {stage} | AFTER[stage], format_table([c for c in checks if not c.ok])
    return {c.metric: c for c in checks if c.stage == stage and not c.ok}


def test_the_stored_baseline_passes_and_is_not_written(rerun):
    checks, _, unwritten = rerun
    failed = [c for c in checks if not c.ok]
    assert not failed, f"the stored baseline regressed:\n{format_table(failed)}\n{_regenerate()}"
    assert unwritten
    names = {c.name for c in checks}
    assert {
        "decode/view_000 distance mean mm",
        "decode/view_000/samples",
        "albedo/view_000 PSNR dB",
        "albedo/view_000 valid IoU",
        "register/view_001 rotation deg",
        "register/view_001 shift mm",
        "fuse/distance mean mm",
        "fuse/distance p95 mm",
        "fuse/faces",
        "simplify/distance p95 mm",
        "texture/model distance mean mm",
        "texture/texture seen PSNR dB",
        "texture/texture filled PSNR dB",
        "texture/charts",
        "recording/entities with equal rows",
    } <= names


def test_the_stored_baseline_is_small_and_holds_what_is_compared():
    files = {
        str(p.relative_to(BASELINE)): p.stat().st_size for p in BASELINE.rglob("*") if p.is_file()
    }
    assert sum(files.values()) < 3_000_000
    session = json.loads((BASELINE / "capture" / "session.json").read_text())
    assert 2 <= len(session["views"]) <= 6 and all(
        v["ground_truth"] is None for v in session["views"]
    )
    assert not [f for f in files if f.endswith((".npz", ".stage.json", ".rrd", ".obj", ".glb"))]
    for name in (
        "lights/lights.json",
        "decode/view_000.ply",
        "albedo/view_000_albedo.png",
        "albedo/view_000_valid.png",
        "register/registration.json",
        "fuse/mesh.ply",
        "simplify/mesh.ply",
        "texture/model.ply",
        "texture/model_albedo.png",
        "texture/view_count.png",
    ):
        assert name in files, name
    meta = json.loads((BASELINE / "baseline.json").read_text())
    assert meta["command"].startswith("slscan baseline recipes/demo.toml --reduced")
    assert meta["inputs"] == ["capture", "lights"] and meta["recording"]


def test_a_change_in_decode_is_caught(rerun, tmp_path, monkeypatch):
    real = pipeline.triangulate

    def shifted(samples, camera, planes, **kw):  # a 'bug': points 0.05 mm further from the camera
        points = real(samples, camera, planes, **kw)
        return points * (1 + 0.05 / np.linalg.norm(points, axis=1, keepdims=True))

    monkeypatch.setattr(pipeline, "triangulate", shifted)
    failed = _caught(_rerun(rerun, tmp_path, again=("decode",)), "decode")
    # the range maps moved along the rays: at most 0.05 mm from their baseline surfaces
    assert {f"view_00{k} distance mean mm" for k in range(6)} <= set(failed)
    assert all(0.01 < c.current <= 0.051 for c in failed.values() if "distance" in c.metric)


def test_dropped_samples_are_caught(rerun, tmp_path, monkeypatch):
    from slscan.decode import hybrid

    real = hybrid.decode_hybrid

    def lossy(*args, **kw):
        result = real(*args, **kw)
        keep = np.arange(len(result.samples)) % 10 != 0  # a 'bug' losing a tenth of the lines
        return type(result)(**{**result.__dict__, "samples": result.samples.subset(keep)})

    monkeypatch.setattr(hybrid, "decode_hybrid", lossy)
    failed = _caught(_rerun(rerun, tmp_path, again=("decode",)), "decode")
    assert {"view_000/samples", "view_000/vertices"} <= set(failed)


def test_a_change_in_albedo_is_caught_by_the_command(capsys):
    # the whole command: re-run with a matte albedo (no specular lobe), exit 1 naming the stages
    assert main(["regress", str(BASELINE), "--set", "albedo.specular=none", "--quiet"]) == 1
    captured = capsys.readouterr()
    out = captured.out
    rows = [
        line.split()
        for line in out.splitlines()
        if line.split() and line.split()[-1] in ("ok", "REGRESSION")
    ]
    failed = {row[0] for row in rows if row[-1] == "REGRESSION"}
    assert "albedo" in failed and failed <= {"albedo", "texture"}, out
    assert any(row[0] == "albedo" and "PSNR" in row and row[-1] == "REGRESSION" for row in rows)
    assert "in stage(s): albedo" in " ".join(captured.err.split())


def test_a_change_in_register_is_caught(rerun, tmp_path, monkeypatch):
    real = multiview.register_scans

    def nudged(
        scans, **kw
    ):  # a 'bug': view_003 turned 0.1 degree about the vertical through its centroid
        result = real(scans, **kw)
        pose = result.poses["view_003"]
        scan = next(s for s in scans if s.name == "view_003")
        c = pose[:3, :3] @ scan.vertices.mean(axis=0) + pose[:3, 3]
        a = np.radians(0.1)
        turn = np.eye(4)
        turn[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        turn[:3, 3] = c - turn[:3, :3] @ c
        return dataclasses.replace(result, poses={**result.poses, "view_003": turn @ pose})

    monkeypatch.setattr(multiview, "register_scans", nudged)
    checks = _rerun(rerun, tmp_path, again=("register", "fuse", "simplify", "texture"))
    failed = _caught(checks, "register")
    assert set(failed) == {"view_003 rotation deg"}
    assert failed["view_003 rotation deg"].current == pytest.approx(0.1, abs=0.01)


def test_a_change_in_fuse_is_caught(rerun, tmp_path, monkeypatch):
    real = fuse.fuse_scans

    def swollen(*args, **kw):  # a 'bug': the fused surface 0.05 mm outwards
        result = real(*args, **kw)
        mesh = result.mesh
        moved = mesh.vertices + 0.05 * vertex_normals(mesh.vertices, mesh.faces)
        return dataclasses.replace(result, mesh=dataclasses.replace(mesh, vertices=moved))

    monkeypatch.setattr(fuse, "fuse_scans", swollen)
    failed = _caught(_rerun(rerun, tmp_path, again=("fuse", "simplify", "texture")), "fuse")
    assert failed["distance mean mm"].current == pytest.approx(0.05, abs=0.005)


def test_a_change_in_simplify_is_caught(rerun, tmp_path):
    # pymeshlab's quadric edge collapse instead of fast-simplification: same face count
    failed = _caught(_rerun(rerun, tmp_path, overrides=("simplify.method=quadric",)), "simplify")
    assert "distance mean mm" in failed and "faces" not in failed


def test_a_change_in_texture_is_caught(rerun, tmp_path):
    # weakly seen texels pulled harder towards the vertex colours: the seen colours change
    checks = _rerun(rerun, tmp_path, overrides=("texture.bake.prior_weight=0.1",))
    failed = _caught(checks, "texture")
    assert "texture seen PSNR dB" in failed
    assert not [c for c in checks if c.stage == "texture" and "distance" in c.metric and not c.ok]


def test_a_change_below_every_tolerance_passes(rerun, tmp_path):
    # a narrower truncation band moves the fused surface by about 0.002 mm; the texture
    # stage packs its atlas anew around the slightly different simplified mesh
    checks = _rerun(rerun, tmp_path, overrides=("fuse.truncation=3.0",))
    assert all(c.ok for c in checks), format_table([c for c in checks if not c.ok])


def test_tolerances_come_from_the_baseline(rerun, tmp_path):
    copy = tmp_path / "demo"
    shutil.copytree(BASELINE, copy)
    meta = json.loads((copy / "baseline.json").read_text())
    meta["tolerances"]["fused_mean_mm"] = 0.0  # float32 references are 1e-6 mm off
    (copy / "baseline.json").write_text(json.dumps(meta))
    failed = {c.name for c in compare(copy, rerun[1], stages=["fuse"]) if not c.ok}
    assert failed == {"fuse/distance mean mm"}
    meta["tolerances"]["fuse_mean"] = 1.0
    (copy / "baseline.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match="unknown tolerance.*fuse_mean"):
        compare(copy, rerun[1])


def test_broken_baselines_are_refused(tmp_path):
    copy = tmp_path / "demo"
    shutil.copytree(BASELINE, copy)
    meta = json.loads((copy / "baseline.json").read_text())
    meta["version"] = 1
    (copy / "baseline.json").write_text(json.dumps(meta))
    with pytest.raises(
        SlscanError, match=r"baseline version 1 is not supported.*regenerate it:  slscan baseline"
    ):
        regress(copy)
    shutil.rmtree(copy / "capture")
    meta["version"] = 2
    (copy / "baseline.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match=r"capture session \(capture/session.json\) is missing"):
        regress(copy)
    (copy / "recipe.resolved.toml").unlink()
    with pytest.raises(SlscanError, match="lacks recipe.resolved.toml"):
        regress(copy)
    with pytest.raises(SlscanError, match="not found"):
        regress(tmp_path / "nowhere")
    with pytest.raises(SlscanError, match="never writes into its baseline"):
        regress(BASELINE, work=BASELINE)


def test_a_baseline_of_another_recipe(tmp_path):
    """make_baseline on a small capture + decode recipe: what it stores, and regress on it."""
    recipe = parse_recipe(
        {
            "recipe": {"name": "mini", "stages": ["capture", "decode"]},
            "capture": {"views": 1, "camera_scale": 0.25, "projector_scale": 0.25, "levels": 7},
        },
        where="test",
    )
    out = make_baseline(recipe, tmp_path / "mini", command="slscan baseline mini.toml --out mini")
    stored = sorted(
        str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and "capture" not in p.parts
    )
    assert stored == ["baseline.json", "decode/view_000.ply", "recipe.resolved.toml"]
    meta = json.loads((out / "baseline.json").read_text())
    assert meta["command"] == "slscan baseline mini.toml --out mini" and meta["inputs"] == [
        "capture"
    ]
    checks = regress(out, executor=IN_PROCESS)
    assert checks and all(c.ok for c in checks), format_table(checks)
    assert {c.stage for c in checks} == {"decode", "recording"}
    with pytest.raises(SlscanError, match="not empty"):
        make_baseline(recipe, out)


def test_stage_metrics_are_collected(tmp_path):
    (tmp_path / "texture").mkdir()
    (tmp_path / "texture" / "texture.json").write_text(
        json.dumps({"metrics": {"charts": 12, "seam_error_mean": 0.9}})
    )
    (tmp_path / "albedo").mkdir()
    (tmp_path / "albedo" / "albedo.json").write_text(
        json.dumps({"views": [{"view": "view_000", "metrics": {"valid_share": 0.8}}]})
    )
    assert collect_metrics(tmp_path) == {
        "texture/charts": 12.0,
        "texture/seam_error_mean": 0.9,
        "albedo/view_000/valid_share": 0.8,
    }
