"""Hard (Dirichlet) handles in the reduced space: generate-data keeps them hard, so a subspace trained on its
snapshots has (numerically) zero rows at a still hard handle's vertices and the reduced model holds them at
their targets — the clamp is as rigid as the full space's, not a spring (docs/results/reduced_accuracy.md)."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from stages.domain.controls import Controls, Handle, Selection, Track
from stages.sim.scene import FrameInputs, simulate
from stages.steps.generate_data import random_controls
from stages.sim import potential as P
from stages.subspace import ReducedModel
from stages.subspace.cubature import ReducedForceSampler, fit_cubature
from stages.subspace.train import fit_subspace
from test_subspace_reduced import POISSON, YOUNG, bar_scene

FRAMES = 14


def _tip_load_inputs(scene, seed: int) -> list[FrameInputs]:
    """The clamp holds still at rest; a random force on the free end (x = 0.2 m) rises over the sequence."""
    rng = np.random.default_rng(seed)
    tip = np.nonzero(scene.rest[:, 0] > 0.2 - 1e-9)[0]
    f_total = rng.uniform(-1, 1, 3) * np.array([0.1, 0.2, 0.4])  # N
    hid = scene.handles[0].ids
    out = []
    for t in range(FRAMES):
        f = np.zeros_like(scene.rest)
        f[tip] = f_total * min(t / 8, 1.0) / len(tip)
        out.append(FrameInputs((scene.rest[hid].copy(),), f, np.zeros((0, 7))))
    return out


@pytest.fixture(scope="module")
def hard():
    """A hard clamp on the first cell layer (x ≤ 25 mm); 5 tip-load sequences simulated in full space; PCA
    r = 6 on the first 4."""
    scene = bar_scene()
    clamp = np.nonzero(scene.rest[:, 0] < 0.025 + 1e-9)[0]
    scene = dataclasses.replace(scene, handles=(dataclasses.replace(scene.handles[0], ids=clamp, hard=True),))
    seqs = [(inp, simulate(scene, inp, YOUNG, POISSON)) for inp in (_tip_load_inputs(scene, s) for s in range(5))]
    train = np.concatenate([x for _, x in seqs[:4]])
    sub, _ = fit_subspace("pca", scene.rest, scene.masses, train, 6)
    return scene, seqs, train, sub


def test_reduced_model_holds_a_still_hard_handle_at_its_targets(hard):
    """Snapshots from hard-handle simulations → PCA r = 6 → reduced trajectory on a held-out load: every held
    vertex within 1e-9 m of its target (the full space holds it exactly; the motion is centimetres)."""
    scene, seqs, _, sub = hard
    model = ReducedModel(sub, scene)
    inp, x_full = seqs[4]
    X = model.decode(model.simulate(inp, YOUNG, POISSON))
    hid = scene.handles[0].ids
    dev = max(float(np.linalg.norm(X[t][hid] - inp[t].handle_targets[0], axis=1).max()) for t in range(FRAMES))
    motion = float(np.linalg.norm(x_full - scene.rest, axis=-1).max())
    assert motion > 1e-3, motion
    assert dev < 1e-9, dev
    # and the trajectory follows the full space's
    assert float(np.linalg.norm(X - x_full, axis=-1).max()) < 0.1 * motion


def test_cubature_skips_points_the_subspace_holds_still(hard):
    """Points whose nodes all lie on the still hard clamp have a round-off reduced-force column (U is ~0
    there): the greedy cubature never picks them, and its weights stay of the order of the point count."""
    scene, _, train, sub = hard
    mu, lam = P.tet_lame(scene, YOUNG, POISSON)
    sampler = ReducedForceSampler(sub, np.asarray(sub.encode(jnp.asarray(train[::3]))), scene.tets, scene.dm_inv,
                                  scene.volumes, np.asarray(mu), np.asarray(lam), scene.material)
    held = np.zeros(len(scene.rest), bool)
    held[scene.handles[0].ids] = True
    still = np.nonzero(held[scene.tets].all(axis=1))[0]
    assert len(still) > 0
    for max_points in (12, len(scene.tets)):  # the greedy path and the all-points NNLS path
        ids, w, info = fit_cubature(sampler, scene.tet_region, 2, max_points=max_points, tol=1e-3, seed=0)
        assert not np.isin(ids, still).any(), (max_points, ids)
        assert np.max(w) < 10 * len(scene.tets), (max_points, np.max(w))
        assert info["error_rel"] < 0.2, info


def test_random_controls_keep_hard_handles_hard():
    """generate-data's random sequences keep each handle's hard flag (and its stiffness)."""
    track = Track(np.array([0]), np.array([[0, 0, 0, 1.0, 0, 0, 0]]), True)
    ctl = Controls(friction=0.0)
    ctl.handles.append(Handle("clamp", Selection("box", np.array([[0, 0, 0], [1, 1, 1.0]])), 500.0, track, hard=True))
    ctl.handles.append(Handle("grip", Selection("box", np.array([[0, 0, 0], [1, 1, 1.0]])), 700.0, track))
    new = random_controls(ctl, 10, 3, 0.1, np.random.default_rng(0))
    assert [h.hard for h in new.handles] == [True, False]
    assert [h.stiffness for h in new.handles] == [500.0, 700.0]
