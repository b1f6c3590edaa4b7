"""Volumetric fusion of aligned range scans into one mesh (weighted TSDF), or screened Poisson.

The TSDF route follows Curless & Levoy [1]_: each scan adds a truncated signed distance,
measured along its view direction, to the voxels near its surface, weighted by its
confidence; the zero set of the weighted average is extracted by marching cubes. The
voxels live in open3d's sparse :class:`open3d.t.geometry.VoxelBlockGrid` (8³-voxel
blocks allocated only near surfaces), which also does the extraction.

How a scan is integrated (our scans are meshes with a view direction, not depth
images): the scan's mesh is ray cast (open3d ``RaycastingScene``) into an orthographic
height map looking along -view direction, pixel ``pixel_size``; every voxel of the
blocks within the truncation distance of the scan is projected onto that map and
bilinearly interpolated, giving ``sdf = voxel height - surface height`` (positive in
front of the surface, towards the sensor). Voxels with ``sdf >= -truncation`` are
updated with ``tsdf = min(sdf / truncation, 1)`` and the observation's weight, the scan's
per-vertex quality interpolated at the ray hit (for Stanford scans: cos(view angle) ×
a ramp to 0 at the scan's boundary [1]_) — or 1 with ``weighting="uniform"``. open3d's
own ``integrate`` takes pinhole depth images and counts observations with weight 1 (its
kernel adds exactly 1 per call; no weight per pixel or per call), so the update is done
here, in place on the grid's own attribute buffers (no copies of the grid): compiled by
numba (:mod:`slscan._tsdf_numba`, the ``fast`` extra; one loop over the blocks' voxels)
when numba is installed and the volume has updated :data:`COMPILED_FROM_BLOCKS` blocks
(below that, loading numba costs more than it saves), otherwise in numpy, ``chunk_blocks`` blocks at a time: every
step a whole-array operation on the chunk's voxels, small enough to stay in the CPU's
cache, the four pixels around each voxel fetched with one gather each from shifted
views of the map, the blocks' tsdf and weight rows gathered and written back whole. Both
do the same float32 operations in the same order: the same volume bit for bit.

Memory stays bounded: scans are integrated one at a time (an iterable is consumed
lazily), the blocks a sequence of scans will need are counted before the grid is made
(and checked against ``max_memory_gib``), only blocks not yet in the grid are activated
(open3d doubles and copies its hash map whenever the keys of one activation, present or
not, would overflow it), and voxels are updated in chunks of ``chunk_blocks`` blocks.

References
----------
.. [1] Curless, Levoy, "A volumetric method for building complex models from range
   images", SIGGRAPH 1996.
.. [2] Kazhdan, Hoppe, "Screened Poisson surface reconstruction", ACM ToG 32(3), 2013.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from slscan.errors import SlscanError
from slscan.executor import Executor, map_retrying
from slscan.fsio import atomic_output_file, native_stderr_silenced
from slscan.meshes import MESH_SUFFIXES, check_face_indices, check_finite_vertices, read_ply_mesh
from slscan.register.rangescan import RangeScan

if TYPE_CHECKING:
    from slscan.fuse_stream import StreamedMesh

log = logging.getLogger(__name__)

BLOCK_RESOLUTION = 8
"""Voxels per block edge of the sparse grid."""
BYTES_PER_VOXEL = 8
"""tsdf (float32) + weight (float32)."""
HASHMAP_BYTES_PER_BLOCK = 64
"""Rough per-block overhead of open3d's hash map (key, index, bookkeeping)."""
MAX_EXTRACT_BLOCKS = 200_000
"""Largest grid meshed in one open3d call (open3d 0.20 crashes from 262,144 blocks on)."""


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh in the world frame.

    vertices : (n, 3) float64, mm
    faces : (m, 3) int64 vertex indices, counter-clockwise seen from outside
    normals : (n, 3) float32 unit vertex normals, or None
    colors : (n, 3) uint8 RGB, or None
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)


@dataclass(frozen=True)
class FuseConfig:
    """Options of :func:`fuse_scans` (lengths in mm)."""

    voxel_size: float = 0.5
    """Voxel edge (paper: 0.57 mm for the Minerva; about the scans' sample spacing)."""
    truncation: float = 4.0
    """Truncation distance of the signed distance, in voxels."""
    pixel_size: float | None = None
    """Pixel of the orthographic height maps; None: one voxel."""
    weighting: str = "quality"
    """{"quality", "uniform"}: an observation weighs the scan's vertex quality there, or 1."""
    min_weight: float = 0.1
    """Voxels with less accumulated weight are not meshed (open3d's weight threshold)."""
    chunk_blocks: int = 256
    """Blocks updated at once (memory of the update: about chunk_blocks × 512 × 60 bytes;
    small enough to stay in the CPU's cache, which is faster than larger chunks)."""
    max_memory_gib: float = 10.0
    """Refuse (SlscanError) when the voxel grid would need more than this; with
    ``brick_size``, the cap of each brick (one task on one worker)."""
    brick_size: float | None = None
    """Fuse in cubic bricks of about this edge (mm, rounded to whole 8-voxel blocks), each a
    task on the executor (:func:`fuse_bricks`); None: one volume in this process."""


@dataclass(frozen=True)
class FusionResult:
    """Outcome of :func:`fuse_scans`.

    mesh : the extracted surface; None when :func:`fuse_bricks` streamed it to a file (``written``)
    n_blocks : voxel blocks allocated (each 8³ voxels)
    grid_bytes : memory of the voxel grid (tsdf + weight + hash map estimate)
    n_scans : scans integrated
    seconds : wall time per phase: "height_maps" (ray casting the scans), "integrate"
        (TSDF updates), "extract" (marching cubes); time spent making lazily supplied
        scans is in none of them (in bricks, summed over the bricks, plus "stitch", and
        "pieces": the caller reading (when lazy), ray casting and cutting the scans)
    """

    mesh: Mesh | None
    n_blocks: int
    grid_bytes: int
    n_scans: int
    seconds: dict[str, float] = field(default_factory=dict)
    n_bricks: int = 1
    """Bricks fused (:func:`fuse_bricks`; n_blocks and grid_bytes are then summed over
    them, halo blocks included, and n_scans counts a scan once per brick it reaches)."""
    written: StreamedMesh | None = None
    """:func:`fuse_bricks` with ``out``: the PLY it wrote (path, counts); ``mesh`` is then None."""


# --- height maps ----------------------------------------------------------------------------------


