"""Regression checks: re-run a recorded session through its recipe and compare with a baseline.

A **baseline** folder holds a recipe run (``recipe.resolved.toml``, one folder per stage),
its recording (``recording.rrd``) and ``baseline.json`` with the metrics measured then.
:func:`regress` re-runs every stage after the recorded capture (the captures are the
fixed input) into a scratch folder and compares metric by metric, with tolerances, and
recording by recording (which entities were logged, how many rows each). The baseline is
only read, never written.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slscan import __version__
from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, read_json, write_json
from slscan.recipe.runner import Recipe, Reporter, load_recipe, run_recipe

BASELINE_FORMAT = "slscan.baseline"
BASELINE_VERSION = 1
RECORDING = "recording.rrd"

COUNT_TOLERANCE = 0.01
"""Relative tolerance on counts (samples, vertices, faces)."""
DISTANCE_TOLERANCE_MM = 0.01
"""Largest mean distance (both ways) between a range map and its baseline."""
SESSION_KINDS = ("session",)


@dataclass(frozen=True)
class Check:
    """One comparison: ``ok`` is False on a regression."""

    name: str
    baseline: float | str
    current: float | str
    tolerance: str
    ok: bool


def collect_metrics(run_dir: Path) -> dict[str, float]:
    """Comparable numbers of a recipe run: per decode stage and view, and the texture
    stage's metrics (charts, utilisation, observed share, seam error)."""
    metrics: dict[str, float] = {}
    for folder in sorted(p for p in run_dir.iterdir() if p.is_dir()):
        if (folder / "range_maps.json").is_file():
            summary = read_json(folder / "range_maps.json", "range-maps summary")
            for entry in summary["views"]:
                for key, value in entry["metrics"].items():
                    metrics[f"{folder.name}/{entry['view']}/{key}"] = float(value)
        if (folder / "texture.json").is_file():
            summary = read_json(folder / "texture.json", "texture manifest")
            for key, value in summary.get("metrics", {}).items():
                metrics[f"{folder.name}/{key}"] = float(value)
    return metrics


def _recording_rows(path: Path) -> dict[str, int]:
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    try:
        chunks = RrdReader(path).stream().to_chunks()
    except Exception as exc:  # rerun raises its own error types for foreign or broken files
        raise SlscanError(f"{path}: not a recording this Rerun can read ({str(exc).splitlines()[0]})") from None
    for chunk in chunks:
        if chunk.entity_path.startswith("/__"):
            continue  # recording properties
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def _rerun_entity(entity: str) -> bool:
    """Entities logged by the stages after capture (decode and later)."""
    return entity.startswith(("/world/camera/image/decode", "/plot")) or entity.endswith("/range_map")


def make_baseline(recipe: Recipe, out: str | os.PathLike, *, reporter: Reporter | None = None) -> Path:
    """Run ``recipe`` into a new baseline folder ``out`` with its recording and metrics."""
    from slscan.viewer.layouts import pipeline_blueprint
    from slscan.viewer.recording import open_recording

    out = Path(out)
    if not any(s.provides in SESSION_KINDS for s, _ in recipe.steps):
        raise SlscanError(f"recipe {recipe.name!r} records no capture session to re-run")
    with atomic_output_dir(out) as tmp:
        with open_recording(save=tmp / RECORDING, recording_name=f"baseline {recipe.name}",
                            blueprint=pipeline_blueprint()) as rec:
            # the captures are the fixed input of later checks: record only what is re-run
            run_recipe(recipe, tmp, rec=rec, reporter=reporter, unrecorded=SESSION_KINDS)
        write_json(tmp / "baseline.json", {
            "format": BASELINE_FORMAT, "version": BASELINE_VERSION, "slscan": __version__,
            "recipe": recipe.name, "metrics": collect_metrics(tmp),
        })
    return out


def _check_baseline(baseline: Path) -> tuple[dict[str, Any], Recipe, str]:
    if not baseline.is_dir():
        raise SlscanError(f"{baseline}: baseline folder not found")
    for name in ("baseline.json", "recipe.resolved.toml", RECORDING):
        if not (baseline / name).is_file():
            raise SlscanError(f"{baseline}: the baseline lacks {name}")
    meta = read_json(baseline / "baseline.json", "baseline description")
    if meta.get("format") != BASELINE_FORMAT:
        raise SlscanError(f"{baseline / 'baseline.json'}: not an slscan baseline")
    if meta.get("version") != BASELINE_VERSION:
        raise SlscanError(f"{baseline / 'baseline.json'}: baseline version {meta.get('version')} is not supported")
    recipe = load_recipe(baseline / "recipe.resolved.toml")
    session_stage = next((s.name for s, _ in recipe.steps if s.provides in SESSION_KINDS), None)
    if session_stage is None or not (baseline / session_stage / "session.json").is_file():
        raise SlscanError(f"{baseline}: the recorded capture session ({session_stage}/session.json) is missing")
    return meta, recipe, session_stage


