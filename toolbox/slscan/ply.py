"""PLY input and output shared by the stages.

:func:`read_ply_elements` parses any PLY (ASCII, binary in either byte order) into
``{element: {property: array}}`` and keeps the header comments slscan writes (a range
map's view, a range scan's name, view direction and grid); :func:`write_triangle_ply`
writes a binary little-endian triangle mesh from a structured vertex array. The stages
build their own types on these (:mod:`slscan.decode.rangemap`,
:mod:`slscan.register.rangescan`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import atomic_output_file, write_error

PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
"""PLY property type names -> numpy type codes (no byte order)."""


class PlyData(dict):
    """Elements of a PLY file: ``{element: {property: array}}``; list properties are
    ``(counts (k,), flat values)``. ``info`` holds ``obj_info`` key/values."""

    info: dict[str, str]
    view_direction: np.ndarray | None = None
    up_direction: np.ndarray | None = None
    grid_shape: tuple[int, int] | None = None
    name: str = ""
    is_slscan_range_map: bool = False


def read_ply_elements(path: str | os.PathLike) -> PlyData:
    """Parse a PLY file (ASCII, binary little- or big-endian) into numpy arrays.

    Raises
    ------
    SlscanError
        Missing, not a PLY, unknown format or type, or truncated (naming the file).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SlscanError(f"{path}: PLY file not found") from None
    except IsADirectoryError:
        raise SlscanError(f"{path}: is a folder; expected a PLY file") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise SlscanError(f"{path}: not a PLY file")
    newline = data.find(b"\n", end)
    body_start = newline + 1 if newline >= 0 else len(data)
    out = PlyData()
    out.info = {}
    elements: list[tuple[str, int, list[list[str]]]] = []
    fmt = None
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "format":
            fmt = parts[1] if len(parts) > 1 else None
        elif key == "obj_info" and len(parts) >= 3:
            out.info[parts[1]] = parts[2]
        elif key == "comment" and len(parts) >= 2:
            _header_comment(out, parts[1:], line)
        elif key == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise SlscanError(f"{path}: malformed PLY header line {line.strip()!r}")
            elements.append((parts[1], int(parts[2]), []))
        elif key == "property":
            if not elements:
                raise SlscanError(f"{path}: PLY property before any element")
            elements[-1][2].append(_property(path, parts[1:], elements[-1]))
    for k in ("num_rows", "num_cols"):
        if k in out.info:
            try:
                out.info[k] = int(out.info[k])
            except ValueError:
                pass
    if fmt == "ascii":
        _parse_ascii(path, data[body_start:], elements, out)
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        _parse_binary(
            path, data, body_start, elements, out, "<" if fmt == "binary_little_endian" else ">"
        )
    else:
        raise SlscanError(f"{path}: unknown PLY format {fmt!r}")
    return out


def _header_comment(out: PlyData, words: list[str], line: str) -> None:
    if words[0] in ("view_direction", "up_direction") and len(words) == 4:
        try:
            d = np.array([float(x) for x in words[1:]])
        except ValueError:
            return
        if np.isfinite(d).all() and np.linalg.norm(d) > 0:
            setattr(out, words[0], d)
    elif words[0] == "grid" and len(words) == 3 and words[1].isdigit() and words[2].isdigit():
        out.grid_shape = (int(words[1]), int(words[2]))
    elif words[0] in ("name", "view") and len(words) >= 2:  # slscan scans; decode range maps
        out.name = line.split(None, 2)[2].strip()
    elif " ".join(words[:3]) == "slscan range map":
        out.is_slscan_range_map = True


def _ply_type(path: Path, name: str) -> str:
    try:
        return PLY_TYPES[name]
    except KeyError:
        raise SlscanError(f"{path}: unknown PLY property type {name!r}") from None


