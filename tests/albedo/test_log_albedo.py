"""Rerun logging of the albedo stage: entity paths, timelines, the blueprint."""

from __future__ import annotations

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from slscan.albedo.lights import LightCalibration
from slscan.errors import SlscanError
from slscan.rig import default_rig
from slscan.viewer.layouts import albedo_blueprint
from slscan.viewer.log_albedo import (
    albedo_error_image,
    log_albedo_error,
    log_albedo_mesh,
    log_albedo_metrics,
    log_lights,
    log_lit_image,
    log_unshaded,
)
from slscan.viewer.recording import FRAME_TIMELINE, VIEW_TIMELINE, open_recording


@pytest.fixture(autouse=True)
def strict_rerun():
    previous = rr.strict_mode()
    rr.set_strict_mode(True)
    yield
    rr.set_strict_mode(previous)


def test_albedo_stage_round_trip(tmp_path):
    out = tmp_path / "albedo.rrd"
    h, w = 24, 32
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    valid = rng.uniform(size=(h, w)) > 0.2
    lights = LightCalibration.from_rig(default_rig(scale=0.1))
    vertices = np.array([[-50, -50, 1300], [50, -50, 1300], [0, 50, 1300]], float)
    with open_recording(save=out) as rec:
        for frame in range(2):
            image = rng.integers(0, 256, (h, w, 3), np.uint8)
            log_lit_image(
                rec,
                image,
                view_index=0,
                frame_index=11 + frame,
                light=frame,
                shadow=rng.uniform(size=(h, w)) > 0.9,
                highlight=rng.uniform(size=(h, w)) > 0.95,
            )
        log_unshaded(
            rec,
            albedo,
            valid,
            view_index=0,
            normal=np.dstack([np.zeros((h, w, 2)), -np.ones((h, w))]),
        )
        log_albedo_error(rec, albedo, albedo * 1.05, valid, view_index=0)
        log_albedo_mesh(
            rec,
            vertices,
            [[0, 1, 2]],
            None,
            np.array([[0.5, 0.2, 0.1], [np.nan] * 3, [1, 1, 1]]),
            view_index=0,
        )
        log_lights(rec, lights)
        log_albedo_metrics(rec, {"valid_share": 0.9, "nan": float("nan")}, view_index=0)
    chunks = RrdReader(out).stream().to_chunks()
    paths = {c.entity_path for c in chunks}
    expected = {
        f"/world/camera/image/albedo/{x}"
        for x in ("lit", "shadow", "highlight", "unshaded", "normal", "error")
    }
    expected |= {
        "/world/albedo/view_000",
        "/world/lights/calibrated",
        "/plot/albedo/valid_share",
        "/log/albedo",
    }
    assert expected <= paths, sorted(expected - paths)
    assert "/plot/albedo/nan" not in paths
    lit = [c for c in chunks if c.entity_path == "/world/camera/image/albedo/lit"]
    assert sum(c.num_rows for c in lit) == 2
    assert all({VIEW_TIMELINE, FRAME_TIMELINE} <= set(c.timeline_names) for c in lit)
    assert any(c.is_static for c in chunks if c.entity_path == "/world/lights/calibrated")


def test_no_recording_is_a_no_op():
    log_lit_image(None, None, view_index=0, frame_index=0, light=0)
    log_unshaded(None, None, None, view_index=0)
    log_albedo_error(None, None, None, None, view_index=0)
    log_albedo_mesh(None, None, None, None, None, view_index=0)
    log_lights(None, None)
    log_albedo_metrics(None, None, view_index=0)


def test_mismatched_shapes_are_refused(tmp_path):
    with open_recording(save=tmp_path / "x.rrd") as rec:
        with pytest.raises(SlscanError, match="shadow mask of light 3"):
            log_lit_image(
                rec,
                np.zeros((4, 5, 3), np.uint8),
                view_index=0,
                frame_index=0,
                light=3,
                shadow=np.zeros((5, 4), bool),
            )
        with pytest.raises(SlscanError, match="ground-truth albedo"):
            log_albedo_error(
                rec, np.zeros((4, 5, 3)), np.zeros((5, 4, 3)), np.zeros((4, 5), bool), view_index=0
            )


def test_error_image_and_blueprint(tmp_path):
    truth = np.full((2, 2, 3), 0.5)
    estimate = truth * np.array([1.0, 1.1, 1.0, 1.0]).reshape(2, 2, 1)
    image = albedo_error_image(estimate, truth, np.array([[True, True], [False, True]]))
    assert image.shape == (2, 2, 3) and image.dtype == np.uint8
    assert image[1, 0].sum() == 0  # invalid: black
    assert image[0, 1].tolist() != image[0, 0].tolist()  # 10 % error: top of the scale
    blueprint = albedo_blueprint()
    assert isinstance(blueprint, rr.blueprint.Blueprint)
    blueprint.save("slscan", tmp_path / "albedo.rbl")
    assert (tmp_path / "albedo.rbl").stat().st_size > 0
