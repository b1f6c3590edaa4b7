"""Rerun streaming of the capture stage: log everything to an .rrd, read it back."""

from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from slscan.capture.session import BACKGROUND, LIT, SHADOW, GroundTruth
from slscan.errors import SlscanError
from slscan.rig import default_rig
from slscan.viewer.layouts import LAYOUTS, capture_blueprint, pipeline_blueprint, save_layouts
from slscan.viewer.log import (
    log_capture,
    log_ground_truth,
    log_pattern,
    log_rig,
    log_scene_mesh,
)
from slscan.viewer.recording import FRAME_TIMELINE, VIEW_TIMELINE, open_recording


@pytest.fixture(autouse=True)
def strict_rerun():
    """Make Rerun raise on bad archetype data instead of logging a warning."""
    previous = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(previous)


@pytest.fixture(scope="module")
def rig():
    return default_rig(scale=0.1, projector_scale=0.25)


def fake_ground_truth(rig) -> GroundTruth:
    """A plane at the working distance filling the middle of the image; NaN elsewhere."""
    w, h = rig.camera.width, rig.camera.height
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    rays = rig.camera.rays_local(np.stack([cols, rows], axis=-1).astype(float))
    point = (rays * rig.working_distance).astype(np.float32)
    fg = (abs(cols - w / 2) < w / 4) & (abs(rows - h / 2) < h / 4)
    point[~fg] = np.nan
    normal = np.where(fg[..., None], np.float32([0, 0, -1]), np.nan).astype(np.float32)
    albedo = np.where(fg[..., None], np.float32([0.6, 0.3, 0.1]), np.nan).astype(np.float32)
    uv = rig.projector.project(point).astype(np.float32)
    visibility = np.full((h, w), BACKGROUND, np.uint8)
    visibility[fg] = LIT
    visibility[fg & (cols < w / 2 - w / 8)] = SHADOW
    return GroundTruth(point, normal, albedo, uv, visibility)


def entity_paths(path) -> set[str]:
    return {c.entity_path for c in RrdReader(path).stream().to_chunks()}


def test_capture_stage_round_trip(tmp_path, rig):
    out = tmp_path / "capture.rrd"
    gt = fake_ground_truth(rig)
    h, w = gt.visibility.shape
    vertices = np.array([[-50, -50, 1300], [50, -50, 1300], [0, 50, 1300]], float)
    triangles = np.array([[0, 1, 2]])
    rng = np.random.default_rng(0)
    lens = rig.projector.lens
    with open_recording(save=out, recording_name="test") as rec:
        assert rec is not None
        log_rig(rec, rig)
        for view in range(2):
            log_scene_mesh(rec, vertices, triangles, np.ones((3, 3)) * 0.5, view_index=view)
            log_ground_truth(rec, gt, view_index=view, projector_width=rig.projector.lens.width)
            for frame in range(3):
                pattern = rng.integers(0, 256, (lens.height, lens.width, 3), np.uint8)
                log_pattern(rec, pattern, view_index=view, frame_index=frame)
                image = rng.integers(0, 65536, (h, w, 3), np.uint16)
                log_capture(rec, image, view_index=view, frame_index=frame, label=f"p{frame}")
            log_capture(
                rec, image[..., 0], view_index=view, frame_index=3, label="raw", compress=False
            )
    assert out.is_file()
    assert not list(tmp_path.glob(".*partial*"))

    paths = entity_paths(out)
    expected = {
        "/world", "/world/camera", "/world/camera/image",
        "/world/projector", "/world/projector/image",
        "/world/lights", "/world/scene/mesh", "/world/camera/image/capture",
        "/world/projector/image/pattern", "/log/capture",
        "/world/scans/view_000/truth_points", "/world/scans/view_001/truth_points",
    } | {
        f"/world/camera/image/truth/{layer}"
        for layer in ("depth", "normal", "albedo", "projector_column", "visibility")
    }
    assert expected <= paths, sorted(expected - paths)

    # the capture is on both timelines; 2 views x 4 frames
    store = RrdReader(out).store()
    all_chunks = store.stream().to_chunks()
    chunks = [c for c in all_chunks if c.entity_path == "/world/camera/image/capture"]
    assert sum(c.num_rows for c in chunks) == 8
    assert all({VIEW_TIMELINE, FRAME_TIMELINE} <= set(c.timeline_names) for c in chunks)
    statics = {c.entity_path for c in all_chunks if c.is_static}
    assert {"/world", "/world/camera/image", "/world/projector", "/world/lights"} <= statics


def test_no_sink_yields_none():
    with open_recording() as rec:
        assert rec is None
    # and every logger is a no-op on None, even with nonsense input
    log_rig(None, None)
    log_capture(None, None, view_index=0, frame_index=0, label="x")
    log_ground_truth(None, None, view_index=0)


