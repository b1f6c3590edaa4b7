"""Run a recipe: stages in order, each skipped when its inputs and configuration are unchanged.

Each stage writes ``OUT/<stage>/``; beside it ``OUT/<stage>.stage.json`` records the
stage's fingerprint (its resolved configuration, the fingerprints of its inputs and the
slscan version), its summary, its time, and a manifest of every file it wrote (path, size,
modification time, SHA-256). A stage whose fingerprint matches the record, and whose files
are still the ones it wrote, is not run again. ``OUT/recipe.resolved.toml`` holds the
recipe with every default filled in and every ``--set`` applied.

The content check on resume is cheap: each file's size and modification time are compared
with the manifest, and only a file whose time differs but size matches (copied, touched,
restored from a backup) is read and hashed again; a file whose hash still matches has its
new time written to the record. A file changed, truncated, gone or added (hidden files are
not results and are ignored) makes the stage run again, with a line saying which file.
A stage run again this way makes the same files from the same inputs (stages are
deterministic, up to the timings their summaries record), so the stages after it keep
their fingerprints and are not run again; a changed setting or input reruns them as
before. A damaged record, or one written before manifests existed, is not trusted: its
stage runs again, once.

Temporaries left by a run that was killed (``.NAME.partial-PID-…``, see
:func:`slscan.fsio.stale_leftovers`) are removed at the start of the next run; a live
writer's are left alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from slscan import __version__
from slscan.errors import SlscanError
from slscan.fsio import (
    atomic_output_file,
    output_lock,
    read_json,
    remove_stale_leftovers,
    write_bytes,
    write_json,
)
from slscan.recipe.config import dumps_toml, from_mapping, parse_override, set_in, to_mapping
from slscan.recipe.stages import SUMMARIES, Stage, StageContext, stages

RECIPE_KEYS = ("name", "description", "stages", "out", "reduced")
MANIFEST_HASH = "sha256"
"""Hash of the output manifests: with the CPU's SHA extensions hashlib's SHA-256 runs at
about 1.5 GB/s, three times BLAKE2b's speed. Hashing every output on each resume would
cost 0.53 s for the paper recipe at 4 views (199 files, 394 MB, from the page cache; far
more from a cold disk, and a 146-view scan holds gigabytes), so a resume compares sizes
and times (7 ms for those 199 files) and hashes only files whose time alone changed;
writing the manifest once costs 0.37 s there."""

log = logging.getLogger(__name__)


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
    if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
        raise SlscanError(f"{where}: recipe.stages: expected a list of stage names, e.g. ['capture'], got {names!r}")
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
    except UnicodeDecodeError as exc:
        raise SlscanError(f"{path}: not valid TOML (not UTF-8 text: byte {exc.start})") from None
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


def shipped_recipes() -> list[str]:
    """Names of the recipes that ship with slscan (``demo``, ``paper``, ...), sorted."""
    try:
        folder = shipped_recipe("demo").parent
    except SlscanError:
        return []
    return sorted(p.stem for p in folder.glob("*.toml"))


def find_recipe(spec: str | os.PathLike) -> Path:
    """The recipe file ``spec`` names, from any current folder.

    An existing file is itself. Otherwise a bare name (``demo``, ``demo.toml``) or a path
    into a ``recipes/`` folder that is not here (``recipes/demo.toml``, as the examples
    write it, run outside the source tree) is the recipe shipped with slscan of that name
    (:func:`shipped_recipe`).

    Raises
    ------
    SlscanError
        Neither a file nor a shipped recipe; the message lists the shipped ones.
    """
    path = Path(spec)
    if path.is_file():
        return path
    if path.is_dir():
        raise SlscanError(f"{path}: is a folder; expected a recipe file (TOML) or a recipe's name")
    parts = path.parts
    by_name = not path.is_absolute() and (
        len(parts) == 1 or (len(parts) == 2 and parts[0] == "recipes")
    ) and path.suffix in ("", ".toml")
    names = shipped_recipes()
    stem = path.name[: -len(".toml")] if path.suffix == ".toml" else path.name
    if by_name and stem in names:
        return shipped_recipe(stem)
    shipped = f" (slscan's own recipes, by name: {', '.join(names)})" if names else ""
    raise SlscanError(f"{path}: recipe not found{shipped}")


def _fingerprint(stage: Stage, config: Any, inputs: dict[str, str]) -> str:
    mapping = to_mapping(config)
    blob = json.dumps({"stage": stage.name, "config": mapping, "inputs": inputs,
                       "files": _referenced_files(mapping), "slscan": __version__}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def _referenced_files(value: Any) -> dict[str, str]:
    """SHA-256 of every existing file a setting names (a user mesh, ``capture.scene_pose``,
    ``capture.rig_file``...), by the setting's text: editing such a file in place changes
    the stage's fingerprint as a changed setting does."""
    found: dict[str, str] = {}
    if isinstance(value, dict):
        for v in value.values():
            found.update(_referenced_files(v))
    elif isinstance(value, (list, tuple)):
        for v in value:
            found.update(_referenced_files(v))
    elif isinstance(value, str) and ("." in value or "/" in value) and len(value) < 4096:
        try:
            if Path(value).is_file():
                found[value] = _hash_file(Path(value))
        except OSError:
            pass
    return found


