"""Gauss–Newton / Levenberg–Marquardt with a Gaussian prior, and the sliding-window (moving-horizon) filter
that ``rsl adapt --estimator gn`` runs.  Pure numpy: no I/O, no simulation.

One window solve minimises, over the unknowns p (k,),

    C(p) = Σ_i σ² ρ(r_i(p)/σ) + ½ (p − m)ᵀ P⁻¹ (p − m),     ρ(u) = ½u² (|u| ≤ δ), δ|u| − ½δ² (Huber)

with residuals r (m,) of the observations (σ the noise level of one residual) and the prior N(m, P) —
the "arrival cost" that summarises every observation before the window.  Each Gauss–Newton step solves

    (Jᵀ W J / σ² + P⁻¹ + λ D) δ = −(Jᵀ W r / σ² + P⁻¹ (p − m)),   W = diag(min(1, δσ/|r_i|))

(iteratively reweighted least squares for the Huber loss; W = I without it), D = diag of the normal
matrix, λ the Levenberg–Marquardt damping (0 first: a pure Gauss–Newton step; raised ×4 while a step
does not lower C, lowered ÷4 after an accepted one).  The posterior covariance is the inverse of the
undamped normal matrix at the solution, N⁻¹ = (Jᵀ W J / σ² + P⁻¹)⁻¹ (Laplace approximation).

For a linear model r = A p − y and no Huber weights this is the closed-form Gaussian posterior
(one step, exact); tests hold it to the Kalman filter and to batch least squares.

Filter over frames (:class:`WindowFilter`): the window's unknowns share θ; when a frame leaves the
window its linearised residuals are folded into the arrival cost by a Kalman update
(:func:`fold`), and the arrival cost is inflated by the process noise Q per frame (:func:`inflate`), so a
material that changes over time can be followed (random walk of log E with σ_q per frame).
A step of the material is caught by :class:`ChangeDetector` (a CUSUM of the new frame's normalised innovation);
the caller then widens the prior and restarts its window.

Honest σ: ``GNResult.cov`` is the posterior with the assumed σ (the closed form above); ``GNResult.cov_scaled``
replaces σ² by the residuals' own level, s² σ² with s² = :func:`residual_scale2` (RSS/dof, Huber's variance factor
with the Huber loss) or, for residuals correlated in clusters (an image's pixels), :func:`cluster_scale2` (the
cluster-robust sandwich); :func:`bounded_sigma` keeps the σ of a parameter held at a bound from collapsing.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np


@dataclass
class Prior:
    """Gaussian N(mean, cov) on the unknowns: mean (k,), cov (k, k)."""

    mean: np.ndarray
    cov: np.ndarray

    @property
    def info(self) -> np.ndarray:
        """P⁻¹ (k, k)."""
        return _sym_inv(self.cov)


@dataclass
class GNResult:
    p: np.ndarray  # (k,) the estimate
    cov: np.ndarray  # (k, k) posterior covariance N⁻¹
    cost: float  # C(p)
    iterations: int  # Jacobian evaluations
    evaluations: int  # residual evaluations
    residuals: np.ndarray  # (m,) at the last linearisation point
    jacobian: np.ndarray  # (m, k) at the last linearisation point
    p_lin: np.ndarray  # (k,) the last linearisation point
    weights: np.ndarray  # (m,) the IRLS weights used there
    scale2: float = 1.0  # s² (:func:`residual_scale2` / :func:`cluster_scale2`) there: 1 when they fit the assumed σ
    cov_scaled: np.ndarray | None = None  # (k, k) (Jᵀ W J / (σ² s²) + P⁻¹)⁻¹: the covariance with σ from the data
    checked: bool = True  # the last step was evaluated (False: taken on the quadratic model, gauss_newton's skip_trial)
    jtwj: np.ndarray | None = None  # (k, k) Jᵀ W J at the last linearisation, as (J W)ᵀ J over J's non-zero rows


def huber_weights(r: np.ndarray, sigma: float, delta: float | None) -> np.ndarray:
    """IRLS weights of the Huber loss: min(1, δσ/max(|r|, 1e-300)) (all ones when δ is None), in place over one
    array — the floats of the branch where(|r| ≤ δσ, 1, δσ/max(|r|, 1e-300)) (:func:`_huber_weights_where`, its
    twin) in fewer passes: a rounded quotient c/a with c ≥ a > 0 is ≥ 1, and δσ/1e-300 overflows to ∞."""
    if delta is None:
        return np.ones_like(r)
    c = float(delta * sigma)
    if not c > 0:
        return _huber_weights_where(r, sigma, delta)
    w = np.abs(r)
    np.maximum(w, 1e-300, out=w)
    with np.errstate(over="ignore"):
        np.divide(c, w, out=w)
    return np.minimum(w, 1.0, out=w)


def _huber_weights_where(r: np.ndarray, sigma: float, delta: float) -> np.ndarray:
    """:func:`huber_weights` by its branch (the slow twin the tests hold it to)."""
    a = np.abs(r)
    return np.where(a <= delta * sigma, 1.0, delta * sigma / np.maximum(a, 1e-300))


def huber_psi(u: np.ndarray, delta: float | None) -> tuple[np.ndarray, np.ndarray]:
    """ψ(u) = ρ'(u) and ψ'(u) of the (Huber) loss for normalised residuals u = r/σ: (u, 1) without Huber,
    (clip(u, ±δ), 1_{|u| ≤ δ}) with it."""
    if delta is None:
        return u, np.ones_like(u)
    return np.clip(u, -delta, delta), (np.abs(u) <= delta).astype(np.float64)


def residual_scale2(r: np.ndarray, sigma: float, delta: float | None, k: int) -> float:
    """s² = [Σ ψ(u_i)² / (m − k)] / [(1/m) Σ ψ'(u_i)]²,  u = r/σ  (Huber 1981, the M-estimator's variance factor).

    The covariance of a (robust) least-squares estimate with σ estimated from the data is s² (Jᵀ W J / σ²)⁻¹:
    without Huber s² = RSS / ((m − k) σ²) — the residual variance per degree of freedom against the assumed
    σ² —, with Huber the clipped residuals replace r and the fraction of inliers the unit Hessian.  A floor of
    1/4 keeps a lucky window (few residuals, all small) from shrinking σ below half the assumed noise."""
    m = len(r)
    if m <= k or sigma <= 0:
        return 1.0
    psi, dpsi = huber_psi(np.asarray(r, np.float64) / sigma, delta)
    mean_d = float(np.mean(dpsi))
    if mean_d <= 0:
        return float(np.inf)
    return max(float(psi @ psi) / (m - k) / mean_d ** 2, 0.25)


def cluster_scale2(r: np.ndarray, J: np.ndarray, sigma: float, delta: float | None, clusters: np.ndarray,
                   jtwj: np.ndarray | None = None, live: np.ndarray | None = None) -> float:
    """s² of residuals whose errors are correlated within clusters (e.g. blocks of neighbouring pixels): the
    cluster-robust (sandwich) covariance of the M-estimate, expressed as a variance factor of the assumed σ².

        A = Σ_i ψ'(u_i) J_i J_iᵀ,   B = Σ_c g_c g_cᵀ,  g_c = Σ_{i ∈ c} σ ψ(u_i) J_i,   V = G/(G−1) A⁻¹ B A⁻¹,
        s² = tr(V Jᵀ W J) / (k σ²)        (u = r/σ, G the clusters with a non-zero g_c, k = J's columns)

    so that (Jᵀ W J / (σ² s²))⁻¹ has V's average size (the two agree exactly when V ∝ A⁻¹).  With one residual
    per cluster and no Huber this is the residual variance against σ² (White's estimator; ≈ RSS/((m − k) σ²), as
    :func:`residual_scale2`); with correlated errors it also counts how many residuals carry one independent
    error — an image's misfit is spatially correlated, and ~10⁵ pixels taken as independent give a covariance
    far too small.  Falls back to :func:`residual_scale2` with fewer than 4k informative clusters.  ``jtwj``: Jᵀ W J
    (k, k) when already formed (W = :func:`huber_weights`; as (J W)ᵀ J over J's non-zero rows, the same floats);
    ``live``: those rows (:func:`live_rows`) when already found."""
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    m, k = J.shape
    if m <= k or sigma <= 0 or k == 0:
        return 1.0
    ids = np.asarray(clusters)
    if ids.dtype.kind not in "iu" or ids.min() < 0 or ids.max() > 4 * m:  # labels → 0..G−1 (np.unique is slow)
        ids = np.unique(ids, return_inverse=True)[1].reshape(-1)
    live = live_rows(J) if live is None else live  # only J's non-zero rows add to A, g, Jᵀ W J (images: background)
    Jl, rl, ids = J[live], r[live], ids[live]
    psi, dpsi = huber_psi(rl / sigma, delta)
    score = Jl * (sigma * psi)[:, None]  # (m_live, k)
    g = np.stack([np.bincount(ids, weights=score[:, j]) for j in range(k)], axis=1)  # (clusters, k): Σ_{i∈c}
    G = int(np.sum(np.any(g != 0.0, axis=1)))
    if G < 4 * k:
        return residual_scale2(r, sigma, delta, k)
    A = (Jl * dpsi[:, None]).T @ Jl
    Ainv = np.linalg.pinv(0.5 * (A + A.T))
    V = G / (G - 1) * Ainv @ (g.T @ g) @ Ainv
    AW = (Jl * huber_weights(rl, sigma, delta)[:, None]).T @ Jl if jtwj is None else jtwj
    s2 = float(np.trace(V @ AW)) / (k * sigma ** 2)
    return s2 if np.isfinite(s2) and s2 > 0 else residual_scale2(r, sigma, delta, k)


def robust_cost(r: np.ndarray, sigma: float, delta: float | None) -> float:
    """Σ σ² ρ(r/σ) (½ Σ r² without Huber) = Σ (a |r| − ½ a²), a = min(|r|, δσ) (σ²ρ(u) = ½r² for |u| ≤ δ, δσ|r| − ½(δσ)²
    beyond: two dot products, no per-residual branch)."""
    if delta is None:
        return 0.5 * float(r @ r)
    ar = np.abs(r)
    a = np.minimum(ar, delta * sigma)  # σ a in the units of r
    return float(a @ ar - 0.5 * (a @ a))


def gauss_newton(evaluate: Callable[[np.ndarray, bool], tuple], p0: np.ndarray, prior: Prior, sigma: float, *,
                 max_iterations: int = 5, huber: float | None = None, tol: float = 1e-3,
                 max_rejections: int = 4, max_step: np.ndarray | float | None = None,
                 lower: np.ndarray | None = None, upper: np.ndarray | None = None, scale: float = 1.0,
                 clusters: np.ndarray | None = None,
                 skip_trial: Callable[[np.ndarray, float], bool] | None = None) -> GNResult:
    """Minimise C(p) (module docstring) from p0.

    evaluate(p, need_jacobian) → (r (m,), J (m, k) or None) or, with the Jacobian, (r, J, jtw) where jtw(W)
    gives Jᵀ diag(W) r exactly (used for the gradient when J is only approximate — the estimate is then the
    exact minimum of C, and J only shapes the steps and the covariance; without jtw, J exact, Jᵀ W r is formed
    here over J's non-zero rows); sigma the noise level of one residual;
    huber δ in units of σ (None: plain least squares); stops after ``max_iterations`` Jacobians or when
    the step's size in units of the posterior σ falls below ``tol``.  ``max_step`` (k,) or scalar: a step is
    scaled down until no |δ_i| exceeds it (a trust region); ``lower``/``upper`` (k,): p is clipped into these
    bounds after each step (NaN or ±inf: unbounded).  ``scale`` s²: the data term's variance factor (σ² s² in the
    normal matrix and the cost; σ and δ still set the Huber weights) — the residuals' own level (``GNResult.scale2``
    of earlier windows) when σ is a robust per-residual noise level that correlated residuals exceed.  ``clusters``
    (m,) ids of residuals with correlated errors: ``GNResult.scale2`` is then :func:`cluster_scale2`, else
    :func:`residual_scale2`.
    ``skip_trial(step, size)``: asked for the undamped step of the last iteration (``size`` = √(δᵀ N δ), the step
    in units of the posterior σ); True takes it without evaluating r there — on the quadratic model, whose cost
    C + gᵀδ + ½ δᵀ N δ goes into ``GNResult.cost`` (``checked`` False) — instead of the Levenberg–Marquardt
    acceptance test (one evaluation, of r and J, per iteration instead of two).
    """
    p = np.asarray(p0, np.float64).copy()
    info = prior.info
    s2 = float(sigma) ** 2 * float(scale)

    def cost(p_, r_):
        d = p_ - prior.mean
        return robust_cost(r_, sigma, huber) / s2 + 0.5 * float(d @ info @ d)

    r, J, jtw = _unpack(evaluate(p, True))
    c = cost(p, r)
    lam = 0.0
    n_eval, it = 1, 0
    p_lin, r_lin, J_lin = p.copy(), r, J
    W = huber_weights(r, sigma, huber) if max_iterations < 1 else None  # (formed in the loop)
    checked = False  # (no iteration: the covariance at p0, which was evaluated)
    for it in range(1, max_iterations + 1):
        p_lin, r_lin, J_lin = p.copy(), r, J
        W = huber_weights(r, sigma, huber)
        live = live_rows(J)  # the rows of J that are 0 (an image's background pixels) add nothing to Jᵀ W J, Jᵀ W r
        Jl = J[live]
        JW = Jl * W[live, None]
        JWJ = JW.T @ Jl
        N = JWJ / s2 + info
        jtwr = JW.T @ r[live] if jtw is None else jtw(W)
        g = jtwr / s2 + info @ (p - prior.mean)
        accepted = checked = False
        r_new = None  # the residuals at the accepted step, when evaluated there
        for _ in range(max_rejections + 1):
            A = N + lam * np.diag(np.diag(N))
            step = -np.linalg.solve(A, g)
            if max_step is not None:
                ratio = float(np.max(np.abs(step) / np.broadcast_to(max_step, step.shape)))
                if ratio > 1.0:
                    step = step / ratio
            p_new = p + step
            if lower is not None:
                p_new = np.where(np.isfinite(lower), np.maximum(p_new, np.nan_to_num(lower, nan=-np.inf)), p_new)
            if upper is not None:
                p_new = np.where(np.isfinite(upper), np.minimum(p_new, np.nan_to_num(upper, nan=np.inf)), p_new)
            step = p_new - p
            if skip_trial is not None and it == max_iterations and lam == 0.0:
                size = float(np.sqrt(max(step @ N @ step, 0.0)))
                if skip_trial(step, size):  # the model's cost at p_new (C's quadratic model about p)
                    c_new = c + float(g @ step) + 0.5 * float(step @ N @ step)
                    accepted = True
                    break
            checked = True
            r_new = evaluate(p_new, False)[0]
            n_eval += 1
            c_new = cost(p_new, r_new)
            if np.isfinite(c_new) and c_new <= c:
                accepted = True
                break
            lam = max(4.0 * lam, 1e-3)
        if not accepted:
            break
        lam = lam / 4.0 if lam > 1e-6 else 0.0
        p, c = p_new, c_new
        size = float(np.sqrt(max(step @ N @ step, 0.0)))  # the step in units of the posterior σ
        if size < tol or it == max_iterations:
            break
        r, J, jtw = _unpack(evaluate(p, True))
        n_eval += 1
        if r is not r_new:  # (the trial's own residuals, e.g. GNWindow.evaluate's ``ahead``: c is their cost)
            c = cost(p, r)
    # the covariance at the last linearisation (the final step is small: the same to first order)
    if it == 0:  # no iteration: Jᵀ W J at p0, formed here as the loop forms it (once for the covariances, the result)
        live = live_rows(J_lin)
        Jl = J_lin[live]
        JWJ = (Jl * W[live, None]).T @ Jl
    cov = posterior_cov(J_lin, W, s2, prior, JWJ)
    k2 = (residual_scale2(r_lin, sigma, huber, len(p)) if clusters is None else
          cluster_scale2(r_lin, J_lin, sigma, huber, clusters, JWJ, live))
    cov_scaled = posterior_cov(J_lin, W, float(sigma) ** 2 * k2, prior, JWJ) if np.isfinite(k2) else cov
    return GNResult(p=p, cov=cov, cost=c, iterations=it, evaluations=n_eval, residuals=r_lin, jacobian=J_lin,
                    p_lin=p_lin, weights=W, scale2=k2, cov_scaled=cov_scaled, checked=checked or it == 0, jtwj=JWJ)


def live_rows(J: np.ndarray) -> np.ndarray:
    """Indices of the rows of J (m, k) with a non-zero entry."""
    J = np.asarray(J)
    if J.shape[1] == 0:
        return np.zeros(0, np.int64)
    live = J[:, 0] != 0.0
    for j in range(1, J.shape[1]):
        live |= J[:, j] != 0.0
    return np.flatnonzero(live)


def _unpack(out: tuple) -> tuple:
    return (out[0], out[1], out[2] if len(out) > 2 else None)


def fold(prior: Prior, p_lin: np.ndarray, r: np.ndarray, J: np.ndarray, sigma: float,
         weights: np.ndarray | None = None, nuisance: tuple | None = None) -> Prior:
    """The posterior of ``prior`` and the linearised observation r(p) ≈ r + J (p − p_lin) with noise σ
    (a Kalman measurement update in information form):  P⁺ = (P⁻¹ + A)⁻¹,  m⁺ = P⁺ (P⁻¹ m + A p_lin − g),
    A = JᵀWJ/σ², g = JᵀWr/σ².

    ``nuisance`` = (J_c (m, k_c), c_lin (k_c,), N(m_c, P_c)): unknowns of this observation alone (a window's
    correction of its starting states, linearised at c_lin), integrated out under their prior — the Schur
    complement  A ← A − B C⁻¹ Bᵀ,  g ← g − B C⁻¹ g_c  with  B = JᵀW J_c/σ²,  C = J_cᵀW J_c/σ² + P_c⁻¹,
    g_c = J_cᵀW r/σ² + P_c⁻¹ (c_lin − m_c): the observation then informs θ only as far as the correction cannot
    explain it too (e.g. the past re-simulated with another θ, nearly collinear with θ itself)."""
    W = np.ones(len(r)) if weights is None else weights
    s2 = float(sigma) ** 2
    info = prior.info
    JW = J * W[:, None]
    if nuisance is None or not np.shape(nuisance[0])[1]:
        cov = _sym_inv(info + JW.T @ J / s2)
        mean = cov @ (info @ prior.mean + JW.T @ (J @ p_lin - r) / s2)
        return Prior(mean, cov)
    Jc, c_lin, pc = nuisance
    ic = pc.info
    B = JW.T @ Jc / s2
    C = Jc.T @ (Jc * W[:, None]) / s2 + ic
    gc = Jc.T @ (W * r) / s2 + ic @ (np.asarray(c_lin, np.float64) - pc.mean)
    BC = np.linalg.solve(0.5 * (C + C.T), B.T).T  # B C⁻¹ (k, k_c)
    A = JW.T @ J / s2 - BC @ B.T
    g = JW.T @ r / s2 - BC @ gc
    cov = _sym_inv(info + 0.5 * (A + A.T))
    mean = cov @ (info @ prior.mean + A @ p_lin - g)
    return Prior(mean, cov)


def inflate(prior: Prior, q: np.ndarray) -> Prior:
    """Process noise: P ← P + diag(q²) (a random walk of the unknowns with σ = q per frame)."""
    return Prior(prior.mean.copy(), prior.cov + np.diag(np.asarray(q, np.float64) ** 2))


def marginal(prior: Prior, idx: np.ndarray) -> Prior:
    """The Gaussian's marginal on the unknowns ``idx``."""
    idx = np.asarray(idx)
    return Prior(prior.mean[idx].copy(), prior.cov[np.ix_(idx, idx)].copy())


def marginal_information(n_data: np.ndarray, prior_info: np.ndarray, i: int) -> float:
    """The information the data give on unknown i when the others are estimated with it (their prior included):
    the Schur complement  I_i = N_ii − N_i,o (N_oo + P⁻¹_oo)⁻¹ N_o,i  of the data's normal matrix N = JᵀWJ/σ² (k, k)
    over the other unknowns o, with ``prior_info`` P⁻¹ (k, k) on them.  1/I_i is the variance of p_i from the data
    alone; a parameter that trades against another (ν against E) has I_i ≪ N_ii."""
    n_data, prior_info = np.asarray(n_data, np.float64), np.asarray(prior_info, np.float64)
    o = np.array([j for j in range(len(n_data)) if j != i], dtype=int)
    if not len(o):
        return float(n_data[i, i])
    a = n_data[np.ix_(o, o)] + prior_info[np.ix_(o, o)]
    return float(n_data[i, i] - n_data[i, o] @ np.linalg.solve(0.5 * (a + a.T), n_data[o, i]))


def weakly_informed(n_data: np.ndarray, prior_info: np.ndarray, arrival_var: np.ndarray, idx, ratio: float
                    ) -> np.ndarray:
    """Per unknown i in ``idx`` (bool array): whether the data inform it less than ``ratio`` × its arrival cost does,
    I_i · P_ii < ratio, with I_i = :func:`marginal_information` (the others estimated with it) and P_ii =
    ``arrival_var`` [i] the variance of everything before.  Such an unknown is better held at its estimate: the
    window cannot tell it from the others, and moving it moves them (ν against E)."""
    return np.array([marginal_information(n_data, prior_info, i) * float(arrival_var[i]) < ratio for i in idx], bool)


def matched_arrival(arrival: Prior, p: np.ndarray, n_data: np.ndarray, prior_info: np.ndarray, idx,
                    threshold: float) -> tuple[Prior, np.ndarray]:
    """Covariance matching of the arrival cost N(m, P) against one window's data, per unknown i in ``idx``.

    The window's estimate p_i (its data under the prior) is the precision-weighted mean of m_i and of where the
    data alone put it, θ_d = m_i + (p_i − m_i)(P_ii + V_i)/P_ii, with V_i = 1/I_i (:func:`marginal_information` of
    the data's normal matrix ``n_data`` (k, k), ``prior_info`` (k, k) on the others).  d_i = |θ_d − m_i| / √(P_ii + V_i)
    is ~N(0, 1) while the arrival cost is consistent with the data; it is tested only where the data inform p_i at
    least as much as the arrival cost does (I_i P_ii ≥ 1).  Where d_i > ``threshold`` it is not (its
    frames were linearised far from the data's θ — a far start —, or the material changed): P_ii is raised to
    (θ_d − m_i)² − V_i (d_i = 1 then), its correlations kept.  Returns (the arrival cost, d (len(idx),))."""
    m, P = arrival.mean, arrival.cov.astype(np.float64)  # (a copy)
    d = np.zeros(len(idx))
    for j, i in enumerate(idx):
        pii = float(P[i, i])
        info = marginal_information(n_data, prior_info, i)
        if not info * pii >= 1.0:  # the data inform it less than the arrival cost: θ_d is p's round-off × V/P
            continue
        v = 1.0 / info
        gap = (float(p[i]) - float(m[i])) * (pii + v) / pii  # θ_d − m_i
        d[j] = abs(gap) / np.sqrt(pii + v)
        if d[j] > threshold:
            f = np.sqrt(max(gap * gap - v, pii) / pii)
            P[i, :] *= f
            P[:, i] *= f
    return Prior(m.copy(), 0.5 * (P + P.T)), d


def condition(prior: Prior, i: int, value: float, hold: float = 1e-10) -> Prior:
    """The Gaussian ``prior`` conditioned on p_i = ``value``:  m_o + P_oi (value − m_i)/P_ii,
    P_oo − P_oi P_io / P_ii  on the others; p_i itself keeps ``hold`` × P_ii of variance (held there by a
    solve, not singular) and no correlation."""
    m, P = prior.mean.astype(np.float64).copy(), prior.cov.astype(np.float64)
    pii = float(P[i, i])
    col = P[:, i].copy()
    mean = m + col * (float(value) - m[i]) / pii
    cov = P - np.outer(col, col) / pii
    mean[i] = float(value)
    cov[i, :], cov[:, i] = 0.0, 0.0
    cov[i, i] = hold * pii
    return Prior(mean, 0.5 * (cov + cov.T))


def posterior_cov(J: np.ndarray, weights: np.ndarray, sigma2: float, prior: Prior,
                  jtwj: np.ndarray | None = None) -> np.ndarray:
    """(Jᵀ W J / σ² + P⁻¹)⁻¹ (k, k): the Laplace covariance of one linearisation J (m, k) under ``prior``; ``jtwj``
    (k, k): Jᵀ W J when already formed (gauss_newton's, as (J W)ᵀ J over J's non-zero rows: the same to rounding)."""
    if jtwj is None:
        JW = np.asarray(J, np.float64) * np.asarray(weights, np.float64)[:, None]
        jtwj = JW.T @ J
    return _sym_inv(jtwj / float(sigma2) + prior.info)


def bounded_sigma(value: np.ndarray, sd: np.ndarray, lower, upper, pinned: float = 0.02) -> np.ndarray:
    """σ of a parameter confined to [lower, upper] (elementwise): ``sd`` (its posterior σ), but where the value lies
    within ``pinned`` × (upper − lower) of a bound — held there by the bound, not located by the data — at least
    the σ of a uniform prior over the range, (upper − lower)/√12.  (A transform that maps the range onto ℝ, e.g.
    a sigmoid, has a vanishing slope at its ends: its delta-method σ shrinks to 0 there whatever the data say.)"""
    value, sd = np.asarray(value, np.float64), np.asarray(sd, np.float64)
    lo, hi = np.broadcast_to(np.asarray(lower, np.float64), value.shape), np.broadcast_to(
        np.asarray(upper, np.float64), value.shape)
    width = hi - lo
    at = (width > 0) & ((value - lo <= pinned * width) | (hi - value <= pinned * width))
    return np.where(at, np.maximum(sd, width / np.sqrt(12.0)), sd)


@dataclass
class ChangeDetector:
    """An innovation test for a change of the unknowns (a one-sided CUSUM of the normalised innovation).

    Per new frame, its residuals r (m,) are predicted with the current estimate (before the frame is used) and
    normalised by the noise level σ the window fits reach:  z = rᵀr / (m σ²)  (≈ 1 while the model with the
    predicted unknowns explains the frame as well as the window does).  One frame with z > ``threshold``² is a
    change at once.  A smaller excess is declared once it persists: the CUSUM  g ← max(0, g + z/b − 1 − drift)
    (h = threshold² − 1 − drift) runs on z relative to its own baseline b = max(1, median of the z seen so far;
    1 until three are seen).  One-step predictions carry model error that the window
    fits (with their state correction) do not show, so z sits above 1 and grows with the load while the material
    stays the same; the baseline keeps that from accumulating into a false change (``make demo``: z = 2.3–7.7
    over frames 3–8 while E was right, 14.5 at the true step).  After a change g restarts; the baseline, the
    model error of one-step predictions, stays (the re-convergence after a change would otherwise look like one).
    """

    threshold: float = 3.0
    drift: float = 1.0
    g: float = 0.0
    seen: list = field(default_factory=list)
    #: True: nothing is declared before three z are seen, and the one-frame rule is z/b > threshold² too — for
    #: residuals whose noise level is itself estimated from misfits that grow with the motion and with θ's error
    #: (images: z = 36–65 over the first frames of a start at 0.5 E_true, more than at a true step of E)
    relative: bool = False

    @staticmethod
    def ratio(r: np.ndarray, sigma: float) -> float:
        """z = rᵀr / (m σ²)."""
        r = np.asarray(r, np.float64)
        return float(r @ r) / (len(r) * sigma * sigma) if len(r) and sigma > 0 else 0.0

    def baseline(self) -> float:
        """b = max(1, median of the z seen so far); 1 until three are seen."""
        return max(1.0, float(np.median(self.seen))) if len(self.seen) >= 3 else 1.0

    def update(self, z: float) -> bool:
        """Add one frame's normalised innovation z; True when a change is declared (g then restarts)."""
        if self.threshold <= 0:
            return False
        b = self.baseline()
        if self.relative and len(self.seen) < 3:
            self.seen.append(float(z))
            return False
        self.g = max(0.0, self.g + z / b - 1.0 - self.drift)
        self.seen.append(float(z))
        if (z / b if self.relative else z) > self.threshold ** 2 or self.g > self.threshold ** 2 - 1.0 - self.drift:
            self.g = 0.0
            return True
        return False


def process_noise(frame: int, changes: list, window: int, settled: float, after_change: float) -> float:
    """σ of the random walk per frame that the arrival cost takes at ``frame``: max(``settled``, ``after_change``)
    during the window + 5 frames after the last detected change of the unknowns (``changes``: their frames), while
    the estimate re-settles on the new value; ``settled`` otherwise (a constant material: the estimate averages over
    the motion rather than follow a model error that varies with it)."""
    if changes and 0 <= frame - changes[-1] < window + 5:
        return float(max(settled, after_change))
    return float(settled)


def _sym_inv(a: np.ndarray) -> np.ndarray:
    a = 0.5 * (a + a.T)
    try:
        c = np.linalg.cholesky(a)
        ci = np.linalg.inv(c)
        out = ci.T @ ci
    except np.linalg.LinAlgError:
        out = np.linalg.pinv(a)
    return 0.5 * (out + out.T)


@dataclass
class WindowFilter:
    """The arrival cost of a sliding-window estimator over θ (module docstring).

    prior: N(m, P) on θ's unknowns, summarising the frames before the window; q (kθ,): process noise σ
    per frame.  ``leave(p_lin, r, J, σ, W, nuisance)`` folds the linearised residuals of the frame that leaves the
    window (:func:`fold`) and adds the process noise of one frame; ``advance()`` adds only the process noise (a
    frame arrived and none left, e.g. while the window grows).
    """

    prior: Prior
    q: np.ndarray

    def leave(self, p_lin: np.ndarray, r: np.ndarray, J: np.ndarray, sigma: float,
              weights: np.ndarray | None = None, nuisance: tuple | None = None) -> None:
        self.prior = inflate(fold(self.prior, p_lin, r, J, sigma, weights, nuisance), self.q)

    def advance(self) -> None:
        self.prior = inflate(self.prior, self.q)
