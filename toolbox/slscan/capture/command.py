"""``slscan scan``: drive a projector and a camera (real, or the virtual rig) through the
acquisition driver, watching each view arrive in Rerun with a quick decode after it."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import time
from pathlib import Path

import numpy as np

from slscan.devices.base import DeviceError, Placement, Stage
from slscan.errors import SlscanError
from slscan.progress import ProgressBar
from slscan.progress import console as _console

log = logging.getLogger(__name__)

DESCRIPTION = """\
Scan with a projector and a camera: every view projects white, black and the coded
patterns (hybrid, Gray code or phase shifting), then switches the ring lights one at a
time, and is written to the capture session as soon as it is complete. Between views you are asked to
move the object (the virtual rig turns its turntable). After each view a quick decode
shows its range map and its holes in Rerun, so you see what is missing before moving on.

device specs:
  --projector screen[:N]   borderless full-screen window on monitor N (pip install 'slscan[screen]')
  --camera opencv[:N]      UVC/V4L2 webcam N, or opencv:FILE for a video or image sequence;
                           opencv:N:WIDTHxHEIGHT@FPS asks for a mode, e.g. opencv:0:1920x1080@30
  --camera gphoto2[:PORT]  tethered still camera through libgphoto2 (pip install 'slscan[gphoto2]')
  --camera folder:DIR      a folder your tethering software saves each shot to
  --camera virtual         the virtual rig (projector, camera, lights and turntable simulated)
  --camera loop            the virtual rig's object seen through the real projector window:
                           a test fake that checks the window shows every pattern exactly
"""

EPILOG = """\
examples:
  slscan scan --camera virtual --views 4 --out figurine --spawn
  slscan scan --projector screen:1 --camera opencv:0 --auto-exposure --views 8 --out bust \\
              --calibration rig.json --lights manual --spawn
  slscan scan --projector screen:1 --camera gphoto2 --board 9x7 --square 25 --views 8 --out board
  slscan scan ... --out bust --resume        continue an interrupted scan with its next view
  slscan scan --camera virtual --preview --preview-seconds 3     live focus, clipping and overlap; no scan
  slscan scan --projector screen:1 --camera opencv:0:1920x1080@30 --stage serial:/dev/ttyUSB0 --preview \
              --turntable-axis turntable.json --views 8 --out bust
