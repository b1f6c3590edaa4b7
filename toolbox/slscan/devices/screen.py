"""The real projector: a borderless full-screen OpenGL window on one monitor, drawn pixel for pixel.

A projector connected as a second monitor is driven by :class:`ScreenProjector`, which opens
a full-screen window of exactly the monitor's resolution and shows each pattern unscaled:
the image is uploaded to a texture of the window's size and copied to the back buffer with
``glBlitFramebuffer`` at 1:1 and ``GL_NEAREST`` (no sampling, no shader, no colour
management, sRGB conversion switched off), so a one-pixel green line stays one pixel of
(0, 255, 0). :func:`grab_screen` reads back what the X server really shows in the
projector's rectangle, independently of OpenGL, to check that.

Why pyglet: PsychoPy, the standard tool for frame-exact visual stimulus display, draws
with pyglet; pyglet is a pure-Python wheel (ctypes over the system's OpenGL, no
compiler), it enumerates monitors (XRandR, else Xinerama, on Linux) and opens a
full-screen window on a chosen one. "On screen" means: buffers swapped with vsync on,
``glFinish`` returned (the swap has executed), and on X11 an ``XSync`` round trip (the X
server has processed the frame), before the window's events are handled.

What was tested: Linux, Xvfb 21.1 (a virtual X server: two Xinerama monitors, and one RandR
monitor at an offset) with Mesa's llvmpipe software OpenGL, pyglet 2.1, mss 10; every hybrid and Gray-code pattern was grabbed back from the X
server identical to the image shown (``tests/devices/test_screen.py``). What was never
run: a real projector, a real GPU driver, a compositing window manager, Wayland,
Windows or macOS. On real hardware vsync timing, the driver's frame queue and the
projector's own processing (scaling, "dynamic contrast", keystone) add latency and may
alter pixels: set the projector to its native resolution with image enhancements off,
and measure the delay with ``slscan scan --settle auto``
(:func:`slscan.capture.driver.measure_latency`).
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
import threading
import time
from typing import Any

import numpy as np

from slscan.devices.base import DeviceError, Projector

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'slscan[screen]'"
CAPTION = "slscan projector"

_displays: dict[str, Any] = {}  # X display name -> pyglet Display, opened once per process


def _import_pyglet() -> Any:
    """pyglet, configured for a projector window; imported on first use only."""
    try:
        import pyglet
    except ImportError as exc:
        raise DeviceError(
            f"screen projector: pyglet is not installed ({exc}): {INSTALL_HINT}"
        ) from None
    if pyglet.version.split(".")[0] != "2":
        raise DeviceError(
            f"screen projector: needs pyglet 2.x, found {pyglet.version}: {INSTALL_HINT}"
        )
    # No hidden shadow window: importing pyglet.window would open one on $DISPLAY, not on
    # the display asked for (and fail where DISPLAY is unset). No effect once imported.
    pyglet.options["shadow_window"] = False
    if pyglet.options["headless"]:
        raise DeviceError(
            "screen projector: pyglet is in headless mode (PYGLET_HEADLESS is set), which cannot show a "
            "window: unset it"
        )
    try:
        import pyglet.display
        import pyglet.gl
        import pyglet.window
    except ImportError as exc:  # e.g. libGL missing
        raise DeviceError(f"screen projector: pyglet cannot load OpenGL: {exc}") from None
    return pyglet


def _describe_monitors(screens: list) -> str:
    listing = ", ".join(f"{i} {s.width}x{s.height} at ({s.x},{s.y})" for i, s in enumerate(screens))
    plural = "monitor" if len(screens) == 1 else "monitors"
    return f"this display has {len(screens)} {plural}: {listing}"


class ScreenProjector(Projector):
    """A borderless full-screen window on monitor ``display``, showing images pixel for pixel.

    display : monitor index (0-based), in the order pyglet enumerates them
    x_display : X display name such as ``":0"`` (default ``$DISPLAY``); Linux only
    expected : (width, height) the monitor must have, or None to take what it has
    settle_s : seconds to wait after each image is on screen (the projector's own latency)

    Use it from the thread that opened it: the window's OpenGL context is current there.
    """

    name = "screen"

    def __init__(
        self,
        display: int = 0,
        *,
        x_display: str | None = None,
        expected: tuple[int, int] | None = None,
        settle_s: float = 0.0,
    ) -> None:
        if not (settle_s >= 0 and np.isfinite(settle_s)):
            raise DeviceError(f"screen projector: settle time must be >= 0 seconds, got {settle_s}")
        self.monitor = int(display)
        self.settle_s = float(settle_s)
        self._window = None
        self._image: np.ndarray | None = None
        self._closed_by_user = False
        self._x_display_ptr = None
        self.x_display = self._display_name(x_display)
        self.name = f"screen projector (monitor {self.monitor})"

        pyglet = _import_pyglet()
        self._pyglet = pyglet
        pdisplay = self._open_display(pyglet)
        screens = pdisplay.get_screens()
        if not 0 <= self.monitor < len(screens):
            raise DeviceError(
                f"{self.name}: monitor {self.monitor} does not exist: {_describe_monitors(screens)}"
            )
        screen = screens[self.monitor]
        self._size = (int(screen.width), int(screen.height))
        self._origin = (int(screen.x), int(screen.y))
        if expected is not None and tuple(expected) != self._size:
            raise DeviceError(
                f"{self.name}: the monitor is {self._size[0]}x{self._size[1]}, expected "
                f"{expected[0]}x{expected[1]} (set the projector to its native resolution in the display "
                f"settings; {_describe_monitors(screens)})"
            )
        self._open_window(pyglet, screen)

    # --- opening ------------------------------------------------------------------------

    def _display_name(self, x_display: str | None) -> str | None:
        if not sys.platform.startswith("linux"):
            return None
        name = x_display if x_display is not None else os.environ.get("DISPLAY")
        if not name:
            raise DeviceError(
                "screen projector: no X display to open the projector window on (DISPLAY is not set); "
                "run on the machine's desktop session, or give the display, e.g. DISPLAY=:0"
            )
        return name

    def _open_display(self, pyglet: Any) -> Any:
        if self.x_display is None:
            return pyglet.display.get_display()
        if self.x_display in _displays:  # pyglet never closes a display connection: reuse it
            return _displays[self.x_display]
        from pyglet.display.xlib import NoSuchDisplayException

        try:
            display = pyglet.display.Display(name=self.x_display)
        except NoSuchDisplayException as exc:
            raise DeviceError(
                f"screen projector: cannot open X display {self.x_display!r} ({exc}): is the X "
                "server running and DISPLAY right?"
            ) from None
        _displays[self.x_display] = display
        return display

    def _open_window(self, pyglet: Any, screen: Any) -> None:
        gl = pyglet.gl
        template = gl.Config(
            double_buffer=True, red_size=8, green_size=8, blue_size=8, depth_size=0
        )
        try:
            config = screen.get_best_config(template)
        except pyglet.window.NoSuchConfigException:  # take the default, the size is checked below
            config = None
        try:
            window = pyglet.window.Window(
                fullscreen=True,
                screen=screen,
                vsync=True,
                config=config,
                caption=CAPTION,
                style=pyglet.window.Window.WINDOW_STYLE_BORDERLESS,
            )
        except Exception as exc:  # noqa: BLE001 - config, GL, X errors: one clear message for all
            raise DeviceError(
                f"{self.name}: cannot open a full-screen OpenGL window: {exc}"
            ) from None
        self._window = window
        try:
            window.set_mouse_visible(False)
            window.push_handlers(
                on_expose=self._on_expose, on_close=self._on_close, on_draw=self._on_draw
            )
            window.switch_to()
            size = tuple(window.get_framebuffer_size())
            if size != self._size:
                raise DeviceError(
                    f"{self.name}: the window's framebuffer is {size[0]}x{size[1]}, not the monitor's "
                    f"{self._size[0]}x{self._size[1]} (display scaling is on?)"
                )
            self._setup_gl(gl)
            if sys.platform.startswith("linux"):
                self._x_display_ptr = window.display._display  # for XSync
            window.dispatch_events()
        except BaseException:
            self.close()
            raise
        log.info(
            "%s: %dx%d window at (%d,%d) on %s",
            self.name,
            *self._size,
            *self._origin,
            self.x_display,
        )

    def _setup_gl(self, gl: Any) -> None:
        w, h = self._size
        tex = gl.GLuint()
        gl.glGenTextures(1, ctypes.byref(tex))
        gl.glBindTexture(gl.GL_TEXTURE_2D, tex)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_NEAREST)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_NEAREST)
        gl.glTexImage2D(
            gl.GL_TEXTURE_2D, 0, gl.GL_RGBA8, w, h, 0, gl.GL_RGB, gl.GL_UNSIGNED_BYTE, None
        )
        fbo = gl.GLuint()
        gl.glGenFramebuffers(1, ctypes.byref(fbo))
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, fbo)
        gl.glFramebufferTexture2D(
            gl.GL_READ_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_TEXTURE_2D, tex, 0
        )
        status = gl.glCheckFramebufferStatus(gl.GL_READ_FRAMEBUFFER)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise DeviceError(f"{self.name}: OpenGL framebuffer incomplete (status {status:#x})")
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, 0)
        # Values unchanged: no sRGB encoding on write, no dithering, no blending.
        gl.glDisable(gl.GL_FRAMEBUFFER_SRGB)
        gl.glDisable(gl.GL_DITHER)
        gl.glDisable(gl.GL_BLEND)
        gl.glDisable(gl.GL_SCISSOR_TEST)
        gl.glPixelStorei(gl.GL_UNPACK_ALIGNMENT, 1)
        gl.glPixelStorei(gl.GL_UNPACK_ROW_LENGTH, 0)
        self._tex, self._fbo = tex, fbo

    # --- drawing ------------------------------------------------------------------------

    @property
    def resolution(self) -> tuple[int, int]:
        return self._size

    @property
    def monitor_origin(self) -> tuple[int, int]:
        """(x, y) px of the monitor's top-left corner on the X screen (where :func:`grab_screen` looks)."""
        return self._origin

    def show(self, image: np.ndarray) -> float:
        image = self.check_image(image)
        window = self._live_window()
        window.switch_to()
        # numpy rows run top to bottom, OpenGL's from the bottom: upload the rows reversed.
        self._image = np.ascontiguousarray(image[::-1])
        w, h = self._size
        gl = self._pyglet.gl
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._tex)
        gl.glTexSubImage2D(
            gl.GL_TEXTURE_2D, 0, 0, 0, w, h, gl.GL_RGB, gl.GL_UNSIGNED_BYTE, self._image.ctypes.data
        )
        self._present()
        shown = time.monotonic()
        window.dispatch_events()  # an expose event here redraws the same image
        if self._closed_by_user:
            raise DeviceError(
                f"{self.name}: the projector window was closed (Escape or the window manager)"
            )
        if self.settle_s:
            time.sleep(self.settle_s)
        return shown

    def poll(self) -> None:
        """Handle the window's pending events: redraw the image where another window uncovered it.

        :meth:`show` does this too; call it while waiting between images if other windows may
        pass over the projector's monitor."""
        self._live_window().dispatch_events()

    def _present(self) -> None:
        """Blit the texture 1:1 to the back buffer, swap, and wait until the frame is out."""
        gl = self._pyglet.gl
        w, h = self._size
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, self._fbo)
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, 0)
        gl.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, gl.GL_COLOR_BUFFER_BIT, gl.GL_NEAREST)
        self._window.flip()
        gl.glFinish()
        if self._x_display_ptr is not None:
            from pyglet.libs.x11 import xlib

            xlib.XSync(self._x_display_ptr, False)

    def _redraw(self) -> None:
        if self._window is None or self._image is None:
            return
        self._window.switch_to()
        self._present()

    def _on_expose(self) -> bool:
        self._redraw()
        return True

    def _on_draw(self) -> bool:
        # pyglet's app loop is not run; if something dispatches on_draw, keep the image.
        return True

    def _on_close(self) -> bool:
        self._closed_by_user = True
        self.close()
        return True

    def _live_window(self) -> Any:
        if self._window is None:
            why = (
                "was closed (Escape or the window manager)" if self._closed_by_user else "is closed"
            )
            raise DeviceError(f"{self.name}: the projector window {why}")
        return self._window

    # --- the rest -----------------------------------------------------------------------

    def close(self) -> None:
        window, self._window = self._window, None
        self._image = None
        self._x_display_ptr = None
        if window is not None:
            try:
                window.close()
            except Exception as exc:  # noqa: BLE001 - closing must not mask the error that led here
                log.warning("%s: closing the window failed: %s", self.name, exc)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "screen",
            "monitor": self.monitor,
            "x_display": self.x_display,
            "resolution": list(self._size),
            "monitor_origin": list(self._origin),
        }


