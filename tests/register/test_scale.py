"""Registration's pairwise alignments on helper processes: the same poses as in this process."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

from slscan.cli import main
from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.register.multiview import PairTask, align_pair_task, register_scans
from slscan.register.pairwise import PairwiseConfig
from slscan.register.rangescan import (
    load_range_scan,
    raycasting_scene,
    render_range_scan,
    scan_source,
    write_range_scan,
)
from slscan.virtual.scenes import builtin_object


@pytest.fixture(scope="module")
def blob_files(tmp_path_factory):
    """Four views of a bumpy blob written as range-scan PLYs and loaded back (so that they
    have files to be loaded from), their true poses, and the same views perturbed by a few
    degrees / mm (the reference, view0, kept)."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=40)
    v = np.asarray(sphere.vertices)
    v = v * 40.0 * (1 + 0.1 * np.sin(5 * v[:, 0] + 1) * np.cos(6 * v[:, 1]) + 0.06 * np.sin(7 * v[:, 2]))[:, None]
    folder = tmp_path_factory.mktemp("blob")
    scans, truth, perturbed = [], {}, {}
    rng = np.random.default_rng(3)
    for k, d in enumerate([[1, 0, 0.3], [0, 1, 0.3], [-1, 0, 0.3], [0, -1, 0.3]]):
        pose = looking_from(d)
        name = f"view{k}"
        scan = render_range_scan(v, np.asarray(sphere.triangles), pose, shape=(60, 60), pixel=1.6, name=name)
        scans.append(load_range_scan(write_range_scan(scan, folder / f"{name}.ply")))
        truth[name] = pose
        turn = np.eye(4)
        if k:
            axis = rng.normal(size=3)
            turn[:3, :3] = o3d.geometry.get_rotation_matrix_from_axis_angle(axis / np.linalg.norm(axis) * np.radians(3))
            turn[:3, 3] = rng.uniform(-2, 2, 3)
        perturbed[name] = turn @ pose
    return scans, truth, perturbed


@pytest.fixture(scope="module")
def figurine_files(tmp_path_factory):
    """The built-in figurine from 6 sides, 60 degrees apart, 80 x 80 samples each (as in
    test_freehand, smaller), written and loaded back; and their true poses."""
    scene = builtin_object(detail=0.5)
    v = np.asarray(scene.vertices, float)
    mesh = raycasting_scene(v - (v.min(axis=0) + v.max(axis=0)) / 2, np.asarray(scene.triangles))
    folder = tmp_path_factory.mktemp("figurine")
    scans, truth = [], {}
    for k in range(6):
        a = 2 * np.pi * k / 6
        pose = looking_from([np.sin(a), -0.35, np.cos(a)], 700.0)
        scan = render_range_scan(None, None, pose, shape=(80, 80), focal=128.0, name=f"v{k}", scene=mesh,
                                 noise=0.1, rng=np.random.default_rng(k))
        scans.append(load_range_scan(write_range_scan(scan, folder / f"v{k}.ply")))
        truth[f"v{k}"] = pose
    return scans, truth


def _same(a, b) -> float:
    """Largest difference between two registrations' poses (the same scans, rejections and
    scans left out, else an assertion fails)."""
    assert set(a.poses) == set(b.poses) and a.left_out == b.left_out
    assert [(r.source, r.target, r.reason) for r in a.rejected] == [(r.source, r.target, r.reason) for r in b.rejected]
    assert [(p.source, p.target) for p in a.pairs] == [(p.source, p.target) for p in b.pairs]
    return max(float(np.abs(a.poses[k] - b.poses[k]).max()) for k in a.poses)


@pytest.mark.parametrize("start", ["poses", "free-hand"])
def test_pairs_on_two_workers_give_the_poses_of_one_process(blob_files, figurine_files, start):
    """With recorded poses (ICP per pair) and free-hand (feature hypotheses, verification
    per pair): the pairs on this process and a helper, the poses as when all run here."""
    if start == "poses":
        scans, truth, poses = blob_files
    else:
        (scans, truth), poses = figurine_files, None
    assert all(scan_source(s) is not None for s in scans)  # sent to the workers by path
    here = register_scans(scans, initial_poses=poses)
    there = register_scans(scans, initial_poses=poses, executor=Executor(workers=2))
    assert set(here.poses) == set(truth), here.left_out  # a working registration is compared
    assert _same(here, there) <= 1e-9
    gauge = truth[here.reference] @ np.linalg.inv(here.poses[here.reference])
    for name, pose in here.poses.items():
        assert np.abs(gauge @ pose - truth[name])[:3, 3].max() < 3.0, name


