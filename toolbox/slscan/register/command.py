"""``slscan register``, ``slscan fuse``, ``slscan simplify``: range maps to one model."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError, about_file
from slscan.progress import ProgressBar, console
from slscan.units import MEMORY_HELP

SHOWN_REJECTED = 5
"""Rejected pairs listed in ``slscan register``'s summary (registration.json has them all)."""
MAX_NEIGHBOURS = 8
"""Default of ``--max-neighbours`` (``MultiviewConfig.max_neighbours``; open3d is imported
only when the command runs)."""


def load_scans(
    path: Path, *, conf: str | None = None, allow_outside: bool = False
) -> tuple[list, dict[str, np.ndarray] | None]:
    """Range scans and their poses (world_from_scan, mm) when known, from what ``path`` is.

    - a MeshLab project (``.mlp``), or a folder holding ``aligned.mlp``;
    - an slscan range-maps folder (``range_maps.json``): each view's pose on the rig
      (``rig_from_object``) gives ``world_from_scan = inverse(rig_from_object)``;
    - a Stanford folder with a ``.conf`` file (e.g. ``bun.conf``; metres): ``conf`` names
      it (required when the folder has several);
    - any folder of PLY meshes (no poses: features align them).

    A project's (or a .conf's) mesh files outside its folder are read only with ``allow_outside``.
    """
    from slscan.fsio import glob_results, read_json
    from slscan.register.meshlab import load_scan_project
    from slscan.register.rangescan import load_range_scan, load_stanford_dir

    if conf and not path.is_dir():
        raise SlscanError(f"{path}: a .conf ({conf}) is chosen only in a Stanford folder")
    if path.suffix == ".mlp":
        return load_scan_project(path, allow_outside=allow_outside)
    if not path.is_dir():
        raise SlscanError(f"{path}: expected a .mlp project or a folder of range maps")
    if conf:
        if not (path / conf).is_file():
            found = ", ".join(p.name for p in glob_results(path, "*.conf")) or "none"
            raise SlscanError(f"{path / conf}: not found (.conf files in {path}: {found})")
        return load_stanford_dir(path, conf=conf, allow_outside=allow_outside)
    if (path / "aligned.mlp").is_file():
        return load_scan_project(path / "aligned.mlp", allow_outside=allow_outside)
    if (path / "range_maps.json").is_file():
        summary = path / "range_maps.json"
        with about_file(summary, "range-maps summary"):
            return _range_map_scans(summary, allow_outside=allow_outside)
    confs = glob_results(path, "*.conf")
    if len(confs) > 1:
        raise SlscanError(
            f"{path}: {len(confs)} .conf files ({', '.join(c.name for c in confs)}); choose one "
            "(--conf NAME; register.conf in a recipe)"
        )
    if confs:
        return load_stanford_dir(path, conf=confs[0].name, allow_outside=allow_outside)
    plys = glob_results(path, "*.ply")
    if not plys:
        raise SlscanError(f"{path}: no range maps found (expected .ply files, range_maps.json, a .conf or a .mlp)")
    return [load_range_scan(p) for p in plys], None


def _range_map_scans(summary: Path, *, allow_outside: bool) -> tuple[list, dict[str, np.ndarray] | None]:
    """The scans a decode output's ``range_maps.json`` lists, and their poses when it has
    one for each (``world_from_scan = inverse(rig_from_object)``)."""
    from slscan.fsio import read_json
    from slscan.register.rangescan import load_range_scan
    from slscan.rig import _as_pose

    views = read_json(summary, "range-maps summary")["views"]
    if not isinstance(views, list) or not views:
        raise SlscanError(f"{summary}: lists no views; expected the range maps slscan decode wrote")
    scans, poses = [], {}
    for i, entry in enumerate(views):
        file = summary.parent / entry["file"]
        if not allow_outside and not file.resolve().is_relative_to(summary.parent.resolve()):
            raise SlscanError(f"{summary}: range map {entry['file']!r} lies outside its folder "
                              "(pass --allow-outside to read it)")
        scan = load_range_scan(file)
        scans.append(scan)
        if entry.get("rig_from_object") is not None:
            try:
                pose = _as_pose(entry["rig_from_object"], "")
            except (SlscanError, TypeError, ValueError):
                raise SlscanError(f"{summary}: views[{i}].rig_from_object: expected a finite, invertible 4x4 "
                                  f"pose, got {entry['rig_from_object']!r}") from None
            poses[scan.name] = np.linalg.inv(pose)
    return scans, (poses if len(poses) == len(scans) else None)


