"""The named light-transport effects: parsing, switching on, recording."""

from __future__ import annotations

import json

import pytest

from slscan.errors import SlscanError
from slscan.recipe.config import from_mapping
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.effects import EFFECTS, apply_effects, parse_effects
from slscan.virtual.render import Optics
from slscan.virtual.sensor import Sensor

NAMES = ("interreflection", "subsurface", "dof", "tone", "vignetting", "jpeg")


def test_every_effect_of_the_issue_is_registered_with_its_reference():
    known = parse_effects("all")
    assert set(NAMES) <= set(known)
    for name in known:
        effect = EFFECTS[name]
        assert effect.summary and effect.reference


@pytest.mark.parametrize("name", NAMES)
def test_an_effect_changes_the_settings_once(name):
    optics, sensor = Optics(), Sensor()
    once = apply_effects((name,), optics, sensor, 1300.0)
    assert once != (optics, sensor), f"{name} changed nothing"
    assert apply_effects((name,), *once, 1300.0) == once


def test_names_are_parsed_in_registry_order_and_checked():
    assert parse_effects("none") == ()
    assert parse_effects(None) == ()
    assert parse_effects("dof, interreflection") == tuple(n for n in EFFECTS if n in ("dof", "interreflection"))
    assert parse_effects(["all", "dof"]) == tuple(EFFECTS)
    with pytest.raises(SlscanError, match=r"--effects: unknown effect 'glare' \(known: all, none, "):
        parse_effects("dof,glare", "--effects")


def test_a_recipe_switches_effects_on_and_the_session_records_what_was_rendered(tmp_path):
    config = from_mapping(VirtualCaptureConfig, {"effects": ["tone", "vignetting"], "camera_scale": 0.1,
                                                 "projector_scale": 0.1, "levels": 4, "lit_images": False},
                          "capture")
    assert config.effects == parse_effects("tone,vignetting")
    assert (config.optics, config.sensor) == apply_effects(config.effects, Optics(), Sensor(), 1300.0)
    with pytest.raises(SlscanError, match="capture.effects: unknown effect .sparkle."):
        from_mapping(VirtualCaptureConfig, {"effects": ["sparkle"]}, "capture")
    capture_session(config, tmp_path / "s")
    recorded = json.loads((tmp_path / "s" / "session.json").read_text())["device"]["config"]
    assert recorded["effects"] == list(config.effects)
    assert recorded["sensor"] == config.sensor.to_dict()
    assert recorded["optics"] == config.optics.to_dict()
