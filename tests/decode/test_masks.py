"""Shadow and saturation masks on synthetic frames with known answers."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from slscan.decode.masks import (
    SaturationReport,
    channel_max,
    channel_mean,
    lit_bounds,
    noise_sigma,
    saturation,
    saturation_report,
    shadow_mask,
    warn_saturation,
)
from slscan.errors import SlscanError

DTYPES = [np.uint8, np.uint16, np.float32]


def _scale(dtype) -> float:
    return 1.0 if np.issubdtype(dtype, np.floating) else float(np.iinfo(dtype).max)


def _frames(dtype, channels: int, *, contrast: float = 0.3, noise: float = 0.0, seed: int = 0):
    """White and black frames (40, 60[, c]): lit block at rows 10..29, columns 20..49."""
    rng = np.random.default_rng(seed)
    shape = (40, 60) if channels == 1 else (40, 60, channels)
    scale = _scale(dtype)
    black = np.full(shape, 0.02 * scale) + noise * scale * rng.standard_normal(shape)
    white = np.full(shape, 0.02 * scale) + noise * scale * rng.standard_normal(shape)
    lit = np.zeros((40, 60), bool)
    lit[10:30, 20:50] = True
    if channels == 1:
        white[lit] += contrast * scale
    else:
        # a strongly coloured surface: only the red channel comes back
        white[lit, 0] += contrast * scale
    if np.issubdtype(dtype, np.integer):
        white, black = np.clip(np.rint(white), 0, scale), np.clip(np.rint(black), 0, scale)
    return white.astype(dtype), black.astype(dtype), lit


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("channels", [1, 3])
def test_shadow_mask_finds_the_lit_block(dtype, channels):
    white, black, lit = _frames(dtype, channels)
    np.testing.assert_array_equal(shadow_mask(white, black), lit)


def test_lit_bounds_grow_by_the_margin_and_stay_in_the_image():
    mask = np.zeros((40, 60), bool)
    mask[10:30, 20:50] = True
    mask[12, 15] = True  # one lone pixel widens the box
    assert lit_bounds(mask, 3) == (slice(7, 33), slice(12, 53))
    assert lit_bounds(mask, 3, row_step=4) == (slice(4, 33), slice(12, 53))  # starts on a multiple
    assert lit_bounds(mask, 50) == (slice(0, 40), slice(0, 60))
    assert lit_bounds(np.zeros((5, 6), bool), 2) == (slice(0, 5), slice(0, 6))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_shadow_mask_threshold_is_relative_to_full_scale(dtype):
    white, black, lit = _frames(dtype, 3, contrast=0.05)
    assert shadow_mask(white, black, min_contrast=0.04).sum() == lit.sum()
    assert not shadow_mask(white, black, min_contrast=0.06).any()


def test_shadow_mask_threshold_rises_above_noise():
    # 16-bit frames with noise of 1 % of full scale: a 3 % step is within 6 sigma of
    # ``white - black`` and must not pass, a 30 % one must
    white, black, lit = _frames(np.uint16, 1, contrast=0.03, noise=0.01)
    sigma = noise_sigma(black)
    assert sigma == pytest.approx(0.01 * 65535, rel=0.15)
    assert shadow_mask(white, black, min_contrast=0.001).sum() < 0.05 * lit.sum()
    white, black, lit = _frames(np.uint16, 1, contrast=0.3, noise=0.01)
    mask = shadow_mask(white, black, min_contrast=0.001)
    assert (mask == lit).mean() > 0.999


def test_shadow_mask_rejects_mismatched_frames():
    white, black, _ = _frames(np.uint8, 3)
    with pytest.raises(SlscanError, match="black image"):
        shadow_mask(white, black[:, :-1])
    with pytest.raises(SlscanError, match="uint16"):
        shadow_mask(white, black.astype(np.uint16))
    with pytest.raises(SlscanError, match="min_contrast"):
        shadow_mask(white, black, min_contrast=1.5)


def test_channel_max_matches_numpy():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 255, (7, 9, 3), dtype=np.uint8)
    np.testing.assert_array_equal(channel_max(image), image.max(axis=2))
    np.testing.assert_array_equal(channel_max(image[..., 0]), image[..., 0])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_channel_mean_matches_numpy(dtype):
    rng = np.random.default_rng(2)
    image = rng.integers(0, np.iinfo(dtype).max, (7, 9, 3), dtype=dtype)
    mean = channel_mean(image)
    assert mean.dtype == np.float32
    np.testing.assert_allclose(mean, image.mean(axis=2), rtol=1e-6)
    np.testing.assert_array_equal(channel_mean(image[..., 1]), image[..., 1].astype(np.float32))
    with pytest.raises(SlscanError, match="got shape"):
        channel_mean(image[None])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_saturation_marks_pixels_clipped_in_any_channel(dtype):
    top = np.iinfo(dtype).max
    image = np.zeros((4, 5, 3), dtype)
    image[1, 2, 1] = top
    image[3, 4] = top
    image[0, 0, 0] = top - 1
    expected = np.zeros((4, 5), bool)
    expected[1, 2] = expected[3, 4] = True
    np.testing.assert_array_equal(saturation(image), expected)
    np.testing.assert_array_equal(saturation(image[..., 1]), expected)  # grey
    np.testing.assert_array_equal(np.argwhere(saturation(image[..., 0])), [[3, 4]])


def test_saturation_honours_bit_depth():
    image = np.full((2, 2), 255, np.uint16)  # 8-bit values stored in 16-bit containers
    assert saturation(image, bit_depth=8).all()
    assert not saturation(image).any()
    with pytest.raises(SlscanError, match="bit depth"):
        saturation(image, bit_depth=12)


def test_saturation_report_shares():
    mask = np.zeros((10, 10), bool)
    mask[:, :5] = True  # 50 lit pixels
    lines = np.zeros((10, 10), bool)
    lines[:, 2] = True  # 10 line pixels
    sat_a = np.zeros((10, 10), bool)
    sat_a[:5, 2] = True  # 5 of the line pixels, 5 of the lit ones
    sat_a[:, 8] = True  # outside the mask: not counted
    sat_b = np.zeros((10, 10), bool)
    report = saturation_report({"a.png": sat_a, "b.png": sat_b}, mask, {"a.png": lines})
    a, b = report
    assert a == SaturationReport("a.png", 0.1, 0.5, 50, 10)
    # an image without its own line map is judged on the union of the others
    assert b == SaturationReport("b.png", 0.0, 0.0, 50, 10)
    (c,) = saturation_report({"c.png": sat_a}, mask)
    assert np.isnan(c.line_share) and c.line_pixels == 0


def test_warn_saturation_names_the_images(caplog):
    reports = (
        SaturationReport("00_white.png", 0.2, 0.3, 100, 10),
        SaturationReport("02_hybrid-01.png", 0.0, 0.005, 100, 10),
        SaturationReport("03_hybrid-02.png", 0.1, 0.25, 100, 10),
    )
    with caplog.at_level(logging.WARNING, logger="slscan.decode.masks"):
        bad = warn_saturation(reports, where="view_000")
    assert [r.name for r in bad] == ["00_white.png", "03_hybrid-02.png"]
    (record,) = caplog.records
    assert "view_000" in record.getMessage()
    assert "00_white.png 30.0 %" in record.getMessage()
    assert "03_hybrid-02.png 25.0 %" in record.getMessage()
    assert "hybrid-01" not in record.getMessage()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="slscan.decode.masks"):
        assert warn_saturation(reports[1:2]) == []
    assert not caplog.records
