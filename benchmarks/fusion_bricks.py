"""Fusion in spatial bricks (``fuse_bricks``) against one volume: time, memory, same mesh.

    .venv/bin/python benchmarks/fusion_bricks.py ALIGNED.mlp [--voxel 0.57] [--brick 80]
                                                 [--ways single,bricks,local2,dask2]
    .venv/bin/python benchmarks/fusion_bricks.py --sphere 60 --voxel 0.3 --brick 40 \
                                                 --ways bricks,stream,dask2,dask2-stream

Fuses the aligned range maps of ``ALIGNED.mlp`` (e.g. ``slscan run recipes/demo.toml --out
/tmp/demo`` then ``/tmp/demo/register/aligned.mlp``: the demo's 8 full-size views) each
way in its own process:

- **single**: ``fuse_scans``, one volume in one process;
- **bricks**: ``fuse_bricks`` in this process, brick after brick;
- **local2**: ``fuse_bricks`` on two local processes (``Executor(workers=2)``: this one
  and a helper);
- **dask2**: ``fuse_bricks`` on a Dask ``LocalCluster`` of 2 single-threaded worker
  processes (started before the clock);
- **stream**, **local2-stream**, **dask2-stream**: the same with ``out=``: each brick writes
  its piece to a scratch folder and the caller streams the PLY, never holding the whole mesh
  (the in-memory ways' mesh is then written with ``write_mesh``, outside the clock).

``--sphere R`` fuses instead six orthographic scans (0.5 mm pixels) of a sphere of radius R
mm, written first as an aligned set in a temporary folder: a synthetic case whose mesh
grows as R² / voxel², to show what the caller holds.

Printed per way: wall seconds (fusion and, streamed, writing the PLY; scans already loaded),
CPU seconds and peak resident memory (sampled every 0.1 s with psutil): of the caller (this
process: with ``bricks`` and ``stream`` it also runs the bricks; with Dask it only gathers
them), of the largest task process (Dask workers, local helpers), and the largest sum over
processes at one time; bricks, faces, and the mesh against the first way's (``single``, else
``bricks``): the same mesh up to order (same vertices and faces after canonical order),
the largest coordinate difference then, and the symmetric Hausdorff and mean distances
between the vertex sets (mm).
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
    peak_me, peak_task, peak_sum = 0, 0, 0
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
            if p.pid == me.pid:
                peak_me = max(peak_me, rss)
            else:
                peak_task = max(peak_task, rss)
        peak_sum = max(peak_sum, total)
        stop.wait(0.1)
    out.update(peak_me=peak_me, peak_task=peak_task, peak_sum=peak_sum, cpu=sum(cpu.values()))


def run_way(way: str, aligned: str, voxel: float, brick: float, mesh_out: str) -> dict:
    """One way in this process (the child); returns its measures."""
    from slscan.executor import Executor
    from slscan.fuse import FuseConfig, fuse_bricks, fuse_scans, write_mesh
    from slscan.register.meshlab import load_scan_project

    try:  # since the bricks take pieces: the scans read one at a time, as `slscan fuse --brick` does
        from slscan.register.command import iter_scans
    except ImportError:  # an older toolbox (--against)
        iter_scans = None
    lazy = way != "single" and iter_scans is not None
    if not lazy:
        scans, poses = load_scan_project(Path(aligned))
    cluster = None
    executor = None
    streamed = way.endswith("-stream") or way == "stream"
    way = way.removesuffix("-stream")
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
    if streamed:
        result = fuse_bricks(scans, poses, config=config, executor=executor, out=mesh_out)
    else:
        result = fuse_scans(scans, poses, config=config, executor=executor)
    wall = time.perf_counter() - t0
    stop.set()
    watcher.join()
    cpu = watched["cpu"] - cpu0
    if not streamed:
        write_mesh(result.mesh, mesh_out)
    if cluster is not None:
        cluster.close()
    faces = result.written.n_faces if streamed else result.mesh.n_faces
    return {"wall": wall, "cpu": cpu, "peak_me": watched["peak_me"], "peak_task": watched["peak_task"],
            "peak_sum": watched["peak_sum"], "bricks": result.n_bricks, "faces": faces}


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

    from slscan.fuse import canonical_order, read_mesh

    a, b = canonical_order(read_mesh(a_path)), canonical_order(read_mesh(b_path))
    same = a.n_vertices == b.n_vertices and np.array_equal(a.faces, b.faces)
    max_diff = float(np.abs(a.vertices - b.vertices).max()) if same else float("nan")
    d_ab = cKDTree(b.vertices).query(a.vertices)[0]
    d_ba = cKDTree(a.vertices).query(b.vertices)[0]
    return {"same": same, "max_diff": max_diff, "hausdorff": float(max(d_ab.max(), d_ba.max())),
            "mean": float((d_ab.mean() + d_ba.mean()) / 2)}


def sphere_project(folder: Path, radius: float) -> str:
    """Six orthographic scans (0.5 mm pixels, 0.05 mm noise) of a sphere of ``radius`` mm, off the
    origin, written as an aligned set in ``folder``; returns its aligned.mlp."""
    import open3d as o3d

    from slscan.register.meshlab import write_scan_project
    from slscan.register.rangescan import render_range_scan

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=max(60, int(radius * 4)))
    v = np.asarray(sphere.vertices) + [3.1, -2.2, 1.7]
    f = np.asarray(sphere.triangles)
    scans, poses = [], {}
    side = int(2.2 * radius / 0.5)
    for k, d in enumerate([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]):
        d = np.asarray(d, float)
        helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        x = np.cross(helper, d)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([x, np.cross(d, x), d], axis=1)
        scans.append(render_range_scan(v, f, pose, shape=(side, side), pixel=0.5, name=f"view{k}", noise=0.05,
                                       rng=np.random.default_rng(k)))
        poses[f"view{k}"] = pose
    return str(write_scan_project(folder, scans, poses))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("aligned", nargs="?")
    parser.add_argument("--sphere", type=float, metavar="R", help="fuse a synthetic sphere of radius R mm instead")
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
    if (args.aligned is None) == (args.sphere is None):
        parser.error("give ALIGNED.mlp or --sphere R")
    with tempfile.TemporaryDirectory() as tmp:
        if args.sphere is not None:
            args.aligned = sphere_project(Path(tmp) / "sphere", args.sphere)
        for way in ways:
            mesh = f"{tmp}/{way}.ply"
            out = subprocess.run([sys.executable, __file__, args.aligned, "--voxel", str(args.voxel),
                                  "--brick", str(args.brick), "--child", way, "--mesh-out", mesh],
                                 check=True, capture_output=True, text=True).stdout
            rows[way] = json.loads(out.strip().splitlines()[-1])
            if way != ways[0]:
                rows[way].update(distances(f"{tmp}/{ways[0]}.ply", mesh))
    what = f"sphere of {args.sphere:g} mm" if args.sphere is not None else args.aligned
    print(f"\n{what}: voxel {args.voxel} mm, bricks of about {args.brick} mm; meshes against {ways[0]}")
    print(f"{'way':13} {'wall s':>7} {'CPU s':>7} {'caller peak':>12} {'task peak':>10} {'peak all':>9} "
          f"{'bricks':>6} {'faces':>10} {'same mesh':>9} {'max |dv| mm':>11} {'Hausdorff mm':>12} {'mean mm':>8}")
    for way, r in rows.items():
        dist = (f"{str(r['same']):>9} {r['max_diff']:>11.2g} {r['hausdorff']:>12.2g} {r['mean']:>8.2g}"
                if "hausdorff" in r else f"{'-':>9} {'-':>11} {'-':>12} {'-':>8}")
        task = f"{r['peak_task'] / 2**30:>6.2f} GiB" if r["peak_task"] else f"{'-':>10}"
        print(f"{way:13} {r['wall']:>7.1f} {r['cpu']:>7.1f} {r['peak_me'] / 2**30:>8.2f} GiB {task} "
              f"{r['peak_sum'] / 2**30:>5.2f} GiB {r['bricks']:>6} {r['faces']:>10,} {dist}")


if __name__ == "__main__":
    main()
