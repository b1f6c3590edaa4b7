"""The virtual rig as a capture device: renders a scene and writes a capture session.

It writes exactly what a real rig would (PNG captures and ``session.json``), plus
per-view ground truth, so the rest of the pipeline never knows the difference.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slscan.capture.driver import (
    FrameCaptured,
    ScanDevices,
    ScanPlan,
    capture_records,
    scan,
    view_exposure,
)
from slscan.capture.session import (
    LIT,
    SHADOW,
    GroundTruth,
    ImageRecord,
    Session,
    ViewRecord,
    read_capture,
    write_capture,
)
from slscan.errors import SlscanError
from slscan.meshes import MESH_SUFFIXES
from slscan.patterns import PatternImage, render, standard_set
from slscan.rig import Rig, default_rig, transform_points
from slscan.virtual.devices import VirtualRig, check_view_geometry, exposure_record, turntable_pose
from slscan.virtual.effects import apply_effects, parse_effects
from slscan.virtual.placement import check_pose_text, parse_pose, parse_units, placement_record
from slscan.virtual.render import (
    Optics,
    ViewGeometry,
    needs_trace,
    shade_light,
    shade_pattern,
    trace_view,
)
from slscan.virtual.rigs import RigParams, load_rig_file
from slscan.virtual.scenes import BUILTIN_SCENES, Scene, scene_by_name
from slscan.virtual.sensor import Sensor, jpeg_round_trip

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


@dataclass(frozen=True)
class VirtualCaptureConfig:
    """What the virtual rig captures and how.

    scene : "object" (the built-in figurine), "tile", "concave", "marble", "bronze" (the
        light-transport scenes, :mod:`slscan.virtual.scenes`), or a mesh file (PLY/OBJ/glTF)
    views : turntable positions, evenly spread over 360° about the object's vertical axis
    patterns : which coded patterns follow white and black: a set name of
        :func:`slscan.patterns.set_names` ("hybrid", "gray", "xor": Gupta's XOR-04 Gray
        codes, "phase", "both": hybrid and Gray code) or several joined by "+"
    levels : hybrid subdivision levels (9 at 1024 px gives 511 lines)
    pattern_options : further options of the families' ``generate`` (phase shifting's
        ``periods``, ``steps``, ``unwrap``, ...; :func:`slscan.patterns.standard_set`)
    gray_rows : also code the projector rows (Gray code, phase shifting)
    lit_images : capture one image per ring light (for albedo)
    camera_scale, projector_scale : sensor size relative to the paper's 1440×960 and
        1024×768 (same field of view); below 1 for quick runs
    lit_exposure : exposure of the ring-light images relative to the pattern images
    seed : noise seed; the same seed gives the same images
    scene_units : a mesh file's units: {"auto", "mm", "cm", "m", "in"} or mm per unit;
        None: auto (mm, or metres when under 10 units across)
    scene_pose : where the scene stands on the turntable (``turntable_from_object``, see
        :mod:`slscan.virtual.placement`): "rx,ry,rz,tx,ty,tz" (degrees, mm), a 4x4 matrix
        file (.json, .txt) or "default"; None: the default placement
    rig_params : the rig's geometry (:class:`slscan.virtual.rigs.RigParams`); None: the paper's
    rig_file : a rig as ``Rig.to_dict`` writes it (or a session.json), instead of ``rig_params``
    effects : light-transport effects switched on by name (:mod:`slscan.virtual.effects`):
        they set ``optics`` and ``sensor`` fields, which then hold what was rendered
    """

    scene: str = "object"
    views: int = 1
    patterns: str = "hybrid"
    levels: int = 9
    pattern_options: dict = field(default_factory=dict)
    gray_rows: bool = False
    lit_images: bool = True
    camera_scale: float = 1.0
    projector_scale: float = 1.0
    sensor: Sensor = field(default_factory=Sensor)
    optics: Optics = field(default_factory=Optics)
    lit_exposure: float = 1.0
    seed: int = 0
    scene_units: str | float | None = None
    scene_pose: str | None = None
    rig_params: RigParams | None = None
    rig_file: str | None = None
    effects: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if isinstance(self.views, int) and self.views < 1:
            raise SlscanError(f"views: expected at least 1 view, got {self.views}")
        for key in ("camera_scale", "projector_scale"):
            if not getattr(self, key) > 0:
                raise SlscanError(f"{key}: expected a positive number, got {getattr(self, key)}")
        if isinstance(self.levels, int) and self.levels < 1:
            raise SlscanError(f"levels: expected at least 1, got {self.levels}")
        if (isinstance(self.scene, str) and self.scene not in BUILTIN_SCENES
                and Path(self.scene).suffix.lower() not in MESH_SUFFIXES):
            suffix = Path(self.scene).suffix
            raise SlscanError(
                f"scene: expected one of {', '.join(BUILTIN_SCENES)} or a mesh file "
                f"({', '.join(MESH_SUFFIXES)}), got {self.scene!r}"
                + (f" (unknown mesh format {suffix!r})" if suffix else "")
            )
        check_placement_settings(self)
        names = parse_effects(self.effects, "effects")
        object.__setattr__(self, "effects", names)
        if names:
            optics, sensor = apply_effects(names, self.optics, self.sensor, self.rig().working_distance)
            object.__setattr__(self, "optics", optics)
            object.__setattr__(self, "sensor", sensor)

    def rig(self) -> Rig:
        if self.rig_file:
            return load_rig_file(self.rig_file, scale=self.camera_scale, projector_scale=self.projector_scale)
        if self.rig_params is not None:
            rig = self.rig_params.rig(scale=self.camera_scale, projector_scale=self.projector_scale)
        else:
            rig = default_rig(scale=self.camera_scale, projector_scale=self.projector_scale)
        rig.validate()
        return rig

    def build_scene(self) -> Scene:
        """The scene of ``scene``, in its units, placed at ``scene_pose``."""
        return scene_by_name(self.scene, units=self.scene_units, pose=parse_pose(self.scene_pose))

    def pattern_set(self, rig: Rig) -> list[PatternImage]:
        lens = rig.projector.lens
        return standard_set(self.patterns, width=lens.width, height=lens.height, levels=self.levels,
                            rows=self.gray_rows, **self.pattern_options)

    def to_dict(self) -> dict:
        return {
            "scene": self.scene, "views": self.views, "patterns": self.patterns, "levels": self.levels,
            "pattern_options": dict(self.pattern_options), "gray_rows": self.gray_rows, "lit_images": self.lit_images, "camera_scale": self.camera_scale,
            "projector_scale": self.projector_scale, "sensor": self.sensor.to_dict(),
            "optics": self.optics.to_dict(), "lit_exposure": self.lit_exposure, "seed": self.seed,
            "scene_units": self.scene_units, "scene_pose": self.scene_pose,
            "rig_params": None if self.rig_params is None else dataclasses.asdict(self.rig_params),
            "rig_file": self.rig_file, "effects": list(self.effects),
        }


def check_placement_settings(config: VirtualCaptureConfig) -> None:
    """Refuse malformed scene units, pose text and rig settings, naming the setting."""
    parse_units(config.scene_units, "scene_units")
    check_pose_text(config.scene_pose, "scene_pose")
    if config.rig_file is not None and config.rig_params is not None:
        raise SlscanError("rig_file and rig_params: give one (a rig file, or the parameters of the default rig)")


def check_visible(scene: Scene, rig: Rig, rig_from_object: np.ndarray) -> None:
    """Raise when the object lies outside the camera's or the projector's field."""
    pts = transform_points(rig_from_object, scene.vertices[:: max(1, len(scene.vertices) // 5000)])
    if np.all(pts[:, 2] <= 0):
        raise SlscanError(f"scene {scene.name!r} is behind the camera")
    cam = rig.camera
    uv = cam.project_local(pts[pts[:, 2] > 0])
    in_cam = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    if not in_cam.any():
        raise SlscanError(f"scene {scene.name!r} lies outside the camera's field of view")
    local_z = transform_points(np.linalg.inv(rig.projector.rig_from_projector), pts)[:, 2]
    puv = rig.projector.project(pts[local_z > 0])
    lens = rig.projector.lens
    in_proj = (puv[:, 0] >= 0) & (puv[:, 0] < lens.width) & (puv[:, 1] >= 0) & (puv[:, 1] < lens.height)
    if not in_proj.any():
        raise SlscanError(f"scene {scene.name!r} lies outside the projector's frustum")


def ground_truth(geom: ViewGeometry) -> GroundTruth:
    """Per-pixel truth of a traced view."""
    visibility = np.where(geom.proj_lit, LIT, np.where(geom.hit, SHADOW, 0)).astype(np.uint8)
    return GroundTruth(
        point=geom.point.astype(np.float32), normal=geom.normal, albedo=geom.albedo,
        projector_uv=geom.proj_uv.astype(np.float32), visibility=visibility,
    )


def capture_view(
    scene: Scene,
    rig: Rig,
    rig_from_object: np.ndarray,
    patterns: list[PatternImage],
    config: VirtualCaptureConfig,
    *,
    view_index: int = 0,
    geometry: ViewGeometry | None = None,
) -> tuple[list[tuple[ImageRecord, np.ndarray]], ViewGeometry]:
    """Render every image of one view: the patterns in order, then one per ring light.

    Returns ``[(record, image), ...]`` and the traced geometry (reuse it for ground truth).
    """
    sensor = config.sensor
    if geometry is not None and not needs_trace(geometry, config.optics):
        geom = geometry
    else:  # traced here, or again when the given geometry lacks the transport the optics need
        geom = trace_view(scene, rig, rig_from_object, config.optics)
    out = []
    for rec, image in _exposed_images(geom, rig, patterns, config, view_index):
        if sensor.jpeg_quality:  # what reading the session's .jpg gives back
            image = jpeg_round_trip(image, sensor.jpeg_quality)
        out.append((rec, image))
    return out, geom


def _exposed_images(geom: ViewGeometry, rig: Rig, patterns: list[PatternImage], config: VirtualCaptureConfig,
                    view_index: int):
    """``(record, image)`` of every image of a traced view, as the sensor exposes it (before
    any JPEG encoding); image ``i`` of view ``v`` draws its noise from ``[seed, v, i]``,
    as the driver's camera does."""
    sensor, optics = config.sensor, config.optics
    records = capture_records(patterns, len(rig.lights) if config.lit_images else 0, jpeg=bool(sensor.jpeg_quality))
    for i, rec in enumerate(records):
        rng = np.random.default_rng([config.seed, view_index, i])
        if rec.kind == "pattern":
            image = sensor.expose(shade_pattern(geom, patterns[i], optics), rng, camera=rig.camera)
        else:
            image = sensor.expose(shade_light(geom, rec.light, rig, optics), rng,
                                  exposure_scale=config.lit_exposure, camera=rig.camera)
        yield rec, image