"""


def add_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``scan`` to the ``slscan`` subcommands; return its parser."""
    from slscan.viewer.recording import add_recording_arguments

    p = subparsers.add_parser(
        "scan", help="scan with a projector and a camera (real or virtual), live in Rerun",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, help="capture-session folder to write (not needed with --check-exposure, "
                   "or with --preview to preview only)")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--resume", action="store_true", help="continue the session in --out with its next view")
    dev = p.add_argument_group("devices")
    dev.add_argument("--projector", default=None, metavar="SPEC",
                     help="screen[:N] or virtual (default: virtual with --camera virtual, else screen:1)")
    dev.add_argument("--camera", default="virtual", metavar="SPEC",
                     help="opencv[:N[:WxH@FPS]|:FILE], gphoto2[:PORT], folder:DIR, virtual (default) or loop")
    dev.add_argument("--lights", choices=("manual", "none", "virtual"), default=None,
                     help="ring lights for the albedo images: manual (you are asked to switch each), none; "
                          "default: virtual on the virtual rig, none on a real one")
    dev.add_argument("--light-count", type=int, default=6, help="manual lights: how many (default 6)")
    add_stage_arguments(dev)
    dev.add_argument("--turntable-axis", type=Path, default=None, metavar="AXIS.json",
                     help="the turntable's axis (slscan turntable-axis): each view then records its pose, so "
                          "registration starts from it")
    dev.add_argument("--preview", action="store_true",
                     help="before scanning, show the live camera in Rerun with focus, clipping and projector "
                          "overlap (as slscan preview) until you press Enter or --preview-seconds pass")
    dev.add_argument("--preview-seconds", type=float, default=None, metavar="S",
                     help="with --preview: stop the preview after S seconds instead of waiting for Enter")
    dev.add_argument("--preview-frames", type=int, default=None, metavar="N",
                     help="with --preview: stop the preview after N refreshes")
    dev.add_argument("--preview-period", type=int, default=4, metavar="PX",
                     help="with --preview: the focus stripes' period, projector px (default 4: 2 px stripes)")
    pat = p.add_argument_group("patterns")
    from slscan.patterns import add_pattern_arguments

    add_pattern_arguments(pat)
    pat.add_argument("--levels", type=int, default=None,
                     help="hybrid levels (default: as many as keep 2 projector px per line, 9 at 1024 px)")
    pat.add_argument("--gray-rows", action="store_true",
                     help="also code the projector rows (Gray code, phase shifting)")
    p.add_argument("--views", type=int, default=1, help="views to capture (default 1); you are asked "
                   "to move the object between views")
    cam = p.add_argument_group("exposure and timing")
    cam.add_argument("--settle", default=None, metavar="SECONDS|auto",
                     help="wait after each pattern before capturing; auto: measure the projector-to-camera "
                          "latency by flashing white (default: auto for opencv and gphoto2 cameras, 0 for a "
                          "watch folder and the virtual rig)")
    cam.add_argument("--auto-exposure", action="store_true",
                     help="before the first view, find the exposure (then gain) that keeps the white frame and "
                          "the finest green lines below saturation; stop if none does (paper Fig. 9)")
    cam.add_argument("--check-exposure", action="store_true",
                     help="only measure saturation and peak level at the current settings and report; no scan")
    cam.add_argument("--lit-exposure", type=float, default=1.0,
                     help="exposure of the lit images relative to the patterns' (cameras with an exposure control)")
    cam.add_argument("--no-quick-decode", action="store_true", help="no range map after each view")
    cal = p.add_argument_group("calibration")
    cal.add_argument("--calibration", type=Path, metavar="CALIB.json",
                     help="the rig's calibration (slscan calibrate): recorded in the session, used by the quick decode")
    cal.add_argument("--board", metavar="COLSxROWS", default=None,
                     help="capture a calibration board instead (inner corners, e.g. 9x7): Gray code with rows "
                          "and hybrid (or the --patterns asked, with rows, e.g. phase), no lit images, corners "
                          "found live in each pose; then run slscan calibrate")
    cal.add_argument("--square", type=float, default=50.0, help="board square side, mm (default 50)")
    cal.add_argument("--target", choices=("chessboard", "charuco"), default="chessboard", help="board kind")
    sim = p.add_argument_group("virtual rig (--camera virtual or loop)")
    sim.add_argument("--scene", default="object", help='"object" (figurine), "tile", "concave", "marble", "bronze" or a mesh file')
    add_placement_arguments(sim)
    sim.add_argument("--scale", type=float, default=0.5,
                     help="camera and projector resolution factor (default 0.5; 1: 1440x960 and 1024x768)")
    sim.add_argument("--exposure", type=float, default=1.0, help="virtual camera exposure (default 1)")
    sim.add_argument("--latency", type=float, default=0.0, help="virtual projector latency, s (default 0)")
    sim.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    p.set_defaults(func=run)
    return p


def add_stage_arguments(p) -> None:
    """``--stage`` and the turntable's settings (``slscan scan``, ``slscan stage``)."""
    p.add_argument("--stage", default=None, metavar="SPEC",
                   help="what turns the object between views: manual (you are asked; default on a real rig), "
                        "serial:PORT[:grbl|marlin][:BAUD] (a stepper turntable speaking G-code, e.g. "
                        "serial:/dev/ttyUSB0; pip install 'slscan[serial]'), or virtual (the virtual rig's)")
    p.add_argument("--stage-axis", default="X", metavar="LETTER",
                   help="the G-code axis the turntable's stepper is on (default X; A on 4-axis builds)")
    p.add_argument("--stage-units-per-degree", type=float, default=1.0, metavar="U",
                   help="G-code units per degree of table rotation (default 1: the firmware's steps per unit "
                        "make one unit one degree)")
    p.add_argument("--stage-home", action="store_true", help="home the turntable first ($H / G28)")
    p.add_argument("--stage-sweep", type=float, default=360.0, metavar="DEG",
                   help="the views' angles span this many degrees (default 360: a full turn in equal steps; "
                        "less: from --stage-start to start + sweep, both included, e.g. 80 for a board)")
    p.add_argument("--stage-start", type=float, default=0.0, metavar="DEG",
                   help="the first view's turntable angle, degrees (default 0)")
    p.add_argument("--stage-timeout", type=float, default=5.0, metavar="S",
                   help="seconds the controller may take to answer a command (default 5)")
    p.add_argument("--stage-boot", type=float, default=2.0, metavar="S",
                   help="seconds to wait after opening the port, while the controller reboots (default 2; "
                        "0 for a board that does not reset when the port opens)")


