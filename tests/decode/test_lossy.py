"""Captures through a camera's tone curve and lossy compression: decoding in linear light
(``camera.response``), and which pattern family ``method="auto"`` decodes."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pytest

from slscan.capture.session import linearise
from slscan.decode.graycode import decode_gray
from slscan.decode.hybrid import decode_hybrid
from slscan.decode.pipeline import choose_method
from slscan.errors import SlscanError
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor, srgb_oetf


def test_linearise_inverts_the_srgb_curve():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    for dtype, top in ((np.uint8, 255), (np.uint16, 65535)):
        coded = np.rint(srgb_oetf(x) * top).astype(dtype)
        back = linearise(coded, "srgb")
        assert back.dtype == np.float32
        # within half a code step of the curve's slope (steepest at full scale: 2.4 / top)
        assert np.max(np.abs(back - x)) <= 1.25 / top + 1e-6
        assert back[-1] == 1.0 and back[0] == 0.0  # full scale stays detectable as clipped
    assert linearise(np.float32([0.5]), "srgb")[0] == pytest.approx(0.2140411, abs=1e-6)
    raw = np.zeros((2, 2), np.uint8)
    assert linearise(raw, "linear") is raw
    with pytest.raises(SlscanError, match="camera response must be one of linear, srgb, got 'log'"):
        linearise(raw, "log")


@pytest.fixture(scope="module")
def tone_sessions(tmp_path_factory: pytest.TempPathFactory):
    """The same noise-free view through a linear and through an sRGB camera response."""
    out = {}
    for response in ("linear", "srgb"):
        config = VirtualCaptureConfig(scene="object", views=1, patterns="both", gray_rows=False, levels=6,
                                      lit_images=False, camera_scale=0.25, projector_scale=0.25,
                                      sensor=Sensor(noise=False, response=response))
        out[response] = capture_session(config, tmp_path_factory.mktemp(response) / "session")
    return out


def _positions(session, family: str) -> dict[tuple[int, float], float]:
    view = session.views[0]
    samples = decode_hybrid(session, view).samples if family == "hybrid" else decode_gray(session, view).edges
    return {(int(r), float(c)): float(x) for r, c, x in zip(samples.row, samples.projector_column, samples.x)}


@pytest.mark.parametrize(("family", "p95_px"), [("hybrid", 0.12), ("gray", 0.03)])
def test_an_srgb_capture_decodes_like_the_linear_one(tone_sessions, family: str, p95_px: float):
    linear, srgb = tone_sessions["linear"], tone_sessions["srgb"]
    assert (linear.response, srgb.response) == ("linear", "srgb")

    def moved(session) -> tuple[float, np.ndarray]:
        a, b = _positions(linear, family), _positions(session, family)
        common = a.keys() & b.keys()
        return len(common) / len(a), np.array([b[k] - a[k] for k in common])

    share, dx = moved(srgb)
    assert share >= 0.97
    assert np.percentile(np.abs(dx), 95) <= p95_px and abs(dx.mean()) <= 0.01
    # the same captures read as if linear: the curve bends the profiles, the axes move
    _, bent = moved(dataclasses.replace(srgb, response="linear"))
    # (mean shifts: hybrid 0.019 px linearised vs 0.035 px not, Gray code 0.005 vs 0.017 px)
    assert np.abs(bent).mean() > 1.5 * np.abs(dx).mean()


def test_decoding_returns_the_white_as_stored(tone_sessions):
    srgb = tone_sessions["srgb"]
    view = srgb.views[0]
    stored = srgb.read_image(view, view.image_for(srgb.flat_frame_ids()[0]))
    for result in (decode_hybrid(srgb, view), decode_gray(srgb, view)):
        assert result.white.dtype == np.uint8 and np.array_equal(result.white, stored)


def test_auto_decodes_gray_code_from_lossy_captures(tone_sessions, tmp_path, caplog):
    both = dataclasses.replace(tone_sessions["linear"], root=tmp_path / "both")
    assert choose_method(both) == "hybrid"  # lossless: the hybrid pattern
    lossy = dataclasses.replace(both, lossy=True)
    with caplog.at_level(logging.INFO, logger="slscan.decode.pipeline"):
        assert [choose_method(lossy) for _ in range(3)] == ["gray"] * 3
        assert choose_method(lossy, "hybrid") == "hybrid"  # asked for: no reason to refuse
    said = [r for r in caplog.records if "decoding the Gray-code patterns, not the hybrid" in r.getMessage()]
    assert len(said) == 1 and "lossy" in said[0].getMessage() and said[0].levelno == logging.INFO
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_a_lossy_hybrid_only_session_warns_once_with_the_measured_cost(tone_sessions, tmp_path, caplog):
    hybrid_only = dataclasses.replace(
        tone_sessions["linear"], root=tmp_path / "hybrid_only", lossy=True,
        patterns=tuple(p for p in tone_sessions["linear"].patterns if p.family != "gray"),
    )
    with caplog.at_level(logging.WARNING, logger="slscan.decode.pipeline"):
        assert [choose_method(hybrid_only) for _ in range(2)] == ["hybrid"] * 2
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "0.89 mm" in warned[0] and "lossy" in warned[0]


def test_lossy_sessions_decode_gray_code_from_luma(tone_sessions, tmp_path):
    """Gray code of a lossy (JPEG) session is read as luma, the channel JPEG keeps at full
    resolution; a lossless one as the mean of its channels."""
    session = tone_sessions["linear"]
    view = session.views[0]
    lossy = dataclasses.replace(session, lossy=True)
    as_luma = decode_gray(session, view, luma=True).edges
    as_mean = decode_gray(session, view).edges
    assert not (len(as_luma) == len(as_mean) and np.array_equal(as_luma.x, as_mean.x))  # the tint differs
    np.testing.assert_array_equal(decode_gray(lossy, view).edges.x, as_luma.x)
    np.testing.assert_array_equal(decode_gray(lossy, view, luma=False).edges.x, as_mean.x)


@pytest.mark.parametrize("luma", [True, False])
def test_streamed_srgb_read_equals_decoding_linearised_captures(tone_sessions, luma: bool):
    """``decode_gray`` reads each sRGB capture as stored, straight into the linear grey plane
    the decoder keeps (one lookup table per channel, no float RGB copy): bit for bit what
    decoding the linearised captures gives, clipping included, and the white as stored."""
    from slscan.decode.graycode import decode_gray_images

    srgb = tone_sessions["srgb"]
    view = srgb.views[0]
    # one clipped pixel in one channel of the white frame, so that clipping is compared too
    stored = {d.id: srgb.read_image(view, view.image_for(d.id)) for d in srgb.patterns if d.family in ("flat", "gray")}
    stored["white"] = stored["white"].copy()
    stored["white"][10, 10, 1] = 255
    linear = {k: linearise(v, "srgb") for k, v in stored.items()}
    new = decode_gray_images(stored, srgb.patterns, stored["white"], stored["black"], luma=luma, response="srgb")
    old = decode_gray_images(linear, srgb.patterns, linear["white"], linear["black"], luma=luma)
    for name in ("column", "mask", "contrast", "saturated", "direct", "global_light"):
        np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)
    assert new.noise == old.noise and new.diagnostics == old.diagnostics and new.saturated[10, 10]
    for name in ("row", "x", "projector_column", "contrast", "saturated"):
        np.testing.assert_array_equal(getattr(new.edges, name), getattr(old.edges, name), err_msg=name)
    res = decode_gray(srgb, view, luma=luma)
    assert res.white.dtype == np.uint8 and np.array_equal(res.white, srgb.read_image(view, view.image_for("white")))


def test_keeping_bit_differences_changes_nothing(tone_sessions, monkeypatch):
    """Float column levels are kept as ``pattern - inverse`` (half the memory), with the
    noise subsample's sums and the finest bits' extremes for the direct/global split taken
    as the captures are read: the decode is bit for bit the one keeping both captures."""
    import slscan.decode.graycode as graycode

    srgb = tone_sessions["srgb"]
    view = srgb.views[0]
    results = []
    for keep in (True, False):
        monkeypatch.setattr(graycode, "_KEEP_DIFFERENCES", keep)
        # the split takes bits 4-6 of 8 here (the finest lacks contrast); bits 5-7 when the
        # finest is never skipped; every bit with 9
        runs = [decode_gray(srgb, view, drop_bits=drop, separation_bits=bits) for drop, bits in ((0, 3), (2, 3), (0, 9))]
        with monkeypatch.context() as m:
            m.setattr(graycode, "SEPARATION_MIN_CONTRAST", 0.0)
            runs.append(decode_gray(srgb, view))
        results.append(runs)
    for new, old in zip(*results):
        for name in ("column", "mask", "contrast", "saturated", "direct", "global_light"):
            np.testing.assert_array_equal(getattr(new, name), getattr(old, name), err_msg=name)
        assert new.noise == old.noise and new.diagnostics == old.diagnostics
        for name in ("row", "x", "projector_column", "contrast", "stripe"):
            np.testing.assert_array_equal(getattr(new.edges, name), getattr(old.edges, name), err_msg=name)
