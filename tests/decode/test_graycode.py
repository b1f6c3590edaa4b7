"""Tests for Gray-code decoding: synthetic known answers, the virtual tile, real captures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slscan.capture.kamino410 import import_kamino410
from slscan.capture.session import LIT
from slscan.decode.graycode import decode_gray, decode_gray_images, gray_pairs
from slscan.errors import SlscanError
from slscan.patterns import graycode

# --- synthetic images with a known answer ----------------------------------------------------

PROJ = (64, 32)  # projector (width, height) px
CAM = (120, 56)  # camera (width, height) px
A_U, B_U = 0.5, 1.3  # projector column u(x) = A_U * x + B_U: two camera px per column
A_V, B_V = 0.5, 2.2  # projector row v(y) = A_V * y + B_V


def _box_bits(coord: np.ndarray, a: float, b: float, bits: int, bit: int) -> np.ndarray:
    """Gray-code bit ``bit`` seen by pixels at ``coord``, box-filtered over [x - 1, x + 1].

    A box of two pixels turns every isolated stripe edge into a linear ramp across the
    two pixels around it, so linear interpolation finds the edge exactly.
    """
    fine = np.linspace(-1, 1, 801)[1:] - 1 / 800  # midpoints of 800 sub-intervals
    u = a * (coord[:, None] + fine[None, :]) + b
    on = (graycode.gray(np.floor(u + 0.5).astype(np.int64)) >> (bits - 1 - bit)) & 1
    return on.mean(axis=1)


def _synthetic(dtype, channels: int, rows: bool = True):
    """Images of a flat scene where u = A_U x + B_U, v = A_V y + B_V; white 0.6, black 0.05."""
    descs = graycode.generate(*PROJ, rows=rows)
    w, h = CAM
    full = float(np.iinfo(dtype).max)
    tint = np.array([0.9, 1.0, 0.7])[:channels] if channels == 3 else np.ones(1)
    white_level, black_level = 0.6, 0.05

    def to_image(signal_2d: np.ndarray) -> np.ndarray:
        level = black_level + (white_level - black_level) * signal_2d
        img = np.rint(level[..., None] * tint * full).astype(dtype)
        return img[..., 0] if channels == 1 else img

    images = {}
    for d in descs:
        bits, bit = d.params["bits"], d.params["bit"]
        if d.axis == "columns":
            s = np.broadcast_to(
                _box_bits(np.arange(w, dtype=float), A_U, B_U, bits, bit)[None, :], (h, w)
            )
        else:
            s = np.broadcast_to(
                _box_bits(np.arange(h, dtype=float), A_V, B_V, bits, bit)[:, None], (h, w)
            )
        images[d.id] = to_image(1 - s if d.params["inverse"] else s)
    return images, descs, to_image(np.ones((h, w))), to_image(np.zeros((h, w)))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3])
def test_synthetic_known_answer(dtype, channels):
    images, descs, white, black = _synthetic(dtype, channels)
    res = decode_gray_images(images, descs, white, black)
    x = np.arange(CAM[0], dtype=float)
    u = A_U * x + B_U
    v = A_V * np.arange(CAM[1], dtype=float) + B_V
    # pixels whose two-pixel box holds no stripe edge decode exactly
    far_u = np.abs(u - np.floor(u) - 0.5) > A_U
    far_v = np.abs(v - np.floor(v) - 0.5) > A_V
    expected_col = np.floor(u + 0.5).astype(int)
    expected_row = np.floor(v + 0.5).astype(int)
    assert np.all(res.column[:, far_u] == expected_col[far_u])
    assert np.all(res.row[far_v, :] == expected_row[far_v][:, None])
    assert res.mask[np.ix_(far_v, far_u)].all()
    decoded = res.column >= 0
    assert np.all(res.column[decoded] == np.broadcast_to(expected_col, res.column.shape)[decoded])
    # every column boundary inside the image, in every row, at its exact position
    e = res.edges
    boundaries = np.arange(int(np.ceil(u[0] - 0.5)), int(np.floor(u[-1] - 0.5)) + 1)
    interior = boundaries  # every boundary lies between two pixels of the image
    assert len(e) == CAM[1] * len(interior)
    assert np.array_equal(np.unique(e.stripe), interior)
    np.testing.assert_array_equal(e.projector_column, e.stripe + 0.5)
    truth_x = (e.projector_column - B_U) / A_U
    assert np.max(np.abs(e.x - truth_x)) < 0.01
    assert not e.saturated.any()
    # edge swing |d(x0)| + |d(x0 + 1)| over white(x0) + white(x0 + 1): 0.55 / 1.2 for these ramps
    np.testing.assert_allclose(e.contrast, 0.55 / 1.2, atol=0.01)


def test_unlit_border_changes_nothing_but_the_coordinates():
    # decoding runs on the lit pixels' bounding box: a dark frame only moves the results
    images, descs, white, black = _synthetic(np.uint8, 3)
    a = decode_gray_images(images, descs, white, black, noise=0.01)
    pad = ((6, 3), (11, 4), (0, 0))
    b = decode_gray_images(
        {k: np.pad(v, pad) for k, v in images.items()}, descs, np.pad(white, pad), np.pad(black, pad),
        noise=0.01,
    )
    inner = (slice(6, -3), slice(11, -4))
    for name in ("column", "row", "mask", "contrast", "saturated"):
        np.testing.assert_array_equal(getattr(b, name)[inner], getattr(a, name))
    assert (b.column[:6] == -1).all() and not b.mask[:, -4:].any()
    np.testing.assert_array_equal(b.edges.row, a.edges.row + 6)
    np.testing.assert_allclose(b.edges.x, a.edges.x + 11, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(b.edges.stripe, a.edges.stripe)


def test_columns_only_gives_no_row():
    images, descs, white, black = _synthetic(np.uint8, 1, rows=False)
    res = decode_gray_images(images, descs, white, black)
    assert res.row is None
    assert res.mask.mean() > 0.3


def test_dark_and_saturated_pixels():
    images, descs, white, black = _synthetic(np.uint8, 1)
    white, black = white.copy(), black.copy()
    white[:, :10] = black[:, :10]  # no contrast: shadow
    images = {k: v.copy() for k, v in images.items()}
    images[descs[0].id][:, 50:52] = 255  # clipped in one image
    white[:, 50:52] = 255
    res = decode_gray_images(images, descs, white, black)
    assert not res.mask[:, :10].any()
    assert np.all(res.column[:, :10] == -1)
    assert res.saturated[:, 50:52].all() and not res.saturated[:, :50].any()
    xa = np.floor(res.edges.x)
    touches = (xa + 1 >= 50) & (xa <= 51)  # an interpolation pixel is clipped
    assert touches.any()
    assert res.edges.saturated[touches].all() and not res.edges.saturated[~touches].any()


def test_missing_inverse_is_an_error():
    images, descs, white, black = _synthetic(np.uint8, 1)
    without = [d for d in descs if d.id != "gray-col-03-inv"]
    with pytest.raises(SlscanError, match="columns bit 3 has no inverse.*gray-col-03"):
        decode_gray_images(images, without, white, black)
    with pytest.raises(SlscanError, match="gray-col-03-inv"):
        decode_gray_images(
            {k: v for k, v in images.items() if k != "gray-col-03-inv"}, descs, white, black
        )


def test_mismatched_images_are_errors():
    images, descs, white, black = _synthetic(np.uint8, 1)
    bad = dict(images, **{"gray-row-01": images["gray-row-01"][:-1]})
    with pytest.raises(SlscanError, match="view_x: gray-row-01: image is 120x55, expected 120x56"):
        decode_gray_images(bad, descs, white, black, where="view_x")
    bad = dict(images, **{"gray-col-00": images["gray-col-00"].astype(np.uint16)})
    with pytest.raises(SlscanError, match="gray-col-00: pixels are uint16, expected uint8"):
        decode_gray_images(bad, descs, white, black)
    with pytest.raises(SlscanError, match="no Gray-code column patterns"):
        decode_gray_images(images, [d for d in descs if d.axis == "rows"], white, black)


def test_gray_pairs_order():
    descs = graycode.generate(1024, 768, rows=True)
    cols = gray_pairs(descs, "columns")
    assert len(cols) == 10 and cols[0] == ("gray-col-00", "gray-col-00-inv")
    assert len(gray_pairs(descs, "rows")) == 10
    assert gray_pairs(graycode.generate(1024, 768), "rows") == []


# --- the virtual tile ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tile(gray_tile_session):
    session = gray_tile_session
    view = session.views[0]
    return session, view, session.load_ground_truth(view), decode_gray(session, view)


def _interior(visibility: np.ndarray) -> np.ndarray:
    """Lit pixels whose 3x3 neighbourhood is lit too (no silhouette or shadow mixing)."""
    lit = visibility == LIT
    out = lit.copy()
    out[1:-1, 1:-1] = np.all(
        [
            lit[1 + dy : lit.shape[0] - 1 + dy, 1 + dx : lit.shape[1] - 1 + dx]
            for dy in (-1, 0, 1)
            for dx in (-1, 0, 1)
        ],
        axis=0,
    )
    out[[0, -1], :] = out[:, [0, -1]] = False
    return out


def test_tile_columns_match_truth(tile):
    session, view, truth, res = tile
    u = truth.projector_uv[..., 0].astype(np.float64)
    interior = _interior(truth.visibility)
    assert res.mask[interior].mean() > 0.8
    # distance (camera px) from each pixel centre to the nearest column boundary
    du_dx = np.abs(np.gradient(u, axis=1))
    to_edge = np.abs(u - np.floor(u) - 0.5) / du_dx
    check = interior & res.mask & (to_edge > 0.5)
    correct = res.column[check] == np.floor(u[check] + 0.5)
    assert check.sum() > 1500  # ~1.2 camera px per column: few pixels are far from an edge
    assert correct.mean() > 0.99
    everywhere = interior & res.mask
    assert (res.column[everywhere] == np.floor(u[everywhere] + 0.5)).mean() > 0.95
    assert res.row is None  # the virtual rig projected no row codes
    # the white frame comes back as read, for the range map's colours
    np.testing.assert_array_equal(res.white, session.read_image(view, view.image_for("white")))


def _truth_crossings(
    u: np.ndarray, rows: np.ndarray, xs: np.ndarray, level: np.ndarray
) -> np.ndarray:
    """Camera x where the row's truth projector column, linearly interpolated, equals ``level``."""
    x0 = np.floor(xs).astype(int)
    out = np.full(len(xs), np.nan)
    for shift in (0, -1, 1):
        xa = np.clip(x0 + shift, 0, u.shape[1] - 2)
        ua, ub = u[rows, xa], u[rows, xa + 1]
        inside = np.isnan(out) & ((ua - level) * (ub - level) <= 0) & (ua != ub)
        out[inside] = xa[inside] + (level[inside] - ua[inside]) / (ub[inside] - ua[inside])
    return out


