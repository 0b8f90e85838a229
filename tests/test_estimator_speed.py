"""Speed paths of the gn estimator held to their slow twins."""
from __future__ import annotations

import jax
import numpy as np
import pytest

import stages.sim.static as st
from test_static import POISSON, YOUNG, reduced  # noqa: F401  (the module-scoped reduced model fixture)
from test_vision_bias import capture  # noqa: F401  (the module-scoped image capture fixture)


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


@pytest.mark.parametrize("anchor", ["rebind", "offset"])
def test_gn_image_jacobian_by_forward_mode_is_held_to_the_central_difference_twin(capture, anchor):  # noqa: F811
    """GNWindow.evaluate with images, the Gaussians anchored at x_0(θ) (start = equilibrium; re-bound there, or offset by
    x_0(θ) − x_fit) and two state-correction
    columns: the forward-mode path (VisionObservation.jacobian_mode "jvp": residuals and J in one pass, Jᵀ W r from
    the exact J) against the central-difference path ("fd": jacobian + binding_jacobian, Jᵀ W r by autograd).  The
    residuals are the same floats; Jᵀ W r agrees with the autograd product to float32 accuracy (1e-4) for random
    weights W; the columns agree with the central differences within their accuracy (15 %: rasterization is only
    piecewise smooth, and the joint anchor/position differences cancel)."""
    from stages.parameters import params_from_theta
    from stages.windows import GNWindow
    from test_vision_bias import E_TRUE, _objective

    cap, ws, _ = capture
    obj, backend = _objective(cap, ws, anchor)
    gn = GNWindow(obj, True, np.zeros(1))
    p = np.concatenate(params_from_theta(np.array([0.7 * E_TRUE]), np.array([0.42]), (0.3, 0.49)))
    E, nu = gn.theta(p)[:2]
    past = obj.win.forward([0, 1, 2], E, nu, None)
    before = past[1:3]
    frames = [3, 4]
    x_b = backend.decode(np.asarray(before))
    D = np.stack([np.stack([v, v]) for v in (x_b[1] - x_b[0], np.roll(x_b[1] - x_b[0], 1, axis=0))])
    pD = np.concatenate([p, np.zeros(2)])
    out = {}
    for mode in ("jvp", "fd"):
        obj.obs.jacobian_mode = mode
        assert obj.obs.uses_jvp() == (mode == "jvp")
        out[mode] = gn.evaluate(frames, pD, before, D, True)
    (r1, J1), (r2, J2, jtw2) = out["jvp"], out["fd"]  # the forward mode's J is exact: no product of its own
    assert np.array_equal(r1, r2)
    assert J1.shape == J2.shape == (len(r1), 4)
    rng = np.random.default_rng(0)
    for _ in range(3):
        W = rng.uniform(0.0, 2.0, len(r1))
        g1, g2 = J1.T @ (W * r1), jtw2(W)
        assert np.allclose(g1, g2, rtol=1e-4, atol=1e-4 * np.abs(g2).max()), (g1, g2)
    for j in range(4):
        assert np.linalg.norm(J2[:, j]) > 0
        assert np.linalg.norm(J1[:, j] - J2[:, j]) <= 0.15 * np.linalg.norm(J2[:, j]), j
