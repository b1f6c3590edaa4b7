"""No viewer to reach: ``slscan view``, ``--spawn`` and ``--connect`` say so in one line and
exit non-zero, at once (never a hang, never a silent exit 0 that dropped the data).

Each runs ``slscan`` in a child process with no ``DISPLAY`` (and no Wayland), under a
timeout; ``--spawn`` and ``--connect`` aim at a free port, where no viewer listens.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from slscan.errors import SlscanError
from slscan.viewer import recording
from slscan.viewer.log import log_capture
from slscan.viewer.recording import open_recording

TIMEOUT_S = 90  # a hang fails the test instead of stalling the suite


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _no_display_env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")}
    env["XDG_RUNTIME_DIR"] = str(tmp_path)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(Path(recording.__file__).parents[2]),
                                                     env.get("PYTHONPATH")) if p)
    return env


def _slscan(args: list[str], tmp_path: Path, *, port: int | None = None) -> tuple[int, str, float]:
    """Run ``slscan ARGS`` with no display (the spawned viewer, if any, on ``port``):
    (exit status, stderr, seconds)."""
    code = "import sys; from slscan.cli import main; sys.exit(main(sys.argv[1:]))"
    if port is not None:  # --spawn's port, where nothing listens
        code = f"import slscan.viewer.recording as r; r.DEFAULT_PORT = {port}; " + code
    start = time.monotonic()
    run = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                         timeout=TIMEOUT_S, env=_no_display_env(tmp_path), cwd=tmp_path)
    return run.returncode, run.stderr, time.monotonic() - start


def _one_line(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    assert len(lines) >= 1, "no message"
    text = " ".join(ln.strip() for ln in lines)  # rich wraps a long line at the terminal width
    assert "Traceback" not in text, stderr
    return text


@pytest.fixture
def small_rrd(tmp_path) -> Path:
    path = tmp_path / "small.rrd"
    with open_recording(save=path) as rec:
        log_capture(rec, np.zeros((8, 8), np.uint8), view_index=0, frame_index=0, label="white")
    return path


def test_view_of_a_recording_without_a_display_fails_in_one_line(small_rrd, tmp_path):
    code, stderr, _ = _slscan(["view", str(small_rrd)], tmp_path)
    assert code != 0
    message = _one_line(stderr)
    assert "small.rrd" in message and "display" in message


def test_view_of_a_folder_spawns_no_viewer_without_a_display(tmp_path):
    folder = tmp_path / "maps"
    folder.mkdir()
    (folder / "range_maps.json").write_text(json.dumps({"views": []}))
    code, stderr, seconds = _slscan(["view", str(folder)], tmp_path, port=_free_port())
    assert code != 0
    message = _one_line(stderr)
    assert "--spawn" in message and "display" in message
    assert seconds < TIMEOUT_S


def test_spawn_without_a_display_raises_before_logging(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_SOCKET", raising=False)
    monkeypatch.setattr(recording, "DEFAULT_PORT", _free_port())
    monkeypatch.setattr(recording.sys, "platform", "linux")
    with pytest.raises(SlscanError, match="no display"):
        with open_recording(spawn=True):
            pytest.fail("the block ran without a viewer")


def test_spawn_uses_a_viewer_already_listening_even_without_a_display(monkeypatch):
    """Nothing to start: the viewer (or server) on the port gets the data."""
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        assert recording._spawn_viewer(None, port) == f"rerun+http://127.0.0.1:{port}/proxy"


CAPTURE = ["capture", "--views", "1", "--scale", "0.1", "--quiet"]
"""A small virtual capture: it opens its recording before it captures anything."""


def test_capture_with_connect_to_nothing_fails_in_one_line_and_writes_nothing(tmp_path):
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    out = tmp_path / "session"
    code, stderr, _ = _slscan([*CAPTURE, "--out", str(out), "--connect", url], tmp_path)
    assert code != 0
    message = _one_line(stderr)
    assert url in message and "no Rerun viewer is listening" in message
    assert not out.exists()


def test_capture_with_spawn_and_no_display_fails_in_one_line_and_writes_nothing(tmp_path):
    out = tmp_path / "session"
    code, stderr, seconds = _slscan([*CAPTURE, "--out", str(out), "--spawn"], tmp_path, port=_free_port())
    assert code != 0
    message = _one_line(stderr)
    assert "--spawn" in message and "display" in message
    assert not out.exists()


def test_open_recording_refuses_a_url_where_nothing_listens():
    url = f"rerun+http://127.0.0.1:{_free_port()}/proxy"
    with pytest.raises(SlscanError, match="no Rerun viewer is listening"):
        with open_recording(connect=url):
            pytest.fail("the block ran with nowhere to send the data")
