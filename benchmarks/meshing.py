"""Range-map meshing settings against the true surface: what each cut costs in coverage and
what each bridge costs in wrong faces.

    .venv/bin/python benchmarks/meshing.py [--scale 1.0] [--edge 4 8] [--gap 3 6 10]
                                           [--views 8] [--voxel 0.57]

Captures the built-in figurine on the virtual rig (paper geometry, default noise, both
pattern families, ``--views`` turntable positions), decodes every view once per decoder,
then meshes the same samples with every pair of ``max_edge_factor`` (``--edge``) and
``max_gap_columns`` (``--gap``, projector columns: hybrid lines are 2 apart, Gray-code
edges 1) and prints per setting, for view 0:

- faces, and coverage: the share of lit camera pixels a range-map face covers
  (``benchmarks/reconstruction.py``'s measure);
- hit: the share of lit pixels whose ray meets the mesh; within 0.5 mm: whose ray meets it
  within 0.5 mm of the true surface; off >1 mm: whose ray meets a face more than 1 mm
  from it (a face bridging a depth step or a shadow);
- mean and p99 of that distance over the pixels hit (mm);

and for the range maps of all views fused at the true poses (weighted TSDF, ``--voxel``
mm, as ``benchmarks/line_ends.py``): model -> truth distance from points spread by area
on the model (mean, p99 mm) and completeness (share of points spread on the true surface
within 1 mm of the model). A face can sit on the true surface in its own view and still
spoil the fused model (grazing observations smear the distance field), which is why
both are shown.

The defaults of :func:`slscan.decode.rangemap.build_range_map` are marked with ``*``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from slscan.capture.session import LIT
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.decode.rangemap import MAX_EDGE_FACTOR, MAX_GAP_COLUMNS, build_range_map
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.scenes import builtin_object

sys.path.insert(0, str(Path(__file__).parent))
from measure import fuse_at_true_poses, model_vs_truth, surface_samples
from reconstruction import coverage, mesh_error


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=1.0, help="resolution factor (1: 1440x960 camera)")
    parser.add_argument("--edge", type=float, nargs="+", default=sorted({MAX_EDGE_FACTOR, 8.0}),
                        help="max_edge_factor values")
    parser.add_argument("--gap", type=float, nargs="+", default=[3.0, MAX_GAP_COLUMNS, 10.0],
                        help="max_gap_columns values (projector columns)")
    parser.add_argument("--views", type=int, default=8, help="turntable views to fuse")
    parser.add_argument("--voxel", type=float, default=0.57, help="fusion voxel size, mm")
    args = parser.parse_args()
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    config = VirtualCaptureConfig(camera_scale=args.scale, projector_scale=args.scale, levels=levels,
                                  lit_images=False, patterns="both", views=args.views)
    with tempfile.TemporaryDirectory() as tmp:
        session = capture_session(config, Path(tmp) / "figurine")
        view = session.views[0]
        camera = session.calibration.camera
        lit = session.load_ground_truth(view).visibility == LIT
        scene = builtin_object()
        truth_points = surface_samples(scene.vertices, scene.triangles, 300_000)
        print(f"figurine, view 0, camera {camera.width}x{camera.height}, {lit.sum()} lit pixels; "
              f"{args.views} views fused at {args.voxel} mm; * = the defaults\n")
        print(f"{'':<24}{'view 0':<57}{'fused':<10}")
        print(f"{'method':<8}{'edge x':>7}{'gap cols':>9}{'faces':>9}{'coverage':>10}{'hit':>8}"
              f"{'<0.5 mm':>9}{'off >1mm':>10}{'mean mm':>9}{'p99 mm':>8}"
              f"{'faces':>10}{'mean mm':>9}{'p99 mm':>8}{'within 1 mm':>13}")
        for method in ("hybrid", "gray"):
            everything = {v.name: decode_view(session, v, DecodeConfig(method=method)) for v in session.views}
            for edge in args.edge:
                for gap in args.gap:
                    maps = {name: build_range_map(res.samples, res.points, white_image=res.white, camera=camera,
                                                  view=name, max_edge_factor=edge, max_gap_columns=gap)
                            for name, res in everything.items()}
                    rm = maps[view.name]
                    cov, _ = coverage(rm, camera, lit)
                    err = mesh_error(rm, camera, lit, scene, view.rig_from_object)
                    hit = np.isfinite(err)
                    mark = "*" if (edge, gap) == (MAX_EDGE_FACTOR, MAX_GAP_COLUMNS) else " "
                    mesh = fuse_at_true_poses(session, maps, args.voxel)
                    d, complete = model_vs_truth(mesh, scene, truth_points)
                    print(f"{method:<8}{edge:>7g}{gap:>9g}{rm.n_faces:>9d}{cov:>10.3f}{hit.mean():>8.3f}"
                          f"{np.mean(err < 0.5):>9.3f}{np.mean(hit & (err > 1.0)):>10.4f}"
                          f"{err[hit].mean():>9.4f}{np.percentile(err[hit], 99):>8.3f}"
                          f"{len(mesh.faces):>10d}{d.mean():>9.4f}{np.percentile(d, 99):>8.4f}{complete:>13.4f} {mark}",
                          flush=True)


if __name__ == "__main__":
    main()
