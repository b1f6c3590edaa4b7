"""The texture stage at campaign scale: memory and time, in one process and across workers.

    .venv/bin/python benchmarks/texture_scale.py --run WORK/runs/local --session WORK/capture \
        [--model WORK/runs/local/model1m.ply] [--size 4096] [--views 12,24] [--before /work/main/toolbox]

``--run`` is a run of ``benchmarks/paper_scale.py`` (its ``albedo/`` and
``aligned/registration.json``); ``--model`` the model to texture (default the run's
``simplified.ply``). For each view count N (the first N views of the registration), each
row is ``slscan texture --size SIZE --no-preview`` in its own process:

- ``before``: the code in ``--before`` (a toolbox folder, e.g. the main tree before the
  change), in one process;
- ``1 proc``: this tree, ``--workers 1``;
- ``2 local``: this tree, ``--workers 2`` (this process and one helper);
- ``2 dask``: this tree on a ``distributed.LocalCluster(n_workers=2, threads_per_worker=1)``.

Per row: wall seconds, CPU seconds (the command's process tree; with Dask, plus the
workers' CPU over the row), peak resident memory of the calling process, of the largest
worker process (helper or Dask worker; both also map the bake's shared arrays, counted in
each one's resident size), and of everything together (sampled every 0.1 s), and the
atlas (``model_albedo.png``, 8-bit sRGB) against the first row's over the texels some view
saw: largest and mean difference in levels.

Each row's numbers are kept in ``WORK/VIEWS-ROW.json`` and not measured again by a later
run into the same ``--work`` (delete them to measure again).

``--profile`` adds, for the first view count, the calling process's peak resident memory
per phase of an in-process run (``--workers 1``) of each code: the peak between one
progress step and the next, named by the step that ends it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TOOLBOX = HERE.parent / "toolbox"
sys.path.insert(0, str(HERE))


def _rss(pid: int) -> int:
    from measure import _rss_bytes

    return _rss_bytes(pid)


def _descendants(root: int) -> list[int]:
    from measure import _children

    tree, out, todo = _children(), [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo.extend(tree.get(pid, ()))
    return out


def run_row(command: list[str], toolbox: Path, workers: list[int]) -> dict:
    """Run ``command`` with ``toolbox`` first on the path; wall, CPU, peaks."""
    import psutil

    env = dict(os.environ, PYTHONPATH=str(toolbox))
    cpu_workers0 = sum(sum(psutil.Process(p).cpu_times()[:2]) for p in workers)
    t0 = time.perf_counter()
    proc = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peaks: dict[int, int] = {}
    total = [0]
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            pids = _descendants(proc.pid) + list(workers)
            now = 0
            for pid in pids:
                r = _rss(pid)
                now += r
                peaks[pid] = max(peaks.get(pid, 0), r)
            total[0] = max(total[0], now)
            done.wait(0.1)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    stdout, stderr = proc.communicate()
    done.set()
    sampler.join()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"failed (exit {proc.returncode}): {' '.join(command)}\n{stderr[-3000:]}")
    cpu_workers = sum(sum(psutil.Process(p).cpu_times()[:2]) for p in workers) - cpu_workers0
    return {"wall": wall, "peaks": peaks, "caller": proc.pid, "total": total[0], "cpu_workers": cpu_workers}


def children_cpu() -> float:
    import resource

    u = resource.getrusage(resource.RUSAGE_CHILDREN)
    return u.ru_utime + u.ru_stime


def atlas_difference(a: Path, b: Path) -> tuple[float, float]:
    """Largest and mean |a - b| (8-bit levels) of two outputs' atlases, over texels seen in ``a``."""
    import cv2

    ia = cv2.imread(str(a / "model_albedo.png"), cv2.IMREAD_UNCHANGED).astype(np.int32)
    ib = cv2.imread(str(b / "model_albedo.png"), cv2.IMREAD_UNCHANGED).astype(np.int32)
    seen = cv2.imread(str(a / "view_count_raw.png"), cv2.IMREAD_UNCHANGED) > 0
    d = np.abs(ia - ib)[seen]
    return float(d.max(initial=0)), float(d.mean()) if d.size else 0.0