def _hash_file(path: Path) -> str:
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, MANIFEST_HASH).hexdigest()


def _result_files(folder: Path) -> list[str]:
    """The files under ``folder`` (POSIX paths relative to it), hidden ones left out."""
    found = []
    for root, dirs, names in os.walk(folder):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        rel = Path(root).relative_to(folder)
        found += [(rel / n).as_posix() for n in names if not n.startswith(".")]
    return sorted(found)


def output_manifest(folder: str | os.PathLike) -> dict[str, dict[str, Any]]:
    """Every result file under ``folder``: relative path → size (bytes), mtime_ns, sha256."""
    folder = Path(folder)
    files = {}
    for rel in _result_files(folder):
        path = folder / rel
        st = path.stat()
        files[rel] = {"size": st.st_size, "mtime_ns": st.st_mtime_ns, MANIFEST_HASH: _hash_file(path)}
    return files


def manifest_digest(files: dict[str, dict[str, Any]]) -> str:
    """One digest of a manifest's paths, sizes and hashes (not of the times)."""
    blob = json.dumps([[rel, f["size"], f[MANIFEST_HASH]] for rel, f in sorted(files.items())])
    return hashlib.sha256(blob.encode()).hexdigest()


@dataclass(frozen=True)
class OutputCheck:
    """What :func:`check_outputs` found.

    problems : one line per file changed, gone or added (empty: the outputs are intact)
    files : the manifest with the times as found now (for files whose hash still matched)
    hashed_files, hashed_bytes : what had to be read (files whose time had changed)
    """

    problems: tuple[str, ...]
    files: dict[str, dict[str, Any]]
    checked_files: int
    hashed_files: int
    hashed_bytes: int
    seconds: float

    @property
    def refreshed(self) -> bool:
        return self.hashed_files > 0 and not self.problems


