"""Online Adam on images while the object is still at rest (stages.steps.adapt._online, the rest phase): an
equilibrium start whose control reaches the object only after a few frames (the dinosaur's pusher still
approaching).  Those frames carry no information on θ, so E must not move; and a window whose states before it are
at rest starts from x_0(θ) — the window [0, s, s + 1, …] skipping the frames at rest — whose dL/dp is checked
against finite differences."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stages.capture import load_capture
from stages.parameters import params_from_theta, theta_from_params
from test_vision_bias import E_TRUE, _film, _make_capture

DELAY = 4  # the cable pulls from frame DELAY + 1 on: frames 0..DELAY are at rest
PR = (0.3, 0.49)


@pytest.fixture(scope="module")
def delayed(tmp_path_factory):
    """A box bar sagging at its equilibrium (start = equilibrium), its cable force delayed by DELAY frames, filmed by
    rsl's own model (P1, 1 step per frame, random Gaussians re-bound to the true frame 0, 2 cameras at 40 px).
    Returns (capture, workspace, backend, window objective)."""
    from stages.observations import VisionObservation
    from stages.sim.scene import frame_inputs, make_scene
    from stages.window_backends import FullSpace
    from stages.windows import StartWindow, WindowObjective

    frames = 10
    cap, ws, meshes = _make_capture(tmp_path_factory.mktemp("vision_rest"), frames)  # P1 mesh.h5, gaussians.h5
    ctl = json.loads((cap / "controls.json").read_text())
    for load in ctl["loads"]:
        f = np.asarray(load["force"], float)
        load["force"] = [f[max(k - DELAY, 0)].tolist() for k in range(len(f))]  # f[0] = 0: no pull up to DELAY
    (cap / "controls.json").write_text(json.dumps(ctl))
    capt = load_capture(cap)
    mesh = meshes[1]
    controls = capt.controls()
    scene = make_scene(mesh, controls, capt.material.model, capt.dt, capt.gravity)
    backend = FullSpace(scene, lambda k: frame_inputs(scene, controls, k), "auto")
    nu = np.array([capt.material.poisson])
    X = StartWindow(backend, capt.start).forward(list(range(frames)), np.array([E_TRUE]), nu, None)
    assert np.array_equal(X[DELAY], X[0]) and not np.allclose(X[DELAY + 1], X[0])  # at rest up to DELAY exactly
    _film(cap, ws, mesh, X)
    obs = VisionObservation(capt, ws, "", mesh, False)  # the frames just written
    return cap, ws, backend, WindowObjective(backend, obs, 1, PR, capt.start)


def test_window_from_rest_skips_the_frames_at_rest_and_its_gradient_matches_finite_differences(delayed):
    """The window [0, s, s+1, s+2] with lead 1 (frame 0 = x_0(θ), then frames s.. from (x_0, x_0)): its states are
    those of the uninterrupted simulation from frame 0 (the skipped frames are at rest), its losses those of the
    observed frames, and dL/dp — through the static solve of x_0(θ), the steps and the anchor x_0(θ) — equals
    Σ_t dL/dX_t · dX_t/dp + dL/dx_a · dx_a/dp with dX/dp, dx_a/dp by central differences of the simulation."""
    _, _, backend, obj = delayed
    E, nu = np.array([0.7 * E_TRUE]), np.array([0.42])
    p = np.concatenate(params_from_theta(E, nu, PR))
    s = DELAY
    sim = [0, s, s + 1, s + 2]
    states, losses, g, _ = obj(sim, p, None, True, lead=1)
    full = obj.win.forward(list(range(s + 3)), E, nu, None)
    np.testing.assert_allclose(backend.decode(states), backend.decode(full[[0, s, s + 1, s + 2]]), atol=1e-12)
    assert len(losses) == 3 and abs(g[0]) > 0
    obj.obs.rebind(obj.anchor_positions(E, nu))
    ref, dX = obj.obs.loss(sim[1:], backend.decode(states)[1:])
    ga = obj.obs.anchor_grad
    np.testing.assert_allclose(losses, ref, rtol=1e-10)
    for i, h in ((0, 1e-5), (1, 1e-4)):
        q = [theta_from_params(x[:1], x[1:], PR) for x in (p + np.eye(2)[i] * h, p - np.eye(2)[i] * h)]
        Xs = [backend.decode(obj.win.forward(sim, *th, None))[1:] for th in q]
        xas = [obj.anchor_positions(*th) for th in q]
        fd = np.sum(dX * (Xs[0] - Xs[1])) / (2 * h) + np.sum(ga * (xas[0] - xas[1])) / (2 * h)
        assert g[i] == pytest.approx(fd, rel=1e-4, abs=1e-8 * abs(g).max()), (i, g, fd)


def _adapt(cap: Path, ws: Path, **kw):
    from stages.artefacts import AdaptArtefact
    from stages.steps import adapt

    adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, window=2, space="full", loss="vision",
                                young_init=0.6 * E_TRUE, fit_poisson=False, estimator="adam", lr=0.1, substeps=1,
                                **kw))
    return AdaptArtefact.load(ws / "adapt.h5").young[:, 0]


@pytest.mark.parametrize("lead_in", [1, 2])
def test_e_does_not_move_while_the_object_is_at_rest_and_moves_toward_the_truth_after(delayed, lead_in):
    """With a lead-in (the rest phase comes with it): frames 0..DELAY show the object at its equilibrium, the re-bound
    Gaussians render them alike for every θ, so online Adam takes no step there (without the rest phase it steps on
    round-off and on the stored states' spurious gradient, and E wanders before the first frame that moves); once
    the cable pulls, E moves toward E_true."""
    cap, ws, _, _ = delayed
    E = _adapt(cap, ws, lead_in=lead_in)
    print(lead_in, np.round(E / E_TRUE, 3))
    assert E[0] == pytest.approx(0.6 * E_TRUE, rel=1e-12) and np.all(E[:DELAY + 1] == E[0]), E
    assert 0.7 < E[-1] / E_TRUE < 1.3, E  # a quarter of the way from 0.6 E_true to it at least, in 5 frames
