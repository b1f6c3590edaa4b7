"""``slscan calibrate``: a capture session of a printed board in, a calibration file out."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from slscan.errors import SlscanError
from slscan.progress import ProgressBar as _ProgressBar
from slscan.progress import console as _console

DESCRIPTION = """\
Calibrate the camera and the projector from a capture session of a printed board
(chessboard or ChArUco) in several poses, each view with the white frame and the coded
patterns. The camera comes from the board's corners (Zhang's method). The projector:

  inverse-camera  board corners mapped into the projector through local homographies of
                  the decoded Gray code (needs row codes), then calibrated like a camera
                  and posed by a stereo calibration (Moreno & Taubin 2012)
  planes          the board as a flat panel: one light plane per hybrid green line or
                  Gray-code edge, then the paper's global fit (Rocchini et al. 2001)
  both            (default) both models, sharing one camera

Writes a JSON calibration file (docs/calibration.md) that `slscan decode` can use.

--import FILE [FILE2] converts another tool's calibration instead of calibrating: OpenCV
FileStorage XML/YAML (kamino410, OpenCV stereo, single-device files, or any keys named
with --keys), Bouguet's Calib_Results_stereo.m, plain-text K/dist/R/T matrices, or
3DUNDERWORLD's per-camera files. A camera + projector becomes the calibration file
--out; two cameras become the cameras.json of the multi-camera folder --out.
"""

EPILOG = """\
examples:
  slscan calibrate board-session --out rig.json --board 9x7 --square 50
  slscan calibrate kamino --out rig.json --square 75 --method inverse-camera --export-xml rig.xml
  slscan calibrate --import calibration_result.xml --session kamino --projector-scale 0.5 --out ref.json
  slscan calibrate --import cal.yml --keys camera=K_c,camera_dist=d_c,projector=K_p,projector_dist=d_p,rotation=R,translation=T --projector-size 1024x768 --camera-size 1280x1024 --out rig.json
  slscan calibrate --import Calib_Results_stereo.m --units-mm 1 --session two-cameras --out two-cameras