def _property(path: Path, words: list[str], element: tuple[str, int, list[list[str]]]) -> list[str]:
    """A header ``property`` line's words after the keyword, checked: ``TYPE NAME`` or
    ``list COUNT_TYPE VALUE_TYPE NAME``, known types, an integer count type, a name not
    already used in the element."""
    where = f"{path}: PLY header, element {element[0]!r}"
    if words[:1] == ["list"]:
        if len(words) != 4:
            raise SlscanError(f"{where}: malformed list property {' '.join(words)!r}; "
                              "expected 'property list COUNT_TYPE VALUE_TYPE NAME'")
        if np.dtype(_ply_type(path, words[1])).kind not in "iu":
            raise SlscanError(f"{where}: list property {words[3]!r} has a count of type {words[1]!r}; "
                              "expected an integer type")
        _ply_type(path, words[2])
    elif len(words) == 2:
        _ply_type(path, words[0])
    else:
        raise SlscanError(f"{where}: malformed property {' '.join(words)!r}; expected 'property TYPE NAME'")
    if any(p[-1] == words[-1] for p in element[2]):
        raise SlscanError(f"{where}: property {words[-1]!r} is declared twice")
    return words


def _typed(path: Path, element: str, prop: str, values: np.ndarray, type_name: str) -> np.ndarray:
    """ASCII values (float64) as the declared type; an integer type refuses values that are
    not whole numbers in its range (NaN, 1e999, 2**32 in an ``int``), naming them."""
    dtype = np.dtype(_ply_type(path, type_name))
    if dtype.kind == "f":
        with np.errstate(over="ignore"):  # 1e308 in a float: inf, refused where it matters
            return values.astype(dtype)
    if len(values):
        info = np.iinfo(dtype)
        bad = ~np.isfinite(values) | (values < info.min) | (values > info.max) | (values != np.round(values))
        if bad.any():
            raise SlscanError(
                f"{path}: element {element!r}, property {prop!r}: value {values[np.argmax(bad)]!r} is not "
                f"a {type_name} ({info.min} to {info.max})"
            )
    return values.astype(dtype)


def _list_count(path: Path, element: str, prop: str, k: float, left: int) -> int:
    """A list's length as read, checked: a whole number, not negative, not past the file's end."""
    if not (np.isfinite(k) and k == int(k) and k >= 0):
        raise SlscanError(f"{path}: element {element!r}, list {prop!r} has length {k!r}; "
                          "expected a whole number, 0 or more")
    if k > left:
        raise SlscanError(f"{path}: file is truncated in element {element!r}")
    return int(k)


def _parse_ascii(path: Path, body: bytes, elements, out: PlyData) -> None:
    try:
        tokens = np.array(body.split(), dtype=np.float64)
    except ValueError:
        raise SlscanError(
            f"{path}: the ASCII PLY body holds something that is not a number"
        ) from None
    pos = 0
    for name, count, props in elements:
        if not props:  # an element without properties holds nothing
            out[name] = {}
            continue
        is_list = [p[0] == "list" for p in props]
        if not any(is_list):
            size = count * len(props)
            if pos + size > len(tokens):
                raise SlscanError(f"{path}: file is truncated in element {name!r}")
            block = tokens[pos : pos + size].reshape(count, len(props))
            out[name] = {
                p[1]: _typed(path, name, p[1], block[:, i], p[0]) for i, p in enumerate(props)
            }
            pos += size
            continue
        if len(props) == 1 and count and pos < len(tokens):
            first = _list_count(path, name, props[0][3], tokens[pos], len(tokens) - pos - 1)
            stride = first + 1
            if pos + count * stride <= len(tokens) and np.all(
                tokens[pos : pos + count * stride : stride] == first
            ):
                block = tokens[pos : pos + count * stride].reshape(count, stride)
                out[name] = {
                    props[0][3]: (
                        np.full(count, first, np.int64),
                        _typed(path, name, props[0][3], block[:, 1:].reshape(-1), props[0][2]),
                    )
                }
                pos += count * stride
                continue
        columns: dict[str, list] = {p[-1]: [] for p in props}
        counts: dict[str, list] = {p[-1]: [] for p in props if p[0] == "list"}
        for _ in range(count):
            for p in props:
                if pos >= len(tokens):
                    raise SlscanError(f"{path}: file is truncated in element {name!r}")
                if p[0] == "list":
                    k = _list_count(path, name, p[-1], tokens[pos], len(tokens) - pos - 1)
                    counts[p[-1]].append(k)
                    columns[p[-1]].append(tokens[pos + 1 : pos + 1 + k])
                    pos += 1 + k
                else:
                    columns[p[-1]].append(tokens[pos])
                    pos += 1
        element = {}
        for p in props:
            if p[0] == "list":
                values = np.concatenate(columns[p[-1]]) if columns[p[-1]] else np.zeros(0)
                element[p[-1]] = (
                    np.array(counts[p[-1]], np.int64),
                    _typed(path, name, p[-1], values, p[2]),
                )
            else:
                element[p[-1]] = _typed(path, name, p[-1], np.array(columns[p[-1]], np.float64), p[0])
        out[name] = element


