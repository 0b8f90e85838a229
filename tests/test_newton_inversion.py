"""Newton keeps elements upright: the feasible step (largest 2⁻ᵏ that inverts no upright quadrature point or corner
tet) and the retry of a step whose solution inverts elements that x_{t−1} has upright (stable Neo-Hookean has no
barrier at det F = 0; on a pushed P2 dinosaur a full step from y crossed it into an inverted local minimum whose Φ
was higher than the upright one's — /tmp-scale reproduction in the session report, not in the suite)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.artefacts import mesh_artefact
from stages.capture import Controls, Handle, Selection, Track
from stages.sim import scene as S
from stages.sim.meshgen import box_tets


def _scene(order: int):
    v, t = box_tets((2, 2, 1), (0.04, 0.04, 0.02))
    h = Handle("base", Selection("box", box=np.array([[-1, -1, -1], [1, 1, 1e-9]])), 1e5,
               Track.constant([0, 0, 0, 1, 0, 0, 0], True), hard=True)
    ctl = Controls(handles=[h], loads=[], obstacles=[], friction=0.0)
    scene = S.make_scene(mesh_artefact(v, t, 1000.0, order=order), ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81])
    return scene, S.frame_inputs(scene, ctl, 0)


@pytest.mark.parametrize("order", [1, 2])
def test_feasible_step_is_the_largest_halving_that_keeps_upright_points_upright(order):
    scene, inp = _scene(order)
    nt = S._Newton(scene, inp, [1e4], [0.45], scene.rest, scene.rest, "auto", "auto", {})
    x = scene.rest.copy()
    top = np.flatnonzero(np.isclose(x[:, 2], x[:, 2].max()))
    dx = np.zeros_like(x)
    dx[top[0], 2] = -3.0 * np.ptp(x[:, 2])  # one top node pushed far through its elements
    J0 = nt.jacobians(x)
    assert J0.min() > 0 and len(J0) == scene.quad.n_points + (len(scene.tets) if order == 2 else 0)
    assert nt.jacobians(x + dx).min() <= 0  # the full step inverts
    a, ok = S._feasible_step(nt, x, dx)
    assert ok.all() and a < 1.0
    assert nt.jacobians(x + a * dx).min() > 0 and nt.jacobians(x + 2 * a * dx).min() <= 0
    alpha, x_new = S._line_search(nt, x, dx, nt.energy(x), -1.0, 1.0, expand=True, feasible=True)
    assert alpha <= a and nt.jacobians(x_new).min() > 0
    # an element inverted at x is free (the step may leave it inverted or right it); the others stay upright
    x_bad = x + 2.2 * a * dx
    bad = nt.jacobians(x_bad) <= 0
    assert bad.any() and not bad.all()
    a2, ok2 = S._feasible_step(nt, x_bad, -dx * 0.01)
    assert np.array_equal(ok2, ~bad) and a2 == 1.0


def test_step_solves_again_when_the_solution_inverts_upright_elements(monkeypatch):
    """The retry rule's wiring: a first solve that returns an inverted state is replaced by a second, line-search
    kept upright (feasible=True), from the same start; iterations count both."""
    scene, inp = _scene(1)
    calls = []
    real = S._solve

    def fake(nt, x0, hessian_mode, rtol, xtol, max_iterations, where, feasible, **kw):
        calls.append((feasible, x0.copy()))
        x, info = real(nt, x0, hessian_mode, rtol, xtol, max_iterations, where, feasible, **kw)
        if not feasible:  # pretend Newton ended in a folded state
            x = x.copy()
            top = np.argmax(x[:, 2])
            x[top, 2] = -0.05
        return x, info

    monkeypatch.setattr(S, "_solve", fake)
    x, info = S.step(scene, inp, [1e4], [0.45], scene.rest, scene.rest)
    assert [c[0] for c in calls] == [False, True] and np.array_equal(calls[0][1], calls[1][1])
    assert info["inversion_retry"] and info["iterations"] > 0
    nt = S._Newton(scene, inp, [1e4], [0.45], scene.rest, scene.rest, "auto", "auto", {})
    assert nt.jacobians(x).min() > 0
    calls.clear()
    monkeypatch.setattr(S, "_solve", real)
    x2, info2 = S.step(scene, inp, [1e4], [0.45], scene.rest, scene.rest)  # an upright solution: one solve
    assert "inversion_retry" not in info2 and np.array_equal(x, x2)


def test_a_blocked_retry_keeps_the_inverted_minimum(monkeypatch):
    """When the upright solve stalls against det F = 0 above Φ of the first solve's inverted state (info["blocked"],
    given that Φ as its ceiling), step returns the first solve's state and info, iterations counting both."""
    scene, inp = _scene(1)
    real, seen = S._solve, {}

    def fake(nt, x0, hessian_mode, rtol, xtol, max_iterations, where, feasible, **kw):
        x, info = real(nt, x0, hessian_mode, rtol, xtol, max_iterations, where, feasible)
        if not feasible:
            x = x.copy()
            x[np.argmax(x[:, 2]), 2] = -0.05
            seen.update(x=x, energy=nt.energy(x), iterations=info["iterations"])
            return x, info
        seen["ceiling"] = kw["ceiling"]
        return x, {**info, "iterations": 3, "blocked": True}

    monkeypatch.setattr(S, "_solve", fake)
    x, info = S.step(scene, inp, [1e4], [0.45], scene.rest, scene.rest)
    assert seen["ceiling"] == seen["energy"] and np.array_equal(x, seen["x"])
    assert info["inversion_retry"] and info["retry_blocked"] and "blocked" not in info
    assert info["iterations"] == seen["iterations"] + 3
