"""Local homographies around board corners: decoded projector pixels to a sub-pixel corner."""

from __future__ import annotations

import cv2
import numpy as np

from slscan.calibrate.procam import projector_corners


def test_local_homographies_map_corners_into_the_projector():
    # camera -> projector is a homography on a plane; the Gray code rounds to whole pixels
    hom = np.array([[0.61, 0.04, 30.0], [-0.03, 0.58, 12.0], [1e-5, -2e-5, 1.0]])
    h, w = 300, 400
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    uv = cv2.perspectiveTransform(np.stack([xs, ys], -1).reshape(-1, 1, 2), hom).reshape(h, w, 2)
    column, row = np.rint(uv[..., 0]).astype(int), np.rint(uv[..., 1]).astype(int)
    valid = np.ones((h, w), bool)
    valid[::7, ::5] = False  # some pixels do not decode
    column[150, 200], row[150, 200] = 900, 900  # a decoding error: an outlier
    corners = np.array([[200.3, 150.7], [100.25, 80.5], [320.9, 220.1], [5.0, 5.0]])
    pc = projector_corners(column, row, valid, corners, half_window=12)
    truth = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), hom).reshape(-1, 2)
    assert pc.ok[:3].all()
    # the rounding's moire biases the corner by up to a few tenths of a projector pixel
    assert np.abs(pc.points[:3] - truth[:3]).max() < 0.3
    assert (pc.support[:3] > 300).all() and (pc.residual[:3] < 0.5).all()
    assert pc.support[3] < 625  # the window is cut by the image border
    assert bool(pc) is False  # fewer than 6 corners mapped
