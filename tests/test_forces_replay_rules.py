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


def test_adam_runs_are_replayed_at_their_calibrations_fits_per_located_segment():
    """adam with images (--anchor-calibration, --recalibrate): each segment between the located changes takes the
    fit of the calibration that began with it; a segment without one (a change too late to calibrate) keeps its
    recorded θ(t); "online" keeps everything as recorded."""
    from stages.forces import calibrated_theta, replay_theta

    young = np.arange(1.0, 11.0)[:, None]
    poisson = np.full((10, 1), 0.4)
    cals = [{"frames": [0, 3], "young": [20.0], "poisson": [0.41]},
            {"frames": [4, 6], "young": [40.0], "poisson": [0.42]}]
    y, p, held = calibrated_theta(young, poisson, cals, [4, 8])
    np.testing.assert_array_equal(y[:, 0], [20, 20, 20, 20, 40, 40, 40, 40, 9, 10])
    np.testing.assert_array_equal(p[:, 0], [0.41] * 4 + [0.42] * 4 + [0.4] * 2)
    assert held == 2
    extra = {"estimator": "adam", "anchor_calibrations": cals, "anchor_change_frames": [4, 8]}
    for rule in ("segment", "smoothed"):
        y2, _, how = replay_theta(young, poisson, extra, rule)
        np.testing.assert_array_equal(y2, y)
        assert "2 of 3 segment(s)" in how, how
    y3, _, _ = replay_theta(young, poisson, extra, "online")
    np.testing.assert_array_equal(y3, young)
    np.testing.assert_array_equal(young[:, 0], np.arange(1.0, 11.0))  # the input is not modified


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


def _theta_rule_errors(cable, online: np.ndarray, true_young: np.ndarray, changes: list[int], step: int) -> dict:
    """{rule: (median error over all frames, over frames < step)} of adapted_forces' replay (Richardson (1, 2)) of an
    online θ(t) (T,) under each θ rule, against the true E(t) (T,) replayed the same way (the part of the error the
    rule adds)."""
    from types import SimpleNamespace

    from stages.forces import THETA_RULES, adapted_forces, force_errors, force_table, replay_forces

    scene, ctl, _, poisson = cable
    ad = SimpleNamespace(mode="online", frames=np.arange(FRAMES), young=online[:, None], poisson=poisson,
                         extra={"estimator": "gn", "material_changes_detected": changes})
    truth = force_table(replay_forces(scene, ctl, true_young[:, None], poisson, "equilibrium", 1, extrapolate=True)[0],
                        1.0 / FPS)
    out = {}
    for rule in THETA_RULES:
        rows, _, _ = adapted_forces(scene, ctl, ad, "equilibrium", 1, None, extrapolate=True, theta=rule)
        got = force_errors(force_table(rows, 1.0 / FPS), truth)["base"]
        before = [e for t, e in zip(got["frames"], got["rel_error_per_frame"]) if t < step]
        out[rule] = (got["median_relative_error"], float(np.median(before)))
    return out


def test_segment_theta_removes_a_start_transient_but_carries_a_later_estimate_across_an_early_detected_change(cable):
    """The two shapes of docs/results/forces_theta.md, against the true E(t) replayed alike (E ×2 at frame 5):
    (a) the estimate starts far off (0.4 E_true), settles within 2 % and follows the step one frame late (detected
    at frame 6): 'segment' (each segment's last estimate) removes the transient: frames before the step within 2 %
    where the recorded θ(t) ('online') errs > 10 %, and half its error over all frames (the beam and the bar with an
    equilibrium start);  (b) the estimate is settled, but the change detector fires at frame 2, three frames before
    the true step, and again at 7: the segment [2, 7) takes frame 6's post-step estimate, so frames 2–4 are replayed
    twice as stiff — 'segment' errs > 10 % before the step where 'online' stays within 2 % (the bar released at
    rest, detected changes 9 and 16 around its step at 12)."""
    step = 5
    true_young = SOFT * np.where(np.arange(FRAMES) < step, 1.0, 2.0)
    transient = SOFT * np.array([0.4, 0.7, 0.9, 1.02, 0.99, 1.01, 1.5, 1.9, 2.04, 1.98])
    a = _theta_rule_errors(cable, transient, true_young, [step + 1], step)
    settled = SOFT * np.array([1.01, 0.99, 1.0, 1.01, 0.99, 1.6, 1.95, 2.01, 1.99, 2.0])
    b = _theta_rule_errors(cable, settled, true_young, [2, 7], step)
    print(a, b)
    assert a["segment"][1] < 0.02 and a["online"][1] > 0.1, a
    assert a["segment"][0] < 0.5 * a["online"][0], a
    assert b["online"][1] < 0.02 and b["segment"][1] > 0.1, b


