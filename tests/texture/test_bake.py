"""Baking: texel rasterisation, visibility, blending, filling — on synthetic scenes with known colour."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from slscan.colour import srgb8
from slscan.errors import SlscanError
from slscan.rig import PinholeModel, look_at, pixel_rays
from slscan.texture.bake import (
    BakeOptions,
    bake,
    blocks_in_view,
    check_texture_memory,
    pad_charts,
    point_blocks,
    rasterise_uv,
)
from slscan.texture.metrics import psnr, render_into_atlas, seam_edges, seam_error
from slscan.texture.views import TextureView

CAMERA = PinholeModel(320, 240, 300.0, 310.0, 161.3, 118.7, (-0.05, 0.01, 0.0, 0.0, 0.0))


def grid_plane(n: int, size: float, z: float, *, bump: float = 0.0):
    """A square n x n grid of vertices in the plane z (mm), two triangles per cell."""
    u, v = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    x, y = (u - 0.5) * size, (v - 0.5) * size
    zz = z + bump * np.sin(x / 7.0) * np.cos(y / 5.0)
    vertices = np.stack([x, y, zz], axis=-1).reshape(-1, 3)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).reshape(-1)
    faces = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return vertices, faces


def planar_atlas(vertices, faces, size):
    uvs = (vertices[:, :2] - vertices[:, :2].min(axis=0)) / np.ptp(vertices[:, :2], axis=0).max()
    uvs = uvs * 0.96 + 0.02
    return SimpleNamespace(vertices=vertices, faces=faces, uvs=uvs.astype(np.float32),
                           source_vertex=np.arange(len(vertices)), size=size, n_charts=1,
                           chart=np.zeros(len(faces), np.int32))


def pattern(points: np.ndarray) -> np.ndarray:
    """A smooth known colour over the plane (linear RGB)."""
    x, y = points[:, 0], points[:, 1]
    return np.stack([0.5 + 0.4 * np.sin(x / 23.0), 0.5 + 0.4 * np.cos(y / 17.0),
                     0.3 + 0.2 * np.sin((x + y) / 31.0)], axis=1).astype(np.float32)


def render_view(name, world_from_camera, vertices, faces, color_at, camera=CAMERA) -> TextureView:
    """The view's albedo image: ``color_at`` of the surface point each pixel sees (NaN: none)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32)))
    rays = pixel_rays(camera).reshape(-1, 3) @ world_from_camera[:3, :3].T
    origin = np.broadcast_to(world_from_camera[:3, 3], rays.shape)
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([origin, rays], 1).astype(np.float32)))
    t = hit["t_hit"].numpy()
    ids = hit["primitive_ids"].numpy().astype(np.int64)
    image = np.full((len(t), 3), np.nan, np.float32)
    ok = np.isfinite(t)
    points = origin[ok] + rays[ok] * t[ok, None]
    image[ok] = color_at(points, ids[ok])
    return TextureView(name, camera, world_from_camera, image.reshape(camera.height, camera.width, 3))


def test_rasterise_uv_covers_each_texel_centre_once_with_exact_barycentrics():
    size = 64
    uv_px = np.array([[3.2, 4.1], [50.7, 6.3], [10.4, 60.2], [55.5, 58.9]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    texel, face, bary = rasterise_uv(uv_px, faces, size)
    assert len(np.unique(texel)) == len(texel)
    rows, cols = np.divmod(texel, size)
    rebuilt = np.einsum("kj,kjc->kc", bary.astype(np.float64), uv_px[faces[face]])
    assert np.allclose(rebuilt, np.stack([cols, rows], 1), atol=1e-4)
    # brute force: a texel centre is covered iff it lies in one of the triangles
    yy, xx = np.mgrid[0:size, 0:size]
    centres = np.stack([xx.ravel(), yy.ravel()], 1).astype(float)

    def inside(tri):
        a, b, c = tri
        def side(p, q):
            return (q[0] - p[0]) * (centres[:, 1] - p[1]) - (q[1] - p[1]) * (centres[:, 0] - p[0])
        s1, s2, s3 = side(a, b), side(b, c), side(c, a)
        return ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))

    expected = np.nonzero(inside(uv_px[faces[0]]) | inside(uv_px[faces[1]]))[0]
    assert np.array_equal(np.sort(texel), expected)


