"""A capture filmed mid-motion ([capture] start = "moving", stages/moving_start.py): frame 0 and the state before it
are the frame-0 equilibrium x_e(θ) plus offsets (Δ_{−1}, Δ_0) that the Gauss–Newton windows estimate.

The window's states, adjoint and sensitivities (through the static solve and along the offsets) against central
differences; zero offsets are the equilibrium start; the force replay from the estimated (x_{−1}, x_0) continues
the simulation it came from; the prior's scale; rsl adapt on a capture `rsl synth --start moving` made, and the
inputs it refuses."""
from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest

from stages.errors import RslError
from stages.moving_start import (START_MOTION_SCALE, StartBasis, image_motion, marker_motion, start_directions,
                                 start_prior)
from stages.sim.static import simulate_from_start
from stages.windows import StartWindow
from stages.window_backends import ReducedSpace, substepped
from test_adapt_substeps import POISSON, YOUNG, _directions, _full_backend, _inputs_at, _scene
from test_adapt_substeps import full, reduced  # noqa: F401  (module-scoped fixtures: the scene, a PCA subspace)


@pytest.fixture(scope="module")
def held():
    """The clamped two-region bar of test_adapt_substeps, turned and raised by its clamp (hard handle)."""
    scene = _scene()
    return scene, _inputs_at(scene)


def test_zero_offsets_are_the_equilibrium_start(held):
    scene, at = held
    b = _full_backend(scene, at, 2, rtol=1e-12)
    frames = [0, 1, 2]
    eq = StartWindow(b, "equilibrium").forward(frames, YOUNG, POISSON, None)
    mv = StartWindow(b, "moving").forward(frames, YOUNG, POISSON, np.zeros((2,) + eq.shape[1:]))
    assert np.allclose(mv, eq, rtol=0, atol=1e-10)


@pytest.mark.parametrize("space, fixed", [("full", False), ("reduced", False), ("full", True)])
def test_moving_window_gradient_and_sensitivity_match_finite_differences(held, reduced, space, fixed):
    """dX/dp along E, ν (through x_e(θ), which moves x_0 and x_{−1} alike) and along the offsets, and dL/dθ by the
    adjoint, against central differences, 2 substeps per frame; offsets of about a millimetre (a start in motion;
    in the reduced space a PCA subspace of r = 6, offsets of z).  ``fixed``: the offsets added to a fixed state
    (StartWindow.reference, images: the Gaussians' fit pose) instead of x_e(θ)."""
    if space == "full":
        scene, at = held
        b = _full_backend(scene, at, 2, rtol=1e-12)
        shape = scene.rest.shape
    else:
        scene, at, model = reduced
        b = substepped(ReducedSpace(model, at), 2, at)
        b.fine.rtol = 1e-12
        shape = np.shape(model.z_rest)
    frames = [0, 1, 2]
    rng = np.random.default_rng(7)
    before = 1e-3 * rng.normal(size=(2,) + shape)
    x_e = StartWindow(b, "equilibrium").forward([0], YOUNG, POISSON, None)[0]
    reference = 0.5 * (x_e + b.rest_state) if fixed else None  # (a state between the rest and the sag)

    def window():
        win_ = StartWindow(b, "moving")
        win_.reference = reference
        return win_

    win = window()
    states = win.forward(frames, YOUNG, POISSON, before)
    assert np.allclose(states[0], (reference if fixed else x_e) + before[1], atol=1e-9)
    v = rng.normal(size=b.decode(states).shape)  # dL/dX of positions
    gE, gN = win.backward(frames, YOUNG, POISSON, states, before, v)
    de, dn, db = _directions(shape, rng)
    Sens = win.sensitivity(frames, YOUNG, POISSON, states, before, de, dn, db)  # positions (k, w, n, 3)
    h = 1e-4
    saved = b.records()  # every solve from the same Newton memory (the reduced one's; its order moves last bits)
    for j in range(len(de)):
        def at_h(s):
            b.restore_records(saved)
            return b.decode(window().forward(frames, YOUNG + s * h * de[j], POISSON + s * h * dn[j],
                                             before + s * h * db[j]))
        fd = (at_h(1) - at_h(-1)) / (2 * h)
        assert np.linalg.norm(fd) > 0
        assert np.linalg.norm(Sens[j] - fd) <= 1e-5 * np.linalg.norm(fd), j
        if not np.any(db[j]):  # the adjoint gives dL/dθ (the offsets are the window's own unknowns)
            fd_l, ad = float(np.sum(v * fd)), float(gE @ de[j] + gN @ dn[j])
            assert abs(ad - fd_l) <= 1e-5 * abs(fd_l) + 1e-8 * np.linalg.norm(v) * np.linalg.norm(fd), (j, ad, fd_l)


