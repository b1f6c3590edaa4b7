"""Phase-shifting decoding: known answers on synthetic images, the virtual rig, bad sets."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from slscan.decode.phase import (
    Fringes,
    decode_phase,
    decode_phase_images,
    fit_phase,
    fix_orders,
    phase_sets,
    unwrap_temporal,
)
from slscan.errors import SlscanError
from slscan.patterns import PatternImage, phase

# --- synthetic images with a known answer ------------------------------------------------------

CAM = (160, 48)  # camera (width, height) px
PROJ = (256, 64)  # projector (width, height) px


def _u(x: np.ndarray) -> np.ndarray:
    """Projector column seen at camera column x: a smooth, non-linear map over the projector."""
    return 3.0 + 1.4 * x + 0.002 * (x - 40) ** 2


def _v(y: np.ndarray) -> np.ndarray:
    return 2.5 + 1.2 * y


def _render(descs, *, dtype=np.uint16, channels=1, white=0.7, black=0.05, gray_shift=0.0):
    """Captures of a scene whose camera pixel (x, y) sees projector (u(x), v(y)), each pixel
    integrating its footprint (a box one camera pixel wide); ``gray_shift`` moves the Gray
    code's stripes (px) against the fringes, as a lens might."""
    w, h = CAM
    sub = (np.arange(16) + 0.5) / 16 - 0.5
    ux = _u(np.arange(w)[:, None] + sub[None, :])  # (w, 16) footprint samples
    vy = _v(np.arange(h)[:, None] + sub[None, :])
    full = float(np.iinfo(dtype).max)

    def image(level_2d):
        level = black + (white - black) * level_2d
        img = np.rint(level * full).astype(dtype)
        return np.repeat(img[..., None], 3, axis=2) if channels == 3 else img

    out = {}
    for d in descs:
        at = ux if d.axis == "columns" else vy
        if d.params["kind"] == "sine":
            values = phase.sine_values(d, at) ** (1 / d.params.get("gamma", 1.0))
        else:
            values = phase.gray_values(d, at + gray_shift).astype(float)
        line = values.mean(axis=1)
        out[d.id] = image(np.broadcast_to(line[None, :] if d.axis == "columns" else line[:, None], (h, w)))
    return out, image(np.ones((h, w))), image(np.zeros((h, w)))


@pytest.mark.parametrize("steps,unwrap,periods", [
    (4, "complementary", (16.0,)),
    (3, "gray", (16.0,)),
    (5, "complementary", (24.0, 9.0)),
    (4, "heterodyne", (16.0, 17.0, 18.0)),
])
def test_synthetic_known_answer(steps, unwrap, periods):
    descs = phase.generate(*PROJ, rows=True, periods=periods, steps=steps, unwrap=unwrap)
    images, white, black = _render(descs)
    res = decode_phase_images(images, descs, white, black, consistency_radius=2)
    u = np.broadcast_to(_u(np.arange(CAM[0]))[None, :], res.column.shape)
    v = np.broadcast_to(_v(np.arange(CAM[1]))[:, None], res.column.shape)
    assert res.mask.all()  # the image border is no rim: nothing mixed there
    err_u, err_v = res.column[res.mask] - u[res.mask], res.row[res.mask] - v[res.mask]
    assert np.abs(err_u).max() < 0.02 and np.abs(err_v).max() < 0.02
    assert res.axes["columns"].method == unwrap
    # plain Gray code misreads the order right at a cell edge (u = 111.99 here), which the
    # neighbour check corrects; the complementary bit and several periods never do
    assert (res.axes["columns"].counts["order_corrected"] > 0) == (unwrap == "gray")


def test_rgb_8bit_and_gamma_predistortion():
    descs = phase.generate(*PROJ, periods=(16.0,), steps=4, gamma=2.0)
    images, white, black = _render(descs, dtype=np.uint8, channels=3)
    # the projector emits value ** 2: what the camera sees is the undistorted cosine again
    images = {k: (255 * (v / 255.0) ** (2.0 if k.startswith("phase-col-p") else 1.0)).round().astype(np.uint8)
              for k, v in images.items()}
    res = decode_phase_images(images, descs, white, black)
    u = np.broadcast_to(_u(np.arange(CAM[0]))[None, :], res.column.shape)
    assert np.abs(res.column[res.mask] - u[res.mask]).max() < 0.1
    assert res.row is None and res.mask.mean() > 0.9


