"""Tests for ray-plane triangulation: exact synthetic answers and the virtual tile."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from slscan.capture.session import LIT
from slscan.decode.graycode import decode_gray
from slscan.decode.samples import StripeSamples
from slscan.decode.triangulate import RigPlanes, intersect_rays_planes, triangulate
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, default_rig, distort


def _rays_on_rows(camera: PinholeModel, rows: np.ndarray, xn: np.ndarray):
    """Undistorted rays (k, 3) whose distorted pixel lies exactly on integer ``rows``, and
    that pixel's x, found by root finding (independent of ``PinholeModel.rays_local``)."""
    dist = camera.dist_array
    yn = np.array(
        [
            brentq(
                lambda y, x=x, r=r: camera.fy * distort(x, y, dist)[1] + camera.cy - r,
                -1.0,
                1.0,
                xtol=1e-15,
            )
            for x, r in zip(xn, rows)
        ]
    )
    xd, _ = distort(xn, yn, dist)
    return np.stack([xn, yn, np.ones_like(xn)], axis=1), camera.fx * xd + camera.cx


def _samples(rows, x, columns) -> StripeSamples:
    k = len(rows)
    return StripeSamples(
        row=np.asarray(rows, np.int32),
        x=np.asarray(x, float),
        projector_column=np.asarray(columns, float),
        stripe=np.arange(k, dtype=np.int32),
        contrast=np.ones(k, np.float32),
        saturated=np.zeros(k, bool),
    )


class _TablePlanes:
    """Light planes looked up by (integer) projector column."""

    def __init__(self, planes: np.ndarray) -> None:
        self.table = planes

    def planes(self, projector_columns: np.ndarray) -> np.ndarray:
        return self.table[np.asarray(projector_columns).astype(int)]


def test_known_planes_recovered_exactly():
    rng = np.random.default_rng(1)
    camera = default_rig().camera  # with radial distortion
    k = 200
    rows = rng.integers(0, camera.height, k)
    rays, x = _rays_on_rows(camera, rows, rng.uniform(-0.5, 0.5, k))
    depth = rng.uniform(800, 1600, k)
    truth = rays * depth[:, None]
    normals = rng.normal(size=(k, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # keep planes well away from containing the ray
    steep = (
        np.abs(np.einsum("ij,ij->i", normals, rays / np.linalg.norm(rays, axis=1, keepdims=True)))
        > 0.2
    )
    planes = np.concatenate([normals, -np.einsum("ij,ij->i", normals, truth)[:, None]], axis=1)
    points = triangulate(_samples(rows, x, np.arange(k)), camera, _TablePlanes(planes))
    assert points.shape == (k, 3) and points.dtype == np.float64
    np.testing.assert_allclose(points[steep], truth[steep], rtol=0, atol=1e-9)


def test_rig_planes_known_answer():
    rig = default_rig()
    rng = np.random.default_rng(2)
    k = 300
    rows = rng.integers(0, rig.camera.height, k)
    rays, x = _rays_on_rows(rig.camera, rows, rng.uniform(-0.4, 0.4, k))
    truth = rays * rng.uniform(900, 1500, k)[:, None]
    u = rig.projector.project(truth)[:, 0]
    planes = RigPlanes(rig.projector)
    pl = planes.planes(u)
    np.testing.assert_allclose(np.linalg.norm(pl[:, :3], axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("ij,ij->i", pl[:, :3], truth) + pl[:, 3], 0.0, atol=1e-9)
    points = triangulate(_samples(rows, x, u), rig.camera, planes)
    np.testing.assert_allclose(points, truth, rtol=0, atol=1e-9)


def test_parallel_and_behind_give_nan():
    rays = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.1, 0.0, 1.0]])
    planes = np.array(
        [
            [1.0, 0.0, 0.0, -100.0],  # x = 100: contains the ray's direction
            [0.0, 0.0, 1.0, 500.0],  # z = -500: behind the camera
            [0.0, 0.0, 1.0, -500.0],  # z = 500
            [np.sin(0.1), 0.0, np.cos(0.1), -500.0],
        ]
    )
    points = intersect_rays_planes(rays, planes)
    assert np.isnan(points[:2]).all()
    np.testing.assert_allclose(points[2], [0, 0, 500])
    assert np.isfinite(points[3]).all()
    # a ray 0.3 degrees from its plane: below the default 0.5 degree limit
    a = np.radians(0.3)
    grazing = intersect_rays_planes(
        np.array([[np.sin(a), 0, np.cos(a)]]), np.array([[1.0, 0, 0, -10.0]])
    )
    assert np.isnan(grazing).all()
    assert np.isfinite(
        intersect_rays_planes(
            np.array([[np.sin(a), 0, np.cos(a)]]), np.array([[1.0, 0, 0, -10.0]]), min_angle_deg=0.1
        )
    ).all()


