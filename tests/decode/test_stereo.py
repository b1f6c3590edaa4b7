"""Two cameras, one projector: multi-camera sessions, the virtual rig's second camera, and
reconstruction by matching projector codes between the cameras, against ground truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from slscan.capture.multicam import MULTICAM_FILE, load_multicam
from slscan.cli import main
from slscan.decode.rangemap import read_ply
from slscan.decode.stereo import (
    StereoConfig,
    code_centroids,
    epipolar_distance,
    reconstruct_view,
    subpixel_positions,
    triangulate_midpoint,
)
from slscan.errors import SlscanError
from slscan.fsio import read_png
from slscan.rig import look_at, transform_points
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.multicam import capture_multicam
from slscan.virtual.scenes import scene_by_name


def _config(scale: float) -> VirtualCaptureConfig:
    return VirtualCaptureConfig(patterns="gray", gray_rows=True, lit_images=False,
                                camera_scale=scale, projector_scale=scale)


@pytest.fixture(scope="module")
def two_cameras(tmp_path_factory):
    """The figurine seen by two cameras at half size (720x480, 512x384 projector), with noise."""
    return capture_multicam(_config(0.5), tmp_path_factory.mktemp("stereo") / "two")


@pytest.fixture(scope="module")
def small_two(tmp_path_factory):
    """The same at quarter size, for the checks that need no accuracy."""
    return capture_multicam(_config(0.25), tmp_path_factory.mktemp("stereo_small") / "two")


def _true_distance(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = scene_by_name("object")
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(transform_points(pose, scene.vertices).astype(np.float32)),
                     o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    return rs.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


# --- the virtual rig's second camera ------------------------------------------------------


def test_camera_0_is_the_single_camera_capture(small_two, tmp_path):
    single = capture_session(_config(0.25), tmp_path / "single")
    cam0 = small_two.sessions[0]
    for rec in single.views[0].images:
        assert np.array_equal(read_png(single.image_path(single.views[0], rec)),
                              read_png(cam0.image_path(cam0.views[0], rec)))
    a, b = small_two.sessions
    assert a.calibration.camera != b.calibration.camera  # each camera its own lens
    img = a.views[0].pattern_images()[0]
    assert not np.array_equal(read_png(a.image_path(a.views[0], img)), read_png(b.image_path(b.views[0], img)))


def test_second_camera_ground_truth_is_the_same_surface(small_two):
    cam1 = small_two.cameras[1]
    s0, s1 = small_two.sessions
    gt1 = s1.load_ground_truth(s1.views[0])
    seen = np.isfinite(gt1.point[..., 0])
    assert seen.mean() > 0.05
    in_cam0 = transform_points(cam1.rig_from_camera, gt1.point[seen].astype(np.float64))
    # on the object where camera 0's view places it (float32 truth: ~1e-4 mm at 1.3 m)
    assert np.max(_true_distance(in_cam0, s0.views[0].rig_from_object)) < 0.01
    # and the projector pixel recorded there is the one camera 0's rig projects it to
    lit = gt1.visibility[seen] == 2
    uv = s0.calibration.projector.project(in_cam0[lit])
    assert np.max(np.abs(uv - gt1.projector_uv[seen][lit])) < 1e-2


# --- the pieces, with known answers -------------------------------------------------------


def test_midpoint_triangulation_and_epipolar_distance_known_answer():
    rng = np.random.default_rng(1)
    p = rng.uniform([-200, -200, 1100], [200, 200, 1500], (50, 3))
    b_pose = look_at([800.0, 50.0, 300.0], [0.0, 0.0, 1300.0])  # a_from_b
    xa = p / p[:, 2:]
    pb = transform_points(np.linalg.inv(b_pose), p)
    xb = pb / pb[:, 2:]
    assert np.max(epipolar_distance(xa, xb, b_pose, 1800.0, 1800.0)) < 1e-6
    da = xa / np.linalg.norm(xa, axis=1, keepdims=True)
    db = pb @ b_pose[:3, :3].T
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    points, gap, s, t = triangulate_midpoint(np.zeros(3), da, b_pose[:3, 3], db)
    np.testing.assert_allclose(points, p, atol=1e-6)
    assert np.max(gap) < 1e-6 and (s > 0).all() and (t > 0).all()
    # moving camera b's point along its epipolar line changes nothing; one pixel across it
    # reads as about one pixel (exactly 1 in image b, the depth ratio of the two cameras in a)
    line = xa @ (np.array([[0, -b_pose[2, 3], b_pose[1, 3]], [b_pose[2, 3], 0, -b_pose[0, 3]],
                           [-b_pose[1, 3], b_pose[0, 3], 0]]) @ b_pose[:3, :3])
    normal = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    moved = xb.copy()
    moved[:, :2] += normal / 1800.0
    np.testing.assert_allclose(epipolar_distance(xa, moved, b_pose, 1800.0, 1800.0), 1.0, rtol=0.1)
    along = xb.copy()
    along[:, :2] += 5 * normal[:, ::-1] * [1, -1] / 1800.0
    assert np.max(epipolar_distance(xa, along, b_pose, 1800.0, 1800.0)) < 1e-6


def test_code_centroids_average_each_code_and_drop_strays():
    column = np.full((20, 30), -1, np.int32)
    row = np.full((20, 30), -1, np.int32)
    column[4:6, 10:13], row[4:6, 10:13] = 7, 3  # six pixels, centroid (11, 4.5)
    column[15, 2], row[15, 2] = 7, 3  # a stray wrong decode far away
    column[9, 20], row[9, 20] = 8, 3
    c = code_centroids(column, row, column >= 0, projector_height=10)
    assert list(c.codes) == [7 * 10 + 3, 8 * 10 + 3]
    np.testing.assert_allclose(c.xy, [[11.0, 4.5], [20.0, 9.0]])
    assert list(c.count) == [6, 1]
    blocks = code_centroids(column, row, column >= 0, projector_height=10, code_step=2)
    assert list(blocks.codes) == [3 * 5 + 1, 4 * 5 + 1]


def test_subpixel_positions_find_the_code_centres_of_a_linear_map():
    """Codes rounded from a known affine map of the pixels: each refined pixel must land
    where the map takes its (column, row) exactly, far closer than the pixel's half-pixel
    rounding."""
    h, w = 60, 80
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    u = 0.77 * x + 0.08 * y + 3.3  # projector px per camera px, a little sheared
    v = -0.05 * x + 0.81 * y + 1.6
    column, row = np.rint(u).astype(np.int32), np.rint(v).astype(np.int32)
    px, py, ok = subpixel_positions(column, row, np.ones((h, w), bool))
    assert ok[5:-5, 5:-5].all()
    # the true position of each pixel's code centre: invert the affine map
    jac = np.array([[0.77, 0.08], [-0.05, 0.81]])
    target = np.stack([column - 3.3, row - 1.6], -1) @ np.linalg.inv(jac).T
    err = np.hypot(px - target[..., 0], py - target[..., 1])[ok]
    plain = np.hypot(x - target[..., 0], y - target[..., 1])[ok]
    # measured 0.067 / 0.18 px (0.10 at the 95th percentile away from the image border)
    assert np.median(err) < 0.08 and np.percentile(err, 95) < 0.2
    assert np.median(plain) > 0.45  # the pixel centre itself: about half a pixel away


# --- reconstruction against ground truth --------------------------------------------------


@pytest.mark.parametrize("subpixel, median_mm, p95_mm", [(True, 0.35, 1.0), (False, 0.47, 1.4)])
def test_stereo_recovers_the_virtual_figurine(two_cameras, subpixel, median_mm, p95_mm):
    """Median and 95th-percentile distance of the range map's vertices to the true surface.

    Half size: a camera pixel spans 1.4 mm at 1.3 m, and a projector pixel about one camera
    pixel, so the plain centroid of a code averages one or two pixel centres and is off by
    up to half a pixel in each camera (measured 0.34 / 0.95 mm): tolerances a third of a
    pixel's footprint (median) and one footprint (95th percentile). The sub-pixel
    refinement (measured 0.24 / 0.70 mm; the camera-projector edges: 0.09 / 0.29 mm) is
    held to a quarter and to 0.7 of a footprint.
    """
    view = two_cameras.sessions[0].views[0]
    result = reconstruct_view(two_cameras, view.name, StereoConfig(subpixel=subpixel))
    st = result.match.stats
    assert st["matched"] > 0.35 * st["codes_a"]
    assert st["matched"] + st["rejected_epipolar"] + st["rejected_ray_gap"] + st["rejected_behind"] == st["common"]
    rm = result.range_map
    # 4392 vertices and 4202 faces measured at the default camera blur σ 0.6 px (5706 and
    # 5514 at σ 0.5, the colour model changes nothing): at half size a projector pixel is
    # about a camera pixel, and more of the finest Gray-code cells drown in the blur
    assert len(rm.vertices) > 4000 and len(rm.faces) > 4000
    d = _true_distance(rm.vertices, view.rig_from_object)
    assert np.median(d) < median_mm
    assert np.percentile(d, 95) < p95_mm
    assert (rm.quality > 0).mean() > 0.95


def test_stereo_thresholds_reject_and_count(small_two):
    view = small_two.view_names[0]
    strict = reconstruct_view(small_two, view, StereoConfig(max_ray_gap_mm=0.3, max_epipolar_px=0.2))
    loose = reconstruct_view(small_two, view, StereoConfig(max_ray_gap_mm=50, max_epipolar_px=50))
    s, lo = strict.match.stats, loose.match.stats
    assert s["common"] == lo["common"]
    assert s["rejected_epipolar"] > 0 and s["rejected_ray_gap"] > 0
    assert lo["matched"] == lo["common"] - lo["rejected_behind"]
    assert s["matched"] < lo["matched"]
    assert np.all(strict.match.ray_gap <= 0.3) and np.all(strict.match.epipolar <= 0.2)


def test_capture_and_decode_commands(tmp_path, capsys):
    out, maps = tmp_path / "two", tmp_path / "maps"
    assert main(["capture", "--cameras", "2", "--scale", "0.25", "--no-lit", "--quiet", "--out", str(out)]) == 0
    multi = load_multicam(out)
    assert [c.name for c in multi.cameras] == ["cam0", "cam1"]
    ids = {p.id for p in multi.sessions[0].patterns}
    assert any(i.startswith("gray-row") for i in ids) and any(i.startswith("hybrid") for i in ids)
    assert main(["decode", str(out), "--out", str(maps), "--quiet"]) == 0
    meta = json.loads((maps / "stereo_cam0_cam1" / "range_maps.json").read_text())
    assert meta["stereo"]["cameras"] == ["cam0", "cam1"] and meta["views"][0]["metrics"]["matched"] > 500
    rm = read_ply(maps / "stereo_cam0_cam1" / "view_000.ply")
    assert len(rm.faces) > 400  # 470 at camera blur σ 0.6 px (650-700 at σ 0.5): see above
    for cam in ("cam0", "cam1"):  # each camera with the projector, as a single-camera session
        assert (maps / cam / "view_000.ply").is_file()
    assert "points from" in capsys.readouterr().err
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "2 cameras" in info and "cam1" in info and info.count("view_000") == 2


# --- bad input: one clear line ------------------------------------------------------------


def _copy(multi, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(multi.root, dst)
    return dst, json.loads((dst / MULTICAM_FILE).read_text())


def _one_error_line(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("slscan: error:"), err
    return lines[0]


def test_missing_camera_folder(small_two, tmp_path, capsys):
    dst, _ = _copy(small_two, tmp_path)
    shutil.rmtree(dst / "cam1")
    err = _one_error_line(capsys, ["decode", str(dst), "--out", str(tmp_path / "o")])
    assert "cameras.json" in err and "'cam1'" in err and "session.json" in err
    with pytest.raises(SlscanError, match="no session.json"):
        load_multicam(dst)


def test_mismatched_pattern_sets(small_two, tmp_path, capsys):
    dst, _ = _copy(small_two, tmp_path)
    meta_path = dst / "cam1" / "session.json"
    meta = json.loads(meta_path.read_text())
    drop = next(p["id"] for p in meta["patterns"] if p["id"].startswith("gray-row"))
    meta["patterns"] = [p for p in meta["patterns"] if p["id"] != drop]
    for v in meta["views"]:
        v["images"] = [r for r in v["images"] if r.get("pattern") != drop]
    meta_path.write_text(json.dumps(meta))
    err = _one_error_line(capsys, ["decode", str(dst), "--out", str(tmp_path / "o")])
    assert "different pattern sets" in err and drop in err


def test_camera_without_calibration(small_two, tmp_path, capsys):
    dst, meta = _copy(small_two, tmp_path)
    meta["cameras"][1]["rig_from_camera"] = None
    (dst / MULTICAM_FILE).write_text(json.dumps(meta))
    err = _one_error_line(capsys, ["decode", str(dst), "--out", str(tmp_path / "o"), "--stereo", "only"])
    assert "'cam1' has no calibration" in err
    # each camera alone still decodes with its projector calibration
    assert main(["decode", str(dst), "--out", str(tmp_path / "alone"), "--stereo", "off", "--quiet"]) == 0
    assert (tmp_path / "alone" / "cam1" / "view_000.ply").is_file()


def test_no_row_codes(tmp_path):
    config = VirtualCaptureConfig(patterns="gray", lit_images=False, camera_scale=0.25, projector_scale=0.25)
    multi = capture_multicam(config, tmp_path / "norows")
    with pytest.raises(SlscanError, match="no Gray-code row patterns"):
        reconstruct_view(multi, "view_000")
