"""Faces that refer to a vertex the file does not have (past the end, 2**32 - 7, -1) are
refused in one line naming the file, the face and the vertex count, before any native
code (Open3D, pymeshlab, fast-simplification, xatlas) sees them (#34).

The commands run in a subprocess, so that a native crash (SIGSEGV) is a failure too."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slscan.errors import SlscanError

TOOLBOX = Path(__file__).resolve().parents[2] / "toolbox"

BAD = {"past_end": 42, "two_pow_32_minus_7": 2**32 - 7, "minus_one": -1}
"""The bad index put into face 5 of a 42-vertex mesh, and what it reads as."""


def grid_mesh(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A gently curved n x (n + 1) grid, 60 mm across: (42, 3) float vertices, (60, 3) faces."""
    u, v = np.meshgrid(np.linspace(-30, 30, n + 1), np.linspace(-30, 30, n), indexing="xy")
    vertices = np.stack([u, v, 0.01 * (u**2 + v**2)], -1).reshape(-1, 3)
    faces = []
    for r in range(n - 1):
        for c in range(n):
            a, b = r * (n + 1) + c, (r + 1) * (n + 1) + c
            faces += [(a, b, a + 1), (a + 1, b, b + 1)]
    return vertices, np.array(faces, np.int64)


def write_bad_ply(path: Path, bad: int, *, binary: bool = True) -> Path:
    """The grid mesh with ``bad`` as the second index of face 5. Binary files store the
    indices as ``uint`` when ``bad`` needs it (2**32 - 7), else ``int``."""
    vertices, faces = grid_mesh()
    faces[5, 1] = bad
    kind = "uint" if bad >= 2**31 else "int"
    head = (
        f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar {kind} vertex_indices\nend_header\n"
    ).encode()
    if binary:
        tri = np.empty(len(faces), np.dtype([("n", "u1"), ("i", "<u4" if kind == "uint" else "<i4", (3,))]))
        tri["n"], tri["i"] = 3, faces
        body = np.asarray(vertices, "<f4").tobytes() + tri.tobytes()
    else:
        body = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in vertices).encode()
        body += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces).encode()
    path.write_bytes(head + body)
    return path


def slscan(*argv: object) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TOOLBOX), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run(
        [sys.executable, "-c", "import sys; from slscan.cli import main; sys.exit(main(sys.argv[1:]))",
         *map(str, argv)],
        capture_output=True, text=True, env=env, timeout=120,
    )


def command_line(command: str, mesh: Path, out: Path) -> list:
    folder = mesh.parent
    if command == "simplify":
        return ["simplify", mesh, "--out", out / "model.ply", "--faces", "10", "--quiet"]
    if command == "texture":
        return ["texture", mesh, "--views", folder / "albedo", "--out", out, "--quiet"]
    if command == "register":
        return ["register", folder, "--out", out, "--quiet"]
    project = folder / "aligned.mlp"
    project.write_text(
        '<!DOCTYPE MeshLabDocument>\n<MeshLabProject><MeshGroup><MLMesh label="scan" filename="scan.ply">'
        "<MLMatrix44>1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1</MLMatrix44></MLMesh></MeshGroup></MeshLabProject>\n"
    )
    return ["fuse", project, "--out", out / "fused.ply", "--voxel", "4", "--quiet"]


@pytest.mark.parametrize("bad", BAD.values(), ids=BAD.keys())
@pytest.mark.parametrize("command", ["simplify", "fuse", "texture", "register"])
def test_commands_refuse_faces_past_the_vertices(tmp_path, command, bad):
    scans = tmp_path / "scans"
    scans.mkdir()
    mesh = write_bad_ply(scans / "scan.ply", bad)
    out = tmp_path / "out"
    done = slscan(*command_line(command, mesh, out))
    assert done.returncode == 2, f"exit {done.returncode} (a negative code is a signal): {done.stderr[-2000:]}"
    lines = [line for line in done.stderr.splitlines() if "slscan: error:" in line]
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr[-2000:]
    line = lines[0]
    assert "scan.ply" in line and "face 5 " in line and "42 vertices" in line, line
    assert not out.exists() or not any(out.iterdir()), "something was written"


def _readers():
    from slscan.decode.rangemap import read_ply
    from slscan.fuse import read_mesh
    from slscan.recipe.surfaces import read_surface
    from slscan.register.rangescan import load_range_scan
    from slscan.virtual.scenes import load_mesh_scene

    return {"read_mesh (Open3D)": read_mesh, "load_range_scan": load_range_scan,
            "rangemap.read_ply": read_ply, "read_surface": read_surface,
            "load_mesh_scene (Open3D)": load_mesh_scene}


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
@pytest.mark.parametrize("bad", BAD.values(), ids=BAD.keys())
@pytest.mark.parametrize("reader", list(_readers()))
def test_every_mesh_reader_checks_face_indices(tmp_path, reader, bad, binary):
    path = write_bad_ply(tmp_path / "scan.ply", bad, binary=binary)
    with pytest.raises(SlscanError, match=r"scan\.ply: face 5 refers to vertex -?\d+ but the file has 42 vertices"):
        _readers()[reader](path)


@pytest.mark.parametrize("reader", list(_readers()))
def test_every_mesh_reader_reads_the_good_mesh(tmp_path, reader):
    """The check refuses only bad faces: the same file with face 5 intact reads whole."""
    vertices, faces = grid_mesh()
    path = write_bad_ply(tmp_path / "scan.ply", int(faces[5, 1]))
    read = _readers()[reader](path)
    n_faces = len(getattr(read, "faces", getattr(read, "triangles", [])))
    assert n_faces == len(faces)


@pytest.mark.parametrize("bad", ["9", "-9", "4294967290"])
def test_obj_atlas_reader_refuses_bad_face_indices(tmp_path, bad):
    """trimesh raises IndexError on an OBJ face past its vertices: one SlscanError instead."""
    from slscan.meshes import read_obj_atlas

    path = tmp_path / "model.obj"
    path.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nf 1/1 2/1 3/1\nf 2/1 {bad}/1 3/1\n")
    with pytest.raises(SlscanError, match=r"model\.obj"):
        read_obj_atlas(path)


@pytest.mark.parametrize("bad", ["9", "-9", "4294967290"])
def test_open3d_obj_path_refuses_bad_face_indices(tmp_path, bad):
    """Meshes that are not PLY go through Open3D: its OBJ reader drops the whole mesh on a bad
    index, which is refused naming the file (and the face check runs on what it keeps)."""
    from slscan.fuse import read_mesh

    path = tmp_path / "model.obj"
    path.write_text(f"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 {bad} 3\n")
    with pytest.raises(SlscanError, match=r"model\.obj"):
        read_mesh(path)
