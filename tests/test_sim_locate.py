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


def test_tet_neighbours_share_the_face_opposite_each_corner():
    from stages.sim.locate import tet_neighbours

    v, t = _box_tets()
    nb = tet_neighbours(t)
    assert nb.shape == t.shape
    for a in range(len(t)):
        for i in range(4):
            b = nb[a, i]
            face = set(np.delete(t[a], i))
            if b < 0:  # a boundary face: no other tet holds it
                assert sum(face <= set(u) for u in t) == 1
            else:
                assert face <= set(t[b]) and a in nb[b]
    # the closed box's boundary: 2 triangles per cell face on its surface
    nx, ny, nz = 4, 3, 2
    assert np.sum(nb < 0) == 4 * (nx * ny + ny * nz + nx * nz)


def test_relocator_equals_the_search_over_a_moving_mesh_inside_outside_and_on_faces():
    """The walk from a hint and the one-query search (Relocator) give locate_in_tets' tets and the very same floats
    over a sequence of deformed configurations, for points inside, outside (near and far) and on shared faces."""
    from stages.sim.locate import Relocator

    v, t = _box_tets()
    rng = np.random.default_rng(11)
    pick = rng.integers(0, len(t), 200)
    x_fit = v + 0.03 * np.sin(7 * v[:, [1, 2, 0]])
    inside = np.einsum("pk,pkd->pd", rng.dirichlet(np.ones(4), 200), x_fit[t[pick]])
    outside = rng.uniform(x_fit.min(0) - 0.08, x_fit.max(0) + 0.08, (150, 3))
    on_face = np.einsum("pk,pkd->pd", rng.dirichlet(np.ones(3), 50), x_fit[t[pick[:50], :3]])  # corners 0-2's face
    pts = np.concatenate([inside, outside, on_face])
    reloc = Relocator(pts, t)
    hint = np.concatenate([pick, rng.integers(0, len(t), 150), pick[:50]])  # (the points' tets, or a guess)
    kept = walked = searched = 0
    for step in range(-1, 6):  # x_fit (the face points on their faces), then growing motions: some points change
        # tet, some leave or enter the mesh
        x = x_fit if step < 0 else x_fit + (0.004 + 0.006 * step) * np.sin(5 * v[:, [2, 0, 1]] + step)
        ref_tet, ref_bary = locate_in_tets(pts, x, t)
        tet, bary = reloc(x, hint)
        same = tet == ref_tet
        # a point on a face shared by two tets may sit in either: the same position and score
        assert np.all(same | (np.abs(bary.min(1) - ref_bary.min(1)) <= 1e-9)), step
        np.testing.assert_allclose(np.einsum("pk,pkd->pd", bary, x[t[tet]]), pts, atol=1e-12)
        np.testing.assert_array_equal(bary[same], ref_bary[same])  # the very floats
        assert np.mean(same) > 0.99
        strict = (tet == hint) & (bary.min(1) > 1e-9)
        kept += int(np.sum(strict))
        walked += int(np.sum((tet != hint) & (bary.min(1) > 1e-9)))
        searched += int(np.sum(bary.min(1) <= 1e-9))
        hint = tet
    assert kept and walked and searched  # every path of the Relocator ran


def test_relocator_with_a_wrong_or_far_hint_still_finds_the_search_s_tets():
    from stages.sim.locate import Relocator

    v, t = _box_tets()
    x = v + 0.03 * np.sin(7 * v[:, [1, 2, 0]])
    rng = np.random.default_rng(12)
    pts = np.concatenate([np.einsum("pk,pkd->pd", rng.dirichlet(np.ones(4), 100), x[t[rng.integers(0, len(t), 100)]]),
                          rng.uniform(x.min(0) - 0.05, x.max(0) + 0.05, (100, 3))])
    ref_tet, ref_bary = locate_in_tets(pts, x, t)
    for walk in (0, 1, 8):  # 0: no walk, every point off its hint goes to the search
        tet, bary = Relocator(pts, t, walk=walk)(x, rng.integers(0, len(t), len(pts)))
        assert np.array_equal(tet, ref_tet)
        np.testing.assert_array_equal(bary, ref_bary)
