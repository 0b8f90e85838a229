"""The marker observation model (stages/sim/markers.py): closest points on triangles, the binding of markers to
the surface, the loss and its gradient (against finite differences), gaps in the capture."""
from __future__ import annotations

import numpy as np
import pytest

from stages.sim.markers import bind_markers, closest_points_on_triangles, fit_binding_to_tracks, marker_loss


def _brute_closest(p, tri, k=60):
    """Closest point by dense barycentric sampling (the plain twin of the closed form)."""
    u, v = np.meshgrid(np.linspace(0, 1, k + 1), np.linspace(0, 1, k + 1))
    keep = u + v <= 1 + 1e-12
    b = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], 1)
    pts = b @ tri
    d = np.linalg.norm(pts - p, axis=1)
    return pts[np.argmin(d)], d.min()


def test_closest_point_matches_sampling_in_every_voronoi_region():
    rng = np.random.default_rng(0)
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0.2, 0.9, 0]]])
    pts = rng.uniform(-1, 2, (200, 3))
    closest, bary = closest_points_on_triangles(pts, tri)
    assert np.allclose(bary.sum(-1), 1) and np.all(bary > -1e-12)
    for i in range(0, 200, 7):
        c_ref, d_ref = _brute_closest(pts[i], tri[0])
        d = np.linalg.norm(closest[i, 0] - pts[i])
        assert d <= d_ref + 1e-12
        assert d >= d_ref - 2e-2  # sampling resolution


def _cube_surface():
    v = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def test_markers_on_the_surface_are_reproduced_exactly_and_follow_affine_motion():
    v, f = _cube_surface()
    rng = np.random.default_rng(1)
    m0 = rng.uniform(0.05, 0.95, (30, 3))
    m0[np.arange(30), rng.integers(0, 3, 30)] = rng.integers(0, 2, 30)  # put each on a face
    b = bind_markers(v, f, m0)
    assert np.allclose(b.positions(v), m0, atol=1e-12)
    assert b.distance.max() < 1e-12
    A = np.array([[1.1, 0.2, 0], [0, 0.9, 0.1], [0.05, 0, 1.2]])
    assert np.allclose(b.positions(v @ A.T + 0.3), m0 @ A.T + 0.3, atol=1e-12)


def test_marker_loss_gradient_matches_finite_differences():
    v, f = _cube_surface()
    rng = np.random.default_rng(2)
    b = bind_markers(v, f, rng.uniform(-0.2, 1.2, (12, 3)))
    X = v[None] + 0.05 * rng.standard_normal((3, 8, 3))
    P = rng.uniform(0, 1, (3, 12, 3))
    L, g = marker_loss(b, X, P)
    h = 1e-6
    for idx in [(0, 0, 0), (1, 3, 2), (2, 7, 1), (2, 5, 0)]:
        Xp, Xm = X.copy(), X.copy()
        Xp[idx] += h
        Xm[idx] -= h
        fd = (marker_loss(b, Xp, P)[0] - marker_loss(b, Xm, P)[0]) / (2 * h)
        assert g[idx] == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_marker_loss_with_gaps_sums_observed_markers_and_its_gradient_matches_finite_differences():
    """Gaps (NaN in P) add nothing: L equals an explicit loop over the observed (t, i), a frame with no observed
    marker adds nothing, and dL/dX matches central differences in every coordinate (exact for the mask)."""
    v, f = _cube_surface()
    rng = np.random.default_rng(3)
    b = bind_markers(v, f, rng.uniform(-0.2, 1.2, (12, 3)))
    X = v[None] + 0.05 * rng.standard_normal((4, 8, 3))
    P = rng.uniform(0, 1, (4, 12, 3))
    gap = rng.uniform(size=(4, 12)) < 0.4
    gap[2] = True  # no marker seen at frame 2
    P[gap] = np.nan
    P[0, 5, 1] = np.nan  # one NaN coordinate makes the whole entry a gap
    gap[0, 5] = True
    L, g = marker_loss(b, X, P)
    assert np.isfinite(L) and np.all(np.isfinite(g))
    slow = 0.0
    for t in range(4):
        for i in range(12):
            if not gap[t, i]:
                m = sum(b.bary[i, k] * X[t, b.faces[i, k]] for k in range(3))
                slow += float(np.sum((m - P[t, i]) ** 2))
    assert L == pytest.approx(slow, rel=1e-12)
    assert L < marker_loss(b, X, np.where(np.isnan(P), 0.3, P))[0]  # the gaps do count once filled in
    assert np.all(g[2] == 0.0)
    h = 1e-6
    for idx in np.ndindex(*X.shape):
        Xp, Xm = X.copy(), X.copy()
        Xp[idx] += h
        Xm[idx] -= h
        fd = (marker_loss(b, Xp, P)[0] - marker_loss(b, Xm, P)[0]) / (2 * h)
        assert g[idx] == pytest.approx(fd, rel=1e-6, abs=1e-9), idx
    # all gaps: zero loss and gradient, no crash
    L0, g0 = marker_loss(b, X, np.full_like(P, np.nan))
    assert L0 == 0.0 and not np.any(g0)


def _track_surface(rng, w=4):
    """A bumpy 6 × 6 grid surface (n, 3), its faces, and w frames of a smooth non-affine motion of it."""
    u, v = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6))
    x0 = np.stack([u.ravel(), v.ravel(), 0.05 * np.sin(3 * u.ravel()) * np.cos(2 * v.ravel())], 1)
    faces = []
    for i in range(5):
        for j in range(5):
            a = i * 6 + j
            faces += [[a, a + 1, a + 7], [a, a + 7, a + 6]]
    faces = np.array(faces)
    X = np.stack([x0 + t * np.stack([0.02 * x0[:, 1] ** 2, 0.01 * x0[:, 0], 0.03 * x0[:, 0] * x0[:, 1]], 1)
                  + 0.002 * t * rng.normal(size=x0.shape) for t in range(w)])
    return X, faces


