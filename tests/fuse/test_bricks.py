"""Fusion in spatial bricks (fuse_bricks) gives the single-volume mesh, under a memory cap."""

from __future__ import annotations

import re

import numpy as np
import pytest
from synthetic_poses import sphere_scans

from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.fuse import FuseConfig, fuse_bricks, fuse_scans
from slscan.meshes import boundary_vertices

RADIUS = 20.0
VOXEL = 0.8


@pytest.fixture(scope="module")
def sphere_views():
    """Six orthographic range scans of a 20 mm sphere off the origin, 0.8 mm pixels, noisy."""
    return sphere_scans(shape=(64, 64), pixel=0.8, radius=RADIUS)


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


def test_fuse_command_in_bricks(sphere_views, tmp_path, capsys, monkeypatch):
    """`slscan fuse --brick MM --workers 1` streams the single-volume mesh (up to order) to the PLY
    and logs it; a mesh over the log's limit is not logged, and says so; a --max-memory too
    small for a brick is one line naming it, exit 2, nothing written."""
    from rerun.chunk import RrdReader

    from slscan import fuse_stream
    from slscan.cli import main
    from slscan.fuse import canonical_order, read_mesh
    from slscan.register.meshlab import write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans, poses)
    out, one, rrd = tmp_path / "fused.ply", tmp_path / "one.ply", tmp_path / "fuse.rrd"
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--workers", "1",
                 "--out", str(out), "--quiet", "--save", str(rrd)]) == 0
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--out", str(one), "--quiet"]) == 0
    _same_mesh(canonical_order(read_mesh(out)), read_mesh(one))
    assert out.with_suffix(".mlp").is_file() and re.search(r"in \d+ bricks, streamed", " ".join(capsys.readouterr().err.split()))
    assert "/object/model/fused" in {c.entity_path for c in RrdReader(rrd).stream().to_chunks()}
    monkeypatch.setattr(fuse_stream, "LOG_MAX_FACES", 10)
    big = tmp_path / "big.ply"
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--out", str(big), "--quiet",
                 "--save", str(tmp_path / "big.rrd")]) == 0
    said = " ".join(capsys.readouterr().err.split())
    assert "is too large to log to Rerun (more than 10); the simplified model is logged" in said
    logged = {c.entity_path for c in RrdReader(tmp_path / "big.rrd").stream().to_chunks()}
    assert "/object/model/fused" not in logged
    small = tmp_path / "small.ply"
    assert main(["fuse", str(aligned), "--voxel", str(VOXEL), "--brick", "12.8", "--max-memory", "0.01MiB",
                 "--out", str(small), "--quiet"]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "needs" in err and "KiB, the cap is 10 KiB: lower --brick (now 12.8 mm)" in err
    assert not small.exists() and not small.with_suffix(".mlp").exists()
    assert main(["fuse", str(aligned), "--brick", "12.8", "--max-memory", "lots", "--out", str(small)]) == 2
    assert "--max-memory 'lots': expected a size such as 4GiB or 512MiB" in capsys.readouterr().err


def test_streamed_bricks_write_the_same_mesh(sphere_views, single, tmp_path):
    """fuse_bricks(out=...) writes the in-memory bricks' mesh, which is the single volume's
    (test above), up to order, with no vertex twice,
    closed, the same bytes on two runs (one on 2 local workers), and leaves no scratch behind."""
    import pymeshlab

    from slscan.fuse import canonical_order, read_mesh
    from slscan.simplify_bricks import ply_layout

    scans, poses = sphere_views
    config = FuseConfig(voxel_size=VOXEL, brick_size=12.8)
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    result = fuse_bricks(scans, poses, config=config, out=a)
    assert result.mesh is None and result.written.path == a and result.n_bricks > 8
    assert result.written.merged > 0  # vertices on brick planes were found twice and merged
    back = read_mesh(a)
    assert (back.n_vertices, back.n_faces) == (result.written.n_vertices, result.written.n_faces)
    _same_mesh(canonical_order(back), single)
    assert len(np.unique(back.vertices.astype(np.float32), axis=0)) == back.n_vertices
    assert len(boundary_vertices(back.faces)) == 0
    layout = ply_layout(a)  # the out-of-core simplification reads it by memory map
    assert (layout.n_vertices, layout.n_faces) == (back.n_vertices, back.n_faces)
    ms = pymeshlab.MeshSet()  # MeshLab's reader
    ms.load_new_mesh(str(a))
    assert (ms.current_mesh().vertex_number(), ms.current_mesh().face_number()) == (back.n_vertices, back.n_faces)
    fuse_bricks(scans, poses, config=config, out=b, executor=Executor(workers=2))
    assert a.read_bytes() == b.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply", "b.ply"]


def test_a_failing_brick_leaves_no_output_and_no_scratch(sphere_views, tmp_path, monkeypatch):
    """A fake failure of the fourth brick, after three wrote their pieces: nothing is written
    at --out and the scratch folder is gone."""
    from slscan import fuse

    scans, poses = sphere_views
    out = tmp_path / "fused.ply"
    real, written = fuse._fuse_brick, []

    def fails_fourth(task):
        if len(written) == 3:
            raise SlscanError(f"brick {task.index}: fake failure")
        result = real(task)
        written.append(result.piece)
        return result

    monkeypatch.setattr(fuse, "_fuse_brick", fails_fourth)
    with pytest.raises(SlscanError, match="fake failure"):
        fuse_bricks(scans, poses, config=FuseConfig(voxel_size=VOXEL, brick_size=12.8), out=out)
    assert len(written) == 3 and all(p.parent.parent == tmp_path for p in written)
    assert list(tmp_path.iterdir()) == []


def test_recipe_fuse_stage_in_bricks_streams_mesh_ply(sphere_views, tmp_path, monkeypatch, caplog):
    """The recipe's fuse stage with fuse.brick_size writes mesh.ply (the single-volume mesh up to
    order) and mesh.mlp through the streamed path, and logs the mesh unless it is over the limit."""
    import rerun as rr
    from rerun.chunk import RrdReader

    from slscan import fuse_stream
    from slscan.fuse import canonical_order, read_mesh
    from slscan.recipe.stages import StageContext, _run_fuse
    from slscan.register.meshlab import load_scan_project, write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans, poses)
    config = FuseConfig(voxel_size=VOXEL, brick_size=12.8)
    rec = rr.RecordingStream("slscan-test")
    rec.save(tmp_path / "stage.rrd")
    ctx = StageContext(out=tmp_path / "fuse", inputs={"aligned": aligned.parent}, rec=rec,
                       executor=Executor(workers=1))
    summary = _run_fuse(ctx, config)
    back = read_mesh(ctx.out / "mesh.ply")
    one = fuse_scans(*load_scan_project(aligned), config=FuseConfig(voxel_size=VOXEL)).mesh  # as read back
    assert summary == {"faces": one.n_faces, "vertices": one.n_vertices}
    _same_mesh(canonical_order(back), one)
    assert sorted(p.name for p in ctx.out.iterdir()) == ["mesh.mlp", "mesh.ply"]
    rec.disconnect()  # closes the file (with its footer)
    assert "/object/model/fused" in {c.entity_path for c in RrdReader(tmp_path / "stage.rrd").stream().to_chunks()}
    monkeypatch.setattr(fuse_stream, "LOG_MAX_FACES", 10)
    with caplog.at_level("WARNING"):
        _run_fuse(ctx, config)
    assert "is too large to log to Rerun (more than 10); the simplified model is logged" in caplog.text


def test_streamed_bricks_refuse_a_missing_scratch_and_a_non_ply(sphere_views, tmp_path):
    """A worker that does not see the scratch folder, and an --out that is not a PLY: one line each."""
    from slscan.fuse import Mesh
    from slscan.fuse_stream import write_piece

    mesh = Mesh(np.eye(3), np.array([[0, 1, 2]]))
    with pytest.raises(SlscanError, match=r"nowhere: the bricks' scratch folder is not there on this worker "
                                          r"\(brick \(1, 2, 3\)\); every worker must see"):
        write_piece(tmp_path / "nowhere", (1, 2, 3), mesh)
    assert not (tmp_path / "nowhere").exists()
    scans, poses = sphere_views
    with pytest.raises(SlscanError, match=r"fused.obj: fusion in bricks streams a binary PLY"):
        fuse_bricks(scans, poses, config=FuseConfig(voxel_size=VOXEL, brick_size=12.8), out=tmp_path / "fused.obj")
    assert list(tmp_path.iterdir()) == []


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
                      FuseConfig(voxel_size=VOXEL, brick_size=12.8), 100, pieces=(str(gone),))
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

