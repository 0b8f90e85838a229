"""Point location in tets (stages/sim/locate.py): barycentric coordinates, and the k-d tree search held to its
one-point-at-a-time twin inside and outside a deformed mesh."""
from __future__ import annotations

import numpy as np

from stages.sim.locate import locate_in_tets, locate_in_tets_brute, tet_barycentrics
from stages.sim.meshgen import box_tets


def _box_tets():
    v, t = box_tets((4, 3, 2), (0.4, 0.3, 0.2))
    return np.asarray(v, float), np.asarray(t, np.int64)


def test_tet_barycentrics_reproduce_the_points_and_are_one_hot_at_corners():
    v, t = _box_tets()
    rng = np.random.default_rng(7)
    pick = rng.integers(0, len(t), 50)
    p = rng.uniform(-0.1, 0.5, (50, 3))
    b = tet_barycentrics(p, v, t[pick])
    assert np.allclose(b.sum(1), 1)
    assert np.allclose(np.einsum("pk,pkd->pd", b, v[t[pick]]), p, atol=1e-12)
    assert np.allclose(tet_barycentrics(v[t[pick, 2]], v, t[pick]), np.eye(4)[np.full(50, 2)], atol=1e-12)


def test_locate_in_tets_matches_the_brute_force_search_inside_and_outside_a_deformed_mesh():
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
