"""Two cameras, one projector: code matching between cameras vs camera-projector triangulation,
and stereo matching under a real two-camera set's conditions.

    .venv/bin/python benchmarks/stereo.py [--scale 1.0] [--scenes object tile] [--keep DIR]
    .venv/bin/python benchmarks/stereo.py --conditions [--scale 3.4] [--spacing 45.2] [--keep DIR]
                                          [--against REV] [--families gray phase]

**Accuracy** (default): captures each scene on the virtual rig with two cameras (the
paper's geometry, camera 1 on the other side of the projector, 40° from camera 0; Gray-code
columns and rows; noise on) and reconstructs view 0 in the same run by

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

**Conditions** (``--conditions``): the figurine seen by two cameras ``--spacing`` apart
(default 45.2°: 1 m apart at 1.3 m) at ``--scale`` (default 3.4: 4896x3264, 16 MP, the
1024x768 projector at its full size, so a projector pixel covers 3.4 x 3.4 camera pixels),
saved as JPEG (quality 90; a linear camera curve: the phase decoder does not read sRGB
sessions yet), once with Gray-code and once with
phase-shifting columns and rows (``--families``). Each is matched in the conditions a real
two-camera set met (issue #31):

- *all bits*: the captures as they are;
- *2 bits missing*: the two finest Gray-code bits of each axis left out (the codes step by
  4: cells of 4 x 4 projector pixels, 14 x 14 camera pixels, wider than the plane fit's
  window);
- *drop 2 bits*: ``gray_drop_bits=2`` (a pixel whose finest bits are weak keeps a coarser
  code);
- *1.8 px off*: camera 1's pose in ``cameras.json`` turned by 1.8 px about its x axis, the
  calibration residual the real set had.

Rows "before" run the matcher of git revision ``--against`` (default: the merge base with
``main``) in a child process, with its defaults (plane fits only, mesh step 1, a fixed
1.5 px epipolar limit); the others this tree's defaults (per-cell centroid fallback, the
mesh at the codes' real step, the epipolar limit from the matches' own distances). For
each: cells each camera saw (and the share plane-fitted), cells common to both, rejected
by each test (epipolar, ray gap, behind), the epipolar limit used, matched points, range-map
vertices and faces, bad matches (matched points more than 2 mm from the true surface:
10 camera pixels at 16 MP), the vertices' distance to the truth (median, 95th percentile,
mm) and the wall time of the view (both cameras decoded).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
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
from measure import cpu_seconds, distances_to_mesh, export_toolbox, run_json


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


# --- conditions --------------------------------------------------------------------------------

BAD_MM = 2.0
"""A matched point further than this from the true surface is a bad match."""

BEFORE = r"""
import json, sys, time
import numpy as np
from slscan.capture.multicam import load_multicam
from slscan.decode.stereo import reconstruct_view

