"""The operator's tools at the rig, measured on the virtual rig against its truth.

    .venv/bin/python benchmarks/operator_tools.py [--scale 0.5]

Table 1, the preview's focus aid: the virtual tile at the working distance, the camera's
optical blur (Gaussian sigma, camera px) varied as a defocused lens would; per blur the
preview's focus value (median stripe contrast of 2 px projector stripes over the tiles,
min and max tile), the clipped share and the overlap (share of the image the projector
lights) next to the rendered truth (pixels the camera sees and the projector lights).

Table 2, the turntable axis from a board: a 9x7 chessboard (25 mm squares) standing on
the virtual turntable 60 mm in front of its axis, leaning back 10 degrees, rendered at
several angles; corners found in each white frame, the board's pose by PnP with the true
camera, the axis fitted (:func:`slscan.calibrate.turntable.fit_turntable_axis`). Errors
against the true axis (+y through (0, 0, working distance)): direction (degrees) and the
distance of the fitted line from the true one at the board's height (mm); scale
(degrees turned per degree commanded, 1 is right) and the fit's residuals.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from rich.console import Console
from rich.table import Table

from slscan.calibrate.camera import detect_corners
from slscan.calibrate.target import Board, board_pose
from slscan.calibrate.turntable import _nearer_of_flips, board_on_turntable, fit_turntable_axis
from slscan.capture.preview import measure_once
from slscan.devices.turntable import view_angles
from slscan.virtual.boards import board_scene, default_edge_sigma
from slscan.virtual.device import VirtualCaptureConfig, virtual_devices
from slscan.virtual.devices import turntable_pose
from slscan.virtual.sensor import Sensor


def focus_table(scale: float) -> Table:
    table = Table("camera blur px", "focus", "tile min", "tile max", "clipped %", "overlap %", "truth %", "s",
                  title=f"preview on the virtual tile (camera and projector scale {scale:g})")
    for blur in (0.3, 0.6, 1.0, 1.5, 2.0, 3.0):
        config = VirtualCaptureConfig(camera_scale=scale, projector_scale=scale, scene="tile",
                                      sensor=Sensor(blur_sigma=blur))
        world = virtual_devices(config)
        world.stage.move_to(0, 1)
        t = time.perf_counter()
        m = measure_once(world.projector, world.camera)
        seconds = time.perf_counter() - t
        truth = float((world.geometry.hit & world.geometry.proj_lit).mean())
        table.add_row(f"{blur:g}", f"{m.focus:.3f}", f"{np.nanmin(m.focus_tiles):.3f}",
                      f"{np.nanmax(m.focus_tiles):.3f}", f"{100 * m.clipped_share:.2f}", f"{100 * m.overlap:.2f}",
                      f"{100 * truth:.2f}", f"{seconds:.2f}")
    return table


def axis_table(scale: float) -> Table:
    board = Board(kind="chessboard", columns=9, rows=7, square=25)
    table = Table("views", "sweep deg", "found", "direction err deg", "line err mm", "scale", "rms deg", "rms mm",
                  title=f"turntable axis from a rendered board (camera scale {scale:g})")
    for views, sweep in ((3, 40), (3, 80), (5, 80), (7, 100)):
        config = VirtualCaptureConfig(camera_scale=scale, projector_scale=0.25, lit_images=False)
        rig = config.rig()
        angles = view_angles(views, sweep_deg=sweep, start_deg=-sweep / 2)
        truth = [turntable_pose(rig, a, board_on_turntable(board)) for a in angles]
        world = virtual_devices(config, scene=board_scene(board, edge_sigma=default_edge_sigma(rig)), poses=truth,
                                rig=rig)
        w, h = world.projector.resolution
        found, used = [], []
        for v, a in enumerate(angles):
            world.stage.move_to(v, views)
            world.projector.show(np.full((h, w, 3), 255, np.uint8))
            detection = detect_corners(world.camera.capture().image, board)
            if not detection:
                continue
            pose = board_pose(rig.camera, detection, board)
            found.append(pose if not found else _nearer_of_flips(pose, found[-1], board))
            used.append(a)
        axis = fit_turntable_axis(found, used, points=board.object_points())
        direction_err = math.degrees(math.acos(min(1.0, abs(float(axis.direction @ [0, 1, 0])))))
        line_err = float(np.hypot(axis.point[0], axis.point[2] - rig.working_distance))
        table.add_row(str(views), f"{sweep:g}", f"{len(found)}/{views}", f"{direction_err:.4f}", f"{line_err:.3f}",
                      f"{axis.scale:.5f}", f"{axis.rms_angle_deg:.4f}", f"{axis.rms_mm:.3f}")
    return table


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scale", type=float, default=0.5, help="camera scale (default 0.5)")
    args = p.parse_args()
    console = Console()
    console.print(focus_table(args.scale))
    console.print(axis_table(args.scale))


if __name__ == "__main__":
    main()
