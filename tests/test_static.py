"""Static equilibrium (stages.sim.static): the residual, continuation, and the adjoint and sensitivity
against central finite differences, in full space and in a reduced (PCA and autoencoder) subspace."""
from __future__ import annotations

import numpy as np
import pytest

from stages.sim import static as st
from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import box_tets
from stages.sim.scene import FrameInputs, HandleSpec, ObstacleSpec, Scene, SimulationError, step

YOUNG, POISSON = np.array([3e4, 9e4]), np.array([0.40, 0.45])


def cantilever(obstacle: bool = False, handles: bool = True, hard: bool = False) -> tuple[Scene, FrameInputs]:
    """0.2 m bar, 10×2×2 cells, clamped at x = 0, two regions (x > 0.1 stiffer), sagging under gravity;
    optionally a floor 4 cm below that the tip touches."""
    v, t = box_tets((10, 2, 2), (0.2, 0.02, 0.02))
    vol, dmi, m = rest_quantities(v, t, 1000.0)
    region = (v[t].mean(1)[:, 0] > 0.1).astype(np.int64)
    hid = np.nonzero(v[:, 0] < 1e-9)[0]
    obs = (ObstacleSpec("floor", "plane", np.array([0.0, 0.0, 1.0]), -0.04, 0.0, None),) if obstacle else ()
    hs = (HandleSpec("clamp", hid, 1e4, hard=hard),) if handles else ()
    scene = Scene(rest=v, tets=t, dm_inv=dmi, volumes=vol, masses=m, tet_region=region, n_regions=2,
                  region_names=("a", "b"), material="stable_neohookean", dt=1 / 30,
                  gravity=np.array([0, 0, -9.81]), handles=hs, loads=(), obstacles=obs, friction=0.3,
                  contact_stiffness=2e3, contact_margin=1e-3)
    inputs = FrameInputs((v[hid],) if handles else (), np.zeros_like(v), np.tile([0, 0, 0, 1.0, 0, 0, 0],
                                                                                   (len(obs), 1)))
    return scene, inputs


@pytest.mark.parametrize("obstacle", [False, True])
def test_equilibrium_residual_is_below_tolerance(obstacle):
    scene, inputs = cantilever(obstacle)
    info = {}
    x = st.equilibrium(scene, inputs, YOUNG, POISSON, info=info)
    r = st.residual(scene, inputs, YOUNG, POISSON, x)
    weight = float(np.linalg.norm(scene.masses[:, None] * scene.gravity))
    assert np.linalg.norm(r) <= 1e-8 * weight
    sag = -x[:, 2].min()
    assert sag > 0.02  # a real sag (m), not the rest shape
    if obstacle:  # the floor holds the tip up at its margin
        assert x[:, 2].min() > -0.04 - 2e-3
    # a time step from the equilibrium at rest (zero velocity) stays there: the dynamic residual is
    # the static one when x_{t-1} = x_{t-2} = x*
    x1, _ = step(scene, inputs, YOUNG, POISSON, x, x, rtol=1e-10)
    assert np.abs(x1 - x).max() < 1e-8 * sag


def test_continuation_reaches_the_same_equilibrium():
    """With a Newton budget too small for one stage, load stepping takes over and lands on the same x*."""
    scene, inputs = cantilever()
    soft = YOUNG / 3
    direct = st.equilibrium(scene, inputs, soft, POISSON)
    info = {}
    stepped = st.equilibrium(scene, inputs, soft, POISSON, max_iterations=10, info=info)
    assert info["stages"] > 1
    assert np.abs(stepped - direct).max() < 1e-9


def test_unsupported_object_fails_with_a_clear_error():
    scene, inputs = cantilever(handles=False)
    with pytest.raises(SimulationError, match="handles or an obstacle"):
        st.equilibrium(scene, inputs, YOUNG, POISSON, max_iterations=15)


def _loss(x, w):
    return float(np.sum(w * x) + 0.5 * np.sum((x[:, 2] + 0.01) ** 2))


def _dloss(x, w):
    g = w.copy()
    g[:, 2] += x[:, 2] + 0.01
    return g


