"""Weak-line rejection of the hybrid decoder: the expected axis error from the line's SNR."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.decode.hybrid import estimate_noise, line_axis_sigma, subpixel_peaks
from slscan.decode.options import DEFAULT_ESTIMATOR
from slscan.decode.pipeline import DecodeConfig
from slscan.errors import SlscanError


def _lines(amplitude: float, *, sigma: float = 0.8, rows: int = 4000, seed: int = 0):
    """``rows`` rows of a Gaussian line (amplitude, sigma px) at a random sub-pixel centre
    near x = 20 on a 0.1 floor, with unit-free noise 0.01; returns signal, true centres."""
    rng = np.random.default_rng(seed)
    centre = 20.0 + rng.uniform(-0.5, 0.5, rows)
    x = np.arange(40)[None, :]
    g = 0.1 + amplitude * np.exp(-0.5 * ((x - centre[:, None]) / sigma) ** 2)
    return g + rng.normal(0.0, 0.01, g.shape), centre


@pytest.mark.parametrize("amplitude", [0.05, 0.2, 0.8])
def test_expected_axis_sigma_matches_the_measured_scatter(amplitude):
    g, centre = _lines(amplitude)
    rows = np.arange(len(g))
    cols = np.argmax(g[:, 15:26], axis=1) + 15
    x, ok = subpixel_peaks(g, rows, cols, estimator="gaussian")
    expected = line_axis_sigma(g, rows, cols, np.full(g.shape, 0.01))
    measured = np.std((x - centre)[ok])
    assert np.median(expected[ok]) == pytest.approx(measured, rel=0.35)


def _band_lines(snr: float, width: float, *, rows: int = 4000, seed: int = 0, shot: float = 0.0):
    """Gaussian lines (amplitude 1, ``width`` px) at random sub-pixel centres between bands
    where the line signal is 0, as the decoder sees them after unmixing; noise ``1 / snr``
    at zero signal, plus shot noise of variance ``shot * g``. Returns signal, noise sigma
    per pixel, true centres."""
    rng = np.random.default_rng(seed)
    centre = 20.0 + rng.uniform(-0.5, 0.5, rows)
    x = np.arange(40)[None, :]
    clean = np.exp(-0.5 * ((x - centre[:, None]) / width) ** 2)
    sigma = np.sqrt((1.0 / snr) ** 2 + shot * clean)
    return clean + sigma * rng.normal(0.0, 1.0, clean.shape), sigma, centre


@pytest.mark.parametrize("width", [0.6, 0.8, 1.0, 1.2])
@pytest.mark.parametrize("snr", [10, 30, 100])
def test_axis_sigma_predicts_the_default_estimators_error(width, snr):
    # known answer: the RMS of the predicted axis sigma over a line's samples is the RMS
    # error of the default (three-point Gaussian) estimator against the true centres
    g, noise, centre = _band_lines(snr, width, seed=int(10 * width) + snr)
    rows = np.arange(len(g))
    cols = np.argmax(g[:, 15:26], axis=1) + 15
    x, ok = subpixel_peaks(g, rows, cols, estimator=DEFAULT_ESTIMATOR)
    assert ok.mean() > 0.99
    predicted = np.sqrt(np.mean(line_axis_sigma(g, rows, cols, noise)[ok] ** 2))
    measured = np.sqrt(np.mean((x - centre)[ok] ** 2))
    assert measured == pytest.approx(predicted, rel=0.2)


def test_axis_sigma_uses_each_pixels_own_noise():
    # shot noise: the line's top is noisier than its flanks; the prediction follows the
    # per-pixel noise, and a flat noise of the peak's level overstates the error
    g, noise, centre = _band_lines(1000, 0.8, shot=4e-3, seed=5)
    rows = np.arange(len(g))
    cols = np.argmax(g[:, 15:26], axis=1) + 15
    x, ok = subpixel_peaks(g, rows, cols, estimator=DEFAULT_ESTIMATOR)
    measured = np.sqrt(np.mean((x - centre)[ok] ** 2))
    predicted = np.sqrt(np.mean(line_axis_sigma(g, rows, cols, noise)[ok] ** 2))
    flat = np.sqrt(np.mean(line_axis_sigma(g, rows, cols, np.full(g.shape, noise.max()))[ok] ** 2))
    assert measured == pytest.approx(predicted, rel=0.1)
    assert flat > 1.2 * measured


def test_a_weak_line_is_rejected_and_a_strong_one_kept():
    threshold = 0.05  # px
    weak, _ = _lines(0.05, rows=200)  # SNR 5: about 0.2 px
    strong, _ = _lines(0.8, rows=200)  # SNR 80: about 0.013 px
    for g, kept in ((weak, False), (strong, True)):
        rows = np.arange(len(g))
        cols = np.argmax(g[:, 15:26], axis=1) + 15
        sigma = line_axis_sigma(g, rows, cols, np.full(g.shape, 0.01))
        share = np.mean(sigma <= threshold)
        assert (share > 0.95) if kept else (share < 0.05)


def test_no_line_above_the_floor_is_never_kept():
    g = np.full((1, 20), 0.3)
    assert np.isinf(line_axis_sigma(g, np.array([0]), np.array([10]), np.full(g.shape, 0.01))).all()


def test_noise_model_recovers_shot_and_read_noise():
    rng = np.random.default_rng(1)
    h, w = 200, 300
    read, gain = 2.0, 0.05  # DN, DN² per DN
    level = np.linspace(50.0, 3000.0, w)[None, :, None] * np.array([1.0, 0.5, 0.2])
    mean = np.broadcast_to(level, (h, w, 3))
    white = 100.0 + mean + rng.normal(0.0, 1.0, (h, w, 3)) * np.sqrt(read**2 + gain * mean)
    black = 100.0 + rng.normal(0.0, read, (h, w, 3))
    a, b = estimate_noise(white, black, np.ones((h, w), bool))
    assert a == pytest.approx(read**2, rel=0.1)
    assert b == pytest.approx(gain, rel=0.1)


def test_negative_threshold_is_an_error():
    with pytest.raises(SlscanError, match="max_line_sigma"):
        DecodeConfig(max_line_sigma=-1.0)


@pytest.fixture(scope="module")
def small_tile(tmp_path_factory):
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    config = VirtualCaptureConfig(scene="tile", camera_scale=0.25, projector_scale=0.25, levels=6,
                                  patterns="hybrid", lit_images=False)
    return capture_session(config, tmp_path_factory.mktemp("weak") / "session")


def test_decoder_counts_weak_lines_and_keeps_strong_ones(small_tile):
    from slscan.decode.hybrid import decode_hybrid

    view = small_tile.views[0]
    off = decode_hybrid(small_tile, view)
    assert off.rejected["weak line"] == 0
    # the neutral tile's lines are strong (expected axis error about 0.01 px): all kept
    loose = decode_hybrid(small_tile, view, max_line_sigma=0.1)
    assert loose.rejected["weak line"] <= 0.01 * len(off.samples.x)
    assert len(loose.samples.x) >= 0.99 * len(off.samples.x)
    # a threshold no real line reaches rejects them all, counted as weak
    strict = decode_hybrid(small_tile, view, max_line_sigma=1e-4)
    assert len(strict.samples.x) == 0
    assert strict.rejected["weak line"] >= len(off.samples.x)


def test_decoder_rejects_a_negative_threshold(small_tile):
    from slscan.decode.hybrid import decode_hybrid

    with pytest.raises(SlscanError, match="max_line_sigma"):
        decode_hybrid(small_tile, small_tile.views[0], max_line_sigma=-0.1)


def test_decoders_axis_sigma_predicts_the_scatter_between_two_captures(small_tile, tmp_path):
    # known answer on the virtual rig: two captures of one view differ only in their noise
    # (every frame's: white, black and patterns), so the RMS of the axis difference over √2
    # is the noise's share of the axis error, which axis_sigma predicts per sample
    from slscan.decode.hybrid import decode_hybrid
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    config = VirtualCaptureConfig(scene="tile", camera_scale=0.25, projector_scale=0.25, levels=6,
                                  patterns="hybrid", lit_images=False, seed=1)
    other = capture_session(config, tmp_path / "again")
    a = decode_hybrid(small_tile, small_tile.views[0], axis_sigma=True)
    b = decode_hybrid(other, other.views[0], axis_sigma=True)
    assert a.axis_sigma is not None and len(a.axis_sigma) == len(a.samples)
    assert np.all(np.isfinite(a.axis_sigma)) and np.all(a.axis_sigma > 0)
    assert decode_hybrid(small_tile, small_tile.views[0]).axis_sigma is None  # only when asked
    key_a = a.samples.row.astype(np.int64) * 4096 + a.samples.stripe
    key_b = b.samples.row.astype(np.int64) * 4096 + b.samples.stripe
    _, ia, ib = np.intersect1d(key_a, key_b, return_indices=True)
    assert len(ia) > 0.9 * len(a.samples)
    scatter = np.sqrt(np.mean((a.samples.x[ia] - b.samples.x[ib]) ** 2) / 2.0)
    predicted = np.sqrt(np.mean(a.axis_sigma[ia] ** 2))
    assert scatter == pytest.approx(predicted, rel=0.2)