def open_stage(args):
    """The turntable of ``--stage serial:...`` opened with the ``--stage-*`` settings (and
    ``--turntable-axis`` where the command has it)."""
    from slscan.devices.turntable import SerialTurntable, parse_turntable_spec

    spec = parse_turntable_spec(args.stage)
    point = direction = None
    if getattr(args, "turntable_axis", None) is not None:
        from slscan.calibrate.turntable import load_turntable_axis

        axis = load_turntable_axis(args.turntable_axis)
        point, direction = axis.point, axis.direction
    if not (math.isfinite(args.stage_timeout) and args.stage_timeout > 0):
        raise SlscanError(f"--stage-timeout must be positive, got {args.stage_timeout}")
    if not (math.isfinite(args.stage_boot) and 0 <= args.stage_boot <= 60):
        raise SlscanError(f"--stage-boot must be in [0, 60] s, got {args.stage_boot}")
    return SerialTurntable(spec.port, firmware=spec.firmware, baud=spec.baud, axis=args.stage_axis,
                           units_per_degree=args.stage_units_per_degree, timeout_s=args.stage_timeout,
                           sweep_deg=args.stage_sweep, start_deg=args.stage_start, axis_point=point,
                           axis_direction=direction, home=args.stage_home, boot_s=args.stage_boot)


def _stage_kind(args) -> str:
    text = (args.stage or "").strip().lower()
    if text in ("", "manual", "virtual"):
        return text or "default"
    if text.startswith("serial:"):
        return "serial"
    raise SlscanError(f"--stage {args.stage!r}: expected manual, virtual or serial:PORT[:grbl|marlin][:BAUD]")


def add_placement_arguments(p: argparse.ArgumentParser) -> None:
    """``--scene-units``, ``--scene-pose``, ``--rig`` and ``--effects``: where the virtual
    rig's object stands, what the rig is and which light it renders (docs/virtual-rig.md)."""
    p.add_argument("--scene-units", default=None, metavar="UNITS",
                   help="the mesh file's units: mm, cm, m, in or mm per unit (default auto: mm, or m "
                        "when the mesh is under 10 units across)")
    p.add_argument("--scene-pose", default=None, metavar="POSE",
                   help='where the object stands on the turntable: "rx,ry,rz,tx,ty,tz" (degrees about the '
                        "turntable's x, y, z, then mm; y is down) or a 4x4 matrix file (.json, .txt) mapping "
                        "the file's coordinates (mm) to the turntable frame (default: turned 180 degrees about "
                        "x, so y up and +z front face up and the camera, bounding box centred on the turntable)")
    p.add_argument("--effects", default=None, metavar="NAMES",
                   help="light-transport effects to render, comma-separated, or all (default: direct light "
                        "only; an unknown name lists the known ones; docs/virtual-rig.md)")
    p.add_argument("--projector-response", type=float, default=None, metavar="GAMMA",
                   help="the virtual projector's response: pattern value v emits v ** GAMMA (default 1: linear; "
                        "the tone effect sets 2.2); for testing a response capture (slscan response) against truth")
    p.add_argument("--rig", type=Path, default=None, metavar="RIG.json",
                   help="the virtual rig's camera, projector and lights as Rig.to_dict writes them (or a "
                        "session.json: its calibration); default: the paper's rig")


def placement_settings(args: argparse.Namespace) -> dict:
    """The :class:`~slscan.virtual.device.VirtualCaptureConfig` settings of the placement
    arguments, refused with the option's name when malformed."""
    from slscan.virtual.placement import check_pose_text, parse_units

    parse_units(args.scene_units, "--scene-units")
    check_pose_text(args.scene_pose, "--scene-pose")
    from slscan.virtual.effects import parse_effects

    settings = {"scene_units": args.scene_units, "scene_pose": args.scene_pose,
                "rig_file": None if args.rig is None else str(args.rig),
                "effects": parse_effects(args.effects, "--effects")}
    if getattr(args, "projector_response", None) is not None:
        from slscan.virtual.render import Optics

        if not 0.2 <= args.projector_response <= 5:
            raise SlscanError(f"--projector-response must be in [0.2, 5], got {args.projector_response}")
        settings["optics"] = Optics(projector_gamma=args.projector_response)
    return settings


# --- devices --------------------------------------------------------------------------------


class FirstViewInPlace(Stage):
    """A hand-operated stage whose first view needs no prompt: the object is in place
    when the scan starts (or resumes); the operator is asked before every later view."""

    def __init__(self, inner: Stage) -> None:
        self.inner, self.name, self._first = inner, inner.name, True

    def move_to(self, view_index: int, views: int) -> Placement:
        if self._first:
            self._first = False
            return Placement()
        return self.inner.move_to(view_index, views)

    def close(self) -> None:
        self.inner.close()

    def describe(self) -> dict:
        return self.inner.describe()


@dataclasses.dataclass
class _Rig:
    devices: object  # ScanDevices
    patterns: list
    world: object = None  # VirtualRig for virtual/loop
    calibration: object = None  # slscan.rig.Rig recorded in the session
    measured: object = None  # slscan.calibrate.io.Calibration given with --calibration
    camera_model: object = None  # PinholeModel for coverage
    simulated: bool = False


