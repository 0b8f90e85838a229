"""The images' anchor calibrated on the first frames (``rsl adapt --anchor-calibration K``, rule 0 of
stages/vision_anchor.py): the window grows from the first frame until K informed frames, θ is fitted to them
(stages.steps.adapt._calibrate_anchor, L-BFGS-B), and the Gaussians' anchor is held at that material from then on."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from stages.parameters import Adam
from stages.steps.adapt import AdaptConfig, _calibrate_anchor, _holds_fit, resolve_model_error
from stages.vision_anchor import AnchorMaterial
from stages.window_backends import SolveCollapsed
from test_adapt_vision_rest import DELAY, _adapt, delayed  # noqa: F401  (the module's capture fixture)
from test_vision_bias import E_TRUE


class _Quadratic:
    """A window objective stand-in: L(p) = Σ_t (p − c_t)ᵀ A (p − c_t) over the frames, dL/dp exact; a trial with
    log E beyond ``collapse`` raises SolveCollapsed, as a simulation whose elements invert does."""

    R = 1

    def __init__(self, centres: np.ndarray, collapse: float = np.inf):
        self.c, self.A, self.collapse, self.calls = centres, np.array([[2.0, 0.3], [0.3, 1.0]]), collapse, 0

    def __call__(self, frames, p, before, need_grad=True, lead=0):
        self.calls += 1
        if p[0] > self.collapse:
            raise SolveCollapsed("inverted")
        d = p[None, :] - self.c[list(frames)]
        losses = np.einsum("ti,ij,tj->t", d, self.A, d)
        return None, losses, 2.0 * (d @ self.A).sum(0), (0.1, 0.2, 0.3)


def test_the_calibration_fit_is_the_minimum_of_the_frames_loss():
    """Σ_t over frames 0..5 of a quadratic in p: the minimum is the mean of the centres, found from far off; the
    objective's times are accumulated per evaluation."""
    rng = np.random.default_rng(0)
    centres = np.array([np.log(E_TRUE), 0.2]) + 0.05 * rng.standard_normal((6, 2))
    obj, times = _Quadratic(centres), np.zeros(3)
    p = _calibrate_anchor(obj, list(range(6)), np.array([np.log(0.3 * E_TRUE), -1.0]), None, None, times)
    np.testing.assert_allclose(p, centres.mean(0), atol=1e-6)
    np.testing.assert_allclose(times, obj.calls * np.array([0.1, 0.2, 0.3]))


def test_a_recalibration_holding_poisson_fits_log_e_alone():
    """hold_poisson: ν's coordinate stays where it was, and log E goes to the minimum of the loss along log E at that
    ν: ∂L/∂p₀ = 0 ⇒ p₀ = c̄₀ − (A₀₁/A₀₀)(p₁ − c̄₁), not to the joint minimum c̄."""
    rng = np.random.default_rng(1)
    centres = np.array([np.log(E_TRUE), 0.2]) + 0.05 * rng.standard_normal((6, 2))
    obj = _Quadratic(centres)
    start = np.array([np.log(0.5 * E_TRUE), -1.0])
    p = _calibrate_anchor(obj, list(range(6)), start, None, None, np.zeros(3), hold_poisson=True)
    c = centres.mean(0)
    assert p[1] == start[1]
    assert p[0] == pytest.approx(c[0] - obj.A[0, 1] / obj.A[0, 0] * (start[1] - c[1]), abs=1e-6)
    assert abs(p[0] - c[0]) > 0.1  # the joint minimum is elsewhere: ν was held, not fitted


def test_e_is_held_at_the_fits_only_where_a_later_change_can_be_seen_and_refitted():
    """--hold-fit holds E(t) at the last fit only with --recalibrate and rule 5's threshold --anchor-change > 0:
    without either the fit would never be replaced, and E(t) stays the window's."""
    cfg = AdaptConfig(capture=Path("c"), workspace=Path("w"))
    assert _holds_fit(cfg)
    for off in ({"hold_fit": False}, {"recalibrate": False}, {"anchor_change": 0.0}):
        assert not _holds_fit(dataclasses.replace(cfg, **off)), off


