"""Out-of-core simplification in bricks (slscan.simplify_bricks) against the in-core result,
on synthetic spheres with a known surface."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from slscan.cli import main
from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.fuse import Mesh, read_mesh, write_mesh
from slscan.ply import write_triangle_ply
from slscan.simplify import simplify_mesh
from slscan.simplify_bricks import (
    boundary_edges,
    parse_memory,
    ply_layout,
    simplify_bricks,
    surface_distance,
)

RADIUS = 50.0


def _sphere(resolution: int = 60, *, open_cap: bool = False) -> Mesh:
    m = o3d.geometry.TriangleMesh.create_sphere(RADIUS, resolution=resolution)
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int64)
    if open_cap:  # cut the top off: an open boundary the bricks must keep
        f = f[v[f].mean(1)[:, 2] < 0.6 * RADIUS]
        used, f = np.unique(f, return_inverse=True)
        v, f = v[used], f.reshape(-1, 3)
    return Mesh(v, f)


def _radial_error(mesh: Mesh) -> float:
    return float(np.abs(np.linalg.norm(mesh.vertices, axis=1) - RADIUS).max())


@pytest.mark.parametrize("open_cap", [False, True])
def test_bricks_match_the_in_core_result(tmp_path, open_cap):
    src = _sphere(open_cap=open_cap)
    path = write_mesh(src, tmp_path / "in.ply")
    target = src.n_faces // 8
    report = simplify_bricks(path, tmp_path / "out.ply", target, bricks=8)
    out = read_mesh(tmp_path / "out.ply")
    assert report.mode == "bricks" and report.grid == (2, 2, 2) and len(report.bricks) == 8
    assert sum(b.faces_in for b in report.bricks) == src.n_faces
    assert report.faces_out == out.n_faces and abs(out.n_faces - target) <= 0.02 * target
    # no cracks: the open boundary of the input is all the output has (a closed sphere: none)
    assert boundary_edges(out.faces) == boundary_edges(src.faces)
    # stitched on global ids: no vertex twice, none unused
    assert len(np.unique(out.vertices, axis=0)) == out.n_vertices
    assert len(np.unique(out.faces)) == out.n_vertices
    incore = simplify_mesh(src, target)
    assert surface_distance(out, incore)["mean"] < 0.2  # mm, on a 50 mm sphere of edges ~6 mm
    # as close to the input as the in-core result: no sliver-collapsed brick interiors
    assert surface_distance(out, src)["max"] < 1.5 * surface_distance(incore, src)["max"]
    assert _radial_error(out) < 2 * _radial_error(incore)  # without the border allowance: 10x


def test_two_workers_give_the_same_mesh(tmp_path):
    src = _sphere(40)
    path = write_mesh(src, tmp_path / "in.ply")
    simplify_bricks(path, tmp_path / "a.ply", 600, bricks=8)
    simplify_bricks(path, tmp_path / "b.ply", 600, bricks=8, executor=Executor(workers=2))
    a, b = read_mesh(tmp_path / "a.ply"), read_mesh(tmp_path / "b.ply")
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.vertices, b.vertices)


def test_a_brick_over_the_cap_is_one_clear_line(tmp_path):
    path = write_mesh(_sphere(40), tmp_path / "in.ply")
    with pytest.raises(SlscanError, match=r"in\.ply: brick \d+ \([\d,]+ faces, 30 mm\) needs about .* "
                                          r"> --max-memory 10\.0 KiB; use a smaller --brick"):
        simplify_bricks(path, tmp_path / "out.ply", 500, brick_mm=30, max_memory=parse_memory("10KiB"))
    assert not (tmp_path / "out.ply").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["in.ply"]  # scratch removed


def test_vertices_at_a_border_vertex_position_are_welded(tmp_path):
    """Marching cubes leaves a few vertices at one position. A brick whose inner vertex sits
    where a border vertex is (here: a second layer of the lowest brick's faces on copies of
    their vertices) is simplified and stitched, not refused as "moved a locked vertex"."""
    src = _sphere(40)
    lo = src.vertices.min(0)
    edge = RADIUS  # brick_mm: 2 x 2 x 2 bricks, faces by their centroid as simplify_bricks does
    brick = np.floor((src.vertices[src.faces].mean(1) - lo) / edge).astype(int)
    corner = src.faces[(brick == 0).all(1)]
    used, inner = np.unique(corner, return_inverse=True)
    v = np.concatenate([src.vertices, src.vertices[used]])
    f = np.concatenate([src.faces, inner.reshape(-1, 3) + src.n_vertices])
    path = write_mesh(Mesh(v, f), tmp_path / "in.ply")
    report = simplify_bricks(path, tmp_path / "out.ply", 1500, brick_mm=edge)
    out = read_mesh(tmp_path / "out.ply")
    assert report.faces_out == out.n_faces and abs(out.n_faces - 1500) <= 0.05 * 1500
    assert surface_distance(out, src)["max"] < 3.0  # mm, on the 50 mm sphere


def test_a_cap_alone_picks_bricks_that_fit_it(tmp_path):
    """--max-memory without --brick/--bricks: as many bricks as keep each under the cap
    (the default 8 would be refused here)."""
    from slscan.simplify_bricks import TASK_BASE_BYTES, TASK_BYTES_PER_FACE, bricks_for

    src = _sphere(60)
    path = write_mesh(src, tmp_path / "in.ply")
    cap = TASK_BASE_BYTES + src.n_faces // 16 * TASK_BYTES_PER_FACE  # a sixteenth of the faces per task
    with pytest.raises(SlscanError, match="use a smaller --brick"):
        simplify_bricks(path, tmp_path / "out.ply", 500, bricks=8, max_memory=cap)
    assert bricks_for(src.n_faces, cap) == 64
    report = simplify_bricks(path, tmp_path / "out.ply", 500, max_memory=cap)
    assert len(report.bricks) > 8 and max(b.faces_in for b in report.bricks) <= src.n_faces // 16
    assert bricks_for(10, 4 << 30) == 8 and bricks_for(10**12, 1 << 30) == 4096


def test_only_binary_triangle_ply(tmp_path):
    ascii_ply = tmp_path / "a.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\n"
                         "property list uchar int vertex_indices\nend_header\n")
    with pytest.raises(SlscanError, match=r"a\.ply: PLY format 'ascii 1.0': expected binary"):
        ply_layout(ascii_ply)
    verts = np.zeros(3, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    write_triangle_ply(tmp_path / "bad.ply", verts, np.array([[0, 1, 7]]), [])
    with pytest.raises(SlscanError, match=r"bad\.ply: faces 0\.\.0 refer to vertices outside 0\.\.2"):
        simplify_bricks(tmp_path / "bad.ply", tmp_path / "out.ply", 4)
    assert not (tmp_path / "out.ply").exists()
    with pytest.raises(SlscanError, match="--max-memory 'lots': expected a size such as 4GiB or 512MiB"):
        parse_memory("lots")


def test_cli_says_which_path_it_took(tmp_path, capsys):
    path = write_mesh(_sphere(40), tmp_path / "in.ply")
    assert main(["simplify", str(path), "--out", str(tmp_path / "a.ply"), "--faces", "500", "--quiet"]) == 0
    said = capsys.readouterr()
    assert "simplify: in-core (6,240 faces, at most 10,000,000)" in said.out + said.err
    assert main(["simplify", str(path), "--out", str(tmp_path / "b.ply"), "--faces", "500", "--bricks", "8",
                 "--workers", "1", "--against", str(tmp_path / "a.ply")]) == 0
    said = capsys.readouterr()
    out = said.out + said.err
    assert "simplify: bricks (8 of grid 2x2x2): 6,240 ->" in out and "distance to" in out
    # the in-core estimate over --max-memory sends it to bricks
    assert main(["simplify", str(path), "--out", str(tmp_path / "c.ply"), "--faces", "500",
                 "--max-memory", "200MiB"]) == 0
    said = capsys.readouterr()
    assert "simplify: bricks (" in said.out + said.err
    assert read_mesh(tmp_path / "c.ply").n_faces <= 500


def test_a_brick_whose_files_a_worker_cannot_see_is_one_line(tmp_path):
    """A Dask worker without the caller's paths: the brick task names the file it misses."""
    from slscan.simplify_bricks import BrickTask, _simplify_brick

    path = write_mesh(_sphere(20), tmp_path / "in.ply")
    task = BrickTask(3, ply_layout(path), tmp_path / "gone" / "brick0003.faces", tmp_path / "gone" / "shared.bool",
                     tmp_path / "gone" / "brick0003.npz", 100, 6.0)
    with pytest.raises(SlscanError, match=r"gone/brick0003\.faces: not found on worker .* \(brick 3\); the workers "
                                          r"need brick files in the scratch folder at the same path"):
        _simplify_brick(task)
