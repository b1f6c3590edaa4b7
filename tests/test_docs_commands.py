"""Help and docs match the command line: every subcommand has a ``--help``, and every
``slscan ...`` command quoted in README.md, docs/*.md and the commands' own help examples
parses with the real argument parser (an option or subcommand that does not exist fails,
naming the file and line)."""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from slscan.cli import build_parser, main

ROOT = Path(__file__).parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "viewer_layouts" / "README.md"]
SEPARATORS = {"&&", "||", "|", ";", "&"}
REDIRECTIONS = {">", ">>", "<", "2>", "2>&1"}
MISSING = "the following arguments are required"


@dataclass(frozen=True)
class Quoted:
    """An ``slscan`` command line quoted somewhere: its words after ``slscan``."""

    where: str  # file:line
    words: tuple[str, ...]
    complete: bool  # a whole command (code block, help example), not a mention in prose

    def __str__(self) -> str:
        return f"{self.where}: slscan {shlex.join(self.words)}"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


SUBCOMMANDS = _subparsers(build_parser())


# --- finding the commands -----------------------------------------------------------------


def _commands_in_line(text: str) -> Iterator[tuple[str, ...]]:
    """The words after ``slscan`` of every slscan command in one shell line."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    lexer.commenters = "#"
    try:
        tokens = list(lexer)
    except ValueError:  # an unbalanced quote: prose, not a command
        return
    segments: list[list[str]] = [[]]
    for token in tokens:
        if token in SEPARATORS:
            segments.append([])
        else:
            segments[-1].append(token)
    for words in segments:
        while words and re.fullmatch(r"[A-Z_][A-Z0-9_]*=\S*", words[0]):  # VAR=value slscan ...
            words = words[1:]
        if not words or not (words[0] == "slscan" or words[0].endswith("/slscan")):
            continue
        words = [w for w in words[1:] if w != "..."]  # "slscan scan ... --resume": the same options
        for k, word in enumerate(words):
            if word in REDIRECTIONS:
                words = words[:k]
                break
        yield tuple(words)


def _fenced_blocks(text: str) -> Iterator[tuple[int, str]]:
    """(first line number, logical line) of every line in a fenced code block, with
    backslash continuations joined."""
    in_block, pending, start = False, "", 0
    for number, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            in_block, pending = not in_block, ""
            continue
        if not in_block:
            continue
        if not pending:
            start = number
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        yield start, pending + line
        pending = ""


def _inline_code(text: str) -> Iterator[tuple[int, str]]:
    """(line number, content) of every inline code span outside the fenced blocks."""
    outside = []
    in_block = False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            in_block = not in_block
            outside.append("")
        else:
            outside.append("" if in_block else line)
    prose = "\n".join(outside)
    for match in re.finditer(r"(?<!`)`([^`]+)`(?!`)", prose):
        yield prose.count("\n", 0, match.start()) + 1, match.group(1).replace("\n", " ")


def quoted_in_docs() -> list[Quoted]:
    found = []
    for path in DOCS:
        text = path.read_text()
        name = path.relative_to(ROOT)
        for line, code in _fenced_blocks(text):
            found += [Quoted(f"{name}:{line}", words, True) for words in _commands_in_line(code)]
        for line, code in _inline_code(text):
            if re.match(r"(\S*/)?slscan\s", code + " "):
                found += [Quoted(f"{name}:{line}", words, False) for words in _commands_in_line(code)]
    return found


def quoted_in_help() -> list[Quoted]:
    """The example lines of the top-level help and of every subcommand's help: lines that
    start with ``slscan``; prose after two spaces is not part of the command."""
    found = []
    parsers = {"slscan": build_parser(), **{f"slscan {k}": v for k, v in SUBCOMMANDS.items()}}
    for name, parser in parsers.items():
        lines = re.sub(r"\s*\\\n\s*", " ", parser.epilog or "").splitlines()
        for k, line in enumerate(lines, 1):
            command = re.split(r"\s{2,}", line.strip())[0]
            if command.startswith("slscan "):
                found += [Quoted(f"{name} --help, epilog line {k}", words, True)
                          for words in _commands_in_line(command)]
    return found


# --- parsing them -------------------------------------------------------------------------


class _ParseError(Exception):
    pass


def _raising(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``parser`` and its subparsers raising :class:`_ParseError` instead of exiting."""

    def error(message: str):
        raise _ParseError(message)

    parser.error = error
    for sub in _subparsers(parser).values():
        _raising(sub)
    return parser


