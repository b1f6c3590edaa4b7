"""The stages a recipe can name: each a config dataclass and a function writing one folder.

A stage **provides** one kind of result (a capture session, range maps, ...) and **needs**
results of earlier stages; the runner hands it the folders of the latest earlier stages
that provide what it needs. Each stage writes its whole output folder ``ctx.out``.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from slscan.errors import SlscanError

log = logging.getLogger(__name__)


@dataclass
class StageContext:
    """What a stage's ``run`` gets.

    out : the folder the stage must write (replacing what is there)
    inputs : result kind → folder of the stage that provided it
    rec : an ``rr.RecordingStream`` or None
    progress : called with a short label as work advances
    """

    out: Path
    inputs: dict[str, Path]
    rec: Any = None
    progress: Callable[[str], None] = lambda label: None
    executor: Any = None
    """Where per-view work runs (:class:`slscan.executor.Executor`); None: local processes."""


@dataclass(frozen=True)
class Stage:
    name: str
    config_type: type
    provides: str
    needs: tuple[str, ...]
    run: Callable[[StageContext, Any], dict[str, Any]]
    """Does the work; returns a small summary (counts, metrics) stored with the stage."""
    size: Callable[[Any], int] = lambda config: 1
    """Steps the progress bar should expect."""
    summary: str = ""
    optional: tuple[str, ...] = ()
    """Results used when an earlier stage provides them (e.g. a measured calibration)."""


@dataclass(frozen=True)
class ImportConfig:
    """Captures made by another tool, turned into a capture session."""

    source: str = ""
    """Folder of the other tool's captures; ``${SLSCAN_DATA}`` expands to the shared data."""
    format: str = "kamino410"
    """{"kamino410"}: procam-calibration's 42 Gray-code images per pose."""


def expand_path(text: str) -> Path:
    """Expand ``${SLSCAN_DATA}`` (the shared real-data folder) and ``~`` in a recipe path."""
    if "${SLSCAN_DATA}" in text:
        from slscan.data import ENV_VAR, shared_data_dir

        data = shared_data_dir()
        if data is None:
            raise SlscanError(f"{text}: the shared data folder is not there (set {ENV_VAR})")
        text = text.replace("${SLSCAN_DATA}", str(data))
    return Path(os.path.expanduser(text))


