"""Volumetric fusion of synthetic range scans of a sphere, and simplification."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

import slscan.fuse as fuse_module
from slscan.errors import SlscanError
from slscan.fuse import (
    BLOCK_RESOLUTION,
    FuseConfig,
    Mesh,
    TsdfVolume,
    _block_keys,
    _compiled_update,
    canonical_order,
    estimate_blocks,
    fuse_scans,
    height_map,
    poisson_reconstruct,
    read_mesh,
    write_mesh,
)
from slscan.meshes import boundary_vertices
from slscan.register.rangescan import render_range_scan
from slscan.simplify import simplify_mesh

RADIUS = 50.0
DIRECTIONS = [
    [1, 0, 0],
    [-1, 0, 0],
    [0, 1, 0],
    [0, -1, 0],
    [0, 0, 1],
    [0, 0, -1],
    [1, 1, 1],
    [-1, -1, 1],
]


@pytest.fixture(scope="module")
def sphere_views():
    """Eight orthographic range scans of a 50 mm sphere, 1.3 mm pixels, 0.05 mm noise."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=RADIUS, resolution=120)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    scans, poses = [], {}
    for k, d in enumerate(DIRECTIONS):
        pose = looking_from(d)
        name = f"view{k}"
        scans.append(
            render_range_scan(
                v,
                f,
                pose,
                shape=(90, 90),
                pixel=1.3,
                name=name,
                noise=0.05,
                rng=np.random.default_rng(k),
            )
        )
        poses[name] = pose
    return scans, poses


@pytest.mark.parametrize("weighting", ["quality", "uniform"])
def test_fused_sphere_has_the_right_radius(sphere_views, weighting):
    scans, poses = sphere_views
    result = fuse_scans(scans, poses, config=FuseConfig(voxel_size=1.0, weighting=weighting))
    mesh = result.mesh
    assert result.n_scans == len(scans) and result.n_blocks > 0
    assert mesh.n_faces > 50_000
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(radius.mean() - RADIUS) < 0.5
    assert radius.std() < 0.1 and np.abs(radius - RADIUS).max() < 0.5
    outward = np.einsum("ij,ij->i", mesh.normals, mesh.vertices / radius[:, None])
    assert np.all(outward > 0.8)
    assert len(boundary_vertices(mesh.faces)) == 0  # eight views close the sphere


def test_scans_can_come_one_at_a_time(sphere_views):
    scans, poses = sphere_views
    lazily = fuse_scans(iter(scans), poses, config=FuseConfig(voxel_size=1.5), expected_blocks=100)
    at_once = fuse_scans(scans, poses, config=FuseConfig(voxel_size=1.5))
    assert lazily.n_blocks == at_once.n_blocks
    assert lazily.mesh.n_faces == at_once.mesh.n_faces
    a, b = (
        lazily.mesh.vertices,
        at_once.mesh.vertices,
    )  # block order may differ after the grid grows
    np.testing.assert_allclose(a[np.lexsort(a.T)], b[np.lexsort(b.T)], atol=1e-5)


def test_fusion_is_the_same_from_run_to_run(sphere_views):
    # open3d's threads order the extracted vertices anew each run; the mesh is put in one order
    scans, poses = sphere_views
    config = FuseConfig(voxel_size=2.0)
    first, again = (fuse_scans(scans, poses, config=config).mesh for _ in range(2))
    assert np.array_equal(first.vertices, again.vertices)
    assert np.array_equal(first.faces, again.faces)
    rng = np.random.default_rng(0)
    perm = rng.permutation(first.n_vertices)
    faces = np.roll(np.argsort(perm)[first.faces], 1, axis=1)  # same triangles, other corner first
    shuffled = Mesh(first.vertices[perm], faces[rng.permutation(first.n_faces)])
    same = canonical_order(shuffled)
    assert np.array_equal(same.vertices, first.vertices) and np.array_equal(same.faces, first.faces)


