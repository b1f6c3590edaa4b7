"""FAKE stepper controllers for the turntable tests: a thread on a pseudo-terminal
(``os.openpty``) answering G-code the way GRBL 1.1 or Marlin 2 do. Not real firmware: it
answers what :mod:`slscan.devices.turntable` sends, with motion simulated as a number of
``Run`` status reports, and faults on demand (silence, an error reply, a fault after N moves)."""

from __future__ import annotations

import os
import re
import select
import threading
import tty


class FakeController:
    """FAKE GRBL / Marlin controller on a pty; :attr:`port` is the device to open.

    firmware : {"grbl", "marlin"}
    silent : never answer (a wrong port, a dead board)
    reply_to : {command prefix: reply} answers instead of ``ok`` (e.g. ``{"G0": "error:9"}``)
    fail_after_moves : after this many ``G0``/``G1`` moves every later move gets ``fault``
    run_reports : how many ``?`` status queries report ``Run`` after a move (GRBL)
    """

    def __init__(self, firmware: str = "grbl", *, silent: bool = False, reply_to: dict | None = None,
                 fail_after_moves: int | None = None, fault: str = "error:9", run_reports: int = 2) -> None:
        self.firmware, self.silent, self.reply_to = firmware, silent, dict(reply_to or {})
        self.fail_after_moves, self.fault, self.run_reports = fail_after_moves, fault, run_reports
        self.received: list[str] = []
        self.position = 0.0
        self.moves = 0
        self._running = 0
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def __enter__(self) -> FakeController:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def _send(self, text: str) -> None:
        os.write(self._master, (text + "\r\n").encode())

    def _serve(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.02)
            if not ready:
                continue
            try:
                data = os.read(self._master, 1024)
            except OSError:
                return
            if self.silent:
                continue
            if self.firmware == "grbl" and b"?" in data:  # real-time status query, no newline
                data = data.replace(b"?", b"")
                state = "Run" if self._running > 0 else "Idle"
                self._running = max(0, self._running - 1)
                self._send(f"<{state}|MPos:{self.position:.3f},0.000,0.000|FS:0,0>")
            buffer += data
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                line = raw.decode().strip()
                if line:
                    self.received.append(line)
                    self._answer(line)

    def _answer(self, line: str) -> None:
        for prefix, reply in self.reply_to.items():
            if line.startswith(prefix):
                self._send(reply)
                return
        move = re.match(r"G[01] ([A-Z])(-?[\d.]+)", line)
        if move:
            self.moves += 1
            if self.fail_after_moves is not None and self.moves > self.fail_after_moves:
                self._send(self.fault)
                return
            self.position = float(move.group(2))
            self._running = self.run_reports
        elif line in ("$H",) or line.startswith("G28") or line.startswith("G92"):
            self.position = 0.0
        elif line == "M400" and self.firmware == "marlin":
            self._send("echo:busy: processing")
        self._send("ok")
