"""Free-hand registration (no poses at all): views within 2 degrees / 2 mm of the truth, and
views wrongly reported aligned.

    .venv/bin/python benchmarks/register_freehand.py [--sets figurine-quarter,figurine-half,
        figurine-full,bust-half,bunny] [--against REV] [--no-peer] [--work DIR] [--data DIR]

Each set of range scans is registered with no poses (the turntable's recorded poses are
the truth, not the start), each registration in its own process:

- ``this tree``: :func:`slscan.register.multiview.register_scans` as it is here;
- with ``--against REV``: the toolbox of git revision REV (the method before);
- ``peer``: plain Open3D, as its multiway-registration tutorial does it: FPFH + RANSAC
  per pair, point-to-plane ICP, a pose graph with line-process pruning; every view it
  places is reported aligned.

Sets: the virtual rig's figurine (``recipes/demo.toml``: 8 turntable views) at quarter,
half and full camera size, the marble bust (``marble``) at half size, and the real Stanford
bunny (10 scans; ``bun.conf`` the truth; ``--data`` or ``SLSCAN_DATA``, default
``../shared/data``). A registration fixes the scans relative to each other only: its
gauge is the one motion, among those putting one registered view onto its true pose,
that puts the most views within 2 degrees / 2 mm (translation at the view's centroid).
Columns: views; within 2 deg / 2 mm; left out (named); false aligned (reported aligned
but outside 2 deg / 2 mm; the target is 0); wall time of the registration (s).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np
from measure import export_toolbox, run_json

ROOT = Path(__file__).resolve().parents[1]
SETS = {  # name: (scene, camera and projector scale, pattern levels)
    "figurine-quarter": ("object", 0.25, 7),
    "figurine-half": ("object", 0.5, 8),
    "figurine-full": ("object", 1.0, 9),
    "bust-half": ("marble", 0.5, 8),
}
ROT_DEG, MM = 2.0, 2.0


def capture(scene: str, scale: float, levels: int, work: Path) -> Path:
    """Range maps of the demo recipe for ``scene`` at ``scale`` (cached in ``work``)."""
    from slscan.recipe.runner import parse_recipe, run_recipe

    out = work / f"{scene}-{scale:g}"
    if (out / "decode" / "range_maps.json").is_file():
        return out / "decode"
    data = tomllib.loads((ROOT / "recipes" / "demo.toml").read_text())
    data["recipe"]["stages"] = ["capture", "decode"]
    data["recipe"].pop("reduced", None)
    for name in list(data):
        if name not in ("recipe", "capture", "decode"):
            data.pop(name)
    data["capture"].update(scene=scene, camera_scale=scale, projector_scale=scale, levels=levels)
    run_recipe(parse_recipe(data, where="demo", path=ROOT / "recipes" / "demo.toml", overrides=[]), out)
    return out / "decode"


def peer(scans) -> dict[str, np.ndarray]:
    """Open3D's multiway registration (its tutorial's recipe) from FPFH + RANSAC per pair."""
    import open3d as o3d

    from slscan.register.pairwise import median_edge_length, scan_point_cloud

    reg = o3d.pipelines.registration
    spacing = float(np.median([median_edge_length(s) for s in scans]))
    voxel = 4.0 * spacing
    clouds = [scan_point_cloud(s).voxel_down_sample(voxel) for s in scans]
    feats = [reg.compute_fpfh_feature(c, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
             for c in clouds]
    graph = reg.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odometry))
    n = len(scans)
    for i in range(n):
        for j in range(i + 1, n):
            coarse = reg.registration_ransac_based_on_feature_matching(
                clouds[i], clouds[j], feats[i], feats[j], True, 1.5 * voxel,
                reg.TransformationEstimationPointToPoint(False), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
                reg.RANSACConvergenceCriteria(100000, 0.999))
            icp = reg.registration_icp(clouds[i], clouds[j], 1.5 * voxel, coarse.transformation,
                                       reg.TransformationEstimationPointToPlane())
            info = reg.get_information_matrix_from_point_clouds(clouds[i], clouds[j], 1.5 * voxel,
                                                                icp.transformation)
            if j == i + 1:
                odometry = np.asarray(icp.transformation) @ odometry
                graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry)))
            graph.edges.append(reg.PoseGraphEdge(i, j, icp.transformation, info, uncertain=j != i + 1))
    reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                            reg.GlobalOptimizationConvergenceCriteria(),
                            reg.GlobalOptimizationOption(max_correspondence_distance=1.5 * voxel,
                                                         edge_prune_threshold=0.25, reference_node=0))
    # open3d's nodes map each scan into the first scan's frame
    return {s.name: np.asarray(graph.nodes[k].pose) for k, s in enumerate(scans)}


def child(args: argparse.Namespace) -> dict:
    """Register one set with no poses; per view: reported aligned? error against the truth."""
    import warnings

    from slscan.register.command import load_scans
    from slscan.register.pairwise import pose_error

    scans, truth = load_scans(Path(args.maps))
    t0 = time.perf_counter()
    if args.method == "peer":
        poses, left_out = peer(scans), {}
    else:
        from slscan.register.multiview import register_scans

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = register_scans(scans, initial_poses=None)
        poses, left_out = result.poses, dict(result.left_out)
    seconds = time.perf_counter() - t0
    centroid = {s.name: s.vertices.mean(axis=0) for s in scans}
    best: tuple[int, dict] = (-1, {})
    for name in poses:
        gauge = truth[name] @ np.linalg.inv(poses[name])
        errors = {k: pose_error(gauge @ p, truth[k], at=centroid[k]) for k, p in poses.items()}
        ok = sum(r <= ROT_DEG and d <= MM for r, d in errors.values())
        if ok > best[0]:
            best = (ok, errors)
    return {"views": len(scans), "within": max(best[0], 0), "left_out": sorted(left_out),
            "false": sorted(k for k, (r, d) in best[1].items() if not (r <= ROT_DEG and d <= MM)),
            "errors": {k: list(v) for k, v in best[1].items()}, "seconds": seconds}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sets", default=",".join([*SETS, "bunny"]), help="which sets (default all)")
    p.add_argument("--against", metavar="REV", help="also register with the toolbox of git revision REV")
    p.add_argument("--no-peer", action="store_true", help="leave out plain Open3D")
    p.add_argument("--work", type=Path, help="keep the captures in this folder (default: a temporary one)")
    p.add_argument("--data", type=Path, default=Path(os.environ.get("SLSCAN_DATA", ROOT.parent / "shared" / "data")),
                   help="real data folder (stanford_bunny/)")
    p.add_argument("--maps", help=argparse.SUPPRESS)
    p.add_argument("--method", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.maps:
        print(json.dumps(child(args)))
        return
    sets = [s for s in args.sets.split(",") if s]
    for name in sets:
        if name not in SETS and name != "bunny":
            raise SystemExit(f"--sets: unknown set {name!r} (expected {', '.join([*SETS, 'bunny'])})")
    with tempfile.TemporaryDirectory(prefix="slscan-register-freehand-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        methods: dict[str, Path | None] = {"this tree": None}
        if args.against:
            methods[args.against] = export_toolbox(args.against, Path(tmp) / "against")
        if not args.no_peer:
            methods["peer"] = None
        header = (f"{'set':17} {'method':10} {'views':>5} {'within 2°/2mm':>13} {'false aligned':>13} "
                  f"{'wall s':>7}  left out (named); false aligned (named)")
        print(header)
        print("-" * len(header))
        for name in sets:
            maps = (args.data / "stanford_bunny") if name == "bunny" else capture(*SETS[name], work)
            for method, toolbox in methods.items():
                r = run_json([sys.executable, __file__, "--maps", str(maps), "--method",
                              "peer" if method == "peer" else "slscan"], f"registration ({method}, {name})", toolbox)
                print(f"{name:17} {method[:10]:10} {r['views']:>5} {r['within']:>13} {len(r['false']):>13} "
                      f"{r['seconds']:7.1f}  {', '.join(r['left_out']) or '-'}; {', '.join(r['false']) or '-'}",
                      flush=True)


if __name__ == "__main__":
    try:
        main()
    except subprocess.CalledProcessError as exc:  # pragma: no cover
        raise SystemExit(str(exc)) from None
