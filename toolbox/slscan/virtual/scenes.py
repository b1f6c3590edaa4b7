"""Scenes for the virtual rig: the built-in figurine, the flat tile, the light-transport
scenes (concave corner, marble bust, bronze vessel), and user meshes.

A scene is a triangle mesh in its own object frame (mm) with shading normals, an albedo
source, a material per triangle (specular lobe, subsurface mean free path), and its
placement on the turntable (see :mod:`slscan.virtual.placement`). The built-in scenes are modelled in place (y down like
the rig, front towards -z, i.e. towards the camera); a user mesh keeps its file's
coordinates (scaled to mm) and is placed by a pose.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from slscan.errors import SlscanError
from slscan.meshes import MESH_SUFFIXES, check_face_indices, read_ply_mesh, vertex_normals
from slscan.rig import rotation_about_axis
from slscan.virtual.placement import AUTO_METRES_BELOW, default_placement, parse_units

log = logging.getLogger(__name__)


class AlbedoSource(Protocol):
    """Linear RGB reflectance at surface points."""

    def at(self, points: np.ndarray, triangle_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Albedo (k, 3) in [0, 1] at object-frame ``points`` (k, 3) on ``triangle_ids`` (k,)
        with barycentric ``bary`` (k, 2) (weights of the triangle's 2nd and 3rd vertex)."""

    def vertex_colors(self, vertices: np.ndarray) -> np.ndarray:
        """Albedo (n, 3) at the mesh vertices, for display and export."""


@dataclass(frozen=True)
class UniformAlbedo:
    color: tuple[float, float, float]

    def at(self, points, triangle_ids, bary):
        return np.broadcast_to(np.asarray(self.color, np.float32), (len(points), 3)).copy()

    def vertex_colors(self, vertices):
        return np.broadcast_to(np.asarray(self.color, np.float32), (len(vertices), 3)).copy()


@dataclass(frozen=True)
class VertexColorAlbedo:
    colors: np.ndarray  # (n, 3) float32 in [0, 1]
    triangles: np.ndarray  # (m, 3)

    def at(self, points, triangle_ids, bary):
        c = self.colors[self.triangles[triangle_ids]]  # (k, 3 corners, 3)
        w = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], axis=1)
        return np.einsum("kc,kcj->kj", w, c).astype(np.float32)

    def vertex_colors(self, vertices):
        return self.colors


@dataclass(frozen=True)
class TextureAlbedo:
    uvs: np.ndarray  # (m, 3, 2) per-corner texture coordinates, (0, 0) bottom-left
    texture: np.ndarray  # (th, tw, 3) float32 linear in [0, 1]
    per_vertex: np.ndarray  # (n, 3) fallback colours for display

    def at(self, points, triangle_ids, bary):
        w = np.stack([1 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], axis=1)
        uv = np.einsum("kc,kcj->kj", w, self.uvs[triangle_ids])
        th, tw = self.texture.shape[:2]
        x = np.clip(uv[:, 0] * tw - 0.5, 0, tw - 1)
        y = np.clip((1 - uv[:, 1]) * th - 0.5, 0, th - 1)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        x1, y1 = np.minimum(x0 + 1, tw - 1), np.minimum(y0 + 1, th - 1)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        t = self.texture
        top = t[y0, x0] * (1 - fx) + t[y0, x1] * fx
        bottom = t[y1, x0] * (1 - fx) + t[y1, x1] * fx
        return (top * (1 - fy) + bottom * fy).astype(np.float32)

    def vertex_colors(self, vertices):
        return self.per_vertex