def _basis(direction: np.ndarray) -> np.ndarray:
    """(3, 3) rows u, v, d: a right-handed orthonormal frame with d = ``direction``."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, d)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    return np.stack([u, v, d])


@dataclass(frozen=True, eq=False)
class HeightMap:
    """A scan's surface as heights above a plane perpendicular to its view direction.

    frame : (3, 3) rows u, v, d (d towards the sensor), world
    origin : (3,) world point at pixel (0, 0), height 0
    pixel : mm
    height : (rows, cols) float32 height along d (mm), NaN where the scan has no surface
    weight : (rows, cols) float32 observation weight, 0 where no surface
    offset : (row, col) of ``height[0, 0]`` on the grid whose pixel (0, 0) is at ``origin``
        (a window of a scan's whole map, :mod:`slscan.fuse_pieces`; the voxels' pixel
        coordinates are computed on the whole grid, so a window updates them bit for bit
        as the whole map does)
    """

    frame: np.ndarray
    origin: np.ndarray
    pixel: float
    height: np.ndarray
    weight: np.ndarray
    offset: tuple[int, int] = (0, 0)

    def surface_points(self) -> np.ndarray:
        """(k, 3) float64 world points of the pixels that see the surface."""
        r, c = np.nonzero(np.isfinite(self.height))
        h = self.height[r, c].astype(np.float64)
        r += self.offset[0]
        c += self.offset[1]
        local = np.stack([c * self.pixel, r * self.pixel, h], 1)
        # einsum, not matmul: BLAS takes 5x longer for (k, 3) @ (3, 3) (same to rounding)
        return np.einsum("ij,jk->ik", local, self.frame) + self.origin

    def bordered(self) -> tuple[np.ndarray, np.ndarray]:
        """Flat (rows * cols,) float32 copies of ``height`` and ``weight`` whose border
        pixels see no surface (NaN), so that a point clipped onto the border samples
        nothing."""
        height = self.height.astype(np.float32, copy=True)
        weight = self.weight.astype(np.float32, copy=True)
        for a in (height, weight):
            a[[0, -1], :] = np.nan
            a[:, [0, -1]] = np.nan
        return height.reshape(-1), weight.reshape(-1)

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance along d (mm) and weight at world ``points`` (k, 3).

        Bilinear in the height map; the weight is 0 (and sdf NaN) unless all four
        neighbouring pixels see the surface.
        """
        local = ((np.asarray(points, np.float64) - self.origin) @ self.frame.T).astype(np.float32)
        return self.sample_local(local[:, 0] / self.pixel, local[:, 1] / self.pixel, local[:, 2])

    def sample_local(
        self, x: np.ndarray, y: np.ndarray, z: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`sample` at map coordinates: x, y in pixels, z heights (mm), float32 (k,)."""
        if self.offset != (0, 0):
            x, y = x - np.float32(self.offset[1]), y - np.float32(self.offset[0])
        rows, cols = self.height.shape
        inside = (x >= 0) & (y >= 0) & (x < cols - 1) & (y < rows - 1)
        c0 = x.astype(np.int32)
        r0 = y.astype(np.int32)
        c0[~inside] = 0
        r0[~inside] = 0
        fx = x - c0
        fy = y - r0
        i = r0 * np.int32(cols) + c0
        h = self.height.reshape(-1)
        top = h[i]
        top += (h[i + 1] - top) * fx
        bottom = h[i + cols]
        bottom += (h[i + cols + 1] - bottom) * fx
        top += (bottom - top) * fy
        sdf = z - top
        sdf[~inside] = np.nan
        weight = np.zeros(len(sdf), np.float32)
        ok = np.flatnonzero(np.isfinite(sdf))
        if len(ok):
            w = self.weight.reshape(-1)
            j, gx, gy = i[ok], fx[ok], fy[ok]
            wt = w[j]
            wt += (w[j + 1] - wt) * gx
            wb = w[j + cols]
            wb += (w[j + cols + 1] - wb) * gx
            wt += (wb - wt) * gy
            weight[ok] = wt
        return sdf, weight


def height_map(
    scan: RangeScan,
    pose: np.ndarray,
    *,
    pixel: float,
    weighting: str = "quality",
    window: tuple[np.ndarray, np.ndarray] | None = None,
) -> HeightMap:
    """Ray cast ``scan`` (placed by ``pose``, world_from_scan) into an orthographic height map.

    Rays run along -view direction from above the scan; a ray's height is the first
    surface it meets, its weight the scan's quality interpolated there (or 1 with
    ``weighting="uniform"``). Hits on faces turned away from the sensor are dropped.
    window : (lo, hi) (3,) world box, mm: only the pixels whose rays pass through it
        (and two around them) are cast, the others see no surface; the map's grid and
        the pixels cast are those of the whole map (a brick of :func:`fuse_bricks`).
    """
    import open3d as o3d
    import open3d.core as o3c

    if pixel <= 0:
        raise SlscanError(f"height map pixel must be positive, got {pixel}")
    pose = np.asarray(pose, np.float64)
    world = scan.transformed_vertices(pose)
    frame = _basis(pose[:3, :3] @ scan.view_direction)
    local = world @ frame.T
    lo, hi = local.min(axis=0), local.max(axis=0)
    origin_local = np.array([lo[0] - pixel, lo[1] - pixel, 0.0])
    cols = math.ceil((hi[0] - lo[0]) / pixel) + 3
    rows = math.ceil((hi[1] - lo[1]) / pixel) + 3
    if rows * cols > 200_000_000:
        raise SlscanError(
            f"scan {scan.name!r}: a height map of {rows}x{cols} pixels of {pixel:g} mm is too "
            "large; use a larger voxel size"
        )
    centred = (local - origin_local).astype(np.float32)
    top = float(hi[2] - origin_local[2]) + 10 * pixel
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3c.Tensor(centred), o3c.Tensor(np.ascontiguousarray(scan.faces, dtype=np.uint32))
    )
    height = np.full((rows, cols), np.nan, np.float32)
    weight = np.zeros((rows, cols), np.float32)
    quality = scan.quality.astype(np.float32)
    r_lo, r_hi, c_lo, c_hi = 0, rows, 0, cols
    if window is not None:
        corners = np.stack(np.meshgrid(*zip(window[0], window[1]), indexing="ij"), -1).reshape(-1, 3)
        px = ((corners @ frame.T)[:, :2] - origin_local[:2]) / pixel
        c_lo, c_hi = max(0, math.floor(px[:, 0].min()) - 2), min(cols, math.ceil(px[:, 0].max()) + 3)
        r_lo, r_hi = max(0, math.floor(px[:, 1].min()) - 2), min(rows, math.ceil(px[:, 1].max()) + 3)
        if c_lo >= c_hi:
            r_hi = r_lo
    band = max(1, 4_000_000 // max(c_hi - c_lo, 1))
    for r_start in range(r_lo, r_hi, band):
        r_stop = min(r_hi, r_start + band)
        rr, cc = np.mgrid[r_start:r_stop, c_lo:c_hi]
        rays = np.zeros((r_stop - r_start, c_hi - c_lo, 6), np.float32)
        rays[..., 0] = cc * pixel
        rays[..., 1] = rr * pixel
        rays[..., 2] = top
        rays[..., 5] = -1.0
        hit = scene.cast_rays(o3c.Tensor(rays))
        t = hit["t_hit"].numpy()
        ok = np.isfinite(t) & (hit["primitive_normals"].numpy()[..., 2] > 0)
        h = np.where(ok, top - t, np.nan).astype(np.float32)
        height[r_start:r_stop, c_lo:c_hi] = h
        if weighting == "uniform":
            weight[r_start:r_stop, c_lo:c_hi] = ok.astype(np.float32)
        else:
            prim = hit["primitive_ids"].numpy()[ok].astype(np.int64)
            uv = hit["primitive_uvs"].numpy()[ok]
            f = scan.faces[prim]
            q = (
                quality[f[:, 0]] * (1 - uv[:, 0] - uv[:, 1])
                + quality[f[:, 1]] * uv[:, 0]
                + quality[f[:, 2]] * uv[:, 1]
            )
            w = np.zeros(ok.shape, np.float32)
            w[ok] = np.clip(q, 0.0, 1.0)
            weight[r_start:r_stop, c_lo:c_hi] = w
    origin = origin_local @ frame
    return HeightMap(frame=frame, origin=origin, pixel=float(pixel), height=height, weight=weight)


def _bilinear(
    v00: np.ndarray, v01: np.ndarray, v10: np.ndarray, v11: np.ndarray,
    i: np.ndarray, fx: np.ndarray, fy: np.ndarray,
) -> np.ndarray:
    """Bilinear interpolation of a flat map at cells ``i`` (top-left pixel index) and
    fractions ``fx``, ``fy``, given the map as four views shifted to the cell's corners
    (float32, same shape as ``i``; NaN when any corner is NaN)."""
    top = np.take(v01, i)
    left = np.take(v00, i)
    top -= left
    top *= fx
    top += left
    bottom = np.take(v11, i)
    left = np.take(v10, i, out=left)
    bottom -= left
    bottom *= fx
    bottom += left
    bottom -= top
    bottom *= fy
    top += bottom
    return top


# --- block bookkeeping ----------------------------------------------------------------------------


def _block_keys(points: np.ndarray, block_size: float, reach: float) -> np.ndarray:
    """Unique int64 keys of the blocks within ``reach`` (per axis) of ``points``."""
    steps = math.ceil(2 * reach / block_size) + 1
    offsets = np.linspace(-reach, reach, steps)
    # per axis, the (shifted) block coordinate of every point moved by every offset
    axes = [
        [np.floor((points[:, a] + off) / block_size).astype(np.int64) + 2**20 for off in offsets]
        for a in range(3)
    ]
    axes = _distinct_coordinates(axes) or axes
    axes = [[c << shift for c in axis] for axis, shift in zip(axes, (42, 21, 0))]
    keys = [np.unique(x | y | z) for x in axes[0] for y in axes[1] for z in axes[2]]
    return np.unique(np.concatenate(keys))


def _distinct_coordinates(axes: list[list[np.ndarray]]) -> list[list[np.ndarray]] | None:
    """:func:`_block_keys`' block coordinates per axis and offset, of one point of each
    distinct combination of all of them (points alike in every one touch the same
    blocks): each point's coordinates at the first offset and their increases at the
    others, packed into one int64 (one ``np.unique`` over the points instead of one per
    combination of offsets), unpacked for the distinct ones. None when they do not fit."""
    first = [axis[0] for axis in axes]
    low = [int(c.min()) for c in first]
    spans = [int(c.max()) - m + 1 for c, m in zip(first, low)]
    steps = [axis[j] - axis[0] for axis in axes for j in range(1, len(axis))]
    if any(int(d.min()) < 0 for d in steps):
        return None
    base = max((int(d.max()) for d in steps), default=0) + 1
    if math.prod(spans) * base ** len(steps) >= 2**62:
        return None
    code = ((first[0] - low[0]) * spans[1] + (first[1] - low[1])) * spans[2] + (first[2] - low[2])
    for d in steps:
        code = code * base + d
    code = np.unique(code)
    unpacked = []
    for _ in steps:
        unpacked.append(code % base)
        code //= base
    unpacked.reverse()
    z = code % spans[2] + low[2]
    code //= spans[2]
    coordinates = [code // spans[1] + low[0], code % spans[1] + low[1], z]
    per_axis = len(axes[0]) - 1
    return [
        [c] + [c + d for d in unpacked[a * per_axis : (a + 1) * per_axis]]
        for a, c in enumerate(coordinates)
    ]


def _key_coords(keys: np.ndarray) -> np.ndarray:
    """(k, 3) int32 block coordinates of :func:`_block_keys` keys."""
    mask = 2**21 - 1
    return np.stack(
        [(keys >> 42) - 2**20, ((keys >> 21) & mask) - 2**20, (keys & mask) - 2**20], 1
    ).astype(np.int32)


def estimate_blocks(
    scans: Sequence[RangeScan],
    poses: Mapping[str, np.ndarray],
    *,
    voxel_size: float,
    truncation: float = 4.0,
) -> int:
    """Number of voxel blocks fusing ``scans`` will allocate (from their vertices)."""
    block = voxel_size * BLOCK_RESOLUTION
    total = np.zeros(0, np.int64)
    for scan in scans:
        keys = _block_keys(
            scan.transformed_vertices(poses[scan.name]), block, truncation * voxel_size
        )
        total = np.union1d(total, keys)
    return len(total)


def grid_memory_bytes(n_blocks: int) -> int:
    """Bytes of a TSDF voxel grid of ``n_blocks`` blocks (tsdf, weight, hash map)."""
    return int(n_blocks) * (BLOCK_RESOLUTION**3 * BYTES_PER_VOXEL + HASHMAP_BYTES_PER_BLOCK)


# --- fusion ---------------------------------------------------------------------------------------

_VOXEL_LATTICE = np.stack(
    np.meshgrid(*(np.arange(BLOCK_RESOLUTION, dtype=np.float64),) * 3, indexing="ij")[::-1], -1
).reshape(-1, 3)
"""(512, 3) voxel offsets (x, y, z) within a block, x fastest (open3d's storage order)."""


COMPILED_FROM_BLOCKS = 100_000
"""Blocks a volume updates in numpy before it loads the numba kernel: loading it (import
numba and the cached kernel) costs about 0.4 s CPU, the kernel saves about 5 µs a block
(measured on 2 cores), so a small fusion is done sooner without it."""
_KERNEL: list = []
"""The numba voxel update once looked for: [] not yet, [None] numba missing, [kernel]."""


def _compiled_update():
    """:func:`slscan._tsdf_numba.update`, or None without numba (imported on first use, so
    that only fusion pays for numba's import and the kernel's compile or cache load)."""
    if not _KERNEL:
        try:
            from slscan._tsdf_numba import update
        except ImportError as exc:  # numba missing, or not importable with this numpy
            log.debug("TSDF update in numpy: %s", exc)
            update = None
        _KERNEL.append(update)
    return _KERNEL[0]


class TsdfVolume:
    """A sparse weighted-TSDF volume (open3d VoxelBlockGrid) that integrates range scans one by one.

    voxel_size : mm; truncation : voxels; block_count : initial capacity in blocks (the
    hash map grows beyond it, at the cost of a copy).
    """

    def __init__(
        self, voxel_size: float, *, truncation: float = 4.0, block_count: int = 10_000
    ) -> None:
        if not (math.isfinite(voxel_size) and voxel_size > 0):
            raise SlscanError(f"voxel size must be a positive number of mm, got {voxel_size}")
        if truncation < 1:
            raise SlscanError(f"truncation must be at least 1 voxel, got {truncation}")
        self.voxel_size = float(voxel_size)
        self.truncation = float(truncation)
        self.grid = self._empty_grid(block_count)
        self.n_scans = 0
        self.blocks_updated = 0
        """Blocks updated so far, summed over the scans (decides the voxel update)."""

    @property
    def n_blocks(self) -> int:
        return int(self.grid.hashmap().size())

    def integrate(
        self,
        depth: HeightMap,
        *,
        chunk_blocks: int = 256,
        compiled: bool | None = None,
        block_range: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Add one scan's height map to the volume (see the module docstring).

        compiled : update the voxels with the numba kernel (:mod:`slscan._tsdf_numba`,
            the ``fast`` extra) or in numpy, whose results are the same bit for bit;
            None: the kernel when numba is installed and either this process has loaded
            it already or the volume has updated :data:`COMPILED_FROM_BLOCKS` blocks.
        block_range : (lo, hi) (3,) int block coordinates: only the blocks with
            ``lo <= coords < hi`` are allocated and updated (a brick of
            :func:`fuse_bricks`); each is updated exactly as without the range.
        """
        points = depth.surface_points()
        if len(points) == 0:
            return
        trunc = self.truncation * self.voxel_size
        res3 = BLOCK_RESOLUTION**3
        coords = _key_coords(_block_keys(points, self.voxel_size * BLOCK_RESOLUTION, trunc))
        del points
        if block_range is not None:
            lo, hi = block_range
            coords = coords[np.all((coords >= lo) & (coords < hi), axis=1)]
            if len(coords) == 0:
                self.n_scans += 1
                return
        buf = self._blocks(coords)
        # voxel (x, y, z) of a block sits at (block * res + (x, y, z)) * voxel_size; in the
        # map's frame (pixels across, mm along d) that is a per-block offset plus a
        # per-voxel lattice (x fastest, as open3d stores them)
        frame = depth.frame * np.array([1.0 / depth.pixel, 1.0 / depth.pixel, 1.0])[:, None]
        base = (coords * (BLOCK_RESOLUTION * self.voxel_size) - depth.origin) @ frame.T
        lattice = (_VOXEL_LATTICE * self.voxel_size) @ frame.T
        rows_px, cols_px = depth.height.shape
        height, weight_px = depth.bordered()
        # the four pixels around a point as views: one gather each, no index arithmetic
        h00, h01, h10, h11 = (height[k:] for k in (0, 1, cols_px, cols_px + 1))
        w00, w01, w10, w11 = (weight_px[k:] for k in (0, 1, cols_px, cols_px + 1))
        cols = np.int32(cols_px)
        r_off, c_off = (np.int32(o) for o in depth.offset)
        x_min, y_min = np.float32(c_off), np.float32(r_off)
        x_max = np.float32(c_off + cols_px - 2)
        y_max = np.float32(r_off + rows_px - 2)
        lattice = lattice.T.astype(np.float32)
        tsdf = self.grid.attribute("tsdf").numpy().reshape(-1, res3)
        weight = self.grid.attribute("weight").numpy().reshape(-1, res3)
        inv_trunc = np.float32(1.0 / trunc)
        use_kernel = compiled
        if use_kernel is None:  # once the kernel pays for its loading, or when loaded already
            use_kernel = bool(_KERNEL) or self.blocks_updated >= COMPILED_FROM_BLOCKS
        kernel = _compiled_update() if use_kernel else None
        if compiled and kernel is None:
            raise SlscanError("compiled TSDF update asked for, but numba is not installed "
                              "(pip install 'slscan[fast]')")
        self.blocks_updated += len(buf)
        if kernel is not None:
            kernel(tsdf, weight, buf, base.astype(np.float32), np.ascontiguousarray(lattice),
                   height, weight_px, cols_px, x_max, y_max, np.float32(-trunc), inv_trunc, c_off, r_off)
            self.n_scans += 1
            return
        for start in range(0, len(buf), chunk_blocks):
            rows = buf[start : start + chunk_blocks]
            b = base[start : start + chunk_blocks].astype(np.float32)
            x = b[:, 0:1] + lattice[0]
            y = b[:, 1:2] + lattice[1]
            sdf = b[:, 2:3] + lattice[2]
            # outside the map: clipped onto its border, whose pixels see no surface (NaN)
            np.clip(x, x_min, x_max, out=x)
            np.clip(y, y_min, y_max, out=y)
            i = x.astype(np.int32)
            r0 = y.astype(np.int32)
            x -= i
            y -= r0
            if c_off or r_off:  # a window: its pixels from the whole grid's
                i -= c_off
                r0 -= r_off
            r0 *= cols
            i += r0
            del r0
            h = _bilinear(h00, h01, h10, h11, i, x, y)
            w = _bilinear(w00, w01, w10, w11, i, x, y)
            sdf -= h
            ok = sdf >= -trunc  # False where NaN: a pixel without surface
            ok &= w > 0
            if not ok.any():
                continue
            w[~ok] = 0.0
            sdf *= inv_trunc
            np.minimum(sdf, np.float32(1.0), out=sdf)
            t_old = tsdf[rows]
            w_old = weight[rows]
            total = w_old + w
            t_new = t_old * w_old
            sdf *= w
            t_new += sdf
            np.divide(t_new, total, out=t_old, where=ok)
            tsdf[rows] = t_old
            weight[rows] = total
        self.n_scans += 1

    def _blocks(self, coords: np.ndarray) -> np.ndarray:
        """Buffer indices (int64) of the blocks at ``coords`` (k, 3), allocated where new.

        Only the missing blocks are activated: open3d grows (doubles and copies) its hash
        map whenever the keys of one activation, present or not, would overflow it.
        """
        import open3d.core as o3c

        hashmap = self.grid.hashmap()
        coords_t = o3c.Tensor(np.ascontiguousarray(coords, dtype=np.int32))
        buf, found = hashmap.find(coords_t)
        missing = ~found.numpy().astype(bool)
        if missing.any():
            new_buf, new_mask = hashmap.activate(
                o3c.Tensor(np.ascontiguousarray(coords[missing], dtype=np.int32))
            )
            new_buf = new_buf.numpy()[new_mask.numpy().astype(bool)].astype(np.int64)
            res3 = BLOCK_RESOLUTION**3
            # attribute buffers move when the hash map grows: views taken after activation
            self.grid.attribute("weight").numpy().reshape(-1, res3)[new_buf] = 0.0
            self.grid.attribute("tsdf").numpy().reshape(-1, res3)[new_buf] = 1.0
            buf, found = hashmap.find(coords_t)
        return buf.numpy().astype(np.int64)

    def extract_mesh(self, *, min_weight: float = 0.1) -> Mesh:
        """Marching-cubes surface of the volume (open3d ``extract_triangle_mesh``).

        open3d 0.20 crashes (32-bit offsets into its per-voxel mesh structure) on grids
        of 2^18 = 262,144 blocks or more, so larger volumes are meshed in slabs of whole
        block layers along x (:data:`MAX_EXTRACT_BLOCKS` blocks each, plus the next layer
        as a halo); each slab keeps the triangles of its own cubes, and the vertices on
        the planes between slabs, computed identically by both, are welded.
        """
        import open3d.core as o3c

        hashmap = self.grid.hashmap()
        n = self.n_blocks
        if n == 0:
            return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
        if n <= MAX_EXTRACT_BLOCKS:
            return _extract(self.grid, min_weight)
        buf = hashmap.active_buf_indices().numpy().astype(np.int64)
        keys = hashmap.key_tensor().numpy()[buf].astype(np.int64)
        order = np.argsort(keys[:, 0], kind="stable")
        buf, keys = buf[order], keys[order]
        layers, starts, counts = np.unique(keys[:, 0], return_index=True, return_counts=True)
        if counts.max() * 2 > MAX_EXTRACT_BLOCKS:
            raise SlscanError(
                f"fusion grid: one block layer holds {counts.max()} blocks, too many to mesh "
                f"with open3d; use a larger voxel size"
            )
        tsdf = self.grid.attribute("tsdf").numpy().reshape(-1, BLOCK_RESOLUTION**3)
        weight = self.grid.attribute("weight").numpy().reshape(-1, BLOCK_RESOLUTION**3)
        block_size = self.voxel_size * BLOCK_RESOLUTION
        pieces = []
        first = 0
        while first < len(layers):
            last = first
            total = counts[first]
            while (
                last + 1 < len(layers)
                and total + counts[last + 1] + counts[min(last + 2, len(layers) - 1)]
                <= MAX_EXTRACT_BLOCKS
            ):
                last += 1
                total += counts[last]
            own = slice(starts[first], starts[last] + counts[last])
            halo = (
                slice(starts[last + 1], starts[last + 1] + counts[last + 1])
                if last + 1 < len(layers)
                else slice(0, 0)
            )
            if last + 1 < len(layers) and layers[last + 1] != layers[last] + 1:
                halo = slice(0, 0)
            group_keys = np.concatenate([keys[own], keys[halo]])
            group_buf = np.concatenate([buf[own], buf[halo]])
            grid = self._empty_grid(len(group_keys) + 16)
            new_buf, _ = grid.hashmap().activate(o3c.Tensor(group_keys.astype(np.int32)))
            new_buf = new_buf.numpy().astype(np.int64)
            grid.attribute("tsdf").numpy().reshape(-1, BLOCK_RESOLUTION**3)[new_buf] = tsdf[
                group_buf
            ]
            grid.attribute("weight").numpy().reshape(-1, BLOCK_RESOLUTION**3)[new_buf] = weight[
                group_buf
            ]
            mesh = _extract(grid, min_weight)
            del grid
            if mesh.n_faces:
                centroid_x = mesh.vertices[mesh.faces].mean(axis=1)[:, 0]
                block_x = np.floor(centroid_x / block_size + 1e-9)
                keep = block_x <= layers[last]
                pieces.append((mesh, keep, float(layers[last] + 1) * block_size))
            first = last + 1
        return _weld(pieces, self.voxel_size)

    def _empty_grid(self, block_count: int):
        import open3d as o3d
        import open3d.core as o3c

        return o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"),
            attr_dtypes=(o3c.float32, o3c.float32),
            attr_channels=((1), (1)),
            voxel_size=self.voxel_size,
            block_resolution=BLOCK_RESOLUTION,
            block_count=max(int(block_count), 1),
            device=o3c.Device("CPU:0"),
        )


def _extract(grid, min_weight: float) -> Mesh:
    """open3d's marching cubes of ``grid``; an empty mesh where its blocks hold no surface
    (open3d raises then, on the empty colour tensor it makes)."""
    try:
        return _mesh_arrays(grid.extract_triangle_mesh(weight_threshold=float(min_weight)))
    except RuntimeError as exc:
        if "has shape {0}" not in str(exc):
            raise
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))


def _mesh_arrays(mesh) -> Mesh:
    """A :class:`Mesh` of an open3d tensor TriangleMesh (normals re-normalised)."""
    vertices = mesh.vertex.positions.numpy().astype(np.float64)
    faces = (
        mesh.triangle.indices.numpy().astype(np.int64)
        if "indices" in mesh.triangle
        else np.zeros((0, 3), np.int64)
    )
    normals = mesh.vertex.normals.numpy().astype(np.float32) if "normals" in mesh.vertex else None
    if normals is not None:
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = normals / np.where(length > 0, length, 1)
    return Mesh(vertices, faces, normals)


def canonical_order(mesh: Mesh) -> Mesh:
    """The same mesh with its vertices sorted by position (x, then y, then z) and its
    faces by their vertices, each face starting at its lowest index (orientation kept).

    open3d's multithreaded marching cubes orders vertices and faces differently from run
    to run; simplification visits them in order, so without this the simplified (and
    textured) model of the same scans would differ between runs by up to a few tenths of
    a millimetre, which regression checks would have to tolerate.
    """
    if mesh.n_vertices == 0:
        return mesh
    order = _position_order(mesh.vertices)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    faces = rank[mesh.faces]
    start = np.argmin(faces, axis=1)[:, None]
    faces = np.take_along_axis(faces, (start + np.arange(3)) % 3, axis=1)
    if mesh.n_vertices <= 2**21:
        # one int64 key per face (21 bits a vertex) sorts like the three columns; faces
        # with equal keys are equal rows, so the sort need not be stable
        faces = faces[np.argsort((faces[:, 0] << 42) | (faces[:, 1] << 21) | faces[:, 2])]
    elif mesh.n_vertices <= 2**31:
        faces = faces[np.lexsort(((faces[:, 1] << 32) | faces[:, 2], faces[:, 0]))]
    else:
        faces = faces[np.lexsort(faces.T[::-1])]
    return Mesh(
        mesh.vertices[order],
        faces,
        None if mesh.normals is None else mesh.normals[order],
        None if mesh.colors is None else mesh.colors[order],
    )


def _position_order(vertices: np.ndarray) -> np.ndarray:
    """``np.lexsort(vertices.T[::-1])``: the stable order by x, then y, then z; with two
    sort keys instead of three when every coordinate is a float32 (open3d's marching
    cubes): x and y in one uint64 of order-preserving bit patterns, then z."""
    single = vertices.astype(np.float32)
    if not np.array_equal(single, vertices):  # also NaN
        return np.lexsort(vertices.T[::-1])
    single += np.float32(0.0)  # -0 to +0, equal to it as a float
    bits = single.view(np.uint32)
    # negative floats: all bits flipped (larger magnitude, smaller key); others: sign set
    keys = np.where(bits >> 31 == 1, ~bits, bits | np.uint32(2**31))
    xy = (keys[:, 0].astype(np.uint64) << np.uint64(32)) | keys[:, 1]
    return np.lexsort((keys[:, 2], xy))


def _weld(pieces: list[tuple[Mesh, np.ndarray, float]], voxel_size: float) -> Mesh:
    """Join slab meshes: keep each slab's own faces, merge vertices equal on the slab planes."""
    vertices, faces, normals = [], [], []
    offset = 0
    planes = []
    for mesh, keep, plane_x in pieces:
        used = np.unique(mesh.faces[keep].reshape(-1))
        remap = np.full(mesh.n_vertices, -1, np.int64)
        remap[used] = np.arange(len(used)) + offset
        vertices.append(mesh.vertices[used])
        normals.append(
            mesh.normals[used] if mesh.normals is not None else np.zeros((len(used), 3), np.float32)
        )
        faces.append(remap[mesh.faces[keep]])
        offset += len(used)
        planes.append(plane_x)
    v = np.concatenate(vertices) if vertices else np.zeros((0, 3))
    f = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    nrm = np.concatenate(normals) if normals else np.zeros((0, 3), np.float32)
    on_plane = np.zeros(len(v), bool)
    for plane_x in planes[:-1]:
        on_plane |= np.abs(v[:, 0] - plane_x) < 1e-3 * voxel_size
    candidates = np.flatnonzero(on_plane)
    if len(candidates):
        rows = (
            np.ascontiguousarray(v[candidates].astype(np.float32))
            .view(np.dtype((np.void, 12)))
            .ravel()
        )
        _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
        target = np.arange(len(v))
        target[candidates] = candidates[first[inverse.ravel()]]
        f = target[f]
        used = np.unique(f.reshape(-1))
        remap = np.full(len(v), -1, np.int64)
        remap[used] = np.arange(len(used))
        v, nrm, f = v[used], nrm[used], remap[f]
    return Mesh(v, f, nrm)


def _integrate_scan(volume: TsdfVolume, scan, pose: np.ndarray, pixel: float, config: FuseConfig,
                    seconds: dict[str, float], *, window=None, block_range=None) -> None:
    """Cast one scan's height map (within ``window``) and add it to ``volume`` (its blocks in
    ``block_range``), adding the times to ``seconds["height_maps"]`` and ``["integrate"]``."""
    t0 = time.perf_counter()
    depth = height_map(scan, pose, pixel=pixel, weighting=config.weighting, window=window)
    t1 = time.perf_counter()
    volume.integrate(depth, chunk_blocks=config.chunk_blocks, block_range=block_range)
    seconds["height_maps"] += t1 - t0
    seconds["integrate"] += time.perf_counter() - t1


def fuse_scans(
    scans: Iterable[RangeScan],
    poses: Mapping[str, np.ndarray],
    *,
    config: FuseConfig = FuseConfig(),
    expected_blocks: int | None = None,
    progress: Callable[[str], None] | None = None,
    executor: Executor | None = None,
    progress_total: Callable[[int], None] | None = None,
    scratch_beside: str | os.PathLike | None = None,
) -> FusionResult:
    """Fuse aligned range scans into one mesh with a weighted TSDF (Curless & Levoy [1]_).

    Parameters
    ----------
    scans : RangeScan, each in its own frame (mm). A sequence is first scanned for the
        blocks it needs (memory check, grid pre-allocation); any other iterable is
        consumed one scan at a time, so scans can be made or loaded lazily.
    poses : {name: (4, 4) world_from_scan} for every scan, mm
    config : FuseConfig
    expected_blocks : block capacity to allocate when ``scans`` is not a sequence
    progress : called with the scan's name after each scan is integrated (with
        ``config.brick_size``: with the brick's name after each brick)
    executor : where the bricks run when ``config.brick_size`` is set (None: this process)
    progress_total : called with the number of bricks before the first runs (progress bars)
    scratch_beside : with ``config.brick_size``, the output file beside which the bricks'
        scratch folder is made (:func:`fuse_bricks`)

    Returns
    -------
    FusionResult
        The mesh (vertices in mm, world frame; outward normals) and the grid's size.

    Raises
    ------
    SlscanError
        A scan without a pose, bad options, or a grid larger than ``max_memory_gib``.
    """
    if config.brick_size is not None:
        return fuse_bricks(scans, poses, config=config, executor=executor, progress=progress,
                           progress_total=progress_total, scratch_beside=scratch_beside)
    if config.weighting not in ("quality", "uniform"):
        raise SlscanError(f"weighting {config.weighting!r}: expected 'quality' or 'uniform'")
    voxel = float(config.voxel_size)
    if not (math.isfinite(voxel) and voxel > 0):
        raise SlscanError(f"voxel size must be a positive number of mm, got {voxel}")
    pixel = config.pixel_size or voxel
    limit = config.max_memory_gib * 2**30
    if isinstance(scans, Sequence):
        missing = [s.name for s in scans if s.name not in poses]
        if missing:
            raise SlscanError(f"no pose for scans {missing}")
        expected_blocks = estimate_blocks(
            scans, poses, voxel_size=voxel, truncation=config.truncation
        )
    if expected_blocks is not None and grid_memory_bytes(expected_blocks) > limit:
        raise SlscanError(
            f"fusion at {voxel:g} mm voxels needs about {grid_memory_bytes(expected_blocks) / 2**30:.1f} GiB "
            f"({expected_blocks} blocks) > max_memory_gib {config.max_memory_gib:g}; use a larger voxel size"
        )
    volume = TsdfVolume(
        voxel,
        truncation=config.truncation,
        block_count=int((expected_blocks or 10_000) * 1.05) + 16,
    )
    seconds = {"height_maps": 0.0, "integrate": 0.0, "extract": 0.0}
    for scan in scans:
        if scan.name not in poses:
            raise SlscanError(f"no pose for scan {scan.name!r}")
        _integrate_scan(volume, scan, poses[scan.name], pixel, config, seconds)
        if grid_memory_bytes(volume.n_blocks) > limit:
            raise SlscanError(
                f"fusion grid grew past max_memory_gib {config.max_memory_gib:g} "
                f"({volume.n_blocks} blocks); use a larger voxel size"
            )
        log.debug("fused %s: %d blocks", scan.name, volume.n_blocks)
        if progress is not None:
            progress(scan.name)
    t0 = time.perf_counter()
    mesh = canonical_order(volume.extract_mesh(min_weight=config.min_weight))
    seconds["extract"] = time.perf_counter() - t0
    return FusionResult(
        mesh, volume.n_blocks, grid_memory_bytes(volume.n_blocks), volume.n_scans, seconds
    )


# --- fusion in bricks -----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _BrickTask:
    """One brick of :func:`fuse_bricks`: its core blocks ``lo <= coords < hi`` (int (3,)),
    the scans that reach it (in the caller's order) and their poses."""

    index: tuple[int, int, int]
    lo: np.ndarray
    hi: np.ndarray
    scans: tuple[RangeScan, ...]
    poses: dict[str, np.ndarray]
    config: FuseConfig
    expected_blocks: int
    scratch: str | None = None
    """Folder where the brick writes its mesh piece (:mod:`slscan.fuse_stream`); None: the
    piece is returned in the result."""
    pieces: tuple[str, ...] = ()
    """Paths of the brick's piece files (:mod:`slscan.fuse_pieces`), in the caller's scan
    order; when given, ``scans`` and ``poses`` are empty."""


@dataclass(frozen=True, eq=False)
class _BrickResult:
    """A brick's triangles (those of the marching cubes in its core) and its grid's size;
    with a scratch folder, the piece's file and counts instead of the mesh."""

    index: tuple[int, int, int]
    mesh: Mesh | None
    n_blocks: int
    n_scans: int
    seconds: dict[str, float]
    piece: Path | None = None
    n_faces: int = 0


def _size(n_bytes: float) -> str:
    """``n_bytes`` for people: "5.1 GiB", "12 MiB", "40 KiB"."""
    if n_bytes >= 2**30 / 10:
        return f"{n_bytes / 2**30:.1f} GiB"
    if n_bytes >= 2**20:
        return f"{n_bytes / 2**20:.0f} MiB"
    return f"{n_bytes / 2**10:.0f} KiB"


def _brick_blocks(
    scans: Sequence[RangeScan], poses: Mapping[str, np.ndarray], *, voxel: float, truncation: float,
    edge: int,
) -> dict[tuple[int, int, int], int]:
    """The blocks each brick of ``edge`` blocks a side will allocate, its one-block halo
    included, estimated from the scans' vertices as :func:`estimate_blocks` does:
    {brick coordinates: blocks}."""
    block = voxel * BLOCK_RESOLUTION
    keys = np.zeros(0, np.int64)
    for scan in scans:
        keys = np.union1d(keys, _block_keys(scan.transformed_vertices(poses[scan.name]), block,
                                            truncation * voxel))
    return _bricks_of_blocks(keys, edge)


def _bricks_of_blocks(keys: np.ndarray, edge: int) -> dict[tuple[int, int, int], int]:
    """{brick coordinates: blocks} of bricks of ``edge`` blocks a side, their one-block halo
    included, given the blocks' keys (:func:`_block_keys`)."""
    coords = _key_coords(keys).astype(np.int64)
    # a block is in the halo of the bricks of its neighbours one block away
    pairs = []
    for d in np.stack(np.meshgrid(*([np.array([-1, 0, 1])] * 3), indexing="ij"), -1).reshape(-1, 3):
        brick = np.floor_divide(coords + d, edge) + 2**20
        pairs.append((brick[:, 0] << 42) | (brick[:, 1] << 21) | brick[:, 2])
    pair_keys = np.concatenate(pairs)
    block_ids = np.tile(np.arange(len(coords)), 27)
    order = np.unique(np.stack([pair_keys, block_ids], 1), axis=0)
    bricks, counts = np.unique(order[:, 0], return_counts=True)
    brick_coords = _key_coords(bricks).astype(np.int64)
    return {tuple(b): int(c) for b, c in zip(brick_coords.tolist(), counts)}


def _bricks_over(first: np.ndarray, last: np.ndarray) -> set[tuple[int, int, int]]:
    """Bricks ``first <= b <= last`` of any row of (k, 3) brick coordinates (floats)."""
    rows = np.concatenate([first, last], axis=1).astype(np.int64)
    if len(rows) == 0:
        return set()
    lo = rows.min(axis=0)
    span = rows.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) < 2.0**62:  # rows as one int64 each: 30x faster than axis=0
        _, first_of = np.unique(np.ravel_multi_index(tuple((rows - lo).T), tuple(span)), return_index=True)
        ranges = rows[first_of]
    else:
        ranges = np.unique(rows, axis=0)
    out: set[tuple[int, int, int]] = set()
    for row in ranges.tolist():
        out.update(itertools.product(*(range(row[a], row[a + 3] + 1) for a in range(3))))
    return out


def _fuse_brick(task: _BrickTask) -> _BrickResult:
    """Integrate the brick's scans into its core blocks and a one-block halo around them, and
    mesh it; keep the triangles of the marching cubes in the core (a task on a worker)."""
    config = task.config
    voxel = float(config.voxel_size)
    pixel = config.pixel_size or voxel
    limit = config.max_memory_gib * 2**30
    volume = TsdfVolume(voxel, truncation=config.truncation,
                        block_count=int(task.expected_blocks * 1.05) + 16)
    reach = (task.lo - 1, task.hi + 1)
    # the rays that can reach the brick's blocks: the block keys of a surface point span
    # the truncation distance around it, and a voxel samples the four pixels around it
    margin = config.truncation * voxel + 2 * pixel
    block = voxel * BLOCK_RESOLUTION
    window = (reach[0] * block - margin, reach[1] * block + margin)
    seconds = {"height_maps": 0.0, "integrate": 0.0, "extract": 0.0}
    from slscan.fuse_pieces import brick_height_maps

    for depth in brick_height_maps(task, pixel=pixel, weighting=config.weighting, window=window,
                                   seconds=seconds):
        t1 = time.perf_counter()
        volume.integrate(depth, chunk_blocks=config.chunk_blocks, block_range=reach)
        seconds["integrate"] += time.perf_counter() - t1
        del depth
        if grid_memory_bytes(volume.n_blocks) > limit:
            raise SlscanError(
                f"brick {task.index} grew to {_size(grid_memory_bytes(volume.n_blocks))}, the cap is "
                f"{_size(limit)}: lower --brick (now {config.brick_size:g} mm)"
            )
    t0 = time.perf_counter()
    mesh = volume.extract_mesh(min_weight=config.min_weight)
    n_blocks = volume.n_blocks
    del volume
    if mesh.n_faces:
        block_size = voxel * BLOCK_RESOLUTION
        # a triangle lies in its marching cube: its centroid names the cube's block, computed
        # from the same float32 vertices by both bricks beside a shared face
        block = np.floor(mesh.vertices[mesh.faces].mean(axis=1) / block_size + 1e-9).astype(np.int64)
        keep = np.all((block >= task.lo) & (block < task.hi), axis=1)
        used, faces = np.unique(mesh.faces[keep], return_inverse=True)
        mesh = Mesh(mesh.vertices[used], faces.reshape(-1, 3),
                    None if mesh.normals is None else mesh.normals[used])
    seconds["extract"] = time.perf_counter() - t0
    if task.scratch is not None:  # streamed: the piece goes to disk, only its path comes back
        from slscan.fuse_stream import write_piece

        piece = write_piece(task.scratch, task.index, canonical_order(mesh))
        return _BrickResult(task.index, None, n_blocks, len(task.pieces) or len(task.scans), seconds, piece, mesh.n_faces)
    return _BrickResult(task.index, mesh, n_blocks, len(task.pieces) or len(task.scans), seconds)


def _stitch(meshes: Sequence[Mesh], *, plane_spacing: float, voxel: float) -> Mesh:
    """Join brick meshes: vertices on the brick planes (coordinates on multiples of
    ``plane_spacing`` mm) equal as float32 are merged; the others are left as they are."""
    vertices, faces, normals = [], [], []
    offset = 0
    for mesh in meshes:
        vertices.append(mesh.vertices)
        faces.append(mesh.faces + offset)
        normals.append(mesh.normals if mesh.normals is not None
                       else np.zeros((mesh.n_vertices, 3), np.float32))
        offset += mesh.n_vertices
    if not vertices:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.float32))
    v, f, nrm = np.concatenate(vertices), np.concatenate(faces), np.concatenate(normals)
    from slscan.fuse_stream import on_planes  # the streamed output's test too

    candidates = np.flatnonzero(on_planes(v, plane_spacing=plane_spacing, voxel=voxel))
    if len(candidates):
        rows = np.ascontiguousarray(v[candidates].astype(np.float32)).view(np.dtype((np.void, 12))).ravel()
        _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
        target = np.arange(len(v))
        target[candidates] = candidates[first[inverse.ravel()]]
        f = target[f]
        used, f = np.unique(f, return_inverse=True)
        v, nrm, f = v[used], nrm[used], f.reshape(-1, 3)
    return Mesh(v, f, nrm)


