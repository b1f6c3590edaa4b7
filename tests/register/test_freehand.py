"""Free-hand registration (no poses at all): a small figurine set is registered within
tolerance, a view of something else is left out and named, a set that cannot be joined is
an error with nothing written, and an aligned set grows with new views (``--into``)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

from slscan.cli import main
from slscan.errors import SlscanError
from slscan.recipe.stages import RegisterConfig, StageContext, _run_register
from slscan.register.command import load_scans
from slscan.register.multiview import RegistrationWarning, check_loops, register_scans
from slscan.register.pairwise import PairwiseResult, free_space_violation, pose_error, rigid_transform
from slscan.register.rangescan import raycasting_scene, render_range_scan, write_range_scan
from slscan.virtual.scenes import builtin_object

PIXELS = 96  # a 96 x 96 range image per view: ~3,000 samples, ~4 mm apart
ROT_DEG, MM = 1.0, 2.0  # tolerance against the truth (mm at each view's centroid)


@pytest.fixture(scope="module")
def figurine():
    """The built-in figurine seen from 8 sides, 45 degrees apart (a turntable's views, but
    registered without their poses): scans and true world_from_scan poses."""
    scene = builtin_object(detail=0.5)
    v = np.asarray(scene.vertices, float)
    v = v - (v.min(axis=0) + v.max(axis=0)) / 2
    mesh = raycasting_scene(v, np.asarray(scene.triangles))
    scans, truth = [], {}
    for k in range(8):
        a = 2 * np.pi * k / 8
        pose = looking_from([np.sin(a), -0.35, np.cos(a)], 700.0)
        name = f"v{k}"
        scans.append(render_range_scan(None, None, pose, shape=(PIXELS, PIXELS), focal=1.6 * PIXELS, name=name,
                                       scene=mesh, noise=0.1, rng=np.random.default_rng(k)))
        truth[name] = pose
    return scans, truth


def _patch(name: str = "patch"):
    """A flat 150 x 150 mm patch seen from 700 mm: overlaps anything, matches nothing."""
    box = o3d.geometry.TriangleMesh.create_box(150, 150, 2)
    v = np.asarray(box.vertices) + [-75.0, -75.0, -2.0]
    return render_range_scan(v, np.asarray(box.triangles), looking_from([0, 0, 1], 700.0), shape=(48, 48),
                             focal=80.0, name=name)


def _errors(poses, truth, scans, reference):
    """Pose errors (degrees, mm at the view's centroid) in the gauge of ``reference``."""
    gauge = truth[reference] @ np.linalg.inv(poses[reference])
    at = {s.name: s.vertices.mean(axis=0) for s in scans}
    return {k: pose_error(gauge @ p, truth[k], at=at[k]) for k, p in poses.items()}


def test_figurine_registers_without_poses_and_a_flat_patch_is_left_out(figurine):
    scans, truth = figurine
    with pytest.warns(RegistrationWarning, match="patch"):
        result = register_scans([*scans, _patch()])
    assert set(result.left_out) == {"patch"} and "patch" not in result.poses
    assert set(result.poses) == set(truth)
    for name, (rotation, translation) in _errors(result.poses, truth, scans, result.reference).items():
        assert rotation < ROT_DEG and translation < MM, (name, rotation, translation)


def test_loops_refute_the_wrong_side_of_a_triangle():
    turn = [rigid_transform([0, 0, a], [0, 0, 0]) for a in (0.3, 0.5)]
    edges = {(0, 1): PairwiseResult(turn[0], 0.5, 0.1), (1, 2): PairwiseResult(turn[1], 0.5, 0.1),
             (0, 2): PairwiseResult(turn[1] @ turn[0], 0.5, 0.1), (2, 3): PairwiseResult(turn[0], 0.5, 0.1),
             (1, 3): PairwiseResult(turn[0] @ turn[1], 0.5, 0.1),
             (0, 3): PairwiseResult(rigid_transform([0, np.pi, 0], [5, 0, 0]), 0.5, 0.1)}  # wrong
    centroids = {k: np.array([10.0, 0, 0]) for k in range(4)}
    confirmed, refuted = check_loops(edges, centroids, max_rotation_deg=1.0, max_distance=1.0)
    assert set(refuted) == {(0, 3)}
    assert confirmed == set(edges) - {(0, 3)}


def test_free_space_violation_sees_a_surface_in_front_of_another(figurine):
    scans, truth = figurine
    scan = scans[0]
    assert free_space_violation(scan.vertices, scan, margin=5.0, radius=4.0) == 0.0
    toward = scan.vertices * 0.9  # 10 % nearer the sensor at the origin: ~70 mm in front
    assert free_space_violation(toward, scan, margin=5.0, radius=4.0) > 0.9


def test_a_set_that_cannot_be_joined_is_an_error_and_nothing_is_written(figurine, tmp_path, capsys):
    scans, _ = figurine
    folder = tmp_path / "two"
    folder.mkdir()
    write_range_scan(scans[0], folder / "v0.ply")
    write_range_scan(_patch(), folder / "patch.ply")
    out = tmp_path / "aligned"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RegistrationWarning)
        assert main(["register", str(folder), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "joined 1 of 2 scans (patch), nothing written" in err and "v0: matches no other scan" in err
    assert not out.exists() and list(tmp_path.iterdir()) == [folder]


@pytest.fixture(scope="module")
def six_aligned(figurine, tmp_path_factory):
    """v0..v5 registered without poses by ``slscan register``; a folder holding v6, v7."""
    scans, truth = figurine
    root = tmp_path_factory.mktemp("grow")
    for k, scan in enumerate(scans):
        folder = root / ("first" if k < 6 else "more")
        folder.mkdir(exist_ok=True)
        write_range_scan(scan, folder / f"{scan.name}.ply")
    assert main(["register", str(root / "first"), "--out", str(root / "aligned"), "--quiet"]) == 0
    old, old_poses = load_scans(root / "aligned")
    assert len(old) == 6
    return root, old_poses


def _check_grown(poses, old_poses, figurine):
    scans, truth = figurine
    assert set(poses) == set(truth)
    for name, pose in old_poses.items():  # the held poses are written back as they were
        np.testing.assert_allclose(poses[name], pose, atol=1e-9, err_msg=name)
    for name, (rotation, translation) in _errors(poses, truth, scans, "v0").items():
        assert rotation < ROT_DEG and translation < MM, (name, rotation, translation)


def test_into_adds_views_to_an_aligned_set_holding_its_poses(six_aligned, figurine, capsys):
    root, old_poses = six_aligned
    grown = root / "grown"
    assert main(["register", str(root / "more"), "--into", str(root / "aligned"), "--out", str(grown),
                 "--quiet"]) == 0
    assert "added 2 of 2 new scans (v6, v7)" in capsys.readouterr().err
    _, poses = load_scans(grown)
    _check_grown(poses, old_poses, figurine)
    summary = json.loads((grown / "registration.json").read_text())
    assert summary["held"] == sorted(old_poses) and summary["left_out"] == {}
    with pytest.raises(SlscanError, match="already holds scans v0"):
        from slscan.register.command import load_into

        load_into(root / "aligned", [figurine[0][0]])


def test_the_recipe_grows_a_set_with_register_into(six_aligned, figurine, tmp_path):
    root, old_poses = six_aligned
    config = RegisterConfig(source=str(root / "more"), use_poses=False, into=str(root / "aligned"))
    summary = _run_register(StageContext(out=tmp_path / "aligned", inputs={}), config)
    assert summary["aligned"] == 8 and summary["added"] == 2 and summary["left_out"] == 0
    _, poses = load_scans(tmp_path / "aligned")
    _check_grown(poses, old_poses, figurine)
