"""The slscan command: help and one-line errors for bad input (the demo: test_demo.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from slscan.capture.session import load_session
from slscan.cli import main


def test_help_lists_the_commands(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for command in ("demo", "capture", "decode", "calibrate", "albedo", "register", "fuse", "simplify", "texture", "run",
                    "regress", "view", "patterns", "import", "info", "layouts"):
        assert command in out


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
        (["simplify", "{tmp}/cloud.ply", "--out", "{tmp}/file.txt"], "file.txt: exists (pass --overwrite"),
        (["fuse", "{tmp}/nothing", "--out", "{tmp}/file.txt"], "file.txt: exists (pass --overwrite"),
        (["demo", "--out", "{tmp}/x", "--scale", "3"], "--scale must be in (0, 2]"),
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
