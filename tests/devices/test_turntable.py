"""The serial turntable against a FAKE GRBL / Marlin controller on a pseudo-terminal
(tests/devices/fake_gcode.py): what it sends, how it waits, its errors, and a scan whose
turntable fails mid-way keeping its finished views for --resume. It has never met a real
controller."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("serial")

from slscan.devices.base import DeviceError, Placement, Stage  # noqa: E402
from slscan.devices.turntable import (  # noqa: E402
    SerialTurntable,
    TurntableSpec,
    parse_turntable_spec,
    turn_about_axis,
    view_angles,
)

from .fake_gcode import FakeController  # noqa: E402

FAST = {"boot_s": 0.0, "timeout_s": 2.0, "move_timeout_s": 5.0}


@pytest.mark.parametrize("text, spec", [
    ("serial:/dev/ttyUSB0", TurntableSpec("/dev/ttyUSB0", "grbl", 115200)),
    ("serial:/dev/ttyACM0:marlin", TurntableSpec("/dev/ttyACM0", "marlin", 115200)),
    ("serial:/dev/ttyUSB1:grbl:57600", TurntableSpec("/dev/ttyUSB1", "grbl", 57600)),
    ("serial:COM3:marlin:250000", TurntableSpec("COM3", "marlin", 250000)),
    ("serial:socket://rig.local:23", TurntableSpec("socket://rig.local:23", "grbl", 115200)),
    ("serial:socket://rig.local:23:marlin:9600", TurntableSpec("socket://rig.local:23", "marlin", 9600)),
    ("serial:/dev/ttyUSB0:9600", TurntableSpec("/dev/ttyUSB0", "grbl", 9600)),
])
def test_specs_parse(text, spec):
    assert parse_turntable_spec(text) == spec


def test_a_bad_spec_says_what_is_expected():
    with pytest.raises(DeviceError, match=r"expected serial:PORT\[:grbl\|marlin\]\[:BAUD\]"):
        parse_turntable_spec("usb:/dev/ttyUSB0")


def test_view_angles_full_turn_and_sweep():
    assert view_angles(4) == [0, 90, 180, 270]
    assert view_angles(5, sweep_deg=80, start_deg=-40) == [-40, -20, 0, 20, 40]


def test_grbl_turns_absolute_and_waits_for_idle():
    with FakeController("grbl", run_reports=3) as fake, SerialTurntable(fake.port, **FAST) as table:
        table.rotate_to(30)
        assert fake.position == 30
        assert fake.received[:4] == ["G90", "G90", "G0 X30.0000", "G4 P0"]
        assert fake._running == 0  # asked '?' until it reported Idle
        table.home()
        assert "$H" in fake.received and table.angle_deg == 0


def test_marlin_axis_letter_units_and_m400():
    with FakeController("marlin") as fake, \
            SerialTurntable(fake.port, firmware="marlin", axis="A", units_per_degree=2.0, **FAST) as table:
        table.rotate_to(45)
        table.home()
        assert fake.received == ["G90", "G90", "G0 A90.0000", "M400", "G28 A", "M400"]
        assert fake.position == 0


def test_no_answer_names_the_port_and_the_wait():
    with FakeController(silent=True) as fake:
        with pytest.raises(DeviceError, match=rf"turntable on {fake.port} did not answer 'G90' in 0.3 s"):
            SerialTurntable(fake.port, boot_s=0, timeout_s=0.3)


def test_an_error_reply_is_quoted_with_its_meaning():
    with FakeController(reply_to={"G0": "error:9"}) as fake, SerialTurntable(fake.port, **FAST) as table:
        with pytest.raises(DeviceError, match=rf"turntable on {fake.port} reported: error:9 \(G-code commands "
                                              "are locked out"):
            table.rotate_to(30)


def test_an_alarm_is_reported():
    with FakeController(reply_to={"$H": "ALARM:9"}) as fake, SerialTurntable(fake.port, **FAST) as table:
        with pytest.raises(DeviceError, match="reported: ALARM:9"):
            table.home()


def test_a_missing_port_is_one_clear_error(tmp_path):
    with pytest.raises(DeviceError, match=r"turntable on .*nothing: cannot open the port"):
        SerialTurntable(str(tmp_path / "nothing"), **FAST)


def test_known_axis_gives_turntable_poses():
    point, direction = np.array([10.0, 0.0, 1300.0]), np.array([0.0, -1.0, 0.0])
    with FakeController() as fake, SerialTurntable(fake.port, axis_point=point, axis_direction=direction,
                                                   **FAST) as table:
        placement = table.move_to(1, 4)
    assert placement.pose_source == "turntable" and placement.turntable_deg == 90
    np.testing.assert_allclose(placement.rig_from_object, turn_about_axis(point, direction, 90))
    moved = placement.rig_from_object @ np.array([*point, 1.0])
    np.testing.assert_allclose(moved[:3], point)  # points on the axis stay


class TurntableTwin(Stage):
    """FAKE: the serial turntable drives the controller; the virtual rig's turntable turns the
    simulated object to the same view, so the camera sees something."""

    name = "turntable twin (fake)"

    def __init__(self, table: SerialTurntable, world) -> None:
        self.table, self.world = table, world

    def move_to(self, view_index: int, views: int) -> Placement:
        placement = self.table.move_to(view_index, views)
        self.world.stage.move_to(view_index, views)
        return placement


def test_a_turntable_failing_mid_scan_keeps_the_finished_views_for_resume(tmp_path):
    from slscan.capture.driver import ScanDevices, scan
    from slscan.capture.session import load_session
    from slscan.devices.base import NoLights
    from slscan.virtual.device import VirtualCaptureConfig, scan_plan, virtual_devices

    config = VirtualCaptureConfig(camera_scale=0.2, projector_scale=0.2, levels=2, lit_images=False)
    out = tmp_path / "s"
    with FakeController(fail_after_moves=1) as fake:
        world = virtual_devices(config)
        table = SerialTurntable(fake.port, **FAST)
        devices = ScanDevices(world.projector, world.camera, NoLights(), TurntableTwin(table, world))
        with pytest.raises(DeviceError, match=r"view_001.*reported: error:9.*1 finished view\(s\) kept.*--resume"):
            scan(devices, scan_plan(config, world.rig), out, views=3)
        table.close()
    assert [v.name for v in load_session(out).views] == ["view_000"]
    with FakeController() as fake:
        world = virtual_devices(config)
        with SerialTurntable(fake.port, **FAST) as table:
            devices = ScanDevices(world.projector, world.camera, NoLights(), TurntableTwin(table, world))
            result = scan(devices, scan_plan(config, world.rig), out, views=3, resume=True)
        assert [ln for ln in fake.received if ln.startswith("G0")] == ["G0 X120.0000", "G0 X240.0000"]
    assert [v.turntable_deg for v in load_session(out).views] == [0, 120, 240]
    assert result.resumed_views == 1


def test_stage_command_homes_turns_and_zeroes(capsys):
    from slscan.cli import main

    with FakeController() as fake:
        code = main(["stage", f"serial:{fake.port}", "--home", "--rotate", "30", "--zero", "--stage-axis", "A",
                     "--stage-boot", "0"])
        assert code == 0
        assert [ln for ln in fake.received if ln != "G90"] == ["$H", "G4 P0", "G0 A30.0000", "G4 P0", "G92 A0"]
    err = capsys.readouterr().err
    assert "turned turntable on" in err and "30 degrees" in err


def test_stage_command_without_an_answer_is_one_line_and_non_zero(capsys):
    from slscan.cli import main

    with FakeController(silent=True) as fake:
        code = main(["stage", f"serial:{fake.port}:marlin", "--rotate", "10", "--stage-timeout", "0.2",
                     "--stage-boot", "0"])
    err = capsys.readouterr().err
    assert code == 2
    assert f"turntable on {fake.port} did not answer 'G90' in 0.2 s" in err and "marlin controller" in err


def test_scan_stage_options_are_checked(tmp_path, capsys):
    from slscan.cli import main

    assert main(["scan", "--camera", "virtual", "--stage", "serial:/dev/ttyUSB0", "--out", str(tmp_path / "a")]) == 2
    assert "the virtual rig turns its own turntable" in capsys.readouterr().err
    assert main(["scan", "--camera", "virtual", "--stage", "usb:3", "--out", str(tmp_path / "b")]) == 2
    assert "expected manual, virtual or serial:PORT" in capsys.readouterr().err


def test_open_stage_reads_the_turntable_axis_file(tmp_path):
    import argparse

    from slscan.calibrate.turntable import TurntableAxis, save_turntable_axis
    from slscan.capture.command import add_stage_arguments, open_stage

    axis = TurntableAxis(np.array([0.0, 0.0, 1300.0]), np.array([0.0, 1.0, 0.0]), 1.0, 0.0, 0.0, 5)
    save_turntable_axis(axis, tmp_path / "turntable.json")
    parser = argparse.ArgumentParser()
    add_stage_arguments(parser)
    parser.add_argument("--turntable-axis")
    with FakeController() as fake:
        args = parser.parse_args(["--stage", f"serial:{fake.port}", "--stage-boot", "0",
                                  "--turntable-axis", str(tmp_path / "turntable.json")])
        with open_stage(args) as table:
            placement = table.move_to(2, 8)
    np.testing.assert_allclose(placement.rig_from_object, axis.pose(90.0))
    assert placement.pose_source == "turntable" and placement.turntable_deg == 90