def iter_scans(path: Path, *, allow_outside: bool = False):
    """:func:`load_scans` one scan at a time, for an aligned set (a ``.mlp`` project, a folder
    holding ``aligned.mlp``) or a range-maps folder whose views all have a pose: (number of
    scans, iterator of RangeScan, poses) where ``poses`` (world_from_scan, mm, by scan name)
    is filled as each scan is yielded; None for any other input (load it with
    :func:`load_scans`). A mesh file is read only when its turn comes."""
    from slscan.fsio import read_json
    from slscan.register.meshlab import iter_scan_project, read_mlp
    from slscan.register.rangescan import load_range_scan
    from slscan.rig import _as_pose

    poses: dict[str, np.ndarray] = {}
    project = path if path.suffix == ".mlp" else path / "aligned.mlp" if (path / "aligned.mlp").is_file() else None
    if project is not None:
        count = len(read_mlp(project, allow_outside=allow_outside))

        def from_project():
            for scan, matrix in iter_scan_project(project, allow_outside=allow_outside):
                poses[scan.name] = matrix
                yield scan
                del scan  # not held while the next one is read

        return count, from_project(), poses
    summary = path / "range_maps.json"
    if not (path.is_dir() and summary.is_file()):
        return None
    with about_file(summary, "range-maps summary"):
        views = read_json(summary, "range-maps summary")["views"]
    if not isinstance(views, list) or not views:
        raise SlscanError(f"{summary}: lists no views; expected the range maps slscan decode wrote")
    if any(not isinstance(v, dict) or v.get("rig_from_object") is None for v in views):
        return None  # some view without a pose: load_scans says so

    def from_range_maps():
        for i, entry in enumerate(views):
            with about_file(summary, "range-maps summary"):  # as load_scans: errors name the summary
                file = summary.parent / entry["file"]
                if not allow_outside and not file.resolve().is_relative_to(summary.parent.resolve()):
                    raise SlscanError(f"{summary}: range map {entry['file']!r} lies outside its folder "
                                      "(pass --allow-outside to read it)")
                try:
                    pose = _as_pose(entry["rig_from_object"], "")
                except (SlscanError, TypeError, ValueError):
                    raise SlscanError(f"{summary}: views[{i}].rig_from_object: expected a finite, invertible "
                                      f"4x4 pose, got {entry['rig_from_object']!r}") from None
                scan = load_range_scan(file)
            poses[scan.name] = np.linalg.inv(pose)
            yield scan
            del scan

    return len(views), from_range_maps(), poses


