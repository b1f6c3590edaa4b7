"""Global alignment of many range scans: overlap graph, pairwise ICP, pose graph, joint refinement.

:func:`register_scans` takes N scans (and, when known, approximate poses), finds the
pairs that overlap, aligns each pair (:func:`slscan.register.pairwise.register_pair`),
and distributes the pairwise errors over all poses by optimising a pose graph (open3d's
Levenberg–Marquardt with a line process that prunes inconsistent pairs [1]_). All poses
are then refined together at full resolution, minimising the point-to-plane distances
of every overlapping pair at once (:func:`refine_jointly`, after [2]_, [3]_): the pose
graph only sees each pair through its ICP result, the joint step sees the samples.

On the Stanford bunny the result does not depend on the start (bun.conf poses, the
same perturbed by up to 10 degrees / 10 mm, or no poses at all agree to 0.001 degree),
and lies 0.04–0.25 degrees from bun.conf: refined from bun.conf itself, the scans move
there too (see ``benchmarks/bunny.py``).

A scan that matches nothing, or that the surviving edges do not connect to the
reference scan, is left out (reported, with a :class:`RegistrationWarning`), never forced
into place. Without poses (free-hand) each pair's alignment is one of several hypotheses,
verified (residual at full resolution, free space), and checked round loops of three
scans; a scan the final poses do not support is left out the same way. Poses are ``world_from_scan`` 4×4 float64 on mm; the gauge is fixed by the
reference scan, which keeps its given pose (identity when none is given).

References
----------
.. [1] Choi, Zhou, Koltun, "Robust reconstruction of indoor scenes", CVPR 2015 (pose
   graph with line processes).
.. [2] Pulli, "Multiview registration for large data sets", 3DIM 1999 (pairwise
   alignments, then a global pass that spreads their error).
.. [3] Neugebauer, "Reconstruction of real-world objects via simultaneous registration
   and robust combination of multiple range images", IJSMA 3(1), 1997.
.. [4] Turk, Levoy, "Zippered polygon meshes from range images", SIGGRAPH 1994 (no
   correspondences onto a mesh's boundary).
"""

from __future__ import annotations

import itertools
import logging
import math
import threading
import uuid
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.meshes import boundary_vertices
from slscan.register.pairwise import (
    PairwiseConfig,
    rotation_angle_deg,
    PairwiseResult,
    ScanFeatures,
    Verification,
    default_voxel_sizes,
    downsample,
    feature_hypotheses,
    free_space_violation,
    median_edge_length,
    refine_icp,
    register_pair,
    scan_clouds,
    scan_extent,
    scan_features,
    scan_point_cloud,
    verify_alignment,
)
from slscan.register.rangescan import RangeScan, scan_source

log = logging.getLogger(__name__)

_reg = o3d.pipelines.registration


class RegistrationWarning(UserWarning):
    """Some scans could not be registered and were left out."""


@dataclass(frozen=True)
class MultiviewConfig:
    """Options of :func:`register_scans` (lengths in mm; None: from the scans' spacing)."""

    pairwise: PairwiseConfig = field(
        default_factory=lambda: PairwiseConfig(max_iterations=(40, 20, 10))
    )
    """Options of each pairwise alignment of the first round. By default it stops at 2
    sample spacings (not at full resolution) and runs fewer ICP iterations at its finer
    levels than :class:`PairwiseConfig`'s: the joint refinement does the fine work (on the
    Stanford bunny the poses agree to 0.001 degree, at 40 % of the ICP cost)."""
    pose_tolerance: float | None = None
    """How far (mm) the initial poses may be off: the first round's correspondence
    distance; a pair ICP moves by more than twice this from its initial poses is rejected,
    and a scan the pose graph moves that far is refined from its initial pose. At least 4
    sample spacings. None: :data:`MISFIT_FACTOR` times the initial poses' misfit
    (:func:`pose_misfit`), between 4 sample spacings and 30 of them (at most 1/8 of the
    scans' size): 22 mm on the Stanford bunny perturbed by up to 10 degrees / 10 mm, 4
    spacings from exact poses. (The 30 spacings alone grew with sparse sampling, and let
    ICP slide exact turntable views round a nearly symmetric object.) Overlapping pairs
    are found within half the larger of this and 30 spacings."""
    min_overlap: float = 0.2
    """A pair is an edge when at least this fraction of the smaller scan lies on the
    other (with the current poses) and ICP agrees."""
    joint_distances_factor: tuple[float, ...] = (4.0, 2.0)
    """Correspondence distances of the joint refinement, in median sample spacings,
    coarse to fine (the last one is the residuals' distance)."""
    edge_prune_threshold: float = 0.25
    """open3d's line-process threshold: edges weighted below it are pruned as outliers."""
    max_rmse_factor: float = 0.3
    """An edge whose inlier RMSE exceeds this fraction of its correspondence distance is
    rejected (a wrong alignment that found some overlap: its residuals spread over the
    whole distance)."""
    max_neighbours: int = 8
    """With initial poses, each scan is aligned with at most this many candidate partners,
    its best by estimated overlap (a pair is kept when either scan ranks the other among
    its best), and the joint refinement matches the same number; the best remaining
    candidates are added where that would leave the graph in pieces. 0: every candidate
    pair (the behaviour before, quadratic in the number of scans)."""
    max_view_angle: float = 150.0
    """Degrees. With ``max_neighbours`` > 0, two scans whose view directions (under the
    initial poses) are further apart than this see different sides of the object and are
    no candidates; nor are scans whose bounding boxes lie apart."""
    hypotheses: tuple[int, ...] = (0, 1, 2)
    """Without initial poses: the seeds of open3d's feature RANSAC, one coarse alignment
    each, tried per pair (with open3d's Fast Global Registration, see ``fgr``); each is
    refined by ICP and verified (overlap, residuals, free space), the best kept."""
    fgr: bool = True
    """Without initial poses: also try open3d's Fast Global Registration per pair."""
    max_violation: float = 0.05
    """A pair (and, under the final poses, a scan) is rejected when more than this fraction
    of one scan's samples in the other's view lie in space the other's sensor saw empty
    (:func:`slscan.register.pairwise.free_space_violation`)."""
    fine_rmse_factor: float = 1.3
    """Without initial poses: a pair whose residual at full resolution exceeds this many
    times the typical pair's (the median of the best N-1 pairs', N scans; with held scans,
    of the best one per new scan) is rejected: a wrong match fits coarse samples, not the
    fine ones (on the figurine at quarter size right pairs leave 0.55-0.75 mm, wrong ones
    0.86 mm and more)."""
    loop_rotation_deg: float = 3.0
    """Without initial poses: a loop of three pairwise alignments closes when the motion
    round it is within this angle (degrees) ..."""
    loop_distance_factor: float = 5.0
    """... and moves the scan's centroid by at most this many sample spacings. Pairs in
    loops that do not close, and in none that does, are rejected (:func:`check_loops`)."""
    overlap_samples: int = 4000
    """With ``max_neighbours`` > 0, the overlap of two scans is estimated from at most this
    many samples of each (an even stride), for speed; pairs whose estimate lies near
    ``min_overlap`` are measured on all their samples."""


@dataclass(frozen=True)
class PairResidual:
    """One overlapping pair, after global alignment.

    source, target : scan names
    fitness : fraction of the source's samples within ``max_distance`` of the target
        under the final poses
    rmse : mm, RMS point-to-plane distance of those samples to the target
    pairwise_rmse : mm, inlier RMSE of the pair's own ICP (before the global step)
    max_distance : mm, correspondence distance used
    """

    source: str
    target: str
    fitness: float
    rmse: float
    pairwise_rmse: float
    max_distance: float


@dataclass(frozen=True)
class RejectedPair:
    """A candidate pair whose own alignment was not used as an edge of the pose graph, and why.

    (The joint refinement may still match the two scans, once the other pairs have put
    them where they overlap: the pair then also has a :class:`PairResidual`.)

    source, target : scan names (the pair's ICP aligned source onto target)
    reason : why it was not used, in words
    fitness : fraction of the source's samples its ICP matched (nan: no ICP result)
    rmse : mm, inlier RMSE of its ICP (nan: no ICP result)
    """

    source: str
    target: str
    reason: str
    fitness: float = math.nan
    rmse: float = math.nan


