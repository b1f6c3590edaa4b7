"""Recipes: every recipe in recipes/ runs at reduced size, resumes, and refuses bad keys by name."""

from __future__ import annotations

import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from slscan.errors import SlscanError
from slscan.recipe.config import dumps_toml
from slscan.recipe.runner import load_recipe, parse_recipe, run_recipe

RECIPES = sorted((Path(__file__).parents[2] / "recipes").glob("*.toml"))


def test_there_are_recipes():
    assert {p.stem for p in RECIPES} >= {"demo", "paper"}


@pytest.mark.parametrize("path", RECIPES, ids=[p.stem for p in RECIPES])
def test_every_recipe_runs_at_reduced_size_and_resumes(path, tmp_path, request):
    recipe = load_recipe(path, reduced=True)
    if any(s.name == "import" for s, _ in recipe.steps) or "SLSCAN_DATA" in path.read_text():
        request.getfixturevalue("shared_data")  # skips with the reason when the real data is absent
    out = tmp_path / "run"
    first = run_recipe(recipe, out)
    assert all(r.ran for r in first)
    for r in first:
        assert r.out.is_dir() and any(r.out.iterdir())
    again = run_recipe(load_recipe(path, reduced=True), out)
    assert not any(r.ran for r in again)
    resolved = tomllib.loads((out / "recipe.resolved.toml").read_text())
    assert resolved == recipe.resolved()
    for project in out.rglob("*.mlp"):
        assert_mlp_files_exist(project)
    for stage, _ in recipe.steps:  # every model a stage writes opens as a MeshLab project
        if stage.name in ("fuse", "simplify"):
            assert_mesh_project(out / stage.name)
    if path.stem == "demo":
        assert_demo_model_upright(out)
    if path.stem == "bunny":  # the Stanford frame is y up; six scans were taken on a turntable
        from slscan.register.frame import read_frame

        frame = read_frame(out / "register" / "registration.json")
        assert frame.up_from == "turntable"
        assert set(frame.turntable_views) == {f"bun{a:03d}" for a in (0, 45, 90, 180, 270, 315)}
        assert (frame.object_from_reference[:3, :3] @ [0.0, 1.0, 0.0])[1] > 0.99


def assert_mlp_files_exist(project: Path) -> None:
    """Every file a MeshLab project names exists relative to the project, as MeshLab itself
    resolves it (no lenient search in other folders, no absolute or parent paths)."""
    root = ET.parse(project).getroot()
    named = [e.get("filename") for e in root.iter("MLMesh")] + [e.get("fileName") for e in root.iter("Plane")]
    assert named and all(named), f"{project}: entries without a file name"
    for name in named:
        assert not Path(name).is_absolute() and ".." not in Path(name).parts, f"{project}: {name}"
        assert (project.parent / name).is_file(), f"{project}: names {name}, which is not beside it"


def assert_mesh_project(folder: Path) -> None:
    """``mesh.mlp`` opens ``mesh.ply`` as it is (identity matrix) in MeshLab (pymeshlab)."""
    import numpy as np
    import pymeshlab

    from slscan.fuse import read_mesh
    from slscan.register.meshlab import read_mlp

    ((mesh_file, matrix),) = read_mlp(folder / "mesh.mlp")
    assert mesh_file == folder / "mesh.ply" and np.array_equal(matrix, np.eye(4))
    ms = pymeshlab.MeshSet()
    ms.load_project(str(folder / "mesh.mlp"))
    assert ms.current_mesh().face_number() == len(read_mesh(mesh_file).faces)


