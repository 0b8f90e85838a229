"""gn's remembered trajectories with ``--substeps S > 1`` (window_backends.Substepped._stitch, StartWindow.memo) held to
their slow twins: a window's substep trajectory stitched from the forwards that simulated its frames against a forward
of that window, the sensitivities from it against those of a backend that never saw the earlier forwards, and a window
continued from the remembered trajectory against one simulated again."""
from __future__ import annotations

import numpy as np
import pytest

from stages.window_backends import StoredStates, Substepped
from stages.windows import StartWindow
from test_adapt_substeps import POISSON, YOUNG, _full_backend, full, reduced  # noqa: F401  (module-scoped fixtures)


def _count_fine(b: Substepped) -> list:
    """Record the substeps each call of the fine backend's forward simulates."""
    calls = []
    orig = b.fine.forward

    def forward(steps, *a, **k):
        calls.append(list(steps))
        return orig(steps, *a, **k)

    b.fine.forward = forward
    return calls


def _online_like(b: Substepped, young=YOUNG):
    """What adapt's gn loop leaves in a substepped backend before the linearisation of window 2..4: windows 0..2
    and 1..3 (the last one as the LM trial that was accepted), then the change test's forward of frame 4 alone from
    the stored states 2, 3.  Returns (stored, X4)."""
    win = StartWindow(b, "rest")
    stored = StoredStates(b)
    X = win.forward([0, 1, 2], young, POISSON, None)
    for i, t in enumerate([0, 1, 2]):
        stored[t] = X[i]
    X = win.forward([1, 2, 3], young, POISSON, np.stack([stored[0], stored[0]]))
    for i, t in enumerate([1, 2, 3]):
        stored[t] = X[i]
    x4 = b.forward([4], np.tile(young, (1, 1)), np.tile(POISSON, (1, 1)), np.stack([stored[2], stored[3]]))[0]
    return stored, x4


def _window_2_to_4(stored, x4):
    """(frames, before (2, …), states (3, …), E (3, R), ν (3, R)) of window 2..4 after :func:`_online_like`."""
    return ([2, 3, 4], np.stack([stored[0], stored[1]]), np.stack([stored[2], stored[3], x4]),
            np.tile(YOUNG, (3, 1)), np.tile(POISSON, (3, 1)))


def _sub(scene, at, S: int) -> Substepped:
    """A substepped full-space backend (S = 1 too: the wrapper itself, as tests/test_adapt_substeps.py builds it)."""
    from stages.window_backends import FullSpace

    return Substepped(FullSpace(scene, at, "auto"), FullSpace(scene, at, "auto"), 1) if S == 1 else \
        _full_backend(scene, at, S)


@pytest.mark.parametrize("S", [1, 2, 3])
def test_stitched_substeps_are_the_windows_own_forward(full, S):  # noqa: F811
    """Substepped._trajectory of window 2..4 (no forward of that window recorded) takes frames 2, 3 from the forward
    of window 1..3 and frame 4 from the one-frame forward, simulating nothing — the very substeps a forward of the
    window from its two stored states takes (bit for bit in full space: each step depends on θ, its inputs and the
    two states before it alone); with another θ for one frame the records do not fit and the window is simulated."""
    scene, at = full
    b = _sub(scene, at, S)
    stored, x4 = _online_like(b)
    frames, before, states, Y, N = _window_2_to_4(stored, x4)
    calls = _count_fine(b)
    fb, Xf = b._trajectory(frames, Y, N, states, before)
    assert calls == []  # stitched, nothing simulated
    ref = b.fine.forward(b.steps(frames), b._expand(Y), b._expand(N), fb)  # the slow twin: the window simulated
    assert len(calls) == 1
    assert np.array_equal(Xf, ref)
    assert np.array_equal(Xf[S - 1::S], states)
    Y2 = Y.copy()
    Y2[1] *= 1.01  # frame 3 with another θ: no record fits
    b._trajectory(frames, Y2, N, states, before)
    assert len(calls) == 2 and calls[-1] == b.steps(frames)


