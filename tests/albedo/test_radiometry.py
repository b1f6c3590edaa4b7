"""Camera-response normalisation of the lit images."""

from __future__ import annotations

from pathlib import Path

import pytest

from slscan.albedo.radiometry import exposure_factor
from slscan.capture.session import ViewRecord
from slscan.errors import SlscanError


class _Session:
    root = Path("/scans/s")


def view(exposure) -> ViewRecord:
    return ViewRecord("view_003", (), exposure=exposure)


def test_exposure_factor_multiplies_the_recorded_settings():
    meta = {
        "sensor": {"white_level": 0.5, "exposure": 2.0, "gain": 1.5, "bit_depth": 8},
        "lit_exposure": 0.25,
    }
    assert exposure_factor(_Session(), view(meta)) == pytest.approx(0.5 * 2.0 * 1.5 * 0.25)
    assert exposure_factor(_Session(), view({"exposure": 4.0})) == pytest.approx(4.0)
    assert exposure_factor(_Session(), view({})) == 1.0  # a real rig that records nothing


@pytest.mark.parametrize(
    ("meta", "key"),
    [
        ({"sensor": {"gain": "high"}}, "gain"),
        ({"lit_exposure": 0}, "lit_exposure"),
        ({"sensor": 3}, "sensor"),
    ],
)
def test_bad_exposure_metadata_names_the_view_and_setting(meta, key):
    with pytest.raises(SlscanError, match=f"view view_003: exposure.*{key}"):
        exposure_factor(_Session(), view(meta))
