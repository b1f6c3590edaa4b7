"""Fusion in spatial bricks (fuse_bricks) gives the single-volume mesh, under a memory cap."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.fuse import FuseConfig, fuse_bricks, fuse_scans
from slscan.meshes import boundary_vertices
from slscan.register.rangescan import render_range_scan

RADIUS = 20.0
DIRECTIONS = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
VOXEL = 0.8


@pytest.fixture(scope="module")
def sphere_views():
    """Six orthographic range scans of a 20 mm sphere off the origin, 0.8 mm pixels, noisy."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=60)
    v = np.asarray(sphere.vertices) + [3.1, -2.2, 1.7]  # brick planes cut it off-centre
    f = np.asarray(sphere.triangles)
    scans, poses = [], {}
    for k, d in enumerate(DIRECTIONS):
        pose = looking_from(d)
        name = f"view{k}"
        scans.append(render_range_scan(v, f, pose, shape=(64, 64), pixel=0.8, name=name, noise=0.05,
                                       rng=np.random.default_rng(k)))
        poses[name] = pose
    return scans, poses


@pytest.fixture(scope="module")
def single(sphere_views):
    scans, poses = sphere_views
    return fuse_scans(scans, poses, config=FuseConfig(voxel_size=VOXEL)).mesh


def _same_mesh(a, b) -> None:
    assert a.n_vertices == b.n_vertices and a.n_faces == b.n_faces
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.vertices, b.vertices, rtol=0, atol=1e-5)
    np.testing.assert_allclose(a.normals, b.normals, rtol=0, atol=1e-4)


@pytest.mark.parametrize("brick", [6.4, 12.8])  # one and two blocks of 8 voxels a side
def test_bricks_give_the_single_volume_mesh(sphere_views, single, brick):
    scans, poses = sphere_views
    result = fuse_bricks(scans, poses, config=FuseConfig(voxel_size=VOXEL, brick_size=brick))
    assert result.n_bricks > 8  # the sphere is cut into many bricks
    _same_mesh(result.mesh, single)
    # no seams: as closed as the single volume, no vertex twice
    assert len(boundary_vertices(result.mesh.faces)) == len(boundary_vertices(single.faces)) == 0
    keys = np.unique(result.mesh.vertices.astype(np.float32), axis=0)
    assert len(keys) == result.mesh.n_vertices


def test_bricks_are_deterministic_and_same_on_two_workers(sphere_views, single):
    scans, poses = sphere_views
    config = FuseConfig(voxel_size=VOXEL, brick_size=12.8)
    a = fuse_scans(scans, poses, config=config).mesh
    b = fuse_scans(scans, poses, config=config, executor=Executor(workers=2)).mesh
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    _same_mesh(b, single)


def test_a_cap_too_small_for_a_brick_names_it(sphere_views):
    scans, poses = sphere_views
    config = FuseConfig(voxel_size=VOXEL, brick_size=12.8, max_memory_gib=10 / 2**20)
    with pytest.raises(SlscanError, match=r"^brick \(-?\d+, -?\d+, -?\d+\) needs \d+ KiB, the cap is "
                                          r"10 KiB: lower --brick \(now 12.8 mm\)$"):
        fuse_bricks(scans, poses, config=config)


def test_fuse_command_in_bricks(sphere_views, tmp_path, capsys):
    """`slscan fuse --brick MM --workers 1` writes the single-volume mesh; a --max-memory too
    small for a brick is one line naming it, exit 2, nothing written."""
    from slscan.cli import main
    from slscan.fuse import read_mesh
    from slscan.register.meshlab import write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans, poses)
    out, one = tmp_path / "fused.ply", tmp_path / "one.ply"
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--workers", "1",
                 "--out", str(out), "--quiet"]) == 0
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--out", str(one), "--quiet"]) == 0
    _same_mesh(read_mesh(out), read_mesh(one))
    capsys.readouterr()
    small = tmp_path / "small.ply"
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--max-memory", "0.01MiB",
                 "--out", str(small), "--quiet"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "needs" in err and "KiB, the cap is 10 KiB: lower --brick (now 12.8 mm)" in err
    assert not small.exists() and not small.with_suffix(".mlp").exists()
    assert main(["fuse", str(aligned), "--brick", "12.8", "--max-memory", "lots", "--out", str(small)]) == 2
    assert "memory size 'lots': expected a size such as 4GiB" in capsys.readouterr().err


def _scratch_left(folder) -> list:
    return sorted(p.name for p in folder.iterdir() if "bricks-scratch" in p.name)


