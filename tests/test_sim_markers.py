"""The marker observation model (stages/sim/markers.py): closest points on triangles, the binding of markers to
the surface, the loss and its gradient (against finite differences), gaps in the capture."""
from __future__ import annotations

import numpy as np
import pytest

from stages.sim.markers import bind_markers, closest_points_on_triangles, marker_loss


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