@pytest.mark.parametrize("unwrap", ["complementary", "gray"])
def test_gray_edges_off_the_phase_wrap_are_corrected_or_caught(unwrap):
    """Gray stripes 0.6 px off the fringes: the complementary bit unwraps every pixel right;
    plain Gray code misreads the order beside each cell edge, and the neighbour check
    corrects those pixels by a period."""
    descs = phase.generate(*PROJ, periods=(16.0,), steps=4, unwrap=unwrap)
    images, white, black = _render(descs, gray_shift=0.6)
    res = decode_phase_images(images, descs, white, black)
    u = np.broadcast_to(_u(np.arange(CAM[0]))[None, :], res.column.shape)
    assert np.abs(res.column[res.mask] - u[res.mask]).max() < 0.02
    assert res.mask.mean() > 0.99
    corrected = res.axes["columns"].counts["order_corrected"]
    assert corrected == 0 if unwrap == "complementary" else corrected > 0


def test_fit_phase_any_shifts():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 2 * np.pi, (20, 30)).astype(np.float32)
    shifts = [0.1, 1.7, 2.9, 4.4, 5.0]
    imgs = [0.4 + 0.3 * np.cos(truth + s) for s in shifts]
    fit = fit_phase(iter(imgs), shifts)
    np.testing.assert_allclose(np.angle(np.exp(1j * (fit.phase - truth))), 0, atol=1e-4)
    np.testing.assert_allclose(fit.amplitude, 0.3, atol=1e-4)
    np.testing.assert_allclose(fit.offset, 0.4, atol=1e-4)
    assert fit.residual.max() < 1e-6
    with pytest.raises(SlscanError, match="do not determine a phase"):
        fit_phase(iter(imgs[:3]), [0.0, 0.0, np.pi])


def test_temporal_unwrapping_finds_the_order_and_flags_ambiguity():
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1023, 5000)
    fringes = [Fringes(p, 0.0, (), ()) for p in (16.0, 17.0, 18.0)]
    phases = [np.mod(2 * np.pi * (x + rng.normal(0, 0.05, x.shape)) / f.period, 2 * np.pi) for f in fringes]
    sigmas = [np.full_like(x, 0.05)] * 3
    found, margin = unwrap_temporal(phases, fringes, sigmas, 1024)
    assert np.abs(found - x).max() < 0.3 and margin.min() > 50
    # with ten times the noise, some orders are near ties: their margin says so
    noisy = [np.mod(p + np.random.default_rng(2).normal(0, 0.3, x.shape), 2 * np.pi) for p in phases]
    found, margin = unwrap_temporal(noisy, fringes, [np.full_like(x, 0.8)] * 3, 1024)
    wrong = np.abs(found - x) > 4
    assert wrong.any() and np.all(margin[wrong] < 9)


def test_fix_orders_moves_a_band_one_period_back():
    yy, xx = np.mgrid[0:40, 0:60]
    coord = 0.3 * xx + 0.1 * yy
    wrong = coord.copy()
    wrong[:, 20:22] += 16  # a two-pixel band misread by one period
    wrong[5, 40] += 8.0  # a speck half a period off: no order explains it
    fixed, valid, corrected, rejected = fix_orders(wrong, np.ones_like(coord, bool), 16.0)
    assert corrected == 80 and rejected == 1 and not valid[5, 40]
    np.testing.assert_allclose(fixed[valid], coord[valid])


@pytest.mark.parametrize("drop,message", [
    ("phase-col-p0-s3", "have 3 image"),  # 4 steps: a missing one is still a valid 3-step set? no: named
    ("phase-col-gray-02", "bit 2 of 5 is missing"),
    ("phase-col-gray-05", "complementary Gray bit has an inverse but no pattern"),
    ("phase-col-gray-03-inv", "with and without inverse"),
])
def test_bad_sets_name_what_is_missing(drop, message):
    descs = [d for d in phase.generate(256, 64, periods=(8.0,), steps=3) if d.id != drop]
    if drop.endswith("-s3"):
        descs = [d for d in phase.generate(256, 64, periods=(8.0,), steps=3) if d.id != "phase-col-p0-s2"]
        message = "have 2 image"
    with pytest.raises(SlscanError, match=message):
        phase_sets(descs)


def test_one_period_without_gray_code_cannot_unwrap():
    descs = [d for d in phase.generate(256, 64, periods=(8.0,)) if d.params["kind"] == "sine"]
    with pytest.raises(SlscanError, match="no way to unwrap"):
        phase_sets(descs)
    short = [replace(d, params={**d.params}) for d in phase.generate(1024, 64, unwrap="heterodyne")]
    short = [PatternImage(d.id, d.family, 4096, 64, d.axis, d.params) for d in short]
    with pytest.raises(SlscanError, match="less than the projector's 4096 px"):
        phase_sets(short)


