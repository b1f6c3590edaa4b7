"""A full disk and a bug, end to end: one error line, exit status, nothing half-written left.

Each case runs twice where it can: on a real, tiny tmpfs (as root, when ``mount`` works;
skipped otherwise) and with the disk's ``ENOSPC`` injected into the write path (always):
Python's writes fail part-way, Open3D's writer leaves a short file and reports success
(as it does on a full disk).
"""

from __future__ import annotations

import builtins
import errno
import io
import os
import shutil
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest
from synthetic_poses import looking_from

from slscan import cli, fsio
from slscan.cli import main
from slscan.errors import SlscanError

SMALL_RECIPE = """\
[recipe]
name = "small"
description = "One 288x192 view of the tile, Gray code: capture and decode (about 1 MB)."
stages = ["capture", "decode"]

[capture]
scene = "tile"
views = 1
patterns = "gray"
lit_images = false
camera_scale = 0.2
projector_scale = 0.2

[decode]
method = "gray"
"""


# --- a full disk, two ways --------------------------------------------------------------------


class InjectedDisk:
    """``free`` bytes left: Python's writes past them fail with ENOSPC after writing what
    fits; Open3D's mesh writer keeps what fits and reports success."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, free: int) -> None:
        self.free = free
        real_open = builtins.open
        real_write_mesh = o3d.io.write_triangle_mesh

        disk = self

        class Full:
            def __init__(self, fh) -> None:
                self.fh = fh

            def write(self, data) -> int:
                data = data if isinstance(data, str) else bytes(data)  # text: one byte a character
                fits = max(min(len(data), disk.free), 0)
                self.fh.write(data[:fits])
                disk.free -= fits
                if fits < len(data):
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                return len(data)

            def __getattr__(self, name):
                return getattr(self.fh, name)

            def __enter__(self):
                return self

            def __exit__(self, *exc) -> None:
                self.fh.close()

            def close(self) -> None:
                self.fh.close()

        def full_open(file, mode="r", *args, **kwargs):
            fh = real_open(file, mode, *args, **kwargs)
            return Full(fh) if any(c in mode for c in "wax+") else fh

        def full_write_mesh(filename, mesh, *args, **kwargs):
            ok = real_write_mesh(filename, mesh, *args, **kwargs)
            size = os.path.getsize(filename)
            keep = max(min(size, disk.free), 0)
            os.truncate(filename, keep)
            disk.free -= keep
            return ok

        monkeypatch.setattr(builtins, "open", full_open)
        monkeypatch.setattr(io, "open", full_open)
        monkeypatch.setattr(o3d.io, "write_triangle_mesh", full_write_mesh)


@pytest.fixture
def tiny_fs(tmp_path):
    """Mount a tmpfs of the given size (bytes) under ``tmp_path``; unmounted afterwards."""
    mounts = []

    def mount(size: int) -> Path:
        if os.geteuid() != 0 or shutil.which("mount") is None:
            pytest.skip("a real full disk needs root and mount")
        where = tmp_path / f"tiny{len(mounts)}"
        where.mkdir()
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                              capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip()}")
        mounts.append(where)
        return where

    yield mount
    for where in mounts:
        subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.fixture(params=["tmpfs", "injected"])
def full_disk(request, tmp_path, monkeypatch):
    """``full_disk(free)`` → a folder on a disk with about ``free`` bytes left."""

    def make(free: int) -> Path:
        if request.param == "tmpfs":
            where = request.getfixturevalue("tiny_fs")(max(free, 4096))
            return where
        where = tmp_path / "disk"
        where.mkdir(exist_ok=True)
        InjectedDisk(monkeypatch, free)
        return where

    return make


# --- inputs -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere_ply(tmp_path_factory) -> Path:
    """A 10 mm sphere, 7,082 vertices, 14,160 faces (524 KB as binary PLY)."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=60)
    mesh.compute_vertex_normals()
    path = tmp_path_factory.mktemp("inputs") / "sphere.ply"
    o3d.io.write_triangle_mesh(str(path), mesh)
    return path


@pytest.fixture(scope="module")
def aligned(tmp_path_factory) -> Path:
    """Four range scans of a 20 mm sphere with their poses, as `slscan register` writes them."""
    from slscan.register.meshlab import write_scan_project
    from slscan.register.rangescan import render_range_scan

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=20.0, resolution=60)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    scans, poses = [], {}
    for k, d in enumerate([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, 0, 1]]):
        pose = looking_from(d)
        scans.append(render_range_scan(v, f, pose, shape=(40, 40), pixel=1.2, name=f"view{k}"))
        poses[f"view{k}"] = pose
    folder = tmp_path_factory.mktemp("inputs") / "aligned"
    write_scan_project(folder, scans, poses)
    return folder


