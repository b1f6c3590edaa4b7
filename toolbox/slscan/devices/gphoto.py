"""Tethered still cameras (DSLR, mirrorless) as a :class:`~slscan.devices.base.Camera`,
through libgphoto2 and its Python binding python-gphoto2 (``pip install 'slscan[gphoto2]'``).

Each :meth:`GPhoto2Camera.capture` fires the shutter (``gp_camera_capture``), downloads the
file, decodes it in memory and deletes it from the camera (unless ``keep_on_camera``). Set
the camera to **JPEG only**: RAW files (NEF, CR2/CR3, ARW, RAF, DNG, ...) are refused with an
error saying so, and in RAW+JPEG mode libgphoto2 hands back only one of the two files. TIFF
and PNG are decoded too. Frames are (h, w, 3) RGB uint8 in the sensor's pixel grid (EXIF
orientation is ignored, so a camera turned on its side still gives frames of one size).

Controls: ``exposure`` is the ``shutterspeed`` setting in seconds (its choices parsed from
"1/60", "0.5", "2", '30"', "0.0100s"; "bulb" and "auto" are left out) and ``gain`` the
``iso`` setting; :meth:`GPhoto2Camera.set_controls` picks the nearest choice the camera
offers (in stops) and returns what the camera reads back: most cameras take shutter speed and
ISO only with the mode dial on M. Focus the lens by hand and switch autofocus off: a camera
that cannot focus on a dark pattern will not fire.

The image size is learnt from the first capture; asking for :attr:`GPhoto2Camera.resolution`
before that takes a test shot.

Tested against libgphoto2's virtual PTP camera (``vcamera``, shipped in the python-gphoto2
wheel's ``libgphoto2/vusb`` and switched on by the ``VCAMERADIR`` environment variable), which
answers as a "Nikon DSC D750" with a ``shutterspeed`` setting and no ``iso``. It has never
been run on a real camera.
"""

from __future__ import annotations

import concurrent.futures
import logging
import math
import re
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slscan.devices.base import Camera, DeviceError, Frame

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'slscan[gphoto2]'"
# fmt: off
RAW_SUFFIXES = frozenset((
    ".3fr", ".arw", ".cr2", ".cr3", ".crw", ".dcr", ".dng", ".erf", ".iiq", ".k25", ".kdc", ".mef",
    ".mos", ".mrw", ".nef", ".nrw", ".orf", ".pef", ".raf", ".raw", ".rw2", ".rwl", ".sr2", ".srf",
    ".srw", ".x3f",
))
# fmt: on
SHUTTER_WIDGETS = ("shutterspeed", "shutterspeed2")
ISO_WIDGETS = ("iso", "isospeed")
INFO_WIDGETS = ("shutterspeed", "iso", "f-number", "aperture", "exposurecompensation")

_FRACTION = re.compile(r"^(\d+(?:\.\d+)?)\s*/\s*(\d+(?:\.\d+)?)\s*(?:s|sec)?$")
_SECONDS = re.compile(r"^(\d+(?:\.\d+)?)\s*(?:s|sec|\")?$")
_QUOTE_DECIMAL = re.compile(r"^(\d+)\"(\d+)$")  # 0"5 = 0.5 s
_ISO = re.compile(r"^(?:iso\s*)?(\d+(?:\.\d+)?)$")


def import_gphoto2() -> Any:
    """The ``gphoto2`` module, or a :class:`DeviceError` saying how to install it."""
    try:
        import gphoto2
    except ImportError as exc:
        raise DeviceError(
            f"camera gphoto2: python-gphoto2 is not installed: {INSTALL_HINT}"
        ) from exc
    return gphoto2


def parse_shutter(text: str) -> float | None:
    """A shutter-speed choice in seconds ("1/60", "0.5", "2", '30"', '0"5', "0.0100s"), or
    None for "bulb", "auto" and anything else."""
    t = text.strip().lower()
    if m := _FRACTION.match(t):
        num, den = float(m[1]), float(m[2])
        value = num / den if den > 0 else 0.0
    elif m := _QUOTE_DECIMAL.match(t):
        value = float(f"{m[1]}.{m[2]}")
    elif m := _SECONDS.match(t):
        value = float(m[1])
    else:
        return None
    return value if value > 0 else None


def parse_iso(text: str) -> float | None:
    """An ISO choice as a number ("100", "ISO 400"), or None for "Auto", "Hi 1", ..."""
    m = _ISO.match(text.strip().lower())
    return float(m[1]) if m and float(m[1]) > 0 else None


