"""Range maps cut into per-brick pieces for :func:`slscan.fuse.fuse_bricks`: a brick task carries
paths to small files, never whole range maps.

The caller of ``fuse_bricks`` goes through the scans one at a time. Each scan is ray cast
once into its whole orthographic height map (:func:`slscan.fuse.height_map`, exactly as the
single volume casts it) and, for every brick the scan reaches, the window of pixels whose
rays can reach the brick's blocks (its core, one-block halo, the truncation distance and
two pixels) is written to a scratch folder: one uncompressed ``.npz`` per (brick, scan),
to a temporary name then renamed. A brick task carries the paths of its pieces, in the
caller's scan order; the brick reads each as a :class:`slscan.fuse.HeightMap` of its
window only (``offset``: its place on the whole grid), which updates every voxel bit for
bit as the whole map does, so the bricks give the single-volume mesh exactly.

Why windows of the cast map and not the triangles under them: Embree (open3d's
``RaycastingScene``) does not give the same hits for a subset of a mesh's triangles as for
the whole mesh (measured on the sphere of ``tests/fuse/test_bricks.py``: heights 1 ulp
apart, 2 more rays hit out of 1,468), and two bricks beside one face then disagree on its
voxels: 354 of 11,766 vertices were left unwelded. Casting each scan once is also cheaper
than one ray-casting structure per (brick, scan).
"""

from __future__ import annotations

import math
import os
import socket
import time
import zipfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from slscan.errors import SlscanError

if TYPE_CHECKING:
    from slscan.fuse import HeightMap, _BrickTask
    from slscan.register.rangescan import RangeScan

PIECE_FORMAT = 1
"""Version of the piece files (a scratch folder is only ever read by the run that wrote it)."""


@dataclass(frozen=True)
class ScanGrid:
    """The pixel grid of a scan's whole height map (:func:`slscan.fuse.height_map`).

    frame : (3, 3) rows u, v, d (d towards the sensor), world
    origin_local : (3,) the grid's pixel (0, 0) at height 0, in the frame's coordinates, mm
    pixel : mm
    rows, cols : the whole map's size, pixels
    top : height (mm, above ``origin_local``) the rays start from
    """

    frame: np.ndarray
    origin_local: np.ndarray
    pixel: float
    rows: int
    cols: int
    top: float


def scan_grid(local: np.ndarray, frame: np.ndarray, pixel: float) -> ScanGrid:
    """The whole height map's grid of a scan whose world vertices are ``local`` (n, 3) in
    ``frame`` coordinates (``world @ frame.T``), mm; the same numbers as ``height_map``."""
    lo, hi = local.min(axis=0), local.max(axis=0)
    origin_local = np.array([lo[0] - pixel, lo[1] - pixel, 0.0])
    cols = math.ceil((hi[0] - lo[0]) / pixel) + 3
    rows = math.ceil((hi[1] - lo[1]) / pixel) + 3
    top = float(hi[2] - origin_local[2]) + 10 * pixel
    return ScanGrid(frame, origin_local, float(pixel), rows, cols, top)


def pixel_window(grid: ScanGrid, window: tuple[np.ndarray, np.ndarray]) -> tuple[int, int, int, int]:
    """(r_lo, r_hi, c_lo, c_hi): the pixels of ``grid`` whose rays pass through the world box
    ``window`` (lo, hi) (3,) mm, and two around them (as ``height_map`` casts them)."""
    corners = np.stack(np.meshgrid(*zip(window[0], window[1]), indexing="ij"), -1).reshape(-1, 3)
    px = ((corners @ grid.frame.T)[:, :2] - grid.origin_local[:2]) / grid.pixel
    c_lo, c_hi = max(0, math.floor(px[:, 0].min()) - 2), min(grid.cols, math.ceil(px[:, 0].max()) + 3)
    r_lo, r_hi = max(0, math.floor(px[:, 1].min()) - 2), min(grid.rows, math.ceil(px[:, 1].max()) + 3)
    if c_lo >= c_hi or r_lo >= r_hi:
        return r_lo, r_lo, c_lo, c_lo
    return r_lo, r_hi, c_lo, c_hi