def virtual_devices(
    config: VirtualCaptureConfig,
    *,
    scene: Scene | None = None,
    poses: list[np.ndarray] | None = None,
    rig: Rig | None = None,
    latency_s: float = 0.0,
    noise_stream: tuple[int, ...] = (),
) -> VirtualRig:
    """The virtual rig of ``config`` as devices (see :mod:`slscan.virtual.devices`)."""
    rig = rig or config.rig()
    rig.validate()
    scene = scene or config.build_scene()
    return VirtualRig(scene, rig, config.sensor, config.optics, poses=poses, seed=config.seed,
                      latency_s=latency_s, noise_stream=noise_stream)


def scan_devices(world: VirtualRig, camera=None) -> ScanDevices:
    """The four devices of the virtual rig (``camera`` replaces its camera, e.g. a
    :class:`slscan.virtual.devices.ScreenLoopCamera`)."""
    return ScanDevices(world.projector, camera or world.camera, world.lights, world.stage)


def scan_plan(config: VirtualCaptureConfig, rig: Rig, *, settle_s: float = 0.0,
              reference_frame: bool = True) -> ScanPlan:
    """What the driver captures per view for ``config``."""
    return ScanPlan(tuple(config.pattern_set(rig)), lit_images=config.lit_images,
                    lit_exposure=config.lit_exposure, settle_s=settle_s, reference_frame=reference_frame)


