"""The virtual rig's placement of a user mesh: what each view records as ``rig_from_object``,
and that the images, the truth and the time stay as they were.

    .venv/bin/python benchmarks/placement.py --against REV [--scale 0.3] [--views 4]

A mesh file is written the way user meshes come: the built-in figurine in metres, y up,
front +z, off-centre (its bounding box centred at (0.4, 0.9, -0.2) m). Then, side by
side in the same run, each in its own subprocess, ``slscan capture --scene FILE --views N``
with the default placement on the toolbox of git revision REV (exported with ``git
archive``) and on this working tree, and the same for the built-in figurine
(``--scene object``).

Columns: CPU seconds (process time of the capture child, incl. its children) and wall
seconds; "pose error": the largest distance (mm) from a view's ground-truth points to the
mesh file's vertices mapped by the view's recorded ``rig_from_object`` (after the file's
units) — 0 when the recorded pose is the mesh-to-rig transform; and, against REV's
session, the largest difference of the captured images (DN) and of the ground-truth
points (mm).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from measure import distances_to_mesh, export_toolbox, run_json

FILE_CENTRE_M = np.array([0.4, 0.9, -0.2])

CHILD = """
import json, resource, subprocess, sys, time
argv = json.loads(sys.argv[1])
t0, r0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
from slscan.cli import main
code = main(argv)
r1 = resource.getrusage(resource.RUSAGE_SELF)
rc = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"code": code, "wall": time.perf_counter() - t0,
                  "cpu": r1.ru_utime + r1.ru_stime - r0.ru_utime - r0.ru_stime + rc.ru_utime + rc.ru_stime}))
"""


def write_user_mesh(path: Path) -> None:
    """The figurine as a user's mesh file: metres, y up, front +z, off-centre (PLY)."""
    import open3d as o3d

    from slscan.virtual.scenes import builtin_object

    scene = builtin_object(detail=0.5)
    vertices = scene.vertices * [1, -1, -1] / 1000.0  # y down, front -z -> y up, front +z; mm -> m
    vertices += FILE_CENTRE_M - (vertices.max(0) + vertices.min(0)) / 2
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices),
                                     o3d.utility.Vector3iVector(scene.triangles))
    o3d.io.write_triangle_mesh(str(path), mesh)


def capture(scene: str, out: Path, args, toolbox: Path | None) -> dict:
    argv = ["capture", "--scene", scene, "--views", str(args.views), "--scale", str(args.scale),
            "--out", str(out), "--quiet"]
    return run_json([sys.executable, "-c", CHILD, json.dumps(argv)], f"capture {scene}", toolbox)


def pose_error(session_dir: Path, mesh_file: Path | None) -> float:
    """Largest distance (mm) of any view's ground-truth points to the scene mapped by its pose."""
    import open3d as o3d

    from slscan.capture.session import load_session
    from slscan.rig import transform_points
    from slscan.virtual.scenes import builtin_object

    session = load_session(session_dir)
    if mesh_file is None:
        scene = builtin_object()
        vertices, faces = scene.vertices, scene.triangles
    else:
        mesh = o3d.io.read_triangle_mesh(str(mesh_file))
        vertices, faces = np.asarray(mesh.vertices) * 1000.0, np.asarray(mesh.triangles)
    worst = 0.0
    for view in session.views:
        point = session.load_ground_truth(view).point.reshape(-1, 3)
        point = point[np.isfinite(point).all(axis=1)]
        d = distances_to_mesh(point, transform_points(view.rig_from_object, vertices), faces)
        worst = max(worst, float(d.max()))
    return worst


def differences(a: Path, b: Path) -> tuple[int, float]:
    """Largest image difference (DN) and ground-truth point difference (mm) of two sessions."""
    import cv2

    from slscan.capture.session import load_session

    sa, sb = load_session(a), load_session(b)
    image, point = 0, 0.0
    for va, vb in zip(sa.views, sb.views, strict=True):
        for ia, ib in zip(va.images, vb.images, strict=True):
            x = cv2.imread(str(a / va.name / ia.file), cv2.IMREAD_UNCHANGED).astype(np.int64)
            y = cv2.imread(str(b / vb.name / ib.file), cv2.IMREAD_UNCHANGED).astype(np.int64)
            image = max(image, int(np.abs(x - y).max()))
        pa, pb = sa.load_ground_truth(va).point, sb.load_ground_truth(vb).point
        if not np.array_equal(np.isfinite(pa), np.isfinite(pb)):
            return image, float("inf")
        both = np.isfinite(pa)
        point = max(point, float(np.abs(pa[both] - pb[both]).max()) if both.any() else 0.0)
    return image, point


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", default="main", help="git revision to compare with (default main)")
    parser.add_argument("--scale", type=float, default=0.3)
    parser.add_argument("--views", type=int, default=4)
    args = parser.parse_args()
    rev = subprocess.run(["git", "rev-parse", "--short", args.against], capture_output=True, text=True,
                         check=False).stdout.strip() or args.against
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        old_toolbox = export_toolbox(args.against, tmp / "old")
        mesh = tmp / "figurine_m_yup.ply"
        write_user_mesh(mesh)
        print(f"virtual rig, --scale {args.scale}, {args.views} views; mesh file: the figurine in metres, y up, "
              f"bounding box centred at {FILE_CENTRE_M.tolist()} m; against {rev}")
        print(f"{'scene':<10} {'code':<12} {'cpu s':>7} {'wall s':>7} {'pose error mm':>14} "
              f"{'image diff DN':>14} {'truth diff mm':>14}")
        for name, scene, file in (("mesh file", str(mesh), mesh), ("object", "object", None)):
            sessions = {}
            for label, toolbox in ((f"old ({rev})", old_toolbox), ("new", None)):
                out = tmp / f"{name.replace(' ', '_')}_{label.split()[0]}"
                result = capture(scene, out, args, toolbox)
                sessions[label] = out
                err = pose_error(out, file)
                if label == "new":
                    image, point = differences(sessions[f"old ({rev})"], out)
                    diff = f"{image:>14d} {point:>14.2e}"
                else:
                    diff = f"{'-':>14} {'-':>14}"
                print(f"{name:<10} {label:<12} {result['cpu']:>7.2f} {result['wall']:>7.2f} {err:>14.4g} {diff}")


if __name__ == "__main__":
    main()
