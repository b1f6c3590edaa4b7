"""Mesh simplification to a target face count (quadric edge collapse), keeping open boundaries.

Two back ends, both quadric-error edge collapse after Garland & Heckbert [1]_:

- ``"fast"``: fast-simplification (Sp4cerat's Fast-Quadric-Mesh-Simplification), the
  default: several million faces a second. With ``preserve_boundary=True`` it refuses
  every collapse of an edge that touches an open-boundary vertex, so each boundary
  vertex is kept exactly where it was (the boundary is not simplified at all);
- ``"quadric"``: pymeshlab's ``meshing_decimation_quadric_edge_collapse``, slower and of
  higher quality (optimal vertex placement, normal and topology checks). With
  ``preserve_boundary=True`` it runs with ``preserveboundary=True`` and a large
  ``boundaryweight``: boundaries are kept in shape, but straight runs of boundary
  edges may still be collapsed, so boundary vertices are not all kept.

References
----------
.. [1] Garland, Heckbert, "Surface simplification using quadric error metrics",
   SIGGRAPH 1997.
"""

from __future__ import annotations

import logging
import math
import os

import numpy as np

from slscan.errors import SlscanError
from slscan.fuse import Mesh
from slscan.meshes import check_finite_vertices

log = logging.getLogger(__name__)

DEFAULT_TARGET_FACES = 1_000_000
"""The paper's archival model size: about a million faces."""

METHODS = ("fast", "quadric")


def simplify_mesh(
    mesh: Mesh,
    target_faces: int = DEFAULT_TARGET_FACES,
    *,
    method: str = "fast",
    preserve_boundary: bool = True,
    aggressiveness: float = 6.0,
    boundary_weight: float = 1000.0,
    chunk_faces: int = 4_000_000,
) -> Mesh:
    """Simplify ``mesh`` to about ``target_faces`` faces.

    Parameters
    ----------
    mesh : Mesh, (n, 3) vertices in mm and (m, 3) faces
    target_faces : wanted face count; a mesh already at or below it is returned as is
    method : {"fast", "quadric"}, see the module docstring
    preserve_boundary : keep open boundaries (exactly with "fast")
    aggressiveness : fast-simplification's ``agg`` (higher: faster, coarser; 6 is as good
        as its default 7 on fused scans and faster, see ``benchmarks/scale.py``)
    boundary_weight : pymeshlab's ``boundaryweight`` when preserving boundaries
    chunk_faces : "fast" simplifies larger meshes in slabs of about this many faces
        first (see :func:`_fast`): less memory, and faster from a fresh process

    Returns
    -------
    Mesh
        Vertices, faces and area-weighted vertex normals (colours are dropped).

    Raises
    ------
    SlscanError
        An unknown method, a target below 4 faces, or vertices holding NaN or inf.
    """
    if method not in METHODS:
        raise SlscanError(f"simplification method {method!r}: expected one of {METHODS}")
    target = int(target_faces)
    if target < 4:
        raise SlscanError(f"target face count must be at least 4, got {target_faces}")
    check_finite_vertices(mesh.vertices, "the mesh to simplify")
    if mesh.n_faces <= target:
        return mesh
    if method == "fast":
        vertices, faces = _fast(mesh, target, preserve_boundary, aggressiveness, chunk_faces)
    else:
        vertices, faces = _quadric(mesh, target, preserve_boundary, boundary_weight)
    from slscan.meshes import vertex_normals

    log.debug("simplified %d -> %d faces (%s)", mesh.n_faces, len(faces), method)
    return Mesh(vertices, faces, vertex_normals(vertices, faces).astype(np.float32))


