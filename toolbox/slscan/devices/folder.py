"""A watch folder as a camera: images saved by tethering software (darktable, digiKam,
EOS Utility, ...) are taken as frames, one new file per capture.

The folder is the queue between the camera and the scan: :class:`FolderCamera` remembers
the files present when it was opened and never returns them; each :meth:`FolderCamera.capture`
waits for the next new file (one that appeared after the previous capture, or after the
folder was opened), oldest modification time first, and returns it only once it is complete:
its size and modification time have not changed for ``stable_s`` seconds **and** it decodes
in full (a JPEG must end with its end-of-image marker, a PNG with its ``IEND`` chunk), so a
file still being written is never returned half. When several new files are waiting, they are
returned one per capture in modification-time order (then by name); ``metadata["pending"]``
says how many more were waiting. :meth:`FolderCamera.flush` discards nothing: every file in
the folder is a shot someone took on purpose.

Someone else presses the shutter, so before every capture the camera asks for the shot:
:meth:`FolderCamera.about_to_capture` rings the terminal bell and writes one line to
stderr, e.g. ``shoot view 3, frame 5 (white) now`` (``prompt=`` replaces it, e.g. with a
remote trigger).

The user's files are only read, never moved, changed or deleted.
"""

from __future__ import annotations

import fnmatch
import logging
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slscan.devices.base import Camera, DeviceError, Frame
from slscan.devices.opencv_camera import bgr_to_rgb

log = logging.getLogger(__name__)

IMAGE_PATTERNS = ("*.jpg", "*.jpeg", "*.png", "*.tif", "*.tiff")
_PNG_END = b"IEND\xaeB`\x82"
_JPEG_END = b"\xff\xd9"


def bell_prompt(message: str) -> None:
    """Ring the terminal bell and write ``message`` as one line to stderr (the default
    prompt of :class:`FolderCamera`: it does not wait, the new file is the answer)."""
    stream = sys.stderr
    if stream is not None:
        stream.write(f"\a{message}\n")
        stream.flush()


@dataclass
class _Watched:
    """A new file seen while waiting: its last (size, mtime) and since when it has kept them."""

    size: int
    mtime_ns: int
    since: float


def decode_complete(data: bytes, name: str) -> np.ndarray | None:
    """The image in ``data`` as (h, w, 3) RGB uint8 / uint16, or None while it is incomplete.

    A JPEG must end with its end-of-image marker and a PNG with its ``IEND`` chunk (trailing
    NUL padding allowed), whatever the decoder makes of a cut-off file (some fill the missing
    part with grey rather than fail). Anything that OpenCV cannot decode counts as incomplete. EXIF orientation is
    ignored: frames stay in the sensor's pixel grid.
    """
    tail = data[-4096:].rstrip(b"\0")
    suffix = Path(name).suffix.lower()
    if suffix in (".jpg", ".jpeg") and not tail.endswith(_JPEG_END):
        return None
    if suffix == ".png" and not tail.endswith(_PNG_END):
        return None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        return None
    return bgr_to_rgb(image, name)


