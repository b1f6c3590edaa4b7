"""Time and memory measurement shared by the benchmark scripts (not a benchmark itself).

- :func:`cpu_seconds`, :func:`peak_rss_bytes`: this process's CPU time and peak resident
  memory (``VmHWM``, which sees C++ allocations by open3d and pymeshlab too);
- :func:`run_measured`: run a command and sample the resident memory of its whole process
  tree (the command and every worker it starts), so a stage that fans out over worker
  processes is charged for all of them at once;
- :func:`surface_samples`, :func:`distances_to_mesh`: surface-to-surface distances;
- :func:`fuse_at_true_poses`, :func:`model_vs_truth`: a virtual session's range maps fused
  at the recorded poses, and how far the fused model is from the true surface.
"""

from __future__ import annotations

import resource
import subprocess
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def cpu_seconds() -> float:
    """User + system CPU time of this process so far (all threads), s."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def peak_rss_bytes() -> int:
    """Peak resident memory of this process, bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _children() -> dict[int, list[int]]:
    tree: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        # "pid (name) state ppid ...": the name may hold spaces and parentheses
        ppid = int(text[text.rindex(")") + 2:].split()[1])
        tree.setdefault(ppid, []).append(int(stat.parent.name))
    return tree


def _rss_bytes(pid: int, field: str = "VmRSS") -> int:
    """Resident memory of ``pid`` now, bytes: ``VmRSS`` (all of it), or ``RssAnon`` (without
    file pages: memory-mapped files that the kernel can drop and read again)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def tree_rss_bytes(root: int) -> int:
    """Resident memory of process ``root`` and all its descendants now, bytes."""
    return sum(tree_rss_by_pid(root).values())


def tree_rss_by_pid(root: int, tree: dict[int, list[int]] | None = None) -> dict[int, int]:
    """{pid: resident memory now, bytes} of process ``root`` and all its descendants."""
    tree, out, todo = tree if tree is not None else _children(), {}, [root]
    while todo:
        pid = todo.pop()
        out[pid] = _rss_bytes(pid)
        todo.extend(tree.get(pid, ()))
    return out


@dataclass
class Measured:
    returncode: int
    seconds: float
    peak_bytes: int  # largest sampled sum over the process tree
    stdout: str
    stderr: str
    peak_main_bytes: int = 0  # largest sampled resident memory of the command's own process
    peak_other_bytes: int = 0  # of any one other process (a helper, a Dask worker)
    peak_main_anon_bytes: int = 0  # the command's own process without file pages (RssAnon)


def run_measured(command: list[str], *, interval: float = 0.1, extra_pids: Sequence[int] = (),
                 **kwargs) -> Measured:
    """Run ``command``; its wall time and the peak resident memory of its process tree.

    The tree is sampled every ``interval`` seconds, so a peak shorter than that can be
    missed; each sample walks /proc (about 1 ms here). ``extra_pids``: processes that work
    for the command without being its children (a Dask cluster's workers), each sample
    adds their trees.
    """
    t0 = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)
    peak = peak_main = peak_other = peak_main_anon = 0
    done = threading.Event()

    def sample() -> None:
        nonlocal peak, peak_main, peak_other, peak_main_anon
        while not done.is_set():
            tree = _children()
            rss = tree_rss_by_pid(proc.pid, tree)
            for pid in extra_pids:
                rss.update(tree_rss_by_pid(pid, tree))
            peak = max(peak, sum(rss.values()))
            peak_main = max(peak_main, rss.get(proc.pid, 0))
            peak_main_anon = max(peak_main_anon, _rss_bytes(proc.pid, "RssAnon"))
            peak_other = max([peak_other, *(v for k, v in rss.items() if k != proc.pid)])
            done.wait(interval)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    stdout, stderr = proc.communicate()
    done.set()
    sampler.join()
    return Measured(proc.returncode, time.perf_counter() - t0, peak, stdout, stderr, peak_main, peak_other,
                    peak_main_anon)


def kamino410_gray_views(src: Path):
    """kamino410's captures in ``src`` imported into a temporary capture session, view by
    view: ``(view name, {pattern id: image} of its Gray-code images, their
    PatternImages, white image, black image)``."""
    import tempfile

    from slscan.capture.kamino410 import import_kamino410

    with tempfile.TemporaryDirectory() as tmp:
        session = import_kamino410(src, Path(tmp) / "session")
        descs = [p for p in session.patterns if p.family == "gray"]
        for view in session.views:
            images = {d.id: session.read_image(view, view.image_for(d.id)) for d in descs}
            white = session.read_image(view, view.image_for("white"))
            black = session.read_image(view, view.image_for("black"))
            yield view.name, images, descs, white, black


def surface_samples(vertices: np.ndarray, faces: np.ndarray, n: int = 500_000, seed: int = 0) -> np.ndarray:
    """(n, 3) points spread uniformly by area on a triangle mesh (fixed seed).

    Distances taken from such points weigh the surface by area; vertex statistics would
    over-count open boundaries' few extrapolated vertices once a mesh is simplified.
    """
    rng = np.random.default_rng(seed)
    vertices = np.asarray(vertices, np.float64)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    pick = rng.choice(len(faces), size=n, p=area / area.sum())
    u, v = rng.random((2, n))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return a[pick] + (b[pick] - a[pick]) * u[:, None] + (c[pick] - a[pick]) * v[:, None]


def distances_to_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest point of a triangle mesh (open3d ray-casting scene)."""
    import open3d as o3d
    import open3d.core as o3c

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3c.Tensor(np.asarray(vertices, np.float32)), o3c.Tensor(np.asarray(faces, np.uint32)))
    return scene.compute_distance(o3c.Tensor(np.asarray(points, np.float32))).numpy()