def parse_memory(text: str) -> float:
    """GiB in a memory size such as "4GiB", "512MiB" or "4" (GiB), for ``FuseConfig.max_memory_gib``:
    :func:`slscan.units.parse_memory` (Dask's units: "4GB" is 4e9 bytes), in GiB."""
    from slscan.units import GIB
    from slscan.units import parse_memory as parse_bytes

    return parse_bytes(text) / GIB


def fuse_bricks(
    scans: Iterable[RangeScan],
    poses: Mapping[str, np.ndarray],
    *,
    config: FuseConfig,
    executor: Executor | None = None,
    progress: Callable[[str], None] | None = None,
    progress_total: Callable[[int], None] | None = None,
    out: str | os.PathLike | None = None,
    _scratch: Path | None = None,
    scratch_beside: str | os.PathLike | None = None,
) -> FusionResult:
    """:func:`fuse_scans` in spatial bricks, each a task on ``executor``, under a memory cap.

    The volume is cut into cubes of ``config.brick_size`` mm rounded to whole 8-voxel
    blocks, so brick faces lie on voxel planes. A brick integrates, in the order of
    ``scans``, the scans whose bounds (grown by the truncation distance) reach it, into
    its own blocks and a one-block halo around them (the marching cubes on its upper faces
    need the next voxels; the normals, the gradient on both sides); every voxel gets the
    same float32 updates, in the same order, as in one volume. Each brick keeps the
    triangles of the marching cubes in its core; the caller stitches them, merging the
    vertices on brick faces (the same float32 positions, computed from the same voxels by
    both bricks). The result is the single-volume mesh, in :func:`canonical_order`.

    Range maps reach the bricks in pieces (:mod:`slscan.fuse_pieces`): the caller goes
    through ``scans`` once, one scan in memory at a time, and writes, for every brick a scan
    reaches, the triangles whose rays can reach the brick, to a scratch folder (beside
    ``scratch_beside`` when given, else in the system's temporary folder; workers of a Dask
    cluster must see it at the same path); a task carries its pieces' paths. The folder is
    removed when fusion ends, on success or error.

    Memory: before any brick runs, each brick's blocks (halo included) are estimated from
    the scans' vertices; a brick whose grid (:func:`grid_memory_bytes`) would exceed
    ``config.max_memory_gib`` is refused, naming it. A worker process holds one brick's
    grid, the height map of one piece (its window only) and the brick's mesh at a time; the
    caller one scan, the bricks' bookkeeping and the stitched mesh.

    Parameters
    ----------
    scans : RangeScan, each in its own frame (mm); any iterable, consumed once, lazily (e.g.
        :func:`slscan.register.meshlab.iter_scan_project`)
    poses : {name: (4, 4) world_from_scan}, mm; looked up as each scan comes (a mapping
        filled by the scans' iterator will do)
    config : FuseConfig with ``brick_size`` (mm) set
    executor : :class:`slscan.executor.Executor` (local processes or a Dask cluster); None:
        in this process
    progress : called with the brick's name, e.g. "brick (2, 0, 1)", as each is done
    progress_total : called with the number of bricks before the first runs
    out : None: the mesh is returned (``FusionResult.mesh``). A path: the mesh is streamed to
        this binary PLY (:mod:`slscan.fuse_stream`) and never held whole: each brick writes its
        piece to a scratch folder beside ``out`` (Dask workers must see it at the same path),
        the caller merges the vertices on brick planes and writes piece after piece
        (``FusionResult.written``; ``mesh`` is None). The same mesh up to the order of its
        vertices and faces (bricks in sorted order, each in canonical order), the same bytes
        from run to run; written atomically, the scratch folder removed after success and
        failure.
    _scratch : internal: the scratch folder made for ``out`` (by the call that made it)
    scratch_beside : without ``out``, a file (the output): the range maps' pieces go to a
        folder ``NAME.bricks-scratch-*`` beside it (with ``out``: in its scratch folder)

    Raises
    ------
    SlscanError
        A scan without a pose, bad options, a brick that cannot fit under the cap, or a
        piece a worker cannot read (naming the brick, the file and the worker's host).
    """
    if out is not None and _scratch is None:
        from slscan.fuse_stream import make_scratch, remove_scratch

        scratch = make_scratch(out)
        try:
            return fuse_bricks(scans, poses, config=config, executor=executor, progress=progress,
                               progress_total=progress_total, out=out, _scratch=scratch)
        finally:
            remove_scratch(scratch)
    if config.weighting not in ("quality", "uniform"):
        raise SlscanError(f"weighting {config.weighting!r}: expected 'quality' or 'uniform'")
    voxel = float(config.voxel_size)
    if not (math.isfinite(voxel) and voxel > 0):
        raise SlscanError(f"voxel size must be a positive number of mm, got {voxel}")
    brick = config.brick_size
    if brick is None or not (math.isfinite(brick) and brick > 0):
        raise SlscanError(f"brick size must be a positive number of mm, got {brick}")
    if isinstance(scans, Sequence):
        missing = [s.name for s in scans if s.name not in poses]
        if missing:
            raise SlscanError(f"no pose for scans {missing}")
    block = voxel * BLOCK_RESOLUTION
    edge = max(1, round(brick / block))
    from slscan.fuse_pieces import cut_pieces

    if _scratch is not None:  # streamed: the pieces go into the output's scratch folder too
        scratch = Path(_scratch) / "pieces"
        scratch.mkdir()
    else:
        if scratch_beside:
            Path(scratch_beside).parent.mkdir(parents=True, exist_ok=True)
        scratch = Path(tempfile.mkdtemp(prefix=f"{Path(scratch_beside).name}.bricks-scratch-" if scratch_beside
                                        else "slscan-bricks-scratch-",
                                        dir=Path(scratch_beside).parent if scratch_beside else None))
    try:
        # one pass over the scans (one in memory at a time): each scan's blocks, the bricks it
        # reaches and its piece for each of them
        t0 = time.perf_counter()
        keys, core, pieces = cut_pieces(scans, poses, voxel=voxel, pixel=config.pixel_size or voxel,
                                        truncation=config.truncation, weighting=config.weighting, edge=edge,
                                        folder=scratch)
        cut_seconds = time.perf_counter() - t0
        needs = _bricks_of_blocks(keys, edge)
        del keys
        limit = config.max_memory_gib * 2**30
        for b, n in sorted(needs.items()):
            if grid_memory_bytes(n) > limit:
                raise SlscanError(
                    f"brick {b} needs {_size(grid_memory_bytes(n))}, the cap is "
                    f"{_size(limit)}: lower --brick (now {brick:g} mm)"
                )
        tasks = []
        for b in sorted(core):
            lo, hi = np.array(b, np.int64) * edge, (np.array(b, np.int64) + 1) * edge
            tasks.append(_BrickTask(b, lo, hi, (), {}, config, needs.get(b, 0),
                                    None if _scratch is None else str(_scratch),
                                    tuple(str(p) for p in pieces.get(b, ()))))
        result = _run_bricks(tasks, edge=edge, block=block, voxel=voxel, config=config, executor=executor,
                             progress=progress, progress_total=progress_total, out=out, scratch=_scratch)
        result.seconds["pieces"] = cut_seconds
        return result
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _run_bricks(tasks: list[_BrickTask], *, edge: int, block: float, voxel: float, config: FuseConfig,
                executor: Executor | None, progress: Callable[[str], None] | None,
                progress_total: Callable[[int], None] | None, out: str | os.PathLike | None = None,
                scratch: Path | None = None) -> FusionResult:
    """Run the brick tasks on ``executor`` and stitch their meshes, or, with ``out`` and
    ``scratch``, stream them to ``out`` (:func:`fuse_bricks`)."""
    log.info("fusing in %d bricks of %d blocks (%.3g mm) a side", len(tasks), edge, edge * block)
    if progress_total is not None:
        progress_total(len(tasks))
    # a local helper process that dies: its bricks are run once more
    done = map_retrying(executor, _fuse_brick, tasks, key=lambda t: t.index, noun="brick",
                        done=None if progress is None else (lambda r: progress(f"brick {r.index}")))
    results = [done[t.index] for t in tasks]
    seconds = {k: sum(r.seconds[k] for r in results) for k in ("height_maps", "integrate", "extract")}
    t0 = time.perf_counter()
    written = None
    if scratch is not None:
        from slscan.fuse_stream import write_streamed

        mesh = None
        written = write_streamed([(r.index, r.piece, r.n_faces) for r in results], out, scratch,
                                 plane_spacing=edge * block, voxel=voxel)
    else:
        mesh = canonical_order(_stitch([r.mesh for r in results], plane_spacing=edge * block, voxel=voxel))
    seconds["stitch"] = time.perf_counter() - t0
    n_blocks = sum(r.n_blocks for r in results)
    return FusionResult(mesh, n_blocks, grid_memory_bytes(n_blocks), sum(r.n_scans for r in results),
                        seconds, n_bricks=len(results), written=written)


