"""Surface distances and texture differences on synthetic models with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.recipe.surfaces import (
    MAX_PSNR,
    Surface,
    read_surface,
    surface_distance,
    texture_difference,
    write_surface,
)


def _grid(
    n: int = 20, size: float = 100.0, z: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat n x n grid of squares in the plane z, its triangles and (u, v) in [0, 1]."""
    t = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(t, t)
    vertices = np.stack([u.ravel() * size, v.ravel() * size, np.full(u.size, z)], axis=1)
    k = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    faces = np.concatenate(
        [np.stack([k, k + 1, k + n + 2], 1), np.stack([k, k + n + 2, k + n + 1], 1)]
    )
    return vertices, faces, np.stack([u.ravel(), v.ravel()], axis=1)


def _painted(size: int = 64) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size]
    return np.stack([x * 3 % 256, y * 2 % 256, (x + y) % 256], axis=2).astype(np.uint8)


def test_parallel_planes_are_their_offset_apart():
    v, f, _ = _grid()
    a, b = Surface(v, f), Surface(v + [0.0, 0.0, 0.3], f)
    mean, p95 = surface_distance(a, b)
    assert mean == pytest.approx(0.3, abs=1e-4) and p95 == pytest.approx(0.3, abs=1e-4)
    assert surface_distance(a, a) == pytest.approx((0.0, 0.0), abs=1e-5)


def test_point_to_surface_not_vertex_to_vertex():
    # the same plane, triangulated at another density: no distance at all
    v, f, _ = _grid(20)
    w, g, _ = _grid(7)
    assert surface_distance(Surface(v, f), Surface(w, g)) == pytest.approx((0.0, 0.0), abs=1e-4)


def test_an_empty_surface_is_infinitely_far():
    v, f, _ = _grid()
    assert surface_distance(Surface(v, f), Surface(v, f[:0])) == (np.inf, np.inf)


def test_texture_colours_do_not_depend_on_the_atlas_layout():
    v, f, uv = _grid()
    image = _painted()
    a = Surface(v, f, uv, image)
    # the same colours in a mirrored atlas with mirrored texture coordinates
    b = Surface(v, f, np.stack([1.0 - uv[:, 0], uv[:, 1]], axis=1), image[:, ::-1].copy())
    diff = texture_difference(a, b)
    assert diff.seen_psnr == MAX_PSNR and diff.seen_share == 1.0
    # every colour 4 levels brighter: PSNR 20 log10(255 / 4)
    brighter = Surface(v, f, uv, np.clip(image.astype(int) + 4, 0, 255).astype(np.uint8))
    expected = 20 * np.log10(255 / 4)
    assert texture_difference(a, brighter).seen_psnr == pytest.approx(expected, abs=0.3)


def test_colours_no_view_saw_are_compared_apart():
    v, f, uv = _grid()
    image = _painted()
    seen = np.ones(image.shape[:2], bool)
    seen[:, 32:] = False  # the right half of the atlas was filled in
    changed = image.copy()
    changed[:, 40:] //= 2
    diff = texture_difference(Surface(v, f, uv, image, seen), Surface(v, f, uv, changed, seen))
    assert diff.seen_psnr == MAX_PSNR and diff.filled_psnr < 20
    assert diff.seen_share == pytest.approx(0.5, abs=0.05)


def test_reference_surfaces_round_trip(tmp_path):
    v, f, uv = _grid(5)
    path = write_surface(tmp_path / "model.ply", Surface(v, f, uv), texture_file="model_albedo.png")
    back = read_surface(path)
    assert np.allclose(back.vertices, v, atol=1e-5) and np.array_equal(back.faces, f)
    assert np.allclose(back.uvs, uv, atol=1e-6)
    assert b"TextureFile model_albedo.png" in path.read_bytes()[:400]
