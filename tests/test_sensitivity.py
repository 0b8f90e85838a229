"""Forward sensitivities dX/dp of a window (full space: stages.sim.sensitivity; reduced: stages.subspace.
sensitivity) against central finite differences of the simulation, and their agreement with the adjoint."""
from __future__ import annotations

import numpy as np
import pytest

from stages.sim.scene import simulate, window_adjoint
from stages.sim.sensitivity import theta_directions, window_sensitivity
from stages.subspace import ReducedModel
from stages.subspace.sensitivity import decode_sensitivity, window_sensitivity as reduced_sensitivity
from stages.subspace.train import fit_subspace
from test_subspace_reduced import POISSON, YOUNG, bar_scene, sequence_inputs

W0, W = 3, 3  # the window: frames 3, 4, 5


@pytest.fixture(scope="module")
def full():
    scene = bar_scene()
    inp = sequence_inputs(scene, 0, frames=W0 + W)
    X = simulate(scene, inp, YOUNG, POISSON, rtol=1e-12)
    return scene, inp, X


def _directions(shape_before, rng, R=2):
    """4 θ directions (unit E_r, unit ν_r) and one on the states before the window."""
    de, dn = theta_directions(R)
    de = np.concatenate([de * YOUNG[None], np.zeros((1, R))])  # dE of size E (relative unit)
    dn = np.concatenate([dn * 0.01, np.zeros((1, R))])
    db = np.zeros((len(de), 2) + shape_before)
    db[-1] = 1e-3 * rng.normal(size=(2,) + shape_before)
    return de, dn, db


def test_full_space_sensitivity_matches_finite_differences(full):
    scene, inp, X = full
    _check_sensitivity_against_fd(scene, inp, X, np.random.default_rng(0))


def _check_sensitivity_against_fd(scene, inp, X, rng):
    """The window's forward sensitivities along θ and state directions against central differences."""
    before = X[W0 - 2:W0]
    win = inp[W0:]
    de, dn, db = _directions(X.shape[1:], rng)
    S = window_sensitivity(scene, win, YOUNG, POISSON, X[W0:], before, de, dn, db)
    assert S.shape == (5, W) + X.shape[1:]
    h = 1e-4
    for j in range(len(de)):
        plus = simulate(scene, win, YOUNG + h * de[j], POISSON + h * dn[j], x_prev=before[1] + h * db[j, 1],
                        x_prev2=before[0] + h * db[j, 0], rtol=1e-12)
        minus = simulate(scene, win, YOUNG - h * de[j], POISSON - h * dn[j], x_prev=before[1] - h * db[j, 1],
                         x_prev2=before[0] - h * db[j, 0], rtol=1e-12)
        fd = (plus - minus) / (2 * h)
        assert np.linalg.norm(S[j] - fd) <= 1e-5 * np.linalg.norm(fd), j
        assert np.linalg.norm(fd) > 0


def test_full_space_sensitivity_is_the_adjoints_transpose(full):
    """Σ_t ⟨v_t, S_t⟩ = ⟨dL/dθ, θ̇⟩ + ⟨dL/dx_before, ẋ_before⟩ for L = Σ_t ⟨v_t, x_t⟩ (exact identity)."""
    scene, inp, X = full
    rng = np.random.default_rng(1)
    before = X[W0 - 2:W0]
    de, dn, db = _directions(X.shape[1:], rng)
    S = window_sensitivity(scene, inp[W0:], YOUNG, POISSON, X[W0:], before, de, dn, db)
    v = rng.normal(size=X[W0:].shape)
    g = window_adjoint(scene, inp[W0:], YOUNG, POISSON, X[W0:], before, v)
    for j in range(len(de)):
        lhs = float(np.sum(v * S[j]))
        rhs = float(g["young"].sum(0) @ de[j] + g["poisson"].sum(0) @ dn[j] + np.sum(g["x_before"] * db[j]))
        assert abs(lhs - rhs) <= 1e-8 * (abs(lhs) + abs(rhs) + 1e-30), j


