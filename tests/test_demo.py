"""slscan demo: the demo recipe, run by the recipe runner, at reduced size; its folders and
its recording, checked against every view of the pipeline layout."""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from slscan.capture.session import load_session
from slscan.cli import demo_overrides, main
from slscan.decode.rangemap import read_ply
from slscan.errors import SlscanError
from slscan.recipe.runner import load_recipe, shipped_recipe
from slscan.viewer.layouts import pipeline_blueprint

ROOT = Path(__file__).parents[1]
STAGES = ["capture", "decode", "lights", "albedo", "register", "fuse", "simplify", "texture"]


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[Path, Path]:
    """``slscan demo --reduced --save``, run once for the module: (OUT, the .rrd)."""
    root = tmp_path_factory.mktemp("demo")
    out, rrd = root / "demo-scan", root / "demo-scan.rrd"
    assert main(["demo", "--out", str(out), "--reduced", "--quiet", "--save", str(rrd)]) == 0
    return out, rrd


def test_the_demo_is_the_demo_recipe():
    assert shipped_recipe("demo").read_text() == (ROOT / "recipes" / "demo.toml").read_text()
    assert [s.name for s, _ in load_recipe(shipped_recipe("demo")).steps] == STAGES
    with pytest.raises(SlscanError, match="not among slscan's recipes"):
        shipped_recipe("no-such-recipe")


def test_demo_options_are_recipe_overrides():
    recipe = load_recipe(shipped_recipe("demo"), overrides=demo_overrides(views=3, scale=0.25))
    config = {s.name: c for s, c in recipe.steps}
    capture = config["capture"]
    assert (capture.views, capture.camera_scale, capture.projector_scale, capture.levels) == (
        3,
        0.25,
        0.25,
        7,
    )
    assert config["fuse"].voxel_size == 2.0
    # the recipe's own values at its default scale: the options change nothing there
    default = load_recipe(shipped_recipe("demo"))
    assert (
        load_recipe(shipped_recipe("demo"), overrides=demo_overrides(views=8, scale=0.5)).resolved()
        == default.resolved()
    )
    with pytest.raises(SlscanError, match="--scale"):
        demo_overrides(scale=3)


def test_the_demo_writes_the_recipe_folders_and_a_textured_model(demo, tmp_path, capsys):
    from slscan.texture.export import glb_summary

    out, rrd = demo
    recipe = load_recipe(shipped_recipe("demo"), reduced=True)
    # what `slscan run recipes/demo.toml --reduced` writes, and nothing else
    assert {p.name for p in out.iterdir()} == {
        *STAGES,
        *(f"{s}.stage.json" for s in STAGES),
        "recipe.resolved.toml",
    }
    assert tomllib.loads((out / "recipe.resolved.toml").read_text()) == recipe.resolved()
    glb = glb_summary(out / "texture" / "model.glb")
    assert glb["faces"] > 10_000 and glb["has_uv"] and glb["texture_size"] is not None
    session = load_session(out / "capture")
    assert len(session.views) == 8
    view = session.views[0]
    assert len(view.pattern_images()) == 2 + 7 and len(view.lit_images()) == 6
    assert rrd.stat().st_size > 10_000
    range_map = read_ply(out / "decode" / "view_000.ply")
    assert len(range_map.faces) > 1000
    assert main(["info", str(out / "capture")]) == 0
    assert "view_000" in capsys.readouterr().out
    # decoding again from the command line gives the same range map
    assert main(["decode", str(out / "capture"), "--out", str(tmp_path / "again"), "--quiet"]) == 0
    # it says how many line samples it left out at paint edges (the painted figurine has some)
    assert re.search(r"paint edges: [1-9][\d,]* line samples dropped", capsys.readouterr().err)
    again = read_ply(tmp_path / "again" / "view_000.ply")
    np.testing.assert_array_equal(again.faces, range_map.faces)
    # trimming the line ends: fewer vertices, and the setting is recorded
    trimmed = tmp_path / "trimmed"
    assert (
        main(
            [
                "decode",
                str(out / "capture"),
                "--out",
                str(trimmed),
                "--quiet",
                "--trim-line-ends",
                "1",
            ]
        )
        == 0
    )
    assert len(read_ply(trimmed / "view_000.ply").vertices) < len(range_map.vertices)
    assert json.loads((trimmed / "range_maps.json").read_text())["config"]["trim_line_ends"] == 1
    # slscan view logs a result folder (here to a file instead of a viewer)
    for result in (out / "capture", out / "decode"):
        saved = tmp_path / f"{result.name}.rrd"
        assert main(["view", str(result), "--save", str(saved)]) == 0
        assert saved.stat().st_size > 10_000


# --- the recording against the pipeline layout ----------------------------------------------


def _entities(rrd: Path) -> dict[str, set[str]]:
    """Entity path (no leading slash) -> the names of the timelines it was logged on."""
    out: dict[str, set[str]] = defaultdict(set)
    for chunk in RrdReader(rrd).stream().to_chunks():
        out[chunk.entity_path.strip("/")] |= set(chunk.timeline_names)
    return out


def _rule_matches(rule: str, entity: str) -> bool:
    """Whether a resolved Rerun entity-path expression (``a/b``, ``a/**``, ``a/**/c``) matches."""
    pattern = ""
    for part in rule.strip("/").split("/"):
        pattern += "(?:/.+)?" if part == "**" else "/" + re.escape(part)
    return re.fullmatch(pattern, "/" + entity) is not None


