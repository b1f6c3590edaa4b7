"""Range maps: mesh one view's triangulated stripe samples into a range surface, and PLY I/O.

The samples of a view lie on a regular grid, camera rows by projector stripes, so the
mesh is the grid's quads split in two, with the triangles that bridge depth
discontinuities or are seen at grazing angles left out (after [1]_ and [2]_). The PLY
files open directly in MeshLab, with per-vertex normal, colour and quality.

References
----------
.. [1] Rocchini, Cignoni, Montani, Pingi, Scopigno, "A low cost 3D scanner based on
   structured light", Computer Graphics Forum 20(3), Eurographics 2001.
.. [2] Turk, Levoy, "Zippered polygon meshes from range images", SIGGRAPH 1994 (range
   grid triangulation with edge-length and grazing-angle tests).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError
from slscan.meshes import check_face_indices, check_finite_vertices
from slscan.ply import read_ply_elements, write_triangle_ply
from slscan.rig import PinholeModel

log = logging.getLogger(__name__)

MAX_EDGE_FACTOR = 4.0
"""Default cut of :func:`build_range_map`: edges longer than this many times the expected
spacing. 8 covers 2 points more of a view's lit pixels, every added face within 1 mm of
the true surface, but the 8 views fused from such maps are 27 % further from the truth
(mean 0.047 -> 0.060 mm; ``benchmarks/meshing.py``)."""

MAX_VIEW_ANGLE_DEG = 80.0
"""Default: faces seen more obliquely than this are dropped."""

MAX_GAP_COLUMNS = 6.0
"""Default bridge of :func:`build_range_map`: missing stripes are bridged while a face's
corners are at most this many projector columns apart: 2 missing hybrid lines (as before
this was counted in columns) or 5 missing Gray-code edges (2 before). Gray code, whose
finest edges drop out first on steep surfaces, then covers 0.80 of the figurine's lit
pixels instead of 0.70, and 8 fused views 0.706 of its surface instead of 0.683 at a
mean error of 0.0375 instead of 0.0372 mm (``benchmarks/meshing.py``)."""

CONTINUITY_WEIGHT = (0.25, 0.5, 1.0)
"""Quality factor by :meth:`StripeSamples.continuity` (0, 1 or 2 neighbouring rows): line
ends are 2-3x less accurate than the line inside them (see there), so fusion trusts them
less."""

PLY_VERTEX_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("nx", "<f4"),
        ("ny", "<f4"),
        ("nz", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("quality", "<f4"),
        ("row", "<i4"),
        ("stripe", "<i4"),
    ]
)
"""Vertex record of the range-map PLY files this module writes."""


@dataclass(frozen=True)
class RangeMap:
    """One view's range surface, in the rig (camera) frame.

    vertices : (n, 3) float64, mm
    faces : (m, 3) int32 vertex indices, counter-clockwise seen from the camera
    normals : (n, 3) float32 unit vertex normals, pointing towards the camera
    colors : (n, 3) uint8 RGB from the white image
    quality : (n,) float32 in [0, 1]: cos(viewing angle) x the sample's contrast x its
        line continuity (``CONTINUITY_WEIGHT``: 1 inside a line, 0.5 at a line's end, 0.25
        for a lone sample); 0 for saturated samples (and for vertices no face uses, when
        they are kept)
    row : (n,) int32 camera row of each vertex's sample
    stripe : (n,) int32 stripe index of each vertex's sample
    view : the view's name
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    quality: np.ndarray
    row: np.ndarray
    stripe: np.ndarray
    view: str = ""

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)


# --- meshing ----------------------------------------------------------------------------------


