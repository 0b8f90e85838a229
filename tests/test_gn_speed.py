"""The one-evaluation path of the gn estimator (AdaptConfig.gn_trust) held to its slow twin, the two-evaluation
Levenberg–Marquardt path: gauss_newton's skip_trial, StartWindow's remembered trajectory, GNWindow.extrapolate and
the online estimates."""
from __future__ import annotations

import numpy as np
import pytest

from stages.estimator import Prior, gauss_newton
from test_adapt_e2e import E_TRUE, _window, beam  # noqa: F401  (the module-scoped beam capture fixture)


def _toy():
    """r(p) = exp(A p) − y (m = 6, k = 2): a smooth nonlinear least-squares problem."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 2))
    y = np.exp(A @ np.array([0.3, -0.2])) + 0.01 * rng.normal(size=6)
    calls = []

    def evaluate(p, nj):
        calls.append(nj)
        e = np.exp(A @ p)
        return (e - y, e[:, None] * A) if nj else (e - y, None)

    return evaluate, calls


def test_gauss_newton_skip_trial_takes_the_undamped_step_on_the_quadratic_model():
    """skip_trial True: one evaluation, the same p as the Levenberg–Marquardt path when that accepts its first
    (undamped) step, and the cost of the quadratic model there; skip_trial False: the slow path exactly."""
    prior = Prior(np.zeros(2), np.eye(2))
    p0 = np.array([0.32, -0.22])
    slow_eval, slow_calls = _toy()
    slow = gauss_newton(slow_eval, p0, prior, 0.1, max_iterations=1)
    assert slow.evaluations == 2 and slow.checked and slow_calls == [True, False]
    fast_eval, fast_calls = _toy()
    seen = []
    fast = gauss_newton(fast_eval, p0, prior, 0.1, max_iterations=1,
                        skip_trial=lambda step, size: seen.append((step, size)) or True)
    assert fast.evaluations == 1 and not fast.checked and fast_calls == [True]
    np.testing.assert_array_equal(fast.p, slow.p)  # the same undamped step, accepted by the slow path too
    step, size = seen[0]
    N = fast.jacobian.T @ fast.jacobian / 0.01 + np.eye(2)
    assert size == pytest.approx(np.sqrt(step @ N @ step), rel=1e-12)
    g = fast.jacobian.T @ fast.residuals / 0.01 + (p0 - prior.mean)
    c0 = 0.5 * fast.residuals @ fast.residuals / 0.01 + 0.5 * p0 @ p0
    assert fast.cost == pytest.approx(c0 + g @ step + 0.5 * step @ N @ step, rel=1e-12)
    assert abs(slow.cost - fast.cost) <= 0.1 * (c0 - fast.cost)  # the model's error: small against its decrease
    never_eval, _ = _toy()
    never = gauss_newton(never_eval, p0, prior, 0.1, max_iterations=1, skip_trial=lambda step, size: False)
    np.testing.assert_array_equal(never.p, slow.p)
    assert never.evaluations == 2 and never.checked and never.cost == slow.cost


def _counting(backend):
    """Wrap backend.forward to record the frames each call simulates."""
    calls = []
    orig = backend.forward

    def forward(frames, *a, **k):
        calls.append(list(frames))
        return orig(frames, *a, **k)

    backend.forward = forward
    return calls


def test_start_window_memo_continues_the_remembered_trajectory(beam):  # noqa: F811
    """StartWindow.memo: a window from two states of the last trajectory with the same θ takes the frames that
    trajectory holds and simulates only the rest; the states equal a fresh simulation to the tolerance of the
    step's Newton solve; another θ or other starting states simulate everything."""
    from test_adapt_e2e import _objective

    cap, ws = beam
    obj, backend = _objective(cap, ws, "markers")
    win = obj.win
    frames, before, p = _window(backend, 6, 3)  # frames 6, 7, 8 from stored states 4, 5
    E, nu = np.exp(p[:1]), np.array([0.42])
    calls = _counting(backend)
    win.memo = True
    X = win.forward(frames, E, nu, before)
    assert calls == [[6, 7, 8]]
    Y = win.forward([7, 8, 9], E, nu, np.stack([before[1], X[0]]))
    assert calls[-1] == [9]  # 7, 8 remembered
    win.memo = False
    Z = win.forward([7, 8, 9], E, nu, np.stack([before[1], X[0]]))
    assert calls[-1] == [7, 8, 9]
    scale = np.abs(Z - before[1]).max()
    assert np.abs(Y - Z).max() <= 1e-6 * scale, np.abs(Y - Z).max() / scale
    win.memo = True
    win.forward([7, 8, 9], 1.1 * E, nu, np.stack([before[1], X[0]]))  # another θ
    assert calls[-1] == [7, 8, 9]
    win.forward([8, 9], E, nu, np.stack([X[0] + 1e-6, X[1]]))  # other states
    assert calls[-1] == [8, 9]


