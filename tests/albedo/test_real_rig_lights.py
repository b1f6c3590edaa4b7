"""Ring-light calibration as a real rig does it: the panel placed by hand at unknown poses,
the lights switched by an operator answering prompts, all through the acquisition driver.

The hardware boundary is faked and named so: :class:`FakeOperatorSwitchedLights` asks at
the terminal exactly as :class:`~slscan.devices.lights.ManualLights` does (``input()`` on
a scripted stdin) and, once "Enter" is read, does what the operator's hand would: switches
the virtual rig's lamp. :class:`FakeHandPlacedPanel` moves the virtual panel but, like an
operator, reports no pose. The panel's plane then has to come from its own range map.
"""

from __future__ import annotations

import io
import sys

import numpy as np
import pytest

from slscan.albedo.lights import MattePanel, calibrate_lights, fit_panel_plane
from slscan.albedo.unshade import load_range_map
from slscan.capture.driver import ScanDevices, scan
from slscan.decode.pipeline import decode_session
from slscan.devices.base import Placement, Stage
from slscan.devices.lights import ManualLights, terminal_prompt
from slscan.errors import SlscanError
from slscan.virtual.device import VirtualCaptureConfig, scan_plan, virtual_devices
from slscan.virtual.panels import light_calibration_poses, panel_scene

PANEL = MattePanel(albedo=(0.7, 0.75, 0.8))


class ScriptedTerminal(io.StringIO):
    """Scripted stdin that says it is a terminal (what an operator's keyboard is)."""

    def isatty(self) -> bool:
        return True


class FakeOperatorSwitchedLights(ManualLights):
    """FAKE real ring lights switched by hand: prompts through ``input()`` like
    :class:`ManualLights`, then switches the virtual rig's lamp as the operator would."""

    name = "fake-operator-switched-lights"

    def __init__(self, world) -> None:
        super().__init__(len(world.rig.lights), prompt=self._ask)
        self.world = world
        self.asked: list[str] = []

    def _ask(self, message: str) -> None:
        terminal_prompt(message, who="the fake operator needs")
        self.asked.append(message)

    def switch(self, index: int, on: bool) -> None:
        super().switch(index, on)
        self.world.lights_on = set(self._on or ())

    def all_off(self) -> None:
        super().all_off()
        self.world.lights_on = set()


class FakeHandPlacedPanel(Stage):
    """FAKE operator placing the panel: the virtual panel moves, no pose is reported."""

    name = "fake-hand-placed-panel"

    def __init__(self, world) -> None:
        self.world = world

    def move_to(self, view_index: int, views: int) -> Placement:
        self.world.stage.move_to(view_index, views)
        return Placement()


@pytest.fixture(scope="module")
def hand_session(tmp_path_factory):
    """Three hand-placed panel poses scanned with operator-switched lights, decoded."""
    root = tmp_path_factory.mktemp("hand")
    config = VirtualCaptureConfig(levels=6, camera_scale=0.25, projector_scale=0.25)
    rig = config.rig()
    world = virtual_devices(config, scene=panel_scene(PANEL), poses=light_calibration_poses(rig, count=4), rig=rig)
    lights = FakeOperatorSwitchedLights(world)
    devices = ScanDevices(world.projector, world.camera, lights, FakeHandPlacedPanel(world))
    stdin = ScriptedTerminal("\n" * 200)
    old = sys.stdin
    sys.stdin = stdin
    try:
        result = scan(devices, scan_plan(config, rig), root / "session", views=4, calibration=rig,
                      calibration_source="measured")
    finally:
        sys.stdin = old
    decode_session(result.session, root / "range_maps")
    return result.session, root / "range_maps", lights, stdin, world


def test_operator_was_asked_for_every_light(hand_session):
    session, _, lights, stdin, _ = hand_session
    assert "Switch light 3 of 6 ON, then press Enter" in lights.asked
    ons = [m for m in lights.asked if m.endswith("ON, then press Enter")]
    assert len(ons) == 4 * 6
    assert stdin.read().count("\n") == 200 - len(lights.asked)  # one Enter read per prompt
    assert all(v.rig_from_object is None for v in session.views)
    assert [len(v.lit_images()) for v in session.views] == [6] * 4


