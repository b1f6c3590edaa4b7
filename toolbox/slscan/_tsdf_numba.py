"""The weighted-TSDF voxel update of :meth:`slscan.fuse.TsdfVolume.integrate`, compiled
with numba (the ``fast`` extra).

Imported only by fusion, on its first integration, and only when numba is installed;
otherwise fusion runs the same update in numpy. Both do the same float32 operations in
the same order (no fused multiply-add: numba's default, without ``fastmath``), so they
give the same tsdf and weights bit for bit; ``tests/fuse/test_fuse.py`` checks it.

Why numba: the update is a gather from a height map and a few float operations per
voxel; in numpy every step is a pass over a chunk's voxels through memory (with the
temporaries it needs), about 4× a loop that keeps a voxel in registers. numba compiles
that loop from Python without a C toolchain at install time, and is a well-kept wheel
for every platform numpy supports.

The compiled code is cached on disk (numba's ``cache=True``: next to this file, or in the
user's cache folder when the install is read-only); with no writable cache location at
all it is compiled in memory, once per process.
"""

from __future__ import annotations

import numba
import numpy as np


def jit(function):
    """``function`` compiled by numba, cached on disk where numba finds a writable place,
    otherwise compiled in memory (numba refuses ``cache=True`` without one)."""
    try:
        return numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return numba.njit(nogil=True)(function)


def _update(tsdf, weight, rows, base, lattice, height, weight_px, cols, x_max, y_max,
            neg_trunc, inv_trunc, c_off, r_off):  # pragma: no cover - runs compiled
    """Update blocks ``rows`` of ``tsdf``/``weight`` (n, 512) float32 with one height map.

    base : (k, 3) float32 each block's first voxel in map coordinates (x, y in pixels,
        z in mm along the view direction); lattice : (3, 512) float32 the voxels'
        offsets from it; height, weight_px : the map's flat bordered pixels
        (:meth:`slscan.fuse.HeightMap.bordered`), ``cols`` per row; x_max, y_max : the
        largest top-left pixel of a bilinear cell; neg_trunc, inv_trunc : float32
        -truncation (mm) and 1 / truncation; c_off, r_off : int32 the grid pixel of the
        map's first (a window of a larger grid; x, y and x_max, y_max are on that grid).

    Mirrors the numpy update in :meth:`slscan.fuse.TsdfVolume.integrate` step by step.
    """
    one = np.float32(1.0)
    zero = np.float32(0.0)
    x_min = np.float32(c_off)
    y_min = np.float32(r_off)
    n_voxels = lattice.shape[1]
    for k in range(len(rows)):
        row = rows[k]
        bx = base[k, 0]
        by = base[k, 1]
        bz = base[k, 2]
        for v in range(n_voxels):
            x = min(max(bx + lattice[0, v], x_min), x_max)
            y = min(max(by + lattice[1, v], y_min), y_max)
            c0 = np.int32(x)
            r0 = np.int32(y)
            fx = np.float32(x - c0)
            fy = np.float32(y - r0)
            i = np.int64(r0 - r_off) * cols + (c0 - c_off)
            left = height[i]
            top = (height[i + 1] - left) * fx + left
            left = height[i + cols]
            bottom = (height[i + cols + 1] - left) * fx + left
            h = top + (bottom - top) * fy
            sdf = (bz + lattice[2, v]) - h
            if not sdf >= neg_trunc:  # also NaN: a pixel without surface
                continue
            left = weight_px[i]
            top = (weight_px[i + 1] - left) * fx + left
            left = weight_px[i + cols]
            bottom = (weight_px[i + cols + 1] - left) * fx + left
            w = top + (bottom - top) * fy
            if not w > zero:
                continue
            sdf = min(sdf * inv_trunc, one)
            w_old = weight[row, v]
            total = w_old + w
            tsdf[row, v] = (tsdf[row, v] * w_old + sdf * w) / total
            weight[row, v] = total


update = jit(_update)
