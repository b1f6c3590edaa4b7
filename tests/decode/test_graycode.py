"""Tests for Gray-code decoding: synthetic known answers, the virtual tile, real captures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slscan.capture.kamino410 import import_kamino410
from slscan.capture.session import LIT
from slscan.decode.graycode import (
    _nearest_on,
    _nearest_shifted,
    decode_gray,
    decode_gray_images,
    gray_pairs,
)
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


# --- both camera axes, missing bits, thresholds ------------------------------------------------


def _transposed(images, white, black):
    """The same captures seen by a camera turned 90 degrees: stripes horizontal."""
    t = {k: np.ascontiguousarray(np.swapaxes(v, 0, 1)) for k, v in images.items()}
    return t, np.ascontiguousarray(np.swapaxes(white, 0, 1)), np.ascontiguousarray(np.swapaxes(black, 0, 1))


def test_rotated_stripes_give_edges_along_columns():
    images, descs, white, black = _synthetic(np.uint8, 1, rows=False)
    upright = decode_gray_images(images, descs, white, black)
    # vertical stripes: every edge along rows, exactly as the row-only search finds them
    assert upright.edges.along_columns is None and upright.edges.y is None
    rows_only = decode_gray_images(images, descs, white, black, edge_axes="rows")
    for name in ("row", "x", "stripe", "contrast", "saturated"):
        np.testing.assert_array_equal(getattr(upright.edges, name), getattr(rows_only.edges, name))
    turned = decode_gray_images(*_transposed(images, white, black)[:1], descs,
                                *_transposed(images, white, black)[1:])
    e = turned.edges
    np.testing.assert_array_equal(turned.column, upright.column.T)
    assert len(e) == len(upright.edges) and e.along_columns.all()
    assert np.all(e.x == np.round(e.x))  # whole camera columns, sub-pixel rows
    truth_y = (e.projector_column - B_U) / A_U
    assert np.max(np.abs(e.y - truth_y)) < 0.01
    np.testing.assert_array_equal(e.row, np.floor(e.y + 0.5))
    np.testing.assert_array_equal(e.pixels(), np.stack([e.x, e.y], axis=1))
    # the row-only search sees (almost) nothing of them
    assert len(decode_gray_images(*_transposed(images, white, black)[:1], descs,
                                  *_transposed(images, white, black)[1:], edge_axes="rows").edges) == 0


def test_rotated_tile_edges_match_upright(tile):
    session, view, truth, res = tile
    descs = [p for p in session.patterns if p.family == "gray"]
    images = {d.id: session.read_image(view, view.image_for(d.id)) for d in descs}
    white = session.read_image(view, view.image_for("white"))
    black = session.read_image(view, view.image_for("black"))
    turned = decode_gray_images(*_transposed(images, white, black)[:1], descs,
                                *_transposed(images, white, black)[1:])
    e = turned.edges
    assert e.along_columns.mean() > 0.99
    assert abs(len(e) - len(res.edges)) < 0.02 * len(res.edges)
    # positions against the truth: a turned camera column is a tile row, its y a tile x
    u = truth.projector_uv[..., 0].astype(np.float64)
    interior = _interior(truth.visibility)
    down = e.along_columns
    col, y = np.round(e.x[down]).astype(int), e.y[down]
    ya = np.floor(y).astype(int)
    inner = interior[col, ya] & interior[col, np.minimum(ya + 1, u.shape[1] - 1)]
    truth_y = _truth_crossings(u, col, y, e.projector_column[down])
    err = (y - truth_y)[inner]
    assert inner.sum() > 5000 and np.isfinite(err).all()
    assert float(np.sqrt(np.mean(err**2))) < 0.1


def test_oblique_boundaries_are_measured_once():
    # stripes at about 60 degrees from vertical: columns cross them more steeply than rows
    h, w = 70, 70  # u below 64, the projector width
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    u = 0.3 * xx + 0.52 * yy + 1.0  # boundary direction: dx/dy = -1.73
    bits = 6
    descs = graycode.generate(64, 32)
    images = {}
    for d in descs:
        fine = np.linspace(-0.5, 0.5, 9)
        on = np.mean([(graycode.gray(np.floor(u + 0.3 * fx + 0.52 * fy + 0.5).astype(np.int64))
                       >> (bits - 1 - d.params["bit"])) & 1 for fx in fine for fy in fine], axis=0)
        level = 0.05 + 0.55 * (1 - on if d.params["inverse"] else on)
        images[d.id] = np.rint(level * 255).astype(np.uint8)
    white, black = np.full((h, w), 153, np.uint8), np.full((h, w), 13, np.uint8)
    res = decode_gray_images(images, descs, white, black)
    e = res.edges
    assert e.along_columns.mean() > 0.95
    # no boundary point measured along both axes: no row sample near a column sample
    down = e.along_columns
    xy = e.pixels()
    for i in np.flatnonzero(~down):
        same = down & (e.stripe == e.stripe[i])
        assert not np.any(np.hypot(*(xy[same] - xy[i]).T) < 1.5)
    # and they lie on their boundaries: u(x, y) = projector column
    u_at = 0.3 * xy[:, 0] + 0.52 * xy[:, 1] + 1.0  # within 0.1 px (a 1 px box blur, linear interpolation)
    np.testing.assert_allclose(u_at, e.projector_column, atol=0.06)


def _drop_bits(images, descs, axis: str, bits: set[int]):
    keep = [d for d in descs if not (d.axis == axis and d.params["bit"] in bits)]
    return {d.id: images[d.id] for d in keep}, keep


def test_missing_low_bit_decodes_coarser(caplog):
    images, descs, white, black = _synthetic(np.uint8, 1, rows=False)
    full = decode_gray_images(images, descs, white, black)
    images, descs = _drop_bits(images, descs, "columns", {5})
    with caplog.at_level("WARNING"):
        res = decode_gray_images(images, descs, white, black, where="v1")
    assert res.bits_used == {"columns": (5, 6)}
    assert "v1: Gray-code column bit(s) 5 missing" in caplog.text
    decoded = res.column >= 0
    assert decoded.mean() > 0.6
    # the centre of the block of two columns holding the full decode
    both = decoded & (full.column >= 0)
    np.testing.assert_array_equal(res.column[both], (full.column[both] // 2) * 2 + 1)
    e = res.edges
    assert len(e) > 0 and np.all(e.projector_column % 2 == 1.5)  # only between blocks
    assert np.array_equal(np.unique(np.diff(np.unique(e.stripe))), [1])  # neighbours
    truth_x = (e.projector_column - B_U) / A_U
    assert np.max(np.abs(e.x - truth_x)) < 0.01
    # every full-resolution edge between blocks is there
    between = full.edges.subset(full.edges.projector_column % 2 == 1.5)
    assert len(e) == len(between)


def test_missing_middle_bit_uses_the_leading_run(caplog):
    images, descs, white, black = _synthetic(np.uint8, 1)
    images, descs = _drop_bits(images, descs, "rows", {2})
    assert len(gray_pairs(descs, "rows")) == 2  # no error for a wholly missing bit
    with caplog.at_level("WARNING"):
        res = decode_gray_images(images, descs, white, black)
    assert res.bits_used == {"columns": (6, 6), "rows": (2, 5)}
    assert "row bit(s) 2 missing" in caplog.text and "bits 3, 4 left unused" in caplog.text
    v = A_V * np.arange(CAM[1]) + B_V
    expected = np.floor(v + 0.5).astype(int) // 8 * 8 + 4
    ok = res.row >= 0
    assert ok.mean() > 0.8
    assert (res.row == expected[:, None])[ok].mean() > 0.97
    images2, descs2 = _drop_bits(images, descs, "columns", {0})
    with pytest.raises(SlscanError, match="lack their most significant bit"):
        decode_gray_images(images2, descs2, white, black)


def _opencv_rule(images, descs, white, black, black_threshold=40, white_threshold=5):
    """OpenCV GrayCodePattern's decode (computeShadowMasks + getProjPixel), grey uint8."""
    valid = np.abs(white.astype(int) - black.astype(int)) > black_threshold
    value = {}
    for axis, size in (("columns", descs[0].width), ("rows", descs[0].height)):
        pairs = gray_pairs(descs, axis)
        code = np.zeros(white.shape, np.int64)
        for pid, inv in pairs:
            p, q = images[pid].astype(float), images[inv].astype(float)
            valid &= ~(np.abs(p - q) < white_threshold)
            code = code * 2 + (p > q)
        value[axis] = graycode.inverse_gray(code)
        valid &= value[axis] < size
    return valid, value["columns"], value["rows"]


