"""Lens and sensor effects of the virtual rig (dof, tone, vignetting, jpeg) against known answers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from slscan.capture.session import load_session
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, default_rig, transform_points
from slscan.virtual.device import VirtualCaptureConfig, capture_session, capture_view
from slscan.virtual.render import (
    COC_PER_SIGMA,
    Optics,
    projector_light_image,
    shade_image,
    trace_view,
)
from slscan.virtual.scenes import Scene, UniformAlbedo
from slscan.virtual.sensor import Sensor

CLEAN = Optics(crosstalk=((1, 0, 0), (0, 1, 0), (0, 0, 1)), ambient=(0, 0, 0), projector_black=0.0,
               projector_blur=0.0)


@pytest.fixture(scope="module")
def rig():
    return default_rig(scale=0.5, projector_scale=0.5)


def projector_plane(rig, depth: float, size: float = 700.0) -> Scene:
    """A square facing the projector, ``depth`` mm along its axis (constant projector depth)."""
    h = size / 2
    local = np.array([[-h, -h, depth], [h, -h, depth], [h, h, depth], [-h, h, depth]])
    verts = transform_points(rig.projector.rig_from_projector, local)
    tris = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    return Scene("plane", verts, tris, None, UniformAlbedo((0.8, 0.8, 0.8)))


def column_step(rig) -> np.ndarray:
    lens = rig.projector.lens
    image = np.zeros((lens.height, lens.width, 3), np.uint8)
    image[:, lens.width // 2 :] = 255
    return image


def box_filtered_edge(u: np.ndarray, width: np.ndarray, centre: float, sigma: float) -> np.ndarray:
    """A unit step at ``centre`` blurred by a Gaussian of ``sigma``, averaged over a box of
    ``width`` around each ``u`` (a camera pixel's footprint), in closed form."""
    from scipy.special import ndtr

    def integral(t):  # of the normal CDF
        return t * ndtr(t) + np.exp(-0.5 * t**2) / np.sqrt(2 * np.pi)

    if sigma <= 0:
        return np.clip((u + width / 2 - centre) / width, 0, 1)
    hi, lo = (u + width / 2 - centre) / sigma, (u - width / 2 - centre) / sigma
    return (integral(hi) - integral(lo)) * sigma / width


def edge_sigma(u: np.ndarray, width: np.ndarray, light: np.ndarray, centre: float) -> float:
    """The Gaussian blur (px) that best explains the samples ``light`` of a rising step."""
    from scipy.optimize import minimize_scalar

    def misfit(sigma):
        return np.sum((box_filtered_edge(u, width, centre, sigma) - light) ** 2)

    return minimize_scalar(misfit, bounds=(0.0, 20.0), method="bounded", options={"xatol": 1e-5}).x


def test_a_plane_at_the_focus_distance_renders_as_without_defocus(rig):
    geom = trace_view(projector_plane(rig, 1300.0), rig, np.eye(4))
    assert geom.hit.sum() > 10000
    sharp = dataclasses.replace(CLEAN, projector_blur=0.35)
    dof = dataclasses.replace(sharp, projector_fnumber=1.0, projector_focus_mm=1300.0)
    step = column_step(rig)
    checker = np.kron(np.indices((24, 32)).sum(0) % 2, np.ones((16, 16)))[..., None].repeat(3, -1)
    for image in (step, (checker * 255).astype(np.uint8)):  # a profile and a 2-D image
        np.testing.assert_array_equal(shade_image(geom, image, dof), shade_image(geom, image, sharp))
    # and off the focus distance the same lens does blur
    off = trace_view(projector_plane(rig, 1100.0), rig, np.eye(4))
    assert np.abs(projector_light_image(off, step, dof) - projector_light_image(off, step, sharp)).max() > 0.05


@pytest.mark.parametrize("depth, fnumber", [(1000.0, 1.0), (1150.0, 1.0), (1700.0, 1.4)])
def test_a_plane_off_focus_blurs_by_the_thin_lens_amount(rig, depth, fnumber):
    geom = trace_view(projector_plane(rig, depth), rig, np.eye(4))
    optics = dataclasses.replace(CLEAN, projector_fnumber=fnumber, projector_focus_mm=1300.0)
    f = optics.projector_focal_mm
    coc = rig.projector.lens.fx * (f / fnumber) * abs(depth - 1300.0) / (depth * (1300.0 - f))
    expected = coc / COC_PER_SIGMA
    assert expected > 0.9
    hit = geom.hit
    u = geom.proj_uv[hit][:, 0]
    width = geom.proj_footprint[hit][:, 0].astype(np.float64)
    light = projector_light_image(geom, column_step(rig), optics)[:, 0]
    centre = rig.projector.lens.width // 2 - 0.5
    near = np.abs(u - centre) < 6 * expected + 3
    measured = edge_sigma(u[near], width[near], light[near], centre)
    # the same measurement finds no blur on the plane at the focus distance
    sharp = projector_light_image(geom, column_step(rig), CLEAN)[:, 0]
    assert edge_sigma(u[near], width[near], sharp[near], centre) < 0.06
    assert measured == pytest.approx(expected, rel=0.05)


def test_projector_gamma_and_the_srgb_camera_response():
    rig = default_rig(scale=0.2, projector_scale=0.2)
    geom = trace_view(projector_plane(rig, 1300.0), rig, np.eye(4))
    lens = rig.projector.lens
    grey = np.full((lens.height, lens.width, 3), 128, np.uint8)
    light = projector_light_image(geom, grey, dataclasses.replace(CLEAN, projector_gamma=2.2))
    np.testing.assert_allclose(light, (128 / 255) ** 2.2)

    radiance = np.array([0.0, 0.001, 0.05, 0.3, 1.0, 2.0], np.float32)[None, :, None].repeat(3, -1)
    x = np.clip(radiance[0, :, 0] * 0.55, 0, 1).astype(np.float64)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    for depth in (8, 16):
        sensor = Sensor(noise=False, blur_sigma=0, response="srgb", bit_depth=depth)
        got = sensor.expose(radiance)[0, :, 0].astype(np.float64)
        np.testing.assert_allclose(got, np.rint(srgb * sensor.max_value), atol=1)
    linear = Sensor(noise=False, blur_sigma=0).expose(radiance)[0, :, 0]
    assert linear[3] == round(0.3 * 0.55 * 255) and Sensor(noise=False, blur_sigma=0, response="srgb").expose(
        radiance)[0, 3, 0] > linear[3] + 50


def test_vignetting_follows_the_cos4_law_of_the_field_of_view():
    cam = PinholeModel(300, 200, 250.0, 250.0, 140.0, 95.0)
    flat = np.full((200, 300, 3), 1.2, np.float32)
    full = Sensor(noise=False, blur_sigma=0, bit_depth=16, white_level=0.7)
    ratio = full.expose(flat, camera=cam).astype(float) / full.expose(flat).astype(float)
    v = dataclasses.replace(full, vignetting=1.0).expose(flat, camera=cam).astype(float) / full.expose(flat)
    for x, y in ((0, 0), (299, 199), (140, 95), (299, 95)):
        cos = 250.0 / np.sqrt(250.0**2 + (x - 140.0) ** 2 + (y - 95.0) ** 2)
        assert v[y, x, 0] == pytest.approx(cos**4, abs=2e-4)
    np.testing.assert_array_equal(ratio, 1.0)  # strength 0: no falloff
    half = dataclasses.replace(full, vignetting=0.5).expose(flat, camera=cam).astype(float) / full.expose(flat)
    np.testing.assert_allclose(half, 0.5 + 0.5 * v, atol=2e-4)
    with pytest.raises(SlscanError, match="sensor.vignetting"):
        dataclasses.replace(full, vignetting=1.0).expose(flat)


SMALL = {"scene": "tile", "views": 1, "levels": 5, "camera_scale": 0.2, "projector_scale": 0.25, "lit_images": True}


def _session_images(config, tmp_path, name):
    session = capture_session(config, tmp_path / name)
    view = session.views[0]
    return session, {rec.file: session.read_image(view, rec) for rec in view.images}


@pytest.mark.parametrize("effect", ["dof", "tone", "vignetting", "jpeg"])
def test_both_render_paths_honour_each_effect(effect, tmp_path):
    """The driver's rig (``VirtualRig.render``) and ``capture_view`` render the same images,
    and the effect changes them."""
    config = VirtualCaptureConfig(**SMALL, effects=(effect,))
    if effect == "dof":  # the tile sits near the focus distance: a stronger lens focused nearer shows it
        config = dataclasses.replace(config, optics=dataclasses.replace(config.optics, projector_fnumber=1.0,
                                                                        projector_focus_mm=1100.0))
    session, images = _session_images(config, tmp_path, "on")
    rig = config.rig()
    rendered, _ = capture_view(config.build_scene(), rig, session.views[0].rig_from_object,
                               config.pattern_set(rig), config)
    assert [rec.file for rec, _ in rendered] == list(images)
    for rec, image in rendered:
        np.testing.assert_array_equal(images[rec.file], image)
    _, plain = _session_images(VirtualCaptureConfig(**SMALL), tmp_path, "off")
    changed = [np.abs(a.astype(int) - b).max() for a, b in zip(images.values(), plain.values(), strict=True)]
    assert max(changed) >= 8
    assert session.lossy == (effect == "jpeg")
    suffixes = {name.rsplit(".", 1)[1] for name in images}
    assert suffixes == ({"jpg"} if effect == "jpeg" else {"png"})
    if effect == "jpeg":
        assert load_session(session.root).lossy


def test_effects_apply_idempotently_and_keep_set_values():
    base = VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.2, effects=("all",))
    assert (base.optics.projector_fnumber, base.optics.projector_focus_mm) == (2.0, base.rig().working_distance)
    assert (base.optics.projector_gamma, base.sensor.response) == (2.2, "srgb")
    assert (base.sensor.vignetting, base.sensor.jpeg_quality) == (1.0, 90)
    again = VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.2, effects=("all",), optics=base.optics,
                                 sensor=base.sensor)
    assert (again.optics, again.sensor) == (base.optics, base.sensor)
    mine = VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.2, effects=("dof", "jpeg"),
                                optics=Optics(projector_fnumber=4.0, projector_focus_mm=900.0),
                                sensor=Sensor(jpeg_quality=75))
    assert (mine.optics.projector_fnumber, mine.optics.projector_focus_mm, mine.sensor.jpeg_quality) == (4.0, 900.0, 75)


