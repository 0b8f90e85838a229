"""Handle and contact forces from a simulated trajectory (`rsl export --forces`)."""
from __future__ import annotations

import numpy as np
import pytest

from stages.artefacts import AdaptArtefact, Provenance
from stages.capture import load_capture
from stages.steps.export import ExportConfig, run
from stages.sim.scene import frame_inputs, make_scene, simulate
from test_export import read_csv, write_capture
from test_stress_meshes import block_artefact

G = 9.81


def _adapt_from_simulation(ws, cap, mesh, young, poisson, frames):
    """Simulate the capture's controls with stages.sim and store the result as a full-space adapt.h5."""
    capture = load_capture(cap)
    controls = capture.controls()
    scene = make_scene(mesh, controls, capture.material.model, capture.dt, capture.gravity)
    inputs = [frame_inputs(scene, controls, t) for t in range(frames)]
    X = simulate(scene, inputs, young, poisson)
    T, R = frames, len(mesh.region_names)
    AdaptArtefact(
        frames=np.arange(T), young=np.full((T, R), young), poisson=np.full((T, R), poisson), z=np.zeros((T, 0)),
        positions=X, loss=np.zeros(T), time_forward_s=np.zeros(T), time_backward_s=np.zeros(T),
        time_render_s=np.zeros(T), time_total_s=np.zeros(T), region_names=list(mesh.region_names),
        mode="offline", space="full", loss_kind="markers", window=T,  # one simulation: forces from its positions
    ).save(ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}))
    return scene, X


def test_hanging_body_handle_force_equals_weight(tmp_path):
    """A column hanging from its top face reaches static equilibrium (large implicit-Euler steps damp
    the motion): the handle holds the whole weight m·g, and the internal forces at the handle
    vertices sum to the weight of everything below them."""
    size = (0.02, 0.02, 0.1)
    mesh = block_artefact(size, (2, 2, 10), density=1000.0)
    eps = 1e-6
    controls = {"handles": [{"name": "top", "select": {"box": [[-1, -1, size[2] - eps], [1, 1, size[2] + eps]]},
                             "stiffness": 1e4, "poses": [[0, 0, 0, 1, 0, 0, 0]]}]}
    cap = write_capture(tmp_path / "cap", mesh, controls, young=1e5, poisson=0.4, fps=10.0,
                        gravity=(0.0, 0.0, -G))
    ws = tmp_path / "ws"
    ws.mkdir()
    mesh.save(ws / "mesh.h5")
    scene, X = _adapt_from_simulation(ws, cap, mesh, 1e5, 0.4, 25)
    assert np.abs(X[-1] - X[-2]).max() < 1e-9  # at rest
    out = run(ExportConfig(workspace=ws, forces=True, vtk=True))
    rows = read_csv(out / "forces.csv")
    assert len(rows) == 25 and {r["name"] for r in rows} == {"top"}
    # the per-vertex applied force of the VTU sums to the handle's row
    import meshio

    vtu = meshio.read(out / "vtk" / "frame_000024.vtu")
    np.testing.assert_allclose(vtu.point_data["applied_force"].sum(0),
                               [float(rows[-1][k]) for k in ("applied_fx_N", "applied_fy_N", "applied_fz_N")],
                               rtol=1e-6, atol=1e-9)
    last = rows[-1]
    weight = mesh.vertex_masses.sum() * G
    handle_ids = scene.handles[0].ids
    below = weight - mesh.vertex_masses[handle_ids].sum() * G
    assert float(last["applied_fz_N"]) == pytest.approx(weight, rel=1e-2)
    assert abs(float(last["applied_fx_N"])) < 1e-6 * weight
    assert float(last["fz_N"]) == pytest.approx(-below, rel=1e-2)
    assert float(last["magnitude_sum_N"]) >= abs(float(last["fz_N"])) - 1e-12
    assert float(last["time_s"]) == pytest.approx(2.4)


