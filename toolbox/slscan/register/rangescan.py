"""Range scans to register: one view's surface mesh in its own frame, with its view direction.

A :class:`RangeScan` is what registration and fusion consume: vertices in the scan's
own frame (mm), faces, unit normals, a per-vertex quality (confidence weight) and the
direction from the surface towards the sensor. Loaders read the Stanford range-grid
PLY files (``bun000.ply`` …, metres, with a ``range_grid`` element), Stanford ``.conf``
pose files, and any triangle-mesh PLY (ASCII or binary), including the range maps the
decode stage writes.

References
----------
.. [1] Turk, Levoy, "Zippered polygon meshes from range images", SIGGRAPH 1994 (range
   grid triangulation with an edge-length test).
.. [2] Curless, Levoy, "A volumetric method for building complex models from range
   images", SIGGRAPH 1996 (weights falling off with grazing angle and near boundaries).
"""

from __future__ import annotations

import logging
import math
import os
import weakref
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from slscan.errors import SlscanError
from slscan.meshes import check_face_indices, check_finite_vertices, vertex_normals
from slscan.ply import fan_triangles, read_ply_elements, write_triangle_ply

log = logging.getLogger(__name__)

STANFORD_VIEW_DIRECTION = (0.0, 0.0, 1.0)
"""Towards the sensor in a Stanford scan's frame: the Cyberware scanner looks along -z."""

OPENCV_UP = (0.0, -1.0, 0.0)
"""The sensor's up in an OpenCV camera frame (x right, y down): slscan's range maps."""
STANFORD_UP = (0.0, 1.0, 0.0)
"""The sensor's up in a Stanford scan's frame (y up)."""

UNITS_TO_MM = {"m": 1000.0, "cm": 10.0, "mm": 1.0}



