"""Comparing two surfaces, and two textured surfaces' colours, for regression checks.

Distances are point-to-surface: points sampled uniformly by area on one mesh, the distance
to the closest point of the other (open3d's ``RaycastingScene``), both ways. Colours are
compared at corresponding surface points, each read through its own model's texture
coordinates, so two atlases laid out differently but holding the same colours agree.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import read_json

SAMPLES = 20_000
"""Points sampled on each surface for distances and texture colours."""
SEED = 0
MAX_PSNR = 100.0
"""PSNR reported for identical images (dB)."""


@dataclass(frozen=True)
class Surface:
    """A triangle mesh as compared: (n, 3) float64 vertices (mm), (m, 3) int64 faces, and
    for a textured model (n, 2) texture coordinates (origin at the image's top-left), its
    (h, w, 3) uint8 texture and which of its texels a view saw ((h, w) bool)."""

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    seen: np.ndarray | None = None


def read_surface(path: str | os.PathLike) -> Surface:
    """A triangle mesh from any PLY (range map, mesh, reference), with per-vertex texture
    coordinates (``texture_u``/``texture_v``, OpenGL convention) when it has them."""
    from slscan.meshes import check_face_indices, check_finite_vertices
    from slscan.ply import fan_triangles, read_ply_elements

    ply = read_ply_elements(path)
    vertex = ply.get("vertex", {})
    if not all(k in vertex for k in "xyz"):
        raise SlscanError(f"{path}: expected vertices with x, y, z")
    vertices = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64)
    check_finite_vertices(vertices, path)
    face = ply.get("face", {})
    index = face.get("vertex_indices", face.get("vertex_index"))
    faces = fan_triangles(*index) if index is not None else np.zeros((0, 3), np.int64)
    check_face_indices(faces, len(vertices), path)
    uvs = None
    if "texture_u" in vertex and "texture_v" in vertex:
        uvs = np.stack([vertex["texture_u"], 1.0 - vertex["texture_v"]], axis=1).astype(np.float64)
    return Surface(vertices, faces, uvs)


def write_surface(
    path: str | os.PathLike, surface: Surface, *, texture_file: str | None = None
) -> Path:
    """Write ``surface`` as a small binary PLY: float32 positions, texture coordinates when
    it has them (MeshLab's ``texture_u``/``texture_v`` and ``TextureFile`` comment)."""
    from slscan.ply import write_triangle_ply

    names = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if surface.uvs is not None:
        names += [("texture_u", "<f4"), ("texture_v", "<f4")]
    vertices = np.empty(len(surface.vertices), np.dtype(names))
    for k, axis in enumerate("xyz"):
        vertices[axis] = surface.vertices[:, k]
    if surface.uvs is not None:
        vertices["texture_u"] = surface.uvs[:, 0]
        vertices["texture_v"] = 1.0 - surface.uvs[:, 1]
    comments = ["slscan baseline reference: geometry only (mm)"]
    if texture_file:
        comments.append(f"TextureFile {texture_file}")
    return write_triangle_ply(path, vertices, surface.faces, comments)


def read_textured_model(folder: Path) -> Surface:
    """The texture stage's model: its OBJ, atlas and view counts, as ``texture.json`` names them."""
    from slscan.fsio import read_png
    from slscan.meshes import read_obj_atlas

    files = read_json(folder / "texture.json", "texture manifest").get("model", {})
    mesh, texture = read_obj_atlas(folder / files.get("obj", "model.obj"))
    seen = read_png(folder / files.get("view_count", "view_count.png")) > 0
    return Surface(
        np.asarray(mesh["vertices"], np.float64),
        np.asarray(mesh["faces"], np.int64),
        np.asarray(mesh["uvs"], np.float64),
        texture,
        seen,
    )


def sample_surface(surface: Surface, n: int, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniformly by area: their faces (n,) and barycentric coordinates (n, 3)."""
    v, f = surface.vertices, surface.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    rng = np.random.default_rng(seed)
    p = area / area.sum() if area.sum() > 0 else None
    face = rng.choice(len(f), size=n, p=p)
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    return face, np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)


def _at(surface: Surface, face: np.ndarray, bary: np.ndarray, values: np.ndarray) -> np.ndarray:
    return np.einsum("kj,kjc->kc", bary, values[surface.faces[face]])


@dataclass(frozen=True)
class Match:
    """Points sampled on surface ``a`` and the closest points of surface ``b``.

    distance : (n,) mm; face_a, bary_a : the points on ``a``; face_b, bary_b : on ``b``
    """

    distance: np.ndarray
    face_a: np.ndarray
    bary_a: np.ndarray
    face_b: np.ndarray
    bary_b: np.ndarray


def match_surfaces(a: Surface, b: Surface, *, samples: int = SAMPLES, seed: int = SEED) -> Match:
    """Sample ``a`` and find the closest point of ``b`` to each sample (open3d raycasting)."""
    import open3d as o3d

    face_a, bary_a = sample_surface(a, samples, seed)
    centre = a.vertices.mean(axis=0)  # float32 near the data keeps 1e-5 mm precision
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor((b.vertices - centre).astype(np.float32)),
        o3d.core.Tensor(b.faces.astype(np.uint32)),
    )
    points = _at(a, face_a, bary_a, a.vertices) - centre
    found = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
    uv = found["primitive_uvs"].numpy().astype(np.float64)
    bary_b = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    face_b = found["primitive_ids"].numpy().astype(np.int64)
    distance = np.linalg.norm(_at(b, face_b, bary_b, b.vertices) - centre - points, axis=1)
    return Match(distance, face_a, bary_a, face_b, bary_b)


def surface_distance(a: Surface, b: Surface, *, samples: int = SAMPLES) -> tuple[float, float]:
    """Symmetric point-to-surface distance (mm): the larger mean and the larger 95th
    percentile of the two directions; inf when one surface is empty and the other not."""
    if len(a.faces) == 0 or len(b.faces) == 0:
        return (0.0, 0.0) if len(a.faces) == len(b.faces) else (math.inf, math.inf)
    ab, ba = match_surfaces(a, b, samples=samples), match_surfaces(b, a, samples=samples)
    return (
        float(max(ab.distance.mean(), ba.distance.mean())),
        float(max(np.percentile(ab.distance, 95), np.percentile(ba.distance, 95))),
    )


def _texel_coords(
    surface: Surface, face: np.ndarray, bary: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    uv = _at(surface, face, bary, surface.uvs)
    h, w = surface.texture.shape[:2]
    return uv[:, 0] * w - 0.5, uv[:, 1] * h - 0.5  # texel centres at integers


def texture_colours(surface: Surface, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(n, 3) float32 colours of a textured surface at points given by face and barycentric
    coordinates, bilinear in its texture."""
    import cv2

    x, y = _texel_coords(surface, face, bary)
    out = cv2.remap(
        surface.texture.astype(np.float32),
        x.astype(np.float32)[:, None],
        y.astype(np.float32)[:, None],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(-1, 3)


def texels_seen(surface: Surface, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(n,) bool: all four texels a point's colour is interpolated from were seen by a view
    (every point when the surface does not say)."""
    if surface.seen is None:
        return np.ones(len(face), bool)
    x, y = _texel_coords(surface, face, bary)
    h, w = surface.seen.shape
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    seen = surface.seen
    return seen[y0, x0] & seen[y0, x1] & seen[y1, x0] & seen[y1, x1]


def psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    """Peak signal-to-noise ratio (dB) of two arrays of values up to ``peak``; :data:`MAX_PSNR` when equal."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    mse = float(np.mean(d * d)) if d.size else 0.0
    return MAX_PSNR if mse == 0 else min(MAX_PSNR, 10.0 * math.log10(peak * peak / mse))


@dataclass(frozen=True)
class TextureDifference:
    """Colours of two textured models at corresponding surface points (8-bit sRGB).

    seen_psnr : dB where views saw both models' colours; filled_psnr : dB where either
    colour was filled in from the vertices; seen_share : the share of points seen in both
    """

    seen_psnr: float
    filled_psnr: float
    seen_share: float


def texture_difference(a: Surface, b: Surface, *, samples: int = SAMPLES) -> TextureDifference:
    """Compare two textured models' colours independently of their atlas layouts: points
    sampled by area on each, the colour read through its own texture coordinates, against
    the colour at the closest point of the other through the other's."""
    old, new, seen = [], [], []
    for x, y in ((a, b), (b, a)):
        m = match_surfaces(x, y, samples=samples)
        cx, cy = texture_colours(x, m.face_a, m.bary_a), texture_colours(y, m.face_b, m.bary_b)
        old.append(cx if x is a else cy)
        new.append(cy if x is a else cx)
        seen.append(texels_seen(x, m.face_a, m.bary_a) & texels_seen(y, m.face_b, m.bary_b))
    old, new, seen = np.concatenate(old), np.concatenate(new), np.concatenate(seen)
    return TextureDifference(
        psnr(old[seen], new[seen], 255.0), psnr(old[~seen], new[~seen], 255.0), float(seen.mean())
    )