def test_extrapolate_is_the_window_at_the_new_estimate_to_first_order(beam):  # noqa: F811
    """GNWindow.extrapolate from the linearisation at p to p + h d against the window evaluated there (simulated and
    observed): the states' and residuals' error is second order (÷ ≈ 4 when h halves) and small against the change;
    the corrected starting states are exact."""
    from stages.windows import GNWindow
    from test_adapt_e2e import _objective

    cap, ws = beam
    obj, backend = _objective(cap, ws, "markers")
    gn = GNWindow(obj, True, np.zeros(1))
    gn.memo = False
    frames, before, p = _window(backend, 9, 3)
    x_b = backend.decode(np.asarray(before))
    D = np.stack([np.stack([v, 0 * v]) for v in (x_b[1] - x_b[0],)])  # one correction of state t0 − 2
    p0 = np.concatenate([p, [0.0]])
    d = np.array([1.0, 0.5, 0.2])
    errs = []
    # (warm-up: the first evaluation away from p of a fresh objective lands elsewhere by more than the step's effect
    # — the solvers' warm starts; from then on r(p) is reproducible to 1e-14)
    gn.evaluate(frames, p0, before, D, False)
    gn.evaluate(frames, p0 + 0.02 * d, before, D, False)
    for h in (0.02, 0.005):  # (at 0.04 a marker changes its nearest triangle: r jumps, MarkerObservation.rebind)
        gn.evaluate(frames, p0, before, D, True)
        X0, r0 = gn.last_states.copy(), np.concatenate(gn.last_rs)
        gn.extrapolate(frames, p0 + h * d, before, D, 1.0)
        Xe, re, be = gn.last_states.copy(), np.concatenate(gn.last_rs), gn.last_before.copy()
        gn.memo = False  # (the window simulated at p + h d, not continued from what extrapolate remembered)
        gn.evaluate(frames, p0 + h * d, before, D, False)
        X1, r1 = gn.last_states, np.concatenate(gn.last_rs)
        np.testing.assert_allclose(be, gn.last_before, rtol=0, atol=1e-15)
        assert np.abs(Xe - X1).max() <= 0.05 * np.abs(X1 - X0).max()
        assert np.linalg.norm(re - r1) <= 0.05 * np.linalg.norm(r1 - r0)
        errs.append((np.abs(Xe - X1).max(), np.linalg.norm(re - r1)))
    for a, b in zip(*errs):
        assert a / b >= 8.0, (a, b)  # second order: h² → (h/4)² divides by 16 (first order: by 4)


