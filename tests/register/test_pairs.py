"""Which pairs registration aligns: each scan's k best candidates, never pairs that cannot
overlap, and a graph that stays connected."""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

from slscan.register import multiview
from slscan.register.multiview import (
    MultiviewConfig,
    pair_overlaps,
    register_scans,
    select_pairs,
    view_angle_deg,
)
from slscan.register.pairwise import pose_error, rigid_transform
from slscan.register.rangescan import raycasting_scene, render_range_scan

RING = 10  # views round the blob at one elevation, plus one from above and one from below
_REGISTER_PAIR = multiview.register_pair


def _connected(nodes, pairs) -> bool:
    reached, frontier = {nodes[0]}, [nodes[0]]
    while frontier:
        a = frontier.pop()
        for i, j in pairs:
            for x, y in ((i, j), (j, i)):
                if x == a and y not in reached:
                    reached.add(y)
                    frontier.append(y)
    return reached == set(nodes)


@pytest.fixture(scope="module")
def ring_views():
    """12 orthographic range scans of a bumpy blob, their true poses and start poses off
    by up to 2 degrees / 2 mm (view00 kept)."""
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=60)
    v = np.asarray(sphere.vertices)
    v = v * 40.0 * (1 + 0.1 * np.sin(5 * v[:, 0] + 1) * np.cos(6 * v[:, 1])
                    + 0.06 * np.sin(7 * v[:, 2]))[:, None]
    scene = raycasting_scene(v, np.asarray(sphere.triangles))
    directions = [[math.cos(a), math.sin(a), 0.3]
                  for a in np.linspace(0, 2 * math.pi, RING, endpoint=False)]
    directions += [[0.1, 0.0, 1.0], [0.0, 0.1, -1.0]]
    rng = np.random.default_rng(3)
    scans, truth, start = [], {}, {}
    for k, d in enumerate(directions):
        name = f"view{k:02d}"
        truth[name] = looking_from(d)
        scans.append(render_range_scan(None, None, truth[name], shape=(80, 80), pixel=1.2,
                                       name=name, scene=scene))
        motion = rigid_transform(rng.uniform(-1, 1, 3) * math.radians(2) / math.sqrt(3),
                                 rng.uniform(-1, 1, 3) * 2 / math.sqrt(3))
        start[name] = truth[name] if k == 0 else motion @ truth[name]
    return scans, truth, start


def test_select_pairs_keeps_each_scans_best_and_joins_the_pieces():
    # two tight groups {0, 1, 2} and {3, 4, 5}, joined only by weak candidates
    scores = {(0, 1): 0.9, (0, 2): 0.8, (1, 2): 0.85, (3, 4): 0.9, (3, 5): 0.8, (4, 5): 0.7,
              (2, 3): 0.3, (1, 4): 0.25, (0, 5): 0.2}
    kept = select_pairs(scores, 1)
    # each scan's best: 0-1, 1-0, 2-1, 3-4, 4-3, 5-3; then the best link between the groups
    assert kept == [(0, 1), (1, 2), (2, 3), (3, 4), (3, 5)]
    assert _connected(list(range(6)), kept)
    assert set(select_pairs(scores, 2)) >= {(0, 1), (0, 2), (1, 2), (3, 4), (3, 5), (4, 5)}
    assert select_pairs(scores, 0) == sorted(scores)  # 0: every candidate
    # a scan with no candidate stays out; the others are still joined
    assert select_pairs({(0, 1): 0.5}, 3) == [(0, 1)]


def test_pair_overlaps_leaves_out_pairs_that_cannot_overlap():
    rng = np.random.default_rng(0)
    plate = np.c_[rng.uniform(0, 50, (2000, 2)), np.zeros(2000)]
    up, down = np.tile([0.0, 0.0, 1.0], (2000, 1)), np.tile([0.0, 0.0, -1.0], (2000, 1))
    clouds = {0: plate, 1: plate + [25.0, 0.0, 0.5], 2: plate, 3: plate + [500.0, 0.0, 0.0]}
    normals = {0: up, 1: up, 2: down, 3: up}
    directions = {0: np.array([0.0, 0.0, 1.0]), 1: np.array([0.0, 0.6, 0.8]),
                  2: np.array([0.0, 0.0, -1.0]), 3: np.array([0.0, 0.0, 1.0])}
    out = pair_overlaps(clouds, normals, 2.0, directions=directions, max_view_angle=150.0)
    assert (0, 2) not in out  # seen from opposite sides (180 degrees)
    assert out[(1, 2)][1] == 0.0  # 143 degrees: looked at, but no sample on the same side
    assert (0, 3) not in out and (1, 3) not in out and (2, 3) not in out  # boxes apart
    overlap, same_side = out[(0, 1)]
    assert overlap == pytest.approx(0.52, abs=0.05) and same_side == pytest.approx(overlap)
    # without the view gate the plate's two sides overlap in space, but not on one side
    both = pair_overlaps(clouds, normals, 2.0)
    assert both[(0, 2)][0] == 1.0 and both[(0, 2)][1] == 0.0
    assert view_angle_deg(directions[0], directions[2]) == pytest.approx(180.0)
    # looking up a stride of the samples estimates the same fraction
    sub = pair_overlaps(clouds, normals, 2.0, max_samples=200)
    assert sub[(0, 1)][0] == pytest.approx(overlap, abs=0.06)
    # unless it lies near the overlap a candidate needs: then every sample is looked up
    assert sub[(0, 1)] != both[(0, 1)]
    near = pair_overlaps(clouds, normals, 2.0, max_samples=200, threshold=overlap + 0.01)
    assert near[(0, 1)] == both[(0, 1)]