def log_virtual_view(rec, world: VirtualRig, view_index: int) -> None:
    """Log what only the virtual rig knows about the view just captured: the scene mesh
    where it stands and the per-pixel truth."""
    if rec is None or world.geometry is None:
        return
    _log_view_truth(rec, world.scene, world.rig, world.pose, ground_truth(world.geometry), view_index)


def _log_view_truth(rec, scene: Scene, rig: Rig, pose: np.ndarray, truth: GroundTruth, view_index: int) -> None:
    from slscan.viewer import log as rlog

    verts = transform_points(pose, scene.vertices)
    rlog.log_scene_mesh(rec, verts, scene.triangles, scene.albedo.vertex_colors(scene.vertices), view_index=view_index)
    rlog.log_ground_truth(rec, truth, view_index=view_index, projector_width=rig.projector.lens.width)


def capture_session(
    config: VirtualCaptureConfig,
    out: str | os.PathLike,
    *,
    overwrite: bool = False,
    rec=None,
    progress: Progress | None = None,
    scene: Scene | None = None,
    poses: list[np.ndarray] | None = None,
    rig: Rig | None = None,
    noise_stream: tuple[int, ...] = (),
    executor=None,
) -> Session:
    """Capture ``config.views`` views of ``config.scene`` on the virtual rig into folder ``out``,
    through the acquisition driver (:func:`slscan.capture.driver.scan`), written at once
    when complete.

    With an ``executor`` (:class:`slscan.executor.Executor`) of more than one worker, the
    views are rendered (traced, shaded, exposed, PNG-encoded) in its processes instead,
    each writing its own view's images; the session is the same image for image, and
    Rerun gets each view's frames when the view is done. Only for ``config``'s own scene
    and the single-camera noise stream (``scene`` and ``noise_stream`` left out).

    rec : an ``rr.RecordingStream`` to stream images, truth and rig to, or None
    progress : called with a short label after each image is written
    scene : capture this scene instead of ``config.scene`` (e.g. a calibration board)
    poses : ``rig_from_object`` (4, 4) of each view instead of ``config.views`` turntable steps
    rig : use this rig instead of ``config.rig()`` (same sensor sizes as the config's)
    noise_stream : a separate noise stream (e.g. ``(k,)`` for camera ``k`` of a multi-camera
        rig, :mod:`slscan.virtual.multicam`); ``()`` gives the single-camera images
    """
    from slscan.viewer import log as rlog
    from slscan.viewer import log_scan

    if config.views < 1:
        raise SlscanError(f"views must be at least 1, got {config.views}")
    if poses is not None and len(poses) == 0:
        raise SlscanError("no poses to capture")
    world = virtual_devices(config, scene=scene, poses=poses, rig=rig, noise_stream=noise_stream)
    views = len(poses) if poses is not None else config.views
    view_poses = []
    for v in range(views):
        pose = poses[v] if poses is not None else turntable_pose(world.rig, 360.0 * v / views, world.scene.placement)
        check_visible(world.scene, world.rig, pose)
        view_poses.append(pose)
    rlog.log_rig(rec, world.rig)
    device = {"kind": "virtual-rig", "scene": world.scene.name, "config": config.to_dict()}
    if poses is None:
        device["scene_placement"] = placement_record(world.scene.placement, world.scene.mm_per_unit,
                                                     config.scene_pose not in (None, "default"))
    if executor is not None and scene is None and not noise_stream and executor.parallel(views):
        return _capture_pooled(config, world, view_poses, out, device, executor, overwrite=overwrite, rec=rec,
                               progress=progress)
    result = scan(
        # no reference frame: the virtual rig has no latency, and its images stay those of
        # earlier slscan versions (each image's noise is drawn from its index in the view)
        scan_devices(world), scan_plan(config, world.rig, reference_frame=False), out, views=views,
        overwrite=overwrite,
        incremental=False, calibration=world.rig, calibration_source="virtual-rig ground truth",
        device_info=device, on_frame=log_scan.frame_logger(rec), progress=progress,
        after_view=None if rec is None else lambda v, _record, _session: log_virtual_view(rec, world, v),
    )
    return result.session


