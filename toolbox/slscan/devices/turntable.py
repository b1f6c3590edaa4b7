"""A motorised turntable driven by a stepper controller that speaks G-code over a serial
port: GRBL (Arduino + CNC shield) or Marlin (3D-printer boards), through pyserial
(``pip install 'slscan[serial]'``).

``slscan scan --stage serial:/dev/ttyUSB0[:grbl|marlin][:BAUD]`` turns the table between
views; ``slscan stage serial:... --home`` / ``--rotate 30`` drives it for setting up.

How it talks (one command per line, each answered by ``ok``, or by ``error:N`` (GRBL) /
``Error:...`` (Marlin), which is raised as a :class:`~slscan.devices.base.DeviceError`
quoting the controller, e.g. "turntable on /dev/ttyUSB0 reported: error:9 (...)"):

- absolute moves: ``G90`` then ``G0 <AXIS><units>``, the axis letter (``X`` by default; ``A``
  on 4-axis builds) and the units per degree configurable: the firmware's steps-per-unit
  (GRBL ``$100``, Marlin ``M92``) should make one unit one degree (the default) or one
  turn ``360 / units_per_degree`` units;
- waiting for the motion to end: GRBL ``G4 P0`` (answered once the planner is empty), then
  the ``?`` status report until it says ``Idle``; Marlin ``M400`` (answered once moves end);
- homing: GRBL ``$H``, Marlin ``G28 <AXIS>``; setting the current angle as zero: ``G92``;
- every wait has a timeout: an unanswered command names the port and the seconds waited.

The controller reboots when the port opens (the Arduino's DTR reset), so :class:`SerialTurntable`
waits ``boot_s`` and then checks that it answers. Tested against a fake controller on a
pseudo-terminal (``tests/devices/test_turntable.py``); it has not met a real one yet.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from slscan.devices.base import DeviceError, Placement, Stage

log = logging.getLogger(__name__)

FIRMWARES = ("grbl", "marlin")
DEFAULT_BAUD = 115200

GRBL_ERRORS = {
    1: "G-code words consist of a letter and a value; letter was not found",
    2: "missing the expected G-code word value or numeric value format is not valid",
    3: "'$' system command was not recognized or supported",
    8: "'$' command only valid when Idle",
    9: "G-code commands are locked out during alarm or jog state: home (--home) or unlock ($X)",
    15: "jog target exceeds machine travel",
    20: "unsupported or invalid g-code command found in block (is the axis letter one the firmware has?)",
    22: "feed rate has not yet been set or is undefined",
}


@dataclass(frozen=True)
class TurntableSpec:
    """``serial:PORT[:grbl|marlin][:BAUD]`` parsed."""

    port: str
    firmware: str = "grbl"
    baud: int = DEFAULT_BAUD


def parse_turntable_spec(text: str) -> TurntableSpec:
    """``"serial:/dev/ttyUSB0:marlin:250000"`` → ``TurntableSpec("/dev/ttyUSB0", "marlin", 250000)``.

    The port is ``/dev/ttyUSB0``, ``COM3``, or a pyserial URL such as ``socket://host:23``
    (whose baud rate, if any, follows a firmware name: ``socket://host:23:grbl:115200``)."""
    kind, sep, rest = text.partition(":")
    if kind.strip().lower() != "serial" or not sep or not rest:
        raise DeviceError(f"stage {text!r}: expected serial:PORT[:grbl|marlin][:BAUD], e.g. serial:/dev/ttyUSB0")
    parts = rest.split(":")
    firmware, baud = "grbl", DEFAULT_BAUD
    url = "://" in rest  # socket://host:23: a number after the host is its port, not a baud rate
    if len(parts) > 2 and parts[-1].isdigit() and parts[-2].lower() in FIRMWARES:
        baud, firmware = int(parts[-1]), parts[-2].lower()
        parts = parts[:-2]
    elif len(parts) > 1 and parts[-1].lower() in FIRMWARES:
        firmware = parts.pop().lower()
    elif len(parts) > 1 and parts[-1].isdigit() and not url:
        baud = int(parts.pop())
    port = ":".join(parts)
    if baud <= 0:
        raise DeviceError(f"stage {text!r}: the baud rate must be positive")
    return TurntableSpec(port, firmware, baud)


def turn_about_axis(point: np.ndarray, direction: np.ndarray, angle_deg: float) -> np.ndarray:
    """(4, 4) rigid motion turning ``angle_deg`` degrees (right hand) about the line through
    ``point`` (3,) mm along the unit ``direction`` (3,)."""
    from slscan.rig import rotation_about_axis

    m = np.eye(4)
    r = rotation_about_axis(np.asarray(direction, float), math.radians(angle_deg))
    m[:3, :3] = r
    m[:3, 3] = np.asarray(point, float) - r @ np.asarray(point, float)
    return m


def view_angles(views: int, *, sweep_deg: float = 360.0, start_deg: float = 0.0) -> list[float]:
    """The turntable angle (degrees) of each of ``views`` views: a full turn (``sweep_deg``
    360) in equal steps without repeating the start; a partial sweep from ``start_deg`` to
    ``start_deg + sweep_deg`` including both ends (e.g. a board turned -40..40)."""
    if views < 1:
        raise DeviceError(f"views must be at least 1, got {views}")
    if not (math.isfinite(sweep_deg) and 0 < abs(sweep_deg) <= 360):
        raise DeviceError(f"the turntable sweep must be in (0, 360] degrees, got {sweep_deg}")
    if abs(sweep_deg) == 360 or views == 1:
        return [start_deg + sweep_deg * v / views for v in range(views)]
    return [start_deg + sweep_deg * v / (views - 1) for v in range(views)]


class SerialTurntable(Stage):
    """A turntable on a GRBL or Marlin controller (see the module docstring).

    Parameters
    ----------
    port : serial port or pyserial URL (``/dev/ttyUSB0``, ``COM3``, ``socket://...``)
    firmware : {"grbl", "marlin"}
    baud : bits per second (GRBL 115200; Marlin often 115200 or 250000)
    axis : the G-code axis letter the table's stepper is wired to ("X", "A", ...)
    units_per_degree : G-code units per degree of table rotation (1: the firmware's
        steps-per-unit is set so that a unit is a degree)
    timeout_s : how long a command may wait for its answer (s)
    move_timeout_s : how long homing or a move may take to finish (s)
    boot_s : wait after opening the port before talking (the controller reboots)
    sweep_deg, start_deg : the views' angles (:func:`view_angles`)
    axis_point, axis_direction : the table's rotation axis in the rig frame (mm; a point
        (3,) on it and a unit direction (3,) that a positive angle turns right-handed about),
        from :mod:`slscan.calibrate.turntable`; with them each view records its pose
        (``rig_from_object``, object frame = the rig frame at angle ``start_deg``)
    home : home the table when opened
    feed : optional feed rate (units/min) sent with moves (``G1 ... F``) instead of ``G0``
    """

    name = "serial-turntable"

    def __init__(
        self,
        port: str,
        *,
        firmware: str = "grbl",
        baud: int = DEFAULT_BAUD,
        axis: str = "X",
        units_per_degree: float = 1.0,
        timeout_s: float = 5.0,
        move_timeout_s: float = 120.0,
        boot_s: float = 2.0,
        sweep_deg: float = 360.0,
        start_deg: float = 0.0,
        axis_point: np.ndarray | None = None,
        axis_direction: np.ndarray | None = None,
        home: bool = False,
        feed: float | None = None,
    ) -> None:
        firmware = firmware.lower()
        self.port, self.firmware, self.baud = port, firmware, int(baud)
        self.name = f"turntable on {port}"
        if firmware not in FIRMWARES:
            raise DeviceError(f"{self.name}: unknown firmware {firmware!r} (expected {' or '.join(FIRMWARES)})")
        axis = axis.upper()
        if len(axis) != 1 or axis not in "XYZABCUVW":
            raise DeviceError(f"{self.name}: the axis must be one G-code axis letter (X, Y, Z, A, B, C), got {axis!r}")
        if not (math.isfinite(units_per_degree) and units_per_degree != 0):
            raise DeviceError(f"{self.name}: units per degree must be a non-zero number, got {units_per_degree}")
        self.axis, self.units_per_degree = axis, float(units_per_degree)
        self.timeout_s, self.move_timeout_s, self.feed = float(timeout_s), float(move_timeout_s), feed
        self.sweep_deg, self.start_deg = float(sweep_deg), float(start_deg)
        view_angles(1, sweep_deg=self.sweep_deg)  # checks the sweep
        if (axis_point is None) != (axis_direction is None):
            raise DeviceError(f"{self.name}: give both the axis point and its direction, or neither")
        self.axis_point = None if axis_point is None else np.asarray(axis_point, float).reshape(3)
        self.axis_direction = None
        if axis_direction is not None:
            d = np.asarray(axis_direction, float).reshape(3)
            self.axis_direction = d / np.linalg.norm(d)
        self.angle_deg: float | None = None
        try:
            import serial  # pyserial
        except ImportError as exc:
            raise DeviceError(f"{self.name}: pyserial is not installed (pip install 'slscan[serial]')") from exc
        self._serial_error = serial.SerialException
        try:
            self._link = serial.serial_for_url(port, baudrate=self.baud, timeout=0.05, write_timeout=self.timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceError(f"{self.name}: cannot open the port ({exc})") from exc
        try:
            if boot_s > 0:
                time.sleep(boot_s)
            self._buffer = b""
            self.command("G90", what="answering")
            if home:
                self.home()
        except BaseException:
            self.close()
            raise

    # --- talking ------------------------------------------------------------------------

    def _readline(self, deadline: float) -> str | None:
        """One line from the controller, or None at ``deadline``."""
        while True:
            nl = self._buffer.find(b"\n")
            if nl >= 0:
                line, self._buffer = self._buffer[:nl], self._buffer[nl + 1:]
                return line.decode("ascii", "replace").strip()
            if time.monotonic() >= deadline:
                return None
            try:
                chunk = self._link.read(max(1, self._link.in_waiting))
            except (self._serial_error, OSError) as exc:
                raise DeviceError(f"{self.name}: the connection failed ({exc}; unplugged?)") from exc
            self._buffer += chunk

    def _write(self, data: bytes) -> None:
        try:
            self._link.reset_input_buffer()
            self._buffer = b""
            self._link.write(data)
            self._link.flush()
        except (self._serial_error, OSError) as exc:
            raise DeviceError(f"{self.name}: cannot send {data!r} ({exc}; unplugged?)") from exc

    def _reported(self, line: str, sent: str) -> str | None:
        low = line.lower()
        if low.startswith("error"):
            text = line
            if self.firmware == "grbl" and low.startswith("error:") and line[6:].strip().isdigit():
                meaning = GRBL_ERRORS.get(int(line[6:].strip()))
                text = f"{line} ({meaning})" if meaning else line
            return f"{self.name} reported: {text} (after {sent!r})"
        if low.startswith("alarm"):
            return (f"{self.name} reported: {line} (after {sent!r}; a limit switch or homing failed: check the "
                    "table, then --home)")
        if low.startswith("!!"):
            return f"{self.name} reported: {line} (after {sent!r}; the firmware halted: reset it)"
        return None

    def command(self, line: str, *, timeout_s: float | None = None, what: str | None = None) -> list[str]:
        """Send one G-code line and wait for its ``ok``; return the lines before it.

        An ``error``/``ALARM`` answer raises quoting it; no answer within ``timeout_s``
        (default :attr:`timeout_s`) raises naming the port and the wait. Marlin's
        ``busy:`` lines (a long move in progress) restart the wait."""
        wait = self.timeout_s if timeout_s is None else timeout_s
        self._write(f"{line}\n".encode("ascii"))
        deadline = time.monotonic() + wait
        lines: list[str] = []
        while True:
            answer = self._readline(deadline)
            if answer is None:
                doing = f" ({what})" if what else ""
                raise DeviceError(f"{self.name} did not answer {line!r} in {wait:g} s{doing}: is it a "
                                  f"{self.firmware} controller at {self.baud} baud, powered and connected?")
            if not answer:
                continue
            if answer == "ok" or answer.startswith("ok "):
                return lines
            reported = self._reported(answer, line)
            if reported:
                raise DeviceError(reported)
            if "busy:" in answer.lower():  # Marlin: "echo:busy: processing"
                deadline = time.monotonic() + wait
                continue
            lines.append(answer)

    def status(self, *, timeout_s: float | None = None) -> str:
        """GRBL's ``?`` status report, e.g. ``<Idle|MPos:30.000,0.000,0.000|FS:0,0>``."""
        wait = self.timeout_s if timeout_s is None else timeout_s
        self._write(b"?")
        deadline = time.monotonic() + wait
        while True:
            answer = self._readline(deadline)
            if answer is None:
                raise DeviceError(f"{self.name} did not answer the status query '?' in {wait:g} s")
            if answer.startswith("<"):
                return answer
            reported = self._reported(answer, "?")
            if reported:
                raise DeviceError(reported)

    def wait_until_still(self, doing: str) -> None:
        """Return once the table has stopped (GRBL: ``G4 P0`` then ``Idle``; Marlin ``M400``)."""
        deadline = time.monotonic() + self.move_timeout_s
        if self.firmware == "marlin":
            self.command("M400", timeout_s=self.move_timeout_s, what=doing)
            return
        self.command("G4 P0", timeout_s=self.move_timeout_s, what=doing)
        while True:
            state = self.status()
            if state.startswith("<Idle"):
                return
            if state.startswith("<Alarm"):
                raise DeviceError(f"{self.name} reported {state} while {doing}")
            if time.monotonic() >= deadline:
                raise DeviceError(f"{self.name} did not finish {doing} in {self.move_timeout_s:g} s "
                                  f"(last status {state})")
            time.sleep(0.05)

    # --- moving -------------------------------------------------------------------------

    def home(self) -> None:
        """Home the table on its switch (GRBL ``$H``, Marlin ``G28 <axis>``); the angle is then 0."""
        if self.firmware == "grbl":
            self.command("$H", timeout_s=self.move_timeout_s, what="homing")
        else:
            self.command(f"G28 {self.axis}", timeout_s=self.move_timeout_s, what="homing")
        self.wait_until_still("homing")
        self.angle_deg = 0.0

    def set_zero(self) -> None:
        """Take the table's current angle as 0 degrees (``G92 <axis>0``)."""
        self.command(f"G92 {self.axis}0")
        self.angle_deg = 0.0

    def rotate_to(self, angle_deg: float) -> None:
        """Turn to ``angle_deg`` degrees (absolute, the controller's zero) and wait until still."""
        if not math.isfinite(angle_deg):
            raise DeviceError(f"{self.name}: cannot turn to {angle_deg} degrees")
        units = angle_deg * self.units_per_degree
        move = f"G0 {self.axis}{units:.4f}" if self.feed is None else f"G1 {self.axis}{units:.4f} F{self.feed:g}"
        doing = f"turning to {angle_deg:g} degrees"
        self.command("G90", what=doing)
        self.command(move, what=doing)
        self.wait_until_still(doing)
        self.angle_deg = float(angle_deg)

    # --- Stage --------------------------------------------------------------------------

    def move_to(self, view_index: int, views: int) -> Placement:
        angles = view_angles(views, sweep_deg=self.sweep_deg, start_deg=self.start_deg)
        if not 0 <= view_index < views:
            raise DeviceError(f"{self.name}: no view {view_index} of {views}")
        angle = angles[view_index]
        self.rotate_to(angle)
        if self.axis_point is None:
            return Placement(turntable_deg=angle)
        pose = turn_about_axis(self.axis_point, self.axis_direction, angle - self.start_deg)
        return Placement(pose, "turntable", turntable_deg=angle)

    def describe(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "kind": "serial-turntable", "port": self.port,
            "firmware": self.firmware, "baud": self.baud, "axis": self.axis,
            "units_per_degree": self.units_per_degree, "sweep_deg": self.sweep_deg, "start_deg": self.start_deg,
        }
        if self.axis_point is not None:
            d["axis_point_mm"] = self.axis_point.tolist()
            d["axis_direction"] = self.axis_direction.tolist()
        return d

    def close(self) -> None:
        link = getattr(self, "_link", None)
        if link is not None:
            try:
                link.close()
            except (self._serial_error, OSError):
                pass
            self._link = None