@dataclass(frozen=True, eq=False)
class RangeScan:
    """One range scan (a view's surface), in the scan's own frame.

    vertices : (n, 3) float64, mm, scan frame
    faces : (m, 3) int32 vertex indices, counter-clockwise seen from the sensor
    normals : (n, 3) float32 unit vertex normals, on the sensor's side
    quality : (n,) float32 in [0, 1], confidence used as a weight by registration and
        fusion (for loaded Stanford scans: cos(angle between normal and view direction)
        times a ramp falling to 0 at the scan's boundary)
    view_direction : (3,) float64 unit vector from the surface towards the sensor, scan
        frame. The Stanford (Cyberware) scans look along -z of their frame, so it is
        +z there (:data:`STANFORD_VIEW_DIRECTION`); for a perspective sensor it is the
        direction towards the sensor from the scan's centroid.
    name : the scan's name (the file stem when loaded)
    grid : (rows, cols) int32 or None: the vertex index of each range-grid cell, -1 where
        the cell has no sample, when the scan came from a range grid
    up_direction : (3,) float64 unit vector, scan frame: the sensor's up, the sensor held
        upright (:data:`OPENCV_UP` for slscan's range maps, :data:`STANFORD_UP` for the
        Stanford scans); it chooses which way the object frame's +Y points
        (:mod:`slscan.register.frame`)
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    quality: np.ndarray
    view_direction: np.ndarray
    name: str = ""
    grid: np.ndarray | None = field(default=None, repr=False)
    up_direction: np.ndarray = field(default_factory=lambda: np.array(OPENCV_UP), repr=False)

    def __post_init__(self) -> None:
        n = len(self.vertices)
        if np.shape(self.vertices) != (n, 3):
            raise SlscanError(
                f"scan {self.name!r}: expected (n, 3) vertices, got {np.shape(self.vertices)}"
            )
        if np.shape(self.normals) != (n, 3):
            raise SlscanError(
                f"scan {self.name!r}: expected ({n}, 3) normals, got {np.shape(self.normals)}"
            )
        if np.shape(self.quality) != (n,):
            raise SlscanError(
                f"scan {self.name!r}: expected ({n},) quality, got {np.shape(self.quality)}"
            )
        if np.ndim(self.faces) != 2 or np.shape(self.faces)[1] != 3:
            raise SlscanError(
                f"scan {self.name!r}: expected (m, 3) faces, got {np.shape(self.faces)}"
            )
        if np.shape(self.view_direction) != (3,):
            raise SlscanError(f"scan {self.name!r}: expected a (3,) view direction")
        if np.shape(self.up_direction) != (3,):
            raise SlscanError(f"scan {self.name!r}: expected a (3,) up direction")

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def transformed_vertices(self, pose: np.ndarray) -> np.ndarray:
        """(n, 3) float64 vertices mapped by the 4×4 ``pose`` (e.g. world_from_scan), mm."""
        pose = np.asarray(pose, np.float64)
        return self.vertices @ pose[:3, :3].T + pose[:3, 3]


# --- building scans ----------------------------------------------------------------------------


def scan_from_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    view_direction: np.ndarray | None = None,
    quality: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    name: str = "",
    grid: np.ndarray | None = None,
    drop_unreferenced: bool = True,
    up_direction: np.ndarray | None = None,
) -> RangeScan:
    """A :class:`RangeScan` from a triangle mesh in the scan frame.

    vertices : (n, 3) float, mm
    faces : (m, 3) int; re-wound counter-clockwise as seen from ``view_direction``
    view_direction : (3,) towards the sensor; default: the mean of the face normals
        (area-weighted), which is right for a surface seen from one side
    quality : (n,) float in [0, 1]; default: cos(angle between normal and view direction)
    normals : (n, 3); default: area-weighted vertex normals of ``faces``
    grid : (rows, cols) int index map, -1 for empty cells (re-indexed with the vertices)
    drop_unreferenced : remove vertices no face uses
    up_direction : (3,) the sensor's up in the scan frame; default :data:`OPENCV_UP`
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(f):
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        face_n = np.cross(b - a, c - a)
    else:
        face_n = np.zeros((0, 3))
    if view_direction is None:
        total = face_n.sum(axis=0)
        if not np.isfinite(total).all() or np.linalg.norm(total) == 0:
            total = np.array(STANFORD_VIEW_DIRECTION)
        view_direction = total
    d = np.asarray(view_direction, np.float64)
    d = d / np.linalg.norm(d)
    if len(f):
        flip = face_n @ d < 0
        f[flip] = f[flip][:, [0, 2, 1]]
    if normals is None:
        n = vertex_normals(v, f) if len(f) else np.tile(d, (len(v), 1))
        n[np.linalg.norm(n, axis=1) == 0] = d
    else:
        n = np.asarray(normals, np.float64)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        ok = np.isfinite(length) & (length > 0)  # a zero, NaN or infinite normal: the view direction
        n = np.where(ok, n / np.where(ok, length, 1), d)
    n[n @ d < 0] *= -1
    if quality is None:
        q = np.clip(n @ d, 0.0, 1.0)
    else:
        q = np.clip(np.asarray(quality, np.float64), 0.0, 1.0)
    keep = np.ones(len(v), bool)
    if drop_unreferenced and len(f):
        keep[:] = False
        keep[f.reshape(-1)] = True
    new = np.full(len(v), -1, np.int64)
    new[keep] = np.arange(int(keep.sum()))
    if grid is not None:
        g = np.asarray(grid, np.int64)
        grid = np.where(g >= 0, new[np.clip(g, 0, None)], -1).astype(np.int32)
    return RangeScan(
        vertices=v[keep],
        faces=new[f].astype(np.int32),
        normals=n[keep].astype(np.float32),
        quality=q[keep].astype(np.float32),
        view_direction=d,
        name=name,
        grid=grid,
        up_direction=_unit(up_direction if up_direction is not None else OPENCV_UP),
    )


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def grid_faces(
    points: np.ndarray,
    grid: np.ndarray,
    *,
    max_edge_factor: float = 4.0,
) -> np.ndarray:
    """Triangulate a range grid: two triangles per full cell quad, one for three corners.

    A quad of grid neighbours is split along its shorter diagonal; a quad with one corner
    missing gives the triangle of the other three; triangles with an edge longer than
    ``max_edge_factor`` times the median neighbour spacing are dropped (depth steps), so
    the mesh breaks at missing cells and discontinuities [1]_.

    points : (n, 3) float, mm
    grid : (rows, cols) int, vertex index per cell or -1
    Returns (m, 3) int64 vertex indices (winding not yet oriented).
    """
    g = np.asarray(grid, np.int64)
    p = np.asarray(points, np.float64)
    if g.ndim != 2 or g.shape[0] < 2 or g.shape[1] < 2:
        return np.zeros((0, 3), np.int64)
    a, b = g[:-1, :-1].ravel(), g[:-1, 1:].ravel()  # (r, c), (r, c + 1)
    c, d = g[1:, :-1].ravel(), g[1:, 1:].ravel()  # (r + 1, c), (r + 1, c + 1)
    va, vb, vc, vd = a >= 0, b >= 0, c >= 0, d >= 0
    full = va & vb & vc & vd

    def dist(i: np.ndarray, j: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p[i] - p[j], axis=1)

    split_ad = np.zeros(len(a), bool)
    split_ad[full] = dist(a[full], d[full]) <= dist(b[full], c[full])
    tris = [
        np.stack([a, c, d], 1)[full & split_ad],
        np.stack([a, d, b], 1)[full & split_ad],
        np.stack([a, c, b], 1)[full & ~split_ad],
        np.stack([b, c, d], 1)[full & ~split_ad],
        np.stack([b, c, d], 1)[~va & vb & vc & vd],
        np.stack([a, c, d], 1)[va & ~vb & vc & vd],
        np.stack([a, d, b], 1)[va & vb & ~vc & vd],
        np.stack([a, c, b], 1)[va & vb & vc & ~vd],
    ]
    tri = np.concatenate(tris)
    if len(tri) == 0:
        return tri.reshape(0, 3)
    both_h = (g[:, :-1] >= 0) & (g[:, 1:] >= 0)
    both_v = (g[:-1] >= 0) & (g[1:] >= 0)
    horizontal = dist(g[:, :-1][both_h], g[:, 1:][both_h])
    vertical = dist(g[:-1][both_v], g[1:][both_v])
    spacing = np.concatenate([horizontal, vertical])
    if len(spacing) == 0:
        return tri
    limit = max_edge_factor * float(np.median(spacing)) * math.sqrt(2.0)
    keep = np.ones(len(tri), bool)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        keep &= dist(tri[:, i], tri[:, j]) <= limit
    return tri[keep]


