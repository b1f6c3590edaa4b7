"""Regression checks: re-run a recorded session through its recipe and compare with a baseline.

A **baseline** folder (``slscan baseline``) holds what is needed to re-run a recipe and
check every stage of it, and nothing that can be recomputed and is not compared:

- the **recorded inputs**, handed to the re-run instead of running their stages: the
  capture session (``capture/``: images re-encoded losslessly, without the virtual rig's
  ground truth) and the ring-light calibration (``lights/lights.json``);
- for every later stage the **references** it is compared with, small and in open
  formats: the calibration (``calibration.json``), range maps and meshes as geometry-only
  binary PLY, the registration's poses
  (``registration.json``), the albedo images, the textured model as a PLY with per-vertex
  texture coordinates beside its atlas PNG (opens textured in MeshLab);
- ``recipe.resolved.toml`` and ``baseline.json``: the stages' metrics, the tolerances,
  the rows each entity of the re-run's Rerun recording had, and the command that made
  the baseline (run it again to regenerate it).

:func:`regress` re-runs the recipe on the recorded inputs into a scratch folder and
:func:`compare` checks it stage by stage against the tolerances in ``baseline.json``
(defaults: :class:`Tolerances`):

- calibrate: the board calibrated with, the camera's and the projector's intrinsics and
  distortion, the projector's pose (inverse camera), the light-plane model and its planes
  (largest angle and change of distance from the camera centre), and every residual;
- decode: each range map's symmetric surface distance (mean, p95) and its metrics;
- albedo: each view's PSNR over the pixels valid in both, and the overlap (IoU) of the
  valid masks;
- register: each view's pose, as the rotation between the two and the shift of the
  scan's centroid;
- fuse, simplify: the mesh's symmetric surface distance (mean, p95) and its face count
  (a simplified mesh with looser tolerances: simplification amplifies tiny differences);
- texture: the textured model's surface distance, and its colours at corresponding
  surface points (:func:`slscan.recipe.surfaces.texture_difference`, independent of the
  atlas layout) as PSNR where views saw both models, and separately where either was
  filled in from the vertices; the stage's metrics, those that follow the atlas layout
  with a looser tolerance;
- the recording: rows per entity.

Surface distances are point-to-surface (:mod:`slscan.recipe.surfaces`). The baseline is
only read, never written.
"""

from __future__ import annotations

import math
import os
import shlex
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from slscan import __version__
from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, glob_results, read_json, write_json
from slscan.recipe.runner import Recipe, Reporter, load_recipe, run_recipe
from slscan.recipe.stages import Stage
from slscan.recipe.surfaces import (
    MAX_PSNR,
    Surface,
    psnr,
    read_surface,
    read_textured_model,
    surface_distance,
    texture_difference,
    write_surface,
)

BASELINE_FORMAT = "slscan.baseline"
BASELINE_VERSION = 2
"""2: the whole pipeline (references per stage, tolerances, recording rows in
baseline.json); 1 held one decode stage and the recording itself."""
RECORDING = "recording.rrd"
"""The re-run's Rerun recording (the baseline keeps only its rows per entity)."""
INPUT_KINDS = ("session", "lights")
"""Results a baseline stores as recorded input and hands to the re-run instead of running
their stages: the capture session and the ring-light calibration, both measured on the rig."""
COUNT_KEYS = ("samples", "vertices", "faces", "pixels_on_range_map")
ATLAS_KEYS = (
    "charts",
    "utilisation",
    "texels_covered",
    "seam_edges",
    "seam_error_mean",
    "seam_error_p95",
    "vertices_observed_share",
)
COVERAGE_KEYS = ("observed_share", "mean_views_per_texel")


