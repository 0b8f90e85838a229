"""Stress, von Mises, vertex averaging and nodal forces (stages/sim/stress.py)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq

from stages.sim import stress as st
from stages.sim.materials import MODELS, energy_density, lame
from test_stress_meshes import block_mesh
from stages.sim.mesh import rest_quantities

E, NU = 1.0e5, 0.45


def _random_F(rng, m, scale=0.2):
    F = np.eye(3) + scale * rng.standard_normal((m, 3, 3))
    det = np.linalg.det(F)
    F[det < 0, :, 0] *= -1  # keep J > 0
    return F


def _snh_P(F, mu, lam):
    """Closed-form P of stages.sim.materials.stable_neohookean:
    P = μ'(1 − 1/(I_C+1)) F + λ'(J − α) J F⁻ᵀ."""
    mu_s, lam_s = 4.0 / 3.0 * mu, lam + 5.0 / 6.0 * mu
    alpha = 1.0 + 0.75 * mu_s / lam_s
    ic = np.sum(F * F)
    J = np.linalg.det(F)
    return mu_s * (1.0 - 1.0 / (ic + 1.0)) * F + lam_s * (J - alpha) * J * np.linalg.inv(F).T


def _snh_uniaxial(l1, mu, lam):
    """Closed form of uniaxial stress along x for SNH: F = diag(l1, l2, l2), l2 from P22 = 0.

    P_ii = μ'(1 − 1/(I_C+1)) l_i + λ'(J − α) J / l_i, I_C = l1² + 2 l2², J = l1 l2².
    Returns (l2, P11, σ11)."""
    mu_s, lam_s = 4.0 / 3.0 * mu, lam + 5.0 / 6.0 * mu
    alpha = 1.0 + 0.75 * mu_s / lam_s

    def p(l2, i):
        ic = l1 * l1 + 2 * l2 * l2
        J = l1 * l2 * l2
        li = l1 if i == 0 else l2
        return mu_s * (1 - 1 / (ic + 1)) * li + lam_s * (J - alpha) * J / li

    l2 = brentq(lambda s: p(s, 1), 0.3, 1.5, xtol=1e-15)
    P11 = p(l2, 0)
    return l2, P11, P11 * l1 / (l1 * l2 * l2)


# ------------------------------------------------------------------------------------------ P, σ
def test_piola_matches_closed_form_snh():
    rng = np.random.default_rng(0)
    F = _random_F(rng, 8)
    mu, lam = lame(E, NU)
    P = st.first_piola(F, np.full(8, mu), np.full(8, lam))
    for k in range(8):
        np.testing.assert_allclose(P[k], _snh_P(F[k], mu, lam), rtol=1e-10, atol=1e-6)


@pytest.mark.parametrize("model", MODELS)
def test_piola_matches_finite_differences(model):
    rng = np.random.default_rng(1)
    F = _random_F(rng, 3)
    mu, lam = lame(E, NU)
    P = st.first_piola(F, np.full(3, mu), np.full(3, lam), model)
    psi = jax.jit(energy_density(model))
    h = 1e-6
    for k in range(3):
        fd = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                d = np.zeros((3, 3))
                d[i, j] = h
                fd[i, j] = (float(psi(jnp.asarray(F[k] + d), mu, lam)) - float(psi(jnp.asarray(F[k] - d), mu, lam))) / (2 * h)
        np.testing.assert_allclose(P[k], fd, rtol=1e-6, atol=1e-3)


@pytest.mark.parametrize("model", MODELS)
def test_rest_state_is_stress_free(model):
    mu, lam = lame(np.full(2, E), np.full(2, NU))
    F = np.stack([np.eye(3)] * 2)
    P = st.first_piola(F, mu, lam, model)
    sig = st.cauchy_stress(F, P)
    assert np.max(np.abs(sig)) < 1e-9 * E
    assert np.max(st.von_mises(sig)) < 1e-9 * E


@pytest.mark.parametrize("model", ["stable_neohookean", "yeoh"])
def test_cauchy_is_symmetric_and_objective(model):
    """σ = J⁻¹PFᵀ is symmetric for isotropic Ψ; under a rotation Q, σ(QF) = Q σ(F) Qᵀ, σ_vM unchanged."""
    rng = np.random.default_rng(2)
    F = _random_F(rng, 5)
    mu, lam = lame(np.full(5, E), np.full(5, NU))
    sig = st.cauchy_stress(F, st.first_piola(F, mu, lam, model))
    np.testing.assert_allclose(sig, np.swapaxes(sig, 1, 2), atol=1e-8 * E)
    q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    q *= np.sign(np.linalg.det(q))
    QF = q @ F
    sig_q = st.cauchy_stress(QF, st.first_piola(QF, mu, lam, model))
    np.testing.assert_allclose(sig_q, q @ sig @ q.T, atol=1e-8 * E)
    np.testing.assert_allclose(st.von_mises(sig_q), st.von_mises(sig), rtol=1e-9)


def test_von_mises_identities():
    # pure pressure has no von Mises stress; uniaxial σ11 = s gives |s|; pure shear τ gives √3 τ.
    assert st.von_mises(np.eye(3) * 7.0) == pytest.approx(0.0, abs=1e-12)
    assert st.von_mises(np.diag([5.0, 0, 0])) == pytest.approx(5.0)
    tau = np.zeros((3, 3))
    tau[0, 1] = tau[1, 0] = 2.0
    assert st.von_mises(tau) == pytest.approx(np.sqrt(3) * 2.0)
    # equals the classical principal-stress formula
    rng = np.random.default_rng(3)
    a = rng.standard_normal((3, 3))
    s = a + a.T
    p1, p2, p3 = st.principal_stresses(s)
    assert st.von_mises(s) == pytest.approx(np.sqrt(0.5 * ((p1 - p2) ** 2 + (p2 - p3) ** 2 + (p3 - p1) ** 2)))


# ------------------------------------------------------------------------------------------ uniaxial
@pytest.mark.parametrize("stretch", [1.05, 1.3, 0.9])
def test_uniaxial_block_matches_closed_form(stretch):
    """A block under F = diag(λ1, λ2, λ2) (zero lateral traction): per-tet σ_vM and the end-face
    force equal the closed-form stable Neo-Hookean values (force = P₁₁ × rest area)."""
    size = (0.1, 0.02, 0.03)
    v, tets, _ = block_mesh(size, (5, 2, 2))
    vol, dm_inv, _ = rest_quantities(v, tets, 1000.0)
    mu, lam = lame(E, NU)
    l2, P11, s11 = _snh_uniaxial(stretch, mu, lam)
    x = v * np.array([stretch, l2, l2])
    m = len(tets)
    out = st.tet_stress(x, tets, dm_inv, np.full(m, mu), np.full(m, lam))
    np.testing.assert_allclose(out["von_mises"], abs(s11), rtol=1e-3)
    np.testing.assert_allclose(out["sigma"][:, 0, 0], s11, rtol=1e-3)
    assert np.max(np.abs(out["sigma"][:, 1, 1])) < 1e-6 * abs(s11)
    f = st.nodal_forces(out["P"], tets, dm_inv, vol, len(v))
    end = np.flatnonzero(np.isclose(v[:, 0], size[0]))
    vec, mag = st.force_sum(f, end)
    area = size[1] * size[2]
    assert vec[0] == pytest.approx(-P11 * area, rel=1e-3)  # the body pulls the handle back
    assert abs(vec[1]) < 1e-6 * abs(P11 * area) and abs(vec[2]) < 1e-6 * abs(P11 * area)
    assert mag == pytest.approx(abs(P11) * area, rel=1e-3)
    interior = np.setdiff1d(np.arange(len(v)), np.flatnonzero(np.isclose(v[:, 0], 0) | np.isclose(v[:, 0], size[0])))
    assert np.max(np.linalg.norm(f[interior][:, [0]], axis=1)) < 1e-6 * abs(P11 * area)


# ------------------------------------------------------------------------------------------ forces
@pytest.mark.parametrize("model", MODELS)
def test_nodal_forces_are_minus_energy_gradient(model):
    rng = np.random.default_rng(4)
    v, tets, _ = block_mesh((0.05, 0.02, 0.02), (2, 1, 1))
    vol, dm_inv, _ = rest_quantities(v, tets, 1000.0)
    m = len(tets)
    mu, lam = lame(rng.uniform(5e4, 2e5, m), rng.uniform(0.3, 0.45, m))
    x = v + 0.002 * rng.standard_normal(v.shape)
    P = st.first_piola(st.deformation_gradients(x, tets, dm_inv), mu, lam, model)
    f = st.nodal_forces(P, tets, dm_inv, vol, len(v))
    psi = jax.vmap(energy_density(model))  # Σ_e V_e Ψ(F_e), the potential nodal_forces is minus the gradient of
    energy = jax.jit(lambda y: jnp.sum(vol * psi(st.deformation_gradients(y, tets, dm_inv), mu, lam)))
    g = np.asarray(jax.grad(energy)(jnp.asarray(x)))
    np.testing.assert_allclose(f, -g, rtol=1e-9, atol=1e-9 * np.abs(g).max())
    # finite differences on a few coordinates
    h = 1e-7
    for i, d in [(0, 0), (3, 2), (len(v) - 1, 1)]:
        e = np.zeros_like(x)
        e[i, d] = h
        fd = (float(energy(jnp.asarray(x + e))) - float(energy(jnp.asarray(x - e)))) / (2 * h)
        assert f[i, d] == pytest.approx(-fd, rel=1e-5, abs=1e-6 * np.abs(f).max())
    # internal forces carry no net force, and no net torque where Ψ is rotation invariant
    assert np.abs(f.sum(0)).max() < 1e-9 * np.abs(f).max()
    if model != "linear":
        assert np.abs(np.cross(x, f).sum(0)).max() < 1e-9 * np.abs(f).max()


def test_tet_lame_from_regions_and_force_sum():
    mu, lam = st.tet_lame_from_regions(np.array([1e5, 4e5]), np.array([0.3, 0.45]), np.array([1, 0, 1]))
    m0, l0 = lame(1e5, 0.3)
    m1, l1 = lame(4e5, 0.45)
    np.testing.assert_allclose(mu, [m1, m0, m1])
    np.testing.assert_allclose(lam, [l1, l0, l1])
    f = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 3.0, 4.0]])
    vec, mag = st.force_sum(f, np.array([0, 1, 2]))
    np.testing.assert_allclose(vec, [0, 3, 4])
    assert mag == pytest.approx(7.0)
    vec, mag = st.force_sum(f, np.array([], int))
    assert mag == 0.0 and not vec.any()


# ------------------------------------------------------------------------------------------ averaging
def test_vertex_average_is_volume_weighted():
    v, tets, _ = block_mesh((0.04, 0.02, 0.02), (2, 1, 1))
    vol, _, _ = rest_quantities(v, tets, 1000.0)
    n = len(v)
    const = st.vertex_average(np.full(len(tets), 3.5), tets, vol, n)
    np.testing.assert_allclose(const, 3.5)
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 1, len(tets))
    avg = st.vertex_average(a, tets, vol, n)
    for i in (0, 7, n - 1):
        sel = np.any(tets == i, axis=1)
        assert avg[i] == pytest.approx(np.sum(a[sel] * vol[sel]) / np.sum(vol[sel]))
    # tensors average component-wise
    t = rng.standard_normal((len(tets), 3, 3))
    avg_t = st.vertex_average(t, tets, vol, n)
    assert avg_t.shape == (n, 3, 3)
    np.testing.assert_allclose(avg_t[:, 1, 2], st.vertex_average(t[:, 1, 2], tets, vol, n))
    # bounded by the min and max of the cell values
    assert avg.min() >= a.min() - 1e-12 and avg.max() <= a.max() + 1e-12


def test_stress_summary():
    s = st.stress_summary(np.array([1.0, 2.0, 3.0, 10.0]), np.array([1.0, 1.0, 1.0, 1.0]))
    assert s["max_pa"] == 10.0 and s["mean_pa"] == 4.0 and s["p50_pa"] == 2.5
