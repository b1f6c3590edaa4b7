"""Texture atlas: face order kept, charts inside the page, apart and connected, bounded stretch."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from slscan.errors import SlscanError
from slscan.texture.atlas import Atlas, AtlasOptions, build_atlas, rasterise

SIZE = 512
PADDING = 4


# --- meshes with known properties -----------------------------------------------------------------


def grid_surface(fn, nu: int, nv: int, u_range, v_range) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated parametric surface ``fn(u, v) -> (..., 3)`` on an nu × nv grid."""
    u, v = np.meshgrid(np.linspace(*u_range, nu), np.linspace(*v_range, nv), indexing="ij")
    vertices = fn(u, v).reshape(-1, 3)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)
    return vertices, faces


def sphere(n: int = 24, radius: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed, welded sphere (an icosphere-like subdivided octahedron), outward faces."""
    vertices = np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float
    )
    faces = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    )
    for _ in range(int(math.log2(n))):
        edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = len(vertices) + inverse.reshape(-1, 3)
        vertices = np.concatenate([vertices, vertices[unique].mean(axis=1)])
        a, b, c = faces.T
        ab, bc, ca = mid.T
        faces = np.concatenate(
            [np.stack(t, 1) for t in ([a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca])]
        )
    vertices /= np.linalg.norm(vertices, axis=1, keepdims=True)
    return radius * vertices, faces


def helicoid() -> tuple[np.ndarray, np.ndarray]:
    """A ramp winding 1.5 turns: every face looks up (within 12°), yet seen from above the
    second turn lies on the first, so one projection cannot flatten it."""
    return grid_surface(
        lambda r, t: np.stack([r * np.cos(t), r * np.sin(t), 2.0 * t], -1),
        8,
        120,
        (10.0, 30.0),
        (0.0, 3 * math.pi),
    )


def rough_sphere() -> tuple[np.ndarray, np.ndarray]:
    """A sphere with radial noise of half its edge length: some faces fold, as in a fused
    scan."""
    v, f = sphere(32)
    rng = np.random.default_rng(7)
    v = v * (1 + 0.02 * rng.standard_normal(len(v)))[:, None]
    return v, f


def with_degenerate_faces(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Adds a face with a repeated vertex, a face on three collinear vertices (one new, on an
    edge) and an isolated zero-area face, between the existing faces."""
    a, b = f[0, 0], f[0, 1]
    extra_v = np.array([0.5 * (v[a] + v[b]), [500.0, 0, 0], [500.0, 0, 0], [500.0, 0, 0]])
    k = len(v)
    degenerate = np.array([[a, a, b], [a, k, b], [k + 1, k + 2, k + 3]])
    half = len(f) // 2
    return np.concatenate([v, extra_v]), np.concatenate([f[:half], degenerate, f[half:]])


def triangle_areas(points: np.ndarray) -> np.ndarray:
    """(n,) unsigned areas of (n, 3, 2 or 3) triangles."""
    e1, e2 = points[:, 1] - points[:, 0], points[:, 2] - points[:, 0]
    if points.shape[-1] == 2:
        return 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)


def signed_uv_areas(atlas: Atlas) -> np.ndarray:
    t = atlas.uvs.astype(np.float64)[atlas.faces] * atlas.size
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def touched_texels(atlas: Atlas) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(chart, col, row) of every texel a triangle touches at all (its inside, its edges,
    its corners), for charts of non-zero area."""
    tri = atlas.uvs.astype(np.float64)[atlas.faces] * atlas.size
    face, col, row = rasterise(tri)
    charts, cols, rows = [atlas.chart[face]], [col], [row]
    for k in range(3):
        a, b = tri[:, k], tri[:, (k + 1) % 3]
        steps = np.ceil(np.linalg.norm(b - a, axis=1) * 4).astype(int) + 1
        edge = np.repeat(np.arange(len(tri)), steps)
        s = (np.arange(len(edge)) - np.repeat(np.cumsum(steps) - steps, steps)) / np.repeat(
            np.maximum(steps - 1, 1), steps
        )
        p = a[edge] + (b[edge] - a[edge]) * s[:, None]
        cell = np.clip(np.floor(p).astype(int), 0, atlas.size - 1)
        charts.append(atlas.chart[edge])
        cols.append(cell[:, 0])
        rows.append(cell[:, 1])
    return np.concatenate(charts), np.concatenate(cols), np.concatenate(rows)


def chart_image(atlas: Atlas) -> np.ndarray:
    """(size, size) int: the chart touching each texel, -1 for none, -2 for several."""
    chart, col, row = touched_texels(atlas)
    image = np.full((atlas.size, atlas.size), -1, np.int64)
    image[row, col] = chart
    clash = image[row, col] != chart
    image[row[clash], col[clash]] = -2
    return image


# --- fixtures -------------------------------------------------------------------------------------


def figurine() -> tuple[np.ndarray, np.ndarray]:
    """The virtual rig's built-in figurine, coarse: thin parts, a ring, a pedestal."""
    from slscan.virtual.scenes import builtin_object

    scene = builtin_object(detail=0.15)
    return np.asarray(scene.vertices), np.asarray(scene.triangles)