def nearest_choice(choices: dict[str, float], value: float) -> str:
    """The choice whose value is nearest ``value`` in stops (log2), e.g. the shutter speed."""
    if value <= 0:
        return min(choices, key=choices.__getitem__)
    return min(choices, key=lambda c: abs(math.log2(choices[c] / value)))


def refuse_raw(name: str, what: str = "camera gphoto2") -> None:
    """Raise a :class:`DeviceError` telling to switch to JPEG if ``name`` is a RAW file."""
    if Path(name).suffix.lower() in RAW_SUFFIXES:
        raise DeviceError(
            f"{what}: the camera saved {name}, a RAW file; RAW is not supported: set the camera's "
            "image format (imageformat / imagequality) to JPEG only"
        )


def decode_camera_file(
    data: bytes | memoryview, name: str, what: str = "camera gphoto2"
) -> np.ndarray:
    """A file downloaded from the camera as (h, w, 3) RGB uint8 (JPEG, TIFF or PNG).

    RAW files are refused: the message tells to set the camera to JPEG. EXIF orientation is
    ignored (frames stay in the sensor's pixel grid).
    """
    refuse_raw(name, what)
    buf = np.frombuffer(data, np.uint8)
    image = (
        cv2.imdecode(buf, cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION) if buf.size else None
    )
    if image is None:
        raise DeviceError(
            f"{what}: could not decode {name} ({buf.size} bytes; expected a JPEG, TIFF or PNG)"
        )
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _in_thread(fn: Any, *args: Any) -> concurrent.futures.Future:
    """``fn(*args)`` in a daemon thread: a call that hangs in libgphoto2 can be given up on
    (see ``timeout_s``) without keeping the program from exiting."""
    future: concurrent.futures.Future = concurrent.futures.Future()

    def target() -> None:
        if future.set_running_or_notify_cancel():
            try:
                future.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller by the future
                future.set_exception(exc)

    threading.Thread(target=target, name="gphoto2", daemon=True).start()
    return future


