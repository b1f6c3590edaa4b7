"""The texture stage end to end on the virtual rig (reduced size): files other programs open,
colour that matches the true albedo, and clear errors for bad input."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from slscan.cli import main
from slscan.errors import SlscanError
from slscan.recipe.runner import load_recipe, run_recipe
from slscan.texture.pipeline import TextureConfig, auto_size, texture_model

DEMO = Path(__file__).parents[2] / "recipes" / "demo.toml"


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """The demo recipe at reduced size, through the texture stage (no Blender preview), run
    into a folder named relative to the current folder, as ``slscan run ... --out run`` does."""
    import os

    parent = tmp_path_factory.mktemp("texture")
    cwd = os.getcwd()
    os.chdir(parent)
    try:
        run_recipe(load_recipe(DEMO.resolve(), reduced=True), Path("run"))
    finally:
        os.chdir(cwd)
    return parent / "run"


def test_the_demo_ends_in_a_textured_glb_and_files_other_programs_open(run):
    from slscan.texture.export import glb_summary

    folder = run / "texture"
    manifest = json.loads((folder / "texture.json").read_text())
    assert manifest["format"] == "slscan-texture" and manifest["version"] == 1
    glb = glb_summary(folder / "model.glb")
    assert glb["faces"] == manifest["model"]["faces"] and glb["has_uv"]
    assert glb["texture_size"] == [512, 512]
    for name in ("model.obj", "model.mtl", "model_albedo.png", "model_vertex_colors.ply", "view_count.png"):
        assert (folder / name).stat().st_size > 0, name
    assert "model_albedo.png" in (folder / "model.mtl").read_text()
    assert len(manifest["views"]) == 8
    for view in manifest["views"]:
        assert (folder / view["image"]).is_file()
        assert view["cx"] == (view["width"] - 1) / 2  # centred: MeshLab mirrors off-centre ones
    metrics = manifest["metrics"]
    assert metrics["observed_share"] > 0.7 and metrics["charts"] >= 1


def test_the_view_count_picture_shows_the_counts_in_its_legend_colours(run):
    """view_count.png is meant to be looked at (the counts are 0-3: as grey levels, black);
    view_count_raw.png keeps the counts, and the legend in texture.json says which is which."""
    from slscan.colour import VIEW_COUNT_OUTSIDE
    from slscan.fsio import read_png

    folder = run / "texture"
    model = json.loads((folder / "texture.json").read_text())["model"]
    picture, raw = read_png(folder / model["view_count_image"]), read_png(folder / model["view_count"])
    assert picture.shape == raw.shape + (3,) and picture.dtype == np.uint8 and raw.dtype == np.uint16
    legend = model["view_count_legend"]
    assert len(legend) == 2 + 8  # outside, filled, then 1 to 8 views
    named = {k: np.array(legend[f"{k} view{'s' if k > 1 else ''}"]) for k in range(1, 9)}
    named[0] = np.array(legend["0 views (filled from the vertex colours)"])
    outside = np.all(picture == VIEW_COUNT_OUTSIDE, axis=-1)
    assert raw[outside].max() == 0 and 0.1 < outside.mean() < 0.9
    for k in np.unique(raw):
        texels = (raw == k) & ~outside
        assert texels.any() and np.all(picture[texels] == named[int(k)]), k
    assert raw.max() >= 2 and len({tuple(c) for c in named.values()}) == 9  # distinct colours
    # visible: every count inside the charts is well above black
    assert picture[~outside].max(axis=-1).min() >= 90


def test_the_meshlab_project_loads_in_pymeshlab_with_model_and_rasters(run):
    import xml.etree.ElementTree as ET

    import pymeshlab

    project = run / "texture" / "model.mlp"
    root = ET.parse(project).getroot()
    files = [m.get("filename") for m in root.iter("MLMesh")] + [p.get("fileName") for p in root.iter("Plane")]
    assert files[0] == "model.ply" and len(files) == 9
    for name in files:  # MeshLab resolves them against the project's folder, strictly
        assert (project.parent / name).is_file(), name
    ms = pymeshlab.MeshSet()
    ms.load_project(str(project))
    assert ms.mesh_number() == 1
    assert ms.raster_number() == 8
    mesh = ms.current_mesh()
    assert mesh.face_number() == json.loads((run / "texture" / "texture.json").read_text())["model"]["faces"]
    assert mesh.has_wedge_tex_coord()
    np.testing.assert_allclose(mesh.wedge_tex_coord_matrix(), _wedge_uvs(run / "texture").reshape(-1, 2), atol=1e-6)
    textures = mesh.textures()  # MeshLab loaded the atlas the PLY names
    assert list(textures) == ["model_albedo.png"]
    assert (textures["model_albedo.png"].width(), textures["model_albedo.png"].height()) == (512, 512)


def _wedge_uvs(folder: Path) -> np.ndarray:
    """(m, 3, 2) texture coordinates of the model's face corners as the OBJ has them (v up
    from the bottom row, 8 decimals), in the order of the model's faces."""
    from slscan.meshes import read_obj_atlas

    atlas, _ = read_obj_atlas(folder / "model.obj")
    uv = np.asarray(atlas["uvs"], np.float64)[np.asarray(atlas["faces"])]
    uv[..., 1] = 1.0 - uv[..., 1]
    return uv