def _slsqp_track_fit(X, faces, P, cand):
    """The least cost over the candidate triangles by scipy's SLSQP on (b_1, b_2) ≥ 0, b_1 + b_2 ≤ 1 from the
    triangle's centre (the plain twin of the closed form)."""
    from scipy.optimize import minimize

    best = np.inf
    for f in cand:
        T = X[:, faces[f]]  # (w, 3, 3)

        def cost(q):
            m = T[:, 0] + q[0] * (T[:, 1] - T[:, 0]) + q[1] * (T[:, 2] - T[:, 0])
            return float(np.sum((m - P) ** 2))

        r = minimize(cost, [1 / 3, 1 / 3], method="SLSQP", bounds=[(0, 1), (0, 1)], options={"ftol": 1e-15},
                     constraints=[{"type": "ineq", "fun": lambda q: 1.0 - q[0] - q[1]}])
        best = min(best, float(r.fun))
    return best


def test_track_fit_finds_the_material_point_that_made_a_track_and_matches_a_dense_search():
    """fit_binding_to_tracks: markers moved with chosen material points (some on edges and corners) are found again
    to rounding; with noisy tracks its cost is the least that SLSQP finds on the same triangles (the constrained
    quadratic's minimum, interior or on an edge)."""
    rng = np.random.default_rng(1)
    X, faces = _track_surface(rng)
    M = 30
    fid = rng.integers(0, len(faces), M)
    bary = rng.dirichlet(np.ones(3), M)
    bary[:5, 0] = 0.0  # on an edge
    bary[:5] /= bary[:5].sum(1, keepdims=True)
    bary[5:8] = [1.0, 0.0, 0.0]  # at a vertex
    P = np.einsum("mk,tmkd->tmd", bary, X[:, faces[fid]])
    b = fit_binding_to_tracks(X, faces, P)
    assert np.allclose(b.positions(X), P, atol=1e-9)
    assert np.all(b.distance <= 1e-9)
    chunked = fit_binding_to_tracks(X, faces, P, chunk=7)  # the candidates searched 7 markers at a time
    assert np.array_equal(chunked.faces, b.faces) and np.array_equal(chunked.bary, b.bary)

    noisy = P + 0.003 * rng.normal(size=P.shape)
    b = fit_binding_to_tracks(X, faces, noisy, candidates=4)
    assert np.all(b.bary >= -1e-12) and np.allclose(b.bary.sum(1), 1.0)
    cost = np.sum((b.positions(X) - noisy) ** 2, axis=(0, 2))
    closest, _ = closest_points_on_triangles(noisy[0], X[0][faces])
    order = np.argsort(np.linalg.norm(closest - noisy[0][:, None], axis=-1), axis=1)[:, :4]
    for i in range(M):
        c_ref = _slsqp_track_fit(X, faces, noisy[:, i], order[i])
        assert abs(cost[i] - c_ref) <= 1e-6 * c_ref, (i, cost[i], c_ref)


def test_track_fit_of_one_frame_is_the_nearest_surface_point_and_gaps_add_nothing():
    """With one frame the fit is bind_markers' nearest point (markers off the surface on either side); a marker
    missing from frame 0 is placed by the frames that see it, its distance taken at the first of them."""
    rng = np.random.default_rng(2)
    X, faces = _track_surface(rng)
    P0 = np.concatenate([rng.uniform(0.05, 0.95, (20, 2)), rng.uniform(-0.1, 0.1, (20, 1))], 1)
    b = fit_binding_to_tracks(X[:1], faces, P0[None])
    ref = bind_markers(X[0], faces, P0)
    assert np.allclose(b.positions(X[0]), ref.positions(X[0]), atol=1e-12)
    assert np.allclose(b.distance, ref.distance, atol=1e-12)

    fid, bary = rng.integers(0, len(faces), 6), rng.dirichlet(np.ones(3), 6)
    P = np.einsum("mk,tmkd->tmd", bary, X[:, faces[fid]])
    P[0, 2] = np.nan
    P[1:3, 4] = np.nan
    b = fit_binding_to_tracks(X, faces, P)
    seen = np.all(np.isfinite(P), -1)
    assert np.allclose(b.positions(X)[seen], P[seen], atol=1e-9)
    assert b.distance[2] <= 1e-12 and np.all(np.isfinite(b.distance))  # (at its first frame: on the surface)


def test_track_fit_searches_a_late_marker_on_the_surface_of_its_first_frame():
    """A marker first seen in the last frame of a track whose surface slid by several triangles since the first:
    searched near its position on that frame's surface (not the first frame's), it is placed exactly."""
    rng = np.random.default_rng(4)
    X, faces = _track_surface(rng, w=3)
    X[1:] += np.array([0.35, 0.0, 0.0])  # a slide of 1.75 triangle widths after the first frame
    fid, bary = rng.integers(0, len(faces), 5), rng.dirichlet(np.ones(3), 5)
    P = np.einsum("mk,tmkd->tmd", bary, X[:, faces[fid]])
    P[:2, 1] = np.nan  # marker 1 seen only in the last frame (a single frame: its nearest surface point)
    P[0, 3] = np.nan
    b = fit_binding_to_tracks(X, faces, P, candidates=4)
    seen = np.all(np.isfinite(P), -1)
    assert np.allclose(b.positions(X)[seen], P[seen], atol=1e-9)
    np.testing.assert_array_equal(b.faces[[1, 3]], faces[fid[[1, 3]]])