def test_replay_from_a_moving_start_continues_the_simulation_it_came_from(held):
    """simulate_from_start("moving", before=(x_{k−1}, x_k)) of a plain run's frames k−1, k repeats that run's frames
    k, k+1, … (one substep per frame: the state before x_k is x_{k−1} itself, no interpolation)."""
    scene, at = held
    T, k = 7, 3
    ref = simulate_from_start(scene, at, YOUNG, POISSON, T, "equilibrium")
    states: list = []
    X = simulate_from_start(scene, lambda f: at(f + k), YOUNG, POISSON, T - k, "moving", before=ref[k - 1:k + 1],
                            states=states)
    assert np.allclose(X, ref[k:], rtol=0, atol=1e-9)
    assert len(states) == T - k
    with pytest.raises(ValueError, match="moving start"):
        simulate_from_start(scene, at, YOUNG, POISSON, 2, "moving")


def test_start_prior_spreads_the_motion_of_one_frame_over_the_directions():
    """σ_j g_j √m = START_MOTION_SCALE · s for both halves; D moves both states along the shape, x_{−1} alone along
    the velocity."""
    m = 4
    sb = StartBasis(np.eye(m), np.array([1.0, 2.0, 4.0, 0.5]))
    markers = np.zeros((3, 5, 3))
    markers[1, :, 0] = 0.003  # every marker moves 3 mm from frame 0 to frame 1
    assert marker_motion(markers) == pytest.approx(0.003)
    sig = start_prior(sb, marker_motion(markers), size=0.2)
    assert sig.shape == (2 * m,)
    assert np.allclose(sig[:m] * sb.gain * np.sqrt(m), START_MOTION_SCALE * 0.003)
    assert np.allclose(sig[m:], sig[:m])
    assert marker_motion(markers[:1]) is None
    one_frame = start_prior(sb, None, size=0.2)  # frame 1 not there yet: 1 % of the size
    assert np.allclose(one_frame[:m] * sb.gain * np.sqrt(m), START_MOTION_SCALE * 0.002)
    D = start_directions(sb)
    assert D.shape == (2 * m, 2, m)
    assert np.array_equal(D[:m, 0], np.eye(m)) and np.array_equal(D[:m, 1], np.eye(m))
    assert np.array_equal(D[m:, 0], np.eye(m)) and not np.any(D[m:, 1])


def test_image_motion_is_the_outline_s_mean_normal_displacement_at_the_object_s_depth():
    """A 20-pixel square moved 3 pixels along x from frame 0 to frame 1, seen 2 m away at f = 100 px: the pixels
    that change, 2·20·3, over the outline's 4·20 − 4 pixels, times 2 m / 100 px — half the motion (the sides
    along it do not see it), the RMS over the cameras; no masks or no frame 1: None."""
    from stages.domain.cameras import Camera

    m = np.zeros((2, 40, 40), bool)
    m[0, 10:30, 10:30] = True
    m[1, 10:30, 13:33] = True
    cam = Camera("c0", np.array([[100.0, 0, 20], [0, 100.0, 20], [0, 0, 1]]), np.zeros(5), np.eye(3), np.zeros(3),
                 40, 40)
    got = image_motion({"c0": m}, [cam], np.array([0.0, 0.0, 2.0]))
    assert got == pytest.approx(2 * 20 * 3 / (4 * 20 - 4) * 2.0 / 100.0, rel=1e-12)
    cam2 = Camera("c1", cam.K, cam.dist, cam.R, np.array([0.0, 0.0, 2.0]), 40, 40)  # twice as far: twice the metres
    both = image_motion({"c0": m, "c1": m}, [cam, cam2], np.array([0.0, 0.0, 2.0]))
    assert both == pytest.approx(got * np.sqrt((1 + 4) / 2), rel=1e-12)
    assert image_motion(None, [cam], np.zeros(3)) is None
    assert image_motion({"c0": m[:1]}, [cam], np.array([0.0, 0.0, 2.0])) is None


