"""A phase-shifting decode in Rerun: its maps, corrections and counts, where the layouts look.

A two-view virtual phase capture (columns and rows, quarter size) decoded by the decode
stage into an .rrd, read back entity by entity; the loggers' colours on synthetic maps;
the layouts that arrange them. ``test_render_phase.py`` renders the phase layout.
"""

from __future__ import annotations

from collections import defaultdict
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import rerun as rr
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from slscan.decode.family import DisplayMap
from slscan.decode.phase import AxisDecode, PhaseResult, display_maps
from slscan.decode.pipeline import decode_session
from slscan.errors import SlscanError
from slscan.patterns import standard_set
from slscan.viewer.layouts import LAYOUTS, decode_blueprint, phase_blueprint
from slscan.viewer.log_decode import colormap_range, log_display_maps, log_metrics
from slscan.viewer.layouts import scan_blueprint
from slscan.viewer.recording import FRAME_TIMELINE, VIEW_TIMELINE, open_recording
from slscan.virtual.device import VirtualCaptureConfig, capture_session

PHASE = "/world/camera/image/decode/phase"
AXES = ("columns", "rows")
COUNTS = ("low_modulation", "order_corrected", "order_rejected", "unwrap_rejected", "out_of_range")


@pytest.fixture(autouse=True)
def strict_rerun():
    previous = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(previous)


@pytest.fixture(scope="module")
def phase_decode(tmp_path_factory):
    """(rrd path, results) of decoding two views of a virtual phase capture with rows."""
    root = tmp_path_factory.mktemp("phase_rrd")
    config = VirtualCaptureConfig(scene="object", patterns="phase", gray_rows=True, views=2, camera_scale=0.25,
                                  projector_scale=0.25, lit_images=False)
    session = capture_session(config, root / "session")
    path = root / "decode.rrd"
    with open_recording(save=path, recording_name="phase") as rec:
        results = decode_session(session, root / "maps", rec=rec)
    return path, results


def _chunks(path) -> dict[str, list]:
    out = defaultdict(list)
    for chunk in RrdReader(path).stream().to_chunks():
        out[chunk.entity_path].append(chunk)
    return out


def test_phase_entities_are_under_the_camera_image(phase_decode):
    path, _ = phase_decode
    chunks = _chunks(path)
    expected = {f"{PHASE}/wrapped/{axis}/period_8" for axis in AXES}  # the default set: one period of 8 px
    expected |= {f"{PHASE}/{kind}/{axis}" for kind in ("unwrapped", "modulation", "order_fix") for axis in AXES}
    expected |= {f"/plot/decode/phase/{axis}/{count}_share" for axis in AXES for count in COUNTS}
    assert expected <= set(chunks), sorted(expected - set(chunks))
    # nothing else of the phase decode lands outside the camera image's decode subtree
    stray = {p for p in chunks if "phase" in p and not p.startswith((PHASE + "/", "/plot/decode/phase/"))}
    assert not stray


def test_phase_maps_are_on_their_views_timeline_value(phase_decode):
    path, _ = phase_decode
    views = defaultdict(list)
    for entity, chunks in _chunks(path).items():
        if not entity.startswith(PHASE + "/"):
            continue
        for chunk in chunks:
            if chunk.is_static:
                continue
            assert {VIEW_TIMELINE, FRAME_TIMELINE} <= set(chunk.timeline_names), entity
            batch = chunk.to_record_batch()
            views[entity] += batch.column(VIEW_TIMELINE).to_pylist()
            assert set(batch.column(FRAME_TIMELINE).to_pylist()) == {0}, entity  # the view's frame 0
    assert views and all(sorted(v) == [0, 1] for v in views.values()), dict(views)


def test_static_data_is_logged_once(phase_decode):
    path, _ = phase_decode
    statics = defaultdict(int)
    for entity, chunks in _chunks(path).items():
        statics[entity] += sum(c.num_rows for c in chunks if c.is_static)
    # two views decoded: the corrections' annotation context and the counts' series style once each
    for axis in AXES:
        assert statics[f"{PHASE}/order_fix/{axis}"] == 1
        for count in COUNTS:
            assert statics[f"/plot/decode/phase/{axis}/{count}_share"] == 1
    assert not any(n for e, n in statics.items() if e.startswith(PHASE + "/") and "order_fix" not in e)


def test_decode_keeps_no_maps_once_streamed(phase_decode):
    _, results = phase_decode
    assert all(r.maps == {} for r in results)
    assert all("phase/columns/order_corrected_share" in r.metrics for r in results)