def assert_demo_model_upright(out: Path) -> None:
    """The demo's model is written in the upright object frame: the figurine's up (the
    scene's -y, the turntable axis) is +Y, it stands on y = 0, and the glb is the OBJ
    scaled to metres."""
    import numpy as np
    import trimesh

    from slscan.fuse import read_mesh
    from slscan.register.frame import read_frame
    from slscan.virtual.scenes import builtin_object

    frame = read_frame(out / "register" / "registration.json")
    assert frame is not None and frame.up_from == "turntable"
    assert len(frame.turntable_views) == 8
    up = frame.object_from_reference[:3, :3] @ [0.0, -1.0, 0.0]  # the reference: the scene's frame
    assert np.degrees(np.arccos(np.clip(up[1], -1, 1))) < 1.0
    scene_height = np.ptp(builtin_object().vertices[:, 1])
    for mesh_file in [out / "fuse" / "mesh.ply", out / "simplify" / "mesh.ply"]:  # within a voxel (2 mm, reduced)
        v = read_mesh(mesh_file).vertices
        assert abs(np.percentile(v[:, 1], 0.1)) < 2.5, mesh_file
        assert np.percentile(v[:, 1], 99.9) == pytest.approx(scene_height, rel=0.05), mesh_file
    obj = trimesh.load(out / "texture" / "model.obj", force="mesh", process=False, maintain_order=True)
    glb = trimesh.load(out / "texture" / "model.glb", force="mesh", process=False)
    np.testing.assert_allclose(np.sort(glb.vertices[:, 1]) * 1000.0, np.sort(obj.vertices[:, 1]), atol=1e-3)
    assert abs(np.percentile(obj.vertices[:, 1], 0.1)) < 2.5


def test_a_changed_setting_reruns_that_stage_and_those_after_it(tmp_path):
    demo = Path(__file__).parents[2] / "recipes" / "demo.toml"
    out = tmp_path / "run"
    run_recipe(load_recipe(demo, reduced=True), out)
    ran = lambda runs: {r.stage: r.ran for r in runs}
    runs = run_recipe(load_recipe(demo, reduced=True, overrides=["decode.estimator=centroid"]), out)
    model = {"register": True, "fuse": True, "simplify": True, "texture": True}
    # decode changed: it and what reads its range maps run; lights does not depend on it
    assert ran(runs) == {"capture": False, "decode": True, "lights": False, "albedo": True, **model}
    runs = run_recipe(load_recipe(demo, reduced=True, overrides=["decode.estimator=centroid", "texture.size=256"]),
                      out)
    assert ran(runs) == {"capture": False, "decode": False, "lights": False, "albedo": False,
                         "register": False, "fuse": False, "simplify": False, "texture": True}
    runs = run_recipe(load_recipe(demo, reduced=True, overrides=["capture.seed=7"]), out)
    assert ran(runs) == {"capture": True, "decode": True, "lights": False, "albedo": True, **model}
    # a stage whose record is gone is run again; what reads it only if its result changed
    (out / "decode.stage.json").unlink()
    runs = run_recipe(load_recipe(demo, reduced=True, overrides=["capture.seed=7"]), out)
    assert ran(runs) == {"capture": False, "decode": True, "lights": False, "albedo": False,
                         **{k: False for k in model}}


@pytest.mark.parametrize(
    "data,message",
    [
        ({"capture": {"scenes": "tile"}}, "[capture]: unknown key 'scenes'"),
        ({"capture": {"views": "two"}}, "[capture].views: expected an integer"),
        ({"capture": {"sensor": {"exposure": "high"}}}, "[capture].sensor.exposure: expected a number"),
        ({"capture": {"sensor": {"bit_depth": 12}}}, "bit depth must be 8 or 16"),
        ({"laser": {}}, "unknown stage 'laser'"),
        ({"decode": {}}, "stage 'decode' needs a session"),
        ({"recipe": {"colour": "red"}, "capture": {}}, "[recipe] unknown key 'colour'"),
    ],
)
def test_bad_recipes_name_the_key(data, message):
    with pytest.raises(SlscanError) as exc:
        parse_recipe(data, where="r.toml")
    assert message in str(exc.value)


def test_overrides_are_typed_and_checked():
    recipe = parse_recipe({"capture": {}}, where="r.toml",
                          overrides=["capture.views=3", "capture.scene=tile", "capture.sensor.noise=false"])
    config = recipe.steps[0][1]
    assert (config.views, config.scene, config.sensor.noise) == (3, "tile", False)
    with pytest.raises(SlscanError, match="expected KEY=VALUE"):
        parse_recipe({"capture": {}}, where="r.toml", overrides=["capture.views"])


def test_toml_writer_round_trips():
    data = {"a": {"x": 1, "y": [1.5, 2.0], "s": 'say "hi"', "b": True, "n": {"deep": [[1, 2], [3, 4]]}}}
    assert tomllib.loads(dumps_toml(data)) == data