# =========================================================================== rsl adapt on a moving capture
def _moving_beam_capture(root, frames: int):
    """The cable-pulled beam of test_adapt_e2e filmed from 8 frames after its equilibrium start (``frames``
    frames; the pull's speed follows the capture's length), on the truth's own P1 mesh: (capture, workspace)."""
    from stages.steps import calibrate, synth, tetrahedralize
    from test_adapt_e2e import BEAM, E_TRUE

    if not BEAM.is_file():
        pytest.skip(f"{BEAM} not present")
    cap = root / "cap"
    synth.run(synth.SynthConfig(mesh=BEAM, out=cap, scenario="cable", cameras=1, frames=frames, resolution=32,
                                young=E_TRUE, markers=30, calib_views=0, seed=0, start="moving", lead_frames=8))
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    ws = root / "ws"
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    return cap, ws


@pytest.fixture(scope="module")
def moving_beam(tmp_path_factory):
    """The cable-pulled beam of test_adapt_e2e, filmed from 8 frames after its equilibrium start (16 frames)."""
    from test_adapt_e2e import E_TRUE

    cap, ws = _moving_beam_capture(tmp_path_factory.mktemp("moving"), frames=16)
    return cap, ws, E_TRUE


def test_adapt_follows_a_capture_filmed_mid_motion(moving_beam):
    """gn, markers, full space, from 0.5 E_true, on the same-model beam (only the start is unknown): the settled E
    within 3 % of the truth (1.001 E_true when this test was written; declared "equilibrium", the same capture gave
    1.04, swinging 0.92–1.24 over its first frames), the trajectory within 1.5 mm of the truth's surface on every frame (0.5 mm), and the estimated
    (x_{−1}, x_0) stored for the force replay."""
    from stages.artefacts import AdaptArtefact, MeshArtefact
    from stages.steps import adapt

    cap, ws, e_true = moving_beam
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, loss="markers", window=3,
                                                         estimator="gn", space="full", young_init=0.5 * e_true,
                                                         substeps=1)))
    settled = art.young[8:, 0] / e_true
    assert np.all(np.abs(settled - 1.0) <= 0.03), settled
    mesh = MeshArtefact.load(ws / "mesh.h5")
    ids = np.unique(mesh.surface_faces)
    truth = np.load(cap / "truth" / "surface.npz")["vertices"]
    err = np.sqrt(np.mean(np.sum((art.positions[:, ids] - truth) ** 2, axis=-1), axis=1))
    assert np.all(err <= 1.5e-3), err
    assert art.start_positions is not None and art.start_positions.shape == (2, mesh.n_vertices, 3)
    assert np.allclose(art.start_positions[1], art.positions[0])
    # the replay of the adapted θ(t) from them (rsl export --forces) starts at adapt's frame 0
    from stages.forces import adapted_forces
    from stages.capture import load_capture
    from stages.sim.scene import make_scene

    c = load_capture(cap)
    scene = make_scene(mesh, c.controls(), c.material.model, c.dt, c.gravity)
    rows, applied, source = adapted_forces(scene, c.controls(), art, c.start, 1, lambda: None, extrapolate=False)
    assert "replay" in source and len(applied) == len(art.frames)
    # the loss sweep starts from that estimated start: the marker loss over the frames lowest at E_true
    from stages.steps import evaluate

    out = json.loads(evaluate.run(evaluate.EvaluateConfig(capture=cap, workspace=ws, sweep=True, sweep_points=5,
                                                          sweep_min=0.7, sweep_max=1.4, plot=False)).read_text())
    sw = out["sweep"]
    assert sw["start"] == "moving" and sw["interior"], sw
    assert sw["min_over_true"] == pytest.approx(1.0, abs=0.03), sw


@pytest.mark.parametrize("kw, message", [
    ({"loss": "markers", "estimator": "adam"}, r"start = \"moving\" needs --estimator gn --mode online"),
    ({"loss": "markers", "frames": "2:8"}, r"start = \"moving\" needs the frame range to start at frame 0"),
])
def test_adapt_refuses_what_a_moving_start_cannot_run(moving_beam, tmp_path, kw, message):
    from stages.steps import adapt

    cap, ws, _ = moving_beam
    ws2 = tmp_path / "ws"
    shutil.copytree(ws, ws2)
    (ws2 / "adapt.h5").unlink(missing_ok=True)
    with pytest.raises(RslError, match=message):
        adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws2, window=3, space="full", **kw))
    assert not (ws2 / "adapt.h5").exists()