def _tried(monkeypatch, fail=frozenset()):
    """Record the pairs register_scans aligns; those in ``fail`` come back failed."""
    tried = []
    real = _REGISTER_PAIR

    def spy(source, target, **kwargs):
        tried.append((source.name, target.name))
        if (source.name, target.name) in fail:
            return multiview.PairwiseResult(np.eye(4), 0.0, math.nan, success=False,
                                            reason="made to fail by the test")
        return real(source, target, **kwargs)

    monkeypatch.setattr(multiview, "register_pair", spy)
    return tried


def test_only_pairs_that_can_overlap_are_aligned(ring_views, monkeypatch):
    scans, truth, start = ring_views
    direction = {s.name: start[s.name][:3, :3] @ s.view_direction for s in scans}
    # a narrow view cone (100 degrees), so that some pairs every-candidate tries fall outside
    everything = _tried(monkeypatch)
    full = register_scans(scans, initial_poses=start, config=MultiviewConfig(max_neighbours=0))
    assert any(view_angle_deg(direction[a], direction[b]) > 100.0 for a, b in everything)
    tried = _tried(monkeypatch)
    with pytest.warns(multiview.RegistrationWarning, match="view11"):
        result = register_scans(scans, initial_poses=start,
                                config=MultiviewConfig(max_neighbours=3, max_view_angle=100.0))
    # the view from below is more than 100 degrees from every other: it has no candidate
    assert set(result.left_out) == {"view11"}
    assert set(result.poses) == set(truth) - {"view11"}
    assert tried and len(tried) <= len(scans) * 3 < len(everything)
    assert not any("view11" in pair for pair in tried)
    for a, b in tried:
        assert view_angle_deg(direction[a], direction[b]) <= 100.0, (a, b)
    for name, pose in result.poses.items():
        rotation, translation = pose_error(pose, truth[name])
        assert rotation < 0.05 and translation < 0.05, name
        rotation, translation = pose_error(pose, full.poses[name])
        assert rotation < 0.05 and translation < 0.05, name


def test_pruning_keeps_the_graph_connected(ring_views, monkeypatch):
    scans, truth, start = ring_views
    # with one partner per scan the kept pairs alone still connect every scan
    tried = _tried(monkeypatch)
    result = register_scans(scans, initial_poses=start, config=MultiviewConfig(max_neighbours=1))
    names = [s.name for s in scans]
    assert _connected(names, tried)
    assert result and set(result.poses) == set(truth)
    # when the pairs kept for a scan all fail, the next best candidates are tried
    chosen = {p for p in tried if "view11" in p}
    assert chosen
    retried = _tried(monkeypatch, fail=chosen)
    totals, ticks = [], []
    result = register_scans(scans, initial_poses=start, config=MultiviewConfig(max_neighbours=1),
                            progress=ticks.append, on_total=totals.append)
    # a progress bar's total: the pairs planned, raised for each joining pair, ends at what ran
    assert totals[0] == len(tried) and totals == sorted(totals) and totals[-1] == len(retried) == len(ticks)
    assert set(retried) > set(tried)
    assert any("view11" in p and p not in chosen for p in retried)
    assert result and set(result.poses) == set(truth)
    for name, pose in result.poses.items():
        rotation, translation = pose_error(pose, truth[name])
        assert rotation < 0.05 and translation < 0.05, name


def test_the_command_and_the_recipe_default_to_the_library_k():
    from slscan.recipe.stages import RegisterConfig
    from slscan.register.command import MAX_NEIGHBOURS

    assert RegisterConfig().max_neighbours == MAX_NEIGHBOURS == MultiviewConfig().max_neighbours