def check_outputs(folder: str | os.PathLike, files: dict[str, dict[str, Any]], *, label: str = "") -> OutputCheck:
    """Compare ``folder`` with the manifest ``files`` (see :func:`output_manifest`), cheaply.

    A file whose size and mtime_ns are as recorded is taken as unchanged; one whose size
    differs has changed; one whose time alone differs is hashed. ``label`` prefixes the
    paths in the problem lines (e.g. ``"decode/"``).
    """
    t = time.perf_counter()
    folder = Path(folder)
    problems = []
    now = {}
    hashed = hashed_bytes = 0
    for rel, want in files.items():
        path = folder / rel
        try:
            st = path.stat()
        except FileNotFoundError:
            problems.append(f"{label}{rel} is gone since it was written")
            continue
        except OSError as exc:
            problems.append(f"{label}{rel} cannot be read ({exc.strerror})")
            continue
        if st.st_size != want.get("size"):
            problems.append(f"{label}{rel} changed since it was written (size {want.get('size')} → {st.st_size})")
            continue
        entry = dict(want)
        if st.st_mtime_ns != want.get("mtime_ns"):
            hashed += 1
            hashed_bytes += st.st_size
            try:
                digest = _hash_file(path)
            except OSError as exc:
                problems.append(f"{label}{rel} cannot be read ({exc.strerror})")
                continue
            if digest != want.get(MANIFEST_HASH):
                problems.append(f"{label}{rel} changed since it was written (same size, other content)")
                continue
            entry["mtime_ns"] = st.st_mtime_ns
        now[rel] = entry
    for rel in _result_files(folder):
        if rel not in files:
            problems.append(f"{label}{rel} appeared since the stage wrote its folder")
    return OutputCheck(tuple(problems), now, len(files), hashed, hashed_bytes, time.perf_counter() - t)


def _read_record(path: Path) -> tuple[dict[str, Any], str]:
    """The stage record at ``path`` ({} when there is none) and why it is unusable ("" if it is usable)."""
    if not path.is_file():
        return {}, ""
    try:
        record = read_json(path)
    except SlscanError:
        return {}, f"its record {path.name} is damaged"
    if not isinstance(record, dict):
        return {}, f"its record {path.name} is damaged"
    return record, ""


def _stale_reason(stage: Stage, folder: Path, record: dict[str, Any]) -> tuple[str, OutputCheck | None]:
    """Why a stage whose fingerprint matches its record must run again ("" if it need not)."""
    if not folder.is_dir():
        return f"its folder {stage.name}/ is gone", None
    outputs = record.get("outputs")
    if not isinstance(outputs, dict) or not isinstance(outputs.get("files"), dict) \
            or outputs.get("hash") != MANIFEST_HASH:
        return "its record predates content checks of the outputs", None
    check = check_outputs(folder, outputs["files"], label=f"{stage.name}/")
    if not check.problems:
        return "", check
    more = f" (and {len(check.problems) - 1} more)" if len(check.problems) > 1 else ""
    return check.problems[0] + more, check


@dataclass(frozen=True)
class StageRun:
    stage: str
    ran: bool
    seconds: float
    summary: dict[str, Any]
    out: Path
    reason: str = ""
    """Why a stage with an unchanged fingerprint ran again (e.g. an output file changed)."""
    check: OutputCheck | None = None
    """The content check of a stage's outputs on resume, when one was made."""


class Reporter:
    """What the runner tells its caller; the CLI shows it with progress bars."""

    def stage_started(self, stage: Stage, total: int) -> None: ...

    def step(self, label: str) -> None: ...

    def stage_finished(self, run: StageRun) -> None: ...

    def note(self, text: str) -> None:
        """A line worth telling the user (a stage runs again because its outputs changed)."""


def _note(reporter: Any, text: str) -> None:
    log.info(text)
    note = getattr(reporter, "note", None)
    if note is not None:
        note(text)


def run_recipe(recipe: Recipe, out: str | os.PathLike, *, force: bool = False, rec=None,
               reporter: Reporter | None = None, given: dict[str, Path] | None = None,
               unrecorded: tuple[str, ...] = (), executor=None) -> list[StageRun]:
    """Run ``recipe`` into folder ``out``, resuming: unchanged stages are not run again.

    given : results already at hand by kind (e.g. ``{"session": recorded_capture}``); the
        stages that would provide them are not run and later stages read these folders
    unrecorded : kinds of result whose stages do not log to ``rec``
    executor : where per-view stages run (:class:`slscan.executor.Executor`)

    ``out`` is held (:func:`slscan.fsio.output_lock`) while the recipe runs: a second run
    into the same folder at the same time fails instead of mixing its stages with these.
    """
    with output_lock(out):
        return _run_recipe(recipe, Path(out), force=force, rec=rec, reporter=reporter, given=given,
                           unrecorded=unrecorded, executor=executor)


