"""Gauss–Newton on images (issue 12/13): the arrival cost of a window whose starting states are corrected along
the past's θ-sensitivities.  The fold integrates the window's state correction out (estimator.fold's nuisance),
and the arrival cost's variance of log E is matched to windows whose data contradict it
(estimator.matched_arrival); both against their Gaussian closed forms, and end to end from 0.5 E_true."""
from __future__ import annotations

import numpy as np
import pytest

from stages.estimator import ChangeDetector, Prior, fold, marginal, marginal_information, matched_arrival


def _joint_marginal(prior, p_lin, r, J, sigma, W, c_prior):
    """The θ-marginal of the joint Gaussian posterior of (θ, c) (the slow twin): prior N(m, P) × N(m_c, P_c) and
    the linear observation r(u) = r + J (u − u_lin) with weights W / σ², in covariance form."""
    k = len(prior.mean)
    m0 = np.concatenate([prior.mean, c_prior.mean])
    P0 = np.block([[prior.cov, np.zeros((k, len(c_prior.mean)))],
                   [np.zeros((len(c_prior.mean), k)), c_prior.cov]])
    y = J @ p_lin - r  # J u = y + noise
    S = J @ P0 @ J.T + np.diag(sigma ** 2 / W)
    G = P0 @ J.T @ np.linalg.inv(S)
    mean = m0 + G @ (y - J @ m0)
    cov = (np.eye(len(m0)) - G @ J) @ P0
    return mean[:k], cov[:k, :k]


def test_fold_with_the_correction_integrated_out_is_the_marginal_of_the_joint_posterior():
    rng = np.random.default_rng(0)
    k, kc, m = 2, 3, 9
    prior = Prior(np.array([0.3, -0.2]), np.array([[0.5, 0.1], [0.1, 0.8]]))
    c_prior = Prior(np.zeros(kc), np.diag([0.25, 0.5, 1.0]))
    J = rng.normal(size=(m, k + kc))
    J[:, 2] = J[:, 0] + 0.01 * rng.normal(size=m)  # a correction nearly collinear with θ₀ (the "past" one)
    u_lin = rng.normal(size=k + kc)
    r, W, sigma = rng.normal(size=m), rng.uniform(0.3, 1.0, m), 0.2
    post = fold(prior, u_lin[:k], r, J[:, :k], sigma, W, (J[:, k:], u_lin[k:], c_prior))
    mean, cov = _joint_marginal(prior, u_lin, r, J, sigma, W, c_prior)
    assert np.allclose(post.mean, mean, rtol=1e-9, atol=1e-12)
    assert np.allclose(post.cov, cov, rtol=1e-9, atol=1e-12)
    # taking the correction as known instead claims θ₀ to a far smaller variance than the data give
    known = fold(prior, u_lin[:k], r + J[:, k:] @ (np.zeros(kc) - u_lin[k:]), J[:, :k], sigma, W)
    assert known.cov[0, 0] < 0.1 * post.cov[0, 0]


def test_fold_without_a_nuisance_is_unchanged_by_an_empty_one():
    rng = np.random.default_rng(1)
    prior = Prior(np.array([0.1, 0.2]), np.array([[2.0, 0.3], [0.3, 1.0]]))
    J, r = rng.normal(size=(4, 2)), rng.normal(size=4)
    a = fold(prior, np.array([0.5, -0.1]), r, J, 0.5)
    b = fold(prior, np.array([0.5, -0.1]), r, J, 0.5, None, (np.zeros((4, 0)), np.zeros(0), Prior(np.zeros(0),
                                                                                                   np.zeros((0, 0)))))
    assert np.allclose(a.mean, b.mean, rtol=0, atol=1e-14) and np.allclose(a.cov, b.cov, rtol=0, atol=1e-14)


def _window_posterior(arrival, n_data, theta_d):
    """The window's estimate of a linear-Gaussian problem: data N(θ_d, n_data⁻¹) under the arrival cost."""
    info = np.linalg.inv(arrival.cov) + n_data
    return np.linalg.solve(info, np.linalg.inv(arrival.cov) @ arrival.mean + n_data @ theta_d)