# --- screened Poisson (pymeshlab) -----------------------------------------------------------------


def poisson_reconstruct(
    scans: Iterable[RangeScan],
    poses: Mapping[str, np.ndarray],
    *,
    voxel_size: float = 0.5,
    depth: int | None = None,
    samples_per_node: float = 1.5,
    point_weight: float = 4.0,
    use_quality: bool = True,
    trim_quantile: float = 0.02,
) -> Mesh:
    """Screened Poisson reconstruction [2]_ of the scans' oriented samples (pymeshlab).

    The alternative to :func:`fuse_scans`: watertight, smoother, fills holes (and may
    invent surface where there was none; the vertices of lowest sample density, the
    ``trim_quantile`` fraction, are removed to cut most of it away).

    Parameters
    ----------
    scans, poses : as for :func:`fuse_scans` (all samples are held in memory at once)
    voxel_size : mm, the finest octree cell wanted; sets ``depth`` when it is None
    depth : octree depth (each level halves the cell); None: from ``voxel_size`` and
        the samples' extent
    samples_per_node, point_weight : pymeshlab's ``samplespernode``, ``pointweight``
    use_quality : use the scans' per-vertex quality as Poisson confidence
    trim_quantile : fraction of vertices (lowest density) to remove, 0 for none
    """
    import pymeshlab

    points, normals, quality = [], [], []
    for scan in scans:
        if scan.name not in poses:
            raise SlscanError(f"no pose for scan {scan.name!r}")
        pose = np.asarray(poses[scan.name], np.float64)
        keep = scan.quality > 0
        points.append(scan.transformed_vertices(pose)[keep])
        normals.append(scan.normals[keep].astype(np.float64) @ pose[:3, :3].T)
        quality.append(scan.quality[keep].astype(np.float64))
    if not points or sum(len(p) for p in points) < 10:
        raise SlscanError("Poisson reconstruction needs scans with samples; got none")
    p = np.concatenate(points)
    extent = float(np.max(p.max(axis=0) - p.min(axis=0)))
    if depth is None:
        depth = int(np.clip(math.ceil(math.log2(extent * 1.1 / voxel_size)), 5, 14))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(
        pymeshlab.Mesh(
            vertex_matrix=p,
            v_normals_matrix=np.concatenate(normals),
            v_scalar_array=np.concatenate(quality),
        ),
        "samples",
    )
    del points, normals, quality, p
    ms.generate_surface_reconstruction_screened_poisson(
        depth=int(depth),
        samplespernode=float(samples_per_node),
        pointweight=float(point_weight),
        confidence=bool(use_quality),
        preclean=True,
        threads=max(os.cpu_count() or 1, 1),
    )
    if trim_quantile > 0:
        density = ms.current_mesh().vertex_scalar_array()
        if len(density):
            threshold = float(np.quantile(density, trim_quantile))
            ms.compute_selection_by_condition_per_vertex(condselect=f"(q < {threshold!r})")
            ms.meshing_remove_selected_vertices()
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    vertices = m.vertex_matrix().astype(np.float64)
    faces = m.face_matrix().astype(np.int64)
    normals_out = m.vertex_normal_matrix().astype(np.float32)
    return Mesh(vertices, faces, normals_out)


