"""Markers first seen after frame 0 (hidden by a gripper or a clamp when the capture starts): accepted by the capture
reader, left out until a window sees them, then bound to their tracks (MarkerObservation.bind_late) and held."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from stages.capture import load_capture, read_markers, write_markers
from test_adapt_e2e import E_TRUE, _make_capture

LATE = [0, 3, 7, 11, 19]  # markers hidden over frames 0..HIDDEN-1
HIDDEN = 3


@pytest.fixture(scope="module")
def beam16(tmp_path_factory) -> tuple[Path, Path]:
    """The cable-pulled beam of test_adapt_e2e (16 frames, the truth's own P1 mesh)."""
    return _make_capture(tmp_path_factory.mktemp("late"), frames=16)


def _late_capture(cap: Path, root: Path) -> Path:
    """A copy of the capture whose markers LATE are not seen in frames 0..HIDDEN−1."""
    cap2 = root / "cap_late"
    shutil.copytree(cap, cap2)
    P = read_markers(cap / "markers.csv")
    P[:HIDDEN, LATE] = np.nan
    write_markers(cap2 / "markers.csv", P)
    return cap2


def _observation(cap: Path, ws: Path):
    from stages.artefacts import MeshArtefact
    from stages.observations import MarkerObservation

    mesh = MeshArtefact.load(ws / "mesh.h5")
    return MarkerObservation(load_capture(cap), mesh.vertices, mesh.surface_faces, mesh.n_vertices), mesh


def _true_positions(cap: Path, mesh) -> np.ndarray:
    """(T, n, 3): the truth's surface tracks on the workspace's mesh (it is the truth's own), interior at rest."""
    surface = np.load(cap / "truth" / "surface.npz")["vertices"]
    X = np.repeat(mesh.vertices[None], len(surface), axis=0)
    X[:, np.unique(mesh.surface_faces)] = surface
    return X


def test_a_late_marker_counts_only_once_bound_to_its_track(beam16, tmp_path):
    """Before bind_late a hidden marker adds no residual (also where it is seen); the markers seen at frame 0 are
    bound exactly as without the hidden ones.  bind_late on the true tracks places it at its material point (the
    synthetic markers are points of the surface: positions within 1e-9 m on every frame); later re-bindings of
    the frame-0 markers leave it where it is, and its rows of the binding's Jacobian are zero."""
    cap, ws = beam16
    cap2 = _late_capture(cap, tmp_path)
    obs, mesh = _observation(cap2, ws)
    full, _ = _observation(cap, ws)
    M = obs.P.shape[1]
    assert np.array_equal(np.flatnonzero(obs.late), LATE) and obs.anchored.sum() == M - len(LATE)
    assert np.isnan(obs.P[:, LATE]).all()  # a gap wherever it is seen, until bound
    keep = np.setdiff1d(np.arange(M), LATE)
    np.testing.assert_array_equal(obs.binding.faces[keep], full.binding.faces[keep])
    np.testing.assert_allclose(obs.binding.bary[keep], full.binding.bary[keep], rtol=0, atol=1e-12)
    X = _true_positions(cap, mesh)
    assert len(obs.residuals([HIDDEN], X[[HIDDEN]])[0]) == 3 * (M - len(LATE))

    frames = [HIDDEN - 1, HIDDEN, HIDDEN + 1]  # the hidden markers seen in 2 of them
    assert obs.bind_late(frames, X[frames], need=3) == 0 and obs.late.sum() == len(LATE)
    assert obs.bind_late(frames, X[frames], need=2) == len(LATE)
    assert not obs.late.any() and obs.bind_late(frames, X[frames]) == 0
    P = read_markers(cap / "markers.csv")
    np.testing.assert_allclose(obs.binding.positions(X)[:, LATE], P[:, LATE], rtol=0, atol=1e-9)
    assert len(obs.residuals([HIDDEN], X[[HIDDEN]])[0]) == 3 * M
    assert np.isnan(obs.P[:HIDDEN, LATE]).all() and np.isfinite(obs.P[HIDDEN:, LATE]).all()

    before = (obs.binding.faces[LATE].copy(), obs.binding.bary[LATE].copy())
    x0 = X[0] + 1e-3 * np.random.default_rng(0).normal(size=X[0].shape)
    obs.rebind(x0)  # the frame-0 state moved (θ changed): only the frame-0 markers follow it
    np.testing.assert_array_equal(obs.binding.faces[LATE], before[0])
    np.testing.assert_array_equal(obs.binding.bary[LATE], before[1])
    assert not np.allclose(obs.binding.bary[keep], full.binding.bary[keep], rtol=0, atol=1e-9)
    dx0 = np.random.default_rng(1).normal(size=(2,) + X[0].shape)
    J = obs.binding_jacobian([HIDDEN], X[[HIDDEN]], x0, dx0)[0].reshape(M, 3, 2)
    assert np.all(J[LATE] == 0.0) and np.abs(J[keep]).max() > 0


def test_fitting_the_bound_markers_to_their_tracks_leaves_late_markers_to_bind_late(beam16, tmp_path):
    """A moving start's re-fits (MarkerObservation.fit_to_tracks over a window that holds frame 0) refit only the
    markers already bound: a late marker seen once in that window stays out until bind_late's rule binds it."""
    cap, ws = beam16
    cap2 = _late_capture(cap, tmp_path)
    obs, mesh = _observation(cap2, ws)
    X = _true_positions(cap, mesh)
    frames = [0, HIDDEN]  # the late markers seen once here
    obs.fit_to_tracks(frames, X[frames])
    assert np.array_equal(np.flatnonzero(obs.late), LATE) and np.isnan(obs.P[:, LATE]).all()
    keep = np.setdiff1d(np.arange(obs.P.shape[1]), LATE)
    P = read_markers(cap / "markers.csv")
    np.testing.assert_allclose(obs.binding.positions(X)[:, keep], P[:, keep], rtol=0, atol=1e-9)


def test_online_adapt_binds_late_markers_and_recovers_young(beam16, tmp_path):
    """gn, full space, from 0.5 E_true, 5 of 30 markers hidden over the first 3 frames: each is bound by the
    first window whose 3 frames see it (frames 3–5: at frame 5, recorded in adapt.h5 and said in the summary),
    and the settled E is within 3 % of the truth, as with every marker seen (1.000 E_true when written)."""
    from stages.artefacts import AdaptArtefact
    from stages.progress import SilentReporter
    from stages.steps import adapt

    cap, ws = beam16
    cap2 = _late_capture(cap, tmp_path)
    rep = SilentReporter()
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap2, workspace=ws, loss="markers", window=3,
                                                         estimator="gn", space="full", young_init=0.5 * E_TRUE,
                                                         substeps=1), rep))
    bound_at = HIDDEN + adapt.LATE_MARKER_FRAMES - 1
    assert art.extra["late_markers_bound"] == [[bound_at, len(LATE)]] and art.extra["late_markers_unbound"] == 0
    assert any(f"5 marker(s) first seen after frame 0 bound to their tracks at frame(s) {bound_at}" in m
               for m in rep.messages)
    settled = art.young[6:, 0] / E_TRUE
    assert np.all(np.abs(settled - 1.0) <= 0.03), settled


