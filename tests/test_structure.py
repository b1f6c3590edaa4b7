"""The package's layering, read from the source with ``ast``: the viewer sits at the edge.

Stage code may call a logger in :mod:`slscan.viewer` (lazily, inside the function that
logs), but no viewer module imports a stage's pipeline or algorithm modules back: what
both need lives below both, in the shared modules listed in :data:`SHARED`.

Imports are counted wherever they are written, at module level or inside a function.
Imports under ``if TYPE_CHECKING:`` are left out: they name types for annotations and
never run, so they load no stage code and close no import cycle.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

import slscan

PACKAGE = Path(slscan.__file__).parent
VIEWER = "slscan.viewer"

SHARED = frozenset(
    {
        "slscan",  # the package: __version__
        "slscan._open3d",  # `import open3d` without Dash and Plotly (run by the package)
        "slscan.errors",
        "slscan.fsio",
        "slscan.ply",
        "slscan.meshes",  # mesh helpers, the textured-OBJ reader
        "slscan.colour",  # sRGB encoding, albedo PNGs
        "slscan.rig",  # camera, projector, lights; pixel rays
        "slscan.progress",
        "slscan.patterns",  # what the projector shows
        "slscan.patterns.flat",
        "slscan.patterns.graycode",
        "slscan.patterns.hybrid",
        "slscan.capture.session",  # the capture-session format
        "slscan.decode.samples",  # stripe samples and light planes (result types)
        "slscan.decode.rangemap",  # the range-map type and its PLY format
        "slscan.calibrate.target",  # boards, corner detections, board poses
        "slscan.calibrate.options",  # the calibrate stage's option vocabularies (board kinds, ...)
    }
)
"""Modules below both the stages and the viewer. Everything else outside
``slscan.viewer`` is stage code (calibrate, capture, decode, albedo, register, fuse,
simplify, texture, virtual, recipe, devices, cli, ...)."""


def _module_names() -> dict[str, tuple[Path, bool]]:
    """Dotted name -> (file, is a package) of every module of the package."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = ("slscan", *path.relative_to(PACKAGE).with_suffix("").parts)
        if parts[-1] == "__init__":
            out[".".join(parts[:-1])] = (path, True)
        else:
            out[".".join(parts)] = (path, False)
    return out


MODULES = _module_names()


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _owner(name: str) -> str | None:
    """The package module that ``import name`` loads last (``name`` or its nearest parent)."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def runtime_imports(module: str, *, type_checking: bool = False) -> list[tuple[str, int]]:
    """(imported slscan module, line) of every import in ``module`` that can run: at module
    level or in a function, not under ``if TYPE_CHECKING:`` (unless ``type_checking``).
    ``from a import b`` counts as an import of ``a.b`` when that is a module."""
    path, is_package = MODULES[module]
    package = module if is_package else module.rpartition(".")[0]
    found = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and _is_type_checking(child) and not type_checking:
                for sub in child.orelse:
                    visit(sub)
                continue
            if isinstance(child, ast.Import):
                found.extend((alias.name, child.lineno) for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    parent = package.split(".")[: len(package.split(".")) - child.level + 1]
                    base = ".".join(parent + ([child.module] if child.module else []))
                subs = [f"{base}.{a.name}" for a in child.names if f"{base}.{a.name}" in MODULES]
                found.extend((s, child.lineno) for s in subs)
                if len(subs) < len(child.names):
                    found.append((base, child.lineno))
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)))
    out = []
    for name, line in found:
        owner = _owner(name) if name == "slscan" or name.startswith("slscan.") else None
        if owner is not None and owner != module:
            out.append((owner, line))
    return out


def import_graph() -> dict[str, set[str]]:
    graph = defaultdict(set)
    for module in MODULES:
        graph[module].update(target for target, _ in runtime_imports(module))
    return graph


def strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Components of more than one module (Tarjan, iterative)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    out.append(component)
    return out


def _is_viewer(module: str) -> bool:
    return module == VIEWER or module.startswith(VIEWER + ".")


def test_graph_sees_the_stage_to_logger_calls():
    """Guard against a vacuous pass: lazy imports of loggers inside stage functions are found."""
    graph = import_graph()
    assert "slscan.viewer.log_calibrate" in graph["slscan.calibrate.pipeline"]
    assert "slscan.viewer.log_albedo" in graph["slscan.albedo.unshade"]
    assert "slscan.viewer.log_texture" in graph["slscan.texture.pipeline"]
    assert set(SHARED) <= set(MODULES), "SHARED names a module that does not exist"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _is_viewer(m)))
def test_viewer_imports_no_stage_code(module):
    bad = [
        f"{target} (line {line})"
        for target, line in runtime_imports(module)
        if not _is_viewer(target) and target not in SHARED
    ]
    assert not bad, f"{module} imports stage code: {', '.join(bad)}; move what it needs below both"


@pytest.mark.parametrize("module", sorted(SHARED))
def test_shared_modules_sit_below_stages_and_viewer(module):
    bad = [
        f"{target} (line {line})"
        for target, line in runtime_imports(module)
        if target not in SHARED
    ]
    assert not bad, f"shared module {module} imports {', '.join(bad)}"


def test_no_import_cycle_through_the_viewer():
    mixed = [
        sorted(c)
        for c in strongly_connected(import_graph())
        if any(_is_viewer(m) for m in c) and not all(_is_viewer(m) for m in c)
    ]
    assert not mixed, f"import cycles between stage code and the viewer: {mixed}"


def test_texture_takes_no_code_from_the_albedo_stage():
    """The texture stage reads the albedo stage's files; colour and camera helpers sit below both."""
    bad = [
        f"{module} -> {target} (line {line})"
        for module in MODULES
        if module.startswith("slscan.texture")
        for target, line in runtime_imports(module)
        if target.startswith("slscan.albedo")
    ]
    assert not bad, ", ".join(bad)


