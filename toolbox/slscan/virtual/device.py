"""The virtual rig as a capture device: renders a scene and writes a capture session.

It writes exactly what a real rig would (PNG captures and ``session.json``), plus
per-view ground truth, so the rest of the pipeline never knows the difference.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slscan.capture.driver import ScanDevices, ScanPlan, capture_records, scan
from slscan.capture.session import LIT, SHADOW, GroundTruth, ImageRecord, Session
from slscan.errors import SlscanError
from slscan.patterns import PatternImage, standard_set
from slscan.rig import Rig, default_rig, transform_points
from slscan.virtual.devices import VirtualRig, turntable_pose
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
from slscan.virtual.scenes import Scene, scene_by_name
from slscan.virtual.sensor import Sensor, jpeg_round_trip

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


@dataclass(frozen=True)
class VirtualCaptureConfig:
    """What the virtual rig captures and how.

    scene : "object" (the built-in figurine), "tile", "concave", "marble", "bronze" (the
        light-transport scenes, :mod:`slscan.virtual.scenes`), or a mesh file (PLY/OBJ/glTF)
    views : turntable positions, evenly spread over 360° about the object's vertical axis
    patterns : {"hybrid", "gray", "both", "xor"}: which coded patterns follow white and black
        ("xor": Gupta's XOR-04 Gray codes, every image high-frequency)
    levels : hybrid subdivision levels (9 at 1024 px gives 511 lines)
    gray_rows : also project row Gray codes
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
        return standard_set(self.patterns, width=lens.width, height=lens.height, levels=self.levels, rows=self.gray_rows)

    def to_dict(self) -> dict:
        return {
            "scene": self.scene, "views": self.views, "patterns": self.patterns, "levels": self.levels,
            "gray_rows": self.gray_rows, "lit_images": self.lit_images, "camera_scale": self.camera_scale,
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
    sensor, optics = config.sensor, config.optics
    if geometry is not None and not needs_trace(geometry, optics):
        geom = geometry
    else:  # traced here, or again when the given geometry lacks the transport the optics need
        geom = trace_view(scene, rig, rig_from_object, optics)
    records = capture_records(patterns, len(rig.lights) if config.lit_images else 0, jpeg=bool(sensor.jpeg_quality))
    out = []
    for i, rec in enumerate(records):
        rng = np.random.default_rng([config.seed, view_index, i])
        if rec.kind == "pattern":
            image = sensor.expose(shade_pattern(geom, patterns[i], optics), rng, camera=rig.camera)
        else:
            image = sensor.expose(shade_light(geom, rec.light, rig, optics), rng,
                                  exposure_scale=config.lit_exposure, camera=rig.camera)
        if sensor.jpeg_quality:  # what reading the session's .jpg gives back
            image = jpeg_round_trip(image, sensor.jpeg_quality)
        out.append((rec, image))
    return out, geom


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
    from slscan.viewer import log as rlog

    if rec is None or world.geometry is None:
        return
    scene = world.scene
    verts = transform_points(world.pose, scene.vertices)
    rlog.log_scene_mesh(rec, verts, scene.triangles, scene.albedo.vertex_colors(scene.vertices), view_index=view_index)
    rlog.log_ground_truth(rec, ground_truth(world.geometry), view_index=view_index,
                          projector_width=world.rig.projector.lens.width)


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
) -> Session:
    """Capture ``config.views`` views of ``config.scene`` on the virtual rig into folder ``out``,
    through the acquisition driver (:func:`slscan.capture.driver.scan`), written at once
    when complete.

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
    for v in range(views):
        pose = poses[v] if poses is not None else turntable_pose(world.rig, 360.0 * v / views, world.scene.placement)
        check_visible(world.scene, world.rig, pose)
    rlog.log_rig(rec, world.rig)
    device = {"kind": "virtual-rig", "scene": world.scene.name, "config": config.to_dict()}
    if poses is None:
        device["scene_placement"] = placement_record(world.scene.placement, world.scene.mm_per_unit,
                                                     config.scene_pose not in (None, "default"))
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


def images_per_view(config: VirtualCaptureConfig) -> int:
    """How many images one view produces (for progress bars)."""
    rig = config.rig()
    return len(config.pattern_set(rig)) + (len(rig.lights) if config.lit_images else 0)
