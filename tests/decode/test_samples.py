"""Stripe samples: smoothing positions along their feature."""

from __future__ import annotations

import numpy as np

from slscan.decode.samples import StripeSamples


def _edges(rows: np.ndarray, stripes: np.ndarray, x: np.ndarray, along: np.ndarray | None = None) -> StripeSamples:
    n = len(rows)
    return StripeSamples(rows.astype(np.int32), x.astype(np.float64), stripes + 0.5, stripes.astype(np.int32),
                         np.ones(n, np.float32), np.zeros(n, bool),
                         y=None if along is None else np.where(along, x, rows).astype(np.float64),
                         along_columns=along)


def test_smoothing_keeps_slanted_edges_and_averages_their_noise():
    rng = np.random.default_rng(3)
    rows = np.repeat(np.arange(200), 20)
    stripes = np.tile(np.arange(20), 200)
    true_x = 30.0 * stripes + 0.37 * rows + 5.0  # straight edges slanted by 0.37 px a row
    noise = rng.normal(0, 0.1, len(rows))
    clean = _edges(rows, stripes, true_x)
    np.testing.assert_allclose(clean.smoothed().x, true_x, atol=1e-12)  # slant kept exactly
    noisy = _edges(rows, stripes, true_x + noise).smoothed()
    inner = (rows > 0) & (rows < 199)
    ratio = np.std((noisy.x - true_x)[inner]) / np.std(noise[inner])
    assert abs(ratio - np.sqrt(6) / 4) < 0.03
    # the first and last rows have one neighbour: kept as they are
    np.testing.assert_array_equal(noisy.x[~inner], (true_x + noise)[~inner])


def test_smoothing_stops_at_depth_steps_and_missing_neighbours():
    rows = np.array([0, 1, 2, 3, 4, 0, 1, 3, 4])
    stripes = np.array([7, 7, 7, 7, 7, 8, 8, 8, 8])
    x = np.array([10.0, 10.2, 10.0, 25.0, 25.1, 40.0, 40.5, 41.0, 41.5])
    out = _edges(rows, stripes, x).smoothed()
    # row 1 of stripe 7: both neighbours near -> (10 + 2 * 10.2 + 10) / 4; row 2: row 3 jumped 15 px
    np.testing.assert_allclose(out.x[:5], [10.0, 10.1, 10.0, 25.0, 25.1])
    # stripe 8 misses row 2: rows 1 and 3 have one neighbour each
    np.testing.assert_array_equal(out.x[5:], x[5:])


def test_samples_found_along_columns_are_smoothed_along_columns():
    cols = np.repeat(np.arange(50), 3)
    stripes = np.tile(np.arange(3), 50)
    y = 40.0 * stripes + 0.5 * cols + 3.2
    along = np.ones(len(cols), bool)
    s = StripeSamples(np.rint(y).astype(np.int32), cols.astype(np.float64), stripes + 0.5, stripes.astype(np.int32),
                      np.ones(len(cols), np.float32), np.zeros(len(cols), bool), y=y + np.where(cols == 10, 0.4, 0.0),
                      along_columns=along)
    out = s.smoothed()
    np.testing.assert_array_equal(out.x, s.x)  # the column stays
    hit = cols == 10
    np.testing.assert_allclose(out.y[hit], y[hit] + 0.2)  # the bump halved
    np.testing.assert_allclose(out.y[(cols == 9) | (cols == 11)], y[(cols == 9) | (cols == 11)] + 0.1)
    np.testing.assert_array_equal(out.row, np.rint(out.y).astype(np.int32))