def test_fit_gaussians_poses_a_moving_start_at_its_equilibrium_and_the_loss_sweep_refuses_it(moving_beam):
    """fit_pose without masks.h5: frame 0 of a moving start is posed at the static equilibrium under its controls
    (with masks, from them: tests/test_moving_start_images.py); a later frame cannot be posed (its velocity is
    unknown)."""
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture
    from stages.sim.scene import frame_inputs, make_scene
    from stages.sim.static import start_state
    from stages.steps.fit_gaussians import fit_pose
    from stages.sweep import sweep

    cap, ws, e_true = moving_beam
    c, mesh = load_capture(cap), MeshArtefact.load(ws / "mesh.h5")
    x, state = fit_pose(c, mesh, 0)
    scene = make_scene(mesh, c.controls(), c.material.model, c.dt, c.gravity)
    xe = start_state(scene, frame_inputs(scene, c.controls(), 0), [c.material.region_young(r) for r in
                     scene.region_names], [c.material.region_poisson(r) for r in scene.region_names], "equilibrium")
    assert (state["start"], state["declared_start"]) == ("equilibrium", "moving")
    assert np.allclose(x, xe, atol=1e-9) and np.abs(x - mesh.vertices).max() > 1e-4  # (it sags)
    with pytest.raises(RslError, match=r"capture.toml: start = \"moving\".*--frame 0"):
        fit_pose(c, mesh, 1)
    with pytest.raises(RslError, match=r"the loss sweep simulates every E from the start state"):
        sweep(c, mesh, [e_true])
    with pytest.raises(ValueError, match=r"should be \(2, \d+, 3\) on the mesh's nodes"):
        sweep(c, mesh, [e_true], before=np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match=r"the sweep's start is 'rest', not moving"):
        sweep(c, mesh, [e_true], start="rest", before=np.stack([mesh.vertices] * 2))
    # rsl evaluate --sweep takes the start adapt estimated; without adapt.h5 it says so
    from stages.steps import evaluate

    bare = ws.parent / "ws_without_adapt"
    bare.mkdir(exist_ok=True)
    shutil.copy(ws / "mesh.h5", bare / "mesh.h5")
    with pytest.raises(RslError, match=r"start = \"moving\": the loss sweep starts from the start state rsl adapt "
                                       r"estimates, and .*adapt.h5 is not there; run rsl adapt first"):
        evaluate.run(evaluate.EvaluateConfig(capture=cap, workspace=bare, sweep=True, plot=False))


def test_capture_toml_names_the_three_starts(moving_beam, tmp_path):
    from stages.capture import load_capture

    cap, _, _ = moving_beam
    bad = tmp_path / "cap"
    shutil.copytree(cap, bad)
    toml = bad / "capture.toml"
    toml.write_text(re.sub(r'start = "\w+"', 'start = "swinging"', toml.read_text()))
    with pytest.raises(RslError, match=r'"equilibrium", "rest" or "moving", found "swinging"'):
        load_capture(bad)


def test_rsl_run_adapts_a_moving_capture_from_its_markers(moving_beam, tmp_path):
    """`rsl run` on a capture filmed mid-motion: with markers, segment and fit-gaussians do not apply (said so in
    the plan) and adapt takes the markers, unless --set adapt.loss=vision; without markers the images."""
    from stages.pipeline import plan, with_capture_defaults

    cap, _, _ = moving_beam
    steps = {st.stage.name: st for st in plan(cap, tmp_path / "ws")}
    for name in ("segment", "fit-gaussians"):
        assert steps[name].action == "skip" and "filmed mid-motion" in steps[name].reason
    assert steps["adapt"].action == "run" and steps["tetrahedralize"].action == "run"
    vision = {st.stage.name: st for st in plan(cap, tmp_path / "ws", overrides={"adapt": {"loss": "vision"}})}
    assert all(vision[name].action == "run" for name in ("segment", "fit-gaussians"))  # images: Gaussians needed
    assert with_capture_defaults(None, True) == {"adapt": {"loss": "markers"}}
    assert with_capture_defaults({"adapt": {"loss": "vision"}}, True) == {"adapt": {"loss": "vision"}}
    assert with_capture_defaults({"export": {"forces": "true"}}, False) == {"export": {"forces": "true"}}
    bare = tmp_path / "cap"
    shutil.copytree(cap, bare)
    (bare / "markers.csv").unlink()
    steps = {st.stage.name: st for st in plan(bare, tmp_path / "ws")}
    assert all(steps[name].action == "run" for name in ("segment", "fit-gaussians"))


