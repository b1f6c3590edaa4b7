"""Time and size of one virtual-rig view at the paper's resolution, next to the PNG-write floor.

    .venv/bin/python benchmarks/capture_speed.py [--scale 1.0] [--repeat 2]

Prints one table: trace (geometry once per view), shading + sensor for all images, PNG
writing of the same images (the I/O floor any rig pays), the whole `capture_session`
with and without a Rerun recording, and the sizes of the session folder and the .rrd.
Ratios hold across machines; absolute times drift on shared machines.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.fsio import write_png
from slscan.viewer.recording import open_recording
from slscan.virtual.device import (
    VirtualCaptureConfig,
    capture_session,
    capture_view,
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
    args = parser.parse_args()

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


if __name__ == "__main__":
    main()
