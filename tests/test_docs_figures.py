"""Figures the docs quote come from the current code, where they are cheap to recompute.

Each row: the doc file, the text it quotes (whitespace-insensitive), and the command line
that prints it today. A change of the code that moves a figure fails here, naming the doc
to update; a doc edited away from the table fails too. Only figures that take seconds are
here: the demo's and the benchmarks' figures are each benchmark's to print.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from slscan.cli import main

ROOT = Path(__file__).parents[1]


@dataclass(frozen=True)
class Figure:
    doc: str
    quoted: str
    command: tuple[str, ...]  # ``{tmp}`` is a fresh folder

    def __str__(self) -> str:
        return f"{self.doc}: {self.quoted[:48]}"


VIRTUAL = ("scan", "--camera", "virtual")  # --scale 0.5, the scan command's default, as in the docs
FIGURES = [
    Figure("docs/scanning.md", "view_000 10,157 vertices, 78.1 % of the decodable pixels covered",
           (*VIRTUAL, "--views", "1", "--lights", "none", "--out", "{tmp}/scan")),
    Figure("docs/scanning.md",
           "exposure virtual-camera at exposure 1.24283, gain 1: peak 84 % of full scale, 0.000 % clipped",
           (*VIRTUAL, "--exposure", "40", "--auto-exposure", "--views", "1", "--lights", "none",
            "--no-quick-decode", "--out", "{tmp}/auto")),
    Figure("docs/scanning.md",
           "exposure virtual-camera at exposure 1, gain 1: peak 68 % of full scale, 0.000 % clipped",
           (*VIRTUAL, "--check-exposure")),
    Figure("docs/scanning.md",
           "exposure 44.71 % of the lit pixels are saturated (virtual-camera at exposure 6, gain 1); "
           "lower the exposure",
           (*VIRTUAL, "--exposure", "6", "--check-exposure")),
]


def _words(text: str) -> str:
    return " ".join(text.split())


@pytest.mark.parametrize("figure", FIGURES, ids=str)
def test_the_docs_quote_it(figure):
    assert _words(figure.quoted) in _words((ROOT / figure.doc).read_text()), (
        f"{figure.doc} no longer quotes {figure.quoted!r}: update this table with the doc"
    )


@pytest.mark.parametrize("figure", FIGURES, ids=str)
def test_the_code_prints_it(figure, tmp_path, capsys):
    main([word.replace("{tmp}", str(tmp_path)) for word in figure.command])
    printed = capsys.readouterr()
    assert _words(figure.quoted) in _words(printed.err + printed.out), (
        f"{figure.doc} quotes {figure.quoted!r}; `slscan {' '.join(figure.command)}` now prints:\n{printed.err}"
    )