def test_rasterise_uv_handles_large_and_degenerate_triangles():
    uv_px = np.array([[0.0, 0.0], [300.0, 0.0], [0.0, 300.0], [5.0, 5.0], [5.0, 5.0], [6.0, 6.0]])
    texel, face, _ = rasterise_uv(uv_px, np.array([[0, 1, 2], [3, 4, 5]]), 512)
    assert set(face.tolist()) == {0}
    assert len(texel) == 301 * 302 // 2  # centres (x, y) >= 0 with x + y <= 300


def test_bake_reproduces_a_known_colour_from_two_views():
    vertices, faces = grid_plane(41, 200.0, 0.0, bump=4.0)
    atlas = planar_atlas(vertices, faces, 256)
    views = [
        render_view("left", look_at([-150, -40, -600], [0, 0, 0]), vertices, faces, lambda p, i: pattern(p)),
        render_view("right", look_at([170, 60, -650], [0, 0, 0]), vertices, faces, lambda p, i: pattern(p)),
    ]
    baked = bake(vertices, faces, atlas, views)
    truth, covered = render_into_atlas(vertices, faces, atlas, pattern)
    assert np.array_equal(covered, baked.covered)
    assert baked.observed.sum() > 0.9 * covered.sum()
    assert psnr(srgb8(baked.linear), srgb8(truth), baked.observed) > 38.0
    assert baked.view_count[baked.observed].max() == 2
    # the per-vertex fallback matches too
    error = np.abs(baked.vertex_colors - pattern(vertices)).max(axis=1)
    assert error[baked.vertex_observed].max() < 0.03
    assert baked.vertex_observed.mean() > 0.85  # the rim fades out (depth discontinuity)
    assert error.max() < 0.1  # unseen rim vertices take their nearest seen neighbour's colour
    # nothing left empty: unseen texels filled, the gutter padded
    assert np.all(np.isfinite(baked.linear))


def test_occluded_texels_do_not_take_the_occluders_colour():
    back_v, back_f = grid_plane(31, 200.0, 0.0)
    front_v, front_f = grid_plane(5, 60.0, -150.0)
    vertices = np.concatenate([back_v, front_v])
    faces = np.concatenate([back_f, front_f + len(back_v)])
    n_back = len(back_f)
    red = np.array([0.9, 0.05, 0.05], np.float32)

    def color_at(points, ids):
        out = pattern(points)
        out[ids >= n_back] = red
        return out

    views = [render_view("front", look_at([0, 0, -700], [0, 0, 0]), vertices, faces, color_at),
             render_view("oblique", look_at([400, 0, -560], [0, 0, 0]), vertices, faces, color_at)]
    atlas = planar_atlas(back_v, back_f, 256)
    # the front plane is part of the model (its depth hides the back) but gets no texels
    both = SimpleNamespace(vertices=vertices, faces=faces, size=256, source_vertex=np.arange(len(vertices)),
                           uvs=np.concatenate([atlas.uvs, np.full((len(front_v), 2), 0.001, np.float32)]))
    baked = bake(vertices, faces, both, views, BakeOptions(edge_px=4.0))
    truth, covered = render_into_atlas(vertices, faces, both, lambda p: pattern(p))
    shadowed = covered & baked.observed
    red_error = np.abs(baked.linear[shadowed] - truth[shadowed]).max(axis=1)
    assert np.percentile(red_error, 99.5) < 0.05, "the occluder's red leaked onto the back plane"


def test_errors_name_the_problem():
    vertices, faces = grid_plane(5, 10.0, 0.0)
    atlas = planar_atlas(vertices, faces, 64)
    view = render_view("v", look_at([0, 0, -100], [0, 0, 0]), vertices, faces, lambda p, i: pattern(p))
    with pytest.raises(SlscanError, match="no faces"):
        bake(vertices, faces[:0], atlas, [view])
    with pytest.raises(SlscanError, match="no views"):
        bake(vertices, faces, atlas, [])
    with pytest.raises(SlscanError, match="GiB"):
        check_texture_memory(8192, available=2**30)
    with pytest.raises(SlscanError, match="16 to 16384"):
        check_texture_memory(65536)
    with pytest.raises(SlscanError, match="is 320x240 but the camera"):
        TextureView("v", PinholeModel(100, 100, 50, 50, 50, 50), np.eye(4), view.albedo)
    with pytest.raises(SlscanError, match="rigid"):
        TextureView("v", CAMERA, np.diag([1.0, 1.0, -1.0, 1.0]), view.albedo)