def test_offline_adapt_says_it_leaves_late_markers_out(beam16, tmp_path):
    from stages.artefacts import AdaptArtefact
    from stages.progress import SilentReporter
    from stages.steps import adapt

    cap, ws = beam16
    cap2 = _late_capture(cap, tmp_path)
    rep = SilentReporter()
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap2, workspace=ws, loss="markers", mode="offline",
                                                         estimator="gn", space="full", young_init=0.5 * E_TRUE,
                                                         frames="0:6", offline_iters=3, substeps=1), rep))
    assert any("5 marker(s) are first seen after frame 0; --mode offline binds markers at frame 0 only" in m
               for m in rep.messages)
    assert art.extra["late_markers_unbound"] == len(LATE)


def test_online_adam_binds_late_markers_too(beam16, tmp_path):
    """The Adam estimator's online loop binds them as gn's does: by the first window whose 3 frames see them."""
    from stages.artefacts import AdaptArtefact
    from stages.steps import adapt

    cap, ws = beam16
    cap2 = _late_capture(cap, tmp_path)
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap2, workspace=ws, loss="markers", window=3,
                                                         estimator="adam", space="full", young_init=0.5 * E_TRUE,
                                                         substeps=1, frames="0:8")))
    assert art.extra["late_markers_bound"] == [[HIDDEN + adapt.LATE_MARKER_FRAMES - 1, len(LATE)]]
    assert art.extra["late_markers_unbound"] == 0