# --- inside the viewer package: paths and timelines below, loggers and layouts beside ----------

LOGGERS = sorted(m for m in MODULES if m.startswith(f"{VIEWER}.log"))
BELOW_VIEWER = frozenset({f"{VIEWER}.paths", f"{VIEWER}.recording"})
"""What both the loggers and the layouts use: entity paths, timelines, recording streams."""


def test_the_viewer_package_has_no_import_cycle():
    graph = import_graph()
    viewer = {m: {t for t in graph[m] if _is_viewer(t)} for m in MODULES if _is_viewer(m)}
    assert len(viewer) > 8 and f"{VIEWER}.log_albedo" in LOGGERS  # the graph sees the package
    cycles = [sorted(c) for c in strongly_connected(viewer)]
    assert not cycles, f"import cycles inside slscan.viewer: {cycles}"
    # and none through stage code either (a viewer module in any cycle of the whole package)
    mixed = [sorted(c) for c in strongly_connected(graph) if any(_is_viewer(m) for m in c)]
    assert not mixed, f"import cycles through slscan.viewer: {mixed}"


def test_strongly_connected_finds_a_cycle():
    """Guard against a vacuous pass of the cycle tests."""
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]


@pytest.mark.parametrize("module", LOGGERS)
def test_no_logger_imports_a_pipeline_or_a_layout(module):
    """Loggers sit below the stages: no stage pipeline, not even for a type annotation, and
    no blueprint (the layouts import the loggers' entity paths, not the loggers)."""
    bad = [
        f"{target} (line {line})"
        for target, line in runtime_imports(module, type_checking=True)
        if target.endswith(".pipeline") or target == f"{VIEWER}.layouts"
    ]
    assert not bad, f"{module} imports {', '.join(bad)}"


def test_layouts_import_only_paths_and_timelines():
    module = f"{VIEWER}.layouts"
    bad = [
        f"{target} (line {line})"
        for target, line in runtime_imports(module, type_checking=True)
        if _is_viewer(target) and target not in BELOW_VIEWER
    ]
    assert not bad, f"{module} imports {', '.join(bad)}: blueprints address slscan.viewer.paths only"
    for below in BELOW_VIEWER:
        assert not [t for t, _ in runtime_imports(below, type_checking=True) if _is_viewer(t)
                    and t not in BELOW_VIEWER], f"{below} must not import loggers or layouts"
