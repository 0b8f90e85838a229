"""Newton's start when the inertial guess y = 2x_{t−1} − x_{t−2} lies beyond det F = 0.

Reproduction (small) of 'Newton did not converge (residual 3.7e-07 after 100 iterations)': a soft P2 box clamped at
its base, moving down at 3 m/s into a sphere, so that y puts its top through its base (every quadrature point
inverted).  From y, |λ| Newton crossed the everted, non-convex region of stable Neo-Hookean, stalled at a symmetric
saddle of Φ (exact Hessian indefinite on the free DOFs) and needed 816 iterations to end in a local minimum with a
higher Φ than the upright one.  Newton now starts at the last upright point on the segment from x_{t−1} to y."""
from __future__ import annotations

import numpy as np
import pytest

from stages.artefacts import mesh_artefact
from stages.capture import Controls, Handle, Obstacle, Selection, Track
from stages.sim import scene as S
from stages.sim.linsolve import available_solvers
from stages.sim.meshgen import box_tets

SIZE = (0.1, 0.1, 0.04)  # m
RADIUS = 0.03  # m, the sphere resting on the top face's centre
YOUNG, POISSON = 1e4, 0.45


def _case(speed: float):
    """(scene, frame-1 inputs, x_{t−1} = rest, x_{t−2}): the top moving down at ``speed`` m/s (linearly in height)."""
    v, t = box_tets((3, 3, 2), SIZE)
    base = Handle("base", Selection("box", box=np.array([[-1, -1, -1], [1, 1, 1e-9]])), 1e5,
                  Track.constant([0, 0, 0, 1, 0, 0, 0], True), hard=True)
    poses = np.array([[SIZE[0] / 2, SIZE[1] / 2, SIZE[2] + RADIUS, 1, 0, 0, 0]] * 2)
    ball = Obstacle("ball", "sphere", radius=RADIUS, poses=Track(np.arange(2), poses, True))
    ctl = Controls(handles=[base], loads=[], obstacles=[ball], friction=0.0)
    scene = S.make_scene(mesh_artefact(v, t, 1000.0, order=2), ctl, "stable_neohookean", 1 / 30, [0, 0, -9.81])
    x1 = scene.rest.copy()
    x2 = scene.rest + (scene.rest[:, 2] / SIZE[2])[:, None] * np.array([0.0, 0.0, speed * scene.dt])
    return scene, S.frame_inputs(scene, ctl, 1), x1, x2


def _phi(scene, inp, x, x1, x2) -> float:
    mu, lam = S._region_lame(scene, [YOUNG], [POISSON])
    return S.total_energy(scene, inp, x, 2 * x1 - x2, x1, mu, lam)


@pytest.mark.parametrize("solver", available_solvers())
def test_step_from_an_everted_guess_converges_to_an_upright_minimum(solver):
    scene, inp, x1, x2 = _case(3.0)
    nt = S._Newton(scene, inp, [YOUNG], [POISSON], x1, x2, solver, "auto", {})
    assert np.all(nt.jacobians(S.apply_hard_targets(scene, inp, nt.y)) <= 0.0)  # y is everted everywhere
    x, info = S.step(scene, inp, [YOUNG], [POISSON], x1, x2, solver=solver)  # default 100 iterations
    assert info["residual"] <= 1e-8 and 0.0 < info["start_alpha"] < 1.0
    assert nt.jacobians(x).min() > 0.5
    # a minimum, not a saddle: the exact Hessian is positive definite on the free DOFs
    H = S.hessian(scene, inp, x, x1, [YOUNG], [POISSON], project=False).toarray()
    free = ~S.fixed_dofs(scene)
    Hf = H[np.ix_(free, free)]
    np.linalg.cholesky(0.5 * (Hf + Hf.T))
    # the same minimum as Newton started at x_{t−1} (upright, no momentum through the base)
    x_prev_start, _ = S.step(scene, inp, [YOUNG], [POISSON], x1, x2, x_init=x1, solver=solver)
    assert np.abs(x - x_prev_start).max() < 1e-8
    assert _phi(scene, inp, x, x1, x2) == pytest.approx(_phi(scene, inp, x_prev_start, x1, x2), rel=1e-10)


def test_upright_start_is_the_guess_when_it_inverts_nothing_and_else_the_largest_upright_halving():
    scene, inp, x1, x2 = _case(1.0)  # y compresses the box by 83 % but inverts nothing
    nt = S._Newton(scene, inp, [YOUNG], [POISSON], x1, x2, "auto", "auto", {})
    upright = nt.jacobians(x1) > 0.0
    x0, a = S._upright_start(nt, nt.y, upright)
    assert a == 1.0 and np.array_equal(x0, S.apply_hard_targets(scene, inp, nt.y))  # ordinary steps: unchanged
    scene, inp, x1, x2 = _case(3.0)
    nt = S._Newton(scene, inp, [YOUNG], [POISSON], x1, x2, "auto", "auto", {})
    x0, a = S._upright_start(nt, nt.y, upright)
    assert 0.0 < a < 1.0 and np.array_equal(x0, S.apply_hard_targets(scene, inp, x1 + a * (nt.y - x1)))
    assert nt.jacobians(x0).min() > 0.0
    assert nt.jacobians(S.apply_hard_targets(scene, inp, x1 + 2 * a * (nt.y - x1))).min() <= 0.0