def _split_contents(origin: str, contents) -> tuple[list[str], list[str]]:
    """(included, excluded) expressions of a view, ``$origin`` substituted."""
    if contents is None:
        contents = ["$origin/**"]
    elif isinstance(contents, str):
        contents = [contents]
    included, excluded = [], []
    for line in contents:
        line = str(line).strip()
        sign, _, expr = line.partition(" ") if line[:1] in "+-" else ("+", "", line)
        expr = expr.strip().replace("$origin", origin.strip("/"))
        (excluded if sign == "-" else included).append(expr)
    return included, excluded


def _code_views() -> list[tuple[str, str, list[str], list[str]]]:
    """(name, origin, included, excluded) of every view of :func:`pipeline_blueprint`."""
    views = []

    def walk(node) -> None:
        if isinstance(node, rrb.Container):
            for child in node.contents:
                walk(child)
        else:
            views.append(
                (node.name, str(node.origin), *_split_contents(str(node.origin), node.contents))
            )

    walk(pipeline_blueprint(STAGES).root_container)
    return views


def _rbl_views(path: Path) -> list[tuple[str, str, list[str], list[str]]]:
    """The same, read back from a saved blueprint file (``viewer_layouts/pipeline.rbl``)."""
    reader = RrdReader(path)
    fields: dict[str, dict[str, object]] = defaultdict(dict)
    for chunk in reader.stream(store=reader.blueprints()[0]).to_chunks():
        match = re.fullmatch(r"/?view/([^/]+)(/ViewContents)?", chunk.entity_path)
        if not match:
            continue
        batch = chunk.to_record_batch()
        for column in (
            "ViewBlueprint:space_origin",
            "ViewBlueprint:display_name",
            "ViewContents:query",
        ):
            if column in batch.schema.names:
                values = [v for v in batch.column(column).to_pylist() if v is not None]
                if values:
                    fields[match.group(1)][column] = values[-1]
    views = []
    for view_id, f in fields.items():
        origin = f.get("ViewBlueprint:space_origin", [""])[0]
        name = (f.get("ViewBlueprint:display_name") or [view_id])[0]
        views.append((name, origin, *_split_contents(origin, f.get("ViewContents:query"))))
    return views


def _unmatched(views, entities) -> list[str]:
    missing = []
    for name, origin, included, excluded in views:
        for rule in included:
            shown = [
                e
                for e in entities
                if _rule_matches(rule, e) and not any(_rule_matches(x, e) for x in excluded)
            ]
            if not shown:
                missing.append(f"{name!r} (origin {origin}): {rule}")
    return missing


def test_the_rule_matcher():
    assert _rule_matches("world/**", "world") and _rule_matches("world/**", "world/a/b")
    assert _rule_matches("world/scans/**/albedo", "world/scans/view_000/albedo")
    assert not _rule_matches("world/scans/**/albedo", "world/scans/view_000/mesh")
    assert not _rule_matches("world/camera", "world/camera/image")
    assert _split_contents("log", None) == (["log/**"], [])
    assert _split_contents("w", ["+ $origin/**", "- $origin/x/**"]) == (["w/**"], ["w/x/**"])


def test_every_view_of_the_pipeline_layout_shows_what_the_demo_logged(demo):
    _, rrd = demo
    entities = _entities(rrd)
    views = _code_views()
    assert len(views) > 20 and any(origin.startswith("plot/register") for _, origin, _, _ in views)
    missing = _unmatched(views, entities)
    assert not missing, (
        "views of pipeline_blueprint() that show nothing of the demo:\n"
        + "\n".join(missing)
        + "\nlogged:\n"
        + "\n".join(sorted(e for e in entities if not re.search(r"view_00[1-9]", e)))
    )


def test_the_saved_pipeline_layout_matches_the_demo_too(demo):
    _, rrd = demo
    views = _rbl_views(ROOT / "viewer_layouts" / "pipeline.rbl")
    assert len(views) == len(_code_views()), (
        "viewer_layouts/pipeline.rbl is stale: run  slscan layouts"
    )
    missing = _unmatched(views, _entities(rrd))
    assert not missing, (
        "views of viewer_layouts/pipeline.rbl that show nothing of the demo "
        "(stale? run  slscan layouts):\n" + "\n".join(missing)
    )


def test_the_recording_has_the_registration(demo):
    out, rrd = demo
    entities = _entities(rrd)
    registration = json.loads((out / "register" / "registration.json").read_text())
    assert registration["pairs"]
    for pair in registration["pairs"]:
        key = f"{pair['source']}-{pair['target']}"
        assert f"plot/register/overlap/{key}" in entities
        if pair["rmse_mm"] is not None and math.isfinite(pair["rmse_mm"]):
            assert f"plot/register/rmse/{key}" in entities
    # every scan at its initial (turntable) pose and at its registered pose: two steps of
    # the stage timeline on its transform
    for name in registration["poses"]:
        transforms = [e for e in entities if re.fullmatch(rf"[^/]+/scans/{name}", e)]
        assert len(transforms) == 1, transforms
        assert "stage" in entities[transforms[0]]
    stage_steps = set()
    for chunk in RrdReader(rrd).stream().to_chunks():
        if (
            re.fullmatch(r"/?[^/]+/scans/view_000", chunk.entity_path)
            and "stage" in chunk.timeline_names
        ):
            stage_steps |= set(chunk.to_record_batch().column("stage").to_pylist())
    assert {0, 1} <= stage_steps, stage_steps
