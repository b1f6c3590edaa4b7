"""Write the textured model where other programs open it.

- ``model.glb``: glTF 2.0 binary, the atlas mesh with a PBR material whose base colour is
  the baked texture (sRGB PNG, embedded); positions in metres, Y up (glTF's conventions:
  ``gltf_from_world`` in ``texture.json`` says how the object frame, mm, maps in: a pure
  scale, the object frame being upright already, see :mod:`slscan.register.frame`). The
  node, mesh, material and image are named after the model (not trimesh's
  ``geometry_0`` / ``Image_0``), so Blender's outliner says what they are.
- ``model.obj`` + ``model.mtl`` + ``model_albedo.png``: the same in the object frame (mm);
  the MTL is matte white under the texture (``Kd 1``, ``Ks 0``), so viewers show the
  texture's own colours rather than trimesh's grey, glossy defaults (``Kd``/``Ks 0.4``).
- ``model.ply`` + ``model_albedo.png``: the model (not split at seams) in the object frame
  (mm) with texture coordinates per face corner ("wedge" ``texcoord``) and a
  ``TextureFile`` comment naming the atlas: MeshLab's own way of storing a textured mesh,
  which every MeshLab reads. ``model.mlp`` names this file, not the OBJ: MeshLab 2020.09
  (the ``meshlab`` package of Debian 12 and Ubuntu 22.04) aborts in its OBJ reader
  (vcglib ``import_obj.h``: an assertion on its count of vertices and faces) on the OBJ.
- ``model_vertex_colors.ply``: the model (not split at seams) with per-vertex sRGB colour.
- ``views/VIEW.png``: each view's un-shaded image, sRGB, resampled to a pure pinhole
  camera with the same fx, fy and the principal point at the image centre (MeshLab
  rasters and Blender cameras have no lens distortion; MeshLab mishandles off-centre
  principal points).

glTF is written with trimesh (well kept; chosen over hand-written glTF so the binary
layout, padding and PNG embedding follow its tested code). The OBJ is formatted here, line
for line as trimesh's ``export_obj`` wrote it (a test compares them), in blocks of rows
with one ``%`` each and its texture PNG encoded once: trimesh's took 5x the CPU and
encoded the PNG a second time for files we replaced.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from slscan.errors import SlscanError
from slscan.fsio import write_bytes, write_png
from slscan.texture.views import TextureView

GLTF_FROM_WORLD = np.diag([0.001, 0.001, 0.001, 1.0])
"""The upright object frame (mm, y up, +z towards the reference view; see
:mod:`slscan.register.frame`) → glTF (metres, y up): a scale."""

MTL_TEMPLATE = """# slscan textured model: matte, the texture's colours as they are
newmtl {material}
Ka 0.000000 0.000000 0.000000
Kd 1.000000 1.000000 1.000000
Ks 0.000000 0.000000 0.000000
Ns 0.000000
d 1.000000
illum 1
map_Kd {image}
"""


def _textured_trimesh(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, texture: np.ndarray,
                      normals: np.ndarray | None = None):
    import PIL.Image
    import trimesh
    from trimesh.visual.material import PBRMaterial

    material = PBRMaterial(
        name="albedo", baseColorTexture=PIL.Image.fromarray(texture), metallicFactor=0.0,
        roughnessFactor=1.0,
    )
    uv = np.asarray(uvs, np.float64).copy()
    uv[:, 1] = 1.0 - uv[:, 1]  # trimesh keeps OBJ's convention: v up from the bottom row
    return trimesh.Trimesh(
        vertices=vertices, faces=faces, vertex_normals=normals,
        visual=trimesh.visual.TextureVisuals(uv=uv, material=material), process=False,
    )


def _check_texture(texture: np.ndarray) -> None:
    if texture.dtype != np.uint8 or texture.ndim != 3 or texture.shape[2] != 3:
        raise SlscanError(f"texture must be an 8-bit RGB image, got {texture.dtype} {texture.shape}")


def write_glb(path: str | os.PathLike, atlas, texture: np.ndarray, normals: np.ndarray | None = None,
              *, gltf_from_world: np.ndarray = GLTF_FROM_WORLD, name: str | None = None) -> Path:
    """Write the atlas mesh with its 8-bit sRGB ``texture`` as glTF binary, atomically.

    normals : (m, 3) per atlas vertex (object frame), or None
    name : the node's and mesh's name (default: the file's stem); the image is
        ``NAME_albedo``, the material ``albedo``
    """
    _check_texture(texture)
    m = np.asarray(gltf_from_world, float)
    vertices = np.asarray(atlas.vertices, np.float64) @ m[:3, :3].T + m[:3, 3]
    if normals is not None:
        rot = m[:3, :3] / np.cbrt(abs(np.linalg.det(m[:3, :3])))
        normals = np.asarray(normals, np.float64) @ rot.T
    mesh = _textured_trimesh(vertices, atlas.faces, atlas.uvs, texture, normals)
    path = Path(path)
    data = name_glb(mesh.export(file_type="glb"), name or path.stem)
    write_bytes(path, data)
    return path


def name_glb(data: bytes, name: str) -> bytes:
    """A one-mesh glb (as trimesh writes it) with its node and mesh called ``name``, its
    images ``NAME_albedo``; the binary chunk is kept byte for byte."""
    import json
    import struct

    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    length, kind = struct.unpack_from("<I4s", data, 12)
    if magic != b"glTF" or kind != b"JSON":
        raise SlscanError("glTF binary: unexpected layout (no JSON chunk first)")
    doc = json.loads(data[20:20 + length])
    for key in ("nodes", "meshes"):
        for item in doc.get(key, []):
            item["name"] = name
    for k, image in enumerate(doc.get("images", [])):
        image["name"] = f"{name}_albedo" + (f"_{k}" if k else "")
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned; JSON pads with spaces
    rest = data[20 + length:]
    return struct.pack("<4sII", magic, version, 12 + 8 + len(text) + len(rest)) + \
        struct.pack("<I4s", len(text), b"JSON") + text + rest


OBJ_MATERIAL = "albedo"
OBJ_ROWS = 65536
"""Rows formatted per ``%`` call when writing an OBJ."""


def _obj_lines(prefix: str, values: np.ndarray, spec: str, per: int = 1) -> list[str]:
    """``prefix v0 v1 ...`` lines of the rows of ``values``, each ``per`` values in ``spec``:
    one ``%`` on a repeated format per block of rows (no per-row Python)."""
    values = np.asarray(values)
    line = prefix + " " + " ".join([spec] * (values.shape[1] // per)) + "\n"
    out = []
    for start in range(0, len(values), OBJ_ROWS):
        block = values[start:start + OBJ_ROWS]
        out.append((line * len(block)) % tuple(block.ravel().tolist()))
    return out


def obj_text(vertices: np.ndarray, faces: np.ndarray, uvs: np.ndarray, normals: np.ndarray | None,
             mtl_name: str, material: str = OBJ_MATERIAL) -> str:
    """The OBJ of a textured mesh, line for line as trimesh wrote it: ``v`` (8 decimals),
    ``vn`` when given, ``vt`` (v up from the bottom row, OBJ's convention), and faces
    ``f v/vt[/vn]`` sharing one index per corner."""
    uv = np.asarray(uvs, np.float64).copy()
    uv[:, 1] = 1.0 - uv[:, 1]
    parts = [f"# slscan textured model\nmtllib {mtl_name}\nusemtl {material}\n"]
    parts += _obj_lines("v", np.asarray(vertices, np.float64), "%.8f")
    if normals is not None:
        parts += _obj_lines("vn", np.asarray(normals, np.float64), "%.8f")
    parts += _obj_lines("vt", uv, "%.8f")
    index = np.asarray(faces, np.int64) + 1
    per = 3 if normals is not None else 2
    parts += _obj_lines("f", np.repeat(index, per, axis=1), "/".join(["%d"] * per), per)
    return "".join(parts)


def write_obj(path: str | os.PathLike, atlas, texture: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """Write ``NAME.obj``, ``NAME.mtl`` and ``NAME_albedo.png`` (object frame, mm), atomically
    file by file (the PNG and MTL first, so an OBJ never names missing files). The MTL is
    :data:`MTL_TEMPLATE`: matte white under the texture. The OBJ text is formatted in
    blocks of rows (:func:`obj_text`), the PNG encoded once."""
    _check_texture(texture)
    path = Path(path)
    stem = path.stem
    vertices = np.asarray(atlas.vertices, np.float64)
    faces = np.asarray(atlas.faces, np.int64)
    if normals is not None and len(normals) != len(vertices):
        raise SlscanError(f"{path}: {len(normals)} normals for {len(vertices)} atlas vertices")
    text = obj_text(vertices, faces, atlas.uvs, normals, f"{stem}.mtl")
    image_name = f"{stem}_albedo.png"
    mtl = MTL_TEMPLATE.format(material=OBJ_MATERIAL, image=image_name).encode()
    write_png(path.parent / image_name, texture)
    write_bytes(path.parent / f"{stem}.mtl", mtl)
    write_bytes(path, text.encode())
    return path


def write_wedge_uv_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, atlas,
                       texture_file: str, normals: np.ndarray | None = None) -> Path:
    """Write the model with per-corner texture coordinates as binary PLY, atomically: the
    format MeshLab writes for a textured mesh, read by MeshLab 2020.09 and current MeshLab.

    vertices : (n, 3) float64, the model's vertices (object frame, mm), written as double
    faces : (m, 3) int indices into ``vertices``, written as ``vertex_indices``
    atlas : the model's :class:`slscan.texture.atlas.Atlas` (face i is face i of ``faces``);
        each face gets ``texcoord``, 6 float32 ``u0 v0 u1 v1 u2 v2`` with v up from the
        bottom row (MeshLab's and OBJ's convention)
    texture_file : the atlas image, relative to the PLY's folder (``comment TextureFile``)
    normals : (n, 3) per vertex, written as float32 ``nx ny nz``, or None
    """
    from slscan.fsio import atomic_output_file

    path = Path(path)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    atlas_faces = np.asarray(atlas.faces, np.int64)
    same = atlas_faces.shape == faces.shape and np.array_equal(np.asarray(atlas.source_vertex)[atlas_faces], faces)
    if not same:
        raise SlscanError(f"{path}: the atlas's faces are not the model's ({len(atlas_faces)} vs {len(faces)})")
    if normals is not None and len(normals) != len(vertices):
        raise SlscanError(f"{path}: {len(normals)} normals for {len(vertices)} vertices")
    if not texture_file or any(c in texture_file for c in "\n\r"):
        raise SlscanError(f"{path}: texture file name must be one non-empty line, got {texture_file!r}")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    vertex = np.empty(len(vertices), np.dtype(fields))
    for k, axis in enumerate("xyz"):
        vertex[axis] = vertices[:, k]
        if normals is not None:
            vertex["n" + axis] = normals[:, k]
    uv = np.asarray(atlas.uvs, np.float64)[atlas_faces]  # (m, 3, 2), v down from the top row
    uv[..., 1] = 1.0 - uv[..., 1]
    face = np.empty(len(faces), np.dtype([("n", "u1"), ("i", "<i4", (3,)), ("k", "u1"), ("t", "<f4", (6,))]))
    face["n"], face["i"], face["k"], face["t"] = 3, faces, 6, uv.reshape(-1, 6)
    names = {"<f8": "double", "<f4": "float"}
    header = ["ply", "format binary_little_endian 1.0", "comment slscan textured model (object frame, mm)",
              f"comment TextureFile {texture_file}", f"element vertex {len(vertex)}",
              *(f"property {names[t]} {n}" for n, t in fields), f"element face {len(face)}",
              "property list uchar int vertex_indices", "property list uchar float texcoord", "end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")
    with atomic_output_file(path, size=len(head) + vertex.nbytes + face.nbytes) as tmp, open(tmp, "wb") as fh:
        fh.write(head)
        fh.write(vertex.tobytes())
        fh.write(face.tobytes())
    return path


def write_vertex_color_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
                           colors_srgb: np.ndarray, normals: np.ndarray | None = None) -> Path:
    """The model with per-vertex 8-bit sRGB colour, binary PLY (the fallback for programs
    without textures)."""
    from slscan.fuse import Mesh, write_mesh

    return write_mesh(Mesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                           None if normals is None else np.asarray(normals, np.float32),
                           np.asarray(colors_srgb, np.uint8)), path)


def centred_camera(view: TextureView) -> tuple[float, float, float, float]:
    """``fx, fy, cx, cy`` of the view's exported image: the same focal lengths, the
    principal point at the image centre. MeshLab mirrors an off-centre principal point
    in x when it renders a raster's depth (vcglib ``Camera::GetFrustum``), which blacks
    out or shifts projected colour; a centred one is exact everywhere."""
    cam = view.camera
    return cam.fx, cam.fy, (cam.width - 1) / 2.0, (cam.height - 1) / 2.0


def undistorted_view_image(view: TextureView) -> np.ndarray:
    """The view's un-shaded image as 8-bit sRGB, resampled (bilinear) to a distortion-free
    pinhole camera with :func:`centred_camera`'s intrinsics (black where the albedo is
    unknown or outside the original image)."""
    import cv2

    from slscan.colour import srgb8

    image = srgb8(view.albedo)
    cam = view.camera
    fx, fy, cx, cy = centred_camera(view)
    new_k = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if not np.any(cam.dist_array) and np.allclose(new_k, cam.K):
        return image
    map_x, map_y = cv2.initUndistortRectifyMap(cam.K, cam.dist_array, None, new_k, (cam.width, cam.height),
                                               cv2.CV_32FC1)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def view_entries(views: Sequence[TextureView], folder: str = "views") -> list[dict]:
    """The manifest's description of each view: the pinhole intrinsics of its exported
    (undistorted, centred) image and its pose."""
    entries = []
    for v in views:
        fx, fy, cx, cy = centred_camera(v)
        entries.append({
            "name": v.name, "image": f"{folder}/{v.name}.png", "width": v.camera.width,
            "height": v.camera.height, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "world_from_camera": np.asarray(v.world_from_camera, float).tolist(), "source": v.image_file,
        })
    return entries


def glb_summary(path: str | os.PathLike) -> dict:
    """What a .glb holds, read back with trimesh: vertices, faces, texture size (for checks)."""
    import trimesh

    data = Path(path).read_bytes()
    mesh = trimesh.load(io.BytesIO(data), file_type="glb", force="mesh", process=False)
    material = getattr(mesh.visual, "material", None)
    tex = getattr(material, "baseColorTexture", None)
    return {
        "vertices": len(mesh.vertices), "faces": len(mesh.faces),
        "texture_size": None if tex is None else list(tex.size),
        "has_uv": getattr(mesh.visual, "uv", None) is not None,
    }
