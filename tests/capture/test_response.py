"""Tests for the camera-response fit: synthetic captures through a known curve, weak
evidence, the virtual rig's linear and sRGB cameras, the kamino410 real captures."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from slscan.capture.response import (
    MIN_SAMPLES,
    ResponseFit,
    describe_response,
    fit_response,
    measure_session_response,
    with_response,
)
from slscan.capture.session import load_session
from slscan.errors import SlscanError

H, W = 96, 160


def _srgb_encode(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.maximum(v, 0.0031308) ** (1 / 2.4) - 0.055)


def _scene(channels: int = 1, blur: float = 1.2, seed: int = 0):
    """Linear light of white, black and 4 column-bit pairs of a flat scene: albedo varying
    across the image (levels from dark to bright), black level 0.02, stripes 2-16 px wide
    blurred by ``blur`` px (0: hard edges on pixel boundaries)."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    albedo = 0.15 + 0.8 * (ys / H) * (0.6 + 0.4 * np.cos(xs / 23.0) ** 2)
    if channels == 3:
        albedo = albedo[..., None] * np.array([0.8, 1.0, 0.6])
    black = 0.02 * np.ones_like(albedo)
    frames = {"white": albedo + black, "black": black}
    pairs = []
    for width in (16, 8, 4, 2):
        on = ((xs // width) % 2).astype(np.float64)
        if blur:
            on = cv2.GaussianBlur(on, (0, 0), blur)
        on = on[..., None] if channels == 3 else on
        pairs.append((albedo * on + black, albedo * (1 - on) + black))
    return frames, pairs


def _store(linear: np.ndarray, curve: str, dtype, rng: np.random.Generator) -> np.ndarray:
    top = np.iinfo(dtype).max
    noisy = np.clip(linear + rng.normal(0, 0.002, linear.shape), 0, 1)
    v = {"linear": noisy, "srgb": _srgb_encode(noisy), "gamma2": noisy ** 0.5}[curve]
    return np.round(v * top).astype(dtype)


def _stored(curve: str, dtype=np.uint8, channels: int = 1, blur: float = 1.2):
    rng = np.random.default_rng(1)
    frames, pairs = _scene(channels, blur)
    return (_store(frames["white"], curve, dtype, rng), _store(frames["black"], curve, dtype, rng),
            [(_store(p, curve, dtype, rng), _store(q, curve, dtype, rng)) for p, q in pairs])


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("curve", ["linear", "srgb"])
def test_the_curve_the_captures_went_through_is_found(curve, channels, dtype):
    white, black, pairs = _stored(curve, dtype, channels)
    fit = fit_response(white, black, pairs)
    assert fit.measured and fit.response == curve, fit.describe()
    other = "srgb" if curve == "linear" else "linear"
    assert fit.residuals[curve] < 0.01 and fit.residuals[other] > 0.2
    assert fit.samples > MIN_SAMPLES and fit.standard_error < 0.005
    assert fit.gamma == pytest.approx(1.0 if curve == "linear" else 2.2, abs=0.15)


def test_a_power_law_is_reported_and_the_nearer_curve_chosen():
    white, black, pairs = _stored("gamma2")
    fit = fit_response(white, black, pairs)
    assert fit.gamma == pytest.approx(2.0, abs=0.05) and fit.gamma_residual < 0.01
    assert fit.response == "srgb" and fit.residuals["srgb"] < fit.residuals["linear"]


def test_without_pixels_that_see_both_stripes_it_falls_back_to_linear():
    """Hard stripe edges on pixel boundaries: every pixel sees pattern = white, inverse =
    black, which any curve satisfies."""
    white, black, pairs = _stored("srgb", blur=0)
    fit = fit_response(white, black, pairs)
    assert not fit.measured and fit.response == "linear" and fit.samples < MIN_SAMPLES
    assert "see both stripes" in fit.reason
    assert fit.describe().startswith("linear (by default, not measured: only 0 pixel samples see both")


def test_clipped_captures_fall_back_to_linear():
    white, black, pairs = _stored("srgb")
    clip = lambda a: np.minimum(a.astype(np.int32) * 4, 255).astype(np.uint8)
    fit = fit_response(clip(white), clip(black), [(clip(p), clip(q)) for p, q in pairs])
    assert not fit.measured and fit.response == "linear"


def test_a_fit_round_trips_and_describes_itself():
    white, black, pairs = _stored("srgb")
    fit = fit_response(white, black, pairs, views=("v0",))
    again = ResponseFit.from_dict(fit.to_dict())
    assert again.response == fit.response and again.views == ("v0",)
    assert again.residuals == pytest.approx(fit.residuals, abs=1e-5)
    text = fit.describe()
    assert text.startswith("srgb (measured on v0") and "residual linear 0." in text and "srgb 0.0" in text
    given = describe_response("linear", {**fit.to_dict(), "source": "given"})
    assert given.startswith("linear (given; the captures measure srgb: srgb (measured")
    assert describe_response("srgb", {}) == "srgb (recorded with the captures; not measured)"
    with pytest.raises(SlscanError, match="camera.response_fit: not a response measurement"):
        ResponseFit.from_dict({"response": "srgb"})


def test_mismatched_captures_are_refused():
    white, black, pairs = _stored("linear")
    with pytest.raises(SlscanError, match="response fit: a capture is"):
        fit_response(white, black[:10], pairs)
    with pytest.raises(SlscanError, match="uint8 or uint16 as stored"):
        fit_response(white.astype(np.float32), black, pairs)


# --- the virtual rig: a linear and an sRGB camera -------------------------------------------


@pytest.fixture(scope="module", params=["linear", "srgb"])
def virtual(request, tmp_path_factory: pytest.TempPathFactory):
    from slscan.virtual.device import VirtualCaptureConfig, capture_session
    from slscan.virtual.sensor import Sensor

    config = VirtualCaptureConfig(scene="object", patterns="gray", camera_scale=0.25, projector_scale=0.25,
                                  lit_images=False, sensor=Sensor(response=request.param))
    return capture_session(config, tmp_path_factory.mktemp("virtual") / "session")


def test_the_virtual_cameras_response_is_measured(virtual):
    fit = measure_session_response(virtual)
    assert fit.measured and fit.response == virtual.response, fit.describe()
    assert fit.residuals[virtual.response] < 0.01 and max(fit.residuals.values()) > 0.25
    # decoding through another curve: recorded as given, beside what was measured
    other = with_response(virtual, "srgb" if virtual.response == "linear" else "linear")
    assert other.response != virtual.response and other.response_fit["source"] == "given"
    measured = with_response(virtual, "measure")
    assert measured.response == virtual.response and measured.response_fit["source"] == "measured"
    with pytest.raises(SlscanError, match="camera response must be measure or one of linear, srgb"):
        with_response(virtual, "gamma")


# --- real captures --------------------------------------------------------------------------


def test_the_kamino410_cameras_are_linear(shared_data: Path, tmp_path: Path):
    from slscan.capture.kamino410 import import_kamino410

    src = shared_data / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        pytest.skip(f"real data not found: {src}")
    import_kamino410(src / "capture_0", tmp_path / "s")
    session = load_session(tmp_path / "s")
    fit = ResponseFit.from_dict(session.response_fit)
    assert session.response == "linear" and fit.measured and session.response_fit["source"] == "measured"
    # measured: 0.024 against 0.40
    assert fit.residuals["linear"] < 0.05 and fit.residuals["srgb"] > 0.3
