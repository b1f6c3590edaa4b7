"""Loggers for registration, fusion, simplification: scans at their poses, pair residuals, models.

One ``log_*`` function per thing logged; each takes the recording stream first and
returns at once when it is ``None``.

Entity tree (the upright object frame of the aligned set, mm, y up; see
:mod:`slscan.register.frame`; ``world/`` keeps the rig frame of capture and decode)::

    object                          ViewCoordinates RUF, y up (static)
    object/scans/<name>             Transform3D object_from_scan     [stage]
    object/scans/<name>/mesh        Mesh3D of the scan, scan frame, one colour per scan (static)
    object/model/fused              Mesh3D of the fused model        [stage = fused]
    object/model/simplified         Mesh3D of the simplified model   [stage = simplified]
    plot/register/rmse/<a>-<b>     point-to-plane RMS of a pair (mm)   [stage]
    plot/register/overlap/<a>-<b>  fraction of a's samples on b         [stage]
    plot/register/rejected          number of candidate pairs rejected   [stage]
    log/register                    TextLog: each rejected pair and why  [stage]

The ``stage`` timeline counts :data:`STAGES`: scrub it to see the scans jump from their
initial to their registered poses. These whole-object results are also logged at
``view = 0`` and ``frame = 0``, so that on the per-view timelines every view shows the
registered scans and the models (the later-logged registered pose wins at equal time).
"""

from __future__ import annotations

import colorsys
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr

from slscan.viewer.paths import MODEL_PATH, OBJECT_PATH, REGISTER_LOG_PATH, REGISTER_PLOT_PATH, SCANS_PATH
from slscan.viewer.recording import FRAME_TIMELINE, STAGE_TIMELINE, VIEW_TIMELINE, first_static

if TYPE_CHECKING:
    from slscan.fuse import Mesh
    from slscan.register.multiview import PairResidual, RejectedPair
    from slscan.register.rangescan import RangeScan

STAGES = {"initial": 0, "registered": 1, "fused": 2, "simplified": 3}
"""Sequence numbers of the pipeline steps on the ``stage`` timeline."""
MAX_LOGGED_FACES = 2_000_000
"""Meshes with more faces are logged as a uniform subset of their faces (display only)."""
MODEL_COLOR = (200, 200, 190)
PLOT_PATH = REGISTER_PLOT_PATH
LOG_PATH = REGISTER_LOG_PATH


def scan_color(index: int) -> tuple[int, int, int]:
    """A distinct display colour for the ``index``-th scan (golden-ratio hues)."""
    h = (index * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.55, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def log_object_frame(rec: rr.RecordingStream | None) -> None:
    """The object frame's axes at ``object`` (static): right-handed, y up, as the archive's
    files (PLY, OBJ, .mlp, glTF) have them, so Rerun shows the model upright."""
    if rec is None:
        return
    if first_static(rec, OBJECT_PATH):
        rec.log(OBJECT_PATH, rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)


def _set_stage(rec: rr.RecordingStream, stage: str) -> None:
    """``stage`` on the stage timeline, and the first view and frame: a whole-object result
    holds for every view, so it shows whichever timeline the viewer is on."""
    rec.set_time(STAGE_TIMELINE, sequence=STAGES.get(stage, len(STAGES)))
    rec.set_time(VIEW_TIMELINE, sequence=0)
    rec.set_time(FRAME_TIMELINE, sequence=0)


def _mesh3d(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None, color
) -> rr.Mesh3D:
    faces = np.asarray(faces)
    if len(faces) > MAX_LOGGED_FACES:
        faces = faces[:: int(np.ceil(len(faces) / MAX_LOGGED_FACES))]
    return rr.Mesh3D(
        vertex_positions=np.asarray(vertices, np.float32),
        triangle_indices=faces.astype(np.uint32),
        vertex_normals=None if normals is None else np.asarray(normals, np.float32),
        albedo_factor=color,
    )


def log_scan_meshes(rec: rr.RecordingStream | None, scans: Sequence[RangeScan]) -> None:
    """Each scan's mesh, own frame, at ``object/scans/<name>/mesh`` (static), one colour each."""
    if rec is None:
        return
    log_object_frame(rec)
    for k, scan in enumerate(scans):
        rec.log(
            f"{SCANS_PATH}/{scan.name}/mesh",
            _mesh3d(scan.vertices, scan.faces, scan.normals, scan_color(k)),
            static=True,
        )


def log_scan_poses(
    rec: rr.RecordingStream | None, poses: Mapping[str, np.ndarray], *, stage: str
) -> None:
    """object_from_scan of each scan as a Transform3D at ``object/scans/<name>``, at ``stage``.

    poses : {name: (4, 4) object_from_scan, mm}
    stage : a key of :data:`STAGES` ("initial", "registered")
    """
    if rec is None:
        return
    _set_stage(rec, stage)
    for name, pose in poses.items():
        pose = np.asarray(pose, np.float64)
        rec.log(
            f"{SCANS_PATH}/{name}", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3])
        )


