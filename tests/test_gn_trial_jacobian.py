"""The gn estimator's per-frame work outside the window's simulation and renders, held to the slow twins: a trial
step evaluated with its Jacobian ahead (GNWindow.trial_jacobian), Jᵀ W r from an exact J over its non-zero rows
(estimator.gauss_newton) and the Huber weights in fewer passes."""
from __future__ import annotations

import numpy as np
import pytest

from stages.estimator import Prior, _huber_weights_where, gauss_newton, huber_weights
from test_adapt_e2e import E_TRUE
from test_gn_speed import _online, beam_step  # noqa: F401  (the module-scoped capture fixture)


def test_huber_weights_are_the_branch_formula():
    """min(1, δσ/max(|r|, 1e-300)) in place: the floats of where(|r| ≤ δσ, 1, δσ/max(|r|, 1e-300)), at 0, ±0, at and
    next to δσ, subnormal and infinite residuals, NaN; and σ = 0."""
    rng = np.random.default_rng(3)
    c = 1.345 * 0.05
    special = np.array([0.0, -0.0, c, -c, np.nextafter(c, 0), np.nextafter(c, 1), 1e-310, 5e-324, np.inf, -np.inf,
                        np.nan, 1e300])
    r = np.concatenate([0.05 * rng.standard_t(2, 20000), special, 1e-300 * rng.normal(size=100)])
    for sigma in (0.05, 1e-3, 0.0):
        np.testing.assert_array_equal(huber_weights(r, sigma, 1.345), _huber_weights_where(r, sigma, 1.345))
    np.testing.assert_array_equal(huber_weights(r, 0.05, None), np.ones_like(r))


def test_gauss_newton_forms_the_exact_jacobians_product_as_calling_it_would():
    """An evaluation returning (r, J), J exact: gauss_newton forms Jᵀ W r from J's non-zero rows itself — the
    estimate of an evaluation that hands it the product over every row as a callable, to rounding."""
    rng = np.random.default_rng(4)
    m, k = 4000, 3
    A = rng.normal(size=(m, k))
    A[rng.uniform(size=m) < 0.6] = 0.0
    y = A @ np.array([0.5, -1.0, 2.0]) + 0.1 * rng.standard_t(2, size=m)
    prior = Prior(np.zeros(k), 4.0 * np.eye(k))

    def plain(p, nj):
        return (A @ p - y, A if nj else None)

    def called(p, nj):  # the same product as an opaque callable: gauss_newton calls it
        return (A @ p - y, A, lambda W: A.T @ (W * (A @ p - y))) if nj else (A @ p - y, None)

    kw = dict(max_iterations=3, huber=1.345, clusters=np.repeat(np.arange(m // 10), 10))
    a, c = (gauss_newton(f, np.zeros(k), prior, 0.1, **kw) for f in (plain, called))
    np.testing.assert_allclose(c.p, a.p, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("trust", [0.0, None])
def test_online_gn_evaluating_trial_steps_ahead_is_the_twin(beam_step, tmp_path, monkeypatch, trust):  # noqa: F811
    """GNWindow.trial_jacobian (images, 2 iterations per frame): the first iteration's trial step evaluated with the
    Jacobian, which the accepted step's linearisation then takes, against the trial rendered alone and the
    linearisation made again — the same estimates and σ (the same floats: the forward-mode pass gives the render's
    residuals, and the window at the trial is the one the linearisation would simulate); one window render fewer
    per accepted trial (the beam with a step of E ×2 at frame 12, 30 Gaussians, from 0.5 E; --gn-trust 0: the last
    iteration's trial too, rendered alone, as is every trial of a solve's last iteration)."""
    from stages.observations import VisionObservation
    from stages.windows import GNWindow
    from test_adapt_e2e import _image_workspace

    cap, ws = beam_step
    ws2 = _image_workspace(ws, tmp_path / "ws")
    out = {}
    orig_res, orig_jac = VisionObservation.residuals, VisionObservation.residuals_and_jacobian
    for ahead in (False, True):
        calls = {"residuals": 0, "jacobian": 0}

        def residuals(self, frames, X):
            calls["residuals"] += 1
            return orig_res(self, frames, X)

        def residuals_and_jacobian(self, *a, **k):
            calls["jacobian"] += 1
            return orig_jac(self, *a, **k)

        monkeypatch.setattr(VisionObservation, "residuals", residuals)
        monkeypatch.setattr(VisionObservation, "residuals_and_jacobian", residuals_and_jacobian)
        monkeypatch.setattr(GNWindow, "trial_jacobian", ahead)
        y, s, _ = _online(cap, ws2, trust, "vision", "0:10", monkeypatch, memo=True, young_init=0.5 * E_TRUE,
                          substeps=1, iters_per_frame=2)
        out[ahead] = (y, s, dict(calls))
    (y0, s0, c0), (y1, s1, c1) = out[False], out[True]
    np.testing.assert_array_equal(y1, y0)
    np.testing.assert_array_equal(s1, s0)
    assert c1["residuals"] < c0["residuals"], (c0, c1)  # trials rendered within the linearising pass instead
    # each trial evaluated ahead is one Jacobian pass more only when it is rejected (then wasted)
    assert c1["jacobian"] - c0["jacobian"] <= c0["residuals"] - c1["residuals"], (c0, c1)
