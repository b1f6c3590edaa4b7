"""Registration's pairwise alignments in this process, on 2 local helper processes, and on a
2-worker Dask cluster: wall, CPU, worker memory and the same poses.

    PYTHONPATH=toolbox .venv/bin/python benchmarks/register_scale.py [--cases bunny,figurine]
        [--figurine-views 8] [--figurine-pixels 96]

Cases:

- ``bunny``: the 10 Stanford bunny scans (``shared/data/stanford_bunny``) from bun.conf's
  poses: multi-scale ICP per candidate pair;
- ``bunny-free``: the same without poses (feature hypotheses + verification per pair, all
  45 pairs: slow);
- ``figurine``: the virtual rig's figurine from ``--figurine-views`` sides (as in
  ``tests/register/test_freehand.py``), written as range-scan PLYs and registered free-hand.

Modes: ``in-process`` (``register_scans`` without an executor); ``2 local`` (``Executor(
workers=2)``: this process and one spawned helper take pairs, the helper's start-up
included); ``dask 2`` (a ``distributed.LocalCluster`` of 2 single-thread worker processes,
started before the clock: a campaign's cluster is up already). The scans go to the workers
as file paths; each worker loads a scan once.

Columns: wall seconds of ``register_scans``; CPU seconds of this process and every process
under it (helpers, Dask workers) over the call; the largest resident memory any worker
reached and this process's (MiB, sampled every 0.1 s, imports included); the largest difference of any pose entry from the in-process result (mm for
translations; 0 means bit for bit).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parent.parent
BUNNY = ROOT.parent / "shared" / "data" / "stanford_bunny"
if not BUNNY.is_dir():
    BUNNY = Path("/work/shared/data/stanford_bunny")


class Sampler:
    """CPU seconds of this process and its descendants, and their peak RSS, while running."""

    def __init__(self) -> None:
        self.me = psutil.Process()
        self.cpu: dict[int, float] = {}
        self.peak: dict[int, int] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> None:
        self.own = max(getattr(self, "own", 0), self.me.memory_info().rss)
        for p in self.me.children(recursive=True):
            try:
                t = p.cpu_times()
                self.cpu[p.pid] = t.user + t.system
                self.peak[p.pid] = max(self.peak.get(p.pid, 0), p.memory_info().rss)
            except psutil.Error:
                pass

    def _run(self) -> None:
        while not self._stop.is_set():
            self._sample()
            time.sleep(0.1)

    def __enter__(self) -> "Sampler":
        self._sample()
        self.before = dict(self.cpu)
        t = self.me.cpu_times()
        self.mine = t.user + t.system
        self.peak, self.own = {}, 0
        self.t0 = time.perf_counter()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.wall = time.perf_counter() - self.t0
        self._sample()
        self._stop.set()
        self._thread.join()
        t = self.me.cpu_times()
        self.total_cpu = (t.user + t.system - self.mine) + sum(
            c - self.before.get(pid, 0.0) for pid, c in self.cpu.items())


def bunny(free: bool):
    from slscan.register.rangescan import load_stanford_dir

    scans, poses = load_stanford_dir(BUNNY, conf="bun.conf")
    return scans, None if free else poses


def figurine(views: int, pixels: int, folder: Path):
    sys.path.insert(0, str(ROOT / "tests"))
    from synthetic_poses import looking_from

    from slscan.register.rangescan import load_range_scan, raycasting_scene, render_range_scan, write_range_scan
    from slscan.virtual.scenes import builtin_object

    scene = builtin_object(detail=0.5)
    v = np.asarray(scene.vertices, float)
    mesh = raycasting_scene(v - (v.min(axis=0) + v.max(axis=0)) / 2, np.asarray(scene.triangles))
    scans = []
    for k in range(views):
        a = 2 * np.pi * k / views
        scan = render_range_scan(None, None, looking_from([np.sin(a), -0.35, np.cos(a)], 700.0), shape=(pixels, pixels),
                                 focal=1.6 * pixels, name=f"v{k}", scene=mesh, noise=0.1, rng=np.random.default_rng(k))
        scans.append(load_range_scan(write_range_scan(scan, folder / f"v{k}.ply")))
    return scans, None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="bunny,figurine")
    parser.add_argument("--figurine-views", type=int, default=8)
    parser.add_argument("--figurine-pixels", type=int, default=96)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    warnings.simplefilter("ignore")

    from distributed import LocalCluster

    from slscan import executor as ex
    from slscan.register.multiview import register_scans

    rows = []
    with tempfile.TemporaryDirectory() as tmp, \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                         silence_logs=logging.ERROR) as cluster:
        for case in args.cases.split(","):
            if case in ("bunny", "bunny-free"):
                scans, poses = bunny(case == "bunny-free")
            elif case == "figurine":
                scans, poses = figurine(args.figurine_views, args.figurine_pixels, Path(tmp))
            else:
                raise SystemExit(f"unknown case {case!r}")
            baseline = None
            for mode, executor in (("in-process", None), ("2 local", ex.Executor(workers=2)),
                                   ("dask 2", ex.Executor(scheduler=cluster.scheduler_address))):
                ex.shutdown()  # each local run starts its helper, as a CLI run does
                with Sampler() as s:
                    result = register_scans(scans, initial_poses=poses, executor=executor)
                baseline = baseline or result
                diff = max(float(np.abs(result.poses[k] - baseline.poses[k]).max()) for k in baseline.poses) \
                    if set(result.poses) == set(baseline.poses) else float("nan")
                workers = list(s.peak.values())
                rows.append((case, len(scans), mode, s.wall, s.total_cpu, s.own / 2**20,
                             max(workers) / 2**20 if workers and executor else float("nan"),
                             len(result.poses), diff))
                print(f"  {case} {mode}: {s.wall:.1f} s", file=sys.stderr, flush=True)
    print(f"\n{'case':<10} {'scans':>5} {'mode':<11} {'wall s':>7} {'CPU s':>7} {'worker MiB':>10} "
          f"{'caller MiB':>10} {'aligned':>7} {'max pose diff':>13}")
    for case, count, mode, wall, cpu, own, mib, aligned, diff in rows:
        print(f"{case:<10} {count:>5} {mode:<11} {wall:>7.1f} {cpu:>7.1f} {mib:>10.0f} {own:>10.0f} {aligned:>7} "
              f"{diff:>13.2e}")
    print(f"\n{os.cpu_count()} cores; worker MiB: the largest resident size of a helper or Dask worker process "
          "(imports included); caller MiB: this process's peak")


if __name__ == "__main__":
    main()