def _mesh_distance(a_path: Path, b_path: Path) -> float:
    """Mean nearest-vertex distance, both ways, between two range maps (mm)."""
    from scipy.spatial import cKDTree

    from slscan.decode.rangemap import read_ply

    a, b = read_ply(a_path).vertices, read_ply(b_path).vertices
    if len(a) == 0 or len(b) == 0:
        return 0.0 if len(a) == len(b) else float("inf")
    return float(max(cKDTree(b).query(a)[0].mean(), cKDTree(a).query(b)[0].mean()))


def regress(baseline: str | os.PathLike, *, work: str | os.PathLike | None = None,
            reporter: Reporter | None = None) -> list[Check]:
    """Re-run ``baseline``'s recorded session through its recipe and compare; never writes it.

    work : keep the re-run here (default: a temporary folder, removed afterwards)
    """
    from slscan.viewer.layouts import pipeline_blueprint
    from slscan.viewer.recording import open_recording

    baseline = Path(baseline)
    meta, recipe, session_stage = _check_baseline(baseline)
    scratch = Path(work) if work else Path(tempfile.mkdtemp(prefix="slscan-regress-"))
    if scratch.resolve() == baseline.resolve():
        raise SlscanError("a regression run never writes into its baseline")
    if work and scratch.exists() and any(scratch.iterdir()):
        raise SlscanError(f"{scratch}: folder exists and is not empty")
    try:
        scratch.mkdir(parents=True, exist_ok=True)
        with open_recording(save=scratch / RECORDING, recording_name=f"regress {recipe.name}",
                            blueprint=pipeline_blueprint()) as rec:
            run_recipe(recipe, scratch, rec=rec, reporter=reporter,
                       given={"session": baseline / session_stage})
        checks = []
        current = collect_metrics(scratch)
        for key, old in sorted(meta["metrics"].items()):
            new = current.get(key)
            if new is None:
                checks.append(Check(key, old, "missing", "present", False))
                continue
            is_count = key.rsplit("/", 1)[-1] in ("samples", "vertices", "faces")
            tol = COUNT_TOLERANCE * max(abs(old), 1.0) if is_count else 1e-3 + 1e-3 * abs(old)
            checks.append(Check(key, old, new, f"±{tol:.3g}", abs(new - old) <= tol))
        for key in sorted(set(current) - set(meta["metrics"])):
            checks.append(Check(key, "missing", current[key], "present", False))
        for ply in sorted(baseline.glob("*/*.ply")):
            rel = ply.relative_to(baseline)
            if (scratch / rel).is_file():
                d = _mesh_distance(ply, scratch / rel)
                checks.append(Check(f"{rel} distance mm", 0.0, d, f"≤{DISTANCE_TOLERANCE_MM}",
                                    d <= DISTANCE_TOLERANCE_MM))
            else:
                checks.append(Check(str(rel), "present", "missing", "present", False))
        old_rows, new_rows = _recording_rows(baseline / RECORDING), _recording_rows(scratch / RECORDING)
        for entity in sorted(set(old_rows) | set(new_rows)):
            if not _rerun_entity(entity):
                continue  # captures are the fixed input: only re-run stages are compared
            o, n = old_rows.get(entity, 0), new_rows.get(entity, 0)
            checks.append(Check(f"recording {entity} rows", o, n, "equal", o == n))
        return checks
    finally:
        if not work:
            shutil.rmtree(scratch, ignore_errors=True)


def format_table(checks: list[Check]) -> str:
    width = max(len(c.name) for c in checks) if checks else 10

    def fmt(v: float | str) -> str:
        return f"{v:.6g}" if isinstance(v, (int, float, np.floating)) else str(v)

    lines = [f"{'check':<{width}}  {'baseline':>12}  {'current':>12}  {'tolerance':>10}  result"]
    for c in checks:
        lines.append(f"{c.name:<{width}}  {fmt(c.baseline):>12}  {fmt(c.current):>12}  {c.tolerance:>10}  "
                     + ("ok" if c.ok else "REGRESSION"))
    return "\n".join(lines)