def log_scans_left_out(
    rec: rr.RecordingStream | None, names: Iterable[str], *, stage: str = "registered"
) -> None:
    """Hide the scans registration left out (clear their transform and mesh) from ``stage`` on."""
    if rec is None:
        return
    _set_stage(rec, stage)
    for name in names:
        rec.log(f"{SCANS_PATH}/{name}", rr.Clear(recursive=False))


def log_pair_residuals(
    rec: rr.RecordingStream | None, pairs: Sequence[PairResidual], *, stage: str = "registered"
) -> None:
    """Point-to-plane RMS (mm) and overlap of each registered pair, as scalars."""
    if rec is None:
        return
    _set_stage(rec, stage)
    for pair in pairs:
        key = f"{pair.source}-{pair.target}"
        if np.isfinite(pair.rmse):
            rec.log(f"plot/register/rmse/{key}", rr.Scalars(float(pair.rmse)))
        rec.log(f"plot/register/overlap/{key}", rr.Scalars(float(pair.fitness)))


def log_rejected_pairs(
    rec: rr.RecordingStream | None, rejected: Sequence[RejectedPair], *, stage: str = "registered"
) -> None:
    """How many candidate pairs were rejected (a scalar at ``plot/register/rejected``) and a
    WARN line at ``log/register`` for each, with its reason."""
    if rec is None:
        return
    _set_stage(rec, stage)
    rec.log(f"{PLOT_PATH}/rejected", rr.Scalars(float(len(rejected))))
    for r in rejected:
        numbers = (f" (fitness {r.fitness:.3f}, RMSE {r.rmse:.3g} mm)"
                   if np.isfinite(r.fitness) and np.isfinite(r.rmse) else "")
        rec.log(LOG_PATH, rr.TextLog(f"pair {r.source}-{r.target} rejected: {r.reason}{numbers}",
                                     level="WARN"))


def log_registration_start(
    rec: rr.RecordingStream | None, scans: Sequence[RangeScan], poses: Mapping[str, np.ndarray] | None
) -> None:
    """Before registering: every scan's mesh, and its recorded pose when there is one."""
    log_scan_meshes(rec, scans)
    if poses:
        log_scan_poses(rec, poses, stage="initial")


def log_registration_result(rec: rr.RecordingStream | None, result) -> None:
    """After registering (a :class:`~slscan.register.multiview.MultiviewResult`): the poses,
    the pair residuals, the rejected pairs, and the scans left out hidden."""
    log_scan_poses(rec, result.poses, stage="registered")
    log_pair_residuals(rec, result.pairs)
    if rec is not None:  # one summary line, so the log says what happened even when all went well
        _set_stage(rec, "registered")
        left = f", left out {', '.join(result.left_out)}" if result.left_out else ""
        rec.log(LOG_PATH, rr.TextLog(
            f"registered {len(result.poses)} scans (reference {result.reference}): "
            f"{len(result.pairs)} pairs kept, {len(result.rejected)} rejected{left}", level="INFO"))
    log_rejected_pairs(rec, result.rejected)
    log_scans_left_out(rec, result.left_out)


def log_fused_mesh(rec: rr.RecordingStream | None, mesh: Mesh) -> None:
    """The fused model at ``object/model/fused`` (stage "fused")."""
    if rec is None:
        return
    log_object_frame(rec)
    _set_stage(rec, "fused")
    rec.log(f"{MODEL_PATH}/fused", _mesh3d(mesh.vertices, mesh.faces, mesh.normals, MODEL_COLOR))


def log_simplified_mesh(rec: rr.RecordingStream | None, mesh: Mesh) -> None:
    """The simplified model at ``object/model/simplified`` (stage "simplified")."""
    if rec is None:
        return
    log_object_frame(rec)
    _set_stage(rec, "simplified")
    rec.log(
        f"{MODEL_PATH}/simplified", _mesh3d(mesh.vertices, mesh.faces, mesh.normals, MODEL_COLOR)
    )
