"""The live preview: focus (stripe contrast per tile), clipping and projector overlap on
synthetic frames with known answers and on the virtual rig (a blurred camera scores lower,
the overlap is the rendered truth), its Rerun entities, and `slscan scan --preview`."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rerun.chunk import RrdReader

from slscan.capture.preview import measure_once, preview_measures, run_preview, stripe_images
from slscan.devices.base import DeviceError
from slscan.virtual.device import VirtualCaptureConfig, virtual_devices
from slscan.virtual.sensor import Sensor


def test_stripes_are_two_px_and_inverse():
    s, i = stripe_images(8, 2)
    assert s[0, :, 0].tolist() == [255, 255, 0, 0, 255, 255, 0, 0]
    assert np.array_equal(s + i, np.full_like(s, 255))
    with pytest.raises(DeviceError, match="even number"):
        stripe_images(8, 2, period_px=3)


def test_known_contrast_clipping_and_overlap():
    h, w = 60, 80
    black = np.full((h, w, 3), 10, np.uint8)
    white = black.copy()
    white[:, :40] = 210  # the projector lights the left half
    white[:6, :4] = 255  # 24 of 2400 lit pixels clipped
    stripes, inverse = black.copy(), black.copy()
    stripes[:, :40] = 10 + 150  # contrast |S - I| / (S + I - 2 black) = 100 / 200 = 0.5
    inverse[:, :40] = 10 + 50
    m = preview_measures(black, white, stripes, inverse, tiles=(2, 4))
    assert m.overlap == pytest.approx(0.5)
    assert m.clipped_share == pytest.approx(24 / 2400)
    np.testing.assert_allclose(m.focus_tiles[:, :2], 0.5, rtol=1e-6)
    assert np.isnan(m.focus_tiles[:, 2:]).all() and m.focus == pytest.approx(0.5)


def _world(blur: float = 0.6, exposure: float = 1.0):
    config = VirtualCaptureConfig(camera_scale=0.25, projector_scale=0.25, scene="tile",
                                  sensor=Sensor(blur_sigma=blur, exposure=exposure))
    world = virtual_devices(config)
    world.stage.move_to(0, 1)
    return world


def test_virtual_rig_focus_falls_with_blur_and_overlap_is_the_truth():
    focus = []
    for blur in (0.3, 1.5, 3.0):
        world = _world(blur)
        m = measure_once(world.projector, world.camera)
        truth = float((world.geometry.hit & world.geometry.proj_lit).mean())
        assert m.overlap == pytest.approx(truth, abs=0.02)
        focus.append(m.focus)
    assert focus[0] > 0.5 > 0.1 > focus[1] > focus[2]
    assert measure_once(*(lambda w: (w.projector, w.camera))(_world())).clipped_share == 0
    assert measure_once(*(lambda w: (w.projector, w.camera))(_world(exposure=4))).clipped_share > 0.5


def test_run_preview_stops_after_frames_or_stop_and_logs(tmp_path):
    from slscan.viewer.log_preview import CLIPPED_PLOT, FOCUS_PATH, FOCUS_PLOT, IMAGE_PATH, OVERLAP_PLOT, log_preview
    from slscan.viewer.recording import open_recording

    world = _world()
    out = tmp_path / "p.rrd"
    with open_recording(save=out, recording_name="test") as rec:
        got = run_preview(world.projector, world.camera, frames=2, on_measures=lambda i, m: log_preview(rec, i, m))
    assert len(got) == 2
    paths = {c.entity_path for c in RrdReader(out).stream().to_chunks()}
    assert {f"/{p}" for p in (IMAGE_PATH, FOCUS_PATH, FOCUS_PLOT, CLIPPED_PLOT, OVERLAP_PLOT)} <= paths
    calls = []
    got = run_preview(world.projector, world.camera, stop=lambda: calls.append(1) or len(calls) >= 3)
    assert len(got) == 3
    with pytest.raises(DeviceError, match="needs an end"):
        run_preview(world.projector, world.camera)


def test_scan_preview_on_the_virtual_rig_prints_each_refresh(capsys):
    from slscan.cli import main

    code = main(["scan", "--camera", "virtual", "--scene", "tile", "--scale", "0.25", "--preview",
                 "--preview-frames", "2", "--quiet"])
    err = capsys.readouterr().err
    assert code == 0
    assert "preview 1" in err and "preview 2" in err and "projector lights" in err
    assert not math.isnan(float(err.split("preview 2")[1].split("focus ")[1].split(",")[0]))


def test_preview_without_a_camera_is_one_line_and_non_zero(tmp_path, capsys):
    from slscan.cli import main

    code = main(["scan", "--camera", f"folder:{tmp_path / 'nothing'}", "--preview", "--preview-frames", "1"])
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert "nothing is not a folder" in err and len(err.splitlines()) == 1


def test_preview_needs_a_terminal_or_a_limit(capsys, monkeypatch):
    import io

    from slscan.cli import main

    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    code = main(["scan", "--camera", "virtual", "--scene", "tile", "--scale", "0.25", "--preview"])
    assert code != 0
    assert "--preview-seconds N" in capsys.readouterr().err
