"""The albedo stage's commands, run through argparse as ``slscan`` would."""

from __future__ import annotations

import argparse
import json

import pytest
from rerun.chunk import RrdReader

from slscan.albedo.command import add_command
from slscan.albedo.lights import read_lights
from slscan.errors import SlscanError


def run(*argv: str) -> int:
    parser = argparse.ArgumentParser(prog="slscan")
    add_command(parser.add_subparsers(dest="command"))
    args = parser.parse_args([str(a) for a in argv])
    return args.func(args)


def test_capture_and_calibrate_lights(tmp_path):
    session = tmp_path / "lights-session"
    assert run("capture-lights", "--out", session, "--poses", "3", "--scale", "0.2", "--quiet") == 0
    assert (session / "light_panel.json").is_file()
    assert run("calibrate-lights", session, "--out", tmp_path / "lights.json") == 0
    lights = read_lights(tmp_path / "lights.json")
    assert len(lights.lights) == 6
    with pytest.raises(SlscanError, match="exists"):
        run("calibrate-lights", session, "--out", tmp_path / "lights.json")


def test_albedo_command(tmp_path, figurine, calibrated):
    from slscan.albedo.lights import write_lights

    session, range_maps = figurine
    write_lights(tmp_path / "lights.json", calibrated)
    out, rrd = tmp_path / "albedo", tmp_path / "albedo.rrd"
    code = run(
        "albedo",
        session.root,
        "--range-maps",
        range_maps,
        "--lights",
        tmp_path / "lights.json",
        "--out",
        out,
        "--quiet",
        "--save",
        rrd,
    )
    assert code == 0
    meta = json.loads((out / "albedo.json").read_text())
    assert [v["view"] for v in meta["views"]] == ["view_000", "view_001"]
    assert meta["lights_source"].endswith("lights.json")
    paths = {c.entity_path for c in RrdReader(rrd).stream().to_chunks()}
    assert {
        "/world/camera/image/albedo/unshaded",
        "/world/camera/image/albedo/error",
        "/world/albedo/view_001",
    } <= paths
    with pytest.raises(SlscanError, match="not empty"):
        run("albedo", session.root, "--range-maps", range_maps, "--out", out, "--quiet")
    with pytest.raises(SystemExit):
        run("albedo", session.root, "--range-maps", range_maps, "--out", out, "--normals", "bogus")
