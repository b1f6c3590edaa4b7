"""The paper's statue beyond one process: fusion in bricks at 0.57 mm against one volume,
the statue at 0.25 mm on a Dask cluster whose workers are capped, and an extrapolation
to campaigns larger than this machine.

    python benchmarks/paper_scale.py --work /work/ps146              # the 146 views, once (decode, register, ...)
    python benchmarks/statue_bricks.py compare --work /work/ps146    # 0.57 mm: one volume, bricks, bricks on Dask
    python benchmarks/statue_bricks.py capped --work /work/ps146 --voxel 0.25 --worker-memory 4GiB
    python benchmarks/statue_bricks.py capped --work /work/ps146 --voxel 0.57 --worker-memory 4GiB
    python benchmarks/statue_bricks.py table --work /work/ps146      # every stored table + the extrapolation

Each way runs the real ``slscan`` commands in their own processes on ``paper_scale.py``'s
local run (``WORK/runs/local``: its registration, albedo and capture):

**compare** fuses the aligned range maps at ``--voxel`` (0.57 mm) three ways, side by side
in one run: one volume (``slscan fuse``), bricks on 2 local processes (``--brick --workers
2``) and bricks on a ``distributed.LocalCluster`` of 2 single-threaded workers
(``--scheduler``). Per way: wall, CPU (the command's process tree, plus the Dask workers'
CPU over the run), peak resident memory of the command's own process, of any one other
process (a helper or a Dask worker) and of all of them together (sampled every 0.1 s), the
faces, and the distance of each bricked mesh to the single volume's (vertex for vertex
when the meshes have the same size, and surface to surface from 300,000 points each way).

**capped** runs fusion in bricks, out-of-core simplification (to ``--faces``) and texture
on a LocalCluster whose 2 workers are capped at ``--worker-memory`` (Dask's nanny kills a
worker that passes 95 % of it; the task is then retried elsewhere and, if it dies again,
the run fails), and compares the simplified model with the statue as ``paper_scale.py``
does. Stages that do not depend on the voxel (decode, albedo, register) are those of the
local run; their memory on Dask is in ``docs/paper-scale.md``.

Tables are stored in ``WORK/bricks.json``; ``table`` prints them with an extrapolation
from the measured per-view and per-surface costs (labelled as such).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from measure import distances_to_mesh, run_measured, surface_samples
from paper_scale import TOOLBOX, DaskCluster, _children_cpu

SLSCAN = [sys.executable, "-m", "slscan.cli"]
GIB = 2**30


def ply_counts(path: Path) -> tuple[int, int]:
    """(vertices, faces) from a PLY header, without reading the body."""
    vertices = faces = 0
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").split()
            if line[:2] == ["element", "vertex"]:
                vertices = int(line[2])
            elif line[:2] == ["element", "face"]:
                faces = int(line[2])
            elif line[:1] == ["end_header"]:
                break
    return vertices, faces


def run(command: list[str], dask: DaskCluster | None = None) -> dict:
    """Run ``command`` measured; raise SystemExit with its stderr when it fails."""
    cpu0 = _children_cpu()
    dask_cpu0 = dask.cpu() if dask else 0.0
    measured = run_measured(command, extra_pids=dask.pids() if dask else ())
    if measured.returncode != 0:
        raise SystemExit(f"failed (exit {measured.returncode}): {' '.join(command)}\n{measured.stderr[-4000:]}")
    return {"wall_s": measured.seconds, "cpu_s": _children_cpu() - cpu0 + ((dask.cpu() - dask_cpu0) if dask else 0),
            "peak_main_gib": measured.peak_main_bytes / GIB, "peak_other_gib": measured.peak_other_bytes / GIB,
            "peak_main_anon_gib": measured.peak_main_anon_bytes / GIB,
            "peak_all_gib": measured.peak_bytes / GIB,
            "stdout": (measured.stdout or "")[-2000:] + (measured.stderr or "")[-2000:]}  # slscan prints on stderr


def _position_faces(mesh) -> tuple[np.ndarray, int]:
    """The mesh's triangles as sorted rows of position ids (vertices equal as float32 share
    an id), the rows sorted; and how many vertices share a position with another."""
    keys = np.ascontiguousarray(mesh.vertices.astype(np.float32)).view(np.dtype((np.void, 12))).ravel()
    _, ids = np.unique(keys, return_inverse=True)
    ids = ids.ravel()
    f = np.sort(ids[mesh.faces], axis=1)
    return f[np.lexsort(f.T[::-1])], int(mesh.n_vertices - (ids.max() + 1))


def mesh_distance(a_path: Path, b_path: Path, samples: int = 300_000) -> dict:
    """How far mesh ``b`` is from mesh ``a``: the same triangles (by their vertices'
    float32 positions: marching cubes leaves a few vertices at one position, numbered in
    either order), the largest vertex difference after slscan's canonical order when they
    have the same size, and surface to surface both ways (sampled; float32 ray casting)."""
    sys.path.insert(0, str(TOOLBOX))
    from slscan.fuse import canonical_order, read_mesh

    a, b = read_mesh(a_path), read_mesh(b_path)
    out: dict = {"same_size": a.n_vertices == b.n_vertices and a.n_faces == b.n_faces}
    if out["same_size"]:
        ca, cb = canonical_order(a), canonical_order(b)
        out["max_dv_mm"] = float(np.abs(ca.vertices.astype(np.float64) - cb.vertices).max())
        del ca, cb
        fa, out["shared_positions"] = _position_faces(a)
        fb, _ = _position_faces(b)
        out["same_faces"] = bool(np.array_equal(fa, fb))
        del fa, fb
    d_ab = distances_to_mesh(surface_samples(b.vertices, b.faces, samples), a.vertices, a.faces)
    d_ba = distances_to_mesh(surface_samples(a.vertices, a.faces, samples), b.vertices, b.faces)
    out["hausdorff_mm"] = float(max(d_ab.max(), d_ba.max()))
    out["mean_mm"] = float(0.5 * (d_ab.mean() + d_ba.mean()))
    return out


def compare(args: argparse.Namespace, store: dict) -> None:
    local = args.work / "runs" / "local"
    aligned = local / "aligned" / "aligned.mlp"
    if not aligned.is_file():
        raise SystemExit(f"{aligned}: not found; run benchmarks/paper_scale.py --work {args.work} first")
    out = args.work / "bricks" / f"compare_{args.voxel:g}"
    out.mkdir(parents=True, exist_ok=True)
    fuse = [*SLSCAN, "fuse", str(aligned), "--voxel", f"{args.voxel:g}", "--quiet", "--overwrite"]
    bricks = ["--brick", f"{args.brick:g}", "--max-memory", args.grid_memory]
    rows = []
    ways = [w.strip() for w in args.ways.split(",") if w.strip()]
    for way in ways:
        print(f"  compare {way} ...", file=sys.stderr, flush=True)
        # dask2t: Dask's workers with 2 OpenMP/BLAS threads each, as the local processes have
        dask = DaskCluster(2, threads=2 if way == "dask2t" else 1) if way.startswith("dask2") else None
        try:
            extra = {"single": [], "local2": [*bricks, "--workers", "2"],
                     "dask2": [*bricks, "--scheduler", dask.address if dask else ""],
                     "dask2t": [*bricks, "--scheduler", dask.address if dask else ""]}[way]
            row = {"way": way, **run([*fuse, *extra, "--out", str(out / f"{way}.ply")], dask)}
        finally:
            if dask:
                dask.close()
        row["faces"] = ply_counts(out / f"{way}.ply")[1]
        rows.append(row)
        print(f"    {row['wall_s']:.1f} s wall, {row['cpu_s']:.1f} s CPU, {row['faces']:,} faces", file=sys.stderr)
    for row in rows:
        if row["way"] != "single" and (out / "single.ply").is_file():
            row.update(mesh_distance(out / "single.ply", out / f"{row['way']}.ply"))
    old = store.get("compare", {})
    if (old.get("voxel"), old.get("brick")) == (args.voxel, args.brick):  # add to the same comparison
        rows = [r for r in old["rows"] if r["way"] not in ways] + rows
        rows.sort(key=lambda r: ["single", "local2", "dask2", "dask2t"].index(r["way"]))
    store["compare"] = {"voxel": args.voxel, "brick": args.brick, "grid_memory": args.grid_memory,
                        "views": views_of(args.work), "rows": rows}


def views_of(work: Path) -> int:
    table = work / "table.json"
    return json.loads(table.read_text())["capture"]["views"] if table.is_file() else 0


def capped(args: argparse.Namespace, store: dict) -> None:
    from paper_scale import model_accuracy

    local = args.work / "runs" / "local"
    out = args.work / "bricks" / f"capped_{args.voxel:g}"
    wanted = args.stages.split(",")
    earlier = store.get("capped", {}).get(f"{args.voxel:g}", {})
    if "fuse" in wanted:  # a fresh run
        if out.exists():
            shutil.rmtree(out)
        out.mkdir(parents=True)
        # model_accuracy reads out/aligned/registration.json and out/simplified.ply
        (out / "aligned").symlink_to(local / "aligned")
        earlier = {}
    elif not (out / "fused.ply").is_file():
        raise SystemExit(f"{out / 'fused.ply'}: not there; run the capped fuse stage first")
    dask = DaskCluster(2, memory_limit=args.worker_memory)
    rows = []
    try:
        stages = [
            ("fuse", [*SLSCAN, "fuse", str(local / "aligned" / "aligned.mlp"), "--voxel", f"{args.voxel:g}",
                      "--brick", f"{args.brick:g}", "--max-memory", args.grid_memory,
                      "--scheduler", dask.address, "--out", str(out / "fused.ply"), "--quiet", "--overwrite"]),
            ("simplify", [*SLSCAN, "simplify", str(out / "fused.ply"), "--faces", str(args.faces),
                          "--max-memory", args.worker_memory, "--scheduler", dask.address,
                          "--out", str(out / "simplified.ply"), "--quiet", "--overwrite"]),
            ("texture", [*SLSCAN, "texture", str(out / "simplified.ply"), "--views", str(local / "albedo"),
                         "--poses", str(local / "aligned" / "registration.json"),
                         "--session", str(args.work / "capture"), "--size", str(args.texture_size),
                         "--no-preview", "--out", str(out / "textured"), "--quiet", "--overwrite",
                         *(["--scheduler", dask.address] if args.texture_on_dask else [])]),
        ]
        for stage, command in stages:
            if stage not in wanted:
                continue
            print(f"  capped {args.voxel:g} mm {stage} ...", file=sys.stderr, flush=True)
            try:
                row = {"stage": stage, **run(command, dask)}
            except SystemExit as exc:  # keep what ran, and say what failed
                rows.append({"stage": stage, "failed": str(exc)[:2000]})
                break
            print(f"    {row['wall_s']:.1f} s wall, {row['cpu_s']:.1f} s CPU, worker peak "
                  f"{row['peak_other_gib']:.2f} GiB, caller {row['peak_main_gib']:.2f} GiB", file=sys.stderr)
            rows.append(row)
    finally:
        dask.close()
    ran = {r["stage"] for r in rows}  # the stages not run again keep their earlier rows
    rows = [r for r in earlier.get("rows", []) if r["stage"] not in ran and "failed" not in r] + rows
    rows.sort(key=lambda r: ["fuse", "simplify", "texture"].index(r["stage"]))
    result = {"voxel": args.voxel, "brick": args.brick, "worker_memory": args.worker_memory,
              "grid_memory": args.grid_memory, "views": views_of(args.work), "rows": rows}
    if (out / "fused.ply").is_file():
        result["fused_faces"] = ply_counts(out / "fused.ply")[1]
        result["fused_bytes"] = (out / "fused.ply").stat().st_size
    if (out / "simplified.ply").is_file():
        result["accuracy"] = model_accuracy(out, args.work)
    store.setdefault("capped", {})[f"{args.voxel:g}"] = result


# --- the tables -------------------------------------------------------------------------------------


def print_compare(c: dict) -> None:
    print(f"\nfusion of the {c['views']}-view statue at {c['voxel']:g} mm: one volume vs bricks of "
          f"{c['brick']:g} mm (grid cap {c['grid_memory']}), 2 local processes vs 2 Dask workers")
    head = (f"{'way':8s} {'wall s':>8s} {'CPU s':>8s} {'peak caller':>12s} {'peak 1 helper':>14s} "
            f"{'peak all':>9s} {'faces':>12s} {'same triangles':>14s} {'max |dv| mm':>11s} {'Hausdorff mm':>12s} "
            f"{'mean mm':>8s}")
    print(head)
    print("-" * len(head))
    for r in c["rows"]:
        same = "-" if r["way"] == "single" else str(r.get("same_faces", False))
        dv = f"{r['max_dv_mm']:.2g}" if "max_dv_mm" in r else "-"
        h = f"{r['hausdorff_mm']:.3g}" if "hausdorff_mm" in r else "-"
        m = f"{r['mean_mm']:.2g}" if "mean_mm" in r else "-"
        print(f"{r['way']:8s} {r['wall_s']:8.1f} {r['cpu_s']:8.1f} {r['peak_main_gib']:8.2f} GiB "
              f"{r['peak_other_gib']:10.2f} GiB {r['peak_all_gib']:5.2f} GiB {r['faces']:12,} {same:>14s} "
              f"{dv:>11s} {h:>12s} {m:>8s}")
    by = {r["way"]: r for r in c["rows"]}
    shared = {r["shared_positions"] for r in c["rows"] if "shared_positions" in r}
    if shared:
        print(f"same triangles: by their vertices' float32 positions ({', '.join(map(str, sorted(shared)))} vertices "
              "share a position with another one, numbered in either order); Hausdorff and mean: 300,000 sampled "
              "points each way")
    for way in ("dask2", "dask2t"):
        if way in by and "local2" in by:
            print(f"{way} vs 2 local processes: {100 * (by[way]['wall_s'] / by['local2']['wall_s'] - 1):+.0f} % wall, "
                  f"{100 * (by[way]['cpu_s'] / by['local2']['cpu_s'] - 1):+.0f} % CPU")


def print_capped(c: dict) -> None:
    print(f"\nthe {c['views']}-view statue at {c['voxel']:g} mm on a LocalCluster of 2 workers capped at "
          f"{c['worker_memory']} (bricks of {c['brick']:g} mm, grid cap {c['grid_memory']})")
    head = (f"{'stage':9s} {'wall s':>8s} {'CPU s':>8s} {'peak/worker':>12s} {'peak caller':>12s} "
            f"{'caller anon':>12s} {'peak all':>9s}")
    print(head)
    print("-" * len(head))
    failed = [r for r in c["rows"] if "failed" in r]
    for r in failed:
        print(f"{r['stage']:9s} FAILED: {r['failed'].splitlines()[-1]}")
    c = {**c, "rows": [r for r in c["rows"] if "failed" not in r]}
    if not c["rows"]:
        return
    for r in c["rows"]:
        anon = f"{r['peak_main_anon_gib']:8.2f} GiB" if "peak_main_anon_gib" in r else f"{'-':>12s}"
        print(f"{r['stage']:9s} {r['wall_s']:8.1f} {r['cpu_s']:8.1f} {r['peak_other_gib']:8.2f} GiB "
              f"{r['peak_main_gib']:8.2f} GiB {anon} {r['peak_all_gib']:5.2f} GiB")
        cut = re.search(r"range maps cut into pieces ([\d.]+) s", r.get("stdout", ""))
        if cut:
            print(f"{'':9s} (of which the caller cut the range maps into pieces, serially: {float(cut.group(1)):.1f} s)")
    rows = c["rows"]
    print(f"total: {sum(r['wall_s'] for r in rows):.1f} s wall ({sum(r['wall_s'] for r in rows) / 60:.1f} min), "
          f"{sum(r['cpu_s'] for r in rows):.1f} s CPU, largest worker {max(r['peak_other_gib'] for r in rows):.2f} GiB, "
          f"largest caller {max(r['peak_main_gib'] for r in rows):.2f} GiB")
    if "fused_faces" in c:
        print(f"fused: {c['fused_faces']:,} faces ({c['fused_bytes'] / GIB:.2f} GiB PLY)", end="")
    if "accuracy" in c:
        a = c["accuracy"]
        print(f"; simplified: {a['faces']:,} faces, {a['mean_mm']:.3f} mm mean / {a['p95_mm']:.3f} mm p95 from the "
              "statue")
    else:
        print()


def extrapolate(store: dict, work: Path, facade_area: float, facade_coverage: float) -> None:
    """Costs per view and per m2 of surface from the measured runs, scaled to larger
    campaigns. An extrapolation: nothing below was run at that size.

    The model: the per-view stages (decode, albedo, register's pairs, texture's views) cost
    CPU per view, measured on the 146-view run; fusion costs CPU per view and per voxel a
    view's rays cross, so it scales as views x (measured voxel / voxel)^2; the fused faces,
    the fused PLY and simplification scale as surface / voxel^2. The caller of decode and
    register holds every view's range map (decode) or its downsampled cloud (register),
    measured per view on the 146-view run.
    """
    table = work / "table.json"
    if not table.is_file() or not store.get("capped"):
        return
    ps = json.loads(table.read_text())
    views = ps["capture"]["views"]
    stage = {}
    for r in ps["rows"]:  # the latest local-executor figure per stage
        if not r["mode"].startswith("dask"):
            stage[r["stage"]] = r
    statue_m2 = 3.33  # the statue's surface (statue.ply)
    cases = [("statue, 1,000 views", 1000, statue_m2, 0.57), ("statue, 1,000 views", 1000, statue_m2, 0.25),
             (f"facade 10 m, {facade_area:g} m2, 0.5 mm", None, facade_area, 0.5)]
    # the statue's views each see about this much surface: the rig's 1.0 x 0.67 m field,
    # about 70 % of it on the statue (the rest background)
    seen_per_view = 0.67 * 0.7
    print(f"\nEXTRAPOLATION, not measured at these sizes: per-view costs from the {views}-view run, fusion per view "
          "and per voxel^2, simplification and the fused mesh per m2 and per voxel^2 (from the capped run at the "
          f"nearest voxel); the facade has {facade_coverage:g}x coverage ({seen_per_view:.2f} m2 seen per view)")
    head = (f"{'campaign':28s} {'views':>6s} {'voxel':>5s} {'per-view CPU h':>14s} {'fuse CPU h':>10s} "
            f"{'serial h':>10s} "
            f"{'simplify CPU h':>14s} {'fused faces':>13s} {'fused PLY GiB':>13s} {'caller decode GiB':>17s} "
            f"{'caller register GiB':>19s} {'wall, 16 workers h':>18s}")
    print(head)
    print("-" * len(head))
    for name, n_views, area, voxel in cases:
        n = n_views or round(area * facade_coverage / seen_per_view)
        key = min(store["capped"], key=lambda k: abs(float(k) - voxel))
        res = store["capped"][key]
        fuse = next((r for r in res["rows"] if r["stage"] == "fuse"), None)
        simp = next((r for r in res["rows"] if r["stage"] == "simplify"), None)
        if fuse is None or "fused_faces" not in res:
            continue
        v_m = float(key)
        per_view_h = sum(stage[s]["cpu_s"] for s in ("decode", "albedo", "register", "texture") if s in stage) \
            * n / views / 3600
        fuse_h = fuse["cpu_s"] * (n / views) * (v_m / voxel) ** 2 / 3600
        surface = (area / statue_m2) * (v_m / voxel) ** 2
        simp_h = (simp["cpu_s"] if simp else 0.0) * surface / 3600
        decode_gib = stage["decode"]["peak_gib"] * n / views if "decode" in stage else float("nan")
        register_gib = stage["register"]["peak_gib"] * n / views if "register" in stage else float("nan")
        # the caller cuts every range map into the bricks' pieces, one after another (not on
        # the workers): per view and per pixel^2, from the run that printed it
        cut_h = float("nan")
        for k, other in sorted(store["capped"].items()):
            f_row = next((r for r in other["rows"] if r["stage"] == "fuse"), {})
            cut = re.search(r"range maps cut into pieces ([\d.]+) s", f_row.get("stdout", ""))
            if cut:
                cut_h = float(cut.group(1)) * (n / views) * (float(k) / voxel) ** 2 / 3600
                break
        wall = (per_view_h + fuse_h + simp_h) / 16 + (0.0 if math.isnan(cut_h) else cut_h)
        serial = "-" if math.isnan(cut_h) else f"{cut_h:.2f}"
        print(f"{name:28s} {n:6d} {voxel:5.2f} {per_view_h:14.1f} {fuse_h:10.1f} {serial:>10s} {simp_h:14.1f} "
              f"{res['fused_faces'] * surface:13,.0f} {res['fused_bytes'] * surface / GIB:13.1f} {decode_gib:17.1f} "
              f"{register_gib:19.1f} {wall:18.1f}")
    print("serial h: the caller cutting the range maps into pieces (not spread over the workers), scaled from the "
          "run whose `slscan fuse` printed it ('-': no stored run did); 'wall, 16 workers' = the CPU hours / 16 + "
          "the serial hours.")
    print("per worker (any size): fusion one brick's grid under --max-memory plus about 0.5 GiB; simplification one "
          "brick; decode about 1 GiB per full-size view. The callers of decode and register grow with the views.")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=("compare", "capped", "table", "recheck"))
    p.add_argument("--work", type=Path, default=Path("/tmp/slscan_paper_scale"), help="paper_scale.py's --work")
    p.add_argument("--voxel", type=float, default=0.57, help="mm")
    p.add_argument("--brick", type=float, default=0.0, help="brick edge, mm (default 160 at 0.57 mm, 240 finer)")
    p.add_argument("--grid-memory", default="2.5GiB", help="fuse --max-memory: the cap on one brick's grid")
    p.add_argument("--worker-memory", default="4GiB", help="capped: each Dask worker's memory limit")
    p.add_argument("--ways", default="single,local2,dask2", help="compare: which ways to run (also dask2t: "
                   "the Dask workers with 2 OpenMP/BLAS threads each)")
    p.add_argument("--stages", default="fuse,simplify,texture", help="capped: which stages to run")
    p.add_argument("--faces", type=int, default=1_000_000)
    p.add_argument("--texture-size", type=int, default=4096)
    p.add_argument("--texture-on-dask", action="store_true", help="capped: texture with --scheduler too")
    p.add_argument("--facade-area", type=float, default=60.0,
                   help="extrapolation: the facade's surface, m2 (10 m x 5 m with relief: 60)")
    p.add_argument("--facade-coverage", type=float, default=4.0,
                   help="extrapolation: how many views see each point of the facade")
    args = p.parse_args()
    os.environ["PYTHONPATH"] = os.pathsep.join([str(TOOLBOX), *filter(None, [os.environ.get("PYTHONPATH")])])
    if not args.brick:
        args.brick = 160.0 if args.voxel >= 0.5 else 240.0
    path = args.work / "bricks.json"
    store = json.loads(path.read_text()) if path.is_file() else {}
    t0 = time.perf_counter()
    if args.what == "compare":
        compare(args, store)
    elif args.what == "recheck":  # the stored comparison's distances again (after a change to them)
        folder = args.work / "bricks" / f"compare_{store['compare']['voxel']:g}"
        for row in store["compare"]["rows"]:
            if row["way"] != "single":
                row.update(mesh_distance(folder / "single.ply", folder / f"{row['way']}.ply"))
    elif args.what == "capped":
        capped(args, store)
    if args.what != "table":
        tmp = path.with_suffix(".partial.json")
        tmp.write_text(json.dumps(store, indent=1))
        os.replace(tmp, path)
        print(f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    if "compare" in store:
        print_compare(store["compare"])
    for _, c in sorted(store.get("capped", {}).items()):
        print_capped(c)
    extrapolate(store, args.work, args.facade_area, args.facade_coverage)


if __name__ == "__main__":
    main()
