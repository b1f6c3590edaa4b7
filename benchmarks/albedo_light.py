"""Albedo from the ring lights against albedo from the projector as the light (virtual rig).

    nice .venv/bin/python benchmarks/albedo_light.py [--scale 0.5] [--panel-scale 0.5]

Two scenes of the virtual rig, one view each, with ring-light images and white/black
frames: the built-in **figurine** (specular lobe 0.12, self-shadowing, saturated paint)
and a tilted **tile** (albedo 0.8, 0.8, 0.776; specular 0.03). Each is captured, decoded
into a range map, and coloured by

- **ring**: the paper's 6-light un-shading (photometric normals, fitted specular lobe),
  lights estimated by ``calibrate-lights`` from a matte-panel session (6 poses);
- **projector**: the white frame minus the black, the projector as the calibrated point
  light (intensity and flat field measured on the same panel session's white and black
  frames), with the range map's vertex normals and with the normals of planes fitted to the
  range surface over up to 9, 21 (the default) and 41 pixels, as planar as the range map's
  noise allows (``projector_normal_window_px``); and
  the default leaving out the pixels within 15° of the mirror direction
  (``projector_highlight_deg=15``);
- **white frame**: the raw white frame scaled by the one global factor that best fits the
  truth (the naive colour: shading and highlights left in; its coverage is every pixel).

Scored against the simulator's per-pixel albedo (ground truth at pixel centres): the RGB
relative error ``|estimate - truth| / |truth|`` per valid pixel, its median and 95th
percentile; "coverage" is the share of the range map's pixels (seen by the camera) with
a valid albedo. "common" scores every method on the pixels valid in all of them.

This is the virtual rig only: its projector is uniform, its sensor linear and its
surfaces follow the rendering model exactly, a weak claim for a real rig (see
``benchmarks/real_flatness.py --projector-light`` for a real white frame).
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.albedo.lights import calibrate_lights
from slscan.albedo.photometric import AlbedoConfig
from slscan.albedo.projector_light import projector_albedo_view, read_flat_frames
from slscan.albedo.unshade import albedo_view
from slscan.decode.pipeline import decode_view
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.panels import capture_light_calibration


def errors(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    e, t = estimate[mask].astype(np.float64), truth[mask].astype(np.float64)
    return np.linalg.norm(e - t, axis=1) / np.linalg.norm(t, axis=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=0.5, help="scene sessions' size (default 0.5: 720x480)")
    parser.add_argument("--panel-scale", type=float, default=0.5, help="light-panel session size (default 0.5)")
    parser.add_argument("--keep", type=Path, default=None, help="keep the sessions in this folder")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    tmp = tempfile.TemporaryDirectory()
    root = args.keep or Path(tmp.name)
    levels = 9 if args.scale >= 1 else max(5, int(np.log2(1024 * args.scale)) - 1)

    t0 = time.perf_counter()
    panel_config = VirtualCaptureConfig(camera_scale=args.panel_scale, projector_scale=args.panel_scale, levels=5)
    panel = capture_light_calibration(root / "panel", config=panel_config, overwrite=True)
    lights = calibrate_lights(panel)
    rig = panel.calibration
    d0 = np.linalg.norm(rig.projector.center - [0, 0, rig.working_distance])
    expected = np.array([1.12, 1.14, 1.16]) * (d0 / rig.working_distance) ** 2
    flat = np.array(lights.projector.flat_field)
    print(f"\nLight calibration: {len(panel.views)} panel poses at scale {args.panel_scale}, "
          f"{time.perf_counter() - t0:.1f} s")
    print(f"projector light: intensity {np.round(lights.projector.intensity, 4).tolist()} "
          f"(virtual rig's true {np.round(expected, 4).tolist()}), flat field {flat.min():.4f}..{flat.max():.4f} "
          "(true: uniform)")

    rows = []
    for scene in ("object", "tile"):
        config = VirtualCaptureConfig(scene=scene, camera_scale=args.scale, projector_scale=args.scale,
                                      levels=levels)
        session = capture_session(config, root / scene, overwrite=True)
        view = session.views[0]
        range_map = decode_view(session, view).range_map
        truth = session.load_ground_truth(view).albedo.astype(np.float64)
        known = np.isfinite(truth[..., 0])
        results = {}
        t = time.perf_counter()
        ring = albedo_view(session, view, range_map, lights, AlbedoConfig())
        results["ring (6 lights un-shaded)"] = (ring.albedo, ring.valid, time.perf_counter() - t)
        for name, cfg in (("projector, range-map normals", AlbedoConfig(projector_normal_window_px=0)),
                          ("projector, plane normals up to 9 px", AlbedoConfig(projector_normal_window_px=9)),
                          ("projector, plane normals up to 21 px (default)", AlbedoConfig()),
                          ("projector, plane normals up to 41 px", AlbedoConfig(projector_normal_window_px=41)),
                          ("projector (default), mirror cone 15° out", AlbedoConfig(projector_highlight_deg=15))):
            t = time.perf_counter()
            res = projector_albedo_view(session, view, range_map, lights.projector, cfg)
            results[name] = (res.albedo, res.valid, time.perf_counter() - t)
        seen = ring.surface.hit
        frames = read_flat_frames(session, view)
        white = frames.white.astype(np.float64)
        mask = seen & known
        e, tr = white[mask].ravel(), truth[mask].ravel()
        scale = float(e @ tr / (e @ e))
        results["white frame x best scale"] = (white * scale, seen.copy(), 0.0)
        common = known.copy()
        for _, valid, _ in results.values():
            common &= valid
        for name, (albedo, valid, seconds) in results.items():
            ok = valid & known
            err = errors(albedo, truth, ok)
            err_c = errors(albedo, truth, common)
            rows.append((
                "figurine" if scene == "object" else "tile", name,
                100 * np.median(err), 100 * np.percentile(err, 95), 100 * ok.sum() / max(seen.sum(), 1),
                100 * np.median(err_c), 100 * np.percentile(err_c, 95), int(common.sum()), seconds,
            ))
    print(f"\nScenes at scale {args.scale}: relative RGB albedo error against the virtual rig's truth")
    print("| scene | method | median % | p95 % | coverage % | common: median % | common: p95 % | "
          "common px | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.1f} | {r[5]:.2f} | {r[6]:.2f} | {r[7]:,} | "
              f"{r[8]:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
