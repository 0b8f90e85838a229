"""`rsl train-subspace`: the stage end to end (artefact contents) and its error messages via the real CLI."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.artefacts import Provenance, SnapshotsArtefact, SubspaceArtefact
from stages.progress import SilentReporter
from stages.artefacts import mesh_artefact
from stages.sim.meshgen import box_tets
from stages.sim.scene import FrameInputs, HandleSpec, Scene
from stages.subspace import ReducedModel
from stages.steps.train_subspace import TrainSubspaceConfig, run
from test_subspace_networks import bend_twist, half_ref, random_net


def _workspace(tmp_path, n_seq=4, per_seq=12, cells=(8, 2, 2)):
    v, t = box_tets(cells, (0.2, 0.05, 0.05))
    mesh = mesh_artefact(v, t, 1000.0)
    ws = tmp_path / "ws"
    mesh.save(ws / "mesh.h5")
    rng = np.random.default_rng(0)
    X, seq, fr = [], [], []
    for s in range(n_seq):
        k, tau = rng.uniform(1, 6), rng.uniform(-6, 6)
        for f in range(per_seq):
            a = (f + 1) / per_seq
            X.append(bend_twist(v, k * a, tau * a, 0.02 * a))
            seq.append(s)
            fr.append(f)
    S = len(X)
    SnapshotsArtefact(np.stack(X), np.full((S, 1), 1e5), np.full((S, 1), 0.45), np.array(seq), np.array(fr),
                      ["body"]).save(ws / "snapshots.h5", Provenance.make({"capture": None}))
    return ws, mesh


def _scene(mesh) -> Scene:
    return Scene(rest=mesh.vertices, tets=mesh.tets, dm_inv=mesh.dm_inv, volumes=mesh.rest_volumes,
                 masses=mesh.vertex_masses, tet_region=mesh.tet_region, n_regions=1, region_names=("body",),
                 material="stable_neohookean", dt=1 / 30, gravity=np.array([0, 0, -9.81]),
                 handles=(HandleSpec("clamp", np.nonzero(mesh.vertices[:, 0] < 1e-9)[0], 1e3),), loads=(),
                 obstacles=(), friction=0.0, contact_stiffness=1e3)


def test_stage_writes_a_usable_subspace(tmp_path):
    ws, mesh = _workspace(tmp_path)
    rep = SilentReporter()
    out = run(TrainSubspaceConfig(workspace=ws, dim=3, epochs=20, cubature_tets=40, cubature_poses=10), rep)
    art = SubspaceArtefact.load(out)
    assert art.subspace_kind == "autoencoder" and art.dim == 3
    assert 0 < art.val_error_m < 0.05 and art.extra["n_val"] == 12  # one held-out sequence of 12 frames
    assert 0 < len(art.extra["cubature_points"]) <= 40 and art.extra["cubature_order"] == 1
    assert np.all(np.array(art.extra["cubature_weights"]) > 0)
    assert art.extra["cubature_error_rel"] < 0.2
    assert "validation error" in rep.messages[-1] and "bbox diagonal" in rep.messages[-1]
    scene = _scene(mesh)
    model = ReducedModel.from_artefacts(art, scene)
    assert len(model.cubature_points) == len(art.extra["cubature_points"])
    hid = scene.handles[0].ids
    inp = FrameInputs((scene.rest[hid],), np.zeros_like(scene.rest), np.zeros((0, 7)))
    Z = model.simulate([inp] * 3, np.array([1e5]), np.array([0.45]))
    assert Z.shape == (3, 3) and np.all(np.isfinite(Z))


def test_few_training_sequences_are_warned_about(tmp_path):
    """Fewer than FEW_SEQUENCES sequences in snapshots.h5: one warning naming the file and the remedy; as many:
    none (the E identified in a reduced space trained on 4 sequences moved with the draw,
    docs/results/training_data.md)."""
    from stages.steps.train_subspace import FEW_SEQUENCES

    for n_seq, warned in ((4, True), (FEW_SEQUENCES, False)):
        ws, _ = _workspace(tmp_path / str(n_seq), n_seq=n_seq, per_seq=4)
        rep = SilentReporter()
        run(TrainSubspaceConfig(workspace=ws, dim=3, epochs=2, cubature_tets=0), rep)
        warnings = [m for m in rep.messages if m.startswith("warning: ")]
        assert len(warnings) == int(warned), warnings
        if warned:
            assert "snapshots.h5: only 4 sequences" in warnings[0] and "--sequences" in warnings[0]


def test_cli_pca(tmp_path, rsl):
    ws, _ = _workspace(tmp_path)
    proc = rsl("train-subspace", "-w", ws, "--dim", "4", "--kind", "pca", "--cubature-tets", "0")
    assert proc.returncode == 0, proc.stderr
    art = SubspaceArtefact.load(ws / "subspace.h5")
    assert art.subspace_kind == "pca" and art.dim == 4 and "cubature_points" not in art.extra
    assert "pca subspace r=4" in proc.stdout + proc.stderr


def test_cli_lbs(tmp_path, rsl):
    """--kind lbs: data-free LBS basis (ceil(dim/12) handles), its snapshot errors reported; ReducedModel loads it."""
    ws, mesh = _workspace(tmp_path)
    proc = rsl("train-subspace", "-w", ws, "--dim", "12", "--kind", "lbs", "--cubature-tets", "0")
    assert proc.returncode == 0, proc.stderr
    art = SubspaceArtefact.load(ws / "subspace.h5")
    assert art.subspace_kind == "lbs" and art.dim == 12 and art.extra["lbs_handles"] == 1
    assert 0 < art.val_error_m < 0.05 and np.isfinite(art.extra["val_error_rel"])
    out = " ".join((proc.stdout + proc.stderr).split())
    assert "lbs subspace r=12" in out and "LBS handles" in out and "bbox diagonal" in out
    model = ReducedModel.from_artefacts(art, _scene(mesh))
    assert model.dim == 12 and np.array_equal(model.decode(np.zeros(12)), mesh.vertices)


def test_cli_unknown_kind(tmp_path, rsl):
    ws, _ = _workspace(tmp_path, n_seq=2, per_seq=4)
    proc = rsl("train-subspace", "-w", ws, "--kind", "linear")
    assert proc.returncode != 0 and "'linear' is not one of 'autoencoder', 'pca', 'lbs'" in " ".join(
        (proc.stdout + proc.stderr).split())  # a usage error now: --kind is a Literal choice
    assert not (ws / "subspace.h5").exists()


@pytest.mark.parametrize("case", ["missing", "mismatch", "too_big"])
def test_cli_bad_input(tmp_path, rsl, case):
    ws, _ = _workspace(tmp_path, n_seq=2, per_seq=4)
    args = ["train-subspace", "-w", ws, "--dim", "3", "--epochs", "2"]
    if case == "missing":
        (ws / "snapshots.h5").unlink()
        want = "snapshots.h5: file not found"
    elif case == "mismatch":
        v, t = box_tets((4, 2, 2), (0.2, 0.05, 0.05))
        mesh_artefact(v, t, 1000.0).save(ws / "mesh.h5")
        want = "rerun generate-data on this mesh"
    else:
        args[4] = "50"
        want = "cannot span a 50-dimensional subspace"
    proc = rsl(*args)
    assert proc.returncode != 0
    assert want in " ".join((proc.stdout + proc.stderr).split())
    assert not (ws / "subspace.h5").exists()


def test_named_array_subspace_file_loads_into_the_equinox_network(tmp_path):
    """A subspace.h5 in the stored layout (named arrays, W (in, out)), written without stages.subspace,
    loads and maps exactly as the plain-jnp twin of the network says."""
    v, t = box_tets((4, 2, 2), (0.2, 0.05, 0.05))
    mesh = mesh_artefact(v, t, 1000.0)
    r, p, n = 3, 7, len(v)
    rng = np.random.default_rng(7)
    weights = dict(random_net(8, r, p, amp=0.2), rest=mesh.vertices, basis=0.05 * rng.normal(size=(n, 3, p)),
                   masses=mesh.vertex_masses, q_scale=rng.uniform(0.5, 2.0, p))
    SubspaceArtefact("autoencoder", r, weights, 0.0, 0.0).save(tmp_path / "subspace.h5")
    model = ReducedModel.from_artefacts(SubspaceArtefact.load(tmp_path / "subspace.h5"), _scene(mesh))
    net = {k: jnp.asarray(a) for k, a in weights.items() if k.startswith(("enc_", "dec_"))}
    U, s, x0 = weights["basis"], weights["q_scale"], weights["rest"]

    def phi_ref(z):
        return x0 + jnp.einsum("nip,p->ni", U, s * half_ref(net, "dec", z))

    z = rng.normal(size=r)
    x = np.asarray(phi_ref(jnp.asarray(z)))
    assert np.abs(model.decode(z) - x).max() <= 1e-13 * np.abs(x).max()
    z_ref = np.asarray(half_ref(net, "enc", jnp.einsum("ni,nip->p", (x - x0) * weights["masses"][:, None], U) / s))
    assert np.abs(model.encode(x) - z_ref).max() <= 1e-13 * np.abs(z_ref).max()
    J_ref = np.asarray(jax.jacfwd(phi_ref)(jnp.asarray(z)))
    assert np.abs(model.jacobian(z) - J_ref).max() <= 1e-13 * np.abs(J_ref).max()
    assert np.array_equal(model.decode(np.zeros(r)), mesh.vertices)  # φ(0) = x̄


@pytest.mark.parametrize("choice", ["median", "range"])
def test_cubature_poisson_choice_is_recorded(tmp_path, choice):
    """--cubature-poisson median fits the cubature at the snapshots' median ν alone, range at both ends of their ν
    (snapshots without a capture: no poisson_range to take); extra cubature_poisson_fitted records which."""
    ws, _ = _workspace(tmp_path)
    snap = SnapshotsArtefact.load(ws / "snapshots.h5")
    nu = np.linspace(0.32, 0.48, len(snap.positions))[:, None]
    SnapshotsArtefact(snap.positions, snap.young, nu, snap.sequence, snap.frame, ["body"]).save(
        ws / "snapshots.h5", Provenance.make({"capture": None}))
    art = SubspaceArtefact.load(run(TrainSubspaceConfig(workspace=ws, dim=3, kind="pca", cubature_tets=40,
                                                        cubature_poses=10, cubature_poisson=choice)))
    got = art.extra["cubature_poisson_fitted"]
    if choice == "median":
        np.testing.assert_allclose(got, [[np.median(nu)]])
    else:
        np.testing.assert_allclose(got, [[0.32], [0.48]])
