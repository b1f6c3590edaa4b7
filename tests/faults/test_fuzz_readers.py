"""Property-based tests of every file reader (#34): valid files from slscan's own writers,
mutated byte- and structure-wise (truncation, flipped bytes, wrong types, huge, negative,
NaN and infinite numbers, missing keys, wrong counts), must read to a valid result or end
in one SlscanError naming the file: never another exception.

A few hundred cases per reader here (derandomised, so CI is stable);
``benchmarks/fuzz_readers.py`` runs 10,000 per reader, each reader in a worker process that
also catches native crashes and hangs. The cases are built by ``tests/fuzz_cases.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fuzz_cases import build_corpus, case_folder, judge, mutate, readers
from slscan.errors import SlscanError

EXAMPLES = 200
"""Mutants per reader in CI (the benchmark runs 10,000)."""

TOOLBOX = Path(__file__).resolve().parents[2] / "toolbox"


@pytest.fixture(scope="module")
def corpus(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return build_corpus(tmp_path_factory.mktemp("fuzz") / "corpus")


@pytest.mark.parametrize("name", list(readers()))
def test_each_reader_reads_its_valid_file(corpus, tmp_path, name):
    """The unmutated file (slscan's writers' output) reads to a valid result."""
    reader = readers()[name]
    verdict = judge(reader, case_folder(corpus, reader, tmp_path))
    assert verdict.outcome == "ok", verdict.detail


@pytest.mark.parametrize("name", list(readers()))
def test_mutated_files_read_or_fail_naming_the_file(corpus, tmp_path_factory, name):
    reader = readers()[name]
    path = case_folder(corpus, reader, tmp_path_factory.mktemp("cases"))
    original = corpus[reader.kind].read_bytes()

    @settings(max_examples=EXAMPLES, deadline=2000, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow])
    @given(st.randoms(use_true_random=False))
    def check(rnd):
        data = mutate(original, reader.syntax, rnd)
        path.write_bytes(data)
        verdict = judge(reader, path)
        assert verdict.outcome in ("ok", "clear error"), (
            f"{name}: {verdict.outcome}: {verdict.detail}\nthe mutant (first 1,500 bytes): {data[:1500]!r}"
        )

    check()


# --- the crashes fuzzing found, one known input each ------------------------------------------


def _edit(path: Path, old: bytes, new: bytes, count: int = 1) -> Path:
    data = path.read_bytes()
    assert old in data, old
    path.write_bytes(data.replace(old, new, count))
    return path


def _huge_list_count(path: Path) -> None:
    """The faces' list count made a uint and the first one 2**31 - 16 (the 40 faces, last in
    the file, take 40 x 13 bytes)."""
    _edit(path, b"list uchar int", b"list uint int")
    data = path.read_bytes()
    start = len(data) - 40 * 13
    path.write_bytes(data[:start] + (2**31 - 16).to_bytes(4, "little") + data[start + 4:])


def _infinite_normal(path: Path) -> None:
    """No quality property (so it comes from the normals), and the first vertex's nx infinite."""
    head, body = path.read_bytes().split(b"end_header\n")
    first, rest = body.split(b"\n", 1)
    words = first.split()
    words[3] = b"inf"
    path.write_bytes(head.replace(b"property float quality", b"property float weight") + b"end_header\n"
                     + b" ".join(words) + b"\n" + rest)


def _nan_pose(path: Path) -> None:
    d = json.loads(path.read_text())
    d["views"][0]["rig_from_object"][0][3] = float("nan")
    path.write_text(json.dumps(d))