"""


def add_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``calibrate`` to the ``slscan`` subcommands; return its parser."""
    from slscan.calibrate.options import (
        BOARD_KINDS,
        CORRESPONDENCES,
        DEFAULT_DICTIONARY,
        DISTORTION_MODELS,
        IMPORT_FORMATS,
        INVERSE_PATTERNS,
        METHODS,
        PLANE_PATTERNS,
        SECOND_KINDS,
    )
    from slscan.viewer.recording import add_recording_arguments

    p = subparsers.add_parser(
        "calibrate",
        help="calibrate camera and projector from views of a printed board",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "session",
        type=Path,
        nargs="?",
        default=None,
        help="capture-session folder: the board in several poses (with --import: as --session)",
    )
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        help="calibration file to write (JSON); with --import of two cameras, the multi-camera "
        "folder whose cameras.json is written",
    )
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    board = p.add_argument_group("board")
    board.add_argument(
        "--target", choices=BOARD_KINDS, default="chessboard", help="default: chessboard"
    )
    board.add_argument(
        "--board",
        default="9x7",
        metavar="COLSxROWS",
        help="inner corners along a row x along a column (default 9x7: 10x8 squares)",
    )
    board.add_argument(
        "--square",
        type=float,
        default=None,
        metavar="MM",
        help="side of a printed square, mm (required unless --import); sets the scale",
    )
    board.add_argument(
        "--marker",
        type=float,
        default=0.0,
        metavar="MM",
        help="ChArUco marker side, mm (default 0.75 square)",
    )
    board.add_argument(
        "--dictionary",
        default=DEFAULT_DICTIONARY,
        help=f"ChArUco marker dictionary (default {DEFAULT_DICTIONARY})",
    )
    method = p.add_argument_group("method")
    method.add_argument(
        "--method", choices=METHODS, default="both", help="projector model(s) (default both)"
    )
    method.add_argument(
        "--planes-pattern",
        choices=PLANE_PATTERNS,
        default="auto",
        help="features whose light planes are measured (default auto: phase shifting, else hybrid "
        "lines, else Gray-code edges, whichever was captured first in that order)",
    )
    method.add_argument(
        "--inverse-pattern",
        choices=INVERSE_PATTERNS,
        default="auto",
        help="codes that map the board corners into the projector, inverse camera (default auto: "
        "phase shifting with rows if captured, else Gray code with rows)",
    )
    method.add_argument(
        "--camera-distortion",
        choices=DISTORTION_MODELS,
        default="radial-tangential",
        help="camera lens model (default radial-tangential: k1 k2 p1 p2)",
    )
    method.add_argument(
        "--projector-distortion",
        choices=DISTORTION_MODELS,
        default="radial-tangential",
        help="projector lens model, inverse camera (default radial-tangential)",
    )
    method.add_argument(
        "--no-refine",
        action="store_true",
        help="keep the camera's intrinsics fixed in the stereo calibration",
    )
    method.add_argument(
        "--correspondences",
        choices=CORRESPONDENCES,
        default="edges",
        help="local homographies from one-coordinate constraints (default: Gray-code stripe edges, "
        "or every phase-decoded pixel's column and row) or from decoded pixels (RANSAC)",
    )
    method.add_argument(
        "--window",
        type=int,
        default=0,
        metavar="PX",
        help="half-size of the local-homography windows, camera px (default: 0.3 squares)",
    )

    imp = p.add_argument_group("import another tool's calibration (docs/calibration.md)")
    imp.add_argument(
        "--import",
        dest="import_files",
        type=Path,
        nargs="+",
        default=None,
        metavar="FILE",
        help="convert FILE [FILE2] instead of calibrating: one file with both devices, or one "
        "file per device (camera first)",
    )
    imp.add_argument(
        "--format",
        choices=IMPORT_FORMATS,
        default="auto",
        help="default auto: .xml/.yml/.yaml/.json OpenCV (3DUNDERWORLD if its top key is "
        "Camera), .m Bouguet, .txt text, a folder 3DUNDERWORLD's text files",
    )
    imp.add_argument(
        "--keys",
        default=None,
        metavar="MAP",
        help="OpenCV or text: which key holds what, ROLE=KEY,... with roles camera, "
        "camera_dist, camera_size, camera_shape, projector (or camera2), projector_dist, "
        "projector_size, rotation, translation, rms, direction (camera-to-projector, "
        "projector-to-camera, camera-to-camera2, camera2-to-camera, world-to-camera)",
    )
    imp.add_argument(
        "--second",
        choices=("auto", *SECOND_KINDS),
        default="auto",
        help="what the second device is (default auto: as the file says)",
    )
    imp.add_argument(
        "--camera-size",
        default=None,
        metavar="WxH[,WxH]",
        help="camera image size(s), px, where the file does not say (checked where it does)",
    )
    imp.add_argument(
        "--projector-size",
        default=None,
        metavar="WxH",
        help="projector size (the pattern images), px, where the file does not say",
    )
    imp.add_argument(
        "--session",
        dest="check_session",
        type=Path,
        default=None,
        metavar="SESSION",
        help="capture session (multi-camera folder for two cameras) whose sizes the "
        "calibration must match",
    )
    imp.add_argument(
        "--units-mm",
        "--xml-units-mm",
        dest="units_mm",
        type=float,
        default=1.0,
        metavar="F",
        help="mm per unit of the file's translation (the board square's unit; default 1)",
    )
    imp.add_argument(
        "--projector-scale",
        "--xml-projector-scale",
        dest="projector_scale",
        type=float,
        default=1.0,
        metavar="F",
        help="pattern pixels per projector pixel of the file (0.5 for procam-calibration's "
        "graycode_step 2; default 1)",
    )
    imp.add_argument(
        "--import-xml",
        type=Path,
        default=None,
        metavar="FILE",
        help="the same as --import FILE --format opencv (SESSION gives the sizes)",
    )
    imp.add_argument(
        "--export-xml",
        type=Path,
        default=None,
        metavar="FILE",
        help="also write the result as procam-calibration XML (needs the inverse camera)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    p.set_defaults(func=run_command)
    return p


def run_command(args: argparse.Namespace) -> int:
    """Run ``slscan calibrate`` with parsed ``args``; raise SlscanError on bad input."""
    from slscan.calibrate.io import export_opencv_xml, save_calibration
    from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session, calibration_steps
    from slscan.calibrate.target import Board, parse_board_size
    from slscan.capture.session import load_session
    from slscan.viewer.layouts import calibrate_blueprint
    from slscan.viewer.recording import recording_from_args

    if args.import_files or args.import_xml is not None:
        return run_import(args)
    out: Path = args.out
    if args.session is None:
        raise SlscanError(
            "give the board's capture session (SESSION), or --import FILE to convert another "
            "tool's calibration"
        )
    if out.exists() and not args.overwrite:
        raise SlscanError(f"{out}: exists (pass --overwrite to replace it)")
    if out.is_dir():
        raise SlscanError(f"{out}: is a folder; expected a calibration file such as rig.json")
    session = load_session(args.session)
    console = _console()
    if args.square is None:
        raise SlscanError("--square: give the side of a printed square in mm (it sets the scale)")
    columns, rows = parse_board_size(args.board)
    board = Board(
        kind=args.target,
        columns=columns,
        rows=rows,
        square=args.square,
        marker=args.marker,
        dictionary=args.dictionary,
    )
    config = CalibrationConfig(
        board=board,
        method=args.method,
        planes_pattern=args.planes_pattern,
        inverse_pattern=args.inverse_pattern,
        camera_distortion=args.camera_distortion,
        projector_distortion=args.projector_distortion,
        refine_camera=not args.no_refine,
        correspondences=args.correspondences,
        window=args.window,
    )
    t0 = time.perf_counter()
    with (
        recording_from_args(
            args,
            recording_name=f"calibrate {args.session.name}",
            blueprint=calibrate_blueprint(),
        ) as rec,
        _ProgressBar(calibration_steps(session, config), "calibrating", args.quiet) as bar,
    ):
        run = calibrate_session(session, config, rec=rec, progress=bar.update)
    cal = run.calibration
    save_calibration(cal, out)
    cam = cal.camera
    lines = [
        (
            f"[green]wrote[/] {out}: {len(run.camera.views)} of {len(session.views)} views, "
            f"{time.perf_counter() - t0:.1f} s"
        ),
        (
            f"camera    fx {cam.fx:.2f}  fy {cam.fy:.2f}  cx {cam.cx:.2f}  cy {cam.cy:.2f} px, "
            f"RMS {run.camera.rms:.3f} px"
        ),
    ]
    if run.inverse_camera is not None:
        lens = cal.projector.lens
        baseline = float((cal.projector.center**2).sum() ** 0.5)
        lines.append(
            f"projector fx {lens.fx:.2f}  fy {lens.fy:.2f}  cx {lens.cx:.2f}  cy {lens.cy:.2f} px, "
            f"baseline {baseline:.1f} mm, stereo RMS {run.inverse_camera.stereo_rms:.3f} px"
        )
    if run.light_planes is not None:
        lp = run.light_planes
        lines.append(
            f"planes    {len(lp.lines)} {lp.pattern} planes, point-to-plane RMS {lp.rms_before:.4f} mm "
            f"raw, {lp.rms_after:.4f} mm after the global fit (fx {lp.model.fx:.2f}, cx {lp.model.cx:.2f} px)"
        )
    for line in lines:
        console.print(line, highlight=False)
    if args.export_xml is not None:
        export_opencv_xml(cal, args.export_xml)
        console.print(f"[green]wrote[/] {args.export_xml}")
    if getattr(args, "save", None):
        console.print(f"[green]recording[/] {args.save}: open it with  rerun {args.save}")
    return 0


# --- importing another tool's calibration ----------------------------------------------


def _sizes(text: str | None, option: str, count: int) -> list[tuple[int, int] | None]:
    """``count`` (width, height) from ``WxH[,WxH]`` (one size serves all), or Nones."""
    if text is None:
        return [None] * count
    sizes = []
    for part in text.split(","):
        try:
            w, h = (int(v) for v in part.strip().lower().split("x"))
        except ValueError:
            raise SlscanError(
                f"{option}: expected WIDTHxHEIGHT in pixels, e.g. 1280x1024, got {part!r}"
            ) from None
        if w <= 0 or h <= 0:
            raise SlscanError(f"{option}: sizes must be positive, got {part!r}")
        sizes.append((w, h))
    if len(sizes) == 1:
        sizes *= count
    if len(sizes) != count:
        raise SlscanError(f"{option}: expected 1 or {count} sizes, got {len(sizes)}")
    return sizes


def _camera_folders(root: Path) -> list[tuple[str, str]] | None:
    """(name, folder) of the cameras in ``root/cameras.json``, if there is one."""
    from slscan.capture.multicam import MULTICAM_FILE
    from slscan.fsio import read_json

    meta = root / MULTICAM_FILE
    if not meta.is_file():
        return None
    d = read_json(meta, "multi-camera description (cameras.json)")
    cams = d.get("cameras") if isinstance(d, dict) else None
    if not isinstance(cams, list) or not all(isinstance(c, dict) and "name" in c for c in cams):
        raise SlscanError(f"{meta}: expected a list of cameras with names")
    if len(cams) != 2:
        raise SlscanError(
            f"{meta}: has {len(cams)} cameras; an imported stereo calibration has two"
        )
    return [(str(c["name"]), str(c.get("session", c["name"]))) for c in cams]


def _stereo_sessions(root: Path, folders: list[tuple[str, str]], *, required: bool):
    """Each camera's capture session in multi-camera folder ``root`` (read without checking
    images), the two checked for one pattern set; None where ``root`` holds none and
    ``required`` is false."""
    from slscan.capture.multicam import MULTICAM_FILE, _check_same_set
    from slscan.capture.session import SESSION_FILE, load_session

    if (root / SESSION_FILE).is_file():
        raise SlscanError(
            f"{root}: a single-camera capture session; two cameras need a multi-camera folder "
            "(cam0/, cam1/ sessions; docs/stereo.md)"
        )
    found = [(root / folder / SESSION_FILE).is_file() for _, folder in folders]
    if not any(found) and not required:
        return None
    for (name, folder), ok in zip(folders, found):
        if not ok:
            raise SlscanError(
                f"{root / folder}: no {SESSION_FILE} for camera {name!r}; expected its capture session"
            )
    sessions = [load_session(root / folder, validate=False) for _, folder in folders]
    _check_same_set(
        root / MULTICAM_FILE, (folders[0][0], sessions[0]), (folders[1][0], sessions[1])
    )
    return sessions


def run_import(args: argparse.Namespace) -> int:
    """``slscan calibrate --import``: another tool's calibration to slscan's calibration file
    (camera + projector) or to a multi-camera folder's ``cameras.json`` (two cameras).
    Everything is read and checked before the one atomic write."""
    import numpy as np

    from slscan.calibrate.importers import parse_keys, read_calibration
    from slscan.calibrate.io import export_opencv_xml, save_calibration
    from slscan.capture.multicam import MULTICAM_FILE, write_cameras_json
    from slscan.capture.session import load_session

    files = list(args.import_files or [])
    fmt = args.format
    if args.import_xml is not None:
        if files:
            raise SlscanError("--import-xml: give the file with --import or --import-xml, not both")
        files, fmt = [args.import_xml], ("opencv" if fmt == "auto" else fmt)
    if args.check_session is not None and args.session is not None:
        raise SlscanError("give the session once: as SESSION or as --session")
    session_dir = args.check_session or args.session
    keys = parse_keys(args.keys) if args.keys else None
    imported = read_calibration(files, format=fmt, keys=keys, units_mm=args.units_mm)
    kind = imported.second_kind if args.second == "auto" else args.second
    if kind is None and imported.second is not None:
        raise SlscanError(
            f"{imported.where}: the file does not say whether the second device is a projector "
            "or a camera; pass --second projector or --second camera"
        )
    out: Path = args.out
    console = _console()
    if kind == "camera":
        for option, given in (
            ("--projector-size", args.projector_size),
            ("--export-xml", args.export_xml),
        ):
            if given is not None:
                raise SlscanError(
                    f"{option}: only for a camera + projector; {imported.where} holds two cameras"
                )
        if args.projector_scale != 1.0:
            raise SlscanError(
                f"--projector-scale: only for a camera + projector; {imported.where} holds two cameras"
            )
        if out.exists() and not out.is_dir():
            raise SlscanError(
                f"{out}: is a file; two cameras are written to a multi-camera folder's {MULTICAM_FILE}"
            )
        if (out / MULTICAM_FILE).exists() and not args.overwrite:
            raise SlscanError(f"{out / MULTICAM_FILE}: exists (pass --overwrite to replace it)")
        folders = (
            (_camera_folders(session_dir) if session_dir is not None else None)
            or (_camera_folders(out) if out.is_dir() else None)
            or [("cam0", "cam0"), ("cam1", "cam1")]
        )
        sessions = None
        if session_dir is not None:
            sessions = _stereo_sessions(session_dir, folders, required=True)
        elif out.is_dir():
            sessions = _stereo_sessions(out, folders, required=False)
        entries = imported.to_cameras(
            sizes=_sizes(args.camera_size, "--camera-size", 2),
            sessions=sessions,
            names=[n for n, _ in folders],
            folders=[f for _, f in folders],
        )
        out.mkdir(parents=True, exist_ok=True)
        write_cameras_json(
            out,
            entries,
            calibration_source=f"imported from {imported.where} ({imported.format}, {imported.layout})",
        )
        baseline = float(np.linalg.norm(entries[1].rig_from_camera[:3, 3]))
        console.print(
            f"[green]wrote[/] {out / MULTICAM_FILE}: {imported.layout} from {imported.where}, "
            f"cameras {entries[0].name} and {entries[1].name}, baseline {baseline:.1f} mm",
            highlight=False,
        )
        return 0
    if out.is_dir():
        raise SlscanError(f"{out}: is a folder; expected a calibration file such as rig.json")
    if out.exists() and not args.overwrite:
        raise SlscanError(f"{out}: exists (pass --overwrite to replace it)")
    session = None if session_dir is None else load_session(session_dir, validate=False)
    camera_size = _sizes(args.camera_size, "--camera-size", 1)[0]
    projector_size = _sizes(args.projector_size, "--projector-size", 1)[0]
    cal = imported.to_calibration(
        camera_size=camera_size,
        projector_size=projector_size,
        projector_scale=args.projector_scale,
        session=session,
    )
    save_calibration(cal, out)
    baseline = float(np.linalg.norm(cal.projector.center))
    console.print(
        f"[green]wrote[/] {out}: {imported.layout} from {imported.where}, camera "
        f"{cal.camera.width}x{cal.camera.height}, projector {cal.projector_size[0]}x"
        f"{cal.projector_size[1]}, baseline {baseline:.1f} mm",
        highlight=False,
    )
    if args.export_xml is not None:
        export_opencv_xml(cal, args.export_xml)
        console.print(f"[green]wrote[/] {args.export_xml}")
    return 0
