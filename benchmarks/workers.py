"""``slscan decode --workers 1`` and ``--workers 2`` on full-size views, optionally side
by side with an earlier version of slscan, and what a worker process pays in imports.

    .venv/bin/python benchmarks/workers.py [--views 4] [--scale 1.0] [--against REV]
        [--rounds 2]

Captures ``--views`` turntable views of the figurine on the virtual rig (hybrid
patterns, no lit images; once, reused), then times the whole ``slscan decode`` command
(a fresh process, as a user runs it) per version and worker count: wall seconds and CPU
seconds of the command and all its worker processes. The range maps of every run are
compared with those of the first (largest vertex difference, mm): the work must not
change with the workers. Then, per version, a fresh interpreter's CPU and wall seconds
to import what a decode worker imports (``slscan.decode.pipeline``) and what an albedo
worker imports (``slscan.albedo.unshade`` and Open3D, which it rasterises with).

``--against REV`` checks REV out into a temporary git worktree; the versions alternate
``--rounds`` times (these machines are shared and noisy: compare ratios taken in the
same run, not absolute times).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
TOOLBOX = HERE.parent / "toolbox"

IMPORTS = {
    "decode worker": "import slscan.decode.pipeline",
    "albedo worker": "import slscan.albedo.unshade, open3d",
}


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def time_decode(toolbox: Path, session: Path, out: Path, workers: int) -> tuple[float, float]:
    """Wall and CPU seconds (the command and its workers) of ``slscan decode``."""
    env = dict(os.environ, PYTHONPATH=str(toolbox))
    cpu, t = _children_cpu(), time.perf_counter()
    subprocess.run([sys.executable, "-m", "slscan.cli", "decode", str(session), "--out", str(out),
                    "--overwrite", "--quiet", "--workers", str(workers)],
                   env=env, check=True, capture_output=True)
    return time.perf_counter() - t, _children_cpu() - cpu


def time_import(toolbox: Path, code: str) -> tuple[float, float]:
    """CPU and wall seconds of ``code`` in a fresh interpreter (after its start-up)."""
    env = dict(os.environ, PYTHONPATH=str(toolbox))
    probe = (f"import time\nc, t = time.process_time(), time.perf_counter()\n{code}\n"
             "import json\nprint(json.dumps([time.process_time() - c, time.perf_counter() - t]))")
    out = subprocess.run([sys.executable, "-c", probe], env=env, check=True,
                         capture_output=True, text=True).stdout
    return tuple(json.loads(out.splitlines()[-1]))


def vertices(folder: Path, views: int) -> list:
    from slscan.decode.rangemap import read_ply

    return [read_ply(folder / f"view_{v:03d}.ply").vertices for v in range(views)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=4, help="turntable views of the figurine")
    parser.add_argument("--scale", type=float, default=1.0, help="resolution (1: 1440x960 camera)")
    parser.add_argument("--against", metavar="REV", help="git revision to time side by side")
    parser.add_argument("--rounds", type=int, default=2, help="alternations of the versions")
    args = parser.parse_args()

    import numpy as np

    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    config = VirtualCaptureConfig(views=args.views, camera_scale=args.scale, projector_scale=args.scale,
                                  levels=levels, lit_images=False)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        session = capture_session(config, tmp / "figurine").root
        print(f"virtual rig, figurine, {args.views} views, camera {config.rig().camera.width}x"
              f"{config.rig().camera.height} (captured in {time.perf_counter() - t:.0f} s); "
              f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
        versions = [("this working tree", TOOLBOX)]
        if args.against:
            worktree = tmp / "against"
            subprocess.run(["git", "-C", str(HERE.parent), "worktree", "add", "--detach", "-q",
                            str(worktree), args.against], check=True)
            versions.insert(0, (args.against, worktree / "toolbox"))
        reference = None
        try:
            print(f"\n{'round':<6}{'version':<20}{'workers':>8}{'wall s':>9}{'CPU s':>8}"
                  f"{'x1 wall':>9}{'vertices':>10}{'max |dv| mm':>13}")
            for k in range(1, args.rounds + 1):
                for label, toolbox in versions:
                    walls = {}
                    for workers in (1, 2):
                        out = tmp / "out"
                        wall, cpu = time_decode(toolbox, session, out, workers)
                        walls[workers] = wall
                        found = vertices(out, args.views)
                        if reference is None:
                            reference = found
                        diff = max(float(np.abs(a - b).max()) if a.shape == b.shape else float("inf")
                                   for a, b in zip(found, reference))
                        print(f"{k:<6}{label[:19]:<20}{workers:>8}{wall:>9.2f}{cpu:>8.2f}"
                              f"{walls[1] / wall:>9.2f}{sum(len(v) for v in found):>10,}{diff:>13.2g}")
            print(f"\n{'import in a fresh process':<26}{'version':<20}{'CPU s':>8}{'wall s':>9}")
            for what, code in IMPORTS.items():
                for label, toolbox in versions:
                    cpu, wall = time_import(toolbox, code)
                    print(f"{what:<26}{label[:19]:<20}{cpu:>8.2f}{wall:>9.2f}")
        finally:
            if args.against:
                subprocess.run(["git", "-C", str(HERE.parent), "worktree", "remove", "--force",
                                str(worktree)], check=False)


if __name__ == "__main__":
    main()
