"""The ``slscan`` command's fixed start-up cost: building its parser, before any work,
side by side with an earlier version of slscan.

    .venv/bin/python benchmarks/cli_start.py [--against REV] [--repeats 5] [--scale 1.0]

Captures one view of the tile on the virtual rig (hybrid patterns, no lit images, with
this tree; at ``--scale 1`` the paper's 1440x960 camera), then times, in a fresh process
each, ``slscan --help``, ``slscan info --help``, ``slscan info SESSION`` and ``slscan
decode --help``: CPU seconds (user + system of the child) and wall seconds, the median of
``--repeats`` runs, the versions alternating run by run. The ``same output`` column
compares each command's output between the versions (it must not change). Then every
subcommand's ``--help`` once per version: how many print the same text in both, and the
most CPU any of them takes; and whether the two parsers are the same, option by option
(defaults and types too, which ``--help`` does not always show).

``--against REV`` writes REV's ``toolbox/`` to a temporary folder (git archive) and runs it
with ``PYTHONPATH`` pointing there; this tree runs from ``toolbox/`` beside this script.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from measure import export_toolbox

TOOLBOX = Path(__file__).resolve().parent.parent / "toolbox"

LIST_COMMANDS = ("from slscan.cli import build_parser\n"
                 "sub = next(a for a in build_parser()._actions if a.dest == 'command')\n"
                 "print(' '.join(sub.choices))")
DUMP_PARSER = """\
import json
from slscan.cli import build_parser

def dump(parser):
    actions = []
    for a in parser._actions:
        sub = a.choices if isinstance(a.choices, dict) else None
        actions.append([type(a).__name__, a.option_strings, a.dest, repr(a.default),
                        None if sub else repr(a.choices), repr(a.nargs), repr(a.const), a.required,
                        getattr(a.type, "__name__", repr(a.type)), repr(a.metavar), a.help,
                        {k: dump(v) for k, v in sub.items()} if sub else None])
    defaults = {k: getattr(v, "__name__", repr(v)) for k, v in parser._defaults.items()}
    return [actions, defaults, parser.description, parser.epilog]

print(json.dumps(dump(build_parser()), sort_keys=True))
"""
"""Every option of every command (strings, default, choices, type, help) and the function
each command runs, as JSON."""


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _env(toolbox: Path) -> dict[str, str]:
    # a fixed width: argparse and rich wrap to COLUMNS, the same for both versions
    return dict(os.environ, PYTHONPATH=str(toolbox), COLUMNS="100")


def run_slscan(toolbox: Path, argv: list[str]) -> tuple[float, float, str]:
    """CPU seconds (the child's user + system), wall seconds and stdout of
    ``python -m slscan.cli ARGV`` with ``toolbox`` as the slscan to import."""
    cpu, t = _children_cpu(), time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "slscan.cli", *argv], env=_env(toolbox),
                          capture_output=True, text=True, check=False)
    wall, cpu = time.perf_counter() - t, _children_cpu() - cpu
    if proc.returncode != 0:
        raise SystemExit(f"slscan {' '.join(argv)} ({toolbox}) exited {proc.returncode}:\n{proc.stderr[-3000:]}")
    return cpu, wall, proc.stdout


def python_out(toolbox: Path, code: str) -> str:
    return subprocess.run([sys.executable, "-c", code], env=_env(toolbox), check=True,
                          capture_output=True, text=True).stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--against", metavar="REV", help="git revision to time side by side")
    parser.add_argument("--repeats", type=int, default=5, help="runs per command and version (median)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="resolution of the captured session (1: the 1440x960 camera)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="cli_start_") as tmp:
        versions = {"this tree": TOOLBOX}
        if args.against:
            versions = {args.against: export_toolbox(args.against, Path(tmp) / "against"), **versions}
        for name, toolbox in versions.items():
            where = python_out(toolbox, "import slscan; print(slscan.__file__)")
            if not Path(where).resolve().is_relative_to(toolbox.resolve()):
                raise SystemExit(f"{name}: slscan imports from {where}, expected {toolbox}")

        session = Path(tmp) / "tile"
        t = time.perf_counter()
        run_slscan(TOOLBOX, ["capture", "--scene", "tile", "--no-lit", "--quiet", "--scale", str(args.scale),
                             "--out", str(session)])
        print(f"captured {session.name}: 1 view at scale {args.scale} in {time.perf_counter() - t:.1f} s",
              flush=True)

        commands = {
            "slscan --help": ["--help"],
            "slscan info --help": ["info", "--help"],
            "slscan info SESSION": ["info", str(session)],
            "slscan decode --help": ["decode", "--help"],
        }
        samples = {(c, v): [] for c in commands for v in versions}
        outputs = {(c, v): set() for c in commands for v in versions}
        for _ in range(args.repeats):
            for command, argv in commands.items():
                for version, toolbox in versions.items():
                    cpu, wall, out = run_slscan(toolbox, argv)
                    samples[command, version].append((cpu, wall))
                    outputs[command, version].add(out)

        names = list(versions)
        head = f"{'command':<22}" + "".join(f"{n + ' CPU s':>20}" for n in names) \
            + "".join(f"{n + ' wall s':>20}" for n in names)
        if len(names) == 2:
            head += f"{'CPU ratio':>11}{'same output':>13}"
        print(f"\nmedian of {args.repeats} runs, a fresh process each (CPU: user + system)")
        print(head)
        for command in commands:
            med = {v: (statistics.median(c for c, _ in samples[command, v]),
                       statistics.median(w for _, w in samples[command, v])) for v in names}
            row = f"{command:<22}" + "".join(f"{med[v][0]:>20.3f}" for v in names) \
                + "".join(f"{med[v][1]:>20.3f}" for v in names)
            if len(names) == 2:
                same = len(outputs[command, names[0]] | outputs[command, names[1]]) == 1
                row += f"{med[names[0]][0] / med[names[1]][0]:>10.1f}x{'yes' if same else 'NO':>13}"
            print(row)

        subcommands = {v: python_out(toolbox, LIST_COMMANDS).split() for v, toolbox in versions.items()}
        every = subcommands["this tree"]
        if any(s != every for s in subcommands.values()):
            print(f"\nsubcommands differ: {subcommands}")
        helps = {v: {c: run_slscan(toolbox, [c, "--help"]) for c in every} for v, toolbox in versions.items()}
        print(f"\nevery subcommand's --help once ({len(every)} subcommands):")
        for version in names:
            worst = max(every, key=lambda c: helps[version][c][0])
            print(f"  {version}: most CPU {helps[version][worst][0]:.3f} s (slscan {worst} --help), "
                  f"median {statistics.median(h[0] for h in helps[version].values()):.3f} s")
        if len(names) == 2:
            same = [c for c in every if helps[names[0]][c][2] == helps[names[1]][c][2]]
            differ = sorted(set(every) - set(same))
            print(f"  same --help text in {names[0]} and this tree: {len(same)} of {len(every)}"
                  + (f"; differ: {', '.join(differ)}" if differ else ""))
            dumps = [python_out(versions[v], DUMP_PARSER) for v in names]
            print("  the parsers (every option's strings, default, choices, type and help, every command's "
                  f"function): {'identical' if dumps[0] == dumps[1] else 'DIFFER'}")


if __name__ == "__main__":
    main()
