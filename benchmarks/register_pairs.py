"""Which view pairs registration aligns, and what that costs, as the number of views grows.

    .venv/bin/python benchmarks/register_pairs.py [--views 24,48] [--against REV]
        [--max-neighbours 8] [--perturb-deg 3] [--perturb-mm 3] [--seed 1]

Synthetic range scans of the virtual rig's figurine (``builtin_object``, about 250 x 380 x
270 mm), ray cast orthographically (2 mm pixels) from N views of a turntable campaign:
N/3 turntable angles at each of three elevations (-25, 15 and 55 degrees). Every view's
start pose is its true pose moved by a random rotation up to ``--perturb-deg`` and a
translation up to ``--perturb-mm`` (recorded turntable poses in error; view 0 holds the
frame and keeps its true pose).

For each N, side by side in the same run, each registration in its own subprocess:

- "all pairs": ``register_scans`` with ``max_neighbours=0`` (every candidate pair whose
  samples overlap under the start poses is aligned: the behaviour before pruning);
- "k nearest": the default (each scan's ``max_neighbours`` best candidates, the pose
  graph kept connected);
- with ``--against REV``: the toolbox of git revision REV (exported with ``git archive``)
  with its own defaults.

Columns: pairwise alignments tried (progress ticks), CPU seconds of the registration
(``time.process_time()``, all threads; making the scans excluded), wall seconds, and the
worst view's rotation (degrees) and translation at its centroid (mm) against the true
poses. The last lines extrapolate each method's CPU time to 146 views by a least-squares
fit ``cpu = a N + b N^2`` over the N measured (needs two N or more).

``--bunny-seeds 1,2,...`` instead registers the Stanford bunny from bun.conf perturbed
by up to ``--bunny-deg`` degrees / ``--bunny-mm`` mm (default 20 / 20, seeds as given;
bun000 kept), all candidate pairs against the k nearest, and prints per seed the scans
left out, the worst scan's error against bun.conf and the largest difference between
the two results: the robustness from perturbed starts, side by side.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ELEVATIONS = (-25.0, 15.0, 55.0)


def campaign(n: int) -> list[np.ndarray]:
    """True world_from_scan of n views: n/3 turntable angles at each elevation (y is the
    turntable axis, the rig's y points down, so positive elevations look from above)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from synthetic_poses import looking_from

    per = max(1, n // len(ELEVATIONS))
    poses = []
    for e, elevation in enumerate(ELEVATIONS):
        for k in range(per):
            azimuth = math.radians(360.0 * k / per + e * 180.0 / per)
            el = math.radians(elevation)
            direction = [math.cos(el) * math.sin(azimuth), -math.sin(el),
                         math.cos(el) * math.cos(azimuth)]
            poses.append(looking_from(direction))
    return poses[:n]


def make_scans(n: int):
    from slscan.register.rangescan import raycasting_scene, render_range_scan
    from slscan.virtual.scenes import builtin_object

    scene = builtin_object()
    ray_scene = raycasting_scene(scene.vertices, scene.triangles)
    truth = campaign(n)
    scans = [render_range_scan(None, None, pose, shape=(220, 220), pixel=2.0, name=f"v{k:03d}",
                               scene=ray_scene) for k, pose in enumerate(truth)]
    return scans, {s.name: p for s, p in zip(scans, truth)}


def perturbed(truth: dict, deg: float, mm: float, seed: int) -> dict:
    from slscan.register.pairwise import rigid_transform

    rng = np.random.default_rng(seed)
    out = {}
    for name, pose in truth.items():
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        motion = rigid_transform(axis / np.linalg.norm(axis) * math.radians(rng.uniform(0, deg)),
                                 direction / np.linalg.norm(direction) * rng.uniform(0, mm))
        out[name] = pose if name == "v000" else motion @ pose
    return out


def stage(args) -> dict:
    """One registration (in this subprocess): its cost and worst pose error."""
    import warnings

    from slscan.register.multiview import MultiviewConfig, register_scans
    from slscan.register.pairwise import pose_error

    scans, truth = make_scans(args.n)
    start = perturbed(truth, args.perturb_deg, args.perturb_mm, args.seed)
    config = MultiviewConfig()
    if args.k is not None:
        config = MultiviewConfig(max_neighbours=args.k)
    ticks = []
    t, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = register_scans(scans, initial_poses=start, reference="v000", config=config,
                                progress=ticks.append)
    seconds, cpu = time.perf_counter() - t, time.process_time() - cpu
    by_name = {s.name: s for s in scans}
    errors = [pose_error(p, truth[k], at=by_name[k].vertices.mean(axis=0))
              for k, p in result.poses.items()]
    start_err = [pose_error(p, truth[k], at=by_name[k].vertices.mean(axis=0))
                 for k, p in start.items()]
    return {"tried": len(ticks), "cpu": cpu, "seconds": seconds,
            "rot": max(e[0] for e in errors), "tr": max(e[1] for e in errors),
            "start_rot": max(e[0] for e in start_err), "start_tr": max(e[1] for e in start_err),
            "registered": len(result.poses), "edges": len(result.pairs),
            "points": int(np.median([s.n_vertices for s in scans]))}


def _run(args, n: int, *, k: int | None, toolbox: Path | None = None) -> dict:
    command = [sys.executable, __file__, "--stage", "--n", str(n), "--seed", str(args.seed),
               "--perturb-deg", str(args.perturb_deg), "--perturb-mm", str(args.perturb_mm)]
    if k is not None:
        command += ["--k", str(k)]
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from measure import run_json

    return run_json(command, f"registration of {n} views (k={k})", toolbox)



def bunny_robustness(args) -> None:
    import warnings

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bunny  # the bunny benchmark's perturbation, at this size

    from slscan.data import shared_data_dir
    from slscan.register.multiview import MultiviewConfig, register_scans
    from slscan.register.pairwise import pose_error
    from slscan.register.rangescan import load_stanford_dir

    bunny.DEG, bunny.MM = args.bunny_deg, args.bunny_mm
    scans, truth = load_stanford_dir(shared_data_dir() / "stanford_bunny")
    by_name = {s.name: s for s in scans}
    k = args.max_neighbours if args.max_neighbours is not None else MultiviewConfig().max_neighbours
    print(f"Stanford bunny from bun.conf perturbed by up to {args.bunny_deg:g} deg / "
          f"{args.bunny_mm:g} mm: all candidate pairs (k=0) vs k={k}; worst scan vs bun.conf "
          "(rotation deg / translation at its centroid mm); diff: largest difference between "
          "the two results")
    print(f"{'seed':>4} {'start':>13} | {'k=0 left out':>14} {'worst':>13} {'pairs':>5} "
          f"{'cpu s':>6} | {f'k={k} left out':>14} {'worst':>13} {'pairs':>5} {'cpu s':>6} | "
          f"{'diff':>13}")
    for seed in [int(v) for v in args.bunny_seeds.split(",") if v.strip()]:
        start = bunny.perturbed(truth, seed)
        row, results = [], []
        for kk in (0, k):
            ticks = []
            cpu = time.process_time()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = register_scans(scans, initial_poses=start, reference="bun000",
                                   config=MultiviewConfig(max_neighbours=kk), progress=ticks.append)
            cpu = time.process_time() - cpu
            err = [pose_error(p, truth[n], at=by_name[n].vertices.mean(axis=0))
                   for n, p in r.poses.items()]
            row.append(f"{','.join(sorted(r.left_out)) or '-':>14} "
                       f"{max(e[0] for e in err):6.3f}/{max(e[1] for e in err):6.3f} "
                       f"{len(ticks):>5} {cpu:6.1f}")
            results.append(r.poses)
        both = set(results[0]) & set(results[1])
        diff = [pose_error(results[1][n], results[0][n], at=by_name[n].vertices.mean(axis=0))
                for n in both]
        s0 = [pose_error(p, truth[n], at=by_name[n].vertices.mean(axis=0)) for n, p in start.items()]
        print(f"{seed:>4} {max(e[0] for e in s0):6.2f}/{max(e[1] for e in s0):6.2f} | {row[0]} | "
              f"{row[1]} | {max(e[0] for e in diff):6.3f}/{max(e[1] for e in diff):6.3f}")


def _extrapolate(ns: list[int], cpus: list[float], to: int = 146) -> float:
    a = np.array([[n, n * n] for n in ns], float)
    coef, *_ = np.linalg.lstsq(a, np.array(cpus), rcond=None)
    return float(coef[0] * to + coef[1] * to * to)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", default="24,48", help="numbers of views, comma-separated")
    parser.add_argument("--against", metavar="REV", help="also run git revision REV's toolbox")
    parser.add_argument("--max-neighbours", type=int, default=None,
                        help="k of the pruned run (default: MultiviewConfig's)")
    parser.add_argument("--perturb-deg", type=float, default=3.0)
    parser.add_argument("--perturb-mm", type=float, default=3.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--bunny-seeds", help="robustness on the bunny instead: seeds, comma-separated")
    parser.add_argument("--bunny-deg", type=float, default=20.0)
    parser.add_argument("--bunny-mm", type=float, default=20.0)
    parser.add_argument("--stage", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--n", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--k", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.stage:
        print(json.dumps(stage(args)))
        return
    if args.bunny_seeds:
        bunny_robustness(args)
        return
    ns = [int(v) for v in args.views.split(",") if v.strip()]
    methods = {"all pairs (k=0)": {"k": 0}, "k nearest": {"k": args.max_neighbours}}
    rows: dict[str, dict[int, dict]] = {m: {} for m in methods}
    with tempfile.TemporaryDirectory(prefix="slscan-pairs-") as tmp:
        toolbox = None
        if args.against:
            sys.path.insert(0, str(Path(__file__).resolve().parent))
            from measure import export_toolbox

            toolbox = export_toolbox(args.against, Path(tmp) / "against")
            rows[f"rev {args.against}"] = {}
        for n in ns:
            for label, kw in methods.items():
                rows[label][n] = _run(args, n, **kw)
            if toolbox is not None:
                rows[f"rev {args.against}"][n] = _run(args, n, k=None, toolbox=toolbox)
    print(f"registration of N synthetic turntable views of the figurine ({os.cpu_count()} CPUs), "
          f"start poses off by up to {args.perturb_deg:g} deg / {args.perturb_mm:g} mm")
    print(f"{'method':<20} {'N':>4} {'pairs':>6} {'of':>6} {'cpu s':>8} {'wall s':>8} "
          f"{'cpu/pair':>8} {'max rot':>8} {'max tr':>7} {'views':>7} {'edges':>6}")
    for label, by_n in rows.items():
        for n, r in by_n.items():
            print(f"{label:<20} {n:>4} {r['tried']:>6} {n * (n - 1) // 2:>6} {r['cpu']:>8.1f} "
                  f"{r['seconds']:>8.1f} {r['cpu'] / max(r['tried'], 1):>8.2f} {r['rot']:>8.3f} "
                  f"{r['tr']:>7.3f} {r['registered']:>3}/{n:<3} {r['edges']:>6}")
    first = rows["k nearest"][ns[0]]
    print(f"    start poses: worst {first['start_rot']:.2f} deg / {first['start_tr']:.2f} mm; "
          f"~{first['points']} samples per scan; pairs: alignments tried, of N(N-1)/2; "
          "edges: overlapping pairs after the global step")
    if len(ns) >= 2:
        for label, by_n in rows.items():
            est = _extrapolate(list(by_n), [r["cpu"] for r in by_n.values()])
            print(f"    {label}: 146 views extrapolated (cpu = a N + b N^2): {est:,.0f} s CPU")


if __name__ == "__main__":
    main()