def test_the_calibration_keeps_log_e_in_the_young_range_and_steps_back_from_a_collapse():
    """The minimum lies above young_range: the fit stops at its bound; trials past log E = collapse raise
    SolveCollapsed (L-BFGS-B's line search backs off) and the result is still the best p evaluated."""
    centres = np.tile([np.log(4 * E_TRUE), 0.0], (3, 1))
    p = _calibrate_anchor(_Quadratic(centres), [0, 1, 2], np.array([np.log(E_TRUE), 0.0]), None,
                          (1e3, 2 * E_TRUE), np.zeros(3))
    assert p[0] == pytest.approx(np.log(2 * E_TRUE), abs=1e-9)
    obj = _Quadratic(centres, collapse=np.log(3 * E_TRUE))
    p = _calibrate_anchor(obj, [0, 1, 2], np.array([np.log(E_TRUE), 0.0]), None, None, np.zeros(3))
    assert np.log(E_TRUE) < p[0] <= np.log(3 * E_TRUE)
    assert obj(range(3), p, None)[1].sum() < obj(range(3), np.array([np.log(E_TRUE), 0.0]), None)[1].sum()


class _Stepwise:
    """A window objective stand-in whose frames show log E = 0 before frame ``change`` and ``jump`` from it on:
    loss_t = (p₀ − c_t)² + ¼ (x_{t−1} − c_t)² with the state x_t = p₀ (the material the frame was simulated
    with), so a frame also pays, less, for a past simulated with the wrong material."""

    R = 1

    def __init__(self, change: int, jump: float = 0.7):
        self.change, self.jump = change, jump

    def c(self, t):
        return self.jump if t >= self.change else 0.0

    def __call__(self, frames, p, before, need_grad=True, lead=0):
        prev, states, losses = float(before[-1][0]), [], []
        for t in frames:
            losses.append((p[0] - self.c(t)) ** 2 + 0.25 * (prev - self.c(t)) ** 2)
            prev = float(p[0])
            states.append(np.array([prev]))
        return np.stack(states), np.array(losses), None, (0.1, 0.2, 0.3)


class _StepwiseGrad(_Stepwise):
    """_Stepwise with dL/dp exact: Σ_t 2(p₀ − c_t) + Σ_{t after the first} ½(p₀ − c_t) (each later frame's x_{t−1}
    is p₀), none along p₁."""

    def __call__(self, frames, p, before, need_grad=True, lead=0):
        states, losses, _, times = super().__call__(frames, p, before, need_grad, lead)
        c = np.array([self.c(t) for t in frames])
        g0 = 2 * np.sum(p[0] - c) + 0.5 * np.sum(p[0] - c[1:])
        return states, losses, np.array([g0, 0.0]), times


class _Loop:
    young_range = None

    def __init__(self, objective, stored):
        self.objective, self.stored = objective, stored

    def before(self, t0):
        return np.stack([self.stored[t0 - 2], self.stored[t0 - 1]])


@pytest.mark.parametrize("change", [9, 11, 13])
def test_a_later_change_is_located_at_the_frame_the_material_changed(change):
    """_locate_change: the frames up to T = 15 show log E 0 before ``change`` and 0.7 from it on; the window's p at
    T (0.5: not yet there) against the old fit (0): the split of lowest loss is the true change frame, and the
    stored states before it are re-simulated with the old material (those after it are left alone)."""
    from stages.steps.adapt import _locate_change

    stored = {t: np.array([0.3 if t >= change else 0.0]) for t in range(16)}  # a past of drifting estimates
    loop, times = _Loop(_Stepwise(change), stored), np.zeros(3)
    c = _locate_change(loop, 15, np.array([0.0, 0.0]), np.array([0.5, 0.0]), range(8, 15), times)
    assert c == change
    assert all(stored[t][0] == 0.0 for t in range(8, c)) and all(stored[t][0] == 0.3 for t in range(c, 16))
    assert times[0] > 0
    # the candidates bound the answer: a change before them is located at their first frame, after at their last
    assert _locate_change(_Loop(_Stepwise(5), dict(stored)), 15, np.zeros(2), np.array([0.5, 0.0]), range(8, 15),
                          np.zeros(3)) == 8
    assert _locate_change(_Loop(_Stepwise(15), dict(stored)), 15, np.zeros(2), np.array([0.5, 0.0]), range(8, 13),
                          np.zeros(3)) == 12


