"""Two cameras, one projector: multi-camera sessions, the virtual rig's second camera, and
reconstruction by matching projector codes between the cameras, against ground truth."""

from __future__ import annotations

import json
import math
import re
import shutil
from dataclasses import replace

import numpy as np
import pytest

from slscan.capture.multicam import MULTICAM_FILE, load_multicam
from slscan.cli import main
from slscan.decode.rangemap import read_ply
from slscan.decode.stereo import (
    StereoConfig,
    StereoMatch,
    code_centroids,
    epipolar_distance,
    epipolar_limit,
    mesh_matches,
    reconstruct_multicam,
    reconstruct_view,
    subpixel_positions,
    triangulate_midpoint,
)
from slscan.errors import SlscanError
from slscan.fsio import read_png
from slscan.rig import look_at, rotation_about_axis, transform_points
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


def _true_distance(points: np.ndarray, pose: np.ndarray, scene: str = "object") -> np.ndarray:
    import open3d as o3d

    scene = scene_by_name(scene)
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
    up to half a pixel in each camera (measured 0.31 / 0.90 mm): tolerances a third of a
    pixel's footprint (median) and one footprint (95th percentile). The sub-pixel
    refinement (measured 0.25 / 0.70 mm; the camera-projector edges: 0.09 / 0.29 mm) is
    held to a quarter and to 0.7 of a footprint.
    """
    view = two_cameras.sessions[0].views[0]
    result = reconstruct_view(two_cameras, view.name, StereoConfig(subpixel=subpixel))
    st = result.match.stats
    assert st["matched"] > 0.35 * st["codes_a"]
    assert st["matched"] + st["rejected_epipolar"] + st["rejected_ray_gap"] + st["rejected_behind"] == st["common"]
    rm = result.range_map
    # 4412 vertices and 4233 faces measured at the default camera blur σ 0.6 px (5706 and
    # 5514 at σ 0.5, the colour model changes nothing; the centroids: 6593 and 6533, their
    # codes 2 apart meshed): at half size a projector pixel is about a camera pixel, and
    # more of the finest Gray-code cells drown in the blur
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
    with pytest.raises(SlscanError, match="'cam0' has no gray row patterns"):
        reconstruct_view(multi, "view_000")


# --- real captures' conditions, at reduced size --------------------------------------------

SPACING_1M = 2 * math.degrees(math.asin(500 / 1300))
"""Camera spacing (45.2°) that puts the two cameras 1 m apart at the rig's 1.3 m."""


def _long_lens(scene: str = "tile", patterns: str = "gray") -> VirtualCaptureConfig:
    """720x480 cameras (f 929 px) and a 128x96 projector (f 232 px): a projector pixel covers
    a block of about 4 x 4 camera pixels, as it does for a 4896-px camera at f ≈ 12,000 px
    and a 1024-px projector at f ≈ 1,900 px (6.5 x 6.5)."""
    return VirtualCaptureConfig(scene=scene, patterns=patterns, gray_rows=True, lit_images=False,
                                camera_scale=0.5, projector_scale=0.125)


@pytest.fixture(scope="module")
def blocks(tmp_path_factory):
    """The flat tile seen through long lenses by two cameras 1 m apart (Gray code, noise on)."""
    return capture_multicam(_long_lens(), tmp_path_factory.mktemp("blocks") / "two", spacing_deg=SPACING_1M)


def _without_fine_bits(multi, missing: int):
    """``multi`` as if its Gray-code sets lacked the ``missing`` finest bits of each axis (a
    set captured with fewer bits, or bits dropped: codes then mark blocks of 2**missing)."""
    sessions = tuple(replace(s, patterns=tuple(p for p in s.patterns if not (
        p.family == "gray" and p.params["bit"] >= p.params["bits"] - missing))) for s in multi.sessions)
    return replace(multi, sessions=sessions)


def _distances(result, pose, scene: str) -> np.ndarray:
    return _true_distance(result.range_map.vertices, pose, scene)


