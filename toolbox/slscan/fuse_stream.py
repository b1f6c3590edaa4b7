"""Fusion in bricks streamed to disk: each brick's mesh piece goes to a scratch folder, the caller
writes one binary PLY brick by brick and never holds the whole fused mesh.

Used by :func:`slscan.fuse.fuse_bricks` with ``out=PATH``:

1. each brick task writes its piece (the triangles it keeps, in :func:`~slscan.fuse.canonical_order`;
   vertices and normals float32, faces int32 local ids) to ``scratch/brick_I_J_K.npz``, atomically,
   and returns only its path and counts. The scratch folder lies next to ``out``
   (``.OUT.bricks-scratch.partial-PID-XXXXXXXX``): Dask workers must see it at the same path;
2. the caller gives every piece's vertices a global id, piece after piece in sorted brick order:
   a vertex on a brick plane (a coordinate on a multiple of the brick's edge) equal as float32 to
   one of an earlier neighbouring brick's plane vertices takes its id, as :func:`slscan.fuse._stitch`
   merges them; every other vertex is new. Only plane vertices are held, and only those of the
   bricks that a later brick can still touch;
3. it writes the PLY (Open3D's layout, as :func:`slscan.fuse.write_mesh`: double x y z nx ny nz,
   ``list uchar uint vertex_indices``) to a temporary name: header, vertices piece by piece, faces
   piece by piece, then renames it to ``out``. The scratch folder is removed after success and
   after failure.

The same bricks give the same bytes, whatever ran them (one process, local helpers or Dask).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import _partial_prefix, atomic_output_file, remove_stale_leftovers

if TYPE_CHECKING:
    from slscan.fuse import Mesh

log = logging.getLogger(__name__)

SCRATCH_SUFFIX = ".bricks-scratch"
"""The scratch folder of ``out`` is ``.{out.name}.bricks-scratch.partial-PID-XXXXXXXX`` beside it: a
run's own (the random part), removed by a later run when the process that made it is gone."""

VERTEX_DTYPE = np.dtype([(n, "<f8") for n in ("x", "y", "z", "nx", "ny", "nz")])
"""One vertex record of the written PLY (as Open3D writes them for :func:`slscan.fuse.write_mesh`)."""
FACE_DTYPE = np.dtype([("n", "u1"), ("i", "<u4", (3,))])
"""One face record: the count 3, then three vertex ids."""


LOG_MAX_FACES = 5_000_000
"""A streamed mesh up to this many faces is read back to be logged to Rerun (about 0.3 GiB); a
larger one is not logged (the simplified model is)."""


@dataclass(frozen=True)
class StreamedMesh:
    """The fused mesh as written by :func:`write_streamed` (nothing of it held in memory).

    path : the binary PLY
    n_vertices, n_faces : its element counts
    plane_vertices : brick-plane vertices held at most at one time while writing (the caller's
        only memory that grows with the surface: 12 + 8 bytes each)
    merged : vertices found twice on brick planes and written once
    """

    path: Path
    n_vertices: int
    n_faces: int
    plane_vertices: int
    merged: int

    @property
    def size_bytes(self) -> int:
        return self.path.stat().st_size


def mesh_to_log(written: StreamedMesh, *, max_faces: int | None = None) -> Mesh | None:
    """The written mesh read back, for the viewer, when it has at most ``max_faces`` faces
    (default :data:`LOG_MAX_FACES`); else None."""
    from slscan.fuse import read_mesh

    if written.n_faces > (LOG_MAX_FACES if max_faces is None else max_faces) or written.n_faces == 0:
        return None
    return read_mesh(written.path)


def _load_piece(path: Path, *names: str) -> tuple[np.ndarray, ...]:
    """Arrays ``names`` of a brick's piece; one line naming it when it is missing or damaged."""
    try:
        with np.load(path) as z:
            return tuple(z[n] for n in names)
    except (OSError, KeyError, ValueError) as exc:
        raise SlscanError(f"{path}: a brick's piece could not be read back ({exc}); did its worker write "
                          "it to another disk? Workers must see the scratch folder at the same path") from None