def _levels(args, width: int) -> int:
    max_levels = int(math.log2(max(4, width))) - 1  # two projector pixels per line
    if args.levels is None:
        return min(9, max_levels)
    if not 1 <= args.levels <= max_levels:
        raise SlscanError(f"--levels must be in 1..{max_levels} for a {width} px wide projector, got {args.levels}")
    return args.levels


def _pattern_set(args, width: int, height: int):
    from slscan.patterns import pattern_options, standard_set, with_rows

    family, rows = args.patterns, args.gray_rows
    if args.board:  # projector rows for the inverse camera; the hybrid's lines (if asked) for the light planes
        family, rows = with_rows(family), True
    return standard_set(family, width=width, height=height, levels=_levels(args, width), rows=rows,
                        **pattern_options(args))


def _board(args):
    if args.board is None:
        return None
    from slscan.calibrate.target import Board, parse_board_size

    cols, rows = parse_board_size(args.board)
    return Board(kind=args.target, columns=cols, rows=rows, square=args.square)


def _open_rig(args, camera_spec, projector_spec) -> _Rig:
    from slscan.capture.driver import ScanDevices
    from slscan.devices.base import NoLights
    from slscan.devices.specs import SIMULATED_CAMERAS, open_camera, open_projector
    from slscan.devices.turntable import view_angles
    from slscan.virtual.device import VirtualCaptureConfig, scan_devices, virtual_devices
    from slscan.virtual.devices import turntable_pose
    from slscan.virtual.sensor import Sensor

    board = _board(args)
    if camera_spec.kind in SIMULATED_CAMERAS:
        if args.calibration is not None:
            raise SlscanError("--calibration is for real rigs: the virtual rig records its true calibration")
        if args.lights == "manual":
            raise SlscanError("--lights manual is for real rigs: the virtual rig switches its own lights")
        if not 0 < args.scale <= 2:
            raise SlscanError(f"--scale must be in (0, 2], got {args.scale}")
        config = VirtualCaptureConfig(
            scene=args.scene, camera_scale=args.scale, projector_scale=args.scale, seed=args.seed,
            lit_images=board is None and args.lights != "none", sensor=Sensor(exposure=args.exposure),
            **placement_settings(args),
        )
        if _stage_kind(args) in ("serial", "manual"):
            raise SlscanError(f"--stage {args.stage}: the virtual rig turns its own turntable (--stage virtual)")
        if args.turntable_axis is not None:
            raise SlscanError("--turntable-axis is for a real turntable: the virtual rig records its true poses")
        scene = poses = angles = None
        turned = args.stage_sweep != 360.0 or args.stage_start != 0.0
        if board is not None:
            from slscan.virtual.boards import board_poses, board_scene, default_edge_sigma

            rig = config.rig()
            scene = board_scene(board, edge_sigma=default_edge_sigma(rig))
            if turned:  # the board stands on the turntable: captures for slscan turntable-axis
                from slscan.calibrate.turntable import board_on_turntable

                angles = view_angles(args.views, sweep_deg=args.stage_sweep, start_deg=args.stage_start)
                poses = [turntable_pose(rig, a, board_on_turntable(board)) for a in angles]
            else:
                poses = board_poses(rig, board, args.views)
        elif turned:
            rig = config.rig()
            scene = config.build_scene()
            angles = view_angles(args.views, sweep_deg=args.stage_sweep, start_deg=args.stage_start)
            poses = [turntable_pose(rig, a, scene.placement) for a in angles]
        world = virtual_devices(config, scene=scene, poses=poses, latency_s=args.latency)
        world.turntable_angles = angles
        lens = world.rig.projector.lens
        patterns = _pattern_set(args, lens.width, lens.height)
        if camera_spec.kind == "virtual":
            if projector_spec is not None and projector_spec.kind != "virtual":
                raise SlscanError("--camera virtual sees the virtual projector only; for a real projector "
                                  "window use --camera loop (a test fake) or a real camera")
            devices = scan_devices(world)
        else:
            from slscan.devices.screen import grab_screen
            from slscan.virtual.devices import ScreenLoopCamera

            if projector_spec is None or projector_spec.kind != "screen":
                raise SlscanError("--camera loop watches a real projector window: give --projector screen[:N]")
            projector = open_projector(projector_spec)
            try:
                if projector.resolution != (lens.width, lens.height):
                    raise DeviceError(
                        f"{projector.name}: the monitor is {projector.resolution[0]}x{projector.resolution[1]}, "
                        f"the virtual rig's projector at --scale {args.scale:g} is {lens.width}x{lens.height}"
                    )
                camera = ScreenLoopCamera(world, lambda: grab_screen(projector), world.camera.sensor)
            except BaseException:
                projector.close()
                raise
            devices = scan_devices(world, camera)
            devices.projector = projector
        if args.lights == "none":  # a rig without ring lights: colour from the projector as the light
            from slscan.devices.base import NoLights

            devices.lights = NoLights()
        return _Rig(devices, patterns, world, world.rig, None, world.rig.camera, simulated=True)

    # real devices
    from slscan.devices.lights import ManualLights, ManualStage

    for option, value in (("--rig", args.rig), ("--scene-pose", args.scene_pose), ("--scene-units", args.scene_units)):
        if value is not None:
            raise SlscanError(f"{option} is for the virtual rig (--camera virtual or loop); a real rig's geometry "
                              "comes from --calibration")

    projector_spec = projector_spec or _default_projector()
    if projector_spec.kind != "screen":
        open_projector(projector_spec)  # refuses it, naming the real ones, before anything opens
    camera = open_camera(camera_spec)  # before the projector: a missing camera is reported before a window opens
    opened = [camera]
    try:
        projector = open_projector(projector_spec)
        opened.append(projector)
        lights_kind = args.lights or "none"
        if lights_kind == "virtual":
            raise SlscanError("--lights virtual needs the virtual rig (--camera virtual)")
        lights = ManualLights(args.light_count) if lights_kind == "manual" and board is None else NoLights()
        kind = _stage_kind(args)
        if kind == "virtual":
            raise SlscanError("--stage virtual is the virtual rig's turntable (--camera virtual)")
        if kind == "serial":
            stage = open_stage(args)
        else:
            if args.turntable_axis is not None:
                raise SlscanError("--turntable-axis needs a turntable: give --stage serial:PORT")
            stage = FirstViewInPlace(ManualStage())
        opened.append(stage)
        devices = ScanDevices(projector, camera, lights, stage)
        w, h = projector.resolution
        patterns = _pattern_set(args, w, h)
        calibration = measured = camera_model = None
        if args.calibration is not None:
            measured = _load_calibration(args.calibration, camera.resolution, (w, h))
            calibration = measured.rig()
            camera_model = measured.camera
        return _Rig(devices, patterns, None, calibration, measured, camera_model)
    except BaseException:
        for device in opened:
            device.close()
        raise


