"""Resuming trusts nothing broken: damaged outputs are redone, killed runs leave no temporaries.

One small demo recipe (reduced, 3 views) is run once for the module as a chain of
``slscan run`` processes, each killed with SIGKILL at the next stage boundary and resumed;
the other cases damage copies of its finished folder and resume them in-process. A stage
run again because its files were damaged makes the same files again, so the stages after it
keep their fingerprints and do not run (tests/recipe/test_recipes.py checks that a changed
setting reruns them).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slscan import fsio
from slscan.recipe.runner import Reporter, check_outputs, load_recipe, run_recipe, shipped_recipe

OVERRIDES = ["capture.views=6"]  # fewer views at reduced size do not overlap: registration refuses them
STAGES = ["capture", "decode", "lights", "albedo", "register", "fuse", "simplify", "texture"]


class Notes(Reporter):
    """A reporter that keeps the runner's notes."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def note(self, text: str) -> None:
        self.lines.append(text)


def _recipe():
    return load_recipe(shipped_recipe("demo"), overrides=OVERRIDES, reduced=True)


def _resume(out: Path) -> tuple[dict[str, object], list[str]]:
    notes = Notes()
    runs = run_recipe(_recipe(), out, reporter=notes)
    return {r.stage: r for r in runs}, notes.lines


def _ran(runs: dict[str, object]) -> list[str]:
    return [s for s, r in runs.items() if r.ran]


def _leftovers(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if ".partial" in p.name or ".old-" in p.name]


def _state(out: Path, stage: str) -> tuple[int, int]:
    """(record's mtime_ns, folder's inode): both change when a stage runs again."""
    return (out / f"{stage}.stage.json").stat().st_mtime_ns, (out / stage).stat().st_ino


def _start(out: Path) -> subprocess.Popen:
    argv = [sys.executable, "-m", "slscan.cli", "run", str(shipped_recipe("demo")), "--reduced", "--quiet",
            "--out", str(out)] + [a for o in OVERRIDES for a in ("--set", o)]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _kill_when(proc: subprocess.Popen, ready, timeout: float = 300.0) -> bool:
    """SIGKILL ``proc`` (and its workers) as soon as ``ready()``; False if it ended first."""
    end = time.monotonic() + timeout
    while proc.poll() is None:
        if ready():
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            return True
        if time.monotonic() > end:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            raise AssertionError("the run neither reached the stage boundary nor ended")
        time.sleep(0.005)
    return False


@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> tuple[Path, list[dict]]:
    """Kill ``slscan run`` mid-capture, then at every stage boundary, resuming each time.

    Returns the finished folder and, per resume, what it found and what it changed.
    """
    out = tmp_path_factory.mktemp("killed") / "run"
    rounds = []
    proc = _start(out)
    killed = _kill_when(proc, lambda: any(out.glob(".capture.partial-*")))
    assert killed, "the capture stage should take long enough to be killed mid-way"
    rounds.append({"killed_in": "capture", "leftovers": _leftovers(out), "records": []})
    for stage in STAGES:
        done = [s for s in STAGES if (out / f"{s}.stage.json").is_file()]
        before = {s: _state(out, s) for s in done}
        left_before = _leftovers(out)
        proc = _start(out)
        killed = _kill_when(proc, lambda s=stage: (out / f"{s}.stage.json").is_file())
        output = proc.stdout.read()
        rounds.append({"stage": stage, "done_before": done, "before": before, "killed": killed,
                       "left_before": left_before, "rc": proc.returncode, "output": output,
                       "after": {s: _state(out, s) for s in done}})
    proc = _start(out)
    output, _ = proc.communicate(timeout=300)
    rounds.append({"final": True, "rc": proc.returncode, "output": output})
    return out, rounds


