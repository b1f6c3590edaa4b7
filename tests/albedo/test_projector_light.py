"""Albedo with the projector as the calibrated light, against the virtual rig's true albedo."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from slscan.albedo.command import add_command
from slscan.albedo.lights import LightCalibration, ProjectorLight, read_panel, write_lights
from slscan.albedo.photometric import AlbedoConfig
from slscan.albedo.projector_light import calibrate_projector_light, projector_albedo_view
from slscan.albedo.unshade import albedo_session, choose_light, load_range_map
from slscan.decode.pipeline import decode_session
from slscan.errors import SlscanError
from slscan.virtual.device import VirtualCaptureConfig, capture_session

from .conftest import SMALL


@pytest.fixture(scope="module")
def projector_light(panel_session) -> ProjectorLight:
    return calibrate_projector_light(panel_session, read_panel(panel_session.root))


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    """A tilted tile (albedo 0.8, 0.8, 0.776) without ring lights: (session, range maps)."""
    root = tmp_path_factory.mktemp("tile")
    config = VirtualCaptureConfig(scene="tile", lit_images=False, levels=7, **SMALL)
    session = capture_session(config, root / "capture")
    decode_session(session, root / "range_maps")
    return session, root / "range_maps"


def _errors(session, view, albedo, valid):
    truth = session.load_ground_truth(view).albedo
    ok = valid & np.isfinite(truth[..., 0])
    return np.linalg.norm(albedo[ok] - truth[ok], axis=1) / np.linalg.norm(truth[ok], axis=1), ok


def test_calibration_recovers_the_virtual_projector(projector_light, panel_session):
    # the virtual projector's white reads sum_k M[c, k] = 1.12, 1.14, 1.16 times the albedo
    # at distance d0 = |centre - (0, 0, wd)|; the calibration refers it to wd
    rig = panel_session.calibration
    d0 = np.linalg.norm(rig.projector.center - [0, 0, rig.working_distance])
    expected = np.array([1.12, 1.14, 1.16]) * (d0 / rig.working_distance) ** 2
    np.testing.assert_allclose(projector_light.intensity, expected, rtol=0.01)
    flat = np.array(projector_light.flat_field)
    assert flat.shape == (6, 8)
    assert np.abs(flat - 1).max() < 0.01  # the virtual projector is uniform


def test_tile_albedo_is_absolute(tile, projector_light):
    session, range_maps = tile
    view = session.views[0]
    range_map, _ = load_range_map(range_maps, view)
    result = projector_albedo_view(session, view, range_map, projector_light)
    err, ok = _errors(session, view, result.albedo, result.valid)
    assert ok.sum() > 0.9 * result.surface.hit.sum() - 300  # all but the outline
    assert np.median(err) < 0.02
    np.testing.assert_allclose(np.nanmedian(result.albedo[result.valid], axis=0), [0.8, 0.8, 0.776], rtol=0.02)


def test_uncalibrated_projector_is_relative(tile, projector_light):
    session, range_maps = tile
    view = session.views[0]
    range_map, _ = load_range_map(range_maps, view)
    nominal = ProjectorLight(reference_distance=projector_light.reference_distance)
    assert not nominal.calibrated
    result = projector_albedo_view(session, view, range_map, nominal)
    ratio = np.nanmedian(result.albedo[result.valid], axis=0) / np.array([0.8, 0.8, 0.776])
    np.testing.assert_allclose(ratio, projector_light.intensity, rtol=0.02)


def test_shadows_grazing_and_saturation_are_left_out(figurine, projector_light):
    session, range_maps = figurine
    view = session.views[0]
    range_map, _ = load_range_map(range_maps, view)
    result = projector_albedo_view(session, view, range_map, projector_light, AlbedoConfig(min_cos=0.5))
    assert not (result.valid & result.shadow[0]).any()
    assert not (result.valid & result.highlight[0]).any()
    cos = np.einsum("hwi,hwi->hw", np.nan_to_num(result.normal), np.nan_to_num(
        (session.calibration.projector.center - result.surface.points)
        / np.linalg.norm(session.calibration.projector.center - result.surface.points, axis=-1, keepdims=True)))
    assert (cos[result.valid] >= 0.5 - 1e-9).all()
    err, _ = _errors(session, view, result.albedo, result.valid)
    assert np.median(err) < 0.08  # the range map's normals, quarter size
    # the mirror-direction test removes pixels, and only those near the half vector
    glossy = projector_albedo_view(session, view, range_map, projector_light,
                                   AlbedoConfig(min_cos=0.5, projector_highlight_deg=15))
    assert glossy.valid.sum() < result.valid.sum() or not result.valid.any()
    assert not (glossy.valid & ~result.valid & (cos >= 0.5)).any()


def test_choose_light(tile, figurine, calibrated):
    tile_session, _ = tile
    fig_session, _ = figurine
    auto = AlbedoConfig()
    assert choose_light(fig_session, calibrated, auto)[0] == "ring"
    light, why = choose_light(tile_session, None, auto)
    assert light == "projector" and "no view has lit images" in why
    assert choose_light(fig_session, calibrated, AlbedoConfig(light="projector"))[0] == "projector"
    only_projector = LightCalibration((), projector=ProjectorLight())
    assert choose_light(fig_session, only_projector, auto)[0] == "projector"
    with pytest.raises(SlscanError, match="describes no lights"):
        choose_light(fig_session, only_projector, AlbedoConfig(light="ring"))
    with pytest.raises(SlscanError, match="unknown albedo light"):
        AlbedoConfig(light="sun")


def test_session_without_lights_gets_colour(tmp_path, tile, projector_light):
    """The real-rig default: no ring lights; `slscan albedo` used to stop with an error."""
    session, range_maps = tile
    lights = LightCalibration((), projector=projector_light)
    write_lights(tmp_path / "lights.json", lights)
    parser = argparse.ArgumentParser(prog="slscan")
    add_command(parser.add_subparsers(dest="command"))
    out = tmp_path / "albedo"
    rrd = tmp_path / "albedo.rrd"
    args = parser.parse_args(["albedo", str(session.root), "--range-maps", str(range_maps),
                              "--lights", str(tmp_path / "lights.json"), "--out", str(out), "--quiet",
                              "--save", str(rrd)])
    assert args.func(args) == 0
    from rerun.chunk import RrdReader

    paths = {c.entity_path for c in RrdReader(rrd).stream().to_chunks()}
    assert {"/world/camera/image/albedo/lit", "/world/camera/image/albedo/unshaded",
            "/world/camera/image/albedo/error", "/world/albedo/view_000"} <= paths
    meta = json.loads((out / "albedo.json").read_text())
    assert meta["light"] == "projector" and meta["views"][0]["light"] == "projector"
    assert meta["projector_light"]["intensity"] == pytest.approx(list(projector_light.intensity))
    from slscan.colour import read_albedo_png
    from slscan.texture.pipeline import albedo_light

    assert albedo_light(out) == "projector"
    albedo = read_albedo_png(out / "view_000_albedo.png", out / "view_000_valid.png")
    valid = np.isfinite(albedo[..., 0])
    err, _ = _errors(session, session.views[0], albedo, valid)
    assert np.median(err) < 0.02
    # forcing the ring on a session without lit images fails at the boundary, naming the fix
    with pytest.raises(SlscanError, match="describes no lights"):
        albedo_session(session, range_maps, tmp_path / "ring", lights=lights, config=AlbedoConfig(light="ring"))
    assert not (tmp_path / "ring").exists()


def test_light_calibration_round_trip(tmp_path, projector_light):
    from slscan.albedo.lights import read_lights

    cal = LightCalibration((), reference_distance=1300.0, projector=projector_light)
    write_lights(tmp_path / "l.json", cal)
    back = read_lights(tmp_path / "l.json")
    assert back.projector == projector_light and back.lights == ()
    d = json.loads((tmp_path / "l.json").read_text())
    del d["projector"]
    (tmp_path / "bad.json").write_text(json.dumps(d))
    with pytest.raises(SlscanError, match="bad.json: no lights"):
        read_lights(tmp_path / "bad.json")


def test_flat_field_interpolates_its_grid():
    grid = ((1.0, 2.0), (3.0, 4.0))
    light = ProjectorLight(flat_field=grid)
    # a 100 x 50 projector: cell centres at x = 24.5, 74.5 and y = 12, 37
    uv = np.array([[24.5, 12.0], [74.5, 37.0], [49.5, 24.5], [0.0, 0.0], [99.0, 49.0]])
    np.testing.assert_allclose(light.flat_at(uv, (100, 50)), [1.0, 4.0, 2.5, 1.0, 4.0])
    assert np.all(ProjectorLight().flat_at(uv, (100, 50)) == 1)
    with pytest.raises(SlscanError, match="flat_field"):
        ProjectorLight(flat_field=((1.0, -1.0),))


def test_window_normals_recover_a_noisy_plane():
    from slscan.albedo.projector_light import window_normals

    rng = np.random.default_rng(0)
    ys, xs = np.mgrid[0:60, 0:80].astype(float)
    true = np.array([0.3, -0.2, -1.0])
    true /= np.linalg.norm(true)
    # points of the plane n . p = n . (0, 0, 1000), 2 mm apart, with 1 mm of depth noise
    px, py = (xs - 40) * 2.0, (ys - 30) * 2.0
    pz = 1000 - (true[0] * px + true[1] * py) / true[2] + rng.normal(0, 1.0, xs.shape)
    points = np.stack([px, py, pz], axis=-1)
    hit = np.ones(xs.shape, bool)
    hit[:, :5] = False
    normals = window_normals(points, hit, 9)
    inner = normals[10:-10, 15:-10]
    angles = np.degrees(np.arccos(np.clip(inner @ true, -1, 1)))
    assert np.median(angles) < 2.0  # a single triangle's normal here is off by ~25°
    assert np.isnan(normals[:, :5]).all()
    with pytest.raises(SlscanError, match="odd"):
        AlbedoConfig(projector_normal_window_px=8)


def test_adaptive_normals_widen_on_a_noisy_plane_and_keep_a_crease():
    from slscan.albedo.projector_light import adaptive_normals, window_normals

    rng = np.random.default_rng(1)
    ys, xs = np.mgrid[0:80, 0:120].astype(float)
    px, py = (xs - 60) * 2.0, (ys - 40) * 2.0
    hit = np.ones(xs.shape, bool)
    # a noisy flat plane facing the camera: the widest window is planar within the noise
    flat = np.stack([px, py, 1000 + rng.normal(0, 1.0, xs.shape)], axis=-1)
    wide = adaptive_normals(flat, hit, 21)[25:-25, 25:-25]
    small = window_normals(flat, hit, 5)[25:-25, 25:-25]
    angle = lambda n: np.degrees(np.arccos(np.clip(-n[..., 2], -1, 1)))  # noqa: E731
    assert np.median(angle(wide)) < 0.5 * np.median(angle(small))
    # a clean 90-degree crease (a roof along x = 0): the normals next to it stay its sides'
    roof = np.stack([px, py, 1000 + np.abs(px) + rng.normal(0, 0.05, xs.shape)], axis=-1)
    normals = adaptive_normals(roof, hit, 21)
    side = np.array([1.0, 0.0, -1.0]) / np.sqrt(2)  # the x > 0 side, towards the camera
    near = normals[20:-20, 60 + 4]  # 4 px (8 mm) from the crease
    assert np.degrees(np.arccos(np.clip(near @ side, -1, 1))).max() < 5.0


def test_srgb_camera_is_read_in_linear_light(tmp_path, tile, projector_light):
    """The white and black frames of a camera saving sRGB codes are read as light: the
    same tile's albedo as from the linear camera (undecoded, 0.8 would read about 0.9)."""
    from slscan.virtual.sensor import Sensor

    session, range_maps = tile
    config = VirtualCaptureConfig(scene="tile", lit_images=False, levels=7, sensor=Sensor(response="srgb"), **SMALL)
    srgb = capture_session(config, tmp_path / "srgb")
    assert srgb.response == "srgb"
    view = srgb.views[0]
    range_map, _ = load_range_map(range_maps, session.views[0])
    result = projector_albedo_view(srgb, view, range_map, projector_light, range_map_source="the linear capture's")
    err, _ = _errors(srgb, view, result.albedo, result.valid)
    assert np.median(err) < 0.03


def test_ambient_light_is_subtracted_with_the_black_frame(tmp_path, tile, projector_light):
    """Room light 30 % of the projector's white: the black frame takes it out."""
    from dataclasses import replace

    from slscan.virtual.render import Optics

    session, range_maps = tile
    config = VirtualCaptureConfig(scene="tile", lit_images=False, levels=7,
                                  optics=replace(Optics(), ambient=(0.3, 0.3, 0.3)), **SMALL)
    lit_room = capture_session(config, tmp_path / "ambient")
    view = lit_room.views[0]
    range_map, _ = load_range_map(range_maps, session.views[0])
    result = projector_albedo_view(lit_room, view, range_map, projector_light, range_map_source="the dark room's")
    err, _ = _errors(lit_room, view, result.albedo, result.valid)
    assert np.median(err) < 0.02