def test_lit_images_show_the_light_asked_for(hand_session):
    session, _, _, _, world = hand_session
    view = session.views[0]
    frames = [session.read_image(view, r).astype(float).mean() for r in view.lit_images()]
    # every light lit the panel: nothing dark, no two images identical
    assert min(frames) > 5
    assert len({round(f, 3) for f in frames}) == 6


def test_panel_plane_from_its_range_map(hand_session):
    session, range_maps, _, _, world = hand_session
    poses = light_calibration_poses(world.rig, count=4)
    for view, pose in zip(session.views, poses):
        fit = fit_panel_plane(session, view, load_range_map(range_maps, view)[0], PANEL)
        true_point, true_normal = PANEL.front_plane(pose)
        point, normal = PANEL.front_plane(fit.rig_from_panel)
        assert np.degrees(np.arccos(min(1.0, normal @ true_normal))) < 0.5
        assert abs((point - true_point) @ true_normal) < 1.0
        assert fit.mask.sum() > 1000


def test_calibration_without_poses(hand_session):
    session, range_maps, _, _, world = hand_session
    with pytest.raises(SlscanError, match="pose is unknown.*range maps"):
        calibrate_lights(session, panel=PANEL)
    cal = calibrate_lights(session, panel=PANEL, range_maps=range_maps, max_samples_per_view=2500)
    true = np.array([light.position for light in world.rig.lights])
    assert np.linalg.norm(cal.positions - true, axis=1).max() < 10.0
    np.testing.assert_allclose(cal.intensities, [light.intensity for light in world.rig.lights], rtol=0.03)
    assert cal.projector is not None
    rig = world.rig
    d0 = np.linalg.norm(rig.projector.center - [0, 0, rig.working_distance])
    expected = np.array([1.12, 1.14, 1.16]) * (d0 / rig.working_distance) ** 2
    np.testing.assert_allclose(cal.projector.intensity, expected, rtol=0.02)
    assert set(cal.fit["panel_planes_rms_mm"]) == {v.name for v in session.views}


def test_calibrate_lights_command_takes_the_range_maps(hand_session, tmp_path):
    import argparse

    from slscan.albedo.command import add_command
    from slscan.albedo.lights import read_lights

    session, range_maps, _, _, _ = hand_session
    parser = argparse.ArgumentParser(prog="slscan")
    add_command(parser.add_subparsers(dest="command"))
    argv = ["calibrate-lights", str(session.root), "--out", str(tmp_path / "lights.json"), "--quiet",
            "--panel-albedo", "0.7", "0.75", "0.8"]
    args = parser.parse_args(argv)
    with pytest.raises(SlscanError, match="pose is unknown"):
        args.func(args)
    assert not (tmp_path / "lights.json").exists()
    args = parser.parse_args([*argv, "--range-maps", str(range_maps)])
    assert args.func(args) == 0
    cal = read_lights(tmp_path / "lights.json")
    assert len(cal.lights) == 6 and cal.projector is not None


def test_driver_switched_lights_calibrate_from_the_range_maps(tmp_path):
    """The same with lights the driver switches itself (the virtual rig's, as a relay board's)."""
    config = VirtualCaptureConfig(levels=6, camera_scale=0.25, projector_scale=0.25)
    rig = config.rig()
    world = virtual_devices(config, scene=panel_scene(PANEL), poses=light_calibration_poses(rig, count=3), rig=rig)
    devices = ScanDevices(world.projector, world.camera, world.lights, FakeHandPlacedPanel(world))
    session = scan(devices, scan_plan(config, rig), tmp_path / "session", views=3, calibration=rig).session
    decode_session(session, tmp_path / "range_maps")
    cal = calibrate_lights(session, panel=PANEL, range_maps=tmp_path / "range_maps", max_samples_per_view=2500)
    true = np.array([light.position for light in rig.lights])
    assert np.linalg.norm(cal.positions - true, axis=1).max() < 15.0
