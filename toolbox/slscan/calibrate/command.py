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
--import-xml converts a procam-calibration (OpenCV XML) result instead of calibrating.
"""

EPILOG = """\
examples:
  slscan calibrate board-session --out rig.json --board 9x7 --square 50
  slscan calibrate kamino --out rig.json --square 75 --method inverse-camera --export-xml rig.xml
  slscan calibrate kamino --out ref.json --import-xml calibration_result.xml
"""


def add_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``calibrate`` to the ``slscan`` subcommands; return its parser."""
    from slscan.calibrate.options import (
        BOARD_KINDS,
        CORRESPONDENCES,
        DEFAULT_DICTIONARY,
        DISTORTION_MODELS,
        METHODS,
        PLANE_PATTERNS,
    )
    from slscan.viewer.recording import add_recording_arguments

    p = subparsers.add_parser(
        "calibrate",
        help="calibrate camera and projector from views of a printed board",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="capture-session folder: the board in several poses")
    p.add_argument("--out", required=True, type=Path, help="calibration file to write (JSON)")
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
        help="side of a printed square, mm (required unless --import-xml); sets the scale",
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
        help="features whose light planes are measured (default auto: hybrid lines if captured)",
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
        help="local homographies from Gray-code stripe edges (default) or decoded pixels",
    )
    method.add_argument(
        "--window",
        type=int,
        default=0,
        metavar="PX",
        help="half-size of the local-homography windows, camera px (default: 0.3 squares)",
    )
    xml = p.add_argument_group("OpenCV XML (kamino410/procam-calibration)")
    xml.add_argument(
        "--import-xml",
        type=Path,
        default=None,
        metavar="FILE",
        help="convert this XML calibration instead of calibrating (SESSION gives the sizes)",
    )
    xml.add_argument(
        "--xml-units-mm",
        type=float,
        default=1.0,
        metavar="F",
        help="--import-xml: mm per unit of its translation (default 1)",
    )
    xml.add_argument(
        "--xml-projector-scale",
        type=float,
        default=1.0,
        metavar="F",
        help="--import-xml: pattern pixels per projector pixel of the file (0.5 for "
        "graycode_step 2; default 1)",
    )
    xml.add_argument(
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
    from slscan.calibrate.io import export_opencv_xml, import_opencv_xml, save_calibration
    from slscan.calibrate.pipeline import CalibrationConfig, calibrate_session, calibration_steps
    from slscan.calibrate.target import Board, parse_board_size
    from slscan.capture.session import load_session
    from slscan.viewer.log_calibrate import calibrate_blueprint
    from slscan.viewer.recording import recording_from_args

    out: Path = args.out
    if out.exists() and not args.overwrite:
        raise SlscanError(f"{out}: exists (pass --overwrite to replace it)")
    if out.is_dir():
        raise SlscanError(f"{out}: is a folder; expected a calibration file such as rig.json")
    session = load_session(args.session)
    console = _console()
    if args.import_xml is not None:
        cal = import_opencv_xml(
            args.import_xml,
            projector_size=session.projector_size,
            units_mm=args.xml_units_mm,
            projector_scale=args.xml_projector_scale,
        )
        if (cal.camera.width, cal.camera.height) != session.camera_size:
            raise SlscanError(
                f"{args.import_xml}: calibration is for a {cal.camera.width}x{cal.camera.height} camera, "
                f"the session's is {session.camera_size[0]}x{session.camera_size[1]}"
            )
        save_calibration(cal, out)
        console.print(f"[green]wrote[/] {out}: imported from {args.import_xml}")
    else:
        if args.square is None:
            raise SlscanError(
                "--square: give the side of a printed square in mm (it sets the scale)"
            )
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
