"""Materials and per-element kernels: energies, gradients and Hessians against finite differences,
the numba stable Neo-Hookean kernel against its JAX twin, identities of the energies."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.sim.elements import (ENERGY, GRADIENT, HESSIAN, element_terms, element_terms_jax, shape_gradients,
                                 snh_kernel, _rotation_svd, _sym3_eig)
from stages.sim.linsolve import SparsePattern
from stages.sim.materials import MODELS, energy_density, lame
from stages.sim.mesh import rest_quantities

jax.config.update("jax_enable_x64", True)

FD_RTOL = 1e-6  # central differences in float64 with h ~ 1e-6 relative


def random_tets(m: int, seed: int, noise: float):
    """m separate random tets (positively oriented) and a deformed configuration."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(4 * m, 3)) * 0.1
    tets = np.arange(4 * m).reshape(m, 4)
    vol, _, _ = rest_quantities(rest, tets, 1.0)
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    vol, dm_inv, _ = rest_quantities(rest, tets, 1.0)
    x = rest + noise * 0.1 * rng.normal(size=rest.shape)
    mu, lam = lame(rng.uniform(1e4, 1e6, m), rng.uniform(0.1, 0.45, m))
    return rest, x, tets, dm_inv, vol, mu, lam


@pytest.mark.parametrize("material", MODELS)
def test_element_gradient_and_hessian_match_finite_differences(material):
    rest, x, tets, dm_inv, vol, mu, lam = random_tets(3, 1, 0.15)
    e, g, h = element_terms_jax(x, tets, dm_inv, vol, mu, lam, material, project=False)
    e, g, h = np.asarray(e), np.asarray(g), np.asarray(h)

    def energies(z):
        return np.asarray(element_terms_jax(z, tets, dm_inv, vol, mu, lam, material, False)[0])

    def grads(z):
        return np.asarray(element_terms_jax(z, tets, dm_inv, vol, mu, lam, material, False)[1])

    eps = 1e-7
    for a in range(4):
        for i in range(3):
            dz = np.zeros_like(x)
            dz[tets[:, a], i] = eps
            fd_g = (energies(x + dz) - energies(x - dz)) / (2 * eps)
            np.testing.assert_allclose(g[:, 3 * a + i], fd_g, rtol=FD_RTOL, atol=1e-9 * np.abs(g).max())
            fd_h = (grads(x + dz) - grads(x - dz)) / (2 * eps)
            np.testing.assert_allclose(h[:, :, 3 * a + i], fd_h, rtol=FD_RTOL, atol=1e-7 * np.abs(h).max())


@pytest.mark.parametrize("material", MODELS)
def test_energy_zero_and_force_free_at_rest(material):
    rest, _, tets, dm_inv, vol, mu, lam = random_tets(5, 2, 0.0)
    e, g, _ = element_terms(rest, tets, dm_inv, vol, mu, lam, material, GRADIENT)
    assert np.abs(e).max() < 1e-12 * np.abs(mu * vol).max()
    assert np.abs(g).max() < 1e-9 * np.abs(mu * vol ** (2 / 3)).max()


@pytest.mark.parametrize("material", ["stable_neohookean", "yeoh"])
def test_energy_unchanged_by_rigid_rotation(material):
    rest, x, tets, dm_inv, vol, mu, lam = random_tets(4, 3, 0.3)
    q = np.array([0.3, -0.5, 0.7, 0.2])
    q /= np.linalg.norm(q)
    from stages.capture import quat_to_matrix
    R = quat_to_matrix(q)
    e0, _, _ = element_terms(x, tets, dm_inv, vol, mu, lam, material, ENERGY, backend="jax")
    e1, _, _ = element_terms(x @ R.T + np.array([1.0, -2.0, 0.5]), tets, dm_inv, vol, mu, lam, material, ENERGY,
                             backend="jax")
    np.testing.assert_allclose(e1, e0, rtol=1e-10, atol=1e-14)


def test_snh_small_strain_stiffness_equals_linear_elasticity():
    mu, lam = lame(2.0e5, 0.42)
    hs = jax.hessian(energy_density("stable_neohookean"))(jnp.eye(3), mu, lam).reshape(9, 9)
    hl = jax.hessian(energy_density("linear"))(jnp.eye(3), mu, lam).reshape(9, 9)
    np.testing.assert_allclose(np.asarray(hs), np.asarray(hl), rtol=1e-12, atol=1e-9 * mu)