def _default_projector():
    from slscan.devices.specs import DeviceSpec

    return DeviceSpec("screen", "1")


def _load_calibration(path: Path, camera_size, projector_size):
    from slscan.calibrate.io import load_calibration

    calibration = load_calibration(path)
    if (calibration.camera.width, calibration.camera.height) != tuple(camera_size):
        raise SlscanError(f"{path}: calibrated for a {calibration.camera.width}x{calibration.camera.height} "
                          f"camera, this camera gives {camera_size[0]}x{camera_size[1]}")
    if tuple(calibration.projector_size) != tuple(projector_size):
        raise SlscanError(f"{path}: calibrated for a {calibration.projector_size[0]}x{calibration.projector_size[1]} "
                          f"projector, this one is {projector_size[0]}x{projector_size[1]}")
    return calibration


# --- after each view -----------------------------------------------------------------------


@dataclasses.dataclass
class ViewReport:
    view: str
    coverage: float | None = None  # covered share of the decodable pixels
    vertices: int = 0
    decodable: float = 0.0  # share of the frame the decoder could read
    corners: int | None = None  # board corners found
    note: str = ""


class AfterView:
    """Quick decode (range map, holes, coverage) or board corners, logged to Rerun."""

    def __init__(self, rig: _Rig, rec, *, quick_decode: bool, board) -> None:
        self.rig, self.rec, self.quick_decode, self.board = rig, rec, quick_decode, board
        self.reports: list[ViewReport] = []
        self.corner_cover: np.ndarray | None = None

    def __call__(self, index: int, record, session) -> None:
        from slscan.viewer.log_scan import log_scan_text

        if self.rig.world is not None and self.rec is not None:
            from slscan.virtual.device import log_virtual_view

            log_virtual_view(self.rec, self.rig.world, index)
        if self.board is not None:
            report = self._board(index, record, session)
        elif self.quick_decode:
            report = self._decode(index, record, session)
        else:
            report = ViewReport(record.name)
        self.reports.append(report)
        log_scan_text(self.rec, f"{record.name}: {report.note}", level="WARN" if "hole" in report.note else "INFO")
        if report.note:
            _console().print(f"[cyan]{record.name}[/] {report.note}", highlight=False)

    def _decode(self, index: int, record, session) -> ViewReport:
        from slscan.decode.pipeline import DecodeConfig, choose_method, decode_view
        from slscan.decode.rangemap import covered_pixels
        from slscan.patterns import family
        from slscan.viewer import log_decode
        from slscan.viewer.log_scan import log_code_map, log_holes

        view = session.view(record.name)
        planes = None
        if self.rig.measured is not None:
            from slscan.calibrate.io import apply_calibration, calibration_planes

            session = apply_calibration(session, self.rig.measured)
            planes = calibration_planes(self.rig.measured)
        if session.calibration is None:
            res = family(choose_method(session)).decode_module().decode(session, view, DecodeConfig())
            codes, code_max = res.codes, max(res.code_max, 1)
            log_code_map(self.rec, log_decode.colormap(codes.astype(np.float64), code_max), view_index=index)
            log_decode.log_display_maps(self.rec, res.maps, view_index=index)
            log_decode.log_metrics(self.rec, res.stats, view_index=index, marked=res.stats)
            share = float(res.mask.mean())
            return ViewReport(record.name, decodable=share,
                              note=f"{100 * share:.1f} % of the frame decoded (no calibration: no range map)")
        result = decode_view(session, view, DecodeConfig(), planes=planes)
        camera = self.rig.camera_model or session.calibration.camera
        covered = covered_pixels(result.range_map, camera, result.mask.shape)
        mask = result.mask
        coverage = float(covered[mask].mean()) if mask.any() else 0.0
        holes = mask & ~covered
        if self.rec is not None:
            rm = result.range_map
            log_decode.log_decode_maps(self.rec, view_index=index, mask=mask, codes=result.codes,
                                       code_max=result.code_max, saturated=result.saturated)
            log_decode.log_range_map(self.rec, rm.vertices, rm.faces, rm.normals, rm.colors, view_index=index)
            log_decode.log_display_maps(self.rec, result.maps, view_index=index)  # e.g. phase, unwrapping
            log_decode.log_metrics(self.rec, result.stats, view_index=index, marked=result.stats)
            log_holes(self.rec, holes, coverage, view_index=index)
        note = (f"{len(result.range_map.vertices):,} vertices, {100 * coverage:.1f} % of the decodable pixels "
                "covered")
        if coverage < 0.7:
            note += " (large holes: check focus, exposure and the angle to the projector)"
        return ViewReport(record.name, coverage, len(result.range_map.vertices), float(mask.mean()), note=note)

    def _board(self, index: int, record, session) -> ViewReport:
        from slscan.calibrate.camera import detect_corners
        from slscan.calibrate.target import board_image_id
        from slscan.viewer.log_calibrate import log_board_image

        view = session.view(record.name)
        rec_white = view.image_for(board_image_id(session))
        image = session.read_image(view, rec_white)
        detection = detect_corners(image, self.board, source=rec_white.file)
        log_board_image(self.rec, image, detection, view_index=index)
        h, w = image.shape[:2]
        if self.corner_cover is None:
            self.corner_cover = np.zeros((4, 4), bool)
        if detection:
            cells = np.clip((detection.corners / [w / 4, h / 4]).astype(int), 0, 3)
            self.corner_cover[cells[:, 1], cells[:, 0]] = True
            covered = int(self.corner_cover.sum())
            note = (f"board found: {len(detection.ids)} corners; corners seen so far in {covered} of 16 image "
                    "cells" + ("" if covered == 16 else " (move the board towards the empty cells and tilt it)"))
        else:
            note = f"board NOT found ({detection.reason}): this pose will not help; try again"
        return ViewReport(record.name, corners=len(detection.ids), note=note)


