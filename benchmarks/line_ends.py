"""Line ends: how much worse they are, and what down-weighting or trimming them buys.

    .venv/bin/python benchmarks/line_ends.py [--views 8] [--scale 1.0] [--voxel 0.57]

Captures the built-in figurine on the virtual rig (paper geometry, default noise, both
pattern families, ``--views`` turntable positions), then prints:

1. per decoder, on view 0: the camera-x error of every sample against the truth's crossing
   of its projector column (px RMS, p95), split by line continuity
   (:meth:`slscan.decode.samples.StripeSamples.continuity`: the sample's line goes on in
   both neighbouring rows, in one — a line end — or in neither);
2. the hybrid range maps of all views fused at the true poses (weighted TSDF,
   ``--voxel`` mm) three ways: vertex quality without the continuity factor (the
   baseline), with it (the default), and with one row trimmed off every line end
   (``slscan decode --trim-line-ends 1``). For each: model → truth distance from points
   spread by area on the model (mean, p95, p99 mm) and completeness (share of points
   spread on the true surface within 1 mm of the model).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from measure import fuse_at_true_poses, model_vs_truth, surface_samples

from slscan.capture.session import Session
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.decode.rangemap import build_range_map
from slscan.decode.samples import StripeSamples
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.scenes import builtin_object

CONTINUITY = ((2, "inside a line"), (1, "line end"), (0, "lone sample"))


def axis_errors(session: Session, samples: StripeSamples) -> np.ndarray:
    """(k,) signed camera-x error of each sample against the truth (NaN where unknown)."""
    truth = session.load_ground_truth(session.views[0])
    return samples.x - truth.column_crossings(samples.row, samples.x, samples.projector_column)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=8, help="turntable views to fuse")
    parser.add_argument("--scale", type=float, default=1.0, help="resolution factor (1: 1440x960 camera)")
    parser.add_argument("--voxel", type=float, default=0.57, help="fusion voxel size, mm (the paper's)")
    args = parser.parse_args()
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    with tempfile.TemporaryDirectory() as tmp:
        session = capture_session(
            VirtualCaptureConfig(views=args.views, camera_scale=args.scale, projector_scale=args.scale,
                                 levels=levels, lit_images=False, patterns="both"),
            Path(tmp) / "figurine",
        )
        print(f"figurine, {args.views} views, camera {session.camera_size[0]}x{session.camera_size[1]}, "
              f"{levels} hybrid levels, default noise\n")
        print("1. camera-x error by line continuity, view 0 (samples within 2 px of the truth)")
        print(f"{'decoder':<10}{'continuity':<16}{'samples':>9}{'share %':>9}{'RMS px':>9}{'p95 px':>9}{'x inside':>10}")
        view = session.views[0]
        for method in ("hybrid", "gray"):
            samples = decode_view(session, view, DecodeConfig(method=method)).samples
            err = np.abs(axis_errors(session, samples))
            ok = np.isfinite(err) & (err < 2.0)
            n = samples.continuity()
            inside = float(np.sqrt(np.mean(err[ok & (n == 2)] ** 2)))
            for k, label in CONTINUITY:
                e = err[ok & (n == k)]
                rms = float(np.sqrt(np.mean(e**2)))
                print(f"{method:<10}{label:<16}{len(e):>9d}{100 * len(e) / ok.sum():>9.1f}{rms:>9.4f}"
                      f"{np.percentile(e, 95):>9.4f}{rms / inside:>10.2f}")

        print(f"\n2. hybrid range maps of {args.views} views fused at the true poses, {args.voxel} mm voxels")
        print(f"{'variant':<34}{'faces':>10}{'mean mm':>9}{'p95 mm':>9}{'p99 mm':>9}{'within 1 mm':>13}")
        scene = builtin_object()
        truth_points = surface_samples(scene.vertices, scene.triangles, 300_000)
        variants = (
            ("quality without continuity", (1.0, 1.0, 1.0), 0),
            ("quality x continuity (default)", None, 0),
            ("line ends trimmed (1 row)", None, 1),
        )
        for label, weight, trim in variants:
            maps = {}
            for v in session.views:
                res = decode_view(session, v, DecodeConfig(method="hybrid", trim_line_ends=trim))
                maps[v.name] = res.range_map
                if weight is not None:
                    maps[v.name] = build_range_map(res.samples, res.points, white_image=res.white,
                                                   camera=session.calibration.camera, view=v.name,
                                                   continuity_weight=weight)
            mesh = fuse_at_true_poses(session, maps, args.voxel)
            d, complete = model_vs_truth(mesh, scene, truth_points)
            print(f"{label:<34}{len(mesh.faces):>10d}{d.mean():>9.4f}{np.percentile(d, 95):>9.4f}"
                  f"{np.percentile(d, 99):>9.4f}{complete:>13.4f}")


if __name__ == "__main__":
    main()
