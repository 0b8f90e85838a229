"""Forward sensitivities of a reduced window (tangent linear model of stages.subspace.reduced).

Each frame solves h_t(z_t; z_{t−1}, z_{t−2}, θ) = ∂E/∂z = 0.  Along a direction p (a change θ̇ of
θ = (E, ν) per region shared by the window frames, and/or a change of the two states before the window)

    H_t S_t = −(∂h_t/∂θ) θ̇ − (∂h_t/∂z_{t−1}) S_{t−1} − (∂h_t/∂z_{t−2}) S_{t−2},     S_t = dz_t/dp (r,)

with H_t = ∂²E/∂z² (r × r, decoder curvature included), solved for all directions at once; the
right-hand sides are JAX Jacobian–vector products.  The positions move by J(z_t) S_t, J = ∂φ/∂z.
The forward twin of ReducedModel.window_adjoint.
"""
from __future__ import annotations

from functools import partial
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .reduced import ReducedInputs, _grad


@partial(jax.jit, static_argnames=("kind", "reference"))
def _hjvp(z, z1, z2, young, poisson, rin, t1, t2, te, tn, d, kind, reference):
    """(∂h/∂z_{t−1}) t1 + (∂h/∂z_{t−2}) t2 + (∂h/∂E) te + (∂h/∂ν) tn, batched over the tangents' first axis."""
    def one(a, b, c, e):
        return jax.jvp(lambda p1, p2, E, nu: _grad(z, p1, p2, E, nu, rin, d, kind, reference),
                       (z1, z2, young, poisson), (a, b, c, e))[1]

    return jax.vmap(one)(t1, t2, te, tn)


def window_sensitivity(model, inputs: Sequence, young, poisson, Z, z_before, d_young, d_poisson,
                       d_before=None) -> np.ndarray:
    """S (k, w, r) = dZ/dp along k directions for a window of w solved reduced states Z (w, r).

    young/poisson (w, R) or (R,); z_before (2, r) = [z_{t0−2}, z_{t0−1}]; d_young, d_poisson (k, R): the
    change of θ along each direction (shared by the window frames); d_before (k, 2, r) or None.
    """
    Z = np.asarray(Z, np.float64)
    w, r = Z.shape
    young, poisson = np.asarray(young, np.float64), np.asarray(poisson, np.float64)
    if young.ndim == 1:
        young, poisson = np.tile(young, (w, 1)), np.tile(poisson, (w, 1))
    zb = np.asarray(z_before, np.float64)
    de, dn = jnp.asarray(d_young, jnp.float64), jnp.asarray(d_poisson, jnp.float64)
    k = de.shape[0]
    db = np.zeros((k, 2, r)) if d_before is None else np.asarray(d_before, np.float64)
    rins = [u if isinstance(u, ReducedInputs) else model.reduce_inputs(u) for u in inputs]
    states = np.concatenate([zb, Z])  # index t + 2 is window frame t
    tang = np.concatenate([db, np.zeros((k, w, r))], axis=1)
    d = model.data
    for t in range(w):
        args = model._args(states[t + 2], states[t + 1], states[t], young[t], poisson[t], rins[t])
        rhs = -np.asarray(_hjvp(*args, jnp.asarray(tang[:, t + 1]), jnp.asarray(tang[:, t]), de, dn, d, model.kind,
                                model.reference))
        H = np.asarray(model._H(*args))
        tang[:, t + 2] = np.linalg.solve(0.5 * (H + H.T), rhs.T).T
    return tang[:, 2:]


def decode_sensitivity(model, Z, S) -> np.ndarray:
    """dX/dp (k, w, n, 3) = J(z_t) S_t for reduced sensitivities S (k, w, r) at states Z (w, r)."""
    Z = np.asarray(Z, np.float64)
    out = []
    for t in range(len(Z)):
        J = model.jacobian(Z[t])  # (n, 3, r)
        out.append(np.einsum("nir,kr->kni", J, S[:, t]))
    return np.stack(out, axis=1)