def _online(cap, ws, trust: float | None, loss: str, frames: str, monkeypatch, memo: bool | None = None, **kw):
    """adapt online gn (trust None: AdaptConfig's default --gn-trust); returns (young (T,), σ_E (T,), the frames whose
    step was taken without evaluation)."""
    from stages.artefacts import AdaptArtefact
    from stages.steps import adapt
    from stages.windows import GNWindow

    skipped = []
    if memo is not None:  # None: GNWindow's own default
        monkeypatch.setattr(GNWindow, "memo", memo)
    orig = GNWindow.extrapolate

    def extrapolate(self, frames_, *a, **k):
        skipped.append(frames_[-1])
        return orig(self, frames_, *a, **k)

    monkeypatch.setattr(GNWindow, "extrapolate", extrapolate)
    trust_kw = {} if trust is None else {"gn_trust": trust}
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, loss=loss, window=3, frames=frames,
                                                         estimator="gn", space="full", **{"iters_per_frame": 1,
                                                                                          **trust_kw, **kw})))
    monkeypatch.undo()
    return art.young[:, 0], art.young_sigma[:, 0], skipped


@pytest.fixture(scope="module")
def beam_step(tmp_path_factory):
    """The beam of test_adapt_e2e filmed 24 frames with E doubling at frame 12."""
    from test_adapt_e2e import _make_capture

    return _make_capture(tmp_path_factory.mktemp("gn_speed"), frames=24, young_schedule=f"{E_TRUE}@0,{2 * E_TRUE}@12")


def test_online_gn_with_one_evaluation_per_frame_tracks_the_levenberg_marquardt_path(beam_step, monkeypatch):
    """Markers, the beam from 0.5 E with a step of E ×2 at frame 12, one substep per frame (as synthesised; with
    more, the model's own error keeps the settled steps above 5 σ and few are taken unevaluated): --gn-trust 5 (steps of at most 5 posterior σ
    taken on the quadratic model, the window's states at the estimate to first order) against --gn-trust 0 (every
    step evaluated, Levenberg–Marquardt).  The large steps (the first frames, the frames after the step of E) are
    still evaluated, most others are not; the estimates agree within 0.05 σ_E on every frame (measured ≤ 0.003 σ_E:
    the first-order states err by O(δp²), far below what the data resolve)."""
    cap, ws = beam_step
    kw = dict(young_init=0.5 * E_TRUE, substeps=1)  # the model the capture was made with: settled steps are small
    y0, s0, sk0 = _online(cap, ws, 0.0, "markers", "0:24", monkeypatch, **kw)
    y1, s1, sk1 = _online(cap, ws, 5.0, "markers", "0:24", monkeypatch, **kw)
    assert sk0 == [] and len(sk1) >= 12 and not {12, 13} & set(sk1), sk1
    assert np.all(np.abs(y1 - y0) <= 0.05 * s0), np.abs(y1 - y0) / s0
    assert abs(y1[-1] / (2 * E_TRUE) - 1) < 0.01


def test_online_gn_remembering_its_trajectories_is_the_simulating_twin(beam_step, monkeypatch):
    """GNWindow.memo (the change test's forward, the linearisation's window and the anchor taken from the last
    trajectory of the same θ and states) against every evaluation simulating its own window and anchor: the same
    estimates to the tolerance of the solves (the Levenberg–Marquardt path, markers, the beam with a step of E; one
    substep per frame and 3, where the window's sensitivities take its substeps stitched from the forwards that
    simulated its frames, window_backends.Substepped._stitch), and fewer simulated frames (substeps)."""
    from stages.window_backends import FullSpace

    cap, ws = beam_step
    out = {}
    orig = FullSpace.forward
    for substeps in (1, 3):
        for memo in (False, True):
            n = [0]

            def forward(self, frames, *a, **k):
                n[0] += len(frames)
                return orig(self, frames, *a, **k)

            monkeypatch.setattr(FullSpace, "forward", forward)
            y, s, _ = _online(cap, ws, 0.0, "markers", "0:24", monkeypatch, memo=memo, young_init=0.5 * E_TRUE,
                              substeps=substeps)
            out[substeps, memo] = (y, s, n[0])
    for substeps in (1, 3):
        (y0, s0, n0), (y1, _, n1) = out[substeps, False], out[substeps, True]
        assert np.all(np.abs(y1 - y0) <= 1e-3 * s0), (substeps, np.abs(y1 - y0) / s0)
        # (the change test's frame is simulated once either way: the test takes it from the linearisation,
        # GNWindow.shared_innovation — measured 91 of 129 frames at 1 substep)
        assert n1 < 0.8 * n0, (substeps, n1, n0)