@dataclass(frozen=True)
class Tolerances:
    """How far a re-run may drift from its baseline. ``slscan baseline`` writes these into
    ``baseline.json``, where they can be edited for one baseline.

    Measured on the demo baseline (quarter-size camera, 6 views, 5 mm voxels, 3000
    faces): a re-run in one process or two, with one OpenMP thread or two, matches the
    baseline to the float32 rounding of its references (distances below 1e-5 mm, poses
    below 1e-5°, PSNR 100 dB, metrics equal). The tolerances leave room for other
    platforms' arithmetic and for the steps that amplify it: a fused mesh 1e-4 mm off
    simplifies to a mesh 0.03 mm (mean) and 0.17 mm (p95) off, and a simplified mesh a
    hair off gets an atlas packed anew, whose seen colours then differ by 45-47 dB, its
    filled ones by 32 dB and its seam metrics by up to 35 %. They still catch a range map
    0.05 mm off, a view turned by 0.1°, a fused surface 0.05 mm off, another
    simplification method, a matte albedo fit and a texture baked with a stronger pull to
    the vertex colours (``tests/recipe/test_regress.py``).
    """

    count: float = 0.01
    """Counts (samples, vertices, faces, valid pixels): relative difference."""
    metric_abs: float = 1e-3
    """Other stage metrics: ``|now - baseline| <= metric_abs + metric_rel * |baseline|``."""
    metric_rel: float = 1e-3
    atlas: float = 0.5
    """Texture metrics that follow the atlas layout, hence the simplified mesh's connectivity
    (charts, utilisation, texels covered, seam edges and error, vertices observed): relative."""
    coverage: float = 0.02
    """Texture coverage (observed share, mean views per texel): relative."""
    range_map_mean_mm: float = 0.01
    """Range maps: mean surface distance (mm)."""
    range_map_p95_mm: float = 0.05
    """Range maps: 95th percentile of the surface distance (mm)."""
    rotation_deg: float = 0.02
    """Registration: rotation between a view's two poses (degrees)."""
    shift_mm: float = 0.1
    """Registration: how far a view's centroid moves between its two poses (mm)."""
    fused_mean_mm: float = 0.02
    """Fused mesh: mean surface distance (mm)."""
    fused_p95_mm: float = 0.1
    """Fused mesh: 95th percentile of the surface distance (mm)."""
    simplified_mean_mm: float = 0.1
    """Simplified and textured models: mean surface distance (mm)."""
    simplified_p95_mm: float = 0.5
    """Simplified and textured models: 95th percentile of the surface distance (mm)."""
    albedo_psnr_db: float = 50.0
    """Albedo images: least PSNR (dB, linear reflectance, peak 1) over pixels valid in both."""
    albedo_valid_iou: float = 0.995
    """Albedo images: least overlap (intersection over union) of the valid masks."""
    texture_psnr_db: float = 40.0
    """Texture: least PSNR (dB, 8-bit sRGB) of the colours at corresponding surface points
    that views saw in both models."""
    filled_psnr_db: float = 25.0
    """Texture: least PSNR where either model's colour was filled in from the vertices
    (no view saw it there): the fill follows the atlas layout."""
    calibration_px: float = 0.05
    """Calibration: camera and projector intrinsics (focal lengths, principal point) and the
    light-plane model's ``fx``, ``cx`` (px)."""
    calibration_distortion: float = 1e-3
    """Calibration: each lens distortion coefficient (absolute)."""
    calibration_deg: float = 0.01
    """Calibration: the projector's rotation (inverse camera, light-plane model) and the
    largest angle between corresponding light planes (degrees)."""
    calibration_mm: float = 0.05
    """Calibration: the projector's position (inverse camera, light-plane model) and the
    largest change of a light plane's distance from the camera centre (mm)."""

    @classmethod
    def from_json(cls, data: dict[str, Any] | None, where: str) -> Tolerances:
        data = dict(data or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise SlscanError(
                f"{where}: unknown tolerance(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})"
            )
        try:
            return cls(**{k: float(v) for k, v in data.items()})
        except (TypeError, ValueError):
            raise SlscanError(f"{where}: tolerances must be numbers") from None


@dataclass(frozen=True)
class Check:
    """One comparison: ``ok`` is False on a regression."""

    stage: str
    metric: str
    baseline: float | str
    current: float | str
    tolerance: str
    ok: bool

    @property
    def name(self) -> str:
        return f"{self.stage}/{self.metric}"


def failed_stages(checks: list[Check]) -> list[str]:
    """Stages with at least one failed check, in the order of ``checks``."""
    return list(dict.fromkeys(c.stage for c in checks if not c.ok))


# --- metrics ----------------------------------------------------------------------------------


def collect_metrics(run_dir: Path) -> dict[str, float]:
    """Comparable numbers of a recipe run: per decode stage and view, per albedo stage and
    view, and the texture stage's metrics (charts, utilisation, observed share, seam error)."""
    metrics: dict[str, float] = {}
    for folder in sorted(p for p in Path(run_dir).iterdir() if p.is_dir() and not p.name.startswith(".")):
        for name, what in (
            ("range_maps.json", "range-maps summary"),
            ("albedo.json", "albedo summary"),
        ):
            if (folder / name).is_file():
                summary = read_json(folder / name, what)
                for entry in summary.get("views", []):
                    for key, value in entry.get("metrics", {}).items():
                        metrics[f"{folder.name}/{entry['view']}/{key}"] = float(value)
        if (folder / "texture.json").is_file():
            summary = read_json(folder / "texture.json", "texture manifest")
            for key, value in summary.get("metrics", {}).items():
                metrics[f"{folder.name}/{key}"] = float(value)
    return metrics


def _metric_checks(old: dict[str, float], new: dict[str, float], tol: Tolerances) -> list[Check]:
    checks = []
    for key in sorted(set(old) | set(new)):
        stage, metric = key.split("/", 1)
        if key not in new:
            checks.append(Check(stage, metric, old[key], "missing", "present", False))
            continue
        if key not in old:
            checks.append(Check(stage, metric, "missing", new[key], "present", False))
            continue
        a, b = old[key], new[key]
        name = metric.rsplit("/", 1)[-1]
        if name in COUNT_KEYS:
            bound = tol.count * max(abs(a), 1.0)
        elif name in ATLAS_KEYS:
            bound = tol.atlas * max(abs(a), 1e-3)
        elif name in COVERAGE_KEYS:
            bound = tol.coverage * max(abs(a), 1e-3)
        else:
            bound = tol.metric_abs + tol.metric_rel * abs(a)
        same = (math.isnan(a) and math.isnan(b)) or abs(b - a) <= bound
        checks.append(Check(stage, metric, a, b, f"±{bound:.3g}", bool(same)))
    return checks


def _at_most(stage: str, metric: str, value: float, bound: float) -> Check:
    return Check(stage, metric, 0.0, value, f"≤{bound:g}", bool(value <= bound))


def _at_least(stage: str, metric: str, value: float, bound: float, ideal: float) -> Check:
    return Check(stage, metric, ideal, value, f"≥{bound:g}", bool(value >= bound))


def _count(stage: str, metric: str, old: int, new: int, rel: float) -> Check:
    bound = rel * max(old, 1)
    return Check(stage, metric, old, new, f"±{bound:.3g}", abs(new - old) <= bound)


def _distance_checks(
    stage: str, prefix: str, old: Surface, new: Surface, tol_mean: float, tol_p95: float
) -> list[Check]:
    mean, p95 = surface_distance(old, new)
    return [
        _at_most(stage, f"{prefix}distance mean mm", mean, tol_mean),
        _at_most(stage, f"{prefix}distance p95 mm", p95, tol_p95),
    ]


def _missing(stage: str, what: str) -> Check:
    return Check(stage, what, "present", "missing", "present", False)


# --- per kind of result: what a baseline stores, and how it is compared ----------------------------

Store = Callable[[Path, Path], dict[str, Any]]
Compare = Callable[[Stage, Path, Path, Tolerances, dict[str, Any]], list[Check]]
"""``compare(stage, baseline_folder, run_folder, tolerances, references)``"""


def _reencode_png(src: Path, dst: Path) -> None:
    """Copy a PNG, re-encoded at the strongest lossless compression when that is smaller
    (pixels checked equal); any other file is copied as it is."""
    import cv2

    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.suffix.lower() == ".png":
        image = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        if image is not None:
            ok, data = cv2.imencode(
                ".png",
                image,
                [
                    cv2.IMWRITE_PNG_COMPRESSION,
                    9,
                    cv2.IMWRITE_PNG_STRATEGY,
                    cv2.IMWRITE_PNG_STRATEGY_FILTERED,
                ],
            )
            if (
                ok
                and data.size < src.stat().st_size
                and np.array_equal(cv2.imdecode(data, cv2.IMREAD_UNCHANGED), image)
            ):
                dst.write_bytes(data.tobytes())
                return
    shutil.copyfile(src, dst)


def _store_session(run: Path, dest: Path) -> dict[str, Any]:
    """The capture session, every image losslessly, without ground truth (a real rig has none)."""
    from slscan.capture.session import load_session

    session = load_session(run)
    views = []
    for view in session.views:
        for rec in view.images:
            path = session.image_path(view, rec)
            _reencode_png(path, dest / path.relative_to(session.root))
        views.append(replace(view, ground_truth=None))
    write_json(dest / "session.json", replace(session, root=dest, views=tuple(views)).to_dict())
    load_session(dest)  # the stored session must be one
    return {}


def _store_json_files(run: Path, dest: Path) -> dict[str, Any]:
    dest.mkdir(parents=True, exist_ok=True)
    for path in glob_results(run, "*.json"):
        shutil.copyfile(path, dest / path.name)
    return {}


def _store_range_maps(run: Path, dest: Path) -> dict[str, Any]:
    for path in glob_results(run, "*.ply"):
        write_surface(dest / path.name, read_surface(path))
    return {}


def _compare_range_maps(
    stage: Stage, old: Path, new: Path, tol: Tolerances, ref: dict
) -> list[Check]:
    checks = []
    for path in glob_results(old, "*.ply"):
        if not (new / path.name).is_file():
            checks.append(_missing(stage.name, path.name))
            continue
        checks += _distance_checks(
            stage.name,
            f"{path.stem} ",
            read_surface(path),
            read_surface(new / path.name),
            tol.range_map_mean_mm,
            tol.range_map_p95_mm,
        )
    return checks


def _store_albedo(run: Path, dest: Path) -> dict[str, Any]:
    for path in glob_results(run, "*_albedo.png") + glob_results(run, "*_valid.png"):
        _reencode_png(path, dest / path.name)
    return {}


def _compare_albedo(stage: Stage, old: Path, new: Path, tol: Tolerances, ref: dict) -> list[Check]:
    from slscan.fsio import read_png

    checks = []
    for path in glob_results(old, "*_albedo.png"):
        view = path.name[: -len("_albedo.png")]
        valid = f"{view}_valid.png"
        if not (new / path.name).is_file() or not (new / valid).is_file():
            checks.append(_missing(stage.name, path.name))
            continue
        a, b = read_png(path), read_png(new / path.name)
        va, vb = read_png(old / valid) > 0, read_png(new / valid) > 0
        if a.shape != b.shape or va.shape != vb.shape:
            checks.append(
                Check(stage.name, f"{view} size", str(a.shape), str(b.shape), "equal", False)
            )
            continue
        union = int((va | vb).sum())
        both = va & vb
        peak = float(np.iinfo(a.dtype).max) if a.dtype.kind == "u" else 1.0
        checks += [
            _at_least(
                stage.name,
                f"{view} PSNR dB",
                psnr(a[both] / peak, b[both] / peak, 1.0),
                tol.albedo_psnr_db,
                MAX_PSNR,
            ),
            _at_least(
                stage.name,
                f"{view} valid IoU",
                float(both.sum() / union) if union else 1.0,
                tol.albedo_valid_iou,
                1.0,
            ),
        ]
    return checks


def _store_registration(run: Path, dest: Path) -> dict[str, Any]:
    from slscan.register.meshlab import load_scan_project

    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run / "registration.json", dest / "registration.json")
    scans, _ = load_scan_project(run / "aligned.mlp")
    return {
        "centroids": {
            s.name: np.asarray(s.vertices, np.float64).mean(axis=0).tolist() for s in scans
        }
    }