@pytest.mark.parametrize("noise,project", [(0.05, False), (0.6, False), (0.05, True), (0.6, True)])
def test_numba_snh_kernel_matches_jax_twin(noise, project):
    """Small and large (some inverted) deformations, exact and projected Hessians."""
    rest, x, tets, dm_inv, vol, mu, lam = random_tets(60, 4, noise)
    J = np.linalg.det(np.einsum("mai,maj->mij", x[tets], shape_gradients(dm_inv)))
    if noise > 0.5:
        assert (J < 0).any() and (J > 0).any()
    e1, g1, h1 = snh_kernel(x, tets, dm_inv, vol, mu, lam, HESSIAN, project)
    e2, g2, h2 = (np.asarray(a) for a in element_terms_jax(x, tets, dm_inv, vol, mu, lam, "stable_neohookean",
                                                            project))
    np.testing.assert_allclose(e1, e2, rtol=1e-11, atol=1e-12 * np.abs(e2).max())
    np.testing.assert_allclose(g1, g2, rtol=1e-10, atol=1e-11 * np.abs(g2).max())
    np.testing.assert_allclose(h1, h2, rtol=1e-8, atol=1e-10 * np.abs(h2).max())
    if project:
        assert np.linalg.eigvalsh(h1).min() > -1e-9 * np.abs(h1).max()


def test_numba_hessian_is_the_derivative_of_numba_gradient():
    """The compiled kernel's own gradient/Hessian against central differences (backward twin)."""
    rest, x, tets, dm_inv, vol, mu, lam = random_tets(8, 5, 0.3)
    e, g, h = snh_kernel(x, tets, dm_inv, vol, mu, lam, HESSIAN, False)
    eps = 1e-7
    for a in range(4):
        for i in range(3):
            dz = np.zeros_like(x)
            dz[tets[:, a], i] = eps
            ep, gp, _ = snh_kernel(x + dz, tets, dm_inv, vol, mu, lam, GRADIENT, False)
            em, gm, _ = snh_kernel(x - dz, tets, dm_inv, vol, mu, lam, GRADIENT, False)
            np.testing.assert_allclose(g[:, 3 * a + i], (ep - em) / (2 * eps), rtol=FD_RTOL,
                                       atol=1e-9 * np.abs(g).max())
            np.testing.assert_allclose(h[:, :, 3 * a + i], (gp - gm) / (2 * eps), rtol=FD_RTOL,
                                       atol=1e-7 * np.abs(h).max())


def test_snh_hessian_indefinite_near_rest_projection_fixes_it():
    """Why projection is needed: under compression the exact SNH Hessian has negative eigenvalues."""
    rest, x, tets, dm_inv, vol, mu, lam = random_tets(40, 6, 0.4)
    _, _, h = snh_kernel(x, tets, dm_inv, vol, mu, lam, HESSIAN, False)
    _, _, hp = snh_kernel(x, tets, dm_inv, vol, mu, lam, HESSIAN, True)
    assert np.linalg.eigvalsh(h).min() < 0
    assert np.linalg.eigvalsh(hp).min() > -1e-9 * np.abs(hp).max()


def test_rotation_svd_and_jacobi_eigen():
    rng = np.random.default_rng(7)
    for _ in range(50):
        F = rng.normal(size=(3, 3))
        U, s, V = _rotation_svd(F)
        np.testing.assert_allclose(U @ np.diag(s) @ V.T, F, atol=1e-12)
        assert np.linalg.det(U) > 0 and np.linalg.det(V) > 0
        np.testing.assert_allclose(np.prod(s), np.linalg.det(F), rtol=1e-10)
        A = F + F.T
        w, Q = _sym3_eig(A)
        np.testing.assert_allclose(Q @ np.diag(w) @ Q.T, A, atol=1e-12)


def test_numba_assembly_matches_bincount_twin():
    from stages.sim.meshgen import box_tets
    v, t = box_tets((3, 2, 2), (0.3, 0.2, 0.2))
    rng = np.random.default_rng(8)
    pat = SparsePattern(t, len(v))
    he = rng.normal(size=(len(t), 12, 12))
    hv = rng.normal(size=(len(v), 3, 3))
    np.testing.assert_allclose(pat.assemble(he, hv), pat.assemble_reference(he, hv), rtol=1e-13, atol=1e-13)
    # the same matrix built entry by entry with scipy's COO summation
    import scipy.sparse as sp
    dof = (3 * t[:, :, None] + np.arange(3)).reshape(-1, 12)
    rows = np.concatenate([np.repeat(dof, 12, axis=1).ravel(), np.repeat(np.arange(3 * len(v)).reshape(-1, 3), 3,
                                                                          axis=1).ravel()])
    cols = np.concatenate([np.tile(dof, (1, 12)).ravel(), np.tile(np.arange(3 * len(v)).reshape(-1, 3),
                                                                  (1, 3)).ravel()])
    A = sp.coo_matrix((np.concatenate([he.ravel(), hv.ravel()]), (rows, cols)), shape=pat.shape).toarray()
    np.testing.assert_allclose(pat.matrix(pat.assemble(he, hv)).toarray(), A, atol=1e-12)