FOUND = {
    # reader name, edit of the valid file, words the message must hold (None: it reads, validly)
    "PLY property declared twice (ValueError from numpy)": (
        "ply.read_ply_elements (binary)", lambda p: _edit(p, b"property float y\n", b"property float x\n"),
        "property 'x' is declared twice"),
    "binary PLY list count read as 2**32-ish (ValueError from numpy)": (
        "register.load_range_scan (binary)", lambda p: _huge_list_count(p), "truncated"),
    "range scan with an infinite normal (NaN quality: a wrong result)": (
        "register.load_range_scan (ASCII)", lambda p: _infinite_normal(p), None),
    "ASCII PLY list of length inf (OverflowError)": (
        "ply.read_ply_elements (ASCII)", lambda p: _edit(p, b"\n3 ", b"\ninf ", 1), "list 'vertex_indices' has length"),
    "ASCII PLY list longer than the file (a wrong result)": (
        "ply.read_ply_elements (ASCII)",
        lambda p: p.write_bytes(p.read_bytes().rstrip(b"\n").rsplit(b"\n", 1)[0] + b"\n3 0 1"), "truncated"),
    "ASCII PLY index 1e999 in an int list (garbage index)": (
        "decode.rangemap.read_ply (ASCII)", lambda p: _edit(p, b"\n3 0 ", b"\n3 1e999 "), "is not a int"),
    "non-UTF-8 byte in JSON (UnicodeDecodeError)": (
        "capture.load_session (session.json)", lambda p: _edit(p, b'"format"', b'"form\xb2at"'), "not UTF-8"),
    "image file named by a number (TypeError)": (
        "capture.load_session (session.json)",
        lambda p: p.write_text(p.read_text().replace('"file": "00_white.png"', '"file": 7')), "malformed"),
    "pattern set that is a list (AttributeError)": (
        "patterns.read_pattern_set (patterns.json)", lambda p: p.write_text("[1, 2]"), "not an slscan pattern set"),
    "codes manifest whose views are a string (AttributeError)": (
        "decode.read_codes (projector_codes.json)",
        lambda p: p.write_text(json.dumps({**json.loads(p.read_text()), "views": "view_000"})), "malformed"),
    "codes manifest naming a folder outside it": (
        "decode.read_codes (projector_codes.json)",
        lambda p: p.write_text(p.read_text().replace('"folder": "view_000"', '"folder": "../../x"')),
        "expected a folder name inside"),
    "range-maps summary whose views are a number (TypeError)": (
        "register.load_scans (range_maps.json)",
        lambda p: p.write_text(json.dumps({**json.loads(p.read_text()), "views": 3.0})), "lists no views"),
    "range-maps summary with a NaN pose (a NaN world accepted)": (
        "register.load_scans (range_maps.json)", lambda p: _nan_pose(p), "expected a finite, invertible 4x4 pose"),
    "calibration JSON with fx of Infinity (an impossible lens accepted)": (
        "calibrate.load_calibration (JSON)",
        lambda p: p.write_text(p.read_text().replace('"fx": ', '"fx": Infinity, "_fx": ', 1)), "must be finite"),
    "Stanford obj_info num_rows -1e308 (ValueError)": (
        "register.load_stanford_scan (ASCII PLY)", lambda p: _edit(p, b"num_rows 3", b"num_rows -1e308"),
        "range_grid has 12 cells"),
    "Stanford range_grid without a list (StopIteration)": (
        "register.load_stanford_scan (ASCII PLY)",
        lambda p: _edit(p, b"property list uchar int vertex_indices\nend_header", b"end_header"),
        "range_grid has no list property"),
    "recipe with a non-UTF-8 byte (UnicodeDecodeError)": (
        "recipe.load_recipe (TOML)", lambda p: _edit(p, b"[", b"\xff[", 1), "not UTF-8"),
    "OpenCV file that is only the XML declaration (cv2.error from FileNode.keys)": (
        "calibrate.import_opencv_xml (XML)", lambda p: p.write_bytes(b'<?xml version="1.0"?>'),
        "not a readable OpenCV FileStorage file"),
    "OpenCV matrix type with non-UTF-8 bytes (UnicodeDecodeError)": (
        "calibrate.read_calibration (OpenCV XML)", lambda p: _edit(p, b"<dt>d</dt>", b"<dt>\xe84\x9f\xf1d</dt>"),
        "not a readable OpenCV FileStorage file"),
    "codes file whose column map is null (a result without columns)": (
        "decode.read_codes (codes.json)",
        lambda p: p.write_text(json.dumps({**json.loads(p.read_text()),
                                           "files": {**json.loads(p.read_text())["files"], "columns": None}})),
        "files.columns is None"),
    "codes manifest naming its view NaN (StopIteration)": (
        "decode.read_codes (projector_codes.json)",
        lambda p: p.write_text(p.read_text().replace('"view": "view_000"', '"view": NaN')), "views named [nan]"),
    "OpenCV matrix with cols inf (OpenCV asked for 51 GB)": (
        "calibrate.import_opencv_xml (XML)", lambda p: _edit(p, b"<cols>3</cols>", b"<cols>inf</cols>", 2),
        "cam_int"),
}


