"""Fusion in spatial bricks (``fuse_bricks``) against one volume: time, memory, same mesh.

    .venv/bin/python benchmarks/fusion_bricks.py ALIGNED.mlp [--voxel 0.57] [--brick 80]
                                                 [--ways single,bricks,local2,dask2]

Fuses the aligned range maps of ``ALIGNED.mlp`` (e.g. ``slscan run recipes/demo.toml --out
/tmp/demo`` then ``/tmp/demo/register/aligned.mlp``: the demo's 8 full-size views) each
way in its own process:

- **single**: ``fuse_scans``, one volume in one process;
- **bricks**: ``fuse_bricks`` in this process, brick after brick;
- **local2**: ``fuse_bricks`` on two local processes (``Executor(workers=2)``: this one
  and a helper);
- **dask2**: ``fuse_bricks`` on a Dask ``LocalCluster`` of 2 single-threaded worker
  processes (started before the clock).

Printed per way: wall seconds (fusion only, scans already loaded, except "scans lazy": the
bricks' ways read the scans one at a time inside the clock, as ``slscan fuse --brick``
does, where the toolbox has ``iter_scans``), CPU seconds and peak resident memory of every
process of the way (sampled every 0.1 s with psutil: the largest process, the largest sum
over processes at one time, the caller, and the largest helper process: a local helper or
a Dask worker, where a brick task runs; in-process ways run the tasks in the caller), bricks, faces, and
the mesh's distance to the single-volume mesh: vertices equal (same count and largest
coordinate difference after canonical order) and the symmetric Hausdorff and mean
distances between the vertex sets (mm).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def _watch(stop: threading.Event, out: dict) -> None:
    """Sample the RSS and CPU of this process and its descendants until ``stop``."""
    import psutil

    me = psutil.Process()
    cpu: dict[int, float] = {}
    peak_one, peak_sum, peak_caller, peak_helper = 0, 0, 0, 0
    while not stop.is_set():
        total = 0
        for p in [me, *me.children(recursive=True)]:
            try:
                rss = p.memory_info().rss
                t = p.cpu_times()
            except psutil.Error:
                continue
            cpu[p.pid] = t.user + t.system
            total += rss
            peak_one = max(peak_one, rss)
            if p.pid == me.pid:
                peak_caller = max(peak_caller, rss)
            else:
                peak_helper = max(peak_helper, rss)
        peak_sum = max(peak_sum, total)
        stop.wait(0.1)
    out.update(peak_one=peak_one, peak_sum=peak_sum, peak_caller=peak_caller, peak_helper=peak_helper,
               cpu=sum(cpu.values()))


def run_way(way: str, aligned: str, voxel: float, brick: float, mesh_out: str) -> dict:
    """One way in this process (the child); returns its measures."""
    from slscan.executor import Executor
    from slscan.fuse import FuseConfig, fuse_scans, write_mesh
    from slscan.register.meshlab import load_scan_project

    try:  # since the bricks take pieces: the scans read one at a time, as `slscan fuse --brick` does
        from slscan.register.command import iter_scans
    except ImportError:
        iter_scans = None
    lazy = way != "single" and iter_scans is not None
    if not lazy:
        scans, poses = load_scan_project(Path(aligned))
    cluster = None
    executor = None
    if way == "local2":
        executor = Executor(workers=2)
        executor.start(2, ("slscan.fuse",))
        time.sleep(3)  # the helper's start-up (imports) is not fusion
    elif way == "dask2":
        from distributed import LocalCluster

        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
        executor = Executor(scheduler=cluster.scheduler_address)
    config = FuseConfig(voxel_size=voxel, brick_size=None if way == "single" else brick)
    stop, watched = threading.Event(), {}
    watcher = threading.Thread(target=_watch, args=(stop, watched))
    cpu0 = _tree_cpu()
    watcher.start()
    t0 = time.perf_counter()
    if lazy:  # reading the scans is then inside the clock
        _, scans, poses = iter_scans(Path(aligned))
    result = fuse_scans(scans, poses, config=config, executor=executor)
    wall = time.perf_counter() - t0
    stop.set()
    watcher.join()
    cpu = watched["cpu"] - cpu0
    write_mesh(result.mesh, mesh_out)
    if cluster is not None:
        cluster.close()
    return {"wall": wall, "cpu": cpu, "peak_one": watched["peak_one"], "peak_sum": watched["peak_sum"],
            "bricks": result.n_bricks, "faces": result.mesh.n_faces, "peak_caller": watched["peak_caller"],
            "peak_helper": watched["peak_helper"], "scans": "lazy" if lazy else "list"}


def _tree_cpu() -> float:
    import psutil

    total = 0.0
    me = psutil.Process()
    for p in [me, *me.children(recursive=True)]:
        try:
            t = p.cpu_times()
        except psutil.Error:
            continue
        total += t.user + t.system
    return total


def distances(a_path: str, b_path: str) -> dict:
    from scipy.spatial import cKDTree

    from slscan.fuse import read_mesh

    a, b = read_mesh(a_path), read_mesh(b_path)
    same = a.n_vertices == b.n_vertices and np.array_equal(a.faces, b.faces)
    max_diff = float(np.abs(a.vertices - b.vertices).max()) if same else float("nan")
    d_ab = cKDTree(b.vertices).query(a.vertices)[0]
    d_ba = cKDTree(a.vertices).query(b.vertices)[0]
    return {"same": same, "max_diff": max_diff, "hausdorff": float(max(d_ab.max(), d_ba.max())),
            "mean": float((d_ab.mean() + d_ba.mean()) / 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("aligned")
    parser.add_argument("--voxel", type=float, default=0.57)
    parser.add_argument("--brick", type=float, default=80.0)
    parser.add_argument("--ways", default="single,bricks,local2,dask2")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    parser.add_argument("--mesh-out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(run_way(args.child, args.aligned, args.voxel, args.brick, args.mesh_out)))
        return
    ways = args.ways.split(",")
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for way in ways:
            mesh = f"{tmp}/{way}.ply"
            out = subprocess.run([sys.executable, __file__, args.aligned, "--voxel", str(args.voxel),
                                  "--brick", str(args.brick), "--child", way, "--mesh-out", mesh],
                                 check=True, capture_output=True, text=True).stdout
            rows[way] = json.loads(out.strip().splitlines()[-1])
            if way != "single" and "single" in rows:
                rows[way].update(distances(f"{tmp}/single.ply", mesh))
    print(f"\n{args.aligned}: voxel {args.voxel} mm, bricks of about {args.brick} mm")
    print(f"{'way':8} {'wall s':>7} {'CPU s':>7} {'peak RSS 1 proc':>16} {'peak RSS all':>13} "
          f"{'caller':>9} {'helper':>9} {'scans':>5} "
          f"{'bricks':>6} {'faces':>10} {'same mesh':>9} {'max |dv| mm':>11} {'Hausdorff mm':>12} {'mean mm':>8}")
    for way, r in rows.items():
        dist = (f"{str(r['same']):>9} {r['max_diff']:>11.2g} {r['hausdorff']:>12.2g} {r['mean']:>8.2g}"
                if "hausdorff" in r else f"{'-':>9} {'-':>11} {'-':>12} {'-':>8}")
        helper = f"{r['peak_helper'] / 2**30:>5.2f} GiB" if r["peak_helper"] else f"{'-':>9}"
        print(f"{way:8} {r['wall']:>7.1f} {r['cpu']:>7.1f} {r['peak_one'] / 2**30:>12.2f} GiB "
              f"{r['peak_sum'] / 2**30:>9.2f} GiB {r['peak_caller'] / 2**30:>5.2f} GiB {helper} {r['scans']:>5} "
              f"{r['bricks']:>6} {r['faces']:>10,} {dist}")


if __name__ == "__main__":
    main()