def test_block_codes_fall_back_to_centroids(blocks):
    """Codes covering blocks of pixels wider than the plane fit's 7 x 7 window (2 bits
    missing: 16 x 16 camera px) leave every fit degenerate; the cells fall back to their
    centroids instead of being lost (before: 0 cells kept)."""
    view = blocks.sessions[0].views[0]
    coarse = _without_fine_bits(blocks, 2)
    fitted = reconstruct_view(coarse, view.name, StereoConfig())
    plain = reconstruct_view(coarse, view.name, StereoConfig(subpixel=False))
    st = fitted.match.stats
    assert st["refined_a"] == st["refined_b"] == 0  # no fit succeeds on 16-px blocks...
    # ...and no block is lost: measured 231 of the 232 cells of the centroids (one, cut by
    # the tile's edge, covers fewer than 9 pixels), placed at the same centroids
    assert st["codes_a"] >= plain.match.stats["codes_a"] - 3 and st["codes_a"] > 150
    assert st["matched"] >= plain.match.stats["matched"] - 3
    both, i, j = np.intersect1d(fitted.match.column * 1000 + fitted.match.row,
                                plain.match.column * 1000 + plain.match.row, return_indices=True)
    np.testing.assert_allclose(fitted.match.points[i], plain.match.points[j])
    # measured: median 0.11 mm, 95 % 1.1 mm (a camera pixel spans 1.4 mm, a block 22 mm)
    d = _distances(fitted, view.rig_from_object, "tile")
    assert np.median(d) < 0.25 and np.percentile(d, 95) < 2.0
    # with every bit, codes cover 4 x 4 px: the fits work, and beat the centroids
    full = reconstruct_view(blocks, view.name, StereoConfig())
    full_plain = reconstruct_view(blocks, view.name, StereoConfig(subpixel=False))
    assert full.match.stats["refined_a"] > 0.9 * full.match.stats["codes_a"]
    # measured: median 0.065 mm plane-fitted, 0.30 mm centroids
    assert np.median(_distances(full, view.rig_from_object, "tile")) < 0.5 * np.median(
        _distances(full_plain, view.rig_from_object, "tile"))


def test_mesh_follows_the_codes_step(blocks, tmp_path):
    """With bits missing, codes step by 4: the mesh links them at that step (before: no
    neighbouring codes, no faces, and "no view gave stereo matches")."""
    view = blocks.sessions[0].views[0]
    coarse = _without_fine_bits(blocks, 2)
    result = reconstruct_view(coarse, view.name, StereoConfig())
    assert result.mesh["spacing_px"] == 4 and 4 in result.mesh["steps"]
    assert len(result.range_map.faces) > 1.2 * result.match.stats["matched"]  # measured 394 for 230
    assert len(result.range_map.vertices) > 0.9 * result.match.stats["matched"]
    # a fixed step of 1 finds no neighbours: the error says so, with every test's count
    with pytest.raises(SlscanError) as err:
        reconstruct_multicam(coarse, tmp_path / "o", StereoConfig(mesh_step=1))
    text = str(err.value)
    assert "\n" not in text and "the matches did not mesh" in text and "0 triangles from 0 grid links" in text
    assert f"{result.match.stats['matched']:,} matched" in text and "matches 4 projector px apart" in text


def _triangle_overlap(rm) -> int:
    """Points of a fine grid of the projector plane covered by more than one triangle."""
    uv = np.stack([rm.stripe, rm.row], 1).astype(np.float64)[rm.faces]  # (f, 3, 2)
    lo, hi = uv.min(axis=(0, 1)), uv.max(axis=(0, 1))
    g = np.stack(np.meshgrid(np.arange(lo[0], hi[0], 0.25) + 0.11, np.arange(lo[1], hi[1], 0.25) + 0.07), -1)
    g = g.reshape(-1, 2)
    count = np.zeros(len(g), np.int32)
    for a, b, c in uv:  # barycentric test, triangle by triangle (a few thousand)
        near = np.flatnonzero((g[:, 0] >= min(a[0], b[0], c[0])) & (g[:, 0] <= max(a[0], b[0], c[0]))
                              & (g[:, 1] >= min(a[1], b[1], c[1])) & (g[:, 1] <= max(a[1], b[1], c[1])))
        m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
        lam = np.linalg.solve(m, (g[near] - a).T).T
        inside = (lam[:, 0] > 0) & (lam[:, 1] > 0) & (lam.sum(axis=1) < 1)
        count[near[inside]] += 1
    return int((count > 1).sum())


