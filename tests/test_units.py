"""One memory-size parser (slscan.units.parse_memory) for every option and recipe key: Dask's units."""

from __future__ import annotations

import math

import pytest

from slscan.errors import SlscanError
from slscan.units import parse_memory


@pytest.mark.parametrize("text, expected", [
    ("4GiB", 4 * 2**30), ("4 gib", 4 * 2**30), ("4Gi", 4 * 2**30), ("512MiB", 512 * 2**20), ("10KiB", 10240),
    ("4GB", 4 * 10**9), ("4G", 4 * 10**9), ("800M", 800 * 10**6), ("5kB", 5000), ("1TiB", 2**40),
    ("4", 4 * 2**30), ("0.5", 2**29), ("1e-6", int(1e-6 * 2**30)), (4, 4 * 2**30), (0.25, 2**28),
    ("100B", 100),
])
def test_units_as_dask_reads_them_and_a_bare_number_is_gib(text, expected):
    assert parse_memory(text) == expected


def test_agrees_with_dask_where_a_unit_is_given():
    dask_utils = pytest.importorskip("dask.utils")
    for text in ("4GiB", "4GB", "4G", "512MiB", "800M", "5kB", "1.5 GiB", "3Ki", "7tb"):
        assert parse_memory(text) == dask_utils.parse_bytes(text), text


@pytest.mark.parametrize("text", ["lots", "", "GiB", "4 GiBs", "4XB", "nan", "NaN GiB", "inf", "-inf", "0",
                                  "0GiB", "-4GiB", "0.1B", math.nan, math.inf, 0, -1, True])
def test_one_line_naming_the_option(text):
    with pytest.raises(SlscanError) as info:
        parse_memory(text, option="--max-memory")
    message = str(info.value)
    assert message.startswith(f"--max-memory {text!r}: expected a size such as 4GiB or 512MiB")
    assert "\n" not in message


def test_the_option_named_is_the_callers():
    with pytest.raises(SlscanError, match=r"^'lots': expected a size such as 4GiB or 512MiB$"):
        parse_memory("lots", option="")
