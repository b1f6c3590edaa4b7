"""Decode + triangulate time per view against the PNG-reading floor, optionally side by
side with an earlier version of slscan.

    .venv/bin/python benchmarks/decode_speed.py [--scale 1.0] [--repeat 9] [--against REV]
        [--rounds 2]

Captures the figurine and the flat tile on the virtual rig (both pattern families,
default noise) and prints, per scene and decoder, the median over ``--repeat`` runs of:
the time to read the view's PNGs (flat frames + that decoder's patterns; the I/O floor),
the decode time (reading included) and the triangulation time, and the ratio
(decode + triangulate) / load — the figure of benchmarks/reconstruction.py (e) — in wall
seconds and in CPU seconds of the process (its reading thread included). Loading and
decoding are taken in turn, so both see the same machine load.

``--against REV`` checks REV out into a temporary git worktree and times it and the
working tree on the same sessions, alternating the two ``--rounds`` times (these
machines are shared and noisy: compare ratios taken in the same run); the working
tree's rows then also give the largest vertex difference (mm) of its range maps from
REV's and whether their vertex and face counts match (accuracy: identical maps measure
alike).
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


def time_sessions(paths: list[Path], repeat: int, dump: Path | None = None) -> list[dict]:
    """Rows of timings for each session folder and decoder (run with the slscan on sys.path);
    the range maps' vertices and faces saved to ``dump`` (.npz) when given."""
    import numpy as np

    from slscan.capture.session import load_session
    from slscan.decode import pipeline
    from slscan.decode.pipeline import DecodeConfig, decode_view
    from slscan.fsio import read_png

    mesh_cpu = []  # the meshing's CPU, left out of decode + triangulate's

    def build_range_map(*args, **kwargs):
        c = time.process_time()
        try:
            return meshing(*args, **kwargs)
        finally:
            mesh_cpu.append(time.process_time() - c)

    meshing, pipeline.build_range_map = pipeline.build_range_map, build_range_map

    rows, maps = [], {}
    for path in paths:
        session = load_session(path)
        view = session.views[0]
        for method in ("hybrid", "gray"):
            recs = [
                r for r in view.pattern_images()
                if session.pattern(r.pattern).family in (method, "flat")
            ]
            loads, decodes, triangulates, load_cpu, work_cpu = [], [], [], [], []
            for _ in range(repeat):
                t, c = time.perf_counter(), time.process_time()
                for rec in recs:
                    read_png(session.image_path(view, rec))
                loads.append(time.perf_counter() - t)
                load_cpu.append(time.process_time() - c)
                c = time.process_time()
                result = decode_view(session, view, DecodeConfig(method=method))
                seconds = result.seconds
                decodes.append(seconds["decode"])
                triangulates.append(seconds["triangulate"])
                work_cpu.append(time.process_time() - c - mesh_cpu.pop())
            maps[f"{path.name}/{method}/vertices"] = result.range_map.vertices
            maps[f"{path.name}/{method}/faces"] = result.range_map.faces
            rows.append({
                "scene": path.name, "method": method, "images": len(recs),
                "load": statistics.median(loads), "load_cpu": statistics.median(load_cpu),
                "decode": statistics.median(decodes),
                "triangulate": statistics.median(triangulates),
                "work_cpu": statistics.median(work_cpu),
                "ratio": statistics.median(
                    (d + t) / lo for d, t, lo in zip(decodes, triangulates, loads)
                ),
                "ratio_cpu": statistics.median(w / lo for w, lo in zip(work_cpu, load_cpu)),
            })
    if dump is not None:
        np.savez(dump, **maps)
    return rows


def compare_maps(rows: list[dict], mine: Path, theirs: Path) -> None:
    """Add to ``rows`` how far the range maps in ``mine`` are from those in ``theirs``."""
    import numpy as np

    with np.load(mine) as a, np.load(theirs) as b:
        for r in rows:
            key = f"{r['scene']}/{r['method']}"
            va, vb = a[f"{key}/vertices"], b[f"{key}/vertices"]
            same = va.shape == vb.shape and np.array_equal(a[f"{key}/faces"], b[f"{key}/faces"])
            r["vertices"] = len(va)
            r["same_mesh"] = same
            r["max_dv"] = float(np.max(np.abs(va - vb), initial=0.0)) if va.shape == vb.shape else None


def run_version(toolbox: Path, paths: list[Path], repeat: int, dump: Path | None = None) -> list[dict]:
    """:func:`time_sessions` in a fresh interpreter importing slscan from ``toolbox``."""
    env = dict(os.environ, PYTHONPATH=str(toolbox))
    extra = ["--dump", str(dump)] if dump is not None else []
    out = subprocess.run(
        [sys.executable, __file__, "--worker", "--repeat", str(repeat), *extra, *map(str, paths)],
        env=env, check=True, capture_output=True, text=True,
    ).stdout
    return json.loads(out.splitlines()[-1])


def print_table(label: str, rows: list[dict]) -> None:
    print(f"\n{label}")
    compared = any("vertices" in r for r in rows)
    print(f"{'scene':<10}{'method':<7}{'images':>7}{'load s':>8}{'CPU s':>7}{'decode s':>9}"
          f"{'triang. s':>10}{'CPU s':>7}{'x load':>7}{'CPU x':>7}"
          + (f"{'vertices':>9}{'max |dv| mm':>12}{'faces':>6}" if compared else ""))
    for r in rows:
        line = (f"{r['scene']:<10}{r['method']:<7}{r['images']:>7d}{r['load']:>8.3f}"
                f"{r['load_cpu']:>7.3f}{r['decode']:>9.3f}{r['triangulate']:>10.3f}"
                f"{r['work_cpu']:>7.3f}{r['ratio']:>7.2f}{r['ratio_cpu']:>7.2f}")
        if compared:
            dv = "n/a" if r["max_dv"] is None else f"{r['max_dv']:.2g}"
            line += f"{r['vertices']:>9d}{dv:>12}{'same' if r['same_mesh'] else 'DIFF':>6}"
        print(line)
    print("load s / CPU s: reading the PNGs, wall / CPU; decode s (reading included) and "
          "triang. s: wall; CPU s: decode + triangulate; x load: (decode + triang.) / load, "
          "wall; CPU x: the same in CPU")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--scale", type=float, default=1.0, help="resolution (1: 1440x960 camera)")
    parser.add_argument("--repeat", type=int, default=9, help="runs per figure (median)")
    parser.add_argument("--against", metavar="REV", help="git revision to time side by side")
    parser.add_argument("--rounds", type=int, default=2, help="alternations with --against")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--dump", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("sessions", nargs="*", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(time_sessions(args.sessions, args.repeat, args.dump)))
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
            theirs, mine = tmp / "against.npz", tmp / "mine.npz"
            for k in range(1, args.rounds + 1):
                print_table(f"round {k}: {args.against}",
                            run_version(worktree / "toolbox", paths, args.repeat, theirs))
                rows = run_version(TOOLBOX, paths, args.repeat, mine)
                compare_maps(rows, mine, theirs)
                print_table(f"round {k}: this working tree (range maps against {args.against})", rows)
        finally:
            subprocess.run(["git", "-C", str(HERE.parent), "worktree", "remove", "--force",
                            str(worktree)], check=False)


if __name__ == "__main__":
    main()
