"""The linear-blend-skinning subspace (stages.subspace.train.lbs_basis, `rsl train-subspace --kind lbs`).

Each fast piece is held to an obvious twin: farthest-point sampling to a loop over all candidates,
the vectorised stiffness Laplacian to a per-tet loop on the 4×4 barycentric system, the sparse
harmonic solve to a dense one.  The span is checked to hold every affine map of the rest shape.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stages.artefacts import SubspaceArtefact
from stages.progress import SilentReporter
from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import box_tets
from stages.sim.scene import FrameInputs
from stages.subspace import ReducedModel
from stages.subspace.networks import KINDS, LINEAR_KINDS, SubspaceMap, required_weights
from stages.subspace.train import (farthest_point_samples, fit_subspace, harmonic_weights, lbs_basis, lbs_modes,
                                   mass_orthonormalise, pca_basis, reconstruction_error, stiffness_laplacian)
from stages.steps.train_subspace import TrainSubspaceConfig, run
from test_subspace_networks import bend_twist
from test_train_subspace_cli import _scene, _workspace


@pytest.fixture(scope="module")
def bar():
    v, t = box_tets((8, 2, 2), (0.2, 0.05, 0.05))
    _, _, m = rest_quantities(v, t, 1000.0)
    return v, t, m


def _affine_copies(v):
    """A rotated + translated, a sheared + stretched and a general affine copy of x̄ (3, n, 3)."""
    rng = np.random.default_rng(3)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    S = np.array([[1.2, 0.4, 0.0], [0.0, 0.9, -0.3], [0.1, 0.0, 1.05]])
    A = np.eye(3) + 0.5 * rng.normal(size=(3, 3))
    return np.stack([v @ R.T + [0.1, -0.2, 0.3], v @ S.T, v @ A.T + [0.0, 0.05, -0.01]])


def _m_residual(U, m, d):
    """d − U Uᵀ M d (the M-orthogonal projection's residual), d (n, 3)."""
    c = np.einsum("ni,n,nip->p", d, m, U)
    return d - np.einsum("nip,p->ni", U, c)


# ---------------------------------------------------------------------------------------- pieces vs twins
def test_farthest_point_samples_match_a_plain_loop(bar):
    v = bar[0]
    ids = farthest_point_samples(v, 6, seed=5)
    first = int(np.random.default_rng(5).integers(len(v)))
    ref = [first]
    for _ in range(5):
        d = [min(np.linalg.norm(v[i] - v[j]) for j in ref) for i in range(len(v))]
        ref.append(int(np.argmax(d)))
    assert ids.tolist() == ref and len(set(ref)) == 6
    assert np.array_equal(farthest_point_samples(v, 6, seed=5), ids)  # deterministic


def _laplacian_twin(v, t):
    """Dense K from each tet's hat functions: [x 1] c = e_a gives λ_a = c·[x; 1], ∇λ_a = c[:3]."""
    K = np.zeros((len(v), len(v)))
    for tet in t:
        A = np.hstack([v[tet], np.ones((4, 1))])  # rows [x_i 1]
        C = np.linalg.inv(A)  # column a: coefficients of λ_a
        g = C[:3].T  # (4, 3) gradients
        vol = abs(np.linalg.det(A)) / 6.0
        K[np.ix_(tet, tet)] += vol * g @ g.T
    return K


def test_stiffness_laplacian_matches_twin_and_integrates_gradients(bar):
    v, t, _ = bar
    K = stiffness_laplacian(v, t).toarray()
    K_ref = _laplacian_twin(v, t)
    assert np.abs(K - K_ref).max() <= 1e-12 * np.abs(K_ref).max()
    assert np.abs(K - K.T).max() <= 1e-12 * np.abs(K).max()
    assert np.abs(K @ np.ones(len(v))).max() <= 1e-12 * np.abs(K).max()
    a = np.array([0.3, -1.2, 2.0])
    f = v @ a + 0.7  # linear: ∫|∇f|² = |a|² · volume
    vol = np.prod(v.max(0) - v.min(0))
    assert f @ K @ f == pytest.approx(a @ a * vol, rel=1e-12)


def test_harmonic_weights_partition_of_unity_and_dense_twin(bar):
    v, t, _ = bar
    ids = farthest_point_samples(v, 4, seed=0)
    W = harmonic_weights(v, t, ids)
    assert W.shape == (len(v), 4)
    assert W.min() >= 0.0 and np.abs(W.sum(1) - 1).max() <= 1e-14
    assert np.array_equal(W[ids], np.eye(4))  # 1 at their handle, 0 at the others
    # dense twin: L_ff w_f = −L_fh w_h, clip, renormalise
    L = _laplacian_twin(v, t)
    free = np.setdiff1d(np.arange(len(v)), ids)
    raw = np.zeros((len(v), 4))
    raw[ids, np.arange(4)] = 1.0
    raw[free] = np.linalg.solve(L[np.ix_(free, free)], -L[np.ix_(free, ids)])
    ref = np.clip(raw, 0, None)
    ref /= ref.sum(1, keepdims=True)
    assert np.abs(W - ref).max() <= 1e-9
    # harmonic: where nothing was clipped, L w = 0 off the handles
    if raw.min() >= 0:
        assert np.abs((L @ W)[free]).max() <= 1e-9 * np.abs(L).max()
    # smooth, not a delta: every weight reaches well beyond its own vertex
    assert np.all((W > 0.05).sum(0) > 4)


# ---------------------------------------------------------------------------------------- the basis
def test_span_holds_every_affine_map_exactly(bar):
    v, t, m = bar
    for r in (12, 24, 30):
        U, info = lbs_basis(v, t, m, r, None, seed=1)
        span = info["span"]
        assert len(info["handle_ids"]) == -(-r // 12) and span.shape[2] == 12 * len(info["handle_ids"])
        for x in _affine_copies(v):
            d = x - v
            assert np.abs(_m_residual(span, m, d)).max() <= 1e-10 * np.abs(d).max()
            if r % 12 == 0:  # the basis is the whole span
                assert np.abs(_m_residual(U, m, d)).max() <= 1e-10 * np.abs(d).max()
    # and a bend is not affine: the span leaves a residual (the check can fail)
    U, info = lbs_basis(v, t, m, 12, None)
    d = bend_twist(v, 6.0, 0.0, 0.0) - v
    assert np.abs(_m_residual(info["span"], m, d)).max() > 1e-3 * np.abs(d).max()


@pytest.mark.parametrize("with_data", [False, True])
def test_basis_is_mass_orthonormal(bar, with_data):
    v, t, m = bar
    rng = np.random.default_rng(0)
    u = np.stack([bend_twist(v, rng.uniform(1, 6), rng.uniform(-6, 6), 0.02) for _ in range(8)]) - v
    U, info = lbs_basis(v, t, m, 30, u if with_data else None, seed=0)
    G = np.einsum("nip,n,niq->pq", U, m, U)
    assert U.shape == (len(v), 3, 30) and np.abs(G - np.eye(30)).max() <= 1e-12
    S = info["span"]
    assert np.abs(np.einsum("nip,n,niq->pq", S, m, S) - np.eye(S.shape[2])).max() <= 1e-12
    # U lies in the span
    for p in range(30):
        assert np.abs(_m_residual(S, m, U[:, :, p])).max() <= 1e-10 * np.abs(U[:, :, p]).max()
    assert ("PCA" in info["selection"]) == with_data


def test_mass_orthonormalise_drops_dependent_columns(bar):
    v, t, m = bar
    W = harmonic_weights(v, t, farthest_point_samples(v, 2))
    raw = lbs_modes(v, W, v[farthest_point_samples(v, 2)])
    dup = np.concatenate([raw, raw[:, :, :5] * 3.0, raw[:, :, 2:3] - raw[:, :, 7:8]], axis=2)
    B = mass_orthonormalise(dup, m)
    assert B.shape[2] == 24
    assert np.abs(np.einsum("nip,n,niq->pq", B, m, B) - np.eye(24)).max() <= 1e-12


def test_snapshot_selection_is_the_best_r_inside_the_span(bar):
    """The data-chosen r directions hold exactly the leading r eigenvalues of the projected data, hence
    reconstruct the snapshots at least as well as the span's first r Gram directions."""
    v, t, m = bar
    rng = np.random.default_rng(2)
    X = np.stack([bend_twist(v, rng.choice([-1, 1]) * rng.uniform(1, 8), rng.uniform(-8, 8), rng.uniform(-.05, .05))
                  for _ in range(40)])
    u = X - v
    U, info = lbs_basis(v, t, m, 20, u, seed=0)
    S = info["span"]
    c = np.einsum("sni,n,nip->sp", u, m, S)
    lam = np.sort(np.linalg.eigvalsh(c.T @ c))[::-1]
    cu = np.einsum("sni,n,nip->sp", u, m, U)
    assert np.sum(cu ** 2) == pytest.approx(lam[:20].sum(), rel=1e-10)
    U0, _ = lbs_basis(v, t, m, 20, None, seed=0)
    sub = SubspaceMap("lbs", v, U, m, np.ones(20), {})
    sub0 = SubspaceMap("lbs", v, U0, m, np.ones(20), {})
    assert reconstruction_error(sub, X) <= reconstruction_error(sub0, X)


def test_lbs_subspace_map_is_linear_and_round_trips(bar):
    v, t, m = bar
    rng = np.random.default_rng(4)
    X = np.stack([bend_twist(v, rng.uniform(1, 6), rng.uniform(-6, 6), 0.0) for _ in range(10)])
    sub, info = fit_subspace("lbs", v, m, X, 14, seed=0, tets=t)
    assert "lbs" in KINDS and "lbs" in LINEAR_KINDS and sub.kind == "lbs" and sub.dim == sub.p == 14
    z = rng.normal(size=14) * 1e-3
    assert np.allclose(np.asarray(sub.decode(jnp.asarray(z))), v + np.einsum("nip,p->ni", sub.basis, z),
                       atol=1e-15)
    assert np.allclose(np.asarray(sub.encode(sub.decode(jnp.asarray(z)))), z, atol=1e-13)
    assert np.allclose(np.asarray(jax.jacfwd(sub.decode)(jnp.zeros(14))), sub.basis)
    w = sub.to_weights()
    assert set(required_weights("lbs")) <= set(w) and w["lbs_handles"].shape == (2, 3)
    back = SubspaceMap.from_weights("lbs", w)
    assert back.kind == "lbs" and np.array_equal(back.basis, sub.basis) and not back.net
    assert np.array_equal(back.aux["lbs_skin_weights"], info["lbs"]["weights"])
    # the pca layout is unchanged: no aux arrays
    pca, _ = fit_subspace("pca", v, m, X, 4)
    assert set(pca.to_weights()) == {"rest", "basis", "masses", "q_scale"}
    with pytest.raises(ValueError, match="tets"):
        fit_subspace("lbs", v, m, X, 14)


def test_lbs_reconstruction_is_no_better_than_pca_of_the_same_data(bar):
    """PCA is the optimal r-dim linear subspace for the training data; LBS must not beat it there."""
    v, t, m = bar
    rng = np.random.default_rng(6)
    X = np.stack([bend_twist(v, rng.uniform(1, 6), rng.uniform(-6, 6), 0.02) for _ in range(30)])
    lbs, _ = fit_subspace("lbs", v, m, X, 12, tets=t)
    pca, _ = fit_subspace("pca", v, m, X, 12)
    assert reconstruction_error(pca, X) <= reconstruction_error(lbs, X) + 1e-12
    U, _ = pca_basis(X - v, m, 12)
    assert U.shape[2] == 12


# ---------------------------------------------------------------------------------------- the stage
def test_stage_lbs_writes_a_subspace_that_steps_and_sags(tmp_path):
    ws, mesh = _workspace(tmp_path)
    rep = SilentReporter()
    out = run(TrainSubspaceConfig(workspace=ws, dim=24, kind="lbs", cubature_tets=60, cubature_poses=10), rep)
    art = SubspaceArtefact.load(out)
    assert art.subspace_kind == "lbs" and art.dim == 24
    ex = art.extra
    assert ex["lbs_handles"] == 2 and ex["lbs_span_dim"] == 24 and ex["pca_dim"] == 24
    assert 0 < art.train_error_m < 0.05 and 0 < art.val_error_m < 0.05
    assert ex["val_error_rel"] == pytest.approx(art.val_error_m / ex["bbox_diag_m"])
    assert ex["lbs_span_val_error_m"] == pytest.approx(art.val_error_m)  # r = 12k: the basis is the span
    assert art.weights["lbs_handles"].shape == (2, 3)
    msg = rep.messages[-1]
    assert "lbs subspace r=24" in msg and "LBS handles" in msg and "bbox diagonal" in msg
    scene = _scene(mesh)
    model = ReducedModel.from_artefacts(art, scene)
    hid = scene.handles[0].ids
    inp = FrameInputs((scene.rest[hid],), np.zeros_like(scene.rest), np.zeros((0, 7)))
    Z = model.simulate([inp] * 6, np.array([1e5]), np.array([0.45]))
    assert Z.shape == (6, 24) and np.all(np.isfinite(Z))
    x = np.asarray(model.decode(Z[-1]))
    tip = mesh.vertices[:, 0] > mesh.vertices[:, 0].max() - 1e-9
    sag = mesh.vertices[tip, 2].mean() - x[tip, 2].mean()
    assert sag > 1e-5, sag  # the free end falls under gravity
    assert np.abs(x[hid] - mesh.vertices[hid]).max() < 0.2 * sag + 1e-6  # the clamped end stays (springs)


def test_stage_lbs_chooses_directions_from_snapshots_and_ignores_their_rank(tmp_path):
    ws, _ = _workspace(tmp_path, n_seq=2, per_seq=4)  # 4 training snapshots: too few for PCA r=10
    rep = SilentReporter()
    art = SubspaceArtefact.load(run(TrainSubspaceConfig(workspace=ws, dim=10, kind="lbs", cubature_tets=0), rep))
    assert art.dim == 10 and art.extra["lbs_span_dim"] == 12 and "PCA" in art.extra["lbs_selection"]
    assert art.extra["lbs_span_train_error_m"] <= art.train_error_m + 1e-12
    assert "leading mass-weighted PCA" in rep.messages[-1]
