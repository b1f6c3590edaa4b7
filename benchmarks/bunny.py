"""Register and fuse the Stanford bunny's 10 real range scans; compare with bun.conf and bun_zipper.

    .venv/bin/python benchmarks/bunny.py [--data ../shared/data] [--voxel 0.5] [--seed 7]

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
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from measure import distances_to_mesh, peak_rss_bytes, surface_samples

DEG, MM = 10.0, 10.0



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
    t = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = register_scans(scans, initial_poses=start, reference="bun000")
    seconds = time.perf_counter() - t
    (args.work / f"poses-{args.start}.json").write_text(
        json.dumps({k: v.tolist() for k, v in result.poses.items()})
    )
    return {
        "seconds": seconds,
        "peak": peak_rss_bytes(),
        "left_out": result.left_out,
        "pairs": len(result.pairs),
        "warnings": [str(w.message) for w in caught],
        "rmse": [p.rmse for p in result.pairs],
        "start": {k: v.tolist() for k, v in (start or {}).items()},
    }


def stage_fuse(args) -> dict:
    from slscan.fuse import FuseConfig, fuse_scans, poisson_reconstruct, write_mesh
    from slscan.register.rangescan import load_stanford_dir

    scans, conf = load_stanford_dir(args.data / "stanford_bunny")
    poses = {
        k: np.array(v)
        for k, v in json.loads((args.work / "poses-perturbed.json").read_text()).items()
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


def _run(args, stage: str, **extra) -> dict:
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
    proc = subprocess.run(command, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"stage {stage} {extra} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


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
    parser.add_argument("--work", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--stage", help=argparse.SUPPRESS)
    parser.add_argument("--start", default="perturbed", help=argparse.SUPPRESS)
    parser.add_argument("--method", default="tsdf", help=argparse.SUPPRESS)
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
            start: json.loads((args.work / f"poses-{start}.json").read_text()) for start in reg
        }
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