def brick_window(lo: np.ndarray, hi: np.ndarray, *, voxel: float, pixel: float, truncation: float,
                 block_resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """The world box (mm) whose rays can reach the blocks ``lo - 1 <= coords < hi + 1`` of a
    brick (its core and halo): grown by the truncation distance (a surface point's blocks
    span it) and two pixels (a voxel samples the four pixels around it)."""
    margin = truncation * voxel + 2 * pixel
    block = voxel * block_resolution
    return (np.asarray(lo) - 1) * block - margin, (np.asarray(hi) + 1) * block + margin


def write_scan_pieces(
    scan: RangeScan, pose: np.ndarray, bricks: list[tuple[tuple[int, int, int], tuple[np.ndarray, np.ndarray]]],
    folder: Path, *, pixel: float, weighting: str, order: int,
) -> dict[tuple[int, int, int], Path]:
    """Cast ``scan`` (a RangeScan placed by ``pose``, world_from_scan) into its whole height
    map (:func:`slscan.fuse.height_map`, once) and write the window of each of ``bricks``
    [(brick index, world window (lo, hi) (3,) mm)] that sees some surface to ``folder`` as
    ``b{i}_{j}_{k}-s{order}.npz``: {brick index: path}.

    A piece holds the map's frame, origin and pixel, its window's place on the whole grid
    (``offset`` (row, col)) and the window's height and weight ((h, w) float32): read back,
    a :class:`slscan.fuse.HeightMap` that updates every voxel bit for bit as the whole map.
    """
    from slscan.fuse import _basis, height_map

    pose = np.asarray(pose, np.float64)
    depth = height_map(scan, pose, pixel=pixel, weighting=weighting)
    local = scan.transformed_vertices(pose) @ _basis(pose[:3, :3] @ scan.view_direction).T
    grid = scan_grid(local, depth.frame, pixel)
    del local
    out = {}
    for index, window in bricks:
        r_lo, r_hi, c_lo, c_hi = pixel_window(grid, window)
        seen = np.isfinite(depth.height[r_lo:r_hi, c_lo:c_hi])
        rows, cols = np.flatnonzero(seen.any(axis=1)), np.flatnonzero(seen.any(axis=0))
        if not len(rows):
            continue
        # only the pixels that see the surface, and one around them (a map's border pixels
        # count as empty, and those outside it are): the same samples for every voxel
        r_lo, r_hi = r_lo + max(rows[0] - 1, 0), min(r_lo + rows[-1] + 2, r_hi)
        c_lo, c_hi = c_lo + max(cols[0] - 1, 0), min(c_lo + cols[-1] + 2, c_hi)
        path = folder / f"b{index[0]}_{index[1]}_{index[2]}-s{order}.npz"
        _save(path, format=np.int64(PIECE_FORMAT), name=np.str_(scan.name), frame=depth.frame,
              origin=depth.origin, pixel=np.float64(depth.pixel), offset=np.array([r_lo, c_lo], np.int64),
              height=depth.height[r_lo:r_hi, c_lo:c_hi], weight=depth.weight[r_lo:r_hi, c_lo:c_hi])
        out[index] = path
    return out


def _save(path: Path, **arrays) -> None:
    """``np.savez`` to a temporary name beside ``path``, then renamed (a piece is whole or absent)."""
    from slscan.fsio import WRITE_ERRNOS, write_error

    tmp = path.with_name(f".{path.name}.partial-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno in WRITE_ERRNOS:
            raise write_error(path, exc) from None
        raise SlscanError(f"{path}: cannot write a fusion piece here ({exc.strerror})") from None


def read_piece(path: str | os.PathLike, brick: tuple[int, int, int]) -> HeightMap:
    """The :class:`slscan.fuse.HeightMap` window of a piece written by :func:`write_scan_pieces`
    for ``brick`` (a brick task on a worker); a missing or broken file is one line naming
    it, the brick and the worker's host."""
    from slscan.fuse import HeightMap

    path = Path(path)
    hint = "Dask workers need the fusion scratch folder at the same path"
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format"]) != PIECE_FORMAT:
                raise ValueError(f"piece format {int(z['format'])}, expected {PIECE_FORMAT}")
            height, weight = z["height"], z["weight"]
            if height.dtype != np.float32 or height.ndim != 2 or weight.shape != height.shape:
                raise ValueError(f"height {height.dtype} {height.shape}, weight {weight.shape}")
            r_off, c_off = (int(x) for x in z["offset"])
            return HeightMap(frame=z["frame"], origin=z["origin"], pixel=float(z["pixel"]), height=height,
                             weight=weight.astype(np.float32), offset=(r_off, c_off))
    except FileNotFoundError:
        raise SlscanError(f"brick {brick}: {path}: not found on worker {socket.gethostname()}; {hint}") from None
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise SlscanError(f"brick {brick}: {path}: not a readable fusion piece on worker "
                          f"{socket.gethostname()} ({exc}); {hint}") from None


def brick_height_maps(task: _BrickTask, *, pixel: float, weighting: str, window: tuple[np.ndarray, np.ndarray],
                      seconds: dict[str, float]) -> Iterator[HeightMap]:
    """The height maps a brick task integrates, in the caller's scan order: from its piece
    files when it has them, else ray cast from the task's whole scans (windowed); the time
    spent making each is added to ``seconds["height_maps"]``."""
    from slscan.fuse import height_map

    if task.pieces:
        for path in task.pieces:
            t0 = time.perf_counter()
            depth = read_piece(path, task.index)
            seconds["height_maps"] += time.perf_counter() - t0
            yield depth
        return
    for scan in task.scans:
        t0 = time.perf_counter()
        depth = height_map(scan, task.poses[scan.name], pixel=pixel, weighting=weighting, window=window)
        seconds["height_maps"] += time.perf_counter() - t0
        yield depth


def cut_pieces(
    scans: Iterable[RangeScan], poses: Mapping[str, np.ndarray], *, voxel: float, pixel: float, truncation: float, weighting: str, edge: int, folder: Path,
) -> tuple[np.ndarray, set[tuple[int, int, int]], dict[tuple[int, int, int], list[Path]]]:
    """One pass over ``scans`` (any iterable of RangeScan, consumed lazily; ``poses`` looked up
    as each comes) for :func:`slscan.fuse.fuse_bricks` with bricks of ``edge`` blocks a side.

    Returns the keys of the blocks the scans' vertices need (:func:`slscan.fuse._block_keys`,
    int64, sorted), the bricks whose core some scan's triangles reach (grown by the
    truncation distance), and {brick: [piece path, in scan order]} for the bricks each
    scan reaches with its halo (see :func:`write_scan_pieces`).
    """
    from slscan.fuse import BLOCK_RESOLUTION, _block_keys, _bricks_over

    block = voxel * BLOCK_RESOLUTION
    span = edge * block
    reach = truncation * voxel
    keys = np.zeros(0, np.int64)
    core: set[tuple[int, int, int]] = set()
    pieces: dict[tuple[int, int, int], list[Path]] = {}
    names: set[str] = set()
    order = -1
    for scan in scans:  # not enumerate(): its reused result tuple holds the last scan during the next read
        order += 1
        if scan.name not in poses:
            raise SlscanError(f"no pose for scan {scan.name!r}")
        if scan.name in names:
            raise SlscanError(f"two scans are named {scan.name!r}")
        names.add(scan.name)
        pose = np.asarray(poses[scan.name], np.float64)
        world = scan.transformed_vertices(pose)
        keys = np.union1d(keys, _block_keys(world, block, reach))
        # the bricks from the scan's triangles, not its vertices: a long triangle's ray hits
        # can reach blocks that none of its vertices does
        tri = world[scan.faces]
        del world
        lo_mm, hi_mm = tri.min(axis=1) - reach, tri.max(axis=1) + reach
        del tri
        core |= _bricks_over(np.floor(lo_mm / span), np.floor(hi_mm / span))
        reached = _bricks_over(np.floor((lo_mm - block) / span), np.floor((hi_mm + block) / span))
        del lo_mm, hi_mm
        windows = []
        for b in sorted(reached):
            lo, hi = np.array(b, np.int64) * edge, (np.array(b, np.int64) + 1) * edge
            windows.append((b, brick_window(lo, hi, voxel=voxel, pixel=pixel, truncation=truncation,
                                            block_resolution=BLOCK_RESOLUTION)))
        for b, path in write_scan_pieces(scan, pose, windows, folder, pixel=pixel, weighting=weighting,
                                         order=order).items():
            pieces.setdefault(b, []).append(path)
        del scan
    if not names:
        raise SlscanError("no scans to fuse")
    return keys, core, pieces
