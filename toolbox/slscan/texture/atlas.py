"""Texture atlas: cut a model into charts and pack them into one square texture page.

Two methods:

- ``"patches"`` (the default, for scanned models up to a few million faces): our own
  segmentation into height-field patches, each flattened by an orthographic projection,
  and xatlas only to pack them (``add_uv_mesh``: it does not cut or flatten);
- ``"xatlas"``: xatlas cuts, flattens (LSCM) and packs the whole mesh itself.

Why not xatlas alone
--------------------
xatlas grows charts by a cost (normal deviation, roundness, straightness) and splits
again any chart whose flattening folds. A fused scan is rough at the scale of its faces,
and fast quadric simplification leaves some faces folded against their neighbours, so
xatlas makes a great many tiny charts, slowly. On the fused Stanford bunny (1,694
connected components, open boundaries), on 2 cores (``benchmarks/atlas.py``):

========================================== ======= ====== =========== =======
method                                     faces   charts utilisation seconds
========================================== ======= ====== =========== =======
xatlas defaults                            100k    7,307  0.625       39.6
xatlas max_iterations=0                    100k    8,328  0.532       10.9
xatlas max_iterations=0, max_cost=0.5      100k    13,269 0.636       7.6
patches                                    100k    1,707  0.621       4.9
xatlas max_iterations=0, either max_cost   1M      —      —           > 300
patches                                    1M      2,232  0.632       16.2
========================================== ======= ====== =========== =======

xatlas's defaults take over 15 minutes on the 1M faces, and its pages came out larger
than the 4096² asked for (it picks the texels per mm); "patches" fill exactly one.
The bunny has 1,694 connected components, so at least as many charts.

The patch segmentation
----------------------
1. **Directions.** Each face is labelled with the nearest of a fixed set of directions
   (``directions``: the 6 axes; or with the 8 cube diagonals, 14; or with the 12 edge
   diagonals too, 26), by its normal averaged over its neighbourhood
   (``smooth_passes``), so that noise does not scatter the labels. A face whose own normal
   is more than ``acos(min_cos)`` from its label's direction takes the direction nearest
   its own normal instead.
2. **Patches.** Faces with the same label connected across edges shared by exactly two
   faces form a patch. Every face of a patch faces its direction, so the orthographic
   projection along it is locally one-to-one (a height field) and scales its area by its
   cosine to the direction, at least ``min_cos``.
3. **Merging.** A patch of fewer than ``min_patch_faces`` faces or ``fold_texels`` texels
   joins the neighbouring patch it shares most edges with, among those whose direction
   all its faces face by more than ``min_cos`` (repeated while any can). Patches of fewer
   than ``fold_texels`` texels left after that come from rough spots and folds: they are
   *absorbed* into the neighbour they share most edges with anyway, although some of
   their faces are then oblique or flipped in its projection ("folded"). A folded face
   overlaps its own chart, over its own small area (it lies on top of its neighbours, so
   what they show is the same), never another chart. On the 1M-face bunny 2.7 % of the
   faces, 0.6 % of the area, are folded instead of making thousands of charts of one or
   two faces, and 0.5 % of the texels covered are covered twice within their chart.
   Components with no neighbour stay charts of their own.
4. **Projection.** A patch is projected along its area-weighted mean normal when all its
   faces that are not folded face it by more than ``min_cos``, else along its direction.
5. **Overlap check.** Patches are rasterised at half the atlas's texel size; one whose
   projection covers a texel twice (an overhang facing the same way; faces within two
   rings of a fold aside) is split between two faces that overlap, each face going with
   the nearer of them over the surface; the pieces are checked again.
6. **Packing.** Each patch goes to xatlas as its own UV mesh (so it stays one chart).
   The texels per mm are first set for the charts, grown by their padding, to fill
   ``fill`` of the page, then adjusted by a few packings to the finest that fits one page.
   xatlas's chart rotation is off: it transposes charts, which would mirror them.
7. **Assembly.** Where xatlas put each chart is fitted as an affine map of our projection
   (it moves, rotates and rounds chart sizes to whole texels), and applied to every atlas
   vertex, including those of faces xatlas leaves out for having zero area.

Every face keeps its index and winding; atlas vertices are (chart, input vertex) pairs, so
vertices on seams are duplicated. Zero-area faces take the chart of a neighbour (their UV
triangle has zero area too); the few with no neighbour in any chart (specks of
micrometre faces) are collapsed onto a point of chart 0.

References
----------
.. [1] Young, "xatlas", https://github.com/jpcy/xatlas (after Castaño's thekla_atlas).
.. [2] Lévy, Petitjean, Ray, Maillot, "Least squares conformal maps for automatic texture
   atlas generation", SIGGRAPH 2002 (xatlas's flattening).
.. [3] Sander, Wood, Gortler, Snyder, Hoppe, "Multi-chart geometry images", SGP 2003
   (charts grown within normal cones, the idea behind the direction labels).
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from slscan.errors import SlscanError

log = logging.getLogger(__name__)

MIN_SIZE = 64
"""Smallest atlas page, texels."""
MAX_SIZE = 16384
"""Largest atlas page, texels (16384² RGBA is 1 GiB; GPUs rarely take more)."""
METHODS = ("patches", "xatlas")
DIRECTION_COUNTS = (6, 14, 26)
CHECK_SCALE = 0.5
"""Patches are checked for overlapping themselves on a grid of this many atlas texels: so
overlaps narrower than about two texels go unseen (and are no worse than a fold)."""
_RASTER_CHUNK = 1_000_000
"""Triangle rows scanned at once when rasterising (memory: about 200 bytes each)."""


@dataclass(frozen=True)
class AtlasOptions:
    """Options of :func:`build_atlas`."""

    size: int = 4096
    """Atlas page width = height, texels."""
    padding: int = 4
    """Texels between charts (room for dilating the texture across seams)."""
    method: str = "patches"
    """{"patches", "xatlas"}: our patch segmentation with xatlas packing, or xatlas alone
    (see the module docstring)."""
    directions: int = 6
    """{6, 14, 26}: projection directions faces are labelled with ("patches"); more make
    more charts and less stretch, for no more texels on the surface."""
    min_cos: float = 0.25
    """A face belongs to a patch only if it faces the patch's direction by at least this
    cosine (0.25: 75°); its texture is stretched by at most 1 / min_cos ("patches")."""
    smooth_passes: int = 6
    """Face → vertex → face normal averaging passes before labelling ("patches")."""
    min_patch_faces: int = 20
    """Patches with fewer faces join a neighbour whose direction they face ("patches")."""
    fold_texels: float = 64.0
    """Patches of less area (in texels at about the final resolution) that could join no
    neighbour that way are absorbed into one anyway, their faces folded ("patches")."""
    fill: float = 0.68
    """Share of the page the charts, grown by half the padding and a texel all round, are
    first sized to fill (xatlas packs them to about 0.7 before some spill over)."""
    max_pack_attempts: int = 6
    """Most packings tried to find the finest scale that fits one page (each takes about
    3 s for 1M faces); see :func:`_pack_patches`."""
    xatlas_max_cost: float = 2.0
    """xatlas ``ChartOptions.max_cost`` ("xatlas"; its default)."""
    xatlas_max_iterations: int = 1
    """xatlas ``ChartOptions.max_iterations`` ("xatlas"; its default)."""

    def __post_init__(self) -> None:
        if not MIN_SIZE <= self.size <= MAX_SIZE:
            raise SlscanError(f"atlas size {self.size}: expected {MIN_SIZE} to {MAX_SIZE} texels")
        if not 0 <= self.padding <= self.size // 16:
            raise SlscanError(
                f"atlas padding {self.padding}: expected 0 to {self.size // 16} texels "
                f"for a {self.size}-texel page"
            )
        if self.method not in METHODS:
            raise SlscanError(f"atlas method {self.method!r}: expected one of {METHODS}")
        if self.directions not in DIRECTION_COUNTS:
            raise SlscanError(
                f"atlas directions {self.directions}: expected one of {DIRECTION_COUNTS}"
            )
        if not 0.0 < self.min_cos < 0.9:
            raise SlscanError(f"atlas min_cos {self.min_cos}: expected between 0 and 0.9")
        if not 0.1 <= self.fill <= 1.0:
            raise SlscanError(f"atlas fill {self.fill}: expected 0.1 to 1")
        if self.smooth_passes < 0 or self.min_patch_faces < 1 or self.max_pack_attempts < 1:
            raise SlscanError(
                "atlas smooth_passes must be >= 0, min_patch_faces and max_pack_attempts >= 1"
            )
        if self.fold_texels < 0:
            raise SlscanError(f"atlas fold_texels {self.fold_texels}: expected >= 0")


@dataclass(frozen=True, eq=False)
class Atlas:
    """A mesh with texture coordinates on one square page.

    vertices : (m, 3) float64, positions of the atlas vertices (input units, mm); a vertex
        on a seam between charts appears once per chart
    faces : (n, 3) int32 indices into ``vertices``; face i is input face i (same order,
        same winding)
    uvs : (m, 2) float32 in [0, 1], glTF convention: (0, 0) is the image's top-left corner
        and v grows downward; texel (col, row) has its centre at
        ((col + 0.5) / size, (row + 0.5) / size)
    source_vertex : (m,) int64, the input vertex each atlas vertex copies
    chart : (n,) int32, chart of each face, 0 .. n_charts - 1; a chart is connected
    n_charts : charts on the page
    size : page width = height, texels
    utilisation : share of the page covered by charts (their UV area; folded faces,
        which lie on their own chart, not counted)
    texels_per_mm : the scale charts were packed at: with "patches", a face's UV area is
        its area × texels_per_mm² × its cosine to its chart's projection axis, up to
        xatlas's rounding of each chart to whole texels (it also enlarges charts smaller
        than a few texels); with "xatlas", on average
    n_folded : faces whose UV triangle is flipped or squeezed below ``min_cos`` (see the
        module docstring; 0 with "xatlas")
    seconds : wall time per phase: "segment", "check", "pack", "assemble" ("patches") or
        "xatlas", "assemble" ("xatlas"); and "total"
    """

    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray
    source_vertex: np.ndarray
    chart: np.ndarray
    n_charts: int
    size: int
    utilisation: float
    texels_per_mm: float
    n_folded: int = 0
    seconds: dict[str, float] = field(default_factory=dict)


def build_atlas(
    vertices: np.ndarray,
    faces: np.ndarray,
    options: AtlasOptions | None = None,
    *,
    progress: Callable[[str], None] | None = None,
) -> Atlas:
    """Cut a triangle mesh into charts and pack them into one ``options.size``² page.

    Parameters
    ----------
    vertices : (k, 3) float, mm
    faces : (n, 3) int indices into ``vertices``, counter-clockwise seen from outside
    options : see :class:`AtlasOptions`; None: the defaults
    progress : called with the name of each phase as it finishes

    Returns
    -------
    Atlas

    Raises
    ------
    SlscanError
        No faces, arrays of the wrong shape or type, indices out of range, non-finite
        vertices, or charts that do not fit one page.
    """
    options = options or AtlasOptions()
    v, f = _check_mesh(vertices, faces)
    done = progress or (lambda phase: None)
    if options.method == "xatlas":
        return _build_xatlas(v, f, options, done)
    return _build_patches(v, f, options, done)


# --- input ----------------------------------------------------------------------------------------


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or not np.issubdtype(v.dtype, np.number):
        raise SlscanError(f"atlas: vertices of shape {v.shape}: expected (k, 3) numbers")
    if f.ndim != 2 or f.shape[1] != 3:
        raise SlscanError(f"atlas: faces of shape {f.shape}: expected (n, 3) vertex indices")
    if len(f) == 0:
        raise SlscanError("atlas: the mesh has no faces")
    if not np.issubdtype(f.dtype, np.integer):
        raise SlscanError(f"atlas: faces of type {f.dtype}: expected integer vertex indices")
    if f.min() < 0 or f.max() >= len(v):
        raise SlscanError(
            f"atlas: face indices span {f.min()} .. {f.max()}: expected 0 .. {len(v) - 1}"
        )
    v = v.astype(np.float64)
    used = np.unique(f)
    if not np.isfinite(v[used]).all():
        raise SlscanError("atlas: the mesh has non-finite (NaN or infinite) vertices")
    return v, f.astype(np.int64)


# --- mesh helpers ---------------------------------------------------------------------------------


def _face_geometry(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cross (n, 3) = 2 × area × normal, unit normals (n, 3) (zero when degenerate),
    areas (n,)). A face is degenerate below 1e-12 of the bounding box diagonal squared."""
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    double = np.linalg.norm(cross, axis=1)
    extent = np.ptp(v[f.ravel()], axis=0)
    tiny = 2e-12 * float(extent @ extent)
    normals = np.where(double[:, None] > tiny, cross / np.maximum(double, 1e-300)[:, None], 0.0)
    return cross, normals, 0.5 * double


