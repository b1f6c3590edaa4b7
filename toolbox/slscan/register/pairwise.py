"""Pairwise alignment of two range scans: coarse (a given pose, or FPFH + RANSAC), then multi-scale ICP.

:func:`register_pair` returns a :class:`PairwiseResult` that is false-valued when the
alignment failed, carrying the reason, instead of raising: a pair that does not
overlap is a normal outcome when many scans are registered.

Transforms are 4×4 float64 matrices on mm coordinates. ``target_from_source`` maps a
point of the source scan's frame into the target scan's frame.

References
----------
.. [1] Chen, Medioni, "Object modelling by registration of multiple range images",
   Image and Vision Computing 10(3), 1992 (point-to-plane ICP).
.. [2] Rusu, Blodow, Beetz, "Fast Point Feature Histograms (FPFH) for 3D registration",
   ICRA 2009.
.. [3] Rusinkiewicz, "A symmetric objective function for ICP", SIGGRAPH 2019.
.. [4] Fischler, Bolles, "Random sample consensus", CACM 24(6), 1981.
.. [5] Zhou, Park, Koltun, "Fast global registration", ECCV 2016.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from slscan.errors import SlscanError
from slscan.register.rangescan import RangeScan

log = logging.getLogger(__name__)

_reg = o3d.pipelines.registration


@dataclass(frozen=True)
class PairwiseConfig:
    """Options of :func:`register_pair` (lengths in mm)."""

    voxel_sizes: tuple[float, ...] | None = None
    """ICP levels, coarse to fine: the scans are voxel-downsampled to each size (0: full
    resolution). None: 8, 4, 2 times the scans' median edge length (at most 1/30 of the
    smaller scan's size), then 0."""
    initial_distance: float | None = None
    """Largest correspondence distance at the coarsest level: how far off the initial pose
    may be. None: 3 times the coarsest voxel size."""
    distance_factor: float = 2.0
    """Correspondence distance at later levels, in voxel sizes of that level (the full
    resolution level uses the median edge length)."""
    max_iterations: tuple[int, ...] = (40, 40, 40, 60)
    """ICP iterations per level (the last value repeats for extra levels)."""
    method: str = "point_to_plane"
    """{"point_to_plane", "symmetric"}: the ICP objective [1]_, [3]_."""
    robust_kernel: str | None = "tukey"
    """{"tukey", "huber", None}: robust loss on residuals, scale = the level's voxel."""
    min_quality: float = 0.05
    """Vertices with lower quality (grazing, at the boundary) take no part."""
    min_fitness: float = 0.1
    """Success needs at least this fraction of source samples matched at the finest level."""
    feature_voxel: float | None = None
    """Downsampling for FPFH features when no initial pose is given; None: 4 times the
    median edge length (normals at 2x, features at 5x this radius)."""
    ransac_iterations: int = 200_000
    """RANSAC iterations of the feature-based coarse alignment."""
    seed: int = 0
    """Seed of open3d's random generator (RANSAC), for repeatable runs."""


@dataclass(frozen=True)
class PairwiseResult:
    """Outcome of aligning a source scan to a target scan; false-valued on failure.

    transform : (4, 4) float64, target_from_source (the last estimate, or the initial
        guess, on failure)
    fitness : fraction of the source's samples (at the finest ICP level) with a target
        sample within the finest correspondence distance: the overlap, seen from the source
    inlier_rmse : mm, RMS point-to-plane distance of those correspondences (at the
        finest level; for the coarse alignment: open3d's point-to-point RMSE)
    information : (6, 6) float64 information matrix of the alignment (open3d's, for pose
        graphs)
    success : whether the alignment is trusted
    reason : why not, when it failed ("" on success)
    max_distance : mm, the finest correspondence distance used
    """

    transform: np.ndarray
    fitness: float
    inlier_rmse: float
    information: np.ndarray = field(default_factory=lambda: np.zeros((6, 6)), repr=False)
    success: bool = True
    reason: str = ""
    max_distance: float = math.nan

    def __bool__(self) -> bool:
        return self.success