def boundary_ramp(grid: np.ndarray, referenced: np.ndarray, cells: float) -> np.ndarray:
    """(n,) float in (0, 1]: grid distance of each vertex to the nearest empty cell over ``cells``.

    Curless & Levoy's weight ramp [2]_: samples near a scan's edge get less weight, so
    fusing overlapping scans leaves no step where one ends.
    """
    g = np.asarray(grid)
    ramp = np.ones(len(referenced))
    if cells <= 0:
        return ramp
    used = g >= 0
    used[used] = referenced[g[used]]
    distance = ndimage.distance_transform_edt(np.pad(used, 1))[1:-1, 1:-1]
    ramp[g[used]] = np.clip(distance[used] / cells, 0.0, 1.0)
    return ramp


# --- Stanford files ----------------------------------------------------------------------------


_SOURCES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def scan_source(scan: RangeScan) -> tuple[str, str] | None:
    """(absolute path, units) of the file ``scan`` was loaded from, as it was loaded
    (:func:`load_range_scan` reads it again the same), or None for a scan made or changed
    in memory. Registration's worker processes load scans from their files by this
    rather than receiving the arrays with every pair."""
    return _SOURCES.get(scan)


def _loaded(scan: RangeScan, path: Path, units: str) -> RangeScan:
    _SOURCES[scan] = (str(path.resolve()), units)
    return scan


