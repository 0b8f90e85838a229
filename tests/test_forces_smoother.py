"""The fixed-interval smoother of θ(t) the force replay can use (stages.forces: rts_smooth, walk_variances, rts_theta,
replay_theta "smoothed"): the Rauch–Tung–Striebel recursion against the batch Gaussian posterior of a random walk,
and the random walk adapt's gn filter assumed (process noise only when a full window folds a frame, change_sigma at
a detected change)."""
from __future__ import annotations

import numpy as np
import pytest


def _kalman(y: np.ndarray, r: np.ndarray, m0: float, p0: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Filtered means and variances of x_{t+1} = x_t + w_t (var q[t]), y_t = x_t + v_t (var r[t]), x_0 ~ N(m0, p0)."""
    m, P = [], []
    mp, pp = m0, p0
    for t in range(len(y)):
        k = pp / (pp + r[t])
        mt, pt = mp + k * (y[t] - mp), (1 - k) * pp
        m.append(mt)
        P.append(pt)
        if t < len(y) - 1:
            mp, pp = mt, pt + q[t]
    return np.array(m), np.array(P)


def _batch(y: np.ndarray, r: np.ndarray, m0: float, p0: float, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The posterior of (x_0 … x_{T−1}) given every y, directly: the joint Gaussian's precision matrix Λ (from
    prior(x_0) + Σ_t (x_{t+1} − x_t)²/q_t + Σ_t (x_t − y_t)²/r_t), mean Λ⁻¹ b, marginal variances
    diag Λ⁻¹."""
    T = len(y)
    L = np.zeros((T, T))
    b = np.zeros(T)
    L[0, 0] += 1 / p0
    b[0] += m0 / p0
    for t in range(T - 1):
        d = np.zeros(T)
        d[t], d[t + 1] = -1.0, 1.0
        L += np.outer(d, d) / q[t]
    L += np.diag(1 / r)
    b += y / r
    cov = np.linalg.inv(L)
    return cov @ b, np.diag(cov)


@pytest.mark.parametrize("T", [2, 3])
def test_rts_equals_the_batch_posterior_of_a_random_walk(T):
    from stages.forces import rts_smooth

    rng = np.random.default_rng(T)
    y = rng.normal(size=T)
    r = rng.uniform(0.2, 2.0, T)
    q = rng.uniform(0.05, 1.0, T - 1)
    m, P = _kalman(y, r, 0.3, 1.5, q)
    xs, Ps = rts_smooth(m, P, q)
    want, want_var = _batch(y, r, 0.3, 1.5, q)
    np.testing.assert_allclose(xs, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(Ps, want_var, rtol=0, atol=1e-12)
    assert xs[-1] == m[-1] and Ps[-1] == P[-1]  # the last frame's filter estimate has seen every frame


def test_rts_limits_and_its_linearity_in_the_means():
    """No walk (q = 0): every frame takes the last estimate (a constant's posterior given all frames); an unbounded
    walk (q → ∞) or a filter certain of a frame (P = 0) keeps the filter's estimate.  The recursion is linear in
    the means: shifting the estimates of frames ≥ c by δ shifts frame t < c by δ Π_{j=t}^{c−1} C_j,
    C_j = P_j/(P_j + q_j) — how far the smoother carries a later estimate back."""
    from stages.forces import rts_smooth

    m = np.array([0.1, 0.4, -0.2, 0.3, 0.25])
    P = np.array([0.5, 0.2, 0.1, 0.05, 0.04])
    xs, Ps = rts_smooth(m, P, np.zeros(4))
    np.testing.assert_allclose(xs, m[-1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(Ps, P[-1], rtol=0, atol=1e-15)
    xs, _ = rts_smooth(m, P, np.full(4, 1e30))
    np.testing.assert_allclose(xs, m, rtol=0, atol=1e-12)
    xs, _ = rts_smooth(m, np.array([0.5, 0.0, 0.1, 0.0, 0.04]), np.zeros(4))
    np.testing.assert_allclose(xs[[1, 3]], m[[1, 3]], rtol=0, atol=0)
    q = np.array([0.01, 0.3, 0.02, 0.1])
    base, _ = rts_smooth(m, P, q)
    c, delta = 3, 0.7
    moved, _ = rts_smooth(m + delta * (np.arange(5) >= c), P, q)
    gain = P[:4] / (P[:4] + q)
    for t in range(c):
        np.testing.assert_allclose(moved[t] - base[t], delta * np.prod(gain[t:c]), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(moved[c:] - base[c:], delta, rtol=1e-12)
    with pytest.raises(ValueError, match="T − 1"):
        rts_smooth(m, P, q[:3])


def _model(**kw):
    from stages.forces import FilterModel

    base = dict(window=3, process_noise=0.005, process_noise_change=0.02, change_sigma=0.5, model_error=0.02,
                model_error_poisson=0.02, poisson_range=(0.3, 0.49))
    return FilterModel(**{**base, **kw})


def test_walk_variances_follow_the_filters_windows():
    """adapt._online_gn: frames 0, 1, 2 share one window's θ (no walk until the window of 3 is full at frame 2); from
    then on q² per frame (process_noise, process_noise_change during w + 5 frames after a change); a change at 6
    adds change_sigma² to log E between frames 5 and 6, and the window restarts (6, 7 share θ, full at 8)."""
    from stages.forces import walk_variances

    qe, qs = walk_variances(np.arange(16), [6], _model())
    settled, after = 0.005 ** 2, 0.02 ** 2
    want_s = [0, 0, settled, settled, settled, settled, 0, 0] + [after] * 6 + [settled]
    np.testing.assert_allclose(qs, want_s, rtol=1e-12)  # frame 8 + 6 = 14 is w + 5 = 8 frames after the change
    want_e = np.array(want_s)
    want_e[5] += 0.25
    np.testing.assert_allclose(qe, want_e, rtol=1e-12)
    qe, _ = walk_variances(np.arange(5), [], _model(window=1, process_noise=0.1))
    np.testing.assert_allclose(qe, 0.01, rtol=1e-12)


def test_filter_model_from_the_adapt_config():
    from stages.forces import filter_model

    cfg = {"window": 3, "process_noise": 0.005, "process_noise_change": 0.02, "change_sigma": 0.5,
           "model_error": 0.02, "model_error_poisson": 0.01}
    assert filter_model(cfg, (0.3, 0.49)) == _model(model_error_poisson=0.01)
    old = {k: v for k, v in cfg.items() if k != "process_noise_change"}  # one σ for every frame then
    assert filter_model(old, (0.3, 0.49)).process_noise_change == 0.005
    assert filter_model({k: v for k, v in cfg.items() if k != "window"}, (0.3, 0.49)) is None
    assert filter_model(None, (0.3, 0.49)) is None
    # options left at their defaults (None in the config): the values that ran, from adapt.h5's extras
    defaults = {**cfg, "process_noise": None, "model_error": None}
    assert filter_model(defaults, (0.3, 0.49)) is None
    ran = filter_model(defaults, (0.3, 0.49), {"process_noise": 0.005, "model_error": 0.08})
    assert ran == _model(model_error_poisson=0.01, model_error=0.08)


def test_rts_theta_smooths_log_e_within_the_filters_model():
    """A start transient (frames 0–2 share the first window's θ; the filter is unsure early) is replaced by the
    settled estimate, a detected change keeps the frames before it (gain ≈ 0 with change_sigma = 0.5), and the
    model-error floor is taken out of σ: a σ at the floor is an estimate the filter is certain of (kept).  ν at its
    floor σ (held) keeps its recorded values."""
    from stages.forces import rts_theta, walk_variances

    T = 12
    young = 1e5 * np.array([0.5, 0.7, 0.9, 1.0, 1.01, 0.99, 1.0, 2.0, 2.02, 1.98, 2.0, 2.01])[:, None]
    rel = np.array([0.5, 0.2, 0.1, 0.03, 0.025, 0.025, 0.025, 0.1, 0.05, 0.03, 0.025, 0.025])
    nu = np.full((T, 1), 0.45)
    y, p = rts_theta(young, young * rel[:, None], nu, np.full((T, 1), 0.02), np.arange(T), [7], _model())
    np.testing.assert_allclose(p, nu, rtol=0, atol=1e-14)
    e = y[:, 0] / 1e5
    assert np.all(np.abs(e[:7] - 1.0) < 0.03), e  # the start transient is gone, the post-change material not carried
    assert np.all(np.abs(e[7:] - 2.0) < 0.04), e
    # the formula itself: var = σ² − e² in log E, the walk of walk_variances
    from stages.forces import rts_smooth

    qe, _ = walk_variances(np.arange(T), [7], _model())
    want, _ = rts_smooth(np.log(young[:, 0]), np.maximum(rel ** 2 - 0.02 ** 2, 0), qe)
    np.testing.assert_allclose(np.log(y[:, 0]), want, rtol=0, atol=1e-12)


def test_replay_theta_smoothed_and_its_fallbacks():
    from stages.forces import replay_theta, rts_theta

    young = 1e5 * np.array([[0.5], [0.9], [1.0], [1.0], [1.02]])
    sy = young * np.array([[0.3], [0.1], [0.03], [0.03], [0.03]])
    nu, snu = np.full((5, 1), 0.45), np.full((5, 1), 0.02)
    extra = {"estimator": "gn", "material_changes_detected": []}
    y, p, how = replay_theta(young, nu, extra, "smoothed", sy, snu, _model())
    want = rts_theta(young, sy, nu, snu, np.arange(5), [], _model())
    np.testing.assert_array_equal(y, want[0])
    assert "Rauch–Tung–Striebel" in how
    for args in ((None, None, _model()), (sy, snu, None)):  # σ or the filter's settings unknown
        y, _, how = replay_theta(young, nu, extra, "smoothed", *args)
        np.testing.assert_array_equal(y, young)
        assert "not smoothed" in how
    y, _, how = replay_theta(young, nu, {"estimator": "adam"}, "smoothed", sy, snu, _model())
    np.testing.assert_array_equal(y, young)
    assert "not smoothed" in how


def test_rts_theta_takes_out_each_regions_own_floor():
    """adapt.h5's extra 'young_model_error' (T, R): each region's recorded floor is taken out of its σ (the weakly
    informed region's larger floor too), and replay_theta passes it on; without it the model's one e."""
    from stages.forces import replay_theta, rts_smooth, rts_theta, walk_variances

    T = 6
    young = np.array([[1.0, 3.0], [1.02, 2.4], [0.99, 2.7], [1.0, 2.9], [1.01, 3.1], [1.0, 3.0]]) * 1e5
    rel = np.array([[0.03, 0.12]] * T)
    floors = np.array([[0.02, 0.09]] * T)
    nu, snu = np.full((T, 2), 0.45), np.full((T, 2), 0.02)
    y, _ = rts_theta(young, young * rel, nu, snu, np.arange(T), [], _model(), floors)
    qe, _ = walk_variances(np.arange(T), [], _model())
    for r in range(2):
        want, _ = rts_smooth(np.log(young[:, r]), rel[:, r] ** 2 - floors[:, r] ** 2, qe)
        np.testing.assert_allclose(np.log(y[:, r]), want, rtol=0, atol=1e-12)
    one, _ = rts_theta(young, young * rel, nu, snu, np.arange(T), [], _model())
    assert not np.allclose(one[:, 1], y[:, 1])  # the stiff region's floor matters
    extra = {"estimator": "gn", "material_changes_detected": [], "young_model_error": floors.tolist()}
    y2, _, _ = replay_theta(young, nu, extra, "smoothed", young * rel, snu, _model())
    np.testing.assert_array_equal(y2, y)


# ------------------------------------------------------------------------------------------------- the CLI
@pytest.mark.slow
def test_evaluate_and_export_replay_the_smoothed_theta_when_asked(tmp_path, rsl):
    """`rsl evaluate --force-theta smoothed` and `rsl export --forces --force-theta smoothed` read the gn filter's
    settings from adapt.h5's provenance and replay the smoothed θ(t): on a same-model capture (the truth's own mesh
    and step, test_evaluate_sweep_forces) an online run whose first frames carry a start transient (E 0.6–0.9 ×
    E_true, large σ) and then settle at E_true gives forces within 0.1 % of the truth (median over frames and
    handles) where the recorded θ(t) errs more than 0.5 % (measured 1.7e-5 and 1.1 %), and export's forces.csv gives
    evaluate's numbers."""
    import json

    from stages.artefacts import AdaptArtefact, MeshArtefact, Provenance
    from stages.capture import load_capture, read_forces_csv
    from stages.forces import force_errors
    from stages.sim.scene import make_scene
    from stages.sweep import simulate_fixed
    from test_evaluate_sweep_forces import E_TRUE as e_true, FRAMES as T, same_model_capture

    cap, ws = same_model_capture(tmp_path)
    capture, mesh = load_capture(cap), MeshArtefact.load(ws / "mesh.h5")
    scene = make_scene(mesh, capture.controls(), capture.material.model, capture.dt, capture.gravity)
    X = simulate_fixed(scene, capture.controls(), np.array([e_true]), np.array([0.45]), T, capture.start)
    young = e_true * np.array([0.6, 0.75, 0.9, 1.0, 1.0, 1.0])[:, None]
    rel = np.array([0.3, 0.2, 0.1, 0.03, 0.025, 0.025])[:, None]
    AdaptArtefact(frames=np.arange(T), young=young, poisson=np.full((T, 1), 0.45), z=np.zeros((T, 0)), positions=X,
                  loss=np.zeros(T), time_forward_s=np.zeros(T), time_backward_s=np.zeros(T),
                  time_render_s=np.zeros(T), time_total_s=np.zeros(T), region_names=list(mesh.region_names),
                  mode="online", space="full", loss_kind="markers", window=3, young_sigma=young * rel,
                  poisson_sigma=np.full((T, 1), 0.02),
                  extra={"estimator": "gn", "material_changes_detected": []}).save(
        ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws), "window": 3,
                                          "process_noise": 0.005, "process_noise_change": 0.02, "change_sigma": 0.5,
                                          "model_error": 0.02, "model_error_poisson": 0.02}))
    step = ("--force-substeps", "0", "--no-force-extrapolate")  # the truth's own step: exact at the true E
    got = {}
    for rule in ("online", "smoothed"):
        p = rsl("evaluate", cap, "-w", ws, "--psnr-frames", "0", "--no-plot", *step, "--force-theta", rule)
        assert p.returncode == 0, p.stderr[-2000:]
        got[rule] = json.loads((ws / "evaluation.json").read_text())["forces"]
    assert "Rauch–Tung–Striebel" in got["smoothed"]["source"] and "smoothed" not in got["online"]["source"]
    print({k: v["median_relative_error"] for k, v in got.items()})
    assert got["smoothed"]["median_relative_error"] < 1e-3 < 5e-3 < got["online"]["median_relative_error"]
    out = tmp_path / "export"
    p = rsl("export", "-w", ws, "--capture", cap, "--forces", "--no-plots", "--no-render", "--no-vtk", "--no-stress",
            "--no-ply", "-o", out, *step, "--force-theta", "smoothed")
    assert p.returncode == 0, p.stderr[-2000:]
    mine = force_errors(read_forces_csv(out / "forces.csv"), read_forces_csv(cap / "truth" / "forces.csv"))
    for name, v in got["smoothed"]["per_set"].items():
        assert mine[name]["median_relative_error"] == pytest.approx(v["median_relative_error"], abs=1e-6)  # csv digits