# --- point clouds -------------------------------------------------------------------------------


def median_edge_length(scan: RangeScan) -> float:
    """Median length (mm) of the scan's mesh edges: its sample spacing."""
    if scan.n_faces == 0:
        raise SlscanError(f"scan {scan.name!r}: no faces, cannot measure its sample spacing")
    f = scan.faces[: min(scan.n_faces, 200_000)]
    e = np.linalg.norm(scan.vertices[f[:, 0]] - scan.vertices[f[:, 1]], axis=1)
    return float(np.median(e))


def scan_point_cloud(
    scan: RangeScan, *, pose: np.ndarray | None = None, min_quality: float = 0.0
) -> o3d.geometry.PointCloud:
    """Legacy open3d point cloud of the scan's vertices (and normals), mapped by ``pose``.

    pose : (4, 4) mapping the scan frame somewhere (e.g. world_from_scan); None: identity
    min_quality : vertices of lower quality are left out
    """
    keep = scan.quality >= min_quality if min_quality > 0 else slice(None)
    points = scan.vertices[keep]
    normals = scan.normals[keep].astype(np.float64)
    if pose is not None:
        pose = np.asarray(pose, np.float64)
        points = points @ pose[:3, :3].T + pose[:3, 3]
        normals = normals @ pose[:3, :3].T
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points)))
    pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals))
    return pcd


def downsample(pcd: o3d.geometry.PointCloud, voxel: float) -> o3d.geometry.PointCloud:
    """Voxel-grid average of ``pcd`` (normals re-normalised); ``voxel <= 0`` returns it as is."""
    if voxel <= 0:
        return pcd
    down = pcd.voxel_down_sample(voxel)
    if down.has_normals():
        n = np.asarray(down.normals)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n /= np.where(length > 0, length, 1.0)
    return down


def _kernel(name: str | None, scale: float):
    if name is None:
        return None
    if name == "tukey":
        return _reg.TukeyLoss(k=scale)
    if name == "huber":
        return _reg.HuberLoss(k=scale)
    raise SlscanError(f"robust_kernel {name!r}: expected 'tukey', 'huber' or None")


def _estimation(method: str, kernel):
    if method == "point_to_plane":
        return (
            _reg.TransformationEstimationPointToPlane(kernel)
            if kernel
            else _reg.TransformationEstimationPointToPlane()
        )
    if method == "symmetric":
        return (
            _reg.TransformationEstimationSymmetric(kernel)
            if kernel
            else _reg.TransformationEstimationSymmetric()
        )
    raise SlscanError(f"ICP method {method!r}: expected 'point_to_plane' or 'symmetric'")


def scan_extent(scan: RangeScan) -> float:
    """Diagonal (mm) of the scan's bounding box."""
    return float(np.linalg.norm(scan.vertices.max(axis=0) - scan.vertices.min(axis=0)))


def default_voxel_sizes(spacing: float, extent: float) -> tuple[float, ...]:
    """ICP levels for scans of sample spacing ``spacing`` and size ``extent`` (mm): 8, 4, 2
    spacings (each at most 1/30 of the extent), then full resolution."""
    cap = extent / 30.0
    sizes = sorted({min(f * spacing, cap) for f in (8, 4, 2)} - {0.0}, reverse=True)
    return (*[v for v in sizes if v > spacing], 0.0)


def _levels(
    config: PairwiseConfig, spacing: float, extent: float
) -> list[tuple[float, float, int]]:
    """(voxel, max correspondence distance, iterations) per ICP level."""
    voxels = (
        list(config.voxel_sizes)
        if config.voxel_sizes
        else list(default_voxel_sizes(spacing, extent))
    )
    if not voxels or any(v < 0 for v in voxels):
        raise SlscanError(
            f"voxel_sizes {config.voxel_sizes}: expected sizes >= 0 (mm), coarse to fine"
        )
    levels = []
    for k, voxel in enumerate(voxels):
        size = voxel if voxel > 0 else spacing
        if k == 0:
            distance = config.initial_distance or 3.0 * size
        else:
            distance = config.distance_factor * size
        iterations = config.max_iterations[min(k, len(config.max_iterations) - 1)]
        levels.append((voxel, distance, iterations))
    return levels


