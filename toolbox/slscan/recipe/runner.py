"""Run a recipe: stages in order, each skipped when its inputs and configuration are unchanged.

Each stage writes ``OUT/<stage>/``; beside it ``OUT/<stage>.stage.json`` records the
stage's fingerprint (its resolved configuration, the fingerprints of its inputs and the
slscan version), its summary and its time. A stage whose fingerprint matches the record,
and whose folder is there, is not run again. ``OUT/recipe.resolved.toml`` holds the
recipe with every default filled in and every ``--set`` applied.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slscan import __version__
from slscan.errors import SlscanError
from slscan.fsio import atomic_output_file, read_json, write_json
from slscan.recipe.config import dumps_toml, from_mapping, parse_override, set_in, to_mapping
from slscan.recipe.stages import Stage, StageContext, stages

RECIPE_KEYS = ("name", "description", "stages", "out", "reduced")


@dataclass(frozen=True)
class Recipe:
    """A parsed recipe: named stages with their resolved configurations, in order."""

    name: str
    description: str
    path: Path | None
    steps: tuple[tuple[Stage, Any], ...]
    out: str | None = None
    reduced: dict[str, Any] = field(default_factory=dict)

    def resolved(self) -> dict[str, Any]:
        """The recipe as plain data, every default filled in."""
        data: dict[str, Any] = {
            "recipe": {"name": self.name, "description": self.description,
                       "stages": [s.name for s, _ in self.steps]},
        }
        for stage, config in self.steps:
            data[stage.name] = to_mapping(config)
        return data


def parse_recipe(data: dict[str, Any], *, where: str, path: Path | None = None,
                 overrides: list[str] = (), reduced: bool = False) -> Recipe:
    """Build a :class:`Recipe` from TOML data; ``overrides`` are ``KEY=VALUE`` strings.

    reduced : apply the recipe's ``[recipe.reduced]`` overrides (its quick, small version)
    """
    data = json.loads(json.dumps(data))  # a deep copy we may modify
    head = data.pop("recipe", {})
    if not isinstance(head, dict):
        raise SlscanError(f"{where}: [recipe] must be a table")
    for key in head:
        if key not in RECIPE_KEYS:
            raise SlscanError(f"{where}: [recipe] unknown key {key!r} (known: {', '.join(RECIPE_KEYS)})")
    small = head.get("reduced", {})
    if reduced:
        for key, value in small.items():
            set_in(data, key.split("."), value)
    for text in overrides:
        keys, value = parse_override(text)
        if keys[0] == "recipe":
            raise SlscanError(f"--set {text}: the [recipe] table cannot be overridden")
        set_in(data, keys, value)
    known = stages()
    names = head.get("stages") or [n for n in known if n in data]
    for name in list(data) + list(names):
        if name not in known:
            raise SlscanError(f"{where}: unknown stage {name!r} (known: {', '.join(known)})")
    for name in data:
        if name not in names:
            raise SlscanError(f"{where}: [{name}] is configured but not in recipe.stages")
    if not names:
        raise SlscanError(f"{where}: the recipe has no stages")
    steps = []
    provided: set[str] = set()
    for name in names:
        stage = known[name]
        for need in stage.needs:
            if need not in provided:
                raise SlscanError(f"{where}: stage {name!r} needs a {need} from an earlier stage")
        table = data.get(name, {})
        if not isinstance(table, dict):
            raise SlscanError(f"{where}: [{name}] must be a table")
        steps.append((stage, from_mapping(stage.config_type, table, f"{where}: [{name}]")))
        provided.add(stage.provides)
    return Recipe(str(head.get("name", path.stem if path else "recipe")), str(head.get("description", "")),
                  path, tuple(steps), head.get("out"), small)


def load_recipe(path: str | os.PathLike, *, overrides: list[str] = (), reduced: bool = False) -> Recipe:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise SlscanError(f"{path}: recipe not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise SlscanError(f"{path}: not valid TOML ({exc})") from None
    return parse_recipe(data, where=str(path), path=path, overrides=list(overrides), reduced=reduced)


def shipped_recipe(name: str) -> Path:
    """Path of a recipe that ships with slscan, e.g. ``"demo"`` → ``recipes/demo.toml``.

    The repository's ``recipes/`` folder is installed as the package ``slscan.recipes``
    (see ``pyproject.toml``): in a wheel the files are copied into it, in an editable
    install it points at ``recipes/`` itself. An editable install made before that mapping
    existed has no ``slscan.recipes``; the source tree's ``recipes/`` is used then.
    """
    import importlib.resources

    try:
        folder = Path(str(importlib.resources.files("slscan.recipes")))
    except ModuleNotFoundError:
        import slscan

        folder = Path(slscan.__file__).resolve().parents[2] / "recipes"
        if not folder.is_dir():
            raise SlscanError(
                f"recipe {name!r}: slscan was installed without its recipes (no package slscan.recipes, "
                f"and no {folder} beside the source); reinstall slscan (pip install .)"
            ) from None
    path = folder / f"{name}.toml"
    if not path.is_file():
        raise SlscanError(f"recipe {name!r}: not among slscan's recipes ({path} not found)")
    return path


def _fingerprint(stage: Stage, config: Any, inputs: dict[str, str]) -> str:
    blob = json.dumps({"stage": stage.name, "config": to_mapping(config), "inputs": inputs,
                       "slscan": __version__}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


@dataclass(frozen=True)
class StageRun:
    stage: str
    ran: bool
    seconds: float
    summary: dict[str, Any]
    out: Path


class Reporter:
    """What the runner tells its caller; the CLI shows it with progress bars."""

    def stage_started(self, stage: Stage, total: int) -> None: ...

    def step(self, label: str) -> None: ...

    def stage_finished(self, run: StageRun) -> None: ...


def run_recipe(recipe: Recipe, out: str | os.PathLike, *, force: bool = False, rec=None,
               reporter: Reporter | None = None, given: dict[str, Path] | None = None,
               unrecorded: tuple[str, ...] = (), executor=None) -> list[StageRun]:
    """Run ``recipe`` into folder ``out``, resuming: unchanged stages are not run again.

    given : results already at hand by kind (e.g. ``{"session": recorded_capture}``); the
        stages that would provide them are not run and later stages read these folders
    unrecorded : kinds of result whose stages do not log to ``rec``
    executor : where per-view stages run (:class:`slscan.executor.Executor`)
    """
    given = {k: Path(v) for k, v in (given or {}).items()}
    out = Path(out)
    reporter = reporter or Reporter()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SlscanError(f"{out}: cannot write here ({exc.strerror})") from None
    with atomic_output_file(out / "recipe.resolved.toml") as tmp:
        header = (f"# {recipe.name}: resolved by slscan {__version__}"
                  + (f" from {recipe.path}" if recipe.path else "") + "\n")
        tmp.write_text(header + dumps_toml(recipe.resolved()))
    results: list[StageRun] = []
    provided: dict[str, tuple[Path, str]] = {}  # kind -> (folder, fingerprint)
    for stage, config in recipe.steps:
        if stage.provides in given:
            folder = given[stage.provides]
            digest = hashlib.sha256(str(folder.resolve()).encode()).hexdigest()
            provided[stage.provides] = (folder, digest)
            results.append(StageRun(stage.name, False, 0.0, {"given": str(folder)}, folder))
            reporter.stage_finished(results[-1])
            continue
        inputs = {need: provided[need] for need in stage.needs + stage.optional if need in provided}
        fingerprint = _fingerprint(stage, config, {k: v[1] for k, v in inputs.items()})
        folder = out / stage.name
        record_path = out / f"{stage.name}.stage.json"
        record = read_json(record_path) if record_path.is_file() else {}
        if not force and folder.is_dir() and record.get("fingerprint") == fingerprint:
            run = StageRun(stage.name, False, 0.0, record.get("summary", {}), folder)
        else:
            record_path.unlink(missing_ok=True)  # a stage half-redone is never trusted
            reporter.stage_started(stage, stage.size(config))
            t = time.perf_counter()
            stage_rec = None if stage.provides in unrecorded else rec
            ctx = StageContext(folder, {k: v[0] for k, v in inputs.items()}, stage_rec, reporter.step, executor)
            summary = stage.run(ctx, config)
            seconds = time.perf_counter() - t
            write_json(record_path, {"stage": stage.name, "fingerprint": fingerprint, "seconds": seconds,
                                     "summary": summary, "slscan": __version__})
            run = StageRun(stage.name, True, seconds, summary, folder)
        reporter.stage_finished(run)
        results.append(run)
        provided[stage.provides] = (folder, fingerprint)
    return results


def describe_stages() -> str:
    """One line per stage for ``--help``."""
    return "\n".join(f"  {s.name:<10} {s.summary}" for s in stages().values())

