"""Registration from exact turntable poses: does ICP leave good poses where they are?

    .venv/bin/python benchmarks/register_poses.py [--seeds 0,1,2,3] [--sizes reduced,demo]
        [--tolerances auto,5] [--against REV] [--work DIR]

The demo recipe (``recipes/demo.toml``: the virtual rig's figurine, 8 turntable views,
default rendering and decoder) is captured and decoded for each seed at each size:
``reduced`` is the recipe's ``[recipe.reduced]`` (quarter-size images, 7 levels: sparse
range maps, ~5 mm sample spacing), ``demo`` the recipe as it is (half size, ~2.6 mm). The
virtual turntable is exact, so the poses the capture records are the true ones. Each
set of range maps is then registered from those poses, each registration in its own
process, side by side in the same run:

- this working tree, with each ``--tolerances`` value (``auto``: no ``pose_tolerance``,
  the default; a number: ``pose_tolerance`` in mm);
- with ``--against REV``: the toolbox of git revision REV (``git archive``), the same.

Per registration: views registered and kept on one turntable axis (of 8; the test the
demo's object frame makes, :func:`slscan.register.frame.turntable_axis`), and the worst
and median view's pose error against the true poses: rotation (degrees) and translation
at the view's centroid (mm). View 0 holds the frame. ``--work DIR`` keeps the captures
(a second run reuses them).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np
from measure import export_toolbox, run_json

ROOT = Path(__file__).resolve().parents[1]
SIZES = ("reduced", "demo")


def capture(size: str, seed: int, work: Path) -> Path:
    """Range maps of the demo recipe at ``size`` for capture seed ``seed`` (cached in ``work``)."""
    from slscan.recipe.runner import parse_recipe, run_recipe

    data = tomllib.loads((ROOT / "recipes" / "demo.toml").read_text())
    data["recipe"]["stages"] = ["capture", "decode"]
    for name in list(data):
        if name not in ("recipe", "capture", "decode"):
            data.pop(name)
    data["recipe"]["reduced"] = {k: v for k, v in data["recipe"]["reduced"].items()
                                 if k.split(".")[0] in ("capture", "decode")}
    recipe = parse_recipe(data, where="demo", path=ROOT / "recipes" / "demo.toml",
                          overrides=[f"capture.seed={seed}"], reduced=size == "reduced")
    out = work / f"{size}-{seed}"
    run_recipe(recipe, out)
    return out / "decode"


def child(args: argparse.Namespace) -> dict:
    """Register one set of range maps from its recorded (true) poses; errors per view."""
    import warnings

    from slscan.register.command import load_scans
    from slscan.register.frame import turntable_axis
    from slscan.register.multiview import MultiviewConfig, register_scans

    scans, truth = load_scans(Path(args.maps))
    tolerance = None if args.tolerance == "auto" else float(args.tolerance)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = register_scans(scans, initial_poses=truth, config=MultiviewConfig(pose_tolerance=tolerance))
    rot, trans = [], []
    for scan in scans:
        if scan.name not in result.poses:
            continue
        pose, true = result.poses[scan.name], truth[scan.name]
        delta = np.linalg.inv(true) @ pose
        rot.append(math.degrees(math.acos(float(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1)))))
        centroid = scan.vertices.mean(axis=0)
        trans.append(float(np.linalg.norm((pose[:3, :3] - true[:3, :3]) @ centroid + pose[:3, 3] - true[:3, 3])))
    axis = turntable_axis(result.poses) if len(result.poses) > 1 else None
    return {"views": len(scans), "registered": len(result.poses), "on_axis": len(axis[2]) if axis else 0,
            "rot": rot, "trans": trans}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="0,1,2,3", help="capture seeds (default 0,1,2,3)")
    p.add_argument("--sizes", default="reduced,demo", help="reduced and/or demo (default both)")
    p.add_argument("--tolerances", default="auto,5", help="pose_tolerance values: auto (none given) or mm")
    p.add_argument("--against", metavar="REV", help="also register with the toolbox of git revision REV")
    p.add_argument("--work", type=Path, help="keep the captures in this folder (default: a temporary one)")
    p.add_argument("--maps", help=argparse.SUPPRESS)
    p.add_argument("--tolerance", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.maps:
        print(json.dumps(child(args)))
        return
    sizes = [s for s in args.sizes.split(",") if s]
    for size in sizes:
        if size not in SIZES:
            raise SystemExit(f"--sizes: expected reduced and/or demo, got {size!r}")
    seeds = [int(s) for s in args.seeds.split(",") if s]
    tolerances = [t for t in args.tolerances.split(",") if t]
    with tempfile.TemporaryDirectory(prefix="slscan-register-poses-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        toolboxes = {"this tree": None}
        if args.against:
            toolboxes[args.against] = export_toolbox(args.against, Path(tmp) / "against")
        header = (f"{'size':8} {'seed':>4}  {'code':12} {'tolerance':>9}  {'on axis':>7}  "
                  f"{'rot max':>7} {'rot med':>7}  {'mm max':>7} {'mm med':>7}")
        print(header)
        print("-" * len(header))
        summary: dict[tuple[str, str, str], list[dict]] = {}
        for size in sizes:
            for seed in seeds:
                maps = capture(size, seed, work)
                for code, toolbox in toolboxes.items():
                    for tol in tolerances:
                        r = run_json([sys.executable, __file__, "--maps", str(maps), "--tolerance", tol],
                                     f"registration ({code}, {size}, seed {seed}, tolerance {tol})", toolbox)
                        summary.setdefault((size, code, tol), []).append(r)
                        print(f"{size:8} {seed:>4}  {code:12} {tol:>9}  {r['on_axis']:>3}/{r['views']:<3}  "
                              f"{max(r['rot']):7.3f} {np.median(r['rot']):7.3f}  "
                              f"{max(r['trans']):7.2f} {np.median(r['trans']):7.2f}", flush=True)
        print("\nover the seeds (views on the axis: total; errors: worst view of any seed, median of "
              "the seeds' medians)")
        for (size, code, tol), rows in summary.items():
            print(f"{size:8} {'all':>4}  {code:12} {tol:>9}  "
                  f"{sum(r['on_axis'] for r in rows):>3}/{sum(r['views'] for r in rows):<3}  "
                  f"{max(max(r['rot']) for r in rows):7.3f} {np.median([np.median(r['rot']) for r in rows]):7.3f}  "
                  f"{max(max(r['trans']) for r in rows):7.2f} {np.median([np.median(r['trans']) for r in rows]):7.2f}")


if __name__ == "__main__":
    try:
        main()
    except subprocess.CalledProcessError as exc:  # pragma: no cover
        raise SystemExit(str(exc)) from None