# --- coarse alignment --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ScanFeatures:
    """FPFH features of a scan's downsampled samples (see :func:`scan_features`).

    cloud : open3d PointCloud of the samples (scan frame, mm); features : open3d Feature
    voxel : mm, the downsampling
    """

    cloud: o3d.geometry.PointCloud
    features: object
    voxel: float


def scan_features(scan: RangeScan, voxel: float, *, min_quality: float = 0.05) -> ScanFeatures:
    """FPFH features [2]_ of ``scan`` downsampled to ``voxel`` mm (normals from the scan,
    features over 5 voxels), for :func:`coarse_align`; compute once per scan."""
    pcd = downsample(scan_point_cloud(scan, min_quality=min_quality), voxel)
    feature = _reg.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )
    return ScanFeatures(pcd, feature, float(voxel))


def coarse_align(
    source: RangeScan,
    target: RangeScan,
    *,
    config: PairwiseConfig = PairwiseConfig(),
    features: tuple[ScanFeatures, ScanFeatures] | None = None,
) -> PairwiseResult:
    """Feature-based coarse alignment: FPFH [2]_ correspondences, RANSAC on them.

    Needs no initial pose. The result is good to a few sample spacings at best; refine
    it with :func:`refine_icp`. Fails (false-valued) when too few samples match.

    features : the two scans' :func:`scan_features`, when already computed
    """
    if features is None:
        spacing = max(median_edge_length(source), median_edge_length(target))
        voxel = config.feature_voxel or 4.0 * spacing
        features = (
            scan_features(source, voxel, min_quality=config.min_quality),
            scan_features(target, voxel, min_quality=config.min_quality),
        )
    for scan, feature in zip((source, target), features):
        if len(feature.cloud.points) < 10:
            return _failure(
                f"scan {scan.name!r} has too few samples ({len(feature.cloud.points)}) for features"
            )
    o3d.utility.random.seed(int(config.seed))
    src, src_f = features[0].cloud, features[0].features
    tgt, tgt_f = features[1].cloud, features[1].features
    voxel = max(features[0].voxel, features[1].voxel)
    distance = 1.5 * voxel
    result = _reg.registration_ransac_based_on_feature_matching(
        src,
        tgt,
        src_f,
        tgt_f,
        True,
        distance,
        _reg.TransformationEstimationPointToPoint(False),
        3,
        [
            _reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
            _reg.CorrespondenceCheckerBasedOnDistance(distance),
        ],
        _reg.RANSACConvergenceCriteria(int(config.ransac_iterations), 0.9999),
    )
    transform = np.asarray(result.transformation).copy()
    fitness = float(result.fitness)
    if fitness < config.min_fitness:
        return _failure(
            f"features matched {fitness:.1%} of {source.name!r} onto {target.name!r} "
            f"(< {config.min_fitness:.0%})",
            transform,
            fitness,
            float(result.inlier_rmse),
        )
    return PairwiseResult(transform, fitness, float(result.inlier_rmse), max_distance=distance)


FGR_SEED = 0
"""Seed of open3d's generator for each pair's Fast Global Registration."""