def test_default_theta_rule_carries_a_later_estimate_across_a_detected_change_only_by_the_smoothers_gain(cable):
    """The default θ(t) rule of the replay (stages.forces.FORCE_THETA, what `rsl export --forces`, `rsl evaluate` and
    `rsl report` use) is 'smoothed' (docs/results/forces_theta.md: lower than 'online' on every capture over the
    frames where the truth's force converges in time).  It is not causal — frame t's θ uses the later estimates —
    but across a material change the gn estimator detected at frame c it carries a later estimate back only by the
    Rauch–Tung–Striebel gain: moving every estimate from c on by a factor k moves frame t < c's E by exactly
    k^(Π_{j=t}^{c−1} C_j), C_j = P_j / (P_j + q_j), where q_{c−1} holds the change σ² (here Π < 1 %), so frames
    before c keep their forces within 1 %; without the detected change the same move is carried back (> 5 %)."""
    from types import SimpleNamespace

    from stages.forces import FORCE_THETA, FilterModel, adapted_forces, replay_theta, walk_variances

    scene, ctl, _, poisson = cable
    model = FilterModel(3, 0.005, 0.02, 0.5, 0.02, 0.02, (0.3, 0.49))
    young = SOFT * np.array([0.4, 0.7, 0.9, 1.02, 0.99, 1.01, 1.0, 0.98, 1.02, 1.0])[:, None]
    rel = np.array([0.5, 0.3, 0.1, 0.04, 0.03, 0.03, 0.06, 0.04, 0.03, 0.03])[:, None]
    later = young.copy()
    c, k = 6, 1.7
    later[c:] *= k

    def run(y, changes):
        ad = SimpleNamespace(mode="online", frames=np.arange(FRAMES), young=y, poisson=poisson, young_sigma=y * rel,
                             poisson_sigma=np.full_like(poisson, 0.02),
                             extra={"estimator": "gn", "material_changes_detected": changes})
        rows, _, how = adapted_forces(scene, ctl, ad, "equilibrium", 1, None, model=model)
        assert "Rauch–Tung–Striebel" in how
        return np.array([f.applied for t, f in rows if t < c])

    assert FORCE_THETA == "smoothed"
    # the gain, from the recorded σ (model error taken out) and the filter's walk
    qe, _ = walk_variances(np.arange(FRAMES), [c], model)
    P = rel[:, 0] ** 2 - 0.02 ** 2
    gain = P[:-1] / (P[:-1] + qe)
    base = replay_theta(young, poisson, {"estimator": "gn", "material_changes_detected": [c]}, "smoothed",
                        young * rel, np.full_like(poisson, 0.02), model)[0]
    moved = replay_theta(later, poisson, {"estimator": "gn", "material_changes_detected": [c]}, "smoothed",
                         later * rel, np.full_like(poisson, 0.02), model)[0]
    carried = np.log(moved[:c, 0] / base[:c, 0]) / np.log(k)
    np.testing.assert_allclose(carried, [np.prod(gain[t:c]) for t in range(c)], rtol=1e-9, atol=1e-15)
    assert carried.max() < 0.01
    top = np.linalg.norm(run(young, [c]), axis=1).max()
    assert np.linalg.norm(run(young, [c]) - run(later, [c]), axis=1).max() < 0.01 * top
    assert np.linalg.norm(run(young, []) - run(later, []), axis=1).max() > 0.05 * top  # no change detected: carried


def test_smoothed_theta_rule_replays_the_rts_estimate_and_removes_a_start_transient(cable):
    """adapted_forces with theta="smoothed" replays stages.forces.rts_theta of adapt.h5's E ± σ under the filter's
    random walk (FilterModel); on shape (a) of the test above (a start transient, the step detected one frame
    late) the frames before the step come within 2 % of the true E(t) replayed alike where 'online' errs > 10 %."""
    from types import SimpleNamespace

    from stages.forces import FilterModel, adapted_forces, force_errors, force_table, replay_forces, rts_theta

    scene, ctl, _, poisson = cable
    step = 5
    model = FilterModel(3, 0.005, 0.02, 0.5, 0.02, 0.02, (0.3, 0.49))
    online = SOFT * np.array([0.4, 0.7, 0.9, 1.02, 0.99, 1.01, 1.5, 1.9, 2.04, 1.98])[:, None]
    rel = np.array([0.5, 0.3, 0.1, 0.03, 0.025, 0.025, 0.1, 0.04, 0.03, 0.025])[:, None]
    ad = SimpleNamespace(mode="online", frames=np.arange(FRAMES), young=online, poisson=poisson,
                         young_sigma=online * rel, poisson_sigma=np.full_like(poisson, 0.02),
                         extra={"estimator": "gn", "material_changes_detected": [step + 1]})
    rows, _, how = adapted_forces(scene, ctl, ad, "equilibrium", 1, None, extrapolate=True, theta="smoothed",
                                  model=model)
    assert "Rauch–Tung–Striebel" in how
    y, p = rts_theta(online, online * rel, poisson, np.full_like(poisson, 0.02), np.arange(FRAMES), [step + 1],
                     model)
    want = replay_forces(scene, ctl, y, p, "equilibrium", 1, extrapolate=True)[0]
    np.testing.assert_allclose(_applied(rows), _applied(want), rtol=1e-12, atol=1e-12)
    true_young = SOFT * np.where(np.arange(FRAMES) < step, 1.0, 2.0)[:, None]
    truth = force_table(replay_forces(scene, ctl, true_young, poisson, "equilibrium", 1, extrapolate=True)[0],
                        1.0 / FPS)

    def before(r):
        got = force_errors(force_table(r, 1.0 / FPS), truth)["base"]
        return float(np.median([e for t, e in zip(got["frames"], got["rel_error_per_frame"]) if t < step]))

    plain = adapted_forces(scene, ctl, ad, "equilibrium", 1, None, extrapolate=True, theta="online")[0]
    assert before(rows) < 0.02 and before(plain) > 0.1, (before(rows), before(plain))
