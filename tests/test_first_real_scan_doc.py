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
    # the free-hand, projector-lit chain on the virtual rig's scan: its outputs are virtual-*
    return "--camera virtual" in text or any(w.startswith("virtual-") for w in words[1:2])


def test_the_doc_has_virtual_and_stage_commands():
    runnable = [w for w in _commands() if _runnable(w)]
    assert {w[0] for w in runnable} == {"scan", "stage", "turntable-axis", "decode", "albedo", "register",
                                        "fuse", "simplify", "texture"}
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
    # no ring lights, no poses: a textured model coloured by the projector, every view registered
    import json

    import numpy as np

    session = json.loads(Path("virtual-scan/session.json").read_text())
    assert session["device"]["lights"]["kind"] == "no-lights"
    assert not any(i["kind"] == "lit" for v in session["views"] for i in v["images"])
    registration = json.loads(Path("virtual-aligned/registration.json").read_text())
    assert not registration["left_out"] and len(registration["poses"]) == 8
    truth = {v["name"]: np.linalg.inv(np.asarray(v["rig_from_object"], float)) for v in session["views"]}
    poses = {k: np.asarray(v, float) for k, v in registration["poses"].items()}
    gauge = truth["view_000"] @ np.linalg.inv(poses["view_000"])  # the object frame is the registration's
    for name, pose in poses.items():
        error = gauge @ pose @ np.linalg.inv(truth[name])
        angle = np.degrees(np.arccos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
        assert angle < 2.0, f"{name} registered {angle:.2f} degrees off"
    texture = json.loads(Path("virtual-texture/texture.json").read_text())
    assert texture["source"]["light"] == "projector" and texture["metrics"]["observed_share"] > 0.7
