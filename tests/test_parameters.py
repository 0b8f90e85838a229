"""stages/parameters.py: the θ ↔ p maps and their Jacobian (against finite differences), and the optax Adam
held to the plain formula it replaced (a slow obvious twin written out below)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.parameters import Adam, chain_params, params_from_theta, theta_from_params, theta_jacobian

RANGE = (0.3, 0.49)


class PlainAdam:
    """The hand-written Adam that stages/adapt_loss.py held before optax: m ← β₁m + (1−β₁)g,
    v ← β₂v + (1−β₂)g², p ← p − lr · m̂ / (√v̂ + ε), ε = eps · max √v̂ + 1e-300."""

    def __init__(self, lr, beta1=0.9, beta2=0.999, eps=1e-6):
        self.lr, self.b1, self.b2, self.eps = lr, beta1, beta2, eps
        self.m = self.v = None
        self.k = 0

    def step(self, p, g):
        if self.m is None:
            self.m, self.v = np.zeros_like(g), np.zeros_like(g)
        self.k += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        mh = self.m / (1 - self.b1 ** self.k)
        vh = self.v / (1 - self.b2 ** self.k)
        eps = self.eps * float(np.sqrt(np.max(vh, initial=0.0))) + 1e-300
        return p - self.lr * mh / (np.sqrt(vh) + eps)


def test_parameter_maps_round_trip():
    E, nu = np.array([1e4, 3e5, 2.5e6]), np.array([0.31, 0.45, 0.4])
    le, s = params_from_theta(E, nu, RANGE)
    E2, nu2 = theta_from_params(le, s, RANGE)
    np.testing.assert_allclose(E2, E, rtol=1e-13)
    np.testing.assert_allclose(nu2, nu, rtol=1e-12)
    # per-region ranges, one of them closed (ν held): s = 0 there and ν comes back exactly
    lo, hi = np.array([0.3, 0.4, 0.2]), np.array([0.49, 0.4, 0.45])
    le, s = params_from_theta(E, nu, (lo, hi))
    assert s[1] == 0.0
    np.testing.assert_allclose(theta_from_params(le, s, (lo, hi))[1], [0.31, 0.4, 0.4], rtol=1e-12)
    # ν outside the range is clipped strictly inside it (finite s)
    _, s = params_from_theta(E[:2], np.array([0.2, 0.6]), RANGE)
    assert np.all(np.isfinite(s))
    nu_c = theta_from_params(np.zeros(2), s, RANGE)[1]
    assert np.all((nu_c > RANGE[0]) & (nu_c < RANGE[1]))


def test_jacobian_matches_finite_differences():
    le, s = np.log(np.array([2e4, 7e5])), np.array([-1.3, 0.8])
    dE, dnu = theta_jacobian(np.exp(le), s, RANGE)
    h = 1e-6
    fd_E = (theta_from_params(le + h, s, RANGE)[0] - theta_from_params(le - h, s, RANGE)[0]) / (2 * h)
    fd_nu = (theta_from_params(le, s + h, RANGE)[1] - theta_from_params(le, s - h, RANGE)[1]) / (2 * h)
    np.testing.assert_allclose(dE, fd_E, rtol=1e-8)
    np.testing.assert_allclose(dnu, fd_nu, rtol=1e-8)


def test_chain_rule_against_finite_differences():
    E, nu = np.array([1e4, 3e5]), np.array([0.31, 0.45])
    le, s = params_from_theta(E, nu, RANGE)
    # L(E, ν) = a E + b ν² ; check dL/dp against finite differences in p
    a, bcoef = np.array([2e-5, -1e-6]), np.array([3.0, 1.0])

    def L(p):
        Ep, nup = theta_from_params(p[:2], p[2:], RANGE)
        return float(np.sum(a * Ep + bcoef * nup ** 2))

    p = np.concatenate([le, s])
    g = np.concatenate(chain_params(a, 2 * bcoef * nu, E, s, RANGE))
    h = 1e-6
    fd = [(L(p + h * e) - L(p - h * e)) / (2 * h) for e in np.eye(4)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)


@pytest.mark.parametrize("lr, beta1", [(0.1, 0.9), (np.array([0.05, 0.2, 0.0]), 0.5)])
def test_optax_adam_follows_the_plain_formula(lr, beta1):
    """On f(p) = ½ Σ c_i (p_i − t_i)² with very different curvatures: the same trajectory as the formula."""
    c, t = np.array([4.0, 1e-3, 2.0]), np.array([1.0, -2.0, 0.5])
    fast, slow = Adam(lr, beta1=beta1), PlainAdam(lr, beta1=beta1)
    p_fast = p_slow = np.array([3.0, 1.0, -1.0])
    for _ in range(200):
        p_fast = fast.step(p_fast, c * (p_fast - t))
        p_slow = slow.step(p_slow, c * (p_slow - t))
        np.testing.assert_allclose(p_fast, p_slow, rtol=1e-12, atol=1e-12)
    assert fast.k == slow.k == 200
    assert isinstance(p_fast, np.ndarray) and p_fast.dtype == np.float64
    moved = np.atleast_1d(lr) * np.ones(3) > 0
    assert np.all(np.abs(p_fast - t)[moved] < np.abs(np.array([3.0, 1.0, -1.0]) - t)[moved])


def test_adam_minimises_a_quadratic_and_ignores_round_off_components():
    opt = Adam(np.array([0.1, 0.1]))
    p = np.array([3.0, 1.0])
    for _ in range(300):
        g = np.array([2 * (p[0] - 1.0), 1e-14 * np.sign(np.sin(p[0] * 1e3))])
        p = opt.step(p, g)
    assert abs(p[0] - 1.0) < 0.05
    assert abs(p[1] - 1.0) < 1e-3  # a round-off gradient does not move the second component


def test_adam_with_zero_gradients_stays_put():
    opt = Adam(np.array([0.1, 0.0]))
    p = np.array([0.7, 0.2])
    for _ in range(3):
        p = opt.step(p, np.zeros(2))
    np.testing.assert_array_equal(p, [0.7, 0.2])
