"""docs/first-real-scan.md runs as written: every virtual-rig command in its code blocks
(in order, in one folder, so the turntable-axis fit reads the board session captured
before it), and every `slscan stage` command against a FAKE GRBL controller on a
pseudo-terminal standing in for /dev/ttyUSB0. Commands for real projectors and cameras
are only parsed (tests/test_docs_commands.py)."""

from __future__ import annotations

import shlex
import time
from pathlib import Path

import pytest

from slscan.cli import main

DOC = Path(__file__).parents[1] / "docs" / "first-real-scan.md"


def _commands() -> list[list[str]]:
    from tests.test_docs_commands import _commands_in_line, _fenced_blocks

    return [list(words) for _, line in _fenced_blocks(DOC.read_text()) for words in _commands_in_line(line)]


def _runnable(words: list[str]) -> bool:
    text = " ".join(words)
    if words[0] == "stage":
        return True
    if words[0] == "turntable-axis":
        return "--calibration" not in text  # the real rig's needs rig.json from a real board
    return "--camera virtual" in text


def test_the_doc_has_virtual_and_stage_commands():
    runnable = [w for w in _commands() if _runnable(w)]
    assert {w[0] for w in runnable} == {"scan", "stage", "turntable-axis"}
    assert len(runnable) >= 7


def test_every_virtual_rig_and_stage_command_runs(tmp_path, monkeypatch, capsys):
    pytest.importorskip("serial")
    from slscan.devices import turntable

    from tests.devices.fake_gcode import FakeController

    class _NoBoot:  # the fake controller does not reboot: no 2 s wait after opening it
        monotonic = staticmethod(time.monotonic)

        @staticmethod
        def sleep(seconds: float) -> None:
            time.sleep(min(seconds, 0.01))

    monkeypatch.setattr(turntable, "time", _NoBoot)
    monkeypatch.chdir(tmp_path)
    with FakeController() as fake:
        for words in filter(_runnable, _commands()):
            words = [w.replace("/dev/ttyUSB0", fake.port) for w in words]
            code = main(words)
            assert code == 0, f"slscan {shlex.join(words)} exited {code}: {capsys.readouterr().err[-2000:]}"
        assert "$H" in fake.received and "G0 X30.0000" in fake.received and "G92 X0" in fake.received
    assert Path("turntable.json").is_file() and Path("first/session.json").is_file()