def feature_hypotheses(
    features: tuple[ScanFeatures, ScanFeatures],
    *,
    seeds: Sequence[int] = (0, 1, 2),
    ransac_iterations: int = 200_000,
    fgr: bool = True,
) -> Iterator[np.ndarray]:
    """Candidate coarse alignments (target_from_source) of two scans from their FPFH
    features [2]_: open3d's Fast Global Registration [5]_, then its RANSAC [4]_ once per
    seed (mutual matches for the first, all matches for the others, with its edge-length
    and distance correspondence checkers). One hypothesis alone is often the wrong
    one on a nearly symmetric object; the caller verifies each (:func:`verify_alignment`)
    after ICP and keeps the best. A generator: each is computed when asked for, so a
    caller that has what it needs (two hypotheses that agree) stops early.

    features : the two scans' :func:`scan_features` (source, target)

    Every hypothesis is seeded (FGR by :data:`FGR_SEED`, each RANSAC by its seed) and found
    on one thread: the same two scans give the same hypotheses in any process, after any
    other pair, on any number of cores.

    Yields (4, 4) float64 transforms; scans with fewer than 10 feature samples give none.
    """
    (src, src_f, sv), (tgt, tgt_f, tv) = ((f.cloud, f.features, f.voxel) for f in features)
    if len(src.points) < 10 or len(tgt.points) < 10:
        return
    distance = 1.5 * max(sv, tv)
    if fgr:  # first: a tenth of a RANSAC's cost, and often the answer
        # FGR draws from open3d's global generator: seeded, its hypothesis does not depend on
        # what ran before it in this process (the pairs before, in whatever order they came)
        o3d.utility.random.seed(FGR_SEED)
        result = _on_one_thread(lambda: _reg.registration_fgr_based_on_feature_matching(
            src, tgt, src_f, tgt_f,
            _reg.FastGlobalRegistrationOption(maximum_correspondence_distance=distance),
        ))
        yield np.asarray(result.transformation).copy()
    for k, seed in enumerate(seeds):
        o3d.utility.random.seed(int(seed))
        result = _on_one_thread(lambda k=k: _reg.registration_ransac_based_on_feature_matching(
            src, tgt, src_f, tgt_f, k == 0, distance,
            _reg.TransformationEstimationPointToPoint(False), 3,
            [_reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             _reg.CorrespondenceCheckerBasedOnDistance(distance)],
            _reg.RANSACConvergenceCriteria(int(ransac_iterations), 0.9999),
        ))
        yield np.asarray(result.transformation).copy()


def _on_one_thread(fn):
    """``fn()`` with open3d on one thread: seeded, its RANSAC still gives different
    hypotheses run to run on several threads (its early exit depends on which thread
    finishes first; open3d issue 7475)."""
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        return fn()
    finally:
        o3d.utility.set_max_threads(before)


