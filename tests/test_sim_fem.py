"""Full-space implicit-Euler FEM: potential vs. Newton's numpy path, convergence, momentum,
a cantilever against Euler–Bernoulli, contact, solvers and the window adjoint against finite differences."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.capture import Controls, Handle, Load, Obstacle, Selection, Track
from stages.sim import potential as pot
from stages.sim.linsolve import available_solvers
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets
from stages.sim.scene import (SimulationError, frame_inputs, hessian, internal_forces, make_scene, simulate, step,
                              total_energy, window_adjoint)

jax.config.update("jax_enable_x64", True)

IDENTITY = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]


def clamp_controls(x_max: float = 1e-9, stiffness: float = 1e5, poses=None, loads=(), obstacles=(),
                   friction=0.0) -> Controls:
    track = Track.constant(IDENTITY, True) if poses is None else poses
    h = Handle("clamp", Selection("box", box=np.array([[-1.0, -1, -1], [x_max, 1, 1]])), stiffness, track)
    return Controls(handles=[h], loads=list(loads), obstacles=list(obstacles), friction=friction)


def two_region_bar(cells=(4, 2, 2), size=(0.2, 0.05, 0.05), density=1000.0):
    v, t = box_tets(cells, size)
    region = (v[t].mean(1)[:, 0] > size[0] / 2).astype(int)
    return mesh_artefact(v, t, density, region, ("soft", "stiff"))


@pytest.mark.parametrize("material,contact", [("stable_neohookean", True), ("yeoh", False), ("linear", False)])
def test_numpy_energy_gradient_hessian_match_jax_potential(material, contact):
    """Newton's numpy/numba path computes the same Φ, ∇Φ and ∇²Φ as the JAX potential (with loads,
    handles, and for one material contact with all three obstacle shapes and friction)."""
    mesh = two_region_bar()
    load = Load("pull", Selection("box", box=np.array([[0.19, -1, -1], [1, 1, 1]])),
                Track.constant([0.5, 0.0, -0.3]))
    floor = Obstacle("floor", "plane", normal=np.array([0.0, 0.0, 1.0]), offset=-0.004)
    ball = Obstacle("ball", "sphere", radius=0.02, poses=Track.constant([0.1, 0.0, -0.015, 1, 0, 0, 0], True))
    box = Obstacle("box", "box", half_extents=np.array([0.02, 0.1, 0.01]),
                   poses=Track.constant([0.17, 0.0, 0.058, 0.98, 0.0, 0.2, 0.0], True))
    ctl = clamp_controls(poses=Track.constant([0.0, 0.0, 0.002, 1, 0, 0, 0], True), loads=[load],
                         obstacles=[floor, ball, box] if contact else [], friction=0.4)
    scene = make_scene(mesh, ctl, material, 1 / 30, [0.0, 0.0, -9.81], contact_stiffness=2e4, contact_margin=1e-3)
    inp = frame_inputs(scene, ctl, 0)
    rng = np.random.default_rng(0)
    x = scene.rest + 0.004 * rng.normal(size=scene.rest.shape)
    x_prev = scene.rest + 0.003 * rng.normal(size=scene.rest.shape)
    x_prev2 = scene.rest + 0.003 * rng.normal(size=scene.rest.shape)
    young, poisson = np.array([5e4, 2e5]), np.array([0.3, 0.45])
    mu, lam = (np.asarray(a) for a in pot.tet_lame(scene, young, poisson))
    y = 2 * x_prev - x_prev2
    s = pot.scene_data(scene)  # the scene as a pytree, so that everything below is jitted
    phi = jax.jit(pot.incremental_potential)(x, y, s, inp, mu, lam, x_prev)
    e_np = total_energy(scene, inp, x, y, x_prev, mu, lam)
    assert abs(e_np - float(phi)) < 1e-10 * abs(float(phi))
    # contact must be active for the test to mean something
    assert (float(jax.jit(pot.contact_energy)(x, s, inp)) > 0) == contact
    grad_fn = jax.jit(jax.grad(pot.step_potential))
    g_jax = np.asarray(grad_fn(x, x_prev, x_prev2, young, poisson, s, inp))
    # the gradient that step() uses
    from stages.sim.scene import _elastic, _scatter_grad, _vertex_terms
    _, ge, _ = _elastic(scene, x, mu, lam, 1, True, "auto")
    _, gv, _ = _vertex_terms(scene, inp, x, y, x_prev, 1, True)
    g_np = _scatter_grad(scene, ge).reshape(-1, 3) + gv
    np.testing.assert_allclose(g_np, g_jax, rtol=1e-9, atol=1e-9 * np.abs(g_jax).max())
    # and the gradient is the derivative of Φ (central difference along a random direction)
    phi_fn = jax.jit(pot.incremental_potential)
    dirn = rng.normal(size=x.shape)
    h = 1e-7
    fd = (float(phi_fn(x + h * dirn, y, s, inp, mu, lam, x_prev)) - float(phi_fn(x - h * dirn, y, s, inp, mu, lam,
                                                                                   x_prev))) / (2 * h)
    assert abs(fd - float(np.sum(g_np * dirn))) < 1e-6 * np.abs(g_np * dirn).sum()
    # the exact Hessian the adjoint uses, as a Hessian-vector product
    H = hessian(scene, inp, x, x_prev, young, poisson, project=False)
    d = rng.normal(size=x.shape)
    hvp = jax.jit(lambda z, dz, s, inp: jax.jvp(
        lambda q: jax.grad(pot.step_potential)(q, x_prev, x_prev2, young, poisson, s, inp), (z,), (dz,))[1])
    hv_jax = np.asarray(hvp(x, d, s, inp))
    np.testing.assert_allclose((H @ d.reshape(-1)).reshape(-1, 3), hv_jax, rtol=1e-8,
                               atol=1e-8 * np.abs(hv_jax).max())


def test_internal_forces_zero_at_rest_and_sum_to_zero():
    mesh = two_region_bar()
    scene = make_scene(mesh, clamp_controls(), "stable_neohookean", 0.01, [0, 0, 0])
    f0 = internal_forces(scene.rest, scene, [1e5, 3e5], [0.3, 0.4])
    assert np.abs(f0).max() < 1e-9
    rng = np.random.default_rng(1)
    f = internal_forces(scene.rest + 0.01 * rng.normal(size=scene.rest.shape), scene, [1e5, 3e5], [0.3, 0.4])
    assert np.abs(f).max() > 1.0
    np.testing.assert_allclose(f.sum(0), 0.0, atol=1e-9 * np.abs(f).max())


@pytest.mark.parametrize("mode", ["exact", "projected"])
def test_newton_converges(mode):
    _solve_bar(mode)


def _solve_bar(mode):
    """Exact Newton converges quadratically near the solution; projected Newton (the SNH Hessian is
    indefinite under compression, so some twist modes are clamped) converges too, at least linearly."""
    mesh = two_region_bar((6, 2, 2), (0.3, 0.05, 0.05))
    ctl = clamp_controls(stiffness=1e6)
    scene = make_scene(mesh, ctl, "stable_neohookean", 0.05, [0, 0, -9.81])
    x, info = step(scene, frame_inputs(scene, ctl, 0), [3e4, 3e4], [0.4, 0.4], scene.rest, scene.rest,
                   rtol=1e-11, xtol=0.0, solver="splu", hessian_mode=mode)
    r = np.array(info["history"])
    assert info["residual"] <= 1e-11
    assert info["iterations"] <= (12 if mode == "exact" else 40)
    if mode == "exact":
        # once in the basin (r < 1e-2) each step squares the residual, up to a constant
        basin = np.flatnonzero(r < 1e-2)
        assert len(basin) >= 2
        for k in basin[:-1]:
            assert r[k + 1] < 10 * r[k] ** 2 or r[k + 1] < 1e-11, r
    return x


def test_exact_and_projected_newton_reach_the_same_solution():
    x1 = _solve_bar("exact")
    x2 = _solve_bar("projected")
    np.testing.assert_allclose(x1, x2, atol=1e-9)


def test_momentum_conserved_without_gravity_handles_or_contact():
    v, t = box_tets((3, 2, 2), (0.15, 0.1, 0.1))
    mesh = mesh_artefact(v, t, 1000.0)
    scene = make_scene(mesh, Controls(), "stable_neohookean", 0.01, [0, 0, 0])
    rng = np.random.default_rng(2)
    vel = np.array([0.3, -0.1, 0.2]) + 0.5 * rng.normal(size=v.shape)  # m/s, deforming
    x_prev = scene.rest
    x_prev2 = scene.rest - scene.dt * vel
    inputs = [frame_inputs(scene, Controls(), i) for i in range(8)]
    X = simulate(scene, inputs, [2e4], [0.35], x_prev, x_prev2, rtol=1e-11)
    m = scene.masses[:, None]
    p0 = np.sum(m * vel, axis=0)
    traj = np.concatenate([x_prev[None], X])
    p = np.sum(m[None] * (traj[1:] - traj[:-1]) / scene.dt, axis=1)
    np.testing.assert_allclose(p, np.broadcast_to(p0, p.shape), atol=1e-8 * np.linalg.norm(m * vel))
    # the body did deform (the test would be trivial for a rigid motion)
    assert np.abs(internal_forces(X[-1], scene, [2e4], [0.35])).max() > 1e-3


def cantilever_deflection(cells, poisson, young=1e8, material="stable_neohookean"):
    """Tip deflection of a bar L=1, b=h=0.1 clamped at x=0, quasi-static (Δt = 100 s), over the
    Euler–Bernoulli value ρgAL⁴/(8EI)."""
    L, b, h, rho, g = 1.0, 0.1, 0.1, 1000.0, 9.81
    v, t = box_tets(cells, (L, b, h))
    mesh = mesh_artefact(v, t, rho)
    ctl = clamp_controls(stiffness=1e9)
    scene = make_scene(mesh, ctl, material, 100.0, [0, 0, -g])
    inp = frame_inputs(scene, ctl, 0)
    x = scene.rest
    for _ in range(2):  # the second step starts at rest velocity from the first solution
        x, _ = step(scene, inp, [young], [poisson], x, x)
    tip = np.isclose(v[:, 0], L)
    deflection = -(x[tip, 2] - v[tip, 2]).mean()
    return deflection / (rho * g * b * h * L ** 4 / (8 * young * b * h ** 3 / 12))


def test_cantilever_coarse_mesh_within_25_percent_of_euler_bernoulli():
    """40×4×4 cells (3840 linear tets) at ν = 0.3: linear tets are too stiff in bending; measured 0.79."""
    ratio = cantilever_deflection((40, 4, 4), 0.3)
    assert 0.75 < ratio < 1.0


def test_cantilever_refined_mesh_within_10_percent_of_euler_bernoulli():
    """80×8×8 cells (30720 tets, 6561 vertices) at ν = 0.3; measured 0.937 (about 5 s of CPU with CHOLMOD)."""
    ratio = cantilever_deflection((80, 8, 8), 0.3)
    assert 0.9 < ratio < 1.1


def test_sphere_dropped_on_floor_stays_above_it():
    v, t = box_tets((3, 3, 3), (0.06, 0.06, 0.06), origin=(-0.03, -0.03, -0.03))
    inside = np.linalg.norm(v[t].mean(1), axis=1) < 0.03  # a voxel "sphere": keep tets inside the ball
    t = t[inside]
    used = np.unique(t)
    remap = -np.ones(len(v), int)
    remap[used] = np.arange(len(used))
    v = v[used] + np.array([0.0, 0.0, 0.05])
    t = remap[t]
    mesh = mesh_artefact(v, t, 1000.0)
    floor = Obstacle("floor", "plane", normal=np.array([0.0, 0.0, 1.0]), offset=0.0)
    ctl = Controls(obstacles=[floor], friction=0.3)
    scene = make_scene(mesh, ctl, "stable_neohookean", 1 / 120, [0, 0, -9.81])
    inputs = [frame_inputs(scene, ctl, i) for i in range(60)]
    X = simulate(scene, inputs, [5e4], [0.4])
    z = X[:, :, 2]
    assert z.min() >= 0.0  # never below the floor
    assert z[-1].min() < 2 * scene.contact_margin + 1e-3  # it did land (fell 2 cm in 0.5 s)
    assert np.all(np.isfinite(X))


def test_handles_drive_and_report_force():
    """A bar pulled by a moving handle: the handle springs' force equals the internal force sum."""
    mesh = two_region_bar()
    poses = Track(np.array([0, 10]), np.array([IDENTITY, [0.01, 0, 0, 1, 0, 0, 0]]), True)
    ctl = Controls(handles=[Handle("left", Selection("box", box=np.array([[-1, -1, -1], [1e-9, 1, 1]])), 1e6,
                                   Track.constant(IDENTITY, True)),
                            Handle("right", Selection("box", box=np.array([[0.2 - 1e-9, -1, -1], [1, 1, 1]])), 1e6,
                                   poses)])
    scene = make_scene(mesh, ctl, "stable_neohookean", 10.0, [0, 0, 0])
    x = scene.rest
    inp = frame_inputs(scene, ctl, 10)
    for _ in range(3):
        x, _ = step(scene, inp, [1e5, 1e5], [0.3, 0.3], x, x, rtol=1e-11)
    f_int = internal_forces(x, scene, [1e5, 1e5], [0.3, 0.3])
    right = scene.handles[1]
    f_spring = -right.stiffness * (x[right.ids] - inp.handle_targets[1])
    np.testing.assert_allclose(f_spring.sum(0), -f_int[right.ids].sum(0), rtol=1e-4,
                               atol=1e-6 * np.abs(f_spring).sum())
    assert f_spring.sum(0)[0] > 0  # pulled in +x