def make_scratch(out: str | os.PathLike) -> Path:
    """A fresh scratch folder beside ``out`` for the bricks' pieces (stale ones of killed runs
    removed first). Dask workers on other machines must see it at the same path."""
    out = Path(out)
    if out.suffix.lower() != ".ply" or out.is_dir():
        raise SlscanError(f"{out}: fusion in bricks streams a binary PLY; expected a .ply file path")
    out.parent.mkdir(parents=True, exist_ok=True)
    name = Path(out.name + SCRATCH_SUFFIX)
    remove_stale_leftovers(out.parent, name=name.name)
    try:
        return Path(tempfile.mkdtemp(prefix=_partial_prefix(name), dir=out.parent))
    except OSError as exc:
        raise SlscanError(f"{out.parent}: cannot make the bricks' scratch folder ({exc.strerror})") from None


def remove_scratch(scratch: Path) -> None:
    """Remove the scratch folder and everything in it (best effort)."""
    shutil.rmtree(scratch, ignore_errors=True)


def piece_path(scratch: str | os.PathLike, index: tuple[int, int, int]) -> Path:
    """Where brick ``index`` writes its piece."""
    return Path(scratch) / f"brick_{index[0]}_{index[1]}_{index[2]}.npz"


def write_piece(scratch: str | os.PathLike, index: tuple[int, int, int], mesh: Mesh) -> Path:
    """Write a brick's mesh (already in canonical order) as its piece, atomically (a task that
    dies leaves no piece; the one run again replaces it). Returns the piece's path.

    mesh.vertices : (n, 3) float64 holding float32 values (marching cubes), mm
    """
    path = piece_path(scratch, index)
    if not path.parent.is_dir():  # a worker elsewhere that does not see the caller's folder
        raise SlscanError(f"{path.parent}: the bricks' scratch folder is not there on this worker "
                          f"(brick {index}); every worker must see the folder beside --out at the same path")
    vertices = np.ascontiguousarray(mesh.vertices, np.float32)
    if mesh.n_vertices and not np.array_equal(vertices, mesh.vertices):
        raise SlscanError(f"brick {index}: vertices are not float32 values; cannot write the piece exactly")
    normals = (np.zeros((mesh.n_vertices, 3), np.float32) if mesh.normals is None
               else np.ascontiguousarray(mesh.normals, np.float32))
    with atomic_output_file(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, vertices=vertices, normals=normals, faces=np.asarray(mesh.faces, np.int32))
    return path


def on_planes(vertices: np.ndarray, *, plane_spacing: float, voxel: float) -> np.ndarray:
    """(n,) bool: vertices (n, 3, mm) with a coordinate on a multiple of ``plane_spacing``: those
    that bricks beside a face both make (:func:`slscan.fuse._stitch` and the streamed writer)."""
    v = np.asarray(vertices, np.float64)
    ratio = v / plane_spacing
    return np.any(np.abs(ratio - np.round(ratio)) * plane_spacing < 1e-3 * voxel, axis=1)


def _keys(vertices: np.ndarray) -> np.ndarray:
    """(n,) 12-byte keys: the float32 coordinates' bytes (what ``_stitch`` compares)."""
    return np.ascontiguousarray(vertices, np.float32).view(np.dtype((np.void, 12))).ravel()


