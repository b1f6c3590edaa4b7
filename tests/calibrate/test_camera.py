"""Camera calibration: corners found in images, Zhang's method recovering a known camera."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest

from slscan.calibrate.camera import calibrate_camera, detect_corners
from slscan.calibrate.target import Board, CornerDetection
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, default_rig
from slscan.virtual.boards import board_poses, board_scene, default_edge_sigma

CAMERA = PinholeModel(1440, 960, 1850.0, 1852.0, 725.0, 470.0, (-0.08, 0.05, 0.001, -0.0005, 0.0))
BOARD = Board(columns=9, rows=7, square=50.0)


def synthetic_views(n=6, noise=0.05, seed=0):
    """Corners of BOARD seen by CAMERA at the virtual rig's calibration poses, with noise (px)."""
    rng = np.random.default_rng(seed)
    rig = default_rig()
    views = []
    for k, pose in enumerate(board_poses(rig, BOARD, n)):
        local = BOARD.object_points() @ pose[:3, :3].T + pose[:3, 3]
        corners = CAMERA.project_local(local) + noise * rng.standard_normal((BOARD.n_corners, 2))
        views.append(CornerDetection(f"view_{k}/white.png", corners, np.arange(BOARD.n_corners)))
    return views


def test_zhang_recovers_a_known_camera():
    exact = calibrate_camera(synthetic_views(noise=0.0), BOARD, (1440, 960))
    np.testing.assert_allclose(exact.lens.K, CAMERA.K, atol=1e-3)
    np.testing.assert_allclose(exact.lens.dist, CAMERA.dist, atol=1e-5)
    # 0.05 px of noise on 8 views: the principal point's spread is about 1.2 px
    cal = calibrate_camera(synthetic_views(8), BOARD, (1440, 960))
    assert abs(cal.lens.fx / CAMERA.fx - 1) < 1e-3 and abs(cal.lens.fy / CAMERA.fy - 1) < 1e-3
    assert abs(cal.lens.cx - CAMERA.cx) < 3 and abs(cal.lens.cy - CAMERA.cy) < 3
    assert 0.03 < cal.rms < 0.08 and cal.view_errors.shape == (8,)
    assert len(cal.views) == 8 and not cal.rejected
    # the board poses are the true ones
    rig = default_rig()
    np.testing.assert_allclose(
        cal.camera_from_board[:, :3, 3], np.stack(board_poses(rig, BOARD, 8))[:, :3, 3], atol=2.0
    )


def test_bad_views_are_rejected_with_a_warning_naming_the_file(caplog):
    views = synthetic_views(7)
    views[2] = CornerDetection(
        views[2].source,
        views[2].corners + np.random.default_rng(1).normal(0, 3, (63, 2)),
        views[2].ids,
    )
    views[4] = CornerDetection.failed("view_4/white.png", "9x7 chessboard not found")
    with caplog.at_level(logging.WARNING):
        cal = calibrate_camera(views, BOARD, (1440, 960))
    assert [name for name, _ in cal.rejected] == ["view_4/white.png", "view_2/white.png"]
    assert "outlier" in cal.rejected[1][1]
    assert "view_2/white.png" in caplog.text and "view_4/white.png" in caplog.text
    assert cal.rms < 0.1


def test_too_few_views_is_an_error():
    views = synthetic_views(3)
    views[0] = CornerDetection.failed("a.png", "9x7 chessboard not found")
    with pytest.raises(SlscanError, match="at least 3 views.*a.png: 9x7 chessboard not found"):
        calibrate_camera(views, BOARD, (1440, 960))


@pytest.mark.parametrize("kind", ["chessboard", "charuco"])
def test_corners_are_found_to_a_tenth_of_a_pixel_in_a_warped_print(kind):
    board = Board(kind=kind, columns=7, rows=5, square=30.0)
    ppsq, margin = 60, 40
    printed = board.image(ppsq, margin).astype(np.float32)
    printed = cv2.GaussianBlur(printed, (0, 0), 1.0)  # about 1 px after the warp
    # board mm -> printed px -> camera px
    mm_to_print = np.array([[ppsq / 30.0, 0, margin], [0, ppsq / 30.0, margin], [0, 0, 1]])
    mm_to_cam = np.array([[2.2, 0.35, 120.0], [-0.2, 2.0, 90.0], [2e-4, 1e-4, 1.0]])
    hom = mm_to_cam @ np.linalg.inv(mm_to_print)
    shift = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]])  # pixel centres at integers
    warp = hom @ shift
    image = cv2.warpPerspective(printed, warp, (720, 560), flags=cv2.INTER_AREA, borderValue=255)
    image = np.clip(40 + image * 0.7, 0, 255).astype(np.uint8)
    det = detect_corners(image, board, source="print.png")
    assert det and len(det.ids) == board.n_corners
    truth = cv2.perspectiveTransform(board.object_points(det.ids)[:, None, :2], mm_to_cam).reshape(
        -1, 2
    )
    err = np.linalg.norm(det.corners - truth, axis=1)
    err = np.minimum(
        err, np.linalg.norm(det.corners[::-1] - truth, axis=1)
    )  # 180 deg symmetric board
    assert np.sqrt(np.mean(err**2)) < 0.1, err
    nothing = detect_corners(np.full((100, 100), 128, np.uint8), board, source="grey.png")
    assert not nothing and "not found" in nothing.reason


def test_charuco_board_on_the_virtual_rig_gives_the_camera():
    """White images of a ChArUco board rendered by the virtual rig, at reduced size."""
    from slscan.patterns import flat
    from slscan.virtual.render import Optics, shade_pattern, trace_view
    from slscan.virtual.sensor import Sensor

    rig = default_rig(scale=0.5, projector_scale=0.5)
    board = Board(kind="charuco", columns=9, rows=7, square=50.0)
    scene = board_scene(board, edge_sigma=default_edge_sigma(rig))
    white = flat.generate(rig.projector.lens.width, rig.projector.lens.height)[0]
    views = []
    for k, pose in enumerate(board_poses(rig, board, 5)):
        radiance = shade_pattern(trace_view(scene, rig, pose), white, Optics())
        image = Sensor().expose(radiance, np.random.default_rng(k))
        views.append(detect_corners(image, board, source=f"view_{k}"))
    assert all(len(v.ids) > 50 for v in views)
    cal = calibrate_camera(views, board, (rig.camera.width, rig.camera.height))
    assert abs(cal.lens.fx / rig.camera.fx - 1) < 0.01
    assert abs(cal.lens.cx - rig.camera.cx) < 3 and abs(cal.lens.cy - rig.camera.cy) < 3
    assert cal.rms < 0.15
