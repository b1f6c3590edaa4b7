"""Bad inputs end in one ``slscan: error:`` line naming the file and what was expected,
exit 2, and write nothing (or, where the input is usable, in a warning naming the problem)."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from slscan.cli import main
from slscan.virtual.device import VirtualCaptureConfig, capture_session
from slscan.virtual.sensor import Sensor

# --- inputs built once ------------------------------------------------------------------


def _small_session(folder: Path, *, lit_images: bool) -> Path:
    """A noise-free 2-view Gray-code capture of the figurine at a fifth of the paper's size."""
    config = VirtualCaptureConfig(
        scene="object", views=2, patterns="gray", camera_scale=0.2, projector_scale=0.2,
        lit_images=lit_images, sensor=Sensor(noise=False),
    )
    capture_session(config, folder / "session")
    return folder / "session"


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _small_session(tmp_path_factory.mktemp("bad_inputs"), lit_images=False)


@pytest.fixture
def session(session_dir: Path, tmp_path: Path) -> Path:
    """A private copy of the session, free to doctor."""
    return Path(shutil.copytree(session_dir, tmp_path / "session"))


def sphere(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """A UV sphere of radius 50 mm: (v, 3) float64 vertices, (f, 3) int faces."""
    theta, phi = np.meshgrid(np.linspace(0.2, np.pi - 0.2, n), np.linspace(0, 2 * np.pi, 2 * n, endpoint=False))
    v = 50 * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    faces = []
    for i in range(2 * n):
        for j in range(n - 1):
            a, b = i * n + j, ((i + 1) % (2 * n)) * n + j
            faces += [(a, b, a + 1), (b, b + 1, a + 1)]
    return v, np.array(faces)


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray, *, binary: bool = False) -> Path:
    """A plain triangle-mesh PLY (float x, y, z; uchar/int vertex_indices)."""
    head = (
        f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    if binary:
        tri = np.empty(len(faces), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
        tri["n"], tri["i"] = 3, faces
        body = np.asarray(vertices, "<f4").tobytes() + tri.tobytes()
    else:
        body = "".join(f"{x} {y} {z}\n" for x, y, z in vertices).encode()
        body += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces).encode()
    path.write_bytes(head.encode() + body)
    return path


def nan_sphere(tmp_path: Path, name: str = "nan.ply", *, binary: bool = False) -> Path:
    v, f = sphere()
    v[[5, 9]] = [np.nan, 0, 0], [np.inf, 1, 1]
    return write_ply(tmp_path / name, v, f, binary=binary)


def write_mlp(path: Path, files: list[str], matrix: str = "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1") -> Path:
    meshes = "".join(
        f'<MLMesh label="{Path(f).stem}" filename="{f}"><MLMatrix44>{matrix}</MLMatrix44></MLMesh>' for f in files
    )
    path.write_text(f"<!DOCTYPE MeshLabDocument>\n<MeshLabProject><MeshGroup>{meshes}</MeshGroup></MeshLabProject>\n")
    return path


def run(argv: list, capsys) -> tuple[int, str, str]:
    """Run the CLI; return (exit code, the error line or '', all of stderr, one line per record)."""
    code = main([str(a) for a in argv])
    err = " ".join(capsys.readouterr().err.split())
    errors = re.findall(r"slscan: error:", err)
    assert len(errors) <= 1, err
    line = err[err.index("slscan: error:"):] if errors else ""
    return code, line, err


def assert_refused(argv: list, capsys, *expected: str, nothing_at: Path | None = None) -> str:
    code, line, err = run(argv, capsys)
    assert code == 2, err
    assert line, err
    assert "Traceback" not in err
    for text in expected:
        assert text in line, line
    if nothing_at is not None:
        assert not nothing_at.exists(), f"{nothing_at} was written"
        assert not list(nothing_at.parent.glob(f".{nothing_at.name}*")), "a partial output was left"
    return line


def edit_session(session: Path, change) -> None:
    meta = session / "session.json"
    d = json.loads(meta.read_text())
    change(d)
    meta.write_text(json.dumps(d))


# --- capture sessions -------------------------------------------------------------------


@pytest.mark.parametrize("command", ["info", "decode"])
@pytest.mark.parametrize("where", ["relative", "absolute", "symlink", "view-name"])
def test_image_outside_the_session_is_refused(session, tmp_path, capsys, command, where):
    outside = tmp_path / "outside.png"
    shutil.copy(session / "view_000" / "00_white.png", outside)
    if where == "relative":
        edit_session(session, lambda d: d["views"][0]["images"][0].update(file="../../outside.png"))
    elif where == "absolute":
        edit_session(session, lambda d: d["views"][0]["images"][0].update(file=str(outside)))
    elif where == "symlink":
        (session / "view_000" / "00_white.png").unlink()
        os.symlink(outside, session / "view_000" / "00_white.png")
    else:
        shutil.copytree(session / "view_000", tmp_path / "elsewhere")
        edit_session(session, lambda d: d["views"][0].update(name="../elsewhere"))
    argv = [command, session] + (["--out", tmp_path / "out"] if command == "decode" else [])
    assert_refused(argv, capsys, "session.json", "outside the session folder", nothing_at=tmp_path / "out")


@pytest.mark.parametrize("command", ["info", "decode"])
@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        ("folder", "is a folder; expected a PNG image"),
        ("truncated", "PNG file is truncated"),
        ("corrupted", "PNG file is corrupted"),
        ("not-png", "not a PNG file"),
    ],
)
def test_damaged_png_is_refused(session, tmp_path, capsys, command, damage, expected):
    png = session / "view_001" / "02_gray-col-00.png"
    data = png.read_bytes()
    png.unlink()
    if damage == "folder":
        png.mkdir()
    elif damage == "truncated":
        png.write_bytes(data[: len(data) // 2])
    elif damage == "corrupted":
        png.write_bytes(data[:60] + bytes(b ^ 0xFF for b in data[60:70]) + data[70:])
    else:
        png.write_bytes(b"GIF89a" + data[6:])
    argv = [command, session] + (["--out", tmp_path / "out"] if command == "decode" else [])
    assert_refused(argv, capsys, "02_gray-col-00.png", expected, nothing_at=tmp_path / "out")


@pytest.mark.parametrize("command", ["info", "decode"])
def test_session_without_views_is_refused(session, tmp_path, capsys, command):
    edit_session(session, lambda d: d.update(views=[]))
    argv = [command, session] + (["--out", tmp_path / "out"] if command == "decode" else [])
    assert_refused(argv, capsys, "session.json", "no views", nothing_at=tmp_path / "out")


@pytest.mark.parametrize("text", ['{"format": "slscan.capture-session", "vers', "", "[1, 2]"])
def test_malformed_session_json_is_refused(session, tmp_path, capsys, text):
    (session / "session.json").write_text(text)
    assert_refused(["decode", session, "--out", tmp_path / "out"], capsys, "session.json", nothing_at=tmp_path / "out")


def _blank(session: Path, view: str, value: int) -> None:
    import cv2

    for png in (session / view).glob("*.png"):
        image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(png), np.full_like(image, value))


@pytest.mark.parametrize(("value", "why"), [(0, "no lit pixels"), (255, "saturated")])
def test_unusable_view_is_a_warning_naming_it(session, tmp_path, capsys, caplog, value, why):
    _blank(session, "view_001", value)
    code, _, err = run(["decode", session, "--out", tmp_path / "out"], capsys)
    assert code == 0, err
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(re.search(rf"view_001: unusable view, left out: .*{why}", w) for w in warnings), warnings
    views = json.loads((tmp_path / "out" / "range_maps.json").read_text())["views"]
    assert [v["view"] for v in views] == ["view_000"]


def test_no_usable_view_is_an_error(session, tmp_path, capsys):
    _blank(session, "view_000", 0)
    _blank(session, "view_001", 255)
    assert_refused(["decode", session, "--out", tmp_path / "out"], capsys, "no usable view",
                   nothing_at=tmp_path / "out")


@pytest.fixture(scope="module")
def lit_session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Like ``session_dir``, with the 6 ring-light images (for albedo)."""
    return _small_session(tmp_path_factory.mktemp("bad_inputs_lit"), lit_images=True)


@pytest.mark.parametrize("blank", ["lit", "all"])
def test_albedo_warns_about_an_unusable_view_and_leaves_it_out(lit_session_dir, tmp_path, capsys, caplog, blank):
    import cv2

    session = Path(shutil.copytree(lit_session_dir, tmp_path / "session"))
    for png in (session / "view_001").glob("*lit*.png" if blank == "lit" else "*.png"):
        image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(png), np.zeros_like(image))
    assert main(["decode", str(session), "--out", str(tmp_path / "dec"), "--quiet"]) == 0
    caplog.clear()
    code, _, err = run(["albedo", session, "--range-maps", tmp_path / "dec", "--out", tmp_path / "alb", "--quiet"],
                          capsys)
    assert code == 0, err
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    expected = "unusable view, left out: its lit images are black" if blank == "lit" else "left out (decode found"
    assert any(w.startswith("view_001: " + expected) for w in warnings), warnings
    views = json.loads((tmp_path / "alb" / "albedo.json").read_text())["views"]
    assert [v["view"] for v in views] == ["view_000"]
    assert not list((tmp_path / "alb").glob("view_001*"))


def test_raw_captures_unchanged_by_refused_commands(session, tmp_path, capsys):
    before = {p: p.read_bytes() for p in session.rglob("*") if p.is_file()}
    (session / "view_001" / "03_gray-col-00-inv.png").write_bytes(before[session / "view_001" / "03_gray-col-00-inv.png"][:100])
    before[session / "view_001" / "03_gray-col-00-inv.png"] = (session / "view_001" / "03_gray-col-00-inv.png").read_bytes()
    assert_refused(["decode", session, "--out", tmp_path / "out"], capsys, "truncated")
    assert {p: p.read_bytes() for p in session.rglob("*") if p.is_file()} == before


# --- meshes -----------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [False, True])
def test_register_refuses_non_finite_vertices(tmp_path, capsys, binary):
    scans = tmp_path / "scans"
    scans.mkdir()
    write_ply(scans / "a.ply", *sphere())
    nan_sphere(scans, "b.ply", binary=binary)
    assert_refused(["register", scans, "--out", tmp_path / "out"], capsys,
                   "b.ply", "2 vertices with non-finite coordinates", "first at index 5",
                   nothing_at=tmp_path / "out")


def test_fuse_refuses_non_finite_vertices(tmp_path, capsys):
    write_ply(tmp_path / "a.ply", *sphere())
    nan_sphere(tmp_path, "b.ply")
    project = write_mlp(tmp_path / "aligned.mlp", ["a.ply", "b.ply"])
    assert_refused(["fuse", project, "--out", tmp_path / "fused.ply", "--voxel", "4"], capsys,
                   "b.ply", "non-finite", nothing_at=tmp_path / "fused.ply")


def test_fuse_refuses_a_non_finite_pose(tmp_path, capsys):
    write_ply(tmp_path / "a.ply", *sphere())
    project = write_mlp(tmp_path / "aligned.mlp", ["a.ply"], matrix="1 0 0 nan 0 1 0 0 0 0 1 0 0 0 0 1")
    assert_refused(["fuse", project, "--out", tmp_path / "fused.ply", "--voxel", "4"], capsys,
                   "aligned.mlp", "a.ply", "non-finite", nothing_at=tmp_path / "fused.ply")


@pytest.mark.parametrize("voxel", ["nan", "inf", "0", "-1"])
def test_fuse_refuses_a_bad_voxel_size(tmp_path, capsys, voxel):
    write_ply(tmp_path / "a.ply", *sphere())
    project = write_mlp(tmp_path / "aligned.mlp", ["a.ply"])
    assert_refused(["fuse", project, "--out", tmp_path / "fused.ply", "--voxel", voxel], capsys,
                   "--voxel", "positive", nothing_at=tmp_path / "fused.ply")


def test_mlp_mesh_outside_its_folder_needs_allow_outside(tmp_path, capsys, caplog):
    write_ply(tmp_path / "a.ply", *sphere())
    (tmp_path / "project").mkdir()
    project = write_mlp(tmp_path / "project" / "aligned.mlp", ["../a.ply"])
    out = tmp_path / "fused.ply"
    assert_refused(["fuse", project, "--out", out, "--voxel", "4"], capsys,
                   "aligned.mlp", "a.ply", "outside", "--allow-outside", nothing_at=out)
    code, _, err = run(["fuse", project, "--out", out, "--voxel", "4", "--allow-outside", "--quiet"], capsys)
    assert code == 0, err
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("outside the project's folder" in w and "a.ply" in w for w in warnings), warnings
    assert out.is_file()


def test_register_mlp_outside_its_folder_needs_allow_outside(tmp_path, capsys):
    write_ply(tmp_path / "a.ply", *sphere())
    write_ply(tmp_path / "b.ply", *sphere())
    (tmp_path / "project").mkdir()
    project = write_mlp(tmp_path / "project" / "aligned.mlp", [str(tmp_path / "a.ply"), "../b.ply"])
    assert_refused(["register", project, "--out", tmp_path / "out"], capsys,
                   "aligned.mlp", "a.ply", "b.ply", "--allow-outside", nothing_at=tmp_path / "out")


def test_a_recipe_reads_an_mlp_outside_its_folder_only_with_allow_outside(tmp_path, capsys):
    write_ply(tmp_path / "a.ply", *sphere())
    write_ply(tmp_path / "b.ply", *sphere())
    (tmp_path / "project").mkdir()
    project = write_mlp(tmp_path / "project" / "aligned.mlp", ["../a.ply", "../b.ply"])
    recipe = tmp_path / "r.toml"
    recipe.write_text(f'[recipe]\nstages = ["register"]\n[register]\nsource = "{project}"\n')
    assert_refused(["run", recipe, "--out", tmp_path / "run", "--quiet"], capsys,
                   "aligned.mlp", "a.ply", "outside", nothing_at=tmp_path / "run" / "register")
    code, _, err = run(["run", recipe, "--out", tmp_path / "run", "--quiet",
                        "--set", "register.allow_outside=true"], capsys)
    assert code == 0, err
    assert (tmp_path / "run" / "register" / "registration.json").is_file()


@pytest.mark.parametrize("method", ["fast", "quadric"])
def test_simplify_refuses_non_finite_vertices(tmp_path, capsys, method):
    source = nan_sphere(tmp_path)
    assert_refused(["simplify", source, "--out", tmp_path / "s.ply", "--faces", "100", "--method", method], capsys,
                   "nan.ply", "2 vertices with non-finite coordinates", "first at index 5",
                   nothing_at=tmp_path / "s.ply")


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("command", ["simplify", "register"])
def test_truncated_ply_is_refused(tmp_path, capsys, binary, command):
    v, f = sphere()
    scans = tmp_path / "scans"
    scans.mkdir()
    write_ply(scans / "a.ply", v, f)
    ply = write_ply(scans / "b.ply", v, f, binary=binary)
    ply.write_bytes(ply.read_bytes()[:-200])
    out = tmp_path / ("s.ply" if command == "simplify" else "out")
    argv = [command, ply if command == "simplify" else scans, "--out", out]
    assert_refused(argv, capsys, "b.ply", "truncated", nothing_at=out)


BOMB = "".join(
    f'<!ENTITY l{i + 1} "{f"&l{i};" * 10}">' for i in range(8)
)
XML_BOMB = f'<!DOCTYPE b [<!ENTITY l0 "lol">{BOMB}]>\n<MeshLabProject><MeshGroup><MLMesh label="&l8;" filename="a.ply"/></MeshGroup></MeshLabProject>'
XML_EXTERNAL = (
    '<!DOCTYPE x [<!ENTITY e SYSTEM "file:///etc/passwd">]>\n'
    '<MeshLabProject><MeshGroup><MLMesh label="x" filename="&e;"/></MeshGroup></MeshLabProject>'
)


@pytest.mark.parametrize(
    "text",
    ["<MeshLabProject><MeshGroup><MLMesh", "", "<other/>", XML_BOMB, XML_EXTERNAL],
    ids=["truncated", "empty", "other-root", "entity-expansion", "external-entity"],
)
def test_malformed_mlp_is_refused(tmp_path, capsys, text):
    (tmp_path / "aligned.mlp").write_text(text)
    assert_refused(["fuse", tmp_path / "aligned.mlp", "--out", tmp_path / "f.ply"], capsys, "aligned.mlp",
                   nothing_at=tmp_path / "f.ply")


@pytest.mark.parametrize("size", ["0", "-4", "3"])
def test_texture_refuses_a_bad_size(tmp_path, capsys, size):
    model = write_ply(tmp_path / "model.ply", *sphere())
    (tmp_path / "albedo").mkdir()
    assert_refused(["texture", model, "--views", tmp_path / "albedo", "--out", tmp_path / "tex", "--size", size],
                   capsys, "--size", nothing_at=tmp_path / "tex")


# --- recipes ----------------------------------------------------------------------------

RECIPE = """[recipe]
name = "t"
stages = ["capture"]

[capture]
scene = "tile"
"""


@pytest.mark.parametrize(
    ("recipe", "overrides", "expected"),
    [
        (RECIPE, ["capture.camera_scale=nan"], "[capture].camera_scale: expected a finite number, got nan"),
        (RECIPE, ["capture.camera_scale=-inf"], "[capture].camera_scale: expected a finite number"),
        (RECIPE.replace('scene = "tile"', 'scene = "tile"\ncamera_scale = nan'), [],
         "[capture].camera_scale: expected a finite number"),
        (RECIPE.replace('stages = ["capture"]', 'stages = "capture"'), [], "recipe.stages: expected a list of stage names"),
        (RECIPE.replace('stages = ["capture"]', "stages = [1]"), [], "recipe.stages: expected a list of stage names"),
        (RECIPE[:-10], [], "not valid TOML"),
    ],
    ids=["set-nan", "set-inf", "toml-nan", "stages-string", "stages-int", "truncated"],
)
def test_bad_recipe_values_are_refused(tmp_path, capsys, recipe, overrides, expected):
    path = tmp_path / "r.toml"
    path.write_text(recipe)
    argv = ["run", path, "--out", tmp_path / "out"] + [x for o in overrides for x in ("--set", o)]
    assert_refused(argv, capsys, expected, nothing_at=tmp_path / "out")


# --- calibration ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text",
    [
        "<?xml version=\"1.0\"?>\n<opencv_storage>\n<cam_int type_id=\"opencv-matrix\"><rows>3</rows>",
        "not xml at all",
        (
            '<?xml version="1.0"?>\n<opencv_storage>\n<cam_int type_id="opencv-matrix"><rows>3</rows><cols>3</cols>'
            "<dt>d</dt><data>nan 0 1 0 1 1 0 0 1</data></cam_int></opencv_storage>\n"
        ),
    ],
    ids=["truncated", "not-xml", "nan"],
)
def test_malformed_calibration_xml_is_refused(session, tmp_path, capsys, text):
    xml = tmp_path / "calib.xml"
    xml.write_text(text)
    assert_refused(["calibrate", session, "--import-xml", xml, "--out", tmp_path / "cal.json"], capsys,
                   "calib.xml", nothing_at=tmp_path / "cal.json")


@pytest.mark.parametrize("text", ['{"format": "slscan.calibration", "ver', "[]"])
def test_malformed_calibration_json_is_refused(session, tmp_path, capsys, text):
    cal = tmp_path / "cal.json"
    cal.write_text(text)
    assert_refused(["decode", session, "--calibration", cal, "--out", tmp_path / "out"], capsys, "cal.json",
                   nothing_at=tmp_path / "out")


# --- Stanford .conf ---------------------------------------------------------------------


def write_stanford_ply(path: Path, *, n: int = 6, z: float = 0.5) -> Path:
    """A Stanford range-grid PLY (ASCII, metres): an n × n grid of a flat patch 4 mm apart."""
    xs, ys = np.meshgrid(np.arange(n) * 0.004, np.arange(n) * 0.004)
    points = np.stack([xs.ravel(), ys.ravel(), np.full(n * n, z)], -1)
    header = ["ply", "format ascii 1.0", f"obj_info num_cols {n}", f"obj_info num_rows {n}",
              f"element vertex {n * n}", "property float x", "property float y", "property float z",
              f"element range_grid {n * n}", "property list uchar int vertex_indices", "end_header"]
    body = [f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in points] + [f"1 {i}" for i in range(n * n)]
    path.write_text("\n".join(header + body) + "\n")
    return path


@pytest.mark.parametrize("where", ["relative", "absolute", "symlink"])
def test_conf_scan_outside_its_folder_needs_allow_outside(tmp_path, capsys, caplog, where):
    from slscan.register.command import load_scans

    scans = tmp_path / "scans"
    scans.mkdir()
    write_stanford_ply(scans / "a.ply")
    outside = write_stanford_ply(tmp_path / "x.ply")
    name = {"relative": "../x.ply", "absolute": str(outside), "symlink": "b.ply"}[where]
    if where == "symlink":
        os.symlink(outside, scans / "b.ply")
    (scans / "bun.conf").write_text(f"bmesh a.ply 0 0 0 0 0 0 1\nbmesh {name} 0 0 0 0 0 0 1\n")
    assert_refused(["register", scans, "--out", tmp_path / "out"], capsys,
                   "bun.conf", "outside its folder", name, "--allow-outside", nothing_at=tmp_path / "out")
    loaded, poses = load_scans(scans, allow_outside=True)
    assert [s.name for s in loaded] == ["a", Path(name).stem] and set(poses) == {"a", Path(name).stem}
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("outside the .conf's folder" in w and name in w for w in warnings), warnings


@pytest.mark.parametrize(
    ("pose", "expected"),
    [("0 0 0 nan 0 0 1", "non-finite"), ("0 0 0 0 inf 0 1", "non-finite"), ("nan 0 0 0 0 0 1", "non-finite"),
     ("0 0 0 0 0 0 0", "quaternion of b.ply is zero")],
    ids=["nan-rotation", "inf-rotation", "nan-translation", "zero-rotation"],
)
@pytest.mark.parametrize("use", ["folder", "poses"])
def test_conf_with_a_bad_pose_is_refused(tmp_path, capsys, pose, expected, use):
    scans = tmp_path / "scans"
    scans.mkdir()
    write_stanford_ply(scans / "a.ply")
    write_stanford_ply(scans / "b.ply", z=0.52)
    conf = (scans if use == "folder" else tmp_path) / "bun.conf"
    conf.write_text(f"bmesh a.ply 0 0 0 0 0 0 1\nbmesh b.ply {pose}\n")
    argv = ["register", scans, "--out", tmp_path / "out"] + (["--poses", conf] if use == "poses" else [])
    assert_refused(argv, capsys, "bun.conf:2", expected, nothing_at=tmp_path / "out")


@pytest.mark.parametrize("command", ["info", "decode"])
def test_session_with_two_views_of_one_name_is_refused(session, tmp_path, capsys, command):
    edit_session(session, lambda d: d["views"][1].update(name=d["views"][0]["name"]))
    argv = [command, session] + (["--out", tmp_path / "out"] if command == "decode" else [])
    assert_refused(argv, capsys, "session.json", "views[1].name", "'view_000'", "views[0]",
                   nothing_at=tmp_path / "out")


# --- simplify ---------------------------------------------------------------------------


@pytest.mark.parametrize("faces", ["10000000000000", "528"])
def test_simplify_to_more_faces_than_the_mesh_has_says_so(tmp_path, capsys, caplog, faces):
    """A target at or above the input's face count (528) writes it unchanged, with a warning:
    the target is a ceiling (the archival size), which a small mesh already meets."""
    source = write_ply(tmp_path / "m.ply", *sphere())
    code, _, err = run(["simplify", source, "--out", tmp_path / "s.ply", "--faces", faces, "--quiet"], capsys)
    assert code == 0, err
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any("m.ply: has 528 faces, not more than --faces" in w and "written unchanged" in w
               for w in warnings), warnings
    from slscan.fuse import read_mesh

    assert read_mesh(tmp_path / "s.ply").n_faces == 528
    caplog.clear()
    assert main(["simplify", str(source), "--out", str(tmp_path / "t.ply"), "--faces", "527", "--quiet"]) == 0
    assert not [r for r in caplog.records if r.levelname == "WARNING"]


# --- two writers of one output ----------------------------------------------------------


@pytest.fixture
def other_writer():
    """A live process standing in for another slscan (a fake: a Python that sleeps), whose
    lock ``hold(out)`` writes beside an output, as :func:`slscan.fsio.output_lock` would."""
    import socket
    import subprocess
    import sys

    from slscan.fsio import lock_path

    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])

    def hold(out: Path) -> Path:
        lock = lock_path(out)
        lock.write_text(json.dumps({"pid": proc.pid, "host": socket.gethostname(), "started": "now",
                                    "command": f"slscan decode s --out {out.name}"}))
        return lock

    yield hold
    proc.kill()
    proc.wait()


@pytest.mark.parametrize("command", ["decode", "simplify", "run"])
def test_a_second_writer_of_the_same_out_fails(session, tmp_path, capsys, other_writer, command):
    out = tmp_path / ("s.ply" if command == "simplify" else "out")
    lock = other_writer(out)
    argv = {"decode": ["decode", session, "--out", out],
            "simplify": ["simplify", write_ply(tmp_path / "m.ply", *sphere()), "--out", out, "--faces", "100"],
            "run": ["run", tmp_path / "r.toml", "--out", out]}[command]
    (tmp_path / "r.toml").write_text(RECIPE)
    code, line, err = run(argv, capsys)
    assert code == 2, err
    assert f"{out}: another slscan is writing it (process " in line, line
    assert f"slscan decode s --out {out.name})" in line and str(lock) in line, line
    assert not out.exists() and lock.is_file()
    assert [p.name for p in tmp_path.glob(f".{out.name}*")] == [lock.name]


def test_the_out_lock_is_gone_after_a_run_and_after_a_refusal(session, tmp_path, capsys):
    assert main(["decode", str(session), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert not list(tmp_path.glob(".out*"))
    assert_refused(["decode", session, "--out", tmp_path / "out"], capsys, "not empty")
    assert not list(tmp_path.glob(".out*"))


# --- recipes: the file and the key, and nothing written ---------------------------------


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ('scene = "tile"\nviews = 0', "r.toml: [capture].views: expected at least 1 view, got 0"),
        ('scene = "__import__(\'os\').system(\'ls\')"', "r.toml: [capture].scene: expected one of object, tile"),
        ('scene = "missing.ply"', "missing.ply: mesh file not found (stage [capture] of "),
    ],
    ids=["views-0", "code-like-scene", "missing-scene-file"],
)
@pytest.mark.parametrize("before", ["new", "earlier-run"])
def test_a_refused_recipe_names_file_and_key_and_writes_nothing(tmp_path, capsys, change, expected, before):
    recipe = tmp_path / "r.toml"
    recipe.write_text(RECIPE.replace('scene = "tile"', change))
    out = tmp_path / "out"
    if before == "earlier-run":
        out.mkdir()
        (out / "recipe.resolved.toml").write_text("# an earlier run's\n")
    line = assert_refused(["run", recipe, "--out", out, "--quiet"], capsys, expected,
                          nothing_at=out if before == "new" else None)
    assert str(recipe) in line, line
    if before == "earlier-run":
        assert [p.name for p in out.iterdir()] == ["recipe.resolved.toml"]
        assert (out / "recipe.resolved.toml").read_text() == "# an earlier run's\n"


@pytest.mark.parametrize("pose", [[[float("nan")] * 4] * 4, [[0.0] * 4] * 4, [1, 2, 3]],
                         ids=["nan", "singular", "short"])
def test_range_maps_with_a_bad_pose_are_refused(session, tmp_path, capsys, pose):
    assert main(["decode", str(session), "--out", str(tmp_path / "dec"), "--quiet"]) == 0
    summary = json.loads((tmp_path / "dec" / "range_maps.json").read_text())
    summary["views"][1]["rig_from_object"] = pose
    (tmp_path / "dec" / "range_maps.json").write_text(json.dumps(summary))
    assert_refused(["register", tmp_path / "dec", "--out", tmp_path / "out"], capsys,
                   "range_maps.json: views[1].rig_from_object: expected a finite, invertible 4x4 pose",
                   nothing_at=tmp_path / "out")


DEMO_RECIPE = Path(__file__).parents[2] / "recipes" / "demo.toml"


@pytest.mark.parametrize(
    ("setting", "expected"),
    [
        ("simplify.faces=0", "[simplify].faces: expected at least 4, got 0"),
        ("simplify.method=best", "[simplify].method: expected one of fast, quadric, got 'best'"),
        ("register.max_neighbours=-2", "[register].max_neighbours: expected >= 0"),
        ("register.pose_tolerance=-1.0", "[register].pose_tolerance: expected >= 0 mm"),
        ("capture.levels=0", "[capture].levels: expected at least 1, got 0"),
        ("capture.projector_scale=0.0", "[capture].projector_scale: expected a positive number, got 0.0"),
    ],
)
def test_a_late_stages_bad_setting_is_refused_before_the_first_stage_runs(tmp_path, capsys, setting, expected):
    """Not after capturing, decoding and fusing: the whole recipe is checked when it is read."""
    assert_refused(["run", DEMO_RECIPE, "--set", setting, "--out", tmp_path / "out"], capsys,
                   f"{DEMO_RECIPE}: {expected}", nothing_at=tmp_path / "out")
