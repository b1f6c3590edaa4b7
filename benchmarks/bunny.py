"""Register and fuse the Stanford bunny's 10 real range scans; compare with bun.conf and bun_zipper.

    .venv/bin/python benchmarks/bunny.py [--data ../shared/data] [--voxel 0.5] [--seed 7]
        [--against REV] [--o3d-voxels 2,1.5] [--register-only]

(a) Registration (gauge fixed on bun000), three starts:

- "perturbed": bun.conf poses moved by random rotations <= 10 degrees and translations
  <= 10 mm (fixed seed);
- "none": every scan at the identity, so all pairs are found from FPFH features;
- "bun.conf": bun.conf itself, to show where ICP's optimum lies relative to bun.conf.

Per scan: rotation error (degrees) and translation error (mm) against bun.conf, the
translation measured at the scan frame's origin and at the scan's centroid (the origin
is ~100 mm from the samples, so a 0.1 degree rotation alone moves it ~0.2 mm). Then the
same after taking out the one rigid motion that best fits the whole registration onto
bun.conf (``fit_gauge``): which scan is held still is a choice, and bun000's bun.conf pose
has error of its own.

(a2) Cost and accuracy side by side, from the perturbed start: slscan's ``register_scans``
(this working tree and, with ``--against REV``, the toolbox of git revision REV, exported
with ``git archive``) and Open3D's multiway registration pipeline as in its tutorial
(``o3d_multiway``: voxel downsampling and normal estimation, point-to-plane ICP at 15 then
1.5 voxels on every pair, odometry edges between consecutive scans, a pose graph optimised
by ``global_optimization`` with a line process), at each voxel of ``--o3d-voxels`` (mm).
CPU time is ``time.process_time()`` around the registration alone (all threads of the
process; loading the scans excluded); the errors are the worst scan's, against bun.conf,
raw (gauge on bun000) and after ``fit_gauge``.

(b) Fusion of the 10 scans at the registered ("perturbed") poses: weighted TSDF
(``fuse_scans``) and screened Poisson (pymeshlab), each compared with Stanford's
``reconstruction/bun_zipper.ply``: mean and 95th percentile distance (mm) from each mesh's
vertices to the other surface, both directions; then simplification of the TSDF mesh to
the zipper's face count.

Each stage runs in its own subprocess: its time and peak memory (VmHWM, which sees
open3d's and pymeshlab's C++ allocations) are its own.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from measure import distances_to_mesh, export_toolbox, peak_rss_bytes, run_json, surface_samples

DEG, MM = 10.0, 10.0
O3D_ORDER = ("chin", "bun315", "bun000", "bun045", "top3", "bun090", "top2", "ear_back",
             "bun180", "bun270")
"""The scans in an order where consecutive ones overlap (42-86 %, under bun.conf): the
tutorial trusts the odometry edge between consecutive scans. In bun.conf's own order
(bun090 -> bun180: 32 %; chin -> ear_back: 7 %) its result is off by more than 7 degrees
at every voxel size tried, even from bun.conf itself."""


def perturbed(poses: dict, seed: int, keep: str = "bun000") -> dict:
    from slscan.register.pairwise import rigid_transform

    rng = np.random.default_rng(seed)
    out = {}
    for name, pose in poses.items():
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        motion = rigid_transform(
            axis / np.linalg.norm(axis) * np.radians(rng.uniform(0, DEG)),
            direction / np.linalg.norm(direction) * rng.uniform(0, MM),
        )
        out[name] = pose if name == keep else motion @ pose
    return out


# --- stages ---------------------------------------------------------------------------------------


def stage_register(args) -> dict:
    import warnings

    from slscan.register.multiview import register_scans
    from slscan.register.rangescan import load_stanford_dir

    scans, truth = load_stanford_dir(args.data / "stanford_bunny")
    start = {"perturbed": perturbed(truth, args.seed), "none": None, "conf": truth}[args.start]
    t, cpu = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if args.method == "open3d":
            poses, edges = o3d_multiway(scans, start, args.o3d_voxel)
            pairs, rmse, left_out = edges, [], {}
        else:
            result = register_scans(scans, initial_poses=start, reference="bun000")
            poses, pairs, left_out = result.poses, len(result.pairs), result.left_out
            rmse = [p.rmse for p in result.pairs]
    seconds, cpu = time.perf_counter() - t, time.process_time() - cpu
    (args.work / f"poses-{args.start}-{args.tag}.json").write_text(
        json.dumps({k: v.tolist() for k, v in poses.items()})
    )
    return {
        "seconds": seconds,
        "cpu": cpu,
        "peak": peak_rss_bytes(),
        "left_out": left_out,
        "pairs": pairs,
        "warnings": [str(w.message) for w in caught],
        "rmse": rmse,
        "start": {k: v.tolist() for k, v in (start or {}).items()},
    }


def o3d_multiway(scans, start: dict, voxel: float) -> tuple[dict, int]:
    """Open3D's multiway registration tutorial on the scans placed at their ``start`` poses:
    world_from_scan of each scan (gauge: bun000 keeps its start pose) and the number of
    pose-graph edges the line process kept."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    by_name = {s.name: s for s in scans}
    order = [n for n in O3D_ORDER if n in by_name]
    pcds = []
    for name in order:
        pcd = o3d.geometry.PointCloud(
            o3d.utility.Vector3dVector(by_name[name].transformed_vertices(start[name]))
        )
        pcd = pcd.voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        pcds.append(pcd)
    coarse, fine = 15 * voxel, 1.5 * voxel
    graph = reg.PoseGraph()
    odometry = np.eye(4)
    graph.nodes.append(reg.PoseGraphNode(odometry))
    for i in range(len(pcds)):
        for j in range(i + 1, len(pcds)):
            icp = reg.registration_icp(pcds[i], pcds[j], coarse, np.eye(4),
                                       reg.TransformationEstimationPointToPlane())
            icp = reg.registration_icp(pcds[i], pcds[j], fine, icp.transformation,
                                       reg.TransformationEstimationPointToPlane())
            info = reg.get_information_matrix_from_point_clouds(pcds[i], pcds[j], fine,
                                                                icp.transformation)
            if j == i + 1:
                odometry = icp.transformation @ odometry
                graph.nodes.append(reg.PoseGraphNode(np.linalg.inv(odometry)))
            graph.edges.append(reg.PoseGraphEdge(i, j, icp.transformation, info,
                                                 uncertain=j != i + 1))
    option = reg.GlobalOptimizationOption(max_correspondence_distance=fine,
                                          edge_prune_threshold=0.25, reference_node=0)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    poses = {n: np.asarray(graph.nodes[k].pose) @ start[n] for k, n in enumerate(order)}
    fix = start["bun000"] @ np.linalg.inv(poses["bun000"])
    return {n: fix @ p for n, p in poses.items()}, len(graph.edges)


