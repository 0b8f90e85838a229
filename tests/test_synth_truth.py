"""`rsl synth` without the inverse crime: a truth on quadratic / refined tets with substeps and hard handles,
the declared start state of frame 0, and truth/forces.csv (the forces `rsl export --forces` reports)."""
from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np
import pytest

from conftest import run_rsl
from stages.capture import FORCE_HEADER, load_capture, read_forces_csv, read_truth
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets, refine_tets
from stages.steps.synth import SynthConfig, run
from test_synth import box_mesh  # noqa: F401  (the module-scoped bar mesh fixture)


@pytest.fixture(scope="module")
def p2_capture(box_mesh, tmp_path_factory) -> Path:
    """A cable capture by the real CLI: P2 truth, 3 substeps, hard handles, equilibrium start."""
    out = tmp_path_factory.mktemp("synth") / "cable_p2"
    proc = run_rsl("synth", box_mesh, out, "--scenario", "cable", "--cameras", "1", "--frames", "5",
                   "--resolution", "32", "--markers", "6", "--calib-views", "0", "--young", "8e4",
                   "--truth-order", "2", "--substeps", "3", "--handles", "hard", "--start", "equilibrium")
    assert proc.returncode == 0, proc.stderr
    assert "truth: P2" in " ".join(proc.stderr.split())
    return out


def _truth_scene(cap, dt=None):
    from stages.sim.scene import make_scene

    m = meshio.read(str(cap.truth_dir / "object.vtu"))
    tets = np.asarray(m.cells_dict["tetra10"], np.int64)
    truth = read_truth(cap)
    art = mesh_artefact(np.asarray(m.points, np.float64), tets, cap.density,
                        np.asarray(m.cell_data_dict["region"]["tetra10"], np.int64), tuple(truth.region_names))
    return make_scene(art, cap.controls(), cap.material.model, cap.dt if dt is None else dt, cap.gravity), truth


def test_p2_capture_declares_its_start_and_ships_the_coarse_rest_surface(p2_capture, box_mesh):
    cap = load_capture(p2_capture)
    assert cap.start == "equilibrium"
    ctl = cap.controls()
    assert all(h.hard for h in ctl.handles)  # a clamp is declared as one
    shipped = meshio.read(str(p2_capture / "object.obj"))
    coarse = meshio.read(str(box_mesh))
    assert len(shipped.points) < len(coarse.points)  # the surface of the coarse mesh, not the truth's nodes
    m = meshio.read(str(cap.truth_dir / "object.vtu"))
    assert m.cells_dict["tetra10"].shape == (144, 10)
    assert not (cap.truth_dir / "object.mesh").exists()


def test_frame0_is_the_static_equilibrium_and_the_sequence_resimulates(p2_capture):
    from stages.sim.scene import frame_inputs
    from stages.sim.static import residual, simulate_from_start

    cap = load_capture(p2_capture)
    scene, truth = _truth_scene(cap)
    ctl = cap.controls()
    T = truth.young.shape[0]
    X = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), truth.young, truth.poisson, T,
                            cap.start, substeps=3)
    np.testing.assert_allclose(truth.vertices, X[:, np.unique(_surface(scene))], atol=1e-9)
    r = residual(scene, frame_inputs(scene, ctl, 0), truth.young[0], truth.poisson[0], X[0])
    weight = np.linalg.norm(scene.masses[:, None] * scene.gravity)
    assert np.linalg.norm(r) < 1e-7 * weight
    assert -(X[0] - scene.rest)[:, 2].min() > 1e-3  # frame 0 sags: it is not the rest shape


def _surface(scene):
    from stages.sim.quadrature import quadratic_surface

    return quadratic_surface(scene.tets)


def test_rest_start_shows_the_rest_shape(box_mesh, tmp_path):
    out = run(SynthConfig(mesh=box_mesh, out=tmp_path / "rest", scenario="cable", cameras=1, frames=3,
                          resolution=32, markers=0, calib_views=0, start="rest", truth_refine=1))
    cap = load_capture(out)
    assert cap.start == "rest"
    truth = read_truth(cap)
    m = meshio.read(str(cap.truth_dir / "object.mesh"))
    assert len(m.cells_dict["tetra"]) == 8 * 144
    assert len(m.points) == len(refine_tets(*box_tets((6, 2, 2), (0.2, 0.05, 0.05)), np.zeros(144, int))[0])
    surf_rest = _rest_surface(cap)
    np.testing.assert_allclose(truth.vertices[0], surf_rest, atol=1e-12)
    assert np.abs(truth.vertices[2] - surf_rest).max() > 1e-4  # released: it moves after frame 0


def _rest_surface(cap) -> np.ndarray:
    from stages.sim.meshgen import surface_faces

    m = meshio.read(str(cap.truth_dir / "object.mesh"))
    return np.asarray(m.points)[np.unique(surface_faces(np.asarray(m.cells_dict["tetra"])))]