def test_matched_arrival_recovers_where_the_data_alone_lie_and_raises_only_an_inconsistent_variance():
    """Two unknowns (log E, s) with correlated data: d = |θ_d − m| / √(P + V) for log E from the window's posterior
    alone; a consistent arrival cost is kept, an inconsistent one gets P = (θ_d − m)² − V, so its d is 1."""
    arrival = Prior(np.array([np.log(0.5), 0.2]), np.array([[4e-4, 1e-5], [1e-5, 0.04]]))
    n_data = np.array([[2.0e4, 3.0e3], [3.0e3, 1.0e3]])
    V = 1.0 / marginal_information(n_data, np.linalg.inv(arrival.cov), 0)
    for gap, moves in ((0.02, False), (0.7, True)):
        theta_d = arrival.mean + np.array([gap, 0.0])
        p = _window_posterior(arrival, n_data, theta_d)
        out, d = matched_arrival(arrival, p, n_data, np.linalg.inv(arrival.cov), [0], 3.0)
        # (the marginal data information on log E with s estimated too: the 1-D formula holds to first order)
        assert d[0] == pytest.approx(abs(gap) / np.sqrt(arrival.cov[0, 0] + V), rel=0.05)
        assert np.array_equal(out.mean, arrival.mean)
        if moves:
            assert out.cov[0, 0] == pytest.approx(gap ** 2 - V, rel=0.1)
            assert out.cov[1, 1] == arrival.cov[1, 1]
            corr = lambda c: c[0, 1] / np.sqrt(c[0, 0] * c[1, 1])  # noqa: E731
            assert corr(out.cov) == pytest.approx(corr(arrival.cov), rel=1e-12)
            p2 = _window_posterior(out, n_data, theta_d)
            _, d2 = matched_arrival(out, p2, n_data, np.linalg.inv(out.cov), [0], 3.0)
            assert d2[0] < 1.1
        else:
            assert np.array_equal(out.cov, arrival.cov)


def test_matched_arrival_leaves_an_unknown_the_data_do_not_inform():
    """A window at rest (the data say nothing of log E: information 1e-20) with p off m by round-off: θ_d would be
    that round-off × V/P; the arrival cost is kept."""
    arrival = Prior(np.array([np.log(0.5)]), np.array([[1.0]]))
    n_data = np.array([[1e-20]])
    out, d = matched_arrival(arrival, arrival.mean + 1e-12, n_data, np.linalg.inv(arrival.cov), [0], 3.0)
    assert np.array_equal(out.cov, arrival.cov) and d[0] == 0.0


def test_relative_change_test_waits_for_a_baseline_and_judges_z_against_it():
    """Images' innovations from a far start (bar, 0.5 E_true: z = 36.5, 52.8, 58.7, … then falling as E converges):
    the absolute test declares a change at the first frame, the relative one none; a later jump to 10× the baseline
    is declared by both."""
    far_start = [36.5, 52.8, 58.7, 64.8, 48.9, 33.1, 21.8, 17.0, 12.9, 10.9]
    absolute, relative = ChangeDetector(3.0), ChangeDetector(3.0, relative=True)
    assert absolute.update(far_start[0])
    assert not any(relative.update(z) for z in far_start)
    assert relative.update(10 * relative.baseline())


def test_a_marginal_of_a_prior_is_its_block():
    prior = Prior(np.arange(4.0), np.diag([1.0, 2.0, 3.0, 4.0]))
    assert np.array_equal(marginal(prior, np.arange(2, 4)).cov, np.diag([3.0, 4.0]))


