"""Lens and sensor effects of the virtual rig: render cost per view and the figurine's decode
error with each effect alone, next to none, in one run.

    .venv/bin/python benchmarks/optics.py [--scale 0.5] [--repeat 1] [--effects dof,tone,vignetting,jpeg]

For each row (no effect, each effect alone at its defaults — ``dof`` f/2 focused at the
working distance, ``tone`` projector gamma 2.2 + sRGB camera, ``vignetting`` the full cos⁴
law, ``jpeg`` quality 90 — then all of them together) one view of the built-in figurine
is captured with hybrid and Gray-code patterns (``patterns="both"``, noise on, seed 0):

- render: ``capture_view`` on the traced geometry (shading + sensor of every image, the
  JPEG round trip included), CPU (this process, all threads) and wall seconds, median of
  ``--repeat``, and the CPU time relative to no effect;
- session: the whole ``capture_session`` through the driver (trace, render, write PNG or
  JPEG files), CPU and wall seconds;
- per decoder (hybrid, Gray): mean and p95 distance (mm) of the range map's vertices to the
  true surface, share of vertices off by more than 1 mm, and coverage (share of the
  projector-lit pixels under range-map triangles).

Ratios hold across machines; absolute times drift on shared machines.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from reconstruction import coverage, true_surface_distance

from slscan.capture.session import LIT, load_session
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.virtual.device import VirtualCaptureConfig, capture_session, capture_view
from slscan.virtual.devices import turntable_pose
from slscan.virtual.effects import parse_effects
from slscan.virtual.render import trace_view

OPTICS = ("dof", "tone", "vignetting", "jpeg")


def render_seconds(config: VirtualCaptureConfig, repeat: int) -> tuple[float, float]:
    """(CPU s, wall s) of rendering one view's images on traced geometry, median of ``repeat``."""
    rig = config.rig()
    scene = config.build_scene()
    pose = turntable_pose(rig, 0.0, scene.placement)
    geom = trace_view(scene, rig, pose)
    patterns = config.pattern_set(rig)
    cpu, wall = [], []
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        capture_view(scene, rig, pose, patterns, config, geometry=geom)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return statistics.median(cpu), statistics.median(wall)


def decode_errors(session, method: str) -> tuple[float, float, float, float]:
    """(mean mm, p95 mm, share > 1 mm, coverage) of ``method``'s range map of view 0."""
    view = session.views[0]
    truth = session.load_ground_truth(view)
    scene = VirtualCaptureConfig().build_scene()
    rm = decode_view(session, view, DecodeConfig(method=method)).range_map
    if len(rm.vertices) == 0:
        return np.nan, np.nan, np.nan, 0.0
    d = true_surface_distance(rm.vertices, scene, view.rig_from_object)
    cov, _ = coverage(rm, session.calibration.camera, truth.visibility == LIT)
    return float(d.mean()), float(np.percentile(d, 95)), float(np.mean(d > 1.0)), cov


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=0.5, help="camera and projector size (1: 1440x960, 1024x768)")
    ap.add_argument("--repeat", type=int, default=1, help="render repetitions; the median is shown")
    ap.add_argument("--effects", default=",".join(OPTICS), help="effects to show alone (comma-separated)")
    args = ap.parse_args()
    names = parse_effects(args.effects, "--effects")
    rows = [("none", ())] + [(n, (n,)) for n in names] + ([("all four", names)] if len(names) > 1 else [])
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    base = {"scene": "object", "views": 1, "patterns": "both", "levels": levels,
            "camera_scale": args.scale, "projector_scale": args.scale}
    rig = VirtualCaptureConfig(**base).rig()
    print(f"virtual rig, one view of the built-in figurine, camera {rig.camera.width}x{rig.camera.height}, "
          f"projector {rig.projector.lens.width}x{rig.projector.lens.height}, hybrid ({levels} levels) + Gray "
          f"patterns, render median of {args.repeat}")
    head = (f"{'effects':<12}{'render CPU s':>13}{'wall s':>8}{'x none':>8}{'session CPU':>13}{'wall s':>8}"
            + "".join(f"{m + ' mean':>13}{'p95':>8}{'>1mm':>8}{'cov':>7}" for m in ("hybrid", "gray")))
    print(head)
    print("-" * len(head))
    ref = None
    with tempfile.TemporaryDirectory() as tmp:
        for label, effects in rows:
            config = VirtualCaptureConfig(**base, effects=effects)
            cpu, wall = render_seconds(config, args.repeat)
            ref = ref or cpu
            c, t = time.process_time(), time.perf_counter()
            capture_session(config, Path(tmp) / label)
            session_cpu, session_s = time.process_time() - c, time.perf_counter() - t
            session = load_session(Path(tmp) / label)
            line = (f"{label:<12}{cpu:>13.2f}{wall:>8.2f}{cpu / ref:>8.2f}{session_cpu:>13.2f}"
                    f"{session_s:>8.2f}")
            for method in ("hybrid", "gray"):
                mean, p95, gross, cov = decode_errors(session, method)
                line += f"{mean:>13.4f}{p95:>8.4f}{gross:>8.4f}{cov:>7.3f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