def _canonical_reference(vertices, faces):
    """canonical_order's definition, straight: lexsort of the positions, faces rotated to
    their lowest index, lexsort of the faces."""
    order = np.lexsort(vertices.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    f = rank[faces]
    f = np.take_along_axis(f, (np.argmin(f, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    return vertices[order], f[np.lexsort(f.T[::-1])]


@pytest.mark.parametrize("n_vertices", [5_000, 2**21 + 5])  # one face key, two
def test_canonical_order_is_the_lexicographic_order(n_vertices):
    rng = np.random.default_rng(n_vertices)
    # float32 positions (as open3d extracts them) with ties, signed zeros, tiny and huge values
    values = np.array([-2.5, -0.0, 0.0, 1e-40, -1e-40, 3e30, -3e30, 7.0], np.float32)
    vertices = rng.choice(values, size=(n_vertices, 3)).astype(np.float64)
    vertices[: n_vertices // 2] = rng.normal(size=(n_vertices // 2, 3)).astype(np.float32)
    faces = rng.integers(0, n_vertices, size=(20_000, 3))
    faces[:50] = faces[50:100]  # repeated faces
    got = canonical_order(Mesh(vertices, faces))
    want_vertices, want_faces = _canonical_reference(vertices, faces)
    assert np.array_equal(got.vertices, want_vertices)
    assert np.array_equal(got.faces, want_faces)
    doubles = rng.normal(size=(3000, 3))  # not float32: sorted as three float64 keys
    faces = rng.integers(0, 3000, size=(4000, 3))
    got = canonical_order(Mesh(doubles, faces))
    assert all(map(np.array_equal, (got.vertices, got.faces), _canonical_reference(doubles, faces)))


@pytest.mark.parametrize("reach", [0.5, 2.0, 3.3, 9.0])
def test_block_keys_are_the_blocks_within_reach_of_every_point(reach):
    # the blocks hit by every point moved by every combination of per-axis offsets
    # (np.linspace(-reach, reach, steps) each), computed point by point
    rng = np.random.default_rng(7)
    surface = rng.normal(size=(3000, 3))
    points = np.concatenate([
        30 * surface / np.linalg.norm(surface, axis=1, keepdims=True),  # dense on a sphere
        rng.uniform(-500, 500, size=(200, 3)),  # scattered
        np.round(rng.uniform(-40, 40, size=(500, 3)) / 4.0) * 4.0,  # on block boundaries
    ])
    block = 4.0
    steps = int(np.ceil(2 * reach / block)) + 1
    offsets = np.linspace(-reach, reach, steps)
    want = set()
    for p in points:
        per_axis = [np.floor((p[a] + offsets) / block).astype(np.int64) + 2**20 for a in range(3)]
        want.update(
            (int(x) << 42) | (int(y) << 21) | int(z)
            for x in per_axis[0] for y in per_axis[1] for z in per_axis[2]
        )
    got = _block_keys(points, block, reach)
    assert got.tolist() == sorted(want)


def test_block_estimate_bounds_memory(sphere_views):
    scans, poses = sphere_views
    blocks = estimate_blocks(scans, poses, voxel_size=1.0)
    result = fuse_scans(scans, poses, config=FuseConfig(voxel_size=1.0))
    assert result.n_blocks <= blocks * 1.05
    with pytest.raises(SlscanError, match="max_memory_gib"):
        fuse_scans(scans, poses, config=FuseConfig(voxel_size=1.0, max_memory_gib=0.001))


def test_fusion_checks_its_input(sphere_views):
    scans, poses = sphere_views
    with pytest.raises(SlscanError, match="no pose"):
        fuse_scans(scans, {})
    with pytest.raises(SlscanError, match="weighting"):
        fuse_scans(scans, poses, config=FuseConfig(weighting="loud"))
    with pytest.raises(SlscanError, match="voxel size"):
        fuse_scans(scans, poses, config=FuseConfig(voxel_size=0))


def _voxels(volume):
    """World centres (k, 512, 3), tsdf and weight (k, 512) of every allocated block's voxels."""
    hashmap = volume.grid.hashmap()
    buf = hashmap.active_buf_indices().numpy().astype(np.int64)
    keys = hashmap.key_tensor().numpy()[buf].astype(np.float64)
    k = np.arange(BLOCK_RESOLUTION, dtype=np.float64)
    lattice = np.stack(np.meshgrid(k, k, k, indexing="ij")[::-1], -1).reshape(-1, 3)  # x fastest
    centres = (keys[:, None, :] * BLOCK_RESOLUTION + lattice) * volume.voxel_size
    res3 = BLOCK_RESOLUTION**3
    tsdf = volume.grid.attribute("tsdf").numpy().reshape(-1, res3)[buf]
    weight = volume.grid.attribute("weight").numpy().reshape(-1, res3)[buf]
    return centres, tsdf, weight


HAVE_NUMBA = _compiled_update() is not None
UPDATES = [False, pytest.param(True, marks=pytest.mark.skipif(
    not HAVE_NUMBA, reason="numba (the fast extra) not installed"))]


@pytest.mark.parametrize("compiled", UPDATES, ids=["numpy", "numba"])
def test_every_voxel_gets_the_weighted_average_of_its_observations(sphere_views, compiled):
    # each voxel of the blocks near a scan: the height map sampled at its centre (bilinear
    # height and quality weight), truncated, averaged with the earlier scans' by weight
    scans, poses = sphere_views
    volume = TsdfVolume(1.0, truncation=3.0)
    trunc = 3.0
    maps = [height_map(s, poses[s.name], pixel=1.0) for s in scans[:3]]
    for depth in maps:
        volume.integrate(depth, chunk_blocks=7, compiled=compiled)  # chunks end inside the list
    centres, tsdf, weight = _voxels(volume)
    points = centres.reshape(-1, 3)
    num = np.zeros(len(points))
    den = np.zeros(len(points))
    count = np.zeros(len(points), int)
    for depth in maps:
        sdf, w = depth.sample(points)
        ok = (w > 0) & (sdf >= -trunc)
        num[ok] += np.minimum(sdf[ok] / trunc, 1.0) * w[ok]
        den[ok] += w[ok]
        count += ok
    seen = den > 0
    assert seen.mean() > 0.3 and (~seen).any()
    # voxels a scan's blocks hold but no scan saw keep the initial values
    np.testing.assert_array_equal(weight.reshape(-1)[~seen], 0.0)
    np.testing.assert_array_equal(tsdf.reshape(-1)[~seen], 1.0)
    np.testing.assert_allclose(weight.reshape(-1)[seen], den[seen], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(tsdf.reshape(-1)[seen], num[seen] / den[seen], atol=2e-5)
    assert (count >= 2).sum() > 10_000  # overlapping scans were averaged


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba (the fast extra) not installed")
def test_compiled_and_numpy_updates_agree_bit_for_bit(sphere_views):
    # every scan, with noise and quality weights: the same float32 operations in the same
    # order, so the same tsdf and weight in every voxel, run after run
    scans, poses = sphere_views
    maps = [height_map(s, poses[s.name], pixel=0.9) for s in scans]
    grids = []
    for compiled in (False, True, True):
        volume = TsdfVolume(0.9, truncation=4.0)
        for depth in maps:
            volume.integrate(depth, compiled=compiled)
        centres, tsdf, weight = _voxels(volume)
        order = np.lexsort(centres[:, 0].T)  # blocks by position (open3d's buffer order varies)
        grids.append((centres[order], tsdf[order], weight[order]))
    (c0, t0, w0), *others = grids
    assert (w0 > 0).sum() > 100_000 and (w0 > 1).sum() > 10_000  # observed, and overlapping
    for c, t, w in others:
        np.testing.assert_array_equal(c, c0)
        assert np.array_equal(t.view(np.uint32), t0.view(np.uint32))
        assert np.array_equal(w.view(np.uint32), w0.view(np.uint32))


def test_the_kernel_is_loaded_once_it_pays(sphere_views, monkeypatch):
    # numpy until the volume has updated COMPILED_FROM_BLOCKS blocks (loading numba costs
    # more than it saves on a small fusion), then the kernel; at once where it is loaded
    scans, poses = sphere_views
    maps = [height_map(s, poses[s.name], pixel=1.0) for s in scans[:3]]
    calls = []

    def load():
        calls.append("load")
        fuse_module._KERNEL.append(lambda *args: calls.append(len(args[2])))
        return fuse_module._KERNEL[0]

    monkeypatch.setattr(fuse_module, "_KERNEL", [])
    monkeypatch.setattr(fuse_module, "_compiled_update", load)
    volume = TsdfVolume(1.0)
    volume.integrate(maps[0])
    first = volume.blocks_updated
    assert calls == [] and first > 100 and (_voxels(volume)[2] > 0).sum() > 1000
    monkeypatch.setattr(fuse_module, "COMPILED_FROM_BLOCKS", first + 1)
    volume.integrate(maps[1])  # first < first + 1: numpy again
    assert calls == []
    before = volume.blocks_updated
    volume.integrate(maps[2])
    assert calls == ["load", volume.blocks_updated - before]  # the kernel, on every block
    monkeypatch.setattr(fuse_module, "_compiled_update", lambda: fuse_module._KERNEL[0])
    TsdfVolume(1.0).integrate(maps[0])  # loaded in this process: used from the start
    assert len(calls) == 3


def test_the_numpy_update_is_chosen_without_numba(sphere_views, monkeypatch):
    # the automatic choice follows what is installed; asking for the kernel without it fails
    scans, poses = sphere_views
    depth = height_map(scans[0], poses["view0"], pixel=1.0)
    monkeypatch.setattr(fuse_module, "COMPILED_FROM_BLOCKS", 0)
    monkeypatch.setattr(fuse_module, "_KERNEL", [None])
    volume = TsdfVolume(1.0)
    volume.integrate(depth)
    assert (_voxels(volume)[2] > 0).sum() > 1000  # updated, in numpy
    with pytest.raises(SlscanError, match="numba is not installed"):
        TsdfVolume(1.0).integrate(depth, compiled=True)


@pytest.mark.skipif(not HAVE_NUMBA, reason="numba (the fast extra) not installed")
def test_the_kernel_compiles_in_memory_where_it_cannot_be_cached():
    # numba refuses cache=True for a function whose source file it cannot cache beside
    # (here: none at all, as for a read-only install without a user cache folder)
    import types

    import numba

    from slscan._tsdf_numba import jit

    def twice(a):
        return 2 * a

    homeless = types.FunctionType(twice.__code__.replace(co_filename="<nowhere>"), {})
    with pytest.raises(RuntimeError, match="cannot cache"):
        numba.njit(cache=True)(homeless)
    assert jit(homeless)(np.arange(3)).tolist() == [0, 2, 4]


def test_the_estimated_grid_is_never_regrown(sphere_views):
    # open3d doubles (and copies) its hash map whenever one activation's keys, present or
    # not, would overflow it: only missing blocks are activated, so an estimate holds
    scans, poses = sphere_views
    blocks = estimate_blocks(scans, poses, voxel_size=1.0)
    volume = TsdfVolume(1.0, block_count=blocks)
    for s in scans:
        volume.integrate(height_map(s, poses[s.name], pixel=1.0))
    assert blocks * 0.9 < volume.n_blocks <= blocks
    assert volume.grid.hashmap().capacity() == blocks


def test_height_map_sees_the_scan(sphere_views):
    scans, poses = sphere_views
    depth = height_map(scans[0], poses["view0"], pixel=1.0)
    points = depth.surface_points()
    assert len(points) > 5000
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), RADIUS, atol=0.3)
    sdf, weight = depth.sample(points * 1.01)
    ok = weight > 0
    assert ok.mean() > 0.9
    assert np.all(sdf[ok] > 0)  # outside the sphere: in front of the surface


def test_poisson_alternative(sphere_views):
    scans, poses = sphere_views
    mesh = poisson_reconstruct(scans, poses, depth=7)
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert mesh.n_faces > 5000
    assert abs(radius.mean() - RADIUS) < 0.5


def test_mesh_file_round_trip(tmp_path):
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    mesh = Mesh(v, np.array([[0, 1, 2]]), np.tile(np.float32([0, 0, 1]), (3, 1)))
    write_mesh(mesh, tmp_path / "m.ply")
    back = read_mesh(tmp_path / "m.ply")
    np.testing.assert_allclose(back.vertices, v)
    np.testing.assert_array_equal(back.faces, [[0, 1, 2]])
    with pytest.raises(SlscanError, match="not found"):
        read_mesh(tmp_path / "none.ply")


# --- simplification ---------------------------------------------------------------------------


def bumpy_sheet(n: int = 240) -> Mesh:
    """An open height field 100 mm square with bumps: (n - 1)² × 2 faces."""
    x, y = np.meshgrid(np.linspace(0, 100, n), np.linspace(0, 100, n))
    z = 3 * np.sin(x / 7) * np.cos(y / 5) + 0.5 * np.sin(x / 2 + y / 3)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    return Mesh(vertices, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]))


@pytest.mark.parametrize("method", ["fast", "quadric"])
def test_simplify_reaches_the_target_and_keeps_the_boundary(method):
    mesh = bumpy_sheet()
    target = 8000
    out = simplify_mesh(mesh, target, method=method, preserve_boundary=True)
    assert abs(out.n_faces - target) <= 0.01 * target
    kept = out.vertices[boundary_vertices(out.faces)]
    original = mesh.vertices[boundary_vertices(mesh.faces)]
    # every boundary vertex of the open mesh is still there, at the same place
    rows = {tuple(p) for p in np.round(kept, 9)}
    assert all(tuple(p) in rows for p in np.round(original, 9))
    assert out.normals.shape == out.vertices.shape


def test_simplify_in_slabs_keeps_the_boundary_and_closes_the_cuts():
    mesh = bumpy_sheet()
    out = simplify_mesh(mesh, 8000, chunk_faces=30_000)  # 114k faces: 4 slabs, then a pass
    assert abs(out.n_faces - 8000) <= 80
    original = mesh.vertices[boundary_vertices(mesh.faces)]
    kept = out.vertices[boundary_vertices(out.faces)]
    # the cuts between slabs were welded: the only boundary left is the sheet's own
    assert len(kept) == len(original)
    assert {tuple(p) for p in np.round(kept, 9)} == {tuple(p) for p in np.round(original, 9)}


def test_simplify_without_boundary_preservation_moves_it():
    mesh = bumpy_sheet(120)
    out = simplify_mesh(mesh, 1000, method="fast", preserve_boundary=False)
    assert abs(out.n_faces - 1000) <= 10
    assert len(boundary_vertices(out.faces)) < len(boundary_vertices(mesh.faces))


def test_simplify_fused_sphere(sphere_views):
    scans, poses = sphere_views
    fused = fuse_scans(scans, poses, config=FuseConfig(voxel_size=1.5)).mesh
    out = simplify_mesh(fused, 5000)
    assert abs(out.n_faces - 5000) <= 50
    radius = np.linalg.norm(out.vertices, axis=1)
    assert abs(radius.mean() - RADIUS) < 0.5


def test_simplify_options():
    mesh = bumpy_sheet(20)
    assert simplify_mesh(mesh, 10**6) is mesh
    with pytest.raises(SlscanError, match="method"):
        simplify_mesh(mesh, 100, method="magic")
    with pytest.raises(SlscanError, match="at least 4"):
        simplify_mesh(mesh, 2)


def test_fuse_and_simplify_commands_write_a_meshlab_project_beside_the_mesh(sphere_views, tmp_path, capsys):
    """`slscan fuse` / `slscan simplify --out X.ply` write X.mlp, which MeshLab (pymeshlab)
    opens with the mesh at the identity (the mesh is in the object frame already)."""
    import pymeshlab

    from slscan.cli import main
    from slscan.register.meshlab import read_mlp, write_scan_project

    scans, poses = sphere_views
    aligned = write_scan_project(tmp_path / "aligned", scans[:3], poses)
    fused, simple = tmp_path / "fused.ply", tmp_path / "simple.ply"
    assert main(["fuse", str(aligned), "--voxel", "3", "--out", str(fused), "--quiet"]) == 0
    assert main(["simplify", str(fused), "--faces", "500", "--out", str(simple), "--quiet"]) == 0
    for mesh_file in (fused, simple):
        project = mesh_file.with_suffix(".mlp")
        ((named, matrix),) = read_mlp(project)
        assert named == mesh_file and np.array_equal(matrix, np.eye(4))
        ms = pymeshlab.MeshSet()
        ms.load_project(str(project))
        assert ms.mesh_number() == 1
        assert ms.current_mesh().face_number() == len(read_mesh(mesh_file).faces)
    capsys.readouterr()
    simple.unlink()  # the project left beside it is not replaced without --overwrite
    assert main(["simplify", str(fused), "--faces", "500", "--out", str(simple), "--quiet"]) == 2
    assert f"{simple.with_suffix('.mlp')}: exists (pass --overwrite" in " ".join(capsys.readouterr().err.split())
    assert not simple.exists()
    assert main(["simplify", str(fused), "--faces", "500", "--out", str(tmp_path / "s.mlp"), "--quiet"]) == 2
    assert "expected a mesh file" in capsys.readouterr().err
