"""Another lab's captures and calibration files to range maps, through the commands a user types.

Issue #31's "done when": JPEG folders as a 3DUNDERWORLD-style tool writes them (white, black,
then column and row (pattern, inverse) pairs, ``0000.jpg`` ...), one camera's folder
missing four images, a ``calib/`` folder of board shots beside the data set, and the
lab's own calibration files (3DUNDERWORLD's per-camera ``calib.xml``; kamino410's
camera-projector XML) go through ``slscan import``, ``slscan calibrate --import`` and
``slscan decode`` — one camera and two — with no Python. The captures are the virtual
rig's (two cameras about 0.9 m apart), so the range maps are measured against the truth.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from slscan.calibrate.io import Calibration, export_opencv_xml
from slscan.cli import main
from slscan.decode.rangemap import read_ply
from slscan.fsio import read_png
from slscan.rig import transform_points
from slscan.virtual.device import VirtualCaptureConfig
from slscan.virtual.multicam import capture_multicam
from slscan.virtual.scenes import scene_by_name

SCALE = 0.25


def _true_distance(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = scene_by_name("object")
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(transform_points(pose, scene.vertices).astype(np.float32)),
                     o3d.core.Tensor(scene.triangles.astype(np.uint32)))
    return rs.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def _write_fs(path, items: dict, nested: str) -> None:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.startWriteStruct(nested, cv2.FileNode_MAP)
    for key, value in items.items():
        fs.write(key, value if isinstance(value, (int, float)) else np.asarray(value, float))
    fs.endWriteStruct()
    fs.release()


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """The lab's folders: ``camK/dataset1/NNNN.jpg`` and ``camK/calib/``, ``calibration/``."""
    root = tmp_path_factory.mktemp("lab")
    config = VirtualCaptureConfig(patterns="gray", gray_rows=True, lit_images=False,
                                  camera_scale=SCALE, projector_scale=SCALE)
    multi = capture_multicam(config, root / "virtual")
    board_from_rig = np.eye(4)
    board_from_rig[:3, 3] = [40.0, -25.0, -900.0]  # the tool calibrates each camera against a board
    for k, (cam, session) in enumerate(zip(multi.cameras, multi.sessions)):
        view = session.views[0]
        order = ["white", "black"]
        for axis in ("col", "row"):
            bits = sorted(p.params["bit"] for p in session.patterns if p.id.startswith(f"gray-{axis}-")
                          and not p.params["inverse"])
            order += [f"gray-{axis}-{b:02d}{inv}" for b in bits for inv in ("", "-inv")]
        if k == 1:
            order = order[:-4]  # the last two row bits never captured: four images missing
        data = root / f"cam{k}" / "dataset1"
        data.mkdir(parents=True)
        for i, pid in enumerate(order):
            image = read_png(session.image_path(view, view.image_for(pid)))
            cv2.imwrite(str(data / f"{i:04d}.jpg"), image[..., ::-1] if image.ndim == 3 else image,
                        [cv2.IMWRITE_JPEG_QUALITY, 95])
        calib = root / f"cam{k}" / "calib"  # board shots: not a view of the data set
        calib.mkdir()
        for i in range(3):
            cv2.imwrite(str(calib / f"{i:04d}.jpg"), np.full((40, 60), 128, np.uint8))  # named like the data
        camera_from_board = np.linalg.inv(board_from_rig @ cam.rig_from_camera)
        (root / "calibration").mkdir(exist_ok=True)
        _write_fs(root / "calibration" / f"camera{k + 1}.xml",
                  {"Calibrated": 1, "Matrix": cam.lens.K, "Distortion": [list(cam.lens.dist)],
                   "Rotation": camera_from_board[:3, :3], "Translation": camera_from_board[:3, 3:],
                   "Height": cam.lens.height, "Width": cam.lens.width}, "Camera")
    truth = multi.sessions[0].calibration  # camera 0 and the projector, as kamino410's tool writes them
    export_opencv_xml(Calibration(camera=truth.camera, projector_size=multi.sessions[0].projector_size,
                                  projector=truth.projector), root / "calibration" / "procam.xml")
    return root, multi


def test_two_cameras_from_the_labs_folders_and_calibration_files(lab, tmp_path, caplog):
    root, multi = lab
    w, h = multi.sessions[0].projector_size
    scan = tmp_path / "scan"
    for k in (0, 1):
        args = ["import", str(root / f"cam{k}"), "--preset", "3dunderworld", "--rotation", "0",
                "--projector", f"{w}x{h}", "--out", str(scan / f"cam{k}"), "--quiet"]
        assert main(args + (["--missing-bits", "drop"] if k else [])) == 0
    assert any("calib/" in r.getMessage() for r in caplog.records)  # board shots skipped, and said so
    assert main(["calibrate", "--import", str(root / "calibration" / "camera1.xml"),
                 str(root / "calibration" / "camera2.xml"), "--out", str(scan)]) == 0
    cameras = json.loads((scan / "cameras.json").read_text())
    assert [c["session"] for c in cameras["cameras"]] == ["cam0", "cam1"]
    assert main(["decode", str(scan), "--out", str(tmp_path / "maps"), "--quiet"]) == 0
    plys = sorted((tmp_path / "maps").rglob("*.ply"))
    stereo = [p for p in plys if "stereo" in str(p)]
    assert stereo, plys
    rm = read_ply(stereo[0])
    d = _true_distance(rm.vertices, multi.sessions[0].views[0].rig_from_object)
    # codes 4 rows apart in camera 1 (two bits missing), JPEG, a quarter of the paper's size (a
    # camera pixel spans 2.8 mm): matched and meshed, within a pixel's footprint
    assert len(rm.vertices) > 500 and np.median(d) < 1.0 and np.percentile(d, 95) < 3.0


def test_one_camera_from_the_labs_folder_and_calibration_file(lab, tmp_path):
    root, multi = lab
    w, h = multi.sessions[0].projector_size
    scan, rig = tmp_path / "scan", tmp_path / "rig.json"
    assert main(["import", str(root / "cam0"), "--preset", "3dunderworld", "--rotation", "0",
                 "--projector", f"{w}x{h}", "--out", str(scan), "--quiet"]) == 0
    assert main(["calibrate", "--import", str(root / "calibration" / "procam.xml"), "--session", str(scan),
                 "--out", str(rig)]) == 0
    assert main(["decode", str(scan), "--calibration", str(rig), "--out", str(tmp_path / "maps"),
                 "--quiet"]) == 0
    rm = read_ply(next((tmp_path / "maps").glob("*.ply")))
    d = _true_distance(rm.vertices, multi.sessions[0].views[0].rig_from_object)
    assert len(rm.vertices) > 2000 and np.median(d) < 0.3 and np.percentile(d, 95) < 1.5
