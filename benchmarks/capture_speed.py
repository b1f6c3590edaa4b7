"""Time and size of one virtual-rig view at the paper's resolution, next to the PNG-write floor.

    .venv/bin/python benchmarks/capture_speed.py [--scale 1.0] [--repeat 2] [--views 4]

Prints one table: trace (geometry once per view), shading + sensor for all images, PNG
writing of the same images (the I/O floor any rig pays), the whole `capture_session`
with and without a Rerun recording, and the sizes of the session folder and the .rrd.
Ratios hold across machines; absolute times drift on shared machines.

With ``--views N`` it then times ``capture_session`` over N turntable views (lit images
included) through the acquisition driver (``workers 1``) and rendered in the worker pool
(``workers 2``, issue #22), side by side: wall seconds, CPU seconds of this process and
its worker processes, and whether the two sessions are the same file for file.
"""

from __future__ import annotations

import argparse
import filecmp
import resource
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.executor import Executor
from slscan.fsio import write_png
from slscan.viewer.recording import open_recording
from slscan.virtual.device import (
    VirtualCaptureConfig,
    capture_session,
    capture_view,
    images_per_view,
    turntable_pose,
)
from slscan.virtual.render import trace_view
from slscan.virtual.scenes import builtin_object


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=1.0, help="resolution factor (1: 1440x960 camera)")
    parser.add_argument("--repeat", type=int, default=2, help="repetitions; the median is shown")
    parser.add_argument("--views", type=int, default=0, help="also time whole captures of this many views, "
                        "1 worker (the driver) against 2 (the pool)")
    args = parser.parse_args()
    if args.views:
        compare_workers(args)
        return

    config = VirtualCaptureConfig(camera_scale=args.scale, projector_scale=args.scale,
                                  levels=min(9, int(np.log2(1024 * args.scale)) - 1))
    rig = config.rig()
    scene = builtin_object()
    pose = turntable_pose(rig, 0.0)
    patterns = config.pattern_set(rig)
    rows: dict[str, list[float]] = {k: [] for k in ("trace", "shade", "png", "session", "session_rrd")}
    sizes = {}
    for _ in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            t = time.perf_counter()
            geom = trace_view(scene, rig, pose)
            rows["trace"].append(time.perf_counter() - t)
            t = time.perf_counter()
            images, _ = capture_view(scene, rig, pose, patterns, config, geometry=geom)
            rows["shade"].append(time.perf_counter() - t)
            t = time.perf_counter()
            for rec, image in images:
                write_png(tmp / rec.file, image)
            rows["png"].append(time.perf_counter() - t)
            t = time.perf_counter()
            capture_session(config, tmp / "s1")
            rows["session"].append(time.perf_counter() - t)
            t = time.perf_counter()
            with open_recording(save=tmp / "s2.rrd") as rec:
                capture_session(config, tmp / "s2", rec=rec)
            rows["session_rrd"].append(time.perf_counter() - t)
            sizes["session"] = _size(tmp / "s1")
            sizes["rrd"] = _size(tmp / "s2.rrd")
            n_images = len(images)

    med = {k: statistics.median(v) for k, v in rows.items()}
    w, h = rig.camera.width, rig.camera.height
    print(f"virtual rig, one view of the built-in figurine, camera {w}x{h}, {n_images} images "
          f"({len(patterns)} patterns + {len(rig.lights)} lit), median of {args.repeat}")
    print(f"{'stage':<44}{'time s':>9}{'x PNG floor':>13}")
    labels = {
        "trace": "trace geometry (camera, projector, 6 lights)",
        "shade": f"shade + sensor, {n_images} images",
        "png": f"write {n_images} PNGs (I/O floor)",
        "session": "capture_session, no logging",
        "session_rrd": "capture_session + Rerun .rrd",
    }
    for key, label in labels.items():
        print(f"{label:<44}{med[key]:>9.2f}{med[key] / med['png']:>13.2f}")
    print(f"{'session folder size':<44}{sizes['session'] / 2**20:>8.1f} MiB")
    print(f"{'.rrd size (JPEG-compressed captures)':<44}{sizes['rrd'] / 2**20:>8.1f} MiB")


def _cpu() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _same(a: Path, b: Path) -> bool:
    cmp = filecmp.dircmp(a, b)
    if cmp.left_only or cmp.right_only or filecmp.cmpfiles(a, b, cmp.common_files, shallow=False)[1:] != ([], []):
        return False
    return all(_same(a / d, b / d) for d in cmp.common_dirs)


def compare_workers(args: argparse.Namespace) -> None:
    """capture_session over ``args.views`` views with 1 and 2 workers, side by side."""
    from slscan.executor import shutdown

    config = VirtualCaptureConfig(views=args.views, camera_scale=args.scale, projector_scale=args.scale,
                                  levels=min(9, int(np.log2(1024 * args.scale)) - 1))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = []
        for workers in (1, 2):
            shutdown()  # each way starts its own helpers, inside its own measurement
            cpu, t = _cpu(), time.perf_counter()
            capture_session(config, tmp / f"w{workers}", executor=Executor(workers=workers))
            shutdown()
            rows.append((workers, time.perf_counter() - t, _cpu() - cpu))
        same = _same(tmp / "w1", tmp / "w2")
    print(f"capture_session, {args.views} views of the figurine, camera {config.rig().camera.width}x"
          f"{config.rig().camera.height}, {images_per_view(config)} images per view")
    print(f"{'workers':<32}{'wall s':>9}{'CPU s':>9}{'x 1 worker wall':>17}")
    for workers, wall, cpu in rows:
        label = "1 (the acquisition driver)" if workers == 1 else f"{workers} (the worker pool)"
        print(f"{label:<32}{wall:>9.1f}{cpu:>9.1f}{wall / rows[0][1]:>17.2f}")
    print(f"the two sessions are the same file for file: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
