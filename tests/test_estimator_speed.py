"""Speed paths of the gn estimator held to their slow twins."""
from __future__ import annotations

import jax
import numpy as np

import stages.sim.static as st
from test_static import POISSON, YOUNG, reduced  # noqa: F401  (the module-scoped reduced model fixture)


def test_jitted_theta_jacobian_of_the_static_gradient_is_the_eager_one(reduced):  # noqa: F811
    """stages.sim.static._dgrad_dtheta (jitted once per model) against the eager jacfwd it replaced, at the
    reduced equilibrium and at a perturbed state, and the sensitivity built on it against −H⁻¹ ∂h/∂θ from the
    eager one."""
    scene, inputs, model = reduced
    sm = st.static_model(model)
    rin = sm.reduce_inputs(inputs)
    z0 = st.reduced_equilibrium(model, inputs, YOUNG, POISSON)
    E, nu = st._theta(sm.scene, YOUNG, POISSON)
    grad = jax.grad(sm.energy_jax, argnums=0)
    for z in (z0, z0 + 0.1 * np.random.default_rng(0).normal(size=z0.shape) * np.abs(z0).max()):
        a = sm._args(z, z, z, E, nu, rin)
        slow = jax.jacfwd(lambda e, n: grad(a[0], a[1], a[2], e, n, rin), argnums=(0, 1))(E, nu)
        fast = st._dgrad_dtheta(sm)(a[0], a[1], a[2], E, nu, rin)
        for s, f in zip(slow, fast):
            s, f = np.asarray(s), np.asarray(f)
            assert np.abs(f - s).max() <= 1e-10 * np.abs(s).max()
    S = st.reduced_equilibrium_sensitivity(model, inputs, YOUNG, POISSON, z0)
    a = sm._args(z0, z0, z0, E, nu, rin)
    h = np.asarray(sm._H(*a))
    jE, jn = jax.jacfwd(lambda e, n: grad(a[0], a[1], a[2], e, n, rin), argnums=(0, 1))(E, nu)
    want = -np.linalg.solve(0.5 * (h + h.T), np.concatenate([np.asarray(jE), np.asarray(jn)], axis=1)).T
    assert np.abs(S - want).max() <= 1e-9 * np.abs(want).max()
