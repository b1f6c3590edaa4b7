"""Capture over views in worker processes (issue #22 item 5): the session is the one the
acquisition driver writes, file for file."""

from __future__ import annotations

import filecmp
from pathlib import Path

import numpy as np
import pytest

from slscan.capture.session import load_session
from slscan.devices.base import DeviceError
from slscan.executor import Executor
from slscan.rig import rotation_about_axis
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor

POOL = Executor(workers=2)
ONE = Executor(workers=1)


def _same_tree(a: Path, b: Path) -> list[str]:
    """Files that differ or exist on one side only (recursively)."""
    cmp, out, todo = None, [], [(a, b, "")]
    while todo:
        x, y, where = todo.pop()
        cmp = filecmp.dircmp(x, y)
        out += [f"{where}{n}" for n in cmp.left_only + cmp.right_only]
        _, mismatch, errors = filecmp.cmpfiles(x, y, cmp.common_files, shallow=False)
        out += [f"{where}{n}" for n in mismatch + errors]
        todo += [(x / d, y / d, f"{where}{d}/") for d in cmp.common_dirs]
    return out


@pytest.mark.parametrize("sensor, lit_exposure", [
    (Sensor(), 1.0),
    (Sensor(jpeg_quality=90), 1.0),
    (Sensor(bit_depth=16, response="srgb", exposure=0.9), 0.3),  # 0.9 * 0.3 / 0.3 != 0.9
])
def test_pooled_capture_writes_the_drivers_session(tmp_path, sensor, lit_exposure):
    config = VirtualCaptureConfig(views=3, camera_scale=0.2, projector_scale=0.25, levels=6,
                                  patterns="both", sensor=sensor, lit_exposure=lit_exposure)
    pooled = capture_session(config, tmp_path / "pooled", executor=POOL)
    capture_session(config, tmp_path / "driver", executor=ONE)  # one worker: the driver
    assert [v.name for v in pooled.views] == ["view_000", "view_001", "view_002"]
    assert _same_tree(tmp_path / "pooled", tmp_path / "driver") == []
    assert len(load_session(tmp_path / "pooled").views) == 3
    assert pooled.views[2].exposure["sensor"]["exposure"] == sensor.exposure  # restored exactly


def test_pooled_capture_with_given_poses_and_progress(tmp_path):
    config = VirtualCaptureConfig(views=1, camera_scale=0.2, projector_scale=0.25, levels=6, lit_images=False)
    base = np.eye(4)
    base[2, 3] = config.rig().working_distance
    poses = []
    for angle in (0.0, 30.0):
        pose = base.copy()
        pose[:3, :3] = rotation_about_axis([0, 1, 0], np.radians(angle))
        poses.append(pose)
    labels: list[str] = []
    session = capture_session(config, tmp_path / "s", poses=poses, executor=POOL, progress=labels.append)
    assert len(labels) == 2 * len(session.views[0].images)
    assert labels[0].startswith("view_000 ") and labels[-1].startswith("view_001 ")
    for view, pose in zip(session.views, poses):
        np.testing.assert_array_equal(view.rig_from_object, pose)


def test_pooled_capture_failure_leaves_nothing(tmp_path, monkeypatch):
    """A view that fails (here the one this process renders: it takes views from the back)
    fails the capture with the view's error; nothing is left at the session's folder."""
    from slscan.virtual import device

    def broken(*args, **kwargs):
        raise DeviceError("view_001: the camera sees nothing of scene 'object'")

    monkeypatch.setattr(device, "_exposed_images", broken)
    config = VirtualCaptureConfig(views=2, camera_scale=0.2, projector_scale=0.25, levels=6, lit_images=False)
    with pytest.raises(DeviceError, match="view_001"):
        capture_session(config, tmp_path / "s", executor=POOL)
    assert list(tmp_path.iterdir()) == []  # no session, and no view a helper was still writing


def test_executor_parallel():
    assert not ONE.parallel(5)
    assert not POOL.parallel(1)
    assert POOL.parallel(2)
    assert Executor(scheduler="tcp://127.0.0.1:1").parallel(1)


class InProcessPool:
    """A fake executor: "parallel", but it renders the views here, one after another, so
    that what the workers log is seen by the test."""

    def parallel(self, n: int) -> bool:
        return True

    def start(self, n: int, modules=()) -> None:
        pass

    def map(self, fn, jobs):
        return map(fn, jobs)


def test_a_mesh_in_metres_is_reported_once(tmp_path, caplog):
    """The units guess ("taking it to be in metres") is made, and said, once: the workers get
    the units this process resolved (each said it again before)."""
    import open3d as o3d

    from slscan.virtual.device import _scene

    ball = o3d.geometry.TriangleMesh.create_sphere(radius=0.15, resolution=16)  # 0.3 units: metres
    ball.compute_vertex_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "ball.ply"), ball)
    _scene.cache_clear()
    config = VirtualCaptureConfig(scene=str(tmp_path / "ball.ply"), views=2, camera_scale=0.2, projector_scale=0.2,
                                  levels=5, lit_images=False)
    session = capture_session(config, tmp_path / "pooled", executor=InProcessPool())
    said = [r.getMessage() for r in caplog.records if "taking it to be in metres" in r.getMessage()]
    assert len(said) == 1, said
    assert len(session.views) == 2
