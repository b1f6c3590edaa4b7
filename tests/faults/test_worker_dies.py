"""A worker that dies mid-brick (SIGKILL, as the kernel's OOM killer does): fusion and
simplification in bricks run the lost bricks once more and give the clean run's mesh; a
second death is one line, with no output and no scratch left. On Dask, the cluster itself
reschedules a killed worker's task.

The kill is real (``slscan`` runs as a subprocess; its helper process is found with psutil
and sent SIGKILL); it is timed from what the run shows: fusion's progress (bricks done),
simplification's finished brick files in its scratch folder.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import sphere_scans

from slscan.fuse import Mesh, read_mesh, write_mesh

psutil = pytest.importorskip("psutil")

TOOLBOX = Path(__file__).parents[2] / "toolbox"
FUSE = ["--voxel", "0.6", "--brick", "9.6"]  # about 60 bricks of 2 blocks a side
SIMPLIFY = ["--faces", "10000", "--bricks", "64"]  # 56 non-empty bricks of a 250k-face sphere
DIED = "a worker process died (out of memory?)"
RETRIED = "a worker process died; running its"
TIMEOUT = 240  # s, for a run on a loaded machine


@pytest.fixture(scope="module")
def aligned(tmp_path_factory) -> Path:
    """Six orthographic range scans (80 x 80 px of 0.6 mm) of a 20 mm sphere, an aligned set."""
    from slscan.register.meshlab import write_scan_project

    scans, poses = sphere_scans(shape=(80, 80), pixel=0.6, resolution=40)
    return write_scan_project(tmp_path_factory.mktemp("aligned") / "aligned", scans, poses).parent


@pytest.fixture(scope="module")
def fused(aligned, tmp_path_factory) -> Path:
    """The aligned set fused in bricks on two local processes, nothing killed."""
    folder = tmp_path_factory.mktemp("clean")
    rc, err, _ = Run(["fuse", str(aligned), *FUSE, "--workers", "2", "--out", "clean.ply"], folder).wait()
    assert rc == 0, err
    return folder / "clean.ply"


@pytest.fixture(scope="module")
def big_mesh(tmp_path_factory) -> Path:
    m = o3d.geometry.TriangleMesh.create_sphere(50.0, resolution=250)
    return write_mesh(Mesh(np.asarray(m.vertices), np.asarray(m.triangles)),
                      tmp_path_factory.mktemp("mesh") / "big.ply")


class Run:
    """``slscan ARGS`` as a subprocess, its stderr read as it comes (progress bars drawn as on
    a terminal, so that the bricks done can be read from them)."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TOOLBOX), os.environ.get("PYTHONPATH", "")]),
               "FORCE_COLOR": "1", "COLUMNS": "200"}
        self.t0 = time.monotonic()
        self.proc = subprocess.Popen([sys.executable, "-m", "slscan", *args], cwd=cwd, env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        self._err: list[bytes] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for chunk in iter(lambda: self.proc.stderr.read1(4096), b""):
            self._err.append(chunk)

    @property
    def err(self) -> str:
        return re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", b"".join(self._err).decode(errors="replace"))

    def bricks_done(self) -> int:
        """The fusion progress bar's count (``12/71``), 0 before it shows."""
        return max((int(a) for a, b in re.findall(r"(\d+)/(\d+)", self.err) if int(b) > 6), default=0)

    def wait(self) -> tuple[int, str, float]:
        try:
            rc = self.proc.wait(TIMEOUT)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise
        self._reader.join(10)
        return rc, self.err, time.monotonic() - self.t0

    def helpers(self) -> list:
        """The run's helper processes (multiprocessing's spawned workers, not its resource tracker)."""
        try:
            children = psutil.Process(self.proc.pid).children(recursive=True)
        except psutil.NoSuchProcess:
            return []
        out = []
        for child in children:
            try:
                if "spawn_main" in " ".join(child.cmdline()):
                    out.append(child)
            except psutil.NoSuchProcess:
                pass
        return out

    def kill_helper(self, ready: Callable[[], bool], *, spare: tuple[int, ...] = ()) -> int:
        """SIGKILL a helper (none of ``spare``) once ``ready()``; its pid. Fails if the run ends first."""
        deadline = time.monotonic() + TIMEOUT
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                pytest.fail(f"the run ended before its helper could be killed:\n{self.err}")
            if ready():
                for helper in self.helpers():
                    if helper.pid not in spare:
                        try:
                            helper.send_signal(signal.SIGKILL)
                        except psutil.NoSuchProcess:
                            continue
                        return helper.pid
            time.sleep(0.005)
        pytest.fail("no helper process to kill")


def _same(a: Path, b: Path) -> None:
    ma, mb = read_mesh(a), read_mesh(b)
    np.testing.assert_array_equal(ma.faces, mb.faces)
    np.testing.assert_array_equal(ma.vertices, mb.vertices)


def _left(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def test_fuse_a_helper_killed_mid_brick_its_bricks_run_again(aligned, fused, tmp_path):
    run = Run(["fuse", str(aligned), *FUSE, "--workers", "2", "--out", "killed.ply"], tmp_path)
    run.kill_helper(lambda: run.bricks_done() >= 1)  # bricks are flowing: the helper is on its next one
    rc, err, _ = run.wait()
    assert rc == 0, err
    assert RETRIED in err and "Traceback" not in err
    _same(tmp_path / "killed.ply", fused)


def test_fuse_a_helper_killed_twice_is_one_line_and_no_output(aligned, tmp_path):
    run = Run(["fuse", str(aligned), *FUSE, "--workers", "2", "--out", "out.ply"], tmp_path)
    first = run.kill_helper(lambda: run.bricks_done() >= 1)
    run.kill_helper(lambda: True, spare=(first,))  # the retry's fresh helper, as soon as it is there
    rc, err, _ = run.wait()
    assert rc != 0
    lines = [line for line in err.splitlines() if DIED in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert _left(tmp_path) == []  # no mesh, no .mlp, nothing half-written


def _brick_done(folder: Path) -> Callable[[], bool]:
    """True once a brick's simplified file is in the scratch folder (bricks are under way)."""
    return lambda: any(folder.glob(".bricks-*/brick*.npz"))


def test_simplify_a_helper_killed_mid_brick_its_bricks_run_again(big_mesh, tmp_path):
    rc, err, _ = Run(["simplify", str(big_mesh), "--out", "clean.ply", *SIMPLIFY, "--workers", "2"],
                     tmp_path).wait()
    assert rc == 0, err
    run = Run(["simplify", str(big_mesh), "--out", "killed.ply", *SIMPLIFY, "--workers", "2"], tmp_path)
    run.kill_helper(_brick_done(tmp_path))
    rc, err, _ = run.wait()
    assert rc == 0, err
    assert RETRIED in err and "Traceback" not in err
    _same(tmp_path / "killed.ply", tmp_path / "clean.ply")
    assert _left(tmp_path) == ["clean.mlp", "clean.ply", "killed.mlp", "killed.ply"]  # no scratch left


def test_simplify_a_helper_killed_twice_is_one_line_and_no_output(big_mesh, tmp_path):
    run = Run(["simplify", str(big_mesh), "--out", "out.ply", *SIMPLIFY, "--workers", "2"], tmp_path)
    first = run.kill_helper(_brick_done(tmp_path))
    run.kill_helper(lambda: True, spare=(first,))
    rc, err, _ = run.wait()
    assert rc != 0
    lines = [line for line in err.splitlines() if DIED in line]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert _left(tmp_path) == []  # no mesh, no .mlp, no .bricks-* scratch


def test_dask_reschedules_a_killed_workers_brick(aligned, fused, tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster.scheduler_address) as client:
        args = ["fuse", str(aligned), *FUSE, "--scheduler", cluster.scheduler_address]
        rc, err, clean_s = Run([*args, "--out", "clean.ply"], tmp_path).wait()
        assert rc == 0, err
        pids = client.run(os.getpid)  # worker address -> its process
        run = Run([*args, "--out", "killed.ply"], tmp_path)
        killed = None
        deadline = time.monotonic() + TIMEOUT
        while killed is None and time.monotonic() < deadline and run.proc.poll() is None:
            busy = [w for w, keys in client.processing().items()
                    if any(str(k).startswith("_fuse_brick") for k in keys)]
            if run.bricks_done() >= 1 and busy:
                killed = pids[busy[0]]
                os.kill(killed, signal.SIGKILL)  # mid-brick: the scheduler shows it processing one
            time.sleep(0.01)
        assert killed is not None, run.err
        rc, err, killed_s = run.wait()
        assert rc == 0, err
    _same(tmp_path / "killed.ply", tmp_path / "clean.ply")
    _same(tmp_path / "clean.ply", fused)
    print(f"\nDask fuse, {FUSE}: clean {clean_s:.1f} s, a worker killed mid-brick {killed_s:.1f} s")