# --- the virtual rig -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    config = VirtualCaptureConfig(scene="tile", patterns="phase", gray_rows=True, camera_scale=0.25,
                                  projector_scale=0.25, lit_images=False, pattern_options={"periods": (8.0,)})
    return capture_session(config, tmp_path_factory.mktemp("phase_tile") / "session")


def test_virtual_tile_projector_coordinates_match_truth(tile):
    from scipy import ndimage

    res = decode_phase(tile, tile.views[0])
    truth = tile.load_ground_truth(tile.views[0])
    inner = ndimage.binary_erosion(truth.visibility == 2, iterations=2)
    assert res.mask[inner].mean() > 0.99
    for est, tru in ((res.column, truth.projector_uv[..., 0]), (res.row, truth.projector_uv[..., 1])):
        err = est[res.mask & inner] - tru[res.mask & inner]
        assert np.sqrt(np.mean(err**2)) < 0.05 and np.abs(err).max() < 0.3


def test_virtual_tile_range_map_is_flat_and_true(tile):
    from slscan.decode.pipeline import DecodeConfig, decode_view

    res = decode_view(tile, tile.views[0], DecodeConfig())
    assert res.method == "phase"
    truth = tile.load_ground_truth(tile.views[0])
    pts = res.points
    ok = np.isfinite(pts[:, 0])
    true = truth.point[res.samples.row[ok], res.samples.x[ok].astype(int)].astype(float)
    dist = np.linalg.norm(pts[ok] - true, axis=1)
    assert np.nanmedian(dist) < 0.15 and len(res.range_map.faces) > 1.5 * len(res.range_map.vertices)


# --- the projector's response (gamma) --------------------------------------------------------------


@pytest.mark.parametrize("steps,gamma", [(3, 2.2), (4, 1.645), (3, 0.6)])
def test_phase_correction_inverts_the_response(steps, gamma):
    from slscan.decode.phase_gamma import measured_phase, phase_correction, phase_error
    from slscan.patterns.phase import generate

    shifts = [d.params["shift"] for d in generate(64, 8, steps=steps) if d.params["kind"] == "sine"]
    theta = np.linspace(0, 2 * np.pi, 997, endpoint=False)
    err = phase_error(theta, shifts, gamma)
    assert np.abs(err).max() > (0.05 if steps == 3 else 0.005)  # the harmonics do bias the phase
    fixed = phase_correction(measured_phase(theta, shifts, gamma).astype(np.float32), shifts, gamma)
    assert np.abs(np.angle(np.exp(1j * (fixed - theta)))).max() < 2e-3


def test_gamma_fit_recovers_a_known_exponent():
    from slscan.decode.phase_gamma import emitted, fit_effective_gamma

    rng = np.random.default_rng(3)
    theta = rng.uniform(0, 2 * np.pi, 4000)
    shifts = [0.0, 2 * np.pi / 3, 4 * np.pi / 3]
    a, b = rng.uniform(0.02, 0.1, theta.shape), rng.uniform(0.3, 0.8, theta.shape)
    images = np.stack([a + b * emitted(theta + d, 1.8) for d in shifts]) + rng.normal(0, 0.003, (3, len(theta)))
    g, rms = fit_effective_gamma(images, theta, shifts)
    assert g == pytest.approx(1.8, rel=0.01) and rms < 0.005


def test_virtual_response_capture_measures_the_projector_gamma(tmp_path, capsys):
    """Through the commands a user runs: capture the response set through a projector of
    known gamma, measure it, write it."""
    import json

    from slscan.cli import main

    session = tmp_path / "response"
    assert main(["capture", "--scene", "tile", "--patterns", "phase-response", "--projector-response", "1.8",
                 "--scale", "0.25", "--no-lit", "--out", str(session), "--quiet"]) == 0
    assert main(["response", str(session), "--out", str(tmp_path / "gamma.json")]) == 0
    found = json.loads((tmp_path / "gamma.json").read_text())
    assert found["gamma"] == pytest.approx(1.8, rel=0.03)
    assert [round(s["pre_distortion"], 2) for s in found["sets"]] == [0.75, 1.25]
    assert max(s["gamma"] for s in found["sets"]) - min(s["gamma"] for s in found["sets"]) < 0.05
    assert f"decode with --projector-gamma {found['gamma']:.3f}" in capsys.readouterr().err
    # a second write needs --overwrite; a session with no response set says what to capture
    assert main(["response", str(session), "--out", str(tmp_path / "gamma.json")]) == 2
    assert "already exists" in capsys.readouterr().err