def test_every_period_wrapped_the_finest_on_top():
    pw, ph, w, h = 1024, 768, 8, 6
    session = SimpleNamespace(projector_size=(pw, ph),
                              patterns=standard_set("phase", width=pw, height=ph, periods=(32.0, 8.0)))
    wrapped = (np.full((h, w), 1.0, np.float32), np.full((h, w), 2.0, np.float32))  # longest period first
    coord = np.full((h, w), 100.0)
    axis = AxisDecode(coord, (coord, coord), wrapped, np.full((h, w), 0.5, np.float32), "complementary", {},
                      np.zeros((h, w), np.int8))
    contrast = np.full((h, w), 0.5, np.float32)
    contrast[0, 0] = 0.0  # not lit
    result = PhaseResult(coord, None, np.ones((h, w), bool), contrast, np.zeros((h, w), bool), 0.001,
                         {"columns": axis})
    maps = display_maps(result, session)
    coarse, fine = maps["phase/wrapped/columns/period_32"], maps["phase/wrapped/columns/period_8"]
    assert fine.draw_order > coarse.draw_order
    assert (coarse.values[1, 1], fine.values[1, 1]) == (1.0, 2.0) and np.isnan(fine.values[0, 0])
    assert coarse.colormap == "twilight" and maps["phase/unwrapped/columns"].value_range == (0.0, pw - 1.0)
    assert not any("rows" in name for name in maps)  # no row fringes, no row maps


def test_display_maps_colours_and_marks(tmp_path):
    wrapped = np.array([[0.0, np.pi / 2, 2 * np.pi - 1e-9, np.nan]])
    rgb = colormap_range(wrapped, (0.0, 2 * np.pi), "twilight")
    assert rgb[0, 3].tolist() == [0, 0, 0]  # NaN: black
    assert np.abs(rgb[0, 0].astype(int) - rgb[0, 2]).max() <= 8  # cyclic: both ends of a turn meet
    assert np.abs(rgb[0, 0].astype(int) - rgb[0, 1]).max() > 60
    turbo = colormap_range(np.array([[-5.0, 0.0, 100.0, 200.0]]), (0.0, 100.0), "turbo")
    assert turbo[0, 0].tolist() == turbo[0, 1].tolist() and turbo[0, 2].tolist() == turbo[0, 3].tolist()
    with pytest.raises(SlscanError, match="colormap"):
        DisplayMap(np.zeros((2, 2)), "jet")

    classes = np.zeros((6, 8), np.uint8)
    classes[1, 2], classes[4, 7] = 1, 3
    labels = {1: ("up", (0, 255, 0, 255)), 3: ("rejected", (255, 0, 255, 255))}
    maps = {"test/fix": DisplayMap(classes, labels=labels), "test/ramp": DisplayMap(np.ones((6, 8)))}
    path = tmp_path / "maps.rrd"
    with open_recording(save=path) as rec:
        for view in range(3):
            log_display_maps(rec, maps, view_index=view)
        log_display_maps(None, maps, view_index=0)  # logging off: nothing to do
    chunks = _chunks(path)["/world/camera/image/decode/test/fix"]
    assert sum(c.num_rows for c in chunks if c.is_static) == 1
    batch = next(c for c in chunks if not c.is_static).to_record_batch()
    points = batch.column("Points2D:positions").to_pylist()[0]
    assert sorted(map(tuple, points)) == [(2.5, 1.5), (7.5, 4.5)]  # pixel centres in Rerun's image space
    assert sorted(batch.column("Points2D:class_ids").to_pylist()[0]) == [1, 3]


def test_metrics_marked_once(tmp_path):
    path = tmp_path / "metrics.rrd"
    with open_recording(save=path) as rec:
        for view in range(3):
            log_metrics(rec, {"phase/columns/x_share": 0.1 * view, "samples": 5.0}, view_index=view,
                        marked={"phase/columns/x_share"})
    chunks = _chunks(path)
    assert sum(c.num_rows for c in chunks["/plot/decode/phase/columns/x_share"] if c.is_static) == 1
    assert not any(c.is_static for c in chunks["/plot/decode/samples"])


def _view_names(container) -> list[str]:
    names = []
    for item in container.contents:
        names += [item.name] if isinstance(item, rrb.View) else _view_names(item)
    return names


def test_phase_layouts():
    assert "phase" in LAYOUTS
    phase = phase_blueprint().root_container
    assert phase.name == "Phase"
    names = _view_names(phase)
    for name in ("Wrapped (columns)", "Wrapped (rows)", "Projector column", "Projector row", "Modulation",
                 "Order fixes", "Range maps"):
        assert name in names
    # the decode stage opens on the family's own tab; other families keep the one Decode view
    tabs = decode_blueprint(family="phase").root_container
    assert [c.name for c in tabs.contents] == ["Decode", "Phase"] and tabs.active_tab == 1
    assert decode_blueprint(family="gray").root_container.name == "Decode"
    # the live scan's quick decode has a phase tab
    scan = scan_blueprint().root_container
    assert {"Wrapped phase", "Projector column", "Modulation", "Order fixes"} <= set(_view_names(scan))


def test_colormap_matches_opencv_at_its_ends():
    # the viewer's colours are OpenCV's maps, so the figures and docs can name them
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[None], cv2.COLORMAP_VIRIDIS)[0, :, ::-1]
    assert colormap_range(np.array([[0.0, 1.0]]), (0.0, 1.0), "viridis")[0].tolist() == [lut[0].tolist(),
                                                                                       lut[255].tolist()]
