"""Forward sensitivities of a full-space window (tangent linear model of stages.sim.scene).

A window of solved frames satisfies r_t(x_t; x_{t−1}, x_{t−2}, θ) = ∇_x Φ_t = 0 (scene.py).  Along a
parameter direction p (a change of θ = (E, ν) per region shared by the window frames, and/or a change
of the two states before the window) the states move by S_t = dx_t/dp, the solution of

    H_t S_t = −(∂r_t/∂θ) θ̇ − (∂r_t/∂x_{t−1}) S_{t−1} − (∂r_t/∂x_{t−2}) S_{t−2},

H_t = ∂r_t/∂x_t the exact (unprojected) Hessian, factorised once per frame and reused for every
direction; the right-hand sides are JAX Jacobian–vector products of scene._residual.  On the DOFs of hard
handles x_t is an input (the target): S_t = 0 there, and H_t, the rhs keep the free DOFs only.  This is the
forward twin of scene.window_adjoint: for any v, Σ_t ⟨v_t, S_t⟩ equals the adjoint's ⟨dL/dθ, θ̇⟩ with
dL/dX = v (tests hold both to finite differences).
"""
from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .linsolve import NotPositiveDefinite
from .scene import _cache, _constrain, _data_for, _per_frame, _residual, hessian


@jax.jit
def _residual_jvp(x, x_prev, x_prev2, young, poisson, s, inputs, t_xp, t_xpp, t_e, t_nu):
    """(∂r/∂x_prev) t_xp + (∂r/∂x_prev2) t_xpp + (∂r/∂E) t_e + (∂r/∂ν) t_nu, batched over the leading axis
    of the tangents (k, …)."""
    def one(a, b, c, d):
        return jax.jvp(lambda xp, xpp, E, nu: _residual(x, xp, xpp, E, nu, s, inputs),
                       (x_prev, x_prev2, young, poisson), (a, b, c, d))[1]

    return jax.vmap(one)(t_xp, t_xpp, t_e, t_nu)


def theta_directions(n_regions: int, fit_poisson: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions of θ = (E_1..E_R, ν_1..ν_R): (dE (k, R), dν (k, R)), k = 2R (R without ν)."""
    R = n_regions
    k = 2 * R if fit_poisson else R
    de, dn = np.zeros((k, R)), np.zeros((k, R))
    de[np.arange(R), np.arange(R)] = 1.0
    if fit_poisson:
        dn[R + np.arange(R), np.arange(R)] = 1.0
    return de, dn


def window_sensitivity(scene, inputs: Sequence, young, poisson, X, x_before, d_young, d_poisson,
                       d_before=None, solver: str = "auto", kernels: str = "auto") -> np.ndarray:
    """S (k, w, n, 3) = dX/dp along k directions for a window of w solved frames.

    young/poisson (w, R) or (R,): θ of the window frames; X (w, n, 3) the solved states; x_before
    (2, n, 3) = [x_{t0−2}, x_{t0−1}]; d_young, d_poisson (k, R): the change of θ along each direction
    (the same for every window frame); d_before (k, 2, n, 3) or None: the change of the states before
    the window along each direction (0 when None).
    """
    X = np.asarray(X, np.float64)
    w = X.shape[0]
    R = scene.n_regions
    young, poisson = _per_frame(young, w, R), _per_frame(poisson, w, R)
    xb = np.asarray(x_before, np.float64)
    de, dn = np.asarray(d_young, np.float64), np.asarray(d_poisson, np.float64)
    k = de.shape[0]
    db = np.zeros((k, 2) + xb.shape[1:]) if d_before is None else np.asarray(d_before, np.float64)
    s = _data_for(scene)
    cache = _cache(scene)
    S = np.zeros((k, w) + X.shape[1:])

    def prev(t, j):  # state and its tangents at x_{t−j}
        i = t - j
        return (X[i], S[:, i]) if i >= 0 else (xb[2 + i], db[:, 2 + i])

    for t in range(w):
        x1, s1 = prev(t, 1)
        x2, s2 = prev(t, 2)
        rhs = -np.asarray(_residual_jvp(jnp.asarray(X[t]), jnp.asarray(x1), jnp.asarray(x2), jnp.asarray(young[t]),
                                        jnp.asarray(poisson[t]), s, inputs[t], jnp.asarray(s1), jnp.asarray(s2),
                                        jnp.asarray(de), jnp.asarray(dn)))
        H = hessian(scene, inputs[t], X[t], x1, young[t], poisson[t], project=False, kernels=kernels)
        S[:, t] = _solve_many(cache, solver, H, rhs.reshape(k, -1)).reshape((k,) + X.shape[1:])
    return S


def _solve_many(cache, solver: str, H, B: np.ndarray) -> np.ndarray:
    """H⁻¹ b for each row b of B (k, 3n), one factorisation (Cholesky when positive definite, else LU); on the
    DOFs of hard handles (inputs: x_t there is the target) the solution is 0 (scene.solve_free)."""
    data = np.array(H.data, np.float64)
    mask = cache.fixed()[0]
    if mask is not None:
        B = np.array(B, np.float64)
        B[:, mask] = 0.0
        _constrain(cache, data)
    lin = cache.solver(solver)
    try:
        lin.factor(data)
    except NotPositiveDefinite:
        lin = cache.solver("splu")
        lin.factor(data)
    return np.stack([lin.solve(b) for b in B]) if len(B) else np.zeros_like(B)