@dataclass(frozen=True)
class Material:
    """How a region of a scene returns light, besides its albedo (which stays the scene's).

    name : what docs and logs call it
    specular : Blinn-Phong specular reflectance, 0 for matte
    specular_colour : (3,) linear RGB tint of the specular lobe ((1, 1, 1): white, as a
        dielectric's; a metal's highlight takes the metal's colour)
    shininess : Blinn-Phong exponent
    mean_free_path : mm, how far light travels under the surface before it leaves
        (subsurface scattering, honoured by the ``subsurface`` effect); 0: none
    """

    name: str
    specular: float = 0.0
    specular_colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    shininess: float = 40.0
    mean_free_path: float = 0.0

    def __post_init__(self) -> None:
        where = f"material {self.name!r}"
        if not (math.isfinite(self.specular) and self.specular >= 0):
            raise SlscanError(f"{where}: specular must be >= 0, got {self.specular}")
        if len(self.specular_colour) != 3 or not all(0 <= c <= 1 for c in self.specular_colour):
            raise SlscanError(f"{where}: specular_colour must be 3 values in [0, 1], got {self.specular_colour}")
        if not (math.isfinite(self.shininess) and self.shininess > 0):
            raise SlscanError(f"{where}: shininess must be > 0, got {self.shininess}")
        if not (math.isfinite(self.mean_free_path) and self.mean_free_path >= 0):
            raise SlscanError(f"{where}: mean_free_path must be >= 0 mm, got {self.mean_free_path}")

    @property
    def white_specular(self) -> bool:
        return tuple(self.specular_colour) == (1.0, 1.0, 1.0)


MATTE = Material("matte")
"""A Lambertian surface (plaster, unglazed clay, matte paint)."""
MARBLE = Material("marble", specular=0.04, shininess=60.0, mean_free_path=1.5)
"""White marble: light travels ~1.5 mm under the surface (Jensen et al. 2001 measure
1/sigma_tr of 1.5-2.2 mm for marble); a weak white polish highlight."""
BRONZE = Material("bronze", specular=0.6, specular_colour=(0.95, 0.64, 0.54), shininess=90.0)
"""Patinated bronze: dark coloured diffuse albedo (set by the scene), a strong copper-tinted
highlight (a metal's specular takes its colour)."""
MATERIALS = {m.name: m for m in (MATTE, MARBLE, BRONZE)}


@dataclass(frozen=True)
class Scene:
    """A mesh to scan.

    vertices : (n, 3) float64 mm, object frame
    triangles : (m, 3) int32
    normals : (n, 3) float64 unit shading normals, or None for flat (face) shading
    albedo : where the surface colour comes from
    specular : Blinn-Phong specular reflectance (white), 0 for matte
    shininess : Blinn-Phong exponent
    placement : (4, 4) float64 mm, rigid, ``turntable_from_object``: where the object frame
        stands on the turntable (:mod:`slscan.virtual.placement`); None: the identity
        (the object frame is the turntable frame)
    mm_per_unit : the scale from the mesh file's units to the object frame's mm
    materials : the scene's materials; empty: one, made from ``specular`` and ``shininess``
    material_ids : (m,) int index into ``materials`` per triangle; None: all the first
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray | None
    albedo: AlbedoSource
    specular: float = 0.0
    shininess: float = 40.0
    placement: np.ndarray | None = None
    mm_per_unit: float = 1.0
    materials: tuple[Material, ...] = ()
    material_ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        if len(self.triangles) == 0:
            raise SlscanError(f"scene {self.name!r}: the mesh has no faces")
        if len(self.vertices) < 3:
            raise SlscanError(f"scene {self.name!r}: the mesh has fewer than 3 vertices")
        if not self.materials:
            own = Material("default", specular=self.specular, shininess=self.shininess)
            object.__setattr__(self, "materials", (own,))
        if self.material_ids is not None:
            ids = np.asarray(self.material_ids)
            if ids.shape != (len(self.triangles),):
                raise SlscanError(f"scene {self.name!r}: material_ids must give one material per triangle "
                                  f"({len(self.triangles)}), got shape {ids.shape}")
            if len(ids) and (ids.min() < 0 or ids.max() >= len(self.materials)):
                raise SlscanError(f"scene {self.name!r}: material_ids must lie in 0..{len(self.materials) - 1}")
            object.__setattr__(self, "material_ids", ids.astype(np.int16))

    def material_of(self, triangle_ids: np.ndarray) -> np.ndarray:
        """Material index (k,) int16 of ``triangle_ids`` (k,)."""
        if self.material_ids is None:
            return np.zeros(len(triangle_ids), np.int16)
        return self.material_ids[triangle_ids]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


# --- mesh helpers -------------------------------------------------------------------


def _uv_sphere(n_lat: int, n_lon: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere (vertices, triangles) with poles on the y axis."""
    lat = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    lon = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    ring = np.stack([np.sin(la) * np.cos(lo), -np.cos(la), np.sin(la) * np.sin(lo)], axis=-1).reshape(-1, 3)
    verts = np.concatenate([[[0, -1, 0]], ring, [[0, 1, 0]]])
    tris = []
    idx = lambda i, j: 1 + i * n_lon + (j % n_lon)
    for j in range(n_lon):
        tris.append((0, idx(0, j + 1), idx(0, j)))
        tris.append((len(verts) - 1, idx(n_lat - 2, j), idx(n_lat - 2, j + 1)))
    i, j = np.meshgrid(np.arange(n_lat - 2), np.arange(n_lon), indexing="ij")
    a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
    quads = np.concatenate(
        [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)]
    )
    return verts.astype(float), np.concatenate([np.array(tris), quads]).astype(np.int32)