def _run_recipe(recipe: Recipe, out: Path, *, force: bool, rec, reporter: Reporter | None,
                given: dict[str, Path] | None, unrecorded: tuple[str, ...], executor) -> list[StageRun]:
    given = {k: Path(v) for k, v in (given or {}).items()}
    reporter = reporter or Reporter()
    made = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SlscanError(f"{out}: cannot write here ({exc.strerror})") from None
    resolved = out / "recipe.resolved.toml"
    try:
        before = resolved.read_bytes()
    except OSError:
        before = None
    results: list[StageRun] = []
    try:
        with atomic_output_file(resolved) as tmp:
            header = (f"# {recipe.name}: resolved by slscan {__version__}"
                      + (f" from {recipe.path}" if recipe.path else "") + "\n")
            tmp.write_text(header + dumps_toml(recipe.resolved()))
        _run_stages(recipe, out, results, force=force, rec=rec, reporter=reporter, given=given,
                     unrecorded=unrecorded, executor=executor)
    except BaseException:
        if not any(r.ran for r in results):  # refused before any stage wrote: leave things as they were
            if before is None:
                resolved.unlink(missing_ok=True)
                if made:
                    with contextlib.suppress(OSError):
                        out.rmdir()
            elif resolved.read_bytes() != before:
                write_bytes(resolved, before)
        raise
    return results


def _stage_context(recipe: Recipe, stage: Stage) -> str:
    """`` (stage [NAME] of RECIPE.toml)``: where a stage's error comes from."""
    return f" (stage [{stage.name}] of {recipe.path if recipe.path else 'recipe ' + repr(recipe.name)})"


def _run_stages(recipe: Recipe, out: Path, results: list[StageRun], *, force: bool, rec,
                reporter: Reporter, given: dict[str, Path], unrecorded: tuple[str, ...], executor) -> None:
    removed = remove_stale_leftovers(out)
    if removed:
        _note(reporter, f"removed {len(removed)} temporary file(s)/folder(s) left by an interrupted run: "
                        + ", ".join(p.name for p in removed[:3]) + (" …" if len(removed) > 3 else ""))
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
        record, damaged = _read_record(record_path)
        reason, check = "", None
        if damaged and not force:
            reason = damaged
        elif not force and record.get("fingerprint") == fingerprint:
            reason, check = _stale_reason(stage, folder, record)
        if not force and not reason and record.get("fingerprint") == fingerprint:
            if check.refreshed:  # same content, new times (copied, touched): next time is cheap again
                write_json(record_path, {**record, "outputs": {**record["outputs"], "files": check.files}})
            run = StageRun(stage.name, False, 0.0, record.get("summary", {}), folder, check=check)
        else:
            if reason:
                _note(reporter, f"{stage.name}: {reason}: running it again")
            record_path.unlink(missing_ok=True)  # a stage half-redone is never trusted
            reporter.stage_started(stage, stage.size(config))
            t = time.perf_counter()
            stage_rec = None if stage.provides in unrecorded else rec
            ctx = StageContext(folder, {k: v[0] for k, v in inputs.items()}, stage_rec, reporter.step, executor)
            try:
                summary = stage.run(ctx, config)
            except SlscanError as exc:
                raise SlscanError(f"{exc}{_stage_context(recipe, stage)}") from None
            seconds = time.perf_counter() - t
            files = output_manifest(folder)
            digest = manifest_digest(files)
            write_json(record_path, {"stage": stage.name, "fingerprint": fingerprint, "seconds": seconds,
                                     "summary": summary, "slscan": __version__,
                                     "outputs": {"hash": MANIFEST_HASH, "digest": digest, "files": files}})
            run = StageRun(stage.name, True, seconds, summary, folder, reason)
        reporter.stage_finished(run)
        results.append(run)
        provided[stage.provides] = (folder, fingerprint)


def describe_stages() -> str:
    """One line per stage for ``--help``."""
    return "\n".join(f"  {name:<10} {summary}" for name, summary in SUMMARIES.items())

