"""Light planes measured on a panel and the paper's global fit, on synthetic stripe samples."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.calibrate.planes import (
    LightPlaneModel,
    PanelView,
    calibrate_light_planes,
    column_crossings,
    per_pixel,
)
from slscan.calibrate.target import Board
from slscan.decode.samples import StripeSamples
from slscan.errors import SlscanError
from slscan.rig import default_rig
from slscan.virtual.boards import board_poses

RIG = default_rig(scale=0.5, projector_scale=0.5)
BOARD = Board(columns=9, rows=7, square=50.0)


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a[:, :3], b[:, :3])), 0, 1)))


def panel_samples(pose: np.ndarray, columns: np.ndarray, noise_px: float, rng) -> StripeSamples:
    """Where the true light planes of ``columns`` cross the board at ``pose``, seen by the
    camera: one sample per camera row, with ``noise_px`` of noise along the row."""
    cam, proj = RIG.camera, RIG.projector
    r, t = pose[:3, :3], pose[:3, 3]
    n_panel = r[:, 2]
    rows, xs, us = [], [], []
    w, h = BOARD.size
    for u, plane in zip(columns, proj.column_planes(columns)):
        direction = np.cross(plane[:3], n_panel)  # the plane meets the panel along this line
        a = np.stack([plane[:3], n_panel, direction])
        p0 = np.linalg.solve(a, [-plane[3], n_panel @ t, direction @ t])
        s = np.linspace(-800, 800, 4000)
        pts = p0 + s[:, None] * direction
        local = (pts - t) @ r
        inside = (local[:, 0] > 0) & (local[:, 0] < w) & (local[:, 1] > 0) & (local[:, 1] < h)
        if inside.sum() < 10:
            continue
        pix = cam.project_local(pts[inside])
        order = np.argsort(pix[:, 1])
        row_int = np.arange(np.ceil(pix[order, 1].min()), np.floor(pix[order, 1].max()) + 1)
        x = np.interp(row_int, pix[order, 1], pix[order, 0])
        rows.append(row_int)
        xs.append(x + noise_px * rng.standard_normal(len(x)))
        us.append(np.full(len(x), u))
    rows, xs, us = np.concatenate(rows), np.concatenate(xs), np.concatenate(us)
    k = len(rows)
    return StripeSamples(
        rows.astype(np.int32),
        xs,
        us,
        np.round(us).astype(np.int32),
        np.ones(k, np.float32),
        np.zeros(k, bool),
    )


@pytest.fixture(scope="module")
def panels():
    rng = np.random.default_rng(0)
    columns = np.arange(10, RIG.projector.lens.width - 10, 4) + 0.5
    return [
        PanelView(f"view_{k}", panel_samples(pose, columns, 0.05, rng), pose)
        for k, pose in enumerate(board_poses(RIG, BOARD, 4))
    ]


def test_the_model_gives_the_projectors_column_planes():
    proj = RIG.projector
    model = LightPlaneModel(proj.lens.width, proj.lens.fx, proj.lens.cx, proj.rig_from_projector)
    u = np.linspace(-5, proj.lens.width + 5, 33)
    np.testing.assert_allclose(model.planes(u), proj.column_planes(u), atol=1e-12)
    back = LightPlaneModel.from_dict(model.to_dict())
    np.testing.assert_allclose(back.planes(u), model.planes(u))
    assert model.projector(proj.lens.height).lens == proj.lens


def test_global_fit_recovers_the_projector(panels):
    res = calibrate_light_planes(panels, RIG.camera, BOARD, RIG.projector.lens.width)
    true = RIG.projector
    m = res.model
    assert abs(m.fx / true.lens.fx - 1) < 2e-3
    assert abs(m.cx - true.lens.cx) < 1.0
    assert np.degrees(np.arccos(abs(m.axis @ true.rig_from_projector[:3, 1]))) < 0.05
    # the centre is pinned at the axis point nearest the camera: here the true centre
    assert np.linalg.norm(m.center - true.center) < 1.0
    u = np.linspace(0, true.lens.width - 1, 40)
    assert angles_deg(m.planes(u), true.column_planes(u)).max() < 0.01
    raw = angles_deg(res.lines.planes, true.column_planes(res.lines.columns))
    assert np.median(raw) < 0.05 and len(res.lines) > 80
    # noise of 0.05 px: points lie within a few hundredths of a mm of their planes
    assert 0.005 < res.rms_before <= res.rms_after < 0.1
    assert res.residuals()["planes"] == len(res.lines)


def test_measured_planes_interpolate_the_raw_planes(panels):
    res = calibrate_light_planes(panels, RIG.camera, BOARD, RIG.projector.lens.width)
    raw = res.measured_planes(use_raw=True)
    cols = res.lines.columns
    got = raw.planes(cols[:5])
    np.testing.assert_allclose(
        got * np.sign(got[:, :1] * res.lines.planes[:5, :1]), res.lines.planes[:5], atol=1e-9
    )
    mid = raw.planes((cols[:-1] + cols[1:]) / 2)
    np.testing.assert_allclose(np.linalg.norm(mid[:, :3], axis=1), 1.0)
    outside = raw.planes([cols[0] - 3])
    np.testing.assert_allclose(outside, res.model.planes([cols[0] - 3]))
    assert angles_deg(res.measured_planes().planes(cols), raw.planes(cols)).max() < 0.2


def test_panel_poses_too_similar_are_degenerate(panels):
    rng = np.random.default_rng(1)
    columns = np.arange(10, RIG.projector.lens.width - 10, 4) + 0.5
    pose = panels[1].camera_from_board
    same = [
        PanelView(f"again_{k}", panel_samples(pose, columns, 0.05, rng), pose) for k in range(2)
    ]
    with pytest.raises(SlscanError, match="poses are degenerate"):
        calibrate_light_planes(same, RIG.camera, BOARD, RIG.projector.lens.width)
    with pytest.raises(SlscanError, match="at least 2 poses"):
        calibrate_light_planes(panels[:1], RIG.camera, BOARD, RIG.projector.lens.width)


# --- per-pixel codes (phase shifting) ------------------------------------------------------


def pixel_samples(pose: np.ndarray, noise_px: float, rng) -> StripeSamples:
    """Every camera pixel on the board at ``pose`` with its true (continuous) projector
    column plus ``noise_px`` of noise: what phase shifting decodes; ``stripe`` is the
    camera column, as in :func:`slscan.decode.phase.pixel_samples`."""
    cam, proj = RIG.camera, RIG.projector
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    rays = cam.rays_local(np.stack([xs, ys], -1).reshape(-1, 2).astype(float))
    r, t = pose[:3, :3], pose[:3, 3]
    pts = rays * ((r[:, 2] @ t) / (rays @ r[:, 2]))[:, None]
    local = (pts - t) @ r
    w, h = BOARD.size
    on = (local[:, 0] > 0) & (local[:, 0] < w) & (local[:, 1] > 0) & (local[:, 1] < h)
    u = proj.project(pts[on])[:, 0] + noise_px * rng.standard_normal(int(on.sum()))
    k = int(on.sum())
    return StripeSamples(
        ys.ravel()[on].astype(np.int32), xs.ravel()[on].astype(float), u,
        xs.ravel()[on].astype(np.int32), np.ones(k, np.float32), np.zeros(k, bool),
    )


def test_column_crossings_of_a_known_column_map():
    # u = 0.8137 x + 0.1071 y + 3.3: linear along each row, so the crossings are exact
    ys, xs = np.mgrid[0:40, 0:60]
    keep = (xs % 17 != 5).ravel()  # a column of pixels that did not decode: no crossing there
    u = (0.8137 * xs + 0.1071 * ys + 3.3).ravel()
    u[(ys * 60 + xs).ravel() == 40 * 60 - 1] = 1e3  # a jump: no crossing either
    n = int(keep.sum())
    samples = StripeSamples(ys.ravel()[keep].astype(np.int32), xs.ravel()[keep].astype(float), u[keep],
                            xs.ravel()[keep].astype(np.int32), np.ones(n, np.float32), np.zeros(n, bool))
    assert per_pixel(samples)
    out = column_crossings(samples)
    assert not per_pixel(out)
    np.testing.assert_allclose(out.x, (out.projector_column - 0.1071 * out.row - 3.3) / 0.8137, atol=1e-9)
    assert np.array_equal(out.projector_column, np.round(out.projector_column))
    assert np.array_equal(out.stripe, out.projector_column.astype(int))
    # every whole column between two decoded neighbours, once: 0.81 per pixel pair
    pairs = keep.reshape(40, 60)[:, :-1] & keep.reshape(40, 60)[:, 1:]
    assert abs(len(out) - 0.8137 * (pairs.sum() - 1)) < 40
    half = column_crossings(samples, step=0.5)
    assert abs(len(half) - 2 * len(out)) < 40
    with pytest.raises(SlscanError, match="step must be positive"):
        column_crossings(samples, step=0)


def test_light_planes_from_per_pixel_codes():
    """Per-pixel codes (phase shifting) with 0.02 px of noise: one plane per whole projector
    column crossed, and the projector recovered to a few parts in a million."""
    rng = np.random.default_rng(2)
    panels = [PanelView(f"view_{k}", pixel_samples(pose, 0.02, rng), pose)
              for k, pose in enumerate(board_poses(RIG, BOARD, 4))]
    res = calibrate_light_planes(panels, RIG.camera, BOARD, RIG.projector.lens.width, pattern="phase")
    true = RIG.projector
    assert res.pattern == "phase" and len(res.lines) > 300
    assert np.array_equal(res.lines.columns, np.round(res.lines.columns))
    # measured: fx 4e-6 relative, cx 0.001 px, normals 0.00013 deg (raw: median 0.0005 deg)
    assert abs(res.model.fx / true.lens.fx - 1) < 1e-4 and abs(res.model.cx - true.lens.cx) < 0.05
    u = np.linspace(0, true.lens.width - 1, 40)
    assert angles_deg(res.model.planes(u), true.column_planes(u)).max() < 0.002
    raw = angles_deg(res.lines.planes, true.column_planes(res.lines.columns))
    assert np.median(raw) < 0.005
    assert res.rms_before < 0.05