def test_padding_grows_charts_into_the_gutter_only():
    image = np.zeros((9, 9, 3), np.float32)
    covered = np.zeros((9, 9), bool)
    covered[4, 4] = True
    image[4, 4] = [1.0, 0.5, 0.25]
    padded, grown = pad_charts(image, covered, 2)
    assert grown.sum() == 25 and np.allclose(padded[grown], [1.0, 0.5, 0.25])
    assert np.all(padded[~grown] == 0)


def test_seam_error_is_zero_for_matching_sides_and_large_for_mismatched_ones():
    # two triangles sharing an edge (model vertices 1 and 2), each its own chart in a
    # different half of the atlas
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    atlas = SimpleNamespace(
        faces=np.array([[0, 1, 2], [3, 4, 5]]), size=64,
        uvs=np.array([[0.05, 0.05], [0.45, 0.05], [0.05, 0.45], [0.55, 0.05], [0.95, 0.05], [0.55, 0.45]]),
    )
    assert len(seam_edges(faces, atlas)) == 1
    same = np.full((64, 64, 3), 128, np.uint8)
    assert seam_error(same, faces, atlas).mean == 0.0
    split = same.copy()
    split[:, 32:] = 40
    assert seam_error(split, faces, atlas).mean > 50


def sphere(radius: float, n: int):
    """A UV sphere (mm) centred at the origin."""
    theta, phi = np.meshgrid(np.linspace(0.05, np.pi - 0.05, n), np.linspace(0, 2 * np.pi, 2 * n, endpoint=False))
    vertices = radius * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)],
                                 axis=-1).reshape(-1, 3)
    rows, cols = 2 * n, n
    r, c = np.meshgrid(np.arange(rows), np.arange(cols - 1), indexing="ij")
    a = (r * cols + c).ravel()
    b = (((r + 1) % rows) * cols + c).ravel()
    faces = np.concatenate([np.stack([a, a + 1, b], 1), np.stack([a + 1, b + 1, b], 1)])
    return vertices, faces


def test_culled_blocks_hold_every_point_a_view_can_see():
    rng = np.random.default_rng(3)
    points = rng.normal(size=(20_000, 3))
    points *= (80.0 / np.linalg.norm(points, axis=1))[:, None]
    normals = points / 80.0 + rng.normal(scale=0.3, size=points.shape)  # rough: wide cones
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    blocks = point_blocks(points.astype(np.float32), normals.astype(np.float32), size=64)
    assert np.array_equal(np.sort(blocks.members[blocks.members >= 0]), np.arange(len(points)))
    block_of = np.empty(len(points), np.int64)
    rows, cols = np.nonzero(blocks.members >= 0)
    block_of[blocks.members[rows, cols]] = rows
    cos_min = np.cos(np.radians(80.0))
    culled_some = False
    for eye in ([0, 0, -400], [300, 200, 100], [0, -250, 30], [500, 0, 0]):
        for target in ([0, 0, 0], [60, 40, 0]):
            view = TextureView("v", CAMERA, look_at(eye, target), np.zeros((240, 320, 3), np.float32))
            m = view.camera_from_world
            pc = points @ m[:3, :3].T + m[:3, 3]
            cos = -np.einsum("ij,ij->i", normals @ m[:3, :3].T, pc) / np.linalg.norm(pc, axis=1)
            pix = CAMERA.project_local(pc)
            seen = (cos > cos_min) & (pc[:, 2] > 0) & (pix[:, 0] >= 0) & (pix[:, 1] >= 0) \
                & (pix[:, 0] <= 319) & (pix[:, 1] <= 239)
            kept = np.zeros(len(blocks.members), bool)
            kept[blocks_in_view(blocks, view, 80.0)] = True
            assert kept[block_of[seen]].all(), "a block holding a visible point was culled"
            culled_some |= not kept.all()
    assert culled_some


