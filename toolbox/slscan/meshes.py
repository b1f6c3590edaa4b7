"""Small triangle-mesh helpers shared by the stages and the viewer."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError

MESH_SUFFIXES = (".ply", ".obj", ".gltf", ".glb", ".off", ".stl")
"""The mesh file formats slscan reads (through Open3D/trimesh)."""


def check_finite_vertices(vertices: np.ndarray, path: str | os.PathLike) -> None:
    """Refuse a mesh whose vertices hold NaN or infinite coordinates, naming the file, how
    many vertices are bad and the first one's index.

    vertices : (n, 3) float
    """
    bad = ~np.isfinite(np.asarray(vertices, np.float64)).all(axis=1)
    if bad.any():
        n = int(bad.sum())
        raise SlscanError(
            f"{path}: {n} vert{'ices' if n != 1 else 'ex'} with non-finite coordinates (NaN or inf), "
            f"the first at index {int(np.argmax(bad))}; expected finite x, y, z"
        )


def check_face_indices(faces: np.ndarray, n_vertices: int, path: str | os.PathLike) -> None:
    """Refuse faces that refer to a vertex the mesh does not have (negative, or ``n_vertices``
    or more), naming the file, the first bad face, its index and the vertex count.

    Every mesh read from a file goes through this before its faces reach native code
    (Open3D, pymeshlab, fast-simplification, xatlas, OpenCV), where an index past the end
    reads or writes outside the vertex array (a crash, or silently a different mesh).

    faces : (m, k) int (any integer type; unsigned indices of 2**31 or more count as bad)
    n_vertices : the number of vertices the file holds
    """
    f = np.asarray(faces)
    if f.size == 0:
        return
    if not np.issubdtype(f.dtype, np.integer):
        raise SlscanError(f"{path}: face vertex indices are not integers ({f.dtype}); expected integer indices")
    f = f.reshape(len(f), -1) if f.ndim > 1 else f.reshape(-1, 1)
    bad = ((f < 0) | (f >= n_vertices)).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        row = f[i]
        index = int(row[(row < 0) | (row >= n_vertices)][0])
        n = int(bad.sum())
        raise SlscanError(
            f"{path}: face {i} refers to vertex {index} but the file has {n_vertices} vertices "
            f"({n} bad face{'s' if n != 1 else ''}); expected vertex indices 0 to {n_vertices - 1}"
        )


@dataclass(frozen=True)
class PlyMesh:
    """A triangle mesh read from a PLY file.

    vertices : (n, 3) float64, the file's units
    faces : (m, 3) int64, checked to index the vertices (polygons fanned into triangles)
    normals : (n, 3) float32 (``nx ny nz``), or None
    colors : (n, 3) uint8 RGB (``red green blue``; float colours in 0..1 scaled), or None
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None