def test_gn_on_images_from_half_the_modulus_reaches_it(tmp_path, rsl):
    """rsl adapt --estimator gn --loss vision on the cable-pulled beam (1 camera, 40², Gaussians fitted by
    fit-gaussians, full space, the capture's own one step per frame), from 0.5 E_true: E within 10 % over frames 5–9
    and within 20 % to the end (the failure this guards against left E at 0.5–0.7 E_true).  After frame 9 the
    estimate drifts low, by a different amount on each machine (under 5 % where this test was written, 7.6 % and
    12.9 % by frame 15 on two others), although each 3-frame window's image loss given the true past is lowest
    within 2 % of E_true on frames 5–15 (rsl evaluate --sweep --sweep-past truth, accuracy_notes.md, thirty-second
    stop): the drift comes from the images' default state correction (along the past's θ-sensitivities), and
    without it (--state-correction off) E holds where the frames 1–5 put it: 0.98–1.01 E_true on one machine, 1.04–1.08
    on another, where the default drifted only to 0.95 (the one 40² camera's Gaussian fit differs between machines;
    thirty-third stop); within 10 % on both.  That correction stays the default: on three cameras' bar filmed
    mid-motion it reads 3.3 % where off reads 9.4 %.  (Before the fold integrated the "past" correction
    out and the images' change test was relative, the arrival cost took one frame's data as var(log E) → 0 far from
    the truth, or a false change held the anchor there.)  The run warns that its images come from one camera; its
    change probes find nothing and change nothing."""
    from stages.artefacts import AdaptArtefact
    from stages.steps import fit_gaussians
    from test_adapt_e2e import E_TRUE, _make_capture

    cap, ws = _make_capture(tmp_path, frames=16, cameras=1, resolution=40)
    fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=ws, iterations=80, gaussians=800))
    args = ("adapt", cap, "-w", ws, "--space", "full", "--loss", "vision", "--window", "3", "--estimator", "gn",
            "--young-init", str(E_TRUE / 2), "--substeps", "1")
    proc = rsl(*args)
    assert proc.returncode == 0, proc.stderr
    art = AdaptArtefact.load(ws / "adapt.h5")
    ratio = art.young[:, 0] / E_TRUE
    assert np.all(np.abs(ratio[5:10] - 1) < 0.10) and np.all(np.abs(ratio[10:] - 1) < 0.20), ratio
    # one camera's images: the run says how much less they measure (docs/results/accuracy_one_camera/)
    assert "the images come from one camera (cam0)" in " ".join(proc.stderr.split())
    # the change probes (--change-probe, the default 0.5) saw no change here, and leave the window's record as the
    # solve left it: without them the same estimates come out
    assert not art.extra["material_changes_detected"]
    assert max(v for v in art.extra["probe_ratio"] if v is not None) < 0.0
    proc = rsl(*args, "--change-probe", "0")
    assert proc.returncode == 0, proc.stderr
    assert np.allclose(AdaptArtefact.load(ws / "adapt.h5").young, art.young, rtol=1e-6, atol=0)
    # without the state correction the estimate holds to the end (within this capture's fit bias)
    proc = rsl(*args, "--state-correction", "off")
    assert proc.returncode == 0, proc.stderr
    off = AdaptArtefact.load(ws / "adapt.h5").young[:, 0] / E_TRUE
    assert np.all(np.abs(off[5:] - 1) < 0.10) and np.ptp(off[5:]) < 0.05, off


def test_gn_on_images_follows_a_step_the_linear_model_misses(tmp_path, rsl):
    """The cable-pulled beam (2 cameras at 64², full space, one step per frame) with E ×2 at frame 12, gn on images
    from 0.5 E_true.  The image Jacobian's linear model puts each window's minimum a few per cent from the old E, so
    without the probes (--change-probe 0) no change is seen and E stays near half the new truth; with them
    (the default) a probe at log E + 0.5 explains a window after the step better by a likelihood ratio above
    --change-threshold², a change is declared within w + 1 frames of the step, and E after it sits at the same
    ratio to the truth as before it (this capture's own bias, one Gaussians fit)."""
    from stages.artefacts import AdaptArtefact
    from stages.capture import load_capture, read_truth
    from stages.steps import fit_gaussians
    from test_adapt_e2e import E_TRUE, _make_capture

    cap, ws = _make_capture(tmp_path, frames=24, cameras=2, resolution=64,
                            young_schedule=f"{E_TRUE:g}@0,{2 * E_TRUE:g}@12")
    fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=ws, iterations=80, gaussians=800))
    truth = read_truth(load_capture(cap)).young[:, 0]
    ratio = {}
    for probe in ("0.5", "0"):
        proc = rsl("adapt", cap, "-w", ws, "--space", "full", "--loss", "vision", "--window", "3", "--estimator",
                   "gn", "--young-init", str(E_TRUE / 2), "--substeps", "1", "--change-probe", probe)
        assert proc.returncode == 0, proc.stderr
        art = AdaptArtefact.load(ws / "adapt.h5")
        ratio[probe] = art.young[:, 0] / truth[np.asarray(art.frames)]
        changes = art.extra["material_changes_detected"]
        probed = [v for v in art.extra["probe_ratio"] if v is not None]
        if probe == "0":
            assert not probed
            continue
        assert len(changes) == 1 and 12 <= changes[0] <= 12 + 3 + 1, (changes, art.extra["probe_ratio"])
        assert max(probed) > 9.0
    before = np.median(ratio["0.5"][6:12])
    assert abs(np.median(ratio["0.5"][18:]) - before) < 0.15, ratio["0.5"]
    assert np.median(ratio["0"][18:]) < before - 0.25, ratio["0"]  # the linear model alone stays behind
