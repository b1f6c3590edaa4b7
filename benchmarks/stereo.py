"""Two cameras, one projector: code matching between cameras vs camera-projector triangulation.

    .venv/bin/python benchmarks/stereo.py [--scale 1.0] [--scenes object tile] [--keep DIR]

Captures each scene on the virtual rig with two cameras (the paper's geometry, camera 1
on the other side of the projector, 40° from camera 0; Gray-code columns and rows; noise
on) and reconstructs view 0 in the same run by

- **stereo**: matching the projector codes between the two calibrated cameras
  (``slscan.decode.stereo``, no projector calibration), per projector pixel
  (``code_step`` 1) and per 2x2 block (``code_step`` 2), from the centroids of the pixels
  carrying each code, and with each pixel first refined onto its code's centre by plane
  fits of the codes around it (``subpixel``);
- **camera-projector**: each camera's Gray-code stripe edges meeting the projector's
  light planes (``slscan.decode.pipeline.decode_view``, the projector calibrated).

For each: range-map vertices and faces, the distance of every vertex to the true surface
(median, 95th percentile, mm), the match counts, and the time (CPU and wall seconds, this
process; stereo decodes both cameras' images, camera-projector one camera's).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.decode.stereo import StereoConfig, reconstruct_view
from slscan.rig import transform_points
from slscan.virtual.device import VirtualCaptureConfig
from slscan.virtual.multicam import capture_multicam
from slscan.virtual.scenes import scene_by_name

sys.path.insert(0, str(Path(__file__).parent))
from measure import cpu_seconds, distances_to_mesh


def _timed(fn):
    c, w = cpu_seconds(), time.perf_counter()
    out = fn()
    return out, cpu_seconds() - c, time.perf_counter() - w


def run_scene(scene_name: str, scale: float, folder: Path) -> list[dict]:
    config = VirtualCaptureConfig(scene=scene_name, patterns="gray", gray_rows=True, lit_images=False,
                                  camera_scale=scale, projector_scale=scale)
    multi, _, wall = _timed(lambda: capture_multicam(config, folder / scene_name, overwrite=True))
    print(f"# {scene_name}: captured 2 cameras x {len(config.pattern_set(config.rig()))} images "
          f"{multi.sessions[0].camera_size[0]}x{multi.sessions[0].camera_size[1]} in {wall:.1f} s", flush=True)
    view = multi.sessions[0].views[0]
    scene = scene_by_name(scene_name)
    truth = transform_points(view.rig_from_object, scene.vertices)

    def error(points: np.ndarray) -> tuple[float, float]:
        d = distances_to_mesh(points, truth, scene.triangles)
        return float(np.median(d)), float(np.percentile(d, 95))

    rows = []
    for step, subpixel in ((1, False), (2, False), (1, True)):
        cfg = StereoConfig(code_step=step, subpixel=subpixel)
        res, cpu, wall = _timed(lambda cfg=cfg: reconstruct_view(multi, view.name, cfg))
        st = res.match.stats
        method = f"stereo codes, step {step}" + (", subpixel" if subpixel else "")
        rows.append({
            "scene": scene_name, "method": method, "vertices": len(res.range_map.vertices),
            "faces": len(res.range_map.faces), "err": error(res.range_map.vertices),
            "matches": f"{st['matched']}/{st['common']} (-{st['rejected_epipolar']} epi, -{st['rejected_ray_gap']} gap)",
            "cpu": cpu, "wall": wall,
        })
    for k, (cam, session) in enumerate(zip(multi.cameras, multi.sessions)):
        res, cpu, wall = _timed(lambda session=session: decode_view(session, view.name, DecodeConfig(method="gray")))
        vertices = res.range_map.vertices
        if k:  # into camera 0's frame, where the truth is
            vertices = transform_points(cam.rig_from_camera, vertices)
        rows.append({
            "scene": scene_name, "method": f"camera-projector, {cam.name}", "vertices": len(vertices),
            "faces": len(res.range_map.faces), "err": error(vertices), "matches": "-", "cpu": cpu, "wall": wall,
        })
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=1.0, help="sensor size factor (default 1: 1440x960, 1024x768)")
    parser.add_argument("--scenes", nargs="+", default=["object", "tile"], help="default: object tile")
    parser.add_argument("--keep", type=Path, help="keep the captures in this folder")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        rows = [r for name in args.scenes for r in run_scene(name, args.scale, folder)]
    print(f"\nscale {args.scale:g}: range-map vertices vs the true surface (mm); time for view 0 (s)\n")
    head = f"{'scene':<7} {'method':<36} {'vertices':>9} {'faces':>9} {'median':>7} {'p95':>7}  {'cpu s':>6} {'wall s':>6}  matched/common (rejected)"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r['scene']:<7} {r['method']:<36} {r['vertices']:>9,} {r['faces']:>9,} {r['err'][0]:>7.3f} "
              f"{r['err'][1]:>7.3f}  {r['cpu']:>6.2f} {r['wall']:>6.2f}  {r['matches']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
