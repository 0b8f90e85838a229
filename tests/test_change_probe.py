"""adapt._probe_log_e (--change-probe): the window's data cost probed at log E ± step, judged by the likelihood ratio
Λ = 2 [C(p̂) − C(p)] / (σ² s²); the window's record is left as the solve left it.  On a stand-in window whose
residuals are a known function of log E."""
from __future__ import annotations

import numpy as np
import pytest

from stages.estimator import robust_cost
from stages.steps.adapt import _probe_log_e
from stages.window_backends import SolveCollapsed


class _Win:
    _traj = "the solve's trajectory"


class _Obj:
    win = _Win()


class _Obs:
    huber = None


class _Window:
    """A GNWindow stand-in: r(p) = tanh(p₀ − a) · v over 50 residuals (a data minimum at log E = a that a linear model
    at a far p₀ hardly sees: tanh saturates), p = (log E, c)."""

    _LINEARISATION = ("last_jac", "last_frames", "last_state_sens")
    _EVALUATION = ("last_states", "last_before", "last_p", "last_rs")
    R = 1

    def __init__(self, a: float, collapse_above: float = np.inf):
        self.a, self.collapse_above = a, collapse_above
        self.v = np.linspace(-1.0, 2.0, 50)
        self.obj = _Obj()
        self.young_range = (np.exp(-3.0), np.exp(3.0))
        self.calls = []
        self.prediction = None
        for name in self._LINEARISATION + self._EVALUATION:
            setattr(self, name, f"solve's {name}")

    def residuals(self, p):
        return np.tanh(p[0] - self.a) * self.v

    def evaluate(self, frames, p, before, D, need_jac, rebind=True):
        assert not need_jac and rebind is False  # probes: no Jacobian, the binding kept
        self.calls.append(np.array(p))
        if p[0] > self.collapse_above:
            raise SolveCollapsed("a probe too far")
        r = self.residuals(p)
        self.last_rs, self.last_states, self.obj.win._traj = [r], "probe states", "probe trajectory"
        return r, None


def test_the_probe_takes_the_side_the_cost_falls_to_and_its_likelihood_ratio():
    gn = _Window(a=0.6)
    p_hat = np.array([0.0, 0.3])
    gn.last_rs = [gn.residuals(p_hat)]
    sigma, scale = 0.05, 4.0
    lam, p = _probe_log_e(gn, [4, 5, 6], p_hat, None, None, sigma, _Obs(), scale, 0.5)
    assert np.allclose(p, [0.5, 0.3])  # the other unknowns at the estimate
    c_hat, c_up = robust_cost(gn.residuals(p_hat), sigma, None), robust_cost(gn.residuals(p), sigma, None)
    assert lam == pytest.approx(2 * (c_hat - c_up) / (sigma ** 2 * scale), rel=1e-12)
    assert lam > 9.0
    assert sorted(c[0] for c in gn.calls) == [-0.5, 0.5]
    # the window's record and the remembered trajectory as the solve left them
    assert gn.last_rs is not None and gn.last_states == "solve's last_states" and gn.last_jac == "solve's last_jac"
    assert gn.obj.win._traj == "the solve's trajectory"


def test_a_probe_at_the_minimum_finds_nothing_and_a_collapsed_or_bounded_probe_is_skipped():
    gn = _Window(a=0.0)
    p_hat = np.array([0.0])
    gn.last_rs = [gn.residuals(p_hat)]
    lam, p = _probe_log_e(gn, [4, 5], p_hat, None, None, 0.05, _Obs(), 1.0, 0.5)
    assert lam < 0 and p is not None
    gn = _Window(a=2.0, collapse_above=1.0)
    p_hat = np.array([0.8])
    gn.last_rs = [gn.residuals(p_hat)]
    lam, p = _probe_log_e(gn, [4, 5], p_hat, None, None, 0.05, _Obs(), 1.0, 0.5)  # + collapses: − remains
    assert np.allclose(p, [0.3]) and lam < 0
    gn = _Window(a=0.0)
    gn.young_range = (np.exp(-3.0), np.exp(2.9))
    p_hat = np.array([2.8])  # + would cross the range: only − is probed
    gn.last_rs = [gn.residuals(p_hat)]
    lam, p = _probe_log_e(gn, [4, 5], p_hat, None, None, 0.05, _Obs(), 1.0, 0.5)
    assert [c[0] for c in gn.calls] == [pytest.approx(2.3)] and lam > 0