@pytest.fixture(scope="module")
def captured(tmp_path_factory) -> Path:
    """A run folder of :data:`SMALL_RECIPE` whose capture stage has run (decode not yet)."""
    root = tmp_path_factory.mktemp("recipe")
    recipe = root / "small.toml"
    recipe.write_text(SMALL_RECIPE)
    assert main(["run", str(recipe), "--out", str(root / "run"), "--workers", "1", "--quiet"]) == 0
    shutil.rmtree(root / "run" / "decode")
    (root / "run" / "decode.stage.json").unlink()
    return root


# --- checks -------------------------------------------------------------------------------------


def only_error_line(capsys, names: str) -> str:
    """The one `slscan: error:` line, naming ``names``, with no traceback."""
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "slscan: error:" in line]
    assert len(lines) == 1, err
    assert names in lines[0], err
    assert "Traceback" not in err
    return lines[0]


def copy_through_write(source: str, dest: str) -> None:
    """Copy a file with ``write`` (which the injected disk counts), keeping its times."""
    with open(source, "rb") as src, open(dest, "wb") as dst:
        dst.write(src.read())
    shutil.copystat(source, dest)


def leftovers(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if fsio.PARTIAL in p.name or ".old-" in p.name]


# --- the commands ------------------------------------------------------------------------------


def test_simplify_on_a_full_disk_leaves_nothing(full_disk, sphere_ply, capsys):
    disk = full_disk(150_000)
    out = disk / "model.ply"  # 6,000 faces: about 217 KB
    rc = main(["simplify", str(sphere_ply), "--faces", "6000", "--out", str(out), "--quiet"])
    assert rc == 2
    line = only_error_line(capsys, str(out))
    assert "free on" in line and "needed" in line
    assert not out.exists() and leftovers(disk) == []


def test_simplify_over_an_existing_model_keeps_it(full_disk, sphere_ply, capsys):
    disk = full_disk(150_000)
    out = disk / "model.ply"
    assert main(["simplify", str(sphere_ply), "--faces", "500", "--out", str(out), "--quiet"]) == 0
    before = out.read_bytes()
    rc = main(["simplify", str(sphere_ply), "--faces", "6000", "--out", str(out), "--overwrite", "--quiet"])
    assert rc == 2
    only_error_line(capsys, str(out))
    assert out.read_bytes() == before and leftovers(disk) == []


def test_fuse_on_a_full_disk_leaves_nothing(full_disk, aligned, capsys):
    disk = full_disk(20_000)
    out = disk / "fused.ply"
    rc = main(["fuse", str(aligned), "--voxel", "1.0", "--out", str(out), "--quiet"])
    assert rc == 2
    only_error_line(capsys, str(out))
    assert not out.exists() and leftovers(disk) == []


def test_fuse_in_bricks_on_a_full_disk_leaves_nothing(full_disk, aligned, capsys, tmp_path):
    """Streamed fusion: the bricks' pieces fit, the PLY written beside them does not."""
    probe = tmp_path / "probe.ply"
    assert main(["fuse", str(aligned), "--voxel", "1.0", "--brick", "16", "--out", str(probe), "--quiet"]) == 0
    disk = full_disk(probe.stat().st_size)
    out = disk / "fused.ply"
    rc = main(["fuse", str(aligned), "--voxel", "1.0", "--brick", "16", "--out", str(out), "--quiet"])
    assert rc == 2
    only_error_line(capsys, str(out))
    assert not out.exists() and list(disk.iterdir()) == []


def test_a_recipe_stage_on_a_full_disk_leaves_the_stages_before_it(full_disk, captured, capsys):
    capture_size = sum(p.stat().st_size for p in (captured / "run").rglob("*") if p.is_file())
    disk = full_disk(capture_size + 200_000)  # the capture fits, the range map (~500 KB) does not
    run = disk / "run"
    shutil.copytree(captured / "run", run, copy_function=copy_through_write)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    rc = main(["run", str(captured / "small.toml"), "--out", str(run), "--workers", "1", "--quiet"])
    assert rc == 2
    only_error_line(capsys, str(run / "decode"))
    assert not (run / "decode").exists() and not (run / "decode.stage.json").exists()
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    assert leftovers(disk) == []


# --- the library writers -----------------------------------------------------------------------


def test_json_and_png_writers_on_a_full_disk(full_disk):
    disk = full_disk(8_000)
    (disk / "old.json").write_bytes(b"{}\n")  # a previous result, 3 bytes
    image = np.random.default_rng(0).integers(0, 255, (100, 100, 3), np.uint8)  # ~30 KB as PNG
    with pytest.raises(SlscanError) as exc:
        fsio.write_png(disk / "image.png", image)
    assert str(disk / "image.png") in str(exc.value) and "free on" in str(exc.value)
    with pytest.raises(SlscanError) as exc:
        fsio.write_json(disk / "old.json", {"values": list(range(5_000))})
    assert str(disk / "old.json") in str(exc.value)
    assert not (disk / "image.png").exists() and (disk / "old.json").read_bytes() == b"{}\n"
    assert leftovers(disk) == []