def test_scans_made_in_memory_go_to_the_workers_whole(blob_files):
    scans, _, perturbed = blob_files
    made = [dataclasses.replace(s) for s in scans]  # no file behind them
    assert scan_source(made[0]) is None
    here = register_scans(made, initial_poses=perturbed)
    assert _same(here, register_scans(made, initial_poses=perturbed, executor=Executor(workers=2))) <= 1e-9


def test_a_worker_that_reads_another_file_says_so(blob_files, tmp_path):
    scans, truth, _ = blob_files
    path = tmp_path / "view0.ply"
    write_range_scan(scans[1], path)  # another scan where view0 should be
    task = PairTask(run="other-run", i=0, j=1, scans=((str(path), "mm"), scan_source(scans[1])),
                    names=("view0", "view1"), n_vertices=(scans[0].n_vertices, scans[1].n_vertices),
                    init=np.linalg.inv(truth["view1"]) @ truth["view0"], first=PairwiseConfig(voxel_sizes=(3.2,)),
                    fine=PairwiseConfig(), config=register_scans.__kwdefaults__["config"], spacing=1.6,
                    feature_voxel=6.4)
    with pytest.raises(SlscanError, match="view0.ply.*same files at the same paths"):
        align_pair_task(task)


def test_pairs_on_a_dask_cluster_give_the_poses_of_one_process(blob_files):
    distributed = pytest.importorskip("distributed")
    scans, _, perturbed = blob_files
    here = register_scans(scans, initial_poses=perturbed)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        there = register_scans(scans, initial_poses=perturbed, executor=Executor(scheduler=cluster.scheduler_address))
    assert _same(here, there) <= 1e-9


def test_register_command_takes_workers(figurine_files, tmp_path):
    scans, _ = figurine_files
    folder = Path(scan_source(scans[0])[0]).parent  # the figurine's PLYs: registered free-hand
    poses = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        assert main(["register", str(folder), "--out", str(out), "--workers", str(workers), "--quiet"]) == 0
        poses[workers] = json.loads((out / "registration.json").read_text())["poses"]
    assert set(poses[1]) == {s.name for s in scans}
    assert max(np.abs(np.subtract(poses[1][k], poses[2][k])).max() for k in poses[1]) <= 1e-9


def test_a_worker_keeps_a_bounded_number_of_scans(blob_files, monkeypatch):
    """Past ``CACHED_SCANS`` the least recently used scan's inputs are dropped (and made
    again when needed: the same poses)."""
    from slscan.register import multiview

    scans, _, perturbed = blob_files
    here = register_scans(scans, initial_poses=perturbed)
    monkeypatch.setattr(multiview, "CACHED_SCANS", 2)
    assert _same(here, register_scans(scans, initial_poses=perturbed)) <= 1e-9
    task = PairTask(run="bounded", i=0, j=1, scans=(scans[0], scans[1]), names=("view0", "view1"),
                    n_vertices=(0, 0), init=None, first=PairwiseConfig(), fine=PairwiseConfig(),
                    config=register_scans.__kwdefaults__["config"], spacing=1.0, feature_voxel=4.0)
    for k in range(4):
        multiview._cached(task, "clouds", k, lambda k=k: k)
    assert sorted(multiview._cache["clouds"]) == [2, 3] and multiview._cache["used"] == [2, 3]
    multiview._seed_cache(None, ())


class _CountingExecutor(Executor):
    """A fake executor: counts the tasks each map is given, then runs them as the real one."""

    calls: list[int] = []

    def map(self, fn, items):
        items = list(items)
        self.calls.append(len(items))
        return super().map(fn, items)


def test_the_recipe_register_stage_hands_its_pairs_to_the_run_executor(figurine_files, tmp_path):
    from slscan.recipe.stages import RegisterConfig, StageContext, _run_register

    scans, _ = figurine_files
    folder = Path(scan_source(scans[0])[0]).parent
    _CountingExecutor.calls.clear()
    summary = _run_register(StageContext(out=tmp_path / "aligned", inputs={}, executor=_CountingExecutor(workers=2)),
                            RegisterConfig(source=str(folder), use_poses=False))
    assert summary["aligned"] == len(scans)
    assert _CountingExecutor.calls == [len(scans) * (len(scans) - 1) // 2]  # every pair, free-hand