def parse_error(words: tuple[str, ...], *, complete: bool) -> str | None:
    """Why ``slscan WORDS`` does not parse, or None. A mention in prose (not ``complete``)
    may leave out required arguments."""
    parser = _raising(build_parser())
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            parser.parse_args(list(words))
    except SystemExit as exc:  # --help, --version
        return None if exc.code in (0, None) else f"exit {exc.code}"
    except _ParseError as exc:
        message = str(exc)
        if not complete and (message.startswith(MISSING) or message.endswith("expected one argument")):
            return None  # prose names a command or an option without all its values
        return message
    return None


DOC_COMMANDS = quoted_in_docs()
HELP_COMMANDS = quoted_in_help()


def test_the_docs_quote_commands():
    files = {q.where.split(":")[0] for q in DOC_COMMANDS}
    assert len(DOC_COMMANDS) > 50 and {"README.md", "docs/scanning.md", "docs/texture.md"} <= files
    assert len(HELP_COMMANDS) > 20


def test_the_extractor():
    line = "bash .ci/setup && .venv/bin/slscan demo --out d --save d.rrd   # comment"
    assert list(_commands_in_line(line)) == [("demo", "--out", "d", "--save", "d.rrd")]
    assert list(_commands_in_line("SLSCAN_DATA=/x slscan run r.toml > log.txt")) == [("run", "r.toml")]
    assert list(_commands_in_line("rerun demo.rrd")) == []
    text = "```bash\nslscan texture m.ply \\\n    --out t\n```\nsee `slscan view t` and `slscan.virtual`\n"
    assert list(_fenced_blocks(text)) == [(2, "slscan texture m.ply      --out t")]
    assert [c for _, c in _inline_code(text)] == ["slscan view t", "slscan.virtual"]
    assert parse_error(("demo", "--out", "x", "--no-such-option"), complete=True)
    assert parse_error(("no-such-command",), complete=False)
    assert parse_error(("decode",), complete=True).startswith(MISSING)
    assert parse_error(("decode",), complete=False) is None


def _placeholder(words: tuple[str, ...]) -> bool:
    """``slscan COMMAND --help``: a placeholder for any command."""
    return bool(words) and words[0].isupper()


@pytest.mark.parametrize("quoted", [q for q in DOC_COMMANDS if not _placeholder(q.words)], ids=str)
def test_commands_in_the_docs_parse(quoted):
    error = parse_error(quoted.words, complete=quoted.complete)
    assert error is None, f"{quoted}\n  -> {error}"


@pytest.mark.parametrize("quoted", HELP_COMMANDS, ids=str)
def test_examples_in_the_help_parse(quoted):
    error = parse_error(quoted.words, complete=quoted.complete)
    assert error is None, f"{quoted}\n  -> {error}"


@pytest.mark.parametrize("command", sorted(SUBCOMMANDS))
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: slscan {command}") and len(out.splitlines()) > 5


def test_commands_that_write_have_out_and_overwrite():
    """The same options everywhere: --out and --overwrite where a command writes, --quiet
    where it shows progress, --save/--spawn/--connect where it logs to Rerun."""
    recording = {"--save", "--spawn", "--connect"}
    # commands that only read, or write a fixed set of files (layouts), or resume into
    # their folder by design (run: --force; regress: --keep is a new folder)
    # (stage: drives a turntable, writes nothing)
    no_overwrite = {"info", "view", "layouts", "run", "regress", "stage"}
    for name, parser in SUBCOMMANDS.items():
        options = {s for a in parser._actions for s in a.option_strings}
        if name not in no_overwrite:
            assert {"--out", "--overwrite"} <= options, name
        if recording & options:
            assert recording <= options or name == "view", name
    stages = ("demo", "capture", "scan", "calibrate", "decode", "capture-lights", "calibrate-lights",
              "albedo", "register", "fuse", "simplify", "texture", "run")
    for name in stages:
        options = {s for a in SUBCOMMANDS[name]._actions for s in a.option_strings}
        assert recording | {"--quiet"} <= options, name
