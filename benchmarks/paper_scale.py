"""The paper's statue end to end: a real N-view run (146 by default) of the paper recipe,
one stage per process, on the local executor and on a local Dask cluster.

    .venv/bin/python benchmarks/paper_scale.py --work /tmp/paper146           # 146 views
    .venv/bin/python benchmarks/paper_scale.py --views 12 --scale 0.5 --work /tmp/ps12
    .venv/bin/python benchmarks/paper_scale.py --work /tmp/paper146 --scheduler local --dask-only
    .venv/bin/python benchmarks/paper_scale.py --views 26 --scale 0.25 --quick   # a smoke run (fewer views do not overlap: registration refuses them)

**The object** is the 1.7 m statue of ``benchmarks/scale.py`` (body, head, arms, legs,
displaced by 1-8 mm bumps), painted with smooth colour variations (vertex colours, matte),
written as a PLY and loaded by the virtual rig as a mesh scene. **The campaign**: views
on six rings around it (feet to head, the rig's camera at about 1.3 m from the surface
along its axis) and a ring above it looking down on the shoulders and head, as the
paper's 146 range maps of the Minerva were taken; each view's image is mostly statue
(the camera sees about 1.0 x 0.67 m at 1.3 m). Every view records its exact pose.

**Capture** (the paper recipe's rig and patterns: 1440x960 camera, 1024x768 projector,
9 hybrid levels, 6 ring-light images per view) is prepared once into ``WORK/capture``,
rendered over views in the worker pool (``capture_session(executor=...)``), timed, and
reused by later runs (delete the folder to capture again).

**The stages**, each as its own ``slscan`` command in its own process, in order: decode,
lights (capture-lights + calibrate-lights on the matte panel), albedo, register, fuse
(0.57 mm), simplify (1M faces), texture (4096 atlas). Per stage the table gives wall
seconds, CPU seconds (the stage's process and every process it started; with Dask, plus
the Dask workers' CPU over the stage) and peak resident memory (sampled sum over the
process tree, Dask workers included). The model is compared with the statue: mean and
95th-percentile distance (mm) from 300,000 points on the simplified model to the true
surface, in the object frame the registration reports (``object_from_reference``).

``--scheduler local`` also runs the per-view stages (decode and albedo: the only stages
that hand work to the executor) on a ``distributed.LocalCluster`` with as many
single-threaded worker processes as ``--workers``, side by side with the local
executor in the same run; the other stages do not use the executor and are not repeated.
``--dask-only`` skips the local stages (a second run on the same WORK, e.g. after a long
local run). Results go to ``WORK/runs/<mode>/`` and the table to ``WORK/table.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from measure import distances_to_mesh, run_measured, surface_samples

HERE = Path(__file__).resolve().parent
TOOLBOX = HERE.parent / "toolbox"
RINGS = (150.0, 450.0, 750.0, 1050.0, 1350.0, 1600.0)
"""Heights (mm above the statue's feet) of the rings of views around it."""
ABOVE = (1450.0, 50.0)
"""The ring above: the height looked at and the elevation (degrees, looking down)."""


# --- the object and the campaign ------------------------------------------------------------------


def write_statue(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Write the 1.7 m statue (mm, z up, feet at z = 0) with smooth vertex colours as PLY."""
    import open3d as o3d
    from scale import statue

    vertices, faces = statue()
    # smooth paint: three colour waves at 150-600 mm, albedo 0.35-0.85, no colour saturated
    rng = np.random.default_rng(146)
    colour = np.full((len(vertices), 3), 0.6)
    for wavelength in (600.0, 300.0, 150.0):
        d = rng.normal(size=3)
        k = 2 * math.pi / wavelength * d / np.linalg.norm(d)
        colour += 0.08 * np.sin(vertices @ k + rng.uniform(0, 2 * math.pi))[:, None] * rng.uniform(0.5, 1.0, 3)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces))
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(colour, 0.05, 0.95))
    tmp = path.with_suffix(".partial.ply")
    o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False)
    os.replace(tmp, path)
    return vertices, faces


def _rotation(axis: int, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    r = np.eye(3)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def campaign(n_views: int, vertices: np.ndarray, faces: np.ndarray, working_distance: float) -> list[np.ndarray]:
    """``rig_from_object`` (4, 4) of ``n_views`` views: a tenth of them on the ring above
    (:data:`ABOVE`), the rest split evenly over the rings around (:data:`RINGS`), each moved along the camera axis so that the surface
    the axis meets is at ``working_distance``."""
    import open3d as o3d
    import open3d.core as o3c

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3c.Tensor(vertices.astype(np.float32)), o3c.Tensor(faces.astype(np.uint32)))
    rings = [(h, 0.0) for h in RINGS] + [ABOVE]
    above = max(1, round(0.1 * n_views)) if n_views > len(RINGS) else 0
    around = n_views - above  # split evenly over the rings, the lower rings taking what is left over
    counts = [around // len(RINGS) + (1 if k < around % len(RINGS) else 0) for k in range(len(RINGS))] + [above]
    # the statue's z up to the rig's y down, its -y (front) towards the camera
    upright = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    poses = []
    for r, ((height, elevation), count) in enumerate(zip(rings, counts)):
        for i in range(count):
            turn = 360.0 * (i + 0.5 * (r % 2)) / max(count, 1)
            rot = _rotation(0, elevation) @ _rotation(1, turn) @ upright
            pose = np.eye(4)
            pose[:3, :3] = rot
            pose[:3, 3] = -rot @ np.array([0.0, 0.0, height]) + [0.0, 0.0, working_distance]
            # move along the axis so that the surface the camera's central rays meet is at the
            # working distance (the median of a 5x5 bundle; between the legs, the far leg)
            obj_from_rig = np.linalg.inv(pose)
            dirs = np.array([[x, y, 1.0] for x in np.linspace(-0.05, 0.05, 5) for y in np.linspace(-0.05, 0.05, 5)])
            dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
            origin = np.broadcast_to(obj_from_rig[:3, 3], dirs.shape)
            rays = np.hstack([origin, dirs @ obj_from_rig[:3, :3].T]).astype(np.float32)
            t = scene.cast_rays(o3c.Tensor(rays))["t_hit"].numpy()
            t = t[np.isfinite(t)]
            if len(t):
                pose[2, 3] += working_distance - float(np.median(t) * dirs[:, 2].mean())
            poses.append(pose)
    return poses


def prepare_capture(work: Path, views: int, scale: float, workers: int) -> dict:
    """Write the statue, the campaign's poses and the capture session (in this process)."""
    sys.path.insert(0, str(TOOLBOX))
    from slscan.executor import Executor
    from slscan.virtual.device import VirtualCaptureConfig, capture_session, images_per_view

    t0 = time.perf_counter()
    vertices, faces = write_statue(work / "statue.ply")
    config = VirtualCaptureConfig(scene=str(work / "statue.ply"), scene_units="mm", views=views, patterns="hybrid",
                                  levels=9 if scale >= 0.99 else max(5, round(9 + math.log2(scale))),
                                  camera_scale=scale, projector_scale=scale, lit_images=True)
    poses = campaign(views, vertices, faces, config.rig().working_distance)
    (work / "poses.json").write_text(json.dumps([p.tolist() for p in poses]))
    t_prep = time.perf_counter() - t0
    done = [0]
    per_view = images_per_view(config)

    def progress(label: str) -> None:
        done[0] += 1
        if done[0] % per_view == 0:
            print(f"  captured {done[0] // per_view}/{views} views at {time.perf_counter() - t0:.0f} s",
                  file=sys.stderr, flush=True)

    session = capture_session(config, work / "capture", poses=poses, overwrite=True, progress=progress,
                              executor=Executor(workers=workers))
    return {"views": len(session.views), "images": sum(len(v.images) for v in session.views),
            "statue_faces": len(faces), "prepare_s": t_prep}


# --- the stages ---------------------------------------------------------------------------------


def stage_commands(work: Path, out: Path, args: argparse.Namespace, scheduler: str | None) -> list[tuple[str, list]]:
    """(stage, [command, ...]) in pipeline order; ``scheduler``: a Dask address for the
    per-view stages, or None for the local executor."""
    slscan = [sys.executable, "-m", "slscan.cli"]
    cap = work / "capture"
    ex = ["--scheduler", scheduler] if scheduler else ["--workers", str(args.workers)]
    q = ["--quiet", "--overwrite"]
    voxel = args.voxel if args.voxel else (0.57 if args.scale >= 0.99 else 0.57 / args.scale)
    return [
        ("decode", [[*slscan, "decode", str(cap), "--out", str(out / "maps"), *ex, *q]]),
        ("lights", [[*slscan, "capture-lights", "--out", str(out / "panel"), "--scale", str(0.5 * args.scale), *q],
                    [*slscan, "calibrate-lights", str(out / "panel"), "--out", str(out / "lights.json"), *q]]),
        ("albedo", [[*slscan, "albedo", str(cap), "--range-maps", str(out / "maps"), "--lights",
                     str(out / "lights.json"), "--out", str(out / "albedo"), *ex, *q]]),
        ("register", [[*slscan, "register", str(out / "maps"), "--out", str(out / "aligned"), *q]]),
        ("fuse", [[*slscan, "fuse", str(out / "aligned" / "aligned.mlp"), "--voxel", f"{voxel:g}",
                   "--out", str(out / "fused.ply"), *q]]),
        ("simplify", [[*slscan, "simplify", str(out / "fused.ply"), "--faces", str(args.faces),
                       "--out", str(out / "simplified.ply"), *q]]),
        ("texture", [[*slscan, "texture", str(out / "simplified.ply"), "--views", str(out / "albedo"),
                      "--poses", str(out / "aligned" / "registration.json"), "--session", str(cap),
                      "--size", str(args.texture_size), "--no-preview", "--out", str(out / "textured"), *q]]),
    ]


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


class DaskCluster:
    """A local Dask cluster: single-threaded worker processes, their CPU and memory
    measured from outside (they are not children of the stage's process)."""

    def __init__(self, workers: int, threads: int = 1, memory_limit: str | None = None) -> None:
        import dask
        from distributed import LocalCluster

        # Dask starts its workers with OMP_NUM_THREADS=1 (and MKL's, OpenBLAS's); ``threads``
        # other than 1 lets Open3D and NumPy in each worker use that many, as the local
        # executor's processes do (they are left at the machine's cores)
        env = {f"distributed.nanny.pre-spawn-environ.{k}": threads
               for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
        with dask.config.set(env if threads != 1 else {}):
            # memory_limit: Dask's nanny restarts a worker past 95 % of it (the task is retried)
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None, **({"memory_limit": memory_limit} if memory_limit else {}))
        self.address = self.cluster.scheduler_address

    def pids(self) -> list[int]:
        from distributed import Client

        with Client(self.address) as client:
            return list(client.run(os.getpid).values())

    def cpu(self) -> float:
        import psutil

        total = 0.0
        for pid in self.pids():
            t = psutil.Process(pid).cpu_times()
            total += t.user + t.system
        return total

    def close(self) -> None:
        self.cluster.close()


def run_stages(work: Path, out: Path, args: argparse.Namespace, mode: str, only: tuple[str, ...] = (),
               dask: DaskCluster | None = None) -> list[dict]:
    """Run the stages one process each; a row per stage."""
    env = dict(os.environ)
    rows = []
    for stage, commands in stage_commands(work, out, args, dask.address if dask else None):
        if only and stage not in only:
            continue
        wall = cpu = 0.0
        peak = 0
        for command in commands:
            cpu0 = _children_cpu()
            dask_cpu0 = dask.cpu() if dask else 0.0
            extra = dask.pids() if dask else []
            measured = run_measured(command, env=env, extra_pids=extra)
            if measured.returncode != 0:
                raise SystemExit(f"{mode} {stage} failed (exit {measured.returncode}):\n"
                                 f"{' '.join(command)}\n{measured.stderr[-4000:]}")
            wall += measured.seconds
            cpu += _children_cpu() - cpu0 + ((dask.cpu() - dask_cpu0) if dask else 0.0)
            peak = max(peak, measured.peak_bytes)
        rows.append({"mode": mode, "stage": stage, "wall_s": wall, "cpu_s": cpu, "peak_gib": peak / 2**30})
        print(f"  {mode:6s} {stage:9s} {wall:8.1f} s wall {cpu:8.1f} s CPU {peak / 2**30:6.2f} GiB",
              file=sys.stderr, flush=True)
    return rows


def model_accuracy(out: Path, work: Path) -> dict:
    """The simplified model against the statue, in the registration's object frame."""
    import open3d as o3d

    reg = json.loads((out / "aligned" / "registration.json").read_text())
    frame = np.asarray(reg["frame"]["object_from_reference"], float)
    truth = o3d.io.read_triangle_mesh(str(work / "statue.ply"))
    tv = np.asarray(truth.vertices) @ frame[:3, :3].T + frame[:3, 3]
    model = o3d.io.read_triangle_mesh(str(out / "simplified.ply"))
    d = distances_to_mesh(surface_samples(np.asarray(model.vertices), np.asarray(model.triangles), 300_000),
                          tv, np.asarray(truth.triangles))
    return {"faces": len(model.triangles), "mean_mm": float(d.mean()), "p95_mm": float(np.percentile(d, 95))}


def pipeline_accuracy(out: Path, work: Path, every: int = 10) -> dict:
    """Registration against the true poses (every view), and albedo against the true
    albedo (every ``every``-th view): relative error on valid pixels."""
    sys.path.insert(0, str(TOOLBOX))
    from slscan.capture.session import load_session
    from slscan.colour import read_albedo_png

    session = load_session(work / "capture", validate=False)
    reg = json.loads((out / "aligned" / "registration.json").read_text())
    frame = np.asarray(reg["frame"]["object_from_reference"], float)
    rot, shift = [], []
    for view in session.views:
        if view.name not in reg["poses"]:
            continue
        d = np.linalg.inv(frame @ np.linalg.inv(view.rig_from_object)) @ np.asarray(reg["poses"][view.name], float)
        rot.append(math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(d[:3, :3]) - 1) / 2)))))
        shift.append(float(np.linalg.norm(d[:3, 3])))
    errors = []
    for view in session.views[::every]:
        image = out / "albedo" / f"{view.name}_albedo.png"
        if not image.is_file():
            continue
        albedo = read_albedo_png(image, out / "albedo" / f"{view.name}_valid.png")
        truth = session.load_ground_truth(view).albedo
        good = np.isfinite(albedo[..., 0]) & np.isfinite(truth[..., 0]) & (truth[..., 0] > 0.05)
        errors.append(np.abs(albedo[good] / truth[good] - 1).ravel())
    rel = np.concatenate(errors) if errors else np.array([np.nan])
    return {"registered": len(rot), "views": len(session.views), "max_rot_deg": max(rot), "max_shift_mm": max(shift),
            "albedo_median_rel": float(np.median(rel)), "albedo_within_5pc": float(np.mean(rel < 0.05)),
            "albedo_views": len(errors)}