@dataclass(frozen=True)
class _ViewJob:
    """One view for a worker to render: where the object stands and where its images go."""

    config: VirtualCaptureConfig
    rig: Rig
    rig_from_object: np.ndarray
    view_index: int
    folder: str


def _file_stamp(name: str) -> tuple[int, int] | None:
    """(modification time, size) of a mesh-file scene, None for a built-in one: a worker
    (kept for the whole run) reads a mesh file again when it has changed."""
    try:
        stat = os.stat(name)
    except OSError:
        return None
    return stat.st_mtime_ns, stat.st_size


@functools.lru_cache(maxsize=2)
def _scene(name: str, units: str | float | None, pose: str | None, stamp: tuple[int, int] | None) -> Scene:
    """A worker's scene, built once per process and file version (a mesh file is read
    once, not per view)."""
    return scene_by_name(name, units=units, pose=parse_pose(pose))


def _render_view(job: _ViewJob) -> ViewRecord:
    """Render one view in a worker: its images and ground truth written into ``job.folder``
    (made by the caller: a worker whose session was given up meanwhile fails, writes nothing)."""
    config, rig = job.config, job.rig
    name = f"view_{job.view_index:03d}"
    scene = _scene(config.scene, config.scene_units, config.scene_pose, _file_stamp(config.scene))
    geom = trace_view(scene, rig, job.rig_from_object, config.optics)
    check_view_geometry(geom, name, scene.name)
    folder = Path(job.folder)
    if not folder.is_dir():
        raise SlscanError(f"{folder}: the view's folder is gone (the capture was given up)")
    sensor, records = config.sensor, []
    for rec, image in _exposed_images(geom, rig, config.pattern_set(rig), config, job.view_index):
        write_capture(folder / rec.file, image, bit_depth=sensor.bit_depth, jpeg_quality=sensor.jpeg_quality or None)
        records.append(rec)
    gt_file = "ground_truth.npz"
    ground_truth(geom).save(folder / gt_file)
    exposure = view_exposure(exposure_record(sensor), scan_plan(config, rig, reference_frame=False))
    return ViewRecord(name, tuple(records), job.rig_from_object, "ground-truth", exposure, gt_file)