@pytest.mark.parametrize("fitted_at", [10, 11, 13, 14])
def test_a_recalibration_locates_the_change_again_with_a_fit_per_split(fitted_at):
    """_relocate_with_fits: the material changes at frame 12 (log E 0 → 0.7), the recalibration was fitted to frames
    from ``fitted_at``, off the change either way (a fit that took in frames of the old material is pulled towards
    it): each split fitted on its own finds 12, with the new material's fit, and the frames before it are stored as
    the old material's."""
    from stages.steps.adapt import _relocate_with_fits

    T, change, hold = 15, 12, True
    stored = {t: np.array([0.0 if t < min(change, fitted_at) else 0.7]) for t in range(T + 1)}
    obj = _StepwiseGrad(change)
    p_fit = _calibrate_anchor(obj, list(range(fitted_at, T + 1)), np.array([0.3, 0.0]),
                              _Loop(obj, stored).before(fitted_at), None, np.zeros(3), hold)
    cands = range(fitted_at - 2, min(fitted_at + 2, T) + 1)
    loop, times = _Loop(obj, stored), np.zeros(3)
    c, p = _relocate_with_fits(loop, T, np.zeros(2), p_fit, fitted_at, cands, hold, times)
    assert c == change
    assert p[1] == 0.0 and abs(p[0] - obj.jump) < abs(p_fit[0] - obj.jump) + 1e-12
    assert abs(p[0] - obj.jump) < 0.05
    assert all(stored[t][0] == 0.0 for t in range(cands[0], c)) and times[0] > 0


def test_a_calibrated_anchor_is_held_whatever_the_window_does():
    """Rule 0: after calibrated(p, T), held() returns p for tied and untied windows alike, the anchor takes no step
    of its own, and rule 5 still marks a later change (which limits the lead-in)."""
    rule = AnchorMaterial(np.array([np.log(0.5 * E_TRUE), 0.0]), np.array([0.15, 0.05]), 0.5, 1, 0.4, 3, 0)
    p_cal = np.array([np.log(E_TRUE), 0.1])
    rule.calibrated(p_cal, 8)
    assert rule.apart_from == 8 and rule.lead_from == 8
    np.testing.assert_array_equal(rule.held(9, True), p_cal)
    np.testing.assert_array_equal(rule.held(9, False), p_cal)
    np.testing.assert_array_equal(rule.after_step(p_cal + 1.0, np.array([5.0, 5.0]), False), p_cal)
    for T, e in enumerate([1.0] * 8 + [2.0] * 8, start=9):  # the window's E steps ×2 at frame 17
        rule.end_frame(T, np.array([np.log(e * E_TRUE), 0.1]), False, lambda F, p: 0.0)
    np.testing.assert_array_equal(rule.p, p_cal)
    assert rule.tests == [] and len(rule.later) == 1 and 17 <= rule.later[0] <= 19, rule.later


