"""Webcams and video sources through OpenCV's ``VideoCapture``: UVC/V4L2 webcams, video
files, image sequences and network streams as a :class:`~slscan.devices.base.Camera`.

Sources (``slscan scan --camera opencv[:N|:SOURCE][:WIDTHxHEIGHT][@FPS]``):

- an ``int`` N: the webcam ``/dev/videoN`` through V4L2 on Linux (OpenCV's default
  back-end elsewhere);
- a mode after the webcam, e.g. ``opencv:0:1920x1080@30``: the frame size and rate asked
  of the driver (``CAP_PROP_FRAME_WIDTH``/``HEIGHT``/``FPS``), refused when the camera
  delivers another (:func:`slscan.devices.specs.split_webcam_mode`);
- a ``str``: anything OpenCV opens, e.g. ``/dev/video2``, ``scan.avi``, an image sequence
  ``frames/%03d.png`` (read exactly, frame by frame, 16-bit PNG/TIFF kept as uint16) or a
  stream URL ``rtsp://...``.

What it does to a webcam when opened, where the driver allows (recorded in
:meth:`OpenCVCamera.describe`): automatic exposure, white balance and focus are switched
off, so that the camera does not adapt between patterns (exposure keeps the driver's current
value unless ``exposure=`` is given; the exposure search of :mod:`slscan.capture.driver` sets
it from there), and the driver buffer is asked for one frame. Exposure and gain are in the
driver's own units (V4L2: ``exposure_absolute`` in 100 µs steps, ``gain`` raw); their ranges
are read from the V4L2 driver (``VIDIOC_QUERYCTRL``), so :meth:`OpenCVCamera.controls`
reports them only for V4L2 devices. OpenCV has no way to ask other back-ends for ranges: there
it reports nothing rather than guess.

Frames are always (h, w, 3) RGB: grey sources are repeated into three equal channels, so a
session's ``channels`` does not depend on the source; uint8, or uint16 where the source
gives 16-bit samples (image sequences of 16-bit PNG/TIFF).

Tested on OpenCV's own readers (FFV1 video files, PNG image sequences); the webcam-only code
(V4L2 controls and ranges, the auto-exposure switch) has not been run on a real webcam.
"""

from __future__ import annotations

import logging
import os
import struct
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slscan.devices.base import Camera, DeviceError, Frame

log = logging.getLogger(__name__)

# V4L2 control ids (linux/v4l2-controls.h) behind OpenCV's CAP_PROP_EXPOSURE / CAP_PROP_GAIN
V4L2_CID_GAIN = 0x00980913
V4L2_CID_EXPOSURE_ABSOLUTE = 0x009A0902
VIDIOC_QUERYCTRL = 0xC0445624  # _IOWR('V', 36, struct v4l2_queryctrl), 68 bytes
_QUERYCTRL = struct.Struct("=II32siiiiI2I")
_CTRL_DISABLED, _CTRL_READ_ONLY = 0x0001, 0x0004

# CAP_PROP_AUTO_EXPOSURE values: V4L2 passes the driver's menu (1 manual, 3 aperture
# priority = auto); DirectShow / Media Foundation use 0.25 manual, 0.75 auto
AUTO_EXPOSURE_MANUAL = {"V4L2": 1.0}
AUTO_EXPOSURE_MANUAL_OTHER = 0.25

_CONTROLS = {
    "exposure": (cv2.CAP_PROP_EXPOSURE, V4L2_CID_EXPOSURE_ABSOLUTE),
    "gain": (cv2.CAP_PROP_GAIN, V4L2_CID_GAIN),
}


def bgr_to_rgb(image: np.ndarray, what: str) -> np.ndarray:
    """An image as OpenCV reads it, as (h, w, 3) RGB of the same dtype.

    image : (h, w) grey, (h, w, 1) grey, (h, w, 3) BGR or (h, w, 4) BGRA; uint8 or uint16
    what : the source, named in the error for anything else

    Grey is repeated into three equal channels; alpha is dropped.
    """
    if image.dtype not in (np.uint8, np.uint16):
        raise DeviceError(f"{what}: {image.dtype} pixels, expected 8- or 16-bit")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2RGB)
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    raise DeviceError(f"{what}: an image of shape {image.shape}, expected grey, BGR or BGRA")