def test_exception_leaves_no_file(tmp_path, rig):
    out = tmp_path / "fail.rrd"
    with pytest.raises(RuntimeError, match="boom"), open_recording(save=out) as rec:
        log_rig(rec, rig)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_exception_keeps_previous_file(tmp_path, rig):
    out = tmp_path / "scan.rrd"
    out.write_bytes(b"previous")
    with pytest.raises(RuntimeError), open_recording(save=out) as rec:
        log_rig(rec, rig)
        raise RuntimeError("boom")
    assert out.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["scan.rrd"]


def test_bad_url_and_path(tmp_path):
    with pytest.raises(SlscanError, match="not a Rerun viewer URL"), open_recording(connect="http://localhost:9876"):
        pass
    with pytest.raises(SlscanError, match="is a folder"), open_recording(save=tmp_path):
        pass
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(SlscanError, match="cannot write here"), open_recording(save=blocker / "sub" / "x.rrd"):
        pass


def test_bad_capture_image_is_reported(tmp_path):
    with open_recording(save=tmp_path / "x.rrd") as rec, pytest.raises(SlscanError, match="float"):
        log_capture(rec, np.zeros((4, 4)), view_index=0, frame_index=0, label="x")


def test_layouts(tmp_path):
    assert capture_blueprint() is not None
    paths = save_layouts(tmp_path)
    assert [p.name for p in paths] == [f"{name}.rbl" for name in LAYOUTS]
    assert all(p.stat().st_size > 0 for p in paths)
    assert not list(tmp_path.glob(".*partial*"))


def test_pipeline_layout_opens_on_the_first_stage_of_the_recipe():
    tabs = pipeline_blueprint().root_container
    names = [c.name for c in tabs.contents]
    assert names == ["Capture", "Decode", "Albedo", "Register", "Texture"]
    assert tabs.active_tab == 0
    # a recipe that starts from range maps (the bunny) opens on Register
    assert names[pipeline_blueprint(["register", "fuse", "simplify"]).root_container.active_tab] == "Register"
    # stages without a tab of their own are passed over
    assert names[pipeline_blueprint(["calibrate", "decode"]).root_container.active_tab] == "Decode"


def _capture_columns(path) -> set[str]:
    names = set()
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.entity_path == "/world/camera/image/capture":
            names |= set(chunk.to_record_batch().schema.names)
    return names


@pytest.mark.parametrize("lossless,column", [(False, "EncodedImage:blob"), (True, "Image:buffer")])
def test_captures_are_jpeg_unless_lossless_is_asked(tmp_path, lossless, column):
    path = tmp_path / "frames.rrd"
    frame = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    with open_recording(save=path, lossless_images=lossless) as rec:
        log_capture(rec, frame, view_index=0, frame_index=0, label="white")
    assert column in _capture_columns(path)


def test_a_second_session_logs_into_its_own_subtree_and_timelines(tmp_path, rig):
    """The light panel beside the scan: the same loggers, another entity tree and timelines;
    each session's rig once, the scan's time cursor not carried into the panel's data."""
    from slscan.viewer.recording import session_stream

    other = default_rig(scale=0.05, projector_scale=0.25)
    path = tmp_path / "two.rrd"
    with open_recording(save=path) as rec:
        log_rig(rec, rig)
        log_capture(rec, np.zeros((rig.camera.height, rig.camera.width), np.uint8), view_index=5,
                    frame_index=2, label="scan")
        with session_stream(rec, "panel") as panel:
            for _ in range(2):  # the same rig again: sent once
                log_rig(panel, other)
            log_capture(panel, np.zeros((other.camera.height, other.camera.width), np.uint8), view_index=1,
                        frame_index=0, label="panel")
        log_rig(rec, rig)  # the scan's again: sent once too
    chunks = list(RrdReader(path).stream().to_chunks())
    timelines = {}
    statics: dict[str, int] = {}
    for c in chunks:
        timelines.setdefault(c.entity_path, set()).update(set(c.timeline_names) - {"log_time"})
        if c.is_static:
            statics[c.entity_path] = statics.get(c.entity_path, 0) + c.num_rows
    assert timelines["/world/camera/image/capture"] == {VIEW_TIMELINE, FRAME_TIMELINE}
    assert timelines["/world/panel/camera/image/capture"] == {"panel_view", "panel_frame"}
    assert timelines["/log/panel/capture"] == {"panel_view", "panel_frame"}
    assert statics["/world/camera/image"] == 1 and statics["/world/panel/camera/image"] == 1
    resolution = {c.entity_path: c.to_record_batch().column("Pinhole:resolution").to_pylist()[0][0]
                  for c in chunks if c.is_static and c.entity_path.endswith("camera/image")}
    assert resolution["/world/camera/image"] == [rig.camera.width, rig.camera.height]
    assert resolution["/world/panel/camera/image"] == [other.camera.width, other.camera.height]
    assert session_stream(None, "panel").__enter__() is None  # logging off
