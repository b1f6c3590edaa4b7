"""Global light transport of the virtual rig: materials, subsurface scattering, inter-reflections."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import integrate

from slscan.errors import SlscanError
from slscan.patterns import graycode, standard_set
from slscan.rig import default_rig
from slscan.virtual import transport
from slscan.virtual.device import (
    VirtualCaptureConfig,
    capture_session,
    capture_view,
    turntable_pose,
)
from slscan.virtual.effects import describe
from slscan.virtual.render import Optics, projector_light_at, shade_light, shade_pattern, trace_view
from slscan.virtual.scenes import (
    BRONZE,
    MARBLE,
    MATTE,
    Material,
    Scene,
    UniformAlbedo,
    _uv_sphere,
    flat_tile,
    scene_by_name,
)

CLEAN = Optics(crosstalk=((1, 0, 0), (0, 1, 0), (0, 0, 1)), ambient=(0, 0, 0), projector_black=0.0)
WHITE = np.array([[255, 255, 255]], np.uint8)


def white_light(uv: np.ndarray, width: np.ndarray | None = None) -> np.ndarray:
    return np.ones((len(uv), 3))


# --- materials ----------------------------------------------------------------------


def test_material_and_optics_settings_are_checked_naming_the_key():
    with pytest.raises(SlscanError, match="mean_free_path"):
        Material("wax", mean_free_path=-1.0)
    with pytest.raises(SlscanError, match="specular_colour"):
        Material("gold", specular_colour=(1.2, 0.8, 0.3))
    with pytest.raises(SlscanError, match="optics.interreflection_samples"):
        Optics(interreflection_samples=0)
    with pytest.raises(SlscanError, match="optics.interreflection_stride"):
        Optics(interreflection_stride=0)
    with pytest.raises(SlscanError, match="optics.subsurface"):
        Optics(subsurface="yes")
    tile = flat_tile()
    with pytest.raises(SlscanError, match="material_ids"):
        dataclasses.replace(tile, materials=(MATTE,), material_ids=np.ones(len(tile.triangles), int))
    names = [n for n, _, _ in describe()]
    assert "subsurface" in names and "interreflection" in names


def test_per_triangle_materials_shade_like_one_material():
    """Two identical materials split over the triangles render as the scene's own one does,
    and a tinted highlight takes its colour."""
    rig = default_rig(scale=0.25, projector_scale=0.25)
    tile = flat_tile()
    pose = turntable_pose(rig, 0.0)
    white = standard_set(width=256, height=192, levels=7)[0]
    one = shade_pattern(trace_view(tile, rig, pose), white, CLEAN)
    same = Material("glaze", specular=tile.specular, shininess=tile.shininess)
    split = dataclasses.replace(tile, materials=(same, same), material_ids=np.arange(len(tile.triangles)) % 2)
    np.testing.assert_allclose(shade_pattern(trace_view(split, rig, pose), white, CLEAN), one, rtol=1e-6, atol=1e-7)

    shiny = Material("shiny", specular=0.8, shininess=5.0)
    tinted = Material("copper", specular=0.8, shininess=5.0, specular_colour=(1.0, 0.5, 0.25))
    geo_white = trace_view(dataclasses.replace(tile, materials=(shiny,)), rig, pose)
    geo_tint = trace_view(dataclasses.replace(tile, materials=(tinted,)), rig, pose)
    assert geo_tint.material is not None and (geo_tint.material[geo_tint.hit] == 0).all()
    a, b = shade_pattern(geo_white, white, CLEAN), shade_pattern(geo_tint, white, CLEAN)
    spec = np.asarray(geo_white.proj_specular)[geo_white.hit]
    np.testing.assert_allclose((a - b)[geo_white.hit], spec[:, None] * [0.0, 0.5, 0.75], rtol=1e-4, atol=1e-6)


def test_builtin_transport_scenes_exist_with_their_materials():
    marble, bronze, concave = (scene_by_name(n, detail=0.3) for n in ("marble", "bronze", "concave"))
    assert MARBLE in marble.materials and 1.0 <= MARBLE.mean_free_path <= 2.0
    assert BRONZE in bronze.materials and not BRONZE.white_specular
    assert set(np.unique(marble.material_ids)) == {0, 1}  # marble and a matte plinth
    for scene in (marble, bronze, concave):
        extent = scene.vertices.max(0) - scene.vertices.min(0)
        assert 300 < extent.max() < 500, scene.name  # like the figurine: fits the frame at 1300 mm


# --- subsurface ---------------------------------------------------------------------


def plane_points(h: int, w: int, spacing: float, *, tilt: float = 0.0) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    x, y = (xs - w / 2) * spacing, (ys - h / 2) * spacing
    return np.stack([x * np.cos(tilt), y, 1300 + x * np.sin(tilt)], -1)


def test_subsurface_conserves_energy_on_a_plane():
    point = plane_points(120, 160, 0.3, tilt=np.radians(40))
    material = np.zeros((120, 160), np.int16)
    kernel = transport.subsurface_kernel(point, material, np.array([1.5]))
    rng = np.random.default_rng(1)
    irradiance = np.zeros((120, 160, 3))
    irradiance[40:80, 50:110] = rng.random((40, 60, 3))  # light away from the borders
    spread = transport.spread_subsurface(irradiance, kernel)
    assert np.abs(spread - irradiance).max() > 0.05  # it did move light
    np.testing.assert_allclose(spread.sum((0, 1)), irradiance.sum((0, 1)), rtol=5e-3)
    # a uniformly lit plane stays uniform away from its borders
    flat = transport.spread_subsurface(np.ones((120, 160, 1)), kernel)
    np.testing.assert_allclose(flat[40:80, 50:110], 1.0, rtol=2e-3)


def test_thin_line_broadens_by_the_exponential_profile():
    """A one-pixel line on a marble plane spreads as the line integral of exp(-r / l)."""
    spacing, mfp = 0.25, 1.5
    point = plane_points(160, 200, spacing)
    kernel = transport.subsurface_kernel(point, np.zeros((160, 200), np.int16), np.array([mfp]))
    irradiance = np.zeros((160, 200, 1))
    irradiance[:, 100] = 1.0
    profile = transport.spread_subsurface(irradiance, kernel)[60:100, :, 0].mean(0)
    x = (np.arange(200) - 100) * spacing
    reach = transport.SUBSURFACE_EXTENT * mfp

    def line_integral(x0):
        if abs(x0) > reach:
            return 0.0
        t = np.sqrt(reach**2 - x0**2)
        return integrate.quad(lambda s: np.exp(-np.hypot(x0, s) / mfp), -t, t)[0]

    expected = np.array([line_integral(v) for v in x])
    expected *= profile.sum() / expected.sum()
    assert profile.sum() == pytest.approx(1.0, rel=5e-3)  # the line's energy, per row
    assert np.abs(profile - expected).max() < 0.03 * expected.max()
    width = np.sqrt((profile * x**2).sum() / profile.sum())
    assert width == pytest.approx(np.sqrt((expected * x**2).sum() / expected.sum()), rel=0.03)
    assert 1.2 * mfp < width < np.sqrt(3) * mfp  # the untruncated exponential's sigma is sqrt(3) l


def test_subsurface_stops_at_material_borders_and_depth_steps():
    point = plane_points(80, 120, 0.3)
    point[:, 60:, 2] += 20.0  # a 20 mm step in depth
    material = np.zeros((80, 120), np.int16)
    material[40:] = 1  # the lower half is matte
    kernel = transport.subsurface_kernel(point, material, np.array([1.5, 0.0]))
    irradiance = np.zeros((80, 120, 1))
    irradiance[10:39, 30:59] = 1.0  # upper left, next to both borders
    spread = transport.spread_subsurface(irradiance, kernel)
    assert spread[40:].max() == 0 and spread[:, 60:].max() == 0
    assert spread[:40, :60].sum() == pytest.approx(irradiance.sum(), rel=1e-6)
    lower = np.zeros_like(irradiance)
    lower[50:70, 20:40] = 1.0
    np.testing.assert_array_equal(transport.spread_subsurface(lower, kernel), lower)  # matte: untouched


# --- inter-reflections --------------------------------------------------------------


def v_groove(side: float = 250.0, height: float = 300.0) -> Scene:
    """Two perpendicular panels meeting at a vertical crease 80 mm behind the turntable
    centre, opened towards the camera."""
    crease = np.array([0.0, 0.0, 80.0])
    u_a, u_b = np.array([-1.0, 0, -1]) / np.sqrt(2), np.array([1.0, 0, -1]) / np.sqrt(2)
    up, down = np.array([0, -height / 2, 0]), np.array([0, height / 2, 0])
    verts = np.array([crease + up, crease + down, crease + up + side * u_a, crease + down + side * u_a,
                      crease + up + side * u_b, crease + down + side * u_b])
    tris = np.array([[0, 1, 3], [0, 3, 2], [0, 4, 5], [0, 5, 1]], np.int32)
    return Scene("groove", verts, tris, None, UniformAlbedo((0.7, 0.7, 0.7)))


def expected_indirect(x: np.ndarray, n_x: np.ndarray, corner: np.ndarray, du: np.ndarray, dv: np.ndarray,
                      n_y: np.ndarray, albedo: float, projector: np.ndarray, d0: float, cells: int = 300):
    """Light (k,) the points ``x`` (k, 3) with normals ``n_x`` receive from the Lambertian
    panel ``corner + s du + t dv`` (s, t in [0, 1]) lit by a white point projector: the
    form-factor integral, by the midpoint rule."""
    s = (np.arange(cells) + 0.5) / cells
    y = corner + s[:, None, None] * du + s[None, :, None] * dv
    y = y.reshape(-1, 3)
    area = np.linalg.norm(np.cross(du, dv)) / cells**2
    to_p = projector - y
    dist_p = np.linalg.norm(to_p, axis=1)
    e_y = np.clip(to_p @ n_y / dist_p, 0, None) * (d0 / dist_p) ** 2
    out = []
    for xi, ni in zip(x, n_x):
        r = y - xi
        r2 = (r**2).sum(1)
        cos_x = np.clip(r @ ni, 0, None) / np.sqrt(r2)
        cos_y = np.clip(-(r @ n_y), 0, None) / np.sqrt(r2)
        out.append((albedo * e_y * cos_x * cos_y / (np.pi * r2)).sum() * area)
    return np.array(out)


@pytest.fixture(scope="module")
def groove_view():
    rig = default_rig(scale=0.25, projector_scale=0.25)
    optics = dataclasses.replace(CLEAN, interreflection=True, interreflection_samples=256, interreflection_stride=4)
    pose = turntable_pose(rig, 0.0)
    return rig, optics, trace_view(v_groove(), rig, pose, optics)


def test_corner_receives_the_form_factor_light(groove_view):
    """Each panel of a V-groove under uniform white receives the other's light: albedo x
    irradiance x form factor, integrated independently (no ray casting)."""
    rig, _optics, geom = groove_view
    paths = geom.transport.indirect
    got = transport.gather_indirect(paths, white_light)
    gw = paths.grid[1]
    ys = paths.receiver_cell // gw * paths.stride + paths.stride // 2
    xs = paths.receiver_cell % gw * paths.stride + paths.stride // 2
    pts = geom.point[ys, xs]
    crease = np.array([0.0, 0.0, 1380.0])
    u_a, u_b = np.array([-1.0, 0, -1]) / np.sqrt(2), np.array([1.0, 0, -1]) / np.sqrt(2)
    on_a = (pts - crease) @ u_a > 15  # away from the crease, where the integrand peaks
    on_a &= np.abs(pts[:, 1]) < 120
    idx = np.flatnonzero(on_a)[::7]
    assert len(idx) >= 20
    d0 = float(np.linalg.norm(rig.projector.center - [0, 0, rig.working_distance]))
    expected = expected_indirect(pts[idx], np.broadcast_to(u_b, (len(idx), 3)), crease + [0, -150, 0],
                                 250 * u_b, np.array([0, 300.0, 0]), u_a, 0.7, rig.projector.center, d0)
    ratio = got[idx, 0] / expected
    assert expected.mean() > 0.05  # a strong effect: > 5 % of the direct light of a facing white
    # 256 stratified samples: ~3 % noise per receiver, ~0.7 % on the mean of >= 20
    assert ratio.mean() == pytest.approx(1.0, abs=0.03)
    assert np.sqrt(np.mean((ratio - 1) ** 2)) < 0.1


def test_convex_object_receives_no_inter_reflection():
    rig = default_rig(scale=0.25, projector_scale=0.25)
    v, t = _uv_sphere(40, 80)
    sphere = Scene("sphere", v * 120.0, t, v.copy(), UniformAlbedo((0.9, 0.9, 0.9)))
    optics = dataclasses.replace(CLEAN, interreflection=True)
    geom = trace_view(sphere, rig, turntable_pose(rig, 0.0), optics)
    assert len(geom.transport.indirect.receiver_cell) > 100
    assert np.abs(transport.gather_indirect(geom.transport.indirect, white_light)).max() < 1e-4
    white = standard_set(width=256, height=192, levels=7)[0]
    direct = shade_pattern(trace_view(sphere, rig, turntable_pose(rig, 0.0)), white, CLEAN)
    np.testing.assert_allclose(shade_pattern(geom, white, optics), direct, atol=1e-4)


def test_indirect_light_follows_the_pattern_shown(groove_view):
    """Coarse patterns give structured indirect light, fine ones about half of white's."""
    rig, optics, geom = groove_view
    paths = geom.transport.indirect
    white = transport.gather_indirect(paths, white_light)[:, 0]
    bits = graycode.generate(rig.projector.lens.width, rig.projector.lens.height)
    finest, coarsest = bits[-1], bits[0]
    fine = transport.gather_indirect(paths, lambda uv, w: projector_light_at(uv, finest, optics, w))[:, 0]
    coarse = transport.gather_indirect(paths, lambda uv, w: projector_light_at(uv, coarsest, optics, w))[:, 0]
    strong = white > 0.5 * white.max()
    assert fine[strong].sum() / white[strong].sum() == pytest.approx(0.5, abs=0.06)
    # each path reads the pattern over its patch (several projector px here), which takes
    # out the binomial noise of which points a few rays happen to hit: against a 4096-ray
    # reference, 256 rays err about half as much on the fine bits (measured 0.019 against
    # 0.035 of white's indirect light for the finest bit, 0.020 against 0.043 for the next)
    assert np.median(paths.footprint) > 2.0
    ref_optics = dataclasses.replace(optics, interreflection_samples=4096)
    ref = trace_view(v_groove(), rig, turntable_pose(rig, 0.0), ref_optics).transport.indirect
    for image in bits[-4:]:
        truth = transport.gather_indirect(ref, lambda uv, w, image=image: projector_light_at(uv, image, optics, 1.0))[:, 0]
        cone = transport.gather_indirect(paths, lambda uv, w, image=image: projector_light_at(uv, image, optics, w))[:, 0]
        point = transport.gather_indirect(paths, lambda uv, w, image=image: projector_light_at(uv, image, optics, 1.0))[:, 0]
        err_cone = np.sqrt(np.mean(((cone - truth) / white)[strong] ** 2))
        err_point = np.sqrt(np.mean(((point - truth) / white)[strong] ** 2))
        assert err_cone < 0.7 * err_point, image.id
    share = coarse[strong] / white[strong]
    # the coarsest bit lights one panel: the other panel's receivers get all, its own none
    assert share.max() > 0.9 and share.min() < 0.1
    # the sampler agrees with the camera-pixel renderer where both see the same projector pixel
    hit = geom.hit
    at_pixels = projector_light_at(geom.proj_uv[hit], finest, optics, width=1.0)
    assert at_pixels.shape == (int(hit.sum()), 3) and 0 <= at_pixels.min() and at_pixels.max() <= 1


