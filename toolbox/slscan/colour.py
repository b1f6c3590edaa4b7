"""Colour encodings shared by the stages and the viewer: 8-bit sRGB, 16-bit linear albedo PNGs.

Albedo is linear RGB reflectance in [0, 1]. It is stored losslessly as a 16-bit PNG of
``round(albedo * 65535)`` (:func:`albedo_png`, read back by :func:`read_albedo_png`)
and shown, exported as a texture or written as PLY vertex colours as 8-bit sRGB
(:func:`srgb8`).
"""

from __future__ import annotations

import os

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import read_png


def srgb8(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB (..., 3) of linear RGB in [0, 1]; NaN becomes 0."""
    c = np.clip(np.nan_to_num(linear, nan=0.0), 0.0, 1.0)
    encoded = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return np.round(encoded * 255).astype(np.uint8)


def albedo_png(albedo: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """16-bit linear RGB pixels (h, w, 3): ``round(albedo * 65535)``, 0 where invalid."""
    a = np.where(valid[..., None], np.clip(np.nan_to_num(albedo, nan=0.0), 0.0, 1.0), 0.0)
    return np.round(a * 65535).astype(np.uint16)


def read_albedo_png(
    path: str | os.PathLike, valid_path: str | os.PathLike | None = None
) -> np.ndarray:
    """Linear albedo (h, w, 3) float32 from a PNG written by
    :func:`slscan.albedo.unshade.albedo_session`; NaN where the ``VIEW_valid.png`` mask
    (if given) is 0."""
    image = read_png(path)
    if image.dtype != np.uint16 or image.ndim != 3:
        raise SlscanError(f"{path}: expected a 16-bit RGB albedo image")
    out = image.astype(np.float32) / 65535.0
    if valid_path is not None:
        out[read_png(valid_path) == 0] = np.nan
    return out


# --- views per texel, as a picture --------------------------------------------------------------

VIEW_COUNT_OUTSIDE = (0, 0, 0)
"""Colour of the texels outside every chart of the atlas."""
VIEW_COUNT_FILLED = (110, 110, 110)
"""Colour of the texels no view saw (filled from the vertex colours)."""


def view_count_colours(max_views: int) -> np.ndarray:
    """(max_views + 1, 3) uint8 sRGB: row ``k`` is the colour of a texel blended from ``k``
    views: grey for 0 (filled from the vertex colours), then Turbo from blue (1 view) to
    red (``max_views``)."""
    import cv2

    n = max(int(max_views), 1)
    t = np.linspace(0.2, 1.0, n) if n > 1 else np.array([0.6])
    turbo = cv2.applyColorMap(np.round(t * 255).astype(np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1]
    return np.vstack([np.array([VIEW_COUNT_FILLED], np.uint8), turbo.astype(np.uint8)])


def view_count_image(count: np.ndarray, covered: np.ndarray | None, max_views: int) -> np.ndarray:
    """The views blended per texel as a picture (h, w, 3) uint8 sRGB: :func:`view_count_colours`
    inside the charts, black outside.

    count : (h, w) int, views per texel; covered : (h, w) bool, texels inside the charts
        (None: the texels with a count)
    max_views : the top of the colour ramp (the number of views); higher counts take its colour
    """
    count = np.asarray(count)
    colours = view_count_colours(max_views)
    picture = colours[np.clip(count, 0, len(colours) - 1).astype(np.intp)]
    inside = count > 0 if covered is None else np.asarray(covered, bool)
    picture[~inside] = VIEW_COUNT_OUTSIDE
    return picture


def view_count_legend(max_views: int) -> dict[str, list[int]]:
    """What each colour of :func:`view_count_image` means, for ``texture.json`` and the viewer."""
    colours = view_count_colours(max_views)
    legend = {"outside the charts": list(VIEW_COUNT_OUTSIDE), "0 views (filled from the vertex colours)":
              colours[0].tolist()}
    legend |= {f"{k} view{'s' if k > 1 else ''}": colours[k].tolist() for k in range(1, len(colours))}
    return legend