# --- the command ----------------------------------------------------------------------------


def _settle(args, rig: _Rig, rec) -> float:
    from slscan.capture.driver import measure_latency
    from slscan.viewer.log_scan import log_scan_text

    # a watch folder gets each shot when something else triggers it: nothing to flash-time
    automatic = not rig.simulated and not args.camera.startswith("folder")
    text = args.settle if args.settle is not None else ("auto" if automatic else "0")
    if text != "auto":
        try:
            value = float(text)
        except ValueError:
            raise SlscanError(f"--settle must be a number of seconds or auto, got {text!r}") from None
        if not (math.isfinite(value) and 0 <= value <= 60):
            raise SlscanError(f"--settle must be in [0, 60] s, got {text}")
        return value
    latency = measure_latency(rig.devices.projector, rig.devices.camera)
    line = (f"projector-to-camera latency {1000 * max(latency.delays):.0f} ms (flashes: "
            f"{', '.join(f'{1000 * d:.0f}' for d in latency.delays)} ms; {1000 * latency.frame_s:.0f} ms per frame): "
            f"settle {1000 * latency.settle_s:.0f} ms")
    _console().print(line, highlight=False)
    log_scan_text(rec, line)
    return latency.settle_s


def _preview(args, rig: _Rig, settle: float, rec, *, then_scan: bool) -> None:
    """The live preview (focus, clipping, overlap) until Enter, --preview-seconds or
    --preview-frames; one line per refresh on the terminal, everything in Rerun."""
    import sys
    import threading

    from slscan.capture.preview import run_preview
    from slscan.viewer.log_preview import log_preview

    seconds, frames = args.preview_seconds, args.preview_frames
    if seconds is not None and not (math.isfinite(seconds) and seconds >= 0):
        raise SlscanError(f"--preview-seconds must be a number of seconds >= 0, got {seconds}")
    if frames is not None and frames < 1:
        raise SlscanError(f"--preview-frames must be at least 1, got {frames}")
    stop = None
    if seconds is None and frames is None:
        if sys.stdin is None or not sys.stdin.isatty():
            raise SlscanError("--preview waits for Enter from an operator at a terminal: give --preview-seconds N "
                              "or --preview-frames N to preview without one")
        pressed = threading.Event()

        def wait_for_enter() -> None:
            try:
                sys.stdin.readline()
            finally:
                pressed.set()

        threading.Thread(target=wait_for_enter, daemon=True).start()
        stop = pressed.is_set
    console = _console()
    until = "press Enter to " + ("start the scan" if then_scan else "stop") if stop is not None else (
        f"for {seconds:g} s" if seconds is not None else f"{frames} refresh(es)")
    console.print(f"[cyan]preview[/] ({until}): turn the focus ring for the highest focus; keep clipped near 0 %",
                  highlight=False)

    def show(index: int, measures) -> None:
        log_preview(rec, index, measures)
        console.print(f"[cyan]preview {index + 1}[/] {measures.line()}", highlight=False)

    if rec is not None and then_scan:  # the preview's layout while it runs, then the scan's
        from slscan.viewer.layouts import preview_blueprint

        rec.send_blueprint(preview_blueprint(), make_active=True, make_default=False)
    try:
        run_preview(rig.devices.projector, rig.devices.camera, seconds=seconds, frames=frames, stop=stop,
                    on_measures=show, period_px=args.preview_period, settle_s=settle)
    except DeviceError as exc:
        raise SlscanError(f"preview: {exc}") from None
    if rec is not None and then_scan:
        from slscan.viewer.layouts import scan_blueprint

        rec.send_blueprint(scan_blueprint(), make_active=True, make_default=False)


