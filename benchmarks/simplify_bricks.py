"""Out-of-core simplification in bricks vs in-core: wall, CPU, peak RSS per process, faces, and
the surface distance (both ways) of each bricks result to the in-core one.

Each configuration runs in a fresh Python process (so its peak RSS is its own):

- ``in-core``: :func:`slscan.simplify.simplify_file` (slscan's PLY reader, fast-simplification);
- ``bricks x1``: :func:`slscan.simplify_bricks.simplify_bricks` with every brick in that process;
- ``bricks x2``: the same with 2 local worker processes (the caller and one helper).

Usage::

    nice -n 10 python benchmarks/simplify_bricks.py MESH.ply --faces 1000000 [--bricks 8 | --brick MM]
    nice -n 10 python benchmarks/simplify_bricks.py --make 12000000 --faces 1000000   # synthetic input
    (--to-input: also each result's distance to the input)

``--make N`` writes a bumpy sphere of about N faces (radius 100 mm, 0.5 mm bumps of several
frequencies, so nothing is trivially flat) to /tmp/oocs-bench/bumpy-N.ply first.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _bumpy_sphere(faces: int, path: Path) -> Path:
    import open3d as o3d

    from slscan.fuse import Mesh, write_mesh

    res = max(8, int(round(np.sqrt(faces / 4))))  # open3d's UV sphere: about 4 res**2 faces
    m = o3d.geometry.TriangleMesh.create_sphere(100.0, resolution=res)
    v = np.asarray(m.vertices)
    d = v / np.linalg.norm(v, axis=1, keepdims=True)
    bump = 0.5 * (np.sin(7 * d[:, 0]) * np.cos(11 * d[:, 1]) + 0.5 * np.sin(37 * d[:, 2] + 13 * d[:, 0])
                  + 0.25 * np.sin(101 * d[:, 1]))
    write_mesh(Mesh(v + d * bump[:, None], np.asarray(m.triangles, np.int64)), path)
    return path


def _peak_rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _run_one(mode: str, mesh: str, out: str, faces: int, bricks: int | None, brick: float | None) -> dict:
    """One configuration, in this (fresh) process."""
    t0, c0 = time.perf_counter(), time.process_time()
    task_peaks: list[int] = []
    if mode == "in-core":
        from slscan.simplify import simplify_file

        n = simplify_file(mesh, out, faces).n_faces
    else:
        from slscan.executor import Executor, shutdown
        from slscan.simplify_bricks import simplify_bricks

        workers = int(mode.split("x")[1])
        rep = simplify_bricks(mesh, out, faces, bricks=bricks, brick_mm=brick, executor=Executor(workers=workers))
        n, task_peaks = rep.faces_out, [b.peak_rss for b in rep.bricks]
        shutdown()
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"mode": mode, "wall": time.perf_counter() - t0,
            "cpu": time.process_time() - c0 + children.ru_utime + children.ru_stime,
            "peak": _peak_rss(), "child_peak": children.ru_maxrss * 1024,
            "task_peak_max": max(task_peaks, default=0), "faces": n, "bricks": len(task_peaks)}


def _to_input(mesh: str, paths: list[str]) -> list[str]:
    """Each result's vertices to the input's triangles (one way), mm: mean / p95 / max."""
    import open3d as o3d

    from slscan.fuse import read_mesh

    src = read_mesh(mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(src.vertices.astype(np.float32)), o3d.core.Tensor(src.faces.astype(np.uint32)))
    del src
    out = []
    for path in paths:
        d = scene.compute_distance(o3d.core.Tensor(read_mesh(path).vertices.astype(np.float32))).numpy()
        out.append(f"{d.mean():.4f} / {np.percentile(d, 95):.4f} / {d.max():.3f}")
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mesh", nargs="?", help="binary PLY mesh (default: --make)")
    p.add_argument("--make", type=int, metavar="N", help="make a bumpy sphere of about N faces")
    p.add_argument("--faces", type=int, default=1_000_000, help="target (default 1000000)")
    p.add_argument("--bricks", type=int, help="about N bricks (default 8)")
    p.add_argument("--brick", type=float, metavar="MM", help="brick edge, mm")
    p.add_argument("--out", type=Path, default=Path("/tmp/oocs-bench"), help="scratch folder")
    p.add_argument("--to-input", action="store_true",
                   help="also each result's distance to the input (its vertices to the input's triangles)")
    p.add_argument("--_run", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args._run:
        mode, mesh, out = args._run.split("|")
        print(json.dumps(_run_one(mode, mesh, out, args.faces, args.bricks, args.brick)))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    if args.mesh is None:
        if not args.make:
            p.error("give a MESH or --make N")
        path = args.out / f"bumpy-{args.make}.ply"
        mesh = str(path if path.is_file() else _bumpy_sphere(args.make, path))
    else:
        mesh = args.mesh
    from slscan.fsio import human_size
    from slscan.fuse import read_mesh
    from slscan.simplify_bricks import ply_layout, surface_distance

    n_in = ply_layout(mesh).n_faces
    rows = []
    for mode in ("in-core", "bricks x1", "bricks x2"):
        out = str(args.out / f"{mode.replace(' ', '-')}.ply")
        cmd = [sys.executable, __file__, "--faces", str(args.faces), "--_run", f"{mode.replace(' ', '')}|{mesh}|{out}"]
        cmd += ["--bricks", str(args.bricks)] if args.bricks else []
        cmd += ["--brick", str(args.brick)] if args.brick else []
        done = subprocess.run(cmd, check=True, capture_output=True, text=True, env=os.environ)
        row = json.loads(done.stdout.strip().splitlines()[-1])
        row["mode"], row["path"] = mode, out
        rows.append(row)
    ref = read_mesh(rows[0]["path"])
    to_input = _to_input(mesh, [r["path"] for r in rows]) if args.to_input else None
    print(f"input {mesh}: {n_in:,} faces -> target {args.faces:,}; {os.cpu_count()} cores\n")
    extra = f" {'to input mean / p95 / max, mm':>29} |" if to_input else ""
    print(f"| {'run':<10} | {'wall s':>7} | {'CPU s':>7} | {'peak RSS main':>13} | {'peak RSS task':>13} | "
          f"{'bricks':>6} | {'faces':>10} | {'to in-core mean / p95 / max, mm':>31} |" + extra)
    print("|" + "|".join("-" * w for w in (12, 9, 9, 15, 15, 8, 12, 33, *((31,) if to_input else ()))) + "|")
    for i, r in enumerate(rows):
        dist = "-"
        if r["mode"] != "in-core":
            d = surface_distance(read_mesh(r["path"]), ref)
            dist = f"{d['mean']:.4f} / {d['p95']:.4f} / {d['max']:.3f}"
        task = human_size(r["task_peak_max"]) if r["bricks"] else "-"
        tail = f" {to_input[i]:>29} |" if to_input else ""
        print(f"| {r['mode']:<10} | {r['wall']:7.1f} | {r['cpu']:7.1f} | {human_size(r['peak']):>13} | {task:>13} | "
              f"{r['bricks'] or '-':>6} | {r['faces']:>10,} | {dist:>31} |" + tail)
    print("\npeak RSS task: the largest brick task's peak (VmHWM reset at the task's start; in-process it "
          "includes the caller's own memory). Distances: both ways, vertices to triangles (Open3D).")


if __name__ == "__main__":
    main()
