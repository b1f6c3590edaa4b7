"""Fuzzing every file reader at scale (issue #34): mutants of valid files, outcome per reader.

    .venv/bin/python benchmarks/fuzz_readers.py [--cases 10000] [--readers SUBSTRING,...]
        [--timeout 20] [--seed 0] [--keep DIR]

The valid files are written by slscan's own writers (a one-view 288x192 virtual Gray-code
capture, decoded; a calibration; a pattern set; a MeshLab project; a recipe ...) and the
mutants made by ``tests/fuzz_cases.py`` (truncation, flipped and inserted bytes, wrong
types, huge, negative, NaN and infinite numbers, missing keys, wrong counts, header edits).
Each reader runs in its own worker process, fed one mutant at a time, so that a native
crash (SIGSEGV, an abort) or a hang (no answer in ``--timeout`` seconds) is counted and
the worker restarted. Outcomes, per reader:

- ``ok``: a valid result (the reader's promise holds: faces index the vertices, ...);
- ``clear error``: SlscanError whose message names the file;
- ``unnamed error``: SlscanError not naming it; ``invalid result``: a result breaking the
  reader's promise; ``crash``: any other exception, or the worker killed by a signal;
  ``hang``: no answer in time. The first mutant of each kind of failure is kept in
  ``--keep`` (default: a temporary folder, printed) as ``NN-KKK-OUTCOME-input.SUFFIX``
  beside ``NN-KKK-OUTCOME.txt`` (the reader, the case, what happened).

The cases are seeded (``--seed``): a run is repeatable.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1] / "tests"
sys.path.insert(0, str(TESTS))

MEMORY_LIMIT = 8 << 30
"""Address space of a worker (bytes): a reader asking for more gets MemoryError (a crash)."""


def _worker(name: str, index: Path) -> int:
    """Read the mutant at each path given on stdin with reader ``name``; one JSON verdict a line."""
    import resource
    import warnings

    from fuzz_cases import judge, readers

    warnings.simplefilter("ignore")
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    reader = readers()[name]
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    for line in sys.stdin:
        verdict = judge(reader, Path(line.strip()))
        sys.stdout.write(json.dumps({"outcome": verdict.outcome, "detail": verdict.detail[:4000]}) + "\n")
        sys.stdout.flush()
    return 0


class Worker:
    """A worker process for one reader; restarted after a crash or a hang."""

    def __init__(self, name: str, index: Path, log: Path):
        self.name, self.index, self.log = name, index, log
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, __file__, "--worker", self.name, "--index", str(self.index)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=open(self.log, "ab"), text=True, bufsize=1,
        )
        if self._line(600.0) != "ready":
            raise RuntimeError(f"the worker for {self.name} did not start; see {self.log}")

    def _line(self, timeout: float) -> str | None:
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        if not ready:
            return None
        line = self.proc.stdout.readline()
        return line.strip() if line else ""

    def judge(self, path: Path, timeout: float) -> tuple[str, str]:
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        try:
            self.proc.stdin.write(f"{path}\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            pass
        line = self._line(timeout)
        if line:
            verdict = json.loads(line)
            return verdict["outcome"], verdict["detail"]
        if line is None:  # no answer in time
            self.stop()
            return "hang", f"no answer in {timeout:g} s"
        code = self.proc.wait()
        self.proc = None
        name = signal.Signals(-code).name if code < 0 else f"exit {code}"
        return "crash", f"the worker died: {name}"

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


OUTCOMES = ("ok", "clear error", "unnamed error", "invalid result", "crash", "hang")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=10_000, help="mutants per reader (default 10000)")
    parser.add_argument("--readers", default="", help="only readers whose name holds one of these (comma-separated)")
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds before a case counts as a hang")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--keep", type=Path, help="folder for the failing mutants (default: a temporary one)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--index", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return _worker(args.worker, args.index)

    from fuzz_cases import build_corpus, case_folder, mutate, readers

    work = Path(tempfile.mkdtemp(prefix="slscan-fuzz-"))
    keep = args.keep or work / "failures"
    keep.mkdir(parents=True, exist_ok=True)
    corpus = build_corpus(work / "corpus")
    index = work / "corpus.json"
    index.write_text(json.dumps({k: str(v) for k, v in corpus.items()}))
    wanted = [w for w in args.readers.split(",") if w]
    names = [n for n in readers() if not wanted or any(w in n for w in wanted)]
    print(f"{len(names)} readers x {args.cases} mutants (seed {args.seed}, timeout {args.timeout:g} s); "
          f"failures kept in {keep}", flush=True)
    header = f"{'reader':44} {'cases':>6} " + " ".join(f"{o:>{max(len(o), 5)}}" for o in OUTCOMES) + f" {'ms/case':>8}"
    rows, found = [], []
    for n, name in enumerate(names):
        reader = readers()[name]
        path = case_folder(corpus, reader, work / "cases")
        original = corpus[reader.kind].read_bytes()
        rnd = random.Random(f"{args.seed}/{name}")
        worker = Worker(name, index, work / f"worker-{n}.log")
        worker.start()
        counts = dict.fromkeys(OUTCOMES, 0)
        seen: set[tuple[str, str]] = set()
        t0 = time.perf_counter()
        for case in range(args.cases):
            data = mutate(original, reader.syntax, rnd)
            path.write_bytes(data)
            outcome, detail = worker.judge(path, args.timeout)
            counts[outcome] += 1
            if outcome in ("ok", "clear error"):
                continue
            key = (outcome, detail.strip().splitlines()[0][:80] if detail.strip() else "")
            if key in seen:
                continue
            seen.add(key)
            stem = keep / f"{n:02d}-{len(seen):03d}-{outcome.replace(' ', '_')}"
            stem.with_name(f"{stem.name}-input{path.suffix}").write_bytes(data)
            stem.with_suffix(".txt").write_text(f"{name}\ncase {case} of seed {args.seed}\n{outcome}\n{detail}\n")
            found.append(f"{name}: {outcome}: {key[1]} ({stem.name})")
        worker.stop()
        ms = (time.perf_counter() - t0) / max(args.cases, 1) * 1000
        row = f"{name:44} {args.cases:6d} " + " ".join(f"{counts[o]:>{max(len(o), 5)}d}" for o in OUTCOMES) + f" {ms:8.1f}"
        rows.append(row)
        print(row if n else header + "\n" + row, flush=True)
    print()
    print(header)
    print("\n".join(rows))
    if found:
        print(f"\n{len(found)} kinds of failure:")
        print("\n".join(found))
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
