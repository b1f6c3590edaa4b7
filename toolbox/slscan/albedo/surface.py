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
    """
    import open3d as o3d

    h, w = camera.height, camera.width
    empty = SurfaceMap(
        np.zeros((h, w), bool),
        np.full((h, w, 3), np.nan),
        np.full((h, w, 3), np.nan),
        np.full((h, w), -1, np.int64),
    )
    if len(range_map.faces) == 0:
        return empty
    if range_map.faces.max() >= len(range_map.vertices) or range_map.faces.min() < 0:
        raise SlscanError(
            f"range map {range_map.view!r}: a face refers to a vertex that does not exist"
        )
    rays = pixel_rays(camera).reshape(-1, 3)
    scene = _scene(range_map)
    cast = scene.cast_rays(
        o3d.core.Tensor(np.concatenate([np.zeros_like(rays), rays], 1).astype(np.float32))
    )
    prim = cast["primitive_ids"].numpy().astype(np.int64)
    hit = prim != scene.INVALID_ID
    idx = np.flatnonzero(hit)
    prim = prim[idx]
    uv = cast["primitive_uvs"].numpy()[idx].astype(np.float64)
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
    points = np.full((h * w, 3), np.nan)
    normals = np.full((h * w, 3), np.nan)
    face = np.full(h * w, -1, np.int64)
    points[idx] = r * t[:, None]
    normals[idx] = n
    face[idx] = prim
    return SurfaceMap(
        hit.reshape(h, w), points.reshape(h, w, 3), normals.reshape(h, w, 3), face.reshape(h, w)
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
