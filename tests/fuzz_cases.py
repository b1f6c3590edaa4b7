"""Fuzzing slscan's file readers: valid files made by slscan's own writers, mutated byte- and
structure-wise, and the verdict on what a reader made of each mutant (#34).

Shared by ``tests/faults/test_fuzz_readers.py`` (Hypothesis, a few hundred cases per reader)
and ``benchmarks/fuzz_readers.py`` (10,000 per reader, each reader in a worker process so
that a native crash or a hang is seen). A reader passes a case when it returns a valid
result or raises :class:`~slscan.errors.SlscanError` whose message names the file.
"""

from __future__ import annotations

import copy
import json
import math
import random
import re
import shutil
import tomllib
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slscan.errors import SlscanError

OUTCOMES = ("ok", "clear error", "unnamed error", "invalid result", "crash", "hang")
"""What a reader made of a case: a valid result; SlscanError naming the file; SlscanError
not naming it; a result that breaks the reader's promise (faces past the vertices, NaN
where it promises finite numbers); any other exception; no answer in time (benchmark)."""

WEIRD_NUMBERS = (
    "0", "-1", "1", "-0", "2147483647", "2147483648", "4294967289", "4294967296", "-2147483649",
    "9223372036854775808", "1e308", "-1e308", "1e-320", "1e999", "nan", "NaN", "inf", "-inf",
    "Infinity", "0.5", "-3.25", "1e6", "65535", "256", "255", "00", "0x10", "1_0", "",
)
WEIRD_VALUES: tuple[Any, ...] = (
    0, -1, 1, 2**31, 2**32 - 7, 2**63, -(2**63), 2**70, 1e308, -1e308, 1e-320, math.nan, math.inf,
    -math.inf, 0.5, -2.5, "", "x", "NaN", "../../etc/passwd", None, True, False, [], {}, [1, 2],
    [[1, 2, 3]], {"a": 1}, [None], "1e999",
)


# --- the corpus: valid files of every kind ------------------------------------------------------


CAM_SIZE, PROJ_SIZE = (288, 192), (205, 154)


def _calibration():
    """A calibration of the paper's rig with a distorted projector and light planes."""
    from slscan.calibrate.io import Calibration
    from slscan.calibrate.planes import LightPlaneModel
    from slscan.calibrate.target import Board
    from slscan.rig import PinholeModel, Projector, default_rig

    rig = default_rig(scale=0.2, projector_scale=0.2)
    lens = rig.projector.lens
    proj = Projector(
        PinholeModel(lens.width, lens.height, lens.fx, lens.fy, lens.cx, lens.cy,
                     (0.01, -0.02, 0.001, 0.0005, 0.003)),
        rig.projector.rig_from_projector,
    )
    model = LightPlaneModel(lens.width, lens.fx, lens.cx, rig.projector.rig_from_projector)
    cols = np.arange(0.5, lens.width - 1, 32.0)
    return Calibration(
        camera=rig.camera, projector_size=(lens.width, lens.height), projector=proj, light_planes=model,
        raw_columns=cols, raw_planes=model.planes(cols), board=Board(kind="charuco", square=40.0),
        residuals={"camera": {"rms_px": 0.05}}, source={"session": "board"},
    )


def _vec(values) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def write_ascii_ply(path: Path, ply, comments: tuple[str, ...] = ()) -> Path:
    """``ply`` (as :func:`slscan.ply.read_ply_elements` returns it) written as ASCII PLY."""
    from slscan.ply import PLY_TYPES

    names = {v: k for k, v in reversed(list(PLY_TYPES.items()))}
    head = ["ply", "format ascii 1.0", *(f"comment {c}" for c in comments)]
    rows_of = {}
    for element, props in ply.items():
        count = None
        columns = []
        for name, value in props.items():
            if isinstance(value, tuple):
                counts, flat = value
                head_line = f"property list uchar {names[flat.dtype.str[1:]]} {name}"
                starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(int)
                columns.append([" ".join([str(k), *map(str, flat[s:s + k])]) for s, k in zip(starts, counts)])
                count = len(counts)
            else:
                head_line = f"property {names[value.dtype.str[1:]]} {name}"
                columns.append([repr(float(x)) if value.dtype.kind == "f" else str(int(x)) for x in value])
                count = len(value)
            head.append(head_line)
        head.insert(len(head) - len(props), f"element {element} {count}")
        rows_of[element] = [" ".join(parts) for parts in zip(*columns)]
    body = "".join(line + "\n" for rows in rows_of.values() for line in rows)
    path.write_text("\n".join(head) + "\nend_header\n" + body)
    return path