def test_layouts_on_a_full_disk_end_in_one_line(full_disk, capsys):
    """Rerun's Blueprint.save hangs when its own write fails; slscan saves elsewhere first."""
    disk = full_disk(20_000)
    assert main(["layouts", "--out", str(disk)]) == 2
    only_error_line(capsys, str(disk / "capture.rbl"))
    assert not any(disk.glob("*.rbl")) and leftovers(disk) == []


def test_texture_export_on_a_full_disk(full_disk):
    from slscan.texture.export import write_glb, write_obj, write_vertex_color_ply, write_wedge_uv_ply

    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=30)
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    atlas = SimpleNamespace(vertices=vertices, faces=faces, source_vertex=np.arange(len(vertices)),
                            uvs=np.random.default_rng(1).random((len(vertices), 2)))
    texture = np.random.default_rng(2).integers(0, 255, (128, 128, 3), np.uint8)  # ~50 KB as PNG
    disk = full_disk(20_000)
    for write, name in [(lambda p: write_glb(p, atlas, texture), "model.glb"),
                        (lambda p: write_obj(p, atlas, texture), "model_albedo.png"),
                        (lambda p: write_vertex_color_ply(p, vertices, faces,
                                                          np.full((len(vertices), 3), 200, np.uint8)),
                         "model_vertex_colors.ply"),
                        (lambda p: write_wedge_uv_ply(p, vertices, faces, atlas, "model_albedo.png"), "model.ply")]:
        target = disk / (name if name.endswith((".glb", ".ply")) else "model.obj")
        with pytest.raises(SlscanError) as exc:
            write(target)
        assert str(disk / name) in str(exc.value) and "free on" in str(exc.value)
        assert not target.exists()
    assert list(disk.iterdir()) == []  # no model file, no temporary


def test_a_short_write_reported_as_success_is_caught(tmp_path, monkeypatch):
    """Open3D's writer returns True over a cut-off file: the header check catches it."""
    from slscan.fuse import Mesh, write_mesh

    real = o3d.io.write_triangle_mesh

    def cut(filename, mesh, *args, **kwargs):
        ok = real(filename, mesh, *args, **kwargs)
        os.truncate(filename, os.path.getsize(filename) - 1)
        return ok

    monkeypatch.setattr(o3d.io, "write_triangle_mesh", cut)
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=10.0, resolution=10)
    mesh = Mesh(np.asarray(sphere.vertices), np.asarray(sphere.triangles))
    with pytest.raises(SlscanError, match="came out short"):
        write_mesh(mesh, tmp_path / "m.ply")
    assert list(tmp_path.iterdir()) == []


# --- bugs and other bad inputs ------------------------------------------------------------------


def test_a_bug_is_one_line_without_verbose_and_a_traceback_with_it(tmp_path, monkeypatch, capsys):
    def broken(args):
        raise RuntimeError("boom\nsecond line")

    monkeypatch.setattr(cli, "_cmd_info", broken)
    assert main(["info", str(tmp_path)]) == cli.EXIT_BUG
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("slscan: error:"), err
    assert "bug" in lines[0] and "RuntimeError: boom" in lines[0] and "-v" in lines[0]
    assert main(["-v", "info", str(tmp_path)]) == cli.EXIT_BUG
    err = capsys.readouterr().err
    assert "Traceback" in err and "boom" in err
    assert sum("slscan: error:" in line for line in err.splitlines()) == 1


@pytest.mark.parametrize("exc,expected", [
    (PermissionError(errno.EACCES, "Permission denied", "/x/scan.ply"), "/x/scan.ply: permission denied"),
    (OSError(errno.ENOSPC, "No space left on device", "/x/out.rrd"), "/x/out.rrd: could not write it"),
    (MemoryError(), "out of memory"),
])
def test_known_errors_escaping_a_command_are_one_line(exc, expected, monkeypatch, capsys, tmp_path):
    def failing(args):
        raise exc

    monkeypatch.setattr(cli, "_cmd_info", failing)
    assert main(["info", str(tmp_path)]) == 2
    only_error_line(capsys, expected)


def test_the_command_line_itself_prints_no_traceback(tmp_path):
    """Through the real entry point: an unreadable (binary) recipe file."""
    recipe = tmp_path / "bad.toml"
    recipe.write_bytes(b"\xff\xfe\x00garbage")
    proc = subprocess.run([sys.executable, "-m", "slscan.cli", "run", str(recipe), "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.count("slscan: error:") == 1


def test_a_device_error_at_the_flush_keeps_the_previous_file(tmp_path, monkeypatch):
    """EIO from ``fsync`` (the data never reached the disk): nothing renamed, the temporary gone."""
    target = tmp_path / "calibration.json"
    fsio.write_json(target, {"version": 1})
    before = target.read_bytes()

    def failing_fsync(fd):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, "fsync", failing_fsync)
    with pytest.raises(SlscanError, match=r"calibration\.json: could not write it: input/output error"):
        fsio.write_json(target, {"version": 2})
    assert target.read_bytes() == before and leftovers(tmp_path) == []