@pytest.mark.parametrize("kind, values, key", [
    (Optics, {"projector_fnumber": -2.0, "projector_focus_mm": 1300.0}, "optics.projector_fnumber"),
    (Optics, {"projector_fnumber": float("nan")}, "optics.projector_fnumber"),
    (Optics, {"projector_fnumber": 2.0, "projector_focus_mm": -5.0}, "optics.projector_focus_mm"),
    (Optics, {"projector_fnumber": 2.0}, "optics.projector_focus_mm"),
    (Optics, {"projector_fnumber": 2.0, "projector_focus_mm": 20.0}, "optics.projector_focus_mm"),
    (Optics, {"projector_focal_mm": 0.0}, "optics.projector_focal_mm"),
    (Optics, {"projector_gamma": 0.0}, "optics.projector_gamma"),
    (Optics, {"projector_blur": -1.0}, "optics.projector_blur"),
    (Sensor, {"response": "log"}, "sensor.response"),
    (Sensor, {"vignetting": 1.5}, "sensor.vignetting"),
    (Sensor, {"vignetting": -0.1}, "sensor.vignetting"),
    (Sensor, {"jpeg_quality": 101}, "sensor.jpeg_quality"),
    (Sensor, {"jpeg_quality": 90.5}, "sensor.jpeg_quality"),
    (Sensor, {"jpeg_quality": 90, "bit_depth": 16}, "sensor.jpeg_quality"),
])
def test_out_of_range_values_name_the_key(kind, values, key):
    with pytest.raises(SlscanError, match=key.replace(".", r"\.")):
        kind(**values)


def test_recipe_tables_set_the_effect_fields_and_bad_ones_name_the_key():
    from slscan.recipe.config import from_mapping

    optics = from_mapping(Optics, {"projector_fnumber": 2.8, "projector_focus_mm": 1200.0,
                                   "projector_gamma": 2.4}, "capture.optics")
    assert (optics.projector_fnumber, optics.projector_focus_mm, optics.projector_gamma) == (2.8, 1200.0, 2.4)
    sensor = from_mapping(Sensor, {"response": "srgb", "vignetting": 0.5, "jpeg_quality": 80}, "capture.sensor")
    assert (sensor.response, sensor.vignetting, sensor.jpeg_quality) == ("srgb", 0.5, 80)
    with pytest.raises(SlscanError, match=r"capture\.optics: optics\.projector_focus_mm.*got -5"):
        from_mapping(Optics, {"projector_fnumber": 2.0, "projector_focus_mm": -5.0}, "capture.optics")