def test_mesh_steps_on_a_synthetic_grid():
    """Known answers: a 4-px lattice meshes in full; a missing code among codes 1 apart stays
    a hole; a lattice stepping by 1 on the left and by 2 on the right meshes both halves
    without triangles overlapping."""
    def match(cols, rows):
        cols, rows = np.asarray(cols), np.asarray(rows)
        pts = np.stack([cols * 0.7 - 100, rows * 0.7 - 80, 1300 + 0.1 * cols], 1).astype(np.float64)
        xy = np.stack([cols, rows], 1).astype(np.float64)
        return StereoMatch(pts, cols.astype(np.int32), rows.astype(np.int32), xy, xy, np.zeros(len(cols)),
                           np.zeros(len(cols)))

    white = np.full((300, 300), 200, np.uint8)
    c, r = np.meshgrid(np.arange(10) * 4 + 2, np.arange(8) * 4 + 2)
    rm = mesh_matches(match(c.ravel(), r.ravel()), white_image=white, steps=(1, 2, 4))
    assert len(rm.faces) == 2 * 9 * 7
    assert len(mesh_matches(match(c.ravel(), r.ravel()), white_image=white).faces) == 0  # steps (1,)
    c, r = np.meshgrid(np.arange(12), np.arange(10))
    keep = ~((c == 5) & (r == 5))
    rm = mesh_matches(match(c[keep], r[keep]), white_image=white, steps=(1, 2, 4))
    span = np.abs(np.diff(np.stack([rm.stripe, rm.row], 1)[rm.faces][:, [0, 1, 2, 0]], axis=1)).max()
    assert span == 1 and len(rm.faces) == 2 * 11 * 9 - 8 + 3  # the hole's four squares, three triangles back
    left = [(x, y) for x in range(0, 10) for y in range(0, 20)]
    right = [(x, y) for x in range(11, 31, 2) for y in range(1, 20, 2)]
    cols, rows = np.array(left + right).T
    rm = mesh_matches(match(cols, rows), white_image=white, steps=(1, 2))
    assert (rm.stripe > 10).sum() == len(right) and len(rm.faces) > 2 * (9 * 19 + 9 * 9)
    assert _triangle_overlap(rm) == 0


def test_mixed_code_steps_from_dropped_bits(blocks, tmp_path):
    """Per-pixel bit dropping: the finest column and row bits washed out on the right half
    of both cameras' images (pattern = inverse there); with ``gray_drop_bits=1`` those pixels
    keep codes 2 apart, the left half codes 1 apart, and the mesh covers both."""
    import cv2

    dst = tmp_path / "washed"
    shutil.copytree(blocks.root, dst)
    multi = load_multicam(dst)
    for s in multi.sessions:
        view = s.views[0]
        for axis in ("col", "row"):
            bits = max(p.params["bit"] for p in s.patterns if p.id.startswith(f"gray-{axis}-"))
            pid = f"gray-{axis}-{bits:02d}"
            a, b = (s.image_path(view, view.image_for(i)) for i in (pid, pid + "-inv"))
            ia, ib = read_png(a), read_png(b)
            mean = ((ia.astype(np.uint16) + ib) // 2).astype(ia.dtype)
            half = ia.shape[1] // 2
            for path, img in ((a, ia), (b, ib)):
                img[:, half:] = mean[:, half:]
                cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img)
    name = multi.view_names[0]
    strict = reconstruct_view(multi, name, StereoConfig())
    dropped = reconstruct_view(multi, name, StereoConfig(gray_drop_bits=1))
    assert dropped.mesh["steps"] == (1, 2)
    rm = dropped.range_map
    xa = dropped.match.xy_a[:, 0]
    w = multi.sessions[0].camera_size[0]
    # the right half: nothing without dropping bits, codes 2 apart with it
    assert (strict.match.xy_a[:, 0] > 0.6 * w).sum() < 0.1 * (xa > 0.6 * w).sum()
    right = dropped.match.column[xa > 0.6 * w]
    assert np.all(right % 2 == 1)  # block centres of 2-column blocks
    assert (rm.stripe % 2 == 1).sum() > 100 and (rm.stripe % 2 == 0).sum() > 100
    assert _triangle_overlap(rm) == 0
    d = _true_distance(rm.vertices, multi.sessions[0].views[0].rig_from_object, "tile")
    assert np.median(d) < 0.3