def stage_fuse(args) -> dict:
    from slscan.fuse import FuseConfig, fuse_scans, poisson_reconstruct, write_mesh
    from slscan.register.rangescan import load_stanford_dir

    scans, conf = load_stanford_dir(args.data / "stanford_bunny")
    poses = {
        k: np.array(v)
        for k, v in json.loads((args.work / "poses-perturbed-slscan.json").read_text()).items()
    }
    if args.method == "tsdf-conf":
        poses = conf
    scans = [s for s in scans if s.name in poses]
    t = time.perf_counter()
    if args.method in ("tsdf", "tsdf-conf"):
        result = fuse_scans(scans, poses, config=FuseConfig(voxel_size=args.voxel))
        mesh, extra = result.mesh, {"blocks": result.n_blocks, "grid_bytes": result.grid_bytes}
    else:
        mesh, extra = poisson_reconstruct(scans, poses, voxel_size=args.voxel), {}
    seconds = time.perf_counter() - t
    write_mesh(mesh, args.work / f"fused-{args.method}.ply")
    return {
        "seconds": seconds,
        "peak": peak_rss_bytes(),
        "faces": mesh.n_faces,
        **extra,
        **_compare(mesh.vertices, mesh.faces, args.data),
    }


def stage_simplify(args) -> dict:
    from slscan.fuse import read_mesh
    from slscan.simplify import simplify_mesh

    mesh = read_mesh(args.work / "fused-tsdf.ply")
    t = time.perf_counter()
    out = simplify_mesh(mesh, args.faces, method=args.method)
    seconds = time.perf_counter() - t
    return {
        "seconds": seconds,
        "peak": peak_rss_bytes(),
        "faces_in": mesh.n_faces,
        "faces": out.n_faces,
        **_compare(out.vertices, out.faces, args.data),
    }


