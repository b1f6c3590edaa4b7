"""Errors slscan raises at its boundaries (bad files, bad rigs, bad options)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


class SlscanError(Exception):
    """A problem the user can fix: the message names the file or option and what was expected.

    The command line prints it as one line and exits non-zero, without a traceback.
    """


MALFORMED = (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError, RecursionError)
"""What Python raises when a file's content has the wrong shape (a list where a mapping
belongs, a string where a number does, a missing key): :func:`about_file` names the file."""


@contextlib.contextmanager
def about_file(path: str | os.PathLike, what: str | None = None) -> Iterator[None]:
    """Make every error raised inside the block name ``path``, the file being read.

    A :class:`SlscanError` whose message does not mention the file (raised by a
    ``from_dict`` deep inside, which does not know it) is raised again prefixed with it.
    With ``what`` (e.g. ``"capture-session metadata"``), the exceptions of
    :data:`MALFORMED` become one ``SlscanError``: ``PATH: malformed WHAT (the reason)``.
    """
    try:
        yield
    except SlscanError as exc:
        if str(path) in str(exc) or Path(path).name in str(exc):
            raise
        raise SlscanError(f"{path}: {exc}") from None
    except MALFORMED as exc:
        if what is None:
            raise
        reason = f"missing {exc.args[0]!r}" if isinstance(exc, KeyError) and exc.args else str(exc)
        if isinstance(exc, RecursionError):
            reason = "nested too deeply"
        raise SlscanError(f"{path}: malformed {what} ({reason[:200]})") from None