def test_epipolar_limit_follows_the_calibrations_residual(two_cameras):
    """A calibration off by 1.8 px (camera 1 turned by 1.8 px about its x axis: as the
    real two-camera set's residual): the fixed 1.5 px limit rejects most good matches, the
    "auto" limits measure the residual and keep them, and say which limits they used (at
    half size 1.8 px is 2.5 mm at 1.3 m: the ray gaps grow past the old fixed 2 mm too)."""
    cam1 = two_cameras.cameras[1]
    turn = np.eye(4)
    turn[:3, :3] = rotation_about_axis([1.0, 0.0, 0.0], 1.8 / cam1.lens.fy)
    off = replace(two_cameras, cameras=(two_cameras.cameras[0], replace(cam1, rig_from_camera=cam1.rig_from_camera @ turn)))
    view = two_cameras.sessions[0].views[0]
    exact = reconstruct_view(two_cameras, view.name, StereoConfig())
    fixed = reconstruct_view(off, view.name, StereoConfig(max_epipolar_px=1.5, max_ray_gap_mm=2.0))
    auto = reconstruct_view(off, view.name, StereoConfig())
    sf, sa = fixed.match.stats, auto.match.stats
    assert sf["rejected_epipolar"] > 0.3 * sf["common"] and sf["matched"] < 0.5 * sa["matched"]
    assert sa["ray_gap_limit_mm"] > 2.0 and exact.match.stats["ray_gap_limit_mm"] == 2.0
    assert 1.5 < sa["epipolar_median_px"] < 2.2 and sa["epipolar_limit_px"] > sa["epipolar_median_px"] + 0.3
    assert sa["matched"] > 0.95 * (sa["common"] - sa["rejected_behind"])
    assert sa["matched"] > 0.95 * exact.match.stats["matched"]
    # an exact calibration: the limit is the 1 px floor
    assert exact.match.stats["epipolar_limit_px"] == pytest.approx(1.0)
    assert epipolar_limit(np.array([1.7, 1.75, 1.8, 1.8, 1.85, 1.9, 40.0])) == pytest.approx(
        1.8 + 4 * 1.4826 * 0.05)
    assert epipolar_limit(np.array([0.1, 0.2, 0.3])) == 1.0 and epipolar_limit(np.zeros(0)) == 1.0


def test_failure_message_counts_each_test(small_two, tmp_path, capsys):
    """A limit nothing passes: one error line with each camera's cells, the common ones,
    what each test rejected, and the test that rejected the most; no guess."""
    err = _one_error_line(capsys, ["decode", str(small_two.root), "--out", str(tmp_path / "o"), "--stereo", "only",
                                   "--stereo-epipolar", "0.001", "--quiet"])
    assert "no view gave a stereo range map (the epipolar test rejected the most matches (--stereo-epipolar): " in err
    assert "view_000: cells seen cam0 " in err and "by the epipolar limit (0.00 px; median " in err
    assert re.search(r"0 by the ray gap \(\d+\.\d\d mm\), 0 behind a camera", err)
    assert "is the object seen by both cameras" not in err


def test_cli_stereo_options(small_two, tmp_path, capsys):
    maps = tmp_path / "maps"
    assert main(["decode", str(small_two.root), "--out", str(maps), "--stereo", "only", "--quiet",
                 "--stereo-refine", "centroid", "--stereo-epipolar", "2.5", "--stereo-ray-gap", "3",
                 "--stereo-mesh-step", "2", "--gray-drop-bits", "1"]) == 0
    meta = json.loads((maps / "stereo_cam0_cam1" / "range_maps.json").read_text())
    assert meta["config"]["subpixel"] is False and meta["config"]["max_epipolar_px"] == 2.5
    assert meta["config"]["max_ray_gap_mm"] == 3 and meta["config"]["mesh_step"] == 2
    assert meta["config"]["gray_drop_bits"] == 1
    assert meta["views"][0]["metrics"]["epipolar_limit_px"] == 2.5
    assert "epipolar > 2.50 px" in capsys.readouterr().err
    err = _one_error_line(capsys, ["decode", str(small_two.root), "--out", str(tmp_path / "x"),
                                   "--stereo-mesh-step", "fine"])
    assert "--stereo-mesh-step must be auto or a whole number" in err


