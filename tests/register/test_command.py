"""``slscan register``'s options (start poses, pose tolerance, .conf choice) and the rejected
pairs in registration.json, on four small synthetic range scans of a blob."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest
from rerun.chunk import RrdReader
from scipy.spatial.transform import Rotation
from synthetic_poses import looking_from

from slscan.cli import main
from slscan.errors import SlscanError
from slscan.recipe.stages import RegisterConfig, StageContext, _run_register
from slscan.register import multiview
from slscan.register.command import load_poses, load_scans
from slscan.register.meshlab import format_mlp
from slscan.register.pairwise import pose_error, rigid_transform
from slscan.register.rangescan import render_range_scan, write_range_scan

NAMES = ["view0", "view1", "view2", "view3"]


@pytest.fixture(scope="module")
def blob(tmp_path_factory):
    """A folder of 4 PLY range scans (no poses), the scans, and their true poses."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=60)
    v = np.asarray(sphere.vertices)
    v = v * 40.0 * (1 + 0.1 * np.sin(5 * v[:, 0] + 1) * np.cos(6 * v[:, 1])
                    + 0.06 * np.sin(7 * v[:, 2]))[:, None]
    f = np.asarray(sphere.triangles)
    folder = tmp_path_factory.mktemp("blob")
    scans, truth = [], {}
    for name, d in zip(NAMES, [[1, 0, 0.3], [0, 1, 0.3], [-1, 0, 0.3], [0, -1, 0.3]]):
        truth[name] = looking_from(d)
        scans.append(render_range_scan(v, f, truth[name], shape=(80, 80), pixel=1.2, name=name))
        write_range_scan(scans[-1], folder / f"{name}.ply")
    return folder, scans, truth