def v4l2_range(device: str | os.PathLike, cid: int) -> tuple[float, float] | None:
    """(min, max) of V4L2 control ``cid`` on ``device`` (e.g. ``/dev/video0``), or None where
    the device or control is missing, disabled or read-only (or not on Linux)."""
    if not sys.platform.startswith("linux"):
        return None
    import fcntl  # POSIX only

    try:
        fd = os.open(device, os.O_RDWR | os.O_NONBLOCK)
    except OSError:
        return None
    try:
        buf = bytearray(_QUERYCTRL.pack(cid, 0, b"", 0, 0, 0, 0, 0, 0, 0))
        fcntl.ioctl(fd, VIDIOC_QUERYCTRL, buf)
    except OSError:
        return None
    finally:
        os.close(fd)
    _, _, _, lo, hi, _, _, flags, _, _ = _QUERYCTRL.unpack(bytes(buf))
    if flags & (_CTRL_DISABLED | _CTRL_READ_ONLY) or hi <= lo:
        return None
    return float(lo), float(hi)


class OpenCVCamera(Camera):
    """A webcam, video file, image sequence or stream read through ``cv2.VideoCapture``.

    Parameters
    ----------
    source : webcam index N (``/dev/videoN``) or any OpenCV source string
        (``/dev/video2``, ``scan.avi``, ``frames/%03d.png``, ``rtsp://...``)
    width, height : ask the webcam for this frame size (px); an error if it delivers another
    fps : ask the webcam for this frame rate (frames per second); an error if the driver
        reports another (within 0.5 fps), a warning if it reports none
    exposure, gain : set at open, in the driver's units (see the module docstring)
    flush_frames : frames :meth:`flush` discards (the driver's buffer depth, or more)
    timeout_s : read timeout asked of the back-end (V4L2 and FFmpeg streams honour it)

    The first frame is read at open to learn the frame size and sample depth; for files and
    image sequences the source is then opened again, so :meth:`capture` starts at frame 0.
    """

    def __init__(
        self,
        source: int | str = 0,
        *,
        width: int | None = None,
        height: int | None = None,
        fps: float | None = None,
        exposure: float | None = None,
        gain: float | None = None,
        flush_frames: int = 4,
        timeout_s: float = 5.0,
    ) -> None:
        if flush_frames < 0:
            raise DeviceError(
                f"camera opencv:{source}: flush_frames must be >= 0, got {flush_frames}"
            )
        self.source = source
        self.name = f"camera opencv:{source}"
        self.flush_frames = int(flush_frames)
        self.timeout_s = float(timeout_s)
        self._device = self._v4l2_device(source)
        self._live = isinstance(source, int) or self._device is not None or "://" in str(source)
        self._cap: cv2.VideoCapture | None = None
        self._settings: dict[str, Any] = {}
        self._frames_read = 0
        self._cap = self._open()
        try:
            self._configure(width, height, exposure, gain)
            if fps is not None:
                self._set_fps(float(fps))
            first = self._read("reading its first frame")
            if not self._live:
                self._cap.release()
                self._cap = self._open()
                self._frames_read = 0
            else:
                self._frames_read = 1
        except BaseException:
            self.close()
            raise
        h, w = first.shape[:2]
        if (width is not None and w != width) or (height is not None and h != height):
            self.close()
            raise DeviceError(
                f"{self.name}: asked for {width or w}x{height or h} frames, it delivers {w}x{h} "
                "(pick one of its modes: v4l2-ctl --list-formats-ext)"
            )
        self._size = (w, h)
        self._dtype = first.dtype
        self._ranges = self._find_ranges()

    # --- opening ------------------------------------------------------------------------

    @staticmethod
    def _v4l2_device(source: int | str) -> str | None:
        if not sys.platform.startswith("linux"):
            return None
        if isinstance(source, int):
            return f"/dev/video{source}"
        return source if source.startswith("/dev/video") else None

    def _open(self) -> cv2.VideoCapture:
        source = self.source
        if isinstance(source, int) or self._device is not None:
            if isinstance(source, int) and source < 0:
                raise DeviceError(f"{self.name}: the device index must be >= 0")
            if self._device is None:  # not Linux: OpenCV's default back-end
                cap = cv2.VideoCapture(source)
                if not cap.isOpened():
                    raise DeviceError(
                        f"{self.name} not found: OpenCV could not open camera index {source}"
                    )
                return cap
            if not Path(self._device).exists():
                present = sorted(p.name for p in Path("/dev").glob("video*"))
                raise DeviceError(
                    f"{self.name} not found: no V4L2 device {self._device} (video devices here: "
                    f"{', '.join(present) or 'none'}; `v4l2-ctl --list-devices` names them)"
                )
            cap = cv2.VideoCapture(source, cv2.CAP_V4L2)
            if not cap.isOpened():
                raise DeviceError(
                    f"{self.name} not found: V4L2 could not open {self._device} (in use by another "
                    "program, not a capture node, or no permission: are you in the 'video' group?)"
                )
            return cap
        if "://" in source:
            ms = int(self.timeout_s * 1000)
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
            cap = cv2.VideoCapture(source, cv2.CAP_FFMPEG, params)
            if not cap.isOpened():
                raise DeviceError(
                    f"{self.name} not found: could not open the stream {source} "
                    f"within {self.timeout_s:g} s"
                )
            return cap
        if "%" in source:
            cap = cv2.VideoCapture(source, cv2.CAP_IMAGES)
            if not cap.isOpened():
                try:
                    first = f" (no file {source % 0}, {source % 1}, ...)"
                except (TypeError, ValueError):
                    first = ""
                raise DeviceError(f"{self.name} not found: no image sequence {source}{first}")
            return cap
        path = Path(source).expanduser()
        if not path.exists():
            raise DeviceError(f"{self.name} not found: no file {path}")
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise DeviceError(
                f"{self.name}: OpenCV cannot read {path} (not a video or image format it decodes)"
            )
        return cap

    def _configure(
        self, width: int | None, height: int | None, exposure: float | None, gain: float | None
    ) -> None:
        cap, s = self._cap, self._settings
        s["backend"] = cap.getBackendName()
        if width is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height is not None:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if not self._live:
            asked = [k for k, v in (("exposure", exposure), ("gain", gain)) if v is not None]
            if asked:
                raise DeviceError(
                    f"{self.name}: a file or image sequence has no {' or '.join(asked)}"
                )
            return
        s["buffer_size_1"] = bool(cap.set(cv2.CAP_PROP_BUFFERSIZE, 1))
        s["read_timeout"] = bool(
            cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, int(self.timeout_s * 1000))
        )
        manual = AUTO_EXPOSURE_MANUAL.get(s["backend"], AUTO_EXPOSURE_MANUAL_OTHER)
        s["auto_exposure_off"] = bool(cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, manual))
        s["auto_white_balance_off"] = bool(cap.set(cv2.CAP_PROP_AUTO_WB, 0))
        s["autofocus_off"] = bool(cap.set(cv2.CAP_PROP_AUTOFOCUS, 0))
        for key, value in (("exposure", exposure), ("gain", gain)):
            if value is not None:
                if not cap.set(_CONTROLS[key][0], float(value)):
                    raise DeviceError(f"{self.name}: the driver refuses to set {key} {value:g}")
                s[key] = float(cap.get(_CONTROLS[key][0]))
        not_done = [k for k, v in s.items() if v is False]
        if not_done:
            log.info("%s: the driver did not take %s", self.name, ", ".join(not_done))

    def _set_fps(self, fps: float) -> None:
        """Ask for ``fps`` frames per second; refuse a rate the driver reports it did not take."""
        cap = self._require_open()
        if not self._live:
            raise DeviceError(f"{self.name}: a file or image sequence has no frame rate to set")
        cap.set(cv2.CAP_PROP_FPS, fps)
        got = float(cap.get(cv2.CAP_PROP_FPS))
        if got <= 0:
            log.warning("%s: asked for %g fps; the driver does not say which rate it took", self.name, fps)
            self._settings["fps_asked"] = fps
            return
        if abs(got - fps) > 0.5:
            raise DeviceError(
                f"{self.name}: asked for {fps:g} fps, the driver set {got:g} fps "
                "(pick one of its modes: v4l2-ctl --list-formats-ext)"
            )
        self._settings["fps"] = got

    def _find_ranges(self) -> dict[str, tuple[float, float]]:
        ranges: dict[str, tuple[float, float]] = {}
        if self._device is None or self._cap is None:
            return ranges
        for key, (prop, cid) in _CONTROLS.items():
            value = self._cap.get(prop)
            rng = v4l2_range(self._device, cid)
            if rng is not None and value != -1 and self._cap.set(prop, value):
                ranges[key] = rng
        return ranges

    # --- Camera -------------------------------------------------------------------------

    @property
    def resolution(self) -> tuple[int, int]:
        return self._size

    @property
    def bit_depth(self) -> int:
        return 16 if self._dtype == np.uint16 else 8

    def controls(self) -> dict[str, tuple[float, float]]:
        """Exposure and gain with their V4L2 (min, max) where the driver lets them be set."""
        return dict(self._ranges)

    def get_controls(self) -> dict[str, float]:
        cap = self._require_open()
        return {key: float(cap.get(_CONTROLS[key][0])) for key in self._ranges}

    def set_controls(self, **values: float) -> dict[str, float]:
        """Set exposure / gain (clamped to the driver's range); return what ``get`` reads back."""
        cap = self._require_open()
        self.check_control_names(values, self._ranges)
        applied = {}
        for key, value in values.items():
            lo, hi = self._ranges[key]
            prop = _CONTROLS[key][0]
            if not cap.set(prop, float(min(max(value, lo), hi))):
                raise DeviceError(f"{self.name}: the driver refused {key} {value:g}")
            applied[key] = float(cap.get(prop))
        return applied

    def flush(self) -> None:
        """Grab and drop ``flush_frames`` frames, so that :meth:`capture` returns a frame
        exposed after the pattern change rather than one waiting in the driver's buffer."""
        cap = self._require_open()
        for _ in range(self.flush_frames):
            if not cap.grab():
                raise DeviceError(self._no_frame())
            self._frames_read += 1

    def capture(self) -> Frame:
        """The next frame as (h, w, 3) RGB uint8 (or uint16), with ``metadata`` ``source``,
        ``frame_index`` (0-based; files and image sequences only) and the exposure / gain
        read back (webcams whose driver reports them)."""
        image = self._read("capturing")
        t = time.monotonic()
        h, w = image.shape[:2]
        if (w, h) != self._size or image.dtype != self._dtype:
            raise DeviceError(
                f"{self.name}: frame {self._frames_read - 1} is {w}x{h} {image.dtype}, the first frame "
                f"was {self._size[0]}x{self._size[1]} {np.dtype(self._dtype).name}"
            )
        metadata: dict[str, Any] = {"source": str(self.source)}
        if not self._live:
            metadata["frame_index"] = self._frames_read - 1
        metadata.update(self.get_controls())
        return Frame(image, t, metadata)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "opencv",
            "source": str(self.source),
            "resolution": list(self._size),
            "bit_depth": self.bit_depth,
            "flush_frames": self.flush_frames,
            **self._settings,
        }

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    # --- helpers ------------------------------------------------------------------------

    def _require_open(self) -> cv2.VideoCapture:
        if self._cap is None:
            raise DeviceError(f"{self.name}: the camera is closed")
        return self._cap

    def _read(self, doing: str) -> np.ndarray:
        cap = self._require_open()
        ok, image = cap.read()
        if not ok or image is None:
            raise DeviceError(self._no_frame(doing))
        self._frames_read += 1
        return bgr_to_rgb(image, self.name)

    def _no_frame(self, doing: str = "capturing") -> str:
        when = "" if doing == "capturing" else f" while {doing}"
        if self._live:
            return f"{self.name}: no frame{when} (unplugged?)"
        return f"{self.name}: no frame{when}: the source ended after {self._frames_read} frame(s)"