def test_kill_9_at_each_stage_boundary_resumes_only_the_interrupted_stage(chain):
    out, rounds = chain
    first, *middle, final = rounds
    assert first["leftovers"], "killed mid-capture: its temporary folder is left behind"
    for i, r in enumerate(middle):
        # everything finished before the kill is exactly as it was: not run again
        assert r["done_before"] == STAGES[:i], r["output"]
        assert r["after"] == r["before"], f"resume at {r['stage']} rewrote a finished stage:\n{r['output']}"
        assert (out / f"{r['stage']}.stage.json").is_file()
    assert all(r["killed"] for r in middle[:-1])  # the last may end on its own first
    # the leftovers of the kill mid-capture are gone from the next run on
    assert middle[0]["left_before"] and not any(p.exists() for p in middle[0]["left_before"])
    assert final["rc"] == 0, final["output"]
    assert "0 of 8 stage(s) run" in final["output"]
    assert not _leftovers(out)
    for stage in STAGES:  # every output is the one its record describes
        record = json.loads((out / f"{stage}.stage.json").read_text())
        assert not check_outputs(out / stage, record["outputs"]["files"]).problems
    assert (out / "texture" / "model.glb").stat().st_size > 0


@pytest.fixture()
def run(chain, tmp_path) -> Path:
    """A copy of the finished run (times kept, so nothing needs hashing)."""
    copy = tmp_path / "run"
    shutil.copytree(chain[0], copy)
    return copy


def test_an_unchanged_run_runs_nothing_and_hashes_nothing(run):
    runs, notes = _resume(run)
    assert not [s for s, r in runs.items() if r.ran] and not notes
    assert sum(r.check.hashed_files for r in runs.values()) == 0
    assert sum(r.check.checked_files for r in runs.values()) > 100