def build_corpus(folder: Path) -> dict[str, Path]:
    """Write one valid file of every kind under ``folder``: {kind: the file}. Files a reader
    reads from a folder (session.json, patterns.json, codes.json) come with their folders.

    A 288 x 192 Gray-code capture of the virtual figurine (one view), decoded with
    ``--codes``; the range map cut to 40 faces; the rest from slscan's own writers, and for
    the formats slscan only reads (other tools' calibrations, Stanford) the files those
    tools write, as the tests of their readers build them.
    """
    from slscan.calibrate.io import export_opencv_xml, save_calibration
    from slscan.cli import main
    from slscan.decode.rangemap import RangeMap, read_ply, write_ply
    from slscan.patterns import standard_set, write_pattern_set
    from slscan.ply import read_ply_elements
    from slscan.recipe.runner import shipped_recipe
    from slscan.register.meshlab import Raster, write_mlp
    from slscan.virtual.device import VirtualCaptureConfig, capture_session
    from slscan.virtual.sensor import Sensor

    import cv2

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    config = VirtualCaptureConfig(scene="object", views=1, patterns="gray", camera_scale=0.2,
                                  projector_scale=0.2, lit_images=False, sensor=Sensor(noise=False))
    capture_session(config, folder / "session")
    files["session.json"] = folder / "session" / "session.json"
    code = main(["decode", str(folder / "session"), "--out", str(folder / "decoded"), "--codes", "--quiet"])
    assert code == 0, "decoding the corpus session failed"
    files["codes.json"] = folder / "decoded" / "view_000" / "codes.json"
    files["projector_codes.json"] = folder / "decoded" / "projector_codes.json"
    files["range_maps.json"] = folder / "decoded" / "range_maps.json"

    rm = read_ply(folder / "decoded" / "view_000.ply")
    keep = rm.faces[:40]
    used, inverse = np.unique(keep, return_inverse=True)
    small = RangeMap(
        vertices=rm.vertices[used], faces=inverse.reshape(-1, 3).astype(np.int32), normals=rm.normals[used],
        colors=rm.colors[used], quality=rm.quality[used], row=rm.row[used], stripe=rm.stripe[used],
        view="view_000",
    )
    meshes = folder / "meshes"
    meshes.mkdir()
    files["range map (binary PLY)"] = write_ply(small, meshes / "view_000.ply")
    files["range map (ASCII PLY)"] = write_ascii_ply(
        meshes / "view_000_ascii.ply", read_ply_elements(meshes / "view_000.ply"),
        ("slscan range map (mm, rig frame)", "view view_000"))
    grid = np.array([[0, 1, 2, -1], [3, 4, 5, 6], [7, 8, -1, 9]])
    points = np.array([(c * 0.001, r * 0.001, 0.0005 * (r + c)) for r in range(3) for c in range(4)])[:10]
    cells = "".join("0\n" if i < 0 else f"1 {i}\n" for i in grid.ravel())
    (meshes / "scan_grid.ply").write_text(
        "ply\nformat ascii 1.0\nobj_info num_cols 4\nobj_info num_rows 3\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element range_grid {grid.size}\nproperty list uchar int vertex_indices\nend_header\n"
        + "".join(f"{x} {y} {z}\n" for x, y, z in points) + cells)
    files["Stanford range grid (ASCII PLY)"] = meshes / "scan_grid.ply"

    world = np.eye(4)
    world[:3, 3] = (1.0, 2.0, 3.0)
    raster = Raster("view_000", "view_000.png", 288, 192, 300.0, 301.0, 143.5, 95.5, world)
    shutil.copy(folder / "session" / "view_000" / "00_white.png", meshes / "view_000.png")
    files[".mlp"] = write_mlp(meshes / "aligned.mlp", [(meshes / "view_000.ply", np.eye(4))], rasters=[raster])
    (meshes / "bun.conf").write_text(
        "camera 0.0 0.0 0.0 0.0 0.0 0.0 1.0\n"
        "bmesh view_000.ply 0.01 -0.02 0.03 0.1 0.2 0.3 0.927\n"
        "bmesh view_000_ascii.ply 0 0 0 0 0 0 1\n")
    files[".conf"] = meshes / "bun.conf"

    patterns = write_pattern_set(folder / "patterns", standard_set("gray", width=64, height=48))
    files["patterns.json"] = patterns / "patterns.json"

    cal = _calibration()
    calib = folder / "calibration"
    calib.mkdir()
    files["calibration JSON"] = save_calibration(cal, calib / "rig.json")
    files["calibration XML (OpenCV)"] = export_opencv_xml(cal, calib / "result.xml")
    cam, proj = cal.camera, cal.projector.lens
    proj_from_cam = np.linalg.inv(cal.projector.rig_from_projector)
    om = cv2.Rodrigues(proj_from_cam[:3, :3])[0].ravel()

    def block(side: str, lens) -> str:
        return (f"fc_{side} = [ {lens.fx!r} {lens.fy!r} ];\ncc_{side} = [ {lens.cx!r} {lens.cy!r} ];\n"
                f"alpha_c_{side} = 0.000000000000000;\nkc_{side} = [ {_vec(lens.dist)} ];\n")

    (calib / "calib.m").write_text(
        "% Projector-Camera Stereo calibration parameters:\n\n% Intrinsic parameters of camera:\n"
        + block("left", cam) + "\n% Intrinsic parameters of projector:\n" + block("right", proj)
        + f"\n% Extrinsic parameters (position of projector wrt camera):\nom = [ {_vec(om)} ]; % Rotation vector\n"
        f"T = [ {_vec(proj_from_cam[:3, 3])} ]; % Translation vector\n")
    files["calibration Bouguet .m"] = calib / "calib.m"
    (calib / "rig.txt").write_text(
        f"# camera\nK_cam:\n{_vec(cam.K[0])}\n{_vec(cam.K[1])}\n{_vec(cam.K[2])}\ndist_cam = [{_vec(cam.dist)}]\n"
        f"K_proj: {_vec(proj.K)}\ndist_proj: {', '.join(repr(v) for v in proj.dist)}\n"
        f"R: {_vec(proj_from_cam[:3, :3])}\nT: {_vec(proj_from_cam[:3, 3])}\nsize_cam: {CAM_SIZE[0]} {CAM_SIZE[1]}\n")
    files["calibration text"] = calib / "rig.txt"

    from slscan.albedo.lights import LightCalibration, write_lights
    from slscan.fsio import write_json
    from slscan.rig import default_rig

    rig = default_rig(scale=0.2, projector_scale=0.2)
    rigs = folder / "rig"
    rigs.mkdir()
    write_json(rigs / "rig.json", rig.to_dict())
    files["rig JSON"] = rigs / "rig.json"
    files["lights JSON"] = write_lights(rigs / "lights.json", LightCalibration.from_rig(rig))
    world = np.eye(4)
    world[:3, 3] = (10.0, -5.0, 2.5)
    write_json(meshes / "registration.json", {"format": "slscan.registration", "version": 1,
                                              "poses": {"view_000": world.tolist(), "scan_grid": np.eye(4).tolist()}})
    files["registration.json"] = meshes / "registration.json"

    recipes = folder / "recipes"
    recipes.mkdir()
    files["recipe TOML"] = Path(shutil.copy(shipped_recipe("demo"), recipes / "demo.toml"))
    return files


