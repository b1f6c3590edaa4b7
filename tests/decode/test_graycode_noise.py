"""Known answer for the Gray-code decoder's noise estimate: plain Gray and XOR codes, a
linear camera and one with an sRGB curve that decoding does not undo."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.decode.graycode import decode_gray_images, gray_bits
from slscan.patterns import graycode
from slscan.virtual.sensor import Sensor

WIDTH, HEIGHT = 256, 8  # projector px; columns only
SCALE = 1.5  # camera px per projector px: the finest (2 px) stripes are 3 camera px wide
BLUR = 1.0  # camera blur, Gaussian sigma px


def _captures(code: str, curve: bool, seed: int):
    """White, black and every column pattern of ``code`` seen by a camera whose rows each
    see the projector at a different albedo (0.35-0.9): light integrated over each pixel,
    then the virtual sensor's model (:class:`Sensor`: blur of ``BLUR`` px, shot noise and
    6 e read noise of a 20 000 e well, the sRGB curve or not; 16 bits, so that the
    noise, not the quantisation, is what the statistics see)."""
    descs = [d for d in graycode.generate(WIDTH, HEIGHT, code=code) if d.axis == "columns"]
    h, w = 120, int(WIDTH * SCALE)
    sub = 8  # samples per camera px
    u = (np.arange(w * sub) + 0.5) / (sub * SCALE)  # projector column under each sample
    albedo = np.linspace(0.35, 0.9, h, dtype=np.float32)[:, None]
    rng = np.random.default_rng(seed)
    sensor = Sensor(bit_depth=16, blur_sigma=BLUR, response="srgb" if curve else "linear")

    def capture(on: np.ndarray) -> np.ndarray:
        light = on[np.minimum(u.astype(int), WIDTH - 1)].astype(np.float32) * 0.98 + 0.02
        radiance = albedo * light.reshape(w, sub).mean(axis=1)[None, :]
        return sensor.expose(np.repeat(radiance[..., None], 3, axis=2), rng)[..., 0]

    images = {d.id: capture(graycode.profile(d)[:, 0] > 0) for d in descs}
    return images, descs, capture(np.ones(WIDTH, bool)), capture(np.zeros(WIDTH, bool))


def _truth(code: str, curve: bool) -> float:
    """Standard deviation (from the MAD) of every bit's ``pattern - inverse`` noise: the
    difference of two captures that differ only in their noise, over sqrt(2)."""
    (im0, descs, *_), (im1, *_) = _captures(code, curve, 0), _captures(code, curve, 1)
    resid = []
    for pid, inv in gray_bits(descs, "columns").pairs:
        d0 = im0[pid].astype(np.float64) - im0[inv]
        d1 = im1[pid].astype(np.float64) - im1[inv]
        resid.append(((d0 - d1) / np.sqrt(2)).ravel())
    r = np.concatenate(resid)
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) / 65535


@pytest.mark.parametrize("code", ["reflected-binary", "xor"])
@pytest.mark.parametrize("curve", [False, True], ids=["linear", "srgb"])
def test_noise_estimate_known_answer(code, curve):
    """The estimate is within 15 % of the true noise for both codes, also when an sRGB
    curve (steep in the darks) turns the light blur leaks into fine stripes' dark halves
    bright (the estimate before, ``pattern + inverse`` against ``white + black`` at every
    pixel, read 2.0x the truth of plain Gray code there)."""
    images, descs, white, black = _captures(code, curve, 0)
    res = decode_gray_images(images, descs, white, black, robust=False)
    truth = _truth(code, curve)
    assert res.noise == pytest.approx(truth, rel=0.15)
