"""Device specs as ``slscan scan`` takes them (``screen:1``, ``opencv:0``, ``opencv:0:1920x1080@30``,
``folder:DIR``),
parsed and opened; each back-end is imported only when its device is opened."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from slscan.devices.base import Camera, DeviceError, Projector

PROJECTOR_KINDS = ("screen", "virtual")
CAMERA_KINDS = ("opencv", "gphoto2", "folder", "virtual", "loop")
SIMULATED_CAMERAS = ("virtual", "loop")


@dataclass(frozen=True)
class DeviceSpec:
    """A parsed ``KIND[:ARG]``."""

    kind: str
    arg: str | None = None

    def __str__(self) -> str:
        return self.kind if self.arg is None else f"{self.kind}:{self.arg}"


def parse_spec(text: str, kinds: tuple[str, ...], what: str) -> DeviceSpec:
    """``"screen:1"`` → ``DeviceSpec("screen", "1")``; an unknown kind names the known ones."""
    kind, sep, arg = text.partition(":")
    kind = kind.strip().lower()
    if kind not in kinds:
        raise DeviceError(f"unknown {what} {text!r}: expected one of {', '.join(kinds)} (e.g. {kinds[0]}:0)")
    return DeviceSpec(kind, arg if sep else None)


def _index(spec: DeviceSpec, what: str) -> int:
    if spec.arg is None or spec.arg == "":
        return 0
    try:
        index = int(spec.arg)
    except ValueError:
        raise DeviceError(f"{what} {spec}: expected a number after ':', e.g. {spec.kind}:1") from None
    if index < 0:
        raise DeviceError(f"{what} {spec}: the index must be >= 0")
    return index


def open_projector(spec: DeviceSpec) -> Projector:
    """Open a real projector (``screen[:N]``: full-screen window on monitor N)."""
    if spec.kind == "screen":
        from slscan.devices.screen import ScreenProjector

        return ScreenProjector(_index(spec, "projector"))
    raise DeviceError(f"projector {spec}: not a real projector (the virtual one comes with the virtual rig)")


_MODE = re.compile(r"(?:(\d+)x(\d+))?(?:@(\d+(?:\.\d+)?))?")


@dataclass(frozen=True)
class WebcamMode:
    """A webcam mode asked for in ``opencv:N:WIDTHxHEIGHT@FPS``; None: the driver's choice."""

    width: int | None = None
    height: int | None = None
    fps: float | None = None


def split_webcam_mode(spec: DeviceSpec) -> tuple[str | None, WebcamMode]:
    """``opencv:0:1920x1080@30`` → ``("0", WebcamMode(1920, 1080, 30.0))``; also
    ``opencv:0:1280x720``, ``opencv:0:@15``, ``opencv:/dev/video2:640x480``. A last
    ``:``-part that is not a mode stays part of the source (a file name, a URL)."""
    arg = spec.arg
    if not arg or ":" not in arg:
        return arg, WebcamMode()
    source, _, last = arg.rpartition(":")
    match = _MODE.fullmatch(last)
    if not last or match is None or not any(match.groups()):
        return arg, WebcamMode()
    if not (source.isdigit() or source.startswith("/dev/video")):
        raise DeviceError(f"camera {spec}: a mode (WIDTHxHEIGHT@FPS) is for a webcam, e.g. opencv:0:{last}")
    w, h, fps = match.groups()
    mode = WebcamMode(None if w is None else int(w), None if h is None else int(h), None if fps is None else float(fps))
    if (mode.width is not None and mode.width < 1) or (mode.height is not None and mode.height < 1) or (
            mode.fps is not None and mode.fps <= 0):
        raise DeviceError(f"camera {spec}: the mode {last!r} must have a positive size and frame rate")
    return source, mode


def open_camera(spec: DeviceSpec) -> Camera:
    """Open a real camera: ``opencv[:N|:SOURCE][:WIDTHxHEIGHT][@FPS]``, ``gphoto2[:PORT]``,
    ``folder:DIR``."""
    if spec.kind == "opencv":
        from slscan.devices.opencv_camera import OpenCVCamera

        source, mode = split_webcam_mode(spec)
        if source and not source.isdigit():  # a video file or an image sequence: no buffered frames
            if source.startswith("/dev/video"):
                return OpenCVCamera(source, width=mode.width, height=mode.height, fps=mode.fps)
            return OpenCVCamera(source, flush_frames=0)
        index = _index(DeviceSpec(spec.kind, source), "camera")
        return OpenCVCamera(index, width=mode.width, height=mode.height, fps=mode.fps)
    if spec.kind == "gphoto2":
        from slscan.devices.gphoto import GPhoto2Camera

        return GPhoto2Camera(port=spec.arg or None)
    if spec.kind == "folder":
        if not spec.arg:
            raise DeviceError("camera folder: name the folder the tethering software saves to, e.g. folder:~/tether")
        from slscan.devices.folder import FolderCamera

        folder = Path(spec.arg).expanduser()
        if not folder.is_dir():
            raise DeviceError(f"camera {spec}: {folder} is not a folder")
        return FolderCamera(folder)
    raise DeviceError(f"camera {spec}: not a real camera (the virtual ones come with the virtual rig)")