# --- mesh files -----------------------------------------------------------------------------------


def write_mesh(mesh: Mesh, path: str | os.PathLike) -> Path:
    """Write ``mesh`` atomically as PLY (binary), OBJ or any format open3d writes, by suffix."""
    import open3d as o3d

    path = Path(path)
    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.ascontiguousarray(mesh.vertices, np.float64)),
        o3d.utility.Vector3iVector(np.ascontiguousarray(mesh.faces, np.int32)),
    )
    if mesh.normals is not None and len(mesh.normals) == mesh.n_vertices:
        m.vertex_normals = o3d.utility.Vector3dVector(
            np.ascontiguousarray(mesh.normals, np.float64)
        )
    if mesh.colors is not None and len(mesh.colors) == mesh.n_vertices:
        m.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.colors, np.float64) / 255.0)
    with atomic_output_file(path) as tmp:
        with _open3d_quiet():  # a failed write is reported below, in one line
            ok = o3d.io.write_triangle_mesh(
                str(tmp),
                m,
                write_ascii=False,
                compressed=False,
                write_vertex_normals=mesh.normals is not None,
                write_vertex_colors=mesh.colors is not None,
            )
        if not ok and path.suffix.lower() not in MESH_SUFFIXES:
            raise SlscanError(
                f"{path}: could not write the mesh (unsupported suffix {path.suffix!r}?)"
            )
        _check_written_mesh(tmp, path, mesh, ok)
    return path


