"""Pieces of `rsl adapt` that need no simulator: marker binding, tet refinement (parameter maps and Adam:
tests/test_parameters.py)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.adapt_loss import bind_markers, closest_points_on_triangles, marker_loss


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


def test_refine_tets_keeps_volume_orientation_and_coarse_vertices():
    from stages.steps.adapt import refine_tets
    from stages.sim.mesh import signed_volumes

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    t = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    t[1] = t[1][[0, 2, 1, 3]] if signed_volumes(v, t[1:])[0] < 0 else t[1]
    v2, t2, r2 = refine_tets(v, t, np.array([0, 1]))
    assert np.array_equal(v2[:5], v)
    vol = signed_volumes(v2, t2)
    assert np.all(vol > 0)
    assert np.allclose(vol.reshape(2, 8).sum(1), signed_volumes(v, t))
    assert np.array_equal(r2, [0] * 8 + [1] * 8)
    assert len(v2) == 5 + 9  # 9 distinct edges


def test_camera_choice_by_index_or_name_and_its_errors():
    from pathlib import Path

    from stages.observations import pick_cameras
    from stages.errors import RslError

    names = ["cam0", "cam1", "cam2"]
    assert pick_cameras("", names, Path("cameras.h5")) == names
    assert pick_cameras("2, 0", names, Path("cameras.h5")) == ["cam2", "cam0"]
    assert pick_cameras("cam1,1", names, Path("cameras.h5")) == ["cam1"]
    with pytest.raises(RslError, match="asks for camera 5 but it holds 3"):
        pick_cameras("5", names, Path("cameras.h5"))
    with pytest.raises(RslError, match="'left', which is not one of"):
        pick_cameras("left", names, Path("cameras.h5"))


def test_frame_range_parsing():
    from pathlib import Path

    from stages.steps.adapt import _parse_frames
    from stages.errors import RslError

    assert _parse_frames("", 40, Path("c")) == (0, 40)
    assert _parse_frames("5:20", 40, Path("c")) == (5, 20)
    assert _parse_frames("5:", 40, Path("c")) == (5, 40)
    assert _parse_frames(":7", None, Path("c")) == (0, 7)
    for bad, msg in (("7:3", "empty or negative"), ("0:50", "only 40 exist"), ("a:b", "should be A:B")):
        with pytest.raises(RslError, match=msg):
            _parse_frames(bad, 40, Path("c"))


# =========================================================================== point location in tets
def _box_tets():
    from stages.sim.meshgen import box_tets

    v, t = box_tets((4, 3, 2), (0.4, 0.3, 0.2))
    return np.asarray(v, float), np.asarray(t, np.int64)


def test_tet_barycentrics_reproduce_the_points_and_are_one_hot_at_corners():
    from stages.adapt_loss import tet_barycentrics

    v, t = _box_tets()
    rng = np.random.default_rng(7)
    pick = rng.integers(0, len(t), 50)
    p = rng.uniform(-0.1, 0.5, (50, 3))
    b = tet_barycentrics(p, v, t[pick])
    assert np.allclose(b.sum(1), 1)
    assert np.allclose(np.einsum("pk,pkd->pd", b, v[t[pick]]), p, atol=1e-12)
    assert np.allclose(tet_barycentrics(v[t[pick, 2]], v, t[pick]), np.eye(4)[np.full(50, 2)], atol=1e-12)


def test_locate_in_tets_matches_the_brute_force_search_inside_and_outside_a_deformed_mesh():
    from stages.adapt_loss import locate_in_tets, locate_in_tets_brute

    v, t = _box_tets()
    x = v + 0.03 * np.sin(7 * v[:, [1, 2, 0]])  # a smooth non-affine deformation
    rng = np.random.default_rng(8)
    pick = rng.integers(0, len(t), 150)
    inside = np.einsum("pk,pkd->pd", rng.dirichlet(np.ones(4), 150), x[t[pick]])
    outside = rng.uniform(x.min(0) - 0.05, x.max(0) + 0.05, (150, 3))
    pts = np.concatenate([inside, outside])
    for cand, widen in ((4, 4), (24, 16), (len(t), 1)):  # (len(t), 1): every tet is a candidate
        tet, bary = locate_in_tets(pts, x, t, candidates=cand, widen=widen)
        tet_b, bary_b = locate_in_tets_brute(pts, x, t, candidates=cand, widen=widen)
        # the same min-barycentric score (ties on shared faces may pick either tet)
        assert np.allclose(bary.min(1), bary_b.min(1), atol=1e-12)
    exhaustive = bary.min(1)
    assert len(t) > 8 * 8
    tet, bary = locate_in_tets(pts, x, t, candidates=8, widen=8)
    assert np.allclose(bary.min(1), exhaustive, atol=1e-12)  # 64 nearest of 144 tets: the best of all here
    assert np.allclose(np.einsum("pk,pkd->pd", bary, x[t[tet]]), pts, atol=1e-12)
    assert np.all(bary[:150].min(1) >= -1e-9)  # points inside the mesh get a holding tet
    assert np.mean(tet[:150] == pick) > 0.9