def _ply_header(path: Path) -> list[str]:
    data = path.read_bytes()
    return data[: data.index(b"end_header")].decode("ascii").splitlines()


def _meshlab_unavailable(reason: str) -> None:
    """Skip where MeshLab 2020.09 is not installed, except in CI (``CI`` set), where
    .ci/setup installs Debian's ``meshlab`` package and Xvfb: there a skip is a failure."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason} (CI is set: .ci/setup should install meshlab and xvfb)")
    pytest.skip(reason)


def test_the_meshlab_project_opens_in_the_meshlab_linux_distributions_ship(run, tmp_path):
    """MeshLab 2020.09 (Debian 12's and Ubuntu 22.04's package) aborts in its OBJ reader on
    our OBJ; the project names the PLY with wedge texture coordinates instead. meshlabserver
    loads the project and saves it again: the saved mesh must have every face, the texture
    coordinates we wrote and the atlas's name, the saved project our 8 rasters. A crash
    (abort, SIGSEGV) is a non-zero exit and fails."""
    import shutil
    import subprocess

    from slscan.fuse import read_mesh
    from slscan.ply import read_ply_elements
    from slscan.register.meshlab import read_mlp_rasters

    server = shutil.which("meshlabserver")
    if server is None:
        _meshlab_unavailable("MeshLab's meshlabserver is not installed (apt-get install meshlab)")
    command = [server]
    if not os.environ.get("DISPLAY"):
        if shutil.which("xvfb-run") is None:
            _meshlab_unavailable("meshlabserver needs an X display: no DISPLAY, no xvfb-run")
        command = ["xvfb-run", "-a", server]
    folder = tmp_path / "texture"  # meshlabserver -w writes MESH_out.ply beside the mesh: a copy
    shutil.copytree(run / "texture", folder)
    done = subprocess.run(
        [*command, "-p", "model.mlp", "-w", str(tmp_path / "saved.mlp"), "-o", str(tmp_path / "saved.ply"),
         "-m", "wt", "vn"],
        cwd=folder, capture_output=True, text=True, timeout=300, check=False,
        env=dict(os.environ, QT_QPA_PLATFORM="xcb"),
    )
    log = (done.stdout + done.stderr).strip()
    assert done.returncode == 0, f"meshlabserver exited with {done.returncode}:\n{log[-1500:]}"
    model = read_mesh(folder / "model.ply")
    saved = read_ply_elements(tmp_path / "saved.ply")
    assert "comment TextureFile model_albedo.png" in _ply_header(tmp_path / "saved.ply")
    counts, indices = saved["face"]["vertex_indices"]
    assert len(counts) == len(model.faces) and np.all(counts == 3)
    np.testing.assert_allclose(  # MeshLab writes float32 positions
        np.stack([saved["vertex"][k] for k in "xyz"], 1)[indices.reshape(-1, 3)],
        model.vertices[model.faces], atol=1e-4,
    )
    uv_counts, uvs = saved["face"]["texcoord"]
    assert np.all(uv_counts == 6)
    np.testing.assert_allclose(uvs.reshape(-1, 3, 2), _wedge_uvs(folder), atol=1e-6)
    rasters = read_mlp_rasters(tmp_path / "saved.mlp", check_files=False)
    views = json.loads((folder / "texture.json").read_text())["views"]
    assert [r.label for r in rasters] == [v["name"] for v in views]
    for raster, view in zip(rasters, views):  # MeshLab writes 6 significant digits
        assert (raster.width, raster.height) == (view["width"], view["height"])
        assert np.allclose([raster.fx, raster.fy, raster.cx, raster.cy],
                           [view["fx"], view["fy"], view["cx"], view["cy"]], rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(raster.world_from_camera, view["world_from_camera"], rtol=1e-5, atol=1e-5)


def test_the_baked_colour_matches_the_true_albedo(run):
    """Registration, camera poses, projection and baking together: wrong poses or a
    flipped axis would drop this to ~12 dB."""
    from slscan.colour import srgb8
    from slscan.fuse import read_mesh
    from slscan.register.frame import read_frame
    from slscan.texture.atlas import AtlasOptions, build_atlas
    from slscan.texture.bake import bake
    from slscan.texture.metrics import psnr, render_into_atlas
    from slscan.texture.views import load_views
    from slscan.virtual.scenes import builtin_object, surface_albedo

    mesh = read_mesh(run / "simplify" / "mesh.ply")
    views = load_views(run / "albedo", run / "register")
    atlas = build_atlas(mesh.vertices, mesh.faces, AtlasOptions(size=512))
    baked = bake(mesh.vertices, mesh.faces, atlas, views)
    scene = builtin_object()
    # the model is in the upright object frame; the scene's albedo is known in the scene's
    frame = read_frame(run / "register" / "registration.json")
    scene_from_model = np.linalg.inv(frame.object_from_reference)
    in_scene = mesh.vertices @ scene_from_model[:3, :3].T + scene_from_model[:3, 3]
    truth, _ = render_into_atlas(in_scene, mesh.faces, atlas, lambda p: surface_albedo(scene, p))
    value = psnr(srgb8(baked.linear), srgb8(truth), baked.observed)
    # quarter-size scans: blurred albedo, registration within about 1 degree of the true
    # poses: 25.7-26.2 dB for capture seeds 0-3 (15-17 dB while registration let ICP slide
    # the views round the figurine from their exact turntable poses). With the paint-edge
    # default "shift" (decode keeps most line samples beside paint edges: fewer holes) it is
    # 23.5 dB against 26.1 with "drop": a colour cost of keeping that surface, open in #35's
    # note; wrong poses still fall far below (12-17 dB, and the 3-degree check below)
    assert value > 23.0, f"PSNR {value:.1f} dB"
    # the same views with their poses turned 3 degrees about the object's vertical axis
    # (a registration error) bake visibly worse colour
    from dataclasses import replace

    from slscan.rig import rotation_about_axis

    turn = np.eye(4)
    turn[:3, :3] = rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(3.0))
    wrong = [replace(v, world_from_camera=turn @ v.world_from_camera) for v in views]
    worse = bake(mesh.vertices, mesh.faces, atlas, wrong)
    worse_value = psnr(srgb8(worse.linear), srgb8(truth), worse.observed)
    assert worse_value < value - 2.0, f"{worse_value:.1f} dB vs {value:.1f} dB"


def test_texture_command_and_bad_input(run, tmp_path):
    out = tmp_path / "tex"
    args = ["texture", str(run / "simplify" / "mesh.ply"), "--views", str(run / "albedo"),
            "--poses", str(run / "register"), "--out", str(out), "--size", "256", "--no-preview", "--quiet"]
    assert main(args) == 0
    assert json.loads((out / "texture.json").read_text())["atlas"]["size"] == 256
    assert main(args) != 0  # exists: not overwritten without --overwrite
    assert main([*args, "--overwrite", "--save", str(tmp_path / "t.rrd")]) == 0
    assert (tmp_path / "t.rrd").stat().st_size > 10_000
    assert main(["view", str(out), "--save", str(tmp_path / "v.rrd")]) == 0

    points_only = tmp_path / "points.ply"
    points_only.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                           "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(SlscanError, match="no triangles"):
        texture_model(points_only, run / "albedo", tmp_path / "a")
    with pytest.raises(SlscanError, match="no albedo.json"):
        texture_model(run / "simplify" / "mesh.ply", run / "decode", tmp_path / "b")
    with pytest.raises(SlscanError, match="has a pose"):
        texture_model(run / "simplify" / "mesh.ply", run / "albedo", tmp_path / "c", poses={"elsewhere": np.eye(4)})
    with pytest.raises(SlscanError, match="expected 16 to 16384"):
        texture_model(run / "simplify" / "mesh.ply", run / "albedo", tmp_path / "d",
                      config=TextureConfig(size=32768))
    assert not any((tmp_path / n).exists() for n in "abcd")


def test_texture_warns_about_a_model_the_views_did_not_see_and_refuses_one_none_sees(run, tmp_path, capsys,
                                                                                        caplog):
    """The right model: no warning. The model 2 m away (seen share 5 %, measured in
    ``benchmarks/texture_seen.py``): textured, with both warnings naming the model. The model
    100 m above the turntable, out of every view: refused, nothing written."""
    from dataclasses import replace

    from slscan.fuse import read_mesh, write_mesh

    mesh = read_mesh(run / "simplify" / "mesh.ply")
    for name, shift in [("far.ply", [2000.0, 0, 0]), ("gone.ply", [0, 100_000.0, 0])]:
        write_mesh(replace(mesh, vertices=mesh.vertices + shift), tmp_path / name)

    def texture(model: Path, out: str) -> tuple[int, list[str]]:
        caplog.clear()
        code = main(["texture", str(model), "--views", str(run / "albedo"), "--poses", str(run / "register"),
                     "--out", str(tmp_path / out), "--size", "128", "--no-preview", "--quiet"])
        return code, [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]

    code, warnings = texture(run / "simplify" / "mesh.ply", "right")
    assert code == 0 and not [w for w in warnings if "seen by a view" in w or "covers only" in w], warnings
    code, warnings = texture(tmp_path / "far.ply", "far")
    assert code == 0
    assert any(w.startswith(f"{tmp_path / 'far.ply'}: only ") and "seen by a view of" in w for w in warnings), warnings
    assert any(w.startswith(f"{tmp_path / 'far.ply'}: the model covers only ") for w in warnings), warnings
    capsys.readouterr()
    code, _ = texture(tmp_path / "gone.ply", "gone")
    err = " ".join(capsys.readouterr().err.split())
    assert code == 2 and f"{tmp_path / 'gone.ply'}: no view of {run / 'albedo'} sees the model" in err, err
    assert not (tmp_path / "gone").exists()


def test_auto_size_gives_about_the_texels_asked_for():
    assert auto_size(20_000) == 512
    assert auto_size(100_000) == 2048
    assert auto_size(1_000_000) == 4096
    assert auto_size(10**8) == 8192


def test_real_blender_imports_the_demo_glb_with_its_texture_and_cameras(run):
    """The demo's own result through the add-on in real Blender (bpy in .venv-blender)."""
    import os

    from slscan.texture.blender import find_blender, import_result

    if os.environ.get("SLSCAN_NO_BLENDER") == "1":
        pytest.skip("SLSCAN_NO_BLENDER=1")
    if find_blender() is None:
        pytest.fail("no Blender: run `bash .ci/setup` (it creates .venv-blender with bpy 5.0.1)")
    scene = import_result(run / "texture")
    manifest = json.loads((run / "texture" / "texture.json").read_text())
    meshes = scene["meshes"]
    assert len(meshes) == 1
    assert sum(m["faces"] for m in meshes) == manifest["model"]["faces"]
    images = [mat["image"] for m in meshes for mat in m["materials"] if mat.get("image_texture")]
    assert images and images[0]["size"] == [manifest["atlas"]["size"]] * 2
    assert len(scene["cameras"]) == len(manifest["views"]) == 8