def _capture_pooled(config: VirtualCaptureConfig, world: VirtualRig, poses: list[np.ndarray], out, device: dict,
                    executor, *, overwrite: bool, rec, progress: Progress | None) -> Session:
    """:func:`capture_session`'s views rendered by ``executor``'s workers, in view order."""
    from slscan.capture.session import SessionWriter

    rig, sensor = world.rig, config.sensor
    patterns = config.pattern_set(rig)
    lens = rig.projector.lens
    writer = SessionWriter(
        out, camera_size=(rig.camera.width, rig.camera.height), projector_size=(lens.width, lens.height),
        channels=world.camera.channels, bit_depth=sensor.bit_depth, patterns=patterns, calibration=rig,
        calibration_source="virtual-rig ground truth", device=device, overwrite=overwrite,
        jpeg_quality=sensor.jpeg_quality or None, response=sensor.response,
    )
    on_frame = None
    if rec is not None:
        from slscan.viewer import log_scan

        on_frame = log_scan.frame_logger(rec)
    with writer:
        # absolute paths: workers (a Dask cluster's) need not share this process's folder
        scene_file = config.scene if os.path.isfile(config.scene) else None
        # the units as this process resolved them: a worker reading the file again must not
        # guess (and warn about the guess) once more
        job_config = dataclasses.replace(config, scene=os.path.abspath(scene_file),
                                         scene_units=world.scene.mm_per_unit) if scene_file else config
        jobs = [_ViewJob(job_config, rig, pose, v, str(writer.view_folder(f"view_{v:03d}").absolute()))
                for v, pose in enumerate(poses)]
        executor.start(len(jobs), ("slscan.virtual.device",))
        for v, record in enumerate(executor.map(_render_view, jobs)):
            writer.add_view(record)
            for i, image_record in enumerate(record.images):
                if on_frame is not None:
                    image = read_capture(Path(jobs[v].folder) / image_record.file)
                    shown = render(patterns[i]) if image_record.kind == "pattern" else None
                    on_frame(FrameCaptured(v, i, image_record, image, shown))
                if progress:
                    progress(f"{record.name} {image_record.file}")
            if rec is not None:
                scene, truth = world.scene, GroundTruth.load(Path(jobs[v].folder) / record.ground_truth)
                _log_view_truth(rec, scene, rig, record.rig_from_object, truth, v)
    return writer.session()


def images_per_view(config: VirtualCaptureConfig) -> int:
    """How many images one view produces (for progress bars)."""
    rig = config.rig()
    return len(config.pattern_set(rig)) + (len(rig.lights) if config.lit_images else 0)