def _sensor_projection(scan: RangeScan):
    """How the scan's sensor sees a point of its frame: a function of (k, 3) points giving
    ((k, 2) image coordinates, (k,) range along the ray, mm), and the image coordinates'
    size of one mm at the scan's distance. A perspective sensor at the frame's origin
    when the view direction points from the scan's centroid to the origin (slscan range
    maps), else parallel rays along the view direction (Stanford scans)."""
    d = np.asarray(scan.view_direction, np.float64)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    centroid = scan.vertices.mean(axis=0)
    distance = float(np.linalg.norm(centroid))
    if distance > 0 and float(np.dot(-centroid / distance, d)) > 1 - 1e-6:
        def project(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            depth = np.maximum(p @ -d, 1e-9)
            return np.stack([p @ u / depth, p @ v / depth], axis=1), np.linalg.norm(p, axis=1)

        return project, 1.0 / distance

    def project_parallel(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.stack([p @ u, p @ v], axis=1), -(p @ d)

    return project_parallel, 1.0


def free_space_violation(
    points: np.ndarray, scan: RangeScan, *, margin: float, radius: float
) -> float:
    """Fraction of ``points`` that lie in space ``scan``'s sensor saw to be empty.

    A point seen by the sensor's ray (samples of ``scan`` within ``radius`` mm of it,
    across the ray) more than ``margin`` mm nearer the sensor than the nearest of them stands
    where the ray passed through nothing: a correct alignment puts no surface there. An
    alignment that overlaps well but is wrong (a nearly symmetric object's front on its
    back) puts much of one scan there.

    points : (k, 3) float64, mm, in the scan's frame (e.g. another scan mapped by an
        alignment); scan : the scan whose sensor is asked
    Returns the fraction of the points in the scan's view (0 when none is).
    """
    if len(points) == 0:
        return 0.0
    project, per_mm = _sensor_projection(scan)
    image, depth = project(scan.vertices)
    tree = cKDTree(image)
    pi, pd = project(np.asarray(points, np.float64))
    d, idx = tree.query(pi, k=8, distance_upper_bound=radius * per_mm)
    seen = np.isfinite(d[:, 0])
    if not np.any(seen):
        return 0.0
    # the nearest surface the ray met near the point (a depth edge's near side counts)
    nearest = np.where(np.isfinite(d), np.append(depth, np.inf)[idx], np.inf).min(axis=1)
    return float(np.mean(pd[seen] < nearest[seen] - margin))


@dataclass(frozen=True)
class Verification:
    """How well an alignment of two scans is supported (see :func:`verify_alignment`).

    overlap : the pair's ICP fitness (fraction of the source's samples matched)
    rmse : mm, the ICP inlier RMSE
    violation : the larger of the two :func:`free_space_violation` fractions
    """

    overlap: float
    rmse: float
    violation: float


def verify_alignment(
    source: RangeScan, target: RangeScan, result: PairwiseResult, *, spacing: float,
    samples: int = 3000,
) -> Verification:
    """Overlap, residual and free-space test of an ICP alignment of ``source`` onto
    ``target`` (``result.transform``: target_from_source), both ways: the source's samples
    in the target's view and the target's in the source's. ``spacing`` (mm) sets the
    margin (5 spacings) and the lateral reach (1 spacing: at 2, the far side of a depth edge
    put up to 6 % of a right alignment of the quarter-size figurine in "empty" space); at most ``samples`` samples
    of each scan are tested (an even stride)."""
    t = np.asarray(result.transform, np.float64)
    inv = np.linalg.inv(t)
    sp = source.vertices[:: max(1, source.n_vertices // samples)]
    tp = target.vertices[:: max(1, target.n_vertices // samples)]
    margin, radius = 5.0 * spacing, 1.0 * spacing
    violation = max(
        free_space_violation(sp @ t[:3, :3].T + t[:3, 3], target, margin=margin, radius=radius),
        free_space_violation(tp @ inv[:3, :3].T + inv[:3, 3], source, margin=margin, radius=radius),
    )
    return Verification(float(result.fitness), float(result.inlier_rmse), violation)


# --- fine alignment ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ScanClouds:
    """A scan's samples prepared for ICP once (see :func:`scan_clouds`), for scans met in
    many pairs.

    spacing : mm, :func:`median_edge_length`; extent : mm, :func:`scan_extent`
    min_quality : the quality threshold the samples passed
    levels : {voxel (mm): open3d PointCloud, scan frame, downsampled to it (0: all samples)}
    """

    spacing: float
    extent: float
    min_quality: float
    levels: dict[float, o3d.geometry.PointCloud] = field(repr=False)


def scan_clouds(
    scan: RangeScan, voxels: Sequence[float], *, min_quality: float = 0.05
) -> ScanClouds:
    """Downsample ``scan`` once to each of ``voxels`` (mm), for :func:`refine_icp`."""
    full = scan_point_cloud(scan, min_quality=min_quality)
    return ScanClouds(
        median_edge_length(scan),
        scan_extent(scan),
        float(min_quality),
        {float(v): downsample(full, v) for v in {0.0, *voxels}},
    )


def refine_icp(
    source: RangeScan,
    target: RangeScan,
    init: np.ndarray,
    *,
    config: PairwiseConfig = PairwiseConfig(),
    clouds: tuple[ScanClouds, ScanClouds] | None = None,
) -> PairwiseResult:
    """Multi-scale ICP from ``init`` (target_from_source), coarse to fine voxel sizes.

    Each level downsamples both scans (voxel averages), matches every source sample to
    its nearest target sample within the level's distance, and minimises the
    point-to-plane (or symmetric) distance under a robust kernel. The last level runs
    at full resolution. The result's fitness and RMSE are measured at the finest level.

    clouds : the two scans' :func:`scan_clouds` (same ``min_quality`` as ``config``),
        when already computed; levels they lack are downsampled here
    """
    init = np.asarray(init, np.float64)
    if init.shape != (4, 4):
        raise SlscanError(f"ICP: expected a 4x4 initial transform, got shape {init.shape}")
    if clouds is None or any(c.min_quality != config.min_quality for c in clouds):
        clouds = (
            scan_clouds(source, (), min_quality=config.min_quality),
            scan_clouds(target, (), min_quality=config.min_quality),
        )
    spacing = max(clouds[0].spacing, clouds[1].spacing)
    src_full, tgt_full = clouds[0].levels[0.0], clouds[1].levels[0.0]
    if len(src_full.points) < 10 or len(tgt_full.points) < 10:
        return _failure(f"too few usable samples in {source.name!r} or {target.name!r}", init)
    transform = init.copy()
    distance = math.nan
    result = None
    extent = min(clouds[0].extent, clouds[1].extent)
    for voxel, distance, iterations in _levels(config, spacing, extent):
        src, tgt = (
            c.levels[float(voxel)] if float(voxel) in c.levels else downsample(full, voxel)
            for c, full in zip(clouds, (src_full, tgt_full))
        )
        scale = voxel if voxel > 0 else spacing
        result = _reg.registration_icp(
            src,
            tgt,
            distance,
            transform,
            _estimation(config.method, _kernel(config.robust_kernel, scale)),
            _reg.ICPConvergenceCriteria(1e-7, 1e-7, int(iterations)),
        )
        if len(result.correspondence_set) < 6:
            return _failure(
                f"ICP lost {source.name!r} against {target.name!r} at voxel {voxel:g} mm "
                f"(no overlap within {distance:g} mm)",
                transform,
                float(result.fitness),
            )
        transform = np.asarray(result.transformation).copy()
    information = _reg.get_information_matrix_from_point_clouds(src, tgt, distance, transform)
    fitness, rmse = (
        float(result.fitness),
        _plane_rmse(src, tgt, transform, result.correspondence_set),
    )
    if fitness < config.min_fitness:
        return _failure(
            f"{source.name!r} overlaps {target.name!r} by {fitness:.1%} (< {config.min_fitness:.0%})",
            transform,
            fitness,
            rmse,
            np.asarray(information),
            distance,
        )
    return PairwiseResult(transform, fitness, rmse, np.asarray(information), True, "", distance)


def _plane_rmse(src, tgt, transform: np.ndarray, correspondences) -> float:
    """RMS point-to-plane distance (mm) of ICP correspondences (source i, target j)."""
    pairs = np.asarray(correspondences)
    if len(pairs) == 0:
        return math.nan
    p = np.asarray(src.points)[pairs[:, 0]] @ transform[:3, :3].T + transform[:3, 3]
    q = np.asarray(tgt.points)[pairs[:, 1]]
    n = np.asarray(tgt.normals)[pairs[:, 1]]
    return float(np.sqrt(np.mean(np.einsum("ij,ij->i", p - q, n) ** 2)))


def register_pair(
    source: RangeScan,
    target: RangeScan,
    *,
    init: np.ndarray | None = None,
    config: PairwiseConfig = PairwiseConfig(),
    features: tuple[ScanFeatures, ScanFeatures] | None = None,
    clouds: tuple[ScanClouds, ScanClouds] | None = None,
) -> PairwiseResult:
    """Align ``source`` onto ``target``: coarse, then :func:`refine_icp`.

    Parameters
    ----------
    source, target : RangeScan, each in its own frame (mm)
    init : (4, 4) float64 target_from_source, e.g. ``inv(world_from_target) @
        world_from_source`` from approximate poses; None: found from FPFH features
        (:func:`coarse_align`)
    config : PairwiseConfig
    features : precomputed :func:`scan_features` of (source, target), used without ``init``
    clouds : precomputed :func:`scan_clouds` of (source, target), for the ICP

    Returns
    -------
    PairwiseResult
        False-valued, with the reason, when the scans do not overlap enough.
    """
    if init is None:
        coarse = coarse_align(source, target, config=config, features=features)
        if not coarse:
            return coarse
        init = coarse.transform
    return refine_icp(source, target, init, config=config, clouds=clouds)


def _failure(
    reason: str,
    transform: np.ndarray | None = None,
    fitness: float = 0.0,
    rmse: float = math.nan,
    information: np.ndarray | None = None,
    distance: float = math.nan,
) -> PairwiseResult:
    log.debug("pairwise: %s", reason)
    return PairwiseResult(
        transform=np.eye(4) if transform is None else np.asarray(transform, np.float64),
        fitness=float(fitness),
        inlier_rmse=float(rmse),
        information=np.zeros((6, 6)) if information is None else information,
        success=False,
        reason=reason,
        max_distance=distance,
    )


# --- transform helpers -------------------------------------------------------------------------


def rotation_angle_deg(rotation: np.ndarray) -> float:
    """Angle (degrees) of a 3×3 rotation matrix (or the rotation part of a 4×4)."""
    r = np.asarray(rotation)[:3, :3]
    return math.degrees(math.acos(float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def pose_error(
    estimate: np.ndarray, truth: np.ndarray, *, at: np.ndarray | None = None
) -> tuple[float, float]:
    """(rotation error in degrees, translation error in mm) of a 4×4 pose against the truth.

    The rotation error is the angle of ``R_estimate · R_truthᵀ``. The translation error
    is the distance between where the two poses put the point ``at`` (scan frame, mm):
    by default the scan frame's origin (the distance between the translations); pass
    the scan's centroid to measure how far its samples moved, free of the lever arm
    between a far-away frame origin and the scan.
    """
    estimate, truth = np.asarray(estimate, np.float64), np.asarray(truth, np.float64)
    delta = estimate[:3, :3] @ truth[:3, :3].T
    point = np.zeros(3) if at is None else np.asarray(at, np.float64)
    moved = (estimate[:3, :3] - truth[:3, :3]) @ point + estimate[:3, 3] - truth[:3, 3]
    return rotation_angle_deg(delta), float(np.linalg.norm(moved))


def fit_gauge(
    poses: dict[str, np.ndarray], reference: dict[str, np.ndarray], points: dict[str, np.ndarray]
) -> np.ndarray:
    """The one rigid motion ``G`` that best puts a registration onto reference poses.

    A registration fixes the scans relative to each other; the frame they share is a
    choice (the gauge, e.g. one scan held still). To compare with reference poses free of
    that choice, ``G`` minimises Σ‖G·P_i·x − T_i·x‖² over each scan's ``points`` (scan
    frame, mm) by the closed-form point-to-point fit (open3d's Kabsch/Umeyama without
    scale); compare ``G @ poses[name]`` with ``reference[name]``.
    """
    names = [n for n in poses if n in reference and n in points]
    if not names:
        raise SlscanError("fit_gauge: no scan has both a pose and a reference pose")
    src, dst = [], []
    for name in names:
        h = np.c_[np.asarray(points[name], np.float64), np.ones(len(points[name]))]
        src.append((h @ np.asarray(poses[name], np.float64).T)[:, :3])
        dst.append((h @ np.asarray(reference[name], np.float64).T)[:, :3])
    src_pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack(src)))
    dst_pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.vstack(dst)))
    pairs = np.repeat(np.arange(len(src_pcd.points), dtype=np.int32)[:, None], 2, axis=1)
    estimate = o3d.pipelines.registration.TransformationEstimationPointToPoint(False)
    return np.asarray(
        estimate.compute_transformation(src_pcd, dst_pcd, o3d.utility.Vector2iVector(pairs)),
        np.float64,
    )


def rigid_transform(rotation_vector: Sequence[float], translation: Sequence[float]) -> np.ndarray:
    """(4, 4) transform from an axis-angle rotation vector (radians) and a translation (mm)."""
    from scipy.spatial.transform import Rotation

    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(np.asarray(rotation_vector, np.float64)).as_matrix()
    t[:3, 3] = translation
    return t