CASES = {
    "sphere": (lambda: sphere(), {}),
    "helicoid": (helicoid, {}),
    "rough": (rough_sphere, {}),
    "degenerate": (lambda: with_degenerate_faces(*sphere()), {}),
    "figurine": (figurine, {}),
    "sphere-xatlas": (lambda: sphere(16), {"method": "xatlas"}),
}


@functools.cache
def case(name: str) -> tuple[np.ndarray, np.ndarray, Atlas]:
    """(vertices, faces, atlas on a SIZE² page) of one of the CASES, built once."""
    make, options = CASES[name]
    v, f = make()
    return v, f, build_atlas(v, f, AtlasOptions(size=SIZE, padding=PADDING, **options))


@pytest.fixture(params=list(CASES))
def any_atlas(request) -> tuple[str, np.ndarray, np.ndarray, Atlas]:
    return (request.param, *case(request.param))


# --- what every atlas must satisfy ----------------------------------------------------------------


def test_faces_keep_their_order_winding_and_vertices(any_atlas):
    _, v, f, atlas = any_atlas
    assert atlas.faces.dtype == np.int32 and atlas.faces.shape == f.shape
    np.testing.assert_array_equal(atlas.vertices[atlas.faces], v[f])
    np.testing.assert_array_equal(atlas.source_vertex[atlas.faces], f)
    np.testing.assert_array_equal(atlas.vertices, v[atlas.source_vertex])
    assert atlas.vertices.dtype == np.float64 and atlas.source_vertex.dtype == np.int64


def test_uvs_on_the_page(any_atlas):
    _, _, f, atlas = any_atlas
    assert atlas.uvs.dtype == np.float32 and atlas.uvs.shape == (len(atlas.vertices), 2)
    assert np.all((atlas.uvs >= 0) & (atlas.uvs <= 1))
    assert atlas.size == SIZE
    assert atlas.chart.dtype == np.int32 and atlas.chart.shape == (len(f),)
    assert atlas.chart.min() >= 0 and atlas.chart.max() == atlas.n_charts - 1
    assert 0.2 < atlas.utilisation <= 1.0
    assert atlas.seconds["total"] > 0


def test_charts_are_padding_apart(any_atlas):
    """No texel is touched by two charts, and texels of different charts are more than the
    padding apart (Chebyshev distance, counting every texel a triangle touches)."""
    _, _, _, atlas = any_atlas
    image = chart_image(atlas)
    assert not (image == -2).any(), "texels touched by two charts"
    for dy in range(-PADDING, PADDING + 1):
        for dx in range(-PADDING, PADDING + 1):
            a = image[max(dy, 0) : SIZE + min(dy, 0), max(dx, 0) : SIZE + min(dx, 0)]
            b = image[max(-dy, 0) : SIZE + min(-dy, 0), max(-dx, 0) : SIZE + min(-dx, 0)]
            near = (a >= 0) & (b >= 0) & (a != b)
            assert not near.any(), f"charts {PADDING} texels or closer at offset ({dx}, {dy})"