def test_sensitivities_of_a_stitched_window_are_those_of_a_fresh_backend(full):  # noqa: F811
    """d states/dp of window 2..4 along θ and along the two stored states (the corrections' directions) from the
    stitched substeps against a backend that simulates the window itself (fresh records of the same states)."""
    scene, at = full
    S = 3
    b = _full_backend(scene, at, S)
    stored, x4 = _online_like(b)
    frames, before, states, Y, N = _window_2_to_4(stored, x4)
    R = len(YOUNG)
    dE = np.concatenate([np.eye(R), np.zeros((R + 1, R))])
    dN = np.concatenate([np.zeros((R, R)), np.eye(R), np.zeros((1, R))])
    db = np.zeros((2 * R + 1,) + before.shape)
    db[-1, 1] = 1e-3 * (stored[1] - stored[0])
    calls = _count_fine(b)
    Sst = b.state_sensitivity(frames, Y, N, states, before, dE, dN, db)
    assert calls == []
    b2 = _full_backend(scene, at, S)  # the slow twin: the same stored states, the window simulated for itself
    stored2, x4b = _online_like(b2)
    assert np.array_equal(x4b, x4) and all(np.array_equal(stored2[t], stored[t]) for t in range(4))
    b2._traj.clear()
    calls2 = _count_fine(b2)
    Sref = b2.state_sensitivity(frames, Y, N, states, before, dE, dN, db)
    assert calls2 == [b2.steps(frames)]
    assert np.array_equal(Sst, Sref)
    assert np.abs(Sst).max() > 0


def test_start_window_memo_with_substeps_simulates_only_the_new_frame(full):  # noqa: F811
    """StartWindow.memo over a substepped backend: window 3..5 after window 2..4 with the same θ simulates frame 5's
    substeps alone; its states and its sensitivities equal the window simulated again (memo off) bit for bit."""
    scene, at = full
    S = 3
    R = len(YOUNG)
    dE, dN = np.eye(2 * R)[:, :R], np.eye(2 * R)[:, R:]
    out = {}
    for memo in (True, False):
        b = _full_backend(scene, at, S)
        win = StartWindow(b, "rest")
        win.memo = memo
        stored = StoredStates(b)
        for frames in ([0, 1, 2], [1, 2, 3], [2, 3, 4]):
            t0 = frames[0]
            before = None if t0 == 0 else np.stack([stored[max(t0 - 2, 0)], stored[t0 - 1]])
            X = win.forward(frames, YOUNG, POISSON, before)
            for i, t in enumerate(frames):
                stored[t] = X[i]
        calls = _count_fine(b)
        before = np.stack([stored[1], stored[2]])
        X = win.forward([3, 4, 5], YOUNG, POISSON, before)
        Sx = win.sensitivity([3, 4, 5], YOUNG, POISSON, X, before, dE, dN)
        out[memo] = (X, Sx, [len(c) for c in calls])
    assert out[True][2] == [S]  # frame 5 alone, and no re-simulation for the sensitivities
    assert out[False][2] == [3 * S]
    assert np.array_equal(out[True][0], out[False][0])
    assert np.array_equal(out[True][1], out[False][1])


def test_reduced_decode_of_states_decoded_before_is_the_decoders_own(reduced):  # noqa: F811
    """ReducedSpace.decode remembers its last few (z, φ(z)): the same z again (the solve guard's decode of a forward,
    then the observation's) gives the decoder's floats, a copy (changing it does not change the next answer); other
    z, also of another shape, are decoded."""
    from stages.window_backends import ReducedSpace

    scene, at, model = reduced
    b = ReducedSpace(model, at)
    rng = np.random.default_rng(2)
    z1, z2 = 0.01 * rng.normal(size=(3, b.dim)), 0.01 * rng.normal(size=(3, b.dim))
    x1 = b.decode(z1)
    again = b.decode(z1.copy())
    assert np.array_equal(again, np.asarray(model.decode(z1))) and np.array_equal(again, x1)
    again[:] = 0.0
    assert np.array_equal(b.decode(z1), x1)
    assert np.array_equal(b.decode(z2), np.asarray(model.decode(z2))) and not np.array_equal(b.decode(z2), x1)
    assert np.array_equal(b.decode(z1[:1]), np.asarray(model.decode(z1[:1])))
    calls = []
    orig = model.decode
    model.decode = lambda z: calls.append(1) or orig(z)
    try:
        b.decode(z2)
        assert calls == []
        b.decode(z2 + 1e-12)
        assert calls == [1]
    finally:
        model.decode = orig