multi = load_multicam(sys.argv[1], validate=False)
t = time.perf_counter()
r = reconstruct_view(multi, multi.view_names[0])
wall = time.perf_counter() - t
np.save(sys.argv[2], r.match.points)
np.save(sys.argv[3], r.range_map.vertices)
print(json.dumps({"stats": r.match.stats, "faces": len(r.range_map.faces), "wall": wall}))
"""


def _capture(family: str, scale: float, projector_scale: float, spacing: float, folder: Path):
    from slscan.capture.multicam import load_multicam
    from slscan.virtual.sensor import Sensor

    out = folder / f"{family}_{scale:g}_{projector_scale:g}_{spacing:g}"
    if (out / "cameras.json").is_file():
        return load_multicam(out, validate=False)
    config = VirtualCaptureConfig(patterns=family, gray_rows=True, lit_images=False, camera_scale=scale,
                                  projector_scale=projector_scale,
                                  sensor=Sensor(jpeg_quality=90))
    t = time.perf_counter()
    multi = capture_multicam(config, out, spacing_deg=spacing)
    print(f"# captured {family}: 2 cameras x 42 JPEG {multi.sessions[0].camera_size[0]}x"
          f"{multi.sessions[0].camera_size[1]} in {time.perf_counter() - t:.0f} s", flush=True)
    return multi


def _variant(multi, name: str, folder: Path):
    """A copy of ``multi`` in ``folder / name`` that shares its images (hard links): 2 finest
    Gray-code bits left out of the sets ("missing"), or camera 1's pose turned by 1.8 px
    about its x axis ("off")."""
    from slscan.capture.multicam import load_multicam
    from slscan.rig import rotation_about_axis

    dst = folder / name
    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    meta = json.loads((multi.root / "cameras.json").read_text())
    for cam in meta["cameras"]:
        src = multi.root / cam.get("session", cam["name"])
        for item in src.rglob("*"):
            target = dst / src.name / item.relative_to(src)
            if item.is_dir():
                target.mkdir(parents=True, exist_ok=True)
            elif item.name != "session.json":
                target.parent.mkdir(parents=True, exist_ok=True)
                os.link(item, target)
        session = json.loads((src / "session.json").read_text())
        if name == "missing":
            drop = {p["id"] for p in session["patterns"] if p["family"] == "gray" and p["bit"] >= p["bits"] - 2}
            session["patterns"] = [p for p in session["patterns"] if p["id"] not in drop]
            for v in session["views"]:
                v["images"] = [r for r in v["images"] if r.get("pattern") not in drop]
        (dst / src.name / "session.json").write_text(json.dumps(session))
    if name == "off":
        cam1 = meta["cameras"][1]
        turn = np.eye(4)
        turn[:3, :3] = rotation_about_axis([1.0, 0.0, 0.0], 1.8 / cam1["lens"]["fy"])
        cam1["rig_from_camera"] = (np.asarray(cam1["rig_from_camera"]) @ turn).tolist()
    (dst / "cameras.json").write_text(json.dumps(meta))
    return load_multicam(dst, validate=False)


def _row(condition: str, method: str, stats: dict, points, vertices, faces: int, wall: float, truth) -> dict:
    bad = int((distances_to_mesh(points, *truth) > BAD_MM).sum()) if len(points) else 0
    d = distances_to_mesh(vertices, *truth) if len(vertices) else np.array([math.nan])
    return {"condition": condition, "method": method, "stats": stats, "bad": bad, "vertices": len(vertices),
            "faces": faces, "err": (float(np.median(d)), float(np.percentile(d, 95))), "wall": wall}


def conditions_table(args: argparse.Namespace, folder: Path) -> list[dict]:
    rev = args.against or subprocess.run(["git", "merge-base", "HEAD", "main"], capture_output=True, text=True,
                                         check=True).stdout.strip()
    old = export_toolbox(rev, folder / "old")
    scene = scene_by_name("object")
    rows = []
    for family in args.families:
        multi = _capture(family, args.scale, args.projector_scale, args.spacing, folder)
        view = multi.sessions[0].views[0]
        truth = (transform_points(view.rig_from_object, scene.vertices), scene.triangles)
        cases = [("all bits", multi, StereoConfig())]
        if family == "gray":
            cases += [("2 bits missing", _variant(multi, "missing", folder), StereoConfig()),
                      ("drop 2 bits", multi, StereoConfig(gray_drop_bits=2))]
        cases += [("1.8 px off", _variant(multi, "off", folder), StereoConfig())]
        for condition, m, config in cases:
            label = f"{family}, {condition}"
            if family == "gray" and config.gray_drop_bits == 0:
                out = run_json([sys.executable, "-c", BEFORE, str(m.root), str(folder / "p.npy"), str(folder / "v.npy")],
                               f"before ({label})", old)
                rows.append(_row(label, f"before ({rev[:7]})", out["stats"], np.load(folder / "p.npy"),
                                 np.load(folder / "v.npy"), out["faces"], out["wall"], truth))
            t = time.perf_counter()
            res = reconstruct_view(m, view.name, config)
            wall = time.perf_counter() - t
            rows.append(_row(label, "now", res.match.stats, res.match.points, res.range_map.vertices,
                             len(res.range_map.faces), wall, truth))
            print(f"# {label}: {res.describe()}", flush=True)
    return rows


def print_conditions(rows: list[dict], args: argparse.Namespace, size: str) -> None:
    print(f"\nfigurine, 2 cameras {args.spacing:g}° apart ({2 * 1300 * math.sin(math.radians(args.spacing) / 2):.0f} mm), "
          f"{size} JPEG, view 0; distances to the true surface in mm; bad: matches > {BAD_MM:g} mm off\n")
    head = (f"{'condition':<22} {'method':<16} {'cells A (fit)':>15} {'cells B':>8} {'common':>8} "
            f"{'-epi':>7} {'-gap':>6} {'-behind':>7} {'limit px':>8} {'matched':>8} {'bad':>5} "
            f"{'vertices':>9} {'faces':>9} {'median':>7} {'p95':>7} {'wall s':>7}")
    print(head)
    print("-" * len(head))
    for r in rows:
        st = r["stats"]
        fit = f"{st['codes_a']:,} ({st['refined_a'] / max(st['codes_a'], 1):.0%})" if "refined_a" in st else f"{st['codes_a']:,}"
        limit = st.get("epipolar_limit_px", 1.5)
        print(f"{r['condition']:<22} {r['method']:<16} {fit:>15} {st['codes_b']:>8,} {st['common']:>8,} "
              f"{st['rejected_epipolar']:>7,} {st['rejected_ray_gap']:>6,} {st['rejected_behind']:>7,} {limit:>8.2f} "
              f"{st['matched']:>8,} {r['bad']:>5,} {r['vertices']:>9,} {r['faces']:>9,} {r['err'][0]:>7.3f} "
              f"{r['err'][1]:>7.3f} {r['wall']:>7.1f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scale", type=float, default=None,
                        help="camera size factor (default 1: 1440x960, 1024x768; --conditions: 3.4, 4896x3264)")
    parser.add_argument("--scenes", nargs="+", default=["object", "tile"], help="default: object tile")
    parser.add_argument("--keep", type=Path, help="keep the captures in this folder (and reuse them)")
    parser.add_argument("--conditions", action="store_true", help="the real-data conditions table instead")
    parser.add_argument("--projector-scale", type=float, default=1.0, help="--conditions: projector size factor")
    parser.add_argument("--spacing", type=float, default=2 * math.degrees(math.asin(500 / 1300)),
                        help="--conditions: angle between the cameras, degrees (default 45.2: 1 m apart)")
    parser.add_argument("--families", nargs="+", default=["gray", "phase"], help="--conditions: default gray phase")
    parser.add_argument("--against", metavar="REV", help="--conditions: the 'before' revision (default: merge base with main)")
    args = parser.parse_args()
    if args.conditions:
        args.scale = 3.4 if args.scale is None else args.scale
        with tempfile.TemporaryDirectory() as tmp:
            folder = args.keep or Path(tmp)
            folder.mkdir(parents=True, exist_ok=True)
            rows = conditions_table(args, folder)
        w, h = round(1440 * args.scale), round(960 * args.scale)
        print_conditions(rows, args, f"{w}x{h}")
        return 0
    args.scale = 1.0 if args.scale is None else args.scale
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
