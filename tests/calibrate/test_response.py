"""Calibration of an sRGB camera (``camera.response`` "srgb"): the codes are decoded in linear light."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from slscan.calibrate.procam import decode_gray_axes
from slscan.calibrate.target import Board
from slscan.decode.graycode import decode_gray
from slscan.virtual.boards import capture_calibration_session
from slscan.virtual.device import VirtualCaptureConfig

BOARD = Board(columns=9, rows=7, square=50.0)
SRGB = VirtualCaptureConfig(
    patterns="gray",
    gray_rows=True,
    lit_images=False,
    camera_scale=0.25,
    projector_scale=0.25,
    levels=6,
    effects=("tone",),
)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A board at 2 poses seen by a camera that saves sRGB-coded images."""
    session = capture_calibration_session(
        tmp_path_factory.mktemp("srgb-board") / "session", BOARD, config=SRGB, n_poses=2
    )
    assert session.response == "srgb"
    return session


def _at(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``image`` (h, w) bilinear at camera px ``(x, y)``."""
    return cv2.remap(image.astype(np.float32), x.astype(np.float32).reshape(1, -1),
                     y.astype(np.float32).reshape(1, -1), cv2.INTER_LINEAR,
                     borderValue=np.nan).reshape(-1)


def test_calibration_decodes_the_codes_as_the_decode_stage(session):
    # before: the calibration read the sRGB codes as light, and its column decode kept
    # 3-10 % more pixels and 12-32 % more edges than decode_gray's (whose thresholds
    # compare light, not codes)
    for view in session.views:
        axes, stage = decode_gray_axes(session, view), decode_gray(session, view)
        np.testing.assert_array_equal(axes.columns.mask, stage.mask)
        np.testing.assert_array_equal(axes.columns.column, stage.column)
        np.testing.assert_array_equal(axes.columns.edges.x, stage.edges.x)
        np.testing.assert_array_equal(axes.columns.edges.camera_y, stage.edges.camera_y)
        # the row edges from the transposed linear-light images sit on the true rows
        uv = session.load_ground_truth(view).projector_uv
        err = _at(uv[..., 1], axes.row_x, axes.row_y) - axes.row_value
        err = err[np.isfinite(err)]
        assert len(err) > 0.8 * len(axes.row_x) > 5000
        assert abs(np.median(err)) < 0.01 and np.median(np.abs(err)) < 0.06, np.median(np.abs(err))