def _parse_binary(path: Path, data: bytes, offset: int, elements, out: PlyData, order: str) -> None:
    for name, count, props in elements:
        if not props:  # an element without properties holds nothing
            out[name] = {}
            continue
        if not any(p[0] == "list" for p in props):
            dt = np.dtype([(p[1], order + _ply_type(path, p[0])) for p in props])
            if offset + dt.itemsize * count > len(data):
                raise SlscanError(f"{path}: file is truncated in element {name!r}")
            arr = np.frombuffer(data, dt, count, offset)
            out[name] = {p[1]: arr[p[1]].copy() for p in props}
            offset += dt.itemsize * count
            continue
        if len(props) == 1 and count:
            _, count_t, value_t, pname = props[0]
            ct, vt = (
                np.dtype(order + _ply_type(path, count_t)),
                np.dtype(order + _ply_type(path, value_t)),
            )
            if offset + ct.itemsize > len(data):
                raise SlscanError(f"{path}: file is truncated in element {name!r}")
            first = int(np.frombuffer(data, ct, 1, offset)[0])
            record = ct.itemsize + vt.itemsize * first
            if 0 <= first < 2**31 - 1 and offset + record * count <= len(data):
                dt = np.dtype([("n", ct), ("v", vt, (first,))])
                arr = np.frombuffer(data, dt, count, offset)
                if np.all(arr["n"] == first):
                    out[name] = {
                        pname: (np.full(count, first, np.int64), arr["v"].reshape(-1).copy())
                    }
                    offset += dt.itemsize * count
                    continue
        element: dict = {p[-1]: [] for p in props}
        counts: dict[str, list] = {p[-1]: [] for p in props if p[0] == "list"}
        for _ in range(count):
            for p in props:
                if p[0] == "list":
                    ct = np.dtype(order + _ply_type(path, p[1]))
                    vt = np.dtype(order + _ply_type(path, p[2]))
                    if offset + ct.itemsize > len(data):
                        raise SlscanError(f"{path}: file is truncated in element {name!r}")
                    k = int(np.frombuffer(data, ct, 1, offset)[0])
                    offset += ct.itemsize
                    if k < 0:
                        raise SlscanError(f"{path}: element {name!r}, list {p[-1]!r} has length {k}; "
                                          "expected 0 or more")
                    if offset + vt.itemsize * k > len(data):
                        raise SlscanError(f"{path}: file is truncated in element {name!r}")
                    element[p[-1]].append(np.frombuffer(data, vt, k, offset))
                    counts[p[-1]].append(k)
                    offset += vt.itemsize * k
                else:
                    t = np.dtype(order + _ply_type(path, p[0]))
                    if offset + t.itemsize > len(data):
                        raise SlscanError(f"{path}: file is truncated in element {name!r}")
                    element[p[-1]].append(np.frombuffer(data, t, 1, offset)[0])
                    offset += t.itemsize
        parsed = {}
        for p in props:
            if p[0] == "list":
                values = element[p[-1]]
                parsed[p[-1]] = (
                    np.array(counts[p[-1]], np.int64),
                    np.concatenate(values) if values else np.zeros(0),
                )
            else:
                parsed[p[-1]] = np.array(element[p[-1]])
        out[name] = parsed