class GPhoto2Camera(Camera):
    """A camera tethered by USB (or PTP/IP), driven through libgphoto2.

    Parameters
    ----------
    port : libgphoto2 port, e.g. ``usb:001,004`` (``gphoto2 --auto-detect`` lists them);
        by default the first camera found
    model : pick the camera whose model name contains this (case-insensitive)
    keep_on_camera : leave each shot on the camera's card (needs the camera's capture target
        set to its memory card) instead of deleting it after download
    timeout_s : the longest one camera call (capture, download) may take before it is
        reported as failed; the camera must then be switched off and on and reopened
    """

    def __init__(
        self,
        *,
        port: str | None = None,
        model: str | None = None,
        keep_on_camera: bool = False,
        timeout_s: float = 30.0,
    ) -> None:
        self._gp = import_gphoto2()
        self.name = "camera gphoto2"
        self.keep_on_camera = bool(keep_on_camera)
        self.timeout_s = float(timeout_s)
        self._stuck: concurrent.futures.Future | None = None
        self._camera: Any = None
        self._size: tuple[int, int] | None = None
        self._first_file = ""
        try:
            self._camera, self.model, self.port = self._connect(port, model)
            self.name = f"camera gphoto2 ({self.model} on {self.port})"
            self._controls = self._find_controls()
            self._info = [w for w in INFO_WIDGETS if self._widget_or_none(w) is not None]
        except BaseException:
            self.close()
            raise

    # --- opening ------------------------------------------------------------------------

    def _connect(self, port: str | None, model: str | None) -> tuple[Any, str, str]:
        gp = self._gp
        try:
            found = gp.Camera.autodetect()
            cameras = [(found.get_name(i), found.get_value(i)) for i in range(found.count())]
            autodetect = "found none"
        except gp.GPhoto2Error as exc:
            cameras, autodetect = [], f"failed: {exc}"
        if not cameras:
            camera = gp.Camera()
            try:  # libgphoto2's own search, for its reason
                self._run("opening", camera.init)
            except DeviceError as exc:
                raise DeviceError(
                    f"camera gphoto2: no camera found by libgphoto2 (autodetect on ports {self._ports()} "
                    f"{autodetect}; gp_camera_init: {exc.__cause__ or exc}). Is the camera on, connected, "
                    "in PTP/PC mode, and not held by another program (a desktop gvfs mount: "
                    "`gio mount -s gphoto2`)?"
                ) from exc
            return camera, camera.get_abilities().model, camera.get_port_info().get_path()
        chosen = [
            (m, p)
            for m, p in cameras
            if (port is None or p == port) and (model is None or model.lower() in m.lower())
        ]
        if not chosen:
            want = " and ".join(f"{k} {v!r}" for k, v in (("port", port), ("model", model)) if v)
            listed = "; ".join(f"{m} on {p}" for m, p in cameras)
            raise DeviceError(f"camera gphoto2: no camera with {want} (libgphoto2 found: {listed})")
        if len(chosen) > 1:
            log.warning(
                "camera gphoto2: %d cameras found (%s); using the first (choose with port=)",
                len(chosen),
                "; ".join(f"{m} on {p}" for m, p in chosen),
            )
        name, path = chosen[0]
        camera = gp.Camera()
        try:
            abilities = gp.CameraAbilitiesList()
            abilities.load()
            camera.set_abilities(abilities[abilities.lookup_model(name)])
            ports = gp.PortInfoList()
            ports.load()
            camera.set_port_info(ports[ports.lookup_path(path)])
        except gp.GPhoto2Error as exc:
            raise DeviceError(f"camera gphoto2 ({name} on {path}): {self._explain(exc)}") from exc
        self.name = f"camera gphoto2 ({name} on {path})"
        self._run("opening", camera.init)
        return camera, name, path

    def _ports(self) -> str:
        gp = self._gp
        try:
            ports = gp.PortInfoList()
            ports.load()
            paths = sorted({ports[i].get_path().split(":")[0] + ":" for i in range(len(ports))})
        except gp.GPhoto2Error as exc:
            return f"no ports ({exc})"
        return ", ".join(paths) or "no ports"

    def _find_controls(self) -> dict[str, tuple[str, dict[str, float]]]:
        gp = self._gp
        out: dict[str, tuple[str, dict[str, float]]] = {}
        for key, names, parse in (
            ("exposure", SHUTTER_WIDGETS, parse_shutter),
            ("gain", ISO_WIDGETS, parse_iso),
        ):
            for wname in names:
                widget = self._widget_or_none(wname)
                if widget is None or widget.get_readonly():
                    continue
                if widget.get_type() not in (gp.GP_WIDGET_RADIO, gp.GP_WIDGET_MENU):
                    continue
                texts = [widget.get_choice(i) for i in range(widget.count_choices())]
                choices = {t: v for t in texts if (v := parse(t)) is not None}
                if choices:
                    out[key] = (wname, choices)
                    break
        return out

    # --- Camera -------------------------------------------------------------------------

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the shots; the first time, before any capture, takes a test shot."""
        if self._size is None:
            log.info("%s: taking a test shot to learn the image size", self.name)
            self.capture()
        return self._size

    def controls(self) -> dict[str, tuple[float, float]]:
        """``exposure`` (s) and ``gain`` (ISO) ranges over the choices the camera offers."""
        return {key: (min(c.values()), max(c.values())) for key, (_, c) in self._controls.items()}

    def get_controls(self) -> dict[str, float]:
        out = {}
        for key, (wname, _) in self._controls.items():
            parse = parse_shutter if key == "exposure" else parse_iso
            value = parse(str(self._widget(wname).get_value()))
            if value is not None:
                out[key] = value
        return out

    def set_controls(self, **values: float) -> dict[str, float]:
        """Set the nearest shutter speed / ISO choice; return the values the camera reads back."""
        self.check_control_names(values, self._controls)
        applied = {}
        for key, value in values.items():
            wname, choices = self._controls[key]
            choice = nearest_choice(choices, float(value))
            widget = self._widget(wname)
            widget.set_value(choice)
            self._run(f"setting {wname} to {choice}", self._camera.set_single_config, wname, widget)
            now = str(self._widget(wname).get_value())
            if now != choice:
                log.warning(
                    "%s: asked for %s %s, the camera kept %s (is the mode dial on M?)",
                    self.name,
                    wname,
                    choice,
                    now,
                )
            parsed = (parse_shutter if key == "exposure" else parse_iso)(now)
            if parsed is not None:
                applied[key] = parsed
        return applied

    def capture(self) -> Frame:
        """Fire, download, decode and (unless ``keep_on_camera``) delete one shot.

        Returns (h, w, 3) RGB uint8 with ``metadata``: ``file`` (its path on the camera),
        ``exposure_s`` and the camera's exposure settings as it shows them (``shutterspeed``,
        ``iso``, ``f-number``, ... where it has them).
        """
        gp = self._gp
        path = self._run("capturing", self._camera.capture, gp.GP_CAPTURE_IMAGE)
        folder, name = path.folder, path.name
        where = f"{folder.rstrip('/')}/{name}"
        try:
            refuse_raw(name, self.name)
            cam_file = self._run(
                f"downloading {where}", self._camera.file_get, folder, name, gp.GP_FILE_TYPE_NORMAL
            )
            image = decode_camera_file(cam_file.get_data_and_size(), name, self.name)
        finally:
            if not self.keep_on_camera:
                try:
                    self._run(f"deleting {where}", self._camera.file_delete, folder, name)
                except DeviceError as exc:
                    log.warning("%s", exc)
        t = time.monotonic()
        h, w = image.shape[:2]
        if self._size is None:
            self._size, self._first_file = (w, h), where
        elif (w, h) != self._size:
            raise DeviceError(
                f"{self.name}: {where} is {w}x{h}, the first shot ({self._first_file}) was "
                f"{self._size[0]}x{self._size[1]}: keep the image size fixed during a scan"
            )
        metadata: dict[str, Any] = {"file": where}
        for wname in self._info:
            metadata[wname] = str(self._widget(wname).get_value())
        exposure = parse_shutter(metadata.get("shutterspeed", ""))
        if exposure is not None:
            metadata["exposure_s"] = exposure
        return Frame(image, t, metadata)

    def describe(self) -> dict[str, Any]:
        return {
            "kind": "gphoto2",
            "model": getattr(self, "model", None),
            "port": getattr(self, "port", None),
            "keep_on_camera": self.keep_on_camera,
            "controls": {k: w for k, (w, _) in self._controls.items()},
        }

    def close(self) -> None:
        camera, self._camera = self._camera, None
        if camera is not None:
            if self._stuck is not None and not self._stuck.done():
                log.warning(
                    "%s: a camera call is still hanging; closing without gp_camera_exit", self.name
                )
            else:
                try:
                    _in_thread(camera.exit).result(timeout=self.timeout_s)
                except (self._gp.GPhoto2Error, concurrent.futures.TimeoutError) as exc:
                    log.warning("%s: gp_camera_exit failed: %s", self.name, exc)

    # --- helpers ------------------------------------------------------------------------

    def _run(self, doing: str, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` in the camera thread, within ``timeout_s``, errors as DeviceError."""
        if self._stuck is not None and not self._stuck.done():
            raise DeviceError(
                f"{self.name}: an earlier camera call is still hanging; switch the camera "
                "off and on, and open it again"
            )
        future = _in_thread(fn, *args)
        try:
            return future.result(timeout=self.timeout_s)
        except concurrent.futures.TimeoutError:
            self._stuck = future
            raise DeviceError(
                f"{self.name}: no answer within {self.timeout_s:g} s while {doing} (autofocus hunting? "
                "focus by hand and switch autofocus off; camera asleep? switch auto power-off off)"
            ) from None
        except self._gp.GPhoto2Error as exc:
            raise DeviceError(f"{self.name}: {doing} failed: {self._explain(exc)}") from exc

    def _explain(self, exc: Exception) -> str:
        gp = self._gp
        claimed = "another program holds the camera (a desktop gvfs mount: `gio mount -s gphoto2`)"
        hints = {
            gp.GP_ERROR_IO_USB_CLAIM: claimed,
            gp.GP_ERROR_IO_USB_FIND: "unplugged or switched off?",
            gp.GP_ERROR_IO: "unplugged or switched off?",
            gp.GP_ERROR_CAMERA_BUSY: "the camera is busy (still saving the last shot?)",
            gp.GP_ERROR_MODEL_NOT_FOUND: "is the camera on, connected, and in PTP/PC mode?",
        }
        hint = hints.get(getattr(exc, "code", None))
        return f"{exc} ({hint})" if hint else str(exc)

    def _widget_or_none(self, wname: str) -> Any:
        try:
            return self._widget(wname)
        except DeviceError:  # the camera has no such setting
            return None

    def _widget(self, wname: str) -> Any:
        return self._run(f"reading {wname}", self._camera.get_single_config, wname)
