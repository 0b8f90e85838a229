"""Loss sweeps (stages/sweep.py): the parabolic minimum, and a marker-loss sweep whose minimum is E_true on a
capture simulated with rsl's own model under each declared start (and off it under the wrong start)."""
from __future__ import annotations

import json

import meshio
import numpy as np
import pytest

from stages.capture import load_capture
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets
from stages.sweep import parabolic_minimum, sweep
from stages.steps.synth import SynthConfig, prepare_mesh, run


def test_parabolic_minimum_finds_the_vertex_on_an_uneven_grid():
    x = np.array([-1.0, -0.3, 0.2, 1.1, 2.0])
    y = 3.0 * (x - 0.37) ** 2 + 1.0
    xm, i, interior = parabolic_minimum(x, y)
    assert interior and i == 2 and xm == pytest.approx(0.37, abs=1e-12)
    xm, i, interior = parabolic_minimum(x, -x)  # decreasing: the grid end, flagged
    assert xm == 2.0 and not interior


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    v, t = box_tets((6, 2, 2), (0.2, 0.04, 0.04))
    path = tmp_path_factory.mktemp("mesh") / "bar.mesh"
    meshio.write(str(path), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    return path, v, t


@pytest.mark.parametrize("start", ["equilibrium", "rest"])
def test_marker_sweep_is_lowest_at_the_truth_on_rsls_own_model(box, tmp_path, start):
    path, v, t = box
    out = run(SynthConfig(mesh=path, out=tmp_path / start, scenario="cable", cameras=1, frames=8, resolution=32,
                          markers=12, calib_views=0, young=6e4, start=start, size=0.2))
    cap = load_capture(out)
    pm = prepare_mesh(v, t, 0.2, "")
    mesh = mesh_artefact(pm.vertices, pm.tets, cap.density)
    grid = 6e4 * np.array([0.7, 0.85, 1.0, 1.15, 1.3])
    res = sweep(cap, mesh, grid, "markers", poisson=0.45)
    assert res.interior and res.i_min == 2
    assert res.young_min == pytest.approx(6e4, rel=0.01)
    assert res.loss[2] < 1e-12 * res.loss.max()  # the same model: the truth reproduces the markers exactly
    other = "rest" if start == "equilibrium" else "equilibrium"
    wrong = sweep(cap, mesh, grid, "markers", poisson=0.45, start=other)
    assert wrong.loss.min() > 1e3 * res.loss[2] + 1e-12  # the wrong start cannot reproduce the markers


def test_a_continued_simulation_repeats_the_uninterrupted_one(box, tmp_path):
    """continue_frames from a simulate_from_start run's last states (last_states) gives, float for float, the frames
    the uninterrupted run gives after them, with substeps too."""
    from stages.sim.scene import frame_inputs, make_scene
    from stages.sim.static import continue_frames, last_states, simulate_from_start

    path, v, t = box
    cap = load_capture(run(SynthConfig(mesh=path, out=tmp_path / "cap", scenario="cable", cameras=1, frames=8,
                                       resolution=32, markers=12, calib_views=0, young=6e4, size=0.2)))
    ctl = cap.controls()
    pm = prepare_mesh(v, t, 0.2, "")
    mesh = mesh_artefact(pm.vertices, pm.tets, cap.density)
    scene = make_scene(mesh, ctl, "stable_neohookean", cap.dt, cap.gravity)
    E, nu = np.array([5e4]), np.array([0.4])
    for S in (1, 3):
        states: list = []
        X = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), E, nu, 8, "equilibrium", S,
                                states=states)
        head: list = []
        Xa = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), E, nu, 4, "equilibrium", S,
                                 states=head)
        Xb = continue_frames(scene, lambda f: frame_inputs(scene, ctl, f), E, nu, range(4, 8),
                             *last_states(Xa, head), S)
        np.testing.assert_array_equal(Xb, X[4:])


