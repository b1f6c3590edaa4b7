"""Calibration boards: corner layout, printed images, sizes and their errors."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.calibrate.target import Board, parse_board_size
from slscan.errors import SlscanError


@pytest.mark.parametrize("kind", ["chessboard", "charuco"])
def test_corners_are_row_major_one_square_in(kind):
    board = Board(kind=kind, columns=5, rows=4, square=30.0)
    pts = board.object_points()
    assert pts.shape == (20, 3)
    np.testing.assert_allclose(pts[0], [30, 30, 0])
    np.testing.assert_allclose(pts[1], [60, 30, 0])
    np.testing.assert_allclose(pts[5], [30, 60, 0])
    np.testing.assert_allclose(board.object_points([19]), [[150, 120, 0]])
    assert board.size == (180.0, 150.0)
    if kind == "charuco":  # OpenCV numbers ChArUco corners the same way
        np.testing.assert_allclose(board.aruco_board().getChessboardCorners(), pts)


@pytest.mark.parametrize("kind", ["chessboard", "charuco"])
def test_printed_board_has_the_squares_where_the_frame_says(kind):
    board = Board(kind=kind, columns=5, rows=4, square=30.0)
    image = board.image(20, margin_px=10)
    assert image.shape == (5 * 20 + 20, 6 * 20 + 20)
    assert image[15, 15] == 0  # the top-left square is black
    assert image[11, 31] == 255  # its right neighbour is white (outside a ChArUco marker)
    assert image[5, 5] == 255  # margin


def test_board_errors_name_the_problem():
    with pytest.raises(SlscanError, match="unknown board kind"):
        Board(kind="circles")
    with pytest.raises(SlscanError, match="at least 2 x 2"):
        Board(columns=1, rows=5)
    with pytest.raises(SlscanError, match="has 50 markers"):
        Board(kind="charuco", columns=15, rows=10, dictionary="DICT_4X4_50")
    with pytest.raises(SlscanError, match="unknown ArUco dictionary"):
        Board(kind="charuco", dictionary="DICT_9X9")
    assert parse_board_size("9x7") == (9, 7)
    with pytest.raises(SlscanError, match="COLUMNSxROWS"):
        parse_board_size("9 by 7")
    assert Board.from_dict(Board(kind="charuco").to_dict()) == Board(kind="charuco")
