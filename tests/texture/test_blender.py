"""The Blender add-on with real Blender (bpy in .venv-blender): import, cameras, preview render.

A small texture result is built here with a known answer: a bumpy sphere with a
four-colour texture, seen by two views with off-centre principal points and fx != fy.
Blender's projection of the imported mesh through each imported camera must agree with
OpenCV's projection of the same world points to a small fraction of a pixel.

Without Blender these tests fail with the set-up command to run; ``SLSCAN_NO_BLENDER=1``
skips them instead.
"""

from __future__ import annotations

import json
import os
import shutil
import types
import zipfile
from pathlib import Path

import numpy as np
import PIL.Image
import pytest
from scipy.ndimage import binary_erosion
from scipy.spatial import cKDTree

from slscan.errors import SlscanError
from slscan.texture import blender
from slscan.texture.blender import find_blender, import_result, render_preview, run_blender_script
from slscan.texture.export import write_glb

CHECK_SCRIPT = Path(__file__).with_name("blender_check.py")
INSTALL_SCRIPT = Path(__file__).with_name("blender_install.py")
ADDON = blender.TOOLBOX / "slscan_blender"
GLTF_FROM_WORLD = np.diag([0.001, -0.001, -0.001, 1.0])
GLTF_TO_BLENDER = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float)
CENTRE = np.array([10.0, -5.0, 700.0])  # mm, in front of the reference camera
RADIUS = 50.0  # mm
TEX_W, TEX_H = 256, 128
QUARTER_COLOURS = np.array([[220, 40, 40], [40, 180, 60], [40, 70, 220], [230, 200, 40]], np.uint8)
VIEWS = [  # name, (w, h), fx, fy, cx, cy, eye (mm)
    ("view000", (320, 240), 900.0, 860.0, 171.3, 108.6, (-40.0, 20.0, 0.0)),
    ("view001", (256, 200), 800.0, 845.0, 120.2, 109.9, (380.0, -150.0, 150.0)),
]
CAMERA_TOLERANCE_PX = 0.02


# --- the synthetic result -------------------------------------------------------------------


