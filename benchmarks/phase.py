"""Phase shifting next to Gray code and the hybrid pattern, on the same virtual rig and scenes.

    .venv/bin/python benchmarks/phase.py [--scale 1.0] [--repeat 5] [--sets phase,phase-n8,...]

Every pattern set is rendered into one session per scene (the same views, the same noise
draw per image), decoded with the default decoder of its family, and measured against the
virtual rig's ground truth. Prints:

  (a) images per view (white and black included), for columns only;
  (b) the flat tile: mean |distance| to the true front plane of the range-map vertices
      whose true surface is the front face (the tile's sides, seen at 75 degrees, are left
      out: only the per-pixel phase decoder reaches them), its 95th percentile, and the
      distance to the plane fitted to them — the paper reports 0.3 mm;
  (c) the figurine: distance of the vertices to the true surface (mean, 95th percentile,
      share beyond 1 mm) and coverage (share of lit camera pixels under a range-map face);
  (d) decode + triangulate time per view next to the time to read that view's images (PNG
      decode: the I/O floor), medians of ``--repeat`` runs taken in turn.

Sets: "hybrid", "gray" (columns, 10 bits), "phase" (the default: 4 steps of 8 px,
complementary Gray code), "phase-rows" (the same with row fringes: triangulated ray to
ray), "phase-n8" (8 steps), "phase-16" (16 px fringes), "phase-hf" (16, 17, 18 px fringes,
temporal unwrapping, no Gray code). Every figure is from our own simulator: a weak claim on
its own; ``benchmarks/phase_real.py`` measures the decoder on real captures.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.capture.session import LIT, load_session
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.fsio import read_png
from slscan.rig import transform_points
from slscan.virtual.device import VirtualCaptureConfig, capture_session

sys.path.insert(0, str(Path(__file__).parent))
from reconstruction import coverage, true_surface_distance

SETS: dict[str, tuple[str, dict, bool]] = {
    "hybrid": ("hybrid", {}, False),
    "gray": ("gray", {}, False),
    "phase": ("phase", {}, False),
    "phase-rows": ("phase", {}, True),
    "phase-n8": ("phase", {"steps": 8}, False),
    "phase-16": ("phase", {"periods": (16.0,)}, False),
    "phase-hf": ("phase", {"unwrap": "heterodyne", "periods": (16.0, 17.0, 18.0)}, False),
}
"""name: (patterns, pattern options, row codes)."""


def capture(scene: str, name: str, scale: float, out: Path):
    patterns, options, rows = SETS[name]
    levels = min(9, int(np.log2(1024 * scale)) - 1)
    config = VirtualCaptureConfig(scene=scene, views=1, patterns=patterns, pattern_options=options, levels=levels,
                                  gray_rows=rows, lit_images=False, camera_scale=scale, projector_scale=scale)
    capture_session(config, out)
    return load_session(out), config.build_scene()


def front_plane(scene, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A point and the unit normal (rig frame) of the tile's front face (facing the camera)."""
    v = transform_points(pose, scene.vertices)[scene.triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    front = int(np.argmin(n[:, 2]))
    return v[front, 0], n[front]


def tile_errors(session, result, scene) -> dict:
    view = session.views[0]
    truth = session.load_ground_truth(view)
    point, normal = front_plane(scene, view.rig_from_object)
    verts = result.range_map.vertices.astype(np.float64)
    px = session.calibration.camera.project_local(verts)
    h, w = truth.visibility.shape
    xi = np.clip(np.rint(px[:, 0]).astype(int), 0, w - 1)
    yi = np.clip(np.rint(px[:, 1]).astype(int), 0, h - 1)
    on_front = truth.normal[yi, xi].astype(np.float64) @ normal > 0.99
    pts = verts[on_front]
    true = np.abs((pts - point) @ normal)
    centre = pts.mean(axis=0)
    fitted = np.abs((pts - centre) @ np.linalg.svd(pts - centre, full_matrices=False)[2][2])
    return {"n": int(on_front.sum()), "mean": float(true.mean()), "p95": float(np.percentile(true, 95)),
            "fitted": float(fitted.mean())}


def object_errors(session, result, scene) -> dict:
    view = session.views[0]
    truth = session.load_ground_truth(view)
    rm = result.range_map
    d = true_surface_distance(rm.vertices, scene, view.rig_from_object)
    cov, _ = coverage(rm, session.calibration.camera, truth.visibility == LIT)
    return {"n": len(rm.vertices), "mean": float(d.mean()), "p95": float(np.percentile(d, 95)),
            "gross": float(np.mean(d > 1.0) * 100), "coverage": cov}


def timing(session, method: str, repeat: int) -> tuple[float, float]:
    view = session.views[0]
    loads, work = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        for rec in view.pattern_images():
            read_png(session.image_path(view, rec))
        loads.append(time.perf_counter() - t)
        result = decode_view(session, view, DecodeConfig(method=method))
        work.append(result.seconds["decode"] + result.seconds["triangulate"])
    return statistics.median(loads), statistics.median(work)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=1.0, help="camera and projector size (1: the paper's)")
    parser.add_argument("--repeat", type=int, default=5, help="timing repetitions (median)")
    parser.add_argument("--sets", default="hybrid,gray,phase,phase-rows,phase-n8,phase-16,phase-hf")
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    names = [s.strip() for s in args.sets.split(",")]
    print(f"virtual rig at {args.scale}x the paper's size (camera {round(1440 * args.scale)}x{round(960 * args.scale)}, "
          f"projector {round(1024 * args.scale)}x{round(768 * args.scale)})")
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            tile, tile_scene = capture("tile", name, args.scale, Path(tmp) / f"tile-{name}")
            obj, obj_scene = capture("object", name, args.scale, Path(tmp) / f"object-{name}")
            method = SETS[name][0]
            res_t = decode_view(tile, tile.views[0], DecodeConfig(method=method))
            res_o = decode_view(obj, obj.views[0], DecodeConfig(method=method))
            load, work = timing(obj, method, args.repeat)
            rows[name] = (len(obj.patterns), tile_errors(tile, res_t, tile_scene),
                          object_errors(obj, res_o, obj_scene), load, work)
            images, t, o, load, work = rows[name]
            print(f"  {name}: {images} images, tile {t['mean']:.4f} mm, figurine {o['mean']:.4f} mm, "
                  f"coverage {o['coverage']:.3f}", flush=True)
    print(f"\n{'set':<11}{'images':>7} | {'tile: verts':>12}{'mean mm':>9}{'p95 mm':>8}{'fitted':>8} | "
          f"{'figurine: verts':>16}{'mean mm':>9}{'p95 mm':>8}{'gross %':>9}{'coverage':>9} | "
          f"{'read s':>7}{'dec+tri s':>10}{'x read':>7}")
    for name, (images, t, o, load, work) in rows.items():
        print(f"{name:<11}{images:>7} | {t['n']:>12d}{t['mean']:>9.4f}{t['p95']:>8.4f}{t['fitted']:>8.4f} | "
              f"{o['n']:>16d}{o['mean']:>9.4f}{o['p95']:>8.3f}{o['gross']:>9.3f}{o['coverage']:>9.3f} | "
              f"{load:>7.3f}{work:>10.3f}{work / load:>7.2f}")
    if {"phase", "gray", "hybrid"} <= rows.keys():
        p, g, h = (rows[k][1]["mean"] for k in ("phase", "gray", "hybrid"))
        print(f"\ntargets (issue #32, our simulator): phase tile {p:.4f} mm <= 0.5 x Gray code's {0.5 * g:.4f}: "
              f"{'yes' if p <= 0.5 * g else 'no'}; <= the hybrid's {h:.4f}: {'yes' if p <= h else 'no'}; "
              f"coverage {rows['phase'][2]['coverage']:.3f} >= the hybrid's {rows['hybrid'][2]['coverage']:.3f}: "
              f"{'yes' if rows['phase'][2]['coverage'] >= rows['hybrid'][2]['coverage'] else 'no'}; "
              f"decode + triangulate {rows['phase'][4] / rows['phase'][3]:.2f} x the image read (target <= 2)")


if __name__ == "__main__":
    main()
