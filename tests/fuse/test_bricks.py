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
    assert "--max-memory 'lots': expected a size such as 4GiB or 512MiB" in capsys.readouterr().err