def test_model_stages_stream_to_rerun(shared_data, tmp_path):
    """register, fuse and simplify in a recipe log what `slscan register/fuse` log."""
    from rerun.chunk import RrdReader

    from slscan.viewer.recording import open_recording

    bunny = Path(__file__).parents[2] / "recipes" / "bunny.toml"
    recording = tmp_path / "bunny.rrd"
    with open_recording(save=recording) as rec:
        run_recipe(load_recipe(bunny, reduced=True), tmp_path / "run", rec=rec)
    paths = {c.entity_path for c in RrdReader(recording).stream().to_chunks()}
    assert {"/object/scans/bun000", "/object/scans/bun000/mesh", "/object/model/fused",
            "/object/model/simplified"} <= paths, sorted(paths)
    assert any(p.startswith("/plot/register/rmse/") for p in paths)


def test_a_file_a_setting_names_is_part_of_the_fingerprint(tmp_path, monkeypatch):
    """Editing a pose or rig file in place reruns the stage, as a changed setting does."""
    from dataclasses import dataclass
    from types import SimpleNamespace

    from slscan.recipe.runner import _fingerprint

    @dataclass
    class Config:
        scene_pose: str = "pose.json"
        nested: tuple = ("rig.json", "object")

    monkeypatch.chdir(tmp_path)
    stage = SimpleNamespace(name="capture")
    without = _fingerprint(stage, Config(), {})
    (tmp_path / "pose.json").write_text("[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]")
    first = _fingerprint(stage, Config(), {})
    assert first != without and _fingerprint(stage, Config(), {}) == first
    (tmp_path / "pose.json").write_text("[[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]")
    second = _fingerprint(stage, Config(), {})
    assert second != first
    (tmp_path / "rig.json").write_text("{}")
    assert _fingerprint(stage, Config(), {}) != second


def test_shipped_recipes_are_found_by_name_from_any_folder(tmp_path, monkeypatch):
    from slscan.recipe.runner import find_recipe, shipped_recipe, shipped_recipes

    monkeypatch.chdir(tmp_path)  # no recipes/ here
    assert set(shipped_recipes()) == {p.stem for p in RECIPES}
    demo = shipped_recipe("demo")
    assert demo.read_text() == (Path(__file__).parents[2] / "recipes" / "demo.toml").read_text()
    for spec in ("demo", "demo.toml", "recipes/demo.toml", Path("recipes") / "demo.toml"):
        assert find_recipe(spec) == demo, spec
    with pytest.raises(SlscanError, match=r"nosuch: recipe not found \(slscan's own recipes, by name: .*demo"):
        find_recipe("nosuch")
    with pytest.raises(SlscanError, match=r"elsewhere/demo\.toml: recipe not found"):
        find_recipe("elsewhere/demo.toml")  # a path elsewhere is that path, never a shipped recipe
    (tmp_path / "recipes").mkdir()
    mine = tmp_path / "recipes" / "demo.toml"
    mine.write_text('[recipe]\nname = "mine"\nstages = ["capture"]\n')
    assert find_recipe("recipes/demo.toml") == Path("recipes/demo.toml")  # a file here wins
    assert load_recipe(find_recipe("recipes/demo.toml")).name == "mine"


def test_slscan_run_takes_a_recipe_name_from_any_folder(tmp_path, monkeypatch, capsys):
    """`slscan run demo` and `slscan run recipes/demo.toml` outside the source tree load the
    shipped recipe (stopped here at an unknown setting, which names the file it came from)."""
    from slscan.cli import main
    from slscan.recipe.runner import shipped_recipe

    monkeypatch.chdir(tmp_path)
    for spec in ("demo", "recipes/demo.toml"):
        assert main(["run", spec, "--set", "capture.no_such_setting=1", "--out", "run"]) == 2
        err = " ".join(capsys.readouterr().err.split())
        assert f"{shipped_recipe('demo')}: [capture]: unknown key 'no_such_setting'" in err
    assert not (tmp_path / "run").exists()
    assert main(["run", "nosuch", "--out", "run"]) == 2
    assert "nosuch: recipe not found" in capsys.readouterr().err