def test_online_gn_change_test_from_the_linearisation_is_the_separate_render(beam_step, tmp_path, monkeypatch):
    """GNWindow.shared_innovation (images): the change test's residuals of the new frame taken from the window's first
    linearisation at the predicted θ (which the solve then starts from) against the test simulating and rendering
    the new frame by itself first — the beam with a step of E ×2 at frame 12, 30 Gaussians, from 0.5 E, a low
    --change-threshold (changes declared on the tested frames after the first three, the speculative
    linearisation then made again for the restarted window; not on those three, where the solve starts from it):
    the same innovations z and change points, the same estimates (to the rounding of the float32 renders; measured
    identical); one render of the new frame fewer per tested frame."""
    from stages.estimator import ChangeDetector
    from stages.observations import VisionObservation
    from stages.windows import GNWindow
    from test_adapt_e2e import _image_workspace

    cap, ws = beam_step
    ws2 = _image_workspace(ws, tmp_path / "ws")
    out = {}
    orig_update, orig_res = ChangeDetector.update, VisionObservation.residuals
    for shared in (False, True):
        zs, declared, calls = [], [], [0]

        def update(self, z):
            zs.append(z)
            hit = orig_update(self, z)
            declared.append(hit)
            return hit

        def residuals(self, frames, X):
            calls[0] += 1
            return orig_res(self, frames, X)

        monkeypatch.setattr(ChangeDetector, "update", update)
        monkeypatch.setattr(VisionObservation, "residuals", residuals)
        monkeypatch.setattr(GNWindow, "shared_innovation", shared)
        y, s, _ = _online(cap, ws2, 0.0, "vision", "0:18", monkeypatch, memo=True, young_init=0.5 * E_TRUE,
                          substeps=1, change_threshold=1.2)  # (threshold² − 1 − drift < 0: every tested
        # frame after the three whose z make the baseline declares a change)
        out[shared] = (y, s, np.array(zs), declared, calls[0])
    (y0, s0, z0, d0, n0), (y1, _, z1, d1, n1) = out[False], out[True]
    assert d1 == d0 and any(d0) and not all(d0), (d0, d1)  # the test declares changes, and passes frames too
    np.testing.assert_allclose(z1, z0, rtol=1e-5, atol=0)
    assert np.all(np.abs(y1 - y0) <= 1e-4 * s0), np.abs(y1 - y0) / s0
    assert n1 == n0 - len(z0), (n0, n1, len(z0))  # the tests' own renders (the jvp renders the linearisations)


def test_gauss_newton_covariances_from_its_own_normal_matrix_are_the_recomputed_ones():
    """gauss_newton forms Jᵀ W J once at the last linearisation and passes it to posterior_cov and cluster_scale2
    (``jtwj``): the covariances and s² are the very floats recomputing it gives (Huber weights, clustered
    residuals)."""
    from stages.estimator import cluster_scale2, posterior_cov

    rng = np.random.default_rng(5)
    A = rng.normal(size=(400, 3))
    y = A @ np.array([0.5, -1.0, 2.0]) + 0.1 * rng.standard_t(2, size=400)
    clusters = np.repeat(np.arange(40), 10)
    prior = Prior(np.zeros(3), 4.0 * np.eye(3))
    res = gauss_newton(lambda p, nj: (A @ p - y, A if nj else None), np.zeros(3), prior, 0.1, max_iterations=3,
                       huber=1.345, clusters=clusters)
    assert res.jtwj is not None
    k2 = cluster_scale2(res.residuals, res.jacobian, 0.1, 1.345, clusters)
    assert res.scale2 == k2
    np.testing.assert_array_equal(res.cov, posterior_cov(res.jacobian, res.weights, 0.1 ** 2, prior))
    np.testing.assert_array_equal(res.cov_scaled, posterior_cov(res.jacobian, res.weights, 0.1 ** 2 * k2, prior))