@dataclass(frozen=True)
class MultiviewResult:
    """Outcome of :func:`register_scans`.

    poses : {name: (4, 4) float64 world_from_scan, mm} of every registered scan
    pairs : residual of every overlapping pair kept in the graph
    left_out : {name: reason} of scans that could not be registered
    reference : the scan whose pose fixes the gauge
    rejected : the candidate pairs aligned but not used as pose-graph edges (ICP failed,
        too little overlap, residuals like a wrong match, moved too far from the initial
        poses, pruned by the pose graph), each with the reason
    """

    poses: dict[str, np.ndarray]
    pairs: tuple[PairResidual, ...]
    left_out: dict[str, str]
    reference: str
    rejected: tuple[RejectedPair, ...] = ()
    fixed: tuple[str, ...] = ()
    """The scans whose given pose was held (a registration grown with new scans)."""

    def __bool__(self) -> bool:
        return not self.left_out


# --- overlap ------------------------------------------------------------------------------------


def overlap_matrix(clouds: Sequence[np.ndarray], distance: float) -> np.ndarray:
    """(n, n) fraction of cloud i's points within ``distance`` of cloud j (0 on the diagonal).

    clouds : n (k_i, 3) float arrays, mm, common frame
    """
    n = len(clouds)
    trees = [cKDTree(c) if len(c) else None for c in clouds]
    lo = [c.min(axis=0) if len(c) else np.zeros(3) for c in clouds]
    hi = [c.max(axis=0) if len(c) else np.zeros(3) for c in clouds]
    out = np.zeros((n, n))
    for i, j in itertools.permutations(range(n), 2):
        if trees[j] is None or len(clouds[i]) == 0:
            continue
        if np.any(lo[i] - distance > hi[j]) or np.any(hi[i] + distance < lo[j]):
            continue
        d, _ = trees[j].query(clouds[i], distance_upper_bound=distance)
        out[i, j] = float(np.mean(np.isfinite(d)))
    return out


def _pair_overlap(m: np.ndarray, i: int, j: int) -> float:
    """Overlap of a pair: the larger of the two directed fractions (the smaller scan's)."""
    return max(m[i, j], m[j, i])


def view_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (degrees) between two unit view directions."""
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def pair_overlaps(
    clouds: Mapping[int, np.ndarray],
    normals: Mapping[int, np.ndarray],
    distance: float,
    *,
    directions: Mapping[int, np.ndarray] | None = None,
    max_view_angle: float = 180.0,
    max_samples: int | None = None,
    normal_cos: float = 0.0,
    threshold: float | None = None,
    margin: float = 0.05,
) -> dict[tuple[int, int], tuple[float, float]]:
    """Estimated overlap of every pair of clouds that can overlap: {(i, j), i < j: (overlap,
    same-side overlap)}.

    A pair is left out, without looking at its samples, when its view directions are more
    than ``max_view_angle`` degrees apart (the two sensors see different sides) or its
    bounding boxes, grown by ``distance``, do not meet. Otherwise, as in
    :func:`overlap_matrix`, the larger of the two directed fractions of a cloud's points
    within ``distance`` of the other (overlap) and of those whose nearest point there also
    has a normal within acos(``normal_cos``) of theirs (same-side overlap: the two sides
    of a thin part, seen from opposite views, do not count).

    clouds, normals : {scan index: (k, 3)} points (mm) and unit normals, common frame
    directions : {scan index: (3,) unit view direction, common frame}
    max_samples : at most this many points of each cloud are looked up (an even stride)
    threshold : with ``max_samples``, a pair whose estimated overlap lies within ``margin``
        of this value (the overlap a candidate needs) is measured again on every point,
        so that which pairs pass does not depend on the stride (4,000 samples estimate a
        fraction to about 0.01)
    """
    keys = sorted(clouds)
    lo = {k: clouds[k].min(axis=0) if len(clouds[k]) else None for k in keys}
    hi = {k: clouds[k].max(axis=0) if len(clouds[k]) else None for k in keys}
    trees: dict[int, cKDTree] = {}
    out: dict[tuple[int, int], tuple[float, float]] = {}
    for i, j in itertools.combinations(keys, 2):
        if lo[i] is None or lo[j] is None:
            continue
        if np.any(lo[i] - distance > hi[j]) or np.any(hi[i] + distance < lo[j]):
            continue
        if directions is not None and view_angle_deg(directions[i], directions[j]) > max_view_angle:
            continue
        for samples in (max_samples, None):
            fractions = []
            for a, b in ((i, j), (j, i)):
                if b not in trees:
                    trees[b] = cKDTree(clouds[b])
                step = max(1, len(clouds[a]) // samples) if samples else 1
                d, idx = trees[b].query(clouds[a][::step], distance_upper_bound=distance)
                hit = np.isfinite(d)
                same = np.einsum("ij,ij->i", normals[a][::step][hit], normals[b][idx[hit]])
                fractions.append((float(np.mean(hit)), float(np.sum(same > normal_cos)) / len(d)))
            out[(i, j)] = (max(f[0] for f in fractions), max(f[1] for f in fractions))
            if (not samples or threshold is None or abs(out[(i, j)][0] - threshold) >= margin
                    or max(len(clouds[i]), len(clouds[j])) <= samples):
                break
    return out


MAX_VERDICT_ROUNDS = 3
"""Rounds of pose graph, joint refinement and verdict per scan (each without the scans the
one before doubted)."""

CONTRADICTION = 3.0
"""A pair found from features that the final poses contradict by more than this many times
the loop tolerances (``loop_rotation_deg``, ``loop_distance_factor``) leaves both its scans
in doubt (on the quarter-size figurine the pose graph corrects a pair slid by 3.2 degrees:
the poses end within 0.8 degrees of the truth)."""

MISFIT_FACTOR = 5.0
"""Without a stated ``pose_tolerance``, the recorded poses are taken to be off by up to this
many times their measured misfit (:func:`pose_misfit`; between 4 sample spacings and the
old bound). The misfit sees offsets across the surface only, not along it: on the Stanford
bunny perturbed by up to 10 degrees / 10 mm it is 4.4-4.7 mm, the largest offset at a
scan's centroid 12.7 mm; from exact poses it is the scans' noise (0.2-0.7 mm)."""


def pose_misfit(
    clouds: Mapping[int, np.ndarray],
    normals: Mapping[int, np.ndarray],
    pairs: Sequence[tuple[int, int]],
    distance: float,
    *,
    max_samples: int | None = None,
    normal_cos: float = 0.5,
) -> float | None:
    """How well the poses the clouds are in already fit: the median over ``pairs`` of the
    median point-to-plane distance (mm) from a sample of i to its nearest sample of j
    within ``distance``, both ways, where the two normals agree within acos(``normal_cos``).
    None when no pair has such samples.

    clouds, normals : {scan index: (k, 3)} points (mm) and unit normals, common frame
    max_samples : at most this many points of each cloud are looked up (an even stride)
    """
    trees: dict[int, cKDTree] = {}
    medians = []
    for i, j in pairs:
        for a, b in ((i, j), (j, i)):
            if not len(clouds[a]) or not len(clouds[b]):
                continue
            if b not in trees:
                trees[b] = cKDTree(clouds[b])
            step = max(1, len(clouds[a]) // max_samples) if max_samples else 1
            p, n = clouds[a][::step], normals[a][::step]
            d, idx = trees[b].query(p, distance_upper_bound=distance)
            hit = np.flatnonzero(np.isfinite(d))
            q, m = clouds[b][idx[hit]], normals[b][idx[hit]]
            agree = np.einsum("ij,ij->i", n[hit], m) > normal_cos
            if np.any(agree):
                medians.append(float(np.median(np.abs(np.einsum("ij,ij->i", m[agree], p[hit][agree] - q[agree])))))
    return float(np.median(medians)) if medians else None


def select_pairs(scores: Mapping[tuple[int, int], float], k: int) -> list[tuple[int, int]]:
    """The candidate pairs to align: each scan's ``k`` best partners by score (a pair is
    kept when either scan ranks the other among its ``k`` best), plus the best remaining
    candidates that join pieces the kept pairs leave apart (a maximum spanning forest of
    the candidates), so the kept pairs connect every scan the candidates connect.

    scores : {(i, j): score, higher is better} of the candidate pairs
    k : partners per scan; 0 or less: every candidate

    Returns the kept pairs, sorted.
    """
    if k <= 0:
        return sorted(scores)
    ranked = sorted(scores, key=lambda key: (-scores[key], key))
    count: dict[int, int] = {}
    kept = set()
    for i, j in ranked:
        if count.get(i, 0) < k or count.get(j, 0) < k:
            kept.add((i, j))
        count[i], count[j] = count.get(i, 0) + 1, count.get(j, 0) + 1
    parts = _Components()
    for i, j in kept:
        parts.join(i, j)
    for i, j in ranked:
        if (i, j) not in kept and parts.join(i, j):
            kept.add((i, j))
    return sorted(kept)


class _Components:
    """Union–find over scan indices."""

    def __init__(self) -> None:
        self.parent: dict[int, int] = {}

    def find(self, a: int) -> int:
        self.parent.setdefault(a, a)
        while self.parent[a] != a:
            self.parent[a] = self.parent[self.parent[a]]
            a = self.parent[a]
        return a

    def join(self, a: int, b: int) -> bool:
        """Join the pieces of a and b; False when they were one already."""
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return False
        self.parent[ra] = rb
        return True


# --- loops ------------------------------------------------------------------------------------


def _relative(edges: Mapping[tuple[int, int], PairwiseResult], a: int, b: int) -> np.ndarray:
    """b_from_a from the edge between a and b (stored as (i, j): j_from_i)."""
    if (a, b) in edges:
        return np.asarray(edges[(a, b)].transform, np.float64)
    return np.linalg.inv(np.asarray(edges[(b, a)].transform, np.float64))


def check_loops(
    edges: Mapping[tuple[int, int], PairwiseResult],
    centroids: Mapping[int, np.ndarray],
    *,
    max_rotation_deg: float,
    max_distance: float,
) -> tuple[set[tuple[int, int]], dict[tuple[int, int], str]]:
    """Which pairwise alignments the loops of three scans confirm, and which they refute.

    Round a loop i → j → k → i the three alignments compose to the identity when all are
    right; a wrong one (a scan turned round a nearly symmetric object) leaves a large
    rotation or moves the scan's centroid. An edge is confirmed by a loop that closes
    within ``max_rotation_deg`` degrees and ``max_distance`` mm. Refuted edges are taken out
    one at a time, greedily: the edge in the most loops that fail, among those no loop
    confirms (ties: the lower fitness), until every edge left is in a closing loop or in
    none that fails; its loops are then counted again without it.

    edges : {(i, j): PairwiseResult with j_from_i}
    centroids : {scan index: (3,) centroid, mm, scan frame}

    Returns (confirmed edges, {refuted edge: reason}).
    """
    keys = set(edges)
    neighbours: dict[int, set[int]] = {}
    for i, j in keys:
        neighbours.setdefault(i, set()).add(j)
        neighbours.setdefault(j, set()).add(i)
    loops: dict[tuple[int, int, int], tuple[bool, float, float]] = {}
    for i, j in keys:
        for k in neighbours[i] & neighbours[j]:
            tri = tuple(sorted((i, j, k)))
            if tri in loops:
                continue
            a, b, c = tri
            round_trip = _relative(edges, c, a) @ _relative(edges, b, c) @ _relative(edges, a, b)
            angle = rotation_angle_deg(round_trip)
            moved = float(np.linalg.norm(round_trip[:3, :3] @ centroids[a] + round_trip[:3, 3] - centroids[a]))
            loops[tri] = (angle <= max_rotation_deg and moved <= max_distance, angle, moved)
    live = set(keys)
    refuted: dict[tuple[int, int], str] = {}

    def tally() -> tuple[dict, dict]:
        good = {e: 0 for e in live}
        bad = {e: [] for e in live}
        for tri, (closes, angle, moved) in loops.items():
            a, b, c = tri
            sides = [e if e in live else (e[1], e[0]) for e in ((a, b), (b, c), (a, c))]
            if not all(e in live for e in sides):
                continue
            for e in sides:
                if closes:
                    good[e] += 1
                else:
                    bad[e].append((tri, angle, moved))
        return good, bad

    while True:
        good, bad = tally()
        suspects = [e for e in live if good[e] == 0 and bad[e]]
        if not suspects:
            break
        worst = max(suspects, key=lambda e: (len(bad[e]), -edges[e].fitness, e))
        tri, angle, moved = bad[worst][0]
        refuted[worst] = (f"in {len(bad[worst])} loop{'s' * (len(bad[worst]) != 1)} of three scans that do "
                          f"not close (e.g. scans {tri}: {angle:.1f} degrees, {moved:.1f} mm) and in none "
                          "that does")
        live.discard(worst)
    good, _ = tally()
    return {e for e in live if good[e] > 0}, refuted


# --- pose graph ---------------------------------------------------------------------------------


def _spanning_tree(
    n: int, edges: Mapping[tuple[int, int], PairwiseResult], root: int,
    first: set[tuple[int, int]] | frozenset = frozenset(),
) -> dict[int, tuple[int, int]]:
    """Maximum spanning tree (by fitness) grown from ``root``: {node: (parent, edge key)};
    the edges in ``first`` (confirmed by loops) are preferred to the others."""
    tree: dict[int, tuple[int, int]] = {root: (-1, -1)}
    candidates = sorted(edges, key=lambda k: (k not in first, -edges[k].fitness))
    grew = True
    while grew:
        grew = False
        for key in candidates:
            i, j = key
            if (i in tree) != (j in tree):
                child = j if i in tree else i
                tree[child] = (i if child == j else j, key)
                grew = True
                break
    return tree


def _chain_poses(
    n: int,
    edges: Mapping[tuple[int, int], PairwiseResult],
    tree: dict,
    root: int,
    root_pose: np.ndarray,
) -> dict[int, np.ndarray]:
    """World poses from the tree's pairwise transforms (edge (i, j): j_from_i)."""
    poses = {root: root_pose}
    pending = [k for k in tree if k != root]
    while pending:
        for node in list(pending):
            parent, key = tree[node]
            if parent not in poses:
                continue
            t = edges[key].transform
            poses[node] = poses[parent] @ (t if node == key[0] else np.linalg.inv(t))
            pending.remove(node)
    return poses


