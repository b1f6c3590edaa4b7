"""slscan demo: the demo recipe, run by the recipe runner, at reduced size; its folders and
its recording, checked against every view of the pipeline layout."""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections import defaultdict
from pathlib import Path

import cv2
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
LIGHTS_SCALE = 0.2
"""The light panel's camera scale in the test's demo; the scan's (reduced) is 0.25."""


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> tuple[Path, Path]:
    """``slscan demo --reduced --save``, run once for the module: (OUT, the .rrd)."""
    root = tmp_path_factory.mktemp("demo")
    out, rrd = root / "demo-scan", root / "demo-scan.rrd"
    # the light panel at another resolution than the scan (as at the demo's full size): two
    # cameras' intrinsics that must not overwrite each other
    assert main(["demo", "--out", str(out), "--reduced", "--quiet", "--save", str(rrd),
                 "--set", f"lights.scale={LIGHTS_SCALE}"]) == 0
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
    recipe = load_recipe(shipped_recipe("demo"), reduced=True, overrides=[f"lights.scale={LIGHTS_SCALE}"])
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
    """Whether a resolved Rerun entity-path expression (``a/b``, ``a/**``) matches, as the
    viewer matches it: ``**`` only as the last part (a subtree); elsewhere it is no wildcard."""
    parts = rule.strip("/").split("/")
    pattern = ""
    for k, part in enumerate(parts):
        pattern += "(?:/.+)?" if part == "**" and k == len(parts) - 1 else "/" + re.escape(part)
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
    # Rerun supports no ``**`` inside a path: such a rule shows nothing in the viewer
    assert not _rule_matches("world/scans/**/albedo", "world/scans/view_000/albedo")
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


# --- one entity tree per session, static data once ------------------------------------------


def _chunks(rrd: Path) -> list:
    return list(RrdReader(rrd).stream().to_chunks())


def _values(chunks, entity: str, timeline: str) -> set[int]:
    out: set[int] = set()
    for chunk in chunks:
        if chunk.entity_path.strip("/") == entity and timeline in chunk.timeline_names:
            out |= set(chunk.to_record_batch().column(timeline).to_pylist())
    return out


def _static(chunks, entity: str, component: str) -> list:
    return [v for c in chunks if c.is_static and c.entity_path.strip("/") == entity
            for v in c.to_record_batch().column(component).to_pylist()]


def test_each_session_logs_into_its_own_entities_and_timelines(demo):
    out, rrd = demo
    entities, chunks = _entities(rrd), _chunks(rrd)
    panel_timelines = {"lights_panel_view", "lights_panel_frame"}
    panel = {e for e in entities if e.startswith(("world/lights_panel/", "log/lights_panel/"))}
    assert "world/lights_panel/camera/image/capture" in panel
    for entity, timelines in entities.items():
        own = timelines - {"log_time"}
        if entity in panel:
            assert own <= panel_timelines, (entity, timelines)
        else:
            assert not own & panel_timelines, f"{entity} is logged on the light panel's timelines"
    # the scan's captures are the scan's views, each once: no panel frame among them
    views = len(load_session(out / "capture").views)
    assert _values(chunks, "world/camera/image/capture", "view") == set(range(views))
    assert _values(chunks, "world/lights_panel/camera/image/capture", "lights_panel_view") == set(
        range(len(load_session(out / "lights" / "session").views))
    )


def test_static_data_is_logged_once_and_each_camera_keeps_its_intrinsics(demo):
    out, rrd = demo
    chunks = _chunks(rrd)
    rows: dict[tuple[str, str], int] = defaultdict(int)
    for chunk in chunks:
        if chunk.is_static:
            batch = chunk.to_record_batch()
            for column in batch.schema.names:
                if ":" in column:  # a component, not a row id
                    rows[chunk.entity_path.strip("/"), column] += batch.num_rows
    twice = {f"{e} {c}": n for (e, c), n in rows.items() if n > 1}
    assert not twice, f"static data logged more than once: {twice}"
    for root, session in (("world", out / "capture"), ("world/lights_panel", out / "lights" / "session")):
        size = load_session(session).camera_size
        assert _static(chunks, f"{root}/camera/image", "Pinhole:resolution") == [[list(map(float, size))]]
    assert load_session(out / "capture").camera_size != load_session(out / "lights" / "session").camera_size


def test_whole_object_results_show_at_every_view(demo):
    out, rrd = demo
    chunks = _chunks(rrd)
    names = json.loads((out / "register" / "registration.json").read_text())["poses"]
    for name in names:  # the initial and the registered pose, both from the first view on
        assert _values(chunks, f"object/scans/{name}", "view") == {0}
        assert _values(chunks, f"object/scans/{name}", "stage") == {0, 1}
    for model in ("fused", "simplified"):
        assert _values(chunks, f"object/model/{model}", "view") == {0}


# --- what the user sees: the real viewer, headless ------------------------------------------

TABS = ("Capture", "Decode", "Albedo", "Register", "Texture")
MIN_FOREGROUND = 0.01
"""Share of a 2D or 3D view's pixels that must differ from its background: not blank."""


