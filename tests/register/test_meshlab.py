"""MeshLab projects of aligned scans, and the range-scan PLY files they point at."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pymeshlab
import pytest

from slscan.errors import SlscanError
from slscan.register.meshlab import load_scan_project, read_mlp, write_mlp, write_scan_project
from slscan.register.pairwise import rigid_transform
from slscan.register.rangescan import load_range_scan, render_range_scan, write_range_scan


@pytest.fixture(scope="module")
def scans():
    box = o3d.geometry.TriangleMesh.create_sphere(radius=30.0, resolution=30)
    v, f = np.asarray(box.vertices), np.asarray(box.triangles)
    out, poses = [], {}
    for k, angle in enumerate((0.0, 0.7, 1.9)):
        pose = rigid_transform([0.2, angle, 0.1], [10.0 * k, -5.0, 3.0])
        out.append(render_range_scan(v, f, pose, shape=(40, 40), pixel=1.6, name=f"scan{k}"))
        poses[f"scan{k}"] = pose
    return out, poses


def test_project_round_trip(tmp_path, scans):
    scans, poses = scans
    project = write_scan_project(tmp_path / "aligned", scans, poses)
    assert project == tmp_path / "aligned" / "aligned.mlp"
    entries = read_mlp(project)
    assert [p.name for p, _ in entries] == ["scan0.ply", "scan1.ply", "scan2.ply"]
    for (path, matrix), scan in zip(entries, scans):
        assert path.is_file()
        np.testing.assert_allclose(matrix, poses[scan.name], rtol=0, atol=1e-15)
    loaded, loaded_poses = load_scan_project(project)
    for a, b in zip(loaded, scans):
        assert a.name == b.name
        np.testing.assert_allclose(a.vertices, b.vertices, atol=1e-5 * np.abs(b.vertices).max())
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_allclose(a.quality, b.quality, atol=1e-7)
        np.testing.assert_allclose(a.view_direction, b.view_direction, atol=1e-8)
        np.testing.assert_array_equal(a.grid, b.grid)
    assert set(loaded_poses) == set(poses)


def test_pymeshlab_opens_the_project(tmp_path, scans):
    scans, poses = scans
    project = write_scan_project(tmp_path / "aligned", scans, poses)
    ms = pymeshlab.MeshSet()
    ms.load_project(str(project))
    assert ms.mesh_number() == len(scans)
    for k, scan in enumerate(scans):
        mesh = ms.mesh(k)
        np.testing.assert_allclose(mesh.transform_matrix(), poses[scan.name], atol=1e-6)
        np.testing.assert_allclose(mesh.vertex_matrix(), scan.vertices, atol=1e-4)
        assert mesh.face_number() == scan.n_faces
        np.testing.assert_allclose(mesh.vertex_scalar_array(), scan.quality, atol=1e-6)


def test_pymeshlab_projects_read_back(tmp_path, scans):
    scans, poses = scans
    ms = pymeshlab.MeshSet()
    for scan in scans:
        write_range_scan(scan, tmp_path / f"{scan.name}.ply")
        ms.load_new_mesh(str(tmp_path / f"{scan.name}.ply"))
        ms.set_matrix(transformmatrix=poses[scan.name], freeze=False)
    ms.save_project(str(tmp_path / "saved.mlp"))
    entries = read_mlp(tmp_path / "saved.mlp")
    assert [p.name for p, _ in entries] == [f"{s.name}.ply" for s in scans]
    for (_, matrix), scan in zip(entries, scans):
        np.testing.assert_allclose(matrix, poses[scan.name], atol=1e-6)


def test_missing_meshes_are_named(tmp_path):
    write_mlp(
        tmp_path / "p.mlp", [(tmp_path / "gone.ply", np.eye(4)), (tmp_path / "lost.ply", np.eye(4))]
    )
    with pytest.raises(SlscanError, match=r"p\.mlp.*gone\.ply.*lost\.ply"):
        read_mlp(tmp_path / "p.mlp")
    assert len(read_mlp(tmp_path / "p.mlp", check_files=False)) == 2


def test_texture_project_names_its_mesh_beside_it_from_a_relative_out(tmp_path, monkeypatch):
    """``slscan texture --out RELATIVE`` wrote the mesh through the doubled temporary folder
    (``out/.textured.partial-X/out/...``), which MeshLab cannot open; the project must name
    ``model.obj`` beside itself whatever the current folder."""
    import xml.etree.ElementTree as ET

    monkeypatch.chdir(tmp_path)
    folder = Path("out") / ".partial"
    folder.mkdir(parents=True)
    (folder / "model.obj").write_text("v 0 0 0\n")
    write_mlp(folder / "model.mlp", [(Path("model.obj"), np.eye(4)), ((folder / "model.obj").resolve(), np.eye(4))])
    names = [m.get("filename") for m in ET.parse(folder / "model.mlp").getroot().iter("MLMesh")]
    assert names == ["model.obj", "model.obj"]
    for name in names:  # as MeshLab resolves them: against the project's folder
        assert (folder / name).is_file()


def test_bad_projects_are_reported(tmp_path):
    with pytest.raises(SlscanError, match="not found"):
        read_mlp(tmp_path / "none.mlp")
    (tmp_path / "x.mlp").write_text("<NotMeshLab/>")
    with pytest.raises(SlscanError, match="MeshLabProject"):
        read_mlp(tmp_path / "x.mlp")
    (tmp_path / "y.mlp").write_text(
        '<MeshLabProject><MeshGroup><MLMesh filename="a.ply"><MLMatrix44>1 2 3</MLMatrix44>'
        "</MLMesh></MeshGroup></MeshLabProject>"
    )
    with pytest.raises(SlscanError, match="3 numbers; expected 16"):
        read_mlp(tmp_path / "y.mlp", check_files=False)


# --- generic PLY loading -------------------------------------------------------------------


def test_ascii_ply_with_quads_and_quality(tmp_path):
    path = tmp_path / "quad.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
        "property float z\nproperty float quality\nelement face 2\n"
        "property list uchar int vertex_indices\nend_header\n"
        "0 0 0 0.5\n1 0 0 1\n1 1 0 1\n0 1 0 0.25\n2 0 0 1\n4 0 1 2 3\n3 1 4 2\n"
    )
    scan = load_range_scan(path)
    assert scan.name == "quad" and scan.n_faces == 3 and scan.n_vertices == 5
    np.testing.assert_allclose(scan.view_direction, [0, 0, 1])
    np.testing.assert_allclose(scan.quality, [0.5, 1, 1, 0.25, 1])


def test_binary_big_endian_ply(tmp_path):
    path = tmp_path / "be.ply"
    header = (
        b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\n"
        b"property double y\nproperty double z\nelement face 1\n"
        b"property list uchar uint vertex_indices\nend_header\n"
    )
    vertices = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0]], ">f8").tobytes()
    face = np.array([3], ">u1").tobytes() + np.array([0, 1, 2], ">u4").tobytes()
    path.write_bytes(header + vertices + face)
    scan = load_range_scan(path, view_direction=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(scan.vertices[1], [0, 0, 1])
    n = np.cross(
        scan.vertices[scan.faces[0, 1]] - scan.vertices[scan.faces[0, 0]],
        scan.vertices[scan.faces[0, 2]] - scan.vertices[scan.faces[0, 0]],
    )
    assert n[0] > 0  # re-wound to face the given view direction


XYZ = "property float x\nproperty float y\nproperty float z\n"
FACES = "element face 1\nproperty list uchar int vertex_indices\n"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (f"ply\nformat ascii 1.0\nelement vertex 0\n{XYZ}end_header\n", "no vertices"),
        (
            f"ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}end_header\n0 0 0\n1 0 0\n0 1 0\n",
            "no faces",
        ),
        (
            f"ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}{FACES}end_header\n0 0 0\n1 0 0\n2 0 0\n3 0 1 2\n",
            "degenerate",
        ),
        (f"ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}end_header\n0 0 0\n1 0\n", "truncated"),
        ("not a ply at all", "not a PLY"),
    ],
)
def test_empty_or_degenerate_ply_is_an_error_naming_the_file(tmp_path, body, message):
    path = tmp_path / "bad.ply"
    path.write_text(body)
    with pytest.raises(SlscanError, match=f"bad.ply.*{message}"):
        load_range_scan(path)