def _compare_registration(
    stage: Stage, old: Path, new: Path, tol: Tolerances, ref: dict
) -> list[Check]:
    if not (new / "registration.json").is_file():
        return [_missing(stage.name, "registration.json")]
    a = read_json(old / "registration.json", "registration")["poses"]
    b = read_json(new / "registration.json", "registration")["poses"]
    centroids = ref.get("centroids", {})
    checks = []
    for view in sorted(set(a) | set(b)):
        if view not in b or view not in a:
            checks.append(
                Check(
                    stage.name,
                    f"{view} pose",
                    "registered" if view in a else "left out",
                    "registered" if view in b else "left out",
                    "equal",
                    False,
                )
            )
            continue
        pa, pb = np.asarray(a[view], np.float64), np.asarray(b[view], np.float64)
        cos = (np.trace(pb[:3, :3] @ pa[:3, :3].T) - 1.0) / 2.0
        c = np.append(np.asarray(centroids.get(view, (0.0, 0.0, 0.0)), np.float64), 1.0)
        checks += [
            _at_most(
                stage.name,
                f"{view} rotation deg",
                math.degrees(math.acos(float(np.clip(cos, -1, 1)))),
                tol.rotation_deg,
            ),
            _at_most(
                stage.name,
                f"{view} shift mm",
                float(np.linalg.norm((pb @ c - pa @ c)[:3])),
                tol.shift_mm,
            ),
        ]
    return checks