def _white_rgb(white_image: np.ndarray, rows: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Bilinear (along x; rows are whole pixels) RGB uint8 of ``white_image`` at samples."""
    img = np.asarray(white_image)
    if img.dtype == np.uint8:
        scale = 1.0
    elif img.dtype == np.uint16:
        scale = 255.0 / 65535.0
    elif np.issubdtype(img.dtype, np.floating):
        scale = 255.0
    else:
        raise SlscanError(f"white image: pixels are {img.dtype}; expected uint8, uint16 or float")
    if img.ndim == 2:
        img = img[..., None]
    h, w = img.shape[:2]
    x0 = np.clip(np.floor(xs).astype(np.int64), 0, w - 1)
    x1 = np.minimum(x0 + 1, w - 1)
    f = np.clip(xs - x0, 0.0, 1.0)[:, None]
    r = np.clip(rows, 0, h - 1)
    value = img[r, x0].astype(np.float64) * (1 - f) + img[r, x1].astype(np.float64) * f
    value = np.clip(np.rint(value * scale), 0, 255).astype(np.uint8)
    if value.shape[1] == 1:
        value = np.repeat(value, 3, axis=1)
    return value[:, :3]


def _grid_lookup(keys: np.ndarray, usable: np.ndarray):
    """A function mapping grid keys to the index of the usable sample there (-1: none)."""
    order = np.flatnonzero(usable)
    order = order[np.argsort(keys[order], kind="stable")]
    sorted_keys = keys[order]

    def find(query: np.ndarray) -> np.ndarray:
        if len(order) == 0:
            return np.full(len(query), -1, np.int64)
        pos = np.minimum(np.searchsorted(sorted_keys, query), len(order) - 1)
        return np.where(sorted_keys[pos] == query, order[pos], -1)

    return find


def _median_ratio(points: np.ndarray, depth: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Median of edge length over depth for the neighbour pairs (a, b)."""
    if len(a) == 0:
        return math.nan
    length = np.linalg.norm(points[a] - points[b], axis=1)
    return float(np.median(length / (0.5 * (depth[a] + depth[b]))))


def build_range_map(
    samples: StripeSamples,
    points: np.ndarray,
    *,
    white_image: np.ndarray,
    camera: PinholeModel,
    view: str = "",
    max_edge_factor: float = MAX_EDGE_FACTOR,
    max_view_angle_deg: float = MAX_VIEW_ANGLE_DEG,
    max_gap_columns: float = MAX_GAP_COLUMNS,
    keep_unreferenced: bool = False,
    continuity_weight: Sequence[float] = CONTINUITY_WEIGHT,
) -> RangeMap:
    """Mesh triangulated samples on their (camera row x stripe) grid into a range map.

    Consecutive camera rows ``r, r + 1`` are zipped together (and, for samples found along
    camera columns, consecutive columns, in a grid of their own): walking both rows' samples
    in stripe order, each new sample makes a triangle with the latest sample of its own
    row and of the other row (a full grid gives two triangles per quad). Stripes missing
    in one row are bridged when the triangle's corners are at most ``max_gap_columns``
    projector columns apart (a fine line or edge lost where the surface is steep or the
    paint dark leaves no hole; in projector columns so that the limit means the same for
    hybrid lines, two columns apart, and Gray-code edges, one apart). A triangle is
    dropped when

    - an edge is longer than ``max_edge_factor`` times the expected spacing there: the
      median edge length over depth of the view's row-direction (and, separately,
      stripe-direction) neighbours, times the edge's depth (diagonals: the hypotenuse of
      the two), so the test adapts to the sampling and to distance; or
    - its normal is more than ``max_view_angle_deg`` from the viewing ray (grazing).

    Samples whose point is NaN, and samples that share their (row, stripe) with another
    (a row crossing one light plane twice), take part in no face.

    Parameters
    ----------
    samples : StripeSamples, k samples
    points : (k, 3) float64, mm, rig frame: the samples triangulated (NaN allowed)
    white_image : (h, w) or (h, w, 3) uint8/uint16 capture under full white, for colour
    camera : the camera that saw the samples (at the rig origin); its size must match
        the white image
    view : name stored with the map
    max_edge_factor : float
        Edges longer than this many times the expected spacing cut the mesh.
    max_view_angle_deg : float, degrees
        Faces seen more obliquely than this are dropped.
    max_gap_columns : float
        Largest step in projector column between a triangle's corners (hybrid lines are 2
        columns apart, Gray-code edges 1).
    keep_unreferenced : bool
        Keep vertices that no face uses (with the viewing direction as normal and
        quality 0); by default they are removed, so the map is a surface (the samples
        themselves stay available from ``samples``).
    continuity_weight : 3 floats
        Quality factor of samples whose line goes on in 0, 1 or 2 of the neighbouring
        rows (:meth:`StripeSamples.continuity`); ``(1, 1, 1)`` ignores continuity.

    Returns
    -------
    RangeMap
    """
    k = len(samples)
    points = np.asarray(points, dtype=np.float64)
    if points.shape != (k, 3):
        raise SlscanError(
            f"range map: expected ({k}, 3) points for {k} samples, got shape {points.shape}"
        )
    white = np.asarray(white_image)
    if white.shape[:2] != (camera.height, camera.width):
        raise SlscanError(
            f"range map: white image is {white.shape[1]}x{white.shape[0]}, the camera is "
            f"{camera.width}x{camera.height}"
        )
    if max_edge_factor <= 0:
        raise SlscanError(f"max_edge_factor must be positive, got {max_edge_factor}")
    if not max_gap_columns > 0:
        raise SlscanError(f"max_gap_columns must be positive, got {max_gap_columns}")
    rows = np.asarray(samples.row, np.int64)
    # the grid's lines: camera rows, and for samples found along camera columns, those
    # columns (kept apart from the rows: the two kinds are meshed separately)
    lines, _ = samples.lines()
    stripes = np.asarray(samples.stripe, np.int64)
    finite = np.all(np.isfinite(points), axis=1)

    faces = np.zeros((0, 3), np.int64)
    if finite.any():
        s_min = int(stripes[finite].min())
        span = int(stripes[finite].max()) - s_min + 2
        keys = (lines - int(lines[finite].min()) + 1) * span + (stripes - s_min)
        keys[~finite] = -1
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        unique = finite & (counts[inverse.reshape(-1)] == 1)
        find = _grid_lookup(keys, unique)
        a = np.flatnonzero(unique)
        b, c = find(keys[a] + 1), find(keys[a] + span)  # (r, s + 1), (r + 1, s)
        depth = np.linalg.norm(points, axis=1)
        m_stripe = _median_ratio(points, depth, a[b >= 0], b[b >= 0])
        m_row = _median_ratio(points, depth, a[c >= 0], c[c >= 0])
        columns = np.asarray(samples.projector_column, np.float64)
        tri = _zipper(np.flatnonzero(unique), lines, stripes, columns, max_gap_columns)
        faces = _filter_faces(
            tri, points, depth, lines, stripes, m_row, m_stripe, max_edge_factor, max_view_angle_deg
        )

    vertex_normals = _vertex_normals(points, faces, finite)
    referenced = np.zeros(k, bool)
    referenced[faces.reshape(-1)] = True
    keep = finite & (referenced | keep_unreferenced)
    view_dir = np.zeros_like(points)
    view_dir[finite] = points[finite] / np.linalg.norm(points[finite], axis=1, keepdims=True)
    cos_view = np.clip(-np.einsum("ij,ij->i", vertex_normals, view_dir), 0.0, 1.0)
    quality = cos_view * np.clip(np.asarray(samples.contrast, np.float64), 0.0, 1.0)
    weight = np.asarray(continuity_weight, np.float64)
    if weight.shape != (3,):
        raise SlscanError(f"continuity_weight: expected 3 factors (0, 1, 2 neighbours), got {continuity_weight!r}")
    quality *= weight[samples.continuity()]
    quality[np.asarray(samples.saturated, bool) | ~referenced] = 0.0

    new_index = np.full(k, -1, np.int64)
    new_index[keep] = np.arange(int(keep.sum()))
    kept_faces = new_index[faces].astype(np.int32)
    colors = _white_rgb(white, rows[keep], np.asarray(samples.x, np.float64)[keep])
    if samples.along_columns is not None and np.any(samples.along_columns[keep]):
        # samples found along columns: bilinear along y on their whole camera column
        down = np.asarray(samples.along_columns, bool)[keep]
        colors[down] = _white_rgb(np.swapaxes(white, 0, 1),
                                  np.rint(np.asarray(samples.x)[keep][down]).astype(np.int64),
                                  samples.camera_y[keep][down])
    log.debug(
        "range map %s: %d samples -> %d vertices, %d faces",
        view or "?",
        k,
        int(keep.sum()),
        len(kept_faces),
    )
    return RangeMap(
        vertices=points[keep],
        faces=kept_faces,
        normals=vertex_normals[keep].astype(np.float32),
        colors=colors,
        quality=quality[keep].astype(np.float32),
        row=rows[keep].astype(np.int32),
        stripe=stripes[keep].astype(np.int32),
        view=view,
    )


def _zipper(
    usable: np.ndarray, rows: np.ndarray, stripes: np.ndarray, columns: np.ndarray, max_gap: float
) -> np.ndarray:
    """Triangles (m, 3) between each pair of consecutive rows, zipping them in stripe order.

    Every usable sample takes part in two row pairs: as the upper row of ``(r, r + 1)``
    and the lower row of ``(r - 1, r)``. In each pair the samples of both rows are merged
    by stripe (upper row first on ties); each merged sample after the first of each row
    closes a triangle with the previous sample of its own row and the current sample of
    the other row. Triangles whose corners are more than ``max_gap`` apart in projector
    column (``columns``) are left out.
    """
    if len(usable) == 0:
        return np.zeros((0, 3), np.int64)
    idx = np.concatenate([usable, usable])
    pair = np.concatenate([rows[usable], rows[usable] - 1])
    side = np.concatenate([np.zeros(len(usable), np.int8), np.ones(len(usable), np.int8)])
    order = np.lexsort((side, stripes[idx], pair))
    idx, pair, side = idx[order], pair[order], side[order]
    n = len(idx)
    pos = np.arange(n)
    group_start = np.flatnonzero(np.r_[True, pair[1:] != pair[:-1]])
    start = np.repeat(group_start, np.diff(np.r_[group_start, n]))

    def last_before(which: int) -> np.ndarray:
        """Position of the latest event of ``side == which`` before each event (-1: none)."""
        mark = np.where(side == which, pos, -1)
        latest = np.maximum.accumulate(mark)
        prev = np.r_[-1, latest[:-1]]
        return np.where(prev >= start, prev, -1)

    last_up, last_down = last_before(0), last_before(1)
    own = np.where(side == 0, last_up, last_down)
    other = np.where(side == 0, last_down, last_up)
    ok = (own >= 0) & (other >= 0)
    new, own, other = idx[ok], idx[own[ok]], idx[other[ok]]
    corners = columns[np.stack([own, new, other])]
    gap_ok = np.ptp(corners, axis=0) <= max_gap + 1e-9
    return np.stack([own, new, other], axis=1)[gap_ok]


def _filter_faces(
    tri: np.ndarray,
    points: np.ndarray,
    depth: np.ndarray,
    rows: np.ndarray,
    stripes: np.ndarray,
    m_row: float,
    m_stripe: float,
    factor: float,
    max_view_angle_deg: float,
) -> np.ndarray:
    """Drop long-edged and grazing triangles; wind the rest counter-clockwise from the camera."""
    if len(tri) == 0:
        return tri.reshape(0, 3)
    keep = np.ones(len(tri), bool)
    m_row = m_row if np.isfinite(m_row) else m_stripe
    m_stripe = m_stripe if np.isfinite(m_stripe) else m_row
    for i, j in ((0, 1), (1, 2), (2, 0)):
        p, q = tri[:, i], tri[:, j]
        length = np.linalg.norm(points[p] - points[q], axis=1)
        n_row = np.abs(rows[p] - rows[q])
        n_stripe = np.abs(stripes[p] - stripes[q])
        expected = np.hypot(n_row * m_row, n_stripe * m_stripe) * 0.5 * (depth[p] + depth[q])
        keep &= length <= factor * expected
    v0, v1, v2 = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    normal = np.cross(v1 - v0, v2 - v0)
    centroid = (v0 + v1 + v2) / 3.0
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_view = -np.einsum("ij,ij->i", normal, centroid) / (
            np.linalg.norm(normal, axis=1) * np.linalg.norm(centroid, axis=1)
        )
    keep &= np.abs(cos_view) >= math.cos(math.radians(max_view_angle_deg))
    tri = tri[keep]
    flip = cos_view[keep] < 0  # normal points away from the camera: swap two corners
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return tri


def _vertex_normals(points: np.ndarray, faces: np.ndarray, finite: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (k, 3), towards the camera; viewing direction
    for vertices in no face."""
    k = len(points)
    acc = np.zeros((k, 3))
    if len(faces):
        v0, v1, v2 = (points[faces[:, i]] for i in range(3))
        face_n = np.cross(v1 - v0, v2 - v0)  # length = twice the area
        for i in range(3):
            np.add.at(acc, faces[:, i], face_n)
    toward = np.zeros((k, 3))
    toward[finite] = -points[finite] / np.linalg.norm(points[finite], axis=1, keepdims=True)
    norm = np.linalg.norm(acc, axis=1)
    has = norm > 0
    acc[has] /= norm[has, None]
    acc[~has] = toward[~has]
    flip = np.einsum("ij,ij->i", acc, toward) < 0
    acc[flip] *= -1
    return acc


# --- PLY ----------------------------------------------------------------------------------------


def write_ply(
    range_map: RangeMap, path: str | os.PathLike, *, extra: dict[str, np.ndarray] | None = None
) -> Path:
    """Write ``range_map`` as a binary little-endian PLY that MeshLab opens, atomically.

    Vertex properties: ``x y z`` (float, mm), ``nx ny nz`` (float), ``red green blue``
    (uchar), ``quality`` (float; MeshLab's vertex quality), ``row stripe`` (int), then any
    ``extra`` per-vertex float properties (name -> (n,) array); faces: ``vertex_indices``
    (uchar count, int indices). The view name is stored as a ``comment view NAME`` line.
    """
    rm = range_map
    n = len(rm.vertices)
    extra = extra or {}
    verts = np.empty(n, np.dtype(PLY_VERTEX_DTYPE.descr + [(k, "<f4") for k in extra]))
    for name, values in extra.items():
        verts[name] = values
    for i, axis in enumerate("xyz"):
        verts[axis] = rm.vertices[:, i]
        verts["n" + axis] = rm.normals[:, i]
    for i, channel in enumerate(("red", "green", "blue")):
        verts[channel] = rm.colors[:, i]
    verts["quality"], verts["row"], verts["stripe"] = rm.quality, rm.row, rm.stripe
    view = " ".join(str(rm.view).split())
    comments = ["slscan range map (mm, rig frame)"] + ([f"view {view}"] if view else [])
    return write_triangle_ply(path, verts, rm.faces, comments)


def read_ply(path: str | os.PathLike) -> RangeMap:
    """Read a triangle-mesh PLY (as :func:`write_ply` writes it; ASCII and binary too).

    Missing normals, colours, quality, row or stripe properties read as zeros (white for
    colours; -1 for row and stripe).

    Raises
    ------
    SlscanError
        Not a PLY, an unknown property type, no vertex positions, non-triangle faces, or a
        truncated file (naming the file).
    """
    path = Path(path)
    ply = read_ply_elements(path)
    vertex = ply.get("vertex")
    if vertex is None:
        raise SlscanError(f"{path}: no vertex element")
    for field in "xyz":
        if field not in vertex:
            raise SlscanError(f"{path}: vertices lack property {field!r}")
    n = len(vertex["x"])
    check_finite_vertices(np.stack([np.asarray(vertex[a], np.float64) for a in "xyz"], axis=1), path)
    faces = np.zeros((0, 3), np.int32)
    if ply.get("face"):
        lists = [v for v in ply["face"].values() if isinstance(v, tuple)]
        if not lists:
            raise SlscanError(f"{path}: element 'face' has no list of vertex indices")
        counts, indices = lists[0]
        if len(counts) and np.any(counts != 3):
            raise SlscanError(f"{path}: element 'face' has non-triangle faces; expected triangles only")
        check_face_indices(np.asarray(indices).reshape(-1, 3), n, path)
        faces = np.asarray(indices).astype(np.int32).reshape(-1, 3)

    def column(field: str, default: float, dtype) -> np.ndarray:
        return np.asarray(vertex[field]).astype(dtype) if field in vertex else np.full(n, default, dtype)

    return RangeMap(
        vertices=np.stack([column(a, 0, np.float64) for a in "xyz"], axis=1),
        faces=faces,
        normals=np.stack([column(a, 0, np.float32) for a in ("nx", "ny", "nz")], axis=1),
        colors=np.stack([column(a, 255, np.uint8) for a in ("red", "green", "blue")], axis=1),
        quality=column("quality", 0, np.float32),
        row=column("row", -1, np.int32),
        stripe=column("stripe", -1, np.int32),
        view=ply.name,
    )


def covered_pixels(range_map: RangeMap, camera, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool camera pixels covered by the range map's triangles.

    camera : the :class:`slscan.rig.PinholeModel` the range map was measured with
    """
    import cv2

    covered = np.zeros(shape, np.uint8)
    if len(range_map.faces):
        pix = camera.project_local(range_map.vertices)
        tris = np.round(pix[range_map.faces] * 16).astype(np.int32)  # 4 bits of sub-pixel
        cv2.fillPoly(covered, list(tris), 1, lineType=cv2.LINE_8, shift=4)
    return covered.astype(bool)