def _compare(vertices: np.ndarray, faces: np.ndarray, data: Path) -> dict:
    """Distances (mm) between a mesh and bun_zipper.ply (scaled to mm), both directions,
    over points spread uniformly by area on the measured surface."""
    from slscan.ply import fan_triangles, read_ply_elements

    ply = read_ply_elements(data / "stanford_bunny" / "reconstruction" / "bun_zipper.ply")
    ref_v = np.stack([ply["vertex"][k] for k in "xyz"], 1).astype(np.float64) * 1000.0
    ref_f = fan_triangles(*ply["face"]["vertex_indices"])

    to_ref = distances_to_mesh(surface_samples(vertices, faces), ref_v, ref_f)
    from_ref = distances_to_mesh(surface_samples(ref_v, ref_f), vertices, faces)
    return {
        "to_ref_mean": float(to_ref.mean()),
        "to_ref_p95": float(np.percentile(to_ref, 95)),
        "from_ref_mean": float(from_ref.mean()),
        "from_ref_p95": float(np.percentile(from_ref, 95)),
    }


# --- driver ---------------------------------------------------------------------------------------


def _run(args, stage: str, *, toolbox: Path | None = None, **extra) -> dict:
    """Run one stage in a subprocess (slscan from ``toolbox`` when given); its JSON result."""
    command = [
        sys.executable,
        __file__,
        "--stage",
        stage,
        "--data",
        str(args.data),
        "--work",
        str(args.work),
        "--voxel",
        str(args.voxel),
        "--seed",
        str(args.seed),
        "--faces",
        str(args.faces),
    ]
    for k, v in extra.items():
        command += [f"--{k}", str(v)]
    return run_json(command, f"stage {stage} {extra}", toolbox)


def _errors(poses: dict, truth: dict, scans: dict) -> dict:
    from slscan.register.pairwise import pose_error

    out = {}
    for name, t in truth.items():
        if name not in poses:
            out[name] = None
            continue
        p = np.asarray(poses[name])
        rot, t_origin = pose_error(p, t)
        _, t_centroid = pose_error(p, t, at=scans[name].vertices.mean(axis=0))
        out[name] = (rot, t_origin, t_centroid)
    return out



