"""Decode + triangulate time per view against the PNG-reading floor, optionally side by
side with an earlier version of slscan.

    .venv/bin/python benchmarks/decode_speed.py [--scale 1.0] [--repeat 9] [--against REV]
        [--rounds 2]

Captures the figurine and the flat tile on the virtual rig (both pattern families,
default noise) and prints, per scene and decoder, the median over ``--repeat`` runs of:
the time to read the view's PNGs (flat frames + that decoder's patterns; the I/O floor),
the decode time (reading included) and the triangulation time, and the ratio
(decode + triangulate) / load — the figure of benchmarks/reconstruction.py (e). Loading
and decoding are taken in turn, so both see the same machine load.

``--against REV`` checks REV out into a temporary git worktree and times it and the
working tree on the same sessions, alternating the two ``--rounds`` times (these
machines are shared and noisy: compare ratios taken in the same run).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

HERE = Path(__file__).resolve().parent
TOOLBOX = HERE.parent / "toolbox"


def time_sessions(paths: list[Path], repeat: int) -> list[dict]:
    """Rows of timings for each session folder and decoder (run with the slscan on sys.path)."""
    from slscan.capture.session import load_session
    from slscan.decode.pipeline import DecodeConfig, decode_view
    from slscan.fsio import read_png

    rows = []
    for path in paths:
        session = load_session(path)
        view = session.views[0]
        for method in ("hybrid", "gray"):
            recs = [
                r for r in view.pattern_images()
                if session.pattern(r.pattern).family in (method, "flat")
            ]
            loads, decodes, triangulates = [], [], []
            for _ in range(repeat):
                t = time.perf_counter()
                for rec in recs:
                    read_png(session.image_path(view, rec))
                loads.append(time.perf_counter() - t)
                seconds = decode_view(session, view, DecodeConfig(method=method)).seconds
                decodes.append(seconds["decode"])
                triangulates.append(seconds["triangulate"])
            rows.append({
                "scene": path.name, "method": method, "images": len(recs),
                "load": statistics.median(loads), "decode": statistics.median(decodes),
                "triangulate": statistics.median(triangulates),
                "ratio": statistics.median(
                    (d + t) / lo for d, t, lo in zip(decodes, triangulates, loads)
                ),
            })
    return rows


def run_version(toolbox: Path, paths: list[Path], repeat: int) -> list[dict]:
    """:func:`time_sessions` in a fresh interpreter importing slscan from ``toolbox``."""
    env = dict(os.environ, PYTHONPATH=str(toolbox))
    out = subprocess.run(
        [sys.executable, __file__, "--worker", "--repeat", str(repeat), *map(str, paths)],
        env=env, check=True, capture_output=True, text=True,
    ).stdout
    return json.loads(out.splitlines()[-1])


def print_table(label: str, rows: list[dict]) -> None:
    print(f"\n{label}")
    print(f"{'scene':<10}{'method':<8}{'images':>7}{'load PNGs s':>12}{'decode s':>10}"
          f"{'triang. s':>10}{'dec+tri x load':>16}")
    for r in rows:
        print(f"{r['scene']:<10}{r['method']:<8}{r['images']:>7d}{r['load']:>12.3f}"
              f"{r['decode']:>10.3f}{r['triangulate']:>10.3f}{r['ratio']:>16.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scale", type=float, default=1.0, help="resolution (1: 1440x960 camera)")
    parser.add_argument("--repeat", type=int, default=9, help="runs per figure (median)")
    parser.add_argument("--against", metavar="REV", help="git revision to time side by side")
    parser.add_argument("--rounds", type=int, default=2, help="alternations with --against")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("sessions", nargs="*", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(time_sessions(args.sessions, args.repeat)))
        return

    import numpy as np

    from slscan.virtual.device import VirtualCaptureConfig, capture_session

    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    base = VirtualCaptureConfig(camera_scale=args.scale, projector_scale=args.scale,
                                levels=levels, lit_images=False, patterns="both")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        paths = [capture_session(base, tmp / "figurine").root,
                 capture_session(replace(base, scene="tile"), tmp / "tile").root]
        print(f"virtual rig, camera {base.rig().camera.width}x{base.rig().camera.height}, "
              f"medians of {args.repeat} runs, loading and decoding in turn")
        if not args.against:
            print_table("this working tree", run_version(TOOLBOX, paths, args.repeat))
            return
        worktree = tmp / "against"
        subprocess.run(["git", "-C", str(HERE.parent), "worktree", "add", "--detach", "-q",
                        str(worktree), args.against], check=True)
        try:
            for k in range(1, args.rounds + 1):
                print_table(f"round {k}: {args.against}",
                            run_version(worktree / "toolbox", paths, args.repeat))
                print_table(f"round {k}: this working tree",
                            run_version(TOOLBOX, paths, args.repeat))
        finally:
            subprocess.run(["git", "-C", str(HERE.parent), "worktree", "remove", "--force",
                            str(worktree)], check=False)


if __name__ == "__main__":
    main()