def _start(truth: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The true poses moved by a few degrees and mm (view0, the reference, kept)."""
    motions = {"view1": ([0.03, -0.02, 0.04], [2.0, -1.0, 1.5]),
               "view2": ([-0.04, 0.02, 0.01], [-1.5, 2.0, 1.0]),
               "view3": ([0.02, 0.04, -0.03], [1.0, 1.0, -2.0])}
    return {n: rigid_transform(*motions[n]) @ p if n in motions else p for n, p in truth.items()}


def _write_poses(path, poses: dict[str, np.ndarray]) -> None:
    """Write world_from_scan poses (mm) as a .conf (metres), registration.json or .mlp."""
    if path.suffix == ".json":
        path.write_text(json.dumps({"poses": {k: v.tolist() for k, v in poses.items()}}))
    elif path.suffix == ".mlp":
        path.write_text(format_mlp([(n, f"{n}.ply", p) for n, p in poses.items()]))
    else:  # Stanford: world_from_scan = [[R^T, t]], R the quaternion's rotation
        lines = ["camera 0 0 0 0 0 0 1"]
        for n, p in poses.items():
            q = Rotation.from_matrix(p[:3, :3].T).as_quat()  # x, y, z, w
            lines.append(f"bmesh {n}.ply " + " ".join(f"{x:.15g}" for x in [*p[:3, 3] / 1000, *q]))
        path.write_text("\n".join(lines) + "\n")


def _relative_errors(poses, truth) -> list[tuple[float, float]]:
    """Pose errors of each scan relative to view0 (free of the registration's gauge)."""
    ref, ref_true = np.linalg.inv(poses["view0"]), np.linalg.inv(truth["view0"])
    return [pose_error(ref @ poses[n], ref_true @ truth[n]) for n in NAMES]


@pytest.fixture
def spy(monkeypatch):
    """What ``register_scans`` is called with (the CLI imports it at call time)."""
    calls = []
    original = multiview.register_scans

    def register_scans(scans, **kwargs):
        calls.append(kwargs)
        return original(scans, **kwargs)

    monkeypatch.setattr(multiview, "register_scans", register_scans)
    return calls


@pytest.mark.parametrize("suffix", [".json", ".conf", ".mlp"])
def test_poses_from_each_format_are_the_start(blob, tmp_path, spy, suffix):
    folder, _, truth = blob
    start = _start(truth)
    file = tmp_path / f"start{suffix}"
    _write_poses(file, start)
    loaded = load_poses(file, NAMES)
    for n in NAMES:
        np.testing.assert_allclose(loaded[n], start[n], atol=1e-9)
    assert main(["register", str(folder), "--poses", str(file), "--out", str(tmp_path / "out"),
                 "--quiet"]) == 0
    used = spy[0]["initial_poses"]
    assert list(used) == NAMES
    for n in NAMES:
        np.testing.assert_allclose(used[n], start[n], atol=1e-9)
    registered = json.loads((tmp_path / "out" / "registration.json").read_text())
    poses = {k: np.asarray(v) for k, v in registered["poses"].items()}
    for rotation, translation in _relative_errors(poses, truth):
        assert rotation < 0.05 and translation < 0.05


def test_re_registered_from_its_own_perturbed_registration_json(blob, tmp_path):
    folder, _, truth = blob
    _write_poses(tmp_path / "start.json", _start(truth))
    assert main(["register", str(folder), "--poses", str(tmp_path / "start.json"),
                 "--out", str(tmp_path / "a"), "--quiet"]) == 0
    first = {k: np.asarray(v) for k, v in
             json.loads((tmp_path / "a" / "registration.json").read_text())["poses"].items()}
    again = _start(first)  # the registration's own poses (its object frame), moved again
    _write_poses(tmp_path / "again.json", again)
    assert main(["register", str(folder), "--poses", str(tmp_path / "again.json"),
                 "--out", str(tmp_path / "b"), "--quiet"]) == 0
    second = {k: np.asarray(v) for k, v in
              json.loads((tmp_path / "b" / "registration.json").read_text())["poses"].items()}
    for rotation, translation in _relative_errors(second, first):
        assert rotation < 0.01 and translation < 0.01
    # and from the .mlp the first run wrote
    assert main(["register", str(folder), "--poses", str(tmp_path / "a" / "aligned.mlp"),
                 "--out", str(tmp_path / "c"), "--quiet"]) == 0


def test_pose_file_names_must_match_the_scans(blob, tmp_path):
    folder, _, truth = blob
    poses = {("ghost" if n == "view2" else n): p for n, p in truth.items()}
    file = tmp_path / "start.json"
    _write_poses(file, poses)
    with pytest.raises(SlscanError, match=r"start\.json: names ghost that match no scan; "
                                          r"no pose for scans view2"):
        load_poses(file, NAMES)
    assert main(["register", str(folder), "--poses", str(file), "--out", str(tmp_path / "out"),
                 "--quiet"]) == 2
    assert not (tmp_path / "out").exists()
    with pytest.raises(SlscanError, match="expected a .conf, a registration.json or a .mlp"):
        (tmp_path / "poses.txt").write_text("x")
        load_poses(tmp_path / "poses.txt", NAMES)


def test_pose_tolerance_reaches_the_config_and_rejected_pairs_are_written(blob, tmp_path, spy):
    folder, _, truth = blob
    _write_poses(tmp_path / "truth.json", truth)
    # a wide tolerance: the opposite views become candidates, and fail (they barely overlap)
    assert main(["register", str(folder), "--poses", str(tmp_path / "truth.json"),
                 "--pose-tolerance", "40", "--out", str(tmp_path / "out"), "--quiet",
                 "--save", str(tmp_path / "register.rrd")]) == 0
    assert spy[0]["config"].pose_tolerance == 40.0
    registered = json.loads((tmp_path / "out" / "registration.json").read_text())
    assert {"reference", "poses", "pairs", "left_out", "rejected"} <= set(registered)
    rejected = {(r["source"], r["target"]): r for r in registered["rejected"]}
    assert {("view0", "view2"), ("view1", "view3")} & set(rejected)
    for r in rejected.values():
        assert r["reason"] and set(r) == {"source", "target", "reason", "fitness", "rmse_mm"}
        assert r["fitness"] is None or 0 <= r["fitness"] < 1
    assert len(registered["poses"]) == 4 and not registered["left_out"]
    entities = {c.entity_path for c in RrdReader(tmp_path / "register.rrd").stream().to_chunks()}
    assert "/log/register" in entities and "/plot/register/rejected" in entities
    assert main(["register", str(folder), "--pose-tolerance", "0", "--out", str(tmp_path / "x"),
                 "--quiet"]) == 2


def test_max_neighbours_reaches_the_config(blob, tmp_path, spy):
    folder, _, truth = blob
    _write_poses(tmp_path / "truth.json", truth)
    assert main(["register", str(folder), "--poses", str(tmp_path / "truth.json"),
                 "--max-neighbours", "1", "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert spy[0]["config"].max_neighbours == 1
    assert main(["register", str(folder), "--max-neighbours", "-1", "--out", str(tmp_path / "x"),
                 "--quiet"]) == 2
    config = RegisterConfig(source=str(folder), poses=str(tmp_path / "truth.json"), max_neighbours=0)
    assert _run_register(StageContext(out=tmp_path / "aligned", inputs={}), config)["aligned"] == 4
    assert spy[1]["config"].max_neighbours == 0
    with pytest.raises(SlscanError, match="max_neighbours: expected >= 0"):
        _run_register(StageContext(out=tmp_path / "y", inputs={}),
                      RegisterConfig(source=str(folder), max_neighbours=-2))


def test_a_pair_failing_the_check_is_rejected_with_its_reason(blob):
    _, scans, truth = blob
    result = multiview.register_scans(scans, initial_poses=truth,
                                      config=multiview.MultiviewConfig(pose_tolerance=40.0))
    pairs = {(r.source, r.target): r for r in result.rejected}
    assert {("view0", "view2"), ("view1", "view3")} & set(pairs)
    for r in pairs.values():
        assert isinstance(r, multiview.RejectedPair) and r.reason
    opposite = pairs.get(("view1", "view3")) or pairs[("view0", "view2")]
    assert "overlap" in opposite.reason or "RMSE" in opposite.reason


def _write_stanford_ply(path, scan) -> None:
    """A Stanford range-grid PLY (ASCII, metres) of a synthetic scan with a grid."""
    rows, cols = scan.grid.shape
    header = ["ply", "format ascii 1.0", f"obj_info num_cols {cols}", f"obj_info num_rows {rows}",
              f"element vertex {scan.n_vertices}", "property float x", "property float y",
              "property float z", f"element range_grid {rows * cols}",
              "property list uchar int vertex_indices", "end_header"]
    body = [" ".join(f"{x:.9g}" for x in p) for p in scan.vertices / 1000.0]
    body += ["0" if i < 0 else f"1 {i}" for i in scan.grid.ravel()]
    path.write_text("\n".join(header + body) + "\n")


def test_conf_choice_and_missing_scans(blob, tmp_path):
    _, scans, truth = blob
    for scan in scans[:2]:
        _write_stanford_ply(tmp_path / f"{scan.name}.ply", scan)
    _write_poses(tmp_path / "a.conf", {n: truth[n] for n in NAMES[:2]})
    _write_poses(tmp_path / "b.conf", {n: truth[n] for n in NAMES[:2]})
    with pytest.raises(SlscanError, match=r"2 \.conf files \(a\.conf, b\.conf\); choose one \(--conf"):
        load_scans(tmp_path)
    assert main(["register", str(tmp_path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    loaded, poses = load_scans(tmp_path, conf="b.conf")
    assert [s.name for s in loaded] == NAMES[:2]
    np.testing.assert_allclose(poses["view1"], truth["view1"], atol=1e-9)
    np.testing.assert_allclose(loaded[1].vertices, scans[1].vertices, atol=1e-5)
    with pytest.raises(SlscanError, match=r"c\.conf: not found \(\.conf files in .*: a\.conf, b\.conf\)"):
        load_scans(tmp_path, conf="c.conf")
    # a line naming a scan that is not there: the .conf, its line and the file
    (tmp_path / "b.conf").write_text("camera 0 0 0 0 0 0 1\nbmesh view0.ply 0 0 0 0 0 0 1\n"
                                     "bmesh view9.ply 0 0 0 0 0 0 1\n")
    with pytest.raises(SlscanError, match=r"b\.conf:3: view9\.ply: scan file not found"):
        load_scans(tmp_path, conf="b.conf")
    assert main(["register", str(tmp_path), "--conf", "b.conf", "--out", str(tmp_path / "out"),
                 "--quiet"]) == 2


def test_recipe_register_stage_takes_poses_and_tolerance(blob, tmp_path, spy):
    folder, _, truth = blob
    start = _start(truth)
    _write_poses(tmp_path / "start.conf", start)
    config = RegisterConfig(source=str(folder), poses=str(tmp_path / "start.conf"), pose_tolerance=12.0)
    summary = _run_register(StageContext(out=tmp_path / "aligned", inputs={}), config)
    assert summary["aligned"] == 4
    assert spy[0]["config"].pose_tolerance == 12.0
    np.testing.assert_allclose(spy[0]["initial_poses"]["view3"], start["view3"], atol=1e-9)
    with pytest.raises(SlscanError, match="register.poses is set but register.use_poses is false"):
        _run_register(StageContext(out=tmp_path / "x", inputs={}),
                      RegisterConfig(source=str(folder), poses="p.json", use_poses=False))
