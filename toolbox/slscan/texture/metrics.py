"""How good a baked texture is: against a reference texture (PSNR) and across seams."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slscan.texture.bake import _bilinear, rasterise_uv


def texel_points(vertices: np.ndarray, faces: np.ndarray, atlas) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices (k,) of the texels the atlas covers and their surface points (k, 3)."""
    texel, face, bary = rasterise_uv(np.asarray(atlas.uvs, np.float64) * atlas.size - 0.5, atlas.faces, atlas.size)
    corner = np.asarray(faces, np.int64)[face]
    points = np.einsum("kj,kjc->kc", bary.astype(np.float64), np.asarray(vertices, np.float64)[corner])
    return texel, points


def render_into_atlas(
    vertices: np.ndarray, faces: np.ndarray, atlas, color_at: Callable[[np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """A reference texture: ``color_at(points)`` (k, 3) at every covered texel's surface
    point. Returns the (size, size, 3) float32 image (0 outside charts) and the coverage mask."""
    size = atlas.size
    texel, points = texel_points(vertices, faces, atlas)
    image = np.zeros((size * size, 3), np.float32)
    image[texel] = color_at(points)
    covered = np.zeros(size * size, bool)
    covered[texel] = True
    return image.reshape(size, size, 3), covered.reshape(size, size)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio (dB) of two 8-bit images over ``mask`` (all pixels if None)."""
    d = a.astype(np.float64) - b.astype(np.float64)
    if mask is not None:
        d = d[mask]
    mse = float(np.mean(d * d)) if d.size else 0.0
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


@dataclass(frozen=True)
class SeamError:
    """Colour difference across chart boundaries, in 8-bit levels (mean over R, G, B).

    edges : seam edges measured; mean, p95 : over sample points along them
    """

    edges: int
    mean: float
    p95: float


def seam_edges(faces: np.ndarray, atlas) -> np.ndarray:
    """(e, 2, 2) pairs of atlas corner indices: for each model edge shared by two faces whose
    texture coordinates differ along it, its two ends in each face's atlas vertices —
    ``[[a0, a1], [b0, b1]]`` with a0/b0 the same model vertex."""
    faces = np.asarray(faces, np.int64)
    af = np.asarray(atlas.faces, np.int64)
    ends = [(0, 1), (1, 2), (2, 0)]
    model = np.concatenate([faces[:, list(e)] for e in ends])
    tex = np.concatenate([af[:, list(e)] for e in ends])
    key = np.sort(model, axis=1)
    flip = model[:, 0] > model[:, 1]
    tex = np.where(flip[:, None], tex[:, ::-1], tex)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, tex = key[order], tex[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    i = np.nonzero(same)[0]
    pairs = np.stack([tex[i], tex[i + 1]], axis=1)  # (e, 2 sides, 2 ends)
    uv = np.asarray(atlas.uvs, np.float64)
    differ = np.any(np.abs(uv[pairs[:, 0]] - uv[pairs[:, 1]]) > 1e-7, axis=(1, 2))
    return pairs[differ]


def seam_error(texture_srgb: np.ndarray, faces: np.ndarray, atlas, *, samples: int = 5) -> SeamError:
    """Colour difference between the two sides of every seam edge, sampled (bilinear) at
    ``samples`` points along the edge in each side's chart."""
    pairs = seam_edges(faces, atlas)
    if len(pairs) == 0:
        return SeamError(0, 0.0, 0.0)
    size = texture_srgb.shape[0]
    image = texture_srgb.astype(np.float32)
    uv = np.asarray(atlas.uvs, np.float64) * size - 0.5
    t = (np.arange(samples) + 0.5) / samples
    diffs = []
    for s in t:
        side = [(1 - s) * uv[pairs[:, k, 0]] + s * uv[pairs[:, k, 1]] for k in (0, 1)]
        ca, cb = (_bilinear(image, np.clip(p[:, 0], 0, size - 1), np.clip(p[:, 1], 0, size - 1)) for p in side)
        diffs.append(np.abs(ca - cb).mean(axis=1))
    d = np.concatenate(diffs)
    return SeamError(len(pairs), float(d.mean()), float(np.percentile(d, 95)))