class FolderCamera(Camera):
    """New images in a folder, one per :meth:`capture` (see the module docstring).

    Parameters
    ----------
    folder : where the tethering software saves the shots
    patterns : file name patterns taken as images (case-insensitive)
    timeout_s : how long :meth:`capture` waits for a new, complete image
    stable_s : a file counts as written once its size and time are unchanged this long (s)
    poll_s : how often the folder is looked at (s)
    resolution : (width, height) px the images must have; by default that of the newest image
        already in the folder (e.g. a test shot), else of the first captured image
    prompt : asks for each shot with a message such as ``"shoot view 3, frame 5 (white) now"``
        (default :func:`bell_prompt`: bell and a line on stderr); None in ``prompt=`` keeps
        the default, ``prompt=False`` asks nothing (a camera on an automatic trigger)
    """

    def __init__(
        self,
        folder: str | os.PathLike,
        *,
        patterns: tuple[str, ...] = IMAGE_PATTERNS,
        timeout_s: float = 60.0,
        stable_s: float = 0.3,
        poll_s: float = 0.05,
        resolution: tuple[int, int] | None = None,
        prompt: Callable[[str], None] | None | bool = None,
    ) -> None:
        self.folder = Path(folder)
        self._prompt = None if prompt is False else (bell_prompt if prompt in (None, True) else prompt)
        self.name = f"folder camera {self.folder}"
        if not self.folder.is_dir():
            raise DeviceError(f"{self.name}: not a folder")
        self.patterns = tuple(p.lower() for p in patterns)
        self.timeout_s, self.stable_s, self.poll_s = (
            float(timeout_s),
            float(stable_s),
            float(poll_s),
        )
        self._seen = {name for name, _ in self._images()}
        self._size = tuple(resolution) if resolution is not None else None
        self._dtype: np.dtype | None = None
        self._size_from = "the resolution argument" if resolution is not None else None
        if self._size is None:
            self._learn_size_from_existing()

    # --- Camera -------------------------------------------------------------------------

    @property
    def resolution(self) -> tuple[int, int]:
        if self._size is None:
            raise DeviceError(
                f"{self.name}: the image size is not known before the first image: save a test "
                "shot into the folder before starting, or give resolution=(width, height)"
            )
        return self._size

    @property
    def bit_depth(self) -> int:
        return 16 if self._dtype == np.uint16 else 8

    def about_to_capture(self, label: str) -> None:
        """Ask for the shot: ``shoot {label} now`` through the prompt (bell + stderr line)."""
        if self._prompt is not None:
            self._prompt(f"shoot {label} now")

    def capture(self) -> Frame:
        """Wait for the next new, completely written image; return it as (h, w, 3) RGB with
        ``metadata`` ``file`` (its name in the folder) and ``pending`` (new files still
        waiting after it)."""
        deadline = time.monotonic() + self.timeout_s
        watched: dict[str, _Watched] = {}
        while True:
            now = time.monotonic()
            new = self._new_files()
            for name in list(watched):
                if name not in new:
                    del watched[name]  # renamed or removed by the tethering software
            if new:
                name, (size, mtime_ns) = min(new.items(), key=lambda kv: (kv[1][1], kv[0]))
                w = watched.get(name)
                if w is None or (w.size, w.mtime_ns) != (size, mtime_ns):
                    watched[name] = _Watched(size, mtime_ns, now)
                elif now - w.since >= self.stable_s:
                    image = self._read(name)
                    if image is not None:
                        self._seen.add(name)
                        return self._frame(name, image, len(new) - 1)
                    w.since = now  # written in pauses: look again after another stable_s
            if now >= deadline:
                break
            time.sleep(min(self.poll_s, max(0.0, deadline - now)))
        waiting = self._new_files()
        if waiting:
            name = min(waiting, key=lambda n: (waiting[n][1], n))
            raise DeviceError(
                f"{self.name}: {name} did not become a complete, readable image within "
                f"{self.timeout_s:g} s (still being written, or not an image?)"
            )
        raise DeviceError(
            f"{self.name}: no new image within {self.timeout_s:g} s "
            "(is the tethering software saving there?)"
        )

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "folder",
            "folder": str(self.folder),
            "patterns": list(self.patterns),
            "stable_s": self.stable_s,
            "ignored_at_open": len(self._seen),
        }

    # --- helpers ------------------------------------------------------------------------

    def _images(self) -> list[tuple[str, os.stat_result]]:
        out = []
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            raise DeviceError(f"{self.name}: cannot list the folder ({exc})") from exc
        for entry in entries:
            low = entry.name.lower()
            if low.startswith(".") or not any(fnmatch.fnmatchcase(low, p) for p in self.patterns):
                continue
            try:
                if entry.is_file():
                    out.append((entry.name, entry.stat()))
            except OSError:
                continue  # gone between listing and stat
        return out

    def _new_files(self) -> dict[str, tuple[int, int]]:
        return {
            name: (st.st_size, st.st_mtime_ns)
            for name, st in self._images()
            if name not in self._seen
        }

    def _read(self, name: str) -> np.ndarray | None:
        try:
            data = (self.folder / name).read_bytes()
        except OSError:
            return None
        return decode_complete(data, name)

    def _frame(self, name: str, image: np.ndarray, pending: int) -> Frame:
        t = time.monotonic()
        h, w = image.shape[:2]
        if self._size is None:
            self._size, self._size_from = (w, h), name
        if self._dtype is None:
            self._dtype = image.dtype
        if (w, h) != self._size or image.dtype != self._dtype:
            raise DeviceError(
                f"{self.name}: {name} is {w}x{h} {image.dtype}, expected {self._size[0]}x{self._size[1]} "
                f"{np.dtype(self._dtype).name} (as {self._size_from}; "
                "keep the camera's image size and format fixed during a scan)"
            )
        if pending:
            log.info("%s: took %s; %d more new image(s) waiting", self.name, name, pending)
        return Frame(image, t, {"file": name, "pending": pending})

    def _learn_size_from_existing(self) -> None:
        for name, _ in sorted(self._images(), key=lambda item: -item[1].st_mtime_ns):
            image = self._read(name)
            if image is not None:
                h, w = image.shape[:2]
                self._size, self._dtype, self._size_from = (
                    (w, h),
                    image.dtype,
                    f"{name}, already there",
                )
                log.info("%s: frames must be %dx%d like %s", self.name, w, h, name)
                return
