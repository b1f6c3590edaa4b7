"""Local homographies around board corners: decoded projector pixels to a sub-pixel corner."""

from __future__ import annotations

import cv2
import numpy as np

from slscan.calibrate.procam import projector_corners, projector_corners_from_edges
from slscan.decode.family import ProjectorConstraints


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


def test_every_pixel_a_constraint_maps_corners_to_thousandths_of_a_pixel():
    """Phase shifting's constraints: every decoded pixel once with its sub-pixel column and
    once with its row (0.02 px of noise), the dark quadrants of a chessboard corner not
    decoded, a few wrong fringe orders; no RANSAC, the least-squares fit and one round of
    outlier rejection recover the corner to a few thousandths of a projector pixel."""
    rng = np.random.default_rng(0)
    hom = np.array([[0.61, 0.04, 30.0], [-0.03, 0.58, 12.0], [1e-5, -2e-5, 1.0]])
    h, w = 300, 400
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    uv = cv2.perspectiveTransform(np.stack([xs, ys], -1).reshape(-1, 1, 2), hom).reshape(h, w, 2)
    corners = np.array([[200.3, 150.7], [100.25, 80.5], [320.9, 220.1], [5.0, 5.0]])
    dark = np.zeros((h, w), bool)
    for cx, cy in corners:  # two opposite quadrants around each corner
        dark |= ((xs < cx) == (ys < cy)) & (np.abs(xs - cx) < 20) & (np.abs(ys - cy) < 20)
    py, px = np.nonzero(~dark)
    n = len(px)
    value = np.concatenate([uv[py, px, 0], uv[py, px, 1]]) + 0.02 * rng.standard_normal(2 * n)
    wrong = rng.random(2 * n) < 0.01
    value[wrong] += rng.choice([-8.0, 8.0], int(wrong.sum()))  # a fringe order off by a period
    constraints = ProjectorConstraints(
        np.concatenate([px, px]).astype(float), np.concatenate([py, py]).astype(float), value,
        np.concatenate([np.zeros(n, bool), np.ones(n, bool)]),
    )
    pc = projector_corners_from_edges(constraints, corners, half_window=12)
    truth = cv2.perspectiveTransform(corners.reshape(-1, 1, 2), hom).reshape(-1, 2)
    assert pc.ok.all()
    assert np.abs(pc.points[:3] - truth[:3]).max() < 0.005
    assert (pc.residual[:3] < 0.03).all()  # the noise, outliers dropped
    for k, (cx, cy) in enumerate(corners[:3]):
        inside = (np.abs(constraints.x - cx) <= 12) & (np.abs(constraints.y - cy) <= 12)
        # every wrong order dropped, and hardly any right one
        assert 0.97 * inside.sum() <= pc.support[k] <= (inside & ~wrong).sum()
    assert pc.support[3] < pc.support[0] / 2  # the window is cut by the image border
