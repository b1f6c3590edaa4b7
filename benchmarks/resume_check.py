"""What the resume check of `slscan run` costs on a finished run (issue #20).

    .venv/bin/python benchmarks/resume_check.py --run OUT [--repeat 5]

OUT is a folder written by ``slscan run`` (e.g. ``slscan run recipes/paper.toml --out OUT
--set capture.views=4``). For each stage folder the table gives its files and bytes and
three costs:

- ``record``: building the manifest when the stage finishes (every file hashed once);
- ``check``: the check a re-run makes when nothing changed (sizes and times only);
- ``all hashed``: the worst case, every file's time changed (copied or restored
  folder): every file is read and hashed again.

The check is timed against the manifest it would compare with (built here, so a run
written before manifests existed works too); nothing in OUT is changed. Times are the
best of ``--repeat`` runs (the page cache is warm after the first).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from slscan.recipe.runner import check_outputs, output_manifest


def _best(fn, repeat: int) -> tuple[float, object]:
    best, result = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t)
    return best, result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a folder written by slscan run")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args(argv)
    stages = sorted(p.with_suffix("").with_suffix("").name for p in args.run.glob("*.stage.json"))
    stages = [s for s in stages if (args.run / s).is_dir()]
    if not stages:
        print(f"{args.run}: no finished stages (no NAME.stage.json beside a NAME/ folder)", file=sys.stderr)
        return 2
    print(f"resume check on {args.run} (best of {args.repeat})")
    print(f"{'stage':10} {'files':>6} {'MB':>8} {'record s':>9} {'check s':>9} {'all hashed s':>13}")
    total = [0, 0, 0.0, 0.0, 0.0]
    for name in stages:
        folder = args.run / name
        record_s, files = _best(lambda f=folder: output_manifest(f), 1)
        check_s, check = _best(lambda f=folder, m=files: check_outputs(f, m), args.repeat)
        assert not check.problems and check.hashed_files == 0, check.problems
        stale = {rel: {**entry, "mtime_ns": entry["mtime_ns"] - 1} for rel, entry in files.items()}
        hashed_s, hashed = _best(lambda f=folder, m=stale: check_outputs(f, m), args.repeat)
        assert not hashed.problems and hashed.hashed_files == len(files), hashed.problems
        size = sum(entry["size"] for entry in files.values())
        print(f"{name:10} {len(files):6d} {size / 1e6:8.1f} {record_s:9.4f} {check_s:9.4f} {hashed_s:13.4f}")
        for i, value in enumerate((len(files), size, record_s, check_s, hashed_s)):
            total[i] += value
    print(f"{'total':10} {total[0]:6d} {total[1] / 1e6:8.1f} {total[2]:9.4f} {total[3]:9.4f} {total[4]:13.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