def test_resting_on_floor_contact_force_equals_weight(tmp_path):
    """A block resting on a floor plane: the contact force of the floor equals the weight, and the
    contact vertices are the bottom face."""
    size = (0.04, 0.04, 0.02)
    mesh = block_artefact(size, (2, 2, 1), density=1000.0, origin=(0.0, 0.0, 0.0005))
    controls = {"obstacles": [{"name": "floor", "shape": "plane", "normal": [0, 0, 1], "offset": 0.0}]}
    cap = write_capture(tmp_path / "cap", mesh, controls, young=1e5, poisson=0.3, fps=10.0, gravity=(0, 0, -G))
    ws = tmp_path / "ws"
    ws.mkdir()
    mesh.save(ws / "mesh.h5")
    _adapt_from_simulation(ws, cap, mesh, 1e5, 0.3, 20)
    out = run(ExportConfig(workspace=ws, forces=True, vtk=True, contact_distance=1e-3))
    rows = read_csv(out / "forces.csv")
    last = rows[-1]
    import meshio

    vtu = meshio.read(out / "vtk" / "frame_000019.vtu")
    assert vtu.point_data["applied_force"].sum(0)[2] == pytest.approx(float(last["applied_fz_N"]), rel=1e-6)
    assert last["name"] == "floor" and last["kind"] == "obstacle"
    weight = mesh.vertex_masses.sum() * G
    assert float(last["applied_fz_N"]) == pytest.approx(weight, rel=1e-2)
    assert int(last["n_vertices"]) == 9  # the bottom face's 3×3 vertices


def test_applied_forces_balance_momentum_with_friction_and_moving_sphere(tmp_path):
    """Implicit Euler: Σ_i m_i (x_t − 2x_{t−1} + x_{t−2})/Δt² = Σ_i (applied_i + m_i g), because internal
    forces sum to zero; so the handle + contact (+ friction) forces export reports must balance it."""
    from stages.sim import stress as st

    size = (0.06, 0.02, 0.02)
    mesh = block_artefact(size, (3, 1, 1), density=1000.0, origin=(0.0, 0.0, 0.0005))
    eps = 1e-6
    poses = [[0.045, 0.01, 0.0205 + 0.012 - 0.0015 * t, 1, 0, 0, 0] for t in range(8)]
    controls = {"handles": [{"name": "left", "select": {"box": [[-eps, -1, -1], [eps, 1, 1]]}, "stiffness": 5e3,
                             "poses": [[0, 0, 0, 1, 0, 0, 0]]}],
                "obstacles": [{"name": "floor", "shape": "plane", "normal": [0, 0, 1], "offset": 0.0},
                              {"name": "pusher", "shape": "sphere", "radius": 0.012, "poses": poses}],
                "friction": 0.3}
    cap = write_capture(tmp_path / "cap", mesh, controls, young=5e4, poisson=0.35, fps=30.0, gravity=(0, 0, -G))
    ws = tmp_path / "ws"
    ws.mkdir()
    mesh.save(ws / "mesh.h5")
    scene, X = _adapt_from_simulation(ws, cap, mesh, 5e4, 0.35, 8)
    controls_obj = load_capture(cap).controls()
    m = mesh.vertex_masses[:, None]
    rest = mesh.vertices
    touched = 0
    for t in range(8):
        xp = X[t - 1] if t >= 1 else rest
        xpp = X[t - 2] if t >= 2 else rest
        inputs = frame_inputs(scene, controls_obj, t)
        applied = st.applied_forces(scene, inputs, X[t], xp)
        inertia = (m * (X[t] - 2 * xp + xpp) / scene.dt ** 2).sum(0)
        np.testing.assert_allclose(applied.sum(0) + (m * scene.gravity).sum(0), inertia,
                                   atol=1e-6 * np.abs(applied).sum())
        f_int = np.zeros_like(X[t])
        rows = st.set_forces(scene, inputs, X[t], xp, f_int)
        pusher = next(r for r in rows if r.name == "pusher")
        touched += pusher.n_vertices > 0
    assert touched >= 3  # the sphere reached the block
    out = run(ExportConfig(workspace=ws, forces=True))
    csv_rows = read_csv(out / "forces.csv")
    assert len(csv_rows) == 8 * 3 and {r["kind"] for r in csv_rows} == {"handle", "obstacle"}
    last = {r["name"]: r for r in csv_rows if r["frame"] == "7"}
    assert float(last["pusher"]["applied_fz_N"]) < 0 < float(last["floor"]["applied_fz_N"])