def read_ply_mesh(path: str | os.PathLike) -> PlyMesh:
    """Read a triangle-mesh PLY (ASCII or binary) with :func:`slscan.ply.read_ply_elements`,
    checked: finite vertices (:func:`check_finite_vertices`) and faces that index them
    (:func:`check_face_indices`). A file without faces gives none.

    Raises
    ------
    SlscanError
        Missing, not a PLY, truncated, no ``x y z`` vertices, non-finite vertices, or faces
        referring to vertices the file does not have (naming the file).
    """
    from slscan.ply import fan_triangles, read_ply_elements

    ply = read_ply_elements(path)
    vertex = ply.get("vertex") or {}
    if not all(k in vertex for k in "xyz"):
        raise SlscanError(f"{path}: no vertex element with x, y, z properties; expected a mesh PLY")
    vertices = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64)
    check_finite_vertices(vertices, path)
    face = ply.get("face") or {}
    index = face.get("vertex_indices", face.get("vertex_index"))
    faces = np.zeros((0, 3), np.int64)
    if index is not None:
        if not isinstance(index, tuple):
            raise SlscanError(f"{path}: the faces' vertex_indices is not a list property")
        faces = fan_triangles(*index)
    check_face_indices(faces, len(vertices), path)
    normals = colors = None
    if all(k in vertex for k in ("nx", "ny", "nz")):
        normals = np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1).astype(np.float32)
    if all(k in vertex for k in ("red", "green", "blue")):
        rgb = np.stack([vertex[k] for k in ("red", "green", "blue")], axis=1)
        if rgb.dtype.kind == "f":
            rgb = np.round(np.nan_to_num(np.clip(rgb, 0.0, 1.0)) * 255)
        colors = np.clip(rgb, 0, 255).astype(np.uint8)
    return PlyMesh(vertices, faces.astype(np.int64), normals, colors)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) float64; zero for unreferenced vertices.

    vertices : (n, 3) float; triangles : (m, 3) int, counter-clockwise seen from outside
    """
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[triangles[:, 0]], v[triangles[:, 1]], v[triangles[:, 2]]
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(v)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def _check_obj_indices(path: Path) -> None:
    """Refuse an OBJ whose faces refer to a vertex or texture coordinate it does not have
    (trimesh raises IndexError on some, and on others allocates one entry per index up to
    the largest: 32 GiB for an index of 2**32); OBJ indices count from 1, negative ones
    back from the last element read so far."""
    counts = {b"v": 0, b"vt": 0}
    names = {0: ("vertex", b"v"), 1: ("texture coordinate", b"vt")}
    face = 0
    try:
        with open(path, "rb") as fh:
            for line in fh:
                words = line.split()
                if not words:
                    continue
                if words[0] in counts:
                    counts[words[0]] += 1
                elif words[0] == b"f":
                    for word in words[1:]:
                        for k, part in enumerate(word.split(b"/")[:2]):
                            if not part:
                                continue
                            name, key = names[k]
                            i, n = int(part), counts[key]
                            if not (1 <= i <= n or -n <= i <= -1):
                                raise SlscanError(
                                    f"{path}: face {face} refers to {name} {i} but the file has {n} before it "
                                    f"(OBJ counts from 1); expected indices 1 to {n}"
                                )
                    face += 1
    except ValueError:
        raise SlscanError(f"{path}: face {face} holds an index that is not an integer") from None
    except OSError as exc:
        raise SlscanError(f"{path}: cannot read it ({exc.strerror})") from None


def read_obj_atlas(path: str | os.PathLike) -> tuple[dict, np.ndarray]:
    """An OBJ written by :func:`slscan.texture.export.write_obj` read back:
    ``{"vertices", "faces", "uvs"}`` (uvs with the origin at the image's top-left, as in
    :class:`slscan.texture.atlas.Atlas`) and its 8-bit texture."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: textured OBJ not found")
    _check_obj_indices(path)
    try:
        mesh = trimesh.load(path, force="mesh", process=False, maintain_order=True)
    except (IndexError, ValueError, KeyError, TypeError) as exc:  # trimesh's parse errors: bad indices, numbers
        raise SlscanError(f"{path}: not a readable textured OBJ ({exc})") from None
    uv = getattr(mesh.visual, "uv", None)
    tex = getattr(getattr(mesh.visual, "material", None), "image", None)
    if uv is None or tex is None:
        raise SlscanError(f"{path}: expected texture coordinates and a texture image")
    check_face_indices(np.asarray(mesh.faces), len(mesh.vertices), path)
    uvs = np.asarray(uv, np.float32).copy()
    uvs[:, 1] = 1.0 - uvs[:, 1]
    return (
        {"vertices": np.asarray(mesh.vertices), "faces": np.asarray(mesh.faces), "uvs": uvs},
        np.asarray(tex.convert("RGB"), np.uint8),
    )


def boundary_vertices(faces: np.ndarray) -> np.ndarray:
    """Sorted indices of the vertices on open boundaries (edges used by one face only).

    faces : (m, 3) int
    """
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int64)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * (int(f.max()) + 1) + edges[:, 1]
    unique, counts = np.unique(key, return_counts=True)
    single = np.isin(key, unique[counts == 1])
    return np.unique(edges[single].reshape(-1))