def _store_mesh(run: Path, dest: Path) -> dict[str, Any]:
    write_surface(dest / "mesh.ply", read_surface(run / "mesh.ply"))
    return {}


def _compare_mesh(stage: Stage, old: Path, new: Path, tol: Tolerances, ref: dict) -> list[Check]:
    """A mesh made from a mesh (simplified) has the simplified tolerances, a fused one the fused."""
    if not (new / "mesh.ply").is_file():
        return [_missing(stage.name, "mesh.ply")]
    a, b = read_surface(old / "mesh.ply"), read_surface(new / "mesh.ply")
    simplified = "mesh" in stage.needs
    return [
        *_distance_checks(
            stage.name,
            "",
            a,
            b,
            *(
                (tol.simplified_mean_mm, tol.simplified_p95_mm)
                if simplified
                else (tol.fused_mean_mm, tol.fused_p95_mm)
            ),
        ),
        _count(stage.name, "faces", len(a.faces), len(b.faces), tol.count),
    ]


CALIBRATION = "calibration.json"
PLANE_COLUMNS = 33
"""Projector columns (evenly spaced, both edges included) at which light planes are compared."""


def _store_calibration(run: Path, dest: Path) -> dict[str, Any]:
    from slscan.calibrate.io import load_calibration

    load_calibration(run / CALIBRATION)  # a calibration this slscan reads back
    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(run / CALIBRATION, dest / CALIBRATION)
    return {}


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) of the rotation between the rotation parts of poses ``a`` and ``b``."""
    cos = (np.trace(np.asarray(b)[:3, :3] @ np.asarray(a)[:3, :3].T) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def _lens_checks(stage: str, what: str, a, b, tol: Tolerances) -> list[Check]:
    """A lens (:class:`slscan.rig.PinholeModel`): size equal, intrinsics in px, distortion."""
    if (a.width, a.height) != (b.width, b.height):
        return [Check(stage, f"{what} size", f"{a.width}x{a.height}", f"{b.width}x{b.height}", "equal", False)]
    checks = [
        _at_most(stage, f"{what} {name} px", abs(getattr(b, name) - getattr(a, name)), tol.calibration_px)
        for name in ("fx", "fy", "cx", "cy")
    ]
    checks.append(_at_most(stage, f"{what} distortion", float(np.max(np.abs(np.subtract(b.dist, a.dist)))),
                           tol.calibration_distortion))
    return checks


def _pose_checks(stage: str, what: str, a: np.ndarray, b: np.ndarray, tol: Tolerances) -> list[Check]:
    return [
        _at_most(stage, f"{what} rotation deg", _rotation_deg(a, b), tol.calibration_deg),
        _at_most(stage, f"{what} position mm",
                 float(np.linalg.norm(np.asarray(b)[:3, 3] - np.asarray(a)[:3, 3])), tol.calibration_mm),
    ]


def _plane_checks(stage: str, a, b, tol: Tolerances) -> list[Check]:
    """The light-plane models: their parameters, then the planes themselves at
    :data:`PLANE_COLUMNS` columns: the largest angle between corresponding planes and the
    largest change of their distance from the camera centre (the rig origin)."""
    if a.width != b.width:
        return [Check(stage, "light planes width px", a.width, b.width, "equal", False)]
    columns = np.linspace(0.0, a.width - 1.0, PLANE_COLUMNS)
    pa, pb = a.planes(columns), b.planes(columns)
    pb = pb * np.where(np.einsum("ij,ij->i", pa[:, :3], pb[:, :3]) < 0, -1.0, 1.0)[:, None]
    cos = np.clip(np.einsum("ij,ij->i", pa[:, :3], pb[:, :3]), -1.0, 1.0)
    return [
        _at_most(stage, "light planes fx px", abs(b.fx - a.fx), tol.calibration_px),
        _at_most(stage, "light planes cx px", abs(b.cx - a.cx), tol.calibration_px),
        *_pose_checks(stage, "light planes centre", a.rig_from_projector, b.rig_from_projector, tol),
        _at_most(stage, "light planes angle deg", float(np.degrees(np.arccos(cos)).max()),
                 tol.calibration_deg),
        _at_most(stage, "light planes offset mm", float(np.abs(pb[:, 3] - pa[:, 3]).max()),
                 tol.calibration_mm),
    ]


def _residual_numbers(value: Any, prefix: str = "") -> dict[str, float]:
    """The numbers of a calibration's ``residuals`` by path (``camera/rms_px``,
    ``inverse_camera/views/2/projector_rms_px``); lists of rejected views by their count;
    names and other text left out (a view's file name holds the run's folder)."""
    out: dict[str, float] = {}
    if isinstance(value, dict):
        for key, item in value.items():
            if key == "rejected" and isinstance(item, list):
                out[f"{prefix}{key} count"] = float(len(item))
            else:
                out.update(_residual_numbers(item, f"{prefix}{key}/"))
    elif isinstance(value, list):
        for k, item in enumerate(value):
            out.update(_residual_numbers(item, f"{prefix}{k}/"))
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        out[prefix.rstrip("/")] = float(value)
    return out


def _compare_calibration(stage: Stage, old: Path, new: Path, tol: Tolerances, ref: dict) -> list[Check]:
    """Camera and projector (inverse camera and light-plane model), and the residuals."""
    from slscan.calibrate.io import load_calibration

    if not (old / CALIBRATION).is_file():
        return [Check(stage.name, f"{CALIBRATION} in the baseline", "missing", "", "present", False)]
    if not (new / CALIBRATION).is_file():
        return [_missing(stage.name, CALIBRATION)]
    a, b = load_calibration(old / CALIBRATION), load_calibration(new / CALIBRATION)
    name = stage.name
    board_a = None if a.board is None else a.board.to_dict()
    board_b = None if b.board is None else b.board.to_dict()
    checks = [
        Check(name, "board", _board_text(board_a), _board_text(board_b), "equal", board_a == board_b),
        Check(name, "models", "+".join(a.methods) or "none", "+".join(b.methods) or "none", "equal",
              a.methods == b.methods),
        *_lens_checks(name, "camera", a.camera, b.camera, tol),
    ]
    if a.projector is not None and b.projector is not None:
        checks += _lens_checks(name, "projector", a.projector.lens, b.projector.lens, tol)
        checks += _pose_checks(name, "projector", a.projector.rig_from_projector,
                               b.projector.rig_from_projector, tol)
    if a.light_planes is not None and b.light_planes is not None:
        checks += _plane_checks(name, a.light_planes, b.light_planes, tol)
    if a.raw_planes is not None or b.raw_planes is not None:
        checks.append(_count(name, "raw light planes", 0 if a.raw_planes is None else len(a.raw_planes),
                             0 if b.raw_planes is None else len(b.raw_planes), tol.count))
    ra, rb = _residual_numbers(a.residuals), _residual_numbers(b.residuals)
    checks += _metric_checks({f"{name}/residuals {k}": v for k, v in ra.items()},
                             {f"{name}/residuals {k}": v for k, v in rb.items()}, tol)
    return checks


def _board_text(board: dict | None) -> str:
    if board is None:
        return "unknown"
    return f"{board.get('kind')} {board.get('columns')}x{board.get('rows')}, {board.get('square')} mm"


MODEL = "model.ply"
MODEL_TEXTURE = "model_albedo.png"
MODEL_SEEN = "view_count.png"


def _store_model(run: Path, dest: Path) -> dict[str, Any]:
    from slscan.fsio import write_png

    model = read_textured_model(run)
    write_surface(dest / MODEL, model, texture_file=MODEL_TEXTURE)
    write_png(dest / MODEL_TEXTURE, model.texture)
    write_png(dest / MODEL_SEEN, model.seen.astype(np.uint8))
    return {}


def _compare_model(stage: Stage, old: Path, new: Path, tol: Tolerances, ref: dict) -> list[Check]:
    from slscan.fsio import read_png

    if not (new / "texture.json").is_file():
        return [_missing(stage.name, "texture.json")]
    a = replace(
        read_surface(old / MODEL),
        texture=read_png(old / MODEL_TEXTURE),
        seen=read_png(old / MODEL_SEEN) > 0,
    )
    b = read_textured_model(new)
    diff = texture_difference(a, b)
    return [
        *_distance_checks(
            stage.name, "model ", a, b, tol.simplified_mean_mm, tol.simplified_p95_mm
        ),
        _at_least(
            stage.name, "texture seen PSNR dB", diff.seen_psnr, tol.texture_psnr_db, MAX_PSNR
        ),
        _at_least(
            stage.name, "texture filled PSNR dB", diff.filled_psnr, tol.filled_psnr_db, MAX_PSNR
        ),
    ]


STORE: dict[str, Store] = {
    "session": _store_session,
    "lights": _store_json_files,
    "range_maps": _store_range_maps,
    "albedo": _store_albedo,
    "calibration": _store_calibration,
    "aligned": _store_registration,
    "mesh": _store_mesh,
    "model": _store_model,
}
"""What a baseline keeps of each kind of result (kinds not named: only their metrics)."""
COMPARE: dict[str, Compare] = {
    "range_maps": _compare_range_maps,
    "albedo": _compare_albedo,
    "calibration": _compare_calibration,
    "aligned": _compare_registration,
    "mesh": _compare_mesh,
    "model": _compare_model,
}


# --- the recording -----------------------------------------------------------------------------


def _run_recorded(recipe: Recipe, folder: Path, name: str, given: dict, reporter, executor) -> None:
    """Run ``recipe`` into ``folder`` on the recorded inputs ``given``, recording what it logs
    to ``folder/recording.rrd`` under the pipeline layout."""
    from slscan.viewer.layouts import pipeline_blueprint
    from slscan.viewer.recording import open_recording

    blueprint = pipeline_blueprint([s.name for s, _ in recipe.steps])
    with open_recording(save=folder / RECORDING, recording_name=name, blueprint=blueprint) as rec:
        run_recipe(recipe, folder, rec=rec, reporter=reporter, executor=executor, given=given)


def recording_rows(path: Path) -> dict[str, int]:
    """Rows per entity of a Rerun recording (recording properties left out)."""
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    try:
        chunks = RrdReader(path).stream().to_chunks()
    except Exception as exc:  # noqa: BLE001 - rerun raises its own error types for foreign or broken files
        raise SlscanError(
            f"{path}: not a recording this Rerun can read ({str(exc).splitlines()[0]})"
        ) from None
    for chunk in chunks:
        if chunk.entity_path.startswith("/__"):
            continue  # recording properties
        rows[chunk.entity_path] = rows.get(chunk.entity_path, 0) + chunk.num_rows
    return rows


def _recording_checks(old: dict[str, int], new: dict[str, int]) -> list[Check]:
    """One check per entity whose rows differ, then one for the whole recording."""
    differ = [e for e in sorted(set(old) | set(new)) if old.get(e, 0) != new.get(e, 0)]
    checks = [
        Check("recording", f"{e} rows", old.get(e, 0), new.get(e, 0), "equal", False)
        for e in differ
    ]
    same = len(set(old) | set(new)) - len(differ)
    return [
        *checks,
        Check("recording", "entities with equal rows", len(old), same, "all", not differ),
    ]


# --- baseline and regress -----------------------------------------------------------------------


def baseline_inputs(baseline: Path, recipe: Recipe) -> dict[str, Path]:
    """The recorded inputs a baseline hands to its re-run, by kind."""
    return {
        s.provides: Path(baseline) / s.name for s, _ in recipe.steps if s.provides in INPUT_KINDS
    }


def make_baseline(
    recipe: Recipe,
    out: str | os.PathLike,
    *,
    reporter: Reporter | None = None,
    overwrite: bool = False,
    executor=None,
    command: str | None = None,
    tolerances: Tolerances | None = None,
) -> Path:
    """Run ``recipe`` into a new baseline folder ``out``: its recorded inputs, the
    references of every later stage, and ``baseline.json``.

    The inputs' stages run first and their results are stored; the whole recipe then runs
    on the stored inputs, as :func:`regress` will, and what :func:`compare` needs of each
    stage is kept.

    overwrite : replace an existing non-empty ``out`` (only once the new baseline is complete)
    command : the command line that made it, recorded to regenerate it
    """

    out = Path(out)
    inputs = tuple((s, c) for s, c in recipe.steps if s.provides in INPUT_KINDS)
    if not any(s.provides == "session" for s, _ in inputs):
        raise SlscanError(f"recipe {recipe.name!r} records no capture session to re-run")
    scratch = Path(tempfile.mkdtemp(prefix="slscan-baseline-"))
    try:
        with atomic_output_dir(out, overwrite=overwrite) as tmp:
            run_recipe(
                replace(recipe, steps=inputs),
                scratch / "inputs",
                reporter=reporter,
                executor=executor,
            )
            for stage, _ in inputs:
                STORE[stage.provides](scratch / "inputs" / stage.name, tmp / stage.name)
            run = scratch / "run"
            run.mkdir()
            _run_recorded(recipe, run, f"baseline {recipe.name}", baseline_inputs(tmp, recipe),
                          reporter, executor)
            references = {}
            for stage, _ in recipe.steps:
                if stage.provides not in INPUT_KINDS and stage.provides in STORE:
                    references[stage.name] = STORE[stage.provides](
                        run / stage.name, tmp / stage.name
                    )
            shutil.copyfile(run / "recipe.resolved.toml", tmp / "recipe.resolved.toml")
            write_json(
                tmp / "baseline.json",
                {
                    "format": BASELINE_FORMAT,
                    "version": BASELINE_VERSION,
                    "slscan": __version__,
                    "recipe": recipe.name,
                    "command": command,
                    "inputs": [s.name for s, _ in inputs],
                    "tolerances": asdict(tolerances or Tolerances()),
                    "metrics": collect_metrics(run),
                    "references": {k: v for k, v in references.items() if v},
                    "recording": recording_rows(run / RECORDING),
                },
            )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return out


def baseline_command(meta: dict[str, Any], baseline: Path) -> str:
    """The command that regenerates a baseline (as recorded in it, else a template)."""
    return (
        meta.get("command")
        or f"slscan baseline RECIPE --out {shlex.quote(str(baseline))} --overwrite"
    )


def load_baseline(
    baseline: str | os.PathLike, *, overrides: list[str] = ()
) -> tuple[dict[str, Any], Recipe]:
    """``baseline.json`` and the baseline's recipe (with ``overrides`` applied), checked."""
    baseline = Path(baseline)
    if not baseline.is_dir():
        raise SlscanError(f"{baseline}: baseline folder not found")
    for name in ("baseline.json", "recipe.resolved.toml"):
        if not (baseline / name).is_file():
            raise SlscanError(f"{baseline}: the baseline lacks {name}")
    meta = read_json(baseline / "baseline.json", "baseline description")
    if meta.get("format") != BASELINE_FORMAT:
        raise SlscanError(f"{baseline / 'baseline.json'}: not an slscan baseline")
    if meta.get("version") != BASELINE_VERSION:
        raise SlscanError(
            f"{baseline / 'baseline.json'}: baseline version {meta.get('version')} is not supported "
            f"(this slscan reads version {BASELINE_VERSION}); regenerate it:  {baseline_command(meta, baseline)}"
        )
    try:
        recipe = load_recipe(baseline / "recipe.resolved.toml", overrides=list(overrides))
    except SlscanError as exc:
        raise SlscanError(
            f"{exc}\n(a baseline made by an older slscan? regenerate it:  "
            f"{baseline_command(meta, baseline)})"
        ) from None
    given = baseline_inputs(baseline, recipe)
    if "session" not in given or not (given["session"] / "session.json").is_file():
        raise SlscanError(
            f"{baseline}: the recorded capture session "
            f"({given['session'].name + '/' if 'session' in given else ''}session.json) is missing"
        )
    for folder in given.values():
        if not folder.is_dir():
            raise SlscanError(f"{baseline}: the recorded input {folder.name}/ is missing")
    return meta, recipe