def _edge_pairs(f: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fa, fb, slot): the faces on either side of each edge shared by exactly two faces,
    and the edge's slot in ``fa`` (3 × face + k for the edge from corner k to k + 1)."""
    edges = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    key = edges[:, 0] * n_vertices + edges[:, 1]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    start = np.r_[True, sorted_key[1:] != sorted_key[:-1]]
    group = np.cumsum(start) - 1
    count = np.bincount(group)[group]
    first = np.flatnonzero(start & (count == 2))
    return order[first] // 3, order[first + 1] // 3, order[first]


def _components(n: int, fa: np.ndarray, fb: np.ndarray, label: np.ndarray) -> np.ndarray:
    """(n,) int64 component of each face over edges joining faces of equal ``label``."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    same = label[fa] == label[fb]
    graph = sp.coo_matrix((np.ones(int(same.sum()), np.int8), (fa[same], fb[same])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    return comp.astype(np.int64)


def _directions(count: int) -> np.ndarray:
    """(count, 3) unit directions: cube faces (6), + corners (14), + edges (26)."""
    cube = np.array([p for p in itertools.product((-1, 0, 1), repeat=3) if any(p)], float)
    order = np.abs(cube).sum(axis=1)
    keep = {6: order == 1, 14: order != 2, 26: order > 0}[count]
    d = cube[keep]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _frames(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit (e1, e2), each (k, 3), with e1 × e2 = normal: projecting on them keeps a face
    that faces ``normal`` counter-clockwise."""
    helper = np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    e1 = np.cross(helper, normal)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(normal, e1)


