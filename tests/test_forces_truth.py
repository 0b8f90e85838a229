"""Handle forces of rsl (stages.forces) against the truth's (rsl synth's truth/forces.csv, stages.steps.synth.
truth_forces): both sides must compute the same quantity — the force a handle exerts on the object at the
frame's time, the residual at its held vertices of the last implicit-Euler step that made the frame.

Found on the bar cable capture of bench/accuracy.py (truth P2 with 3 substeps, hard base handle; rsl online):
a 62 % median force error (78 % with a full-space adapt) with a 4–10 % E error, from forces taken on adapt.h5's
recorded positions — frame-level second differences of a trajectory spliced from windows solved with different
θ.  A full-space replay of the controls with the adapted θ(t) gives 14 % (1 step per frame; 11 % with 3), the
true E replayed 12.8 % (1 step) / 1.4 % (3 substeps, the truth's)."""
from __future__ import annotations

import numpy as np
import pytest

FPS, FRAMES, E, NU = 30.0, 12, 1.0e6, 0.45
SOFT = 5.0e4  # Pa


@pytest.fixture(scope="module")
def bar():
    """A P1 bar 0.2 × 0.04 × 0.04 m held hard at x = 0, a load pulling its far end up slowly (smooth ramp to 2 N)."""
    from stages.artefacts import mesh_artefact
    from stages.domain.controls import Controls, Handle, Load, Selection, Track
    from stages.sim.meshgen import box_tets
    from stages.sim.scene import make_scene

    v, t = box_tets((6, 2, 2), (0.2, 0.04, 0.04))
    mesh = mesh_artefact(v, t, 1000.0)
    ident = Track(np.array([0]), np.array([[0.0, 0, 0, 1, 0, 0, 0]]), True)
    force = np.zeros((FRAMES, 3))
    r = np.linspace(0.0, 1.0, FRAMES)
    force[:, 2] = 2.0 * r * r * (3.0 - 2.0 * r)  # smoothstep: a slow, smooth pull
    ctl = Controls(handles=[Handle("base", Selection("box", box=np.array([[-1e-3, -1, -1], [1e-3, 1, 1]])), 1e4,
                                   ident, hard=True)],
                   loads=[Load("tip", Selection("box", box=np.array([[0.199, -1, -1], [0.201, 1, 1]])),
                               Track(np.arange(FRAMES), force))])
    scene = make_scene(mesh, ctl, "stable_neohookean", 1.0 / FPS, (0.0, 0.0, -9.81))
    young, poisson = np.full((FRAMES, 1), E), np.full((FRAMES, 1), NU)
    return scene, ctl, young, poisson


def _truth(scene, ctl, young, poisson, substeps):
    """truth/forces.csv rows of a simulation with ``substeps`` per frame (what rsl synth writes)."""
    from stages.sim.scene import frame_inputs
    from stages.sim.static import simulate_from_start
    from stages.steps.synth import truth_forces

    states: list = []
    X = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), young, poisson, FRAMES, "equilibrium",
                            substeps, states=states)
    rows = truth_forces(scene, ctl, X, states, young, poisson, substeps, FPS)
    keys = ["frame", "time_s", "name", "kind", "fx_N", "fy_N", "fz_N", "magnitude_sum_N", "applied_fx_N",
            "applied_fy_N", "applied_fz_N", "n_vertices"]
    return X, [dict(zip(keys, r)) for r in rows]


def _applied(rows):
    return np.array([[r["applied_fx_N"], r["applied_fy_N"], r["applied_fz_N"]] for r in rows])


def test_replay_reproduces_the_truth_forces_and_substeps_change_them_little_on_a_slow_motion(bar):
    from stages.forces import force_errors, force_table, replay_forces

    scene, ctl, young, poisson = bar
    _, truth3 = _truth(scene, ctl, young, poisson, 3)
    # the same model and substeps: the very same numbers (one definition on both sides)
    rows, applied, X = replay_forces(scene, ctl, young, poisson, "equilibrium", 3)
    est = force_table(rows, 1.0 / FPS)
    np.testing.assert_allclose(_applied(est), _applied(truth3), rtol=1e-7, atol=1e-9)
    # the held vertices sit at their targets and the applied field sums to the rows' forces
    np.testing.assert_allclose(X[:, scene.handles[0].ids], np.repeat(X[:1, scene.handles[0].ids], FRAMES, 0),
                               atol=1e-12)
    np.testing.assert_allclose(applied[:, scene.handles[0].ids].sum(1), _applied(est), rtol=1e-9, atol=1e-9)
    # one step per frame against the truth's 3 substeps: a slow motion, so the same force within 2 %
    rows1, _, _ = replay_forces(scene, ctl, young, poisson, "equilibrium", 1)
    err = force_errors(force_table(rows1, 1.0 / FPS), truth3)["base"]
    assert err["median_relative_error"] < 0.02, err
    # frame 0 (equilibrium): the handle carries the whole weight, exactly
    weight = scene.masses.sum() * 9.81
    assert _applied(truth3)[0] == pytest.approx([0.0, 0.0, weight], abs=1e-6 * weight)