def test_opencv_threshold_matches_the_opencv_rule():
    images, descs, white, black = _synthetic(np.uint8, 1)
    rng = np.random.default_rng(3)
    noisy = {k: np.clip(v + rng.normal(0, 4, v.shape), 0, 255).astype(np.uint8) for k, v in images.items()}
    white = (black + rng.integers(20, 90, white.shape)).astype(np.uint8)  # some under 40 DN
    res = decode_gray_images(noisy, descs, white, black, threshold="opencv")
    valid, col, row = _opencv_rule(noisy, descs, white, black)
    assert 0.2 < valid.mean() < 0.95
    np.testing.assert_array_equal(res.mask, valid)
    np.testing.assert_array_equal(res.column[valid], col[valid])
    np.testing.assert_array_equal(res.row[valid], row[valid])
    d = res.diagnostics
    assert d["threshold_mode"] == "opencv" and d["weak_bit_ratio"] == 0
    assert d["lit"] + d["low_contrast"] == d["pixels"] == valid.size
    assert d["lit"] == d["valid"] + d["weak_bit_noise"] + d["weak_bit_ratio"] + d["out_of_range"]
    assert d["valid"] == valid.sum()


def test_adaptive_diagnostics_say_what_limited_the_mask():
    images, descs, white, black = _synthetic(np.uint8, 1)
    white = white.copy()
    white[:, :20] = black[:, :20]  # shadow
    images = dict(images)  # a weak bit: 5 DN of swing, under 10 % of white - black (14 DN)
    images["gray-col-05"] = images["gray-col-05"].copy()
    images["gray-col-05"][:, 60:70] = images["gray-col-05-inv"][:, 60:70] + 5
    res = decode_gray_images(images, descs, white, black, noise=2 / 255)
    d = res.diagnostics
    assert d["threshold_mode"] == "adaptive" and d["noise_dn"] == pytest.approx(2.0)
    assert d["low_contrast"] >= 20 * CAM[1]
    assert d["lit"] == d["valid"] + d["weak_bit_noise"] + d["weak_bit_ratio"] + d["out_of_range"]
    assert d["valid"] == res.mask.sum()
    assert d["weak_bit_ratio"] == 10 * CAM[1] and d["weak_bit_noise"] == 0
    # a larger noise moves the blame to the noise term
    noisy = decode_gray_images(images, descs, white, black, noise=40 / 255).diagnostics
    assert noisy["weak_bit_noise"] > d["weak_bit_noise"] and noisy["valid"] < d["valid"]
    with pytest.raises(SlscanError, match="unknown Gray-code threshold 'fixed'"):
        decode_gray_images(images, descs, white, black, threshold="fixed")