def _foreground(picture: np.ndarray, level: int = 40) -> np.ndarray:
    """(h, w) bool: pixels away from the view's background (its most common colour)."""
    flat = picture.reshape(-1, 3)
    colours, counts = np.unique(flat[:: max(1, len(flat) // 20000)], axis=0, return_counts=True)
    background = colours[np.argmax(counts)].astype(int)
    return np.abs(picture.astype(int) - background).max(axis=-1) > level


def _colourful(picture: np.ndarray) -> float:
    """Share of clearly coloured pixels: the painted figurine has them, the grey panel none."""
    p = picture.astype(int)
    return float(((p.max(axis=-1) - p.min(axis=-1) > 60) & (p.max(axis=-1) > 80)).mean())


def _upright_figurine(picture: np.ndarray) -> tuple[bool, str]:
    """One object, taller than wide, narrow head at the top and the wide base below."""
    mask = _foreground(picture, 60).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    if not len(areas):
        return False, "nothing drawn"
    biggest = 1 + int(np.argmax(areas))
    share = areas.max() / areas.sum()
    rows = np.flatnonzero((labels == biggest).any(axis=1))
    top, bottom = rows.min(), rows.max()
    widths = [np.ptp(np.flatnonzero(labels[r] == biggest)) for r in range(top, bottom + 1)]
    quarter = max(1, len(widths) // 4)
    head, base = float(np.mean(widths[:quarter])), float(np.mean(widths[-quarter:]))
    x, y, w, h = stats[biggest, :4]
    ok = share > 0.9 and h > w and head < 0.8 * base
    return ok, f"{share:.0%} in one piece, {w}x{h} px, head {head:.0f} px wide, base {base:.0f} px"


def test_every_tab_of_the_pipeline_layout_renders_what_the_user_expects(demo, tmp_path):
    from viewer.headless import HeadlessViewer  # tests/ is on sys.path (rootdir)

    _, rrd = demo
    blank, failures = [], []
    with HeadlessViewer(rrd, tmp_path) as viewer:
        for tab in TABS:
            views = viewer.show_tab("slscan pipeline", tab)
            assert views, tab
            viewer.set_time("view", 0)
            shots = {}  # at view 0, kept in tmp_path for a human look
            for view_id, kind, name in views:
                if kind in ("2D", "3D"):
                    shots[name] = viewer.screenshot(f"{tab} - {name}", view_id)
                    if _foreground(shots[name]).mean() < MIN_FOREGROUND:
                        blank.append(f"{tab}/{name}")
            if tab == "Capture":
                # the figurine's captures, whole: not the grey light panel, not a quarter of them
                for view in (0, 3):
                    if view:
                        viewer.set_time("view", view)
                    picture = shots["Capture"] if view == 0 else viewer.screenshot(
                        f"capture at view {view}", _view_id(views, "Capture"))
                    mask = _foreground(picture, 50)
                    ys, xs = np.nonzero(mask)
                    centre = (xs.mean() / mask.shape[1], ys.mean() / mask.shape[0]) if len(xs) else (0, 0)
                    if _colourful(picture) < 0.002 or not (0.35 < centre[0] < 0.65 and 0.3 < centre[1] < 0.7):
                        failures.append(f"Capture at view {view}: colourful share {_colourful(picture):.4f}, "
                                        f"object centre at {centre[0]:.2f}, {centre[1]:.2f} of the view")
            if tab == "Register":
                # one upright object, the same at every view of the scan
                seen = {0: shots["Range maps at their poses"]}
                for view in (0, 3, 7):
                    if view:
                        viewer.set_time("view", view)
                        seen[view] = viewer.screenshot(f"register at view {view}",
                                                       _view_id(views, "Range maps at their poses"))
                    ok, why = _upright_figurine(seen[view])
                    if not ok:
                        failures.append(f"Register at view {view}: {why}")
                for view in (3, 7):
                    change = np.abs(seen[view].astype(int) - seen[0]).mean()
                    if change > 1.0:
                        failures.append(f"Register: view {view} differs from view 0 by {change:.1f} levels")
        # the light panel's own captures, on its own timeline
        viewer.show_tab("slscan pipeline", "Albedo")
        views = viewer.show_tab("Albedo", "Light panel")
        viewer.set_time("lights_panel_view", 2)
        picture = viewer.screenshot("light panel", _view_id(views, "Light panel"))
        if _foreground(picture).mean() < 0.1 or _colourful(picture) > 0.001:
            failures.append(f"Light panel: {_foreground(picture).mean():.3f} of the view drawn, "
                            f"{_colourful(picture):.4f} coloured (the panel is grey)")
        # the views per texel, in the colours of the legend (not the raw counts 0-3: black)
        viewer.show_tab("slscan pipeline", "Texture")
        views = viewer.show_tab("Texture", "Views per texel")
        picture = viewer.screenshot("views per texel", _view_id(views, "Views per texel"))
        legend = json.loads((demo[0] / "texture" / "texture.json").read_text())["model"].get("view_count_legend")
        if legend is None:
            failures.append("texture.json: no view_count_legend")
        for label in ("1 view", "2 views") if legend else ():
            share = (np.abs(picture.astype(int) - legend[label]).max(axis=-1) <= 8).mean()
            if share < 0.005:
                failures.append(f"Views per texel: the colour of {label!r} covers {share:.4f} of the view")
        failures += [f"the viewer logged an error: {e.target}: {e.message[:200]}"
                     for e in viewer.client.get_logs() if e.level == "ERROR"]
    failures += [f"blank view: {name}" for name in blank]
    assert not failures, f"screenshots in {tmp_path}:\n" + "\n".join(failures)


def _view_id(views, name: str) -> str:
    return next(view_id for view_id, _, n in views if n == name)
