"""Tests for range-map meshing and PLY I/O, on synthetic sample grids with known answers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slscan.capture.session import LIT
from slscan.decode.graycode import decode_gray
from slscan.decode.rangemap import RangeMap, build_range_map, read_ply, write_ply
from slscan.decode.samples import StripeSamples
from slscan.decode.triangulate import RigPlanes, triangulate
from slscan.errors import SlscanError
from slscan.rig import default_rig

CAMERA = default_rig(scale=0.25).camera  # 360 x 240
ROWS = np.arange(10, 20)  # 10 camera rows
STRIPES = np.arange(5, 25)  # 20 stripes
FLAT_FACES = 2 * (len(ROWS) - 1) * (len(STRIPES) - 1)


def _grid(depth=lambda x, y: 1000.0 + 0.2 * x):
    """Samples on every (row, stripe) of the grid and their points, 3 mm x 2.5 mm apart."""
    r, s = (a.ravel() for a in np.meshgrid(ROWS, STRIPES, indexing="ij"))
    k = len(r)
    samples = StripeSamples(
        row=r.astype(np.int32),
        x=100.0 + 2.0 * (s - 5) + 0.25,
        projector_column=s + 0.5,
        stripe=s.astype(np.int32),
        contrast=np.full(k, 0.8, np.float32),
        saturated=np.zeros(k, bool),
    )
    x, y = (s - 15) * 3.0, (r - 15) * 2.5
    points = np.stack([x, y, depth(x, y)], axis=1).astype(float)
    return samples, points


def _white() -> np.ndarray:
    """Grey white image whose value is the column index (bilinear colour is then x)."""
    return np.broadcast_to(
        np.arange(CAMERA.width, dtype=np.uint8)[None, :], (CAMERA.height, CAMERA.width)
    ).copy()


def _build(samples, points, **kw) -> RangeMap:
    return build_range_map(
        samples, points, white_image=_white(), camera=CAMERA, view="view 007", **kw
    )


def _facing_camera(rm: RangeMap) -> np.ndarray:
    v = rm.vertices[rm.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    return np.einsum("ij,ij->i", n, -v.mean(axis=1)) > 0


def test_flat_grid_meshes_completely():
    samples, points = _grid()
    rm = _build(samples, points)
    assert rm.n_vertices == len(samples) and rm.n_faces == FLAT_FACES
    assert rm.faces.dtype == np.int32 and rm.faces.min() >= 0 and rm.faces.max() < rm.n_vertices
    np.testing.assert_array_equal(rm.vertices, points)
    np.testing.assert_array_equal(rm.row, samples.row)
    np.testing.assert_array_equal(rm.stripe, samples.stripe)
    assert rm.view == "view 007"
    assert _facing_camera(rm).all()
    # every face joins neighbouring rows and stripes only
    rows, stripes = rm.row[rm.faces], rm.stripe[rm.faces]
    assert np.all(np.ptp(rows, axis=1) == 1) and np.all(np.ptp(stripes, axis=1) == 1)
    # the plane z = 1000 + 0.2 x has normal (0.2, 0, -1)/|.| towards the camera
    expected = np.array([0.2, 0.0, -1.0]) / np.hypot(0.2, 1.0)
    np.testing.assert_allclose(rm.normals, np.broadcast_to(expected, rm.normals.shape), atol=1e-6)
    cos_view = -np.einsum(
        "ij,ij->i", expected[None, :], points / np.linalg.norm(points, axis=1, keepdims=True)
    )
    # the first and last rows end every line: half the quality there
    ends = np.isin(samples.row, [ROWS[0], ROWS[-1]])
    np.testing.assert_allclose(rm.quality, 0.8 * cos_view * np.where(ends, 0.5, 1.0), rtol=1e-5)
    # colour: the white image bilinear at (x, row); here the value is x itself
    np.testing.assert_array_equal(
        rm.colors, np.repeat(np.rint(samples.x).astype(np.uint8)[:, None], 3, axis=1)
    )


def test_depth_step_is_not_bridged():
    samples, points = _grid(lambda x, y: 1000.0 + 0.2 * x + np.where(x >= 0, 60.0, 0.0))
    left, right = samples.stripe < 15, samples.stripe >= 15
    expected = (
        2 * (len(ROWS) - 1) * ((left.sum() // len(ROWS) - 1) + (right.sum() // len(ROWS) - 1))
    )
    for options in ({}, {"max_view_angle_deg": 90.0}):  # the edge-length test alone suffices
        rm = _build(samples, points, **options)
        sides = (rm.stripe >= 15)[rm.faces]
        assert not np.any(sides.any(axis=1) & ~sides.all(axis=1)), options
        assert rm.n_faces == expected
    # with both tests disabled the step is bridged: the check above can fail
    rm = _build(samples, points, max_edge_factor=1e6, max_view_angle_deg=90.0)
    assert rm.n_faces == FLAT_FACES


def test_grazing_faces_dropped():
    samples, points = _grid(lambda x, y: 1000.0 + 12.0 * x)  # surface 85 degrees from the view
    assert _build(samples, points).n_faces == 0
    assert _build(samples, points, keep_unreferenced=True).n_vertices == len(samples)
    assert _build(samples, points, max_view_angle_deg=89.0).n_faces == FLAT_FACES


def test_nan_duplicate_and_saturated_samples():
    samples, points = _grid()
    centre = np.flatnonzero((samples.row == 14) & (samples.stripe == 12))[0]
    points[centre] = np.nan
    twin = np.flatnonzero((samples.row == 16) & (samples.stripe == 18))[0]
    fields = ("row", "x", "projector_column", "stripe", "contrast", "saturated")
    dup = StripeSamples(
        *(np.concatenate([getattr(samples, f), getattr(samples, f)[[twin]]]) for f in fields)
    )
    points = np.concatenate([points, points[[twin]] + [0, 0, 0.5]])
    saturated = dup.saturated.copy()
    hot = np.flatnonzero((dup.row == 11) & (dup.stripe == 6))[0]
    saturated[hot] = True
    dup = StripeSamples(dup.row, dup.x, dup.projector_column, dup.stripe, dup.contrast, saturated)

    strict = _build(dup, points, max_gap_columns=1)
    steps = np.abs(np.diff(strict.stripe[strict.faces][:, [0, 1, 2, 0]], axis=1))
    assert steps.max() == 1  # no face spans a missing stripe
    # per hole: the 6 triangles around the missing vertex go, one is re-formed from the
    # three corners that remain of a quad: 5 fewer faces
    assert strict.n_faces == FLAT_FACES - 5 - 5
    rm = _build(dup, points)
    # bridged: the gap is closed by 4 triangles instead of 6
    assert rm.n_faces == FLAT_FACES - 2 - 2
    assert rm.n_vertices == len(samples) - 1 - 1  # NaN and both twins dropped, twin's pair too
    assert not np.isnan(rm.vertices).any()
    is_hot = (rm.row == 11) & (rm.stripe == 6)
    assert rm.quality[is_hot] == 0 and np.all(rm.quality[~is_hot] > 0)
    kept = _build(dup, points, keep_unreferenced=True)
    assert kept.n_faces == rm.n_faces
    assert kept.n_vertices == len(dup) - 1 and kept.n_faces == rm.n_faces
    twins = (kept.row == 16) & (kept.stripe == 18)
    assert twins.sum() == 2 and np.all(kept.quality[twins] == 0)


def _without(samples: StripeSamples, *cells: tuple[int, int]) -> StripeSamples:
    drop = np.zeros(len(samples), bool)
    for row, stripe in cells:
        drop |= (samples.row == row) & (samples.stripe == stripe)
    return samples.subset(~drop)


def _at(samples: StripeSamples, values: np.ndarray, row: int, stripe: int):
    return values[(samples.row == row) & (samples.stripe == stripe)].tolist()


def test_line_continuity_and_trimming():
    grid, _ = _grid()
    samples = _without(grid, (14, 12), (12, 20), (11, 20))
    n = samples.continuity()
    assert n.dtype == np.int8
    assert _at(samples, n, 13, 12) == [1] and _at(samples, n, 15, 12) == [1]  # around the hole
    assert _at(samples, n, 10, 20) == [0]  # rows 11 and 12 missing: alone
    assert _at(samples, n, 13, 20) == [1] and _at(samples, n, 14, 20) == [2]
    assert np.all(n[samples.row == ROWS[0]] <= 1) and np.all(n[samples.row == ROWS[-1]] <= 1)
    assert _at(samples, n, 15, 7) == [2]
    # a feature of the same stripe 3 px away in the next row is another line
    x = samples.x.copy()
    x[(samples.row == 16) & (samples.stripe == 7)] += 3.0
    moved = StripeSamples(samples.row, x, samples.projector_column, samples.stripe,
                          samples.contrast, samples.saturated)
    n_moved = moved.continuity()
    assert _at(moved, n_moved, 15, 7) == [1] and _at(moved, n_moved, 16, 7) == [0]
    assert _at(moved, n_moved, 17, 7) == [1]
    # a row crossing one plane twice: the twin 40 px away comes first, the line still goes on
    fields = ("row", "x", "projector_column", "stripe", "contrast", "saturated")
    far = grid.subset((grid.row == 15) & (grid.stripe == 9))
    both = StripeSamples(*(np.concatenate([getattr(far, f), getattr(grid, f)]) for f in fields))
    both = StripeSamples(both.row, both.x + np.r_[40.0, np.zeros(len(grid))],
                         both.projector_column, both.stripe, both.contrast, both.saturated)
    assert _at(both, both.continuity(), 14, 9) == [2]

    once = samples.trim_line_ends(1)
    assert len(once) == int((n == 2).sum())
    assert set(once.row.tolist()) == set(ROWS[1:-1].tolist())
    assert not _at(once, once.x, 13, 12) and not _at(once, once.x, 10, 20)
    assert _at(once, once.x, 12, 12) and not _at(once, once.x, 13, 20)
    twice = samples.trim_line_ends(2)
    assert set(twice.row.tolist()) == set(ROWS[2:-2].tolist()) and not _at(twice, twice.x, 12, 12)
    assert len(samples.trim_line_ends(0)) == len(samples)
    assert len(samples.subset(np.zeros(len(samples), bool)).continuity()) == 0

    # quality: 1, 0.5, 0.25 of cos(view) x contrast by continuity
    _, points = _grid()
    keep = np.ones(len(grid), bool)
    for row, stripe in ((14, 12), (12, 20), (11, 20)):
        keep &= ~((grid.row == row) & (grid.stripe == stripe))
    rm = _build(samples, points[keep], keep_unreferenced=True)
    base = _build(grid, points, keep_unreferenced=True)
    full = {(r, s): q for r, s, q in zip(base.row, base.stripe, base.quality)}
    for (row, stripe), factor in (((15, 7), 1.0), ((13, 12), 0.5), ((10, 20), 0.25)):
        q = rm.quality[(rm.row == row) & (rm.stripe == stripe)][0]
        assert q == pytest.approx(factor * full[(row, stripe)] / (0.5 if row == ROWS[0] else 1.0))
    plain = _build(samples, points[keep], keep_unreferenced=True, continuity_weight=(1, 1, 1))
    assert plain.quality[(plain.row == 13) & (plain.stripe == 12)][0] == pytest.approx(full[(13, 12)])
    with pytest.raises(SlscanError, match="continuity_weight"):
        _build(samples, points[keep], continuity_weight=(1, 1))


def test_gaps_are_bridged_up_to_a_distance_in_projector_columns():
    """A run of missing stripes in one row is bridged when the stripes on either side are at
    most ``max_gap_columns`` projector columns apart: the same limit for lines two columns
    apart (hybrid) as for edges one apart (Gray code)."""
    samples, points = _grid()
    row = 14
    for spacing in (1.0, 2.0):  # projector columns between neighbouring stripes
        spaced = StripeSamples(samples.row, samples.x, samples.stripe * spacing, samples.stripe,
                               samples.contrast, samples.saturated)
        for missing in (1, 3, 4):  # stripes 10 .. 10 + missing - 1 lost in one row
            lost = (samples.row == row) & (samples.stripe >= 10) & (samples.stripe < 10 + missing)
            keep = ~lost
            step = (missing + 1) * spacing  # the bridge's span in projector columns
            sub = spaced.subset(keep)
            assert len(sub) == len(samples) - missing
            for limit in (step - 0.5, step):
                rm = _build(sub, points[keep], max_gap_columns=limit)
                spans = np.ptp(rm.stripe[rm.faces], axis=1) * spacing
                bridged = np.any(spans >= step)
                assert bridged == (limit >= step), (spacing, missing, limit)
                assert spans.max() <= limit
    with pytest.raises(SlscanError, match="max_gap_columns"):
        _build(samples, points, max_gap_columns=0)


def test_bad_inputs():
    samples, points = _grid()
    with pytest.raises(SlscanError, match=r"expected \(200, 3\) points"):
        _build(samples, points[:-1])
    with pytest.raises(SlscanError, match="white image is 10x10, the camera is 360x240"):
        build_range_map(samples, points, white_image=np.zeros((10, 10), np.uint8), camera=CAMERA)


def test_uint16_rgb_white():
    samples, points = _grid()
    white = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint16)
    white[..., 0], white[..., 1], white[..., 2] = 65535, 257 * 100, 0
    rm = build_range_map(samples, points, white_image=white, camera=CAMERA)
    assert np.all(rm.colors == [255, 100, 0])


# --- PLY --------------------------------------------------------------------------------------


@pytest.fixture
def mesh() -> RangeMap:
    samples, points = _grid(lambda x, y: 1000.0 + 0.2 * x + 0.01 * y**2)
    return _build(samples, points)


def test_ply_round_trip(mesh: RangeMap, tmp_path: Path):
    path = write_ply(mesh, tmp_path / "view.ply")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["view.ply"]  # nothing half-written left
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "format binary_little_endian 1.0" in header and "property float quality" in header
    assert "comment view view 007" in header
    back = read_ply(path)
    np.testing.assert_allclose(back.vertices, mesh.vertices, rtol=1e-7)  # stored as float32
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.normals, mesh.normals)
    np.testing.assert_array_equal(back.colors, mesh.colors)
    np.testing.assert_array_equal(back.quality, mesh.quality)
    np.testing.assert_array_equal(back.row, mesh.row)
    np.testing.assert_array_equal(back.stripe, mesh.stripe)
    assert back.view == mesh.view


def test_pymeshlab_opens_ply(mesh: RangeMap, tmp_path: Path):
    pymeshlab = pytest.importorskip("pymeshlab")
    path = write_ply(mesh, tmp_path / "view.ply")
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    m = ms.current_mesh()
    assert m.vertex_number() == mesh.n_vertices and m.face_number() == mesh.n_faces
    np.testing.assert_allclose(m.vertex_matrix(), mesh.vertices, rtol=1e-6)
    np.testing.assert_array_equal(m.face_matrix(), mesh.faces)
    np.testing.assert_allclose(m.vertex_scalar_array(), mesh.quality, rtol=1e-6)  # vertex quality
    np.testing.assert_allclose(m.vertex_color_matrix()[:, :3] * 255, mesh.colors, atol=0.5)


def test_read_ply_errors(mesh: RangeMap, tmp_path: Path):
    with pytest.raises(SlscanError, match="PLY file not found"):
        read_ply(tmp_path / "absent.ply")
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n"
    )
    with pytest.raises(SlscanError, match="ascii.ply: vertices lack property 'y'"):
        read_ply(ascii_ply)
    # ASCII (as MeshLab may save a range map) reads like binary
    ascii_ply.write_text(
        "ply\nformat ascii 1.0\ncomment view v3\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float quality\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n0 0 1 0.5\n1 0 1 0.5\n0 1 1 0.5\n3 0 1 2\n"
    )
    rm = read_ply(ascii_ply)
    assert rm.view == "v3" and rm.faces.tolist() == [[0, 1, 2]] and rm.vertices[2].tolist() == [0, 1, 1]
    assert np.all(rm.quality == 0.5) and np.all(rm.row == -1) and np.all(rm.colors == 255)
    quad = tmp_path / "quad.ply"
    quad.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 1\n1 0 1\n1 1 1\n0 1 1\n4 0 1 2 3\n"
    )
    with pytest.raises(SlscanError, match="quad.ply: element 'face' has non-triangle faces"):
        read_ply(quad)
    path = write_ply(mesh, tmp_path / "cut.ply")
    path.write_bytes(path.read_bytes()[:-5])
    with pytest.raises(SlscanError, match="cut.ply: file is truncated"):
        read_ply(path)
    (tmp_path / "not.ply").write_text("hello")
    with pytest.raises(SlscanError, match="not a PLY file"):
        read_ply(tmp_path / "not.ply")


# --- the virtual tile, end to end ---------------------------------------------------------------


def test_tile_range_map(gray_tile_session, tmp_path: Path):
    session = gray_tile_session
    view = session.views[0]
    rig = session.calibration
    edges = decode_gray(session, view).edges
    points = triangulate(edges, rig.camera, RigPlanes(rig.projector))
    white = session.read_image(view, view.image_for("white"))
    rm = build_range_map(edges, points, white_image=white, camera=rig.camera, view=view.name)
    # a nearly complete grid: about two faces per vertex, every sample used
    assert rm.n_vertices > 0.99 * len(edges)
    assert rm.n_faces > 1.9 * rm.n_vertices
    assert _facing_camera(rm).all()
    truth = session.load_ground_truth(view)
    true_normal = np.nanmedian(truth.normal[truth.visibility == LIT], axis=0)
    true_normal /= np.linalg.norm(true_normal)
    angle = np.degrees(np.arccos(np.clip(rm.normals @ true_normal, -1, 1)))
    # 0.2 mm of point noise on ~3 mm spacing at this size tilts single faces by a few degrees
    assert np.median(angle) < 5 and np.percentile(angle, 90) < 8
    lit_white = white[truth.visibility == LIT].mean(axis=0)
    assert np.all(np.abs(np.median(rm.colors, axis=0) - lit_white) < 10)
    back = read_ply(write_ply(rm, tmp_path / "tile.ply"))
    assert back.n_faces == rm.n_faces and back.view == view.name


def test_samples_along_columns_mesh_on_their_own_grid():
    # the flat grid turned: stripes along camera rows, found along camera columns
    samples, points = _grid()
    cols, stripes = samples.row.astype(float) + 100, samples.stripe
    y = 50.0 + 2.0 * (stripes - 5) + 0.25
    down = StripeSamples(
        row=np.floor(y + 0.5).astype(np.int32), x=cols, projector_column=samples.projector_column,
        stripe=stripes, contrast=samples.contrast, saturated=samples.saturated, y=y,
        along_columns=np.ones(len(y), bool),
    )
    rm = _build(down, points)
    assert rm.n_faces == FLAT_FACES and _facing_camera(rm).all()
    # colour from the white image at the samples' own column (its value is x)
    assert set(rm.colors[:, 0].tolist()) == set(cols.astype(int).tolist())
    # mixed with the upright grid, the two are meshed apart
    both = StripeSamples.concatenate([samples, down])
    rm2 = _build(both, np.concatenate([points, points + [0, 0, 50]]))
    assert rm2.n_faces == 2 * FLAT_FACES
