"""Virtual-rig sessions shared by the albedo tests (rendered once per test run)."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.albedo.lights import calibrate_lights
from slscan.decode.pipeline import decode_session
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.panels import capture_light_calibration

SMALL = {"camera_scale": 0.25, "projector_scale": 0.25}


@pytest.fixture(scope="session")
def panel_session(tmp_path_factory: pytest.TempPathFactory):
    """The matte panel at its 6 default poses, quarter size, with sensor noise."""
    config = VirtualCaptureConfig(levels=5, **SMALL)
    return capture_light_calibration(tmp_path_factory.mktemp("panel") / "session", config=config)


@pytest.fixture(scope="session")
def calibrated(panel_session):
    """Lights calibrated from ``panel_session``, started 40-80 mm away from the truth."""
    true = np.array([light.position for light in panel_session.calibration.lights])
    rng = np.random.default_rng(3)
    start = true + rng.choice([-1, 1], true.shape) * rng.uniform(40, 80, true.shape)
    return calibrate_lights(panel_session, initial=start, max_samples_per_view=2500)


@pytest.fixture(scope="session")
def figurine(tmp_path_factory: pytest.TempPathFactory):
    """The figurine, two turntable views at quarter size, and its range maps: (session, folder)."""
    root = tmp_path_factory.mktemp("figurine")
    session = capture_session(VirtualCaptureConfig(views=2, levels=7, **SMALL), root / "capture")
    decode_session(session, root / "range_maps")
    return session, root / "range_maps"