# --- mutations ----------------------------------------------------------------------------------


_NUMBER = re.compile(rb"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def _bytes_mutation(data: bytes, rnd: random.Random) -> bytes:
    """Truncate, flip, overwrite, insert, delete or duplicate bytes."""
    n = len(data)
    op = rnd.randrange(7)
    i = rnd.randrange(n + 1) if n else 0
    if op == 0:  # truncation
        return data[:i]
    if op == 1 and n:  # bit flips
        b = bytearray(data)
        for _ in range(rnd.randint(1, 8)):
            b[rnd.randrange(n)] ^= 1 << rnd.randrange(8)
        return bytes(b)
    if op == 2 and n:  # overwrite with random or special bytes
        k = rnd.randint(1, 16)
        fill = bytes(rnd.choice((0, 0xFF, 0x7F, 0x80, rnd.randrange(256))) for _ in range(k))
        return data[:i] + fill + data[i + k:]
    if op == 3:  # insertion
        return data[:i] + rnd.randbytes(rnd.randint(1, 32)) + data[i:]
    if op == 4:  # deletion
        return data[:i] + data[i + rnd.randint(1, 64):]
    if op == 5:  # duplication
        j = min(n, i + rnd.randint(1, 256))
        return data[:j] + data[i:j] + data[j:]
    return data[: i // 2] if rnd.random() < 0.5 else b""


def _text_mutation(data: bytes, rnd: random.Random) -> bytes:
    """Replace a number by a weird one, or drop, duplicate or swap lines."""
    op = rnd.randrange(4)
    numbers = list(_NUMBER.finditer(data))
    if op <= 1 and numbers:
        for _ in range(rnd.randint(1, 3)):
            m = rnd.choice(numbers)
            data = data[: m.start()] + rnd.choice(WEIRD_NUMBERS).encode() + data[m.end():]
            numbers = list(_NUMBER.finditer(data))
            if not numbers:
                break
        return data
    lines = data.split(b"\n")
    if len(lines) < 2:
        return _bytes_mutation(data, rnd)
    i, j = rnd.randrange(len(lines)), rnd.randrange(len(lines))
    if op == 2:
        del lines[i]
    elif rnd.random() < 0.5:
        lines.insert(j, lines[i])
    else:
        lines[i], lines[j] = lines[j], lines[i]
    return b"\n".join(lines)


def _tree_paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(node, dict):
        for k, v in node.items():
            out += _tree_paths(v, prefix + (k,))
    elif isinstance(node, list):
        for k, v in enumerate(node):
            out += _tree_paths(v, prefix + (k,))
    return out


def _mutate_tree(tree: Any, rnd: random.Random) -> Any:
    """Delete a key or element, give it a weird value or type, empty, shorten or lengthen a list."""
    paths = [p for p in _tree_paths(tree) if p]
    if not paths:
        return copy.deepcopy(rnd.choice(WEIRD_VALUES))
    path = rnd.choice(paths)
    parent = tree
    for key in path[:-1]:
        parent = parent[key]
    key, value = path[-1], parent[path[-1]]
    op = rnd.randrange(5)
    if op == 0:
        del parent[key]
    elif op == 1 and isinstance(value, list):
        cut = value[: rnd.randrange(len(value) + 1)]
        parent[key] = cut if rnd.random() < 0.5 else value + value[:1] * rnd.randint(1, 3)
    elif op == 2 and isinstance(value, (int, float)) and not isinstance(value, bool):
        parent[key] = rnd.choice([-value, value * 1e6, value + 1, value - 1, math.nan, math.inf, 0, -1, 2**32 - 7])
    elif op == 3 and isinstance(value, str):
        parent[key] = rnd.choice(["", value * 2, value[:-1], "../" + value, value.upper(), "\x00", "é" + value])
    else:
        parent[key] = copy.deepcopy(rnd.choice(WEIRD_VALUES))  # a copy: never a tree holding itself
    return tree


def _json_mutation(data: bytes, rnd: random.Random) -> bytes:
    tree = json.loads(data)
    for _ in range(rnd.randint(1, 3)):
        tree = _mutate_tree(tree, rnd)
    return json.dumps(tree).encode()


def _toml_mutation(data: bytes, rnd: random.Random) -> bytes:
    from slscan.recipe.config import dumps_toml

    tree = tomllib.loads(data.decode())
    for _ in range(rnd.randint(1, 3)):
        tree = _mutate_tree(tree, rnd)
    try:
        return dumps_toml(tree).encode()
    except Exception:  # a value TOML cannot hold (None): mutate the text instead
        return _text_mutation(data, rnd)


def _xml_mutation(data: bytes, rnd: random.Random) -> bytes:
    """Drop an element or attribute, or give an element's text or an attribute a weird value."""
    declaration = data.split(b"\n", 1)[0] + b"\n" if data.startswith(b"<?xml") else b""
    doctype = re.search(rb"<!DOCTYPE[^>]*>\n?", data)
    root = ET.fromstring(data)
    nodes = list(root.iter())
    node = rnd.choice(nodes)
    op = rnd.randrange(4)
    if op == 0 and node is not root:
        parent = next(p for p in nodes if node in list(p))
        parent.remove(node)
    elif op == 1 and node.attrib:
        key = rnd.choice(sorted(node.attrib))
        if rnd.random() < 0.3:
            del node.attrib[key]
        else:
            node.set(key, rnd.choice(WEIRD_NUMBERS + ("x", "", "-5 3", "1 2 3")))
    elif op == 2 and (node.text or "").strip():
        words = node.text.split()
        words[rnd.randrange(len(words))] = rnd.choice(WEIRD_NUMBERS)
        if rnd.random() < 0.3:
            words = words[: rnd.randrange(len(words) + 1)]
        node.text = " ".join(words)
    else:
        node.append(ET.fromstring(rnd.choice(['<MLMesh filename="x.ply"/>', "<Plane/>", "<rows>0</rows>",
                                              '<VCGCamera FocalMm="1"/>', "<data>nan</data>"])))
    return declaration + (doctype.group(0) if doctype else b"") + ET.tostring(root)


def _ply_mutation(data: bytes, rnd: random.Random) -> bytes:
    """Change the header (counts, types, properties, format) or, in a binary body, a number."""
    end = data.find(b"end_header")
    if end < 0:
        return _bytes_mutation(data, rnd)
    body_start = data.find(b"\n", end) + 1
    head, body = data[:body_start].split(b"\n"), data[body_start:]
    op = rnd.randrange(6)
    lines = [i for i, line in enumerate(head) if line.startswith((b"element", b"property", b"format"))]
    if op <= 2 and lines:
        i = rnd.choice(lines)
        words = head[i].split()
        if words[0] == b"element" and len(words) == 3:
            words[2] = rnd.choice(WEIRD_NUMBERS).encode()
        elif words[0] == b"property":
            types = [b"char", b"uchar", b"short", b"ushort", b"int", b"uint", b"float", b"double", b"int64",
                     b"list"]
            words[rnd.randrange(1, len(words))] = rnd.choice(types)
        elif words[0] == b"format":
            words[1] = rnd.choice([b"ascii", b"binary_little_endian", b"binary_big_endian", b"binary"])
        if op == 2:
            head.insert(i, head[i]) if rnd.random() < 0.5 else head.pop(i)
        else:
            head[i] = b" ".join(words)
        return b"\n".join(head) + body
    if op == 3 and b"format ascii" not in data[:body_start] and len(body) >= 4:
        i = rnd.randrange(len(body) // 4) * 4 + rnd.choice((0, 1, 0))
        value = rnd.choice([
            np.int32(-1).tobytes(), np.uint32(2**32 - 7).tobytes(), np.int32(2**31 - 1).tobytes(),
            np.float32(np.nan).tobytes(), np.float32(np.inf).tobytes(), np.float32(-1e38).tobytes(),
            np.int32(1000).tobytes(), b"\xff\xff\xff\xff",
        ])
        return data[:body_start] + body[:i] + value + body[i + 4:]
    return _text_mutation(data, rnd) if op == 4 else _bytes_mutation(data, rnd)


def mutate(data: bytes, kind: str, rnd: random.Random) -> bytes:
    """One to three mutations of ``data``, a valid file of ``kind`` (json, toml, xml, ply, text)."""
    structured = {"json": _json_mutation, "toml": _toml_mutation, "xml": _xml_mutation, "ply": _ply_mutation}
    for _ in range(rnd.randint(1, 3)):
        r = rnd.random()
        try:
            if r < 0.5 and kind in structured:
                data = structured[kind](data, rnd)
            elif r < 0.8:
                data = _text_mutation(data, rnd)
            else:
                data = _bytes_mutation(data, rnd)
        except (ValueError, TypeError, ET.ParseError, tomllib.TOMLDecodeError, UnicodeDecodeError, StopIteration):
            data = _bytes_mutation(data, rnd)  # an earlier mutation broke the syntax
    return data


# --- the readers and what each promises ----------------------------------------------------------


def _finite(a) -> bool:
    return bool(np.isfinite(np.asarray(a, np.float64)).all())


def _mesh_check(vertices, faces) -> str | None:
    vertices, faces = np.asarray(vertices), np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        return f"vertices of shape {vertices.shape}"
    if not _finite(vertices):
        return "non-finite vertices"
    if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
        return f"a face index outside 0..{len(vertices) - 1}"
    return None


def _check_ply(ply) -> str | None:
    for element, props in ply.items():
        lengths = set()
        for value in props.values():
            if isinstance(value, tuple):
                counts, flat = value
                if int(np.sum(counts)) != len(flat) or (len(counts) and counts.min() < 0):
                    return f"{element}: list counts {int(np.sum(counts))} for {len(flat)} values"
                lengths.add(len(counts))
            else:
                lengths.add(len(value))
        if len(lengths) > 1:
            return f"{element}: properties of different lengths {sorted(lengths)}"
    return None


def _check_range_map(rm) -> str | None:
    n = len(rm.vertices)
    bad = _mesh_check(rm.vertices, rm.faces)
    if bad:
        return bad
    if any(len(a) != n for a in (rm.normals, rm.colors, rm.quality, rm.row, rm.stripe)):
        return "vertex properties of different lengths"
    return None


def _check_scan(scan) -> str | None:
    return _mesh_check(scan.vertices, scan.faces) or (None if _finite(scan.quality) else "non-finite quality")


def _check_codes(codes) -> str | None:
    shape = codes.mask.shape
    if codes.column is None or codes.column.shape != shape or (codes.row is not None and codes.row.shape != shape):
        return "maps of different shapes"
    return None


def _check_pose_dict(poses) -> str | None:
    if not poses or any(np.shape(m) != (4, 4) for m in poses.values()):
        return "not a (4, 4) pose per scan"
    return None


def _check_mlp(entries) -> str | None:
    if any(np.shape(m) != (4, 4) or not _finite(m) for _, m in entries):
        return "a non-finite or misshapen matrix"
    return None


def _check_calibration(cal) -> str | None:
    """A calibration's (or a rig's) lenses and projector pose are possible."""
    lenses = [cal.camera] + ([cal.projector.lens] if cal.projector is not None else [])
    for lens in lenses:
        values = (lens.fx, lens.fy, lens.cx, lens.cy, *lens.dist)
        if not _finite(values) or lens.fx <= 0 or lens.fy <= 0 or lens.width <= 0 or lens.height <= 0:
            return f"an impossible lens {values[:4]} {lens.width}x{lens.height}"
    if cal.projector is not None and not _finite(cal.projector.rig_from_projector):
        return "a non-finite projector pose"
    return None


@dataclass(frozen=True)
class Reader:
    """One reader under test.

    name : the row of the benchmark's table
    kind : the corpus file it reads (a key of :func:`build_corpus`)
    syntax : how that file is mutated structurally {"json", "toml", "xml", "ply", "text"}
    read : reads the case (given the mutated file's path; returns the result)
    check : the reader's promise on a result: None, or what is wrong
    """

    name: str
    kind: str
    syntax: str
    read: Callable[[Path], Any]
    check: Callable[[Any], str | None] = lambda result: None


def _readers() -> list[Reader]:
    from slscan.calibrate.importers import read_bouguet, read_calibration, read_text
    from slscan.calibrate.io import import_opencv_xml, load_calibration
    from slscan.capture.session import load_session
    from slscan.decode.codes import read_codes
    from slscan.decode.rangemap import read_ply
    from slscan.fuse import read_mesh
    from slscan.patterns import read_pattern_set
    from slscan.ply import read_ply_elements
    from slscan.recipe.runner import load_recipe
    from slscan.recipe.surfaces import read_surface
    from slscan.albedo.lights import read_lights
    from slscan.register.command import load_poses, load_scans
    from slscan.texture.views import read_poses
    from slscan.virtual.rigs import load_rig_file
    from slscan.register.meshlab import read_mlp, read_mlp_rasters
    from slscan.register.rangescan import load_bun_conf, load_range_scan

    ply_readers = []
    for kind, tag in (("range map (binary PLY)", "binary"), ("range map (ASCII PLY)", "ASCII")):
        ply_readers += [
            Reader(f"ply.read_ply_elements ({tag})", kind, "ply", read_ply_elements, _check_ply),
            Reader(f"decode.rangemap.read_ply ({tag})", kind, "ply", read_ply, _check_range_map),
            Reader(f"register.load_range_scan ({tag})", kind, "ply", load_range_scan, _check_scan),
            Reader(f"fuse.read_mesh, Open3D ({tag})", kind, "ply", read_mesh,
                   lambda m: _mesh_check(m.vertices, m.faces)),
            Reader(f"recipe.read_surface ({tag})", kind, "ply", read_surface,
                   lambda s: _mesh_check(s.vertices, s.faces)),
        ]
    return ply_readers + [
        Reader("register.load_stanford_scan (ASCII PLY)", "Stanford range grid (ASCII PLY)", "ply",
               load_range_scan, _check_scan),
        Reader("capture.load_session (session.json)", "session.json", "json", lambda p: load_session(p.parent)),
        Reader("patterns.read_pattern_set (patterns.json)", "patterns.json", "json",
               lambda p: read_pattern_set(p.parent), lambda r: None if r else "no patterns"),
        Reader("decode.read_codes (codes.json)", "codes.json", "json", lambda p: read_codes(p.parent),
               _check_codes),
        Reader("decode.read_codes (projector_codes.json)", "projector_codes.json", "json",
               lambda p: read_codes(p.parent), _check_codes),
        Reader("register.load_scans (range_maps.json)", "range_maps.json", "json",
               lambda p: load_scans(p.parent), lambda r: None if r[0] else "no scans"),
        Reader("register.read_mlp (.mlp)", ".mlp", "xml", read_mlp, _check_mlp),
        Reader("register.read_mlp_rasters (.mlp)", ".mlp", "xml", read_mlp_rasters),
        Reader("register.load_bun_conf (.conf)", ".conf", "text", load_bun_conf, _check_pose_dict),
        Reader("calibrate.load_calibration (JSON)", "calibration JSON", "json", load_calibration,
               _check_calibration),
        Reader("calibrate.import_opencv_xml (XML)", "calibration XML (OpenCV)", "xml",
               lambda p: import_opencv_xml(p, projector_size=PROJ_SIZE), _check_calibration),
        Reader("calibrate.read_calibration (OpenCV XML)", "calibration XML (OpenCV)", "xml",
               lambda p: read_calibration([p]).to_calibration(projector_size=PROJ_SIZE), _check_calibration),
        Reader("calibrate.read_bouguet (.m)", "calibration Bouguet .m", "text",
               lambda p: read_bouguet(p).to_calibration(camera_size=CAM_SIZE, projector_size=PROJ_SIZE),
               _check_calibration),
        Reader("calibrate.read_text (.txt)", "calibration text", "text",
               lambda p: read_text(p).to_calibration(projector_size=PROJ_SIZE), _check_calibration),
        Reader("recipe.load_recipe (TOML)", "recipe TOML", "toml", load_recipe),
        Reader("virtual.load_rig_file (rig JSON)", "rig JSON", "json", load_rig_file,
               _check_calibration),
        Reader("albedo.read_lights (lights JSON)", "lights JSON", "json", read_lights,
               lambda cal: None if _finite([x.position for x in cal.lights]) and _finite(cal.ambient)
               else "non-finite lights"),
        Reader("texture.read_poses (registration.json)", "registration.json", "json", read_poses,
               lambda poses: None if all(_finite(m) for m in poses.values()) else "a non-finite pose"),
        Reader("register.load_poses (registration.json)", "registration.json", "json",
               lambda p: load_poses(p, ["view_000", "scan_grid"]),
               lambda poses: None if all(_finite(m) for m in poses.values()) else "a non-finite pose"),
    ]


READERS: dict[str, Reader] = {}


def readers() -> dict[str, Reader]:
    """Every reader under test, by name (imported on first use)."""
    if not READERS:
        READERS.update((r.name, r) for r in _readers())
    return READERS


def case_folder(corpus: dict[str, Path], reader: Reader, root: Path) -> Path:
    """A private copy of the folder of ``reader``'s corpus file under ``root``; returns the
    file's path in it (mutants are written there, over the file)."""
    source = corpus[reader.kind]
    target = root / re.sub(r"[^A-Za-z0-9]+", "_", reader.name).strip("_")
    if not target.exists():
        shutil.copytree(source.parent, target, symlinks=True)
    return target / source.name


@dataclass(frozen=True)
class Verdict:
    """What a reader made of one case: an entry of :data:`OUTCOMES` and the detail."""

    outcome: str
    detail: str = ""


def judge(reader: Reader, path: Path) -> Verdict:
    """Read ``path`` with ``reader`` in this process and judge the outcome (no time limit)."""
    try:
        result = reader.read(path)
    except SlscanError as exc:
        message = str(exc)
        named = path.name in message or str(path.parent) in message
        return Verdict("clear error" if named else "unnamed error", message)
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # noqa: BLE001 - any other exception is what we look for
        import traceback

        return Verdict("crash", "".join(traceback.format_exception_only(type(exc), exc)).strip()
                       + "\n" + "".join(traceback.format_tb(exc.__traceback__)[-3:]))
    reason = reader.check(result)
    return Verdict("invalid result", reason) if reason else Verdict("ok")