def _check_written_mesh(tmp: Path, path: Path, mesh: Mesh, ok: bool) -> None:
    """Open3D reports success when its writes failed (a full disk): check the file it wrote
    before it is renamed into place (:func:`slscan.ply.check_written_ply`; other formats
    are read back and their triangles counted)."""
    import open3d as o3d

    from slscan.fsio import write_error
    from slscan.ply import check_written_ply

    if not ok:
        raise write_error(path, written=tmp.stat().st_size if tmp.exists() else 0)
    if path.suffix.lower() == ".ply":
        check_written_ply(tmp, path, vertices=mesh.n_vertices, faces=len(mesh.faces))
        return
    with _open3d_quiet():
        back = o3d.io.read_triangle_mesh(str(tmp))
    if len(back.triangles) != len(mesh.faces):
        raise write_error(path, written=tmp.stat().st_size)


@contextlib.contextmanager
def _open3d_quiet():
    """No Open3D warnings and no RPly lines (printed by C to fd 2) while a mesh file is read
    or written: slscan checks the result and says what went wrong in one line."""
    import open3d as o3d

    with native_stderr_silenced(), o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        yield


def read_mesh(path: str | os.PathLike) -> Mesh:
    """Read a triangle mesh: PLY with slscan's reader (:func:`slscan.meshes.read_ply_mesh`),
    other formats (OBJ, …) with Open3D; SlscanError when missing, malformed or empty.

    PLY files are not given to Open3D: its reader crashes (SIGSEGV) on some malformed
    bodies, and keeps faces that refer to vertices the file does not have."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: mesh file not found")
    if path.suffix.lower() == ".ply":
        ply = read_ply_mesh(path)
        if len(ply.faces) == 0:
            raise SlscanError(f"{path}: no triangles read; expected a triangle mesh")
        return Mesh(ply.vertices, ply.faces, ply.normals, ply.colors)
    with _open3d_quiet():  # a bad file is named below, in one line
        m = o3d.io.read_triangle_mesh(str(path))
    if len(m.triangles) == 0:
        raise SlscanError(f"{path}: no triangles read; expected a triangle mesh")
    check_finite_vertices(np.asarray(m.vertices), path)
    check_face_indices(np.asarray(m.triangles), len(m.vertices), path)
    normals = np.asarray(m.vertex_normals, np.float32) if m.has_vertex_normals() else None
    colors = (
        np.round(np.asarray(m.vertex_colors) * 255).astype(np.uint8)
        if m.has_vertex_colors()
        else None
    )
    return Mesh(
        np.asarray(m.vertices, np.float64), np.asarray(m.triangles, np.int64), normals, colors
    )
