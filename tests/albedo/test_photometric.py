"""The per-pixel solver's blocks against their dense definitions, on random pixels."""

from __future__ import annotations

import numpy as np
import pytest

from slscan.albedo import photometric as ph

K, N = 6, 200


@pytest.fixture(scope="module")
def pixels():
    rng = np.random.default_rng(7)
    points = rng.normal(size=(N, 3)) * 30 + [0.0, 0.0, 600.0]
    positions = rng.normal(size=(K, 3)) * 80
    geo = ph._geometry(points, positions, 600.0)
    n = np.array([0.0, 0.0, -3.0])[:, None] + rng.normal(size=(3, N))
    n /= np.linalg.norm(n, axis=0)
    a = rng.uniform(0.1, 0.9, (3, N))
    intens = rng.uniform(0.7, 1.3, (K, 3, 1))
    ambient = np.full((1, 3, 1), 0.02)
    values = rng.uniform(0.0, 1.0, (K, 3, N))
    weight = (rng.uniform(size=(K, N)) > 0.2).astype(float)
    return geo, n, a, intens, ambient, values, weight


def dense_jacobian(pixels, lobe, eps=1e-7):
    """(N, K*3, 5) by central differences of the model in (tangent 1, tangent 2, albedo)."""
    geo, n, a, intens, ambient, _, _ = pixels
    t1, t2 = ph._tangents(n)
    cols = []
    for j in range(5):

        def at(h, j=j):
            nn, aa = n.copy(), a.copy()
            if j < 2:
                nn = ph._normalised(n + h * (t1, t2)[j])
            else:
                aa[j - 2] += h
            return ph._model(geo, nn, aa, intens, ambient, lobe)[0]

        cols.append((at(eps) - at(-eps)) / (2 * eps))
    return np.stack(cols, -1).transpose(2, 0, 1, 3).reshape(N, K * 3, 5)


@pytest.mark.parametrize("lobe", [ph.SpecularLobe(), ph.SpecularLobe(0.15, 30.0)])
def test_normal_equations_in_blocks_are_the_dense_ones(pixels, lobe):
    geo, n, a, intens, ambient, values, weight = pixels
    s = ph._system(values, weight, geo, n, a, intens, ambient, lobe)
    jac = dense_jacobian(pixels, lobe)
    w = np.repeat(weight.T, 3, axis=1)[..., None]  # (N, K*3, 1)
    r = (values - ph._model(geo, n, a, intens, ambient, lobe)[0]).transpose(2, 0, 1)
    jtj = np.swapaxes(jac * w, 1, 2) @ jac
    jtr = (np.swapaxes(jac * w, 1, 2) @ r.reshape(N, K * 3, 1))[..., 0]
    scale = np.abs(jtj).max()
    np.testing.assert_allclose(s.hnn[0], jtj[:, 0, 0], atol=1e-6 * scale)
    np.testing.assert_allclose(s.hnn[1], jtj[:, 0, 1], atol=1e-6 * scale)
    np.testing.assert_allclose(s.hnn[2], jtj[:, 1, 1], atol=1e-6 * scale)
    np.testing.assert_allclose(s.hna.transpose(2, 0, 1), jtj[:, :2, 2:], atol=1e-6 * scale)
    # the albedo block is diagonal
    haa = np.einsum("np,pq->npq", s.haa.T, np.eye(3))
    np.testing.assert_allclose(haa, jtj[:, 2:, 2:], atol=1e-6 * scale)
    np.testing.assert_allclose(np.concatenate([s.gn, s.ga]).T, jtr, atol=1e-6 * np.abs(jtr).max())
    # the closed-form damped step is the dense solve's, on the same blocks
    damping = np.geomspace(1e-6, 10.0, N)
    xn, xa = ph._block_solve(s, damping, s.gn, s.ga)
    h = np.zeros((N, 5, 5))
    h[:, 0, 0], h[:, 0, 1], h[:, 1, 0], h[:, 1, 1] = s.hnn[0], s.hnn[1], s.hnn[1], s.hnn[2]
    h[:, :2, 2:] = s.hna.transpose(2, 0, 1)
    h[:, 2:, :2] = s.hna.transpose(2, 1, 0)
    h[:, 2:, 2:] = haa
    diag = np.maximum(np.einsum("npp->np", h), 1e-12)
    h += damping[:, None, None] * np.einsum("np,pq->npq", diag, np.eye(5)) + 1e-15 * np.eye(5)
    dense = np.linalg.solve(h, np.concatenate([s.gn, s.ga]).T[..., None])[..., 0]
    np.testing.assert_allclose(np.concatenate([xn, xa]).T, dense, rtol=1e-9, atol=1e-12)


def test_linear_normals_solve_their_normal_equations(pixels):
    geo, n, _, intens, _, _, weight = pixels
    # Lambertian, no ambient, grey intensities: photometric stereo is exact
    grey = np.ones_like(intens)
    shade = np.maximum(ph._dot(geo.directions, n[:, None, :]), 0.0) * geo.falloff
    lit = (shade > 0).astype(float) * weight
    values = 0.5 * shade[:, None, :] * grey
    found = ph._linear_normals(values, lit, geo, grey)
    # the dense definition: (sum_k w l_k l_k^T + 1e-9 I) g = sum_k w l_k grey_k
    l_k = (geo.directions * geo.falloff).transpose(2, 1, 0)  # (N, K, 3)
    m = np.einsum("nki,nkj,kn->nij", l_k, l_k, lit) + 1e-9 * np.eye(3)
    g = np.linalg.solve(m, np.einsum("nki,kn,kn->ni", l_k, values[:, 0], lit)[..., None])[..., 0]
    ok = lit.sum(0) >= 3
    assert ok.sum() > N / 2
    dense = g / np.linalg.norm(g, axis=1, keepdims=True)
    np.testing.assert_allclose(found[:, ok], dense[ok].T, atol=1e-9)
    well_posed = ok & (np.linalg.cond(m) < 1e4)
    np.testing.assert_allclose(found[:, well_posed], n[:, well_posed], atol=1e-6)


def test_each_pixel_stops_when_converged(pixels):
    """Noise-free pixels: every one converges, to the truth, and more iterations change
    nothing (converged pixels are not iterated further)."""
    geo, n, a, intens, ambient, _, _ = pixels
    lobe = ph.SpecularLobe(0.1, 20.0)
    values = ph._model(geo, n, a, intens, ambient, lobe)[0]
    lit = ph._dot(geo.directions, n[:, None, :]) > 0.3
    keep = lit.sum(0) >= 4
    sub = ph._take(geo, keep)
    w = lit[:, keep].astype(float)
    tilt = ph._normalised(n[:, keep] + 0.05 * ph._tangents(n[:, keep])[0])
    a8, n8, _, conv8 = ph._levenberg_marquardt(
        values[:, :, keep], w, sub, tilt, intens, ambient, lobe, 8
    )
    a30, n30, _, _ = ph._levenberg_marquardt(
        values[:, :, keep], w, sub, tilt, intens, ambient, lobe, 30
    )
    assert conv8.mean() > 0.95
    np.testing.assert_allclose(a8[:, conv8], a[:, keep][:, conv8], rtol=1e-6)
    np.testing.assert_allclose(n8[:, conv8], n[:, keep][:, conv8], atol=1e-6)
    np.testing.assert_array_equal(a8[:, conv8], a30[:, conv8])
    np.testing.assert_array_equal(n8[:, conv8], n30[:, conv8])
