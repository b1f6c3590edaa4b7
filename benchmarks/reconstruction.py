"""Reconstruction accuracy and speed on the virtual rig, against its ground truth.

    .venv/bin/python benchmarks/reconstruction.py [--scale 1.0] [--repeat 7] [--figure PNG]

At the paper's geometry with default noise (full size unless --scale), prints:

  (a) green-line medial-axis error per estimator (px RMS, 95th percentile) — from
      benchmarks/stripe_axes.py's evaluation, on the figurine — with the default
      estimator's error by surface colour and by line continuity (inside a line, at its
      ends), and with the line ends trimmed;
  (b) flat tile: mean |distance| of the range map to its fitted plane and to the true
      plane (mm); the paper reports 0.3 mm;
  (c) figurine: distance of every range-map vertex to the true surface (mean, 95th pct),
      and coverage: the share of camera pixels that see projector-lit surface and are
      covered by a range-map triangle (all lit pixels; and lit pixels more than 2 px from
      the lit region's border, where a triangle can reach at all); "off >1mm": the share
      of lit pixels covered by a face more than 1 mm from the true surface (the pixel's
      ray cast onto the mesh: a face bridging a depth step shows here, not in the vertex
      distances); coverage by how obliquely the camera and the projector see the
      surface, and the uncovered lit pixels by cause. The figurine is decoded a second time with the line ends trimmed
      (``--trim-line-ends 1``): what that gains in accuracy and costs in coverage;
  (d) the same at 4x exposure: the saturation warning and what it costs;
  (e) decode + triangulate + mesh time per view next to the time to just load that
      view's PNGs (the I/O floor), measured in the same run.

Both decoders are shown: hybrid (the paper's green lines) and Gray code (stripe edges).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from slscan.capture.session import LIT, load_session
from slscan.decode.masks import channel_mean, full_scale
from slscan.decode.pipeline import DecodeConfig, decode_view
from slscan.decode.rangemap import covered_pixels
from slscan.fsio import read_png
from slscan.rig import transform_points
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.scenes import builtin_object, flat_tile
from slscan.virtual.sensor import Sensor

sys.path.insert(0, str(Path(__file__).parent))
import stripe_axes


class _Warnings(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def true_surface_distance(points: np.ndarray, scene, pose: np.ndarray) -> np.ndarray:
    import open3d as o3d

    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(
        o3d.core.Tensor(transform_points(pose, scene.vertices).astype(np.float32)),
        o3d.core.Tensor(scene.triangles.astype(np.uint32)),
    )
    return rs.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def coverage(range_map, camera, lit: np.ndarray) -> tuple[float, float]:
    """Share of lit pixels covered by range-map triangles: all, and > 2 px inside."""
    covered = covered_pixels(range_map, camera, lit.shape)
    inner = cv2.erode(lit.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return float(covered[lit].mean()), float(covered[inner].mean())


def mesh_error(range_map, camera, lit: np.ndarray, scene, pose: np.ndarray) -> np.ndarray:
    """(n,) for the n lit pixels (row-major): distance (mm) from where the pixel's ray meets
    the range mesh to the true surface; inf where the ray misses the mesh. Vertex distances
    say nothing of the faces between them: this catches a face bridging a depth step."""
    import open3d as o3d

    ys, xs = np.nonzero(lit)
    rays = camera.rays_local(np.stack([xs, ys], axis=1).astype(np.float64))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(range_map.vertices.astype(np.float32)),
                     o3d.core.Tensor(range_map.faces.astype(np.uint32)))
    t = rs.cast_rays(o3d.core.Tensor(np.concatenate([np.zeros_like(rays), rays], 1).astype(np.float32)))
    t = t["t_hit"].numpy().astype(np.float64)
    err = np.full(len(t), np.inf)
    hit = np.isfinite(t)
    if hit.any():
        err[hit] = true_surface_distance(rays[hit] * t[hit, None], scene, pose)
    return err


def obliquity(truth, projector_centre: np.ndarray) -> np.ndarray:
    """(h, w) degrees: the larger of the angles between the true surface normal and the
    rays to the camera and to the projector (NaN off the object)."""
    p = truth.point.astype(np.float64)
    n = truth.normal.astype(np.float64)
    to_cam = -p / np.linalg.norm(p, axis=-1, keepdims=True)
    to_proj = np.asarray(projector_centre, np.float64) - p
    to_proj /= np.linalg.norm(to_proj, axis=-1, keepdims=True)
    cos = np.minimum(np.abs((n * to_cam).sum(-1)), np.abs((n * to_proj).sum(-1)))
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))


def lit_contrast(white: np.ndarray, black: np.ndarray) -> np.ndarray:
    """(h, w) white - black frame, channel mean, in 8-bit digital numbers."""
    return (channel_mean(white) - channel_mean(black)) * (255.0 / full_scale(white, "white frame"))


CAUSE_COLOURS = {
    "within 2 px of the lit region's border": (1.0, 1.0, 0.0),
    "lit < 10 DN above black": (0.0, 0.5, 1.0),
    "beyond 80 deg to camera or projector": (1.0, 0.5, 0.0),
    "other": (1.0, 0.0, 1.0),
}
"""Colours of the uncovered lit pixels by cause in ``--figure`` (covered: green tint)."""


def write_figure(path: Path, picture: np.ndarray, lit: np.ndarray) -> None:
    """The (h, w, 3) RGB float picture cropped to the lit pixels, doubled, as a PNG."""
    ys, xs = np.nonzero(lit)
    crop = picture[max(ys.min() - 5, 0):ys.max() + 6, max(xs.min() - 5, 0):xs.max() + 6]
    rgb = np.clip(np.rint(crop * 255), 0, 255).astype(np.uint8)
    rgb = cv2.resize(rgb, None, fx=2, fy=2, interpolation=cv2.INTER_NEAREST)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)):
        raise SystemExit(f"could not write {path}")
    print(f"    wrote {path} (covered: green; uncovered: yellow border, blue dim, orange oblique, magenta other)")


def plane_errors(points: np.ndarray, scene, pose: np.ndarray) -> tuple[float, float]:
    """Mean |distance| to the fitted plane and to the tile's true front plane (mm)."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    fitted = np.abs((points - centre) @ normal)
    v = transform_points(pose, scene.vertices)[scene.triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    front = int(np.argmin(n[:, 2]))
    true = np.abs((points - v[front, 0]) @ n[front])
    return float(fitted.mean()), float(true.mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=1.0, help="resolution factor (1: 1440x960 camera)")
    parser.add_argument("--repeat", type=int, default=7, help="timing repetitions (median)")
    parser.add_argument("--figure", type=Path, metavar="PNG",
                        help="also write the hybrid figurine's coverage by cause as a picture "
                             "(docs/images/coverage_figurine.png)")
    args = parser.parse_args()
    levels = min(9, int(np.log2(1024 * args.scale)) - 1)
    base = VirtualCaptureConfig(camera_scale=args.scale, projector_scale=args.scale, levels=levels,
                                lit_images=False, patterns="both")
    warnings = _Warnings()
    logging.getLogger("slscan").addHandler(warnings)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sessions = {
            "tile": capture_session(replace(base, scene="tile"), tmp / "tile"),
            "figurine": capture_session(base, tmp / "figurine"),
            "figurine 4x exposure": capture_session(replace(base, sensor=Sensor(exposure=4.0)), tmp / "fig4"),
        }
        rig = base.rig()
        w, h = rig.camera.width, rig.camera.height
        print(f"virtual rig at the paper's geometry, camera {w}x{h}, projector "
              f"{rig.projector.lens.width}x{rig.projector.lens.height}, {levels} hybrid levels, default noise\n")

        # (a)
        print("(a) green-line medial axis vs ground truth, figurine")
        print(f"{'estimator':<18}{'samples':>9}{'indexed ok':>12}{'RMS px':>9}{'p95 px':>9}")
        fig = sessions["figurine"]
        from slscan.decode.hybrid import DEFAULT_ESTIMATOR, ESTIMATORS, decode_hybrid

        for estimator in ESTIMATORS:
            m = stripe_axes.evaluate(fig, decode_hybrid(fig, fig.views[0], estimator=estimator))
            print(f"{estimator:<18}{m['samples']:>9d}{m['indexed']:>11.2f}%{m['rms']:>9.4f}{m['p95']:>9.4f}")
            if estimator == DEFAULT_ESTIMATOR:
                default = m
        result = decode_hybrid(fig, fig.views[0])
        trimmed = stripe_axes.evaluate(fig, replace(result, samples=result.samples.trim_line_ends(1)))
        print(f"{DEFAULT_ESTIMATOR + ', trim 1':<18}{trimmed['samples']:>9d}{trimmed['indexed']:>11.2f}%"
              f"{trimmed['rms']:>9.4f}{trimmed['p95']:>9.4f}   (line ends dropped: --trim-line-ends 1)")
        print(f"  {DEFAULT_ESTIMATOR}, by the true surface colour under the sample, and by line continuity:")
        print(f"  {'surface':<15}{'samples':>8}{'RMS px':>9}{'p95 px':>9}{'% of MS':>10}")
        stripe_axes.print_by_surface(default, indent="  ")
        stripe_axes.print_by_surface(default, indent="  ", key="by_continuity")

        # (b)-(d)
        print("\n(b)-(d) range maps vs ground truth")
        header = (f"{'scene':<22}{'method':<14}{'vertices':>9}{'plane fit':>11}{'true plane':>12}"
                  f"{'mean mm':>9}{'p95 mm':>9}{'coverage':>10}{'interior':>10}{'off >1mm':>10}{'saturated':>11}")
        print(header)
        timing = []
        by_angle = {}
        for name, session in sessions.items():
            session = load_session(session.root)
            view = session.views[0]
            scene = flat_tile() if name == "tile" else builtin_object()
            truth = session.load_ground_truth(view)
            variants = [("hybrid", 0), ("gray", 0)]
            if name == "figurine":
                variants += [("hybrid", 1), ("gray", 1)]
            for method, trim in variants:
                label = method if not trim else f"{method} trim {trim}"
                warnings.messages.clear()
                result = decode_view(session, view, DecodeConfig(method=method, trim_line_ends=trim))
                rm = result.range_map
                d = true_surface_distance(rm.vertices, scene, view.rig_from_object)
                lit = truth.visibility == LIT
                cov, inner = coverage(rm, rig.camera, lit)
                off = float(np.mean(np.isfinite(e := mesh_error(rm, rig.camera, lit, scene, view.rig_from_object))
                                    & (e > 1.0)))
                fit, true_plane = plane_errors(rm.vertices, scene, view.rig_from_object) if name == "tile" else (np.nan, np.nan)
                sat = result.metrics["saturated_sample_share"]
                print(f"{name:<22}{label:<14}{len(rm.vertices):>9d}{fit:>11.4f}{true_plane:>12.4f}"
                      f"{d.mean():>9.4f}{np.percentile(d, 95):>9.4f}{cov:>10.3f}{inner:>10.3f}{off:>10.4f}{sat:>11.3f}")
                for message in dict.fromkeys(warnings.messages):
                    print(f"{'':<22}warning: {message}")
                if "4x" not in name and not trim:
                    timing.append((name, method))
                if name == "figurine" and not trim:
                    by_angle[method] = (covered_pixels(rm, rig.camera, lit.shape), lit,
                                        obliquity(truth, session.calibration.projector.center),
                                                        result.white,
                                        lit_contrast(result.white, read_png(
                                            session.image_path(view, view.image_for(session.flat_frame_ids()[1])))))

        print("\n(c) figurine coverage by obliquity: lit pixels whose surface is within the limit of both")
        print("    the camera's and the projector's ray (true normals)")
        print(f"{'limit deg':<10}{'share of lit':>14}" + "".join(f"{m + ' cov.':>13}" for m in by_angle))
        for limit in (60, 70, 75, 80, 85, 90):
            within = None
            row = ""
            for covered, lit_px, angle, *_ in by_angle.values():
                within = lit_px & (angle <= limit)
                row += f"{covered[within].mean():>13.3f}"
            print(f"{limit:<10}{within.sum() / lit_px.sum():>14.3f}{row}")

        print("\n(c) the figurine's lit pixels left uncovered, by cause (each pixel counted under the")
        print("    first that applies; shares of all lit pixels)")
        print(f"{'cause':<48}" + "".join(f"{m:>10}" for m in by_angle))
        causes = {}
        for method, (covered, lit_px, angle, white, dn) in by_angle.items():
            border = lit_px & ~cv2.erode(lit_px.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            left = lit_px & ~covered
            picture = (np.asarray(white, np.float32) * (0.5 / 255 if white.dtype == np.uint8 else 0.5 / 65535))
            picture[lit_px & covered] = 0.6 * picture[lit_px & covered] + [0.0, 0.3, 0.0]
            for label, where in (
                ("within 2 px of the lit region's border", border),
                ("lit < 10 DN above black", dn < 10),
                ("beyond 80 deg to camera or projector", angle > 80),
                ("other", np.ones_like(lit_px)),
            ):
                causes.setdefault(label, {})[method] = (left & where).sum() / lit_px.sum()
                picture[left & where] = CAUSE_COLOURS[label]
                left = left & ~where
            if method == "hybrid":
                figure = (picture, lit_px)
        for label, shares in causes.items():
            print(f"{label:<48}" + "".join(f"{v:>10.3f}" for v in shares.values()))
        if args.figure:
            write_figure(args.figure, *figure)

        # (e)
        print("\n(e) time per view next to loading the view's PNGs (decode includes reading them;")
        print(f"    medians of {args.repeat} runs, loading and decoding taken in turn so that both see")
        print("    the same machine load)")
        print(f"{'scene':<12}{'method':<8}{'load PNGs s':>12}{'decode s':>10}{'triang. s':>10}{'mesh s':>8}"
              f"{'total s':>9}{'dec+tri x load':>16}{'total x load':>14}")
        for name, method in timing:
            session = sessions[name]
            view = session.views[0]
            # load only the images this method reads: flat frames + its patterns
            family = "hybrid" if method == "hybrid" else "gray"
            recs = [r for r in view.pattern_images() if session.pattern(r.pattern).family in (family, "flat")]
            loads, totals, parts = [], [], []
            for _ in range(args.repeat):
                t = time.perf_counter()
                for rec in recs:
                    read_png(session.image_path(view, rec))
                loads.append(time.perf_counter() - t)
                t = time.perf_counter()
                result = decode_view(session, view, DecodeConfig(method=method))
                totals.append(time.perf_counter() - t)
                parts.append(result.seconds)
            load, total = statistics.median(loads), statistics.median(totals)
            part = {k: statistics.median(p[k] for p in parts) for k in parts[0]}
            dec_tri = statistics.median(p["decode"] + p["triangulate"] for p in parts)
            print(f"{name:<12}{method:<8}{load:>12.3f}{part['decode']:>10.3f}{part['triangulate']:>10.3f}"
                  f"{part['mesh']:>8.3f}{total:>9.3f}{dec_tri / load:>16.2f}{total / load:>14.2f}")

if __name__ == "__main__":
    main()
