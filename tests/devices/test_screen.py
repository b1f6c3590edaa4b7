"""ScreenProjector on private Xvfb servers: what the X server shows is the image, pixel for pixel."""

from __future__ import annotations

import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from slscan.devices.base import DeviceError
from slscan.devices.screen import ScreenProjector, grab_screen
from slscan.patterns import render, standard_set

from .conftest import MONITORS, OFFSET_MONITOR

LEVELS = 9  # 2**9 - 1 lines, two pixels per line: the most that fits 1024 px


def _random_image(w: int, h: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_every_pattern_is_on_screen_pixel_for_pixel(projector: ScreenProjector) -> None:
    w, h = projector.resolution
    patterns = standard_set("both", width=w, height=h, levels=LEVELS, rows=True)
    families = {d.family for d in patterns}
    assert {"hybrid", "gray", "flat"} <= families
    show_s, grab_s = [], []
    for desc in patterns:
        image = render(desc)
        t = time.perf_counter()
        projector.show(image)
        show_s.append(time.perf_counter() - t)
        t = time.perf_counter()
        shown = grab_screen(projector)
        grab_s.append(time.perf_counter() - t)
        assert shown.shape == (h, w, 3) and shown.dtype == np.uint8
        if not np.array_equal(shown, image):
            bad = np.argwhere((shown != image).any(axis=2))
            y, x = bad[0]
            pytest.fail(
                f"{desc.id}: {len(bad)} pixels differ, first at (x={x}, y={y}): "
                f"screen {shown[y, x]} vs image {image[y, x]}"
            )
    print(
        f"\n{len(patterns)} patterns at {w}x{h}: show median {1e3 * np.median(show_s):.1f} ms "
        f"(max {1e3 * max(show_s):.1f}), grab median {1e3 * np.median(grab_s):.1f} ms "
        f"(max {1e3 * max(grab_s):.1f})"
    )


def test_single_pixel_line_and_orientation(projector: ScreenProjector) -> None:
    """One green pixel row and column stay one pixel wide, pure green, where they were put."""
    w, h = projector.resolution
    image = np.zeros((h, w, 3), np.uint8)
    image[3, :] = (0, 255, 0)  # near the top: a flipped image would put it at h - 4
    image[:, w - 6] = (0, 255, 0)  # near the right
    image[h - 1, 0] = (1, 2, 3)  # bottom-left corner, not symmetric in any channel
    projector.show(image)
    shown = grab_screen(projector)
    assert np.array_equal(shown, image)
    green_rows = np.flatnonzero((shown == (0, 255, 0)).all(axis=2).all(axis=1))
    assert green_rows.tolist() == [3]


def test_random_images_and_blank(projector: ScreenProjector) -> None:
    w, h = projector.resolution
    for seed in range(3):
        image = _random_image(w, h, seed)
        projector.show(image)
        assert np.array_equal(grab_screen(projector), image)
    projector.blank()
    assert not grab_screen(projector).any()


def test_show_returns_the_presentation_time(projector: ScreenProjector) -> None:
    w, h = projector.resolution
    before = time.monotonic()
    shown = projector.show(np.full((h, w, 3), 128, np.uint8))
    assert before <= shown <= time.monotonic()


def test_redraws_after_being_uncovered(projector: ScreenProjector, x_display: str) -> None:
    import pyglet

    w, h = projector.resolution
    image = _random_image(w, h, seed=7)
    projector.show(image)
    display = pyglet.display.Display(name=x_display)
    screen = display.get_screens()[0]  # not get_default_screen: pyglet 2.1 fails on Xinerama heads
    cover = pyglet.window.Window(
        300, 200, screen=screen, style=pyglet.window.Window.WINDOW_STYLE_BORDERLESS
    )
    cover.set_location(50, 60)
    cover.switch_to()
    pyglet.gl.glClearColor(1.0, 0.0, 1.0, 1.0)
    cover.clear()
    cover.flip()
    pyglet.gl.glFinish()
    cover.dispatch_events()
    assert not np.array_equal(grab_screen(projector), image)  # the cover is on top
    cover.close()
    projector.poll()
    assert np.array_equal(grab_screen(projector), image)


def test_opens_on_the_chosen_monitor(x_display: str) -> None:
    w, h = MONITORS[1]
    with ScreenProjector(1, x_display=x_display, expected=(w, h)) as proj:
        assert proj.resolution == (w, h)
        assert proj.describe() == {
            "kind": "screen",
            "monitor": 1,
            "x_display": x_display,
            "resolution": [w, h],
            "monitor_origin": [0, 0],
        }
        image = _random_image(w, h, seed=1)
        proj.show(image)
        assert np.array_equal(grab_screen(proj), image)


def test_window_and_grab_use_the_monitor_origin(x_display_offset: str) -> None:
    """A monitor at (1024, 0): the window is there, and only there."""
    import mss

    x, y, w, h = OFFSET_MONITOR
    with ScreenProjector(0, x_display=x_display_offset) as proj:
        assert proj.resolution == (w, h)
        assert proj.monitor_origin == (x, y)
        image = _random_image(w, h, seed=2)
        proj.show(image)
        assert np.array_equal(grab_screen(proj), image)
        factory = getattr(mss, "MSS", None) or mss.mss
        with factory(display=x_display_offset) as sct:
            left = sct.grab({"left": 0, "top": 0, "width": x, "height": h})
        assert not np.array_equal(
            np.frombuffer(left.raw, np.uint8).reshape(h, x, 4)[:, :w, 2::-1], image
        )


def test_out_of_range_monitor_lists_the_monitors(x_display: str) -> None:
    with pytest.raises(DeviceError) as err:
        ScreenProjector(3, x_display=x_display)
    message = str(err.value)
    assert "monitor 3 does not exist" in message
    assert "this display has 2 monitors: 0 1024x768 at (0,0), 1 800x600 at (0,0)" in message


def test_wrong_expected_resolution(x_display: str) -> None:
    with pytest.raises(DeviceError, match=r"the monitor is 1024x768, expected 1920x1080"):
        ScreenProjector(0, x_display=x_display, expected=(1920, 1080))


@pytest.mark.parametrize(
    ("shape", "dtype"),
    [
        ((768, 1023, 3), np.uint8),
        ((767, 1024, 3), np.uint8),
        ((768, 1024), np.uint8),
        ((768, 1024, 3), np.uint16),
    ],
)
def test_wrong_image_is_refused(projector: ScreenProjector, shape: tuple, dtype: type) -> None:
    with pytest.raises(DeviceError):
        projector.show(np.zeros(shape, dtype))


def test_no_x_server(x_display: str) -> None:
    with pytest.raises(DeviceError) as err:
        ScreenProjector(0, x_display=":987")
    message = str(err.value)
    assert "\n" not in message and ":987" in message


def test_display_not_set(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    with pytest.raises(DeviceError, match=r"no X display .*DISPLAY is not set") as err:
        ScreenProjector(0)
    assert "\n" not in str(err.value)


def test_pyglet_missing(monkeypatch: pytest.MonkeyPatch, x_display: str) -> None:
    monkeypatch.setitem(sys.modules, "pyglet", None)
    with pytest.raises(DeviceError, match=r"pip install 'slscan\[screen\]'"):
        ScreenProjector(0, x_display=x_display)


def test_close_is_idempotent_and_final(x_display: str) -> None:
    proj = ScreenProjector(1, x_display=x_display)
    w, h = proj.resolution
    proj.close()
    proj.close()
    with pytest.raises(DeviceError, match="closed"):
        proj.show(np.zeros((h, w, 3), np.uint8))


def test_settle_time_is_waited(x_display: str) -> None:
    with ScreenProjector(1, x_display=x_display, settle_s=0.05) as proj:
        w, h = proj.resolution
        t = time.monotonic()
        shown = proj.show(np.zeros((h, w, 3), np.uint8))
        assert time.monotonic() - shown >= 0.05 and shown >= t


def test_display_defaults_to_the_environment(
    monkeypatch: pytest.MonkeyPatch, x_display: str
) -> None:
    monkeypatch.setenv("DISPLAY", x_display)
    with ScreenProjector(1) as proj:
        assert proj.describe()["x_display"] == x_display
        assert proj.resolution == MONITORS[1]


def test_grab_from_another_thread(projector: ScreenProjector) -> None:
    """The closed-loop camera may grab from its own thread (one mss instance per thread)."""
    w, h = projector.resolution
    image = _random_image(w, h, seed=11)
    projector.show(image)
    with ThreadPoolExecutor(2) as pool:
        grabs = list(pool.map(lambda _: grab_screen(projector), range(4)))
    assert all(np.array_equal(g, image) for g in grabs)
