"""Gray-code decoding on real captures (kamino410) and plane-fit accuracy on the virtual tile.

    .venv/bin/python benchmarks/graycode_real.py [--data DIR] [--repeat 3] [--no-tile] [--drop-bits 0,2]

Prints two tables.

1. The five kamino410/procam-calibration captures (1280x1024 grey, 1024x768 projector,
   column and row Gray codes with inverses), imported with ``import_kamino410``: share of
   pixels whose column and row decode (the mask), share whose column decodes, monotonicity
   (share of horizontally adjacent pixel pairs in the mask whose column does not decrease;
   likewise for rows downwards), stripe-edge samples, estimated noise, and times: reading
   the 22 PNGs and ``decode_gray_images`` on them (median of ``--repeat``); one row per
   ``--drop-bits`` value (per-pixel bit dropping, ``drop_bits``; default 0 only).
2. The virtual flat tile (``VirtualCaptureConfig(scene="tile", patterns="gray")``) at
   reduced size without noise, reduced size with the default sensor noise, and full size
   (1440x960 camera, 1024x768 projector) with default noise: edge position error against
   the ground truth (px), and the triangulated edges' plane fit (SVD) and error against the
   ground-truth points (mm), over edges whose pixels and neighbours are all lit.

The data folder is ``slscan.data.shared_data_dir()`` (``$SLSCAN_DATA`` or ``../shared/data``)
unless ``--data`` is given; without it the first table is skipped with a message.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from slscan.capture.kamino410 import import_kamino410
from slscan.capture.session import LIT
from slscan.data import ENV_VAR, shared_data_dir
from slscan.decode.graycode import decode_gray, decode_gray_images
from slscan.decode.triangulate import RigPlanes, triangulate
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor


def kamino410_table(data: Path, repeat: int, drop_bits: tuple[int, ...] = (0,)) -> None:
    src = data / "procam_graycode_kamino410" / "sample_data"
    if not src.is_dir():
        print(f"kamino410 captures not found at {src}: table skipped")
        return
    with tempfile.TemporaryDirectory() as tmp:
        session = import_kamino410(src, Path(tmp) / "session")
        descs = [p for p in session.patterns if p.family == "gray"]
        print(f"kamino410 captures from {src}")
        print(
            f"camera {session.camera_size[0]}x{session.camera_size[1]}, projector "
            f"{session.projector_size[0]}x{session.projector_size[1]}, "
            f"median of {repeat} runs"
        )
        head = (
            f"{'capture':<11}{'drop':>5}{'col+row':>8}{'col':>7}{'mono col':>10}{'mono row':>10}"
            f"{'edges':>9}{'noise DN':>9}{'read s':>8}{'decode s':>9}"
        )
        print(head)
        print("-" * len(head))
        for view in session.views:
            for drop in drop_bits:
                t_read, t_dec = [], []
                for _ in range(repeat):
                    t = time.perf_counter()
                    images = {d.id: session.read_image(view, view.image_for(d.id)) for d in descs}
                    white = session.read_image(view, view.image_for("white"))
                    black = session.read_image(view, view.image_for("black"))
                    t_read.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    res = decode_gray_images(images, descs, white, black, drop_bits=drop)
                    t_dec.append(time.perf_counter() - t)
                c, r, m = res.column, res.row, res.mask
                pair = m[:, 1:] & m[:, :-1]
                mono_col = float(((c[:, 1:] - c[:, :-1])[pair] >= 0).mean())
                pair = m[1:] & m[:-1]
                mono_row = float(((r[1:] - r[:-1])[pair] >= 0).mean())
                print(
                    f"{view.name:<11}{drop:>5d}{m.mean():>8.3f}{(c >= 0).mean():>7.3f}{mono_col:>10.5f}"
                    f"{mono_row:>10.5f}{len(res.edges):>9d}{res.noise * 255:>9.2f}"
                    f"{statistics.median(t_read):>8.2f}{statistics.median(t_dec):>9.2f}"
                )


def _tile_row(label: str, config: VirtualCaptureConfig, **options) -> str:
    """One row of the tile table; ``options`` go to ``decode_gray``."""
    with tempfile.TemporaryDirectory() as tmp:
        session = capture_session(config, Path(tmp) / "session")
        view = session.views[0]
        truth = session.load_ground_truth(view)
        t = time.perf_counter()
        edges = decode_gray(session, view, **options).edges
        t_dec = time.perf_counter() - t
    rig = session.calibration
    points = triangulate(edges, rig.camera, RigPlanes(rig.projector))
    vis = truth.visibility
    w = vis.shape[1]
    xa = np.floor(edges.x).astype(int)
    inner = np.isfinite(points).all(axis=1)
    for dx in (-1, 0, 1, 2):
        inner &= vis[edges.row, np.clip(xa + dx, 0, w - 1)] == LIT
    # edge position error: where the truth projector column crosses c + 0.5 along the row
    u = truth.projector_uv[..., 0].astype(np.float64)
    truth_x = np.full(len(edges), np.nan)
    for shift in (0, -1, 1):
        a = np.clip(xa + shift, 0, w - 2)
        ua, ub = u[edges.row, a], u[edges.row, a + 1]
        lv = edges.projector_column
        hit = np.isnan(truth_x) & ((ua - lv) * (ub - lv) <= 0) & (ua != ub)
        truth_x[hit] = a[hit] + (lv[hit] - ua[hit]) / (ub[hit] - ua[hit])
    x_err = (edges.x - truth_x)[inner & np.isfinite(truth_x)]
    p = points[inner]
    centre = p.mean(axis=0)
    normal = np.linalg.svd(p - centre, full_matrices=False)[2][2]
    dist = np.abs((p - centre) @ normal)
    f = (edges.x - xa)[:, None]
    gt = truth.point.astype(np.float64)
    expected = gt[edges.row, xa] * (1 - f) + gt[edges.row, np.minimum(xa + 1, w - 1)] * f
    err = np.linalg.norm(points - expected, axis=1)[inner]
    cam = rig.camera
    return (
        f"{label:<26}{cam.width:>5}x{cam.height:<5}{int(inner.sum()):>8d}"
        f"{np.sqrt(np.mean(x_err**2)):>9.4f}{dist.mean():>9.3f}{np.sqrt(np.mean(dist**2)):>9.3f}"
        f"{np.median(err):>9.3f}{np.percentile(err, 99):>9.3f}{t_dec:>9.2f}"
    )


def tile_table() -> None:
    print()
    print("virtual flat tile, Gray code, one view (edges with all pixels lit)")
    head = (
        f"{'configuration':<26}{'camera':<11}{'edges':>8}{'x RMS px':>9}{'|d| mm':>9}"
        f"{'RMS mm':>9}{'gt med':>9}{'gt p99':>9}{'dec s':>9}"
    )
    print(head)
    print("-" * len(head))
    quiet = Sensor(noise=False)
    configs = [
        ("0.25 size, noise-free", {"camera_scale": 0.25, "projector_scale": 0.25, "sensor": quiet}),
        ("0.25 size, default noise", {"camera_scale": 0.25, "projector_scale": 0.25}),
        ("0.5 size, default noise", {"camera_scale": 0.5, "projector_scale": 0.5}),
        ("full size, noise-free", {"sensor": quiet}),
        ("full size, default noise", {}),
    ]
    for label, options in configs:
        config = VirtualCaptureConfig(scene="tile", patterns="gray", lit_images=False, **options)
        print(_tile_row(label, config), flush=True)
    print(
        "|d|, RMS: distance to the SVD plane fit; gt: distance to the ground-truth point "
        "interpolated at the sample"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, default=None, help="shared data folder")
    parser.add_argument("--repeat", type=int, default=3, help="timing repetitions (median)")
    parser.add_argument("--no-tile", action="store_true", help="skip the virtual-tile table")
    parser.add_argument("--drop-bits", default="0", help="comma-separated drop_bits values, one row each")
    args = parser.parse_args()
    data = args.data or shared_data_dir()
    if data is None or not data.is_dir():
        print(
            f"real data not found: set {ENV_VAR} or pass --data (expected a folder holding "
            "procam_graycode_kamino410/); kamino410 table skipped"
        )
    else:
        kamino410_table(data, args.repeat, tuple(int(v) for v in args.drop_bits.split(",")))
    if not args.no_tile:
        tile_table()


if __name__ == "__main__":
    main()
