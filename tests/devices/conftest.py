"""Fixtures for the projector window: private Xvfb servers, and an open ScreenProjector.

Two virtual X servers (Mesa llvmpipe renders OpenGL in software):

- ``x_display``: two monitors, 1024x768 and 800x600, as two Xvfb screens joined by
  Xinerama. RandR is switched off so that pyglet lists the Xinerama heads (with RandR on
  it lists Xvfb's single RandR output, one monitor). Xvfb 21.1 puts every screen's origin
  at (0, 0), so the two monitors overlap: they differ in size and index, not in position.
- ``x_display_offset``: one 1824x768 screen whose only RandR monitor is set to 800x600 at
  (1024, 0), as a projector right of a 1024-wide desktop monitor would be: checks that the
  window and the screen grab use the monitor's origin.

Xvfb missing fails the tests (run ``.ci/setup``): a skipped test never runs in CI.
"""

from __future__ import annotations

import ctypes
import os
import select
import shutil
import subprocess
import time
from collections.abc import Iterator

import pytest

MONITORS = ((1024, 768), (800, 600))
OFFSET_SCREEN = (1824, 768)
OFFSET_MONITOR = (1024, 0, 800, 600)  # x, y, width, height
START_TIMEOUT_S = 20.0
START_ATTEMPTS = 5
FIRST_DISPLAY = 90  # clear of the :0, :1 a desktop uses


def _free_display_number(start: int) -> int:
    for n in range(start, start + 100):
        if not os.path.exists(f"/tmp/.X11-unix/X{n}") and not os.path.exists(f"/tmp/.X{n}-lock"):
            return n
    pytest.fail(f"no free X display number in :{start}..:{start + 99}")


def _start_xvfb(args: list[str]) -> tuple[subprocess.Popen, str]:
    """Start ``Xvfb`` on a free display number from :90 up; return once it accepts connections.

    ``-displayfd`` makes Xvfb write the display number to a pipe once it is ready, so there
    is no polling for the socket; a number taken meanwhile by another server is retried."""
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.fail("Xvfb is not installed: run .ci/setup (it apt-get installs xvfb and Mesa GL)")
    number = FIRST_DISPLAY
    for _ in range(START_ATTEMPTS):
        number = _free_display_number(number)
        read_fd, write_fd = os.pipe()
        try:
            proc = subprocess.Popen(
                [
                    exe,
                    f":{number}",
                    "-displayfd",
                    str(write_fd),
                    "-nolisten",
                    "tcp",
                    "-noreset",
                    *args,
                ],
                pass_fds=(write_fd,),
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
            )
        finally:
            os.close(write_fd)
        try:
            ready = _read_line(read_fd, START_TIMEOUT_S)
        finally:
            os.close(read_fd)
        if ready:
            return proc, f":{number}"
        proc.kill()
        err = proc.communicate()[1].decode(errors="replace").strip()
        if "already active" not in err and "server is already" not in err:
            pytest.fail(
                f"Xvfb :{number} {' '.join(args)} did not start within {START_TIMEOUT_S:g} s: {err}"
            )
        number += 1
    pytest.fail(f"Xvfb: no free display number after {START_ATTEMPTS} attempts")


def _read_line(fd: int, timeout_s: float) -> bytes:
    """What Xvfb writes to ``-displayfd`` (the display number and a newline), or b"" if it exits."""
    data = b""
    deadline = time.monotonic() + timeout_s
    while not data.endswith(b"\n"):
        ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        chunk = os.read(fd, 64) if ready else b""
        if not chunk:
            return b""
        data += chunk
    return data


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _place_randr_monitor(name: str, x: int, y: int, width: int, height: int) -> None:
    """Set the server's (single) RandR output to a width x height mode at (x, y).

    Xvfb accepts any mode for its output; the server runs with ``-noreset``, so the setting
    outlives this client's connection."""
    from pyglet.libs.x11 import xlib, xrandr

    lib = ctypes.cdll.LoadLibrary("libXrandr.so.2")
    lib.XRRCreateMode.restype = ctypes.c_ulong
    lib.XRRCreateMode.argtypes = [
        ctypes.c_void_p,
        ctypes.c_ulong,
        ctypes.POINTER(xrandr.XRRModeInfo),
    ]
    lib.XRRAddOutputMode.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong]
    dpy = xlib.XOpenDisplay(name.encode())
    if not dpy:
        pytest.fail(f"cannot connect to the test X server {name}")
    try:
        root = xlib.XDefaultRootWindow(dpy)
        res = xrandr.XRRGetScreenResources(dpy, root)
        output, crtc = res.contents.outputs[0], res.contents.crtcs[0]
        info = xrandr.XRRModeInfo()
        mode_name = f"slscan-{width}x{height}".encode()
        info.width, info.height = width, height
        info.hSyncStart, info.hSyncEnd, info.hTotal = width + 40, width + 168, width + 256
        info.vSyncStart, info.vSyncEnd, info.vTotal = height + 1, height + 5, height + 28
        info.dotClock = info.hTotal * info.vTotal * 60
        info.name, info.nameLength = mode_name, len(mode_name)
        mode = lib.XRRCreateMode(dpy, root, ctypes.byref(info))
        lib.XRRAddOutputMode(dpy, output, mode)
        outputs = (xrandr.RROutput * 1)(output)
        status = xrandr.XRRSetCrtcConfig(
            dpy, res, crtc, 0, x, y, mode, 1, outputs, 1
        )  # 1: RR_Rotate_0
        xrandr.XRRFreeScreenResources(res)
        xlib.XSync(dpy, False)
        if status != 0:
            pytest.fail(f"{name}: XRRSetCrtcConfig failed with status {status}")
    finally:
        xlib.XCloseDisplay(dpy)


@pytest.fixture(scope="session")
def x_display() -> Iterator[str]:
    """Name (":N") of a private Xvfb with two monitors, 1024x768 and 800x600 (Xinerama)."""
    screens: list[str] = []
    for i, (w, h) in enumerate(MONITORS):
        screens += ["-screen", str(i), f"{w}x{h}x24"]
    proc, name = _start_xvfb([*screens, "+xinerama", "-extension", "RANDR"])
    yield name
    _stop(proc)


@pytest.fixture(scope="session")
def x_display_offset() -> Iterator[str]:
    """Name of a private Xvfb whose one monitor is 800x600 at (1024, 0) (RandR)."""
    w, h = OFFSET_SCREEN
    proc, name = _start_xvfb(["-screen", "0", f"{w}x{h}x24"])
    try:
        _place_randr_monitor(name, *OFFSET_MONITOR)
    except BaseException:
        _stop(proc)
        raise
    yield name
    _stop(proc)


@pytest.fixture(scope="module")
def projector(x_display: str):
    """A ScreenProjector open on monitor 0 (1024x768) of ``x_display``."""
    from slscan.devices.screen import ScreenProjector

    with ScreenProjector(0, x_display=x_display, expected=MONITORS[0]) as proj:
        yield proj
