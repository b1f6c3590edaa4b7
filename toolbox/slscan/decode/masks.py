"""Pixel masks for decoding: which pixels the projector lights, and which captures clipped.

The shadow mask (the paper's "purge pixels in shadow") keeps the pixels whose white frame
stands clearly above the black frame; :func:`saturation` marks clipped pixels, and
:func:`saturation_report` says, per captured image, how many of the lit pixels and of the
measured line pixels clipped. Saturated green lines lose their sub-pixel profile and leave
ribs in the range map (paper Fig. 9), so decoders warn with :func:`warn_saturation`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from slscan.errors import SlscanError

log = logging.getLogger(__name__)

DEFAULT_MIN_CONTRAST = 0.02
"""Default shadow threshold: white − black, fraction of full scale (about 5 DN at 8 bit)."""

NOISE_SIGMAS = 6.0
"""The shadow threshold is also at least this many standard deviations of ``white − black``."""

SATURATION_WARNING = 0.01
"""Share of saturated line pixels above which decoders warn."""


def full_scale(image: np.ndarray, name: str = "image", *, bit_depth: int | None = None) -> float:
    """The largest pixel value of ``image``: ``2**bit_depth - 1`` or from its dtype.

    Floating-point images are taken to be in [0, 1].
    """
    if bit_depth is not None:
        if bit_depth not in (8, 16):
            raise SlscanError(f"{name}: bit depth must be 8 or 16, got {bit_depth}")
        return float(2**bit_depth - 1)
    if image.dtype == np.uint8:
        return 255.0
    if image.dtype == np.uint16:
        return 65535.0
    if np.issubdtype(image.dtype, np.floating):
        return 1.0
    raise SlscanError(
        f"{name}: pixels are {image.dtype}; expected uint8, uint16 or float in [0, 1]"
    )


def like_white(image: np.ndarray, white: np.ndarray, name: str, where: str = "") -> np.ndarray:
    """``image`` as an array; an error naming it (``where`` + ``name``) when its size,
    channels or pixel type differ from the view's white frame ``white``."""
    image = np.asarray(image)
    if image.shape != white.shape:
        raise SlscanError(
            f"{where}{name}: image is {shape_text(image.shape)}, "
            f"expected {shape_text(white.shape)} like the white image"
        )
    if image.dtype != white.dtype:
        raise SlscanError(
            f"{where}{name}: pixels are {image.dtype}, expected {white.dtype} like the white image"
        )
    return image


def shape_text(shape: tuple[int, ...]) -> str:
    """An image shape as people write it: ``1440x960`` or ``1440x960x3``."""
    text = f"{shape[1]}x{shape[0]}" if len(shape) >= 2 else str(shape)
    return text + (f"x{shape[2]}" if len(shape) == 3 else "")


def channel_max(image: np.ndarray) -> np.ndarray:
    """Per-pixel maximum over channels, (h, w); a grey (h, w) image is returned as is.

    (Channel by channel: several times faster than ``image.max(axis=2)`` on 3 channels.)
    """
    image = np.asarray(image)
    if image.ndim == 2:
        return image
    if image.ndim != 3:
        raise SlscanError(f"expected an (h, w) or (h, w, channels) image, got shape {image.shape}")
    out = image[..., 0].copy()
    for c in range(1, image.shape[2]):
        np.maximum(out, image[..., c], out=out)
    return out


def channel_mean(image: np.ndarray) -> np.ndarray:
    """Per-pixel mean over channels, (h, w) float32; a grey (h, w) image is converted as is.

    (Channel by channel, like :func:`channel_max`: about ten times faster than
    ``image.mean(axis=2)``, which reduces over a 3-long innermost axis.)
    """
    image = np.asarray(image)
    if image.ndim == 2:
        return image.astype(np.float32)
    if image.ndim != 3:
        raise SlscanError(f"expected an (h, w) or (h, w, channels) image, got shape {image.shape}")
    out = image[..., 0].astype(np.float32)
    for c in range(1, image.shape[2]):
        out += image[..., c]
    out *= np.float32(1.0 / image.shape[2])
    return out


