"""The virtual rig's full object, stage by stage: time, peak memory, and the model vs the truth.

    .venv/bin/python benchmarks/multiview.py [--views 8] [--scale 1.0] [--voxel 0.57]
        [--faces 1000000] [--texture 4096] [--work DIR] [--workers N]

Runs ``recipes/paper.toml`` (the paper's rig: 1440x960 camera, 1024x768 projector, 9
hybrid levels, 6 ring lights; the built-in figurine on a turntable whose recorded angles
carry error) one stage at a time, each in its own ``slscan run`` process that resumes the
stages before it. Per stage: the stage's own time (from its record) and the peak resident
memory of the whole process tree (``slscan run`` plus the worker processes per-view stages
fan out to), sampled every 0.1 s; the last row is the same process doing nothing but
importing and finding every stage done (the floor every row includes).

Then the fused and the simplified model against the figurine's true mesh (mm, in the
object frame the registration recovers from the turntable's first recorded pose): distance
from points spread by area on the model to the true surface (accuracy), and from points
spread by area on the true surface to the model (completeness: surfaces no view saw — the
pedestal's underside, the inside of the ring — count against it).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np
from measure import distances_to_mesh, run_measured, surface_samples

ROOT = Path(__file__).resolve().parents[1]


def recipe_for(args: argparse.Namespace) -> dict:
    data = tomllib.loads((ROOT / "recipes" / "paper.toml").read_text())
    data["recipe"].pop("reduced", None)
    data["capture"].update(views=args.views, camera_scale=args.scale, projector_scale=args.scale, levels=args.levels)
    data["fuse"]["voxel_size"] = args.voxel
    data["simplify"]["faces"] = args.faces
    data["texture"].update(size=args.texture, preview=False)
    return data


def run_stages(args: argparse.Namespace, work: Path) -> list[dict]:
    from slscan.recipe.config import dumps_toml

    data = recipe_for(args)
    stages = list(data["recipe"]["stages"])
    slscan = Path(sys.executable).with_name("slscan")
    run_dir = work / "run"
    rows = []
    for k, stage in enumerate([*stages, None]):
        part = dict(data, recipe=dict(data["recipe"], stages=stages[: k + 1] if stage else stages))
        for name in stages[k + 1 :] if stage else ():
            part.pop(name, None)
        path = work / f"recipe-{k}.toml"
        path.write_text(dumps_toml(part))
        command = [str(slscan), "run", str(path), "--out", str(run_dir), "--quiet"]
        if args.workers:
            command += ["--workers", str(args.workers)]
        print(f"  {stage or 'all done'} ...", file=sys.stderr, flush=True)
        measured = run_measured(command)
        if measured.returncode != 0:
            raise SystemExit(f"stage {stage} failed:\n{measured.stderr[-3000:]}")
        record = json.loads((run_dir / f"{stage}.stage.json").read_text()) if stage else {}
        rows.append({"stage": stage or "(all resumed)", "seconds": record.get("seconds", 0.0),
                     "wall": measured.seconds, "peak": measured.peak_bytes,
                     "summary": record.get("summary", {})})
    return rows


def accuracy(run_dir: Path) -> list[tuple]:
    from slscan.fuse import read_mesh
    from slscan.virtual.scenes import builtin_object

    scene = builtin_object()
    truth_v, truth_f = np.asarray(scene.vertices, np.float64), np.asarray(scene.triangles)
    truth_points = surface_samples(truth_v, truth_f, 1_000_000, seed=1)
    rows = []
    for label, path in (("fused", run_dir / "fuse" / "mesh.ply"), ("simplified", run_dir / "simplify" / "mesh.ply")):
        mesh = read_mesh(path)
        to_truth = distances_to_mesh(surface_samples(mesh.vertices, mesh.faces, 1_000_000), truth_v, truth_f)
        from_truth = distances_to_mesh(truth_points, mesh.vertices, mesh.faces)
        rows.append((label, len(mesh.faces), to_truth.mean(), np.percentile(to_truth, 95),
                     np.percentile(to_truth, 99), from_truth.mean(), np.percentile(from_truth, 95),
                     (from_truth <= 0.5).mean(), (from_truth <= 1.0).mean()))
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--views", type=int, default=8, help="turntable views (default 8)")
    p.add_argument("--scale", type=float, default=1.0, help="camera and projector scale (1.0: the paper's)")
    p.add_argument("--levels", type=int, default=9, help="hybrid pattern levels (9: 511 lines on 1024 px)")
    p.add_argument("--voxel", type=float, default=0.57, help="fusion voxel size, mm (the paper's 0.57)")
    p.add_argument("--faces", type=int, default=1_000_000, help="simplification target")
    p.add_argument("--texture", type=int, default=4096, help="texture atlas size, texels")
    p.add_argument("--workers", type=int, default=0, help="worker processes for per-view stages (default: one per core)")
    p.add_argument("--work", type=Path, help="keep the run in this folder (default: a temporary one)")
    args = p.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="slscan-multiview-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rows = run_stages(args, work)
        acc = accuracy(work / "run")

    print(f"## the paper recipe on the virtual rig: {args.views} turntable views, camera scale {args.scale:g}, "
          f"fused at {args.voxel:g} mm, {args.faces:,} faces ({os.cpu_count()} CPUs)")
    print(f"{'stage':<15} {'stage s':>8} {'process s':>10} {'peak GiB':>9}  summary")
    total = 0.0
    for r in rows:
        total += r["seconds"]
        keys = ("views", "vertices", "faces", "aligned", "left_out", "median_pair_rmse_mm", "charts")
        summary = ", ".join(f"{k} {r['summary'][k]}" for k in keys if k in r["summary"])
        print(f"{r['stage']:<15} {r['seconds']:8.1f} {r['wall']:10.1f} {r['peak'] / 2**30:9.2f}  {summary}")
    print(f"{'total':<15} {total:8.1f}")
    print("(peak: resident memory of the slscan process and its workers together, sampled every 0.1 s)")
    print()
    print("## models vs the figurine's true mesh, mm (1M points spread by area on each surface)")
    print(f"{'model':<11} {'faces':>10} {'to truth mean':>14} {'p95':>7} {'p99':>7} {'truth to it mean':>17} "
          f"{'p95':>7} {'within 0.5':>11} {'within 1':>9}")
    for label, faces, m, p95, p99, fm, fp95, w05, w1 in acc:
        print(f"{label:<11} {faces:>10,} {m:14.4f} {p95:7.4f} {p99:7.4f} {fm:17.3f} {fp95:7.3f} {w05:11.3f} {w1:9.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