def test_a_truncated_output_runs_its_stage_again_naming_the_file(run):
    ply = run / "simplify" / "mesh.ply"
    size = ply.stat().st_size
    with open(ply, "r+b") as fh:
        fh.truncate(size // 2)
    runs, notes = _resume(run)
    assert notes == [(f"simplify: simplify/mesh.ply changed since it was written (size {size} → {size // 2}): "
                      "running it again")]
    assert _ran(runs) == ["simplify"]  # the same mesh again: texture keeps its fingerprint
    assert ply.stat().st_size == size
    again, notes = _resume(run)
    assert not any(r.ran for r in again.values()) and not notes


def test_a_same_size_corruption_is_found_by_its_hash(run):
    ply = run / "decode" / "view_001.ply"
    data = bytearray(ply.read_bytes())
    data[-100:] = bytes(100)
    ply.write_bytes(bytes(data))
    runs, notes = _resume(run)
    assert notes[0] == "decode: decode/view_001.ply changed since it was written (same size, other content): " \
                       "running it again"
    assert _ran(runs) == ["decode"]
    assert ply.read_bytes() != bytes(data)


def test_a_deleted_or_added_file_or_folder_runs_its_stage_again(run):
    (run / "texture" / "model.glb").unlink()
    (run / "fuse" / "extra.ply").write_bytes(b"ply\n")
    shutil.rmtree(run / "register")
    runs, notes = _resume(run)
    assert "texture: texture/model.glb is gone since it was written: running it again" in notes
    assert "fuse: fuse/extra.ply appeared since the stage wrote its folder: running it again" in notes
    assert "register: its folder register/ is gone: running it again" in notes
    assert _ran(runs) == ["register", "fuse", "texture"]
    assert not (run / "fuse" / "extra.ply").exists() and (run / "texture" / "model.glb").is_file()


def test_a_touched_file_is_hashed_once_and_hidden_files_are_ignored(run):
    png = next((run / "capture").rglob("*.png"))
    os.utime(png, ns=(time.time_ns(), time.time_ns()))
    (run / "decode" / ".DS_Store").write_bytes(b"finder")
    runs, notes = _resume(run)
    assert not any(r.ran for r in runs.values()) and not notes
    assert runs["capture"].check.hashed_files == 1
    again, _ = _resume(run)  # the record took the new time: nothing to hash now
    assert again["capture"].check.hashed_files == 0


def test_an_old_or_damaged_record_is_not_trusted(run):
    record = json.loads((run / "register.stage.json").read_text())
    del record["outputs"]
    (run / "register.stage.json").write_text(json.dumps(record))
    (run / "simplify.stage.json").write_text('{"stage": "simpl')
    runs, notes = _resume(run)
    assert "register: its record predates content checks of the outputs: running it again" in notes
    assert "simplify: its record simplify.stage.json is damaged: running it again" in notes
    assert _ran(runs) == ["register", "simplify"]


def test_leftovers_of_dead_writers_are_removed_and_never_results(run, tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    alive = subprocess.Popen(["sleep", "60"])
    try:
        stale = run / f".decode.partial-{dead.pid}-abcd1234"
        live = run / f".decode.partial-{alive.pid}-efgh5678"
        stale_file = run / f".decode.stage.json.partial-{dead.pid}-zz9.json"
        for folder in (stale, live):
            folder.mkdir()
            (folder / "view_000.ply").write_bytes(b"half")
        stale_file.write_text("{")
        legacy_old, legacy_new = run / ".fuse.partial-k2j4h5g6", run / ".fuse.partial-a1b2c3d4"
        legacy_old.mkdir(), legacy_new.mkdir()
        hour_ago = time.time() - fsio.LEGACY_LEFTOVER_AGE_S - 60
        os.utime(legacy_old, (hour_ago, hour_ago))
        hidden = run / "decode" / f".view_009.ply.partial-{dead.pid}-x1y2z3w4.ply"
        hidden.write_bytes(b"ply\n")
        assert [p.name for p in fsio.glob_results(run / "decode", "*.ply")] == [
            f"view_00{i}.ply" for i in range(6)]
        runs, notes = _resume(run)
        assert not any(r.ran for r in runs.values())  # a hidden file is no result of decode
        assert any(n.startswith("removed 3 temporary") for n in notes), notes
        assert not stale.exists() and not stale_file.exists() and not legacy_old.exists()
        assert live.exists() and legacy_new.exists()  # a live writer's, and a fresh one of unknown owner
    finally:
        alive.kill()
        alive.wait()


def test_a_leftover_whose_process_id_was_reused_is_stale():
    """In a container a resumed run may get the killed run's process id: a process that
    started after the temporary last changed (its ctime, which cannot be set back) is not
    its writer."""
    later = subprocess.Popen(["sleep", "60"])
    try:
        time.sleep(0.2)
        assert fsio._owner_alive(later.pid, time.time())  # changed while it runs: maybe its writer
        assert not fsio._owner_alive(later.pid, time.time() - 60)  # changed before it started
        assert not fsio._owner_alive(os.getpid(), time.time() - 3600)  # this very process: the same
    finally:
        later.kill()
        later.wait()


def _write_slowly(target: str, tag: str, files: int) -> None:
    with fsio.atomic_output_dir(target, overwrite=True) as tmp:
        for i in range(files):
            (tmp / f"part_{i:02d}.txt").write_text(tag)
            time.sleep(0.01)
        (tmp / "done.txt").write_text(tag)


def test_two_concurrent_writers_leave_one_whole_output(tmp_path):
    """Each writer's temporary is its own (named for its process): neither removes the
    other's; one may lose the final rename (an error), the output is always one whole
    writer's, and what a loser left is removed by the next write of that output."""
    import multiprocessing

    target = tmp_path / "out"
    ctx = multiprocessing.get_context("spawn")
    for _ in range(3):
        procs = [ctx.Process(target=_write_slowly, args=(str(target), tag, 20)) for tag in "ab"]
        for p in procs:
            p.start()
        for p in procs:
            p.join(60)
        assert 0 in [p.exitcode for p in procs]
        tags = {f.read_text() for f in target.iterdir()}
        assert len(tags) == 1 and len(list(target.iterdir())) == 21  # one writer's, whole
    _write_slowly(str(target), "c", 2)
    assert not _leftovers(tmp_path)