def fuse_at_true_poses(session, range_maps: dict, voxel: float):
    """The range maps (view name -> :class:`slscan.decode.rangemap.RangeMap`) of a virtual
    session fused at the views' recorded object poses (weighted TSDF, ``voxel`` mm): the
    fused mesh, in the object frame."""
    from slscan.fuse import FuseConfig, fuse_scans
    from slscan.register.rangescan import scan_from_mesh

    scans, poses = [], {}
    for v in session.views:
        rm = range_maps[v.name]
        centre = rm.vertices.mean(axis=0)
        scans.append(scan_from_mesh(rm.vertices, rm.faces, quality=rm.quality, normals=rm.normals,
                                    name=v.name, view_direction=-centre / np.linalg.norm(centre)))
        poses[v.name] = np.linalg.inv(v.rig_from_object)
    return fuse_scans(scans, poses, config=FuseConfig(voxel_size=voxel)).mesh


def model_vs_truth(mesh, scene, truth_points: np.ndarray) -> tuple[np.ndarray, float]:
    """Distances (mm) from 300 000 points spread by area on ``mesh`` to the true surface
    ``scene``, and completeness: the share of ``truth_points`` (spread on the true surface)
    within 1 mm of the mesh."""
    d = distances_to_mesh(surface_samples(mesh.vertices, mesh.faces, 300_000), scene.vertices, scene.triangles)
    complete = float(np.mean(distances_to_mesh(truth_points, mesh.vertices, mesh.faces) < 1.0))
    return d, complete


def export_toolbox(rev: str, folder: Path) -> Path:
    """``toolbox/`` of git revision ``rev`` written to ``folder`` (git archive: the working
    tree and the repository are left as they are), for ``--against REV`` runs."""
    import io
    import tarfile

    root = Path(__file__).resolve().parent.parent
    proc = subprocess.run(["git", "-C", str(root), "archive", rev, "toolbox"],
                          capture_output=True, check=False)
    if proc.returncode != 0:
        raise SystemExit(f"--against {rev}: {proc.stderr.decode(errors='replace').strip()}")
    folder.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(proc.stdout)) as tar:
        tar.extractall(folder, filter="data")
    return folder / "toolbox"


def run_json(command: list[str], what: str, toolbox: Path | None = None) -> dict:
    """Run a benchmark's child process (with ``toolbox`` first on its PYTHONPATH, for an
    ``--against`` revision) and return the JSON object its last output line holds."""
    import json
    import os

    env = None
    if toolbox is not None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(
            [str(toolbox), *filter(None, [os.environ.get("PYTHONPATH")])]))
    proc = subprocess.run(command, capture_output=True, text=True, check=False, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"{what} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])
