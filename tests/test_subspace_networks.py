"""Subspace maps and their training (stages.subspace.networks / train): PCA and the autoencoder.

Sample-like data: a bar bent, twisted and stretched by three random amounts (large rotations, so a
linear subspace of the same size cannot hold them).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import box_tets
from stages.subspace.networks import SubspaceMap
from stages.subspace.train import fit_subspace, pca_basis, reconstruction_error


def bend_twist(rest: np.ndarray, kappa: float, tau: float, stretch: float) -> np.ndarray:
    """Stretch along x, twist τ rad/m about the bar's axis, bend with curvature κ (1/m) about y."""
    c = rest.mean(0)
    x, y, z = rest[:, 0] * (1 + stretch), rest[:, 1] - c[1], rest[:, 2] - c[2]
    a = tau * x
    y, z = y * np.cos(a) - z * np.sin(a), y * np.sin(a) + z * np.cos(a)
    th = x * kappa
    R = 1.0 / kappa
    return np.stack([(R - z) * np.sin(th), y + c[1], R - (R - z) * np.cos(th) + c[2]], -1)


@pytest.fixture(scope="module")
def bar_data():
    v, t = box_tets((12, 3, 3), (0.2, 0.05, 0.05))
    _, _, m = rest_quantities(v, t, 1000.0)
    rng = np.random.default_rng(0)
    X = np.stack([bend_twist(v, rng.choice([-1, 1]) * rng.uniform(0.5, 8), rng.uniform(-10, 10),
                             rng.uniform(-0.1, 0.1)) for _ in range(240)])
    return v, m, X[:200], X[200:]


@pytest.fixture(scope="module")
def ae3(bar_data):
    v, m, xt, xv = bar_data
    sub, info = fit_subspace("autoencoder", v, m, xt, 3, xv, epochs=120, seed=0, pca_dim=24)
    return sub, info


def test_pca_basis_is_mass_orthonormal(bar_data):
    v, m, xt, _ = bar_data
    U, sig = pca_basis(xt - v, m, 10)
    G = np.einsum("nip,n,niq->pq", U, m, U)
    assert np.allclose(G, np.eye(10), atol=1e-10)
    assert np.all(np.diff(sig) <= 1e-12)


def test_decode_encode_identities(bar_data, ae3):
    """φ(0) = rest, ψ(rest) = 0, and PCA's ψ∘φ is the identity."""
    v, m, xt, _ = bar_data
    sub, _ = ae3
    assert np.allclose(np.asarray(sub.decode(jnp.zeros(3))), v, atol=1e-14)
    assert np.allclose(np.asarray(sub.encode(jnp.asarray(v))), 0.0, atol=1e-12)
    pca, _ = fit_subspace("pca", v, m, xt, 5)
    z = np.random.default_rng(0).normal(size=5) * 0.01
    assert np.allclose(np.asarray(pca.encode(pca.decode(jnp.asarray(z)))), z, atol=1e-12)


def test_jacobian_and_row_decoding(bar_data, ae3):
    v, _, _, xv = bar_data
    sub, _ = ae3
    z = np.asarray(sub.encode(jnp.asarray(xv[0])))
    J = np.asarray(sub.jacobian(jnp.asarray(z)))
    h = 1e-6
    fd = np.stack([(np.asarray(sub.decode(jnp.asarray(z + h * e))) - np.asarray(sub.decode(jnp.asarray(z - h * e))))
                   / (2 * h) for e in np.eye(3)], -1)
    assert np.abs(fd - J).max() <= 1e-6 * np.abs(J).max()
    ids = np.array([0, 7, 50, len(v) - 1])
    assert np.allclose(np.asarray(sub.decode_rows(jnp.asarray(z), ids)), np.asarray(sub.decode(jnp.asarray(z)))[ids])


def test_autoencoder_beats_pca_at_equal_dimension(bar_data, ae3):
    v, m, xt, xv = bar_data
    sub, info = ae3
    pca, _ = fit_subspace("pca", v, m, xt, 3)
    e_ae, e_pca = reconstruction_error(sub, xv), reconstruction_error(pca, xv)
    assert e_ae < 0.5 * e_pca, (e_ae, e_pca)
    assert info["history"][-1][0] < info["history"][0][0]  # training lowered the loss


def test_weights_round_trip(bar_data, ae3):
    _, _, _, xv = bar_data
    sub, _ = ae3
    back = SubspaceMap.from_weights("autoencoder", sub.to_weights())
    x = jnp.asarray(xv[:3])
    assert np.allclose(np.asarray(back.decode(back.encode(x))), np.asarray(sub.decode(sub.encode(x))), atol=1e-14)
    assert back.dim == 3 and back.p == 24


def test_training_is_reproducible(bar_data):
    v, m, xt, xv = bar_data
    a, _ = fit_subspace("autoencoder", v, m, xt[:64], 2, epochs=3, seed=4, pca_dim=8)
    b, _ = fit_subspace("autoencoder", v, m, xt[:64], 2, epochs=3, seed=4, pca_dim=8)
    for k in a.net:
        assert np.array_equal(np.asarray(a.net[k]), np.asarray(b.net[k]))


def test_jacobian_q_matches_autodiff_for_pca(bar_data):
    v, m, xt, _ = bar_data
    pca, _ = fit_subspace("pca", v, m, xt, 4)
    assert np.array_equal(np.asarray(pca.jacobian_q(jnp.zeros(4))), np.eye(4))
    J = np.asarray(jax.jacfwd(pca.decode)(jnp.zeros(4)))
    assert np.allclose(J, pca.basis)