@pytest.mark.skipif(len(available_solvers()) < 2, reason="only one sparse solver installed")
def test_solvers_agree():
    mesh = two_region_bar()
    ctl = clamp_controls()
    scene = make_scene(mesh, ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81])
    inputs = [frame_inputs(scene, ctl, i) for i in range(3)]
    runs = [simulate(scene, inputs, [1e5, 2e5], [0.4, 0.3], solver=s, rtol=1e-11) for s in available_solvers()]
    for r in runs[1:]:
        np.testing.assert_allclose(r, runs[0], atol=1e-10)


def test_newton_failure_names_the_frame():
    mesh = two_region_bar()
    ctl = clamp_controls()
    scene = make_scene(mesh, ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81])
    inputs = [frame_inputs(scene, ctl, i) for i in range(3)]
    with pytest.raises(SimulationError, match=r"Newton did not converge at frame 0 \(residual .* after 1 "):
        simulate(scene, inputs, [1e5, 2e5], [0.4, 0.3], max_iterations=1, rtol=1e-14)


@pytest.mark.parametrize("friction", [0.0, 0.5])
def test_window_adjoint_matches_finite_differences(friction):
    """dL/dθ_t for E and ν of two regions on every window frame, L = Σ_t W_t · x_t over a window of 3
    after 2 lead-in frames, with gravity, a clamp and (second case) a frictional floor contact."""
    mesh = two_region_bar()
    floor = Obstacle("floor", "plane", normal=np.array([0.0, 0.0, 1.0]), offset=-0.002)
    ctl = clamp_controls(obstacles=[floor] if friction else [], friction=friction)
    scene = make_scene(mesh, ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81], contact_stiffness=5e3,
                       contact_margin=1e-3)
    T, w = 5, 3
    inputs = [frame_inputs(scene, ctl, i) for i in range(T)]
    young = np.array([[4e4, 1.5e5]] * T) * (1 + 0.1 * np.arange(T))[:, None]
    poisson = np.array([[0.4, 0.3]] * T)
    rng = np.random.default_rng(3)
    W = rng.normal(size=(w, scene.n_vertices, 3))

    def loss(E, nu):
        X = simulate(scene, inputs, E, nu, rtol=1e-12)
        return float(np.sum(W * X[T - w:])), X

    L0, X = loss(young, poisson)
    if friction:
        from stages.sim.potential import contact_energy
        assert float(contact_energy(jnp.asarray(X[-1]), scene, inputs[-1])) > 0  # contact is active
    g = window_adjoint(scene, inputs[T - w:], young[T - w:], poisson[T - w:], X[T - w:], X[T - w - 2:T - w], W)
    worst = 0.0
    for k in range(w):
        for r in range(2):
            for key, arr, h in (("young", 0, 1e-5 * young[T - w + k, r]), ("poisson", 1, 1e-6)):
                P, M = [young.copy(), poisson.copy()], [young.copy(), poisson.copy()]
                P[arr][T - w + k, r] += h
                M[arr][T - w + k, r] -= h
                fd = (loss(*P)[0] - loss(*M)[0]) / (2 * h)
                rel = abs(g[key][k, r] - fd) / abs(fd)
                worst = max(worst, rel)
    assert worst < 1e-4, worst
    # the gradient w.r.t. the lead-in states, checked along one random direction
    d = rng.normal(size=(2, scene.n_vertices, 3)) * 1e-7
    Xw_p = simulate(scene, inputs[T - w:], young[T - w:], poisson[T - w:], X[T - w - 1] + d[1],
                    X[T - w - 2] + d[0], rtol=1e-12)
    Xw_m = simulate(scene, inputs[T - w:], young[T - w:], poisson[T - w:], X[T - w - 1] - d[1],
                    X[T - w - 2] - d[0], rtol=1e-12)
    fd = (np.sum(W * Xw_p) - np.sum(W * Xw_m)) / 2
    np.testing.assert_allclose(np.sum(g["x_before"] * d), fd, rtol=1e-4)


