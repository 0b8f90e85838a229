"""The replay rules of stages.forces: Richardson extrapolation in time (S and 2S substeps) and the smoothed θ(t).

Implicit Euler's handle reactions converge at first order in Δt / S (docs/results/forces_converged.md): the
extrapolation 2 F_2S − F_S cancels that term, so its error must fall faster than the plain replay's as S doubles."""
from __future__ import annotations

import numpy as np
import pytest

FPS, FRAMES, SOFT, NU = 30.0, 10, 5.0e4, 0.45


# ------------------------------------------------------------------------------------------- Richardson, exact
def test_richardson_is_exact_for_an_error_of_the_integrators_order():
    from stages.forces import richardson

    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(4, 3)), rng.normal(size=(4, 3))
    h = 0.37
    np.testing.assert_allclose(richardson(a + b * h, a + b * h / 2), a, rtol=0, atol=1e-14)  # first order
    np.testing.assert_allclose(richardson(a + b * h ** 2, a + b * (h / 2) ** 2, order=2), a, rtol=0, atol=1e-14)
    # a second-order error is not removed by the first-order rule, only reduced (to −h²/2 · b)
    np.testing.assert_allclose(richardson(a + b * h ** 2, a + b * (h / 2) ** 2), a - b * h ** 2 / 2, atol=1e-14)
    assert richardson(3.0, 2.0) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="one shape"):
        richardson(np.zeros(3), np.zeros(4))


def test_richardson_rows_match_frame_and_name_whatever_the_order():
    from stages.forces import richardson_rows
    from stages.sim.stress import SetForce

    def sf(name, v, n=2):
        return SetForce(name, "handle", np.full(3, v), abs(v), np.array([v, 2 * v, 3 * v]), n)

    coarse = [(0, sf("a", 1.0)), (0, sf("b", 10.0)), (1, sf("a", 2.0)), (1, sf("b", 20.0))]
    fine = [(1, sf("b", 21.0, 5)), (0, sf("a", 1.5)), (1, sf("a", 2.5)), (0, sf("b", 11.0))]
    out = {(t, f.name): f for t, f in richardson_rows(coarse, fine)}
    assert [(t, f.name) for t, f in richardson_rows(coarse, fine)] == [(t, f.name) for t, f in fine]
    for (t, name), want in {(0, "a"): 2.0, (1, "a"): 3.0, (0, "b"): 12.0, (1, "b"): 22.0}.items():
        np.testing.assert_allclose(out[(t, name)].applied, [want, 2 * want, 3 * want])
        np.testing.assert_allclose(out[(t, name)].internal, np.full(3, want))
        assert out[(t, name)].magnitude_sum == pytest.approx(want)
    assert out[(1, "b")].n_vertices == 5  # the fine replay's
    with pytest.raises(ValueError, match="same"):
        richardson_rows(coarse, fine[:3])


# --------------------------------------------------------------------------------------- Richardson, order
@pytest.fixture(scope="module")
def cable():
    """A soft P1 bar 0.2 × 0.04 × 0.04 m held hard at x = 0, pulled up and sideways at its free end (sin² over the
    frames, up to 0.8 × its weight): a dynamic handle reaction.  Returns (scene, controls, E (T, 1), ν (T, 1))."""
    from stages.artefacts import mesh_artefact
    from stages.domain.controls import Controls, Handle, Load, Selection, Track
    from stages.sim.meshgen import box_tets
    from stages.sim.scene import make_scene

    v, t = box_tets((6, 2, 2), (0.2, 0.04, 0.04))
    mesh = mesh_artefact(v, t, 1070.0)
    ident = Track(np.array([0]), np.array([[0.0, 0, 0, 1, 0, 0, 0]]), True)
    weight = float(mesh.vertex_masses.sum()) * 9.81
    s = np.sin(np.pi * np.arange(FRAMES) / (FRAMES - 1)) ** 2
    force = (0.8 * weight * s)[:, None] * np.array([0.0, 0.35, 0.9])
    ctl = Controls(handles=[Handle("base", Selection("box", box=np.array([[-1e-3, -1, -1], [1e-3, 1, 1]])), 1e4,
                                   ident, hard=True)],
                   loads=[Load("cable", Selection("box", box=np.array([[0.199, -1, -1], [0.201, 1, 1]])),
                               Track(np.arange(FRAMES), force))])
    scene = make_scene(mesh, ctl, "stable_neohookean", 1.0 / FPS, (0.0, 0.0, -9.81))
    return scene, ctl, np.full((FRAMES, 1), SOFT), np.full((FRAMES, 1), NU)


def _applied(rows):
    return np.array([f.applied for _, f in rows])


