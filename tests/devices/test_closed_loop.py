"""Closed loop: the real projector window (pyglet, on a private Xvfb) and a fake camera
that renders the virtual object lit by a grab of that window, through ``slscan scan``.

The window is pixel-exact exactly when the loop reproduces the direct virtual scan bit for
bit; a one-pixel shift of the screen (a stand-in for a scaling or misplaced window) is
caught."""

from __future__ import annotations

import json

import numpy as np
import pytest

from slscan.capture.driver import scan
from slscan.capture.session import load_session
from slscan.cli import main
from slscan.devices.screen import ScreenProjector, grab_screen
from slscan.fsio import read_png
from slscan.virtual.device import VirtualCaptureConfig, scan_devices, scan_plan, virtual_devices
from slscan.virtual.devices import ScreenLoopCamera


def _images(root):
    session = load_session(root)
    return {f"{v.name}/{r.file}": read_png(session.image_path(v, r)) for v in session.views for r in v.images}


def test_scan_through_the_projector_window_equals_the_direct_virtual_scan(tmp_path, x_display, monkeypatch):
    monkeypatch.setenv("DISPLAY", x_display)
    common = ["--scale", "1", "--views", "1", "--quiet", "--seed", "3"]
    assert main(["scan", "--projector", "screen:0", "--camera", "loop", "--out", str(tmp_path / "loop"), *common]) == 0
    assert main(["scan", "--camera", "virtual", "--out", str(tmp_path / "direct"), *common]) == 0
    loop, direct = _images(tmp_path / "loop"), _images(tmp_path / "direct")
    assert loop.keys() == direct.keys() and len(loop) == 17  # white, black, 9 levels, 6 lit
    for name in loop:
        assert np.array_equal(loop[name], direct[name]), name
    meta = json.loads((tmp_path / "loop" / "session.json").read_text())
    assert meta["device"]["projector"]["kind"] == "screen"
    # on to a range map, as a user would
    assert main(["decode", str(tmp_path / "loop"), "--out", str(tmp_path / "maps"), "--quiet"]) == 0
    maps = json.loads((tmp_path / "maps" / "range_maps.json").read_text())
    assert maps["views"][0]["metrics"]["vertices"] > 20000


def test_a_shifted_screen_changes_the_scan(tmp_path, x_display):
    config = VirtualCaptureConfig(views=1, lit_images=False, levels=9)
    runs = {}
    with ScreenProjector(0, x_display=x_display) as projector:
        for shift in (0, 1):
            world = virtual_devices(config)

            def grab(shift=shift):
                return np.roll(grab_screen(projector), shift, axis=1)

            camera = ScreenLoopCamera(world, grab, world.camera.sensor)
            devices = scan_devices(world, camera)
            devices.projector = projector
            scan(devices, scan_plan(config, world.rig), tmp_path / f"s{shift}", views=1)
            runs[shift] = _images(tmp_path / f"s{shift}")
    name = "view_000/10_hybrid-09.png"
    diff = np.abs(runs[0][name].astype(int) - runs[1][name].astype(int))
    assert diff.max() > 40 and (diff > 8).mean() > 0.005


@pytest.mark.parametrize("argv, message", [
    (["--projector", "screen:7", "--camera", "loop"], "monitor 7 does not exist"),
    (["--projector", "screen:0", "--camera", "loop", "--scale", "0.5"], "the monitor is 1024x768"),
    (["--camera", "loop"], "give --projector screen"),
    (["--projector", "screen:0", "--camera", "opencv:9"], "camera opencv:9 not found"),
    (["--projector", "screen:0", "--camera", "folder:/nonexistent/dir"], "is not a folder"),
])
def test_bad_projector_choices_are_one_line_errors(tmp_path, x_display, monkeypatch, capsys, argv, message):
    monkeypatch.setenv("DISPLAY", x_display)
    out = tmp_path / "s"
    assert main(["scan", *argv, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not out.exists()


def test_no_display_is_a_one_line_error(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    assert main(["scan", "--projector", "screen:1", "--camera", "loop", "--out", str(tmp_path / "s")]) == 2
    assert "no X display" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()