def _exposure(args, rig: _Rig, settle: float, rec) -> None:
    from rich.table import Table

    from slscan.capture.driver import find_exposure
    from slscan.viewer.log_scan import log_scan_text

    result = find_exposure(rig.devices.projector, rig.devices.camera, rig.patterns, settle_s=settle)
    table = Table("trial", *[k for k in result.trials[0].controls], "clipped %", "peak %", title="exposure")
    for i, t in enumerate(result.trials):
        table.add_row(str(i), *[f"{v:g}" for v in t.controls.values()], f"{100 * t.clipped_share:.3f}",
                      f"{100 * t.peak:.1f}")
    console = _console()
    console.print(table)
    log_scan_text(rec, "exposure: " + result.message, level="INFO" if result.ok else "WARN")
    if not result.ok:
        raise SlscanError(f"exposure: {result.message}")
    console.print(f"[green]exposure[/] {result.message}", highlight=False)


def run(args: argparse.Namespace) -> int:
    from slscan.capture.driver import ScanPlan, scan
    from slscan.devices.specs import CAMERA_KINDS, PROJECTOR_KINDS, parse_spec
    from slscan.viewer.log import log_rig
    from slscan.viewer.layouts import scan_blueprint
    from slscan.viewer.log_scan import frame_logger
    from slscan.viewer.recording import recording_from_args

    if args.out is None and not (args.check_exposure or args.preview):
        raise SlscanError("--out: name the capture-session folder to write")
    preview_only = args.preview and args.out is None and not args.check_exposure
    if not args.preview and (args.preview_seconds is not None or args.preview_frames is not None):
        raise SlscanError("--preview-seconds and --preview-frames go with --preview")
    if args.out is None:
        args.out = Path("check-exposure")  # never written
    if args.views < 1:
        raise SlscanError(f"--views must be at least 1, got {args.views}")
    if not (math.isfinite(args.lit_exposure) and args.lit_exposure > 0):
        raise SlscanError(f"--lit-exposure must be positive, got {args.lit_exposure}")
    if args.resume and args.overwrite:
        raise SlscanError("--resume and --overwrite contradict each other")
    camera_spec = parse_spec(args.camera, CAMERA_KINDS, "camera")
    projector_spec = parse_spec(args.projector, PROJECTOR_KINDS, "projector") if args.projector else None
    if args.lights == "virtual" and camera_spec.kind not in ("virtual", "loop"):
        raise SlscanError("--lights virtual needs the virtual rig (--camera virtual or loop)")
    if not args.check_exposure and not args.resume and not args.overwrite and args.out.exists() \
            and (not args.out.is_dir() or any(args.out.iterdir())):
        raise SlscanError(f"{args.out}: exists and is not empty (pass --resume to continue it, or --overwrite)")
    console = _console()
    rig = _open_rig(args, camera_spec, projector_spec)
    devices = rig.devices
    try:
        if preview_only:
            from slscan.viewer.layouts import preview_blueprint

            layout, name = preview_blueprint(), "preview"
        else:
            layout, name = scan_blueprint(), f"scan {args.out.name}"
        with recording_from_args(args, recording_name=name, blueprint=layout) as rec:
            if rig.calibration is not None:
                log_rig(rec, rig.calibration)
            if rig.world is not None:
                devices.stage.move_to(0, args.views)  # the object in view for latency and exposure
            settle = _settle(args, rig, rec)
            if args.preview:
                _preview(args, rig, settle, rec, then_scan=not preview_only)
                if preview_only:
                    return 0
            if args.check_exposure or args.auto_exposure:
                if args.check_exposure:
                    from slscan.capture.driver import find_exposure

                    r = find_exposure(devices.projector, devices.camera, rig.patterns, settle_s=settle,
                                      search=False)
                    console.print(("[green]" if r.ok else "[red]") + "exposure[/] " + r.message, highlight=False)
                    return 0 if r.ok else 2
                _exposure(args, rig, settle, rec)
            plan = ScanPlan(tuple(rig.patterns), lit_images=args.board is None and devices.lights.count > 0,
                            lit_exposure=args.lit_exposure, settle_s=settle)
            n_lights = devices.lights.count if plan.lit_images else 0
            done = _views_done(args.out) if args.resume else 0
            total = max(0, args.views - done) * (len(rig.patterns) + n_lights)
            after = AfterView(rig, rec, quick_decode=not args.no_quick_decode, board=_board(args))
            device_info = devices.describe()
            if rig.world is not None:
                device_info["scene"] = rig.world.scene.name
            t0 = time.perf_counter()
            with ProgressBar(total, "scanning", args.quiet) as bar:
                try:
                    result = scan(
                        devices, plan, args.out, views=args.views, overwrite=args.overwrite, resume=args.resume,
                        calibration=rig.calibration,
                        calibration_source=("virtual-rig ground truth" if rig.simulated else
                                            (str(args.calibration) if rig.calibration is not None else None)),
                        device_info=device_info, on_frame=frame_logger(rec), after_view=after,
                        progress=bar.step,
                    )
                except KeyboardInterrupt:
                    kept = _views_done(args.out)
                    console.print(f"[red]interrupted[/]: {kept} finished view(s) in {args.out}; "
                                  "--resume continues with the next one")
                    return 130
            if args.board:
                nxt = f"slscan calibrate {args.out} --out rig.json --board {args.board} --square {args.square:g}"
            else:
                nxt = f"slscan decode {args.out} --out {args.out}-range-maps"
            _print_summary(result, after.reports, time.perf_counter() - t0, args.out, nxt)
    finally:
        devices.close()
    return 0


def _views_done(out: Path) -> int:
    from slscan.capture.session import SESSION_FILE, load_session

    return len(load_session(out, validate=False).views) if (out / SESSION_FILE).is_file() else 0


def _print_summary(result, reports, seconds: float, out: Path, next_step: str) -> None:
    from rich.table import Table

    table = Table("view", "imgs", "move", "show", "settle", "capture", "write", "total", "retry", "cover",
                  title="seconds per view (cover: decodable pixels under the range map)")
    by_view = {r.view: r for r in reports}
    for t in result.timings:
        r = by_view.get(t.view)
        cov = "-" if r is None or r.coverage is None else f"{100 * r.coverage:.1f}%"
        table.add_row(t.view.removeprefix("view_"), str(t.images), f"{t.move:.2f}", f"{t.show:.2f}", f"{t.settle:.2f}", f"{t.capture:.2f}",
                      f"{t.write:.2f}", f"{t.total:.2f}", str(t.retries), cov)
    console = _console()
    console.print(table)
    n = len(result.session.views)
    resumed = f" ({result.resumed_views} from before)" if result.resumed_views else ""
    console.print(f"[green]wrote[/] {out}: {n} view(s){resumed}, {seconds:.1f} s; next: {next_step}",
                  highlight=False)
