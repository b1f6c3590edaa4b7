"""Importing other tools' calibrations: a known rig written in each format, read back exactly;
the kamino410 reference file; and bad inputs refused in one line naming the file and key."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from slscan.calibrate.importers import (
    KAMINO410,
    parse_keys,
    read_3dunderworld,
    read_bouguet,
    read_calibration,
    read_opencv,
    read_text,
    rigid_inverse,
)
from slscan.calibrate.io import load_calibration
from slscan.capture.multicam import load_multicam
from slscan.cli import main
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, default_rig, look_at

CAM_SIZE, PROJ_SIZE = (360, 240), (256, 192)
PROJ_DIST = (0.01, -0.02, 0.001, 0.0005, 0.003)
CM = 10.0  # files below write translations in cm


@pytest.fixture(scope="module")
def rig():
    """The paper's rig at a quarter size, the projector with distortion; camera 1 of a stereo
    pair (its own lens) where the projector is."""
    base = default_rig(scale=0.25, projector_scale=0.25)
    assert (base.camera.width, base.camera.height) == CAM_SIZE
    assert (base.projector.lens.width, base.projector.lens.height) == PROJ_SIZE
    proj = PinholeModel(*PROJ_SIZE, 464.1, 463.2, 128.3, 95.6, PROJ_DIST)
    cam1 = PinholeModel(
        *CAM_SIZE, 470.5, 471.25, 181.0, 118.5, (-0.05, 0.03, 0.0002, -0.0001, 0.001)
    )
    return base.camera, proj, cam1, base.projector.rig_from_projector


def assert_lens(lens: PinholeModel, truth: PinholeModel) -> None:
    assert lens == truth  # every intrinsic and the distortion, exactly


def assert_pose(pose: np.ndarray, truth: np.ndarray) -> None:
    np.testing.assert_allclose(pose, truth, rtol=0, atol=1e-9)


def write_fs(path: Path, items: dict, nested: str | None = None) -> Path:
    """An OpenCV FileStorage file (XML or YAML by its name) of matrices and numbers."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if nested:
        fs.startWriteStruct(nested, cv2.FileNode_MAP)
    for key, value in items.items():
        fs.write(key, np.asarray(value, float) if not isinstance(value, (int, float)) else value)
    if nested:
        fs.endWriteStruct()
    fs.release()
    return path


def write_kamino(path: Path, rig, *, units: float = 1.0, **changes) -> Path:
    cam, proj, _, rig_from_proj = rig
    proj_from_cam = rigid_inverse(rig_from_proj)
    items = {
        "img_shape": [[CAM_SIZE[1]], [CAM_SIZE[0]]],
        "rms": 0.25,
        "cam_int": cam.K,
        "cam_dist": [cam.dist],
        "proj_int": proj.K,
        "proj_dist": [proj.dist],
        "roration": proj_from_cam[:3, :3],
        "translation": proj_from_cam[:3, 3:] / units,
    }
    items.update(changes)
    return write_fs(path, {k: v for k, v in items.items() if v is not None})


