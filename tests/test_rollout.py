"""`rsl rollout`: predicting new controls with the adapted material."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stages.artefacts import AdaptArtefact, Provenance
from stages.capture import load_capture
from stages.steps.export import ExportConfig
from stages.steps.export import run as export_run
from stages.steps.rollout import RolloutConfig, run
from stages.sim.scene import frame_inputs, make_scene, simulate
from test_export import read_csv, write_capture
from test_stress_meshes import block_artefact

SIZE = (0.08, 0.02, 0.02)
T1, T2 = 6, 5


def pull_controls(n_frames, start=0):
    """Left face fixed; right face pulled along x and lifted, frames start..start+n_frames−1."""
    eps = 1e-6
    poses = [[0.004 * np.sin(0.4 * t), 0.0, 0.003 * t / 10, 1, 0, 0, 0] for t in range(start, start + n_frames)]
    return {"handles": [
        {"name": "left", "select": {"box": [[-eps, -1, -1], [eps, 1, 1]]}, "stiffness": 2e3,
         "poses": [[0, 0, 0, 1, 0, 0, 0]]},
        {"name": "right", "select": {"box": [[SIZE[0] - eps, -1, -1], [SIZE[0] + eps, 1, 1]]}, "stiffness": 2e3,
         "poses": poses}]}


@pytest.fixture(scope="module")
def adapted(tmp_path_factory):
    """A full-space adapt.h5 made by simulating the capture's controls with a θ(t) that changes."""
    root = tmp_path_factory.mktemp("rollout")
    mesh = block_artefact(SIZE, (4, 1, 1), density=1100.0)
    cap = write_capture(root / "cap", mesh, pull_controls(T1 + T2), young=5e4, poisson=0.4, fps=30.0,
                        gravity=(0.0, 0.0, -9.81))
    ws = root / "ws"
    ws.mkdir()
    mesh.save(ws / "mesh.h5")
    capture = load_capture(cap)
    controls = capture.controls()
    scene = make_scene(mesh, controls, capture.material.model, capture.dt, capture.gravity)
    inputs = [frame_inputs(scene, controls, t) for t in range(T1 + T2)]
    young = np.linspace(4e4, 8e4, T1)[:, None]
    poisson = np.full((T1, 1), 0.4)
    X = simulate(scene, inputs[:T1], young, poisson)
    AdaptArtefact(
        frames=np.arange(T1), young=young, poisson=poisson, z=np.zeros((T1, 0)), positions=X, loss=np.zeros(T1),
        time_forward_s=np.zeros(T1), time_backward_s=np.zeros(T1), time_render_s=np.zeros(T1),
        time_total_s=np.zeros(T1), region_names=["body"], mode="online", space="full", loss_kind="vision",
        window=2,
    ).save(ws / "adapt.h5", Provenance.make({"capture": str(cap), "workspace": str(ws)}))
    # the same motion continued for T2 more frames with the last θ: what a rollout from the adapted state must give
    full = simulate(scene, inputs, np.concatenate([young, np.repeat(young[-1:], T2, 0)]), np.full((T1 + T2, 1), 0.4))
    tail = root / "tail_controls.json"
    tail.write_text(json.dumps(pull_controls(T2, start=T1)))
    return {"root": root, "ws": ws, "cap": cap, "X": X, "young": young, "full": full, "tail": tail, "mesh": mesh}


def test_rollout_with_original_controls_reproduces_adapted_trajectory(adapted):
    out = run(RolloutConfig(capture=adapted["cap"], workspace=adapted["ws"], controls=adapted["cap"] / "controls.json",
                            frames=T1, material="replay", from_rest=True))
    r = AdaptArtefact.load(out)
    assert r.mode == "rollout" and r.space == "full"
    np.testing.assert_allclose(r.young, adapted["young"])
    np.testing.assert_allclose(r.positions, adapted["X"], atol=1e-9)
    # with the last θ only, the early frames differ (E was lower then)
    out = run(RolloutConfig(capture=adapted["cap"], workspace=adapted["ws"], controls=adapted["cap"] / "controls.json",
                            frames=T1, material="last", from_rest=True))
    r_last = AdaptArtefact.load(out)
    assert np.abs(r_last.positions - adapted["X"]).max() > 1e-6
    np.testing.assert_allclose(r_last.young, np.repeat(adapted["young"][-1:], T1, 0))


def test_rollout_from_adapted_state_continues_the_motion(adapted):
    """From the last two adapted positions, the rest of the controls gives the continued simulation."""
    out = run(RolloutConfig(capture=adapted["cap"], workspace=adapted["ws"], controls=adapted["tail"]))
    r = AdaptArtefact.load(out)
    assert r.positions.shape[0] == T2  # the length of the new controls
    np.testing.assert_allclose(r.positions, adapted["full"][T1:], atol=1e-9)
    assert r.extra["start"] == f"adapted frame {T1 - 1}"
    # summaries a controller can read: one entry per frame
    assert len(r.extra["stress"]["max_pa"]) == T2
    assert set(r.extra["forces"]) == {"left", "right"}
    right = r.extra["forces"]["right"]
    assert len(right["internal_N"]) == T2 and len(right["applied_N"]) == T2
    assert all(m >= np.linalg.norm(v) - 1e-12 for m, v in zip(right["magnitude_sum_N"], right["internal_N"]))