def print_table(capture: dict | None, rows: list[dict], accuracy: dict | None, views: int) -> None:
    print(f"\npaper recipe, {views} views of the 1.7 m statue" + (f" (scale {ARGS.scale:g})" if ARGS.scale != 1 else ""))
    if capture:
        print(f"capture (prepared once, {capture['workers']} workers): {capture['wall_s']:.1f} s wall, "
              f"{capture['cpu_s']:.1f} s CPU, peak {capture['peak_gib']:.2f} GiB, {capture['images']} images")
    modes = list(dict.fromkeys(r["mode"] for r in rows))
    stages = list(dict.fromkeys(r["stage"] for r in rows))
    head = f"{'stage':10s}" + "".join(f" | {m + ' wall s':>12s} {'CPU s':>9s} {'peak GiB':>9s}" for m in modes)
    print(head)
    print("-" * len(head))
    for stage in stages:
        line = f"{stage:10s}"
        for m in modes:
            r = next((r for r in rows if r["mode"] == m and r["stage"] == stage), None)
            line += (f" | {r['wall_s']:12.1f} {r['cpu_s']:9.1f} {r['peak_gib']:9.2f}" if r
                     else f" | {'(not run)':>12s} {'':9s} {'':9s}")
        print(line)
    for m in modes:
        mine = [r for r in rows if r["mode"] == m]
        print(f"{'total ' + m:10s}: {sum(r['wall_s'] for r in mine):.1f} s wall "
              f"({sum(r['wall_s'] for r in mine) / 60:.1f} min), {sum(r['cpu_s'] for r in mine):.1f} s CPU, "
              f"peak {max(r['peak_gib'] for r in mine):.2f} GiB ({len(mine)} stages)")
    if accuracy:
        print(f"model vs statue: {accuracy['faces']:,} faces, mean {accuracy['mean_mm']:.3f} mm, "
              f"p95 {accuracy['p95_mm']:.3f} mm")
        if "registered" in accuracy:
            print(f"registration: {accuracy['registered']}/{accuracy['views']} views, worst pose error "
                  f"{accuracy['max_rot_deg']:.3f} deg / {accuracy['max_shift_mm']:.3f} mm; albedo "
                  f"({accuracy['albedo_views']} views): median relative error "
                  f"{100 * accuracy['albedo_median_rel']:.1f} %, {100 * accuracy['albedo_within_5pc']:.1f} % "
                  f"of pixels within 5 %")