def test_richardson_replay_converges_faster_than_the_plain_one(cable):
    """Against a very fine replay (Richardson of 32 and 64 substeps), the plain replay's error falls about as S
    (first order) while the extrapolated one's falls faster (observed order > 1.25 over S = 1 → 4), and at a
    lower cost: Richardson (S, 2S) (3S steps per frame) is closer than plain 4S.  The extrapolated replay is the
    frame-by-frame combination of the two plain ones (forces, applied field, positions)."""
    from stages.forces import replay_forces, richardson, richardson_rows

    scene, ctl, young, poisson = cable
    ref = _applied(replay_forces(scene, ctl, young, poisson, "equilibrium", 32, extrapolate=True)[0])
    plain = {S: replay_forces(scene, ctl, young, poisson, "equilibrium", S) for S in (1, 2, 4, 8, 16)}

    def err(rows):
        a = _applied(rows)
        return float(np.median(np.linalg.norm(a - ref, axis=1) / np.linalg.norm(ref, axis=1)))

    e_plain = {S: err(plain[S][0]) for S in (1, 2, 4, 8, 16)}
    e_rich = {S: err(richardson_rows(plain[S][0], plain[2 * S][0])) for S in (1, 2, 4)}
    order_plain = np.log2(e_plain[1] / e_plain[4]) / 2
    order_rich = np.log2(e_rich[1] / e_rich[4]) / 2
    print(e_plain, e_rich, order_plain, order_rich)
    assert 0.5 < order_plain < 1.1, e_plain
    assert order_rich > 1.25 and order_rich > order_plain + 0.4, (e_plain, e_rich)
    assert all(e_rich[S] < e_plain[4 * S] for S in (1, 2, 4)), (e_plain, e_rich)
    rows, applied, X = replay_forces(scene, ctl, young, poisson, "equilibrium", 2, extrapolate=True)
    np.testing.assert_allclose(_applied(rows), _applied(richardson_rows(plain[2][0], plain[4][0])), rtol=1e-12,
                               atol=1e-12)
    np.testing.assert_allclose(applied, richardson(plain[2][1], plain[4][1]), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(X, richardson(plain[2][2], plain[4][2]), rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------------ smoothed θ
def test_segments_and_the_smoothed_theta():
    from stages.forces import segments, smoothed_theta

    assert segments([4, 7], 10) == [(0, 4), (4, 7), (7, 10)]
    assert segments([7, 4, 4, 0, 12], 10) == [(0, 4), (4, 7), (7, 10)]  # sorted, unique, inside (0, T)
    assert segments([], 3) == [(0, 3)]
    young = np.arange(10.0)[:, None] * [1.0, 10.0]
    poisson = 0.3 + 0.01 * np.arange(10.0)[:, None] * [1.0, 1.0]
    y, p = smoothed_theta(young, poisson, [4, 7])
    np.testing.assert_array_equal(y[:, 0], [3, 3, 3, 3, 6, 6, 6, 9, 9, 9])
    np.testing.assert_array_equal(y[:, 1], 10 * y[:, 0])
    np.testing.assert_allclose(p[:, 0], 0.3 + 0.01 * y[:, 0])
    y1, _ = smoothed_theta(young, poisson, [4, 7], lag=1)
    np.testing.assert_array_equal(y1[:, 0], [1, 2, 3, 3, 5, 6, 6, 8, 9, 9])
    y0, _ = smoothed_theta(young, poisson, [4, 7], lag=0)
    np.testing.assert_array_equal(y0, young)


def test_replay_theta_rules():
    from stages.forces import replay_theta

    young = np.array([[1.0], [2.0], [3.0], [4.0]])
    poisson = np.full((4, 1), 0.4)
    y, _, how = replay_theta(young, poisson, {"estimator": "gn", "material_changes_detected": [2]}, "online")
    np.testing.assert_array_equal(y, young)
    y, _, how = replay_theta(young, poisson, {"estimator": "gn", "material_changes_detected": [2]}, "segment")
    np.testing.assert_array_equal(y[:, 0], [2, 2, 4, 4])
    assert "2 segment(s) between detected changes" in how
    y, _, how = replay_theta(young, poisson, {"estimator": "gn", "material_changes_detected": []}, "segment")
    np.testing.assert_array_equal(y[:, 0], [4, 4, 4, 4])  # no change detected: one segment
    y, _, how = replay_theta(young, poisson, {"estimator": "adam", "material_changes_detected": []}, "segment")
    np.testing.assert_array_equal(y, young)  # no change detector: kept as recorded
    assert "not smoothed" in how
    with pytest.raises(ValueError, match="one of"):
        replay_theta(young, poisson, {}, "median")


def test_adapted_forces_follows_the_rules(cable):
    """adapted_forces (export, evaluate, report) = replay_forces with the rule's θ(t) and time extrapolation."""
    from types import SimpleNamespace

    from stages.forces import adapted_forces, replay_forces, smoothed_theta

    scene, ctl, _, poisson = cable
    young = SOFT * np.linspace(0.5, 1.2, FRAMES)[:, None]
    ad = SimpleNamespace(mode="online", frames=np.arange(FRAMES), young=young, poisson=poisson,
                         extra={"estimator": "gn", "material_changes_detected": [5]})
    rows, applied, how = adapted_forces(scene, ctl, ad, "equilibrium", 1, None, extrapolate=True, theta="segment")
    y, p = smoothed_theta(young, poisson, [5])
    want, want_applied, _ = replay_forces(scene, ctl, y, p, "equilibrium", 1, extrapolate=True)
    np.testing.assert_allclose(_applied(rows), _applied(want), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(applied, want_applied, rtol=1e-12, atol=1e-12)
    assert "Richardson" in how and "smoothed" in how
    rows, _, how = adapted_forces(scene, ctl, ad, "equilibrium", 1, None, extrapolate=False, theta="online")
    want, _, _ = replay_forces(scene, ctl, young, poisson, "equilibrium", 1)
    np.testing.assert_allclose(_applied(rows), _applied(want), rtol=1e-12, atol=1e-12)
    assert "Richardson" not in how and "smoothed" not in how