def test_each_chart_is_connected(any_atlas):
    """Faces of a chart (of non-zero UV area) are connected through shared vertices."""
    _, _, f, atlas = any_atlas
    keep = np.flatnonzero(np.abs(signed_uv_areas(atlas)) > 1e-9)
    n = len(keep)
    incidence = sp.coo_matrix(
        (np.ones(3 * n), (np.repeat(np.arange(n), 3), f[keep].ravel()))
    ).tocsr()
    adjacency = (incidence @ incidence.T).tocoo()
    same = atlas.chart[keep][adjacency.row] == atlas.chart[keep][adjacency.col]
    graph = sp.coo_matrix((np.ones(same.sum()), (adjacency.row[same], adjacency.col[same])), (n, n))
    _, component = connected_components(graph, directed=False)
    per_chart = np.zeros(atlas.n_charts, np.int64)
    first = np.unique(component, return_index=True)[1]
    np.add.at(per_chart, atlas.chart[keep][first], 1)
    assert per_chart.max() == 1, f"{np.sum(per_chart > 1)} charts in several pieces"


def test_one_orientation_on_the_page(any_atlas):
    """Charts are placed by rotations, never mirrored: the faces that are not folded all
    keep one orientation in UV."""
    name, _, _, atlas = any_atlas
    area = signed_uv_areas(atlas)
    big = np.abs(area) > 0.05
    positive = np.mean(area[big] > 0)
    if name == "rough":  # folded faces flip; they are few
        assert max(positive, 1 - positive) > 0.97
        assert np.sum(big & (np.sign(area) != np.sign(np.median(area[big])))) <= atlas.n_folded
    else:
        assert positive in (0.0, 1.0)


# --- known answers --------------------------------------------------------------------------------


# xatlas sizes each chart to whole texels, so a chart's scale may differ from
# texels_per_mm by a texel over its width: a few % on these small pages
SCALE_TOLERANCE = 0.05


def test_sphere_stretch_is_bounded():
    """On a clean sphere no face is folded, each face's UV area is its surface area times
    texels_per_mm² times the cosine to its projection (so between min_cos and 1), and the
    page is used as well as six big charts allow."""
    v, f, atlas = case("sphere")
    options = AtlasOptions()
    assert atlas.n_folded == 0
    assert 6 <= atlas.n_charts <= 30
    ratio = triangle_areas(atlas.uvs.astype(np.float64)[atlas.faces] * SIZE) / (
        triangle_areas(v[f]) * atlas.texels_per_mm**2
    )
    assert ratio.max() <= (1 + SCALE_TOLERANCE) ** 2
    assert ratio.min() >= options.min_cos * (1 - SCALE_TOLERANCE) ** 2
    area = triangle_areas(v[f])
    assert np.sum(ratio * area) / area.sum() > 0.8
    assert atlas.utilisation > 0.45


def test_lengths_keep_their_scale_along_the_projection_plane():
    """An orthographic projection keeps the length of every edge up to the cosine of its
    tilt: UV length / (3D length × texels_per_mm) lies in [min_cos, 1]."""
    v, f, atlas = case("sphere")
    uv = atlas.uvs.astype(np.float64)[atlas.faces] * SIZE
    uv_len = np.linalg.norm(uv[:, [1, 2, 0]] - uv, axis=2)
    length = np.linalg.norm(v[f][:, [1, 2, 0]] - v[f], axis=2)
    ratio = uv_len / (length * atlas.texels_per_mm)
    assert ratio.max() <= 1 + SCALE_TOLERANCE
    assert ratio.min() >= AtlasOptions().min_cos * (1 - SCALE_TOLERANCE)


def test_ramp_that_overlaps_itself_is_cut():
    """All faces of the helicoid face up, but its projection covers itself: the atlas must
    cut it into charts that do not overlap, even within a chart."""
    _, _, atlas = case("helicoid")
    assert atlas.n_folded == 0
    assert atlas.n_charts >= 2
    _, col, row = rasterise(atlas.uvs.astype(np.float64)[atlas.faces] * SIZE)
    key = row * SIZE + col
    assert len(np.unique(key)) == len(key), "texels covered twice"


def test_degenerate_faces_keep_their_place():
    """Zero-area faces keep their index and vertices and get a zero-area UV triangle."""
    _, f, atlas = case("degenerate")
    half = (len(f) - 3) // 2
    degenerate = np.arange(half, half + 3)
    np.testing.assert_array_equal(atlas.source_vertex[atlas.faces[degenerate]], f[degenerate])
    assert np.all(np.abs(signed_uv_areas(atlas)[degenerate]) < 1e-6)
    others = np.setdiff1d(np.arange(len(f)), degenerate)
    assert np.all(np.abs(signed_uv_areas(atlas)[others]) > 0)


