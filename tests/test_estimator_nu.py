"""The ν-information rule of the Gauss–Newton window estimator (stages.estimator: marginal_information,
weakly_informed, condition, posterior_cov) against the Gaussian identities it rests on."""
from __future__ import annotations

import numpy as np

from stages.estimator import Prior, condition, gauss_newton, marginal_information, posterior_cov, weakly_informed


def _spd(rng, k: int) -> np.ndarray:
    a = rng.normal(size=(k, k))
    return a @ a.T + 0.1 * np.eye(k)


def test_marginal_information_is_the_inverse_variance_from_the_data_with_the_others_priors():
    """I_i = 1 / [(N + P⁻¹ without row/column i)⁻¹]_ii: the variance of p_i when the data N and the others' prior
    determine it (no prior on p_i itself)."""
    rng = np.random.default_rng(0)
    for k in (1, 2, 5):
        N, Pinv = _spd(rng, k), _spd(rng, k)
        for i in range(k):
            Q = Pinv.copy()
            Q[i, :], Q[:, i] = 0.0, 0.0
            want = 1.0 / np.linalg.inv(N + Q)[i, i]
            assert np.isclose(marginal_information(N, Pinv, i), want, rtol=1e-10)


def test_weakly_informed_flags_a_column_that_trades_against_another():
    """Two unknowns observed through u and u + εv: the second is informed only through ε (it trades against the
    first); with independent columns both are informed by the data's full weight."""
    rng = np.random.default_rng(1)
    u, v = rng.normal(size=200), rng.normal(size=200)
    prior_info = np.eye(2)
    for eps, held in ((1e-3, True), (1.0, False)):
        J = np.stack([u, u + eps * v], axis=1)
        n = J.T @ J / 0.1 ** 2
        assert weakly_informed(n, prior_info, np.array([1.0, 0.01]), [1], 1.0).tolist() == [held], eps
    n = np.stack([u, u], axis=1)
    assert not weakly_informed(n.T @ n, prior_info, np.ones(2), [0, 1], 0.0).any()  # ratio 0: never held


def test_condition_is_the_gaussian_conditional():
    """Conditioning N(m, P) on p_i = v: the others' mean and covariance from the information form
    (Λ_oo⁻¹ and m_o − Λ_oo⁻¹ Λ_oi (v − m_i)); p_i keeps hold × P_ii and no correlation."""
    rng = np.random.default_rng(2)
    P, m = _spd(rng, 4), rng.normal(size=4)
    lam = np.linalg.inv(P)
    for i in range(4):
        o = [j for j in range(4) if j != i]
        c = condition(Prior(m, P), i, 0.7, hold=1e-6)
        cov_o = np.linalg.inv(lam[np.ix_(o, o)])
        assert np.allclose(c.cov[np.ix_(o, o)], cov_o, rtol=1e-9, atol=1e-12)
        assert np.allclose(c.mean[o], m[o] - cov_o @ lam[o, i] * (0.7 - m[i]), rtol=1e-9, atol=1e-12)
        assert c.mean[i] == 0.7 and np.isclose(c.cov[i, i], 1e-6 * P[i, i])
        assert np.all(c.cov[i, o] == 0.0)


def test_a_held_unknown_stays_put_and_posterior_cov_restores_its_prior_sigma():
    """A linear problem solved under the prior conditioned on p_1 = its prior mean: p_1 does not move, p_0 is the
    conditional least-squares answer; posterior_cov with the unconditioned prior is the ordinary posterior
    (JᵀJ/σ² + P⁻¹)⁻¹."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(30, 2))
    y = A @ np.array([0.3, -0.4]) + rng.normal(0, 0.05, 30)
    prior = Prior(np.zeros(2), np.diag([1.0, 0.04]))
    held = condition(prior, 1, 0.0)
    res = gauss_newton(lambda p, nj: (A @ p - y, A if nj else None), prior.mean, held, 0.05, max_iterations=5)
    assert abs(res.p[1]) < 1e-6
    want0 = (A[:, 0] @ y / 0.05 ** 2) / (A[:, 0] @ A[:, 0] / 0.05 ** 2 + 1.0)
    assert np.isclose(res.p[0], want0, rtol=1e-4)
    cov = posterior_cov(A, np.ones(30), 0.05 ** 2, prior)
    assert np.allclose(cov, np.linalg.inv(A.T @ A / 0.05 ** 2 + np.linalg.inv(prior.cov)), rtol=1e-10)


def test_a_window_that_starts_at_a_change_point_keeps_its_starting_states():
    """adapt._correction_kind: no correction of the starting states in the window that restarts at a change point
    (they are the old material's fitted states; corrected, they traded against E: +20–26 % on the demo's step);
    otherwise as --state-correction asks (states with markers, past with images or after the modes failed)."""
    from stages.steps.adapt import _correction_kind

    assert _correction_kind("states", "markers", False, False) == "states"
    assert _correction_kind("states", "markers", True, False) is None
    assert _correction_kind("states", "vision", False, False) == "past"
    assert _correction_kind("states", "markers", False, True) == "past"
    assert _correction_kind("past", "markers", False, False) == "past"
    assert _correction_kind("past", "vision", True, False) is None
    assert _correction_kind("off", "markers", False, False) is None
