"""Virtual-rig sessions shared by the decode tests (rendered once per test run)."""

from __future__ import annotations

import pytest

from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor


@pytest.fixture(scope="session")
def gray_tile_session(tmp_path_factory: pytest.TempPathFactory):
    """A noise-free Gray-code capture of the flat tile at quarter size."""
    config = VirtualCaptureConfig(
        scene="tile", patterns="gray", camera_scale=0.25, projector_scale=0.25,
        lit_images=False, sensor=Sensor(noise=False),
    )
    return capture_session(config, tmp_path_factory.mktemp("gray_tile") / "session")
