"""The neighbour check of fringe orders says, per pixel, what it corrected or rejected."""

from __future__ import annotations

import numpy as np

from slscan.decode.phase import fix_orders, order_fixes


def test_order_fixes_mark_corrected_and_rejected_pixels():
    period = 32.0
    ys, xs = np.mgrid[0:20, 0:30]
    truth = 100.0 + 0.8 * xs + 0.1 * ys  # a smooth surface: projector px
    coord = truth.copy()
    coord[5, 5] += period  # an order misread by one period (moved back down)
    coord[12, 20] -= period  # ... and the other way (moved up)
    coord[15, 10] += 0.5 * period  # agrees with no neighbour, at no whole period: rejected
    coord[0, 0:3] = np.nan  # not decoded
    valid = np.isfinite(coord)

    fixed, ok, corrected, rejected = fix_orders(coord, valid, period)
    fix = order_fixes(coord, fixed, ok, period)

    assert fix.dtype == np.int8 and fix.shape == coord.shape
    assert (corrected, rejected) == (2, 1)
    assert fix[5, 5] == -1 and fix[12, 20] == 1 and fix[15, 10] == 2
    assert np.count_nonzero(fix) == 3  # every other pixel, decoded or not, untouched
    assert not ok[15, 10] and ok[5, 5] and ok[12, 20]
    np.testing.assert_allclose(fixed[ok], truth[ok])
