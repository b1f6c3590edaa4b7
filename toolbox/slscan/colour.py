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
