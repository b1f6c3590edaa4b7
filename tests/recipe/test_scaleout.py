"""`slscan run --workers/--scheduler`: the stages that split their work (fuse and simplify in
bricks) hand it to the run's executor, with the same result as in one process."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_poses import sphere_scans

from slscan.errors import SlscanError
from slscan.executor import Executor
from slscan.fuse import FuseConfig, fuse_scans, read_mesh
from slscan.recipe.runner import parse_recipe, run_recipe
from slscan.simplify_bricks import simplify_bricks

VOXEL = 0.8


class RecordingExecutor:
    """The run's executor (two local processes), noting which task function each map ran."""

    def __init__(self, inner: Executor) -> None:
        self.inner, self.calls = inner, []

    def map(self, fn, items):
        items = list(items)
        self.calls.append((fn.__name__, len(items)))
        return self.inner.map(fn, items)

    def __getattr__(self, name):
        return getattr(self.inner, name)


@pytest.fixture(scope="module")
def aligned(tmp_path_factory):
    """Six orthographic range scans of a 20 mm sphere, written as an aligned set (.mlp)."""
    from slscan.register.meshlab import write_scan_project

    scans, poses = sphere_scans(shape=(64, 64), pixel=0.8, resolution=40)
    folder = write_scan_project(tmp_path_factory.mktemp("aligned") / "aligned", scans, poses)
    return folder.parent if folder.suffix == ".mlp" else folder, scans, poses


def _recipe(**simplify):
    return parse_recipe({"recipe": {"stages": ["register", "fuse", "simplify"]},
                         "fuse": {"voxel_size": VOXEL, "brick_size": 12.8},
                         "simplify": {"faces": 600, **simplify}}, where="r.toml")


def test_fuse_and_simplify_bricks_run_on_the_runs_executor(aligned, tmp_path):
    folder, _, _ = aligned
    executor = RecordingExecutor(Executor(workers=2))
    runs = run_recipe(_recipe(bricks=8), tmp_path / "run", given={"aligned": folder}, executor=executor)
    assert [r.stage for r in runs if r.ran] == ["fuse", "simplify"]
    names = dict(executor.calls)
    assert names.get("_fuse_brick", 0) > 8 and names.get("_simplify_brick", 0) == 8, executor.calls
    # the same meshes as in one process
    # the bricks stream the mesh to disk, brick by brick: the same mesh up to the order
    from slscan.fuse import canonical_order

    fused = canonical_order(read_mesh(tmp_path / "run" / "fuse" / "mesh.ply"))
    from slscan.register.meshlab import load_scan_project

    single = fuse_scans(*load_scan_project(folder / "aligned.mlp"), config=FuseConfig(voxel_size=VOXEL)).mesh
    np.testing.assert_array_equal(fused.faces, single.faces)
    np.testing.assert_allclose(fused.vertices, single.vertices, rtol=0, atol=1e-5)
    simplified = read_mesh(tmp_path / "run" / "simplify" / "mesh.ply")
    simplify_bricks(tmp_path / "run" / "fuse" / "mesh.ply", tmp_path / "one.ply", 600, bricks=8)
    one = read_mesh(tmp_path / "one.ply")
    np.testing.assert_array_equal(simplified.faces, one.faces)
    np.testing.assert_array_equal(simplified.vertices, one.vertices)
    summary = next(r for r in runs if r.stage == "simplify").summary
    assert summary["bricks"] == 8 and summary["faces"] == one.n_faces
    assert (tmp_path / "run" / "simplify" / "mesh.mlp").is_file()
    assert not list((tmp_path / "run").rglob(".bricks-*"))  # no scratch left


def test_without_bricks_simplify_stays_in_core_on_a_small_mesh(aligned, tmp_path):
    folder, _, _ = aligned
    executor = RecordingExecutor(Executor(workers=1))
    run_recipe(_recipe(max_memory="4GiB"), tmp_path / "run", given={"aligned": folder}, executor=executor)
    assert "_simplify_brick" not in dict(executor.calls)
    assert read_mesh(tmp_path / "run" / "simplify" / "mesh.ply").n_faces <= 620


@pytest.mark.parametrize("table, message", [
    ({"max_memory": "lots"}, "r.toml: [simplify].max_memory: 'lots': expected a size such as 4GiB or 512MiB"),
    ({"max_memory": 0}, "r.toml: [simplify].max_memory: 0.0: expected a size such as 4GiB or 512MiB"),
    ({"brick": -3.0}, "r.toml: [simplify].brick: expected a positive brick edge in mm, got -3.0"),
    ({"bricks": 0}, "r.toml: [simplify].bricks: expected at least 1, got 0"),
    ({"bricks": 8, "method": "quadric"}, "r.toml: [simplify].bricks: simplifying in bricks needs method"),
])
def test_a_bad_simplify_key_is_named(table, message):
    with pytest.raises(SlscanError) as info:
        _recipe(**table)
    assert str(info.value).startswith(message)