def _washed_out(images, descs, white, black, bits: set[int], x0: int):
    """The column bits ``bits`` washed out (pattern = inverse = mid grey) right of ``x0``,
    as subsurface scattering washes out the finest stripes."""
    out = dict(images)
    mid = ((white.astype(np.int32) + black) // 2).astype(white.dtype)
    for d in descs:
        if d.axis == "columns" and d.params["bit"] in bits:
            img = out[d.id].copy()
            img[:, x0:] = mid[:, x0:]
            out[d.id] = img
    return out


@pytest.mark.parametrize("robust", [True, False])
def test_per_pixel_bit_dropping_keeps_the_coarse_code(robust):
    images, descs, white, black = _synthetic(np.uint8, 1, rows=False)
    x0 = CAM[0] // 2
    washed = _washed_out(images, descs, white, black, {4, 5}, x0)
    full = decode_gray_images(images, descs, white, black, robust=robust)
    old = decode_gray_images(washed, descs, white, black, robust=robust)
    one = decode_gray_images(washed, descs, white, black, robust=robust, drop_bits=1)
    res = decode_gray_images(washed, descs, white, black, robust=robust, drop_bits=2)
    assert not (old.column[:, x0:] >= 0).any()  # every bit or none
    assert not (one.column[:, x0:] >= 0).any()  # two bits lost, one may be dropped
    # left of the wash: exactly as before
    np.testing.assert_array_equal(res.column[:, : x0 - 2], full.column[:, : x0 - 2])
    # right of it: the centre of the block of 4 columns holding the truth
    u = A_U * np.arange(CAM[0], dtype=float) + B_U
    truth = np.broadcast_to(np.floor(u + 0.5).astype(int), res.column.shape)
    right = np.zeros(res.column.shape, bool)
    right[:, x0:] = True
    decoded = right & (res.column >= 0)
    assert decoded.sum() > 0.8 * right.sum()
    np.testing.assert_array_equal(res.column[decoded], truth[decoded] // 4 * 4 + 2)
    assert res.diagnostics["bits_dropped"] == int(decoded.sum())
    # edges right of the wash only between blocks of 4, each at its exact position
    e = res.edges
    coarse = e.x > x0
    assert coarse.sum() > 0 and np.all(e.projector_column[coarse] % 4 == 3.5)
    truth_x = (e.projector_column - B_U) / A_U
    assert np.max(np.abs(e.x - truth_x)) < 0.01
    # every block boundary right of the wash, in every row, once
    blocks = np.unique(e.projector_column[coarse])
    expected = [c for c in np.arange(3.5, PROJ[0], 4) if x0 < (c - B_U) / A_U < CAM[0] - 1]
    np.testing.assert_array_equal(blocks, expected)
    assert coarse.sum() == CAM[1] * len(expected)
    # left of it every boundary, as the full decode has them
    np.testing.assert_array_equal(e.subset(e.x < x0 - 2).stripe, full.edges.subset(full.edges.x < x0 - 2).stripe)
    # stripes count columns (the boundary's low column) at every level
    np.testing.assert_array_equal(e.projector_column, e.stripe + 0.5)


def test_drop_bits_must_be_a_count():
    images, descs, white, black = _synthetic(np.uint8, 1, rows=False)
    with pytest.raises(SlscanError, match="drop_bits must be an integer >= 0"):
        decode_gray_images(images, descs, white, black, drop_bits=-1)


def _nearest_brute(line, pos, stripe, q_line, q_pos, q_stripe):
    out = np.full(len(q_line), np.inf)
    for i in range(len(q_line)):
        same = (line == q_line[i]) & (stripe == q_stripe[i])
        if same.any():
            out[i] = np.abs(pos[same] - q_pos[i]).min()
    return out


def test_nearest_sample_on_other_lines_is_the_brute_force_one():
    # the edge samples' neighbours on the lines next to theirs (_both_axes), sorted once
    # for several lines, against a search of every sample; ties in position included
    rng = np.random.default_rng(3)
    n = 400
    line = rng.integers(5, 25, n)
    stripe = rng.integers(0, 6, n)
    pos = np.round(rng.uniform(0, 50, n), 1)
    for got, d in zip(_nearest_shifted(line, pos, stripe, (-1, 1, 2)), (-1, 1, 2)):
        np.testing.assert_array_equal(got, _nearest_brute(line, pos, stripe, line + d, pos, stripe))
    q_line = rng.integers(3, 27, 150)
    q_pos, q_stripe = np.round(rng.uniform(0, 50, 150), 1), rng.integers(0, 7, 150)
    found = _nearest_on(line, pos, stripe, [q_line, q_line + 1], q_pos, q_stripe)
    for got, q in zip(found, (q_line, q_line + 1)):
        np.testing.assert_array_equal(got, _nearest_brute(line, pos, stripe, q, q_pos, q_stripe))
    assert np.isfinite(found[0]).any() and np.isinf(found[0]).any()


def test_luma_read_ignores_what_only_the_colour_carries():
    """``luma=True`` reads RGB captures as BT.601 luma (integer weights 77/150/29): a
    disturbance that JPEG would put in the chroma only (here +29 t in red, -77 t in blue,
    different in every image) leaves the luma levels, and so every code and edge, exactly
    as without it; the channel mean sees it and moves the edges."""
    images, descs, white, black = _synthetic(np.uint16, 3, rows=False)
    rng = np.random.default_rng(5)
    h, w = CAM[1], CAM[0]
    noisy = {}
    for pid, img in images.items():
        t = rng.integers(-20, 21, size=(h, w)).astype(np.int64)
        out = img.astype(np.int64)
        out[..., 0] += 29 * t
        out[..., 2] -= 77 * t
        assert out.min() >= 0 and out.max() <= 65535
        noisy[pid] = out.astype(np.uint16)
    clean = decode_gray_images(images, descs, white, black, luma=True)
    truth_x = (clean.edges.projector_column - B_U) / A_U
    assert np.max(np.abs(clean.edges.x - truth_x)) < 0.01
    seen = decode_gray_images(noisy, descs, white, black, luma=True)
    np.testing.assert_array_equal(seen.column, clean.column)
    np.testing.assert_array_equal(seen.edges.x, clean.edges.x)
    mean = decode_gray_images(noisy, descs, white, black)
    assert len(mean.edges) == len(clean.edges)
    assert np.max(np.abs(mean.edges.x - clean.edges.x)) > 0.01  # measured 0.019 px