def test_forces_from_recorded_positions_need_one_simulation_and_a_replay_is_one(bar):
    """Forces from recorded positions (frame-level differences) are the model's only on ONE simulation.  An
    online adapt records frame t from a window solved with θ_t (and state-corrected): a splice of simulations,
    every state an exact solution, whose second differences are no accelerations — the forces move off the
    truth's (here by > 2 % with E ± 20 % on a same-model bar; by far more with reduced-space states).  A replay
    of θ(t) is one simulation: its rows are the recorded-position forces of its own trajectory."""
    from stages.forces import force_errors, force_table, replay_forces, trajectory_forces
    from stages.sim.scene import internal_forces

    scene, ctl, _, poisson = bar
    young = np.full((FRAMES, 1), SOFT)  # soft enough that the splice's position jumps matter
    X, truth = _truth(scene, ctl, young, poisson, 1)

    def recorded_position_error(X, young):
        f_int = np.stack([internal_forces(X[t], scene, young[t], poisson[t]) for t in range(FRAMES)])
        rows, _ = trajectory_forces(scene, ctl, np.arange(FRAMES), X, f_int)
        return rows, force_errors(force_table(rows, 1.0 / FPS), truth)["base"]["median_relative_error"]

    # one simulation, the truth's own model: the recorded-position forces are the truth's
    assert recorded_position_error(X, young)[1] < 1e-7
    # the splice: E ± 20 % frame to frame, frame t taken from the whole simulation with θ_t
    scatter = np.where(np.arange(FRAMES) % 2 == 0, 0.8, 1.2)[:, None] * young
    runs = [_truth(scene, ctl, np.full_like(young, e), poisson, 1)[0] for e in (0.8 * SOFT, 1.2 * SOFT)]
    spliced = np.stack([runs[t % 2][t] for t in range(FRAMES)])
    assert recorded_position_error(spliced, scatter)[1] > 0.02
    # a replay of θ(t) is one simulation: its rows are the recorded-position forces of its own trajectory
    rows, _, Xr = replay_forces(scene, ctl, scatter, poisson, "equilibrium", 1)
    rows_r, _ = recorded_position_error(Xr, scatter)
    np.testing.assert_allclose(_applied(force_table(rows, 1.0 / FPS)), _applied(force_table(rows_r, 1.0 / FPS)),
                               rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------------------------- the default step
CABLE_FRAMES = 10
TRUTH_SUBSTEPS = 12


@pytest.fixture(scope="module")
def foreign_cable():
    """A capture rsl did not make, as bench/forces.py's: a bar 0.2 × 0.04 × 0.04 m (8 × 2 × 2 cells) held hard at
    x = 0 and pulled up and sideways at its free end by a cable (synth's 'cable' profile, up to 0.8 × its weight),
    start = equilibrium; truth on P2 tets of the once-refined mesh with 12 substeps per frame, finer in time than
    any replay tested (rsl synth --truth-order 2 --truth-refine 1 --substeps 12 --handles hard), rsl's model on P2
    tets of the unrefined mesh.
    Returns (rsl's scene, controls, E (T, 1), ν (T, 1), truth/forces.csv rows)."""
    from stages.artefacts import mesh_artefact
    from stages.domain.controls import Controls, Handle, Load, Selection, Track
    from stages.sim.meshgen import box_tets, refine_tets
    from stages.sim.scene import frame_inputs, make_scene
    from stages.sim.static import simulate_from_start
    from stages.steps.synth import truth_forces

    v, t = box_tets((8, 2, 2), (0.2, 0.04, 0.04))
    vf, tf, _ = refine_tets(v, t, np.zeros(len(t), np.int64))
    fine, coarse = mesh_artefact(vf, tf, 1070.0, order=2), mesh_artefact(v, t, 1070.0, order=2)
    ident = Track(np.array([0]), np.array([[0.0, 0, 0, 1, 0, 0, 0]]), True)
    weight = float(coarse.vertex_masses.sum()) * 9.81
    s = np.sin(np.pi * np.arange(CABLE_FRAMES) / (CABLE_FRAMES - 1)) ** 2  # up and back
    force = (0.8 * weight * s)[:, None] * np.array([0.0, 0.35, 0.9])
    ctl = Controls(handles=[Handle("base", Selection("box", box=np.array([[-1e-3, -1, -1], [1e-3, 1, 1]])), 1e4,
                                   ident, hard=True)],
                   loads=[Load("cable", Selection("box", box=np.array([[0.199, -1, -1], [0.201, 1, 1]])),
                               Track(np.arange(CABLE_FRAMES), force))])
    young, poisson = np.full((CABLE_FRAMES, 1), SOFT), np.full((CABLE_FRAMES, 1), NU)
    truth_scene = make_scene(fine, ctl, "stable_neohookean", 1.0 / FPS, (0.0, 0.0, -9.81))
    states: list = []
    X = simulate_from_start(truth_scene, lambda f: frame_inputs(truth_scene, ctl, f), young, poisson, CABLE_FRAMES,
                            "equilibrium", TRUTH_SUBSTEPS, states=states)
    keys = ["frame", "time_s", "name", "kind", "fx_N", "fy_N", "fz_N", "magnitude_sum_N", "applied_fx_N",
            "applied_fy_N", "applied_fz_N", "n_vertices"]
    rows = [dict(zip(keys, r)) for r in truth_forces(truth_scene, ctl, X, states, young, poisson, TRUTH_SUBSTEPS,
                                                     FPS)]
    scene = make_scene(coarse, ctl, "stable_neohookean", 1.0 / FPS, (0.0, 0.0, -9.81))
    return scene, ctl, young, poisson, rows


def test_replay_of_the_true_young_converges_in_time_toward_a_finer_truth(foreign_cable):
    """The replay's handle force with the true E approaches a truth simulated finer in time (12 substeps per frame)
    as the replay's substeps grow — implicit Euler's numerical damping shrinks with the step — and the stages'
    default rule (`--force-substeps 0`: adapt's own substeps, 6 by default, plain) is closer to it than the former
    default, Richardson over 1 and 2 substeps.  The truth is deliberately not simulated at the replays' steps: a
    match there would only show the replay copying the truth's integrator (docs/results/forces.md)."""
    import dataclasses

    from stages.forces import (FORCE_EXTRAPOLATE, FORCE_SUBSTEPS, FORCE_THETA, force_errors, force_table,
                               replay_forces, replay_substeps)
    from stages.steps.adapt import AdaptConfig
    from stages.steps.evaluate import EvaluateConfig
    from stages.steps.export import ExportConfig

    scene, ctl, young, poisson, truth = foreign_cable
    for config in (EvaluateConfig, ExportConfig):  # the stages' defaults are stages.forces' (one rule)
        defaults = {f.name: f.default for f in dataclasses.fields(config)}
        assert defaults["force_substeps"] == FORCE_SUBSTEPS
        assert defaults["force_extrapolate"] == FORCE_EXTRAPOLATE
        assert defaults["force_theta"] == FORCE_THETA
    adapt_default = type("A", (), {"extra": {"substeps": AdaptConfig.substeps}})()
    s_default = replay_substeps(FORCE_SUBSTEPS, adapt_default)  # an adapt.h5 of adapt's default substeps
    steps = sorted({1, 2, 3, s_default})
    assert TRUTH_SUBSTEPS > max(steps)

    def error(S, extrapolate=False):
        rows, _, _ = replay_forces(scene, ctl, young, poisson, "equilibrium", S, extrapolate=extrapolate)
        return force_errors(force_table(rows, 1.0 / FPS), truth)["base"]["median_relative_error"]

    err = {S: error(S) for S in steps}
    err_default = error(s_default, FORCE_EXTRAPOLATE)
    err_richardson_1_2 = error(1, True)
    print(err, err_default, err_richardson_1_2)
    assert all(err[a] > err[b] for a, b in zip(steps, steps[1:])), err
    assert err_default < err_richardson_1_2, (err_default, err_richardson_1_2)
