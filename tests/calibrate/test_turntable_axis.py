"""The turntable axis from board poses: synthetic poses turned about a known, tilted axis
(recovered exactly, the angle scale too), and the virtual rig's turntable seen through its
camera (board corners found in rendered white frames, poses by PnP, axis within 1 mm)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slscan.calibrate.target import Board
from slscan.calibrate.turntable import (
    TurntableAxis,
    board_on_turntable,
    fit_turntable_axis,
    load_turntable_axis,
    save_turntable_axis,
)
from slscan.devices.turntable import turn_about_axis
from slscan.errors import SlscanError


def _board_start() -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = np.array([[0.96, 0.0, -0.28], [0.0, 1.0, 0.0], [0.28, 0.0, 0.96]])
    pose[:3, 3] = [-90.0, -60.0, 1180.0]
    return pose


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_a_known_tilted_axis_is_recovered(scale):
    point, direction = np.array([15.0, -40.0, 1290.0]), np.array([0.05, -0.99, 0.1])
    direction /= np.linalg.norm(direction)
    angles = [-30.0, -10.0, 10.0, 30.0, 50.0]
    start = _board_start()
    poses = [turn_about_axis(point, direction, scale * (a - angles[0])) @ start for a in angles]
    axis = fit_turntable_axis(poses, angles)
    np.testing.assert_allclose(axis.direction, direction, atol=1e-9)
    offset = axis.point - point  # any point of the same line
    np.testing.assert_allclose(offset - (offset @ direction) * direction, 0, atol=1e-6)
    assert axis.scale == pytest.approx(scale, abs=1e-9)
    assert axis.rms_angle_deg < 1e-6 and axis.rms_mm < 1e-6
    pose = axis.pose(angles[2], angles[0]) @ start
    if scale == 1.0:
        np.testing.assert_allclose(pose, poses[2], atol=1e-6)


def test_too_little_turn_is_refused():
    start = _board_start()
    with pytest.raises(SlscanError, match="less than 10 degrees"):
        fit_turntable_axis([start, turn_about_axis([0, 0, 1300], [0, 1, 0], 3) @ start], [0, 3])


def test_axis_file_round_trip_and_errors(tmp_path):
    axis = TurntableAxis(np.array([1.0, 2.0, 3.0]), np.array([0.0, 1.0, 0.0]), 1.0, 0.01, 0.2, 5, (0.0, 20.0))
    path = save_turntable_axis(axis, tmp_path / "t.json")
    back = load_turntable_axis(path)
    np.testing.assert_array_equal(back.point, axis.point)
    assert back.views == 5 and back.angles_deg == (0.0, 20.0)
    (tmp_path / "bad.json").write_text(json.dumps({"kind": "slscan-turntable-axis", "point_mm": [0, 0, 0]}))
    with pytest.raises(SlscanError, match=r"bad.json: missing key 'direction'"):
        load_turntable_axis(tmp_path / "bad.json")
    with pytest.raises(SlscanError, match="not a turntable axis file"):
        load_turntable_axis(_write(tmp_path / "x.json", {"kind": "rig"}))


def _write(path, data):
    path.write_text(json.dumps(data))
    return path


def test_virtual_turntable_axis_from_rendered_board_views():
    """The virtual rig's turntable turns about +y through (0, 0, working distance): the axis
    fitted from a board on it, seen through the rendered camera, lies within 1 mm of it."""
    from slscan.calibrate.camera import detect_corners
    from slscan.calibrate.target import board_pose
    from slscan.calibrate.turntable import _nearer_of_flips
    from slscan.virtual.boards import board_scene, default_edge_sigma
    from slscan.virtual.device import VirtualCaptureConfig, virtual_devices
    from slscan.virtual.devices import turntable_pose

    board = Board(kind="chessboard", columns=9, rows=7, square=25)
    config = VirtualCaptureConfig(camera_scale=0.5, projector_scale=0.25, lit_images=False)
    rig = config.rig()
    angles = [-40.0, -15.0, 10.0, 35.0]
    poses_true = [turntable_pose(rig, a, board_on_turntable(board)) for a in angles]
    world = virtual_devices(config, scene=board_scene(board, edge_sigma=default_edge_sigma(rig)), poses=poses_true,
                            rig=rig)
    w, h = world.projector.resolution
    found = []
    for v in range(len(angles)):
        world.stage.move_to(v, len(angles))
        world.projector.show(np.full((h, w, 3), 255, np.uint8))
        detection = detect_corners(world.camera.capture().image, board)
        assert detection, f"view {v}: board not found"
        pose = board_pose(rig.camera, detection, board)
        found.append(pose if not found else _nearer_of_flips(pose, found[-1], board))
    axis = fit_turntable_axis(found, angles, points=board.object_points())
    assert np.degrees(np.arccos(axis.direction @ [0, 1, 0])) < 0.2
    assert np.hypot(axis.point[0], axis.point[2] - rig.working_distance) < 1.0
    assert axis.scale == pytest.approx(1.0, abs=0.005)
    assert axis.rms_mm < 0.5