# --- phase codes -------------------------------------------------------------------------------


def test_subpixel_positions_on_sub_pixel_codes():
    """Float (phase) maps of a known affine map, with 0.02 px noise: each pixel lands on the
    centre of the projector pixel its code falls in."""
    h, w = 60, 80
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    jac = np.array([[0.37, 0.05], [-0.04, 0.41]])
    rng = np.random.default_rng(3)
    u = jac[0, 0] * x + jac[0, 1] * y + 3.3 + rng.normal(0, 0.02, (h, w))
    v = jac[1, 0] * x + jac[1, 1] * y + 1.6 + rng.normal(0, 0.02, (h, w))
    u[:, :4] = np.nan  # not decoded
    px, py, ok = subpixel_positions(u, v, np.isfinite(u))
    assert ok[5:-5, 9:-5].all() and not ok[:, :4].any()
    target = np.stack([np.rint(u) - 3.3, np.rint(v) - 1.6], -1) @ np.linalg.inv(jac).T
    err = np.hypot(px - target[..., 0], py - target[..., 1])[ok]
    assert np.median(err) < 0.03 and np.percentile(err, 95) < 0.08  # 0.02 projector px ~ 0.05 camera px
    c = code_centroids(u, v, np.isfinite(u), projector_height=40, subpixel=True)
    assert len(c) > 0.9 * len(np.unique(np.rint(u[np.isfinite(u)]) * 40 + np.rint(v[np.isfinite(u)])))


@pytest.fixture(scope="module")
def phase_two(tmp_path_factory):
    """The figurine at half size with phase-shifting columns and rows, two cameras."""
    config = VirtualCaptureConfig(patterns="phase", gray_rows=True, lit_images=False, camera_scale=0.5,
                                  projector_scale=0.5)
    return capture_multicam(config, tmp_path_factory.mktemp("phase") / "two")


def test_stereo_with_phase_codes(phase_two, two_cameras):
    """Phase codes are matched by projector position: every projector pixel both cameras see
    (their sub-pixel codes fitted by planes onto its centre), denser and at least as accurate
    as the Gray-code cells of the same rig."""
    from slscan.decode.codes import codes_family

    assert codes_family(phase_two.sessions[0]).name == "phase"
    view = phase_two.sessions[0].views[0]
    result = reconstruct_view(phase_two, view.name, StereoConfig())
    gray = reconstruct_view(two_cameras, view.name, StereoConfig())
    st = result.match.stats
    assert st["refined_a"] > 0.9 * st["codes_a"]
    assert st["matched"] > 1.5 * gray.match.stats["matched"]
    d = _true_distance(result.range_map.vertices, view.rig_from_object)
    g = _true_distance(gray.range_map.vertices, view.rig_from_object)
    assert np.median(d) < np.median(g) and np.percentile(d, 95) < np.percentile(g, 95) * 1.1
    assert len(result.range_map.faces) > len(gray.range_map.faces)


def test_codes_are_coarsened_to_the_bits_both_cameras_read():
    from slscan.decode.codes import ProjectorCodes, ValidShare
    from slscan.decode.stereo import coarsened

    col = np.array([[0, 5, 6, 255, -1]], np.int32)
    row = np.array([[3, 4, 7, 8, 9]], np.int32)
    share = ValidShare(1.0, 1.0, 0.0, 0.0, 0.0, None, "decoder")
    codes = ProjectorCodes("v", col, row, col >= 0, (256, 192), (8, 8), share)
    out = coarsened(codes, (8, 6))  # the other camera lacks the last two row bits: blocks of 4
    np.testing.assert_array_equal(out.column, col)
    np.testing.assert_array_equal(out.row, [[2, 6, 6, 10, 10]])  # each block's centre, as a coarse set decodes it
    assert out.bits == (8, 6) and coarsened(out, (8, 6)) is out