def test_a_moving_start_may_show_an_obstacle_already_pressing():
    """check_obstacles_clear: a sphere 2 % of the object's size inside its rest shape at frame 0 is an error for a
    declared start, allowed for a capture filmed mid-motion (up to MOVING_CONTACT_DEPTH), and one 30 % deep is an
    error for both."""
    from pathlib import Path

    from stages.capture import CaptureError, check_obstacles_clear, parse_controls

    g = np.linspace(-0.1, 0.1, 11)
    v = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)  # size: diagonal 0.346 m
    size = float(np.linalg.norm(np.ptp(v, axis=0)))

    def controls(depth: float):  # a sphere whose surface lies ``depth`` × size inside the grid's +x face
        r = 0.05
        c = 0.1 + r - depth * size
        return parse_controls({"obstacles": [{"name": "pusher", "shape": "sphere", "radius": r,
                                              "poses": [[c, 0, 0, 1, 0, 0, 0]]}]}, Path("controls.json"))

    with pytest.raises(CaptureError, match="starts inside the object at frame 0"):
        check_obstacles_clear(controls(0.02), v, start="equilibrium")
    check_obstacles_clear(controls(0.02), v, start="moving")
    for start in ("equilibrium", "moving"):
        with pytest.raises(CaptureError, match="inside"):
            check_obstacles_clear(controls(0.3), v, start=start)


def test_adapt_checks_a_moving_start_s_markers_against_its_estimated_frame_0(tmp_path):
    """A beam pulled fast, filmed 8 frames in (4 frames): its frame-0 markers lie 12 % of its size from the frame-0
    equilibrium, so declared `equilibrium` adapt warns; declared `moving` it checks them against frame 0 as
    estimated (once the windows leave frame 0), and does not."""
    from stages.progress import SilentReporter
    from stages.steps import adapt
    from test_adapt_e2e import E_TRUE

    cap, ws = _moving_beam_capture(tmp_path, frames=4)
    toml = cap / "capture.toml"
    warned = {}
    for start in ("moving", "equilibrium"):
        toml.write_text(re.sub(r'start = "\w+"', f'start = "{start}"', toml.read_text()))
        reporter = SilentReporter()
        adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, loss="markers", window=3, estimator="gn",
                                    space="full", young_init=0.5 * E_TRUE, substeps=1), reporter)
        warned[start] = [m for m in reporter.messages if "frame-0 marker lies" in m]
    assert warned["equilibrium"] and "simulated with the initial E" in warned["equilibrium"][0]
    assert not warned["moving"], warned["moving"]


def test_markers_of_a_moving_start_are_judged_against_frame_0_as_estimated(tmp_path):
    """MarkerObservation.fit_to_tracks: markers 10 % of the object's size off the equilibrium surface (a capture
    filmed in a large motion) raise the frame-0 check there; fitted to tracks on which they lie, their distance
    and the check fall to 0, and the bound points follow the tracks."""
    from types import SimpleNamespace

    from stages.observations import MarkerObservation

    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.linspace(0, 0.2, 5), np.linspace(0, 0.2, 5))
    x_eq = np.stack([u.ravel(), v.ravel(), np.zeros(25)], 1)
    faces = np.array([[i * 5 + j, i * 5 + j + 1, i * 5 + j + 6] for i in range(4) for j in range(4)]
                     + [[i * 5 + j, i * 5 + j + 6, i * 5 + j + 5] for i in range(4) for j in range(4)])
    X = np.stack([x_eq + [0.0, 0.0, 0.02 + 0.001 * t] for t in range(3)])  # frame 0 lifted by 0.02 m
    fid, bary = rng.integers(0, len(faces), 12), rng.dirichlet(np.ones(3), 12)
    P = np.einsum("mk,tmkd->tmd", bary, X[:, faces[fid]])
    capture = SimpleNamespace(markers=lambda: P, markers_path=tmp_path / "markers.csv")
    obs = MarkerObservation(capture, x_eq, faces, len(x_eq))
    assert obs.far >= 0.05
    moved = obs.fit_to_tracks(range(3), X)
    assert moved > 0.0 and obs.far <= 1e-9
    assert np.allclose(obs.binding.positions(X), P, atol=1e-12)
