"""The hybrid decoder under physical colour, camera blur and a stand-in for global light.

    .venv/bin/python benchmarks/hybrid_colour.py [--scale 0.5] [--blurs 0.4 0.7 1.0]
                                                 [--scenes object tile] [--beta 0.5]

Captures one view per scene and camera blur with ``Optics(colour_model="physical")`` (the
paint acts after the projector → camera crosstalk) and decodes it with every decoder
variant side by side in the same run:

- ``global``: one crosstalk matrix for the view (the decoder before 2026-11)
- ``pixel``: per-pixel mixing from the session's own bands (the default)
- ``pixel+edges``: also drops lines across paint edges (``paint_edges=True``)
- ``pixel+global``: also removes the global light estimated from the finest levels
  (``global_light=True``)

Per variant: samples, indexed % (line index right), RMS and p95 camera-x error of the
axis (px, :func:`stripe_axes.evaluate`), the share of samples more than 1 px off or
wrongly indexed ("gross %"), and the RMS on neutral, red and blue surfaces with the
red/neutral and blue/neutral ratios. ``--beta B`` adds a row block with a TEST-ONLY
STAND-IN for global light (not a light-transport model): every capture gets ``B`` times a
Gaussian-blurred (sigma ``--global-sigma`` camera px) copy of its own black-subtracted
image, as a smooth indirect term would add, before decoding.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from slscan.decode.hybrid import decode_hybrid_images, hybrid_pattern_ids
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.render import Optics
from slscan.virtual.sensor import Sensor

sys.path.insert(0, str(Path(__file__).parent))
import stripe_axes

VARIANTS = {
    "global": {"mixing": "global"},
    "pixel": {"mixing": "pixel"},
    "pixel+edges": {"mixing": "pixel", "paint_edges": True},
    "pixel+global": {"mixing": "pixel", "global_light": True},
}


def stand_in_global(image: np.ndarray, black: np.ndarray, beta: float, sigma: float) -> np.ndarray:
    """TEST-ONLY STAND-IN for global light: ``image + beta * blur(image - black)``."""
    full = 255.0 if image.dtype == np.uint8 else 65535.0 if image.dtype == np.uint16 else 1.0
    direct = image.astype(np.float32) - black.astype(np.float32)
    out = image.astype(np.float32) + beta * cv2.GaussianBlur(direct, (0, 0), sigma)
    return np.clip(np.round(out) if full > 1 else out, 0, full).astype(image.dtype)


def row(label: str, m: dict, seconds: float) -> str:
    surf = m["by_surface"]
    rms = {k: surf[k][1] if k in surf else float("nan") for k in ("neutral", "red paint", "blue paint")}
    return (
        f"{label:<30}{m['samples']:>8d}{m['indexed']:>9.2f}{m['rms']:>8.3f}{m['p95']:>8.3f}"
        f"{m['gross']:>8.2f}{rms['neutral']:>9.3f}{rms['red paint']:>8.3f}{rms['blue paint']:>8.3f}"
        f"{rms['red paint'] / rms['neutral']:>7.2f}{rms['blue paint'] / rms['neutral']:>7.2f}"
        f"{seconds:>8.2f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--blurs", type=float, nargs="+", default=[0.4, 0.7, 1.0])
    parser.add_argument("--scenes", nargs="+", default=["object", "tile"])
    parser.add_argument("--beta", type=float, default=0.5)
    parser.add_argument("--global-sigma", type=float, default=40.0)
    args = parser.parse_args()
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    print(f"physical colour, scale {args.scale}, {levels} levels; errors in camera px")
    header = (f"{'scene / blur / variant':<30}{'samples':>8}{'idx %':>9}{'RMS':>8}{'p95':>8}"
              f"{'gross%':>8}{'neutral':>9}{'red':>8}{'blue':>8}{'r/n':>7}{'b/n':>7}{'cpu s':>8}")
    print(header)
    print("-" * len(header))
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes:
            for blur in args.blurs:
                config = VirtualCaptureConfig(
                    camera_scale=args.scale, projector_scale=args.scale, levels=levels,
                    lit_images=False, scene=scene, sensor=Sensor(blur_sigma=blur),
                    optics=Optics(colour_model="physical"),
                )
                session = capture_session(config, Path(tmp) / f"{scene}-{blur}")
                view = session.views[0]
                white_id, black_id, descs = hybrid_pattern_ids(session)
                recs = {r.pattern: r for r in view.images if r.kind == "pattern"}
                raw = {pid: session.read_image(view, recs[pid]) for pid in (white_id, black_id,
                                                                           *(d.id for d in descs))}
                blocks = [("", raw)]
                if args.beta > 0:
                    black = raw[black_id]
                    blocks.append((f" +global {args.beta:g}", {
                        k: (v if k == black_id else stand_in_global(v, black, args.beta,
                                                                    args.global_sigma))
                        for k, v in raw.items()}))
                for suffix, images in blocks:
                    for name, options in VARIANTS.items():
                        t = time.process_time()
                        result = decode_hybrid_images(
                            images[white_id], images[black_id], images, descs,
                            bit_depth=session.bit_depth, **options)
                        seconds = time.process_time() - t
                        m = stripe_axes.evaluate(session, result)
                        m["gross"] = gross_share(session, result)
                        print(row(f"{scene} {blur:g}{suffix} {name}", m, seconds), flush=True)


def gross_share(session, result) -> float:
    """% of samples wrongly indexed or more than 1 camera px off the true axis."""
    truth = session.load_ground_truth(session.views[0])
    s = result.samples
    true_x = truth.column_crossings(s.row, s.x, s.projector_column)
    bad = ~np.isfinite(true_x) | (np.abs(s.x - np.nan_to_num(true_x, nan=1e9)) > 1.0)
    return 100.0 * float(bad.mean()) if len(s) else 0.0


if __name__ == "__main__":
    main()
