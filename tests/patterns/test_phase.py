"""Phase-shifting pattern descriptions: the fringes, the Gray code and its complementary bit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slscan.errors import SlscanError
from slscan.patterns import families_in, family, phase, profile, render, set_families, standard_set
from slscan.patterns.graycode import inverse_gray


def test_fringes_are_the_documented_cosines_at_pixel_centres():
    images = phase.generate(64, 32, periods=(8.0,), steps=4)
    sines = [d for d in images if d.params["kind"] == "sine"]
    assert [d.params["step"] for d in sines] == [0, 1, 2, 3]
    x = np.arange(64)
    for d in sines:
        want = np.rint(255 * (0.5 + 0.5 * np.cos(2 * np.pi * x / 8 + 2 * np.pi * d.params["step"] / 4)))
        np.testing.assert_array_equal(profile(d)[:, 0], want)
        np.testing.assert_array_equal(profile(d)[:, 1], profile(d)[:, 2])
    img = render(sines[1])
    assert img.shape == (32, 64, 3) and np.all(img == img[:1])


def test_gamma_predistorts_the_fringes():
    d = phase.generate(64, 8, periods=(16.0,), steps=3, gamma=2.2)[0]
    v = profile(d)[:, 0] / 255.0
    np.testing.assert_allclose(v ** 2.2, phase.sine_values(d, np.arange(64.0)), atol=0.02)


@pytest.mark.parametrize("width,period", [(1024, 8.0), (1000, 16.0), (200, 12.5)])
def test_gray_code_names_the_period_and_the_complementary_bit_its_half(width, period):
    images = phase.generate(width, 8, periods=(period,), unwrap="complementary")
    grays = [d for d in images if d.params["kind"] == "gray" and not d.params["inverse"]]
    main = [d for d in grays if not d.params.get("complementary")]
    comp = [d for d in grays if d.params.get("complementary")]
    assert len(main) == math.ceil(math.log2(width / period)) and len(comp) == 1
    x = np.arange(width, dtype=float)
    code = np.zeros(width, np.int64)
    for d in main:
        code = (code << 1) | (profile(d)[:, 0] > 127)
    np.testing.assert_array_equal(inverse_gray(code), np.floor(x / period))
    fine = (code << 1) | (profile(comp[0])[:, 0] > 127)
    np.testing.assert_array_equal(inverse_gray(fine), np.floor(2 * x / period))
    # every pattern has its inverse
    inv = {d.id for d in images if d.params.get("inverse")}
    assert inv == {d.id + "-inv" for d in grays}


def test_rows_and_ids():
    images = phase.generate(64, 48, rows=True, periods=(8.0,), steps=3)
    assert {d.axis for d in images} == {"columns", "rows"}
    assert len({d.id for d in images}) == len(images)
    rows = [d for d in images if d.axis == "rows" and d.params["kind"] == "sine"]
    assert all(profile(d).shape == (48, 3) for d in rows)


def test_heterodyne_needs_periods_that_repeat_beyond_the_projector():
    assert phase.joint_period([16, 17, 18]) == pytest.approx(2448)
    images = phase.generate(1024, 8, unwrap="heterodyne")
    assert {d.params["period"] for d in images} == set(phase.DEFAULT_HETERODYNE)
    assert all(d.params["kind"] == "sine" for d in images)
    with pytest.raises(SlscanError, match="repeat together every 72 px"):
        phase.generate(1024, 8, unwrap="heterodyne", periods=(8, 9))
    with pytest.raises(SlscanError, match="needs two or three periods"):
        phase.generate(1024, 8, unwrap="heterodyne", periods=(16,))


@pytest.mark.parametrize("kwargs,message", [
    ({"periods": (2000.0,)}, "does not fit a 1024 px projector"),
    ({"periods": (2.0,)}, "does not fit"),
    ({"steps": 2}, "whole number >= 3"),
    ({"unwrap": "magic"}, "expected one of complementary, gray, heterodyne"),
    ({"periods": (8.0, 16.0)}, "must be the longest"),
    ({"gamma": 0.0}, "gamma must be in"),
])
def test_bad_sets_say_which_option(kwargs, message):
    with pytest.raises(SlscanError, match=message):
        phase.generate(1024, 768, **kwargs)


def test_registry_knows_the_family_and_routes_its_options():
    assert family("phase").decoder == "slscan.decode.phase"
    assert set_families("hybrid+phase") == ("hybrid", "phase")
    images = standard_set("phase", width=256, height=128, rows=True, periods=(16.0,), steps=5)
    assert [d.id for d in images[:2]] == ["white", "black"]
    assert sum(d.params.get("kind") == "sine" for d in images) == 10
    assert [f.name for f in families_in(images)] == ["phase"]
    with pytest.raises(SlscanError, match="do not apply to the 'gray' patterns"):
        standard_set("gray", width=256, height=128, steps=5)
    # the finest fringe is what exposure and focus checks look at
    assert phase.finest(images).params["period"] == 16.0
