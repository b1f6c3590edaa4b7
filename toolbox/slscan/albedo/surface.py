"""The range map seen from the camera: per-pixel surface point and normal, and shadow rays.

The range map (rig frame, mm) is ray cast from the camera centre through every pixel
centre with Open3D's ``RaycastingScene``, so the albedo image is registered with the
geometry by construction. Shadow rays from each surface point towards each light test
the same range-map mesh for occluders.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slscan.decode.rangemap import RangeMap
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, pixel_rays

SHADOW_OFFSET_MM = 1.0
"""Shadow rays start this far off the surface (along the normal and towards the light):
the range map's own noise and tessellation must not shadow it."""


@dataclass(frozen=True)
class SurfaceMap:
    """The range surface at each camera pixel, over (h, w) pixels.

    hit : (h, w) bool, a range-map triangle is seen
    points : (h, w, 3) float64 mm rig frame, NaN where not hit
    normals : (h, w, 3) float64 unit, interpolated vertex normals (towards the camera)
    face : (h, w) int64 triangle index, -1 where not hit
    """

    hit: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    face: np.ndarray


def _scene(range_map: RangeMap):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(range_map.vertices, np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(range_map.faces, np.uint32)),
    )
    return scene


def rasterise(range_map: RangeMap, camera: PinholeModel) -> SurfaceMap:
    """Ray cast ``range_map`` from the camera centre through every pixel centre.

    The hit point is recomputed in float64 on the hit triangle's plane; the normal is the
    barycentric interpolation of the range map's vertex normals, turned to face the camera.
    Only the pixels of :func:`pixel_window` are cast (no other can see the range map).
    """
    import open3d as o3d

    h, w = camera.height, camera.width
    surface = SurfaceMap(
        np.zeros((h, w), bool),
        np.full((h, w, 3), np.nan),
        np.full((h, w, 3), np.nan),
        np.full((h, w), -1, np.int64),
    )
    if len(range_map.faces) == 0:
        return surface
    if range_map.faces.max() >= len(range_map.vertices) or range_map.faces.min() < 0:
        raise SlscanError(
            f"range map {range_map.view!r}: a face refers to a vertex that does not exist"
        )
    rows, cols = pixel_window(range_map, camera)
    if rows.stop <= rows.start or cols.stop <= cols.start:
        return surface
    if (rows.stop - rows.start) * (cols.stop - cols.start) > WINDOW_SHARE * h * w:
        rays = pixel_rays(camera)[rows, cols].reshape(-1, 3)  # cached per camera
    else:
        grid = np.stack(
            np.meshgrid(
                np.arange(cols.start, cols.stop, dtype=float),
                np.arange(rows.start, rows.stop, dtype=float),
            ),
            axis=-1,
        )
        rays = camera.rays_local(grid).reshape(-1, 3)
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    scene = _scene(range_map)
    win = (rows.stop - rows.start, cols.stop - cols.start)
    cast = scene.cast_rays(
        o3d.core.Tensor(np.concatenate([np.zeros_like(rays), rays], 1).astype(np.float32))
    )
    prim = cast["primitive_ids"].numpy().astype(np.int64)
    uvs = cast["primitive_uvs"].numpy()
    hit = prim != scene.INVALID_ID
    # a range map with a vertex at every pixel centre (phase shifting) puts rays exactly
    # through vertices and along edges, where single-precision ray casting can miss: cast
    # the misses beside hits again through a point a hundredth of a pixel away
    for dx, dy in ((1.0, 0.7), (-0.7, 1.0), (-1.0, -0.7), (0.7, -1.0)):
        near = np.flatnonzero(_beside(hit.reshape(win)).reshape(-1) & ~hit)
        if not len(near):
            break
        step = JITTER * np.array([dx / camera.fx, dy / camera.fy, 0.0])
        again = rays[near] + step
        again /= np.linalg.norm(again, axis=1, keepdims=True)
        cast2 = scene.cast_rays(
            o3d.core.Tensor(np.concatenate([np.zeros_like(again), again], 1).astype(np.float32))
        )
        p2 = cast2["primitive_ids"].numpy().astype(np.int64)
        ok = p2 != scene.INVALID_ID
        prim[near[ok]] = p2[ok]
        uvs[near[ok]] = cast2["primitive_uvs"].numpy()[ok]
        hit[near[ok]] = True
    idx = np.flatnonzero(hit)
    prim = prim[idx]
    uv = uvs[idx].astype(np.float64)
    tri = range_map.faces[prim]
    v = range_map.vertices
    v0, v1, v2 = v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]
    face_n = np.cross(v1 - v0, v2 - v0)
    r = rays[idx]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("ij,ij->i", face_n, v0) / np.einsum("ij,ij->i", face_n, r)
    t = np.where(np.isfinite(t) & (t > 0), t, cast["t_hit"].numpy()[idx])
    wts = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    n = np.einsum("kc,kcj->kj", wts, range_map.normals[tri].astype(np.float64))
    length = np.linalg.norm(n, axis=1, keepdims=True)
    face_unit = face_n / np.maximum(np.linalg.norm(face_n, axis=1, keepdims=True), 1e-300)
    n = np.where(length > 1e-6, n / np.maximum(length, 1e-300), face_unit)
    n[np.einsum("ij,ij->i", n, r) > 0] *= -1
    surface.hit[rows, cols] = hit.reshape(win)
    surface.points[rows, cols] = _scatter(idx, r * t[:, None], win, np.nan)
    surface.normals[rows, cols] = _scatter(idx, n, win, np.nan)
    surface.face[rows, cols] = _scatter(idx, prim, win, -1)
    return surface