@pytest.fixture(scope="module", params=["pca", "autoencoder"])
def reduced(request, full):
    scene, inp, X = full
    train = np.concatenate([simulate(scene, sequence_inputs(scene, s, frames=8), YOUNG, POISSON) for s in (1, 2)])
    if request.param == "pca":
        sub, _ = fit_subspace("pca", scene.rest, scene.masses, train, 6)
    else:
        sub, _ = fit_subspace("autoencoder", scene.rest, scene.masses, train, 4, epochs=20, seed=0, pca_dim=8)
    model = ReducedModel(sub, scene)
    Z = model.simulate(inp, YOUNG, POISSON, rtol=1e-12)
    return model, inp, Z


def test_reduced_sensitivity_matches_finite_differences(reduced):
    model, inp, Z = reduced
    rng = np.random.default_rng(2)
    zb = Z[W0 - 2:W0]
    win = inp[W0:]
    de, dn, db = _directions((model.dim,), rng)
    db[-1] *= 10.0
    S = reduced_sensitivity(model, win, YOUNG, POISSON, Z[W0:], zb, de, dn, db)
    assert S.shape == (5, W, model.dim)
    h = 1e-4
    for j in range(len(de)):
        # each difference's solves from a fresh Newton memory (ReducedModel.solver_memory): carried from one solve to
        # the next, it moves their last bits by the order of the solves, and one direction's differences by 1e-5
        # of their norm on some machines (under 1e-7 from a fresh memory)
        model.restore_solver_memory(None)
        plus = model.simulate(win, np.tile(YOUNG + h * de[j], (W, 1)), np.tile(POISSON + h * dn[j], (W, 1)),
                              z_prev=zb[1] + h * db[j, 1], z_prev2=zb[0] + h * db[j, 0], rtol=1e-12)
        model.restore_solver_memory(None)
        minus = model.simulate(win, np.tile(YOUNG - h * de[j], (W, 1)), np.tile(POISSON - h * dn[j], (W, 1)),
                               z_prev=zb[1] - h * db[j, 1], z_prev2=zb[0] - h * db[j, 0], rtol=1e-12)
        fd = (plus - minus) / (2 * h)
        assert np.linalg.norm(fd) > 0
        assert np.linalg.norm(S[j] - fd) <= 1e-5 * np.linalg.norm(fd), j
        dX = decode_sensitivity(model, Z[W0:], S[j:j + 1])[0]
        fdx = (model.decode(plus) - model.decode(minus)) / (2 * h)
        assert np.linalg.norm(dX - fdx) <= 1e-5 * np.linalg.norm(fdx), j


def test_reduced_sensitivity_is_the_adjoints_transpose(reduced):
    model, inp, Z = reduced
    rng = np.random.default_rng(3)
    zb = Z[W0 - 2:W0]
    de, dn, db = _directions((model.dim,), rng)
    S = reduced_sensitivity(model, inp[W0:], YOUNG, POISSON, Z[W0:], zb, de, dn, db)
    v = rng.normal(size=Z[W0:].shape)
    g = model.window_adjoint(inp[W0:], YOUNG, POISSON, Z[W0:], zb, dL_dZ=v)
    for j in range(len(de)):
        lhs = float(np.sum(v * S[j]))
        rhs = float(g["young"].sum(0) @ de[j] + g["poisson"].sum(0) @ dn[j] + np.sum(g["z_before"] * db[j]))
        assert abs(lhs - rhs) <= 1e-8 * (abs(lhs) + abs(rhs) + 1e-30), j


def test_damped_full_space_sensitivity_matches_finite_differences():
    """With the material's viscous damping (Scene.damping β > 0; its term couples x_t to x_{t−1} and to θ): the
    forward sensitivities against central differences, as undamped."""
    import dataclasses

    scene = dataclasses.replace(bar_scene(), damping=0.01)
    inp = sequence_inputs(scene, 0, frames=W0 + W)
    _check_sensitivity_against_fd(scene, inp, simulate(scene, inp, YOUNG, POISSON, rtol=1e-12), np.random.default_rng(2))