def slscan_python(code: str, *args: object) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh Python with this slscan (a native crash kills only it)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TOOLBOX), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=120)


@pytest.mark.parametrize("case", list(FOUND))
def test_what_fuzzing_found_is_a_clear_error(corpus, tmp_path, case):
    name, edit, words = FOUND[case]
    reader = readers()[name]
    path = case_folder(corpus, reader, tmp_path)
    edit(path)
    if words is None:  # a valid result was to come, and now does
        verdict = judge(reader, path)
        assert verdict.outcome == "ok", verdict.detail
        return
    with pytest.raises(SlscanError) as info:
        reader.read(path)
    assert path.name in str(info.value) and words in str(info.value), str(info.value)


def test_open3d_crash_on_a_truncated_body_is_a_clear_error(corpus, tmp_path):
    """Open3D's PLY reader died of SIGSEGV on this file (a binary body cut short and shifted):
    ``slscan simplify`` now reads PLY itself and says the file is truncated (in a subprocess,
    so that a crash is a failure, not the end of the test run)."""
    path = tmp_path / "cut.ply"
    data = corpus["range map (binary PLY)"].read_bytes()
    head = data.index(b"end_header\n") + len(b"end_header\n")
    body = data[head:]
    path.write_bytes(data[:head] + body[:300] + body[700:])
    done = slscan_python("import sys; from slscan.cli import main; sys.exit(main(sys.argv[1:]))",
                         "simplify", path, "--out", tmp_path / "out.ply", "--quiet")
    assert done.returncode == 2, f"exit {done.returncode}: {done.stderr[-2000:]}"
    assert "cut.ply" in done.stderr and "truncated" in done.stderr, done.stderr
    assert not (tmp_path / "out.ply").exists()


def test_polygons_are_fanned_in_order():
    """fan_triangles (vectorised for #34) keeps the order: by fan step, then by polygon."""
    from slscan.ply import fan_triangles

    tris = fan_triangles(np.array([4, 3, 5, 2, 0]), np.arange(14))
    np.testing.assert_array_equal(
        tris, [[0, 1, 2], [4, 5, 6], [7, 8, 9], [0, 2, 3], [7, 9, 10], [7, 10, 11]]
    )


def test_opencv_matrix_without_cols_does_not_corrupt_the_heap(corpus, tmp_path):
    """``FileNode.mat()`` of a matrix without ``<cols>`` wrote past its buffer: reading such a
    file a few hundred times aborted Python (``malloc(): invalid size``). Now every read is
    the same one-line error."""
    path = tmp_path / "result.xml"
    path.write_bytes(corpus["calibration XML (OpenCV)"].read_bytes().replace(b"<cols>3</cols>", b"", 1))
    done = slscan_python(
        "import sys\nfrom slscan.calibrate.io import import_opencv_xml\nfrom slscan.errors import SlscanError\n"
        "for _ in range(300):\n"
        "    try:\n        import_opencv_xml(sys.argv[1], projector_size=(205, 154))\n"
        "    except SlscanError as exc:\n        message = str(exc)\n"
        "print(message)\n", path)
    assert done.returncode == 0, f"exit {done.returncode}: {done.stderr[-2000:]}"
    assert "result.xml: key 'cam_int' is not a list of numbers" in done.stdout


def test_range_map_faces_without_a_list_are_a_clear_error(tmp_path):
    """Found reading the code beside the fuzzed paths: a ``face`` element whose property is
    not a list raised ValueError (unpacking) in the range-map reader."""
    from slscan.decode.rangemap import read_ply

    path = tmp_path / "nolist.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty int vertex_indices\nend_header\n"
                    "0 0 0\n1 0 0\n0 1 0\n5\n")
    with pytest.raises(SlscanError, match=r"nolist\.ply: element 'face' has no list of vertex indices"):
        read_ply(path)
