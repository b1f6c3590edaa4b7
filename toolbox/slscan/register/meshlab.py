"""MeshLab projects (``.mlp``) of aligned range scans: write one, read one back.

A project lists meshes by file name (relative to the project's folder) with a 4×4
transform each, written in ``<MLMatrix44>`` as 16 numbers row by row (translation in the
last column), the same world_from_scan pose this package uses. The meshes keep their
own frame; MeshLab (and ``pymeshlab.MeshSet().load_project``) applies the matrix when
showing them, and "Freeze matrix" bakes it in.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import atomic_output_dir, atomic_output_file
from slscan.register.rangescan import RangeScan, load_range_scan, write_range_scan


def format_mlp(entries: Sequence[tuple[str, str, np.ndarray]]) -> str:
    """Text of a MeshLab project: ``entries`` are (label, file name, (4, 4) transform)."""
    lines = ["<!DOCTYPE MeshLabDocument>", "<MeshLabProject>", " <MeshGroup>"]
    for label, filename, matrix in entries:
        m = np.asarray(matrix, np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise SlscanError(
                f"MeshLab project: transform of {label!r} must be a finite 4x4 matrix"
            )
        numbers = " ".join(f"{x:.17g}" for x in m.reshape(-1))
        lines += [
            f'  <MLMesh label="{_xml_attr(label)}" visible="1" filename="{_xml_attr(filename)}">',
            "   <MLMatrix44>",
            numbers + " ",
            "</MLMatrix44>",
            "  </MLMesh>",
        ]
    lines += [" </MeshGroup>", " <RasterGroup/>", "</MeshLabProject>", ""]
    return "\n".join(lines)


def write_mlp(
    path: str | os.PathLike, meshes: Sequence[tuple[str | os.PathLike, np.ndarray]]
) -> Path:
    """Write a MeshLab project naming existing mesh files, atomically.

    meshes : (mesh file, (4, 4) transform) pairs; files are written relative to the
        project's folder when they lie under it, absolute otherwise
    """
    path = Path(path)
    base = path.parent.resolve()
    entries = []
    for file, matrix in meshes:
        file = Path(file)
        resolved = (base / file) if not file.is_absolute() else file
        try:
            name = resolved.resolve().relative_to(base).as_posix()
        except ValueError:
            name = str(resolved.resolve())
        entries.append((Path(name).name, name, matrix))
    with atomic_output_file(path) as tmp:
        tmp.write_text(format_mlp(entries))
    return path


def write_scan_project(
    folder: str | os.PathLike,
    scans: Sequence[RangeScan],
    poses: Mapping[str, np.ndarray],
    *,
    project_name: str = "aligned.mlp",
    overwrite: bool = False,
) -> Path:
    """Write an aligned set: each scan as ``NAME.ply`` (scan frame, mm) and a project.

    The folder is written atomically (see :func:`slscan.fsio.atomic_output_dir`); scans
    without a pose are left out of it. Returns the project's path.
    """
    folder = Path(folder)
    missing = [s.name for s in scans if s.name not in poses]
    if missing:
        raise SlscanError(f"{folder}: no pose for scans {missing}")
    names = [s.name for s in scans]
    if len(set(names)) != len(names) or any(not n or "/" in n or "\\" in n for n in names):
        raise SlscanError(
            f"{folder}: scan names must be distinct, non-empty file names, got {names}"
        )
    with atomic_output_dir(folder, overwrite=overwrite) as tmp:
        entries = []
        for scan in scans:
            write_range_scan(scan, tmp / f"{scan.name}.ply")
            entries.append((scan.name, f"{scan.name}.ply", poses[scan.name]))
        (tmp / project_name).write_text(format_mlp(entries))
    return folder / project_name


def read_mlp(path: str | os.PathLike, *, check_files: bool = True) -> list[tuple[Path, np.ndarray]]:
    """Read a MeshLab project: [(mesh file path, (4, 4) float64 transform)], in order.

    Relative file names are resolved against the project's folder. A mesh without a
    ``MLMatrix44`` gets the identity.

    Raises
    ------
    SlscanError
        Missing or malformed project, a bad matrix, or (with ``check_files``) mesh files
        that do not exist (all of them named).
    """
    path = Path(path)
    try:
        root = ET.fromstring(path.read_text())
    except FileNotFoundError:
        raise SlscanError(f"{path}: MeshLab project not found") from None
    except (ET.ParseError, UnicodeDecodeError) as exc:
        raise SlscanError(f"{path}: not a MeshLab project ({exc})") from None
    if root.tag != "MeshLabProject":
        raise SlscanError(f"{path}: root element is <{root.tag}>; expected <MeshLabProject>")
    out = []
    for mesh in root.iter("MLMesh"):
        filename = mesh.get("filename")
        if not filename:
            raise SlscanError(f"{path}: an <MLMesh> has no filename attribute")
        matrix = np.eye(4)
        node = mesh.find("MLMatrix44")
        if node is not None and (node.text or "").strip():
            try:
                values = [float(x) for x in node.text.split()]
            except ValueError:
                raise SlscanError(
                    f"{path}: MLMatrix44 of {filename!r} holds something that is not a number"
                ) from None
            if len(values) != 16:
                raise SlscanError(
                    f"{path}: MLMatrix44 of {filename!r} has {len(values)} numbers; expected 16"
                )
            matrix = np.array(values).reshape(4, 4)
        file = Path(filename)
        out.append((file if file.is_absolute() else path.parent / file, matrix))
    if check_files:
        missing = [str(f) for f, _ in out if not f.is_file()]
        if missing:
            raise SlscanError(
                f"{path}: the project names mesh files that do not exist: {', '.join(missing)}"
            )
    return out


def load_scan_project(path: str | os.PathLike) -> tuple[list[RangeScan], dict[str, np.ndarray]]:
    """Scans and world_from_scan poses (mm) of a MeshLab project of range scans.

    Scans are named by their file stems, which must be distinct.
    """
    scans, poses = [], {}
    for file, matrix in read_mlp(path):
        scan = load_range_scan(file)
        if scan.name in poses:
            raise SlscanError(f"{path}: two meshes are named {scan.name!r}")
        scans.append(scan)
        poses[scan.name] = matrix
    if not scans:
        raise SlscanError(f"{path}: the project lists no meshes")
    return scans, poses


def _xml_attr(text: str) -> str:
    return (
        str(text)
        .replace("&", "&amp;")
        .replace('"', "&quot;")
        .replace("<", "&lt;")
        .replace(">", "&gt;")
    )
