"""Memory sizes as users type them ("4GiB", "512MiB", "4GB"): one parser for every option and recipe key."""

from __future__ import annotations

import math
import re

from slscan.errors import SlscanError

GIB = 2**30

_UNITS = {
    "": GIB,  # a bare number is GiB (slscan's own convention: "--max-memory 4")
    "b": 1,
    "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40, "pib": 2**50,
    "ki": 2**10, "mi": 2**20, "gi": 2**30, "ti": 2**40, "pi": 2**50,
    "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12, "pb": 10**15,
    "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12, "p": 10**15,
}
"""Units, case-insensitive, as ``dask.utils.parse_bytes`` reads them (so a cap means the same to
slscan and to a Dask worker's ``--memory-limit``): "KiB"/"MiB"/"GiB" (and "Ki", "Mi", "Gi") are
powers of 1024; "kB"/"MB"/"GB" and the bare "k"/"M"/"G" are powers of 1000. Unlike Dask, a number
without a unit is GiB, not bytes."""

MEMORY_HELP = ("e.g. 4GiB or 512MiB (GiB, MiB: powers of 1024; GB, MB, G, M: powers of 1000, as Dask "
               "reads them; a bare number is GiB)")
"""What ``--help`` says about a memory size."""

_NUMBER_UNIT = re.compile(r"^\s*([0-9.eE+-]+|nan|inf|infinity)\s*([a-zA-Z]*)\s*$", re.IGNORECASE)


def parse_memory(text: str | float, *, option: str = "--max-memory") -> int:
    """Bytes in the memory size ``text``: ``"4GiB"`` -> 4 * 2**30, ``"4GB"`` or ``"4G"`` -> 4e9,
    ``"512MiB"``, ``"1.5"`` (GiB), or a number (GiB).

    Parameters
    ----------
    text : the size as typed (a recipe may give a TOML number: GiB)
    option : what the error names, e.g. ``"--max-memory"``; ``""`` for just the value

    Raises
    ------
    SlscanError
        One line, ``--max-memory 'lots': expected a size such as 4GiB or 512MiB``, for anything
        that is not a finite size of at least one byte (NaN, inf, zero and negative sizes too).
    """
    where = f"{option} {text!r}" if option else repr(text)
    if isinstance(text, bool):
        raise SlscanError(f"{where}: expected a size such as 4GiB or 512MiB")
    if isinstance(text, (int, float)):
        value = float(text) * GIB
    else:
        match = _NUMBER_UNIT.match(str(text))
        unit = match.group(2).lower() if match else None
        if unit not in _UNITS:
            raise SlscanError(f"{where}: expected a size such as 4GiB or 512MiB")
        try:
            value = float(match.group(1)) * _UNITS[unit]
        except ValueError:
            raise SlscanError(f"{where}: expected a size such as 4GiB or 512MiB") from None
    if not (math.isfinite(value) and value >= 1):
        raise SlscanError(f"{where}: expected a size such as 4GiB or 512MiB (a positive, finite size)")
    return int(value)


__all__ = ("parse_memory", "MEMORY_HELP", "GIB")