def _print_side_by_side(side: dict, side_poses: dict, truth: dict, by_name: dict,
                        samples: dict) -> None:
    """Table (a2): CPU time and worst-scan errors of each registration from the perturbed start."""
    from slscan.register.pairwise import fit_gauge

    base = next((r["cpu"] for label, r in side.items() if label.startswith("Open3D")), None)
    print(f"(a2) from the perturbed start, side by side ({os.cpu_count()} CPUs): CPU time "
          "(process, all threads), wall time, worst scan vs bun.conf: rotation (deg) / "
          "translation at its centroid (mm), raw and after fit_gauge")
    print(f"{'registration':<30} {'cpu s':>7} {'x Open3D':>8} {'wall s':>7} "
          f"{'max rot':>8} {'max tr':>7} {'fit rot':>8} {'fit tr':>7} {'scans':>6} {'edges':>6}")
    for label, r in side.items():
        p = {k: np.array(v) for k, v in side_poses[label].items()}
        raw = [e for e in _errors(p, truth, by_name).values() if e is not None]
        gauge = fit_gauge(p, truth, samples)
        fit = [e for e in _errors({k: gauge @ v for k, v in p.items()}, truth, by_name).values()
               if e is not None]
        ratio = f"{r['cpu'] / base:8.2f}" if base else f"{'':>8}"
        print(f"{label:<30} {r['cpu']:7.1f} {ratio} {r['seconds']:7.1f} "
              f"{max(e[0] for e in raw):8.3f} {max(e[2] for e in raw):7.3f} "
              f"{max(e[0] for e in fit):8.3f} {max(e[2] for e in fit):7.3f} "
              f"{len(p):>3}/{len(truth):<2} {r['pairs']:6d}")
    print("    x Open3D: CPU time over the first Open3D row's; edges: slscan's overlapping pairs, "
          "Open3D's pose-graph edges kept")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    from slscan.data import shared_data_dir

    parser.add_argument("--data", type=Path, default=shared_data_dir(), help="shared data folder")
    parser.add_argument("--voxel", type=float, default=0.5, help="fusion voxel size, mm")
    parser.add_argument("--seed", type=int, default=7, help="seed of the pose perturbation")
    parser.add_argument(
        "--faces", type=int, default=69_451, help="simplification target (bun_zipper's count)"
    )
    parser.add_argument("--against", metavar="REV",
                        help="also time the registration of git revision REV (exported with git archive)")
    parser.add_argument("--o3d-voxels", default="2,1.5",
                        help="voxel sizes (mm) of Open3D's multiway pipeline, comma-separated (default 2,1.5)")
    parser.add_argument("--register-only", action="store_true", help="stop after the registration tables")
    parser.add_argument("--work", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--o3d-voxel", type=float, default=2.0, help=argparse.SUPPRESS)
    parser.add_argument("--tag", default="slscan", help=argparse.SUPPRESS)
    parser.add_argument("--stage", help=argparse.SUPPRESS)
    parser.add_argument("--start", default="perturbed", help=argparse.SUPPRESS)
    parser.add_argument("--method", default="", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.data is None or not (args.data / "stanford_bunny").is_dir():
        raise SystemExit("bunny data not found: pass --data or set SLSCAN_DATA")
    if args.stage:
        fn = {"register": stage_register, "fuse": stage_fuse, "simplify": stage_simplify}[
            args.stage
        ]
        print(json.dumps(fn(args)))
        return

    from slscan.register.rangescan import load_stanford_dir

    scans, truth = load_stanford_dir(args.data / "stanford_bunny")
    by_name = {s.name: s for s in scans}
    with tempfile.TemporaryDirectory(prefix="slscan-bunny-") as tmp:
        args.work = Path(tmp)
        reg = {
            start: _run(args, "register", start=start) for start in ("perturbed", "none", "conf")
        }
        poses = {
            start: json.loads((args.work / f"poses-{start}-slscan.json").read_text())
            for start in reg
        }
        runs = {"slscan (this tree)": ("slscan", reg["perturbed"])}
        if args.against:
            toolbox = export_toolbox(args.against, args.work / "against")
            runs[f"slscan ({args.against})"] = (
                "against", _run(args, "register", toolbox=toolbox, tag="against"))
        for voxel in [float(v) for v in args.o3d_voxels.split(",") if v.strip()]:
            tag = f"o3d-{voxel:g}"
            runs[f"Open3D multiway, {voxel:g} mm"] = (
                tag, _run(args, "register", method="open3d", tag=tag, **{"o3d-voxel": voxel}))
        side = {label: r for label, (_, r) in runs.items()}
        side_poses = {
            label: json.loads((args.work / f"poses-perturbed-{tag}.json").read_text())
            for label, (tag, _) in runs.items()
        }
        if not args.register_only:
            fused = {m: _run(args, "fuse", method=m) for m in ("tsdf", "poisson", "tsdf-conf")}
            simp = {m: _run(args, "simplify", method=m) for m in ("fast", "quadric")}

    initial = _errors(
        {k: np.array(v) for k, v in reg["perturbed"]["start"].items()}, truth, by_name
    )
    errs = {s: _errors({k: np.array(v) for k, v in poses[s].items()}, truth, by_name) for s in reg}

    def cell(e):
        return "  left out       " if e is None else f"{e[0]:6.3f} {e[1]:6.3f} {e[2]:6.3f}"

    print(f"(a) registration vs bun.conf, gauge on bun000 ({os.cpu_count()} CPUs)")
    print(
        "    columns per start: rotation (deg), translation at the scan origin (mm), at its centroid (mm)"
    )
    print(
        f"{'scan':<9} {'perturbed start':>21} | {'from perturbed':>21} | {'from no poses':>21} | {'from bun.conf':>21}"
    )
    for name in truth:
        print(
            f"{name:<9} {cell(initial[name]):>21} | {cell(errs['perturbed'][name]):>21} | "
            f"{cell(errs['none'][name]):>21} | {cell(errs['conf'][name]):>21}"
        )
    def worst(table):
        cols = []
        for s in ("perturbed", "none", "conf"):
            vals = [e for e in table[s].values() if e is not None]
            cols.append(f"{max(v[0] for v in vals):6.3f} {max(v[1] for v in vals):6.3f} {max(v[2] for v in vals):6.3f}")
        return f"{'':>21} | {cols[0]:>21} | {cols[1]:>21} | {cols[2]:>21}"

    print(f"{'max':<9} {worst(errs)}")
    # the gauge (bun000 held at its bun.conf pose) is a choice: bun000's bun.conf pose has
    # error too. Take out the one rigid motion that best fits the whole set to bun.conf.
    from slscan.register.pairwise import fit_gauge

    samples = {n: s.vertices[::25] for n, s in by_name.items()}
    fitted = {}
    for s in reg:
        p = {k: np.array(v) for k, v in poses[s].items()}
        gauge = fit_gauge(p, truth, samples)
        fitted[s] = _errors({k: gauge @ v for k, v in p.items()}, truth, by_name)
    print("    the same after the one rigid motion that best fits all scans onto bun.conf:")
    for name in truth:
        print(
            f"{name:<9} {'':>21} | {cell(fitted['perturbed'][name]):>21} | "
            f"{cell(fitted['none'][name]):>21} | {cell(fitted['conf'][name]):>21}"
        )
    print(f"{'max':<9} {worst(fitted)}")
    print(
        f"{'time':<9} {'':>21} | "
        + " | ".join(f"{reg[s]['seconds']:19.1f} s" for s in ("perturbed", "none", "conf"))
    )
    print(
        f"{'cpu':<9} {'':>21} | "
        + " | ".join(f"{reg[s]['cpu']:19.1f} s" for s in ("perturbed", "none", "conf"))
    )
    print(
        f"{'peak':<9} {'':>21} | "
        + " | ".join(f"{reg[s]['peak'] / 2**20:17.0f} MiB" for s in ("perturbed", "none", "conf"))
    )
    print(
        f"{'pairs':<9} {'':>21} | "
        + " | ".join(
            f"{reg[s]['pairs']:3d}, RMS {np.median(reg[s]['rmse']):.3f} mm".rjust(21)
            for s in ("perturbed", "none", "conf")
        )
    )
    for s in reg:
        if reg[s]["left_out"]:
            print(f"  {s}: left out {reg[s]['left_out']}")
    print()
    _print_side_by_side(side, side_poses, truth, by_name, samples)
    if args.register_only:
        return
    print()
    print(
        f"(b) fusion of the 10 scans at the poses registered from the perturbed start, "
        f"{args.voxel:g} mm; distances (mm) over points spread by area on the measured surface"
    )
    print(
        f"{'model':<27} {'faces':>9} {'time':>8} {'peak':>9}  {'to zipper mean/p95':>19}  "
        f"{'zipper to it mean/p95':>22}"
    )
    rows = [
        (f"TSDF ({args.voxel:g} mm)", fused["tsdf"]),
        ("screened Poisson", fused["poisson"]),
        ("TSDF -> fast simplify", simp["fast"]),
        ("TSDF -> quadric (MeshLab)", simp["quadric"]),
        ("TSDF at bun.conf poses", fused["tsdf-conf"]),
    ]
    for label, r in rows:
        print(
            f"{label:<27} {r['faces']:>9} {r['seconds']:>6.1f} s {r['peak'] / 2**20:>5.0f} MiB  "
            f"{r['to_ref_mean']:>8.3f} / {r['to_ref_p95']:.3f}  {r['from_ref_mean']:>11.3f} / {r['from_ref_p95']:.3f}"
        )


if __name__ == "__main__":
    main()