def test_export_reads_rollout(adapted):
    run(RolloutConfig(capture=adapted["cap"], workspace=adapted["ws"], controls=adapted["tail"]))
    out = export_run(ExportConfig(workspace=adapted["ws"], source="rollout", forces=True, stress=True,
                                  out=adapted["root"] / "export_rollout"))
    rows = read_csv(out / "forces.csv")
    assert len(rows) == 2 * T2
    r = AdaptArtefact.load(adapted["ws"] / "rollout.h5")
    # forces.csv and the rollout's own summaries agree
    right = [row for row in rows if row["name"] == "right"]
    np.testing.assert_allclose([float(x["fz_N"]) for x in right],
                               [v[2] for v in r.extra["forces"]["right"]["internal_N"]], rtol=1e-6, atol=1e-12)
    summary = read_csv(out / "stress_summary.csv")
    np.testing.assert_allclose([float(s["max_pa"]) for s in summary], r.extra["stress"]["max_pa"], rtol=1e-6)


def test_material_schedule_replay_holds_the_last_value(adapted):
    from stages.steps.rollout import material_schedule

    a = AdaptArtefact.load(adapted["ws"] / "adapt.h5")
    E, nu = material_schedule(a, "replay", T1 + 3)
    np.testing.assert_allclose(E[:T1], a.young)
    np.testing.assert_allclose(E[T1:], np.repeat(a.young[-1:], 3, 0))
    assert nu.shape == (T1 + 3, 1)


def test_cli_rollout_bad_controls(rsl, adapted, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    p = rsl("rollout", adapted["cap"], "-w", adapted["ws"], "--controls", bad)
    assert p.returncode != 0 and "bad.json: not valid JSON" in p.stderr


def test_rollout_bad_input_messages(adapted, tmp_path):
    from stages.errors import RslError

    with pytest.raises(RslError, match="--material 'best' is neither"):
        run(RolloutConfig(capture=adapted["cap"], workspace=adapted["ws"], controls=adapted["tail"], material="best"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(RslError, match="adapt.h5: file not found"):
        run(RolloutConfig(capture=adapted["cap"], workspace=tmp_path / "empty", controls=adapted["tail"]))
    handle_nowhere = tmp_path / "nowhere.json"
    handle_nowhere.write_text(json.dumps({"handles": [{"name": "h", "select": {"box": [[5, 5, 5], [6, 6, 6]]},
                                                       "stiffness": 1e3, "poses": [[0, 0, 0, 1, 0, 0, 0]]}]}))
    with pytest.raises(RslError, match="nowhere.json: handle 'h' selects no vertex"):
        run(RolloutConfig(capture=adapted["cap"], workspace=adapted["ws"], controls=handle_nowhere))


def test_cli_rollout_runs(rsl, adapted):
    p = rsl("rollout", adapted["cap"], "-w", adapted["ws"], "--controls", adapted["tail"], "--frames", "3")
    assert p.returncode == 0, p.stderr
    assert "rollout: 3 frames" in p.stderr
    assert AdaptArtefact.load(adapted["ws"] / "rollout.h5").positions.shape[0] == 3


def test_reduced_rollout_with_a_complete_basis_equals_full(adapted, tmp_path):
    """With U = M^(-1/2) (every vertex coordinate a mode, Uᵀ M U = I) the reduced dynamics is the full
    dynamics: the reduced rollout must give the full rollout's positions, from the adapted state too."""
    import shutil

    from stages.artefacts import SubspaceArtefact
    from stages.subspace.networks import SubspaceMap

    ws = tmp_path / "ws"
    shutil.copytree(adapted["ws"], ws)
    mesh = adapted["mesh"]
    n = mesh.n_vertices
    basis = np.zeros((n, 3, 3 * n))
    for i in range(n):
        for d in range(3):
            basis[i, d, 3 * i + d] = 1.0 / np.sqrt(mesh.vertex_masses[i])
    sub = SubspaceMap("pca", mesh.vertices, basis, mesh.vertex_masses, np.ones(3 * n), {})
    SubspaceArtefact("pca", 3 * n, sub.to_weights(), 0.0, 0.0).save(ws / "subspace.h5")
    run(RolloutConfig(capture=adapted["cap"], workspace=ws, controls=adapted["tail"], space="full"))
    full = AdaptArtefact.load(ws / "rollout.h5")
    run(RolloutConfig(capture=adapted["cap"], workspace=ws, controls=adapted["tail"], space="reduced"))
    red = AdaptArtefact.load(ws / "rollout.h5")
    assert red.space == "reduced" and red.z.shape == (T2, 3 * n) and full.space == "full"
    np.testing.assert_allclose(red.positions, full.positions, atol=1e-7)
    np.testing.assert_allclose(red.positions, adapted["full"][T1:], atol=1e-7)
    # auto picks full space for a full-space adapt.h5
    run(RolloutConfig(capture=adapted["cap"], workspace=ws, controls=adapted["tail"]))
    assert AdaptArtefact.load(ws / "rollout.h5").space == "full"