def test_equilibrium_start_is_refused_for_a_falling_object(box_mesh, tmp_path):
    proc = run_rsl("synth", box_mesh, tmp_path / "drop", "--scenario", "drop", "--frames", "2", "--cameras", "1",
                   "--resolution", "32", "--calib-views", "0", "--start", "equilibrium")
    assert proc.returncode != 0
    assert "--start rest" in proc.stderr and "Traceback" not in proc.stderr


def test_truth_forces_have_the_export_header_and_balance_the_load(p2_capture):
    from stages.steps.export import FORCE_HEADER as EXPORT_HEADER

    assert FORCE_HEADER == EXPORT_HEADER
    cap = load_capture(p2_capture)
    rows = read_forces_csv(cap.truth_dir / "forces.csv")
    T = read_truth(cap).young.shape[0]
    assert [r["frame"] for r in rows] == list(range(T))  # one handle, no obstacle
    scene, _ = _truth_scene(cap)
    ctl = cap.controls()
    weight = scene.masses.sum() * scene.gravity
    load0 = ctl.loads[0].force.at(0)
    # frame 0 is a static equilibrium: what the clamp exerts balances gravity and the cable
    applied0 = np.array([rows[0]["applied_fx_N"], rows[0]["applied_fy_N"], rows[0]["applied_fz_N"]])
    np.testing.assert_allclose(applied0, -(weight + load0), atol=1e-6 * np.linalg.norm(weight))
    # and the body's internal forces on the clamped vertices balance the clamp minus their own weight
    hid = scene.handles[0].ids
    internal0 = np.array([rows[0]["fx_N"], rows[0]["fy_N"], rows[0]["fz_N"]])
    w_h = scene.masses[hid].sum() * scene.gravity
    np.testing.assert_allclose(internal0, -(applied0 + w_h), atol=1e-6 * np.linalg.norm(weight))
    assert all(r["n_vertices"] == len(hid) for r in rows)


def test_export_style_forces_on_the_truth_model_reproduce_truth_forces(p2_capture):
    """The forces `rsl export --forces` computes (stages.sim.stress.set_forces with the internal nodal forces,
    hard-handle reactions from the residual) on a model with the truth's discretisation (P2 on the shipped
    coarse mesh, 3 substeps) and the true E reproduce truth/forces.csv: both files mean the same thing."""
    import dataclasses

    from stages.sim.scene import frame_inputs, internal_forces, make_scene
    from stages.sim.static import simulate_from_start
    from stages.sim.stress import set_forces

    cap = load_capture(p2_capture)
    truth = read_truth(cap)
    T = truth.young.shape[0]
    v, t = box_tets((6, 2, 2), (0.2, 0.05, 0.05))
    v = v - 0.5 * (v.min(0) + v.max(0))
    ctl = cap.controls()
    scene = make_scene(mesh_artefact(v, t, cap.density, order=2), ctl, cap.material.model, cap.dt, cap.gravity)
    states: list = []
    X = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), truth.young, truth.poisson, T, cap.start,
                            substeps=3, states=states)
    fine = dataclasses.replace(scene, dt=scene.dt / 3)
    rows = read_forces_csv(cap.truth_dir / "forces.csv")
    for f in range(T):
        inp = frame_inputs(fine, ctl, f)
        (sf,) = set_forces(fine, inp, X[f], states[f][0], internal_forces(X[f], fine, truth.young[f],
                                                                          truth.poisson[f]), x_prev2=states[f][1])
        r = rows[f]
        scale = np.linalg.norm(sf.applied)
        np.testing.assert_allclose([r["applied_fx_N"], r["applied_fy_N"], r["applied_fz_N"]], sf.applied,
                                   atol=1e-6 * scale)
        np.testing.assert_allclose([r["fx_N"], r["fy_N"], r["fz_N"]], sf.internal, atol=1e-6 * scale)
        assert r["magnitude_sum_N"] == pytest.approx(sf.magnitude_sum, rel=1e-6)


@pytest.mark.parametrize("args,msg", [(["--truth-order", "3"], "--truth-order should be 1 or 2"),
                                      (["--substeps", "0"], "--substeps should be at least 1"),
                                      (["--truth-refine", "5"], "--truth-refine should lie in 0..3")])
def test_bad_truth_options_fail_with_one_clear_sentence(box_mesh, tmp_path, args, msg):
    proc = run_rsl("synth", box_mesh, tmp_path / "x", "--frames", "2", "--cameras", "1", "--resolution", "32",
                   "--calib-views", "0", *args)
    assert proc.returncode != 0
    assert msg in " ".join(proc.stderr.split()) and "Traceback" not in proc.stderr
    assert not (tmp_path / "x").exists()
