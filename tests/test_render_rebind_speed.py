"""The fast paths adapt's vision loss takes per frame, held to their slow twins: point location with a host hint
(ImageLoss.rebind) against the search without one, and ``one_torch_thread``."""
from __future__ import annotations

import numpy as np
import pytest


def _moved_box(order: int, seed: int):
    from stages.sim import quadrature as Q
    from stages.sim.meshgen import box_tets

    v, t = box_tets((5, 3, 3), (0.5, 0.3, 0.3))
    v, t = np.asarray(v, float), np.asarray(t, np.int64)
    if order == 2:
        v, t = Q.quadratic_tets(v, t)
    rng = np.random.default_rng(seed)
    x_fit = v + 0.02 * np.sin(7 * v[:, [1, 2, 0]])  # where the points were located
    x_new = x_fit + 0.004 * np.sin(5 * v[:, [2, 0, 1]] + 1.0)  # a small further motion: some points change tet
    return v, t, x_fit, x_new, rng


def test_locate_with_a_host_hint_equals_the_search_without_one():
    from stages.sim.locate import locate_in_elements

    for order in (1, 2):
        v, t, x_fit, x_new, rng = _moved_box(order, 3)
        host0 = rng.integers(0, len(t), 400)
        b0 = rng.dirichlet(np.ones(4), 400)
        from stages.sim import quadrature as Q

        N, _, _ = Q.point_map(v, t, host0, b0) if order == 2 else (b0, None, None)
        pts = np.einsum("gk,gkd->gd", N, x_fit[t[host0]]) if order == 2 else \
            np.einsum("gk,gkd->gd", b0, x_fit[t[host0, :4]])
        outside = rng.uniform(x_new.min(0) - 0.03, x_new.max(0) + 0.03, (60, 3))
        pts = np.concatenate([pts, outside])
        hint = np.concatenate([host0, rng.integers(0, len(t), 60)])
        h_ref, b_ref = locate_in_elements(pts, x_new, t)
        h, b = locate_in_elements(pts, x_new, t, hint=hint)
        moved = np.mean(h[:400] != host0)
        assert 0.01 < moved < 0.9, moved  # the case exercises both the kept hints and the search
        assert np.array_equal(h, h_ref)
        np.testing.assert_array_equal(b, b_ref)  # the same floats


def test_locate_with_a_relocator_equals_the_search():
    """locate_in_elements with a Relocator (walk from the hint, one k-d tree query) against the search without a hint:
    the same elements and floats, linear and quadratic, points inside and outside, over successive motions."""
    from stages.sim import quadrature as Q
    from stages.sim.locate import Relocator, locate_in_elements

    for order in (1, 2):
        v, t, x_fit, x_new, rng = _moved_box(order, 4)
        host0 = rng.integers(0, len(t), 400)
        b0 = rng.dirichlet(np.ones(4), 400)
        N = Q.point_map(v, t, host0, b0)[0] if order == 2 else b0
        pts = np.concatenate([np.einsum("gk,gkd->gd", N, x_fit[t[host0][:, :N.shape[1]]]),
                              rng.uniform(x_new.min(0) - 0.03, x_new.max(0) + 0.03, (60, 3))])
        reloc = Relocator(pts, t)
        hint = np.concatenate([host0, rng.integers(0, len(t), 60)])
        for x in (x_new, x_new + 0.5 * (x_new - x_fit), x_fit):
            h_ref, b_ref = locate_in_elements(pts, x, t)
            h, b = locate_in_elements(pts, x, t, hint=hint, relocator=reloc)
            assert np.array_equal(h, h_ref)
            np.testing.assert_array_equal(b, b_ref)  # the same floats
            hint = h
        with pytest.raises(ValueError):
            locate_in_elements(pts[1:], x_fit, t, hint=hint[1:], relocator=reloc)


@pytest.mark.parametrize("order", [1, 2])
def test_image_loss_rebind_with_the_relocator_equals_its_slow_twin(order):
    """ImageLoss.rebind (relocate: the Relocator) against the hint search (relocate False) over a sequence of anchor
    configurations: the same host elements, barycentrics and rest covariance factors."""
    from stages.render.image_loss import ImageLoss
    from test_render_project_bound import _mesh_and_gaussians

    mesh, art = _mesh_and_gaussians(order, 300)
    runs = []
    for relocate in (True, False):
        il = ImageLoss(art, mesh, [])
        il.relocate = relocate
        out = []
        for s in range(4):
            x = mesh.vertices + 0.004 * s * np.sin(mesh.vertices[:, [1, 2, 0]] * 20.0 + s)
            il.rebind(x)
            out.append((il.host_tet.copy(), il.bary.copy(), il._factor.numpy().copy()))
        runs.append(out)
    moved = 0
    for (h1, b1, f1), (h2, b2, f2) in zip(*runs):
        assert np.array_equal(h1, h2)
        np.testing.assert_array_equal(b1, b2)
        np.testing.assert_array_equal(f1, f2)
        moved += int(np.sum(h1 != runs[0][0][0]))
    assert moved  # the motions moved some Gaussians to other elements


def test_one_torch_thread_sets_one_and_restores():
    import torch

    from stages.render.gaussians import one_torch_thread

    before = torch.get_num_threads()
    with one_torch_thread():
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
    try:
        with one_torch_thread():
            raise KeyError
    except KeyError:
        pass
    assert torch.get_num_threads() == before