def fan_triangles(counts: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(m, 3) int64 triangles of polygons given as counts and flat indices (fans).

    A polygon of k vertices gives k - 2 triangles (v0, v[j+1], v[j+2]); polygons of fewer
    than 3 vertices give none. Triangles are ordered by j, then by polygon."""
    counts = np.asarray(counts, np.int64)
    values = np.asarray(values).astype(np.int64)
    if len(counts) == 0:
        return np.zeros((0, 3), np.int64)
    if np.all(counts == 3):
        return values.reshape(-1, 3)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    n_tri = np.maximum(counts - 2, 0)
    poly = np.repeat(np.arange(len(counts)), n_tri)
    j = np.arange(len(poly)) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    order = np.lexsort((poly, j))
    poly, j = poly[order], j[order]
    first = starts[poly]
    return np.stack([values[first], values[first + j + 1], values[first + j + 2]], 1)


_PLY_NAMES = {"f4": "float", "u1": "uchar", "i4": "int", "f8": "double"}


def write_triangle_ply(
    path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, comments: list[str]
) -> Path:
    """Write a binary little-endian triangle-mesh PLY atomically.

    vertices : (n,) structured array, one field per vertex property (little-endian
        float32/float64, uint8 or int32)
    faces : (m, 3) vertex indices, written as ``vertex_indices`` (uchar count, int)
    comments : header ``comment`` lines, without the keyword
    """
    path = Path(path)
    faces = np.asarray(faces).reshape(-1, 3)
    records = np.empty(len(faces), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    records["n"] = 3
    records["i"] = faces
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
    header.append(f"element vertex {len(vertices)}")
    header += [f"property {_PLY_NAMES[vertices.dtype[f].str[1:]]} {f}" for f in vertices.dtype.names]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")
    size = len(head) + vertices.nbytes + records.nbytes
    with atomic_output_file(path, size=size) as tmp, open(tmp, "wb") as fh:
        fh.write(head)
        fh.write(vertices.tobytes())
        fh.write(records.tobytes())
    return path


def check_written_ply(written: str | os.PathLike, target: str | os.PathLike, *, vertices: int,
                      faces: int) -> None:
    """Check a triangle-mesh PLY another library just wrote, before it is renamed into place.

    Its header must say ``vertices`` and ``faces``, and a binary file must be exactly as
    long as the header says (faces are triangles); an ASCII file must have a line per
    vertex and per face. Writers such as Open3D's report success when their writes
    failed (a full disk); this turns the short file into :func:`slscan.fsio.write_error`
    naming ``target``.
    """
    written = Path(written)
    with open(written, "rb") as fh:
        data = fh.read(1 << 16)
        end = data.find(b"end_header")
        newline = data.find(b"\n", end) if end >= 0 else -1
        actual = written.stat().st_size
        if not data.startswith(b"ply") or newline < 0:
            raise write_error(target, written=actual)
        elements: list[tuple[str, int, list[list[str]]]] = []
        fmt = None
        for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
            parts = line.split()
            if parts[:1] == ["format"] and len(parts) > 1:
                fmt = parts[1]
            elif parts[:1] == ["element"] and len(parts) == 3 and parts[2].isdigit():
                elements.append((parts[1], int(parts[2]), []))
            elif parts[:1] == ["property"] and elements:
                elements[-1][2].append(parts[1:])
        counts = {name: n for name, n, _ in elements}
        if counts.get("vertex") != vertices or counts.get("face", 0) != faces:
            raise SlscanError(f"{target}: the mesh writer wrote {counts.get('vertex')} vertices and "
                              f"{counts.get('face', 0)} faces, expected {vertices} and {faces}")
        if fmt == "ascii":
            fh.seek(newline + 1)
            lines = sum(1 for line in fh if line.strip())
            if lines < vertices + faces:
                raise write_error(target, written=actual)
            return
    try:
        body = 0
        for _, n, props in elements:
            record = 0
            for prop in props:
                if prop[0] == "list":  # count, then three indices (triangles)
                    record += np.dtype(PLY_TYPES[prop[1]]).itemsize + 3 * np.dtype(PLY_TYPES[prop[2]]).itemsize
                else:
                    record += np.dtype(PLY_TYPES[prop[0]]).itemsize
            body += n * record
    except (KeyError, IndexError):
        raise SlscanError(f"{target}: the mesh writer wrote a PLY header slscan cannot check") from None
    needed = newline + 1 + body
    if actual != needed:
        raise write_error(target, needed=needed, written=actual)
