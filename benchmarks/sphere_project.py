"""An aligned set whose range maps weigh more than their fusion: views of a 100 mm sphere.

    .venv/bin/python benchmarks/sphere_project.py OUT [--views 24] [--size 600] [--pixel 0.35]

Writes ``OUT/aligned.mlp`` and one PLY per view (orthographic range grids of SIZE x SIZE
pixels of PIXEL mm, from random directions, seed 0: 24 views of 250,000 vertices, 365 MiB
in memory, by default) and prints a line saying so. Used to measure what the caller of
``slscan fuse --brick`` holds (docs/paper-scale.md, "Fusion in bricks"), e.g.::

    /usr/bin/time -f "%M KiB" slscan fuse OUT/aligned.mlp --voxel 1 --brick 80 --workers 1 --out f.ply
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--views", type=int, default=24)
    parser.add_argument("--size", type=int, default=600)
    parser.add_argument("--pixel", type=float, default=0.35)
    args = parser.parse_args()
    import open3d as o3d

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from synthetic_poses import looking_from

    from slscan.register.meshlab import write_scan_project
    from slscan.register.rangescan import render_range_scan

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=100.0, resolution=200)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    rng = np.random.default_rng(0)
    scans, poses = [], {}
    for k in range(args.views):
        d = rng.normal(size=3)
        pose = looking_from(d / np.linalg.norm(d))
        scan = render_range_scan(v, f, pose, shape=(args.size, args.size), pixel=args.pixel, name=f"v{k:02d}")
        scans.append(scan)
        poses[scan.name] = pose
    project = write_scan_project(args.out, scans, poses)
    size = sum(s.vertices.nbytes + s.faces.nbytes + s.normals.nbytes + s.quality.nbytes for s in scans)
    print(f"{project}: {len(scans)} views, {len(scans[0].vertices):,} vertices each, {size / 2**20:.0f} MiB in memory")


if __name__ == "__main__":
    main()
