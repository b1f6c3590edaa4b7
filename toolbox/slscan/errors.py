"""Errors slscan raises at its boundaries (bad files, bad rigs, bad options)."""

from __future__ import annotations


class SlscanError(Exception):
    """A problem the user can fix: the message names the file or option and what was expected.

    The command line prints it as one line and exits non-zero, without a traceback.
    """