def compare(
    baseline: str | os.PathLike, run: str | os.PathLike, *, stages: list[str] | None = None
) -> list[Check]:
    """Compare a re-run in folder ``run`` with ``baseline``, stage by stage, then the
    recording (when ``run`` has one).

    stages : compare only these stages (default: all)
    """
    baseline, run = Path(baseline), Path(run)
    meta, recipe = load_baseline(baseline)
    tol = Tolerances.from_json(meta.get("tolerances"), str(baseline / "baseline.json"))
    references = meta.get("references", {})
    checks: list[Check] = []
    metrics = _metric_checks(meta.get("metrics", {}), collect_metrics(run), tol)
    for stage, _ in recipe.steps:
        if stage.provides in INPUT_KINDS or (stages is not None and stage.name not in stages):
            continue
        if stage.provides in COMPARE:
            if not (run / stage.name).is_dir():
                checks.append(_missing(stage.name, f"{stage.name}/"))
            else:
                checks += COMPARE[stage.provides](
                    stage,
                    baseline / stage.name,
                    run / stage.name,
                    tol,
                    references.get(stage.name, {}),
                )
        checks += [c for c in metrics if c.stage == stage.name]
    if stages is None:
        named = {s.name for s, _ in recipe.steps}
        checks += [c for c in metrics if c.stage not in named]
        if (run / RECORDING).is_file():
            checks += _recording_checks(meta.get("recording", {}), recording_rows(run / RECORDING))
    return checks


