"""A user mesh placed on the virtual rig's turntable by explicit units and pose, the pose each
view records, and the rig set from a recipe or a rig file (reduced sizes)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from slscan.capture.session import load_session
from slscan.cli import main
from slscan.rig import transform_points
from slscan.virtual.devices import turntable_pose
from slscan.virtual.placement import FLIP_Y_Z, pose_from_euler
from slscan.virtual.rigs import RigParams

SMALL = ["--scale", "0.2", "--patterns", "gray", "--no-lit", "--quiet"]


def _write_box(path, size, corner) -> np.ndarray:
    """An axis-aligned box mesh (file units) with its minimum corner at ``corner``; its vertices."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(*size)
    box.translate(corner)
    o3d.io.write_triangle_mesh(str(path), box)
    return np.asarray(box.vertices, dtype=float)


def _distance_to_mesh(points: np.ndarray, pose: np.ndarray, path, mm_per_unit: float = 1.0) -> np.ndarray:
    """Distances (k,) of rig-frame ``points`` to the mesh file ``path`` as read (its own
    coordinates, times ``mm_per_unit``) moved by ``pose``."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices = transform_points(pose, mm_per_unit * np.asarray(mesh.vertices, dtype=float))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)),
                     o3d.core.Tensor(np.asarray(mesh.triangles, dtype=np.uint32)))
    return rc.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def _truth_points(session, view) -> np.ndarray:
    point = session.load_ground_truth(view).point.reshape(-1, 3)
    return point[np.isfinite(point).all(axis=1)].astype(np.float64)


def test_recorded_pose_maps_the_mesh_file_onto_the_ground_truth(tmp_path):
    # a box in metres, far from its file's origin, turned and moved by an explicit pose
    path = tmp_path / "box.ply"
    file_vertices = _write_box(path, (0.42, 0.25, 0.16), (0.5, 0.3, -0.1))
    centre_mm = 1000 * (file_vertices.min(0) + file_vertices.max(0)) / 2
    rotation = pose_from_euler(25.0, -40.0, 12.0, 0, 0, 0)[:3, :3]
    t = -rotation @ centre_mm + [15.0, -10.0, 20.0]
    pose_text = ",".join(repr(float(v)) for v in (25.0, -40.0, 12.0, *t))
    out = tmp_path / "scan"
    assert main(["capture", "--scene", str(path), "--scene-units", "m", f"--scene-pose={pose_text}",
                 "--views", "3", "--out", str(out), *SMALL]) == 0
    session = load_session(out)
    placement = pose_from_euler(25.0, -40.0, 12.0, *t)
    record = session.device["scene_placement"]
    np.testing.assert_allclose(record["turntable_from_object"], placement, atol=1e-9)
    assert record["mm_per_unit"] == 1000.0 and record["pose"] == "given"
    for k, view in enumerate(session.views):
        np.testing.assert_allclose(view.rig_from_object, turntable_pose(session.calibration, 120.0 * k) @ placement,
                                   atol=1e-9)
        truth = _truth_points(session, view)
        assert len(truth) > 500
        d = _distance_to_mesh(truth, view.rig_from_object, path, 1000.0)
        assert np.max(d) < 0.01, np.max(d)  # mm: float32 points at 1.3 m
        # the strongest predicate: the pose of another view does not fit
        other = session.views[(k + 1) % 3].rig_from_object
        assert np.median(_distance_to_mesh(truth, other, path, 1000.0)) > 5.0


def test_default_placement_turns_y_up_and_centres_the_bounding_box(tmp_path):
    path = tmp_path / "slab.obj"
    file_vertices = _write_box(path, (300.0, 200.0, 60.0), (1000.0, -50.0, 400.0))  # mm, off-centre
    out = tmp_path / "scan"
    assert main(["capture", "--scene", str(path), "--scene-units", "mm", "--views", "2", "--out", str(out),
                 *SMALL]) == 0
    session = load_session(out)
    record = session.device["scene_placement"]
    assert record["pose"] == "default" and record["mm_per_unit"] == 1.0
    wd = session.calibration.working_distance
    centre = (file_vertices.min(0) + file_vertices.max(0)) / 2
    for k, view in enumerate(session.views):
        pose = view.rig_from_object
        # the bounding box's centre on the turntable's centre, for every turn
        np.testing.assert_allclose(transform_points(pose, centre), [0, 0, wd], atol=1e-9)
        # file +y (up) is rig -y (up in the camera image), whatever the turn
        np.testing.assert_allclose(pose[:3, :3] @ [0, 1, 0], [0, -1, 0], atol=1e-12)
        # view 0: the file's +z (front) faces the camera (rig -z)
        expected = turntable_pose(session.calibration, 180.0 * k) @ FLIP_Y_Z
        expected[:3, 3] = [0, 0, wd] - expected[:3, :3] @ centre
        np.testing.assert_allclose(pose, expected, atol=1e-9)
        d = _distance_to_mesh(_truth_points(session, view), pose, path)
        assert np.max(d) < 0.01
    np.testing.assert_allclose(session.views[0].rig_from_object[:3, :3] @ [0, 0, 1], [0, 0, -1], atol=1e-12)


def test_builtin_scene_can_be_placed_too(tmp_path):
    out = tmp_path / "tile"
    assert main(["capture", "--scene", "tile", "--scene-pose", "0,30,0,0,0,200", "--out", str(out), *SMALL]) == 0
    session = load_session(out)
    expected = turntable_pose(session.calibration, 0.0) @ pose_from_euler(0, 30, 0, 0, 0, 200)
    np.testing.assert_allclose(session.views[0].rig_from_object, expected, atol=1e-12)
    truth = _truth_points(session, session.views[0])
    assert abs(np.median(truth[:, 2]) - 1500.0) < 60.0  # the tile moved 200 mm back


RECIPE = """\
[recipe]
name = "placed"
stages = ["capture"]

