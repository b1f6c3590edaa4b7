"""Per-pixel colour mixing, blurred lines and global light for the hybrid decoder."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from slscan.decode.hybrid import (
    _mixing_fractions,
    _PixelUnmixer,
    decode_hybrid,
    estimate_mixing,
    nan_median,
    paint_edge_mode,
    paint_read_peaks,
    pattern_shares,
    separate_global,
    subpixel_peaks,
)
from slscan.patterns import hybrid
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.render import Optics
from slscan.virtual.sensor import Sensor

M = np.array([[1.0, 0.10, 0.02], [0.06, 1.0, 0.08], [0.02, 0.14, 1.0]])
PAINTS = np.array([[0.6, 0.6, 0.6], [0.75, 0.04, 0.03], [0.05, 0.08, 0.7]])


def test_nan_median():
    stack = np.array([[1.0, np.nan, 3.0], [5.0, np.nan, np.nan], [2.0, np.nan, 4.0]])
    out = nan_median(stack)
    assert out[0] == 2.0 and np.isnan(out[1]) and out[2] == 3.5


@pytest.mark.parametrize("n", [1, 2, 5, 6, 8, 11])  # up to 8: min/max exchanges; beyond: np.sort
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_nan_median_matches_numpy(n, dtype):
    rng = np.random.default_rng(n)
    stack = rng.normal(size=(n, 40, 30)).astype(dtype)
    stack[rng.random(stack.shape) < 0.4] = np.nan
    stack[:, 0, :] = np.nan  # a row with nothing
    with np.errstate(all="ignore"), pytest.warns(RuntimeWarning):
        expected = np.nanmedian(stack, axis=0)
    out = nan_median(stack)
    assert out.dtype == dtype and np.isnan(out[0]).all()
    np.testing.assert_allclose(out, expected, rtol=1e-6 if dtype == np.float32 else 1e-12)


def _mixing_scene():
    """Three paints side by side, coarse images of red | green line | blue regions as the
    hybrid pattern has them; the physical model: I − B = paint ∘ (M p)."""
    h, w = 24, 192
    paint = np.repeat(PAINTS, w // 3, axis=0)[None].repeat(h, axis=0)  # (h, w, 3)
    black = np.full((h, w, 3), 0.02)
    x = np.arange(w)
    coarse, redness = [], []
    for period in (192, 96, 48, 24):
        pos = (x % period) / period
        p = np.zeros((w, 3))
        p[pos < 0.5, 0] = 1.0
        p[pos >= 0.5, 2] = 1.0
        p[x % period == period // 2, :] = [0.0, 1.0, 0.0]
        coarse.append(black + paint * (p @ M.T)[None])
        redness.append(np.broadcast_to(0.5 + 0.5 * (p[:, 0] - p[:, 2]), (h, w)))
    white = black + paint * M.sum(axis=1)
    return paint, white, black, coarse, redness


def test_pixel_unmixer_from_the_shares_is_the_one_from_the_mixing():
    # the decoder's path (band shares straight to the unmixer, on the lit pixels) against
    # estimate_mixing's (h, w, 3, 3) answer: the same numbers on every lit pixel
    _, white, black, coarse, redness = _mixing_scene()
    mask = np.ones(white.shape[:2], bool)
    mask[:3] = False
    mask[:, 150:160] = False
    mixing = estimate_mixing(white, black, coarse, redness, mask=mask)
    lit, bands = _mixing_fractions(white, black, coarse, redness, mask=mask, wanted=mask)
    a = _PixelUnmixer.build(black, mixing, mask)
    b = _PixelUnmixer.from_fractions(black, lit, bands, mask)
    assert a.inside.any() and not a.inside[~mask].any()
    np.testing.assert_array_equal(a.inside, b.inside)
    for field in ("inverse", "offset", "weights"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    image = coarse[2]
    for got, want in zip(b.signals(image), a.signals(image)):
        np.testing.assert_array_equal(got, want)


def test_mixing_recovers_paint_times_crosstalk():
    paint, white, black, coarse, redness = _mixing_scene()
    h, w = white.shape[:2]
    mixing = estimate_mixing(white, black, coarse, redness, mask=np.ones((h, w), bool))
    expected = paint[..., :, None] * M[None, None]  # (h, w, channel, primary)
    # away from the paint boundaries (the shares are averaged over a few px)
    inner = np.zeros(w, bool)
    for k in range(3):
        inner[k * 64 + 8 : (k + 1) * 64 - 8] = True
    np.testing.assert_allclose(mixing[:, inner], expected[:, inner], rtol=0.01, atol=1e-4)


def _blurred_line(centre: float, sigma: float, width: float = 1.4, n: int = 60) -> np.ndarray:
    """A projector line ``width`` px wide blurred by a Gaussian, integrated over pixels."""
    xs = np.arange(n, dtype=np.float64)[:, None] + np.linspace(-0.5, 0.5, 41)[None]
    s = np.sqrt(2.0) * sigma
    return (0.5 * (erf((xs - centre + width / 2) / s) - erf((xs - centre - width / 2) / s))).mean(axis=1)


@pytest.mark.parametrize("sigma", [0.4, 0.6, 0.8, 1.0])
def test_default_estimator_is_unbiased_on_a_blurred_line(sigma):
    centres = 30.0 + np.arange(21) / 20
    errors = []
    for c in centres:
        f = _blurred_line(c, sigma)
        x, ok = subpixel_peaks(f, [0], [int(np.argmax(f))])
        assert ok.all()
        errors.append(x[0] - c)
    errors = np.array(errors)
    assert abs(errors.mean()) < 1e-3
    assert np.abs(errors).max() < 0.02


def test_global_estimate_recovers_a_known_global_term():
    descs = hybrid.generate(256, 8, levels=7)
    rng = np.random.default_rng(1)
    w = 256
    direct = 0.7 + 0.2 * rng.random((1, w, 3))
    glob = np.stack([np.full(w, 0.3), np.full(w, 0.25), np.full(w, 0.2)], axis=-1)[None]
    seen, shares = [], []
    for d in descs[-3:]:
        labels = hybrid.band_labels(d)
        p = np.stack([labels == 0, labels == 2, labels == 1], axis=-1).astype(float)[None]
        share = pattern_shares(d)
        seen.append(direct * p + glob * share)
        shares.append(share)
    # one pixel in 16 is lit by a primary in all three images: its estimate is the direct
    # light, unless the smallest share is also taken over neighbouring pixels
    alone = separate_global(seen, shares)
    assert (alone > 0.5).mean() == pytest.approx(1 / 16, abs=0.01)
    estimate = separate_global(seen, shares, window=3)
    # (the projector's first columns are red in every image: no neighbour helps there)
    np.testing.assert_allclose(estimate[:, 2:], np.broadcast_to(glob, estimate.shape)[:, 2:], rtol=0.05)


@pytest.fixture(scope="module")
def physical_figurine(tmp_path_factory):
    config = VirtualCaptureConfig(
        scene="object", camera_scale=0.35, projector_scale=0.35, levels=7, lit_images=False,
        sensor=Sensor(noise=False), optics=Optics(colour_model="physical"),
    )
    return capture_session(config, tmp_path_factory.mktemp("physical") / "session")


def _paint_errors(session, result) -> dict[str, float]:
    truth = session.load_ground_truth(session.views[0])
    s = result.samples
    true_x = truth.column_crossings(s.row, s.x, s.projector_column)
    ok = np.isfinite(true_x)
    albedo = truth.albedo[s.row[ok], np.clip(np.round(s.x[ok]).astype(int), 0, truth.albedo.shape[1] - 1)]
    err = np.abs(s.x[ok] - true_x[ok])
    red = (albedo[:, 0] > 4 * albedo[:, 1:].max(axis=1))
    blue = (albedo[:, 2] > 4 * albedo[:, :2].max(axis=1))
    return {"red": float(np.sqrt(np.mean(err[red] ** 2))), "blue": float(np.sqrt(np.mean(err[blue] ** 2)))}


def test_pixel_mixing_beats_one_matrix_on_paint_under_physical_colour(physical_figurine):
    view = physical_figurine.views[0]
    old = _paint_errors(physical_figurine, decode_hybrid(physical_figurine, view, mixing="global"))
    new = _paint_errors(physical_figurine, decode_hybrid(physical_figurine, view, mixing="pixel"))
    assert new["red"] < 0.9 * old["red"]
    assert new["blue"] < 0.9 * old["blue"]


def test_rejections_are_counted(physical_figurine):
    result = decode_hybrid(physical_figurine, physical_figurine.views[0], paint_edges=True,
                           global_light=True)
    assert {"edge", "paint edge", "global", "order", "ambiguous bit"} <= set(result.rejected)
    assert result.rejected["paint edge"] > 0


def _blurred_row(values: np.ndarray, sigma: float, oversample: int) -> np.ndarray:
    """A fine 1-D profile blurred by a Gaussian of ``sigma`` camera px and box-filtered
    into camera pixels of ``oversample`` fine samples each."""
    reach = int(np.ceil(6 * sigma * oversample))  # an odd kernel: "same" keeps it centred
    t = np.arange(-reach, reach + 1) / oversample
    kernel = np.exp(-0.5 * (t / sigma) ** 2)
    fine = np.convolve(values, kernel / kernel.sum(), mode="same")
    return fine.reshape(-1, oversample).mean(axis=1)


@pytest.mark.parametrize(("step_px", "moved_px"), [(1.0, 0.1), (1.5, 0.03)])
def test_paint_read_peaks_reads_a_line_in_its_centres_paint(step_px, moved_px):
    # a line narrower than the camera blur (Gaussian sigma 0.3 px) beside a paint step
    # 1 -> 0.2 (the same in every channel), camera blur sigma 0.6 px: divided pixel by
    # pixel by the white, its centre moves towards the dark side; read in the centre's
    # paint it stays (the known answer: where the line was projected)
    over, n, centre = 16, 32, 15.3
    s = (np.arange(n * over) + 0.5) / over - 0.5
    line = np.exp(-0.5 * ((s - centre) / 0.3) ** 2)
    paint = np.where(s < centre + step_px, 1.0, 0.2)
    image = _blurred_row(paint * line, 0.6, over)
    white = _blurred_row(paint, 0.6, over)
    ratio = (image / white).astype(np.float32)[None]
    rows, cols = np.array([0]), np.array([int(np.argmax(ratio[0]))])
    plain, _ = subpixel_peaks(ratio, rows, cols)
    lit = np.repeat(white[None, :, None], 3, axis=2).astype(np.float32)
    readout = np.array([[0.2], [0.7], [-0.1]])  # any channel weights: the paint is grey
    read, ok = paint_read_peaks(ratio, lit, readout, rows, cols, smooth_rows=False)
    assert ok[0]
    assert plain[0] - centre > moved_px
    assert abs(read[0] - centre) < 0.01


def test_paint_edges_shift_drops_the_samples_the_paint_moves(physical_figurine):
    view = physical_figurine.views[0]
    truth = physical_figurine.load_ground_truth(view)
    found = {}
    for mode in ("keep", "shift", "drop"):
        result = decode_hybrid(physical_figurine, view, paint_edges=mode)
        s = result.samples
        error = s.x - truth.column_crossings(s.row, s.x, s.projector_column)
        found[mode] = ({(r, k): e for r, k, e in zip(s.row, s.stripe, error)}, result.rejected["paint edge"])
    keep, shift, drop = (found[m][0] for m in ("keep", "shift", "drop"))
    assert found["keep"][1] == 0 < found["shift"][1] < found["drop"][1] / 2
    assert len(drop) < len(shift) < len(keep)

    def rms(errors):
        errors = np.array([e for e in errors if np.isfinite(e)])
        return float(np.sqrt(np.mean(errors**2)))

    # what "shift" drops is far worse than what it keeps (noise-free: 0.36 vs 0.126 px)
    dropped = [e for key, e in keep.items() if key not in shift]
    assert len(dropped) > 50
    assert rms(dropped) > 2.0 * rms(shift.values())
    assert rms(shift.values()) < rms(keep.values())


def test_paint_edges_settings():
    from slscan.decode.pipeline import DecodeConfig
    from slscan.errors import SlscanError

    assert [paint_edge_mode(v) for v in (True, False, "shift", "drop", "keep")] == [
        "drop", "keep", "shift", "drop", "keep"]
    assert DecodeConfig().paint_edges == "shift"
    with pytest.raises(SlscanError, match="paint_edges 'sometimes': expected one of shift, drop, keep"):
        DecodeConfig(paint_edges="sometimes")
    with pytest.raises(SlscanError, match="paint_edge_shift must be >= 0"):
        DecodeConfig(paint_edge_shift=-0.1)


def test_unknown_mixing_is_an_error(physical_figurine):
    from slscan.errors import SlscanError

    with pytest.raises(SlscanError, match="mixing"):
        decode_hybrid(physical_figurine, physical_figurine.views[0], mixing="magic")
