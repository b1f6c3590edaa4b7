"""Out-of-core simplification in spatial bricks (after Lindstrom's OOCS and Cignoni et al.'s
external-memory simplification, the paper's ref. 9).

A mesh too large for one process is never loaded whole:

1. the binary PLY body is memory-mapped; vertices are read in chunks for the bounding box,
   faces in chunks and each face is assigned to the brick holding its centroid, appended
   (global vertex ids, int32) to that brick's file on disk; per vertex the smallest and the
   largest brick using it are kept (memory-mapped too): a vertex used by two bricks is a
   *border* vertex;
2. each brick is one :class:`~slscan.executor.Executor` task: it reads its faces and its
   vertices (from the memory map), simplifies them to its share of the target with
   fast-simplification and ``preserve_border`` — the brick's open boundary, which holds every
   border vertex, is not touched, so border vertices keep their exact coordinates — and
   writes the result with the global id of each kept border vertex;
3. the bricks are stitched on those global ids (no coordinate matching) and a last pass over
   the whole stitched mesh (about the target's size: it fits) reaches the target, this time
   keeping only the input's own open boundaries.

The peak memory of a brick task is estimated from its face count before it starts; one over
``max_memory`` is refused with one line naming the brick and the cap.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import resource
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from typing import TYPE_CHECKING

from slscan.errors import SlscanError
from slscan.units import MEMORY_HELP, parse_memory

if TYPE_CHECKING:
    from slscan.fuse import Mesh

log = logging.getLogger(__name__)

TASK_BYTES_PER_FACE = 800
TASK_BASE_BYTES = 128 << 20
"""Peak memory of one brick task: ``TASK_BASE_BYTES`` (the process) plus this per input face
(faces, vertices, fast-simplification's arrays, the memory-mapped pages read), checked against
``max_memory`` before a task starts. Measured with ``benchmarks/simplify_bricks.py``: 417 B/face
with a 1.75M-face fused mesh as one brick, about 800 B/face with 1.5M-face bricks of a 12M-face
mesh (1.2 GiB; there the caller's own stitching memory is in the figure too)."""

INCORE_BYTES_PER_FACE = 500
INCORE_BASE_BYTES = 256 << 20
"""Peak memory of the in-core path (:func:`slscan.simplify.simplify_file`: slscan's PLY reader,
then fast-simplification; Open3D imported): 822 MiB for 1.75M faces, measured the same way."""

CHUNK = 1 << 20
"""Vertices or faces read from the memory map at a time."""

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass(frozen=True)
class PlyLayout:
    """Where a binary PLY triangle mesh's vertex and face records lie in its file.

    vertex_dtype : one record per vertex (must hold x, y, z)
    face_dtype : one record per face: a uchar/int count (always 3) and 3 indices
    """

    path: Path
    n_vertices: int
    n_faces: int
    vertex_offset: int
    vertex_dtype: np.dtype
    face_offset: int
    face_dtype: np.dtype

    def vertices(self) -> np.memmap:
        """(n_vertices,) structured records, memory-mapped (nothing read yet)."""
        return np.memmap(self.path, self.vertex_dtype, "r", self.vertex_offset, (self.n_vertices,))

    def faces(self) -> np.memmap:
        """(n_faces,) records with fields ``n`` (count) and ``i`` (3 indices), memory-mapped."""
        return np.memmap(self.path, self.face_dtype, "r", self.face_offset, (self.n_faces,))


def ply_layout(path: str | os.PathLike) -> PlyLayout:
    """Read only the header of a binary PLY triangle mesh; SlscanError naming the file otherwise.

    Supported: ``binary_little_endian`` or ``big_endian``; a ``vertex`` element of scalar
    properties with x, y, z; then a ``face`` element whose only property is a list with a
    1-byte count and 4-byte indices, every face a triangle (checked while streaming).
    """
    path = Path(path)
    if not path.is_file():
        raise SlscanError(f"{path}: mesh file not found")
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise SlscanError(f"{path}: not a PLY file (expected a binary PLY mesh for brick simplification)")
    body = head.find(b"\n", end) + 1
    order, elements = None, []
    for line in head[:end].decode("ascii", "replace").splitlines()[1:]:
        w = line.split()
        if not w:
            continue
        if w[0] == "format":
            order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(w[1] if len(w) > 1 else "")
            if order is None:
                raise SlscanError(f"{path}: PLY format {' '.join(w[1:])!r}: expected binary_little_endian "
                                  "or binary_big_endian for brick simplification")
        elif w[0] == "element" and len(w) == 3 and w[2].isdigit():
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements:
            elements[-1][2].append(w[1:])
    names = [e[0] for e in elements]
    if order is None or names[:2] != ["vertex", "face"]:
        raise SlscanError(f"{path}: expected a binary PLY with a vertex then a face element, got {names}")
    (_, nv, vprops), (_, nf, fprops) = elements[:2]
    try:
        vdt = np.dtype([(p[1], order + _TYPES[p[0]]) for p in vprops])
    except (KeyError, IndexError):
        raise SlscanError(f"{path}: vertex properties {vprops}: expected scalar PLY types") from None
    if not {"x", "y", "z"} <= set(vdt.names or ()):
        raise SlscanError(f"{path}: vertex element without x, y, z properties")
    if (len(fprops) != 1 or fprops[0][:1] != ["list"] or len(fprops[0]) != 4
            or _TYPES.get(fprops[0][1]) not in ("u1", "i1") or _TYPES.get(fprops[0][2]) not in ("i4", "u4")):
        raise SlscanError(f"{path}: face properties {fprops}: expected only 'list uchar int vertex_indices'")
    fdt = np.dtype([("n", "u1"), ("i", order + _TYPES[fprops[0][2]], (3,))])
    face_offset = body + nv * vdt.itemsize
    if path.stat().st_size < face_offset + nf * fdt.itemsize:
        raise SlscanError(f"{path}: truncated: {nv} vertices and {nf} triangles need "
                          f"{face_offset + nf * fdt.itemsize} bytes, the file has {path.stat().st_size}")
    return PlyLayout(path, nv, nf, body, vdt, face_offset, fdt)


def _xyz(records: np.ndarray) -> np.ndarray:
    return np.stack([records["x"], records["y"], records["z"]], 1).astype(np.float64)


@dataclass(frozen=True)
class BrickTask:
    """One brick's work (picklable: it crosses to helper processes or Dask workers)."""

    index: int
    layout: PlyLayout
    faces_file: Path
    shared_file: Path
    out_file: Path
    target: int
    aggressiveness: float


@dataclass(frozen=True)
class BrickResult:
    """faces_in, faces_out : the brick's triangles before and after; peak_rss : the task's
    peak resident memory in bytes (Linux VmHWM, reset at the task's start); seconds : wall."""

    index: int
    faces_in: int
    faces_out: int
    peak_rss: int
    seconds: float


@dataclass(frozen=True)
class BrickReport:
    """What :func:`simplify_bricks` did.

    mode : "bricks" or "in-core"
    grid : bricks per axis; bricks : the non-empty ones' results, in brick order
    faces_in, faces_stitched, faces_out : input, after the bricks, after the last pass
    final_peak_rss : this process's peak RSS in bytes at the end (whole run)
    """

    mode: str
    faces_in: int
    faces_stitched: int
    faces_out: int
    grid: tuple[int, int, int]
    bricks: tuple[BrickResult, ...]
    final_peak_rss: int
    seconds: float


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def _peak_rss() -> int:
    """This process's peak RSS in bytes (VmHWM; ru_maxrss where /proc is missing)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _simplify_brick(task: BrickTask) -> BrickResult:
    from slscan.simplify import _fast_pass

    t0 = time.perf_counter()
    _reset_peak()
    for path, what in ((task.layout.path, "the mesh"), (task.faces_file, "brick files in the scratch folder"),
                       (task.shared_file, "brick files in the scratch folder")):
        if not Path(path).is_file():
            import socket

            raise SlscanError(f"{path}: not found on worker {socket.gethostname()} (brick {task.index}); the "
                              f"workers need {what} at the same path (the scratch folder is made next to --out)")
    faces = np.fromfile(task.faces_file, np.int32).reshape(-1, 3)
    used, local = np.unique(faces, return_inverse=True)
    local = local.reshape(-1, 3).astype(np.int32)
    del faces
    verts = _xyz(task.layout.vertices()[used])
    shared = np.memmap(task.shared_file, np.bool_, "r")[used]
    # The locked open boundary (brick borders, the input's own boundaries) keeps its vertices, about
    # one face each: without them on top of the brick's share, a brick with a long border and few
    # faces would have its interior collapsed to slivers (1.3 mm off a 50 mm sphere's cap, 0.2 without).
    locked = _boundary_vertex_count(local)
    v, f = _fast_pass(verts, local, task.target + locked, True, task.aggressiveness)
    # Border vertices were kept exactly: find each kept one's global id by its coordinates.
    # Marching cubes leaves a few vertices at one position (the fused statue: 182 of 11.6M);
    # every output vertex at a border vertex's position takes the global id of the first
    # border vertex there (the smallest id, the same in the bricks on both sides), so such
    # twins are welded, and every border position must be found.
    gid = np.full(len(v), -1, np.int64)
    if shared.any():
        border_ids = used[np.flatnonzero(shared)]
        keys = np.ascontiguousarray(verts[shared]).view(np.dtype((np.void, 24))).ravel()
        unique_keys, first = np.unique(keys, return_index=True)
        out_keys = np.ascontiguousarray(v).view(np.dtype((np.void, 24))).ravel()
        at = np.clip(np.searchsorted(unique_keys, out_keys), 0, len(unique_keys) - 1)
        hit = unique_keys[at] == out_keys
        gid[hit] = border_ids[first[at[hit]]]
        found = len(np.unique(at[hit]))
        if found != len(unique_keys):
            raise SlscanError(f"brick {task.index}: {len(unique_keys)} border positions, "
                              f"{found} kept: the simplifier moved a locked vertex")
    tmp = task.out_file.with_suffix(".tmp.npz")
    np.savez(tmp, vertices=v, faces=f.astype(np.int32), gid=gid)
    os.replace(tmp, task.out_file)
    return BrickResult(task.index, len(local), len(f), _peak_rss(), time.perf_counter() - t0)


def _boundary_vertex_count(faces: np.ndarray) -> int:
    """Vertices on the open boundary of ``faces`` (m, 3): those of edges used by one triangle."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1).astype(np.int64)
    _, inverse, count = np.unique(e[:, 0] * (int(e.max(initial=0)) + 1) + e[:, 1], return_inverse=True,
                                  return_counts=True)
    return len(np.unique(e[count[inverse.ravel()] == 1]))


def bricks_for(n_faces: int, max_memory: int) -> int:
    """How many bricks to ask for when only ``max_memory`` (bytes per task) is given: enough
    that an average brick's estimate is a quarter of the cap (a bounding-box grid over a
    surface fills its cells unevenly), at least the default 8, at most 4096."""
    per_brick = max(1.0, (max_memory - TASK_BASE_BYTES) / TASK_BYTES_PER_FACE)
    return int(min(4096, max(8, math.ceil(4 * n_faces / per_brick))))


def _grid(lo: np.ndarray, hi: np.ndarray, brick_mm: float | None, bricks: int | None) -> tuple[np.ndarray, float]:
    extent = np.maximum(hi - lo, 1e-9)
    if brick_mm is None:
        n = max(1, int(bricks or 8))
        # cells of edge e with prod(ceil(extent / e)) about n: start from the volume's cube root
        e = float(np.prod(extent) / n) ** (1 / 3)
        while np.prod(np.ceil(extent / e)) > n and e < extent.max():
            e *= 1.01
        brick_mm = e
    if not brick_mm > 0:
        raise SlscanError(f"--brick {brick_mm}: expected a positive brick edge in mm")
    dims = np.maximum(1, np.ceil(extent / brick_mm)).astype(np.int64)
    return dims, float(brick_mm)


def simplify_bricks(
    mesh_path: str | os.PathLike,
    out: str | os.PathLike,
    faces: int,
    *,
    brick_mm: float | None = None,
    bricks: int | None = None,
    executor=None,
    max_memory: int | None = None,
    aggressiveness: float = 6.0,
    workdir: str | os.PathLike | None = None,
) -> BrickReport:
    """Simplify the binary PLY ``mesh_path`` to about ``faces`` triangles in bricks; write ``out``.

    Parameters
    ----------
    mesh_path : binary PLY triangle mesh (vertices in mm), never loaded whole
    out : the simplified mesh (PLY, written atomically, with vertex normals)
    faces : target face count
    brick_mm : brick edge in mm; or ``bricks``: about this many bricks (default 8, or with
        ``max_memory`` as many as :func:`bricks_for` says)
    executor : :class:`slscan.executor.Executor` running the brick tasks (default: this process)
    max_memory : bytes one brick task may use (estimated before it starts); None: no cap
    workdir : scratch folder for the brick files (default: a temporary one next to ``out``)

    Raises
    ------
    SlscanError
        A file that is not a binary triangle PLY, a bad index, a target below 4, or a brick
        whose estimated memory is over ``max_memory`` (one line naming the brick and the cap).
    """
    from slscan.executor import Executor
    from slscan.fsio import human_size
    from slscan.fuse import Mesh, write_mesh
    from slscan.meshes import vertex_normals
    from slscan.simplify import _fast_pass

    t0 = time.perf_counter()
    target = int(faces)
    if target < 4:
        raise SlscanError(f"target face count must be at least 4, got {faces}")
    layout = ply_layout(mesh_path)
    out = Path(out)
    executor = executor or Executor(workers=1)
    scratch = Path(tempfile.mkdtemp(prefix=".bricks-", dir=workdir or out.parent))
    try:
        # 1. bounding box, streamed
        vrec = layout.vertices()
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for s in range(0, layout.n_vertices, CHUNK):
            xyz = _xyz(vrec[s:s + CHUNK])
            if not np.isfinite(xyz).all():
                raise SlscanError(f"{layout.path}: vertices {s}..{s + len(xyz) - 1} hold NaN or inf")
            lo, hi = np.minimum(lo, xyz.min(0)), np.maximum(hi, xyz.max(0))
        if brick_mm is None and bricks is None and max_memory is not None:
            bricks = bricks_for(layout.n_faces, max_memory)
        dims, edge = _grid(lo, hi, brick_mm, bricks)
        nb = int(np.prod(dims))
        if nb > 4096:
            raise SlscanError(f"--brick {edge:g} mm makes {nb} bricks (at most 4096): use a larger brick")
        # 2. faces to bricks, streamed; smallest and largest brick using each vertex
        bmin = np.lib.format.open_memmap(scratch / "bmin.npy", "w+", np.int16, (layout.n_vertices,))
        bmax = np.lib.format.open_memmap(scratch / "bmax.npy", "w+", np.int16, (layout.n_vertices,))
        bmin[:] = np.iinfo(np.int16).max
        bmax[:] = -1
        counts = np.zeros(nb, np.int64)
        frec = layout.faces()
        handles = {}
        try:
            for s in range(0, layout.n_faces, CHUNK):
                rec = frec[s:s + CHUNK]
                if (rec["n"] != 3).any():
                    bad = s + int(np.argmax(rec["n"] != 3))
                    raise SlscanError(f"{layout.path}: face {bad} has {rec['n'][bad - s]} vertices; "
                                      "expected triangles")
                idx = rec["i"].astype(np.int64)
                if idx.size and (idx.min() < 0 or idx.max() >= layout.n_vertices):
                    raise SlscanError(f"{layout.path}: faces {s}..{s + len(idx) - 1} refer to vertices outside "
                                      f"0..{layout.n_vertices - 1}")
                centre = _xyz(vrec[idx.ravel()]).reshape(-1, 3, 3).mean(1)
                cell = np.minimum(((centre - lo) / edge).astype(np.int64), dims - 1)
                b = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
                np.minimum.at(bmin, idx.ravel(), np.repeat(b, 3).astype(np.int16))
                np.maximum.at(bmax, idx.ravel(), np.repeat(b, 3).astype(np.int16))
                order = np.argsort(b, kind="stable")
                bs, starts = np.unique(b[order], return_index=True)
                for k, a, z in zip(bs, starts, [*starts[1:], len(order)]):
                    if k not in handles:
                        handles[k] = open(scratch / f"brick{k:04d}.faces", "wb")
                    idx[order[a:z]].astype(np.int32).tofile(handles[k])
                    counts[k] += z - a
        finally:
            for h in handles.values():
                h.close()
        shared_raw = scratch / "shared.bool"
        shared = np.memmap(shared_raw, np.bool_, "w+", shape=(max(1, layout.n_vertices),))
        for s in range(0, layout.n_vertices, CHUNK):
            shared[s:s + CHUNK] = (bmax[s:s + CHUNK] >= 0) & (bmin[s:s + CHUNK] != bmax[s:s + CHUNK])
        shared.flush()
        del bmin, bmax, shared
        # 3. one task per non-empty brick, checked against the cap first
        tasks = []
        for k in np.flatnonzero(counts):
            need = TASK_BASE_BYTES + int(counts[k]) * TASK_BYTES_PER_FACE
            if max_memory is not None and need > max_memory:
                raise SlscanError(
                    f"{layout.path}: brick {k} ({int(counts[k]):,} faces, {edge:g} mm) needs about "
                    f"{human_size(need)} > --max-memory {human_size(max_memory)}; use a smaller --brick")
            share = max(4, round(target * counts[k] / layout.n_faces))
            tasks.append(BrickTask(int(k), layout, scratch / f"brick{k:04d}.faces", shared_raw,
                                   scratch / f"brick{k:04d}.npz", share, aggressiveness))
        log.info("%s: %d faces in %d bricks of %g mm (grid %s)", layout.path, layout.n_faces, len(tasks),
                 edge, "x".join(map(str, dims)))
        results = _run_bricks(executor, tasks)
        # 4. stitch on global ids
        parts_v, parts_f, parts_g, offset = [], [], [], 0
        for task in tasks:
            with np.load(task.out_file) as z:
                parts_v.append(z["vertices"])
                parts_f.append(z["faces"].astype(np.int64) + offset)
                parts_g.append(z["gid"])
            offset += len(parts_v[-1])
            task.out_file.unlink()
        all_v = np.concatenate(parts_v) if parts_v else np.zeros((0, 3))
        all_g = np.concatenate(parts_g) if parts_g else np.zeros(0, np.int64)
        tri = np.concatenate(parts_f) if parts_f else np.zeros((0, 3), np.int64)
        del parts_v, parts_f, parts_g
        fresh = all_g < 0
        n_fresh = int(fresh.sum())
        _, first, inverse = np.unique(all_g[~fresh], return_index=True, return_inverse=True)
        new = np.empty(len(all_v), np.int64)
        new[fresh] = np.arange(n_fresh)
        new[~fresh] = n_fresh + inverse.ravel()
        vertices = np.concatenate([all_v[fresh], all_v[~fresh][first]])
        tri = new[tri]
        del all_v, all_g, new
        stitched = len(tri)
        # 5. the last pass over the whole stitched mesh (about the target's size)
        v, f = _fast_pass(vertices, tri.astype(np.int32), target, True, aggressiveness)
        f = np.asarray(f, np.int64)
        write_mesh(Mesh(v, f, vertex_normals(v, f).astype(np.float32)), out)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return BrickReport("bricks", layout.n_faces, stitched, len(f), tuple(int(d) for d in dims), results,
                       _peak_rss(), time.perf_counter() - t0)


def _run_bricks(executor, tasks: list[BrickTask]) -> tuple[BrickResult, ...]:
    """The brick tasks on ``executor``, results in brick order. A local helper process that dies
    (killed, out of memory) loses only the bricks not yet back: they run once more, on fresh
    helpers (each writes its file under a temporary name, so a half-written one is never read).
    A second death is the executor's one line ("a worker process died ...")."""
    from slscan.executor import map_retrying

    done = map_retrying(executor, _simplify_brick, tasks, key=lambda t: t.index, noun="brick")
    return tuple(done[t.index] for t in tasks)


def incore_memory(mesh_path: str | os.PathLike) -> int:
    """Estimated peak bytes of simplifying ``mesh_path`` in one process (from its header)."""
    return INCORE_BASE_BYTES + ply_layout(mesh_path).n_faces * INCORE_BYTES_PER_FACE


def surface_distance(a: Mesh, b: Mesh) -> dict[str, float]:
    """Point-to-surface distances in mm, both ways, from each mesh's vertices to the other's
    triangles (Open3D RaycastingScene): keys ``mean``, ``p95``, ``max`` (of both directions
    pooled) and ``a_to_b_mean``, ``b_to_a_mean``."""
    import open3d as o3d

    def one(points: np.ndarray, mesh: Mesh) -> np.ndarray:
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
        return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()

    ab, ba = one(a.vertices, b), one(b.vertices, a)
    both = np.concatenate([ab, ba])
    return {"mean": float(both.mean()), "p95": float(np.percentile(both, 95)), "max": float(both.max()),
            "a_to_b_mean": float(ab.mean()), "b_to_a_mean": float(ba.mean())}


def boundary_edges(faces: np.ndarray) -> int:
    """Edges used by exactly one triangle of ``faces`` (m, 3)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, c = np.unique(e, axis=0, return_counts=True)
    return int((c == 1).sum())


__all__: Sequence[str] = ("simplify_bricks", "choose_path", "BrickReport", "BrickResult", "ply_layout",
                          "parse_memory",
                          "incore_memory", "surface_distance", "boundary_edges")


INCORE_FACE_LIMIT = 10_000_000
"""``slscan simplify`` without ``--max-memory``, ``--brick`` or ``--bricks`` simplifies meshes of
up to this many faces in one process (about 5 GiB, see ``INCORE_BYTES_PER_FACE``), larger ones in bricks."""


def extend_simplify_parser(p) -> None:
    """Give ``slscan simplify`` (``p``, made by :mod:`slscan.register.command`) its out-of-core
    options, and route it: in bricks with ``--brick``/``--bricks`` or when the mesh is too large
    for one process, else in-core (the parser's own command)."""
    from slscan.executor import add_executor_arguments

    p.description += (
        f" Meshes above {INCORE_FACE_LIMIT:,} faces (or whose in-core estimate exceeds --max-memory), or any "
        "with --brick/--bricks, are simplified out of core: the binary PLY is streamed into spatial bricks on "
        "disk, each brick simplified as a task (--workers, --scheduler) with its border locked, then the "
        "bricks are stitched and simplified once more across the borders.")
    p.epilog += ("\n  slscan simplify big.ply --out small.ply --faces 1000000 --brick 60 --workers 2 "
                 "--max-memory 4GiB")
    g = p.add_argument_group("out of core", "simplify in bricks (binary PLY input, --method fast)")
    g.add_argument("--brick", type=float, metavar="MM", help="simplify in bricks of this edge (mm)")
    g.add_argument("--bricks", type=int, metavar="N", help="simplify in about N bricks")
    g.add_argument("--max-memory", metavar="SIZE", help="memory one process may use: in-core when "
                   f"the estimate fits, else bricks; a brick over it is refused; {MEMORY_HELP}")
    g.add_argument("--against", type=Path, metavar="MESH", help="also report the surface distance (both ways) "
                   "to this mesh, e.g. the in-core result")
    add_executor_arguments(p)
    p.set_defaults(func=functools.partial(_cmd_simplify, p.get_default("func")))


def _cmd_simplify(incore, args) -> int:
    from slscan.executor import executor_from_args
    from slscan.fsio import human_size
    from slscan.fuse import read_mesh
    from slscan.progress import console

    if args.out.exists() and not args.overwrite:
        raise SlscanError(f"{args.out}: exists (pass --overwrite to replace it)")
    cap = parse_memory(args.max_memory) if args.max_memory else None
    in_bricks, why = choose_path(args.mesh, brick_mm=args.brick, bricks=args.bricks, max_memory=cap)
    if not in_bricks:
        console().print(f"simplify: in-core ({why})", highlight=False, soft_wrap=True)
        rc = incore(args)
    else:
        if args.method != "fast" or args.free_boundary:
            raise SlscanError("simplifying in bricks: only --method fast, without --free-boundary "
                              "(the brick borders must stay locked)")
        from slscan.register.meshlab import write_mesh_project

        rep = simplify_bricks(args.mesh, args.out, args.faces, brick_mm=args.brick, bricks=args.bricks,
                              executor=executor_from_args(args), max_memory=cap)
        write_mesh_project(args.out)
        peak = max((b.peak_rss for b in rep.bricks), default=0)
        console().print(
            f"simplify: bricks ({len(rep.bricks)} of grid {'x'.join(map(str, rep.grid))}): {rep.faces_in:,} -> "
            f"{rep.faces_stitched:,} stitched -> {rep.faces_out:,} faces in {rep.seconds:.1f} s, task peak "
            f"{human_size(peak)}, this process {human_size(rep.final_peak_rss)}; wrote {args.out}",
            highlight=False, soft_wrap=True)
        rc = 0
    if args.against:
        d = surface_distance(read_mesh(args.out), read_mesh(args.against))
        console().print(f"distance to {args.against}: mean {d['mean']:.4f} mm, p95 {d['p95']:.4f} mm, "
                        f"max {d['max']:.4f} mm (both ways)", highlight=False, soft_wrap=True)
    return rc


def choose_path(mesh_path: str | os.PathLike, *, brick_mm: float | None = None, bricks: int | None = None,
                max_memory: int | None = None) -> tuple[bool, str]:
    """Whether ``slscan simplify`` (and a recipe's simplify stage) works in bricks, and why.

    In bricks when ``brick_mm`` or ``bricks`` is given; else in-core when the mesh is not a binary
    PLY, or when its in-core estimate fits ``max_memory`` (bytes), or, without a cap, when it has
    at most :data:`INCORE_FACE_LIMIT` faces; in bricks otherwise. Reads only the PLY header.
    """
    from slscan.fsio import human_size

    if brick_mm is not None or bricks is not None:
        return True, "--brick" if brick_mm is not None else "--bricks"
    path = Path(mesh_path)
    if path.suffix.lower() != ".ply" or not _binary_ply(path):
        return False, "not a binary PLY"
    n_faces = ply_layout(path).n_faces
    estimate = INCORE_BASE_BYTES + n_faces * INCORE_BYTES_PER_FACE
    if max_memory is not None:
        if estimate <= max_memory:
            return False, f"estimate {human_size(estimate)} within --max-memory"
        return True, f"in-core estimate {human_size(estimate)} > --max-memory {human_size(max_memory)}"
    if n_faces <= INCORE_FACE_LIMIT:
        return False, f"{n_faces:,} faces, at most {INCORE_FACE_LIMIT:,}"
    return True, f"{n_faces:,} faces, more than {INCORE_FACE_LIMIT:,}"


def _binary_ply(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return False
    return b"format binary_" in head