def _run_capture(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.virtual.device import capture_session

    session = capture_session(config, ctx.out, overwrite=True, rec=ctx.rec, progress=ctx.progress,
                              executor=ctx.executor)
    return {"views": len(session.views), "images": sum(len(v.images) for v in session.views)}


def _capture_size(config) -> int:
    from slscan.virtual.device import images_per_view

    return config.views * images_per_view(config)


def _run_import(ctx: StageContext, config: ImportConfig) -> dict[str, Any]:
    if config.format != "kamino410":
        raise SlscanError(f"import.format: unknown format {config.format!r} (known: kamino410)")
    if not config.source:
        raise SlscanError("import.source: the folder of captures to import is not set")
    from slscan.capture.kamino410 import import_kamino410

    session = import_kamino410(expand_path(config.source), ctx.out, overwrite=True,
                               progress=lambda done, total: ctx.progress(f"{done}/{total}"))
    return {"views": len(session.views), "images": sum(len(v.images) for v in session.views)}


def _run_decode(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.capture.session import load_session
    from slscan.decode.pipeline import decode_session

    session = load_session(ctx.inputs["session"])
    planes = None
    if "calibration" in ctx.inputs:
        from slscan.calibrate.io import apply_calibration, calibration_planes, load_calibration

        calibration = load_calibration(ctx.inputs["calibration"] / "calibration.json")
        session = apply_calibration(session, calibration)
        planes = calibration_planes(calibration)
    from slscan.executor import LOCAL

    results = decode_session(session, ctx.out, config, overwrite=True, rec=ctx.rec, progress=ctx.progress,
                             planes=planes, executor=ctx.executor or LOCAL)
    return {
        "range_maps": len(results),
        "vertices": sum(len(r.range_map.vertices) for r in results),
        "faces": sum(len(r.range_map.faces) for r in results),
    }


def _run_calibrate(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.calibrate.io import save_calibration
    from slscan.calibrate.pipeline import calibrate_session
    from slscan.fsio import atomic_output_dir

    run = calibrate_session(ctx.inputs["session"], config, rec=ctx.rec,
                            progress=lambda done, total, label: ctx.progress(label))
    with atomic_output_dir(ctx.out, overwrite=True) as tmp:
        save_calibration(run.calibration, tmp / "calibration.json")
    return {"views": len(run.camera.views), "camera_rms_px": round(float(run.camera.rms), 4)}


def _calibrate_size(config) -> int:
    return 2 * 5 + len(config.methods) + 1  # the progress bar's estimate for five board views


def _run_lights(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.viewer.paths import LIGHTS_PANEL
    from slscan.viewer.recording import session_stream
    from slscan.virtual.panels import calibrate_virtual_lights

    # the panel is a session of its own: its subtree (world/lights_panel/...), its timelines
    # and its camera's intrinsics, never the scanned object's
    with session_stream(ctx.rec, LIGHTS_PANEL) as rec:
        lights = calibrate_virtual_lights(config, ctx.out, overwrite=True, rec=rec, progress=ctx.progress)
    return {"lights": len(lights.lights), "rms": round(float(lights.fit["rms"]), 5)}


def _run_albedo(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.albedo.unshade import albedo_session
    from slscan.executor import LOCAL

    lights = ctx.inputs["lights"] / "lights.json" if "lights" in ctx.inputs else None
    results = albedo_session(ctx.inputs["session"], ctx.inputs["range_maps"], ctx.out, lights=lights,
                             config=config, overwrite=True, rec=ctx.rec, progress=ctx.progress,
                             executor=ctx.executor or LOCAL)
    return {"views": len(results), "valid_pixels": sum(r.valid_pixels for r in results)}


@dataclass(frozen=True)
class RegisterConfig:
    """Align range maps: the decoded ones, or those in ``source``."""

    source: str = ""
    """Range scans to align instead of an earlier decode stage's (a Stanford folder with a
    .conf, a folder of PLYs, a .mlp); ``${SLSCAN_DATA}`` expands to the shared data."""
    use_poses: bool = True
    """Start from the recorded poses (turntable, .conf); false: align from features."""
    reference: str = ""
    """Scan that keeps its pose (default: the first)."""
    pose_tolerance: float = 0.0
    """How far (mm) the recorded poses may be off; 0: from how well they already fit (5
    times their misfit, at least 4 sample spacings: exact turntable poses stay within
    that). Set it when the poses are known to be further off than their misfit shows."""
    poses: str = ""
    """Start from the poses in this file instead of the recorded ones: a Stanford .conf
    (metres), an slscan registration.json or a MeshLab .mlp (mm), one pose per scan by
    name; ``${SLSCAN_DATA}`` expands as in ``source``."""
    conf: str = ""
    """The .conf to read when ``source`` is a Stanford folder holding several (file name)."""
    allow_outside: bool = False
    """Let a ``source`` .mlp or .conf name scans outside its folder (as ``--allow-outside`` does);
    they are reported. False: such a project is refused."""
    max_neighbours: int = 8
    """With poses, align each scan with at most this many partners, its best candidates
    by estimated overlap (the graph kept connected); 0: every candidate pair (quadratic in
    the number of views). The default is ``MultiviewConfig.max_neighbours``."""
    into: str = ""
    """Grow this aligned set (a folder ``slscan register`` or a register stage wrote): its
    poses are held, the new scans found from features against it (their recorded poses
    unused); the stage writes the set with them. ``${SLSCAN_DATA}`` expands as in ``source``."""

    def __post_init__(self) -> None:  # "KEY: why": a recipe's error names [register].KEY
        if self.max_neighbours < 0:
            raise SlscanError(f"max_neighbours: expected >= 0 (0: every candidate pair), "
                              f"got {self.max_neighbours}")
        if self.pose_tolerance < 0:
            raise SlscanError(f"pose_tolerance: expected >= 0 mm (0: from the start poses' misfit), "
                              f"got {self.pose_tolerance}")


@dataclass(frozen=True)
class SimplifyConfig:
    """Simplify the fused mesh."""

    faces: int = 1_000_000
    """Target face count (the paper: about 1M)."""
    method: str = "fast"
    """{"fast", "quadric"}: fast-simplification, or pymeshlab's quadric edge collapse."""
    preserve_boundary: bool = True
    brick: float | None = None
    """Simplify out of core in bricks of this edge (mm), each a task on the run's executor
    (``--workers``, ``--scheduler``), as ``slscan simplify --brick``; needs method "fast" and
    preserve_boundary (the brick borders stay locked). Unset: see ``max_memory``."""
    bricks: int | None = None
    """Or in about this many bricks (``--bricks``)."""
    max_memory: str | float | None = None
    """Memory one task may use, e.g. "4GiB" (GiB, MiB: powers of 1024; GB, MB: of 1000; a bare
    number: GiB), as ``--max-memory``: without brick/bricks, in-core when the estimate fits,
    else in bricks; a brick over it is refused. Unset: in-core up to 10M faces, else bricks
    (with method "fast" and preserve_boundary; otherwise always in-core)."""

    def __post_init__(self) -> None:  # checked when the recipe is read, not after fusing
        if self.faces < 4:
            raise SlscanError(f"faces: expected at least 4, got {self.faces}")
        if self.method not in ("fast", "quadric"):  # slscan.simplify.METHODS, without importing open3d
            raise SlscanError(f"method: expected one of fast, quadric, got {self.method!r}")
        if self.brick is not None and not (math.isfinite(self.brick) and self.brick > 0):
            raise SlscanError(f"brick: expected a positive brick edge in mm, got {self.brick}")
        if self.bricks is not None and self.bricks < 1:
            raise SlscanError(f"bricks: expected at least 1, got {self.bricks}")
        if self.brick is not None and self.bricks is not None:
            raise SlscanError("brick: set brick (mm) or bricks (a count), not both")
        if self.max_memory is not None:
            from slscan.units import parse_memory

            try:
                parse_memory(self.max_memory, option="")
            except SlscanError as exc:
                raise SlscanError(f"max_memory: {exc}") from None
        if (self.brick is not None or self.bricks is not None) and (self.method != "fast"
                                                                     or not self.preserve_boundary):
            raise SlscanError(f"{'brick' if self.brick is not None else 'bricks'}: simplifying in bricks "
                              'needs method = "fast" and preserve_boundary = true (the borders stay locked)')

    def max_memory_bytes(self) -> int | None:
        """``max_memory`` in bytes (None: no cap)."""
        from slscan.units import parse_memory

        if self.max_memory is None:
            return None
        return parse_memory(self.max_memory, option="[simplify].max_memory")


def _run_register(ctx: StageContext, config: RegisterConfig) -> dict[str, Any]:
    from slscan.executor import LOCAL
    from slscan.register.command import check_joined, load_into, load_poses, load_scans, save_registration
    from slscan.register.multiview import median_pair_rmse, register_scans

    if config.poses and not config.use_poses:
        raise SlscanError("register: register.poses is set but register.use_poses is false")
    if config.source:
        scans, poses = load_scans(expand_path(config.source), conf=config.conf or None,
                                  allow_outside=config.allow_outside)
    elif "range_maps" in ctx.inputs:
        scans, poses = load_scans(ctx.inputs["range_maps"])
    else:
        raise SlscanError("register: set register.source, or decode range maps in an earlier stage")
    if config.poses:
        poses = load_poses(expand_path(config.poses), [s.name for s in scans])
    from slscan.register.frame import preview_frame, to_object_frame
    from slscan.register.multiview import MultiviewConfig
    from slscan.viewer import log_register as rlog

    poses = poses if config.use_poses else None
    held: list[str] = []
    reference = config.reference or None
    if config.into:
        scans, poses, held, frame, old_reference = load_into(expand_path(config.into), scans,
                                                             allow_outside=config.allow_outside)
        reference = reference or old_reference
    start = preview_frame(scans, poses)
    rlog.log_registration_start(ctx.rec, scans, start.apply(poses) if start else poses)
    result = register_scans(scans, initial_poses=poses, reference=reference, progress=ctx.progress,
                            config=MultiviewConfig(pose_tolerance=config.pose_tolerance or None,
                                                   max_neighbours=config.max_neighbours), fixed=held,
                            executor=ctx.executor or LOCAL)
    check_joined(result, scans, Path(config.into or config.source or ctx.inputs.get("range_maps", "")))
    if not held:
        result, frame = to_object_frame(scans, result)
    rlog.log_registration_result(ctx.rec, result)
    save_registration(ctx.out, scans, result, overwrite=True, frame=frame)
    median = median_pair_rmse(result.pairs)
    return {"aligned": len(result.poses), "left_out": len(result.left_out),
            **({"left_out_scans": ", ".join(sorted(result.left_out))} if result.left_out else {}),
            **({"added": len(result.poses) - len(held)} if held else {}),
            "up_from": frame.up_from if frame is not None else None,
            "median_pair_rmse_mm": None if median is None else round(median, 4)}


def _run_fuse(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.fsio import atomic_output_dir
    from slscan.fuse import fuse_scans, write_mesh
    from slscan.register.meshlab import load_scan_project, write_mesh_project

    if config.brick_size is not None:  # in bricks: the scans are read one at a time
        from slscan.register.command import iter_scans

        _, scans, poses = iter_scans(ctx.inputs["aligned"] / "aligned.mlp")
    else:
        scans, poses = load_scan_project(ctx.inputs["aligned"] / "aligned.mlp")
    from slscan.viewer.log_register import log_fused_mesh

    from slscan.executor import LOCAL

    # with fuse.brick_size the bricks run on the run's executor (--workers, --scheduler), their
    # pieces and meshes in a scratch folder inside the stage's (Dask workers must see the run's folder)
    if config.brick_size is not None:
        return _run_fuse_streamed(ctx, config, scans, poses)
    result = fuse_scans(scans, poses, config=config, progress=ctx.progress, executor=ctx.executor or LOCAL)
    with atomic_output_dir(ctx.out, overwrite=True) as tmp:
        write_mesh(result.mesh, tmp / "mesh.ply")
        write_mesh_project(tmp / "mesh.ply")  # mesh.mlp: MeshLab opens the model upright
    log_fused_mesh(ctx.rec, result.mesh)
    return {"faces": len(result.mesh.faces), "vertices": len(result.mesh.vertices)}


def _run_fuse_streamed(ctx: StageContext, config, scans, poses) -> dict[str, Any]:
    """The fuse stage in bricks: the mesh streams to ``mesh.ply`` in the stage's temporary folder
    (the caller never holds it whole); logged when small enough to read back."""
    from slscan.executor import LOCAL
    from slscan.fsio import atomic_output_dir
    from slscan.fuse import fuse_bricks
    from slscan import fuse_stream
    from slscan.register.meshlab import write_mesh_project
    from slscan.viewer.log_register import log_fused_mesh

    with atomic_output_dir(ctx.out, overwrite=True) as tmp:
        written = fuse_bricks(scans, poses, config=config, progress=ctx.progress, executor=ctx.executor or LOCAL,
                              out=tmp / "mesh.ply").written
        write_mesh_project(tmp / "mesh.ply")  # mesh.mlp: MeshLab opens the model upright
    if ctx.rec is not None:
        mesh = fuse_stream.mesh_to_log(replace(written, path=ctx.out / "mesh.ply"))
        if mesh is not None:
            log_fused_mesh(ctx.rec, mesh)
        else:
            log.warning("fuse: the fused mesh (%d faces) is too large to log to Rerun (more than %d); the "
                        "simplified model is logged", written.n_faces, fuse_stream.LOG_MAX_FACES)
    return {"faces": written.n_faces, "vertices": written.n_vertices}


def _run_simplify(ctx: StageContext, config: SimplifyConfig) -> dict[str, Any]:
    from slscan.fsio import atomic_output_dir
    from slscan.register.meshlab import write_mesh_project
    from slscan.simplify import simplify_file
    from slscan.simplify_bricks import choose_path

    source = ctx.inputs["mesh"] / "mesh.ply"
    cap = config.max_memory_bytes()
    in_bricks = config.method == "fast" and config.preserve_boundary
    if in_bricks:  # as `slscan simplify` chooses; a quadric or free-boundary recipe stays in-core
        in_bricks, _ = choose_path(source, brick_mm=config.brick, bricks=config.bricks, max_memory=cap)
    summary: dict[str, Any] = {}
    with atomic_output_dir(ctx.out, overwrite=True) as tmp:
        if in_bricks:
            from slscan.executor import LOCAL
            from slscan.fuse import read_mesh
            from slscan.simplify_bricks import simplify_bricks

            # each brick is a task on the run's executor (--workers, --scheduler)
            report = simplify_bricks(source, tmp / "mesh.ply", config.faces, brick_mm=config.brick,
                                     bricks=config.bricks, executor=ctx.executor or LOCAL, max_memory=cap)
            mesh = read_mesh(tmp / "mesh.ply")
            summary = {"bricks": len(report.bricks), "task_peak_mib": round(max(
                (b.peak_rss for b in report.bricks), default=0) / 2**20, 1)}
        else:
            mesh = simplify_file(source, tmp / "mesh.ply", config.faces, method=config.method,
                                 preserve_boundary=config.preserve_boundary, option="[simplify] faces")
        write_mesh_project(tmp / "mesh.ply")  # mesh.mlp: MeshLab opens the model upright
    from slscan.viewer.log_register import log_simplified_mesh

    log_simplified_mesh(ctx.rec, mesh)
    return {"faces": len(mesh.faces), **summary}


def _run_texture(ctx: StageContext, config) -> dict[str, Any]:
    from slscan.executor import LOCAL
    from slscan.texture.pipeline import texture_model

    poses = ctx.inputs.get("aligned")
    result = texture_model(ctx.inputs["mesh"] / "mesh.ply", ctx.inputs["albedo"], ctx.out, poses=poses,
                           session=ctx.inputs.get("session"), config=config, overwrite=True, rec=ctx.rec,
                           progress=ctx.progress, executor=ctx.executor or LOCAL)
    return {"faces": result.faces, "charts": result.charts, "size": result.size,
            "observed_share": result.metrics["observed_share"],
            "seam_error_mean": result.metrics["seam_error_mean"]}


SUMMARIES: dict[str, str] = {
    "capture": "render a capture session on the virtual rig",
    "import": "import another tool's captures",
    "calibrate": "calibrate camera and projector from views of a printed board",
    "decode": "decode patterns into range maps (with a measured calibration when one was made)",
    "lights": "calibrate the ring lights on a matte panel (virtual rig)",
    "albedo": "un-shade the ring-light images into albedo",
    "register": "align range maps (ICP + pose graph) into a MeshLab project",
    "fuse": "fuse the aligned range maps (weighted TSDF)",
    "simplify": "simplify the mesh to a face count",
    "texture": "bake the views' un-shaded colour into a texture atlas; glb, OBJ, PLY, .mlp",
}
"""Every stage's name and one-line summary, in pipeline order: what ``slscan run --help``
lists without importing the stages' modules (:func:`stages` loads them)."""


def _registry() -> dict[str, Stage]:
    from slscan.albedo.photometric import AlbedoConfig
    from slscan.calibrate.pipeline import CalibrationConfig
    from slscan.decode.pipeline import DecodeConfig
    from slscan.fuse import FuseConfig
    from slscan.texture.pipeline import TextureConfig
    from slscan.virtual.device import VirtualCaptureConfig
    from slscan.virtual.panels import LightPanelConfig

    stages = [
        Stage("capture", VirtualCaptureConfig, "session", (), _run_capture, _capture_size,
              SUMMARIES["capture"]),
        Stage("import", ImportConfig, "session", (), _run_import, summary=SUMMARIES["import"]),
        Stage("calibrate", CalibrationConfig, "calibration", ("session",), _run_calibrate, _calibrate_size,
              SUMMARIES["calibrate"]),
        Stage("decode", DecodeConfig, "range_maps", ("session",), _run_decode, lambda config: 1,
              SUMMARIES["decode"], optional=("calibration",)),
        Stage("lights", LightPanelConfig, "lights", (), _run_lights, lambda c: c.poses * 13,
              SUMMARIES["lights"]),
        Stage("albedo", AlbedoConfig, "albedo", ("session", "range_maps"), _run_albedo, lambda c: 1,
              SUMMARIES["albedo"], optional=("lights",)),
        Stage("register", RegisterConfig, "aligned", (), _run_register, lambda c: 1,
              SUMMARIES["register"], optional=("range_maps",)),
        Stage("fuse", FuseConfig, "mesh", ("aligned",), _run_fuse, lambda c: 1,
              SUMMARIES["fuse"]),
        Stage("simplify", SimplifyConfig, "mesh", ("mesh",), _run_simplify, lambda c: 1,
              SUMMARIES["simplify"]),
        Stage("texture", TextureConfig, "model", ("mesh", "albedo"), _run_texture, lambda c: 12,
              SUMMARIES["texture"], optional=("aligned", "session")),
    ]
    return {s.name: s for s in stages}


STAGES: dict[str, Stage] = {}


def stages() -> dict[str, Stage]:
    """All stages by name, in pipeline order."""
    if not STAGES:
        STAGES.update(_registry())
    return STAGES