def regress(
    baseline: str | os.PathLike,
    *,
    work: str | os.PathLike | None = None,
    overrides: list[str] = (),
    reporter: Reporter | None = None,
    executor=None,
) -> list[Check]:
    """Re-run ``baseline``'s recipe on its recorded inputs and :func:`compare`; never writes it.

    work : keep the re-run here (default: a temporary folder, removed afterwards)
    overrides : ``KEY=VALUE`` settings changed for the re-run (what would this change do?)
    executor : where per-view stages run (:class:`slscan.executor.Executor`)
    """

    baseline = Path(baseline)
    _, recipe = load_baseline(baseline, overrides=list(overrides))
    scratch = Path(work) if work else Path(tempfile.mkdtemp(prefix="slscan-regress-"))
    if scratch.resolve() == baseline.resolve():
        raise SlscanError("a regression run never writes into its baseline")
    if work and scratch.exists() and any(scratch.iterdir()):
        raise SlscanError(f"{scratch}: folder exists and is not empty")
    try:
        scratch.mkdir(parents=True, exist_ok=True)
        _run_recorded(recipe, scratch, f"regress {recipe.name}", baseline_inputs(baseline, recipe),
                      reporter, executor)
        return compare(baseline, scratch)
    finally:
        if not work:
            shutil.rmtree(scratch, ignore_errors=True)


def _fmt(v: float | str) -> str:
    return f"{v:.6g}" if isinstance(v, (int, float, np.floating, np.integer)) else str(v)


def format_table(checks: list[Check]) -> str:
    """The checks as a text table: stage, metric, baseline, now, tolerance, ok."""
    sw = max([len("stage"), *(len(c.stage) for c in checks)])
    mw = max([len("metric"), *(len(c.metric) for c in checks)])
    lines = [
        f"{'stage':<{sw}}  {'metric':<{mw}}  {'baseline':>12}  {'now':>12}  {'tolerance':>10}  ok"
    ]
    for c in checks:
        lines.append(
            f"{c.stage:<{sw}}  {c.metric:<{mw}}  {_fmt(c.baseline):>12}  {_fmt(c.current):>12}  "
            f"{c.tolerance:>10}  " + ("ok" if c.ok else "REGRESSION")
        )
    return "\n".join(lines)
