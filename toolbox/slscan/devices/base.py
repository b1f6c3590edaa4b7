"""The device interfaces every rig implements: Projector, Camera, Lights and Stage.

The acquisition driver (:mod:`slscan.capture.driver`) talks to a rig only through these
four classes, so the virtual rig (:mod:`slscan.virtual.devices`) and real hardware
(:mod:`slscan.devices.screen`, :mod:`slscan.devices.opencv_camera`,
:mod:`slscan.devices.gphoto`, :mod:`slscan.devices.folder`, :mod:`slscan.devices.lights`)
share one code path. A new back-end (a relay board for the lights, a motorised
turntable, an industrial camera) subclasses one of them; see ``docs/scanning.md``.

Conventions:

- images are numpy arrays, (h, w) grey or (h, w, 3) **RGB**, uint8 or uint16, in the
  device's native pixel grid (never rescaled);
- times are ``time.monotonic()`` seconds;
- a device that fails raises :class:`DeviceError` naming the device and what it was doing;
- every device is a context manager; ``close()`` is safe to call twice.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any, Self

import numpy as np

from slscan.errors import SlscanError


class DeviceError(SlscanError):
    """A device could not be opened, or failed while scanning (unplugged, timed out, ...)."""


@dataclass(frozen=True)
class Frame:
    """One captured camera frame.

    image : (h, w) or (h, w, 3) RGB, uint8 or uint16
    timestamp : monotonic seconds at which the frame was read back (after its exposure)
    metadata : what the device reports about it (exposure, gain, file name, ...), JSON types
    """

    image: np.ndarray
    timestamp: float
    metadata: dict[str, Any] = field(default_factory=dict)


class Device(abc.ABC):
    """Common base: a name for messages, context-manager use, idempotent ``close``."""

    name: str = "device"

    def close(self) -> None:
        """Release the device (window, file handle, USB connection)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def describe(self) -> dict[str, Any]:
        """JSON description recorded in ``session.json`` under ``device``."""
        return {"kind": self.name}


class Projector(Device):
    """Shows full-frame images, pixel for pixel."""

    @property
    @abc.abstractmethod
    def resolution(self) -> tuple[int, int]:
        """(width, height) projector pixels."""

    @abc.abstractmethod
    def show(self, image: np.ndarray) -> float:
        """Show ``image`` (height, width, 3) uint8 RGB exactly, without scaling or filtering;
        return once it is on screen, with the monotonic time it was presented."""

    def blank(self) -> float:
        """Show black (or switch the light off where the device can); see :meth:`show`."""
        w, h = self.resolution
        return self.show(np.zeros((h, w, 3), np.uint8))

    def check_image(self, image: np.ndarray) -> np.ndarray:
        """``image`` as contiguous (h, w, 3) uint8 matching :attr:`resolution`, or raise."""
        w, h = self.resolution
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise DeviceError(f"{self.name}: expected an (h, w, 3) uint8 RGB image, got {image.shape} {image.dtype}")
        if image.shape[:2] != (h, w):
            raise DeviceError(
                f"{self.name}: the image is {image.shape[1]}x{image.shape[0]}, the projector shows {w}x{h} "
                "(patterns must be made for the projector's native resolution)"
            )
        return np.ascontiguousarray(image)


class Camera(Device):
    """Captures frames; exposure and gain are settable where the device allows."""

    @property
    @abc.abstractmethod
    def resolution(self) -> tuple[int, int]:
        """(width, height) pixels of the frames it returns."""

    @property
    def channels(self) -> int:
        """1 (grey) or 3 (RGB)."""
        return 3

    @property
    def bit_depth(self) -> int:
        """8 or 16 bits per sample."""
        return 8

    @property
    def jpeg_quality(self) -> int | None:
        """The JPEG quality (1–100) the camera delivers its captures at, so the session
        stores them as ``.jpg`` (``camera.lossy``); None: lossless frames (PNG)."""
        return None

    @property
    def response(self) -> str:
        """The camera's tone curve, recorded as ``camera.response``: "linear" (RAW-like,
        the default) or "srgb" (decoders undo it)."""
        return "linear"

    def controls(self) -> dict[str, tuple[float, float]]:
        """Settable controls and their (min, max): e.g. ``{"exposure": (lo, hi), "gain": (lo, hi)}``.

        ``exposure`` is in the device's own unit (seconds for still cameras, a driver value
        for webcams, a relative factor for the virtual rig); larger always means brighter.
        Empty when nothing can be set."""
        return {}

    def get_controls(self) -> dict[str, float]:
        """Current values of the settable controls."""
        return {}

    def set_controls(self, **values: float) -> dict[str, float]:
        """Set controls by name; return the values the device actually applied."""
        self.check_control_names(values)
        return {}

    def check_control_names(self, values: dict[str, float], settable=None) -> None:
        """Raise naming the controls in ``values`` that are not in ``settable`` (default:
        :meth:`controls`)."""
        settable = self.controls() if settable is None else settable
        unknown = [k for k in values if k not in settable]
        if unknown:
            have = ", ".join(settable) or "none"
            raise DeviceError(f"{self.name}: cannot set {', '.join(unknown)} (settable: {have})")

    def exposure_record(self) -> dict[str, Any]:
        """What ``session.json`` records of the capture settings of each view (JSON types).

        Device controls go under ``"camera"`` in the device's own units. A camera whose
        response is known in slscan's radiometric units adds a ``"sensor"`` block with
        ``exposure``, ``gain`` and ``white_level`` (the virtual rig does), which the albedo
        stage multiplies into its exposure factor."""
        return {"camera": self.get_controls()}

    def flush(self) -> None:
        """Discard frames buffered before now (called after every pattern change)."""

    def about_to_capture(self, label: str) -> None:
        """Called by the driver just before each :meth:`capture`, with what the frame is for,
        as an operator reads it (e.g. ``"view 3, frame 5 (white)"``, numbered from 1). A
        camera that someone else triggers (a watch folder) asks for the shot here; the
        default does nothing."""

    @abc.abstractmethod
    def capture(self) -> Frame:
        """Expose and read one frame, taken after this call started."""


class Lights(Device):
    """Ring lights around the camera, switched one at a time for the albedo images."""

    @property
    @abc.abstractmethod
    def count(self) -> int:
        """How many lights."""

    @abc.abstractmethod
    def switch(self, index: int, on: bool) -> None:
        """Switch light ``index`` (0-based) on or off; return once it has settled."""

    def all_off(self) -> None:
        for k in range(self.count):
            self.switch(k, False)


class NoLights(Lights):
    """A rig without ring lights (no albedo images)."""

    name = "no-lights"

    @property
    def count(self) -> int:
        return 0

    def switch(self, index: int, on: bool) -> None:
        raise DeviceError(f"{self.name}: this rig has no lights (asked for light {index})")


@dataclass(frozen=True)
class Placement:
    """Where the object is for one view.

    rig_from_object : (4, 4) mm, or None when unknown (a hand-placed object)
    pose_source : how the pose is known, e.g. "ground-truth", "turntable", or None
    turntable_deg : the angle a turntable was turned to (degrees), or None
    """

    rig_from_object: np.ndarray | None = None
    pose_source: str | None = None
    turntable_deg: float | None = None


class Stage(Device):
    """What moves the object between views: an operator, a turntable, or the virtual rig."""

    @abc.abstractmethod
    def move_to(self, view_index: int, views: int) -> Placement:
        """Bring the object into position ``view_index`` of ``views``; return once it is still."""

    def ground_truth(self):
        """The current view's :class:`slscan.capture.session.GroundTruth`, or None (real rigs)."""
        return