JITTER = 0.01
"""Pixels: how far from its centre a missed pixel's ray is cast again (:func:`rasterise`)."""


def _beside(hit: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels with a hit among their four neighbours."""
    out = np.zeros_like(hit)
    out[1:] |= hit[:-1]
    out[:-1] |= hit[1:]
    out[:, 1:] |= hit[:, :-1]
    out[:, :-1] |= hit[:, 1:]
    return out


def _scatter(idx: np.ndarray, values: np.ndarray, shape: tuple[int, int], fill) -> np.ndarray:
    """``values`` at the flat indices ``idx`` of a (shape + values' trailing shape) array."""
    out = np.full((shape[0] * shape[1],) + values.shape[1:], fill, values.dtype)
    out[idx] = values
    return out.reshape(shape + values.shape[1:])


WINDOW_SHARE = 0.5
"""A window larger than this share of the frame takes its rays from the per-camera cache."""
WINDOW_MARGIN_PX = 2
"""Margin of :func:`pixel_window` around the vertices' projections: a triangle's edges
are straight in the ideal image and bent by the lens distortion between their ends."""


def pixel_window(range_map: RangeMap, camera: PinholeModel) -> tuple[slice, slice]:
    """(rows, cols) of the camera's pixels that can see ``range_map``: its vertices'
    projections with a margin (:data:`WINDOW_MARGIN_PX`), within the frame; the whole frame
    if a vertex is not in front of the camera."""
    h, w = camera.height, camera.width
    v = np.asarray(range_map.vertices, float)
    if len(v) == 0:
        return slice(0, 0), slice(0, 0)
    pix = camera.project_local(v)
    if not (np.all(v[:, 2] > 0) and np.all(np.isfinite(pix))):
        return slice(0, h), slice(0, w)
    lo = np.floor(pix.min(0)).astype(int) - WINDOW_MARGIN_PX
    hi = np.ceil(pix.max(0)).astype(int) + WINDOW_MARGIN_PX + 1
    return (
        slice(int(np.clip(lo[1], 0, h)), int(np.clip(hi[1], 0, h))),
        slice(int(np.clip(lo[0], 0, w)), int(np.clip(hi[0], 0, w))),
    )


def occluded(
    range_map: RangeMap,
    points: np.ndarray,
    normals: np.ndarray,
    light_positions: np.ndarray,
    *,
    offset: float = SHADOW_OFFSET_MM,
) -> np.ndarray:
    """Cast shadows: True where the range map blocks the segment from a point to a light.

    points, normals : (n, 3) mm and unit, rig frame
    light_positions : (k, 3) mm
    Returns (k, n) bool. Rays start ``offset`` mm off the surface along the normal and
    ``offset`` mm along the ray, and stop ``offset`` mm short of the light.
    """
    import open3d as o3d

    k = len(light_positions)
    out = np.zeros((k, len(points)), bool)
    if len(points) == 0 or len(range_map.faces) == 0:
        return out
    scene = _scene(range_map)
    origin0 = points + offset * normals
    for i, position in enumerate(np.asarray(light_positions, float)):
        d = position - origin0
        dist = np.linalg.norm(d, axis=1)
        u = d / np.maximum(dist, 1e-9)[:, None]
        origin = origin0 + offset * u
        rays = np.concatenate([origin, u], axis=1).astype(np.float32)
        t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        out[i] = t_hit < dist - 2 * offset
    return out