@pytest.mark.parametrize("obstacle,hard", [(False, False), (True, False), (False, True)])
def test_adjoint_and_sensitivity_against_finite_differences(obstacle, hard):
    scene, inputs = cantilever(obstacle, hard=hard)
    x = st.equilibrium(scene, inputs, YOUNG, POISSON)
    w = np.random.default_rng(0).normal(size=x.shape)
    g = st.equilibrium_adjoint(scene, inputs, YOUNG, POISSON, x, _dloss(x, w))
    S = st.equilibrium_sensitivity(scene, inputs, YOUNG, POISSON, x)
    assert S.shape == (4,) + x.shape
    for k in range(4):  # E_a, E_b, ν_a, ν_b
        theta = np.concatenate([YOUNG, POISSON])
        h = 1e-4 * theta[k]
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        xp = st.equilibrium(scene, inputs, tp[:2], tp[2:], x_init=x)
        xm = st.equilibrium(scene, inputs, tm[:2], tm[2:], x_init=x)
        fd_x = (xp - xm) / (2 * h)
        fd_l = (_loss(xp, w) - _loss(xm, w)) / (2 * h)
        an = (g["young"] if k < 2 else g["poisson"])[k % 2]
        assert an == pytest.approx(fd_l, rel=1e-5, abs=1e-9 * abs(fd_l) + 1e-12)
        assert np.abs(S[k] - fd_x).max() <= 1e-5 * np.abs(fd_x).max()
    if hard:  # the clamped vertices sit at their targets and do not move with θ
        ids = scene.handles[0].ids
        assert np.abs(x[ids] - inputs.handle_targets[0]).max() == 0.0
        assert np.abs(S[:, ids]).max() == 0.0


def test_adjoint_equals_sensitivity_contraction():
    """dL/dθ = Σ (dx*/dθ) · ∂L/∂x: the adjoint and the forward sensitivity agree to round-off."""
    scene, inputs = cantilever()
    x = st.equilibrium(scene, inputs, YOUNG, POISSON)
    dl = np.random.default_rng(1).normal(size=x.shape)
    g = st.equilibrium_adjoint(scene, inputs, YOUNG, POISSON, x, dl)
    S = st.equilibrium_sensitivity(scene, inputs, YOUNG, POISSON, x)
    via_s = np.einsum("knd,nd->k", S, dl)
    np.testing.assert_allclose(np.concatenate([g["young"], g["poisson"]]), via_s, rtol=1e-8,
                               atol=1e-10 * np.abs(via_s).max())


# --------------------------------------------------------------------------- reduced space
@pytest.fixture(scope="module")
def reduced():
    """A ReducedModel (PCA, r = 8) on snapshots of equilibria at several E and ν, and a dynamic sag."""
    from stages.sim.scene import simulate
    from stages.subspace import ReducedModel
    from stages.subspace.train import fit_subspace

    scene, inputs = cantilever()
    snaps = [st.equilibrium(scene, inputs, YOUNG * s, POISSON - d) for s in (0.5, 1.0, 2.0) for d in (0.0, 0.05)]
    snaps += list(simulate(scene, [inputs] * 6, YOUNG, POISSON))
    sub, _ = fit_subspace("pca", scene.rest, scene.masses, np.stack(snaps), 8)
    return scene, inputs, ReducedModel(sub, scene)


def test_reduced_equilibrium_is_a_projected_equilibrium(reduced):
    scene, inputs, model = reduced
    z = st.reduced_equilibrium(model, inputs, YOUNG, POISSON)
    x = model.decode(z)
    r = st.residual(scene, inputs, YOUNG, POISSON, x)
    weight = float(np.linalg.norm(model.jacobian_transpose(z, scene.masses[:, None] * scene.gravity)))
    assert np.linalg.norm(model.jacobian_transpose(z, r)) <= 1e-7 * weight  # Jᵀ r(φ(z*)) = 0
    x_full = st.equilibrium(scene, inputs, YOUNG, POISSON)
    assert np.abs(x - x_full).max() < 0.05 * np.abs(x_full - scene.rest).max()  # the subspace holds x*


def test_reduced_adjoint_and_sensitivity_against_finite_differences(reduced):
    scene, inputs, model = reduced
    z = st.reduced_equilibrium(model, inputs, YOUNG, POISSON)
    w = np.random.default_rng(2).normal(size=scene.rest.shape)
    x = model.decode(z)
    g = st.reduced_equilibrium_adjoint(model, inputs, YOUNG, POISSON, z, dL_dx=_dloss(x, w))
    S = st.reduced_equilibrium_sensitivity(model, inputs, YOUNG, POISSON, z)
    assert S.shape == (4, model.dim)
    theta = np.concatenate([YOUNG, POISSON])
    for k in range(4):
        h = 1e-4 * theta[k]
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        zp = st.reduced_equilibrium(model, inputs, tp[:2], tp[2:], z_init=z)
        zm = st.reduced_equilibrium(model, inputs, tm[:2], tm[2:], z_init=z)
        fd_l = (_loss(model.decode(zp), w) - _loss(model.decode(zm), w)) / (2 * h)
        an = (g["young"] if k < 2 else g["poisson"])[k % 2]
        assert an == pytest.approx(fd_l, rel=1e-5)
        fd_z = (zp - zm) / (2 * h)
        assert np.abs(S[k] - fd_z).max() <= 1e-5 * np.abs(fd_z).max()
