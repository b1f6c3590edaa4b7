"""``slscan stage`` (drive a serial turntable by hand while setting up) and
``slscan turntable-axis`` (fit its rotation axis from a board captured on it)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from slscan.errors import SlscanError
from slscan.progress import console as _console

STAGE_EPILOG = """\
examples:
  slscan stage serial:/dev/ttyUSB0 --home
  slscan stage serial:/dev/ttyUSB0 --rotate 30
  slscan stage serial:/dev/ttyACM0:marlin:250000 --stage-axis A --rotate -15 --zero
"""

AXIS_DESCRIPTION = """\
Fit the turntable's rotation axis from a calibration board standing on it, captured at
several turntable angles (slscan scan --board ... --stage serial:PORT --stage-sweep 80
--stage-start -40). The board's pose is found in each view's white frame with the camera
of --calibration (or the session's own), and the one axis about which every view turned
from the first is fitted. Give the result to slscan scan --turntable-axis, and each view
records its pose, so registration starts from the turntable's poses.
"""

AXIS_EPILOG = """\
examples:
  slscan scan --camera virtual --board 9x7 --square 25 --stage-sweep 80 --stage-start -40 --views 5 --out axis-board
  slscan turntable-axis axis-board --board 9x7 --square 25 --out turntable.json
"""


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Add ``stage`` and ``turntable-axis`` to the ``slscan`` subcommands."""
    from slscan.capture.command import add_stage_arguments

    p = subparsers.add_parser(
        "stage", help="drive a serial turntable by hand (home, turn to an angle, set zero)",
        description="Drive a G-code turntable (GRBL or Marlin through pyserial) while setting up the rig: "
                    "home it, turn it to an absolute angle, take the current angle as zero. The steps run "
                    "in that order.",
        epilog=STAGE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("spec", metavar="SPEC", help="serial:PORT[:grbl|marlin][:BAUD], e.g. serial:/dev/ttyUSB0")
    p.add_argument("--home", action="store_true", help="home the turntable on its switch ($H / G28)")
    p.add_argument("--rotate", type=float, default=None, metavar="DEG",
                   help="turn to this absolute angle, degrees, and wait until it stands still")
    p.add_argument("--zero", action="store_true", help="take the current angle as 0 degrees (G92)")
    add_stage_arguments(p)
    p.set_defaults(func=run_stage)

    p = subparsers.add_parser(
        "turntable-axis", help="fit the turntable's rotation axis from a board captured on it",
        description=AXIS_DESCRIPTION, epilog=AXIS_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("session", type=Path, help="capture session of the board at several turntable angles")
    p.add_argument("--out", type=Path, required=True, help="turntable axis file to write (JSON)")
    p.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x7")
    p.add_argument("--square", type=float, required=True, help="board square side, mm")
    p.add_argument("--target", choices=("chessboard", "charuco"), default="chessboard", help="board kind")
    p.add_argument("--calibration", type=Path, default=None, metavar="CALIB.json",
                   help="the camera's calibration (slscan calibrate); default: the one the session records")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.set_defaults(func=run_turntable_axis)


def run_stage(args: argparse.Namespace) -> int:
    """``slscan stage``: home / rotate / zero, then report the angle."""
    from slscan.capture.command import open_stage

    if not (args.home or args.zero or args.rotate is not None):
        raise SlscanError("slscan stage: say what to do: --home, --rotate DEG and/or --zero")
    if args.rotate is not None and not math.isfinite(args.rotate):
        raise SlscanError(f"--rotate must be a number of degrees, got {args.rotate}")
    args.stage, args.stage_home = args.spec, args.home or args.stage_home
    console = _console()
    with open_stage(args) as table:
        if table.angle_deg == 0.0:
            console.print(f"[green]homed[/] {table.name}", highlight=False)
        if args.rotate is not None:
            table.rotate_to(args.rotate)
            console.print(f"[green]turned[/] {table.name} to {args.rotate:g} degrees", highlight=False)
        if args.zero:
            table.set_zero()
            console.print(f"[green]zero[/] {table.name}: this angle is now 0 degrees", highlight=False)
    return 0


def run_turntable_axis(args: argparse.Namespace) -> int:
    """``slscan turntable-axis``: board poses per view → the fitted axis, written to --out."""
    from rich.table import Table

    from slscan.calibrate.target import Board, parse_board_size
    from slscan.calibrate.turntable import board_poses_in_session, fit_turntable_axis, save_turntable_axis
    from slscan.capture.session import load_session

    if args.out.exists() and not args.overwrite:
        raise SlscanError(f"{args.out}: exists (pass --overwrite to replace it)")
    if not (math.isfinite(args.square) and args.square > 0):
        raise SlscanError(f"--square must be a positive length in mm, got {args.square}")
    cols, rows = parse_board_size(args.board)
    board = Board(kind=args.target, columns=cols, rows=rows, square=args.square)
    session = load_session(args.session)
    if args.calibration is not None:
        from slscan.calibrate.io import load_calibration

        lens = load_calibration(args.calibration).camera
    elif session.calibration is not None:
        lens = session.calibration.camera
    else:
        raise SlscanError(f"{args.session}: the session records no calibration: give --calibration rig.json")
    if (lens.width, lens.height) != tuple(session.camera_size):
        raise SlscanError(f"{args.calibration or args.session}: the camera is calibrated at {lens.width}x"
                          f"{lens.height}, the session's images are {session.camera_size[0]}x{session.camera_size[1]}")
    poses, angles, names = board_poses_in_session(session, board, lens)
    if len(poses) < 2:
        raise SlscanError(f"{args.session}: the board was found in {len(poses)} view(s); the axis needs two or more")
    axis = fit_turntable_axis(poses, angles, points=board.object_points())
    save_turntable_axis(axis, args.out)
    table = Table("", "value", title=f"turntable axis from {len(names)} board views ({', '.join(names)})")
    table.add_row("direction", " ".join(f"{v:+.4f}" for v in axis.direction))
    table.add_row("point, mm", " ".join(f"{v:.1f}" for v in axis.point))
    table.add_row("turned / commanded", f"{axis.scale:.4f}")
    table.add_row("angle residual, deg", f"{axis.rms_angle_deg:.3f}")
    table.add_row("corner residual, mm", f"{axis.rms_mm:.3f}")
    console = _console()
    console.print(table)
    if abs(axis.scale - 1) > 0.02:
        console.print(f"[yellow]warning[/] the table turned {axis.scale:.3f} degrees per degree commanded: "
                      "check --stage-units-per-degree (or the firmware's steps per unit)", highlight=False)
    console.print(f"[green]wrote[/] {args.out}; next: slscan scan ... --stage serial:PORT --turntable-axis {args.out}",
                  highlight=False)
    return 0
