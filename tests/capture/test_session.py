"""Capture-session round trip: what the virtual rig writes is what every later stage reads."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from slscan.capture.session import LIT, SHADOW, GroundTruth, load_session
from slscan.errors import SlscanError
from slscan.fsio import write_png
from slscan.virtual.device import (
    VirtualCaptureConfig,
    capture_session,
    capture_view,
    turntable_pose,
)
from slscan.virtual.scenes import builtin_object

SMALL = VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.25, levels=6, views=2)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "session"
    capture_session(SMALL, out)
    return load_session(out)


def test_session_round_trip(session):
    assert session.camera_size == (288, 192)
    assert session.projector_size == (256, 192)
    assert (session.channels, session.bit_depth) == (3, 8)
    assert [v.name for v in session.views] == ["view_000", "view_001"]
    assert session.calibration == SMALL.rig()
    ids = [p.id for p in session.patterns]
    assert ids[:2] == ["white", "black"] and ids[2:] == [f"hybrid-{k:02d}" for k in range(1, 7)]
    view = session.views[1]
    assert len(view.pattern_images()) == 8 and [r.light for r in view.lit_images()] == list(range(6))
    np.testing.assert_allclose(view.rig_from_object, turntable_pose(SMALL.rig(), 180.0))
    # images on disk equal a fresh render with the same seed
    rig = SMALL.rig()
    rendered, _ = capture_view(
        builtin_object(), rig, view.rig_from_object, SMALL.pattern_set(rig), SMALL, view_index=1
    )
    for rec, image in rendered:
        np.testing.assert_array_equal(session.read_image(view, rec), image)
    truth = session.load_ground_truth(view)
    assert truth.point.shape == (192, 288, 3)
    assert (truth.visibility == LIT).sum() > 1000 and (truth.visibility == SHADOW).sum() > 0


def test_bad_sessions_are_refused_naming_the_file(session, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(session.root, bad)
    view = session.views[0]
    victim = bad / view.name / view.images[3].file
    write_png(victim, np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SlscanError, match=f"{victim.name}: image is 10x10"):
        load_session(bad)
    victim.unlink()
    with pytest.raises(SlscanError, match=f"{victim.name}: image not found"):
        load_session(bad)

    meta = json.loads((session.root / "session.json").read_text())
    meta["version"] = 99
    (bad / "session.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match="version 99 is not supported"):
        load_session(bad)
    meta["version"] = 1
    meta["camera"]["width"] = "wide"
    (bad / "session.json").write_text(json.dumps(meta))
    with pytest.raises(SlscanError, match="wrong type"):
        load_session(bad)
    (bad / "session.json").write_text("{not json")
    with pytest.raises(SlscanError, match="not valid JSON"):
        load_session(bad)
    with pytest.raises(SlscanError, match="not found"):
        load_session(tmp_path / "nowhere")


def test_failed_capture_leaves_nothing(tmp_path):
    out = tmp_path / "never"
    with pytest.raises(SlscanError):
        capture_session(replace(SMALL, scene=str(tmp_path / "missing.ply")), out)
    assert not out.exists()
    assert not list(tmp_path.glob(".never*"))


def test_sixteen_bit_sessions(tmp_path):
    from slscan.virtual.sensor import Sensor

    config = replace(SMALL, views=1, lit_images=False, sensor=Sensor(bit_depth=16), scene="tile")
    s = load_session(capture_session(config, tmp_path / "s16").root)
    image = s.read_image(s.views[0], s.views[0].images[0])
    assert image.dtype == np.uint16 and image.max() > 1000


def test_ground_truth_column_crossings():
    # projector column u = 0.8 x + 10 along every row, rising; background (NaN) on row 1
    h, w = 3, 40
    u = np.tile(0.8 * np.arange(w, dtype=np.float32) + 10, (h, 1))
    u[1] = np.nan
    uv = np.stack([u, np.zeros_like(u)], axis=-1)
    nan3 = np.full((h, w, 3), np.nan, np.float32)
    truth = GroundTruth(nan3, nan3, nan3, uv, np.full((h, w), LIT, np.uint8))
    rows = np.array([0, 2, 0, 1])
    columns = np.array([20.0, 31.0, 20.0, 20.0])
    x = np.array([12.7, 26.0, 20.0, 12.5])  # measured near 12.5, 26.25; the third too far
    got = truth.column_crossings(rows, x, columns)
    np.testing.assert_allclose(got[:2], [12.5, 26.25], rtol=0, atol=1e-5)
    assert np.isnan(got[2]) and np.isnan(got[3])
    assert np.isnan(truth.column_crossings(rows[:1], x[:1] + 5.5, columns[:1])[0])
    assert truth.column_crossings(rows[:1], x[:1] + 5.5, columns[:1], reach=6)[0] == pytest.approx(12.5)
