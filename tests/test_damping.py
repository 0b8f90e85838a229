"""The material's viscous damping (Scene.damping β, Kelvin–Voigt on the Green strain, materials.viscous_density):
its density against finite differences and identities, the numpy fast path against the JAX potential, the adjoint
through it against finite differences, and what it does to a vibration."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stages.sim import potential as pot
from stages.sim.materials import lame, viscous_density
from stages.sim.scene import (frame_inputs, handle_reactions, hessian, internal_forces, make_scene, simulate, step,
                              total_energy)
from test_forces_truth import bar  # noqa: F401 (a fixture)
from test_sim_p2 import clamp, curved_p2, p2_bar, random_state, window_adjoint_fd_error

from stages.artefacts import mesh_artefact

BETA = 0.01  # s


def test_viscous_density_is_zero_for_rigid_motion_and_linear_damping_at_small_strain():
    """D(R F, F) = 0 for a rotation R of the whole configuration (ΔE = 0); at rest, D(I + εG, I) / ε² → the
    linear elastic energy of sym(G) (Rayleigh's β K₀ v at small strain), to O(ε)."""
    rng = np.random.default_rng(0)
    mu, lam = lame(1e5, 0.4)
    F = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    R = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    assert abs(float(viscous_density(jnp.asarray(R @ F), jnp.asarray(F), mu, lam))) < 1e-18 * mu
    G = rng.normal(size=(3, 3))
    eps = 0.5 * (G + G.T)
    linear = mu * np.sum(eps * eps) + 0.5 * lam * np.trace(eps) ** 2
    for e in (1e-3, 1e-4):
        d = float(viscous_density(jnp.asarray(np.eye(3) + e * G), jnp.eye(3), mu, lam)) / e ** 2
        assert abs(d - linear) <= 10 * e * linear


def _two_region_p2(damping: float):
    v, t = curved_p2(cells=(3, 1, 1), size=(0.3, 0.1, 0.1))
    region = (v[t[:, :4]].mean(1)[:, 0] > 0.15).astype(int)
    mesh = mesh_artefact(v, t, 1000.0, region, ("a", "b"))
    ctl = clamp(False)
    return make_scene(mesh, ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81], damping=damping), ctl


def test_numpy_energy_gradient_hessian_with_damping_match_the_jax_potential():
    """total_energy, ∇ (internal_forces with x_prev) and the exact Hessian of the fast path against
    pot.incremental_potential / step_potential and their JAX derivatives, on a curved P2 mesh of two regions;
    and the damping term equals β/Δt Σ w D directly, so that it is really there (0 without damping)."""
    scene, ctl = _two_region_p2(BETA)
    inp = frame_inputs(scene, ctl, 0)
    x, xp, xpp = (random_state(scene.rest, 0.003, s) for s in (1, 2, 3))
    young, poisson = np.array([5e4, 2e5]), np.array([0.3, 0.45])
    mu, lam = (np.asarray(a) for a in pot.tet_lame(scene, young, poisson))
    s = pot.scene_data(scene)
    y = 2 * xp - xpp
    phi = float(jax.jit(pot.incremental_potential)(x, y, s, inp, mu, lam, xp))
    assert abs(total_energy(scene, inp, x, y, xp, mu, lam) - phi) < 1e-10 * abs(phi)
    dmp = float(pot.damping_energy(x, xp, s, mu, lam))
    undamped = dataclasses.replace(scene, damping=0.0)
    assert dmp > 0 and float(pot.damping_energy(x, xp, pot.scene_data(undamped), mu, lam)) == 0.0
    assert total_energy(scene, inp, x, y, xp, mu, lam) - total_energy(undamped, inp, x, y, xp, mu, lam) \
        == pytest.approx(dmp, rel=1e-9)
    f = internal_forces(x, scene, young, poisson, x_prev=xp)
    f_jax = -np.asarray(jax.grad(lambda z: pot.elastic_energy(z, s, mu, lam) + pot.damping_energy(z, xp, s, mu, lam))(
        jnp.asarray(x)))
    np.testing.assert_allclose(f, f_jax, atol=1e-10 * np.abs(f_jax).max())
    H = hessian(scene, inp, x, xp, young, poisson, project=False)
    dz = np.random.default_rng(4).normal(size=x.shape)
    hv = np.asarray(jax.jvp(lambda z: jax.grad(pot.step_potential)(z, xp, xpp, young, poisson, s, inp),
                            (jnp.asarray(x),), (jnp.asarray(dz),))[1])
    np.testing.assert_allclose(H @ dz.reshape(-1), hv.reshape(-1), atol=1e-9 * np.abs(hv).max())