def _group_starts(group: np.ndarray, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """(order, starts): ``order`` sorts by group; group g is order[starts[g]:starts[g + 1]]."""
    order = np.argsort(group, kind="stable")
    return order, np.searchsorted(group[order], np.arange(n_groups + 1))


# --- segmentation ---------------------------------------------------------------------------------


def _label_faces(
    v: np.ndarray, f: np.ndarray, cross: np.ndarray, normals: np.ndarray, options: AtlasOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(label (n,), directions (K, 3), cos (n, K) float32 of each face to each direction;
    1 for degenerate faces, which fit anywhere)."""
    dirs = _directions(options.directions)
    smooth = cross
    flat = f.ravel()
    for _ in range(options.smooth_passes):
        vertex = np.stack(
            [np.bincount(flat, np.repeat(smooth[:, k], 3), minlength=len(v)) for k in range(3)], 1
        )
        smooth = vertex[f[:, 0]] + vertex[f[:, 1]] + vertex[f[:, 2]]
    label = np.argmax(smooth @ dirs.T, axis=1)
    cos = (normals @ dirs.T).astype(np.float32)
    cos[~normals.any(axis=1)] = 1.0
    rows = np.arange(len(f))
    off = cos[rows, label] <= options.min_cos
    label[off] = np.argmax(cos[off], axis=1)
    return label, dirs, cos


def _merge_small(
    label: np.ndarray,
    cos: np.ndarray,
    texels: np.ndarray,
    fa: np.ndarray,
    fb: np.ndarray,
    min_faces: int,
    min_texels: float,
    min_cos: float | None,
    max_rounds: int = 30,
) -> tuple[np.ndarray, np.ndarray]:
    """Give small patches the label of a larger neighbour (the one sharing most edges).

    With ``min_cos``, patches of fewer than ``min_faces`` faces or ``min_texels`` texels
    (``texels``: (n,) texel area of each face) take only the label of a neighbour whose
    direction all their faces face by more than ``min_cos``; without, patches of fewer
    than ``min_texels`` texels take the label of any. Returns (label, patch).
    """
    n = len(label)
    for _ in range(max_rounds):
        patch = _components(n, fa, fb, label)
        n_patch = int(patch.max()) + 1
        size = np.bincount(patch, minlength=n_patch)
        area = np.bincount(patch, texels, n_patch)
        small = area < min_texels
        if min_cos is not None:
            small |= size < min_faces
        plabel = np.zeros(n_patch, np.int64)
        plabel[patch] = label
        cross = label[fa] != label[fb]
        a = np.r_[patch[fa[cross]], patch[fb[cross]]]
        b = np.r_[patch[fb[cross]], patch[fa[cross]]]
        ok = small[a] & ((size[b] > size[a]) | ((size[b] == size[a]) & (b < a)))
        if min_cos is not None and ok.any():
            order, starts = _group_starts(patch, n_patch)
            worst = np.minimum.reduceat(cos[order], starts[:-1], axis=0)  # (n_patch, K)
            ok &= worst[a, plabel[b]] > min_cos
        a, b = a[ok], b[ok]
        if len(a) == 0:
            return label, patch
        pair, shared = np.unique(a * n_patch + b, return_counts=True)
        pa, pb = pair // n_patch, pair % n_patch
        best = np.lexsort((-size[pb], -shared, pa))
        pa, pb = pa[best], pb[best]
        first = np.r_[True, pa[1:] != pa[:-1]]
        plabel[pa[first]] = plabel[pb[first]]
        label = plabel[patch]
    return label, _components(n, fa, fb, label)


@dataclass(frozen=True, eq=False)
class _Patches:
    """patch : (n,) int64 patch of each face; axis : (P, 3) projection direction of each;
    folded : (n,) bool faces facing their patch's axis by min_cos or less."""

    patch: np.ndarray
    axis: np.ndarray
    folded: np.ndarray


def _segment(
    v: np.ndarray,
    f: np.ndarray,
    cross: np.ndarray,
    normals: np.ndarray,
    fa: np.ndarray,
    fb: np.ndarray,
    options: AtlasOptions,
) -> _Patches:
    """Patches of faces (steps 1-4 of the module docstring)."""
    label, dirs, cos = _label_faces(v, f, cross, normals, options)
    # texel area of each face at about the final resolution (padding aside)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    texels = area * (options.fill * options.size**2 / max(float(area.sum()), 1e-300))
    merge = (texels, fa, fb, options.min_patch_faces, options.fold_texels)
    label, _ = _merge_small(label, cos, *merge, min_cos=options.min_cos)
    label, patch = _merge_small(label, cos, *merge, min_cos=None)
    n_patch = int(patch.max()) + 1
    plabel = np.zeros(n_patch, np.int64)
    plabel[patch] = label
    rows = np.arange(len(f))
    fits = cos[rows, label] > options.min_cos
    # project along the mean normal where all fitting faces face it well enough
    weighted = np.where(fits[:, None], cross, 0.0)
    mean = np.stack([np.bincount(patch, weighted[:, k], n_patch) for k in range(3)], 1)
    length = np.linalg.norm(mean, axis=1, keepdims=True)
    mean = np.where(length > 0, mean / np.maximum(length, 1e-300), dirs[plabel])
    cos_mean = np.einsum("ij,ij->i", normals, mean[patch])
    cos_mean[~normals.any(axis=1)] = 1.0
    worst = np.ones(n_patch)
    np.minimum.at(worst, patch[fits], cos_mean[fits])
    use_mean = worst > options.min_cos
    axis = np.where(use_mean[:, None], mean, dirs[plabel])
    cos_axis = np.where(use_mean[patch], cos_mean, cos[rows, label])
    return _Patches(patch, axis, cos_axis <= options.min_cos)


# --- projection and overlap check -----------------------------------------------------------------


def _project(v: np.ndarray, f: np.ndarray, patch: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """(n, 3, 2) corners of each face projected along its patch's axis, mm."""
    e1, e2 = _frames(axis)
    corners = v[f]
    return np.stack(
        [
            np.einsum("ijk,ik->ij", corners, e1[patch]),
            np.einsum("ijk,ik->ij", corners, e2[patch]),
        ],
        axis=2,
    )


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _uv_areas(uv: np.ndarray) -> np.ndarray:
    """(n,) signed areas of (n, 3, 2) triangles, counter-clockwise positive."""
    return 0.5 * _cross2(uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0])


def rasterise(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texel centres inside triangles, by scanlines.

    tri : (m, 3, 2) float corners in texels (texel (col, row) has its centre at
        (col + 0.5, row + 0.5)), either winding

    Returns (face, col, row), each (h,) int64, ``face`` indexing ``tri``. A centre on an
    edge belongs to at most one of the triangles sharing that edge (columns strictly
    inside, rows half-open), so triangles that only touch never share a texel, and
    degenerate triangles cover nothing.
    """
    tri = np.asarray(tri, np.float64)
    first = np.ceil(tri[:, :, 1].min(axis=1) - 0.5).astype(np.int64)
    rows = np.maximum(np.floor(tri[:, :, 1].max(axis=1) - 0.5).astype(np.int64) - first + 1, 0)
    ends = np.cumsum(rows)
    out = []
    begin = 0
    while begin < len(tri):
        base = ends[begin - 1] if begin else 0
        end = max(int(np.searchsorted(ends, base + _RASTER_CHUNK, side="right")), begin + 1)
        n_rows = rows[begin:end]
        face = np.repeat(np.arange(begin, end), n_rows)
        row = first[face] + np.arange(len(face)) - np.repeat(np.cumsum(n_rows) - n_rows, n_rows)
        y = row + 0.5
        t = tri[face]
        left = np.full(len(face), np.inf)
        right = np.full(len(face), -np.inf)
        crossings = np.zeros(len(face), np.int8)
        for k in range(3):
            a, b = t[:, k], t[:, (k + 1) % 3]
            cross = (np.minimum(a[:, 1], b[:, 1]) <= y) & (y < np.maximum(a[:, 1], b[:, 1]))
            dy = np.where(cross, b[:, 1] - a[:, 1], 1.0)
            x = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
            left = np.where(cross, np.minimum(left, x), left)
            right = np.where(cross, np.maximum(right, x), right)
            crossings += cross
        ok = crossings == 2
        face, row, left, right = face[ok], row[ok], left[ok], right[ok]
        c0 = np.floor(left - 0.5).astype(np.int64) + 1  # first centre right of ``left``
        count = np.maximum(np.ceil(right - 0.5).astype(np.int64) - c0, 0)
        span = np.repeat(np.arange(len(face)), count)
        col = c0[span] + np.arange(len(span)) - np.repeat(np.cumsum(count) - count, count)
        out.append((face[span], col, row[span]))
        begin = end
    if not out:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty
    return tuple(np.concatenate(parts) for parts in zip(*out))


def _overlaps(tri: np.ndarray, group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pair of triangles per group that covers a texel centre twice: (first, second),
    each (k,) indexing ``tri``, one pair for each such group.

    tri : (m, 3, 2) corners in texels; group : (m,) int64 group of each triangle
    """
    face, col, row = rasterise(tri)
    if len(face) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    col = col - col.min()
    row = row - row.min()
    width = int(col.max()) + 1
    key = (group[face] * (int(row.max()) + 1) + row) * width + col
    order = np.argsort(key, kind="stable")
    twice = np.flatnonzero(key[order[1:]] == key[order[:-1]])
    first, second = face[order[twice]], face[order[twice + 1]]
    _, one = np.unique(group[first], return_index=True)
    return first[one], second[one]


def _split_overlaps(
    v: np.ndarray,
    f: np.ndarray,
    fa: np.ndarray,
    fb: np.ndarray,
    patches: _Patches,
    texels_per_mm: float,
    fold_rings: int = 2,
    max_rounds: int = 50,
) -> tuple[_Patches, int]:
    """Split patches whose projection covers a texel twice (folded faces aside), between
    two faces that overlap: each face of the patch goes with the nearer of the two (by
    paths over the surface), until no patch overlaps itself. Only split patches are
    checked again. Returns (patches, number of splits)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    patch, axis, folded = patches.patch, patches.axis, patches.folded
    centre = v[f].mean(axis=1)
    near_fold = _near(f, len(v), folded, rings=fold_rings)
    check = np.flatnonzero(~near_fold)
    splits = 0
    for _ in range(max_rounds):
        uv = _project(v, f[check], patch[check], axis)
        first, second = _overlaps(uv * texels_per_mm, patch[check])
        log.debug("atlas: overlap check of %d faces: %d patches overlap", len(check), len(first))
        if len(first) == 0:
            break
        seeds = np.r_[check[first], check[second]]
        splits += len(first)
        bad = np.zeros(len(axis), bool)
        bad[patch[seeds]] = True
        inner = (patch[fa] == patch[fb]) & bad[patch[fa]]
        a, b = fa[inner], fb[inner]
        length = np.linalg.norm(centre[a] - centre[b], axis=1) + 1e-12
        graph = sp.coo_matrix((length, (a, b)), shape=(len(f),) * 2).tocsr()
        _, _, nearest = dijkstra(
            graph, directed=False, indices=seeds, return_predecessors=True, min_only=True
        )
        piece = np.where(nearest >= 0, np.searchsorted(np.sort(seeds), nearest), -1)
        n_patch = len(axis)
        split = np.where(bad[patch] & (piece >= 0), n_patch + piece, patch)
        new = _components(len(f), fa, fb, split)
        parent = np.zeros(int(new.max()) + 1, np.int64)
        parent[new] = patch
        patch, axis = new, axis[parent]
        check = np.flatnonzero(~near_fold & bad[parent[patch]])
    else:
        log.warning("atlas: patches still overlap after %d rounds of splitting", max_rounds)
    return _Patches(patch, axis, folded), splits


def _near(f: np.ndarray, n_vertices: int, faces: np.ndarray, rings: int) -> np.ndarray:
    """(n,) bool: ``faces`` (a mask) and the faces within ``rings`` vertex rings of them."""
    near = faces.copy()
    for _ in range(rings):
        touched = np.zeros(n_vertices, bool)
        touched[f[near].ravel()] = True
        near = touched[f].any(axis=1)
    return near


def _perimeters(
    uv: np.ndarray, patch: np.ndarray, n_patch: int, fa: np.ndarray, fb: np.ndarray, slot
) -> np.ndarray:
    """(n_patch,) length of each patch's outline in UV, mm."""
    length = np.linalg.norm(uv[:, [1, 2, 0]] - uv, axis=2)  # (n, 3): edge k from corner k
    total = np.bincount(patch, length.sum(axis=1), n_patch)
    inner = patch[fa] == patch[fb]
    return total - 2 * np.bincount(patch[fa[inner]], length.ravel()[slot[inner]], n_patch)


# --- packing --------------------------------------------------------------------------------------


def _texels_per_mm(area: np.ndarray, perimeter: np.ndarray, options: AtlasOptions) -> float:
    """Texels per mm at which charts of these UV areas (mm²) and perimeters (mm), each
    grown by half the padding all round, cover ``options.fill`` of the page."""
    pad = 0.5 * options.padding + 1.0
    a = float(area.sum())
    b = float(perimeter.sum()) * pad
    c = len(area) * 4 * pad * pad - options.fill * options.size**2
    if c >= 0 or a <= 0:
        raise SlscanError(
            f"atlas: {len(area)} charts with {options.padding}-texel padding do not fit a "
            f"{options.size}² page; use a larger size or a smaller padding"
        )
    return (-b + math.sqrt(b * b - 4 * a * c)) / (2 * a)


def _pack_options(options: AtlasOptions, texels_per_mm: float):
    import xatlas

    pack = xatlas.PackOptions()
    pack.resolution = options.size
    pack.padding = (options.padding + 1) // 2  # xatlas pads each chart: gaps are twice this
    pack.texels_per_unit = texels_per_mm
    pack.bilinear = True
    pack.blockAlign = True  # 4×4 blocks: much faster, hardly less dense
    pack.bruteForce = False
    pack.rotate_charts = False  # it transposes (mirrors) charts
    return pack


def _pack_patches(
    local_uv: np.ndarray,
    local_faces: np.ndarray,
    vertex_starts: np.ndarray,
    face_starts: np.ndarray,
    texels_per_mm: float,
    options: AtlasOptions,
):
    """Pack each patch (its own xatlas UV mesh) on one page, as finely as a few packings find.

    Starts at ``texels_per_mm``. A packing that spills onto a second page is redone at the
    scale its first page's share suggests, and at least 10 % smaller per spill so far (a
    sliver that keeps spilling is a chart too long for the room left); one that fits with room to spare (xatlas fills
    pages to about 0.7) is tried larger; once one fits and a larger one does not, the
    scale is bisected while packings are left and the two differ by more than 3 %.
    Returns (xatlas.Atlas, texels_per_mm) of the finest packing that fit.
    """
    import xatlas

    fit = None  # (texels_per_mm, atlas)
    too_big = math.inf
    spills = 0
    t = texels_per_mm
    for _ in range(options.max_pack_attempts):
        atlas = xatlas.Atlas()
        for k in range(len(vertex_starts) - 1):
            atlas.add_uv_mesh(
                local_uv[vertex_starts[k] : vertex_starts[k + 1]],
                local_faces[face_starts[k] : face_starts[k + 1]],
            )
        atlas.generate(xatlas.ChartOptions(), _pack_options(options, t))
        used = [atlas.get_utilization(i) for i in range(atlas.atlas_count)]
        log.debug(
            "atlas: packed at %.3f texels/mm: pages used %s",
            t,
            ", ".join(f"{u:.3f}" for u in used),
        )
        if atlas.atlas_count == 1 and max(atlas.width, atlas.height) <= options.size:
            fit = (t, atlas)
            if too_big == math.inf:
                if used[0] > 0.62:
                    break  # about as full as xatlas gets
                t *= math.sqrt(0.68 / used[0])
        else:
            too_big = t
            spills += 1
            if fit is None:
                # the first page's share says how much to shrink; when a sliver keeps spilling
                # (a chart too long for what is left on the page), shrink faster each time
                t *= min(0.99 * math.sqrt(used[0] / sum(used)), 0.9**spills)
        if fit is not None and too_big < math.inf:
            if too_big / fit[0] < 1.03:
                break
            t = math.sqrt(fit[0] * too_big)
    if fit is None:
        raise SlscanError(
            f"atlas: the charts did not fit one {options.size}² page in "
            f"{options.max_pack_attempts} packings; raise max_pack_attempts or lower fill"
        )
    return fit[1], fit[0]


def _fit_affine(src: np.ndarray, dst: np.ndarray, group: np.ndarray, n_groups: int):
    """Per group, the affine map dst ≈ A (src - mean) + b, by least squares.

    src, dst : (k, 2); group : (k,) int64 in 0 .. n_groups - 1
    Returns (mean (G, 2), A (G, 2, 2), b (G, 2), largest residual).
    """
    count = np.maximum(np.bincount(group, minlength=n_groups), 1)[:, None]
    mean_s = np.stack([np.bincount(group, src[:, j], n_groups) for j in range(2)], 1) / count
    mean_d = np.stack([np.bincount(group, dst[:, j], n_groups) for j in range(2)], 1) / count
    s = src - mean_s[group]
    d = dst - mean_d[group]
    ss = np.zeros((n_groups, 2, 2))
    sd = np.zeros((n_groups, 2, 2))
    for i in range(2):
        for j in range(2):
            ss[:, i, j] = np.bincount(group, s[:, i] * s[:, j], n_groups)
            sd[:, i, j] = np.bincount(group, s[:, i] * d[:, j], n_groups)
    ridge = (1e-12 * np.trace(ss, axis1=1, axis2=2) + 1e-30)[:, None, None] * np.eye(2)
    affine = np.transpose(np.linalg.solve(ss + ridge, sd), (0, 2, 1))
    fitted = np.einsum("kij,kj->ki", affine[group], s) + mean_d[group]
    residual = float(np.abs(fitted - dst).max()) if len(dst) else 0.0
    return mean_s, affine, mean_d, residual


def _adopt_charts(
    chart: np.ndarray, patch: np.ndarray, fa: np.ndarray, fb: np.ndarray
) -> np.ndarray:
    """Give faces xatlas left out (zero UV area) the chart of a neighbour in their patch,
    else of any chart of their patch; -1 where their patch has no chart."""
    chart = chart.copy()
    same = patch[fa] == patch[fb]
    a, b = np.r_[fa[same], fb[same]], np.r_[fb[same], fa[same]]
    while True:
        take = (chart[a] < 0) & (chart[b] >= 0)
        if not take.any():
            break
        chart[a[take]] = chart[b[take]]
    missing = chart < 0
    if missing.any():
        any_chart = np.full(int(patch.max()) + 1, -1, np.int64)
        placed = ~missing
        any_chart[patch[placed]] = chart[placed]
        chart[missing] = any_chart[patch[missing]]
    return chart


def _utilisation(uvs: np.ndarray, faces: np.ndarray, skip: np.ndarray) -> float:
    """Summed UV area of the faces not in ``skip``, as a share of the unit square."""
    area = np.abs(_uv_areas(uvs.astype(np.float64)[faces]))
    return float(min(area[~skip].sum(), 1.0))


# --- the two methods ------------------------------------------------------------------------------


def _build_patches(v: np.ndarray, f: np.ndarray, options: AtlasOptions, done) -> Atlas:
    n, nv = len(f), len(v)
    seconds: dict[str, float] = {}
    t0 = t = time.perf_counter()
    cross, normals, area = _face_geometry(v, f)
    if not area.any():
        raise SlscanError("atlas: all faces of the mesh have zero area")
    fa, fb, slot = _edge_pairs(f, nv)
    patches = _segment(v, f, cross, normals, fa, fb, options)
    seconds["segment"] = time.perf_counter() - t
    done("segment")

    t = time.perf_counter()
    guess = _resolution(v, f, patches, fa, fb, slot, options)
    patches, cuts = _split_overlaps(v, f, fa, fb, patches, CHECK_SCALE * guess)
    if cuts:
        log.info("atlas: cut %d self-overlapping patches", cuts)
    seconds["check"] = time.perf_counter() - t
    done("check")

    # one UV mesh per patch; its vertices are (patch, input vertex) pairs
    t = time.perf_counter()
    patch, n_patch = patches.patch, len(patches.axis)
    texels_per_mm = _resolution(v, f, patches, fa, fb, slot, options)
    order, face_starts = _group_starts(patch, n_patch)
    key, inverse = np.unique((patch[order, None] * nv + f[order]).ravel(), return_inverse=True)
    vertex_starts = np.searchsorted(key // nv, np.arange(n_patch + 1))
    local_faces = inverse.reshape(-1, 3) - vertex_starts[patch[order], None]
    key_uv = np.zeros((len(key), 2))
    key_uv[inverse] = _project(v, f[order], patch[order], patches.axis).reshape(-1, 2)
    shift = np.minimum.reduceat(key_uv, vertex_starts[:-1], axis=0)  # keeps float32 precise
    key_uv -= shift[key // nv]
    atlas, texels_per_mm = _pack_patches(
        key_uv.astype(np.float32),
        local_faces.astype(np.uint32),
        vertex_starts,
        face_starts,
        texels_per_mm,
        options,
    )
    seconds["pack"] = time.perf_counter() - t
    done("pack")

    # xatlas's charts, and where it put each: an affine map of our projection
    t = time.perf_counter()
    chart = np.full(n, -1, np.int64)
    src, dst, fit_chart = [], [], []
    n_charts = 0
    scale = np.array([atlas.width, atlas.height], np.float64)
    for k in range(n_patch):
        count = atlas.get_mesh_chart_count(k)
        if count == 0:
            continue
        vmap, indices, out_uv = atlas.get_mesh(k)
        local_chart = np.full(face_starts[k + 1] - face_starts[k], -1, np.int64)
        for c in range(count):
            local_chart[np.asarray(atlas.get_mesh_chart(k, c).faces, np.int64)] = n_charts + c
        chart[order[face_starts[k] : face_starts[k + 1]]] = local_chart
        placed = local_chart >= 0
        corners = np.asarray(indices, np.int64)[placed].ravel()
        src.append(key_uv[vertex_starts[k] + np.asarray(vmap, np.int64)[corners]])
        dst.append(np.asarray(out_uv, np.float64)[corners] * scale)
        fit_chart.append(np.repeat(local_chart[placed], 3))
        n_charts += count
    if n_charts == 0:
        raise SlscanError("atlas: the mesh has no face of non-zero area to make a chart of")
    mean_s, affine, mean_d, residual = _fit_affine(
        np.concatenate(src), np.concatenate(dst), np.concatenate(fit_chart), n_charts
    )
    if residual > 0.05:
        log.warning("atlas: chart placements fit to %.3f texels only", residual)
    chart_patch = np.zeros(n_charts, np.int64)
    chart_patch[chart[chart >= 0]] = patch[chart >= 0]
    chart = _adopt_charts(chart, patch, fa, fb)
    collapsed = chart < 0
    if collapsed.any():
        log.info("atlas: %d zero-area faces collapsed onto chart 0", int(collapsed.sum()))
    chart[collapsed] = 0

    # atlas vertices: (chart, input vertex) pairs; collapsed faces get their own, at one point
    key = chart[:, None] * nv + f
    key[collapsed] += n_charts * nv
    key, inverse = np.unique(key.ravel(), return_inverse=True)
    source = key % nv
    vchart = key // nv
    lone = vchart >= n_charts
    vchart[lone] -= n_charts
    vpatch = chart_patch[vchart]
    e1, e2 = _frames(patches.axis)
    local = np.stack(
        [
            np.einsum("ij,ij->i", v[source], e1[vpatch]),
            np.einsum("ij,ij->i", v[source], e2[vpatch]),
        ],
        axis=1,
    )
    local -= shift[vpatch] + mean_s[vchart]
    texel = np.einsum("kij,kj->ki", affine[vchart], local) + mean_d[vchart]
    texel[lone] = mean_d[0]
    return _assembled(
        v, source, inverse.reshape(-1, 3), texel, chart, n_charts, patches.folded,
        texels_per_mm, options, seconds, (t0, t), done,
    )


def _assembled(
    v, source, faces, texel, chart, n_charts, folded, texels_per_mm, options, seconds, starts, done
) -> Atlas:
    """The :class:`Atlas` of a finished layout: texel positions (n, 2) of the output
    vertices ``v[source]`` scaled to UVs; ``starts``: when the build and its assembly began."""
    uvs = np.clip(texel / options.size, 0.0, 1.0).astype(np.float32)
    faces = faces.astype(np.int32)
    seconds["assemble"] = time.perf_counter() - starts[1]
    seconds["total"] = time.perf_counter() - starts[0]
    done("assemble")
    return Atlas(
        vertices=v[source],
        faces=faces,
        uvs=uvs,
        source_vertex=source,
        chart=chart.astype(np.int32),
        n_charts=n_charts,
        size=options.size,
        utilisation=_utilisation(uvs, faces, folded),
        texels_per_mm=texels_per_mm,
        n_folded=int(folded.sum()),
        seconds=seconds,
    )


def _resolution(v, f, patches: _Patches, fa, fb, slot, options: AtlasOptions) -> float:
    """Texels per mm that fill the page with these patches (see :func:`_texels_per_mm`)."""
    n_patch = len(patches.axis)
    uv = _project(v, f, patches.patch, patches.axis)
    area = np.where(patches.folded, 0.0, np.abs(_uv_areas(uv)))
    return _texels_per_mm(
        np.bincount(patches.patch, area, n_patch),
        _perimeters(uv, patches.patch, n_patch, fa, fb, slot),
        options,
    )


def _build_xatlas(v: np.ndarray, f: np.ndarray, options: AtlasOptions, done) -> Atlas:
    import xatlas

    t0 = time.perf_counter()
    chart_options = xatlas.ChartOptions()
    chart_options.max_cost = options.xatlas_max_cost
    chart_options.max_iterations = options.xatlas_max_iterations
    texels_per_mm = 0.0  # first try: xatlas's own estimate for the page size
    for _ in range(options.max_pack_attempts):
        atlas = xatlas.Atlas()
        atlas.add_mesh(v.astype(np.float32), f.astype(np.uint32))
        atlas.generate(chart_options, _pack_options(options, texels_per_mm))
        side = max(atlas.width, atlas.height)
        log.debug(
            "atlas: xatlas at %.3f texels/mm: %d charts, %d pages of %d x %d",
            atlas.texels_per_unit,
            atlas.chart_count,
            atlas.atlas_count,
            atlas.width,
            atlas.height,
        )
        if atlas.atlas_count == 1 and side <= options.size:
            break
        texels_per_mm = 0.95 * atlas.texels_per_unit * min(1.0, options.size / side)
        if atlas.atlas_count > 1:
            texels_per_mm *= 0.93
    else:
        raise SlscanError(
            f"atlas: xatlas's charts did not fit one {options.size}² page in "
            f"{options.max_pack_attempts} tries"
        )
    seconds = {"xatlas": time.perf_counter() - t0}
    done("xatlas")

    t = time.perf_counter()
    vmap, indices, out_uv = atlas.get_mesh(0)
    faces_out = np.asarray(indices, np.int64)
    if len(faces_out) != len(f):
        raise SlscanError(f"atlas: xatlas returned {len(faces_out)} faces for {len(f)}")
    chart = np.full(len(f), -1, np.int64)
    n_charts = atlas.get_mesh_chart_count(0)
    for c in range(n_charts):
        chart[np.asarray(atlas.get_mesh_chart(0, c).faces, np.int64)] = c
    fa, fb, _ = _edge_pairs(f, len(v))
    chart = _adopt_charts(chart, np.zeros(len(f), np.int64), fa, fb)
    chart[chart < 0] = 0
    source = np.asarray(vmap, np.int64)
    texel = np.asarray(out_uv, np.float64) * [atlas.width, atlas.height]
    return _assembled(
        v, source, faces_out, texel, chart, max(n_charts, 1), np.zeros(len(f), bool),
        float(atlas.texels_per_unit), options, seconds, (t0, t), done,
    )
