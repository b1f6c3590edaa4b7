"""The upright object frame: recovered from turntable poses with a known axis and base."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slscan.register.frame import object_frame, rotation_axis_angle, sample_points, turntable_axis
from slscan.register.rangescan import STANFORD_UP, load_range_scan, scan_from_mesh, write_range_scan
from slscan.rig import rotation_about_axis

TILT = math.radians(20)  # the camera looks down at the turntable, 20 degrees
DISTANCE = 1300.0


def rig_from_object(angle_deg: float) -> np.ndarray:
    """Object (y down, like the virtual rig's scenes) turned about its y axis on a turntable,
    seen by a camera tilted down by TILT."""
    turn = np.eye(4)
    turn[:3, :3] = rotation_about_axis([0, 1, 0], math.radians(angle_deg))
    place = np.eye(4)
    place[:3, :3] = rotation_about_axis([1, 0, 0], -TILT)
    place[:3, 3] = [0.0, 0.0, DISTANCE]
    return place @ turn


def object_points() -> np.ndarray:
    """A box 100 mm wide, 300 mm tall (y down: its base at y = +150), off the axis by 20 mm."""
    rng = np.random.default_rng(1)
    return rng.uniform([-50, -150, -40], [50, 150, 40], (4000, 3)) + [20.0, 0.0, 0.0]


def poses_in(reference: str, angles: list[float]) -> dict[str, np.ndarray]:
    """reference_from_scan for each view: the object frame, or view 0's camera frame."""
    object_from_rig = {f"v{i}": np.linalg.inv(rig_from_object(a)) for i, a in enumerate(angles)}
    if reference == "object":
        return object_from_rig
    ref = np.linalg.inv(object_from_rig["v0"])
    return {k: ref @ v for k, v in object_from_rig.items()}


def to_frame(frame, reference: str, points_object: np.ndarray) -> np.ndarray:
    """Object-scene points → the upright frame, through the reference frame."""
    if reference == "object":
        ref_from_object = np.eye(4)
    else:
        ref_from_object = rig_from_object(0.0)
    m = frame.object_from_reference @ ref_from_object
    return points_object @ m[:3, :3].T + m[:3, 3]


@pytest.mark.parametrize("reference", ["object", "camera"])
@pytest.mark.parametrize("angles", [[0, 45, 90, 135, 180, 225, 270, 315], [0, 30], [0, 40, 200]])
def test_turntable_frame_is_upright_on_its_axis_at_the_base(reference, angles):
    poses = poses_in(reference, angles)
    pts = object_points()
    ref_from_object = np.eye(4) if reference == "object" else rig_from_object(0.0)
    pts_ref = pts @ ref_from_object[:3, :3].T + ref_from_object[:3, 3]
    frame = object_frame(poses, pts_ref)
    assert frame.up_from == "turntable"
    assert set(frame.turntable_views) == set(poses)
    assert frame.tilt_deg <= 20.01  # the cameras look down 20 degrees; around a full turn, 0
    up = to_frame(frame, reference, np.array([[0.0, -1.0, 0.0]])) - to_frame(frame, reference, np.zeros((1, 3)))
    np.testing.assert_allclose(up[0], [0, 1, 0], atol=1e-9)  # the object's y-down axis points down
    origin = to_frame(frame, reference, np.array([[0.0, 150.0, 0.0]]))[0]
    np.testing.assert_allclose(origin, [0, 0, 0], atol=0.5)  # on the axis, at the base
    # +Z faces view v0's camera: its centre has no x and a positive z
    cam = frame.object_from_reference @ poses["v0"] @ [0, 0, 0, 1]
    assert abs(cam[0]) < 1e-6 and cam[2] > 0


def test_the_frame_is_the_same_from_either_reference():
    angles = [0, 45, 90, 135, 180, 225, 270, 315]
    pts = object_points()
    a = object_frame(poses_in("object", angles), pts)
    cam = rig_from_object(0.0)
    b = object_frame(poses_in("camera", angles), pts @ cam[:3, :3].T + cam[:3, 3])
    np.testing.assert_allclose(to_frame(a, "object", pts), to_frame(b, "camera", pts), atol=1e-6)


def test_without_a_turntable_up_is_the_cameras_up():
    rng = np.random.default_rng(3)
    poses = {}
    for i in range(5):  # a free hand: small random tilts, cameras upright on average
        m = np.eye(4)
        axis = rng.normal(size=3)
        m[:3, :3] = rotation_about_axis(axis, math.radians(rng.uniform(15, 25)))
        m[:3, 3] = rng.normal(scale=50, size=3)
        poses[f"v{i}"] = m
    frame = object_frame(poses, object_points())
    assert frame.up_from == "cameras"
    ups = np.array([frame.object_from_reference[:3, :3] @ p[:3, :3] @ [0, -1, 0] for p in poses.values()])
    assert ups.mean(axis=0) @ [0, 1, 0] > 0.9


def test_one_view_stands_upright_on_its_lowest_point():
    pts = object_points()
    frame = object_frame({"v0": np.eye(4)}, pts)  # camera frame, y down
    out = pts @ frame.object_from_reference[:3, :3].T + frame.object_from_reference[:3, 3]
    assert frame.up_from == "cameras"
    np.testing.assert_allclose(frame.object_from_reference[:3, :3] @ [0, -1, 0], [0, 1, 0], atol=1e-12)
    assert np.percentile(out[:, 1], 0.1) == pytest.approx(0.0, abs=1e-9)
    assert out[:, 0].min() == pytest.approx(-out[:, 0].max(), abs=1e-6)


def test_stanford_scans_use_their_own_up():
    pts = object_points() * [1, -1, 1]  # y up
    frame = object_frame({"v0": np.eye(4)}, pts, camera_up={"v0": STANFORD_UP})
    np.testing.assert_allclose(frame.object_from_reference[:3, :3] @ [0, 1, 0], [0, 1, 0], atol=1e-12)


def test_rotation_axis_angle_round_trips_including_half_turns():
    for axis, angle in [([0, 1, 0], 0.3), ([1, 2, 3], math.pi), ([1, 0, 0], 2.0)]:
        found, theta = rotation_axis_angle(rotation_about_axis(axis, angle))
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        assert theta == pytest.approx(angle)
        assert abs(found @ a) == pytest.approx(1.0)


def test_turntable_axis_refuses_mixed_motions():
    poses = {"a": np.eye(4), "b": np.eye(4), "c": np.eye(4)}
    poses["b"][:3, :3] = rotation_about_axis([0, 1, 0], 0.5)
    poses["c"][:3, :3] = rotation_about_axis([1, 0, 0], 0.5)
    assert turntable_axis(poses) is None


def test_up_direction_survives_a_ply_round_trip(tmp_path):
    v = np.array([[0, 0, 100.0], [10, 0, 100], [0, 10, 100]])
    scan = scan_from_mesh(v, np.array([[0, 1, 2]]), view_direction=np.array([0, 0, -1.0]), name="s",
                          up_direction=np.array(STANFORD_UP))
    back = load_range_scan(write_range_scan(scan, tmp_path / "s.ply"))
    np.testing.assert_allclose(back.up_direction, STANFORD_UP)
    pts = sample_points([back], {"s": np.eye(4)}, count=10)
    assert pts.shape == (3, 3)