def optimise_pose_graph(
    poses: Mapping[int, np.ndarray],
    edges: Mapping[tuple[int, int], PairwiseResult],
    *,
    root: int,
    certain: set[tuple[int, int]],
    max_distance: float,
    edge_prune_threshold: float = 0.25,
) -> tuple[dict[int, np.ndarray], set[tuple[int, int]]]:
    """Optimise world poses over pairwise constraints; return poses and the surviving edges.

    poses : {node: (4, 4) world_from_node} initial guesses, the nodes of the graph
    edges : {(i, j): PairwiseResult with j_from_i}
    certain : edges the line process may not prune (a spanning tree)
    """
    nodes = sorted(poses)
    index = {node: k for k, node in enumerate(nodes)}
    graph = _reg.PoseGraph()
    for node in nodes:
        graph.nodes.append(_reg.PoseGraphNode(np.asarray(poses[node], np.float64)))
    keys = []
    for (i, j), res in edges.items():
        if i not in index or j not in index:
            continue
        graph.edges.append(
            _reg.PoseGraphEdge(
                index[i], index[j], res.transform, res.information, uncertain=(i, j) not in certain
            )
        )
        keys.append((i, j))
    option = _reg.GlobalOptimizationOption(
        max_correspondence_distance=float(max_distance),
        edge_prune_threshold=float(edge_prune_threshold),
        preference_loop_closure=1.0,
        reference_node=index[root],
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        _reg.global_optimization(
            graph,
            _reg.GlobalOptimizationLevenbergMarquardt(),
            _reg.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    kept = {(nodes[e.source_node_id], nodes[e.target_node_id]) for e in graph.edges}
    out = {node: np.asarray(graph.nodes[index[node]].pose).copy() for node in nodes}
    # fix the gauge exactly on the root
    fix = np.asarray(poses[root], np.float64) @ np.linalg.inv(out[root])
    return {node: fix @ p for node, p in out.items()}, kept & set(keys)


# --- joint refinement ----------------------------------------------------------------------------


def usable_rim(scan: RangeScan, min_quality: float) -> np.ndarray:
    """(n,) bool: the vertices on the rim of the scan's usable surface, that is on an edge
    of only one face whose vertices all have quality >= ``min_quality`` (the scan's outline
    and the edges of its holes), or usable vertices in no such face."""
    usable = scan.quality >= min_quality
    faces = scan.faces[usable[scan.faces].all(axis=1)]
    in_face = np.zeros(len(usable), bool)
    in_face[faces.ravel()] = True
    rim = usable & ~in_face
    rim[boundary_vertices(faces)] = True
    return rim


def refine_jointly(
    scans: Sequence[RangeScan],
    poses: Mapping[int, np.ndarray],
    pairs: Sequence[tuple[int, int]],
    *,
    root: int,
    distances: Sequence[float],
    min_quality: float = 0.05,
    normal_cos: float = 0.5,
    max_points: int = 60_000,
    coarse_points: int = 10_000,
    max_iterations: int = 30,
    tolerance: float = 1e-2,
    fixed: Sequence[int] = (),
) -> tuple[dict[int, np.ndarray], list[tuple[float, float]]]:
    """Simultaneous point-to-plane ICP of all scans over all overlapping pairs [2]_, [3]_.

    Minimises, over every pose but the root's, the sum over pairs (both directions) of
    w·(n_q·(p - q))², p a source sample, q its nearest target sample within the level's
    distance, n_q the target normal, w the product of the two samples' qualities;
    correspondences onto target samples of quality < ``min_quality`` (the scan's
    boundary band), onto the rim of the usable surface (:func:`usable_rim`: a sample
    beyond the target's edge or a hole's finds its nearest partner there, and pulls the
    scans over the edge [4]_), or with normals more than acos(``normal_cos``) apart are
    rejected.
    Gauss–Newton on the linearised motions, re-matching each iteration, until the largest
    update is below ``tolerance`` (mm, rotations measured at 100 mm; on the bunny, 0.01 mm
    ends within 0.0001 degree of 0.001 mm's poses in two thirds of the iterations).

    poses : {scan index: (4, 4) world_from_scan}
    pairs : (i, j) scan indices to match
    distances : correspondence distances (mm), one level each, coarse to fine
    fixed : scans whose pose is held, like the root's
    max_points : samples per scan used at the finest level (an even stride), for speed
    coarse_points : samples per scan used at the coarser levels: they only bring the
        poses within reach of the finest level, so a sparser stride does (a third of the
        Stanford bunny's samples: this step twice as fast, the same poses to 0.001 degree)

    Returns the refined poses and, per pair, (fitness of i onto j: the share of i's
    samples matched, point-to-plane RMS mm) at the finest level.
    """
    poses = {k: np.asarray(p, np.float64).copy() for k, p in poses.items()}
    nodes = sorted(poses)
    cols = {k: a for a, k in enumerate(k for k in nodes if k != root and k not in set(fixed))}
    usable = {k: np.flatnonzero(scans[k].quality >= min_quality) for k in nodes}
    rim = {k: usable_rim(scans[k], min_quality) for k in nodes}
    centre = np.mean([scans[k].transformed_vertices(poses[k]).mean(axis=0) for k in nodes], axis=0)
    stats: list[tuple[float, float]] = [(0.0, math.nan)] * len(pairs)
    to_centre, from_centre = np.eye(4), np.eye(4)
    to_centre[:3, 3], from_centre[:3, 3] = centre, -centre
    sampling = None
    for level, distance in enumerate(distances):
        limit = max_points if level == len(distances) - 1 else min(coarse_points, max_points)
        if limit != sampling:
            sampling = limit
            samples = {k: u[:: max(1, len(u) // limit)] for k, u in usable.items()}
            # trees in each scan's own frame, built once per sampling: queries are mapped
            # into the target's frame
            local = {k: scans[k].vertices[samples[k]] for k in nodes}
            trees = {k: cKDTree(local[k]) for k in nodes}
            inner = {k: ~rim[k][samples[k]] for k in nodes}
        for _ in range(max_iterations):
            world = {}
            for k in nodes:
                s, p, idx = scans[k], poses[k], samples[k]
                world[k] = (
                    local[k] @ p[:3, :3].T + p[:3, 3] - centre,
                    s.normals[idx].astype(np.float64) @ p[:3, :3].T,
                    s.quality[idx].astype(np.float64),
                )
            size = 6 * len(cols)
            h = np.zeros((size, size))
            g = np.zeros(size)
            for e, (i, j) in enumerate(pairs):
                hits, sq = 0, 0.0
                for a, b in ((i, j), (j, i)):
                    pa, na, qa = world[a]
                    pb, nb, qb = world[b]
                    pose_b = poses[b]
                    in_b = (pa + centre - pose_b[:3, 3]) @ pose_b[:3, :3]
                    d, idx = trees[b].query(in_b, distance_upper_bound=distance)
                    ok = np.isfinite(d)
                    src, idx = np.flatnonzero(ok), idx[ok]
                    ok = (np.einsum("ij,ij->i", na[src], nb[idx]) > normal_cos) & inner[b][idx]
                    src, idx = src[ok], idx[ok]
                    p, n = pa[src], nb[idx]
                    r = np.einsum("ij,ij->i", n, p - pb[idx])
                    w = qa[src] * qb[idx]
                    if a == i:
                        hits, sq = len(src), float(np.sum(r * r))
                        stats[e] = (
                            hits / max(len(pa), 1),
                            math.sqrt(sq / hits) if hits else math.nan,
                        )
                    jac = np.hstack(
                        [np.cross(p, n), n]
                    )  # d r / d (omega_a, v_a); b gets the negative
                    jw = jac * w[:, None]
                    jtj, jtr = jac.T @ jw, jw.T @ r
                    blocks = [(cols[k], sign) for k, sign in ((a, 1.0), (b, -1.0)) if k in cols]
                    for u, su in blocks:
                        g[6 * u : 6 * u + 6] += su * jtr
                        for v, sv in blocks:
                            h[6 * u : 6 * u + 6, 6 * v : 6 * v + 6] += su * sv * jtj
            if size == 0:
                break
            try:
                x = -np.linalg.solve(h + 1e-9 * np.trace(h) / size * np.eye(size), g)
            except np.linalg.LinAlgError:
                log.warning("joint refinement: singular system, stopping")
                break
            step = 0.0
            for k, u in cols.items():
                xi = x[6 * u : 6 * u + 6]
                update = np.eye(4)
                update[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
                update[:3, 3] = xi[3:]
                poses[k] = to_centre @ update @ from_centre @ poses[k]
                step = max(
                    step, 100.0 * float(np.linalg.norm(xi[:3])) + float(np.linalg.norm(xi[3:]))
                )
            if step < tolerance:
                break
    return poses, stats


# --- pairwise alignments as tasks -----------------------------------------------------------------


@dataclass(frozen=True)
class PairTask:
    """One pairwise alignment of :func:`register_scans`, runnable in any process: this one,
    a helper process or a Dask worker (:class:`slscan.executor.Executor`).

    run : the registration it belongs to (a worker keeps that run's scans, coarse clouds
        and features, and drops them when a task of another run arrives)
    i, j : scan indices; the alignment is of scan i onto scan j
    scans : per scan, (absolute path, units) of its file (:func:`scan_source`: the
        worker loads it once), or the :class:`RangeScan` itself (made in memory: sent
        with every task)
    names, n_vertices : the two scans', to check what a worker loads
    init : (4, 4) j_from_i from the recorded poses, or None: from features
    first, fine : the ICP options of the pass (coarse levels; the check at full resolution)
    spacing : mm, median sample spacing of the scans
    feature_voxel : mm, voxel of the FPFH features
    """

    run: str
    i: int
    j: int
    scans: tuple[tuple[str, str] | RangeScan, tuple[str, str] | RangeScan]
    names: tuple[str, str]
    n_vertices: tuple[int, int]
    init: np.ndarray | None
    first: PairwiseConfig
    fine: PairwiseConfig
    config: MultiviewConfig
    spacing: float
    feature_voxel: float


@dataclass(frozen=True)
class PairOutcome:
    """What a :class:`PairTask` found: the alignment, and without poses its verification
    and why it is rejected ("" when it holds; with poses the caller judges it)."""

    result: PairwiseResult
    check: Verification | None = None
    verdict: str = ""


CACHED_SCANS = 16
"""A worker keeps the inputs (scan, ICP clouds, features) of at most this many scans, the
ones it used last: its memory stays bounded however many scans a registration has, and
after the registration (the helpers outlive it, into the next stages) it holds no more."""

_cache_lock = threading.Lock()
_cache: dict = {"run": None, "scans": {}, "clouds": {}, "features": {}, "used": [], "seeded": False}
"""This process's inputs of the registration under way: {scan index: RangeScan}, its
clouds per ICP level and its features, each made once per process; "used": the scan
indices, least recently used first."""


def _seed_cache(run: str | None, scans: Sequence[RangeScan]) -> None:
    """Start this process's cache for ``run`` with the scans in hand (None: empty it). The
    caller's own scans are all kept (it holds them anyway)."""
    with _cache_lock:
        _cache.update(run=run, scans=dict(enumerate(scans)), clouds={}, features={}, used=[], seeded=True)


def _cached(task: PairTask, kind: str, k: int, make: Callable[[], object]) -> object:
    """``kind``'s entry for scan ``k`` in this process's cache, made by ``make`` when missing."""
    with _cache_lock:
        if _cache["run"] != task.run:
            _cache.update(run=task.run, scans={}, clouds={}, features={}, used=[], seeded=False)
        if k in _cache["used"]:
            _cache["used"].remove(k)
        _cache["used"].append(k)
        if k in _cache[kind]:
            return _cache[kind][k]
    value = make()  # outside the lock: a Dask worker's threads make different scans' at once
    with _cache_lock:
        if _cache["run"] == task.run:
            _cache[kind].setdefault(k, value)
            while len(_cache["used"]) > CACHED_SCANS:
                old = _cache["used"].pop(0)
                for entries in (_cache["clouds"], _cache["features"], {} if _cache["seeded"] else _cache["scans"]):
                    entries.pop(old, None)
    return value


def _task_scan(task: PairTask, side: int) -> RangeScan:
    """The task's scan ``side`` (0: i, 1: j), loaded once per process."""
    ref, name, count = task.scans[side], task.names[side], task.n_vertices[side]

    def load() -> RangeScan:
        if isinstance(ref, RangeScan):
            return ref
        from slscan.register.rangescan import load_range_scan

        path, units = ref
        scan = load_range_scan(path, units=units)
        if scan.name != name or scan.n_vertices != count:
            raise SlscanError(f"{path}: a worker read scan {scan.name!r} of {scan.n_vertices} vertices, expected "
                              f"{name!r} of {count}: the workers need the same files at the same paths")
        return scan

    return _cached(task, "scans", (task.i, task.j)[side], load)


def align_pair_task(task: PairTask) -> PairOutcome:
    """Run one :class:`PairTask` (the work :func:`register_scans` hands its executor): with
    ``init``, multi-scale ICP from it (:func:`register_pair`); without, the best verified
    alignment from feature hypotheses (:func:`feature_hypotheses`, seeded per hypothesis:
    the same outcome in any process and order)."""
    si, sj = _task_scan(task, 0), _task_scan(task, 1)
    pw = task.config.pairwise
    ci, cj = (_cached(task, "clouds", k,
                      lambda s=s: scan_clouds(s, task.first.voxel_sizes, min_quality=pw.min_quality))
              for k, s in ((task.i, si), (task.j, sj)))
    if task.init is not None:
        return PairOutcome(register_pair(si, sj, init=task.init, config=task.first, clouds=(ci, cj)))
    fi, fj = (_cached(task, "features", k,
                      lambda s=s: scan_features(s, task.feature_voxel, min_quality=pw.min_quality))
              for k, s in ((task.i, si), (task.j, sj)))
    return _freehand_pair(task, si, sj, (ci, cj), (fi, fj))


def _freehand_pair(task: PairTask, si: RangeScan, sj: RangeScan, clouds: tuple, features: tuple) -> PairOutcome:
    """The best verified alignment of scan i onto scan j from feature hypotheses, its
    verification, and why it is rejected ("" when it holds)."""
    config, spacing, pw = task.config, task.spacing, task.config.pairwise
    icp = replace(task.first, initial_distance=None)
    best: tuple[PairwiseResult, Verification | None, str] | None = None
    tried: list[tuple[np.ndarray, bool]] = []
    for hypothesis in feature_hypotheses(features, seeds=config.hypotheses,
                                         ransac_iterations=pw.ransac_iterations, fgr=config.fgr):
        res = refine_icp(si, sj, hypothesis, config=icp, clouds=clouds)
        same = [passed for t, passed in tried if _close(res.transform, t, si, spacing)]
        if same and same[0]:
            break  # two hypotheses agree on an alignment that passed: no need for more
        if same:
            continue  # the same alignment as an earlier hypothesis's
        coarse_transform = res.transform
        verdict = _check_edge(res, config)
        check = None
        if not verdict:
            # the residual at full resolution tells a right match (the scans' noise) from a
            # wrong one that fits the coarse samples
            res = refine_icp(si, sj, res.transform, config=task.fine, clouds=clouds)
            verdict = _check_edge(res, config)
        if not verdict:
            check = verify_alignment(si, sj, res, spacing=spacing)
            if check.violation > config.max_violation:
                verdict = (f"{check.violation:.0%} of one scan lies where the other's sensor saw empty "
                           f"space (> {config.max_violation:.0%}): a wrong match")
        tried.append((coarse_transform, not verdict))
        rank = (not verdict, -res.inlier_rmse if math.isfinite(res.inlier_rmse) else -math.inf)
        if best is None or rank > (not best[2], -best[0].inlier_rmse
                                   if math.isfinite(best[0].inlier_rmse) else -math.inf):
            best = (res, check, verdict)
    if best is None:
        return PairOutcome(PairwiseResult(np.eye(4), 0.0, math.nan, success=False, reason="no features"), None,
                           f"too few feature samples in {task.names[0]!r} or {task.names[1]!r}")
    return PairOutcome(*best)


# --- main entry -----------------------------------------------------------------------------------


def register_scans(
    scans: Sequence[RangeScan],
    *,
    initial_poses: Mapping[str, np.ndarray] | None = None,
    reference: str | None = None,
    config: MultiviewConfig = MultiviewConfig(),
    progress: Callable[[str], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    fixed: Sequence[str] = (),
    executor: Executor | None = None,
) -> MultiviewResult:
    """Register N overlapping range scans into one frame.

    1. Candidate pairs: with initial poses, the pairs whose samples overlap within
       ``pose_tolerance``, of which each scan keeps its ``max_neighbours`` best (view
       directions more than ``max_view_angle`` apart and bounding boxes apart are no
       candidates; where the kept pairs, or the ones ICP accepts of them, leave the graph
       in pieces, the best remaining candidates joining them are aligned too); without,
       every pair (aligned from FPFH features).
    2. Pairwise multi-scale ICP on each candidate (coarse levels); a pair is an edge when
       it succeeds with enough overlap and a low RMSE; the others are returned as
       ``rejected``, each with the reason.
    3. Pose graph over the edges (open3d, Levenberg–Marquardt, line process pruning
       inconsistent edges [1]_), from poses chained along a maximum spanning tree.
    4. Joint point-to-plane refinement of all poses over the pairs that overlap under
       the optimised poses, each scan's ``max_neighbours`` best (:func:`refine_jointly`),
       at full resolution; a scan the pose graph moved more than twice
       ``pose_tolerance`` from its initial pose starts from the initial pose.

    Without initial poses, each pair gets several coarse alignments from features
    (:func:`slscan.register.pairwise.feature_hypotheses`), each refined by ICP and
    verified (overlap, residuals, no surface where the other sensor saw empty space), the
    best kept; the loops of three scans then confirm or refute them (:func:`check_loops`).
    Under the final poses every scan must overlap another and put no surface in space
    another saw empty; a scan that does not is left out and named, never reported aligned.

    Parameters
    ----------
    scans : N RangeScan, each in its own frame (mm), distinct names
    initial_poses : {name: (4, 4) world_from_scan} approximate poses (good to
        ``config.pose_tolerance``); scans without one are placed from features. None: all
        pairs are aligned from features (N(N-1)/2 feature matches: slow for many scans).
    reference : name of the scan that fixes the gauge (keeps its initial pose, or the
        identity); default: the first scan
    config : MultiviewConfig
    progress : called with a short label after each pairwise alignment (progress bars)
    on_total : called with the number of pairwise alignments planned, once the pairs are
        chosen and again whenever a joining pair is added (a progress bar's total)
    fixed : scans whose ``initial_poses`` are exact and held (an existing registration
        that the other scans join, found from features against it); the reference is
        one of them
    executor : where the pairwise alignments run (:class:`PairTask`, independent of each
        other: local helper processes or a Dask cluster); the pose graph, loops and
        verdicts run here. Scans loaded from files go to the workers as their paths (each
        worker loads a scan once); the poses are the same wherever the pairs ran. None:
        all in this process

    Returns
    -------
    MultiviewResult
        Poses of the registered scans, residual per overlapping pair, scans left out,
        candidate pairs rejected.

    Warns
    -----
    RegistrationWarning
        When scans match nothing or the graph does not connect them to the reference.
    """
    names = [s.name for s in scans]
    if len(scans) < 2:
        raise SlscanError(f"registration needs at least 2 scans, got {len(scans)}")
    if len(set(names)) != len(names):
        raise SlscanError(f"scan names must be distinct, got {names}")
    if reference is not None and reference not in names:
        raise SlscanError(f"reference scan {reference!r} is not among the scans {names}")
    initial_poses = dict(initial_poses or {})
    unknown = sorted(set(initial_poses) - set(names))
    if unknown:
        raise SlscanError(f"poses given for unknown scans {unknown}; scans are {names}")
    unposed = [name for name in fixed if name not in initial_poses]
    if unposed:
        raise SlscanError(f"scans {unposed} are to be held but have no pose")
    if fixed and reference is not None and reference not in fixed:
        raise SlscanError(f"reference scan {reference!r} is not among the held scans {list(fixed)}")
    held = {names.index(name) for name in fixed}
    root = names.index(reference) if reference is not None else (min(held) if held else 0)
    n = len(scans)
    spacing = float(np.median([median_edge_length(s) for s in scans]))
    extent = float(np.median([scan_extent(s) for s in scans]))
    # how far the recorded poses may be off: as stated, or at most 30 spacings (1/8 of the
    # scans' size) until the recorded poses' own misfit is measured below
    tolerance = (max(config.pose_tolerance, 4.0 * spacing) if config.pose_tolerance
                 else min(30.0 * spacing, extent / 8.0))
    pw = config.pairwise
    rejected: dict[tuple[str, str], RejectedPair] = {}
    tick = progress or (lambda label: None)

    # 1-2. candidate pairs and their alignments
    have = [names[k] in initial_poses for k in range(n)]
    poses0 = {k: np.asarray(initial_poses[names[k]], np.float64) for k in range(n) if have[k]}
    coarse_voxel = 4.0 * spacing
    prune = config.max_neighbours > 0
    coarse = {
        k: downsample(scan_point_cloud(s, pose=poses0[k], min_quality=pw.min_quality), coarse_voxel)
        for k, s in enumerate(scans)
        if have[k]
    }
    world = [np.asarray(coarse[k].points) if k in coarse else np.zeros((0, 3)) for k in range(n)]
    reach = max(tolerance / 2, coarse_voxel)
    if prune:
        estimates = pair_overlaps(
            {k: world[k] for k in coarse},
            {k: np.asarray(c.normals) for k, c in coarse.items()},
            reach,
            directions={k: poses0[k][:3, :3] @ scans[k].view_direction for k in coarse},
            max_view_angle=config.max_view_angle,
            max_samples=config.overlap_samples,
            threshold=config.min_overlap,
        )
        candidates = {key: same for key, (o, same) in estimates.items() if o >= config.min_overlap}
    else:
        m = overlap_matrix(world, reach)
        candidates = {
            (i, j): _pair_overlap(m, i, j)
            for i, j in itertools.combinations(range(n), 2)
            if have[i] and have[j] and _pair_overlap(m, i, j) >= config.min_overlap
        }
    chosen = set(select_pairs(candidates, config.max_neighbours))
    if not config.pose_tolerance:
        misfit = pose_misfit({k: world[k] for k in coarse}, {k: np.asarray(c.normals) for k, c in coarse.items()},
                             sorted(chosen), reach, max_samples=config.overlap_samples)
        if misfit is not None:
            tolerance = float(np.clip(MISFIT_FACTOR * misfit, 4.0 * spacing, tolerance))
            log.info("recorded poses: median misfit %.2f mm, tolerance %.1f mm", misfit, tolerance)
    first = replace(
        pw,
        initial_distance=pw.initial_distance or tolerance,
        voxel_sizes=pw.voxel_sizes or default_voxel_sizes(spacing, extent)[:-1] or (2 * spacing,),
    )
    fine = replace(pw, voxel_sizes=(0.0,), initial_distance=2.0 * spacing, distance_factor=1.5,
                   max_iterations=(30,))
    feature_voxel = pw.feature_voxel or 4.0 * spacing
    run = uuid.uuid4().hex
    _seed_cache(run, scans)  # this process aligns pairs too: from the scans in hand
    refs = [scan_source(s) or s for s in scans]
    edges: dict[tuple[int, int], PairwiseResult] = {}

    verified: dict[tuple[int, int], Verification] = {}
    freehand: set[tuple[int, int]] = set()
    exact: set[tuple[int, int]] = set()

    def task(i: int, j: int) -> PairTask:
        return PairTask(run=run, i=i, j=j, scans=(refs[i], refs[j]), names=(names[i], names[j]),
                        n_vertices=(scans[i].n_vertices, scans[j].n_vertices),
                        init=np.linalg.inv(poses0[j]) @ poses0[i] if have[i] and have[j] else None,
                        first=first, fine=fine, config=config, spacing=spacing, feature_voxel=feature_voxel)

    def align(i: int, j: int, outcome: PairOutcome | None) -> None:
        """Scan i onto scan j from its task's ``outcome`` (None: both poses held): an edge
        when it holds, else rejected with the reason."""
        if outcome is None:
            # both poses held: the pair is what they say, and closes loops through the others
            t = np.linalg.inv(poses0[j]) @ poses0[i]
            information = np.asarray(_reg.get_information_matrix_from_point_clouds(
                coarse[i], coarse[j], coarse_voxel, np.eye(4)))
            edges[(i, j)] = PairwiseResult(t, 1.0, 0.0, 100.0 * information, max_distance=coarse_voxel)
            exact.add((i, j))
            return
        res = outcome.result
        tick(f"{names[i]}-{names[j]}")
        if have[i] and have[j]:
            moved = _median_displacement(res.transform, np.linalg.inv(poses0[j]) @ poses0[i], world[i], poses0[i])
            if res and moved > 2 * tolerance:
                rejected[(names[i], names[j])] = _rejected(
                    names[i], names[j], res,
                    f"ICP moved it {moved:.1f} mm from the recorded poses, more than twice their "
                    f"tolerance ({tolerance:.1f} mm): a slide along a symmetric surface",
                )
                return
            verdict = _check_edge(res, config)
            if verdict:
                rejected[(names[i], names[j])] = _rejected(names[i], names[j], res, verdict)
                return
            edges[(i, j)] = res
            return
        if outcome.verdict:
            rejected[(names[i], names[j])] = _rejected(names[i], names[j], res, outcome.verdict)
            return
        edges[(i, j)] = res
        verified[(i, j)] = outcome.check
        freehand.add((i, j))

    todo = [(i, j) for i, j in itertools.combinations(range(n), 2)
            if (i, j) in chosen or not (have[i] and have[j])]
    planned = len(todo)
    if on_total is not None:
        on_total(planned)
    # the pairs are independent: aligned wherever the executor runs them (in input order
    # back here, so the result does not depend on where or in which order they ran)
    tasks = [task(i, j) for i, j in todo if not (i in held and j in held)]
    try:
        outcomes = (executor or Executor(workers=1)).map(align_pair_task, tasks)
        for i, j in todo:
            align(i, j, None if i in held and j in held else next(outcomes))
        if prune:
            # pairs that failed may leave the graph in pieces: try the best remaining
            # candidates that would join them (one at a time, here: each depends on the last)
            parts = _Components()
            for i, j in edges:
                parts.join(i, j)
            for i, j in sorted(set(candidates) - chosen, key=lambda key: (-candidates[key], key)):
                if parts.find(i) != parts.find(j):
                    planned += 1
                    if on_total is not None:
                        on_total(planned)
                    align(i, j, None if i in held and j in held else align_pair_task(task(i, j)))
                    if (i, j) in edges:
                        parts.join(i, j)
    finally:
        _seed_cache(None, ())

    # 2b. residuals: a pair found from features is right when its residual at full resolution
    # is the scans' noise, as the best pairs' are (a wrong match leaves 1.5-3 times it)
    confirmed: set[tuple[int, int]] = set()
    if freehand:
        ranked = sorted(edges[key].inlier_rmse for key in freehand if key in edges)
        # the fewest pairs that can join the scans: N - 1, or one per new scan joining held ones
        typical = float(np.median(ranked[: max(1, n - len(held) if held else n - 1)])) if ranked else math.inf
        limit = config.fine_rmse_factor * typical
        for key in sorted(freehand):
            if edges[key].inlier_rmse > limit:
                rejected[(names[key[0]], names[key[1]])] = _rejected(
                    names[key[0]], names[key[1]], edges[key],
                    f"residual at full resolution {edges[key].inlier_rmse:.2f} mm > {config.fine_rmse_factor:g} x "
                    f"the typical pair's {typical:.2f} mm: a wrong match that fits the coarse samples")
                del edges[key]
                freehand.discard(key)
    if freehand:
        centroids = {k: s.vertices.mean(axis=0) for k, s in enumerate(scans)}
        confirmed, refuted = check_loops(edges, centroids, max_rotation_deg=config.loop_rotation_deg,
                                         max_distance=config.loop_distance_factor * spacing)
        for key, reason in refuted.items():
            if key in exact:  # held poses are not in question
                continue
            rejected[(names[key[0]], names[key[1]])] = _rejected(names[key[0]], names[key[1]], edges[key], reason)
            del edges[key]
        log.info("loops of three scans: %d pairs confirmed, %d refuted", len(confirmed), len(refuted))
        log.info("pairs found from features: %s", ", ".join(
            f"{names[i]}-{names[j]} ({edges[(i, j)].inlier_rmse:.2f} mm)" for i, j in sorted(freehand) if (i, j) in edges))

    def _place(edges: dict[tuple[int, int], PairwiseResult]):
        """Poses from the pose graph over ``edges``, refined jointly; the pairs refined and
        their (fitness, rmse)."""
        poses, kept = _solve(n, edges, root, poses0.get(root, np.eye(4)), spacing, config, names, rejected,
                             confirmed=confirmed, exact=exact)
        for k in held:
            if k in poses:
                poses[k] = poses0[k].copy()
        # a recorded pose holds where the pose graph moved it beyond its tolerance (as a pair
        # that moves that far is rejected): the slide of some edges along a symmetric surface
        for k in sorted(set(poses) & set(poses0) - held):
            moved = _median_displacement(poses[k], poses0[k], world[k], poses0[k])
            if moved > 2 * tolerance:
                log.info("%s: the pose graph moved it %.1f mm from its recorded pose (tolerance %.1f mm); "
                         "refined from the recorded pose", names[k], moved, tolerance)
                poses[k] = poses0[k].copy()

        # 4. joint refinement over the pairs that overlap under the optimised poses
        pairs: list[tuple[int, int]] = []
        stats: list[tuple[float, float]] = []
        if len(poses) > 1:
            order = sorted(poses)
            fine = {
                k: downsample(
                    scan_point_cloud(scans[k], pose=poses[k], min_quality=pw.min_quality), 2 * spacing
                )
                for k in order
            }
            if prune:
                estimates = pair_overlaps(
                    {k: np.asarray(c.points) for k, c in fine.items()},
                    {k: np.asarray(c.normals) for k, c in fine.items()},
                    4 * spacing,
                    directions={k: poses[k][:3, :3] @ scans[k].view_direction for k in order},
                    max_view_angle=config.max_view_angle,
                    max_samples=config.overlap_samples,
                    threshold=config.min_overlap,
                )
                pairs = select_pairs(
                    {key: same for key, (o, same) in estimates.items() if o >= config.min_overlap},
                    config.max_neighbours,
                )
            else:
                m = overlap_matrix([np.asarray(fine[k].points) for k in order], 4 * spacing)
                pairs = [
                    (order[a], order[b])
                    for a, b in itertools.combinations(range(len(order)), 2)
                    if _pair_overlap(m, a, b) >= config.min_overlap
                ]
            poses, stats = refine_jointly(
                scans,
                poses,
                pairs,
                root=root,
                distances=[f * spacing for f in config.joint_distances_factor],
                min_quality=pw.min_quality,
                fixed=sorted(held),
            )
        return poses, pairs, stats

    # 3-5. pose graph, joint refinement, a verdict per scan; again without the scans doubted
    verdicts: dict[int, str] = {}
    for attempt in range(MAX_VERDICT_ROUNDS):
        live = {key: res for key, res in edges.items() if key[0] not in verdicts and key[1] not in verdicts}
        poses, pairs, stats = _place(live)
        if not freehand or len(poses) < 2:
            break
        # the verdict per scan: under the final poses each scan overlaps another and puts no
        # surface where another's sensor saw empty space, or it is left out
        doubted = _contradicted(scans, live, poses, freehand, held | {root}, spacing, config)
        doubted.update({k: r for k, r in _final_verdict(scans, poses, pairs, stats, held | {root}, spacing,
                                                        config).items() if k not in doubted})
        if not doubted:
            break
        verdicts.update(doubted)
        if attempt == MAX_VERDICT_ROUNDS - 1:
            poses = {k: p for k, p in poses.items() if k not in verdicts}
            kept_pairs = [e for e, (i, j) in enumerate(pairs) if i in poses and j in poses]
            pairs, stats = [pairs[e] for e in kept_pairs], [stats[e] for e in kept_pairs]

    residuals = tuple(
        PairResidual(
            names[i],
            names[j],
            fit,
            rmse,
            edges[(i, j)].inlier_rmse if (i, j) in edges else math.nan,
            config.joint_distances_factor[-1] * spacing,
        )
        for (i, j), (fit, rmse) in zip(pairs, stats)
    )
    residuals = _matched_pairs(residuals, rejected)

    left_out = {}
    for k in range(n):
        if k in verdicts:
            left_out[names[k]] = verdicts[k]
        elif k not in poses:
            touching = [key for key in rejected if names[k] in key]
            matched = any(k in key for key in edges)
            left_out[names[k]] = (
                "not connected to the reference scan by the pairs that held"
                if matched
                else "matches no other scan"
            ) + (f" ({len(touching)} candidate pairs rejected)" if touching else "")
    if left_out:
        message = "registration left out " + "; ".join(f"{k}: {v}" for k, v in left_out.items())
        log.warning(message)
        warnings.warn(message, RegistrationWarning, stacklevel=2)
    return MultiviewResult(
        poses={names[k]: p for k, p in sorted(poses.items())},
        pairs=residuals,
        left_out=left_out,
        reference=names[root],
        rejected=tuple(rejected.values()),
        fixed=tuple(names[k] for k in sorted(held)),
    )


def _matched_pairs(
    residuals: Sequence[PairResidual], rejected: dict[tuple[str, str], RejectedPair]
) -> tuple[PairResidual, ...]:
    """The residuals of pairs the joint refinement matched; a pair it matched no sample of
    (fitness 0, RMS undefined) has no residual to report or average: it goes to ``rejected``
    (unless it is there already, with its own reason)."""
    kept = []
    for r in residuals:
        if r.fitness > 0 and math.isfinite(r.rmse):
            kept.append(r)
            continue
        log.info("pair %s-%s: the joint refinement matched no samples; not a residual", r.source, r.target)
        rejected.setdefault(
            (r.source, r.target),
            RejectedPair(r.source, r.target, "no samples matched under the final poses", float(r.fitness),
                         float(r.rmse)),
        )
    return tuple(kept)


def median_pair_rmse(pairs: Sequence[PairResidual]) -> float | None:
    """Median point-to-plane RMS (mm) over the pairs with a residual; None when there are none
    (never NaN: a summary shows no number rather than ``nan``)."""
    values = [p.rmse for p in pairs if math.isfinite(p.rmse)]
    return float(np.median(values)) if values else None


def _close(a: np.ndarray, b: np.ndarray, scan: RangeScan, spacing: float) -> bool:
    """Whether two alignments of ``scan`` agree within a degree and a sample spacing at its centroid."""
    delta = a @ np.linalg.inv(b)
    c = scan.vertices.mean(axis=0)
    c = a[:3, :3] @ c + a[:3, 3]
    return rotation_angle_deg(delta) < 1.0 and float(np.linalg.norm(delta[:3, :3] @ c + delta[:3, 3] - c)) < spacing


def _contradicted(
    scans: Sequence[RangeScan],
    edges: Mapping[tuple[int, int], PairwiseResult],
    poses: Mapping[int, np.ndarray],
    found: set[tuple[int, int]],
    trusted: set[int],
    spacing: float,
    config: MultiviewConfig,
) -> dict[int, str]:
    """{scan index: reason} of the scans at either end of a pair found from features that the
    final poses contradict (the pose graph pruned it, or the joint refinement moved away
    from it by more than :data:`CONTRADICTION` times what a loop may be off: a pair slid
    by a few degrees along a symmetric surface is the pose graph's to correct, one on the
    wrong side of the object is not): both its scans passed every check, the poses
    can hold only one of them right, and which one is not known; neither is reported
    aligned (never a ``trusted`` one)."""
    out: dict[int, str] = {}
    for i, j in sorted(found & set(edges)):
        if i not in poses or j not in poses:
            continue
        implied = np.linalg.inv(poses[j]) @ poses[i]
        delta = np.asarray(edges[(i, j)].transform) @ np.linalg.inv(implied)
        angle = rotation_angle_deg(delta)
        # how far the pair's alignment and the final poses put scan i's centroid apart
        c = implied[:3, :3] @ scans[i].vertices.mean(axis=0) + implied[:3, 3]
        moved = float(np.linalg.norm(delta[:3, :3] @ c + delta[:3, 3] - c))
        if (angle > CONTRADICTION * config.loop_rotation_deg
                or moved > CONTRADICTION * config.loop_distance_factor * spacing):
            for k, other in ((i, j), (j, i)):
                if k not in trusted and k not in out:
                    out[k] = (f"the final poses contradict its pair with {scans[other].name} ({angle:.1f} degrees, "
                              f"{moved:.1f} mm off): the set is ambiguous here (a nearly symmetric part?)")
    return out


def _final_verdict(
    scans: Sequence[RangeScan],
    poses: Mapping[int, np.ndarray],
    pairs: Sequence[tuple[int, int]],
    stats: Sequence[tuple[float, float]],
    trusted: set[int],
    spacing: float,
    config: MultiviewConfig,
    samples: int = 3000,
) -> dict[int, str]:
    """{scan index: reason} of the scans their overlaps do not support under the final poses.

    A scan is supported when some pair puts at least half ``min_overlap`` of either scan
    on the other (the joint refinement's fitness) and no scan lies more than
    ``max_violation`` in space its sensor saw empty. Where two scans contradict each
    other so, the one with fewer supporting pairs is doubted (both when they have as many;
    never a ``trusted`` one), one clash at a time, and the rest judged again without it.
    """
    nodes = set(poses)
    world = {k: scans[k].transformed_vertices(poses[k])[:: max(1, scans[k].n_vertices // samples)]
             for k in nodes}
    margin, radius = 5.0 * spacing, 1.0 * spacing
    violation: dict[tuple[int, int], float] = {}
    for i, j in itertools.permutations(sorted(nodes), 2):
        inv = np.linalg.inv(poses[j])
        # only scans whose boxes meet can put surface in each other's view
        lo, hi = world[j].min(axis=0) - margin, world[j].max(axis=0) + margin
        if np.any(world[i].max(axis=0) < lo) or np.any(world[i].min(axis=0) > hi):
            continue
        violation[(i, j)] = free_space_violation(world[i] @ inv[:3, :3].T + inv[:3, 3], scans[j],
                                                 margin=margin, radius=radius)
    overlap = {}
    for (i, j), (fit, _) in zip(pairs, stats):
        overlap[(i, j)] = overlap[(j, i)] = max(overlap.get((i, j), 0.0), fit)
    doubted: dict[int, str] = {}
    while True:
        live = nodes - set(doubted)
        support = {k: sum(1 for j in live if overlap.get((k, j), 0.0) >= config.min_overlap / 2
                          and max(violation.get((k, j), 0.0), violation.get((j, k), 0.0)) <= config.max_violation)
                   for k in live}
        clashes = sorted(((v, key) for key, v in violation.items()
                          if v > config.max_violation and set(key) <= live), reverse=True)
        lonely = [k for k in live - trusted if support[k] == 0]
        if clashes:
            v, (i, j) = clashes[0]
            blame = [k for k in (i, j) if k not in trusted]
            if not blame:
                break
            if len(blame) == 2 and support[i] == support[j]:
                for k in blame:  # as well supported as each other: which is wrong is not known
                    doubted[k] = (f"under the final poses {v:.0%} of {scans[i].name} lies where "
                                  f"{scans[j].name}'s sensor saw empty space, and the two have as many "
                                  f"supporting overlaps ({support[k]}): which is wrong is not known")
                continue
            k = min(blame, key=lambda k: (support[k], k))
            other = j if k == i else i
            doubted[k] = (f"under the final poses {v:.0%} of {scans[i].name} lies where {scans[j].name}'s "
                          f"sensor saw empty space; {scans[k].name} has fewer supporting overlaps than "
                          f"{scans[other].name} ({support[k]} against {support[other]})")
        elif lonely:
            for k in lonely:
                doubted[k] = ("under the final poses it overlaps no other scan by "
                              f">= {config.min_overlap / 2:.0%} without a free-space clash")
        else:
            break
    if doubted:
        log.info("final verdict: %s", "; ".join(f"{scans[k].name}: {r}" for k, r in doubted.items()))
    return doubted


def _median_displacement(found: np.ndarray, init: np.ndarray, world_points: np.ndarray,
                         world_from_scan: np.ndarray) -> float:
    """Median distance (mm) the source scan's samples move between the initial guess and
    the alignment found (both target_from_source)."""
    if len(world_points) == 0:
        return 0.0
    scan_from_world = np.linalg.inv(world_from_scan)
    p = world_points @ scan_from_world[:3, :3].T + scan_from_world[:3, 3]
    delta = p @ (found[:3, :3] - init[:3, :3]).T + (found[:3, 3] - init[:3, 3])
    return float(np.median(np.linalg.norm(delta, axis=1)))


def _rejected(source: str, target: str, res: PairwiseResult, reason: str) -> RejectedPair:
    log.info("pair %s-%s rejected: %s", source, target, reason)
    return RejectedPair(source, target, reason, float(res.fitness), float(res.inlier_rmse))


def _check_edge(res: PairwiseResult, config: MultiviewConfig) -> str:
    """Why an alignment is not used as an edge ("" when it is)."""
    if not res:
        return res.reason
    if res.fitness < config.min_overlap:
        return f"overlap {res.fitness:.1%} < {config.min_overlap:.0%}"
    limit = config.max_rmse_factor * res.max_distance
    if not math.isfinite(res.inlier_rmse) or res.inlier_rmse > limit:
        return (
            f"inlier RMSE {res.inlier_rmse:.3g} mm > {config.max_rmse_factor:g} x the "
            f"correspondence distance {res.max_distance:.3g} mm: residuals spread like a wrong match"
        )
    return ""


def _solve(
    n: int,
    edges: dict[tuple[int, int], PairwiseResult],
    root: int,
    root_pose: np.ndarray,
    spacing: float,
    config: MultiviewConfig,
    names: list[str],
    rejected: dict[tuple[str, str], RejectedPair],
    *,
    confirmed: set[tuple[int, int]] | frozenset = frozenset(),
    exact: set[tuple[int, int]] | frozenset = frozenset(),
) -> tuple[dict[int, np.ndarray], set[tuple[int, int]]]:
    """Spanning tree from the root (loop-confirmed edges first), initial poses along it,
    pose-graph optimisation; the tree's edges and the ``exact`` ones (between held poses)
    are not pruned."""
    tree = _spanning_tree(n, edges, root, confirmed)
    if len(tree) < 2:
        return {root: root_pose}, set()
    component = {k: v for k, v in edges.items() if k[0] in tree and k[1] in tree}
    init = _chain_poses(n, component, tree, root, root_pose)
    certain = {key for node, (parent, key) in tree.items() if parent >= 0} | set(exact)
    distance = max(res.max_distance for res in component.values())
    poses, kept = optimise_pose_graph(
        init,
        component,
        root=root,
        certain=certain,
        max_distance=distance,
        edge_prune_threshold=config.edge_prune_threshold,
    )
    for key in set(component) - kept:
        rejected[(names[key[0]], names[key[1]])] = _rejected(
            names[key[0]], names[key[1]], component[key],
            "pruned by the pose graph (inconsistent with the others)",
        )
    return poses, kept