def test_culling_leaves_the_bake_unchanged():
    vertices, faces = sphere(60.0, 40)
    atlas = SimpleNamespace(
        vertices=vertices, faces=faces, size=256, source_vertex=np.arange(len(vertices)),
        uvs=np.stack([np.arctan2(vertices[:, 1], vertices[:, 0]) / (2 * np.pi) + 0.5,
                      np.arccos(vertices[:, 2] / 60.0) / np.pi], axis=1).astype(np.float32) * 0.96 + 0.02)
    views = [render_view(f"v{k}", look_at(eye, [0, 0, 0]), vertices, faces, lambda p, i: pattern(p))
             for k, eye in enumerate(([0, 0, -400], [380, 0, -120], [-250, 300, 0], [0, -90, 420], [20, 15, -500]))]
    culled = bake(vertices, faces, atlas, views, BakeOptions(chunk=5000))
    every = bake(vertices, faces, atlas, views, BakeOptions(chunk=5000, cull=False))
    assert culled.observed.sum() > 0.5 * culled.covered.sum()
    for name in ("linear", "covered", "observed", "view_count", "vertex_colors", "vertex_observed"):
        assert np.array_equal(getattr(culled, name), getattr(every, name)), name


def test_model_share_is_the_share_of_the_views_object_the_model_covers():
    """A plane seen whole: the model lies on every object pixel; the same plane moved by half
    its width: on about half of them; moved out of view: on none (and nothing is seen)."""
    import logging

    from slscan.texture.bake import DepthMap, model_share
    from slscan.texture.pipeline import check_seen

    vertices, faces = grid_plane(21, 200.0, 0.0)
    view = render_view("front", look_at([0, 0, -400], [0, 0, 0]), vertices, faces, lambda p, i: pattern(p))
    object_pixels = np.all(np.isfinite(view.albedo), axis=2)
    assert 0.1 < object_pixels.mean() < 0.9  # the plane fills part of the frame
    for shift, expected in [(0.0, 1.0), (100.0, 0.5), (5000.0, 0.0)]:
        moved = vertices + [shift, 0, 0]
        atlas = planar_atlas(moved, faces, 64)
        baked = bake(moved, faces, atlas, [view])
        assert baked.view_model_share["front"] == pytest.approx(expected, abs=0.03), shift
        if shift == 5000.0:
            assert not baked.observed.any()
            with pytest.raises(SlscanError, match=r"m\.ply: no view of albedo sees the model"):
                check_seen(baked, "m.ply", "albedo")
        else:
            records = []
            handler = logging.Handler()
            handler.emit = records.append
            logging.getLogger("slscan.texture.pipeline").addHandler(handler)
            try:
                check_seen(baked, "m.ply", "albedo")
            finally:
                logging.getLogger("slscan.texture.pipeline").removeHandler(handler)
            warned = [r.getMessage() for r in records if "covers only" in r.getMessage()]
            assert bool(warned) == (expected < 0.75), warned
    empty = DepthMap(np.full(view.albedo.shape[:2], np.inf, np.float32), np.zeros(view.albedo.shape[:2], np.float32))
    assert model_share(empty, view) == 0.0


def _view_files(views, folder):
    """The views as the albedo stage writes them (16-bit linear PNG + validity mask), on disk."""
    from slscan.fsio import write_png
    from slscan.texture.views import ViewFile

    files = []
    for v in views:
        valid = np.all(np.isfinite(v.albedo), axis=2)
        image = np.rint(np.clip(np.nan_to_num(v.albedo), 0, 1) * 65535).astype(np.uint16)
        write_png(folder / f"{v.name}_albedo.png", image)
        write_png(folder / f"{v.name}_valid.png", (valid * 255).astype(np.uint8))
        files.append(ViewFile(v.name, v.camera, v.world_from_camera, str(folder / f"{v.name}_albedo.png"),
                              str(folder / f"{v.name}_valid.png")))
    return files


def _four_views(vertices, faces):
    eyes = ([-150, -40, -600], [170, 60, -650], [0, 200, -500], [-90, -160, -550])
    return [render_view(f"v{k}", look_at(eye, [0, 0, 0]), vertices, faces, lambda p, i: pattern(p))
            for k, eye in enumerate(eyes)]


