"""ManualLights and ManualStage: what the operator is asked, in order, through an injected
prompt; the default prompt refuses to wait without a terminal."""

from __future__ import annotations

import io

import pytest

from slscan.devices.base import DeviceError, Lights, Placement
from slscan.devices.lights import ManualLights, ManualStage, terminal_prompt


def test_lights_prompt_in_the_drivers_order():
    asked: list[str] = []
    lights = ManualLights(3, prompt=asked.append)
    assert isinstance(lights, Lights) and lights.count == 3
    lights.all_off()  # the driver at the start of a view
    for k in range(3):  # then light by light, as slscan.capture.driver does
        if k > 0:
            lights.switch(k - 1, False)
        lights.switch(k, True)
    lights.switch(2, False)
    lights.all_off()  # already all off: nothing to ask
    assert asked == [
        "Switch all 3 lights OFF, then press Enter",
        "Switch light 1 of 3 ON, then press Enter",
        "Switch light 1 of 3 OFF, then press Enter",
        "Switch light 2 of 3 ON, then press Enter",
        "Switch light 2 of 3 OFF, then press Enter",
        "Switch light 3 of 3 ON, then press Enter",
        "Switch light 3 of 3 OFF, then press Enter",
    ]
    assert lights.describe() == {"kind": "manual-lights", "count": 3}


def test_lights_ask_before_the_state_is_known_and_check_the_index():
    asked: list[str] = []
    lights = ManualLights(2, prompt=asked.append)
    lights.switch(1, False)  # state unknown: ask even to switch off
    lights.switch(1, False)  # known off now
    assert asked == ["Switch light 2 of 2 OFF, then press Enter"]
    with pytest.raises(DeviceError, match="no light 2 .there are 2, numbered from 0"):
        lights.switch(2, True)
    ManualLights(0, prompt=asked.append).all_off()
    assert len(asked) == 1


def test_stage_prompts_for_each_view():
    asked: list[str] = []
    stage = ManualStage(prompt=asked.append)
    placements = [stage.move_to(v, 3) for v in range(3)]
    assert asked == [f"Place the object for view {v} of 3, then press Enter" for v in (1, 2, 3)]
    assert all(p == Placement() and p.rig_from_object is None for p in placements)
    with pytest.raises(DeviceError, match="no view 3 of 3"):
        stage.move_to(3, 3)


def test_default_prompt_needs_a_terminal(monkeypatch):
    monkeypatch.setattr("sys.stdin", io.StringIO("\n"))  # not a TTY
    lights, stage = ManualLights(2), ManualStage()  # making them does not need one
    with pytest.raises(DeviceError, match="manual lights need an operator at a terminal"):
        lights.all_off()
    with pytest.raises(DeviceError, match="the manual stage needs an operator at a terminal"):
        stage.move_to(0, 2)


class _FakeTTY(io.StringIO):
    """FAKE: a terminal the operator has already typed into."""

    def isatty(self) -> bool:
        return True


def test_default_prompt_waits_for_enter(monkeypatch, capsys):
    monkeypatch.setattr("sys.stdin", _FakeTTY("\n"))
    ManualStage().move_to(1, 2)
    assert "Place the object for view 2 of 2, then press Enter" in capsys.readouterr().out
    with pytest.raises(DeviceError, match="terminal closed"):  # EOF: nothing more typed
        terminal_prompt("Switch light 1 of 1 ON")
