"""Open3D is imported only where it is used, and without Dash and Plotly (slscan._open3d).

Each check runs in a fresh interpreter: the test session has long imported Open3D.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import slscan

TOOLBOX = str(Path(slscan.__file__).parent.parent)
HEAVY = ("open3d", "dash", "plotly", "numba")  # numba: only fusion imports it, when it fuses


def _modules_after(code: str) -> set[str]:
    """Top-level names in ``sys.modules`` after running ``code`` in a fresh interpreter."""
    env = dict(os.environ, PYTHONPATH=TOOLBOX)
    out = subprocess.run(
        [sys.executable, "-c", f"{code}\nimport sys\nprint(' '.join(sorted(sys.modules)))"],
        env=env, check=True, capture_output=True, text=True,
    ).stdout
    return set(out.splitlines()[-1].split())


@pytest.mark.parametrize("module", [
    "slscan.decode.pipeline",  # what a decode worker imports
    "slscan.albedo.unshade",  # albedo rasterises with Open3D, inside the functions that do
    "slscan.virtual.device",
    "slscan.capture.driver",
    "slscan.fuse",
    "slscan.texture.bake",
    "slscan.recipe.stages",
    "slscan.executor",
    "slscan.cli",
])
def test_stage_modules_import_no_open3d(module):
    loaded = _modules_after(f"import {module}")
    assert module in loaded
    assert not loaded & set(HEAVY), f"importing {module} loads {sorted(loaded & set(HEAVY))}"


def test_open3d_comes_without_dash_and_plotly():
    loaded = _modules_after("import slscan, open3d\nopen3d.geometry.TriangleMesh.create_box()")
    assert "open3d" in loaded and "open3d.visualization" in loaded
    assert not {"dash", "plotly"} & loaded


def test_open3d_plotly_viewer_still_works_when_called():
    loaded = _modules_after(
        "import slscan, open3d as o3d\n"
        "fig = o3d.visualization.get_plotly_fig([o3d.geometry.TriangleMesh.create_box()])\n"
        "assert type(fig).__name__ == 'Figure', type(fig)\n"
        "from open3d.visualization.draw_plotly import get_max_bound\n"
        "assert get_max_bound([o3d.geometry.TriangleMesh.create_box()]).tolist() == [1, 1, 1]\n"
    )
    assert "plotly" in loaded
