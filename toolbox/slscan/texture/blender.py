"""Blender from slscan: find a Blender, import a texture result with the add-on, render a preview.

Blender runs in a subprocess: either the ``bpy`` module in its own environment (the repo's
``.venv-blender``, made by ``bash .ci/setup``: bpy 5.0.1 needs CPython 3.11 and numpy < 2,
slscan numpy >= 2) or a ``blender`` executable. The subprocess runs
``toolbox/slscan_blender/batch.py``, which registers the add-on ``slscan_blender`` and
drives it exactly as a user's File > Import would.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from slscan.errors import SlscanError
from slscan.fsio import atomic_output_file

log = logging.getLogger(__name__)

ENV_VAR = "SLSCAN_BLENDER_PYTHON"
TOOLBOX = Path(__file__).resolve().parents[2]  # toolbox/, holding slscan_blender
REPO_BLENDER_PYTHON = TOOLBOX.parent / ".venv-blender" / "bin" / "python"
BATCH_SCRIPT = TOOLBOX / "slscan_blender" / "batch.py"
STDERR_TAIL = 3000  # characters of Blender's output quoted in an error


def _prefix_for(executable: str) -> list[str]:
    """Command prefix for a Python with bpy, or for a Blender executable (name starts 'blender')."""
    if Path(executable).name.lower().startswith("blender"):
        # --python-exit-code: a script that raises makes Blender exit non-zero
        return [executable, "-b", "--factory-startup", "--python-exit-code", "1", "--python"]
    return [executable]


def find_blender() -> list[str] | None:
    """Command prefix that runs a Python script with bpy, or None when there is no Blender.

    Looked for in order: the environment variable ``SLSCAN_BLENDER_PYTHON`` (a Python with
    bpy installed, or a Blender executable), the repo's ``.venv-blender/bin/python``, a
    ``blender`` executable on PATH (run as ``blender -b --factory-startup --python``). The
    script path follows the prefix, then ``--`` and the script's arguments.
    """
    env = os.environ.get(ENV_VAR)
    if env:
        found = shutil.which(env)
        if found is None:
            raise SlscanError(f"{ENV_VAR}={env}: no such executable")
        return _prefix_for(found)
    if REPO_BLENDER_PYTHON.is_file() and os.access(REPO_BLENDER_PYTHON, os.X_OK):
        return [str(REPO_BLENDER_PYTHON)]
    found = shutil.which("blender")
    return _prefix_for(found) if found else None


def _require_blender() -> list[str]:
    prefix = find_blender()
    if prefix is None:
        raise SlscanError(
            f"no Blender found: run 'bash .ci/setup' (makes .venv-blender with bpy), set {ENV_VAR} "
            "to a Python with bpy, or put 'blender' on PATH"
        )
    return prefix


def run_blender_script(
    script: str | os.PathLike, args: Sequence[str], *, timeout: float = 300.0, what: str = "Blender"
) -> subprocess.CompletedProcess:
    """Run ``script`` with bpy (see :func:`find_blender`), ``toolbox/`` importable.

    Raises :class:`SlscanError` quoting the tail of Blender's output when the script fails
    or runs past ``timeout`` seconds.
    """
    cmd = [*_require_blender(), str(script), "--", *map(str, args)]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(TOOLBOX)  # not the caller's: its numpy 2 must not shadow bpy's numpy
    env.pop("PYTHONHOME", None)
    env["PYTHONNOUSERSITE"] = "1"
    log.debug("running %s", " ".join(cmd))
    try:
        proc = subprocess.run(
            cmd,
            check=False,
            env=env,
            capture_output=True,
            text=True,
            errors="replace",
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired:
        raise SlscanError(f"{what}: gave up after {timeout:.0f} s ({' '.join(cmd)})") from None
    except OSError as exc:
        raise SlscanError(f"{what}: cannot run {cmd[0]} ({exc.strerror})") from None
    if proc.returncode != 0:
        tail = (proc.stderr.strip() or proc.stdout.strip())[-STDERR_TAIL:]
        raise SlscanError(f"{what} failed (exit status {proc.returncode}):\n{tail}")
    return proc


def _texture_json(result_dir: str | os.PathLike) -> Path:
    path = Path(result_dir)
    if path.is_dir():
        path = path / "texture.json"
    if not path.is_file():
        raise SlscanError(f"{path}: texture result manifest not found")
    return path.resolve()


def import_result(result_dir: str | os.PathLike, *, timeout: float = 300.0) -> dict[str, Any]:
    """Import a texture result with the Blender add-on; return what the scene then holds.

    result_dir : the texture stage's output folder (or its ``texture.json``)

    Returns a JSON-able dict: ``blender`` (version), ``objects`` (name, type, collections),
    ``meshes`` (vertex, face and triangle counts, UV layers, materials with
    ``image_texture`` and ``image`` ``{name, size: [w, h]}``), ``cameras`` (per view:
    ``matrix_world`` (4x4, metres, Blender frame), ``lens`` (mm), ``sensor_width``,
    ``shift_x``, ``shift_y``, ``resolution`` [w, h] px, ``pixel_aspect``,
    ``background_image``), ``scene_camera`` and ``resolution``.
    """
    texture_json = _texture_json(result_dir)
    with tempfile.TemporaryDirectory(prefix="slscan-blender-") as tmp:
        out = Path(tmp) / "summary.json"
        run_blender_script(
            BATCH_SCRIPT,
            ["summary", texture_json, out],
            timeout=timeout,
            what=f"Blender import of {texture_json}",
        )
        return json.loads(out.read_text())


def render_preview(
    result_dir: str | os.PathLike,
    out_png: str | os.PathLike,
    *,
    size: tuple[int, int] = (640, 480),
    samples: int = 16,
    timeout: float = 600.0,
) -> Path:
    """Render a preview PNG of a texture result in Blender (Cycles, CPU).

    The result is imported through the add-on, lit by a key sun and a grey world, and seen
    from a 3/4 view that fits the model's bounding sphere: from the first scanner view's
    side, turned 30° and raised 20°.

    size : (width, height) px of the PNG
    samples : Cycles samples per pixel (no denoising)

    Returns ``out_png``, written atomically (8-bit RGB).
    """
    texture_json = _texture_json(result_dir)
    width, height = (int(s) for s in size)
    if width <= 0 or height <= 0 or samples <= 0:
        raise SlscanError(f"preview: size and samples must be positive, got {size}, {samples}")
    out_png = Path(out_png)
    with atomic_output_file(out_png) as tmp:
        run_blender_script(
            BATCH_SCRIPT,
            [
                "preview",
                texture_json,
                tmp,
                "--width",
                width,
                "--height",
                height,
                "--samples",
                samples,
            ],
            timeout=timeout,
            what=f"Blender preview of {texture_json}",
        )
    return out_png
