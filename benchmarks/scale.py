"""Paper-scale fusion and simplification: a 1.7 m synthetic statue, 146 range maps of ~500k points.

    .venv/bin/python benchmarks/scale.py                       # the full paper-size case
    .venv/bin/python benchmarks/scale.py --maps 12 --voxel 1.0 # a quick, smaller run

The statue is a procedurally displaced figure (body, head, arms, legs; bumps of 1-8 mm at
20-200 mm wavelengths), 1.7 m tall. Range maps are ray cast (open3d RaycastingScene) from
pinhole sensors on rings around it, 1440x1080 pixels of about 0.6 mm at 1 m (the paper's
camera: 1440x960, 0.7 x 1.4 mm), and meshed on their pixel grid. Each stage runs in its own subprocess so that its
peak memory (VmHWM, which sees open3d's C++ allocations too) is its own:

1. fuse: make the maps one at a time and integrate each into the TSDF grid
   (:func:`slscan.fuse.fuse_scans`), extract the mesh, write it as PLY;
2. simplify: read the fused mesh, simplify it to 1M faces (fast-simplification, boundaries
   kept), write it.

Prints one table: time and peak memory per stage, map count and size, faces in and out,
distance of the models to the statue's true surface. Targets on a 2-core machine: fusion
<= 15 min, simplification <= 1 min, peak <= 12 GiB.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from measure import cpu_seconds, distances_to_mesh, peak_rss_bytes, surface_samples

HEIGHT_MM = 1700.0
IMAGE_SHAPE = (1080, 1440)
FOCAL_PX = 1650.0  # 0.6 mm pixels at 1 m
RING_RADIUS_MM = 1300.0


# --- the statue -----------------------------------------------------------------------------------


def statue() -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) mm, faces (m, 3)) of a displaced 1.7 m figure, z up, feet at z = 0."""
    import open3d as o3d

    rng = np.random.default_rng(2001)
    waves = []
    for wavelength, amplitude in ((200, 8.0), (120, 5.0), (60, 3.0), (35, 2.0), (20, 1.0)):
        for _ in range(3):
            d = rng.normal(size=3)
            waves.append(
                (
                    2 * math.pi / wavelength * d / np.linalg.norm(d),
                    amplitude,
                    rng.uniform(0, 2 * math.pi),
                )
            )

    def part(centre, axes, tilt_deg, resolution):
        sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=resolution)
        unit = np.asarray(sphere.vertices)
        v = unit * axes
        normal = unit / np.asarray(axes)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        t = math.radians(tilt_deg)
        rot = np.array([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]])
        v = v @ rot.T + centre
        normal = normal @ rot.T
        disp = sum(a * np.sin(v @ k + phase) for k, a, phase in waves)
        return v + normal * disp[:, None], np.asarray(sphere.triangles)

    parts = [
        part((0, 0, 900), (230, 170, 650), 0, 600),  # body
        part((0, 0, 1585), (105, 110, 125), 0, 250),  # head
        part((-285, 0, 1080), (60, 65, 380), 12, 300),  # arms
        part((285, 0, 1080), (60, 65, 380), -12, 300),
        part((-105, 0, 420), (95, 95, 420), -3, 300),  # legs
        part((105, 0, 420), (95, 95, 420), 3, 300),
    ]
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def sensor_poses(n_maps: int) -> list[np.ndarray]:
    """world_from_scan of ``n_maps`` pinhole sensors on rings around the statue (looking at it)."""
    rings = [(200, 200), (500, 500), (800, 800), (1100, 1100), (1400, 1400), (1750, 1550)]
    top = max(0, min(8, n_maps // 18))
    per_ring = (n_maps - top) // len(rings)
    extra = n_maps - top - per_ring * len(rings)
    poses = []
    for k, (z_cam, z_look) in enumerate(rings):
        count = per_ring + (1 if k < extra else 0)
        for i in range(count):
            a = 2 * math.pi * (i + 0.5 * (k % 2)) / max(count, 1)
            poses.append(
                _look_at(
                    [RING_RADIUS_MM * math.cos(a), RING_RADIUS_MM * math.sin(a), z_cam],
                    [0, 0, z_look],
                )
            )
    for i in range(top):
        a = 2 * math.pi * i / max(top, 1)
        poses.append(_look_at([500 * math.cos(a), 500 * math.sin(a), 2500], [0, 0, 1300]))
    return poses


def _look_at(eye, target) -> np.ndarray:
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = eye - target
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.95 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eye
    return pose


# --- stages (each in its own process) -------------------------------------------------------------



def stage_fuse(args: argparse.Namespace) -> dict:
    from slscan.fuse import BLOCK_RESOLUTION, FuseConfig, _block_keys, fuse_scans, write_mesh
    from slscan.register.rangescan import raycasting_scene, render_range_scan

    t0 = time.perf_counter()
    vertices, faces = statue()
    scene = raycasting_scene(vertices, faces)
    poses = sensor_poses(args.maps)
    names = [f"map{k:03d}" for k in range(len(poses))]
    # capacity from the statue's own surface, with room for noise (growing the hash map copies it)
    expected = int(
        1.3 * len(_block_keys(vertices, args.voxel * BLOCK_RESOLUTION, 4.0 * args.voxel))
    )
    t_scene = time.perf_counter() - t0
    timing = {"render": 0.0, "points": []}

    def maps():
        for name, pose in zip(names, poses):
            t = time.perf_counter()
            scan = render_range_scan(
                None,
                None,
                pose,
                scene=scene,
                shape=IMAGE_SHAPE,
                focal=FOCAL_PX,
                name=name,
                noise=args.noise,
                rng=np.random.default_rng(len(timing["points"])),
            )
            timing["render"] += time.perf_counter() - t
            timing["points"].append(scan.n_vertices)
            yield scan

    t1 = time.perf_counter()
    cpu1 = cpu_seconds()
    done = [0]

    def progress(name: str) -> None:
        done[0] += 1
        if args.verbose:
            print(
                f"  fused {name} ({done[0]}/{len(names)}) at {time.perf_counter() - t1:.0f} s",
                file=sys.stderr,
                flush=True,
            )

    result = fuse_scans(
        maps(),
        dict(zip(names, poses)),
        config=FuseConfig(voxel_size=args.voxel),
        expected_blocks=expected,
        progress=progress,
    )
    t_total = time.perf_counter() - t1
    cpu_total = cpu_seconds() - cpu1
    write_mesh(result.mesh, args.work / "fused.ply")
    truth = _distance_to_truth(result.mesh.vertices, result.mesh.faces, vertices, faces)
    return {
        "scene_s": t_scene,
        "cpu_s": cpu_total,
        "render_s": timing["render"],
        "fuse_s": t_total - timing["render"],
        "maps": len(names),
        "points_mean": float(np.mean(timing["points"])),
        "points_total": int(np.sum(timing["points"])),
        "blocks": result.n_blocks,
        "grid_bytes": result.grid_bytes,
        "faces": result.mesh.n_faces,
        "phases": result.seconds,
        "vertices": result.mesh.n_vertices,
        "truth": truth,
        "peak": peak_rss_bytes(),
    }


def stage_simplify(args: argparse.Namespace) -> dict:
    from slscan.fuse import read_mesh, write_mesh
    from slscan.simplify import simplify_mesh

    mesh = read_mesh(args.work / "fused.ply")
    t = time.perf_counter()
    cpu = cpu_seconds()
    out = simplify_mesh(mesh, args.faces, method=args.method, preserve_boundary=True)
    seconds = time.perf_counter() - t
    cpu = cpu_seconds() - cpu
    write_mesh(out, args.work / "simplified.ply")
    vertices, faces = statue()
    return {
        "simplify_s": seconds,
        "cpu_s": cpu,
        "faces_in": mesh.n_faces,
        "faces": out.n_faces,
        "truth": _distance_to_truth(out.vertices, out.faces, vertices, faces),
        "peak": peak_rss_bytes(),
    }


def _distance_to_truth(vertices: np.ndarray, faces: np.ndarray, truth_v, truth_f) -> dict:
    """Distance (mm) of a mesh to the statue's true surface: mean and 95th percentile over
    2M points spread uniformly by area on the mesh (vertex statistics would over-count
    the open boundaries' few, extrapolated vertices once a mesh is simplified)."""
    d = distances_to_mesh(surface_samples(vertices, faces, 2_000_000), truth_v, truth_f)
    return {"mean": float(d.mean()), "p95": float(np.percentile(d, 95))}


# --- driver ---------------------------------------------------------------------------------------


def _run_stage(stage: str, args: argparse.Namespace) -> dict:
    command = [
        sys.executable,
        __file__,
        "--stage",
        stage,
        "--maps",
        str(args.maps),
        "--voxel",
        str(args.voxel),
        "--faces",
        str(args.faces),
        "--method",
        args.method,
        "--noise",
        str(args.noise),
        "--work",
        str(args.work),
    ] + (["--verbose"] if args.verbose else [])
    t = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True, check=False)
    if args.verbose and proc.stderr:
        print(proc.stderr, file=sys.stderr, end="")
    if proc.returncode != 0:
        raise SystemExit(f"stage {stage} failed:\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["wall_s"] = time.perf_counter() - t
    return out


def _gib(n: float) -> str:
    return f"{n / 2**30:.2f} GiB"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--maps", type=int, default=146, help="range maps (paper: 146)")
    parser.add_argument("--voxel", type=float, default=0.57, help="voxel size, mm (paper: 0.57)")
    parser.add_argument("--faces", type=int, default=1_000_000, help="simplification target")
    parser.add_argument("--method", default="fast", choices=("fast", "quadric"), help="simplifier")
    parser.add_argument(
        "--noise", type=float, default=0.1, help="range noise, mm (standard deviation)"
    )
    parser.add_argument(
        "--work", type=Path, default=None, help="folder for the meshes (default: a temporary one)"
    )
    parser.add_argument("--verbose", action="store_true", help="progress on stderr")
    parser.add_argument(
        "--reuse-fused",
        action="store_true",
        help="with --work: reuse the fused mesh and numbers of an earlier run there",
    )
    parser.add_argument("--stage", choices=("fuse", "simplify"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.stage:
        result = stage_fuse(args) if args.stage == "fuse" else stage_simplify(args)
        print(json.dumps(result))
        return

    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="slscan-scale-") as tmp:
        args.work = args.work or Path(tmp)
        args.work.mkdir(parents=True, exist_ok=True)
        saved = args.work / "fuse.json"
        if args.reuse_fused and saved.is_file() and (args.work / "fused.ply").is_file():
            fuse = json.loads(saved.read_text())
            if (fuse.get("maps"), fuse.get("voxel")) != (args.maps, args.voxel):
                raise SystemExit(
                    f"{saved}: made with other --maps/--voxel; run without --reuse-fused"
                )
            print(f"(fusion results reused from {saved})")
        else:
            fuse = _run_stage("fuse", args)
            saved.write_text(json.dumps(dict(fuse, voxel=args.voxel)))
        simp = _run_stage("simplify", args)
    rows = [
        (
            "range maps",
            f"{fuse['maps']}",
            f"{fuse['points_mean'] / 1e3:.0f}k points each, {fuse['points_total'] / 1e6:.1f}M in all",
        ),
        ("statue + poses", f"{fuse['scene_s']:.1f} s", ""),
        (
            "render maps",
            f"{fuse['render_s']:.1f} s",
            "ray casting + grid meshing (synthetic input, not fusion)",
        ),
        (
            "fuse (TSDF)",
            f"{fuse['fuse_s']:.1f} s",
            (
                f"{args.voxel:g} mm voxels, {fuse['blocks']} blocks ({_gib(fuse['grid_bytes'])} grid), "
                f"{fuse['faces'] / 1e6:.1f}M faces"
            ),
        ),
        (
            "  height maps",
            f"{fuse['phases']['height_maps']:.1f} s",
            "ray casting each scan along its view direction",
        ),
        ("  integrate", f"{fuse['phases']['integrate']:.1f} s", "weighted TSDF updates"),
        ("  extract", f"{fuse['phases']['extract']:.1f} s", "marching cubes (open3d), in slabs"),
        (
            "  CPU time",
            f"{fuse.get('cpu_s', float('nan')):.1f} s",
            "user + system, rendering and fusion (2 threads can exceed wall time)",
        ),
        ("  fuse stage peak", _gib(fuse["peak"]), "VmHWM of the fusion process (incl. rendering)"),
        (
            "  fused vs truth",
            f"{fuse['truth']['mean']:.3f} mm",
            f"p95 {fuse['truth']['p95']:.3f} mm",
        ),
        (
            "simplify",
            f"{simp['simplify_s']:.1f} s",
            f"{simp['faces_in'] / 1e6:.1f}M -> {simp['faces'] / 1e6:.2f}M faces ({args.method})",
        ),
        ("  CPU time", f"{simp.get('cpu_s', float('nan')):.1f} s", "user + system"),
        (
            "  simplify peak",
            _gib(simp["peak"]),
            "VmHWM of the simplification process (incl. reading the mesh)",
        ),
        (
            "  simplified vs truth",
            f"{simp['truth']['mean']:.3f} mm",
            f"p95 {simp['truth']['p95']:.3f} mm",
        ),
    ]
    print(
        f"scale benchmark: {args.maps} maps, {args.voxel:g} mm voxels, {os.cpu_count()} CPUs, "
        f"load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after"
    )
    width = max(len(r[0]) for r in rows)
    print(f"{'stage':<{width}}  {'value':>12}  notes")
    for name, value, note in rows:
        print(f"{name:<{width}}  {value:>12}  {note}")


if __name__ == "__main__":
    main()