def test_rough_surface_makes_few_charts():
    """Noise folds some faces: they stay in their patches (folded) instead of each small
    patch of them becoming a chart."""
    v, f, atlas = case("rough")
    assert 0 < atlas.n_folded < 0.05 * len(f)
    unfolded = build_atlas(v, f, AtlasOptions(size=SIZE, padding=PADDING, fold_texels=0))
    assert unfolded.n_folded == 0
    assert atlas.n_charts < 60 < unfolded.n_charts


def test_page_size_is_respected_at_another_size():
    v, f = sphere(16)
    atlas = build_atlas(v, f, AtlasOptions(size=128, padding=2))
    assert atlas.size == 128
    assert np.all((atlas.uvs >= 0) & (atlas.uvs <= 1))
    # texels per mm scale with the page: a 4x page is about 4x as fine
    big = build_atlas(v, f, AtlasOptions(size=512, padding=2))
    assert 3.0 < big.texels_per_mm / atlas.texels_per_mm < 5.0


def test_progress_reports_each_phase():
    v, f = sphere(8)
    phases: list[str] = []
    atlas = build_atlas(v, f, AtlasOptions(size=256), progress=phases.append)
    assert phases == ["segment", "check", "pack", "assemble"]
    assert set(phases) <= set(atlas.seconds)


def test_rasterise_known_answers():
    # a right triangle with legs of 4 texels covers the centres strictly below its diagonal
    face, col, row = rasterise(np.array([[[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]]]))
    assert sorted(zip(col.tolist(), row.tolist())) == sorted(
        (c, r) for c in range(4) for r in range(4) if c + r < 3
    )
    # a square cut along its diagonal (either winding): each centre once, none on the diagonal
    square = np.array([[[0, 0], [4, 0], [4, 4]], [[0, 0], [0, 4], [4, 4]]], float)
    face, col, row = rasterise(square)
    assert len(face) == 12 and len(set(zip(col.tolist(), row.tolist()))) == 12
    # degenerate triangles cover nothing
    assert len(rasterise(np.array([[[0.0, 0.0], [2.0, 2.0], [4.0, 4.0]]]))[0]) == 0


# --- errors ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "vertices, faces, match",
    [
        (np.zeros((3, 3)), np.zeros((0, 3), int), "no faces"),
        (np.zeros((3, 2)), np.array([[0, 1, 2]]), "vertices of shape"),
        (np.zeros((3, 3)), np.array([0, 1, 2]), "faces of shape"),
        (np.zeros((3, 3)), np.array([[0.0, 1.0, 2.0]]), "integer"),
        (np.zeros((3, 3)), np.array([[0, 1, 3]]), "indices span"),
        (np.zeros((3, 3)), np.array([[0, -1, 2]]), "indices span"),
        (np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]), "non-finite"),
    ],
)
def test_bad_meshes_are_refused(vertices, faces, match):
    with pytest.raises(SlscanError, match=match):
        build_atlas(vertices, faces)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"size": 32768}, "size"),
        ({"size": 16}, "size"),
        ({"padding": -1}, "padding"),
        ({"method": "magic"}, "method"),
        ({"directions": 7}, "directions"),
        ({"min_cos": 1.5}, "min_cos"),
        ({"fill": 2.0}, "fill"),
    ],
)
def test_bad_options_are_refused(kwargs, match):
    with pytest.raises(SlscanError, match=match):
        AtlasOptions(**kwargs)


def test_too_many_charts_for_the_page_is_an_error():
    """300 separate triangles cannot be 4 texels apart on a 64² page: it says so."""
    rng = np.random.default_rng(1)
    v = (rng.uniform(0, 100, (300, 1, 3)) + [[[0, 0, 0], [1, 0, 0], [0, 1, 0]]]).reshape(-1, 3)
    f = np.arange(900).reshape(300, 3)
    with pytest.raises(SlscanError, match="fit"):
        build_atlas(v, f, AtlasOptions(size=64, padding=4))