def _torus(major: float, minor: float, n_major: int, n_minor: int) -> tuple[np.ndarray, np.ndarray]:
    """Torus around the z axis (vertices, triangles)."""
    a = np.linspace(0, 2 * np.pi, n_major, endpoint=False)
    b = np.linspace(0, 2 * np.pi, n_minor, endpoint=False)
    A, B = np.meshgrid(a, b, indexing="ij")
    r = major + minor * np.cos(B)
    verts = np.stack([r * np.cos(A), r * np.sin(A), minor * np.sin(B)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_major), np.arange(n_minor), indexing="ij")
    idx = lambda i, j: (i % n_major) * n_minor + (j % n_minor)
    a0, a1, b0, b1 = idx(i, j), idx(i + 1, j), idx(i, j + 1), idx(i + 1, j + 1)
    tris = np.concatenate([np.stack([a0, a1, b0], -1).reshape(-1, 3), np.stack([a1, b1, b0], -1).reshape(-1, 3)])
    return verts, tris.astype(np.int32)


def _cylinder(radius: float, y0: float, y1: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed cylinder along y from ``y0`` to ``y1`` (vertices, triangles)."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([radius * np.cos(a), np.zeros(n), radius * np.sin(a)], -1)
    top, bottom = ring + [0, y0, 0], ring + [0, y1, 0]
    verts = np.concatenate([top, bottom, [[0, y0, 0], [0, y1, 0]]])
    i = np.arange(n)
    j = (i + 1) % n
    side = np.concatenate([np.stack([i, n + i, j], -1), np.stack([j, n + i, n + j], -1)])
    caps = np.concatenate([np.stack([np.full(n, 2 * n), i, j], -1), np.stack([np.full(n, 2 * n + 1), n + j, n + i], -1)])
    return verts, np.concatenate([side, caps]).astype(np.int32)


def _relief(points: np.ndarray) -> np.ndarray:
    """Surface relief (k,) mm in [-1, 1]: carved ripples of 9-25 mm wavelength."""
    x, y, z = points.T
    return (
        0.45 * np.sin(2 * np.pi * x / 17.0) * np.sin(2 * np.pi * y / 23.0)
        + 0.35 * np.sin(2 * np.pi * (x + z) / 11.0)
        + 0.2 * np.cos(2 * np.pi * (y - 0.5 * z) / 9.0)
    )


def _add_part(parts: list, verts: np.ndarray, tris: np.ndarray, part: int, relief: float = 0.0) -> None:
    """Append ``(verts, tris, part)`` to ``parts``, the vertices pushed along their normals by
    ``relief`` times the carved relief pattern (:func:`_relief`)."""
    if relief:
        verts = verts + relief * _relief(verts)[:, None] * vertex_normals(verts, tris)
    parts.append((verts, tris, part))


def _paint(points: np.ndarray, part: np.ndarray) -> np.ndarray:
    """The figurine's painted albedo (k, 3): stone, saturated red and blue paint, dark ink."""
    x, y, z = points.T
    mottling = 1 + 0.08 * np.sin(x / 13.0) * np.cos(z / 17.0) + 0.05 * np.sin(y / 7.0 + x / 29.0)
    color = np.array([0.62, 0.55, 0.45])[None, :] * mottling[:, None]
    red = (part == 0) & (np.abs(y - 35) < 16)  # a saturated red sash around the body
    color[red] = [0.75, 0.04, 0.03]
    blue_spots = (part == 0) & (np.sin(x / 9.0) * np.sin(y / 11.0 + 1.0) * np.cos(z / 10.0) > 0.45)
    color[blue_spots] = [0.04, 0.10, 0.72]
    cap = (part == 1) & (y < -205)  # a blue cap on the head
    color[cap] = [0.05, 0.12, 0.75]
    ink = (part == 0) & (np.abs(np.sin(x / 6.0 + y / 40.0)) < 0.06) & (y > 60)  # dark ink lines
    color[ink] = [0.07, 0.06, 0.05]
    color[part == 2] = [0.80, 0.62, 0.22]  # gilded ring
    color[part == 3] = [0.86, 0.85, 0.82]  # white arm
    base_stripes = (part == 4) & (np.sin(np.arctan2(z, x) * 12) > 0.3)
    color[part == 4] = [0.30, 0.32, 0.36]
    color[base_stripes] = [0.70, 0.06, 0.05]
    return np.clip(color, 0, 1).astype(np.float32)


@dataclass(frozen=True)
class _PartAlbedo:
    part_of_triangle: np.ndarray
    part_of_vertex: np.ndarray

    def at(self, points, triangle_ids, bary):
        return _paint(points, self.part_of_triangle[triangle_ids])

    def vertex_colors(self, vertices):
        return _paint(vertices, self.part_of_vertex)


def builtin_object(*, detail: float = 1.0) -> Scene:
    """The built-in figurine, about 380 mm tall, centred on the object origin.

    A bumpy body with ~1 mm carved relief, a head with a cap, a gilded ring on its left
    (the camera sees the body through it), an arm reaching towards the camera and the
    projector (it casts projector shadows on the body), and a striped pedestal. The paint
    includes saturated red and blue, which fool colour-coded patterns (paper §3.1).
    ``detail`` scales the tessellation (1.0: ~2 mm triangles on the body).
    """
    parts = []
    add = functools.partial(_add_part, parts)

    n = max(16, round(300 * detail))
    v, t = _uv_sphere(n // 2, n)
    body_r = np.array([100.0, 120.0, 85.0])
    wobble = 1 + 0.07 * np.sin(3 * np.arctan2(v[:, 2], v[:, 0])) * np.cos(2 * v[:, 1])
    add(v * body_r * wobble[:, None] + [0, 20, 0], t, 0, relief=1.0)
    v, t = _uv_sphere(max(12, n // 4), max(16, n // 2))
    add(v * 58.0 + [0, -150, -5], t, 1, relief=1.0)
    v, t = _torus(46.0, 12.0, max(24, n // 3), max(12, n // 10))
    v = v @ rotation_about_axis([0, 1, 0], math.radians(60)).T + [-108, -10, -20]
    add(v, t, 2)
    v, t = _cylinder(17.0, 0.0, 1.0, max(16, n // 8))
    # arm: a capped tube from the body towards the camera; it shadows the body from the projector
    start, end = np.array([40.0, 10.0, -50.0]), np.array([25.0, 30.0, -175.0])
    axis = (end - start) / np.linalg.norm(end - start)
    v = v.copy()
    v[:, 1] *= np.linalg.norm(end - start)
    rot_axis = np.cross([0, 1, 0], axis)
    angle = math.acos(np.clip(axis[1], -1, 1))
    v = v @ rotation_about_axis(rot_axis, angle).T + start
    add(v, t, 3)
    v, t = _cylinder(95.0, 135.0, 175.0, max(32, n // 2))
    add(v, t, 4)

    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    vertices = np.concatenate([p[0] for p in parts])
    triangles = np.concatenate([p[1] + o for p, o in zip(parts, offsets)]).astype(np.int32)
    part_t = np.concatenate([np.full(len(p[1]), p[2]) for p in parts])
    part_v = np.concatenate([np.full(len(p[0]), p[2]) for p in parts])
    # shading normals per part (smooth within a part, hard between parts)
    normals = np.concatenate([vertex_normals(p[0], p[1]) for p in parts])
    return Scene("figurine", vertices, triangles, normals, _PartAlbedo(part_t, part_v), specular=0.12, shininess=30.0)


def flat_tile(*, width: float = 400.0, height: float = 300.0, thickness: float = 12.0,
              tilt_deg: tuple[float, float] = (15.0, 8.0), albedo: float = 0.8) -> Scene:
    """A flat ceramic tile facing the camera, tilted by ``tilt_deg`` (about y, about x)."""
    hx, hy, hz = width / 2, height / 2, thickness / 2
    corners = np.array([[x, y, z] for z in (-hz, hz) for y in (-hy, hy) for x in (-hx, hx)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int32)
    # make faces wind outwards
    centroid = corners.mean(axis=0)
    v = corners[tris]
    face_n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", face_n, v.mean(axis=1) - centroid) < 0
    tris[flip] = tris[flip][:, ::-1]
    r = rotation_about_axis([0, 1, 0], math.radians(tilt_deg[0])) @ rotation_about_axis([1, 0, 0], math.radians(tilt_deg[1]))
    return Scene("tile", corners @ r.T, tris, None, UniformAlbedo((albedo, albedo, albedo * 0.97)), specular=0.03, shininess=60.0)


def load_mesh_scene(path: str | os.PathLike, *, units: str | float | None = "auto",
                    pose: np.ndarray | None = None, specular: float = 0.05) -> Scene:
    """A user mesh (PLY/OBJ/glTF/GLB/OFF/STL) with its texture or vertex colours.

    The object frame is the file's own coordinates, scaled to mm by ``units``: a unit name
    {"mm", "cm", "m", "in"}, mm per unit, or "auto" / None (mm, or metres when the mesh is
    less than 10 units across). ``pose`` is its ``turntable_from_object`` (4, 4) mm; None:
    the default placement (:func:`slscan.virtual.placement.default_placement`: y up and
    front +z turned to the rig's y down and front to the camera, the bounding box centred
    on the turntable).
    """
    import open3d as o3d

    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SlscanError(f"{path}: unknown mesh format {path.suffix!r}; expected one of {', '.join(MESH_SUFFIXES)}")
    if not path.is_file():
        raise SlscanError(f"{path}: mesh file not found")
    mm_per_unit = parse_units(units, "units")
    if path.suffix.lower() == ".ply":
        read_ply_mesh(path)  # Open3D's PLY reader crashes on some malformed files: check it first
    mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=True)
    vertices = np.asarray(mesh.vertices, dtype=float)
    triangles = np.asarray(mesh.triangles, dtype=np.int32)
    if len(triangles) == 0 or len(vertices) < 3:
        raise SlscanError(f"{path}: the mesh has no faces (a point cloud cannot be scanned)")
    check_face_indices(np.asarray(mesh.triangles), len(vertices), path)
    if mm_per_unit is None:
        diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        mm_per_unit = 1000.0 if diag < AUTO_METRES_BELOW else 1.0
        if mm_per_unit != 1.0:
            log.warning("%s is %.3g units across: taking it to be in metres (set the units to say)", path, diag)
    vertices = vertices * mm_per_unit
    placement = default_placement(vertices) if pose is None else np.asarray(pose, dtype=float)
    normals = vertex_normals(vertices, triangles)
    if mesh.has_vertex_colors():
        colors = np.asarray(mesh.vertex_colors, dtype=np.float32)
    else:
        colors = np.full((len(vertices), 3), 0.7, np.float32)
    albedo: AlbedoSource
    if mesh.has_triangle_uvs() and len(mesh.textures) > 0 and np.asarray(mesh.textures[0]).size:
        tex = np.asarray(mesh.textures[0])
        tex = tex[..., :3].astype(np.float32) / (65535.0 if tex.dtype == np.uint16 else 255.0)
        tex = np.where(tex <= 0.04045, tex / 12.92, ((tex + 0.055) / 1.055) ** 2.4)  # sRGB -> linear
        uvs = np.asarray(mesh.triangle_uvs, dtype=np.float64).reshape(-1, 3, 2)
        uvs[..., 1] = 1 - uvs[..., 1]  # open3d stores v downwards
        albedo = TextureAlbedo(uvs, tex.astype(np.float32), colors)
    elif mesh.has_vertex_colors():
        albedo = VertexColorAlbedo(colors, triangles)
    else:
        albedo = UniformAlbedo((0.7, 0.7, 0.7))
    return Scene(path.stem, vertices, triangles, normals, albedo, specular=specular, placement=placement,
                 mm_per_unit=mm_per_unit)


# --- light-transport scenes ------------------------------------------------------------


def _rotation_from_to(a, b) -> np.ndarray:
    """Rotation (3, 3) turning unit direction ``a`` onto ``b`` (not opposite)."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    axis = np.cross(a, b)
    if np.linalg.norm(axis) < 1e-12:
        return np.eye(3)
    return rotation_about_axis(axis, math.acos(float(np.clip(a @ b, -1, 1))))


def _grid_quad(origin, du, dv, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n grid of quads from ``origin`` spanned by ``du``, ``dv`` (vertices, triangles)."""
    s, t = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    verts = np.asarray(origin, float) + s.reshape(-1, 1) * np.asarray(du, float) + t.reshape(-1, 1) * np.asarray(dv, float)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    idx = lambda i, j: i * (n + 1) + j
    a, b, c, d = idx(i, j), idx(i + 1, j), idx(i, j + 1), idx(i + 1, j + 1)
    tris = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return verts, tris.astype(np.int32)


@dataclass(frozen=True)
class _PaintedParts:
    """Albedo from a function of (object-frame points, part index)."""

    paint: object
    part_of_triangle: np.ndarray
    part_of_vertex: np.ndarray

    def at(self, points, triangle_ids, bary):
        return self.paint(points, self.part_of_triangle[triangle_ids])

    def vertex_colors(self, vertices):
        return self.paint(vertices, self.part_of_vertex)


def _assemble(name: str, parts: list, paint, materials: tuple[Material, ...], material_of_part: dict,
              *, smooth: bool = True) -> Scene:
    """A scene from ``parts`` [(vertices, triangles, part index)]."""
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    vertices = np.concatenate([p[0] for p in parts])
    triangles = np.concatenate([p[1] + o for p, o in zip(parts, offsets)]).astype(np.int32)
    part_t = np.concatenate([np.full(len(p[1]), p[2]) for p in parts])
    part_v = np.concatenate([np.full(len(p[0]), p[2]) for p in parts])
    normals = np.concatenate([vertex_normals(p[0], p[1]) for p in parts]) if smooth else None
    ids = np.array([material_of_part[int(k)] for k in part_t], dtype=np.int16)
    first = materials[0]
    return Scene(name, vertices, triangles, normals, _PaintedParts(paint, part_t, part_v),
                 specular=first.specular, shininess=first.shininess, materials=materials, material_ids=ids)


def concave_corner(*, side: float = 300.0, albedo: float = 0.8, detail: float = 1.0) -> Scene:
    """A cube corner seen from inside along its diagonal: three perpendicular matte panels
    ``side`` mm square (about 420 mm across in the image), every panel lighting the other
    two (strong inter-reflection, Gupta et al. 2011's V-groove). One vertical crease."""
    n = max(2, round(24 * detail))
    parts = [
        _grid_quad([0, 0, 0], [0, side, 0], [0, 0, side], n) + (0,),   # x = 0
        _grid_quad([0, 0, 0], [0, 0, side], [side, 0, 0], n) + (1,),   # y = 0
        _grid_quad([0, 0, 0], [side, 0, 0], [0, side, 0], n) + (2,),   # z = 0
    ]
    diag = np.ones(3) / np.sqrt(3)
    r = _rotation_from_to(diag, [0, 0, -1])  # the diagonal towards the camera: the corner's inside faces it
    crease = r @ np.array([0.0, 1.0, 0.0])
    crease_to = np.array([0.0, -1.0, 0.0]) - (np.array([0.0, -1.0, 0.0]) @ [0, 0, -1]) * np.array([0, 0, -1.0])
    crease_now = crease - (crease @ [0, 0, -1]) * np.array([0, 0, -1.0])
    spin = math.atan2(np.cross(crease_now, crease_to) @ [0, 0, -1.0], crease_now @ crease_to)
    r = rotation_about_axis([0, 0, -1], spin) @ r
    centre = np.full(3, side / 3)
    parts = [((v - centre) @ r.T, t, k) for v, t, k in parts]

    def paint(points, part):
        return np.full((len(points), 3), [albedo, albedo, albedo * 0.97], np.float32)

    return _assemble("concave", parts, paint, (MATTE,), {0: 0, 1: 0, 2: 0}, smooth=False)


def _marble_paint(points: np.ndarray, part: np.ndarray) -> np.ndarray:
    """White marble with faint grey veins; a dark stone plinth (part 4)."""
    x, y, z = points.T
    vein = np.abs(np.sin((x + 0.6 * y + 0.3 * z) / 11.0 + 1.5 * np.sin(y / 27.0 + z / 31.0))) < 0.06
    color = np.tile(np.array([0.86, 0.84, 0.80], np.float32), (len(points), 1))
    color[vein] = [0.58, 0.58, 0.60]
    color[part == 4] = [0.22, 0.22, 0.24]
    return color


def marble_bust(*, detail: float = 1.0) -> Scene:
    """A bust-like marble object, about 440 mm tall: a head with a nose and carved ~1 mm
    relief, a neck, shoulders, on a matte dark-stone plinth (a material border)."""
    parts = []
    add = functools.partial(_add_part, parts)

    n = max(16, round(200 * detail))
    v, t = _uv_sphere(n // 2, n)
    add(v * [70.0, 90.0, 78.0] + [0, -160, 0], t, 0, relief=1.0)               # head
    v, t = _uv_sphere(max(8, n // 8), max(12, n // 4))
    add(v * [13.0, 24.0, 16.0] + [0, -150, -72], t, 1)                           # nose
    v, t = _cylinder(34.0, -90.0, 10.0, max(24, n // 4))
    add(v, t, 2)                                                                   # neck
    v, t = _uv_sphere(n // 2, n)
    keep = v[t].max(axis=1)[:, 1] < 0.55                                           # chest and shoulders,
    add(v * [160.0, 110.0, 85.0] + [0, 90, 0], t[keep], 3, relief=1.0)           # cut flat below
    v, t = _cylinder(95.0, 150.0, 195.0, max(32, n // 3))
    add(v, t, 4)                                                                   # plinth
    return _assemble("marble", parts, _marble_paint, (MARBLE, MATTE), {0: 0, 1: 0, 2: 0, 3: 0, 4: 1})


def _bronze_paint(points: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Dark bronze with green patina patches; a matte stone base (part 4)."""
    x, y, z = points.T
    patina = np.sin(x / 14.0 + 0.5) * np.sin(y / 17.0) * np.cos(z / 12.0) > 0.55
    color = np.tile(np.array([0.40, 0.24, 0.11], np.float32), (len(points), 1))
    color[patina] = [0.14, 0.26, 0.20]
    color[part == 4] = [0.45, 0.44, 0.42]
    return color


def bronze_vessel(*, detail: float = 1.0) -> Scene:
    """A bronze vessel, about 380 mm tall: an open hemispherical bowl tilted towards the
    camera (its inside lights itself with coloured highlights), two ring handles, a stem,
    on a matte stone base."""
    parts = []
    n = max(16, round(160 * detail))
    v, t = _uv_sphere(n // 2, n)
    keep = v[t].max(axis=1)[:, 1] <= 1e-9                       # the half towards -y: a bowl opening to +y
    used = np.unique(t[keep])
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    bowl_v, bowl_t = v[used] * 125.0, remap[t[keep]]
    r = _rotation_from_to([0, 1, 0], [0, -math.sin(math.radians(35)), -math.cos(math.radians(35))])
    bowl_v = bowl_v @ r.T + [0, -60, 0]
    parts.append((bowl_v, bowl_t.astype(np.int32), 0))
    for side in (-1, 1):
        v, t = _torus(38.0, 9.0, max(24, n // 4), max(12, n // 10))
        v = v @ rotation_about_axis([0, 1, 0], math.radians(90)).T + [side * 150, -70, 20]
        parts.append((v, t, 1))
    v, t = _cylinder(22.0, 20.0, 120.0, max(24, n // 4))
    parts.append((v, t, 2))
    v, t = _uv_sphere(max(8, n // 8), max(16, n // 4))
    parts.append((v * [45.0, 18.0, 45.0] + [0, 70, 0], t, 3))   # a knop on the stem
    v, t = _cylinder(90.0, 120.0, 160.0, max(32, n // 3))
    parts.append((v, t, 4))
    return _assemble("bronze", parts, _bronze_paint, (BRONZE, MATTE), {0: 0, 1: 0, 2: 0, 3: 0, 4: 1})


BUILTIN_SCENES = ("object", "tile", "concave", "marble", "bronze")
_BUILDERS = {"object": builtin_object, "tile": flat_tile, "concave": concave_corner, "marble": marble_bust,
             "bronze": bronze_vessel}


def scene_by_name(name: str, *, units: str | float | None = None, pose: np.ndarray | None = None,
                  **kwargs) -> Scene:
    """``"object"`` (built-in figurine), ``"tile"``, the light-transport scenes ``"concave"``
    (cube corner), ``"marble"`` (bust), ``"bronze"`` (vessel), or a mesh file path
    (``units``: see :func:`load_mesh_scene`), placed on the turntable at ``pose``
    (``turntable_from_object``; None: the default placement)."""
    if name in BUILTIN_SCENES:
        if units is not None and not (isinstance(units, str) and units.strip().lower() == "auto"):
            raise SlscanError(f"scene_units: the built-in scene {name!r} is modelled in mm; units are for a mesh file")
        scene = _BUILDERS[name](**kwargs)
        return scene if pose is None else dataclasses.replace(scene, placement=np.asarray(pose, dtype=float))
    return load_mesh_scene(name, units="auto" if units is None else units, pose=pose, **kwargs)


def shading_normals(scene: Scene, rotation: np.ndarray, tri: np.ndarray, wts: np.ndarray, geo_n: np.ndarray,
                    facing: np.ndarray) -> np.ndarray:
    """Unit shading normals (k, 3) at k surface hits: ``scene``'s vertex normals turned by
    ``rotation`` (3, 3), interpolated over the hit triangles' corners ``tri`` (k, 3) with
    barycentric weights ``wts`` (k, 3), turned to the side seen (``facing`` False: seen from
    behind) and replaced by the face normal ``geo_n`` (k, 3, already turned to that side)
    where they point away from it; ``geo_n`` itself for a scene without normals."""
    if scene.normals is None:
        return geo_n
    n = np.einsum("kc,kcj->kj", wts, (scene.normals @ rotation.T)[tri])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[~facing] *= -1
    back = np.einsum("ij,ij->i", n, geo_n) <= 0.05  # keep them on the visible side of the face
    n[back] = geo_n[back]
    return n


def surface_albedo(scene: Scene, points: np.ndarray) -> np.ndarray:
    """True albedo (k, 3) linear RGB at the surface points nearest to object-frame ``points``
    (k, 3): ground truth for baked textures."""
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(scene.vertices, np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(scene.triangles, np.uint32)),
    )
    out = np.empty((len(points), 3), np.float32)
    for start in range(0, len(points), 1_000_000):
        chunk = np.ascontiguousarray(points[start:start + 1_000_000], np.float32)
        hit = rc.compute_closest_points(o3d.core.Tensor(chunk))
        ids = hit["primitive_ids"].numpy().astype(np.int64)
        bary = hit["primitive_uvs"].numpy().astype(np.float64)
        out[start:start + len(chunk)] = scene.albedo.at(hit["points"].numpy().astype(np.float64), ids, bary)
    return out
