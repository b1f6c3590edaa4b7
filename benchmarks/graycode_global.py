"""Robust Gray-code decoding and XOR codes under global light, old and new side by side.

    .venv/bin/python benchmarks/graycode_global.py [--data DIR] [--scale 0.5] [--repeat 3]

Three tables, each decoding the same captures with ``decode_gray_images(robust=False)``
(the decoder as it was) and ``robust=True`` (direct/global split, Gupta's reliability rule,
inconsistent codes left out) in the same run:

1. the five kamino410/procam-calibration real captures (1280x1024, column and row codes):
   share of pixels decoded (column and row), monotonicity of the columns along rows and
   of the rows down columns (share of adjacent decoded pairs not decreasing), edge
   samples, pixels left out as unreliable / inconsistent, and the decode's CPU and wall
   seconds (median of ``--repeat``);
2. the virtual flat tile at ``--scale`` with default noise: the edges' triangulation
   error against the ground truth (as ``benchmarks/graycode_real.py``);
3. the figurine at ``--scale`` with direct light only and with the TEST-ONLY stand-in
   for global light (``tests/decode/global_stand_in.py``: ``beta`` x albedo x the
   pattern's direct radiance blurred over ``sigma`` camera px, until the rig renders real
   inter-reflections), plain Gray code and XOR-04 codes: decoded share of the surface
   pixels, wrong codes (decoded column more than 1 / 8 columns from the true
   ``projector_uv``) as shares of the decoded pixels, and coverage relative to plain Gray
   code decoded the old way.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "decode"))

from global_stand_in import capture_with_global_stand_in
from graycode_real import _tile_row
from measure import kamino410_gray_views

from slscan.data import shared_data_dir
from slscan.decode.graycode import decode_gray_images
from slscan.virtual.device import VirtualCaptureConfig

MODES = (("old", False), ("robust", True))


def _timed(repeat: int, captures, robust: bool):
    """``decode_gray_images(*captures, robust=robust)``, its median CPU and wall seconds."""
    cpu, wall = [], []
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        out = decode_gray_images(*captures, robust=robust)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return out, statistics.median(cpu), statistics.median(wall)


def kamino410_table(data: Path, repeat: int) -> None:
    src = data / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        print(f"kamino410 captures not found at {src}: table skipped")
        return
    print(f"1. kamino410 real captures ({src}), median of {repeat} runs")
    head = (f"{'capture':<11}{'decoder':<8}{'col+row':>8}{'mono col':>10}{'mono row':>10}{'edges':>8}"
            f"{'unrel':>7}{'incons':>7}{'g/d med':>8}{'cpu s':>7}{'wall s':>7}")
    print(head)
    print("-" * len(head))
    for view_name, images, descs, white, black in kamino410_gray_views(src):
        for name, robust in MODES:
            res, cpu, wall = _timed(repeat, (images, descs, white, black), robust)
            c, r, m = res.column, res.row, res.mask
            pair = m[:, 1:] & m[:, :-1]
            mono_col = float(((c[:, 1:] - c[:, :-1])[pair] >= 0).mean())
            pair = m[1:] & m[:-1]
            mono_row = float(((r[1:] - r[:-1])[pair] >= 0).mean())
            d = res.diagnostics
            print(f"{view_name:<11}{name:<8}{m.mean():>8.4f}{mono_col:>10.5f}{mono_row:>10.5f}"
                  f"{len(res.edges):>8d}{d.get('unreliable_global', 0):>7d}{d.get('inconsistent', 0):>7d}"
                  f"{d.get('global_direct_median', float('nan')):>8.3f}{cpu:>7.2f}{wall:>7.2f}", flush=True)


def tile_table(scale: float) -> None:
    print()
    print(f"2. virtual flat tile, Gray code, {scale} size, default noise (edges with all pixels lit)")
    head = (f"{'decoder':<26}{'camera':<11}{'edges':>8}{'x RMS px':>9}{'|d| mm':>9}"
            f"{'RMS mm':>9}{'gt med':>9}{'gt p99':>9}{'dec s':>9}")
    print(head)
    print("-" * len(head))
    config = VirtualCaptureConfig(scene="tile", patterns="gray", lit_images=False, camera_scale=scale,
                                  projector_scale=scale)
    for name, robust in MODES:
        print(_tile_row(name, config, robust=robust), flush=True)


def global_table(scale: float, repeat: int) -> None:
    print()
    print(f"3. figurine, {scale} size, stand-in global light (TEST-ONLY: beta x albedo x blurred direct)")
    head = (f"{'beta':>5}{'sigma px':>9} {'patterns':<9}{'decoder':<8}{'decoded':>8}{'wrong>1':>9}"
            f"{'wrong>8':>9}{'coverage':>9}{'unrel':>7}{'incons':>7}{'g/d med':>8}{'cpu s':>7}{'wall s':>7}")
    print(head)
    print("-" * len(head))
    sigma = 80 * scale
    for beta in (0.0, 2.0, 4.0):
        reference = None
        for patterns in ("gray", "xor"):
            config = VirtualCaptureConfig(scene="object", patterns=patterns, camera_scale=scale,
                                          projector_scale=scale, lit_images=False)
            images, descs, white, black, uv = capture_with_global_stand_in(config, beta=beta, sigma_px=sigma)
            u = uv[..., 0]
            surface = np.isfinite(u)
            for name, robust in MODES:
                res, cpu, wall = _timed(repeat, (images, descs, white, black), robust)
                check = res.mask & surface
                err = np.abs(res.column[check] - np.floor(u[check] + 0.5))
                n = int(check.sum())
                reference = n if reference is None else reference
                d = res.diagnostics
                print(f"{beta:>5.1f}{sigma:>9.0f} {patterns:<9}{name:<8}{n / surface.sum():>8.3f}"
                      f"{(err > 1).mean():>9.3%}{(err > 8).mean():>9.3%}{n / reference:>9.3f}"
                      f"{d.get('unreliable_global', 0):>7d}{d.get('inconsistent', 0):>7d}"
                      f"{d.get('global_direct_median', float('nan')):>8.3f}{cpu:>7.2f}{wall:>7.2f}", flush=True)
    print("decoded: share of the surface pixels; wrong>1, wrong>8: decoded column more than 1 / 8 columns "
          "from the truth, share of the decoded; coverage: decoded pixels relative to plain Gray, old decoder")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None, help="shared data folder")
    ap.add_argument("--scale", type=float, default=0.5, help="virtual camera and projector scale")
    ap.add_argument("--repeat", type=int, default=3, help="timing repetitions (median)")
    args = ap.parse_args()
    data = args.data or shared_data_dir()
    if data is None or not data.is_dir():
        print("real data not found (pass --data): table 1 skipped")
    else:
        kamino410_table(data, args.repeat)
    tile_table(args.scale)
    global_table(args.scale, args.repeat)


if __name__ == "__main__":
    main()
