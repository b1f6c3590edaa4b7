"""Poses for synthetic multi-view tests (importable from every test folder: pytest puts
``tests/`` on the path)."""

from __future__ import annotations

import numpy as np


def looking_from(direction, distance: float = 0.0) -> np.ndarray:
    """world_from_scan of a sensor on the side ``direction`` (scan +z points to it),
    ``distance`` mm out along it."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, d)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(d, x), d], axis=1)
    pose[:3, 3] = d * distance
    return pose


SIX_SIDES = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
"""The six axis directions: one orthographic scan from each side."""


def sphere_scans(*, shape: tuple[int, int], pixel: float, radius: float = 20.0, resolution: int = 60):
    """Six orthographic range scans (``shape`` pixels of ``pixel`` mm, 0.05 mm noise, seeded)
    of a sphere of ``radius`` mm off the origin (so brick planes cut it off-centre):
    ([RangeScan "view0".."view5"], {name: world_from_scan})."""
    import open3d as o3d

    from slscan.register.rangescan import render_range_scan

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    v = np.asarray(sphere.vertices) + [3.1, -2.2, 1.7]
    f = np.asarray(sphere.triangles)
    scans, poses = [], {}
    for k, d in enumerate(SIX_SIDES):
        name = f"view{k}"
        poses[name] = looking_from(d)
        scans.append(render_range_scan(v, f, poses[name], shape=shape, pixel=pixel, name=name, noise=0.05,
                                       rng=np.random.default_rng(k)))
    return scans, poses