def test_rule_5_passes_over_the_quiet_frames_after_a_fit():
    """restart_watch(p, quiet): the window's log E away from the fit in the first ``quiet`` frames (a restarted
    Adam's lr-sized first steps) is no change; the same excursion later is one."""
    kick = [1.6, 1.6, 1.0, 1.0, 1.0, 1.0]  # E / fit per frame after the fit
    seen = []
    for quiet in (0, 3):
        rule = AnchorMaterial(np.array([np.log(0.5 * E_TRUE), 0.0]), np.array([0.15, 0.05]), 0.5, 1, 0.4, 3, 0)
        rule.calibrated(np.array([np.log(E_TRUE), 0.1]), 8, quiet)
        for T, e in enumerate(kick, start=9):
            rule.end_frame(T, np.array([np.log(e * E_TRUE), 0.1]), False, lambda F, p: 0.0)
        seen.append(list(rule.later))
    assert seen[0][:1] == [10] and seen[1] == [], seen  # (quiet 0: the kick, and its return to the fit)
    rule.restart_watch(np.array([np.log(E_TRUE), 0.1]), quiet=1)
    for T, e in enumerate([1.0] + kick, start=20):  # the kick after the quiet frame: seen
        rule.end_frame(T, np.array([np.log(e * E_TRUE), 0.1]), False, lambda F, p: 0.0)
    assert rule.later[:1] == [22], rule.later


def test_adam_restart_makes_the_next_step_a_first_step():
    g = np.array([3.0, -0.01])
    used = Adam(np.array([0.15, 0.05]), beta1=0.5)
    p = np.zeros(2)
    for _ in range(5):
        p = used.step(p, np.array([40.0, 2.0]))
    used.restart()
    np.testing.assert_allclose(used.step(p, g) - p, Adam(np.array([0.15, 0.05]), beta1=0.5).step(p, g) - p,
                               rtol=1e-12)
    assert used.k == 1


def test_online_adam_calibrates_the_anchor_on_the_first_moving_frames(delayed):  # noqa: F811
    """The delayed bar (frames 0..DELAY at rest, own model, 8-bit images): E does not move while at rest, the
    anchor is calibrated once K = 3 frames have moved (frame DELAY + 3), at an E within 3 % of the truth (the
    model is the capture's own), and held there: adapt.h5 records that frame and the same anchor E after it."""
    from stages.artefacts import AdaptArtefact

    cap, ws, _, _ = delayed
    E = _adapt(cap, ws, anchor_calibration=3)
    extra = AdaptArtefact.load(ws / "adapt.h5").extra
    T_c = DELAY + 3
    assert extra["anchor_apart_from"] == T_c, extra["anchor_apart_from"]
    assert np.all(E[:DELAY + 1] == E[0]), E
    anchor = np.asarray(extra["anchor_young"], float)[:, 0]
    assert anchor[T_c] == pytest.approx(E[T_c], rel=1e-12) and np.all(anchor[T_c:] == anchor[T_c]), anchor
    assert abs(anchor[T_c] / E_TRUE - 1) < 0.03, anchor[T_c] / E_TRUE



def test_a_held_calibration_fit_reports_its_sigma(delayed):  # noqa: F811
    """--hold-fit: E(t) holds the calibration's fit from its frame on, and σ with it — the Gauss–Newton (Laplace)
    covariance of that fit over its frames with the model-error floor (adapt._fit_sigma), NaN while E moves with
    Adam before it.  Own model, so the fit is within 3 % and the truth inside ±2σ; σ ≥ the floor, which adapt.h5
    records on those frames."""
    from stages.artefacts import AdaptArtefact

    cap, ws, _, _ = delayed
    E = _adapt(cap, ws, anchor_calibration=3)
    art = AdaptArtefact.load(ws / "adapt.h5")
    T_c = DELAY + 3
    s = np.asarray(art.young_sigma, float)[:, 0]
    assert np.all(np.isnan(s[:T_c])) and np.all(np.isfinite(s[T_c:])), s
    assert np.all(s[T_c:] == s[T_c]) and np.all(E[T_c:] == E[T_c]), (E, s)  # held with the fit
    floor = resolve_model_error(AdaptConfig(capture="c", workspace="w"), "vision")  # the images' default
    assert art.extra["model_error"] == floor
    assert s[T_c] >= floor * E[T_c] * (1 - 1e-9) and abs(E[T_c] - E_TRUE) <= 2 * s[T_c], (E[T_c], s[T_c])
    floors = np.asarray(art.extra["young_model_error"], float)[:, 0]
    assert np.all(np.isnan(floors[:T_c])) and np.allclose(floors[T_c:], floor)
