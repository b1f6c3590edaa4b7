"""Pairwise registration: a known rigid motion between two synthetic range scans is recovered."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

from slscan.errors import SlscanError
from slscan.register.pairwise import (
    PairwiseConfig,
    coarse_align,
    fit_gauge,
    pose_error,
    refine_icp,
    register_pair,
    rigid_transform,
)
from slscan.register.rangescan import RangeScan, render_range_scan

RADIUS = 50.0


def bumpy_sphere(radius: float = RADIUS) -> tuple[np.ndarray, np.ndarray]:
    """A sphere with smooth bumps (no symmetry ICP could slide along), mm."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=80)
    v = np.asarray(sphere.vertices)
    bumps = (
        0.1 * np.sin(5 * v[:, 0] + 1) * np.cos(6 * v[:, 1])
        + 0.06 * np.sin(7 * v[:, 2] + 3 * v[:, 0])
        + 0.04 * np.cos(9 * v[:, 1] * v[:, 2])
    )
    return v * radius * (1 + bumps)[:, None], np.asarray(sphere.triangles)


def two_views(noise: float, angle_deg: float = 40.0) -> tuple[RangeScan, RangeScan, np.ndarray]:
    v, f = bumpy_sphere()
    a = np.radians(angle_deg)
    pose_s = looking_from([np.sin(a / 2), 0.1, np.cos(a / 2)], 30.0)
    pose_t = looking_from([-np.sin(a / 2), -0.1, np.cos(a / 2)], -20.0)
    rng = np.random.default_rng(1)
    kw = {"shape": (110, 110), "pixel": 1.0, "noise": noise, "rng": rng}
    source = render_range_scan(v, f, pose_s, name="source", **kw)
    target = render_range_scan(v, f, pose_t, name="target", **kw)
    return source, target, np.linalg.inv(pose_t) @ pose_s


@pytest.mark.parametrize("noise", [0.0, 0.02])
def test_known_transform_recovered_from_a_rough_start(noise):
    source, target, truth = two_views(noise)
    init = rigid_transform(np.radians(6.0) * np.array([0.6, -0.64, 0.48]), [4.0, -3.0, 2.0]) @ truth
    result = register_pair(source, target, init=init)
    assert result
    assert result.reason == ""
    rotation, translation = pose_error(result.transform, truth)
    assert rotation < 0.05
    assert translation < 0.05
    assert 0.3 < result.fitness <= 1.0
    assert result.inlier_rmse < 0.05 + 2 * noise  # point-to-plane, mm
    assert result.information.shape == (6, 6)


def test_known_transform_recovered_from_features_alone():
    source, target, truth = two_views(0.0)
    coarse = coarse_align(source, target)
    assert coarse
    rotation, translation = pose_error(coarse.transform, truth)
    assert rotation < 10.0 and translation < 10.0
    result = register_pair(source, target)  # no initial pose: features, then ICP
    rotation, translation = pose_error(result.transform, truth)
    assert result and rotation < 0.05 and translation < 0.05


def test_symmetric_objective_recovers_it_too():
    source, target, truth = two_views(0.0)
    init = rigid_transform(np.radians(3.0) * np.array([0.0, 0.6, 0.8]), [1.0, 2.0, -1.0]) @ truth
    result = register_pair(source, target, init=init, config=PairwiseConfig(method="symmetric"))
    rotation, translation = pose_error(result.transform, truth)
    assert result and rotation < 0.05 and translation < 0.05


def test_scans_that_do_not_overlap_fail_with_a_reason():
    v, f = bumpy_sphere()
    front = render_range_scan(
        v, f, looking_from([0, 0, 1]), shape=(60, 60), pixel=1.0, name="front"
    )
    back = render_range_scan(v, f, looking_from([0, 0, -1]), shape=(60, 60), pixel=1.0, name="back")
    far = np.eye(4)
    far[:3, 3] = [0.0, 0.0, 500.0]
    result = refine_icp(front, back, far)
    assert not result
    assert "front" in result.reason and "back" in result.reason
    assert result.transform.shape == (4, 4)


def test_bad_options_raise():
    source, target, truth = two_views(0.0)
    with pytest.raises(SlscanError, match="ICP method"):
        register_pair(source, target, init=truth, config=PairwiseConfig(method="nope"))
    with pytest.raises(SlscanError, match="4x4"):
        refine_icp(source, target, np.eye(3))


def test_pose_error_measures_at_a_point():
    truth = np.eye(4)
    estimate = rigid_transform([0.0, 0.0, np.radians(1.0)], [0.0, 0.0, 0.0])
    rotation, at_origin = pose_error(estimate, truth)
    _, at_point = pose_error(estimate, truth, at=[100.0, 0.0, 0.0])
    assert rotation == pytest.approx(1.0)
    assert at_origin == pytest.approx(0.0)
    assert at_point == pytest.approx(100.0 * np.radians(1.0), rel=1e-3)


def test_fit_gauge_recovers_a_global_motion_exactly():
    rng = np.random.default_rng(3)
    truth = {f"s{k}": rigid_transform(rng.normal(size=3), rng.normal(size=3) * 50) for k in range(4)}
    points = {n: rng.normal(size=(200, 3)) * 30 for n in truth}
    motion = rigid_transform([0.2, -0.1, 0.3], [5.0, -7.0, 2.0])
    moved = {n: np.linalg.inv(motion) @ p for n, p in truth.items()}  # same scans, other gauge
    gauge = fit_gauge(moved, truth, points)
    np.testing.assert_allclose(gauge, motion, atol=1e-9)
    for name, pose in truth.items():
        assert pose_error(gauge @ moved[name], pose) == pytest.approx((0.0, 0.0), abs=1e-6)
    with pytest.raises(SlscanError, match="no scan"):
        fit_gauge(moved, {}, points)
