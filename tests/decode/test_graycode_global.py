"""Gray-code decoding under global light: XOR codes, the direct/global split, Gupta's
reliability rule and the rejection of inconsistent codes."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.decode.graycode import (
    _inconsistent,
    bit_reliable,
    decode_gray,
    decode_gray_images,
    gray_bits,
    separate_light,
)
from slscan.errors import SlscanError
from slscan.patterns import graycode, profile, standard_set
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor

from .global_stand_in import capture_with_global_stand_in

PROJ = (64, 32)
CAM = (120, 40)
A_U, B_U = 0.5, 1.3  # projector column u(x) = A_U x + B_U: two camera px per column


def _synthetic(code: str, rows: bool = False):
    """Noise-free captures of a flat scene with u = A_U x + B_U (white 0.6, black 0.05), each
    camera pixel box-filtered over [x - 1, x + 1]."""
    descs = graycode.generate(*PROJ, rows=rows, code=code)
    w, h = CAM
    fine = np.linspace(-1, 1, 801)[1:] - 1 / 800
    u = A_U * (np.arange(w, dtype=float)[:, None] + fine[None, :]) + B_U
    col = np.clip(np.floor(u + 0.5).astype(np.int64), 0, PROJ[0] - 1)
    v = 0.5 * (np.arange(h, dtype=float)[:, None] + fine[None, :]) + 2.2
    row = np.clip(np.floor(v + 0.5).astype(np.int64), 0, PROJ[1] - 1)

    def to_image(signal: np.ndarray) -> np.ndarray:
        return np.rint((0.05 + 0.55 * signal) * 255).astype(np.uint8)

    images = {}
    for d in descs:
        on = profile(d)[:, 0] / 255.0
        if d.axis == "columns":
            s = np.broadcast_to(on[col].mean(axis=1)[None, :], (h, w))
        else:
            s = np.broadcast_to(on[row].mean(axis=1)[:, None], (h, w))
        images[d.id] = to_image(s)
    return images, descs, to_image(np.ones((h, w))), to_image(np.zeros((h, w)))


# --- XOR patterns ------------------------------------------------------------------------


@pytest.mark.parametrize("width", [64, 100, 1024])
def test_xor_patterns_xor_back_to_gray_code(width):
    descs = graycode.generate(width, 8, code="xor")
    bits = graycode.n_bits(width)
    base = bits - 2  # XOR-04: the bit with 4 px stripes
    assert {d.params["base"] for d in descs} == {base}
    on = {(d.params["bit"], d.params["inverse"]): profile(d)[:, 0] > 0 for d in descs}
    for bit in range(bits):
        assert np.array_equal(on[(bit, True)], ~on[(bit, False)])
        decoded = on[(bit, False)] ^ (on[(base, False)] if bit < base else False)
        truth = (graycode.gray(np.arange(width)) >> (bits - 1 - bit)) & 1
        assert np.array_equal(decoded, truth.astype(bool))
        # every image is high-frequency: no stripe wider than the base's 4 px
        runs = np.diff(np.flatnonzero(np.diff(on[(bit, False)].astype(int))))
        assert runs.max() <= 4
        # ... and none narrower than 2 px (1 px stripes blur away: their edges drift)
        assert runs.min() >= 2


def test_xor_set_in_standard_set_and_session(tmp_path):
    descs = standard_set("xor", width=64, height=32, rows=True)
    assert [d.id for d in descs[:3]] == ["white", "black", "xor-col-00"]
    assert all(d.params["code"] == "xor" for d in descs[2:])
    assert gray_bits(descs, "columns").base == 4 and gray_bits(descs, "rows").base == 3
    with pytest.raises(SlscanError, match="unknown pattern family 'xr'"):
        standard_set("xr")


def test_xor_set_errors():
    descs = graycode.generate(*PROJ, code="xor")
    base = descs[0].params["base"]
    no_base = [d for d in descs if d.params["bit"] != base]
    with pytest.raises(SlscanError, match="lack their base bit"):
        gray_bits(no_base, "columns")
    mixed = [d for d in descs if d.params["bit"] != 0] + graycode.generate(*PROJ)[:2]
    with pytest.raises(SlscanError, match="mix codes"):
        gray_bits(mixed, "columns")
    with pytest.raises(SlscanError, match="unknown Gray-code variant"):
        graycode.generate(*PROJ, code="xor-2")


@pytest.mark.parametrize("robust", [False, True])
def test_xor_synthetic_decodes_like_gray(robust):
    """Known answer: the XOR set gives the same columns, rows and edges as plain Gray code."""
    plain = decode_gray_images(*_synthetic("reflected-binary", rows=True), robust=robust)
    xor = decode_gray_images(*_synthetic("xor", rows=True), robust=robust)
    u = A_U * np.arange(CAM[0]) + B_U
    truth = np.broadcast_to(np.floor(u + 0.5)[None, :], xor.column.shape)
    assert xor.mask.mean() > 0.6
    assert np.array_equal(xor.column[xor.mask], truth[xor.mask])
    both = xor.mask & plain.mask
    assert both.sum() > 0.9 * min(xor.mask.sum(), plain.mask.sum())
    assert np.array_equal(xor.row[both], plain.row[both])
    # edges: the true crossing of u = c + 0.5, to the interpolation's accuracy
    e = xor.edges
    assert len(e) > 0.9 * len(plain.edges)
    x_true = (e.projector_column - B_U) / A_U
    assert np.abs(e.x - x_true).max() < 0.02


def _edge_errors(session, res) -> np.ndarray:
    """Projector px between each edge's projector column (an integer + 0.5) and the true
    projector column at its camera position (linear between the two pixels around it)."""
    u = session.load_ground_truth(session.views[0]).projector_uv[..., 0].astype(np.float64)
    e = res.edges
    x0 = np.floor(e.x).astype(int)
    ok = (x0 >= 0) & (x0 + 1 < u.shape[1])
    r, x0, f = e.row[ok], x0[ok], (e.x - np.floor(e.x))[ok]
    truth = u[r, x0] + f * (u[r, x0 + 1] - u[r, x0])
    err = truth - e.projector_column[ok]
    return err[np.isfinite(err)]


@pytest.mark.parametrize("effects", [(), ("tone",)])
def test_xor_edges_at_true_boundaries(tmp_path, effects):
    """Known answer on the flat tile: the XOR set's edges sit at the true column boundaries
    (integer + 0.5 projector px) as closely as plain Gray code's, and a camera with an sRGB
    curve (``tone``: blur light in the dark stripes turns bright) still decodes as much."""
    found = {}
    for pat in ("gray", "xor"):
        config = VirtualCaptureConfig(scene="tile", patterns=pat, camera_scale=0.25, projector_scale=0.25,
                                      lit_images=False, effects=effects)
        session = capture_session(config, tmp_path / pat)
        res = decode_gray(session, session.views[0])
        err = _edge_errors(session, res)
        found[pat] = (len(err), float(np.sqrt(np.mean(err**2))), res.mask.sum())
    n_gray, rms_gray, valid_gray = found["gray"]
    n_xor, rms_xor, valid_xor = found["xor"]
    assert rms_xor < 0.1 and rms_xor < 1.2 * rms_gray
    assert n_xor > 0.95 * n_gray and valid_xor > 0.95 * valid_gray


def test_xor_virtual_capture_decodes_to_truth(tmp_path):
    """A virtual XOR capture (the session records its pattern descriptions) decodes to
    the true projector columns like a plain Gray-code capture."""
    results = {}
    for pat in ("gray", "xor"):
        config = VirtualCaptureConfig(scene="tile", patterns=pat, camera_scale=0.25, projector_scale=0.25,
                                      lit_images=False, sensor=Sensor(noise=False))
        session = capture_session(config, tmp_path / pat)
        assert {p.params.get("code") for p in session.patterns if p.family == "gray"} == (
            {"xor"} if pat == "xor" else {"reflected-binary"})
        view = session.views[0]
        truth = session.load_ground_truth(view)
        res = decode_gray(session, view)
        u = truth.projector_uv[..., 0].astype(np.float64)
        check = res.mask & np.isfinite(u)
        correct = (res.column[check] == np.floor(u[check] + 0.5)).mean()
        results[pat] = (check.sum(), correct, len(res.edges))
    n_gray, ok_gray, edges_gray = results["gray"]
    n_xor, ok_xor, edges_xor = results["xor"]
    assert ok_xor > 0.95 and ok_xor >= ok_gray - 0.01
    assert n_xor > 0.7 * n_gray and edges_xor > 0.7 * edges_gray


# --- the direct/global split and Gupta's rule -------------------------------------------------


def test_separate_light_known_answer():
    rng = np.random.default_rng(1)
    direct = rng.uniform(0.1, 0.6, (6, 7)).astype(np.float32)
    glob = rng.uniform(0.0, 0.4, (6, 7)).astype(np.float32)
    black = np.full((6, 7), 0.04, np.float32)
    highs = []
    for shift in range(3):  # half-on patterns and their inverses at several phases
        on = ((np.arange(7)[None, :] + shift) // (shift + 1)) % 2 == 0
        for lit in (on, ~on):
            highs.append(black + glob / 2 + direct * np.broadcast_to(lit, direct.shape))
    d, g = separate_light(highs, black)
    np.testing.assert_allclose(d, direct, atol=1e-6)
    np.testing.assert_allclose(g, glob, atol=1e-6)


def test_bit_reliable_rule():
    D = np.full(5, 0.2, np.float32)  # direct
    G = np.array([0.1, 0.6, 0.6, 0.6, 0.6], np.float32)  # global
    a = np.array([0.0, 0.5, 0.05, 0.95, 0.5], np.float32)  # the share of global in the lit image
    p = D + a * G  # the bit's pattern lights the pixel
    q = (1 - a) * G
    ok = bit_reliable(p, q, D, G, min_direct=0.01)
    # direct > global: certain. G > D: p - q lies in [-0.4, 0.8] when the bit is 1 and in
    # [-0.8, 0.4] when it is 0; an even split gives p - q = 0.2, which a 0 with a = 0.33
    # gives too: uncertain; a = 0.05 reads wrong (p = 0.23 < q = 0.57; |p - q| = 0.34 <
    # 0.4): uncertain; a = 0.95: p - q = 0.74 > 0.4, only a 1 gives it: certain
    assert ok.tolist() == [True, False, False, True, False]
    assert (p[2] > q[2]) is np.False_  # the case the rule guards against
    assert not bit_reliable(p, q, D, G, min_direct=0.3).any()


def test_inconsistent_codes_are_flagged():
    h, w = 12, 20
    value = np.broadcast_to((np.arange(w) * 0.7).astype(np.int32)[None, :], (h, w)).copy()
    valid = np.ones((h, w), bool)
    value[5, 8] += 64  # one wrong low-frequency bit
    value[2, 3] += 1  # within the tolerance: kept
    flagged = _inconsistent(value, valid)
    assert np.flatnonzero(flagged).tolist() == [5 * w + 8]
    valid[:, 15:] = False  # invalid neighbours neither vote nor get flagged
    value[8, 17] = 500
    assert np.flatnonzero(_inconsistent(value, valid)).tolist() == [5 * w + 8]


def test_robust_diagnostics_and_maps():
    images, descs, white, black = _synthetic("reflected-binary")
    images = dict(images)
    # a wrong code in an otherwise clean image: bit 0 flipped on a 2x2 patch, strongly
    for pid, other in (("gray-col-00", "gray-col-00-inv"),):
        p, q = images[pid].copy(), images[other].copy()
        p[10:12, 30:32], q[10:12, 30:32] = q[10:12, 30:32], images[pid][10:12, 30:32]
        images[pid], images[other] = p, q
    old = decode_gray_images(images, descs, white, black, robust=False)
    new = decode_gray_images(images, descs, white, black)
    assert old.direct is None and "inconsistent" not in old.diagnostics
    assert old.mask[10:12, 30:32].all()  # the old path keeps the wrong codes
    assert not new.mask[10:12, 30:32].any()
    d = new.diagnostics
    assert d["inconsistent"] >= 4
    assert d["lit"] == (d["valid"] + d["weak_bit_noise"] + d["weak_bit_ratio"] + d["out_of_range"]
                        + d["unreliable_global"] + d["inconsistent"])
    assert d["valid"] == new.mask.sum()
    # direct light only: direct = white - black, no global light
    lit = new.mask
    np.testing.assert_allclose(new.direct[lit], 0.55, atol=0.01)
    assert np.abs(new.global_light[lit]).max() < 0.01
    assert new.direct.shape == white.shape
    with pytest.raises(SlscanError, match="separation_bits"):
        decode_gray_images(images, descs, white, black, separation_bits=0)


# --- the test-only stand-in for global light ------------------------------------------------


@pytest.fixture(scope="module")
def figurine_with_global():
    out = {}
    for pat in ("gray", "xor"):
        config = VirtualCaptureConfig(scene="object", patterns=pat, camera_scale=0.35, projector_scale=0.35,
                                      lit_images=False)
        out[pat] = capture_with_global_stand_in(config, beta=4.0, sigma_px=40.0)
    return out


def _wrong_share(res, uv) -> tuple[float, int]:
    u = uv[..., 0]
    check = res.mask & np.isfinite(u)
    return float((np.abs(res.column[check] - np.floor(u[check] + 0.5)) > 1).mean()), int(check.sum())


def test_stand_in_global_light_robust_gray_and_xor(figurine_with_global):
    images, descs, white, black, uv = figurine_with_global["gray"]
    plain_wrong, plain_n = _wrong_share(decode_gray_images(images, descs, white, black, robust=False), uv)
    robust = decode_gray_images(images, descs, white, black)
    robust_wrong, robust_n = _wrong_share(robust, uv)
    assert plain_wrong > 0.002  # the stand-in flips low-frequency bits of plain Gray code
    assert robust_wrong < plain_wrong / 4  # ...which robust decoding leaves out
    assert robust.diagnostics["unreliable_global"] > 0 and robust_n > 0.5 * plain_n
    assert robust.diagnostics["global_direct_median"] > 0.3
    images, descs, white, black, uv = figurine_with_global["xor"]
    xor_wrong, xor_n = _wrong_share(decode_gray_images(images, descs, white, black, robust=False), uv)
    assert xor_wrong < plain_wrong / 4  # XOR codes: global light cancels, no rule needed
    assert xor_n > 0.5 * plain_n