def test_tasks_carry_pieces_and_the_scratch_folder_goes(sphere_views, single, tmp_path, monkeypatch):
    """A brick task carries piece paths (no scan); the scratch folder beside the output is
    there while bricks run and gone after success and after a failure."""
    import slscan.fuse as fuse

    scans, poses = sphere_views
    seen = []
    real = fuse._fuse_brick

    def spy(task):
        assert task.scans == () and task.poses == {} and task.pieces
        assert all(p.endswith(".npz") and "/out.ply.bricks-scratch-" in p for p in task.pieces)
        seen.append(len(task.pieces))
        return real(task)

    monkeypatch.setattr(fuse, "_fuse_brick", spy)
    config = FuseConfig(voxel_size=VOXEL, brick_size=12.8)
    result = fuse_bricks(scans, poses, config=config, scratch_beside=tmp_path / "out.ply")
    _same_mesh(result.mesh, single)
    assert len(seen) == result.n_bricks and max(seen) <= len(scans)
    assert _scratch_left(tmp_path) == []

    def broken(task):
        raise SlscanError(f"brick {task.index}: failed on purpose")

    monkeypatch.setattr(fuse, "_fuse_brick", broken)
    with pytest.raises(SlscanError, match="failed on purpose"):
        fuse_bricks(scans, poses, config=config, scratch_beside=tmp_path / "out.ply")
    assert _scratch_left(tmp_path) == []


def test_a_missing_piece_is_one_line_naming_brick_file_and_host(sphere_views, tmp_path):
    import socket

    from slscan.fuse import _BrickTask, _fuse_brick

    scans, poses = sphere_views
    gone = tmp_path / "b0_0_0-s0.npz"
    task = _BrickTask((0, 0, 0), np.zeros(3, np.int64), np.full(3, 2, np.int64), (), {},
                      FuseConfig(voxel_size=VOXEL, brick_size=12.8), 100, (str(gone),))
    with pytest.raises(SlscanError) as info:
        _fuse_brick(task)
    assert str(info.value) == (f"brick (0, 0, 0): {gone}: not found on worker {socket.gethostname()}; "
                               "Dask workers need the fusion scratch folder at the same path")
    gone.write_bytes(b"PK\x03\x04 not a piece")
    with pytest.raises(SlscanError, match=r"^brick \(0, 0, 0\): .*b0_0_0-s0.npz: not a readable fusion piece"):
        _fuse_brick(task)


def test_bricks_read_a_project_one_scan_at_a_time(sphere_views, tmp_path):
    """From a MeshLab project, fusion in bricks holds one loaded scan at a time (the loader
    yields each after the previous one is gone), and gives the single-volume mesh."""
    import gc
    import weakref

    from slscan.register.command import iter_scans
    from slscan.register.meshlab import load_scan_project, write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans, poses)
    count, lazy, lazy_poses = iter_scans(aligned)
    assert count == len(scans) and lazy_poses == {}
    alive = weakref.WeakSet()
    most = []

    def watched():
        for scan in lazy:
            gc.collect()
            most.append(len(alive))  # loaded scans still alive when the next one comes
            alive.add(scan)
            yield scan
            del scan

    result = fuse_bricks(watched(), lazy_poses, config=FuseConfig(voxel_size=VOXEL, brick_size=12.8))
    assert most == [0] * len(scans)
    assert set(lazy_poses) == {s.name for s in scans}
    # the project's PLYs hold the scans to float32: the single volume of the same files
    _same_mesh(result.mesh, fuse_scans(*load_scan_project(aligned), config=FuseConfig(voxel_size=VOXEL)).mesh)


def test_fuse_command_in_bricks_with_a_broken_scan_file(sphere_views, tmp_path, capsys):
    """A scan file of the project that is missing or broken: one line naming it, exit 2,
    nothing written, no scratch folder left."""
    from slscan.cli import main
    from slscan.register.meshlab import write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans, poses)
    out = tmp_path / "fused.ply"
    victim = tmp_path / "aligned" / "view3.ply"
    victim.write_bytes(victim.read_bytes()[:200])
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--workers", "1",
                 "--out", str(out), "--quiet"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert str(victim) in err, err
    assert not out.exists() and not out.with_suffix(".mlp").exists() and _scratch_left(tmp_path) == []
    victim.unlink()
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--workers", "1",
                 "--out", str(out), "--quiet"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert str(victim) in err and "do not exist" in err, err
    assert not out.exists() and _scratch_left(tmp_path) == []


def test_the_fuse_stage_in_bricks_gives_the_command_mesh(sphere_views, tmp_path):
    """`slscan run`'s fuse stage with fuse.brick_size: the scans read one at a time, the
    single-volume mesh, no scratch folder left beside the stage's."""
    from slscan.executor import Executor
    from slscan.fuse import read_mesh
    from slscan.recipe.stages import StageContext, _run_fuse
    from slscan.register.meshlab import load_scan_project, write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans, poses)
    ctx = StageContext(out=tmp_path / "run" / "fuse", inputs={"aligned": aligned.parent},
                       executor=Executor(workers=1))
    summary = _run_fuse(ctx, FuseConfig(voxel_size=VOXEL, brick_size=12.8))
    one = fuse_scans(*load_scan_project(aligned), config=FuseConfig(voxel_size=VOXEL)).mesh
    _same_mesh(read_mesh(ctx.out / "mesh.ply"), one)
    assert summary["faces"] == one.n_faces
    assert _scratch_left(tmp_path / "run") == []