def test_materials_agree_at_small_strain():
    """A bar sagging 0.6 % of its length: stable Neo-Hookean, Yeoh and linear elasticity share the
    small-strain stiffness, so their deflections agree to 1 % (Yeoh and linear run on the JAX element path)."""
    ratios = {m: cantilever_deflection((12, 2, 2), 0.3, young=1e8, material=m) for m in ("stable_neohookean",
                                                                                           "yeoh", "linear")}
    ref = ratios["stable_neohookean"]
    assert ref > 0.2
    for m, r in ratios.items():
        assert abs(r - ref) < 0.01 * ref, ratios


def test_bench_quick_runs():
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "bench" / "fem.py"
    spec = importlib.util.spec_from_file_location("bench_fem", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    cases = mod.main(["--quick", "--frames", "3", "--repeats", "1"])
    for c in cases:
        for key in ("vertices", "tets", "solver", "newton_iteration_s", "assembly_s", "solve_s", "projection_s",
                    "adjoint_frame_s"):
            assert key in c
        assert c["iterations_per_frame"] >= 1


def test_auto_hessian_falls_back_to_projection_when_indefinite():
    """A slender bar compressed 10 % between two clamps, quasi-static (Δt = 100 s): the exact Hessian at the
    straight compressed state is indefinite, yet Newton ("auto") converges, to a stable equilibrium."""
    v, t = box_tets((10, 1, 1), (0.2, 0.02, 0.02))
    mesh = mesh_artefact(v, t, 1000.0)
    squeeze = Track.constant([-0.02, 0.0, 0.0, 1, 0, 0, 0], True)
    ctl = Controls(handles=[Handle("left", Selection("box", box=np.array([[-1, -1, -1], [1e-9, 1, 1]])), 1e7,
                                   Track.constant(IDENTITY, True)),
                            Handle("right", Selection("box", box=np.array([[0.2 - 1e-9, -1, -1], [1, 1, 1]])), 1e7,
                                   squeeze)])
    scene = make_scene(mesh, ctl, "stable_neohookean", 100.0, [0.0, 0.0, -0.01])
    inp = frame_inputs(scene, ctl, 0)
    straight = scene.rest * np.array([0.9, 1.0, 1.0])
    H = hessian(scene, inp, straight, straight, [1e5], [0.3], project=False).toarray()
    assert np.linalg.eigvalsh(H).min() < 0
    for solver in available_solvers():
        x, info = step(scene, inp, [1e5], [0.3], straight, straight, solver=solver)
        assert info["iterations"] > 0
        # Newton left the unstable straight state for a stable equilibrium (positive definite Hessian)
        Hx = hessian(scene, inp, x, straight, [1e5], [0.3], project=False).toarray()
        assert np.linalg.eigvalsh(Hx).min() > 0
        assert np.linalg.norm(x[:, 1:] - straight[:, 1:], axis=1).max() > 1e-4


def test_auto_solver_falls_back_to_splu_without_cholmod(monkeypatch):
    from stages.sim import linsolve
    monkeypatch.setattr(linsolve, "_cholmod", None)
    assert linsolve.available_solvers() == ["splu"]
    assert linsolve.resolve_solver("auto") == "splu"
    with pytest.raises(ValueError, match="scikit-sparse"):
        linsolve.resolve_solver("cholmod")
    mesh = two_region_bar()
    ctl = clamp_controls()
    scene = make_scene(mesh, ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81])
    X = simulate(scene, [frame_inputs(scene, ctl, i) for i in range(2)], [1e5, 2e5], [0.4, 0.3])
    assert np.all(np.isfinite(X)) and X[-1, :, 2].min() < -1e-4