def test_tile_edges_subpixel(tile):
    _, _, truth, res = tile
    e = res.edges
    u = truth.projector_uv[..., 0].astype(np.float64)
    interior = _interior(truth.visibility)
    xa = np.floor(e.x).astype(int)
    inner = interior[e.row, xa] & interior[e.row, np.minimum(xa + 1, u.shape[1] - 1)]
    truth_x = _truth_crossings(u, e.row, e.x, e.projector_column)
    err = (e.x - truth_x)[inner]
    assert inner.sum() > 5000 and np.isfinite(err).all()
    rms = float(np.sqrt(np.mean(err**2)))
    assert rms < 0.1, rms  # about 0.034 px (linear interpolation's pixel-locking)
    # nearly every boundary the truth crosses inside the tile has its sample
    found = set(zip(e.row.tolist(), e.stripe.tolist()))
    expected = set()
    for r in range(0, u.shape[0], 7):
        cols = np.flatnonzero(interior[r, :-1] & interior[r, 1:])
        ua, ub = u[r, cols], u[r, cols + 1]
        lo, hi = np.floor(np.minimum(ua, ub) - 0.5), np.floor(np.maximum(ua, ub) - 0.5)
        expected |= {(r, int(c)) for c in lo[hi > lo]}
    assert len(expected) > 500
    assert len(expected & found) / len(expected) > 0.97


# --- real captures ------------------------------------------------------------------------------


def test_real_capture_0(shared_data: Path, tmp_path: Path):
    src = shared_data / "procam_graycode_kamino410" / "sample_data" / "capture_0"
    if not src.is_dir():
        pytest.skip(f"real data not found: {src}")
    session = import_kamino410(src, tmp_path / "session")
    res = decode_gray(session, session.views[0])
    assert res.column.shape == (1024, 1280) and res.row is not None
    assert res.mask.mean() > 0.3
    c, m = res.column, res.mask
    pair = m[:, 1:] & m[:, :-1]
    step = (c[:, 1:] - c[:, :-1])[pair]
    assert (step >= 0).mean() > 0.95
    # rows decode too and increase down the image
    r = res.row
    pair = m[1:, :] & m[:-1, :]
    assert ((r[1:, :] - r[:-1, :])[pair] >= 0).mean() > 0.95
    assert len(res.edges) > 100_000
    assert np.all(np.diff(res.edges.row) >= 0)