def test_views_baked_in_groups_on_two_workers_give_the_atlas_of_one_process(tmp_path):
    """Groups of views in 2 local processes (reading the views' PNGs there, the texels'
    points from shared files): the same atlas, counts and vertex colours, bit for bit, as
    the same groups in this process; the files are gone afterwards."""
    from slscan.executor import Executor

    vertices, faces = grid_plane(41, 200.0, 0.0, bump=4.0)
    atlas = planar_atlas(vertices, faces, 256)
    files = _view_files(_four_views(vertices, faces), tmp_path)
    options = BakeOptions(views_per_task=1, chunk=5000)
    one = bake(vertices, faces, atlas, files, options, executor=Executor(workers=1))
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    two = bake(vertices, faces, atlas, files, options, executor=Executor(workers=2), scratch=scratch)
    assert one.observed.sum() > 0.9 * one.covered.sum() and one.view_count.max() == 4
    for name in ("linear", "covered", "observed", "view_count", "vertex_colors", "vertex_observed"):
        assert np.array_equal(getattr(one, name), getattr(two, name)), name
    assert one.view_model_share == two.view_model_share
    assert list(scratch.iterdir()) == []
    # other groupings round the float32 sums differently, nothing more
    whole = bake(vertices, faces, atlas, files, BakeOptions(views_per_task=4, chunk=5000))
    assert np.array_equal(whole.view_count, one.view_count)
    assert np.abs(whole.linear - one.linear).max() < 1e-5


def test_streaming_the_views_leaves_the_bake_as_blending_them_all_at_once():
    """One group of every view: texel colours exactly those of :func:`blend_views` over
    every view's depth map held at once (the bake before views were streamed), with the
    per-vertex prior and fill applied as documented."""
    from slscan.meshes import vertex_normals
    from slscan.texture.bake import _fill_vertices, _raycasting_scene, blend_views, depth_map

    vertices, faces = grid_plane(41, 200.0, 0.0, bump=4.0)
    atlas = planar_atlas(vertices, faces, 256)
    views = _four_views(vertices, faces)
    options = BakeOptions(chunk=5000)
    baked = bake(vertices, faces, atlas, views, options)

    normals = vertex_normals(vertices, faces).astype(np.float32)
    scene = _raycasting_scene(vertices, faces)
    depths = [depth_map(scene, v, options) for v in views]
    vblend = blend_views(vertices.astype(np.float32), normals, views, depths, options)
    vertex_colors, _ = _fill_vertices(vertices, vblend.color)
    texel, face, bary = rasterise_uv(np.asarray(atlas.uvs, np.float64) * 256 - 0.5, faces, 256)
    corner = faces[face]
    points = np.einsum("kj,kjc->kc", bary, vertices[corner].astype(np.float32))
    tn = np.einsum("kj,kjc->kc", bary, normals[corner])
    tn /= np.maximum(np.linalg.norm(tn, axis=1, keepdims=True), 1e-12)
    tblend = blend_views(points, tn, views, depths, options)
    fill = np.einsum("kj,kjc->kc", bary, vertex_colors[corner])
    seen = np.all(np.isfinite(tblend.color), axis=1)
    w = tblend.weight[seen, None]
    expected = ((tblend.color[seen] * w + fill[seen] * options.prior_weight) / (w + options.prior_weight))
    assert np.array_equal(baked.vertex_colors, vertex_colors)
    assert np.array_equal(baked.linear.reshape(-1, 3)[texel[seen]], expected.astype(np.float32))
    assert np.array_equal(baked.view_count.ravel()[texel], tblend.views)


def test_a_view_image_missing_where_a_worker_reads_it_is_named(tmp_path):
    from slscan.executor import Executor

    vertices, faces = grid_plane(21, 200.0, 0.0)
    atlas = planar_atlas(vertices, faces, 64)
    files = _view_files(_four_views(vertices, faces)[:2], tmp_path)
    (tmp_path / "v1_albedo.png").unlink()
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    with pytest.raises(SlscanError, match=r"v1_albedo\.png: un-shaded image of view v1 not found"):
        bake(vertices, faces, atlas, files, BakeOptions(views_per_task=1), executor=Executor(workers=2),
             scratch=scratch)
    assert list(scratch.iterdir()) == []
