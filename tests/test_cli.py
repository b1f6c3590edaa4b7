"""The slscan command: help, the demo at reduced size, and one-line errors for bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from slscan.capture.session import load_session
from slscan.cli import main
from slscan.decode.rangemap import read_ply


def test_help_lists_the_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for command in ("demo", "capture", "decode", "calibrate", "albedo", "register", "fuse", "simplify", "texture", "run",
                    "regress", "view", "patterns", "import", "info", "layouts"):
        assert command in out


def test_demo_at_reduced_size_ends_in_a_textured_model(tmp_path, capsys):
    from slscan.texture.export import glb_summary

    out, rrd = tmp_path / "demo", tmp_path / "demo.rrd"
    assert main(["demo", "--out", str(out), "--scale", "0.25", "--quiet", "--save", str(rrd)]) == 0
    glb = glb_summary(out / "textured" / "model.glb")
    assert glb["faces"] > 10_000 and glb["has_uv"] and glb["texture_size"] is not None
    session = load_session(out / "capture")
    assert len(session.views) == 8
    view = session.views[0]
    assert len(view.pattern_images()) == 2 + 7 and len(view.lit_images()) == 6
    assert rrd.stat().st_size > 10_000
    range_map = read_ply(out / "range_maps" / "view_000.ply")
    assert len(range_map.faces) > 1000
    assert main(["info", str(out / "capture")]) == 0
    assert "view_000" in capsys.readouterr().out
    # decoding again from the command line gives the same range map
    assert main(["decode", str(out / "capture"), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    again = read_ply(tmp_path / "again" / "view_000.ply")
    np.testing.assert_array_equal(again.faces, range_map.faces)
    # trimming the line ends: fewer vertices, and the setting is recorded
    trimmed = tmp_path / "trimmed"
    assert main(["decode", str(out / "capture"), "--out", str(trimmed), "--quiet", "--trim-line-ends", "1"]) == 0
    assert len(read_ply(trimmed / "view_000.ply").vertices) < len(range_map.vertices)
    assert json.loads((trimmed / "range_maps.json").read_text())["config"]["trim_line_ends"] == 1
    # slscan view logs a result folder (here to a file instead of a viewer)
    for result in (out / "capture", out / "range_maps"):
        rrd = tmp_path / f"{result.name}.rrd"
        assert main(["view", str(result), "--save", str(rrd)]) == 0
        assert rrd.stat().st_size > 10_000


def test_capture_and_patterns_commands(tmp_path):
    assert main(["capture", "--scene", "tile", "--patterns", "gray", "--no-lit", "--scale", "0.2",
                 "--out", str(tmp_path / "tile"), "--quiet"]) == 0
    assert len(load_session(tmp_path / "tile").views[0].images) == 2 + 2 * 8  # 205 px: 8 bits
    assert main(["patterns", "--out", str(tmp_path / "pat"), "--family", "both"]) == 0
    assert (tmp_path / "pat" / "patterns.json").is_file()


@pytest.mark.parametrize(
    "args,message",
    [
        (["capture", "--scene", "statue.3ds", "--out", "{tmp}/x"], "unknown mesh format"),
        (["capture", "--scene", "{tmp}/cloud.ply", "--out", "{tmp}/x"], "no faces"),
        (["demo", "--out", "{tmp}/file.txt/x", "--scale", "0.2"], "cannot write"),
        (["demo", "--out", "{tmp}/full", "--scale", "0.2"], "not empty"),
        (["info", "{tmp}/nothing"], "not found"),
        (["decode", "{tmp}/nothing", "--out", "{tmp}/x"], "not found"),
    ],
)
def test_bad_input_gives_one_line_and_a_non_zero_exit(tmp_path, args, message):
    (tmp_path / "file.txt").write_text("x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.png").write_text("x")
    (tmp_path / "cloud.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    )
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args] + ["--quiet"] * (args[0] not in ("info", "decode"))
    proc = subprocess.run([sys.executable, "-m", "slscan.cli", *argv], capture_output=True, text=True, check=False)
    assert proc.returncode == 2, proc.stderr
    err = proc.stderr.strip()
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()
    assert (tmp_path / "full" / "keep.png").exists()
