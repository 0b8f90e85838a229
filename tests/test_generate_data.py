"""`rsl generate-data`: random sequences within the capture's control envelope, material sampled per
frame inside the prior range, identical snapshots from the pool and from one process."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import meshio
import numpy as np
import pytest

from stages.artefacts import MeshArtefact, Provenance, SnapshotsArtefact
from stages.capture import load_capture, parse_controls, quat_to_matrix, select_handles
from stages.steps.generate_data import (GenerateDataConfig, material_ends, plan_sequences, random_controls, run,
                                  sample_material)
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets

TOML = """[capture]
name = "tiny"
fps = 30.0
gravity = [0.0, 0.0, -9.81]
cameras = []
[object]
mesh = "object.mesh"
density = 1070.0
[material]
young = 1.0e5
poisson = 0.4
young_range = [5.0e4, 2.0e5]
poisson_range = [0.35, 0.45]
"""


def _controls() -> dict:
    c, s = np.cos(np.radians(15)), np.sin(np.radians(15))  # 30° about x
    return {
        "handles": [
            {"name": "left", "select": {"box": [[-0.01, -1, -1], [0.001, 1, 1]]}, "stiffness": 2e4,
             "poses": [[0, 0, 0, 1, 0, 0, 0]]},
            {"name": "right", "select": {"box": [[0.199, -1, -1], [0.21, 1, 1]]}, "stiffness": 2e4,
             "keyframes": {"frame": [0, 10, 20],
                           "pose": [[0, 0, 0, 1, 0, 0, 0], [0.03, 0, 0.01, c, s, 0, 0], [0, 0, 0, 1, 0, 0, 0]]}},
        ],
        "loads": [{"name": "poke", "select": {"ids": [5, 6]}, "force": [[0, 0, 0], [0, 0.2, -0.1]]}],
    }


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("gen")
    cap_dir, ws = root / "capture", root / "ws"
    cap_dir.mkdir()
    v, t = box_tets((5, 1, 1), (0.2, 0.04, 0.04))
    meshio.write(str(cap_dir / "object.mesh"), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    (cap_dir / "capture.toml").write_text(TOML)
    (cap_dir / "controls.json").write_text(json.dumps(_controls()))
    cap = load_capture(cap_dir)
    mesh = mesh_artefact(v, t, cap.density)
    mesh.handles = select_handles(cap.controls(), v)
    mesh.save(ws / "mesh.h5", Provenance.make({}, []))
    return cap_dir, ws


def test_random_controls_stay_in_the_envelope_and_start_at_frame_zero(workspace):
    cap = load_capture(workspace[0])
    ctl = cap.controls()
    ref = ctl.handles[1].poses.sample(21)
    lo, hi = ref[:, :3].min(0), ref[:, :3].max(0)
    span = hi - lo
    for seed in range(5):
        rng = np.random.default_rng(seed)
        new = random_controls(ctl, 40, 6, 0.1, rng)
        right = new.handles[1].poses
        assert np.array_equal(right.values[0], ctl.handles[1].poses.at(0))
        samples = right.sample(40)
        assert np.all(samples[:, :3] >= lo - 0.1 * span - 1e-12) and np.all(samples[:, :3] <= hi + 0.1 * span + 1e-12)
        angles = [np.degrees(np.arccos(np.clip((np.trace(quat_to_matrix(q)) - 1) / 2, -1, 1))) for q in samples[:, 3:]]
        assert max(angles) <= 30 * 1.1 + 1e-6
        # the still handle stays still, the load stays within its range (+ jitter)
        assert np.allclose(new.handles[0].poses.sample(40), ctl.handles[0].poses.at(0))
        f = new.loads[0].force.sample(40)
        assert np.all(np.abs(f) <= np.array([0, 0.2, 0.1]) * 1.1 + 1e-12)
        assert np.all(np.diff(right.frames) >= 6) and right.frames[-1] >= 39
    a = random_controls(ctl, 40, 6, 0.1, np.random.default_rng(1)).to_json()
    b = random_controls(ctl, 40, 6, 0.1, np.random.default_rng(1)).to_json()
    c = random_controls(ctl, 40, 6, 0.1, np.random.default_rng(2)).to_json()
    assert a == b and a != c


def test_material_is_sampled_per_frame_inside_the_range():
    log_e, nu = material_ends((5e4, 2e5), (0.35, 0.45), 3, 2, np.random.default_rng(0))
    assert log_e.shape == nu.shape == (3, 2, 2)
    young, poisson = sample_material(log_e[0], nu[0], (5e4, 2e5), 30, "ramp")
    assert young.shape == poisson.shape == (30, 2)
    assert young.min() >= 5e4 and young.max() <= 2e5
    assert poisson.min() >= 0.35 and poisson.max() <= 0.45
    # linear in log E over the sequence, from one end to the other
    assert np.allclose(np.diff(np.log(young), 2, axis=0), 0, atol=1e-12)
    assert np.allclose(np.log(young[[0, -1]]), log_e[0]) and np.allclose(poisson[[0, -1]], nu[0])
    assert np.ptp(young[:, 0]) > 0
    const, _ = sample_material(log_e[1], nu[1], (5e4, 2e5), 10, "constant")
    assert np.all(const == const[0])


@pytest.mark.parametrize("n_sequences", [1, 4, 9])
def test_latin_design_puts_one_end_in_each_stratum_of_both_ranges(n_sequences):
    """latin: the 2n ends of log E and of ν, per region, fall one in each 2n-th of the range (constant: n ends, one
    in each n-th, the last end equal to the first); independent draws stay in the range without that."""
    young_range, poisson_range = (2e4, 5e5), (0.30, 0.49)
    for mode, n_ends in (("ramp", 2 * n_sequences), ("constant", n_sequences)):
        log_e, nu = material_ends(young_range, poisson_range, n_sequences, 2, np.random.default_rng(3), "latin",
                                  mode)
        if mode == "constant":
            assert np.array_equal(log_e[:, 0], log_e[:, 1]) and np.array_equal(nu[:, 0], nu[:, 1])
            log_e, nu = log_e[:, :1], nu[:, :1]
        u_e = (log_e - np.log(young_range[0])) / np.log(young_range[1] / young_range[0])
        u_nu = (nu - poisson_range[0]) / (poisson_range[1] - poisson_range[0])
        for u in (u_e, u_nu):
            for region in range(2):
                strata = np.floor(u[..., region].ravel() * n_ends).astype(int)
                assert sorted(strata) == list(range(n_ends))
    log_e, nu = material_ends(young_range, poisson_range, n_sequences, 2, np.random.default_rng(3), "independent")
    assert nu.min() >= 0.30 and nu.max() <= 0.49
    assert log_e.min() >= np.log(2e4) and log_e.max() <= np.log(5e5)


def test_latin_design_spans_more_of_the_range_than_independent_draws():
    """Over 200 seeds, four sequences: the snapshots' ν span is at least 3/4 of the range with the Latin hypercube
    (one end in each eighth), which independent draws miss on a good part of the seeds."""
    spans = {}
    for design in ("latin", "independent"):
        spans[design] = np.array([np.ptp(material_ends((2e4, 5e5), (0.30, 0.49), 4, 1,
                                                       np.random.default_rng([seed, 4, 1]), design)[1])
                                  for seed in range(200)]) / 0.19
    assert spans["latin"].min() >= 0.75 - 1e-12
    assert np.mean(spans["independent"] < 0.75) > 0.2


def test_generate_data_writes_snapshots_with_requested_counts(workspace, rsl):
    cap_dir, ws = workspace
    proc = rsl("generate-data", cap_dir, "-w", ws, "--sequences", "3", "--frames", "6", "--workers", "1",
               "--seed", "4")
    assert proc.returncode == 0, proc.stderr
    assert "3 sequences × 6 frames = 18 snapshots" in proc.stderr
    snap = SnapshotsArtefact.load(ws / "snapshots.h5")
    n = meshio.read(str(cap_dir / "object.mesh")).points.shape[0]
    assert snap.positions.shape == (18, n, 3)
    assert snap.young.shape == snap.poisson.shape == (18, 1)
    assert snap.young.min() >= 5e4 and snap.young.max() <= 2e5
    assert snap.poisson.min() >= 0.35 and snap.poisson.max() <= 0.45
    assert list(snap.sequence) == [0] * 6 + [1] * 6 + [2] * 6 and list(snap.frame) == list(range(6)) * 3
    assert snap.region_names == ["body"]
    # the snapshots hold motion, and differ between sequences
    rest = meshio.read(str(cap_dir / "object.mesh")).points
    assert np.abs(snap.positions - rest[None]).max() > 1e-3
    assert not np.allclose(snap.positions[5], snap.positions[11])
    # the plan is the one drawn from the seed
    config = GenerateDataConfig(cap_dir, ws, sequences=3, frames=6, seed=4)
    plans = plan_sequences(config, load_capture(cap_dir).controls(),
                           (5e4, 2e5), (0.35, 0.45), 1)
    assert np.array_equal(snap.young[6:12], plans[1].young)


def test_sequences_start_from_the_chosen_state_and_take_the_substeps(workspace):
    """simulate_sequence: start released, from the rest shape one frame before frame 0 (its twin at one step per
    frame: scene.simulate, which steps frame 0 from the rest shape); start rest, frame 0 the rest shape; start
    equilibrium, frame 0 the static equilibrium under the frame-0 controls with the sequence's own material; with S substeps the frames are every
    S-th state of steps Δt/S, the controls at the fractional frames (stepped one by one here)."""
    from stages.sim import scene as sc
    from stages.sim.static import start_state
    from stages.steps.generate_data import SequencePlan, simulate_sequence

    cap_dir, ws = workspace
    cap = load_capture(cap_dir)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    ctl = cap.controls()
    T = 4
    young = np.geomspace(8e4, 1.2e5, T)[:, None]
    plan = SequencePlan(0, ctl.to_json(), young, np.full((T, 1), 0.4))
    args = (mesh, plan, "stable_neohookean", cap.dt, cap.gravity, 100, 0.0)
    _, rest_run, err = simulate_sequence(*args, "released", 1)
    _, eq_run, err2 = simulate_sequence(*args, "equilibrium", 1)
    _, sub_run, err3 = simulate_sequence(*args, "released", 3)
    _, at_rest, err4 = simulate_sequence(*args, "rest", 1)
    assert err == err2 == err3 == err4 == ""
    assert np.allclose(at_rest[0], mesh.vertices) and not np.allclose(rest_run[0], mesh.vertices)
    scene = sc.make_scene(mesh, parse_controls(plan.controls, Path("plan")), "stable_neohookean", cap.dt, cap.gravity)
    inputs = [sc.frame_inputs(scene, ctl, t) for t in range(T)]
    assert np.allclose(rest_run, sc.simulate(scene, inputs, plan.young, plan.poisson), atol=1e-9)
    x0 = start_state(scene, inputs[0], plan.young[0], plan.poisson[0], "equilibrium")
    assert np.allclose(eq_run[0], x0, atol=1e-9)
    assert np.abs(x0 - mesh.vertices).max() > 1e-5  # (it sags under gravity)
    # the substepped frames, stepped by hand from the rest shape one frame before frame 0
    fine = dataclasses.replace(scene, dt=cap.dt / 3)
    xp = xpp = np.array(mesh.vertices, np.float64)
    for t in range(T):
        for k in range(1, 4):
            x, _ = sc.step(fine, sc.frame_inputs(scene, ctl, max(t - 1 + k / 3, 0.0)), plan.young[t],
                           plan.poisson[t], xp, xpp, None, frame=t)
            xpp, xp = xp, x
        assert np.allclose(sub_run[t], x, atol=1e-8), t
    assert not np.allclose(sub_run, rest_run, atol=1e-6)


def test_generate_data_refuses_unknown_start_and_zero_substeps(workspace, rsl):
    cap_dir, ws = workspace
    for opts, words in ((["--substeps", "0"], "--substeps"), (["--start", "sideways"], "sideways")):
        proc = rsl("generate-data", cap_dir, "-w", ws, "--sequences", "1", "--frames", "2", "--workers", "1", *opts)
        assert proc.returncode != 0 and words in proc.stderr, proc.stderr


def test_run_refuses_an_unknown_material_design_or_sampling(workspace):
    """A Python caller's unknown value is refused as the CLI's choices refuse it (not drawn some other way)."""
    from stages.errors import RslError
    from stages.steps.generate_data import GenerateDataConfig, run

    cap_dir, ws = workspace
    for kw, words in (({"material_design": "sobol"}, "--material-design 'sobol' is unknown"),
                      ({"material_sampling": "steps"}, "--material-sampling 'steps' is unknown")):
        with pytest.raises(RslError, match=words):
            run(GenerateDataConfig(capture=cap_dir, workspace=ws, sequences=1, frames=2, workers=1, **kw))


def test_pool_and_serial_runs_give_identical_snapshots(workspace, tmp_path):
    cap_dir, ws = workspace
    import shutil

    results = {}
    for workers in (1, 2):
        w = tmp_path / f"ws{workers}"
        w.mkdir()
        shutil.copy(ws / "mesh.h5", w / "mesh.h5")
        run(GenerateDataConfig(cap_dir, w, sequences=3, frames=5, workers=workers, seed=11))
        results[workers] = SnapshotsArtefact.load(w / "snapshots.h5")
    a, b = results[1], results[2]
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.young, b.young) and np.array_equal(a.poisson, b.poisson)
    assert np.array_equal(a.sequence, b.sequence) and np.array_equal(a.frame, b.frame)


def test_missing_mesh_fails_with_a_clear_message(workspace, tmp_path, rsl):
    proc = rsl("generate-data", workspace[0], "-w", tmp_path / "empty", "--sequences", "1")
    assert proc.returncode == 1
    assert "mesh.h5: file not found; run `rsl tetrahedralize" in proc.stderr


def test_ray_without_ray_installed_says_how_to_get_it(workspace, monkeypatch):
    import sys

    from stages.errors import RslError

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError, as when not installed

    with pytest.raises(RslError, match=r"pip install 'rsl\[ray\]'"):
        run(GenerateDataConfig(workspace[0], workspace[1], sequences=1, frames=2, ray="auto"))


@pytest.mark.slow
def test_ray_local_instance_matches_serial(workspace, tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'rsl[ray]')")
    import shutil

    cap_dir, ws = workspace
    out = {}
    for name, kw in (("serial", {"workers": 1}), ("ray", {"ray": "local"})):
        w = tmp_path / name
        w.mkdir()
        shutil.copy(ws / "mesh.h5", w / "mesh.h5")
        run(GenerateDataConfig(cap_dir, w, sequences=2, frames=4, seed=5, **kw))
        out[name] = SnapshotsArtefact.load(w / "snapshots.h5")
    assert np.array_equal(out["serial"].positions, out["ray"].positions)