# --- both render paths --------------------------------------------------------------


def test_effects_act_in_both_render_paths(tmp_path):
    config = VirtualCaptureConfig(scene="marble", camera_scale=0.25, projector_scale=0.25, levels=7,
                                  effects=("subsurface", "interreflection"))
    assert config.optics.subsurface and config.optics.interreflection
    session = capture_session(config, tmp_path / "s")
    from slscan.fsio import read_png

    rig, scene = config.rig(), config.build_scene()
    pose = turntable_pose(rig, 0.0, scene.placement)
    images, geom = capture_view(scene, rig, pose, config.pattern_set(rig), config)
    view = session.views[0]
    for record, image in images:
        np.testing.assert_array_equal(read_png(session.root / view.name / record.file), image)
    plain = dataclasses.replace(config, effects=(), optics=Optics())
    off, _ = capture_view(scene, rig, pose, config.pattern_set(rig), plain)
    assert any(not np.array_equal(a[1], b[1]) for a, b in zip(images, off))
    # ring-light images are spread under the marble too, and keep their energy
    base = trace_view(scene, rig, pose)
    with_sss = shade_light(geom, 0, rig, config.optics)
    without = shade_light(base, 0, rig, Optics())
    assert not np.array_equal(with_sss, without)
    assert with_sss.sum() == pytest.approx(without.sum(), rel=0.02)


def test_shading_a_view_traced_without_transport_is_refused():
    rig = default_rig(scale=0.25, projector_scale=0.25)
    geom = trace_view(flat_tile(), rig, turntable_pose(rig, 0.0))
    white = standard_set(width=256, height=192, levels=7)[0]
    with pytest.raises(SlscanError, match="trace_view"):
        shade_pattern(geom, white, Optics(subsurface=True))


def test_recipe_keys_switch_the_effects_and_are_checked():
    from slscan.recipe.runner import parse_recipe

    recipe = parse_recipe({"capture": {"scene": "marble", "effects": ["subsurface"],
                                       "optics": {"interreflection": True, "interreflection_samples": 32}}},
                          where="r.toml")
    optics = recipe.steps[0][1].optics
    assert (optics.subsurface, optics.interreflection, optics.interreflection_samples) == (True, True, 32)
    with pytest.raises(SlscanError, match="optics.interreflection_samples"):
        parse_recipe({"capture": {"optics": {"interreflection_samples": 0}}}, where="r.toml")