def profile_child(spec: dict) -> None:
    """In this process: texture_model with a sampler; the peak RSS per progress step."""
    from slscan.texture.pipeline import TextureConfig, texture_model

    peak = [0]
    marks: list[tuple[str, float, float]] = []
    done = threading.Event()
    t0 = time.perf_counter()

    def sample() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], _rss(os.getpid()))
            done.wait(0.02)

    def progress(label: str) -> None:
        peak[0] = max(peak[0], _rss(os.getpid()))
        marks.append((label, peak[0] / 2**30, time.perf_counter() - t0))
        peak[0] = 0

    threading.Thread(target=sample, daemon=True).start()
    kwargs = {}
    if spec["new"]:
        from slscan.executor import Executor

        kwargs["executor"] = Executor(workers=1)
    texture_model(spec["model"], spec["albedo"], spec["out"], poses=spec["poses"], session=spec["session"],
                  config=TextureConfig(size=spec["size"], preview=False), overwrite=True,
                  progress=progress, **kwargs)
    done.set()
    print(json.dumps(marks))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", type=Path, help="a paper_scale.py run folder (albedo/, aligned/)")
    p.add_argument("--session", type=Path, help="its capture session")
    p.add_argument("--model", type=Path, default=None, help="model to texture (default RUN/simplified.ply)")
    p.add_argument("--size", type=int, default=4096)
    p.add_argument("--views", default="24", help="view counts, comma-separated")
    p.add_argument("--before", type=Path, default=Path("/work/main/toolbox"), help="toolbox of the 'before' row")
    p.add_argument("--rows", default="before,1 proc,2 local,2 dask")
    p.add_argument("--profile", action="store_true")
    p.add_argument("--work", type=Path, default=None, help="scratch folder (default: a temporary one)")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        profile_child(json.loads(args.child))
        return

    model = args.model or args.run / "simplified.ply"
    work = args.work or Path(tempfile.mkdtemp(prefix="texture_scale_"))
    work.mkdir(parents=True, exist_ok=True)
    poses = json.loads((args.run / "aligned" / "registration.json").read_text())["poses"]
    names = sorted(poses)
    rows_wanted = [r.strip() for r in args.rows.split(",")]
    cluster = None
    if "2 dask" in rows_wanted:
        from paper_scale import DaskCluster

        os.environ["PYTHONPATH"] = str(TOOLBOX)  # the Dask workers import this tree,
        sys.path.insert(0, str(TOOLBOX))  # and so does the scheduler (in this process: it unpickles the tasks)
        cluster = DaskCluster(2)
    table = []
    profiles = {}
    try:
        for n in [int(v) for v in args.views.split(",")]:
            pose_file = work / f"poses{n}.json"
            pose_file.write_text(json.dumps({"poses": {k: poses[k] for k in names[:n]}}))
            if args.profile and not profiles:
                for label, toolbox, new in (("before", args.before, False), ("after", TOOLBOX, True)):
                    cached = work / f"profile-{label}.json"
                    if cached.is_file():
                        profiles[label] = json.loads(cached.read_text())
                        continue
                    spec = {"model": str(model), "albedo": str(args.run / "albedo"), "out": str(work / f"p-{label}"),
                            "poses": str(pose_file), "session": str(args.session), "size": args.size, "new": new}
                    out = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)], check=True,
                                         env=dict(os.environ, PYTHONPATH=str(toolbox)), capture_output=True,
                                         text=True)
                    profiles[label] = json.loads(out.stdout.strip().splitlines()[-1])
                    cached.write_text(json.dumps(profiles[label]))
                    print(f"profiled {label}", file=sys.stderr, flush=True)
            first = None
            for row in rows_wanted:
                out = work / f"{n}-{row.replace(' ', '_')}"
                cmd = [sys.executable, "-m", "slscan.cli", "texture", str(model), "--views", str(args.run / "albedo"),
                       "--poses", str(pose_file), "--session", str(args.session), "--size", str(args.size),
                       "--no-preview", "--quiet", "--overwrite", "--out", str(out)]
                toolbox = args.before if row == "before" else TOOLBOX
                workers: list[int] = []
                if row == "1 proc":
                    cmd += ["--workers", "1"]
                elif row == "2 local":
                    cmd += ["--workers", "2"]
                elif row == "2 dask":
                    cmd += ["--scheduler", cluster.address]
                    workers = cluster.pids()
                cpu0 = children_cpu()
                cached = work / f"{n}-{row.replace(' ', '_')}.json"
                if cached.is_file():  # measured by an earlier run into the same --work
                    r = json.loads(cached.read_text())
                    table.append(r)
                    first = first or out
                    continue
                m = run_row(cmd, toolbox, workers)
                cpu = children_cpu() - cpu0 + m["cpu_workers"]
                caller = m["peaks"].get(m["caller"], 0)
                others = [v for pid, v in m["peaks"].items() if pid != m["caller"]]
                # helpers of the local executor are the caller's children; the resource tracker is tiny
                worker_peak = max(others, default=0) if row in ("2 local", "2 dask") else 0
                diff = (0.0, 0.0) if first is None else atlas_difference(first, out)
                first = first or out
                r = {"views": n, "row": row, "wall": m["wall"], "cpu": cpu, "caller": caller / 2**30,
                     "worker": worker_peak / 2**30, "total": m["total"] / 2**30, "max_diff": diff[0],
                     "mean_diff": diff[1]}
                cached.write_text(json.dumps(r))
                table.append(r)
                print(f"  {n} views {row:8s} {m['wall']:7.1f} s", file=sys.stderr, flush=True)
    finally:
        if cluster is not None:
            cluster.close()

    print(f"slscan texture, {model.name}, atlas {args.size}; atlas difference in 8-bit levels against the "
          "first row, over seen texels")
    print(f"{'views':>5} {'row':9} {'wall s':>7} {'CPU s':>7} {'caller GiB':>10} {'worker GiB':>10} "
          f"{'total GiB':>9} {'max diff':>8} {'mean diff':>9}")
    for r in table:
        worker = f"{r['worker']:10.2f}" if r["worker"] else f"{'-':>10}"
        print(f"{r['views']:5d} {r['row']:9} {r['wall']:7.1f} {r['cpu']:7.1f} {r['caller']:10.2f} {worker} "
              f"{r['total']:9.2f} {r['max_diff']:8.0f} {r['mean_diff']:9.4f}")
    for label, marks in profiles.items():
        print(f"\npeak RSS of the calling process per phase, {label} (in-process, "
              f"{args.views.split(',')[0]} views): step, GiB, s")
        for step, gib, t in marks:
            print(f"  {step:28s} {gib:6.2f} {t:7.1f}")
    (work / "table.json").write_text(json.dumps({"rows": table, "profiles": profiles}, indent=1))


if __name__ == "__main__":
    main()
