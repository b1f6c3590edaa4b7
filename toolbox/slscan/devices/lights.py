"""Hand-operated lights and stage: the operator is asked, at the terminal, to switch each
ring light and to place the object for each view.

:class:`ManualLights` and :class:`ManualStage` prompt through a callable that shows a
message and returns once the operator has done it (by default ``input()``, which needs an
operator at a terminal: without one they raise :class:`~slscan.devices.base.DeviceError`
when they would ask, not when they are made). Messages number lights and views from 1, as
an operator counts them; the methods take 0-based indices like every other device.

Adding a relay board
--------------------
Lights switched by a computer are a :class:`~slscan.devices.base.Lights` subclass with
``count`` and ``switch``; ``switch`` returns once the light has settled. For example a USB
serial relay board that takes one byte command per relay, with pyserial (``pip install
pyserial``; not a dependency of slscan)::

    import time

    import serial  # pyserial

    from slscan.devices.base import DeviceError, Lights


    class SerialRelayLights(Lights):
        name = "serial-relay-lights"

        def __init__(self, port: str = "/dev/ttyUSB0", count: int = 6, settle_s: float = 0.2):
            try:
                self._serial = serial.Serial(port, 9600, timeout=1.0)
            except serial.SerialException as exc:
                raise DeviceError(f"{self.name}: cannot open {port} ({exc})") from exc
            self._count, self.settle_s = count, settle_s

        @property
        def count(self) -> int:
            return self._count

        def switch(self, index: int, on: bool) -> None:
            if not 0 <= index < self._count:
                raise DeviceError(f"{self.name}: no light {index} (the board has {self._count})")
            # the command bytes are the board's own: see its manual
            self._serial.write(bytes([0xA0, index + 1, int(on), 0xA1 + index + int(on)]))
            self._serial.flush()
            time.sleep(self.settle_s)  # the lamp reaches full brightness

        def close(self) -> None:
            if self._serial.is_open:
                self.all_off()
                self._serial.close()

        def describe(self) -> dict:
            return {"kind": self.name, "port": self._serial.port, "count": self._count}
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from functools import partial
from typing import Any

from slscan.devices.base import DeviceError, Lights, Placement, Stage

Prompt = Callable[[str], None]


def terminal_prompt(message: str, *, who: str = "manual devices need") -> None:
    """Show ``message`` and wait for Enter; a :class:`DeviceError` when stdin is no terminal
    (``who`` starts its message, e.g. "manual lights need")."""
    stdin = sys.stdin
    if stdin is None or not stdin.isatty():
        raise DeviceError(f"{who} an operator at a terminal (was going to ask: {message!r})")
    try:
        input(f"{message} ")
    except EOFError as exc:
        raise DeviceError(f"the operator's terminal closed (was asking: {message!r})") from exc


class ManualLights(Lights):
    """Ring lights the operator switches by hand when asked.

    Parameters
    ----------
    count : how many lights
    prompt : shows a message and returns once the operator has done it (default: ``input()``
        at the terminal)

    It remembers what it last asked for, so a light already known to be off is not asked
    about again, and :meth:`all_off` asks once for all of them.
    """

    name = "manual-lights"

    def __init__(self, count: int = 6, *, prompt: Prompt | None = None) -> None:
        if count < 0:
            raise DeviceError(f"{self.name}: count must be >= 0, got {count}")
        self._count = int(count)
        self._prompt = prompt or partial(terminal_prompt, who="manual lights need")
        self._on: set[int] | None = None  # None: unknown until the first all_off

    @property
    def count(self) -> int:
        return self._count

    def switch(self, index: int, on: bool) -> None:
        if not 0 <= index < self._count:
            raise DeviceError(
                f"{self.name}: no light {index} (there are {self._count}, numbered from 0)"
            )
        if self._on is not None and (index in self._on) == on:
            return
        self._prompt(
            f"Switch light {index + 1} of {self._count} {'ON' if on else 'OFF'}, then press Enter"
        )
        if self._on is None:
            self._on = set()
        if on:
            self._on.add(index)
        else:
            self._on.discard(index)

    def all_off(self) -> None:
        if self._count == 0 or self._on == set():
            return
        self._prompt(f"Switch all {self._count} lights OFF, then press Enter")
        self._on = set()

    def describe(self) -> dict[str, Any]:
        return {"kind": self.name, "count": self._count}


class ManualStage(Stage):
    """The operator places the object for each view when asked; the pose is unknown.

    Parameters
    ----------
    prompt : shows a message and returns once the operator has done it (default: ``input()``
        at the terminal)
    """

    name = "manual-stage"

    def __init__(self, *, prompt: Prompt | None = None) -> None:
        self._prompt = prompt or partial(terminal_prompt, who="the manual stage needs")

    def move_to(self, view_index: int, views: int) -> Placement:
        if not 0 <= view_index < views:
            raise DeviceError(f"{self.name}: no view {view_index} of {views}")
        self._prompt(f"Place the object for view {view_index + 1} of {views}, then press Enter")
        return Placement()

    def describe(self) -> dict[str, Any]:
        return {"kind": self.name}