# --- reading back what is on screen ------------------------------------------------------

_grabbers = threading.local()


def _grabber(x_display: str | None) -> Any:
    """One mss instance per thread and X display (mss instances are not thread-safe)."""
    cache = getattr(_grabbers, "by_display", None)
    if cache is None:
        cache = _grabbers.by_display = {}
    sct = cache.get(x_display)
    if sct is None:
        try:
            import mss
        except ImportError as exc:
            raise DeviceError(
                f"grab_screen: mss is not installed ({exc}): {INSTALL_HINT}"
            ) from None
        factory = getattr(mss, "MSS", None) or mss.mss  # mss >= 10.2 renamed the factory
        kwargs = {"display": x_display} if x_display is not None else {}
        try:
            sct = cache[x_display] = factory(**kwargs)
        except Exception as exc:  # noqa: BLE001 - mss.ScreenShotError and ctypes errors alike
            raise DeviceError(
                f"grab_screen: cannot connect to display {x_display!r}: {exc}"
            ) from None
    return sct


def grab_screen(projector: ScreenProjector) -> np.ndarray:
    """(h, w, 3) uint8 RGB: what the X server shows now in the projector's monitor rectangle.

    Read from the screen (XShmGetImage/XGetImage through mss), not from OpenGL, so it checks
    what is really displayed. Fast enough to call after every ``show``: about a millisecond
    per megapixel on Xvfb."""
    w, h = projector.resolution
    x, y = projector.monitor_origin
    shot = _grabber(projector.x_display).grab({"left": x, "top": y, "width": w, "height": h})
    bgra = np.frombuffer(shot.raw, np.uint8).reshape(shot.height, shot.width, 4)
    return np.ascontiguousarray(bgra[:, :, 2::-1])