def vec(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


# --- each format, a known rig ----------------------------------------------------------


def test_kamino410_layout_and_units(tmp_path, rig):
    cam, proj, _, rig_from_proj = rig
    imported = read_calibration([write_kamino(tmp_path / "result.xml", rig, units=CM)], units_mm=CM)
    assert (imported.format, imported.layout, imported.second_kind) == (
        "opencv",
        "kamino410",
        "projector",
    )
    assert imported.rms_px == 0.25 and imported.camera.size_key == "img_shape"
    cal = imported.to_calibration(projector_size=PROJ_SIZE)
    assert_lens(cal.camera, cam)
    assert_lens(cal.projector.lens, proj)
    assert_pose(cal.projector.rig_from_projector, rig_from_proj)
    assert cal.source["units_mm"] == CM and cal.residuals["imported"]["stereo_rms_px"] == 0.25


def test_yaml_with_a_key_map_both_directions(tmp_path, rig):
    cam, proj, _, rig_from_proj = rig
    items = {
        "Kc": cam.K,
        "dc": [cam.dist],
        "Kp": proj.K,
        "dp": [proj.dist],
        "Rcp": rig_from_proj[:3, :3],
        "tcp": rig_from_proj[:3, 3],
    }
    path = write_fs(tmp_path / "cal.yaml", items)
    text = "camera=Kc,camera_dist=dc,projector=Kp,projector_dist=dp,rotation=Rcp,translation=tcp"
    keys = parse_keys(text + ",direction=projector-to-camera")
    cal = read_opencv(path, keys=keys).to_calibration(
        camera_size=CAM_SIZE, projector_size=PROJ_SIZE
    )
    assert_lens(cal.camera, cam)
    assert_lens(cal.projector.lens, proj)
    assert_pose(cal.projector.rig_from_projector, rig_from_proj)
    # the documented default direction is camera-to-projector: the inverse pose
    flipped = read_opencv(path, keys=parse_keys(text)).camera_from_second
    assert_pose(flipped, rigid_inverse(rig_from_proj))


def test_opencv_stereo_one_file_two_files_and_rectification(tmp_path, rig):
    cam, _, cam1, rig_from_1 = rig
    one_from_cam = rigid_inverse(rig_from_1)
    r, t = one_from_cam[:3, :3], one_from_cam[:3, 3]
    r1, r2, p1, p2, q, *_ = cv2.stereoRectify(
        cam.K, cam.dist_array, cam1.K, cam1.dist_array, CAM_SIZE, r.copy(), t.reshape(3, 1).copy()
    )
    intrinsics = {
        "M1": cam.K,
        "D1": [cam.dist],
        "M2": cam1.K,
        "D2": [cam1.dist],
        "imageSize": list(CAM_SIZE),
    }
    extrinsics = {"R": r, "T": t, "R1": r1, "R2": r2, "P1": p1, "P2": p2, "Q": q}
    both = write_fs(tmp_path / "stereo.yml", {**intrinsics, **extrinsics})
    split = (
        write_fs(tmp_path / "intrinsics.yml", intrinsics),
        write_fs(tmp_path / "extrinsics.yml", extrinsics),
    )
    for imported in (read_opencv(both), read_calibration(split)):
        assert (imported.layout, imported.second_kind) == ("opencv-stereo", "camera")
        e0, e1 = imported.to_cameras()
        assert_lens(e0.lens, cam)
        assert_lens(e1.lens, cam1)
        assert_pose(e0.rig_from_camera, np.eye(4))
        assert_pose(e1.rig_from_camera, rig_from_1)
    edited = write_fs(tmp_path / "edited.yml", {**intrinsics, **extrinsics, "R1": r2})
    with pytest.raises(SlscanError, match="edited.yml: keys 'R1', 'R2' disagree with 'R'"):
        read_opencv(edited)
    with pytest.raises(SlscanError, match=r"intrinsics.yml: missing key 'R'"):
        read_opencv(split[0])


def test_bouguet_stereo_and_procam_forms(tmp_path, rig):
    cam, proj, cam1, rig_from_right = rig
    right_from_left = rigid_inverse(rig_from_right)
    om = cv2.Rodrigues(right_from_left[:3, :3])[0].ravel()

    def block(side: str, lens: PinholeModel, col: bool) -> str:
        sep = " ; " if col else " "
        return (
            f"%-- Focal Length:\nfc_{side} = [ {sep.join(repr(v) for v in (lens.fx, lens.fy))} ];\n"
            f"cc_{side} = [ {sep.join(repr(v) for v in (lens.cx, lens.cy))} ];\n"
            f"alpha_c_{side} = 0.000000000000000;\n"
            f"kc_{side} = [ {sep.join(repr(float(v)) for v in lens.dist)} ];\n"
            f"fc_{side}_error = [ 1.0 ; 1.0 ];\n"
        )

    stereo = tmp_path / "Calib_Results_stereo.m"
    stereo.write_text(
        "% Intrinsic and Extrinsic Camera Parameters\n\n%-- Intrinsic parameters of left camera:\n"
        + block("left", cam, True)
        + "\n%-- Intrinsic parameters of right camera:\n"
        + block("right", cam1, True)
        + "\n%-- Extrinsic parameters (position of right camera wrt left camera):\n"
        + f"%-- Rotation vector:\nom = [ {' ; '.join(repr(float(v)) for v in om)} ];\n"
        + f"%-- Translation vector:\nT = [ {' ; '.join(repr(float(v) / CM) for v in right_from_left[:3, 3])} ];\n"
        + f"\n%-- Image size:\nnx = {CAM_SIZE[0]};\nny = {CAM_SIZE[1]};\n"
    )
    imported = read_calibration([stereo], units_mm=CM)
    assert (imported.format, imported.second_kind) == ("bouguet", "camera")
    e0, e1 = imported.to_cameras()
    assert_lens(e0.lens, cam)
    assert_lens(e1.lens, cam1)
    assert_pose(e1.rig_from_camera, rig_from_right)
    procam = tmp_path / "calib.m"  # the form Moreno & Taubin's procam tool writes: row vectors
    procam.write_text(
        "% Projector-Camera Stereo calibration parameters:\n\n% Intrinsic parameters of camera:\n"
        + block("left", cam, False)
        + "\n% Intrinsic parameters of projector:\n"
        + block("right", proj, False)
        + "\n% Extrinsic parameters (position of projector wrt camera):\n"
        + f"om = [ {vec(om)} ]; % Rotation vector\nT = [ {vec(right_from_left[:3, 3])} ]; % Translation vector\n"
    )
    imported = read_bouguet(procam)
    assert imported.second_kind == "projector"
    cal = imported.to_calibration(camera_size=CAM_SIZE, projector_size=PROJ_SIZE)
    assert_lens(cal.projector.lens, proj)
    assert_pose(cal.projector.rig_from_projector, rig_from_right)
    skewed = tmp_path / "skew.m"
    skewed.write_text(
        stereo.read_text().replace("alpha_c_right = 0.000000000000000", "alpha_c_right = 0.001")
    )
    with pytest.raises(SlscanError, match="skew.m: key 'alpha_c_right' is 0.001"):
        read_bouguet(skewed)


def test_plain_text_labelled_per_device_and_bare(tmp_path, rig):
    cam, proj, _, rig_from_proj = rig
    proj_from_cam = rigid_inverse(rig_from_proj)
    one = tmp_path / "rig.txt"
    one.write_text(
        f"# camera\nK_cam:\n{vec(cam.K[0])}\n{vec(cam.K[1])}\n{vec(cam.K[2])}\ndist_cam = [{vec(cam.dist)}]\n"
        f"K_proj: {vec(proj.K)}\ndist_proj: {', '.join(repr(v) for v in proj.dist)}\n"
        f"R: {vec(proj_from_cam[:3, :3])}\nT: {vec(proj_from_cam[:3, 3])}\nsize_cam: {CAM_SIZE[0]} {CAM_SIZE[1]}\n"
    )
    imported = read_text(one)
    assert (imported.layout, imported.second_kind) == ("text camera+projector", "projector")
    cal = imported.to_calibration(projector_size=PROJ_SIZE)
    assert_lens(cal.camera, cam)
    assert_lens(cal.projector.lens, proj)
    assert_pose(cal.projector.rig_from_projector, rig_from_proj)
    # one file per device: the camera's without a pose, the projector's R, T from the camera
    (tmp_path / "cam.txt").write_text(f"K\n{vec(cam.K)}\nD: {vec(cam.dist)}\n")
    (tmp_path / "proj.txt").write_text(
        f"{vec(proj.K)}\n{vec(proj.dist)}\n{vec(proj_from_cam[:3, :3])}\n"
        f"{vec(proj_from_cam[:3, 3] / CM)}\n"
    )  # bare numbers, in cm
    pair = read_calibration([tmp_path / "cam.txt", tmp_path / "proj.txt"], units_mm=CM)
    assert pair.second_kind is None  # plain text does not say: the CLI asks for --second
    cal = pair.to_calibration(camera_size=CAM_SIZE, projector_size=PROJ_SIZE)
    assert_lens(cal.camera, cam)
    assert_lens(cal.projector.lens, proj)
    assert_pose(cal.projector.rig_from_projector, rig_from_proj)


def test_3dunderworld_pair_by_the_board(tmp_path, rig):
    cam, _, cam1, rig_from_1 = rig
    cam_from_board = look_at([100.0, -50.0, 0.0], [0.0, 0.0, 900.0])  # any board pose
    cam_from_board = rigid_inverse(cam_from_board)
    one_from_board = rigid_inverse(rig_from_1) @ cam_from_board
    for name, lens, pose in (("camera1", cam, cam_from_board), ("camera2", cam1, one_from_board)):
        (tmp_path / name).mkdir()
        write_fs(
            tmp_path / name / "calib.xml",
            {
                "Calibrated": 1,
                "Matrix": lens.K,
                "Distortion": [lens.dist],
                "Translation": pose[:3, 3:],
                "Rotation": pose[:3, :3],
                "Height": CAM_SIZE[1],
                "Width": CAM_SIZE[0],
            },
            nested="Camera",
        )
        out = tmp_path / name / "output"  # the text files the tool exports (tab-separated)
        out.mkdir()
        for file, value in (
            ("cam_matrix.txt", lens.K),
            ("cam_distortion.txt", [lens.dist]),
            ("cam_rotation_matrix.txt", pose[:3, :3]),
            ("cam_trans_vectror.txt", pose[:3, 3:]),
        ):
            (out / file).write_text(
                "".join(
                    "\t".join(repr(float(v)) for v in row) + "\t\n" for row in np.atleast_2d(value)
                )
            )
    xmls = [tmp_path / "camera1" / "calib.xml", tmp_path / "camera2" / "calib.xml"]
    texts = [tmp_path / "camera1" / "output", tmp_path / "camera2" / "output"]
    for imported, sizes in (
        (read_calibration(xmls), (None, None)),
        (read_3dunderworld(*texts), (CAM_SIZE,) * 2),
    ):
        assert imported.format == "3dunderworld" and imported.second_kind == "camera"
        e0, e1 = imported.to_cameras(sizes=sizes)
        assert_lens(e0.lens, cam)
        assert_lens(e1.lens, cam1)
        assert_pose(e1.rig_from_camera, rig_from_1)


def test_distortion_forms(tmp_path, rig):
    cam = rig[0]
    for n in (4, 8, 14):
        d = np.zeros(n)
        d[: min(n, 5)] = cam.dist[: min(n, 5)]
        path = write_kamino(tmp_path / f"d{n}.xml", rig, cam_dist=[d])
        expected = cam.dist if n > 4 else (*cam.dist[:4], 0.0)
        assert read_opencv(path).camera.dist == expected
    d8 = np.array([*cam.dist, 0.001, 0, 0])
    with pytest.raises(
        SlscanError, match=r"d8.xml: key 'cam_dist' has non-zero terms beyond k3 \(0.001, 0, 0\)"
    ):
        read_opencv(write_kamino(tmp_path / "d8.xml", rig, cam_dist=[d8]))


# --- the real kamino410 file ------------------------------------------------------------


def test_kamino410_reference_round_trip(shared_data, tmp_path):
    path = shared_data / "procam_graycode_kamino410" / "sample_data" / "calibration_result.xml"
    if not path.is_file():
        pytest.skip(f"kamino410's calibration_result.xml not found at {path}")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    truth = {
        k: fs.getNode(k).mat()
        for k in ("cam_int", "cam_dist", "proj_int", "proj_dist", "roration", "translation")
    }
    fs.release()
    out = tmp_path / "ref.json"
    assert (
        main(
            ["calibrate", "--import", str(path), "--projector-size", "1024x768", "--out", str(out)]
        )
        == 0
    )
    cal = load_calibration(out)
    assert (cal.camera.width, cal.camera.height) == (1280, 1024)
    np.testing.assert_array_equal(cal.camera.K, truth["cam_int"])
    np.testing.assert_array_equal(cal.projector.lens.K, truth["proj_int"])
    assert cal.camera.dist == tuple(truth["cam_dist"].ravel())
    assert cal.projector.lens.dist == tuple(truth["proj_dist"].ravel())
    proj_from_cam = rigid_inverse(cal.projector.rig_from_projector)
    np.testing.assert_allclose(proj_from_cam[:3, :3], truth["roration"], atol=1e-9)
    np.testing.assert_allclose(proj_from_cam[:3, 3], truth["translation"].ravel(), atol=1e-9)
    # and the same file through the key map the docs give, written out in full
    keys = (
        "camera=cam_int,camera_dist=cam_dist,projector=proj_int,projector_dist=proj_dist,"
        "rotation=roration,translation=translation,direction=camera-to-projector,camera_shape=img_shape"
    )
    again = read_opencv(path, keys=parse_keys(keys)).to_calibration(projector_size=(1024, 768))
    assert again.camera == cal.camera and again.projector == cal.projector
    assert read_opencv(path, keys=KAMINO410).layout == "kamino410"


# --- the command line -------------------------------------------------------------------


def write_session(
    folder: Path, camera: tuple[int, int], projector: tuple[int, int], patterns: int = 2
) -> Path:
    """A capture session with no views: only its sizes and pattern set matter here."""
    folder.mkdir(parents=True)
    pats = [
        {
            "id": f"gray_x_{i:02d}",
            "family": "gray",
            "width": projector[0],
            "height": projector[1],
            "axis": "columns",
        }
        for i in range(patterns)
    ]
    (folder / "session.json").write_text(
        json.dumps(
            {
                "format": "slscan.capture-session",
                "version": 1,
                "camera": {"width": camera[0], "height": camera[1]},
                "projector": {"width": projector[0], "height": projector[1]},
                "patterns": pats,
                "views": [],
            }
        )
    )
    return folder


def refused(argv: list, capsys, *expected: str, nothing_at: Path) -> str:
    capsys.readouterr()  # what earlier commands printed
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("slscan: error:"), err
    for text in expected:
        assert text in err, err
    assert not nothing_at.exists(), f"{nothing_at} was written"
    assert not list(nothing_at.parent.glob(f".{nothing_at.name}*")), "a partial output was left"
    return err


def test_cli_procam_against_a_session(tmp_path, rig, capsys):
    _, proj, _, rig_from_proj = rig
    xml = write_kamino(tmp_path / "result.xml", rig)
    session = write_session(tmp_path / "session", CAM_SIZE, PROJ_SIZE)
    out = tmp_path / "rig.json"
    assert (
        main(["calibrate", "--import", str(xml), "--session", str(session), "--out", str(out)]) == 0
    )
    cal = load_calibration(out)
    assert_lens(cal.projector.lens, proj)
    assert_pose(cal.projector.rig_from_projector, rig_from_proj)
    # the old spelling: the session as SESSION, --import-xml
    old = tmp_path / "old.json"
    assert main(["calibrate", str(session), "--import-xml", str(xml), "--out", str(old)]) == 0
    assert load_calibration(old).camera == cal.camera
    small = write_session(tmp_path / "small", (180, 120), PROJ_SIZE)
    refused(
        ["calibrate", "--import", xml, "--session", small, "--out", tmp_path / "x.json"],
        capsys,
        "result.xml: key 'img_shape' says the camera is 360x240",
        "small/session.json: key 'camera'",
        "180x120",
        nothing_at=tmp_path / "x.json",
    )
    other = write_session(tmp_path / "other", CAM_SIZE, (512, 384))
    refused(
        [
            "calibrate",
            "--import",
            xml,
            "--session",
            other,
            "--projector-size",
            "256x192",
            "--out",
            tmp_path / "x.json",
        ],
        capsys,
        "--projector-size says the projector is 256x192",
        "other/session.json: key 'projector'",
        "512x384",
        nothing_at=tmp_path / "x.json",
    )


def test_cli_stereo_writes_cameras_json(tmp_path, rig, capsys):
    cam, _, cam1, rig_from_1 = rig
    one_from_cam = rigid_inverse(rig_from_1)
    yml = write_fs(
        tmp_path / "stereo.yml",
        {
            "M1": cam.K,
            "D1": [cam.dist],
            "M2": cam1.K,
            "D2": [cam1.dist],
            "R": one_from_cam[:3, :3],
            "T": one_from_cam[:3, 3] / CM,
        },
    )
    two = tmp_path / "two"
    write_session(two / "cam0", CAM_SIZE, PROJ_SIZE)
    write_session(two / "cam1", CAM_SIZE, PROJ_SIZE)
    assert main(["calibrate", "--import", str(yml), "--units-mm", str(CM), "--out", str(two)]) == 0
    multi = load_multicam(two, validate=False)
    assert_lens(multi.cameras[1].lens, cam1)
    assert_pose(multi.cameras[1].rig_from_camera, rig_from_1)
    assert "stereo.yml" in multi.calibration_source
    refused(
        ["calibrate", "--import", yml, "--out", two],
        capsys,
        "cameras.json: exists",
        nothing_at=tmp_path / "nothing",
    )
    odd = tmp_path / "odd"
    write_session(odd / "cam0", CAM_SIZE, PROJ_SIZE)
    write_session(odd / "cam1", CAM_SIZE, PROJ_SIZE, patterns=3)
    refused(
        ["calibrate", "--import", yml, "--session", odd, "--out", tmp_path / "new"],
        capsys,
        "cameras.json: cameras 'cam0' and 'cam1' have different pattern sets",
        nothing_at=tmp_path / "new",
    )
    small = tmp_path / "small"
    write_session(small / "cam0", CAM_SIZE, PROJ_SIZE)
    write_session(small / "cam1", (180, 120), PROJ_SIZE)
    refused(
        [
            "calibrate",
            "--import",
            yml,
            "--session",
            small,
            "--camera-size",
            "360x240",
            "--out",
            tmp_path / "new",
        ],
        capsys,
        "--camera-size says the camera is 360x240",
        "cam1/session.json: key 'camera' says 180x120",
        nothing_at=tmp_path / "new",
    )


@pytest.mark.parametrize(
    ("change", "keys", "expected"),
    [
        (
            {},
            (
                "camera=cam_int,camera_dist=cam_dist,projector=proj_int,"
                "projector_dist=proj_distortion,rotation=roration,translation=translation"
            ),
            "missing key 'proj_distortion'",
        ),
        ({"roration": np.diag([1.0, 1.0, 1.1])}, None, "key 'roration' is not a rotation"),
        ({"cam_dist": [[np.nan, 0, 0, 0, 0]]}, None, "key 'cam_dist' holds non-finite numbers"),
        (
            {"proj_int": [[400.0, 2.0, 128], [0, 400, 96], [0, 0, 1]]},
            None,
            "key 'proj_int' has a skew",
        ),
        (
            {"translation": [1.0, 2.0]},
            None,
            "key 'translation' has the wrong size: expected 3 values, got 2",
        ),
    ],
    ids=["keymap-missing-key", "not-a-rotation", "nan", "skew", "wrong-size"],
)
def test_cli_bad_files_are_refused_naming_file_and_key(
    tmp_path, rig, capsys, change, keys, expected
):
    xml = write_kamino(tmp_path / "result.xml", rig, **change)
    argv = [
        "calibrate",
        "--import",
        xml,
        "--projector-size",
        "256x192",
        "--out",
        tmp_path / "rig.json",
    ]
    refused(
        argv + (["--keys", keys] if keys else []),
        capsys,
        "result.xml",
        expected,
        nothing_at=tmp_path / "rig.json",
    )


def test_cli_unknown_format_and_ambiguous_pairs(tmp_path, rig, capsys):
    junk = tmp_path / "calib.dat"
    junk.write_text("{ not a calibration }\n")
    refused(
        ["calibrate", "--import", junk, "--out", tmp_path / "rig.json"],
        capsys,
        "calib.dat",
        "tried OpenCV FileStorage",
        "Bouguet",
        "plain text",
        nothing_at=tmp_path / "rig.json",
    )
    cam, proj, _, _ = rig
    (tmp_path / "a.txt").write_text(f"K: {vec(cam.K)}\n")
    (tmp_path / "b.txt").write_text(f"K: {vec(proj.K)}\nR: 0 0 0\nT: 100 0 0\n")
    refused(
        [
            "calibrate",
            "--import",
            tmp_path / "a.txt",
            tmp_path / "b.txt",
            "--out",
            tmp_path / "rig.json",
        ],
        capsys,
        "a.txt, ",
        "b.txt",
        "--second",
        nothing_at=tmp_path / "rig.json",
    )
    assert (
        main(
            [
                "calibrate",
                "--import",
                str(tmp_path / "a.txt"),
                str(tmp_path / "b.txt"),
                "--second",
                "projector",
                "--camera-size",
                "360x240",
                "--projector-size",
                "256x192",
                "--out",
                str(tmp_path / "rig.json"),
            ]
        )
        == 0
    )
    cal = load_calibration(tmp_path / "rig.json")
    assert_pose(
        cal.projector.rig_from_projector,
        rigid_inverse(np.array([[1, 0, 0, 100], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])),
    )


def test_parse_keys_refuses_what_it_cannot_use():
    for text, message in (
        ("camera=K,projector=P,camera2=Q", "not both"),
        ("camera=K,lens=L", "unknown role 'lens'"),
        (
            "camera=K,projector=P,direction=camera-to-camera2",
            "does not fit a key map with projector",
        ),
        ("projector=P", "name the camera's matrix"),
        ("camera=K,direction=sideways", "direction 'sideways' is not one of"),
    ):
        with pytest.raises(SlscanError, match=message):
            parse_keys(text)
    assert parse_keys("camera=K").direction == "world-to-camera"


def test_a_recognised_layout_names_its_missing_key(tmp_path, rig):
    path = write_kamino(tmp_path / "result.xml", rig, proj_dist=None)
    with pytest.raises(SlscanError, match=r"result.xml: missing key 'proj_dist'"):
        read_calibration([path])