def _texture() -> np.ndarray:
    """(TEX_H, TEX_W, 3) uint8: a colour per longitude quarter, darker latitude bands."""
    tex = np.repeat(QUARTER_COLOURS, TEX_W // 4, axis=0)[None].repeat(TEX_H, axis=0)
    band = (np.arange(TEX_H) // 16) % 2 == 1
    tex[band] = (tex[band] * 0.6).astype(np.uint8)
    return tex


def _sphere_points(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """World points (mm; y down) of the bumpy sphere at polar angle theta, longitude phi."""
    r = RADIUS * (1 + 0.08 * np.sin(3 * phi) * np.sin(theta) ** 2 * np.sin(4 * theta))
    d = np.stack([np.sin(theta) * np.cos(phi), -np.cos(theta), np.sin(theta) * np.sin(phi)], -1)
    return CENTRE + r[..., None] * d


def _sphere_mesh(n_lat: int = 24, n_lon: int = 48) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices (n, 3) world mm, faces (m, 3), uv (n, 2) in [0, 1], v down from the top row."""
    i, j = np.meshgrid(np.arange(n_lat + 1), np.arange(n_lon + 1), indexing="ij")
    verts = _sphere_points(np.pi * i / n_lat, 2 * np.pi * j / n_lon).reshape(-1, 3)
    uv = np.stack([j / n_lon, i / n_lat], -1).reshape(-1, 2)

    def idx(a: int, b: int) -> int:
        return a * (n_lon + 1) + b

    faces = []
    for a in range(n_lat):
        for b in range(n_lon):
            if a > 0:
                faces.append((idx(a, b), idx(a + 1, b + 1), idx(a, b + 1)))
            if a < n_lat - 1:
                faces.append((idx(a, b), idx(a + 1, b), idx(a + 1, b + 1)))
    return verts, np.array(faces), uv


def _look_at(eye, target) -> np.ndarray:
    """world_from_camera (4, 4), OpenCV axes, looking from ``eye`` at ``target``, y down-ish."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    m[:3, 3] = eye
    return m


def _project(points: np.ndarray, view: dict) -> np.ndarray:
    """OpenCV pinhole projection (n, 2) px of world points (n, 3) mm."""
    m = np.asarray(view["world_from_camera"])
    cam = (points - m[:3, 3]) @ m[:3, :3]
    return np.stack(
        [
            view["fx"] * cam[:, 0] / cam[:, 2] + view["cx"],
            view["fy"] * cam[:, 1] / cam[:, 2] + view["cy"],
        ],
        -1,
    )


def _view_image(view: dict, tex: np.ndarray) -> np.ndarray:
    """What the view sees: the textured sphere splatted with a z-buffer, on grey."""
    theta, phi = np.meshgrid(
        np.linspace(0, np.pi, 600), np.linspace(0, 2 * np.pi, 1200, endpoint=False), indexing="ij"
    )
    pts = _sphere_points(theta, phi).reshape(-1, 3)
    colours = tex[
        np.minimum((theta / np.pi * TEX_H).astype(int), TEX_H - 1),
        np.minimum((phi / (2 * np.pi) * TEX_W).astype(int), TEX_W - 1),
    ].reshape(-1, 3)
    m = np.asarray(view["world_from_camera"])
    depth = (pts - m[:3, 3]) @ m[:3, 2]
    uv = np.rint(_project(pts, view)).astype(int)
    w, h = view["width"], view["height"]
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    order = np.argsort(-depth[ok])  # far first, near overwrites
    image = np.full((h, w, 3), 90, np.uint8)
    image[uv[ok][order, 1], uv[ok][order, 0]] = colours[ok][order]
    return image


def build_result(folder: Path) -> dict:
    """Write a texture result (texture.json, model.glb, views/*.png); return its manifest."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "views").mkdir(exist_ok=True)
    tex = _texture()
    verts, faces, uv = _sphere_mesh()
    # the texture stage's own glb writer (trimesh underneath), with a stand-in for its atlas
    atlas = types.SimpleNamespace(vertices=verts, faces=faces, uvs=uv)
    write_glb(folder / "model.glb", atlas, tex, gltf_from_world=GLTF_FROM_WORLD)
    views = []
    for name, (w, h), fx, fy, cx, cy, eye in VIEWS:
        view = {
            "name": name,
            "image": f"views/{name}.png",
            "width": w,
            "height": h,
            "fx": fx,
            "fy": fy,
            "cx": cx,
            "cy": cy,
            "world_from_camera": _look_at(np.array(eye), CENTRE).tolist(),
        }
        PIL.Image.fromarray(_view_image(view, tex)).save(folder / view["image"])
        views.append(view)
    manifest = {
        "format": "slscan-texture",
        "version": 1,
        "written_by": "test_blender",
        "units": "mm",
        "model": {"glb": "model.glb"},
        "gltf_from_world": GLTF_FROM_WORLD.tolist(),
        "views": views,
    }
    (folder / "texture.json").write_text(json.dumps(manifest, indent=1))
    return {**manifest, "world_vertices": verts, "faces": faces, "texture": tex}


def _variant(src: Path, dst: Path, change) -> Path:
    """A copy of the result at ``src`` with ``change(manifest, folder)`` applied."""
    shutil.copytree(src, dst)
    manifest = json.loads((dst / "texture.json").read_text())
    change(manifest, dst)
    (dst / "texture.json").write_text(json.dumps(manifest))
    return dst / "texture.json"


# --- fixtures --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def have_blender() -> None:
    if os.environ.get("SLSCAN_NO_BLENDER") == "1":
        pytest.skip("SLSCAN_NO_BLENDER=1")
    if find_blender() is None:
        pytest.fail(
            "no Blender for the add-on tests: run 'bash .ci/setup' (it makes .venv-blender "
            "with bpy 5.0.1), or set SLSCAN_NO_BLENDER=1 to skip them",
            pytrace=False,
        )


@pytest.fixture(scope="module")
def result(tmp_path_factory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("blender") / "result"
    return folder, build_result(folder)


@pytest.fixture(scope="module")
def checked(have_blender, result, tmp_path_factory) -> dict:
    """One Blender run of blender_check.py on the result and on broken copies of it."""
    folder, _ = result
    tmp = tmp_path_factory.mktemp("blender-bad")

    def drop_view_image(m, d):
        (d / m["views"][1]["image"]).unlink()

    bad = {
        "format": _variant(folder, tmp / "format", lambda m, d: m.update(format="something-else")),
        "version": _variant(folder, tmp / "version", lambda m, d: m.update(version=2)),
        "glb": _variant(folder, tmp / "glb", lambda m, d: (d / "model.glb").unlink()),
        "image": _variant(folder, tmp / "image", drop_view_image),
    }
    out = tmp / "check.json"
    renders = tmp / "renders"
    pixels = ["--pixel", "5", "10", "--pixel", "20", "200"]  # (row, col) in the texture
    args = [folder / "texture.json", out, *pixels, "--render", renders]
    for path in bad.values():
        args += ["--bad", path]
    run_blender_script(CHECK_SCRIPT, args, timeout=300, what="blender_check.py")
    report = json.loads(out.read_text())
    report["bad_by_kind"] = {kind: report["bad"][str(path)] for kind, path in bad.items()}
    report["renders"] = renders
    return report


def _camera_errors(report: dict, manifest: dict) -> dict[str, float]:
    """Largest |Blender - OpenCV| (px) per view over the imported vertices in front of it.

    Imported vertices are matched to the written ones through the documented frames
    (glTF (x, y, z) is Blender (x, -z, y)), independently of the add-on's code.
    """
    world = manifest["world_vertices"]
    blender_from_world = GLTF_TO_BLENDER @ GLTF_FROM_WORLD
    expected = world @ blender_from_world[:3, :3].T + blender_from_world[:3, 3]
    got = np.asarray(report["vertices_blender"])
    dist, index = cKDTree(expected).query(got)
    assert dist.max() < 1e-6, (
        f"imported mesh is not where the frames say (off by {dist.max():.2e} m)"
    )
    out = {}
    for view in manifest["views"]:
        uvz = np.asarray(report["cameras"][view["name"]]["uvz"])
        ref = _project(world[index], view)
        front = uvz[:, 2] > 0
        out[view["name"]] = float(np.abs(uvz[front, :2] - ref[front]).max())
    return out


# --- tests -----------------------------------------------------------------------------------


def test_find_blender_honours_the_environment_variable(monkeypatch, tmp_path):
    exe = tmp_path / "python3.11"
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    monkeypatch.setenv(blender.ENV_VAR, str(exe))
    assert find_blender() == [str(exe)]
    exe = exe.rename(tmp_path / "blender")
    monkeypatch.setenv(blender.ENV_VAR, str(exe))
    assert find_blender()[:2] == [str(exe), "-b"] and find_blender()[-1] == "--python"
    monkeypatch.setenv(blender.ENV_VAR, str(tmp_path / "missing"))
    with pytest.raises(SlscanError, match="no such executable"):
        find_blender()


def test_addon_registers_and_unregisters_cleanly(checked):
    reg = checked["registration"]
    assert reg["registered_operator"] and reg["menu_entry"]
    assert not reg["operator_after_unregister"] and not reg["menu_after_unregister"]


@pytest.mark.parametrize("mode", ["extension", "legacy"])
def test_addon_installs_from_a_zip(have_blender, result, tmp_path, monkeypatch, mode):
    """The folder zipped as docs/blender.md says installs and works, as extension or legacy add-on."""
    zip_path = tmp_path / "slscan_blender.zip"
    with zipfile.ZipFile(zip_path, "w") as zf:
        for path in sorted(ADDON.rglob("*")):
            if path.is_file() and "__pycache__" not in path.parts:
                zf.write(path, path.relative_to(ADDON.parent))
    monkeypatch.setenv("BLENDER_USER_RESOURCES", str(tmp_path / "user"))
    folder, _ = result
    out = tmp_path / "install.json"
    run_blender_script(INSTALL_SCRIPT, [mode, zip_path, folder / "texture.json", out], timeout=120)
    report = json.loads(out.read_text())
    module = "bl_ext.user_default.slscan_blender" if mode == "extension" else "slscan_blender"
    assert module in report["addons"] and report["operator"]
    assert f"{module}.operators" in report["menu"]
    assert report["status"] == ["FINISHED"]
    assert {("view000", "CAMERA"), ("view001", "CAMERA")} <= set(map(tuple, report["objects"]))
    assert (tmp_path / "user").is_dir()  # installed there, not in the user's Blender


def test_import_gives_the_textured_mesh_and_a_camera_per_view(have_blender, result):
    folder, manifest = result
    summary = import_result(folder)
    assert summary["blender"].startswith(("4.", "5."))
    (mesh,) = summary["meshes"]
    assert mesh["vertices"] == len(np.unique(manifest["faces"]))  # unused vertices are dropped
    assert mesh["triangles"] == mesh["faces"] == 2 * 24 * 48 - 2 * 48
    (material,) = mesh["materials"]
    assert material["image_texture"] and material["image"]["size"] == [TEX_W, TEX_H]
    cams = {c["view"]: c for c in summary["cameras"]}
    assert sorted(cams) == ["view000", "view001"]
    for view in manifest["views"]:
        cam = cams[view["name"]]
        assert cam["resolution"] == [view["width"], view["height"]]
        assert cam["background_image"]["size"] == [view["width"], view["height"]]
        assert cam["lens"] == pytest.approx(
            view["fx"] * cam["sensor_width"] / view["width"], rel=1e-5
        )
        assert cam["shift_x"] != 0 and cam["shift_y"] != 0
        assert cam["pixel_aspect"][0] / cam["pixel_aspect"][1] == pytest.approx(
            view["fy"] / view["fx"]
        )
    in_views = [o for o in summary["objects"] if o["type"] == "CAMERA"]
    assert all(o["collections"] == ["slscan views"] for o in in_views)
    assert summary["scene_camera"] == "view000" and summary["resolution"] == [320, 240]


def test_texture_image_arrives_intact(checked, result):
    _, manifest = result
    tex = checked["texture"]
    assert tex["size"] == [TEX_W, TEX_H] and tex["base_color_linked"]
    for (r, c), got in zip([(5, 10), (20, 200)], tex["pixels"]):
        assert got == manifest["texture"][r, c].tolist()


def test_cameras_project_the_model_like_opencv(checked, result):
    _, manifest = result
    for view in manifest["views"]:
        cam = checked["cameras"][view["name"]]
        assert cam["resolution"] == [view["width"], view["height"]]
        uvz = np.asarray(cam["uvz"])
        inside = (
            (uvz[:, 0] > 0)
            & (uvz[:, 0] < view["width"])
            & (uvz[:, 1] > 0)
            & (uvz[:, 1] < view["height"])
        )
        assert (uvz[:, 2] > 0).all() and inside.all()  # the whole sphere is in view
    errors = _camera_errors(checked, manifest)
    assert max(errors.values()) < CAMERA_TOLERANCE_PX, errors


def test_renders_through_the_cameras_match_the_view_images(checked, result):
    """Blender's own render (not only world_to_camera_view) shows the model where the view saw
    it, with the texture the right way round.

    The view images were drawn by OpenCV projection of the textured sphere: silhouettes must
    coincide, and each pixel's texture colour (of 8: 4 quarters, light or dark band) agree.
    """
    folder, manifest = result
    palette = np.concatenate([QUARTER_COLOURS, (QUARTER_COLOURS * 0.6).astype(np.uint8)]).astype(
        float
    )

    def colour_class(image: np.ndarray) -> np.ndarray:
        return np.argmin(((image[..., None, :3].astype(float) - palette) ** 2).sum(-1), -1)

    for view in manifest["views"]:
        render = np.asarray(PIL.Image.open(checked["renders"] / f"{view['name']}.png"))
        assert render.shape == (view["height"], view["width"], 4)
        image = np.asarray(PIL.Image.open(folder / view["image"]))
        seen = np.abs(image.astype(int) - 90).max(axis=2) > 0
        rendered = render[..., 3] > 127
        assert (seen & rendered).sum() / (seen | rendered).sum() > 0.95
        centroids = [np.argwhere(mask).mean(axis=0) for mask in (seen, rendered)]
        assert np.abs(centroids[0] - centroids[1]).max() < 0.2, centroids
        inner = binary_erosion(seen & (render[..., 3] == 255), iterations=2)
        agree = np.mean(colour_class(render)[inner] == colour_class(image)[inner])
        assert agree > 0.9, f"{view['name']}: texture colours agree on {agree:.0%} of the pixels"


@pytest.mark.parametrize("kind", ["translate 1 mm", "tilt 0.05 deg", "cx + 1 px"])
def test_a_wrong_camera_would_be_caught(checked, result, kind):
    """The comparison has the power to see small mistakes: each is well over the tolerance."""
    _, manifest = result
    views = [dict(v) for v in manifest["views"]]
    view = views[1]
    pose = np.array(view["world_from_camera"])
    if kind == "translate 1 mm":
        pose[:3, 3] += [1.0, 0.0, 0.0]
    elif kind == "tilt 0.05 deg":
        a = np.radians(0.05)
        pose[:3, :3] = pose[:3, :3] @ np.array(
            [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
        )
    else:
        view["cx"] += 1.0
    view["world_from_camera"] = pose.tolist()
    errors = _camera_errors(checked, {**manifest, "views": views})
    assert errors[views[0]["name"]] < CAMERA_TOLERANCE_PX
    assert errors[view["name"]] > 25 * CAMERA_TOLERANCE_PX, errors


def test_bad_results_are_reported_clearly(checked, have_blender, result, tmp_path):
    msgs = checked["bad_by_kind"]
    assert "not an slscan texture result" in msgs["format"] and "something-else" in msgs["format"]
    assert "newer slscan" in msgs["version"]
    assert "model.glb" in msgs["glb"] and "not found" in msgs["glb"]
    assert "view001.png" in msgs["image"] and "not found" in msgs["image"]
    # through the driver: Blender's error surfaces as an SlscanError
    folder, _ = result
    bad = _variant(folder, tmp_path / "bad", lambda m, d: m.update(version=7))
    with pytest.raises(SlscanError, match="newer slscan"):
        import_result(bad.parent)


def test_render_preview_shows_the_textured_model(have_blender, result, tmp_path):
    folder, _ = result
    out = render_preview(folder, tmp_path / "preview.png", size=(160, 120), samples=4)
    image = np.asarray(PIL.Image.open(out).convert("RGB")).astype(float)
    assert image.shape == (120, 160, 3)
    background = np.median(np.concatenate([image[0], image[-1]]), axis=0)
    model = np.abs(image - background).max(axis=2) > 40
    assert 0.05 < model.mean() < 0.9, "the model should fill part of the frame"
    # the texture's colours: at least two quarters' dominant channels show on the visible side
    r, g, b = image[model].T
    red = np.mean((r > g + 40) & (r > b + 40))
    green = np.mean((g > r + 40) & (g > b + 30))
    blue = np.mean((b > r + 40) & (b > g + 40))
    yellow = np.mean((r > b + 60) & (g > b + 60))
    assert sum(x > 0.03 for x in (red, green, blue, yellow)) >= 2, (red, green, blue, yellow)
    assert not list(tmp_path.glob(".preview.png.partial*"))
