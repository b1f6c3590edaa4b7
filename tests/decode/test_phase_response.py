"""Phase decoding of a non-linear projector without a response capture: the exponent
estimated from the fitted phases themselves (``projector_gamma="auto"``), against exact
synthetic fringes and the virtual rig's per-pixel truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slscan.decode.phase import Fringes, decode_phase, fit_phase
from slscan.decode.phase_gamma import gamma_from_phases
from slscan.errors import SlscanError
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.render import Optics

SHIFTS3 = (-2 * math.pi / 3, 0.0, 2 * math.pi / 3)


def test_the_exponent_is_found_from_the_phases_and_a_linear_set_left_alone():
    rng = np.random.default_rng(1)
    true = rng.uniform(0, 2 * np.pi, 50_000)
    fringes = [Fringes(100.0, 0.0, ("a", "b", "c"), SHIFTS3, 1.0)]

    def fitted(gamma: float) -> np.ndarray:
        light = [(0.5 + 0.5 * np.cos(true + d)) ** gamma + rng.normal(0, 0.002, true.shape) for d in SHIFTS3]
        return fit_phase([x[None, :] for x in light], SHIFTS3).phase[0]

    gamma, after, before = gamma_from_phases([fitted(2.2)], fringes)
    assert gamma == pytest.approx(2.2, abs=0.05) and before > 0.3 and after < 0.02
    gamma, after, before = gamma_from_phases([fitted(1.0)], fringes)
    assert before < 0.02 and before - after < 0.01  # nothing to gain: the decoder keeps gamma 1
    # fringes pre-distorted for 1.25 (value ** (1 / 1.25)) on a 2.2 projector bend by 2.2 / 1.25
    pre = [Fringes(100.0, 0.0, ("a", "b", "c"), SHIFTS3, 1.25)]
    gamma, _, _ = gamma_from_phases([fitted(2.2 / 1.25)], pre)
    assert gamma == pytest.approx(2.2, abs=0.06)


@pytest.fixture(scope="module")
def bent_capture(tmp_path_factory):
    """The virtual tile through a projector of gamma 2.2, 3-step fringes of 16 px (Gray code)."""
    config = VirtualCaptureConfig(scene="tile", patterns="phase", pattern_options={"steps": 3, "periods": (16,)},
                                  lit_images=False, camera_scale=0.4, projector_scale=0.5,
                                  optics=Optics(projector_gamma=2.2))
    return capture_session(config, tmp_path_factory.mktemp("bent") / "session")


def _column_error(session, **options) -> tuple[float, float, float]:
    result = decode_phase(session, session.views[0], **options)
    truth = session.load_ground_truth(session.views[0]).projector_uv[..., 0]
    both = np.isfinite(result.column) & np.isfinite(truth)
    error = result.column[both] - truth[both]
    return float(np.sqrt(np.mean(error**2))), float(both.sum()), result.projector_gamma


def test_a_bent_projector_is_estimated_and_corrected(bent_capture):
    rms_raw, n_raw, gamma_raw = _column_error(bent_capture, projector_gamma=None)
    rms, n, gamma = _column_error(bent_capture)
    assert gamma_raw == 1.0 and 1.7 < gamma < 2.5  # projector blur softens the curve a little
    assert n >= 0.98 * n_raw > 1000
    assert rms_raw > 0.3 and rms < 0.1, (rms_raw, rms)
    rms_given, _, gamma_given = _column_error(bent_capture, projector_gamma=2.0)
    assert gamma_given == 2.0 and rms_given < 0.12


def test_bad_projector_gamma_is_refused(bent_capture):
    with pytest.raises(SlscanError, match="projector_gamma"):
        decode_phase(bent_capture, bent_capture.views[0], projector_gamma="linear")


@pytest.mark.parametrize("gamma", [1.0, 2.2])
def test_four_steps_through_a_bent_projector_are_not_taken_for_noise(gamma, tmp_path):
    """With N >= 4 the fit's residual measures the noise; a bent fringe's harmonics are
    residual too, but common to adjacent pixels, so the noise is measured on their
    differences (before: gamma 2.2 read as 0.09 of full scale of noise, every pixel 'noisy';
    now 0.05, from the harmonics' change over a pixel of these 20-px fringes)."""
    config = VirtualCaptureConfig(scene="tile", patterns="phase", pattern_options={"steps": 4, "periods": (16,)},
                                  lit_images=False, camera_scale=0.4, projector_scale=0.5,
                                  optics=Optics(projector_gamma=gamma))
    session = capture_session(config, tmp_path / "session")
    result = decode_phase(session, session.views[0])
    counts = result.axes["columns"].counts
    assert counts["valid"] > 0.9 * counts["lit"], (result.noise, counts)
    if gamma == 1.0:  # the sensor's own noise, as the residual of each pixel measured it
        assert 0.0015 < result.noise < 0.0025