def _fast(
    mesh: Mesh,
    target: int,
    preserve_boundary: bool,
    aggressiveness: float,
    max_chunk_faces: int = 4_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """fast-simplification; meshes above ``max_chunk_faces`` go in slabs first.

    Large meshes are cut into slabs along their longest axis; each slab is simplified
    to its share of the target with its border (the cut and any open boundary) kept,
    the slabs are joined on the cut vertices (kept exactly, so equal coordinates), and
    a last pass over the joined mesh reaches the target. Besides lowering the peak
    memory, this is faster on fresh processes: fast-simplification grows its arrays one
    element at a time, and after the first slab the later ones reuse that memory.
    """
    vertices = np.ascontiguousarray(mesh.vertices, np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    n = len(faces)
    if n > max_chunk_faces:
        pieces = math.ceil(n / max_chunk_faces)
        centre = vertices[faces].mean(axis=1)
        axis = int(np.argmax(centre.max(axis=0) - centre.min(axis=0)))
        cuts = np.quantile(centre[:, axis], np.linspace(0, 1, pieces + 1)[1:-1])
        slab = np.searchsorted(cuts, centre[:, axis])
        del centre
        out_v, out_f, offset = [], [], 0
        for k in range(pieces):
            part = faces[slab == k]
            used, local = np.unique(part, return_inverse=True)
            share = max(4, round(target * len(part) / n))
            v, f = _fast_pass(
                vertices[used], local.reshape(-1, 3).astype(np.int32), share, True, aggressiveness
            )
            out_v.append(v)
            out_f.append(f + offset)
            offset += len(v)
        vertices, faces = _weld_equal(np.concatenate(out_v), np.concatenate(out_f))
        log.debug("fast-simplification: %d slabs joined, %d faces", pieces, len(faces))
        if len(faces) <= target:
            return vertices, faces.astype(np.int64)
    v, f = _fast_pass(vertices, faces.astype(np.int32), target, preserve_boundary, aggressiveness)
    return v, f.astype(np.int64)


def _fast_pass(
    vertices: np.ndarray, faces: np.ndarray, target: int, preserve_border: bool, agg: float
) -> tuple[np.ndarray, np.ndarray]:
    """One fast-simplification run, re-run with +1 aggressiveness (up to 3 more times)
    while it stops more than 1 % above the target (a low ``agg`` can stall before it)."""
    import fast_simplification

    if len(faces) <= target:
        return vertices, faces
    for _ in range(4):
        vertices, faces = fast_simplification.simplify(
            np.ascontiguousarray(vertices, np.float64),
            np.ascontiguousarray(faces, dtype=np.int32),
            target_count=target,
            agg=float(agg),
            preserve_border=bool(preserve_border),
        )
        if len(faces) <= 1.01 * target:
            break
        log.debug("fast-simplification stopped at %d faces (agg %g); again", len(faces), agg)
        agg += 1.0
    return np.asarray(vertices, np.float64), np.asarray(faces, np.int64)


def _weld_equal(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical coordinates; drop faces that become degenerate."""
    rows = np.ascontiguousarray(vertices).view(np.dtype((np.void, vertices.dtype.itemsize * 3)))
    _, first, inverse = np.unique(rows.ravel(), return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    f = rank[inverse.ravel()][faces]
    good = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    return vertices[first[order]], f[good]


def _quadric(
    mesh: Mesh, target: int, preserve_boundary: bool, boundary_weight: float
) -> tuple[np.ndarray, np.ndarray]:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(
        pymeshlab.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)),
        "mesh",
    )
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=int(target),
        preserveboundary=bool(preserve_boundary),
        boundaryweight=float(boundary_weight) if preserve_boundary else 1.0,
        preservenormal=True,
        preservetopology=False,
        optimalplacement=True,
        planarquadric=True,
        qualitythr=0.3,
        autoclean=True,
    )
    m = ms.current_mesh()
    return m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)


def simplify_file(
    source: str | os.PathLike,
    target: str | os.PathLike,
    target_faces: int = DEFAULT_TARGET_FACES,
    *,
    method: str = "fast",
    preserve_boundary: bool = True,
    option: str = "target_faces",
) -> Mesh:
    """Read a mesh file, simplify it (:func:`simplify_mesh`), write the result atomically.

    A mesh with no more faces than ``target_faces`` is written unchanged, with a warning
    naming the file, its face count and the ``option`` that set the target (``--faces``,
    ``[simplify] faces``). Not an error: the target is a ceiling (the archival model's
    size), which a small mesh already meets, and a recipe run at reduced size must not
    fail on it; but a user who asked for more faces than there are is told so.
    """
    from slscan.fuse import read_mesh, write_mesh

    mesh = read_mesh(source)
    result = simplify_mesh(mesh, target_faces, method=method, preserve_boundary=preserve_boundary)
    if result is mesh:
        log.warning("%s: has %s faces, not more than %s %s: written unchanged, not simplified",
                    source, f"{mesh.n_faces:,}", option, f"{int(target_faces):,}")
    write_mesh(result, target)
    return result