def _global_ids(pieces: Sequence[tuple[tuple[int, int, int], Path]], scratch: Path, *, plane_spacing: float,
                voxel: float) -> tuple[list[Path], list[int], int, int, int]:
    """Pass 1: every piece's local -> global vertex ids, saved as ``ID.gid.npy`` in ``scratch``.

    Returns (the id files, the first new id of each piece, the vertex count, the most plane
    vertices held at once, the vertices merged)."""
    tables: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}
    files, firsts = [], []
    next_id, held, most_held, merged = 0, 0, 0, 0
    for index, path in pieces:
        # a brick's plane vertices can only be shared with its 26 neighbours; the last of them in
        # sorted order is index + (1, 1, 1): past it, the brick's table is not needed any more
        for old in [k for k in tables if (k[0] + 1, k[1] + 1, k[2] + 1) < index]:
            held -= len(tables.pop(old)[0])
        (vertices,) = _load_piece(path, "vertices")
        gid = np.full(len(vertices), -1, np.int64)
        plane = np.flatnonzero(on_planes(vertices, plane_spacing=plane_spacing, voxel=voxel))
        keys = _keys(vertices[plane])
        for near, (table, ids) in tables.items():
            if max(abs(a - b) for a, b in zip(near, index)) > 1 or not len(table):
                continue
            open_ = gid[plane] < 0
            at = np.searchsorted(table, keys[open_])
            at = np.minimum(at, len(table) - 1)
            hit = table[at] == keys[open_]
            rows = plane[open_][hit]
            gid[rows] = ids[at[hit]]
        new = gid < 0
        firsts.append(next_id)
        gid[new] = next_id + np.arange(int(new.sum()))
        next_id += int(new.sum())
        merged += int((~new).sum())
        mine = plane[new[plane]]
        order = np.argsort(keys[new[plane]], kind="stable")
        tables[index] = (keys[new[plane]][order], gid[mine][order])
        held += len(mine)
        most_held = max(most_held, held)
        file = scratch / (path.stem + ".gid.npy")
        np.save(file, gid)
        files.append(file)
    return files, firsts, next_id, most_held, merged


def write_streamed(pieces: Sequence[tuple[tuple[int, int, int], Path, int]], out: str | os.PathLike,
                   scratch: Path, *, plane_spacing: float, voxel: float) -> StreamedMesh:
    """Write the bricks' pieces as one binary little-endian PLY at ``out`` (atomically).

    Parameters
    ----------
    pieces : (brick index, piece path, face count) in sorted brick order
    out : the PLY to write (a temporary beside it is renamed into place at the end)
    scratch : the pieces' folder (the global ids go there too)
    plane_spacing : brick edge (mm): vertices with a coordinate on a multiple of it are merged
        with the equal float32 vertex of an earlier neighbouring brick
    voxel : voxel edge (mm), for the plane test's tolerance
    """
    out = Path(out)
    t0 = time.perf_counter()
    located = [(index, path) for index, path, _ in pieces]
    gid_files, firsts, n_vertices, most_held, merged = _global_ids(located, scratch, plane_spacing=plane_spacing,
                                                                   voxel=voxel)
    n_faces = sum(n for _, _, n in pieces)
    if n_vertices >= 2**32:
        raise SlscanError(f"{out}: {n_vertices:,} vertices do not fit the PLY's uint vertex ids")
    header = ("ply\nformat binary_little_endian 1.0\ncomment slscan fuse (bricks, streamed)\n"
              f"element vertex {n_vertices}\n"
              + "".join(f"property double {name}\n" for name in VERTEX_DTYPE.names)
              + f"element face {n_faces}\nproperty list uchar uint vertex_indices\nend_header\n").encode("ascii")
    size = len(header) + n_vertices * VERTEX_DTYPE.itemsize + n_faces * FACE_DTYPE.itemsize
    with atomic_output_file(out, size=size) as tmp, open(tmp, "wb") as fh:
        fh.write(header)
        for (_, path), gid_file, first in zip(located, gid_files, firsts):
            vertices, normals = _load_piece(path, "vertices", "normals")
            new = np.load(gid_file) >= first
            records = np.empty(int(new.sum()), VERTEX_DTYPE)
            for a, name in enumerate("xyz"):
                records[name] = vertices[new, a]
                records["n" + name] = normals[new, a]
            fh.write(records.tobytes())
        for (_, path), gid_file in zip(located, gid_files):
            (faces,) = _load_piece(path, "faces")
            records = np.empty(len(faces), FACE_DTYPE)
            records["n"] = 3
            records["i"] = np.load(gid_file)[faces]
            fh.write(records.tobytes())
    log.info("%s: %d vertices (%d merged on brick planes), %d faces written from %d bricks in %.1f s",
             out, n_vertices, merged, n_faces, len(pieces), time.perf_counter() - t0)
    return StreamedMesh(out, n_vertices, n_faces, most_held, merged)