def load_poses(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Start poses (world_from_scan, mm) by scan name, from a file, for the scans ``names``.

    path : a Stanford ``.conf`` (``bmesh FILE tx ty tz qx qy qz qw``; metres, as Stanford's),
        an slscan ``registration.json`` (its ``poses``, mm) or a MeshLab ``.mlp`` (a mesh's
        name is its file stem; mm)

    Raises
    ------
    SlscanError
        An unreadable file, or one whose names do not match the scans: naming the file, the
        names it has that match no scan, and the scans it has no pose for.
    """
    from slscan.fsio import read_json
    from slscan.register.meshlab import read_mlp
    from slscan.register.rangescan import load_bun_conf

    if not path.is_file():
        raise SlscanError(f"{path}: pose file not found")
    suffix = path.suffix.lower()
    if suffix == ".conf":
        poses = load_bun_conf(path)
    elif suffix == ".mlp":
        poses = {file.stem: np.asarray(m, float) for file, m in read_mlp(path, check_files=False)}
    elif suffix == ".json":
        data = read_json(path, "registration result")
        try:
            poses = {str(k): np.asarray(v, float).reshape(4, 4) for k, v in data["poses"].items()}
        except (KeyError, TypeError, AttributeError, ValueError):
            raise SlscanError(f"{path}: expected a 'poses' object of scan name -> 4x4 matrix") from None
        bad = [k for k, m in poses.items() if not np.isfinite(m).all()]
        if bad:
            raise SlscanError(f"{path}: poses.{bad[0]} holds non-finite numbers; expected a finite 4x4 matrix")
    else:
        raise SlscanError(f"{path}: expected a .conf, a registration.json or a .mlp pose file")
    unknown = [n for n in poses if n not in names]
    missing = [n for n in names if n not in poses]
    if unknown or missing:
        problems = ([f"names {', '.join(unknown)} that match no scan"] if unknown else []) + (
            [f"no pose for scans {', '.join(missing)}"] if missing else [])
        raise SlscanError(f"{path}: {'; '.join(problems)} (the scans are {', '.join(names)})")
    return {n: poses[n] for n in names}


def _number(x: float) -> float | None:
    """``x``, or None (JSON null) when it is not finite."""
    return float(x) if np.isfinite(x) else None


def save_registration(folder: Path, scans, result, *, overwrite: bool = False, frame=None) -> Path:
    """Write a registration: the aligned set (each registered scan as PLY + ``aligned.mlp``,
    atomically) and ``registration.json`` (reference, poses, residual per pair, scans left
    out, pairs rejected with the reason, and with ``frame`` — a
    :class:`~slscan.register.frame.ObjectFrame` — the object frame the poses are in).
    Returns the project's path."""
    from slscan.fsio import write_json
    from slscan.register.meshlab import write_scan_project

    project = write_scan_project(folder, [s for s in scans if s.name in result.poses], result.poses,
                                 overwrite=overwrite)
    write_json(folder / "registration.json", {
        "reference": result.reference,
        "poses": {k: v.tolist() for k, v in result.poses.items()},
        "pairs": [{"source": p.source, "target": p.target, "fitness": p.fitness, "rmse_mm": p.rmse}
                  for p in result.pairs],
        "left_out": result.left_out,
        **({"held": list(result.fixed)} if result.fixed else {}),
        "rejected": [{"source": r.source, "target": r.target, "reason": r.reason,
                      "fitness": _number(r.fitness), "rmse_mm": _number(r.rmse)}
                     for r in result.rejected],
        **({"frame": frame.to_json()} if frame is not None else {}),
    })
    return project


def _cmd_register(args: argparse.Namespace) -> int:
    from slscan.executor import executor_from_args
    from slscan.register.frame import preview_frame, to_object_frame
    from slscan.register.multiview import MultiviewConfig, median_pair_rmse, register_scans
    from slscan.viewer import log_register as rlog
    from slscan.viewer.recording import recording_from_args

    if args.pose_tolerance is not None and not args.pose_tolerance > 0:
        raise SlscanError(f"--pose-tolerance must be > 0 mm, got {args.pose_tolerance}")
    if args.max_neighbours < 0:
        raise SlscanError(f"--max-neighbours must be >= 0 (0: every candidate pair), got {args.max_neighbours}")
    if args.out is None and args.into is None:
        raise SlscanError("register: --out FOLDER is required (or --into an aligned set, to grow it)")
    out_folder = args.out if args.out is not None else (args.into if args.into.suffix != ".mlp" else args.into.parent)
    scans, poses = load_scans(args.scans, conf=args.conf, allow_outside=args.allow_outside)
    if args.poses is not None:
        poses = load_poses(args.poses, [s.name for s in scans])
    if args.no_poses:
        poses = None
    held: list[str] = []
    old_frame = None
    if args.into is not None:
        scans, poses, held, old_frame, reference = load_into(args.into, scans, allow_outside=args.allow_outside)
        if args.reference is None:
            args.reference = reference
    config = MultiviewConfig(pose_tolerance=args.pose_tolerance, max_neighbours=args.max_neighbours)
    t0 = time.perf_counter()
    from slscan.viewer.layouts import register_blueprint

    with recording_from_args(args, recording_name=f"register {args.scans.name}",
                             blueprint=register_blueprint()) as rec:
        start = preview_frame(scans, poses)
        rlog.log_registration_start(rec, scans, start.apply(poses) if start else poses)
        n_pairs = len(scans) * (len(scans) - 1) // 2
        with ProgressBar(n_pairs + 1, "registering", args.quiet) as bar:
            result = register_scans(scans, initial_poses=poses, reference=args.reference, config=config,
                                    progress=bar.step, on_total=lambda k: bar.set_total(k + 1), fixed=held,
                                    executor=executor_from_args(args))
        check_joined(result, scans, args.scans)
        if held:  # the held poses are in the set's object frame already
            frame = old_frame
        else:
            result, frame = to_object_frame(scans, result)
        rlog.log_registration_result(rec, result)
    project = save_registration(out_folder, scans, result, overwrite=args.overwrite or args.out is None,
                                frame=frame)
    out = console()
    median = median_pair_rmse(result.pairs)
    residual = "no pair residual" if median is None else f"median residual {median:.3f} mm"
    if held:
        added = [s.name for s in scans if s.name in result.poses and s.name not in held]
        out.print(f"[green]added[/] {len(added)} of {len(scans) - len(held)} new scans "
                  f"({', '.join(added) or 'none'}) to the {len(held)} held in {args.into}", highlight=False)
    out.print(f"[green]aligned[/] {len(result.poses)} of {len(scans)} scans in {time.perf_counter() - t0:.1f} s; "
              f"{len(result.pairs)} overlapping pairs, {residual} -> {project}", highlight=False)
    if result.rejected:
        n = len(result.rejected)
        out.print(f"{n} candidate pair{'s' * (n != 1)} rejected (all in registration.json):",
                  highlight=False)
        for r in result.rejected[:SHOWN_REJECTED]:
            out.print(f"  [yellow]rejected[/] {r.source}-{r.target}: {r.reason}", highlight=False)
        if len(result.rejected) > SHOWN_REJECTED:
            out.print(f"  ... and {len(result.rejected) - SHOWN_REJECTED} more", highlight=False)
    for name, reason in result.left_out.items():
        out.print(f"[yellow]left out[/] {name}: {reason}", highlight=False)
    if result.left_out:
        out.print(f"[yellow]warning[/]: {len(result.left_out)} of {len(scans)} scans left out, not aligned: "
                  f"{', '.join(result.left_out)} (reasons in registration.json)", highlight=False)
    if frame is not None:
        up = (f"the turntable axis of {len(frame.turntable_views)} views" if frame.up_from == "turntable"
              else "the cameras' up (no turntable axis found)")
        out.print(f"object frame: y up along {up}, origin at the object's base", highlight=False)
    return 0


def check_joined(result, scans, source: Path) -> None:
    """Raise when the registration joined fewer than 2 scans (nothing is written then): one
    line naming the scans and why each was left out."""
    if len(result.poses) >= 2:
        return
    reasons = "; ".join(f"{name}: {why}" for name, why in result.left_out.items())
    joined = f" ({', '.join(result.poses)})" if result.poses else ""
    raise SlscanError(f"{source}: registration joined {len(result.poses)} of {len(scans)} scans{joined}, nothing "
                      f"written (need at least 2 that overlap): {reasons}")


def load_into(into: Path, new_scans: list, *, allow_outside: bool = False):
    """The aligned set ``into`` (a folder with ``aligned.mlp``, or the .mlp) joined by
    ``new_scans``: (all scans, their known poses — the set's, held —, the held names, the
    set's object frame or None, its reference scan or None).

    Raises SlscanError when ``into`` has no aligned set or a new scan's name is in it.
    """
    from slscan.register.frame import read_frame
    from slscan.register.meshlab import load_scan_project

    project = into / "aligned.mlp" if into.is_dir() else into
    if not project.is_file():
        raise SlscanError(f"{into}: no aligned set to grow (expected aligned.mlp from `slscan register`)")
    old, old_poses = load_scan_project(project, allow_outside=allow_outside)
    clash = sorted({s.name for s in old} & {s.name for s in new_scans})
    if clash:
        raise SlscanError(f"{project}: already holds scans {', '.join(clash)}; new scans need other names")
    summary = project.parent / "registration.json"
    frame, reference = None, None
    if summary.is_file():
        from slscan.fsio import read_json

        frame = read_frame(summary)
        reference = read_json(summary, "registration result").get("reference")
        if reference not in old_poses:
            reference = None
    return [*old, *new_scans], dict(old_poses), [s.name for s in old], frame, reference


def _cmd_fuse(args: argparse.Namespace) -> int:
    from slscan.executor import executor_from_args
    from slscan.fuse import FuseConfig, fuse_bricks, fuse_scans, parse_memory, poisson_reconstruct, write_mesh
    from slscan.register.meshlab import write_mesh_project
    from slscan.viewer import log_register as rlog
    from slscan.viewer.layouts import register_blueprint
    from slscan.viewer.recording import recording_from_args

    if not (math.isfinite(args.voxel) and args.voxel > 0):
        raise SlscanError(f"--voxel must be a positive number of mm, got {args.voxel}")
    _check_mesh_out(args.out, args.overwrite)
    config = FuseConfig(voxel_size=args.voxel, brick_size=args.brick,
                        **({"max_memory_gib": parse_memory(args.max_memory)} if args.max_memory else {}))
    # in bricks, the scans are read one at a time as the bricks' pieces are cut
    lazy = iter_scans(args.aligned, allow_outside=args.allow_outside) if (
        args.brick is not None and args.method == "tsdf") else None
    if lazy is not None:
        n_scans, scans, poses = lazy
    else:
        scans, poses = load_scans(args.aligned, allow_outside=args.allow_outside)
        n_scans = len(scans)
    if poses is None:
        raise SlscanError(f"{args.aligned}: the scans have no poses; run `slscan register` first")
    t0 = time.perf_counter()
    if args.method == "tsdf" and args.brick is not None and args.out.suffix.lower() == ".ply":
        return _fuse_streamed(args, config, scans, poses, t0, n_scans)
    with recording_from_args(args, recording_name=f"fuse {args.aligned.name}", blueprint=register_blueprint()) as rec:
        with ProgressBar(n_scans, f"fusing ({args.method})", args.quiet) as bar:
            if args.method == "tsdf":
                mesh = fuse_scans(scans, poses, config=config, progress=bar.step, progress_total=bar.set_total,
                                  executor=executor_from_args(args), scratch_beside=args.out).mesh
            else:
                mesh = poisson_reconstruct(scans, poses, voxel_size=args.voxel)
        rlog.log_fused_mesh(rec, mesh)
    write_mesh(mesh, args.out)
    project = write_mesh_project(args.out)
    console().print(f"[green]fused[/] {n_scans} scans at {args.voxel} mm: {len(mesh.faces):,} faces in "
                    f"{time.perf_counter() - t0:.1f} s -> {args.out} (MeshLab: {project})", highlight=False)
    return 0


def _fuse_streamed(args: argparse.Namespace, config, scans, poses, t0: float, n_scans: int) -> int:
    """``slscan fuse --brick MM --out X.ply``: the bricks' mesh streams to the PLY (the caller never
    holds it whole); logged to Rerun only when small enough to read back."""
    from slscan.executor import executor_from_args
    from slscan.fuse import fuse_bricks
    from slscan import fuse_stream
    from slscan.fuse_stream import mesh_to_log
    from slscan.register.meshlab import write_mesh_project
    from slscan.viewer import log_register as rlog
    from slscan.viewer.layouts import register_blueprint
    from slscan.viewer.recording import recording_from_args

    name = f"fuse {args.aligned.name}"
    with recording_from_args(args, recording_name=name, blueprint=register_blueprint()) as rec:
        with ProgressBar(n_scans, "fusing (tsdf, bricks)", args.quiet) as bar:
            t_bricks = time.perf_counter()
            result = fuse_bricks(scans, poses, config=config, progress=bar.step, progress_total=bar.set_total,
                                 executor=executor_from_args(args), out=args.out)
            t_bricks = time.perf_counter() - t_bricks
            written = result.written
        if rec is not None:
            mesh = mesh_to_log(written)
            if mesh is not None:
                rlog.log_fused_mesh(rec, mesh)
            else:
                console().print(f"fuse: the fused mesh ({written.n_faces:,} faces) is too large to log to Rerun "
                                f"(more than {fuse_stream.LOG_MAX_FACES:,}); the simplified model is logged "
                                "(slscan simplify with --save, --spawn or --connect)",
                                highlight=False, soft_wrap=True)
    project = write_mesh_project(args.out)
    cut, write = result.seconds.get("pieces", 0.0), result.seconds.get("stitch", 0.0)
    console().print(f"[green]fused[/] {n_scans} scans at {args.voxel} mm in {result.n_bricks} bricks, streamed: "
                    f"{written.n_faces:,} faces in {time.perf_counter() - t0:.1f} s (range maps cut into pieces "
                    f"{cut:.1f} s, bricks {t_bricks - cut - write:.1f} s, PLY written {write:.1f} s) -> {args.out} "
                    f"(MeshLab: {project})", highlight=False)
    return 0


def _check_mesh_out(out: Path, overwrite: bool) -> None:
    """Refuse to replace an existing mesh file ``out``, or the MeshLab project written beside
    it (``OUT.mlp``), unless ``overwrite`` (before any work)."""
    if out.is_dir():
        raise SlscanError(f"{out}: is a folder; expected a mesh file such as model.ply")
    if out.suffix.lower() == ".mlp":
        raise SlscanError(f"{out}: expected a mesh file such as model.ply (the .mlp is written beside it)")
    for path in (out, out.with_suffix(".mlp")):
        if path.exists() and not overwrite:
            raise SlscanError(f"{path}: exists (pass --overwrite to replace it)")


def _cmd_simplify(args: argparse.Namespace) -> int:
    from slscan.register.meshlab import write_mesh_project
    from slscan.simplify import simplify_file
    from slscan.viewer import log_register as rlog
    from slscan.viewer.layouts import register_blueprint
    from slscan.viewer.recording import recording_from_args

    _check_mesh_out(args.out, args.overwrite)
    t0 = time.perf_counter()
    with (recording_from_args(args, recording_name=f"simplify {args.mesh.name}", blueprint=register_blueprint()) as rec,
          ProgressBar(1, f"simplifying ({args.method})", args.quiet) as bar):
        mesh = simplify_file(args.mesh, args.out, args.faces, method=args.method,
                             preserve_boundary=not args.free_boundary, option="--faces")
        bar.step(f"{len(mesh.faces):,} faces")
        rlog.log_simplified_mesh(rec, mesh)
    project = write_mesh_project(args.out)
    console().print(f"[green]simplified[/] {args.mesh} to {len(mesh.faces):,} faces in "
                    f"{time.perf_counter() - t0:.1f} s -> {args.out} (MeshLab: {project})", highlight=False)
    return 0


def add_command(subparsers: argparse._SubParsersAction) -> None:
    """Add ``register``, ``fuse`` and ``simplify`` to the ``slscan`` subcommands."""
    from slscan.executor import add_executor_arguments
    from slscan.viewer.recording import add_recording_arguments

    p = subparsers.add_parser(
        "register", help="align overlapping range maps (ICP + pose graph) into a MeshLab project",
        description="Align range maps into one frame: coarse alignment from their recorded poses "
                    "(or from geometric features when there are none: several hypotheses per pair, each "
                    "verified by its fine residual and free space, then loops of three scans), "
                    "point-to-plane ICP on every overlapping pair, then a pose graph. Scans that match "
                    "nothing, or whose alignment their overlaps do not support, are reported and left out. Writes each scan as PLY, aligned.mlp (MeshLab) and registration.json "
                    "(poses, a residual per pair, the pairs rejected and why).",
        epilog="examples:\n  slscan register demo-run/decode --out aligned\n"
               "  slscan register ../shared/data/stanford_bunny --out bunny-aligned --no-poses\n"
               "  slscan register demo-run/decode --poses aligned/registration.json --pose-tolerance 5 "
               "--out aligned2\n"
               "  slscan register more-views/decode --into aligned        (add views to a registration)\n\n"
               "A scan whose alignment its overlaps do not support is left out and named (exit 0, with a "
               "warning); fewer than 2 scans joined is an error (exit 1, nothing written).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scans", type=Path, help="range-maps folder (slscan decode), Stanford folder (.conf), "
                                            "folder of PLYs, or a .mlp project")
    p.add_argument("--out", type=Path, help="folder for the aligned set (default with --into: that set, updated)")
    p.add_argument("--into", type=Path, metavar="ALIGNED",
                   help="grow an existing aligned set (a folder of `slscan register`): its poses are "
                        "held, the new scans found from features against it (their recorded poses "
                        "unused), and the set rewritten with them (or written to --out)")
    start = p.add_mutually_exclusive_group()
    start.add_argument("--no-poses", action="store_true", help="ignore recorded poses; align from features")
    start.add_argument("--poses", type=Path, metavar="FILE",
                       help="start from these poses instead of the recorded ones: a Stanford .conf "
                            "(metres), an slscan registration.json or a MeshLab .mlp (mm); poses by "
                            "scan name, one for every scan")
    p.add_argument("--pose-tolerance", type=float, metavar="MM",
                   help="how far (mm) the start poses may be off: the first ICP round's reach; a "
                        "pair ICP moves by more than twice this is rejected (default: 5 times the "
                        "start poses' misfit, between 4 and 30 sample spacings)")
    p.add_argument("--max-neighbours", type=int, metavar="K", default=MAX_NEIGHBOURS,
                   help="with start poses, align each scan with at most K partners, its best "
                        "candidates by estimated overlap, keeping the graph connected; 0: every "
                        f"candidate pair, quadratic in the scans (default {MAX_NEIGHBOURS})")
    p.add_argument("--conf", metavar="NAME",
                   help="the .conf to read in a Stanford folder (needed when it holds several)")
    p.add_argument("--reference", help="scan that keeps its pose (default: the first)")
    p.add_argument("--allow-outside", action="store_true",
                   help="read mesh files a .mlp (or a Stanford .conf) names outside its folder (each "
                        "is named in a warning)")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    add_executor_arguments(p)  # the pairwise alignments run on helper processes or a Dask cluster
    p.set_defaults(func=_cmd_register)

    p = subparsers.add_parser(
        "fuse", help="fuse aligned range maps into one mesh (volumetric)",
        description="Fuse an aligned set (aligned.mlp) into one watertight-where-seen mesh: a "
                    "weighted TSDF in a sparse voxel-block grid (quality and view direction as "
                    "weights; memory bounded), or screened Poisson (pymeshlab).",
        epilog="example:\n  slscan fuse aligned/aligned.mlp --voxel 0.57 --out fused.ply",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("aligned", type=Path, help="aligned.mlp (or its folder) from slscan register or MeshLab")
    p.add_argument("--out", required=True, type=Path,
                   help="mesh file to write (PLY); a MeshLab project OUT.mlp opening it is written beside")
    p.add_argument("--voxel", type=float, default=0.57, help="voxel size, mm (default 0.57, the paper's)")
    p.add_argument("--method", choices=("tsdf", "poisson"), default="tsdf", help="default: tsdf")
    p.add_argument("--brick", type=float, metavar="MM",
                   help="fuse in cubic bricks of about MM mm a side (whole 8-voxel blocks), each a task "
                        "for --workers or --scheduler; the same mesh as one volume (default: one volume). "
                        "A PLY --out is streamed: each brick writes its piece to a scratch folder beside "
                        "--out (Dask workers must see it at the same path), the PLY is written brick by brick")
    p.add_argument("--max-memory", metavar="SIZE",
                   help="memory cap of the voxel grid; with --brick, per brick (per worker); "
                        "a brick that cannot fit is named before anything runs (default 10GiB); " + MEMORY_HELP)
    p.add_argument("--allow-outside", action="store_true",
                   help="read mesh files the .mlp names outside its folder (each is named in a warning)")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    add_executor_arguments(p)
    p.set_defaults(func=_cmd_fuse)

    p = subparsers.add_parser(
        "simplify", help="simplify a mesh to a target face count (default 1,000,000)",
        description="Quadric simplification with fast-simplification (default) or pymeshlab's "
                    "quadric edge collapse (--method quadric, slower, higher quality); mesh "
                    "boundaries are preserved unless --free-boundary.",
        epilog="example:\n  slscan simplify fused.ply --faces 1000000 --out model.ply",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("mesh", type=Path, help="mesh file (PLY/OBJ)")
    p.add_argument("--out", required=True, type=Path,
                   help="mesh file to write; a MeshLab project OUT.mlp opening it is written beside")
    p.add_argument("--faces", type=int, default=1_000_000, help="target face count (default 1000000)")
    p.add_argument("--method", choices=("fast", "quadric"), default="fast", help="default: fast")
    p.add_argument("--free-boundary", action="store_true", help="let boundary edges collapse")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_recording_arguments(p)
    p.set_defaults(func=_cmd_simplify)
