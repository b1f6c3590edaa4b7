"""The real Rerun viewer, headless, for tests that check what a user sees.

``rerun`` runs without a window (an offscreen harness on Mesa's Vulkan rasteriser,
lavapipe) and is driven over gRPC with Rerun's ``ViewerClient``: open a recording, pick a
tab of its blueprint, move the time cursor, screenshot the window or one view. Needs
Mesa's Vulkan driver (Debian ``mesa-vulkan-drivers``), which ``.ci/setup`` installs:
:func:`requirements` skips the test without it, or fails it when ``CI`` is set.
"""

from __future__ import annotations

import glob
import os
import shutil
import socket
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest


def requirements() -> str:
    """The ``rerun`` executable; skips (fails under CI) when the viewer cannot render here."""
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    vulkan = glob.glob("/usr/share/vulkan/icd.d/lvp_icd*.json")
    missing = [name for name, found in (("rerun (rerun-sdk)", rerun),
                                        ("Mesa's Vulkan driver lavapipe (mesa-vulkan-drivers)", vulkan)) if not found]
    if missing:
        message = f"rendering the viewer needs {', '.join(missing)}: run .ci/setup"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return rerun


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def drawn_share(picture: np.ndarray, level: int = 40) -> float:
    """Share of the pixels away from the picture's most common colour (its background)."""
    flat = picture.reshape(-1, 3)
    colours, counts = np.unique(flat[:: max(1, len(flat) // 20000)], axis=0, return_counts=True)
    background = colours[np.argmax(counts)].astype(int)
    return float((np.abs(picture.astype(int) - background).max(axis=-1) > level).mean())


class HeadlessViewer:
    """A headless ``rerun`` showing one recording; a context manager that quits it."""

    def __init__(self, rrd: Path, shots: Path) -> None:
        from rerun.experimental import ViewerClient

        os.environ.setdefault("XDG_RUNTIME_DIR", str(shots))  # else winit complains on stderr
        os.environ["RUST_LOG"] = "error"  # no toasts (software rasteriser) over the views
        self.shots = shots
        self.client = ViewerClient.spawn(headless=True, port=free_port(), hide_welcome_screen=True,
                                         executable_path=requirements())
        self.client.open([str(rrd)])
        self.store = self._wait_for_recording()

    def _wait_for_recording(self, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            state = self.client.get_state()
            if state.active_recording and not state.loading:
                return state.active_recording
            time.sleep(0.2)
        raise AssertionError("the viewer did not load the recording")

    def __enter__(self) -> HeadlessViewer:
        return self

    def __exit__(self, *exc) -> None:
        self.client.quit()

    # --- blueprint ---------------------------------------------------------------------------

    def _blueprint(self) -> dict:
        return self.client.get_blueprint(store_id=self.store).blueprint

    def show_tab(self, tabs: str, tab: str) -> list[tuple[str, str, str]]:
        """Make ``tab`` (a container or view's display name) the active tab of the Tabs
        container named ``tabs``; return (view id, class, name) of every view inside it."""
        bp = self._blueprint()

        def name(path: str) -> str | None:
            fields = bp.get(path, {})
            return (fields.get("ContainerBlueprint") or fields.get("ViewBlueprint") or {}).get("display_name")

        parent = next(p for p, f in bp.items() if f.get("ContainerBlueprint", {}).get("display_name") == tabs
                      and f["ContainerBlueprint"].get("container_kind") == "Tabs")
        child = next(c for c in bp[parent]["ContainerBlueprint"]["contents"] if name(c) == tab)
        bp[parent]["ContainerBlueprint"]["active_tab"] = child
        self.client.set_blueprint(bp, store_id=self.store)

        views, todo = [], [child]
        while todo:
            path = todo.pop()
            fields = bp.get(path, {})
            if "ContainerBlueprint" in fields:
                container = fields["ContainerBlueprint"]
                contents = container.get("contents", [])
                if container.get("container_kind") == "Tabs":  # only what is on screen
                    contents = [container.get("active_tab") or contents[0]] if contents else []
                todo.extend(contents)
            elif "ViewBlueprint" in fields:
                view = fields["ViewBlueprint"]
                views.append((path.rsplit("/", 1)[-1], view.get("class_identifier", ""), view.get("display_name", "")))
        return views

    # --- time and pictures -------------------------------------------------------------------

    def set_time(self, timeline: str, value: int) -> None:
        self.client.set_time(timeline, sequence=value, play_state="paused")

    def screenshot(self, name: str, view_id: str | None = None, *, settle_s: float = 10.0) -> np.ndarray:
        """(h, w, 3) uint8 RGB picture of the window, or of one view.

        A view still blank (:func:`drawn_share` under 1 %: e.g. only the loading dots) is
        taken again for up to ``settle_s``: images are decoded in the background after the
        time cursor moves.
        """
        path = self.shots / f"{name}.png"
        deadline = time.monotonic() + settle_s
        while True:
            self.client.save_screenshot(str(path), view_id=view_id)
            picture = cv2.imread(str(path))
            assert picture is not None, f"no screenshot at {path}"
            if drawn_share(picture) > 0.01 or time.monotonic() > deadline:
                return np.ascontiguousarray(picture[..., ::-1])
            time.sleep(0.5)