ARGS: argparse.Namespace


def main() -> None:
    global ARGS
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--views", type=int, default=146)
    p.add_argument("--scale", type=float, default=1.0, help="camera and projector size (1: the paper's)")
    p.add_argument("--work", type=Path, default=Path("/tmp/slscan_paper_scale"))
    p.add_argument("--workers", type=int, default=2, help="local processes (and Dask workers)")
    p.add_argument("--scheduler", choices=("none", "local"), default="none",
                   help="local: also run decode and albedo on a local Dask cluster")
    p.add_argument("--dask-only", action="store_true", help="run only the Dask rows (needs a local run's WORK)")
    p.add_argument("--dask-stages", default="decode,albedo", help="the per-view stages to run on Dask")
    p.add_argument("--dask-threads", type=int, default=1, help="OpenMP/BLAS threads per Dask worker "
                   "(Dask's default 1; the local executor's processes use the machine's cores); its rows "
                   "are labelled 'dask Nt' when not 1")
    p.add_argument("--voxel", type=float, default=0.0, help="fusion voxel, mm (default 0.57 / scale)")
    p.add_argument("--faces", type=int, default=1_000_000)
    p.add_argument("--texture-size", type=int, default=4096)
    p.add_argument("--quick", action="store_true", help="a smoke run: 20k faces, 512 atlas")
    p.add_argument("--only", default="", help="re-run only these stages (comma-separated) as column --label, "
                   "from the local run's results (e.g. --only decode,fuse --label new after a change)")
    p.add_argument("--label", default="rerun", help="the column of an --only run")
    p.add_argument("--table", action="store_true", help="print WORK's stored table and stop")
    p.add_argument("--child-capture", action="store_true", help=argparse.SUPPRESS)
    args = ARGS = p.parse_args()
    # this tree's slscan for every process started from here: the stages, and the Dask
    # workers (started by this process, they inherit its environment)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(TOOLBOX), *filter(None, [os.environ.get("PYTHONPATH")])])
    if args.quick:
        args.faces, args.texture_size = 20_000, 512
    args.work.mkdir(parents=True, exist_ok=True)
    if args.child_capture:
        print(json.dumps(prepare_capture(args.work, args.views, args.scale, args.workers)))
        return
    table_path = args.work / "table.json"
    table = json.loads(table_path.read_text()) if table_path.is_file() else {}
    if args.table:
        if not table:
            raise SystemExit(f"{table_path}: no table yet (run the benchmark with --work {args.work})")
        print_table(table.get("capture"), table.get("rows", []), table.get("accuracy"), table["capture"]["views"])
        return
    session = args.work / "capture" / "session.json"
    key = {"views": args.views, "scale": args.scale}
    if not session.is_file() or table.get("capture_key") != key:
        print(f"capturing {args.views} views into {args.work / 'capture'} ...", file=sys.stderr, flush=True)
        cpu0 = _children_cpu()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([os.environ["PYTHONPATH"], str(HERE)]))
        measured = run_measured([sys.executable, str(Path(__file__).resolve()), "--child-capture", "--views",
                                 str(args.views), "--scale", str(args.scale), "--work", str(args.work),
                                 "--workers", str(args.workers)], env=env)
        if measured.returncode != 0:
            raise SystemExit(f"capture failed:\n{measured.stderr[-4000:] if measured.stderr else ''}")
        info = json.loads(measured.stdout.strip().splitlines()[-1])
        table = {"capture_key": key, "capture": {**info, "wall_s": measured.seconds, "workers": args.workers,
                                                 "cpu_s": _children_cpu() - cpu0,
                                                 "peak_gib": measured.peak_bytes / 2**30}}
        table_path.write_text(json.dumps(table, indent=1))
    rows = [r for r in table.get("rows", []) if not (r["mode"] == "local" and not (args.dask_only or args.only))
            and not (args.only and r["mode"] == args.label)]
    if args.only:
        only = tuple(x.strip() for x in args.only.split(",") if x.strip())
        known = [stage for stage, _ in stage_commands(args.work, args.work, args, None)]
        if not set(only) <= set(known):
            raise SystemExit(f"--only: unknown stage(s) {sorted(set(only) - set(known))}; known: {', '.join(known)}")
        local, out = args.work / "runs" / "local", args.work / "runs" / args.label
        out.mkdir(parents=True, exist_ok=True)
        made = {"decode": ["maps"], "lights": ["panel", "lights.json"], "albedo": ["albedo"], "register": ["aligned"],
                "fuse": ["fused.ply"], "simplify": ["simplified.ply"], "texture": ["textured"]}
        for stage, names in made.items():  # what the stages left out would have made: the local run's
            for name in names:
                link = out / name
                if stage not in only and not link.exists() and (local / name).exists():
                    link.symlink_to(local / name)
        rows += run_stages(args.work, out, args, args.label, only=only)
        table["rows"] = rows
        table_path.write_text(json.dumps(table, indent=1))
    elif not args.dask_only:
        out = args.work / "runs" / "local"
        rows += run_stages(args.work, out, args, "local")
        table["accuracy"] = {**model_accuracy(out, args.work), **pipeline_accuracy(out, args.work)}
        table["rows"] = rows
        table_path.write_text(json.dumps(table, indent=1))
    if args.scheduler == "local":
        local = args.work / "runs" / "local"
        if not (local / "maps").is_dir():
            raise SystemExit(f"--scheduler local needs the local run's range maps in {local} (run without --dask-only)")
        dask = DaskCluster(args.workers, args.dask_threads)
        mode = "dask" if args.dask_threads == 1 else f"dask {args.dask_threads}t"
        try:
            out = args.work / "runs" / "dask"
            out.mkdir(parents=True, exist_ok=True)
            if not (out / "lights.json").exists():
                shutil.copy(local / "lights.json", out / "lights.json")
            stages = tuple(x.strip() for x in args.dask_stages.split(",") if x.strip())
            if not set(stages) <= {"decode", "albedo"}:
                raise SystemExit(f"--dask-stages: only decode and albedo hand work to the executor, got {stages}")
            rows = [r for r in rows if not (r["mode"] == mode and r["stage"] in stages)] + \
                run_stages(args.work, out, args, mode, only=stages, dask=dask)
        finally:
            dask.close()
        table["rows"] = rows
        table_path.write_text(json.dumps(table, indent=1))
    print_table(table.get("capture"), rows, table.get("accuracy"), args.views)


if __name__ == "__main__":
    main()