def load_stanford_scan(
    path: str | os.PathLike,
    *,
    units: str = "m",
    max_edge_factor: float = 4.0,
    ramp_cells: float = 8.0,
) -> RangeScan:
    """Read a Stanford range-grid PLY (``bun000.ply`` …) as a :class:`RangeScan` in mm.

    The vertices are meshed on the ``range_grid`` (row-major, ``num_rows`` × ``num_cols``
    from the header's ``obj_info``) with :func:`grid_faces`. The view direction is
    :data:`STANFORD_VIEW_DIRECTION` (+z: the scanner looks along -z of the scan frame).
    Quality is cos(normal, view direction) times a ramp over ``ramp_cells`` grid cells
    from the scan's boundary (:func:`boundary_ramp`), times the vertex ``confidence``
    when the file has one.

    Parameters
    ----------
    path : the PLY file
    units : {"m", "cm", "mm"}, the file's length unit (Stanford: metres)
    max_edge_factor : triangles with an edge longer than this many median grid spacings
        are dropped
    ramp_cells : width of the boundary weight ramp, grid cells (0: none)

    Raises
    ------
    SlscanError
        Not a PLY, no ``range_grid`` element, or no triangle can be made (naming the file).
    """
    path = Path(path)
    scale = _unit_scale(units, path)
    ply = read_ply_elements(path)
    vertex = ply.get("vertex")
    if vertex is None or not all(k in vertex for k in "xyz"):
        raise SlscanError(f"{path}: no vertex element with x, y, z; expected a Stanford range scan")
    grid_el = ply.get("range_grid")
    if grid_el is None:
        raise SlscanError(f"{path}: no range_grid element; expected a Stanford range-grid PLY")
    rows, cols = ply.info.get("num_rows"), ply.info.get("num_cols")
    lists = [v for v in grid_el.values() if isinstance(v, tuple)]
    if not lists:
        raise SlscanError(f"{path}: range_grid has no list property; expected the vertex index of each cell")
    counts, values = lists[0]
    if not isinstance(rows, int) or not isinstance(cols, int) or rows < 0 or cols < 0 or rows * cols != len(counts):
        raise SlscanError(
            f"{path}: range_grid has {len(counts)} cells but obj_info says "
            f"{rows} rows x {cols} columns"
        )
    if np.any(counts > 1):
        log.warning("%s: some grid cells hold several samples; the first is used", path)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    grid = np.where(
        counts > 0, values[np.minimum(starts, max(len(values) - 1, 0))] if len(values) else -1, -1
    )
    grid = grid.astype(np.int64).reshape(int(rows), int(cols))
    points = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64) * scale
    check_finite_vertices(points, path)
    if len(points) == 0 or np.any(grid >= len(points)):
        raise SlscanError(
            f"{path}: range_grid indexes {grid.max() + 1} vertices, the file has {len(points)}"
        )
    faces = grid_faces(points, grid, max_edge_factor=max_edge_factor)
    if len(faces) == 0:
        raise SlscanError(
            f"{path}: no triangle could be made from the range grid (empty or degenerate scan)"
        )
    direction = np.array(STANFORD_VIEW_DIRECTION)
    scan = scan_from_mesh(points, faces, view_direction=direction, name=path.stem, grid=grid,
                          up_direction=np.array(STANFORD_UP))
    referenced = np.ones(scan.n_vertices, bool)
    quality = scan.quality.astype(np.float64) * boundary_ramp(scan.grid, referenced, ramp_cells)
    if "confidence" in vertex:
        if not np.isfinite(np.asarray(vertex["confidence"], np.float64)).all():
            raise SlscanError(f"{path}: vertex confidence holds NaN or inf; expected finite weights")
        used = np.zeros(len(points), bool)
        used[faces.reshape(-1)] = True
        quality *= np.clip(vertex["confidence"][used], 0.0, 1.0)
    scan = replace(scan, quality=quality.astype(np.float32))
    if max_edge_factor == 4.0 and ramp_cells == 8.0:  # as load_range_scan reads it
        _loaded(scan, path, units)
    return scan


