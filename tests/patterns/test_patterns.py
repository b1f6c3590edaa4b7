"""Pattern structure: line positions, band colours, and the code of every projector column."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.errors import SlscanError
from slscan.fsio import read_png
from slscan.patterns import (
    PatternImage,
    graycode,
    hybrid,
    read_pattern_set,
    render,
    standard_set,
    write_pattern_set,
)

RED, GREEN, BLUE = [255, 0, 0], [0, 255, 0], [0, 0, 255]


def test_hybrid_paper_defaults_have_511_lines_two_pixels_apart():
    images = hybrid.generate(1024, 768, levels=9)
    assert [len(d.params["lines"]) for d in images] == [2 ** (k - 1) for k in range(1, 10)]
    lines = sorted(c for d in images for _, c in d.params["lines"])
    assert len(lines) == 511
    np.testing.assert_array_equal(lines, np.arange(2, 1024, 2))
    # line indices are 0..510 left to right
    index_to_col = dict(i for d in images for i in d.params["lines"])
    assert [index_to_col[i] for i in range(511)] == lines
    assert images[0].params["lines"] == [[255, 512]]


@pytest.mark.parametrize("width,levels", [(1024, 9), (800, 7), (1280, 8), (64, 5)])
def test_hybrid_bands_are_red_left_blue_right_of_each_one_pixel_green_line(width, levels):
    for desc in hybrid.generate(width, 4, levels=levels):
        img = render(desc)
        assert img.shape == (4, width, 3)
        assert np.all(img == img[:1])  # columns pattern: every row identical
        row = img[0]
        greens = np.flatnonzero(np.all(row == GREEN, axis=1))
        assert greens.tolist() == [c for _, c in desc.params["lines"]]
        for (_, col), (start, stop) in zip(desc.params["lines"], desc.params["regions"]):
            assert start < col < stop - 1 or (start < col and col == stop - 1) or start <= col
            assert np.all(row[start:col] == RED)
            assert np.all(row[col + 1 : stop] == BLUE)
        # regions tile the projector
        edges = np.array(desc.params["regions"])
        assert edges[0, 0] == 0 and edges[-1, 1] == width
        assert np.all(edges[1:, 0] == edges[:-1, 1])


@pytest.mark.parametrize("width,levels", [(1024, 9), (800, 7), (100, 5)])
def test_hybrid_column_code_counts_the_lines_to_its_left(width, levels):
    images = hybrid.generate(width, 8, levels=levels)
    codes = hybrid.column_codes(images)
    lines = hybrid.line_columns(width, levels)
    for c in range(width):
        if c in lines:
            assert codes[c] == -(int(np.flatnonzero(lines == c)[0]) + 1)
        else:
            assert codes[c] == np.count_nonzero(lines < c)


def test_hybrid_lines_new_at_level_k_are_indexed_by_the_bands_of_earlier_levels():
    images = hybrid.generate(1024, 8, levels=9)
    for k, desc in enumerate(images, start=1):
        earlier = images[: k - 1]
        for line_index, col in desc.params["lines"]:
            bits = [int(hybrid.band_labels(d)[col]) for d in earlier]  # red 0, blue 1 at the line
            region = int("".join(map(str, bits)), 2) if bits else 0
            # the region number from earlier bands picks the line of this level
            assert desc.params["lines"][region] == [line_index, col]


def test_hybrid_rejects_more_levels_than_the_projector_resolves():
    with pytest.raises(SlscanError, match="at least 2048 px"):
        hybrid.generate(1024, 768, levels=10)


@pytest.mark.parametrize("size", [1024, 768, 1000, 37])
def test_gray_code_decodes_every_column(size):
    images = graycode.generate(size, 2)
    bits = [render(d)[0, :, 0] > 0 for d in images if not d.params["inverse"]]
    inverses = [render(d)[0, :, 0] > 0 for d in images if d.params["inverse"]]
    assert len(bits) == graycode.n_bits(size)
    for b, inv in zip(bits, inverses):
        assert np.all(b != inv)
    code = np.zeros(size, dtype=np.int64)
    for b in bits:
        code = code * 2 + b
    np.testing.assert_array_equal(graycode.inverse_gray(code), np.arange(size))
    # neighbouring columns differ in exactly one bit
    diff = np.stack(bits)[:, 1:] != np.stack(bits)[:, :-1]
    assert np.all(diff.sum(axis=0) == 1)


def test_gray_rows_vary_along_rows():
    rows = [d for d in graycode.generate(16, 8, rows=True) if d.axis == "rows"]
    assert len(rows) == 6
    img = render(rows[0])
    assert np.all(img == img[:, :1])


def test_pattern_set_round_trip(tmp_path):
    images = standard_set("both", width=256, height=192, levels=6, rows=True)
    out = write_pattern_set(tmp_path / "set", images)
    back = read_pattern_set(out)
    assert back == images
    for i, desc in enumerate(back):
        files = sorted(p for p in out.iterdir() if p.suffix == ".png")
        np.testing.assert_array_equal(read_png(files[i]), render(desc))
    assert [d.id for d in back[:2]] == ["white", "black"]


def test_pattern_description_errors_name_the_problem():
    with pytest.raises(SlscanError, match="unknown family"):
        PatternImage("x", "laser", 10, 10, "columns")
    with pytest.raises(SlscanError, match="missing"):
        PatternImage.from_dict({"id": "x", "family": "flat"})