def test_damping_gradient_and_hessian_match_finite_differences():
    """β/Δt Σ w D of the JAX twin: its gradient against central differences of the energy, its Hessian-vector
    product against central differences of the gradient."""
    scene, _ = _two_region_p2(BETA)
    s = pot.scene_data(scene)
    mu, lam = (np.asarray(a) for a in pot.tet_lame(scene, [5e4, 2e5], [0.3, 0.45]))
    x, xp = random_state(scene.rest, 0.004, 1), random_state(scene.rest, 0.004, 2)
    e = lambda z: float(pot.damping_energy(jnp.asarray(z), xp, s, mu, lam))  # noqa: E731
    g = np.asarray(jax.grad(lambda z: pot.damping_energy(z, xp, s, mu, lam))(jnp.asarray(x)))
    d = np.random.default_rng(5).normal(size=x.shape)
    h = 1e-6
    assert float(np.sum(g * d)) == pytest.approx((e(x + h * d) - e(x - h * d)) / (2 * h), rel=1e-6)
    scene_h = hessian(scene, frame_inputs(scene, clamp(False), 0), x, xp, [5e4, 2e5], [0.3, 0.45], project=False)
    undamped = hessian(dataclasses.replace(scene, damping=0.0), frame_inputs(scene, clamp(False), 0), x, xp,
                       [5e4, 2e5], [0.3, 0.45], project=False)
    gf = lambda z: np.asarray(jax.grad(lambda q: pot.damping_energy(q, xp, s, mu, lam))(jnp.asarray(z)))  # noqa
    fd = (gf(x + h * d) - gf(x - h * d)) / (2 * h)
    np.testing.assert_allclose((scene_h - undamped) @ d.reshape(-1), fd.reshape(-1), atol=1e-6 * np.abs(fd).max())


def test_window_adjoint_with_damping_matches_finite_differences():
    """dL/dθ_t through damped steps (the viscous term depends on x_{t−1} and on θ through μ, λ), as
    test_sim_p2's undamped check: a P2 bar of two regions, a moving hard clamp, a window of 2 after 2 frames."""
    worst = window_adjoint_fd_error(True, BETA)
    assert worst < 1e-4, worst


def test_damping_takes_energy_out_of_a_vibration_and_keeps_the_static_sag():
    """A P2 bar clamped at one end (E 5 MPa), released from rest at Δt = 1 ms for 0.3 s (about three periods of its
    first mode): with β = 3 ms the tip's swing about the static equilibrium over the last half is less than half of
    implicit Euler's own damping alone, and it settles on that equilibrium (β damps motion, not the sag)."""
    from stages.sim.static import start_state

    swing, last = {}, {}
    for beta in (0.0, 3e-3):
        scene, ctl = p2_bar(True, dt=1e-3)
        scene = dataclasses.replace(scene, damping=beta)
        inp = frame_inputs(scene, ctl, 0)
        X = simulate(scene, [inp] * 300, [5e6], [0.4], rtol=1e-10)
        tip = scene.rest[:, 0] > scene.rest[:, 0].max() - 1e-9
        z = X[:, tip, 2].mean(axis=1)
        z_static = start_state(scene, inp, [5e6], [0.4], "equilibrium")[tip, 2].mean()
        swing[beta] = np.abs(z[150:] - z_static).max()
        last[beta] = abs(z[-1] - z_static)
    assert swing[3e-3] < 0.5 * swing[0.0], swing
    assert last[3e-3] < 0.05 * abs(scene.rest[tip, 2].mean() - z_static), last


def test_handle_reaction_with_damping_holds_the_weight_at_rest():
    """At rest (x = x_prev = x_prev2, the static equilibrium) the viscous force is zero: the hard clamp's
    reaction is the weight, as without damping."""
    from stages.sim.static import start_state

    scene, ctl = p2_bar(True, dt=1 / 30)
    scene = dataclasses.replace(scene, damping=BETA)
    inp = frame_inputs(scene, ctl, 0)
    x0 = start_state(scene, inp, [1e5], [0.4], "equilibrium")
    x1, _ = step(scene, inp, [1e5], [0.4], x0, x0, rtol=1e-12)
    np.testing.assert_allclose(x1, x0, atol=1e-9)
    f = handle_reactions(scene, inp, x1, x0, x0, [1e5], [0.4])
    weight = scene.masses.sum() * 9.81
    np.testing.assert_allclose(f[0], [0, 0, weight], atol=1e-5 * weight)


