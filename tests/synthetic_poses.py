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