def noise_sigma(black: np.ndarray) -> float:
    """Standard deviation (DN) of one frame's noise, from the black frame's pixel-to-pixel jitter.

    black : (h, w) or (h, w, c) the projector-black capture

    Uses the median absolute deviation of horizontal neighbour differences (scene texture
    under ambient light is smooth next to sensor noise), so one dark frame suffices.
    """
    step = max(1, np.shape(black)[0] // 64)  # 64 rows: the MAD to about 1 %
    b = channel_max(np.asarray(black)[::step]).astype(np.float32)
    d = np.diff(b, axis=1).ravel()
    if d.size == 0:
        return 0.0
    mad = float(np.median(np.abs(d - np.median(d))))
    return 1.4826 * mad / np.sqrt(2.0)


def shadow_mask(
    white: np.ndarray,
    black: np.ndarray,
    *,
    min_contrast: float = DEFAULT_MIN_CONTRAST,
    bit_depth: int | None = None,
    noise_sigmas: float = NOISE_SIGMAS,
) -> np.ndarray:
    """Pixels lit by the projector, (h, w) bool.

    white, black : (h, w) grey or (h, w, 3) RGB captures under projector white and black,
        uint8, uint16 or float in [0, 1]; the same shape and dtype
    min_contrast : the smallest ``white − black`` kept, as a fraction of full scale; taken
        per pixel over the channels' maximum, so strongly coloured surfaces (red paint
        reflects little green and blue) are kept on the strength of one channel
    bit_depth : {8, 16} when the values do not use their dtype's full range
    noise_sigmas : the threshold is also at least this many standard deviations of
        ``white − black`` (noise estimated from the black frame, :func:`noise_sigma`)

    Pixels in projector shadow, background and surfaces facing away see the same light in
    both frames and fall below the threshold.
    """
    white, black = np.asarray(white), np.asarray(black)
    if white.shape != black.shape:
        raise SlscanError(
            f"shadow mask: white image is {white.shape}, black image is {black.shape}"
        )
    if white.dtype != black.dtype:
        raise SlscanError(
            f"shadow mask: white image is {white.dtype}, black image is {black.dtype}"
        )
    if not 0 <= min_contrast < 1:
        raise SlscanError(
            "shadow mask: min_contrast must be a fraction of full scale in [0, 1), "
            f"got {min_contrast}"
        )
    scale = full_scale(white, "white image", bit_depth=bit_depth)
    if np.issubdtype(white.dtype, np.integer):
        # in the pixels' own type (5x faster than in floats); negative contrast reads 0,
        # below any threshold
        diff = np.maximum(white, black)
        diff -= black
    else:
        diff = white.astype(np.float32) - black.astype(np.float32)
    contrast = channel_max(diff)
    threshold = max(min_contrast * scale, noise_sigmas * np.sqrt(2.0) * noise_sigma(black))
    return contrast > threshold


def lit_bounds(mask: np.ndarray, margin: int, *, row_step: int = 1) -> tuple[slice, slice]:
    """The bounding box of ``mask``'s pixels grown by ``margin`` px, clamped to the image.

    mask : (h, w) bool, e.g. :func:`shadow_mask`
    margin : px added on every side (windows around a lit pixel stay inside the box)
    row_step : the first row is a multiple of this (row-subsampled statistics then see
        the same rows as on the whole image)

    Returns ``(rows, cols)`` slices; the whole image when nothing is lit. Decoders work on
    this box only: outside the mask every signal is zero anyway, and an object that fills
    a tenth of the frame costs a tenth of the arithmetic.
    """
    mask = np.asarray(mask, bool)
    h, w = mask.shape
    rows = np.flatnonzero(mask.any(axis=1))
    if len(rows) == 0:
        return slice(0, h), slice(0, w)
    cols = np.flatnonzero(mask[rows[0] : rows[-1] + 1].any(axis=0))
    y0 = max(0, int(rows[0]) - margin)
    y0 -= y0 % max(1, row_step)
    return (
        slice(y0, min(h, int(rows[-1]) + margin + 1)),
        slice(max(0, int(cols[0]) - margin), min(w, int(cols[-1]) + margin + 1)),
    )


def uncrop(values: np.ndarray, box: tuple[slice, slice], shape: tuple[int, int], fill) -> np.ndarray:
    """``values`` computed on ``image[box]`` put back into a ``shape`` image filled with ``fill``."""
    out = np.full(shape, fill, values.dtype)
    out[box] = values
    return out


def saturation(image: np.ndarray, *, bit_depth: int | None = None) -> np.ndarray:
    """Pixels (h, w) bool where any channel of ``image`` reached full scale.

    image : (h, w) or (h, w, c), uint8, uint16 or float in [0, 1]
    bit_depth : {8, 16}; full scale is ``2**bit_depth - 1`` (default: from the dtype)
    """
    image = np.asarray(image)
    scale = full_scale(image, "image", bit_depth=bit_depth)
    return channel_max(image) >= scale


@dataclass(frozen=True)
class SaturationReport:
    """How much of one captured image clipped.

    name : the image (pattern id or file name)
    masked_share : saturated share of the lit (masked) pixels, in [0, 1]
    line_share : saturated share of the pixels on measured green lines, in [0, 1]
        (NaN when the image has no line pixels)
    masked_pixels, line_pixels : how many pixels each share is taken over
    """

    name: str
    masked_share: float
    line_share: float
    masked_pixels: int
    line_pixels: int


def saturation_report(
    saturated: Mapping[str, np.ndarray],
    mask: np.ndarray,
    line_pixels: Mapping[str, np.ndarray] | np.ndarray | None = None,
) -> tuple[SaturationReport, ...]:
    """Per-image saturation of one view, in the order of ``saturated``.

    saturated : image name -> (h, w) bool clipped pixels (:func:`saturation` of the capture)
    mask : (h, w) bool lit pixels (:func:`shadow_mask`)
    line_pixels : (h, w) bool pixels on the measured lines, either one map for all images
        or per image name (images missing from the mapping use the union of the others)
    """
    mask = np.asarray(mask, bool)
    if isinstance(line_pixels, Mapping):
        maps = {k: np.asarray(v, bool) for k, v in line_pixels.items()}
        union = np.logical_or.reduce(list(maps.values())) if maps else np.zeros_like(mask)
    else:
        maps = {}
        union = np.zeros_like(mask) if line_pixels is None else np.asarray(line_pixels, bool)
    n_mask = int(mask.sum())
    reports = []
    for name, sat in saturated.items():
        sat = np.asarray(sat, bool)
        if sat.shape != mask.shape:
            raise SlscanError(f"{name}: saturation map is {sat.shape}, the mask is {mask.shape}")
        lines = maps.get(name, union)
        n_line = int(lines.sum())
        reports.append(
            SaturationReport(
                name=name,
                masked_share=float(np.count_nonzero(sat & mask)) / n_mask if n_mask else 0.0,
                line_share=float(np.count_nonzero(sat & lines)) / n_line
                if n_line
                else float("nan"),
                masked_pixels=n_mask,
                line_pixels=n_line,
            )
        )
    return tuple(reports)


def warn_saturation(
    reports: Iterable[SaturationReport], *, where: str = "", threshold: float = SATURATION_WARNING
) -> list[SaturationReport]:
    """Log a warning naming the images whose saturated line share exceeds ``threshold``.

    Returns the offending reports (empty when none).
    """
    bad = [r for r in reports if np.isfinite(r.line_share) and r.line_share > threshold]
    if bad:
        listing = ", ".join(f"{r.name} {100 * r.line_share:.1f} %" for r in bad)
        log.warning(
            "%ssaturated green-line pixels in %d image(s): %s; clipped lines lose their sub-pixel "
            "profile and leave ribs (paper Fig. 9): lower the exposure or the projector brightness",
            f"{where}: " if where else "",
            len(bad),
            listing,
        )
    return bad
