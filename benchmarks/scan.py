"""Scanning through the real projector window (closed loop) next to the direct virtual scan.

    .venv/bin/python benchmarks/scan.py [--views 2] [--scale 1.0]

Both scans run through the same acquisition driver (``slscan.capture.driver.scan``) at
the paper's resolution: "virtual" with the virtual rig's projector and camera; "loop"
with the pyglet projector window on a private Xvfb (Mesa llvmpipe) and the fake camera
that renders the virtual figurine lit by an mss screen grab of that window. Prints:

(a) accuracy of each view's range map against the true surface, and whether the loop's
    images equal the direct scan's bit for bit;
(b) time per view split into move (turntable + ray tracing), show, settle, capture,
    write, and per image;
(c) the projector→camera latency measured by flashing white on the loop.

Xvfb and llvmpipe stand in for a real display and GPU: the loop's show and capture times
say what the window and the grab cost here, not what a real projector adds.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).parent))

from reconstruction import true_surface_distance

from slscan.capture.driver import measure_latency, scan
from slscan.capture.session import load_session
from slscan.decode.pipeline import decode_view
from slscan.fsio import read_png
from slscan.virtual.device import (
    VirtualCaptureConfig,
    scan_devices,
    scan_plan,
    virtual_devices,
)
from slscan.virtual.devices import ScreenLoopCamera


def _scan(kind: str, config: VirtualCaptureConfig, out: Path, x_display: str | None):
    world = virtual_devices(config)
    projector = None
    if kind == "loop":
        from slscan.devices.screen import ScreenProjector, grab_screen

        projector = ScreenProjector(0, x_display=x_display)
        camera = ScreenLoopCamera(world, lambda: grab_screen(projector), world.camera.sensor)
        devices = scan_devices(world, camera)
        devices.projector = projector
    else:
        devices = scan_devices(world)
    try:
        result = scan(devices, scan_plan(config, world.rig), out, views=config.views, calibration=world.rig)
        latency = None
        if projector is not None:
            world.stage.move_to(0, config.views)
            latency = measure_latency(projector, devices.camera, flashes=5, rest_s=0.2)
    finally:
        if projector is not None:
            projector.close()
    return world, result, latency


def _accuracy(world, session) -> list[tuple[str, int, float, float]]:
    rows = []
    for view in session.views:
        result = decode_view(session, view)
        v = result.range_map.vertices
        d = true_surface_distance(v, world.scene, view.rig_from_object)
        rows.append((view.name, len(v), float(d.mean()), float(np.percentile(d, 95))))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--scale", type=float, default=1.0, help="1: 1440x960 camera, 1024x768 projector")
    args = parser.parse_args()
    from tests.devices.conftest import _start_xvfb, _stop

    w, h = round(1024 * args.scale), round(768 * args.scale)
    proc, x_display = _start_xvfb(["-screen", "0", f"{w}x{h}x24"])
    config = VirtualCaptureConfig(views=args.views, camera_scale=args.scale, projector_scale=args.scale)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            runs = {kind: _scan(kind, config, Path(tmp) / kind, x_display) for kind in ("virtual", "loop")}
            sessions = {kind: load_session(Path(tmp) / kind) for kind in runs}
            identical = all(
                np.array_equal(read_png(sessions["virtual"].image_path(v, r)),
                               read_png(sessions["loop"].image_path(sessions["loop"].view(v.name), r)))
                for v in sessions["virtual"].views for r in v.images
            )
            print(f"(a) range maps vs the true surface ({args.views} views, camera "
                  f"{sessions['virtual'].camera_size[0]}x{sessions['virtual'].camera_size[1]})")
            print(f"{'path':<8} {'view':<9} {'vertices':>9} {'mean mm':>8} {'p95 mm':>8}")
            for kind, (world, _, _) in runs.items():
                for name, n, mean, p95 in _accuracy(world, sessions[kind]):
                    print(f"{kind:<8} {name:<9} {n:>9} {mean:>8.4f} {p95:>8.4f}")
            print(f"loop images identical to the virtual scan's, bit for bit: {identical}")
            print()
            print("(b) seconds per view (mean over views) and per image")
            print(f"{'path':<8} {'images':>6} {'move':>6} {'show':>6} {'settle':>6} {'capture':>7} {'write':>6} "
                  f"{'total':>6} {'/image':>7}")
            for kind, (_, result, _) in runs.items():
                t = result.timings
                m = {k: statistics.mean(getattr(x, k) for x in t)
                     for k in ("move", "show", "settle", "capture", "write", "total")}
                images = t[0].images
                print(f"{kind:<8} {images:>6} {m['move']:>6.2f} {m['show']:>6.2f} {m['settle']:>6.2f} "
                      f"{m['capture']:>7.2f} {m['write']:>6.2f} {m['total']:>6.2f} {m['total'] / images:>7.3f}")
            latency = runs["loop"][2]
            print()
            print("(c) projector->camera latency on the loop (Xvfb window, screen-grab camera)")
            print("flashes ms: " + ", ".join(f"{1000 * d:.1f}" for d in latency.delays)
                  + f"; frame {1000 * latency.frame_s:.1f} ms; settle {1000 * latency.settle_s:.1f} ms")
    finally:
        _stop(proc)


if __name__ == "__main__":
    main()