def load_bun_conf(path: str | os.PathLike, *, units: str = "m") -> dict[str, np.ndarray]:
    """Read a Stanford ``.conf`` file: ``{scan name: (4, 4) world_from_scan}``, mm.

    Lines ``bmesh FILE tx ty tz qx qy qz qw``; the scan name is FILE's stem. With ``R``
    the rotation of the quaternion (qx, qy, qz, qw) as written (scalar last), a scan
    point ``p`` maps to the common frame as ``Rᵀ·p + t`` (checked on the bunny: plain
    ``R·p + t`` is off by 16–129 mm), so ``world_from_scan = [[Rᵀ, t], [0, 1]]``.
    ``camera`` and other lines are ignored.

    Raises
    ------
    SlscanError
        Missing file, a malformed ``bmesh`` line, or no ``bmesh`` line (naming the file).
    """
    return {Path(file).stem: pose for _, file, pose in _conf_entries(Path(path), units)}


def _conf_entries(path: Path, units: str) -> list[tuple[int, str, np.ndarray]]:
    """(line number, FILE as written, (4, 4) world_from_scan in mm) of each ``bmesh`` line."""
    scale = _unit_scale(units, path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise SlscanError(f"{path}: pose file not found") from None
    except IsADirectoryError:
        raise SlscanError(f"{path}: is a folder; expected a pose file") from None
    except UnicodeDecodeError as exc:
        raise SlscanError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    entries: list[tuple[int, str, np.ndarray]] = []
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts or parts[0] != "bmesh":
            continue
        try:
            t = np.array([float(x) for x in parts[2:5]]) * scale
            q = np.array([float(x) for x in parts[5:9]])
        except ValueError:
            raise SlscanError(
                f"{path}:{number}: expected 'bmesh FILE tx ty tz qx qy qz qw'"
            ) from None
        if len(parts) != 9:
            raise SlscanError(f"{path}:{number}: expected 'bmesh FILE tx ty tz qx qy qz qw'")
        if not (np.isfinite(t).all() and np.isfinite(q).all()):
            raise SlscanError(
                f"{path}:{number}: the pose of {parts[1]} holds non-finite numbers; expected finite "
                "'tx ty tz qx qy qz qw'"
            )
        if np.linalg.norm(q) == 0:
            raise SlscanError(
                f"{path}:{number}: the rotation quaternion of {parts[1]} is zero; expected a unit quaternion"
            )
        pose = np.eye(4)
        pose[:3, :3] = quaternion_matrix(q).T
        pose[:3, 3] = t
        entries.append((number, parts[1], pose))
    if not entries:
        raise SlscanError(f"{path}: no 'bmesh' line; expected a Stanford .conf pose file")
    return entries


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation matrix of the quaternion ``q = (qx, qy, qz, qw)`` (scalar last)."""
    x, y, z, w = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def load_stanford_dir(
    folder: str | os.PathLike, *, conf: str = "bun.conf", units: str = "m", allow_outside: bool = False
) -> tuple[list[RangeScan], dict[str, np.ndarray]]:
    """Every scan a Stanford ``.conf`` names (in its order), and their poses (mm).

    Scan files are found relative to the folder; a ``bmesh`` line naming a file that is
    not there is an error naming the ``.conf``, the line and the file. As with a MeshLab
    project, scan files that resolve (symlinks followed) outside the folder (``../x.ply``,
    an absolute path) are refused unless ``allow_outside``, and then named in a warning.
    """
    from slscan.register.meshlab import _check_outside

    folder = Path(folder)
    path = folder / conf
    entries = _conf_entries(path, units)
    missing = [f"{path}:{number}: {file}" for number, file, _ in entries
               if not (folder / file).is_file()]
    if missing:
        raise SlscanError(
            f"{'; '.join(missing)}: scan file not found in {folder} (the .conf names "
            f"{'it' if len(missing) == 1 else 'them'}; fix the line or add the file)"
        )
    _check_outside(path, [folder / file for _, file, _ in entries], "scan", allow_outside, owner=".conf")
    poses = {Path(file).stem: pose for _, file, pose in entries}
    scans = [load_stanford_scan(folder / file, units=units) for _, file, _ in entries]
    return scans, poses


# --- synthetic scans ------------------------------------------------------------------------------


def raycasting_scene(vertices: np.ndarray, faces: np.ndarray):
    """An open3d RaycastingScene of a mesh (world frame, mm), for :func:`render_range_scan`."""
    import open3d as o3d
    import open3d.core as o3c

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3c.Tensor(np.asarray(vertices, np.float32)),
        o3c.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
    )
    return scene


def render_range_scan(
    vertices: np.ndarray | None,
    faces: np.ndarray | None,
    world_from_scan: np.ndarray,
    *,
    shape: tuple[int, int],
    pixel: float | None = None,
    focal: float | None = None,
    name: str = "",
    noise: float = 0.0,
    rng: np.random.Generator | None = None,
    max_edge_factor: float = 4.0,
    max_view_angle_deg: float = 80.0,
    ramp_cells: float = 8.0,
    scene=None,
) -> RangeScan:
    """A synthetic range scan of a triangle mesh, ray cast on a pixel grid (open3d).

    The sensor looks along -z of the scan frame, like the Stanford scanner. With
    ``pixel`` the rays are parallel (orthographic, spacing ``pixel`` mm, the grid centred
    on the scan frame's z axis; view direction +z); with ``focal`` (px) they leave the
    scan frame's origin (pinhole, principal point at the centre; view direction from the
    scan's centroid to the origin). Hits become the vertices (scan frame, mm), meshed on
    the pixel grid (:func:`grid_faces`), with faces seen at more than
    ``max_view_angle_deg`` dropped; quality as for :func:`load_stanford_scan`.

    vertices : (n, 3) float, mm, world; faces : (m, 3) int (unused when ``scene`` is given)
    world_from_scan : (4, 4) pose of the sensor frame
    shape : (rows, cols) of the pixel grid
    noise : standard deviation (mm) of Gaussian noise added along each ray
    scene : a :func:`raycasting_scene` of the mesh, to reuse it across many scans
    """
    import open3d.core as o3c

    if (pixel is None) == (focal is None):
        raise SlscanError(
            "render_range_scan: give exactly one of pixel (orthographic) or focal (pinhole)"
        )
    pose = np.asarray(world_from_scan, np.float64)
    if scene is None:
        if vertices is None or faces is None:
            raise SlscanError("render_range_scan: give the mesh (vertices, faces) or a scene")
        scene = raycasting_scene(vertices, faces)
    rows, cols = shape
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float64)
    if pixel is not None:
        bounds = scene_bounds(scene)
        far = (
            float(
                np.linalg.norm(bounds[1] - bounds[0])
                + np.linalg.norm(pose[:3, 3] - bounds.mean(axis=0))
            )
            + 100.0
        )
        origin = np.stack(
            [(c - (cols - 1) / 2) * pixel, ((rows - 1) / 2 - r) * pixel, np.full_like(r, far)], -1
        )
        direction = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origin.shape)
    else:
        origin = np.zeros((rows, cols, 3))
        direction = np.stack(
            [(c - (cols - 1) / 2) / focal, ((rows - 1) / 2 - r) / focal, -np.ones_like(r)], -1
        )
        direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    world_origin = origin @ pose[:3, :3].T + pose[:3, 3]
    world_direction = direction @ pose[:3, :3].T
    rays = np.concatenate([world_origin, world_direction], -1).astype(np.float32)
    del world_origin, world_direction
    t = scene.cast_rays(o3c.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    del rays
    hit = np.isfinite(t)
    if noise > 0:
        rng = rng or np.random.default_rng(0)
        t = t + rng.normal(0.0, noise, t.shape)
    points = (origin + direction * np.where(hit, t, 0.0)[..., None])[hit]
    grid = np.full((rows, cols), -1, np.int64)
    grid[hit] = np.arange(int(hit.sum()))
    faces_out = grid_faces(points, grid, max_edge_factor=max_edge_factor)
    if len(faces_out) == 0:
        raise SlscanError(f"render_range_scan {name!r}: the object is not in view")
    view = np.array(STANFORD_VIEW_DIRECTION) if pixel is not None else -points.mean(axis=0)
    view = view / np.linalg.norm(view)
    a, b, cc = (points[faces_out[:, i]] for i in range(3))
    face_n = np.cross(b - a, cc - a)
    centre = (a + b + cc) / 3
    toward = np.broadcast_to(view, centre.shape) if pixel is not None else -centre
    cos = np.abs(np.einsum("ij,ij->i", face_n, toward)) / (
        np.linalg.norm(face_n, axis=1) * np.linalg.norm(toward, axis=1) + 1e-300
    )
    faces_out = faces_out[cos >= math.cos(math.radians(max_view_angle_deg))]
    if len(faces_out) == 0:
        raise SlscanError(f"render_range_scan {name!r}: every face is seen at a grazing angle")
    scan = scan_from_mesh(points, faces_out, view_direction=view, name=name, grid=grid)
    ramp = boundary_ramp(scan.grid, np.ones(scan.n_vertices, bool), ramp_cells)
    return replace(scan, quality=(scan.quality * ramp).astype(np.float32))


def scene_bounds(scene) -> np.ndarray:
    """(2, 3) lower and upper corners (mm) of a RaycastingScene's geometry, to within ~10 mm.

    The scene keeps no bounds: the closest surface point to a probe far out along an
    axis is (nearly) the extreme point along it.
    """
    import open3d.core as o3c

    probes = np.concatenate([np.eye(3), -np.eye(3)]).astype(np.float32) * 1e5
    closest = scene.compute_closest_points(o3c.Tensor(probes))["points"].numpy().astype(np.float64)
    upper = np.diag(closest[:3])
    lower = np.diag(closest[3:])
    return np.stack([lower, upper])


# --- generic PLY -------------------------------------------------------------------------------


def load_range_scan(
    path: str | os.PathLike,
    *,
    units: str = "mm",
    view_direction: np.ndarray | None = None,
) -> RangeScan:
    """Read a triangle-mesh PLY (ASCII or binary) as a :class:`RangeScan`.

    Stanford range-grid files are meshed as in :func:`load_stanford_scan` (their units
    still follow ``units``). Otherwise the file needs ``vertex`` (x, y, z) and ``face``
    (``vertex_indices``; polygons are fanned) elements; ``nx ny nz`` and ``quality``
    (or ``confidence``) vertex properties are read when present. The view direction is,
    in order: the argument; a ``comment view_direction X Y Z`` header line (as
    :func:`write_range_scan` writes); for slscan range maps (``comment slscan range
    map``, sensor at the origin) the direction from the centroid to the origin; else the
    mean face normal. The scan is named by a ``comment name`` (or decode's ``comment
    view``) header line, else by the file's stem.

    Raises
    ------
    SlscanError
        Missing or malformed file, no vertices, no faces (naming the file).
    """
    path = Path(path)
    scale = _unit_scale(units, path)
    ply = read_ply_elements(path)
    if "range_grid" in ply:
        return load_stanford_scan(path, units=units)
    vertex = ply.get("vertex")
    if vertex is None or not all(k in vertex for k in "xyz"):
        raise SlscanError(f"{path}: no vertex element with x, y, z properties")
    points = np.stack([vertex[k] for k in "xyz"], axis=1).astype(np.float64) * scale
    if len(points) == 0:
        raise SlscanError(f"{path}: the PLY has no vertices; expected a range scan mesh")
    check_finite_vertices(points, path)
    face_el = ply.get("face")
    faces = np.zeros((0, 3), np.int64)
    if face_el is not None:
        prop = face_el.get("vertex_indices", face_el.get("vertex_index"))
        if prop is None:
            raise SlscanError(f"{path}: face element has no vertex_indices list")
        faces = fan_triangles(*prop)
    if len(faces) == 0:
        raise SlscanError(f"{path}: the PLY has no faces; expected a triangle mesh (range scan)")
    check_face_indices(faces, len(points), path)
    a, b, c = (points[faces[:, i]] for i in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    faces = faces[area > 0]
    if len(faces) == 0:
        raise SlscanError(f"{path}: every face is degenerate (zero area)")
    direction = view_direction
    if direction is None and ply.view_direction is not None:
        direction = ply.view_direction
    if direction is None and ply.is_slscan_range_map:
        direction = -points.mean(axis=0)
    up = ply.up_direction if ply.up_direction is not None else np.array(OPENCV_UP)
    normals = None
    if all(k in vertex for k in ("nx", "ny", "nz")):
        normals = np.stack([vertex[k] for k in ("nx", "ny", "nz")], axis=1)
        if not np.any(np.linalg.norm(normals, axis=1) > 0):
            normals = None
    quality = None
    for key in ("quality", "confidence"):
        if key in vertex:
            quality = vertex[key]
            bad = ~np.isfinite(np.asarray(quality, np.float64))
            if bad.any():
                raise SlscanError(f"{path}: {int(bad.sum())} vertices with a non-finite {key} (NaN or inf), "
                                  f"the first at index {int(np.argmax(bad))}; expected finite weights")
            break
    grid = None
    if ply.grid_shape is not None and "row" in vertex and "col" in vertex:
        rows, cols = ply.grid_shape
        grid = np.full((rows, cols), -1, np.int64)
        r, cc = vertex["row"].astype(np.int64), vertex["col"].astype(np.int64)
        ok = (r >= 0) & (r < rows) & (cc >= 0) & (cc < cols)
        grid[r[ok], cc[ok]] = np.flatnonzero(ok)
    scan = scan_from_mesh(
        points,
        faces,
        view_direction=direction,
        quality=quality,
        normals=normals,
        name=ply.name or path.stem,
        grid=grid,
        up_direction=up,
    )
    return _loaded(scan, path, units) if view_direction is None else scan


def write_range_scan(scan: RangeScan, path: str | os.PathLike) -> Path:
    """Write ``scan`` as a binary little-endian PLY that MeshLab opens, atomically.

    Vertex properties ``x y z`` (float, mm, scan frame), ``nx ny nz``, ``quality``
    (MeshLab's vertex quality) and, with a grid, ``row col`` (int); faces
    ``vertex_indices``. Header comments carry the name, view and up directions and grid size, so
    :func:`load_range_scan` reads the scan back whole.
    """
    n = scan.n_vertices
    fields = [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("nx", "<f4"),
        ("ny", "<f4"),
        ("nz", "<f4"),
        ("quality", "<f4"),
    ]
    if scan.grid is not None:
        fields += [("row", "<i4"), ("col", "<i4")]
    verts = np.empty(n, np.dtype(fields))
    for i, axis in enumerate("xyz"):
        verts[axis] = scan.vertices[:, i]
        verts["n" + axis] = scan.normals[:, i]
    verts["quality"] = scan.quality
    if scan.grid is not None:
        verts["row"] = verts["col"] = -1
        g = scan.grid
        r, c = np.nonzero(g >= 0)
        verts["row"][g[r, c]] = r
        verts["col"][g[r, c]] = c
    d = scan.view_direction
    comments = ["slscan range scan (mm, scan frame)"]
    name = " ".join(str(scan.name).split())
    if name:
        comments.append(f"name {name}")
    comments.append(f"view_direction {d[0]:.9g} {d[1]:.9g} {d[2]:.9g}")
    u = scan.up_direction
    comments.append(f"up_direction {u[0]:.9g} {u[1]:.9g} {u[2]:.9g}")
    if scan.grid is not None:
        comments.append(f"grid {scan.grid.shape[0]} {scan.grid.shape[1]}")
    return write_triangle_ply(path, verts, scan.faces, comments)


def _unit_scale(units: str, path: Path) -> float:
    try:
        return UNITS_TO_MM[units]
    except KeyError:
        raise SlscanError(
            f"{path}: unknown units {units!r}; expected one of {sorted(UNITS_TO_MM)}"
        ) from None