def test_a_sweep_after_a_step_of_e_given_the_past_is_lowest_at_the_new_e(box, tmp_path):
    """past_young: frames 0..4 simulated with the truth's E (6e4), frames 5..9 with each grid value: on rsl's own
    model the loss of frames 5..9 vanishes at the new E (1.8e5) and is lowest there; swept from frame 0 with one E
    (no past) the same frames are not reproduced by any grid value."""
    path, v, t = box
    out = run(SynthConfig(mesh=path, out=tmp_path / "step", scenario="cable", cameras=1, frames=10, resolution=32,
                          markers=12, calib_views=0, young=6e4, young_schedule="6e4@0,1.8e5@5", size=0.2))
    cap = load_capture(out)
    pm = prepare_mesh(v, t, 0.2, "")
    mesh = mesh_artefact(pm.vertices, pm.tets, cap.density)
    grid = 1.8e5 * np.array([0.7, 0.85, 1.0, 1.15, 1.3])
    res = sweep(cap, mesh, grid, "markers", frames=(5, 10), poisson=0.45, past_young=np.full((5, 1), 6e4))
    assert res.interior and res.i_min == 2 and res.young_min == pytest.approx(1.8e5, rel=0.01)
    assert res.loss[2] < 1e-12 * res.loss.max()
    plain = sweep(cap, mesh, grid, "markers", frames=(5, 10), poisson=0.45)
    assert plain.loss.min() > 1e3 * res.loss[2] + 1e-12
    with pytest.raises(ValueError, match="past_young"):
        sweep(cap, mesh, grid, "markers", frames=(5, 10), poisson=0.45, past_young=np.full((4, 1), 6e4))
    # rsl evaluate --sweep-past truth: the same sweep, its past read from truth/material.csv
    from stages.steps.evaluate import EvaluateConfig
    from stages.steps.evaluate import run as evaluate

    ws = tmp_path / "ws"
    ws.mkdir()
    mesh.save(ws / "mesh.h5")
    kw = dict(capture=out, workspace=ws, sweep=True, sweep_frames="5:10", sweep_points=5, sweep_min=0.7,
              sweep_max=1.3, plot=False)
    given = json.loads(evaluate(EvaluateConfig(**kw, sweep_past="truth")).read_text())["sweep"]
    assert given["past"] == "truth" and given["min_over_true"] == pytest.approx(1.0, rel=0.01)
    ends = [0, -1]  # (the grid's ends are the same E; evaluate spaces the others evenly in log E)
    assert np.allclose(np.array(given["loss_values"])[ends], res.loss[ends], rtol=1e-9)
    alone = json.loads(evaluate(EvaluateConfig(**kw)).read_text())["sweep"]
    assert alone["past"] == "grid" and np.allclose(np.array(alone["loss_values"])[ends], plain.loss[ends], rtol=1e-9)


def test_one_regions_sweep_is_lowest_at_its_own_truth(box, tmp_path):
    """region=...: only that region's E takes the grid's values, the other held at its base_young. On rsl's own
    two-region model each region's marker loss vanishes at its own E_true; the stiff half swept with the body held
    at a wrong E is not reproduced; an unknown region is refused."""
    path, v, t = box
    out = run(SynthConfig(mesh=path, out=tmp_path / "two", scenario="cable", cameras=1, frames=8, resolution=32,
                          markers=12, calib_views=0, young=6e4, region="stiff=1.8e5@x>0.5", size=0.2))
    cap = load_capture(out)
    pm = prepare_mesh(v, t, 0.2, "stiff=1.8e5@x>0.5")
    mesh = mesh_artefact(pm.vertices, pm.tets, cap.density, pm.tet_region, tuple(pm.region_names))
    scales = np.array([0.7, 0.85, 1.0, 1.15, 1.3])
    truth = {"body": 6e4, "stiff": 1.8e5}
    base = [truth[r] for r in pm.region_names]
    for name, e in truth.items():
        res = sweep(cap, mesh, e * scales, "markers", poisson=0.45, base_young=base, region=name)
        assert res.interior and res.i_min == 2 and res.young_min == pytest.approx(e, rel=0.01), name
        assert res.loss[2] < 1e-12 * res.loss.max(), name
        assert res.info["region"] == name
    off = sweep(cap, mesh, 1.8e5 * scales, "markers", poisson=0.45, base_young=[0.7 * b for b in base],
                region="stiff")
    assert off.loss.min() > 1e3 * res.loss[2] + 1e-12  # the body held at 0.7 E_true: no stiff E reproduces it
    with pytest.raises(ValueError, match="no region 'tip'"):
        sweep(cap, mesh, scales, "markers", poisson=0.45, region="tip")