@pytest.mark.parametrize("with_normals", [True, False])
def test_obj_text_is_line_for_line_what_trimesh_writes(with_normals, tmp_path):
    from types import SimpleNamespace

    from trimesh.exchange.obj import export_obj

    from slscan.meshes import read_obj_atlas
    from slscan.texture.export import _textured_trimesh, obj_text, write_obj

    rng = np.random.default_rng(5)
    vertices = rng.normal(scale=80.0, size=(700, 3))
    vertices[0] = [-0.0, 1e-9, 123456.123456789]  # signed zero, tiny and large values
    faces = rng.integers(0, 700, size=(1300, 3))
    uvs = rng.random((700, 2)).astype(np.float32)
    normals = rng.normal(size=(700, 3)).astype(np.float32) if with_normals else None
    texture = np.zeros((8, 8, 3), np.uint8)
    mesh = _textured_trimesh(vertices, faces, uvs, texture, normals)
    theirs, _ = export_obj(mesh, include_normals=with_normals, include_texture=True, return_texture=True,
                           mtl_name="model.mtl")
    ours = obj_text(vertices, faces, uvs, normals, "model.mtl")
    assert [line for line in theirs.splitlines() if line and not line.startswith("#")] == ours.splitlines()[1:]
    # and it reads back as the atlas it was written from
    write_obj(tmp_path / "model.obj", SimpleNamespace(vertices=vertices, faces=faces, uvs=uvs), texture, normals)
    back, image = read_obj_atlas(tmp_path / "model.obj")
    assert np.array_equal(np.asarray(back["faces"]), faces)
    assert np.allclose(back["vertices"], vertices, atol=1e-8)
    assert np.allclose(back["uvs"], uvs, atol=1e-7)
    assert image.shape == texture.shape