def test_replay_reproduces_a_damped_truth_s_forces(bar):
    """The same damped model on both sides (rsl synth's truth_forces and stages.forces.replay_forces): the very
    same numbers; and the damping changes them (the pull is not quasi-static at 3 substeps)."""
    from stages.forces import force_table, replay_forces
    from test_forces_truth import FPS, _applied, _truth

    scene0, ctl, young, poisson = bar
    scene = dataclasses.replace(scene0, damping=BETA)
    _, truth = _truth(scene, ctl, young, poisson, 3)
    rows, _, _ = replay_forces(scene, ctl, young, poisson, "equilibrium", 3)
    np.testing.assert_allclose(_applied(force_table(rows, 1.0 / FPS)), _applied(truth), rtol=1e-7, atol=1e-9)
    _, undamped = _truth(scene0, ctl, young, poisson, 3)
    assert np.abs(_applied(truth) - _applied(undamped)).max() > 1e-4 * np.abs(_applied(undamped)).max()


def test_synth_writes_its_damping_into_capture_toml_and_adapt_simulates_with_it(tmp_path):
    """rsl synth --damping β: capture.toml [material] damping = β (left out with --undeclared-damping), the truth
    moves differently from the undamped one, and rsl adapt records the β it simulated with."""
    from stages.capture import load_capture
    from stages.steps import synth
    from test_adapt_e2e import BEAM

    if not BEAM.is_file():
        pytest.skip(f"{BEAM} not present")
    base = dict(mesh=BEAM, scenario="cable", cameras=1, frames=6, resolution=32, markers=10, calib_views=0, seed=0)
    synth.run(synth.SynthConfig(out=tmp_path / "d", damping=0.02, **base))
    synth.run(synth.SynthConfig(out=tmp_path / "u", damping=0.02, undeclared_damping=True, **base))
    synth.run(synth.SynthConfig(out=tmp_path / "n", **base))
    assert load_capture(tmp_path / "d").material.damping == 0.02
    assert load_capture(tmp_path / "u").material.damping == 0.0 == load_capture(tmp_path / "n").material.damping
    xd, xu, xn = (np.load(tmp_path / k / "truth" / "surface.npz")["vertices"] for k in "dun")
    np.testing.assert_array_equal(xd, xu)
    assert np.abs(xd[-1] - xn[-1]).max() > 1e-5
    from stages.artefacts import AdaptArtefact
    from stages.steps import adapt, calibrate, tetrahedralize

    cap, ws = tmp_path / "d", tmp_path / "ws"
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    from stages.progress import SilentReporter

    rep = SilentReporter()
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, loss="markers", window=3,
                                                         estimator="gn", space="full", substeps=1), rep))
    assert art.extra["damping"] == 0.02
    assert any("viscous damping β = 0.02 s" in m for m in rep.messages)


@pytest.mark.parametrize("project", [False, True, "abs"])
def test_numba_viscous_kernel_matches_its_jax_twin(project):
    """elements.viscous_point_kernel (closed-form ∂D/∂F and ∂²D/∂F², 9×9 projection) against the JAX autodiff of
    the density, per element of a curved P2 mesh (four points each), energies, gradients and Hessians."""
    from stages.sim.elements import HESSIAN, point_damping_terms

    scene, _ = _two_region_p2(BETA)
    q = scene.quad
    mu, lam = (np.asarray(a)[q.element] for a in pot.tet_lame(scene, [5e4, 2e5], [0.3, 0.45]))
    x, xp = random_state(scene.rest, 0.01, 1), random_state(scene.rest, 0.01, 2)
    args = (x, xp, q.nodes, q.grad, q.weight * 3.0, mu, lam, HESSIAN, project, q.element, len(scene.tets))
    fast, twin = point_damping_terms(*args, backend="numba"), point_damping_terms(*args, backend="jax")
    for a, b in zip(fast, twin):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * np.abs(b).max())
    if not project:  # the projection did something on this state (else it would test nothing)
        proj = point_damping_terms(*args[:8], True, *args[9:], backend="numba")[2]
        assert np.abs(proj - fast[2]).max() > 1e-6 * np.abs(fast[2]).max()