def test_errors_and_empty():
    camera = default_rig(scale=0.25).camera
    bad = _TablePlanes(np.zeros((1, 3)))
    with pytest.raises(SlscanError, match=r"expected \(1, 4\) planes"):
        triangulate(_samples([0], [1.0], [0]), camera, bad)
    assert triangulate(_samples([], [], []), camera, bad).shape == (0, 3)
    with pytest.raises(SlscanError, match="Projector"):
        RigPlanes(camera)


# --- the virtual tile ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tile(gray_tile_session):
    session = gray_tile_session
    view = session.views[0]
    edges = decode_gray(session, view).edges
    points = triangulate(
        edges, session.calibration.camera, RigPlanes(session.calibration.projector)
    )
    return session.load_ground_truth(view), edges, points


def test_tile_points_on_plane_and_truth(tile):
    truth, edges, points = tile
    vis = truth.visibility
    xa = np.floor(edges.x).astype(int)
    w = vis.shape[1]
    inner = np.ones(len(edges), bool)
    for dx in (-1, 0, 1, 2):  # both interpolation pixels and their neighbours lit
        inner &= vis[edges.row, np.clip(xa + dx, 0, w - 1)] == LIT
    assert np.isfinite(points).all()
    p = points[inner]
    assert len(p) > 5000
    centre = p.mean(axis=0)
    normal = np.linalg.svd(p - centre, full_matrices=False)[2][2]
    distance = np.abs((p - centre) @ normal)
    # At camera_scale 0.25 a camera pixel spans 2.8 mm at 1.3 m and one pixel of edge
    # error moves a point ~8 mm along its plane (20 degree triangulation angle); linear
    # interpolation of the blurred stripe edge is off by up to 0.045 px depending on the
    # edge's sub-pixel phase (RMS 0.034 px), which is 0.2 mm here (4x less at full size).
    assert distance.mean() < 0.3, distance.mean()
    true_normal = np.nanmedian(truth.normal[vis == LIT], axis=0)
    assert abs(normal @ true_normal) / np.linalg.norm(true_normal) > 0.99999
    # against ground truth, interpolated along the row at the sample
    f = (edges.x - xa)[:, None]
    gt = truth.point.astype(np.float64)
    expected = gt[edges.row, xa] * (1 - f) + gt[edges.row, np.minimum(xa + 1, w - 1)] * f
    error = np.linalg.norm(points - expected, axis=1)[inner]
    assert np.median(error) < 0.35 and np.percentile(error, 99) < 0.6


def test_samples_along_columns_use_their_subpixel_row():
    rig = default_rig(scale=0.25)
    k = 50
    rng = np.random.default_rng(4)
    x, y = rng.integers(20, 300, k).astype(float), rng.uniform(20, 200, k)
    cols = rng.uniform(50, 200, k)
    down = StripeSamples(
        row=np.floor(y + 0.5).astype(np.int32), x=x, projector_column=cols,
        stripe=np.arange(k, dtype=np.int32), contrast=np.ones(k, np.float32),
        saturated=np.zeros(k, bool), y=y, along_columns=np.ones(k, bool),
    )
    planes = RigPlanes(rig.projector)
    got = triangulate(down, rig.camera, planes)
    rays = rig.camera.rays_local(np.stack([x, y], axis=1))
    np.testing.assert_allclose(got, intersect_rays_planes(rays, planes.planes(cols)), rtol=1e-12)
    # the rounded row would be up to half a pixel off
    assert not np.allclose(got, triangulate(_samples(down.row, x, cols), rig.camera, planes))