def _cluster_scale2_all_rows(r, J, sigma, delta, clusters):
    """cluster_scale2's formula over every row of J (the slow twin of its restriction to the rows that are not 0)."""
    from stages.estimator import huber_psi, huber_weights

    k = J.shape[1]
    psi, dpsi = huber_psi(r / sigma, delta)
    ids = np.unique(clusters, return_inverse=True)[1].reshape(-1)
    g = np.stack([np.bincount(ids, weights=(J * (sigma * psi)[:, None])[:, j]) for j in range(k)], axis=1)
    G = int(np.sum(np.any(g != 0.0, axis=1)))
    A = (J * dpsi[:, None]).T @ J
    Ainv = np.linalg.pinv(0.5 * (A + A.T))
    V = G / (G - 1) * Ainv @ (g.T @ g) @ Ainv
    return float(np.trace(V @ ((J * huber_weights(r, sigma, delta)[:, None]).T @ J))) / (k * sigma ** 2)


def test_cluster_scale2_over_the_rows_with_a_derivative_is_the_formula_over_all_rows():
    """cluster_scale2 sums only the rows of J that are not 0 (an image's background pixels, where r may still be
    non-zero): the same s² as the formula over every row, to rounding (Huber weights, clustered residuals)."""
    from stages.estimator import cluster_scale2

    rng = np.random.default_rng(7)
    m, k = 6000, 3
    J = rng.normal(size=(m, k))
    J[rng.uniform(size=m) < 0.7] = 0.0  # background
    J[:50, 1] = 0.0  # rows with some columns 0 stay
    r = 0.05 * rng.standard_t(3, size=m)
    clusters = np.repeat(np.arange(m // 20), 20)
    got = cluster_scale2(r, J, 0.05, 1.345, clusters)
    want = _cluster_scale2_all_rows(r, J, 0.05, 1.345, clusters)
    assert got == pytest.approx(want, rel=1e-12) and abs(got - 1.0) > 0.01


def test_robust_cost_by_dot_products_is_the_huber_sum():
    """robust_cost as a·|r| − ½ a·a, a = min(|r|, δσ): the per-residual Huber sum σ² Σ ρ(|r|/σ) to rounding, for
    residuals on both sides of δσ (and ½ r·r without Huber)."""
    from stages.estimator import robust_cost

    rng = np.random.default_rng(11)
    r = 0.05 * rng.standard_t(2, size=5000)
    r[:1000] = 0.0
    u = np.abs(r) / 0.05
    want = 0.05 ** 2 * np.sum(np.where(u <= 1.345, 0.5 * u * u, 1.345 * u - 0.5 * 1.345 ** 2))
    assert np.sum(u > 1.345) > 100 and np.sum((u > 0) & (u <= 1.345)) > 100
    assert robust_cost(r, 0.05, 1.345) == pytest.approx(want, rel=1e-12)
    assert robust_cost(r, 0.05, None) == 0.5 * float(r @ r)


def test_gauss_newton_over_the_rows_of_j_that_are_not_zero_is_the_full_step():
    """gauss_newton forms Jᵀ W J and Jᵀ W r over the rows of J that are not 0 (an image's background pixels, whose
    residuals still count in the cost): the step, the covariance and s² are those of the full-row formulas to
    rounding (Huber weights, clustered residuals)."""
    from stages.estimator import huber_weights

    rng = np.random.default_rng(13)
    m, k = 3000, 3
    A = rng.normal(size=(m, k))
    A[rng.uniform(size=m) < 0.6] = 0.0
    y = A @ np.array([0.5, -1.0, 2.0]) + 0.1 * rng.standard_t(2, size=m)
    clusters = np.repeat(np.arange(m // 10), 10)
    prior = Prior(np.zeros(k), 4.0 * np.eye(k))
    res = gauss_newton(lambda p, nj: (A @ p - y, A if nj else None), np.zeros(k), prior, 0.1, max_iterations=1,
                       huber=1.345, clusters=clusters)
    r0 = -y
    W = huber_weights(r0, 0.1, 1.345)
    N = (A * W[:, None]).T @ A / 0.01 + prior.info
    step = -np.linalg.solve(N, A.T @ (W * r0) / 0.01)
    np.testing.assert_allclose(res.p, step, rtol=1e-12, atol=0)
    np.testing.assert_allclose(res.cov, np.linalg.inv(N), rtol=1e-10, atol=0)
    np.testing.assert_allclose(res.jtwj, (A * W[:, None]).T @ A, rtol=1e-12, atol=0)
    assert res.scale2 == pytest.approx(_cluster_scale2_all_rows(r0, A, 0.1, 1.345, clusters), rel=1e-12)


def test_gn_window_holds_blas_to_its_threads_over_images_only():
    """GNWindow.blas_limit: numpy's BLAS at GNWindow.blas_threads (1) threads inside the context for images and as it
    was after it; untouched for markers and with blas_threads None (the twin the bench compares)."""
    from types import SimpleNamespace

    from threadpoolctl import threadpool_info, threadpool_limits

    from stages.windows import GNWindow

    def blas():
        return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]

    gn = GNWindow(SimpleNamespace(R=1), False, np.zeros(1))
    with threadpool_limits(limits=2, user_api="blas"):  # (a machine whose BLAS has one thread already)
        before = blas()
        assert before and max(before) == 2, before
        with gn.blas_limit("vision"):
            assert blas() == [1] * len(before)
        assert blas() == before
        with gn.blas_limit("markers"):
            assert blas() == before
        gn.blas_threads = None
        with gn.blas_limit("vision"):
            assert blas() == before


def test_vision_residuals_from_the_kept_targets_are_the_obvious_formula(beam_step, tmp_path):
    """VisionObservation.residuals with the frames' flattened float64 targets kept (8 frames) and no copy
    when nothing is occluded: bit for bit (render − targets) · keep of the obvious formula, for frames read anew and
    kept; the forward-mode residuals the same floats; _masked zeroes the occluded rows of r and of J."""
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture
    from stages.observations import VisionObservation
    from test_adapt_e2e import _image_workspace

    cap, ws = beam_step
    ws2 = _image_workspace(ws, tmp_path / "ws")
    mesh = MeshArtefact.load(ws2 / "mesh.h5")
    obs = VisionObservation(load_capture(cap), ws2, "", mesh, False)
    assert not obs.occluded
    rng = np.random.default_rng(4)
    frames = list(range(12)) + [3, 11]  # (frames 0–3 leave the kept ones, 3 is flattened anew)
    X = mesh.vertices[None] + 1e-3 * rng.normal(size=(len(frames),) + mesh.vertices.shape)
    rs = obs.residuals(frames, X)
    assert len(obs._flat) == 8
    for t, x, r in zip(frames, X, rs):
        ref = (obs._renders(x) - np.concatenate([im.reshape(-1) for im in obs.targets(t)]).astype(np.float64)) * 1.0
        assert np.array_equal(r, ref) and np.abs(r).max() > 0
    dX = 1e-3 * rng.normal(size=(2, 2) + mesh.vertices.shape)
    r2, J2 = obs.residuals_and_jacobian(frames[-2:], X[-2:], dX)
    for a, b, J in zip(r2, rs[-2:], J2):
        assert np.array_equal(a, b) and J.shape == (len(a), 2) and np.abs(J).max() > 0
    keep = (rng.random(len(rs[0])) > 0.5).astype(np.float64)
    J = rng.normal(size=(len(rs[0]), 2))
    assert VisionObservation._masked(rs[0], 1.0) is rs[0]
    assert np.array_equal(VisionObservation._masked(rs[0], keep), rs[0] * keep)
    assert np.array_equal(VisionObservation._masked(J, keep), J * keep[:, None])


def test_gn_trust_default_resolves_from_the_loss():
    """resolve_gn_trust: AdaptConfig's default --gn-trust (None) is GN_TRUST_IMAGES (5) with images and 0 (every step
    tested) with markers and silhouettes; a value given always wins, 0 included."""
    from pathlib import Path

    from stages.steps.adapt import GN_TRUST_IMAGES, AdaptConfig, resolve_gn_trust

    cfg = AdaptConfig(capture=Path("c"), workspace=Path("w"))
    assert cfg.gn_trust is None and GN_TRUST_IMAGES == 5.0
    assert resolve_gn_trust(cfg, "vision") == GN_TRUST_IMAGES
    assert resolve_gn_trust(cfg, "markers") == 0.0 and resolve_gn_trust(cfg, "silhouette") == 0.0
    for given in (0.0, 2.5):
        explicit = AdaptConfig(capture=Path("c"), workspace=Path("w"), gn_trust=given)
        assert resolve_gn_trust(explicit, "vision") == given and resolve_gn_trust(explicit, "markers") == given


def _mesh_workspace(ws, out):
    """A copy of ws's mesh.h5 and cameras.h5 alone in ``out`` (no adapt.h5 of an earlier test); returns out."""
    import shutil

    out.mkdir()
    for f in ("mesh.h5", "cameras.h5"):
        shutil.copy(ws / f, out / f)
    return out


def test_gn_trust_negative_is_rejected(beam_step, tmp_path):
    """--gn-trust below 0 fails before any compute, with the option's name and the value."""
    from stages.errors import RslError
    from stages.steps import adapt

    cap, ws = beam_step
    ws2 = _mesh_workspace(ws, tmp_path / "ws")
    with pytest.raises(RslError, match=r"--gn-trust must be 0 or more, found -1\.0"):
        adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws2, loss="markers", estimator="gn", gn_trust=-1.0))
    assert not (ws2 / "adapt.h5").exists()


def test_gn_images_at_the_default_trust_take_one_evaluation_and_record_it(beam_step, tmp_path, monkeypatch):
    """Images, gn at AdaptConfig's default --gn-trust, rsl adapt's default iterations: the small last steps are taken
    on the quadratic model (GNWindow.extrapolate, gauss_newton unchecked) and adapt.h5 records the resolved 5 (its
    extra; the provenance keeps the option as given, None, so that `rsl run` finds the artefact up to date); markers
    at the default: every step tested (no extrapolation) and 0 recorded."""
    from stages.artefacts import AdaptArtefact, read_provenance
    from stages.steps import adapt
    from test_adapt_e2e import _image_workspace

    cap, ws = beam_step
    ws2 = _image_workspace(ws, tmp_path / "ws")
    results = []
    orig = adapt.gauss_newton

    def counted(*a, **k):
        res = orig(*a, **k)
        results.append(res)
        return res

    monkeypatch.setattr(adapt, "gauss_newton", counted)
    iters = adapt.AdaptConfig.iters_per_frame
    _, _, skipped = _online(cap, ws2, None, "vision", "0:10", monkeypatch, substeps=1, iters_per_frame=iters)
    assert AdaptArtefact.load(ws2 / "adapt.h5").extra["gn_trust"] == adapt.GN_TRUST_IMAGES
    assert read_provenance(ws2 / "adapt.h5")["config"]["gn_trust"] is None
    unchecked = [r for r in results if not r.checked]
    assert len(skipped) >= 3 and len(unchecked) == len(skipped), (skipped, len(unchecked))
    # a linearisation per iteration and a trial per iteration but the last (every step tested: 2 per iteration)
    assert all(r.evaluations == 2 * r.iterations - 1 for r in unchecked), \
        [(r.iterations, r.evaluations) for r in unchecked]
    ws3 = _mesh_workspace(ws, tmp_path / "ws3")
    _, _, skipped = _online(cap, ws3, None, "markers", "0:6", monkeypatch, substeps=1)
    assert skipped == [] and AdaptArtefact.load(ws3 / "adapt.h5").extra["gn_trust"] == 0.0