[capture]
scene = "{mesh}"
scene_units = "cm"
scene_pose = "{pose}"
views = 2
patterns = "gray"
lit_images = false
camera_scale = 0.25
projector_scale = 0.25

[capture.rig_params]
camera_size = [1280, 720]
projector_size = [800, 600]
working_distance = 1000.0
axes_angle_deg = 25.0
sampling_mm = 0.6
lights = 4
"""


def test_recipe_sets_the_rig_and_the_placement(tmp_path):
    mesh = tmp_path / "block.ply"
    _write_box(mesh, (40.0, 24.0, 36.0), (-20.0, -12.0, -18.0))  # cm, centred
    pose = json.dumps([[0, 0, 1, 0], [0, 1, 0, 30], [-1, 0, 0, 0], [0, 0, 0, 1]])  # 90 degrees about y, 30 mm down
    (tmp_path / "pose.json").write_text(pose)
    recipe = tmp_path / "placed.toml"
    recipe.write_text(RECIPE.format(mesh=mesh.as_posix(), pose=(tmp_path / "pose.json").as_posix()))
    assert main(["run", str(recipe), "--out", str(tmp_path / "run"), "--quiet"]) == 0
    session = load_session(tmp_path / "run" / "capture")
    params = RigParams(camera_size=(1280, 720), projector_size=(800, 600), working_distance=1000.0,
                       axes_angle_deg=25.0, sampling_mm=0.6, lights=4)
    rig = params.rig(scale=0.25, projector_scale=0.25)
    assert session.calibration == rig
    assert session.camera_size == (320, 180) and len(rig.lights) == 4
    assert session.device["config"]["rig_params"]["working_distance"] == 1000.0
    placement = np.asarray(json.loads(pose), float)
    for k, view in enumerate(session.views):
        np.testing.assert_allclose(view.rig_from_object, turntable_pose(rig, 180.0 * k) @ placement, atol=1e-12)
        d = _distance_to_mesh(_truth_points(session, view), view.rig_from_object, mesh, 10.0)
        assert np.max(d) < 0.01


def test_rig_file_is_used_as_given(tmp_path):
    rig = RigParams(working_distance=900.0, axes_angle_deg=30.0, lights=2).rig()
    (tmp_path / "rig.json").write_text(json.dumps(rig.to_dict()))
    assert main(["capture", "--scene", "tile", "--rig", str(tmp_path / "rig.json"), "--out", str(tmp_path / "a"),
                 *SMALL]) == 0
    session = load_session(tmp_path / "a")
    assert session.calibration == RigParams(working_distance=900.0, axes_angle_deg=30.0, lights=2).rig(
        scale=0.2, projector_scale=0.2)
    np.testing.assert_allclose(session.views[0].rig_from_object[:3, 3], [0, 0, 900.0])
    # a session.json is a rig file too: its calibration
    assert main(["capture", "--scene", "tile", "--rig", str(tmp_path / "a" / "session.json"), "--scale", "1",
                 "--levels", "3", "--patterns", "gray", "--no-lit", "--quiet", "--out", str(tmp_path / "b")]) == 0
    assert load_session(tmp_path / "b").calibration == session.calibration


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--scene-pose", "10,20,30"], "--scene-pose: expected \"rx,ry,rz,tx,ty,tz\""),
        (["--scene-pose", "a,b,c,d,e,f"], "--scene-pose: expected"),
        (["--scene-pose", "{tmp}/missing.json"], "missing.json: pose file not found"),
        (["--scene-pose", "{tmp}/scaled.txt"], "scaled.txt: the 3x3 part is not a rotation"),
        (["--scene-pose", "{tmp}/short.txt"], "short.txt: expected a 4x4 matrix"),
        (["--scene-units", "furlong"], "--scene-units: unknown units 'furlong'"),
        (["--scene-units", "-3"], "--scene-units: mm per unit must be a positive number"),
        (["--rig", "{tmp}/missing.json"], "missing.json: rig file not found"),
        (["--rig", "{tmp}/norig.json"], "norig.json: rig: missing field 'camera'"),
        (["--rig", "{tmp}/scaled.txt"], "scaled.txt: not valid JSON"),
    ],
)
def test_bad_placement_and_rig_give_one_line(tmp_path, capsys, args, expected):
    (tmp_path / "scaled.txt").write_text("2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n")
    (tmp_path / "short.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
    (tmp_path / "norig.json").write_text(json.dumps({"projector": {}}))
    argv = ["capture", "--scene", "tile", "--out", str(tmp_path / "x"), *SMALL,
            *[a.replace("{tmp}", str(tmp_path)) for a in args]]
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and expected in lines[0], err
    assert "Traceback" not in err and not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    ("table", "expected"),
    [
        ('scene_units = "furlong"', "r.toml: [capture].scene_units: unknown units 'furlong'"),
        ('scene_pose = "1,2"', "r.toml: [capture].scene_pose: expected"),
        ("[capture.rig_params]\nworking_distance = -1.0",
         "r.toml: [capture].rig_params.working_distance: expected a positive number"),
        ("[capture.rig_params]\ncamera_size = [1280]", "[capture].rig_params.camera_size: expected a list of 2"),
        ("[capture.rig_params]\nfocal = 3", "[capture].rig_params: unknown key 'focal'"),
        ('rig_file = "rig.json"\n[capture.rig_params]\nlights = 2', "rig_file and rig_params: give one"),
    ],
)
def test_bad_recipe_placement_and_rig_name_the_key(tmp_path, capsys, table, expected):
    recipe = tmp_path / "r.toml"
    recipe.write_text(f'[recipe]\nname = "r"\nstages = ["capture"]\n\n[capture]\nscene = "tile"\n{table}\n')
    assert main(["run", str(recipe), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert re.search(re.escape(expected), err), err
    assert not (tmp_path / "out").exists()
