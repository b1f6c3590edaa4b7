"""The slscan command: help and one-line errors for bad input (the demo: test_demo.py)."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pytest

import slscan
from slscan.capture.session import load_session
from slscan.cli import build_parser, main


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


# --- the parser: every command's options without the stages' imports -----------------------

HEAVY = ("rerun", "scipy", "open3d")
"""Packages that building the parser must not import (about 1 s CPU between them)."""
STAGE_MODULES = (
    "slscan.virtual",  # the virtual rig (its ray caster, scenes, effects)
    "slscan.fuse",
    "slscan.calibrate.pipeline",  # SciPy's optimisers through calibrate.planes
    "slscan.calibrate.camera",
    "slscan.decode.hybrid",
    "slscan.decode.pipeline",
    "slscan.albedo.unshade",
    "slscan.register.multiview",
    "slscan.texture.pipeline",
    "slscan.viewer.layouts",
    "slscan.viewer.log",
)
"""Stage and logging modules the commands import when they run, not when their options are built."""


def _modules_after(code: str) -> set[str]:
    """Every name in ``sys.modules`` after running ``code`` in a fresh interpreter."""
    toolbox = str(Path(slscan.__file__).parent.parent)
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint(' '.join(sorted(sys.modules)))"],
        env=dict(os.environ, PYTHONPATH=toolbox), check=True, capture_output=True, text=True,
    ).stdout
    return set(out.splitlines()[-1].split())


def _loaded(modules: set[str], names: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules if any(m == n or m.startswith(n + ".") for n in names))


def test_building_the_parser_imports_no_stage_code():
    loaded = _modules_after(
        "from slscan.cli import build_parser\n"
        "commands = next(a for a in build_parser()._actions if a.dest == 'command').choices\n"
        "assert len(commands) > 15, commands"
    )
    assert {"slscan.cli", "slscan.viewer.recording", "slscan.calibrate.command"} <= loaded
    assert not _loaded(loaded, HEAVY), f"building the parser imports {_loaded(loaded, HEAVY)[:10]}"
    assert not _loaded(loaded, STAGE_MODULES), f"building the parser imports {_loaded(loaded, STAGE_MODULES)}"


def test_the_import_check_sees_the_heavy_modules():
    """Guard against a vacuous pass: what a command imports when it runs is seen."""
    loaded = _modules_after("import slscan.calibrate.pipeline, slscan.viewer.layouts")
    assert "scipy" in loaded and "rerun" in loaded and "slscan.decode.hybrid" in loaded


def test_a_command_without_a_recording_needs_no_rerun(tmp_path):
    """``open_recording`` with no sink yields None without importing Rerun; with one, it does."""
    code = ("from slscan.viewer.recording import open_recording\n"
            "with open_recording() as rec:\n    assert rec is None\n")
    assert "rerun" not in _modules_after(code)
    saved = tmp_path / "x.rrd"
    assert "rerun" in _modules_after(code + f"with open_recording(save={str(saved)!r}) as rec:\n"
                                            "    assert rec is not None\n")
    assert saved.stat().st_size > 0


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next(a for a in parser._actions if a.dest == "command").choices


COMMANDS = sorted(_commands(build_parser()))


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: slscan {command} ") and "options:" in out
    assert callable(build_parser().parse_args(_minimal_args(command)).func)


def _minimal_args(command: str) -> list[str]:
    """``command`` with its required arguments filled in (parsed, never run)."""
    parser = _commands(build_parser())[command]
    argv = [command]
    for action in parser._actions:
        if not action.option_strings and action.nargs != 0 and action.dest != "help":
            argv.append("x")
        elif action.required:
            argv += [action.option_strings[0], "1" if action.type in (int, float) else "x"]
    return argv


def _option(command: str, option: str) -> argparse.Action:
    parser = _commands(build_parser())[command]
    return next(a for a in parser._actions if option in a.option_strings)


def _config_types():
    from slscan.albedo.photometric import AlbedoConfig
    from slscan.calibrate.pipeline import CalibrationConfig
    from slscan.calibrate.target import Board
    from slscan.decode.pipeline import DecodeConfig

    return {"decode": DecodeConfig, "calibrate": CalibrationConfig, "board": Board, "albedo": AlbedoConfig}


@pytest.mark.parametrize("command,option,config,field", [
    ("decode", "--method", "decode", "method"),
    ("decode", "--estimator", "decode", "estimator"),
    ("decode", "--gray-threshold", "decode", "gray_threshold"),
    ("calibrate", "--method", "calibrate", "method"),
    ("calibrate", "--planes-pattern", "calibrate", "planes_pattern"),
    ("calibrate", "--camera-distortion", "calibrate", "camera_distortion"),
    ("calibrate", "--projector-distortion", "calibrate", "projector_distortion"),
    ("calibrate", "--correspondences", "calibrate", "correspondences"),
    ("calibrate", "--target", "board", "kind"),
    ("albedo", "--normals", "albedo", "normals"),
])
def test_option_choices_are_what_the_stage_accepts(command, option, config, field):
    """The parser's choices and default, built without the stage's modules, are exactly the
    values the stage's config accepts and its default."""
    import dataclasses

    from slscan.errors import SlscanError

    action, config_type = _option(command, option), _config_types()[config]
    default = next(f for f in dataclasses.fields(config_type) if f.name == field).default
    assert action.default == default
    for choice in action.choices:
        assert getattr(config_type(**{field: choice}), field) == choice
    with pytest.raises(SlscanError):
        config_type(**{field: "not-" + action.choices[0]})


def test_option_defaults_are_the_stages_defaults():
    from slscan.albedo.photometric import AlbedoConfig
    from slscan.calibrate.target import Board

    assert _option("calibrate", "--dictionary").default == Board().dictionary
    assert _option("albedo", "--specular").default == AlbedoConfig().specular
    assert set(_option("albedo", "--specular").choices) >= {AlbedoConfig().specular}
    assert _option("albedo", "--min-lights").default == AlbedoConfig().min_lights


def test_run_help_lists_every_recipe_stage(capsys):
    from slscan.recipe.stages import SUMMARIES, stages

    assert list(SUMMARIES) == list(stages())
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    out = capsys.readouterr().out
    for stage in stages().values():
        assert f"  {stage.name:<10} {stage.summary}" in out


def test_python_dash_m_slscan_runs_the_cli():
    """``python -m slscan`` is the ``slscan`` script (e.g. where the script is not on PATH)."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "slscan", "--version"], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("slscan ")
