"""Handle and obstacle forces along a trajectory, and their error against a truth — shared by ``rsl export
--forces`` (forces.csv) and ``rsl evaluate`` (the error against truth/forces.csv); not a stage.

Per frame and per handle / obstacle (stages.sim.stress.set_forces): the internal-force sum over its vertices
and the force it exerts on the object — a spring handle's pull Σ k (x̄ − x), a hard handle's reaction (the
residual of the implicit-Euler step without the handle at its vertices, with the inertia of x_{t−1}, x_{t−2}),
an obstacle's contact force −∂E_c/∂x.  The states before a row follow the start convention (docs/capture.md):
the earlier rows when their frames are consecutive, and before frame 0, x_{−1} = x_{−2} = x_0; a row whose
earlier frames are not in the trajectory is taken at rest (x_{t−1} = x_{t−2} = x_t).

Two ways to get the states, one definition of the force (:func:`step_forces`, also what ``rsl synth`` writes to
truth/forces.csv): the force at frame t is the residual of the LAST implicit-Euler step that produced x_t
(Δt / S with S substeps per frame, from that step's own x_{t−1}, x_{t−2}), at its held vertices.
* :func:`replay_forces` (export, evaluate and report for an online run, :func:`adapted_forces`): the controls
  re-simulated in the full space with θ(t) of the trajectory (:func:`replay_theta`), the capture's start state and
  S substeps per frame (:func:`replay_substeps`: ``--force-substeps``, default :data:`FORCE_SUBSTEPS` = 0, adapt's
  own), so every step is a solved step of the model (free-vertex residual 0, held vertices at their targets,
  inertia from that step's own states); with ``--force-extrapolate`` (off by default, :data:`FORCE_EXTRAPOLATE`)
  two replays, with S and 2S substeps, Richardson-extrapolated frame by frame (:func:`richardson`: 2 F_2S − F_S).
* :func:`trajectory_forces`: the recorded positions themselves, with frame-level finite differences.  Only
  meaningful for a trajectory that IS one simulation: an online adapt records frame t from a window solved with
  θ_t (a splice of simulations, so x − 2x_{t−1} + x_{t−2} is not an acceleration), and a reduced-space state
  leaves a residual on the free vertices and holds hard handles as springs.  On the bar cable capture
  (docs/results/accuracy.md, first row; truth P2, 3 substeps, hard base): recorded positions 62 % median error
  (reduced space), 78 % (full space); the replay of the same θ(t) 14 % (S = 1) / 11 % (S = 3, full-space θ).

The time step of the replay.  The default replays θ(t) with the time step it was estimated with (adapt's
--substeps, 6 by default), plainly: the estimated θ is the θ of that discretisation, and a replay finer in time
meets the part of the material that θ absorbed from the estimate's own numerical damping.  The adapted θ(t)
(smoothed) of the bars with E steps (equilibrium start / released at rest) and the two-region beam against truths
converged in time (docs/results/forces_theta_undamped.md, forces_theta_damped.md; bench/forces.py --part theta),
plain at adapt's S = 6 / Richardson (1, 2), the former default / Richardson (6, 12) at 3× the CPU: undamped 22.8 /
28.1 / 11.2 %, 28.9 / 52.5 / 36.8 %, 2.0 / 2.9 / 2.3 %; damped (β = 3 ms declared) 19.1 / 25.5 / 16.4 %, 37.7 /
47.6 / 20.0 %.  With β estimated (`rsl adapt --damping auto`, by hand with `rsl evaluate`, accuracy_notes.md
nineteenth stop) 5.6 / 15.9 / 21.2 % and 23.3 / 38.7 / — %; the dinosaur (undamped) 9.2 / 13.1 / — %.  Plain at
adapt's S is below Richardson (1, 2) on every capture; Richardson (6, 12) is lower on three and higher on two.
Against the table's truths of 3 substeps per frame it reads worse (bars 8.7 / 23.1 / 11.6 % against 4.4 / 8.8 /
4.9 % for the equilibrium, rest and moving starts; the dinosaur 6.1 against 9.0 %): Richardson (1, 2) takes 3 steps
per frame as that truth did (its integrator's damping, see below).  Without material damping the dynamic part of a
hard handle's reaction (the inertia of the oscillating body) carries implicit Euler's numerical damping, an error of
first order in Δt / S — on the truth's side too.  docs/results/forces_converged.md (bench/forces.py --part time)
compares the replays of the true E with truths simulated with N = 12, 24 (48) substeps and extrapolated
(2 F_2N − F_N):
* where the truths converge in time — the two-region beam (constant E; N = 12 and 24 differ by 0.7 %) and the
  bars' frames before their first E step (0.1–3.5 %) — so does the replay: plain S = 1 / 3 / 12 err 8.0 / 4.4 /
  1.8 % on the beam, 3.1 / 1.3 / 0.4 % (bar, equilibrium start) and 25 / 15 / 6.6 % (bar released at rest, which
  rings from t = 0); Richardson (1, 2) — 3 steps per frame, like S = 3, at 1.15× its CPU — 3.8, 0.6 and 12.2 %,
  lower than S = 3 on every capture, and plain S = 6 2.7, 0.6 and 10.5 % (the former default was Richardson (1, 2));
* after an instantaneous step of E the undamped body rings with modes implicit Euler damps at every step
  measured: the truths themselves differ by 11 % (N = 12 vs 24) and 9.5 % (24 vs 48), and over all frames no
  replay measured comes within 14 % of the reference on the bars (plain S = 12: 29–30 %; Richardson (6, 12), 18
  steps per frame: 15–18 %).  The force of an undamped model after a sudden change of stiffness depends on the
  integrator by tens of per cent.  With a damped material (β = 3 ms, docs/results/forces_damped.md) the truths
  converge (N = 12 against 24: 4.6 / 8.8 % on the bars) and the true E's replay does too: Richardson (6, 12)
  3.6 / 8.8 %, plain S = 6 15.4 / 31.2 %, Richardson (1, 2) 19.7 / 41.3 %.
Against a truth made with 3 substeps, plain S = 3 errs ~1 % only because it copies that truth's integrator
(docs/results/forces.md).

θ(t) of the replay (:func:`replay_theta`, ``--force-theta``): "online" = each frame's filter estimate as adapt.h5
records it (the force of frame t depends on the estimates of frames ≤ t only); "segment" = within each segment
between the material changes adapt's gn estimator detected, the segment's last estimate (:func:`smoothed_theta`; it
has seen the whole segment); "smoothed" (default :data:`FORCE_THETA`) = the fixed-interval (Rauch–Tung–Striebel)
smoother of the recorded E ± σ, ν ± σ under the random walk the gn filter itself assumed (:func:`rts_theta`: its
process noise per frame, none between frames that shared a window, its change σ at a detected change — the settings
come from adapt.h5's provenance, :func:`filter_model`); an Adam run with images and --anchor-calibration (σ of
its held fits only) is held per segment between its located changes at the calibrations' fits
(:func:`calibrated_theta`), any other Adam run keeps its recorded θ(t).  Export runs after adapt, so the replay need not be causal.
docs/results/forces_theta.md (bench/forces.py --part theta; gn, markers, full space, replay Richardson (1, 2), two adapt runs per capture)
measured against the truth refined in time.  The default is chosen on the frames where the truth's force is defined
— converged in time: every frame of the two-region beam (constant E) and every capture's frames before its first
step of E (docs/results/forces_converged.md) — where "smoothed" is lower than "online" on every capture: beam
25.2 / 26.0 % → 5.0 / 4.6 %, bar with an equilibrium start 7.8 % → 1.1 %, bar released at rest 18.4 % → 17.6 %
(and over all 40 frames of `make demo`'s capture, against its truth made with 2 substeps per frame: 11.4 % →
2.0 %; "segment" 1.7 %, the true E(t) replayed alike 1.8 %; measured by hand on the demo's workspace).  Over all
frames of the bars no replay is meaningful: after an instantaneous step of E the truths themselves do not converge
and the true E(t) replayed alike errs 51.3 % (equilibrium start) and 64.9 % (released at rest); there "online"
happens to read 60.0 % and "smoothed" 67.2 % on the bar released at rest, whose change detector fired at frame 9,
three frames before the true step, so the smoother carries the later material into frames 9–11 (as "segment" does,
68.1 %).

The error against a truth (rows of forces.csv, stages.capture.FORCE_HEADER): per handle / obstacle and frame,
e_t = ‖F_t − F_t^true‖ / ‖F_t^true‖ on the applied force (N), over the frames where ‖F_t^true‖ is at least
``floor`` × its largest value (a contact that is not there has no relative error); the median over them.
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np
from scipy.special import expit, logit

from stages.estimator import process_noise
from stages.progress import Reporter, SilentReporter
from stages.results import previous_states
from stages.sim import stress as st

APPLIED = ("applied_fx_N", "applied_fy_N", "applied_fz_N")
FORCE_SUBSTEPS = 0  # default implicit-Euler steps per frame S of the replay: 0 = adapt.h5's own (module doc)
FORCE_EXTRAPOLATE = False  # default: plain, not Richardson-extrapolated over S and 2S substeps (module doc)
FORCE_THETA = "smoothed"  # default θ(t) of the replay: "smoothed" | "online" (as adapt.h5 records it) | "segment"
THETA_RULES = ("online", "segment", "smoothed")


def replay_substeps(requested: int, adapt) -> int:
    """S of the full-space replay: ``requested`` when ≥ 1; 0 = the substeps adapt.h5 was made with
    (extra['substeps'], 1 when not recorded).  ValueError when negative."""
    if requested < 0:
        raise ValueError(f"substeps should be 0 (adapt's) or at least 1, found {requested}")
    return int(requested) or int((getattr(adapt, "extra", None) or {}).get("substeps", 1) or 1)


def states_before(frames: np.ndarray, positions: np.ndarray, row: int) -> tuple[np.ndarray, np.ndarray]:
    """(x_{t−1}, x_{t−2}) (n, 3) of row ``row`` of a trajectory (frames (T,), positions (T, n, 3)) under the
    start convention: earlier consecutive rows, else the row itself (frame 0: x_{−1} = x_{−2} = x_0)."""
    return previous_states(frames, positions, positions[row], row)


def trajectory_forces(scene, controls, frames: np.ndarray, positions: np.ndarray, internal: np.ndarray,
                      contact_distance: float = 1.0e-3, reporter: Reporter = SilentReporter()
                      ) -> tuple[list[tuple[int, st.SetForce]], np.ndarray]:
    """Forces of every handle and obstacle of ``scene`` (stages.sim Scene built with ``controls``) at each row
    of a trajectory: frames (T,), positions (T, n, 3) m, internal nodal forces (T, n, 3) N.  Returns the rows
    [(frame, SetForce)] and the per-vertex force (T, n, 3) N the handles and obstacles apply."""
    from stages.sim.scene import frame_inputs

    rows: list[tuple[int, st.SetForce]] = []
    applied = np.zeros_like(positions)
    with reporter.task("forces", len(frames)) as task:
        for i, frame in enumerate(frames):
            inputs = frame_inputs(scene, controls, int(frame))
            x = positions[i]
            xp, xpp = states_before(frames, positions, i)
            for f in st.set_forces(scene, inputs, x, xp, internal[i], contact_distance, x_prev2=xpp):
                rows.append((int(frame), f))
            applied[i] = st.applied_forces(scene, inputs, x, xp, x_prev2=xpp, f_int=internal[i])
            task.advance(1)
    return rows, applied


def step_forces(scene, controls, X: np.ndarray, states: Sequence[tuple[np.ndarray, np.ndarray]],
                young: np.ndarray, poisson: np.ndarray, substeps: int = 1, contact_distance: float = 1.0e-3,
                frames: np.ndarray | None = None) -> tuple[list[tuple[int, st.SetForce]], np.ndarray, np.ndarray]:
    """Forces at frames of a simulation: X (T, n, 3) m, ``states`` per frame (x_{t−1}, x_{t−2}) (n, 3) of the
    last step that made X[t] (stages.sim.static.simulate_from_start(states=...)), θ young/poisson (T, R), its
    substeps S (the step is Δt / S).  Returns the rows [(frame, SetForce)], the applied per-vertex force and the
    internal nodal forces, both (T, n, 3) N."""
    from stages.sim.scene import frame_inputs, internal_forces

    fine = scene if substeps == 1 else dataclasses.replace(scene, dt=scene.dt / substeps)
    frames = np.arange(len(X)) if frames is None else np.asarray(frames)
    rows: list[tuple[int, st.SetForce]] = []
    applied, internal = np.zeros_like(X), np.zeros_like(X)
    for i, frame in enumerate(frames):
        inputs = frame_inputs(fine, controls, int(frame))
        (xp, xpp), x = states[i], X[i]
        internal[i] = internal_forces(x, fine, young[i], poisson[i], x_prev=xp)  # (viscous with damping)
        rows += [(int(frame), f) for f in st.set_forces(fine, inputs, x, xp, internal[i], contact_distance,
                                                         x_prev2=xpp)]
        applied[i] = st.applied_forces(fine, inputs, x, xp, x_prev2=xpp, f_int=internal[i])
    return rows, applied, internal


def adapted_forces(scene, controls, adapt, start: str | None, substeps: int, internal, contact_distance: float = 1.0e-3,
                   reporter: Reporter = SilentReporter(), extrapolate: bool = FORCE_EXTRAPOLATE,
                   theta: str = FORCE_THETA, model: FilterModel | None = None
                   ) -> tuple[list[tuple[int, st.SetForce]], np.ndarray, str]:
    """The forces ``rsl export --forces``, ``rsl evaluate`` and ``rsl report`` give for an adapt.h5 trajectory, one
    rule for all three: an online run that starts at frame 0 (a splice of windows) is replayed in the full space
    (:func:`replay_forces`, from the capture's ``start`` with ``substeps`` per frame); an offline or static run,
    one that does not start at frame 0, or one whose capture is unknown (``start`` None) uses its recorded
    positions (:func:`trajectory_forces`; ``internal()`` gives their internal forces (T, n, 3) N).  θ(t) of the
    replay: :func:`replay_theta` with rule ``theta``, adapt.h5's young_sigma / poisson_sigma and ``model`` (the gn
    filter's random walk, :func:`filter_model`; without it "smoothed" keeps the recorded θ(t)).
    A capture filmed mid-motion (``start`` "moving") is replayed from the x_{−1}, x_0 that adapt estimated (adapt.h5
    start_positions), or, without them, uses the recorded positions.
    Returns (rows, applied (T, n, 3) N, a phrase naming the source)."""
    before = getattr(adapt, "start_positions", None)
    if (getattr(adapt, "mode", "online") == "online" and start is not None and replayable(adapt.frames)
            and (start != "moving" or before is not None)):
        young, poisson, how = replay_theta(adapt.young, adapt.poisson, getattr(adapt, "extra", None), theta,
                                           getattr(adapt, "young_sigma", None), getattr(adapt, "poisson_sigma", None),
                                           model)
        rows, applied, _ = replay_forces(scene, controls, young, poisson, start, substeps, contact_distance, reporter,
                                         extrapolate, before)
        steps = (f"Richardson-extrapolated from {substeps} and {2 * substeps} substeps per frame" if extrapolate
                 else f"{substeps} substep(s) per frame")
        return rows, applied, f"full-space replay of the controls with {how}, {steps}"
    rows, applied = trajectory_forces(scene, controls, adapt.frames, adapt.positions, internal(), contact_distance,
                                      reporter)
    return rows, applied, "adapt.h5 positions"


def replayable(frames: np.ndarray) -> bool:
    """Whether a trajectory's frames are 0, 1, …, T−1 (a replay starts at frame 0's start state)."""
    frames = np.asarray(frames)
    return len(frames) > 0 and bool(np.array_equal(frames, np.arange(len(frames))))


def replay_forces(scene, controls, young: np.ndarray, poisson: np.ndarray, start: str, substeps: int = 1,
                  contact_distance: float = 1.0e-3, reporter: Reporter = SilentReporter(),
                  extrapolate: bool = False, before: np.ndarray | None = None
                  ) -> tuple[list[tuple[int, st.SetForce]], np.ndarray, np.ndarray]:
    """Forces of the controls re-simulated in the full space (module doc): frames 0..T−1 from the ``start`` state
    (docs/capture.md; "moving": from ``before`` = (x_{−1}, x_0) (2, n, 3) m, stages.sim.static.simulate_from_start),
    θ(t) = young/poisson (T, R), ``substeps`` implicit-Euler steps per frame; with
    ``extrapolate``, :func:`richardson` of the replays with S and 2S substeps, frame by frame.  Returns
    (rows [(frame, SetForce)], applied per-vertex force (T, n, 3) N, replayed positions (T, n, 3) m)."""
    if extrapolate:
        coarse = replay_forces(scene, controls, young, poisson, start, substeps, contact_distance, reporter,
                               before=before)
        fine = replay_forces(scene, controls, young, poisson, start, 2 * substeps, contact_distance, reporter,
                             before=before)
        return (richardson_rows(coarse[0], fine[0]), richardson(coarse[1], fine[1]), richardson(coarse[2], fine[2]))
    from stages.sim.scene import frame_inputs
    from stages.sim.static import simulate_from_start

    T = len(young)
    states: list = []
    with reporter.task(f"forces (full-space replay, {substeps} substep(s))", T) as task:
        X = simulate_from_start(scene, lambda f: frame_inputs(scene, controls, f), young, poisson, T, start,
                                substeps, callback=lambda _t: task.advance(1), states=states, before=before)
    rows, applied, _ = step_forces(scene, controls, X, states, np.asarray(young), np.asarray(poisson), substeps,
                                   contact_distance)
    return rows, applied, X


def richardson(coarse, fine, order: int = 1):
    """Richardson extrapolation to Δt → 0 of a quantity computed with steps h (``coarse``) and h / 2 (``fine``) by
    an integrator of ``order`` p: q ≈ q_{h/2} + (q_{h/2} − q_h) / (2^p − 1) (p = 1, implicit Euler:
    2 q_{h/2} − q_h), which cancels the error term of order p.  Arrays of one shape (or floats)."""
    c, f = np.asarray(coarse, np.float64), np.asarray(fine, np.float64)
    if c.shape != f.shape:
        raise ValueError(f"Richardson extrapolation needs one shape, found {c.shape} and {f.shape}")
    return f + (f - c) / (2.0 ** order - 1.0)


def richardson_rows(coarse: Sequence[tuple[int, st.SetForce]], fine: Sequence[tuple[int, st.SetForce]],
                    order: int = 1) -> list[tuple[int, st.SetForce]]:
    """The rows [(frame, SetForce)] of two replays of the same frames (steps h and h / 2), matched by (frame, name),
    with their forces extrapolated (:func:`richardson`: internal, magnitude sum, applied); the vertex count of the
    fine one.  ValueError when the two do not hold the same (frame, name) rows."""
    by_key = {(frame, f.name): f for frame, f in coarse}
    keys = [(frame, f.name) for frame, f in fine]
    if len(by_key) != len(coarse) or sorted(by_key) != sorted(keys):
        raise ValueError("the two replays do not hold the same (frame, handle/obstacle) rows")
    out = []
    for frame, f in fine:
        c = by_key[(frame, f.name)]
        out.append((frame, dataclasses.replace(
            f, internal=richardson(c.internal, f.internal, order), applied=richardson(c.applied, f.applied, order),
            magnitude_sum=float(richardson(c.magnitude_sum, f.magnitude_sum, order)))))
    return out


def segments(changes: Sequence[int], T: int) -> list[tuple[int, int]]:
    """Frame ranges [a, b) of frames 0..T−1 between change points (each change frame starts a segment)."""
    cuts = sorted({int(c) for c in changes if 0 < int(c) < T})
    edges = [0, *cuts, T]
    return [(a, b) for a, b in zip(edges, edges[1:])]


def smoothed_theta(young: np.ndarray, poisson: np.ndarray, changes: Sequence[int], lag: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """θ(t) (T, R) of an online run smoothed within the segments between detected material changes: frame t takes
    the estimate of frame min(t + lag, b − 1), b the end of its segment (:func:`segments`); ``lag`` None = the
    segment's last estimate (the one that has seen the whole segment: fixed-interval smoothing of a constant)."""
    young, poisson = np.asarray(young, np.float64), np.asarray(poisson, np.float64)
    T = len(young)
    idx = np.arange(T)
    for a, b in segments(changes, T):
        idx[a:b] = b - 1 if lag is None else np.minimum(np.arange(a, b) + int(lag), b - 1)
    return young[idx], poisson[idx]


@dataclasses.dataclass(frozen=True)
class FilterModel:
    """The random walk adapt's gn filter assumed (its AdaptConfig) and the capture's ν range: σ per frame of the
    walk of log E and of ν's parameter s (``process_noise``; ``process_noise_change`` during the window + 5 frames
    after a detected change, stages.estimator.process_noise), the σ added to log E at a detected change
    (``change_sigma``), the window w, the model-error floors the reported σ carry (``model_error`` relative for E,
    ``model_error_poisson`` for ν; stages.windows.sigma_from_cov) and ν = lo + (hi − lo) sigmoid(s)."""

    window: int
    process_noise: float
    process_noise_change: float
    change_sigma: float
    model_error: float
    model_error_poisson: float
    poisson_range: tuple[float, float]


def filter_model(config: dict | None, poisson_range, extra: dict | None = None) -> FilterModel | None:
    """The FilterModel of an adapt.h5 from its provenance config (stages.artefacts.read_provenance(...)["config"])
    and the capture's [material] poisson_range; None when the config lacks one of the filter's settings (a run not
    made by the gn estimator can lack them).  --process-noise and --model-error left at their defaults (None in the
    config) are read from the adapt.h5's ``extra`` (the values that ran).  A config from before
    --process-noise-change had one σ for all frames."""
    config = config or {}
    for key in ("process_noise", "model_error"):  # left at their defaults: the value that ran, from the extras
        if config.get(key) is None and (extra or {}).get(key) is not None:
            config = {**config, key: extra[key]}
    keys = ("window", "process_noise", "change_sigma", "model_error", "model_error_poisson")
    if any(config.get(k) is None for k in keys) or poisson_range is None:
        return None
    q, change = float(config["process_noise"]), config.get("process_noise_change")
    lo, hi = (float(v) for v in np.ravel(poisson_range)[:2])
    return FilterModel(int(config["window"]), q, q if change is None else float(change),
                       float(config["change_sigma"]),
                       float(config["model_error"]), float(config["model_error_poisson"]), (lo, hi))


def rts_smooth(mean: np.ndarray, var: np.ndarray, q_var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-interval (Rauch–Tung–Striebel) smoother of a random walk x_{t+1} = x_t + w_t, w_t ~ N(0, q_var[t]),
    from the filtered means (T,) and variances var (T,) (Gaussian posteriors of x_t given frames ≤ t):

        x_s(T−1) = m(T−1),   x_s(t) = m(t) + C_t (x_s(t+1) − m(t)),   C_t = P(t) / (P(t) + q_t)
        P_s(t) = P(t) + C_t² (P_s(t+1) − P(t) − q_t)

    (the walk predicts x_{t+1} by m(t) with variance P(t) + q_t); C_t = 0 where P(t) + q_t = 0.  q_var (T − 1,):
    the walk's variance from frame t to t + 1.  Returns the smoothed means and variances (T,), each the posterior
    of x_t given all frames."""
    m, P, q = (np.asarray(a, np.float64) for a in (mean, var, q_var))
    T = len(m)
    if P.shape != (T,) or q.shape != (max(T - 1, 0),):
        raise ValueError(f"rts_smooth needs mean and var of one length T and q_var of T − 1, found {m.shape}, "
                         f"{P.shape}, {q.shape}")
    xs, Ps = m.copy(), P.copy()
    for t in range(T - 2, -1, -1):
        pred = P[t] + q[t]
        C = P[t] / pred if pred > 0 else 0.0
        xs[t] = m[t] + C * (xs[t + 1] - m[t])
        Ps[t] = P[t] + C * C * (Ps[t + 1] - pred)
    return xs, Ps


def walk_variances(frames: np.ndarray, changes: Sequence[int], model: FilterModel) -> tuple[np.ndarray, np.ndarray]:
    """The variance (T − 1,) of the gn filter's random walk from each recorded frame to the next, for log E and for
    ν's parameter s, as stages.steps.adapt._online_gn adds it: after the solve of the window ending at frame t, a
    FULL window (w frames since the later of the first frame and the last detected change ≤ t) folds its oldest
    frame into the arrival cost with process noise q(t)² (stages.estimator.process_noise); a window still growing
    adds none (its frames share one θ); a change detected at frame t + 1 adds change_sigma² to log E (not to s)."""
    frames = np.asarray(frames)
    found = sorted(int(c) for c in changes)
    first = int(frames[0]) if len(frames) else 0
    qe, qs = np.zeros(max(len(frames) - 1, 0)), np.zeros(max(len(frames) - 1, 0))
    for i, t in enumerate(frames[:-1]):
        t = int(t)
        seen = [c for c in found if c <= t]
        start = max([first, *seen])
        if t - start + 1 >= model.window:
            q = process_noise(t, seen, model.window, model.process_noise, model.process_noise_change)
            qe[i] = qs[i] = q * q
        if int(frames[i + 1]) in found:
            qe[i] += model.change_sigma ** 2
    return qe, qs


def rts_theta(young: np.ndarray, young_sigma: np.ndarray, poisson: np.ndarray, poisson_sigma: np.ndarray,
              frames: np.ndarray, changes: Sequence[int], model: FilterModel,
              young_floor: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """θ(t) (T, R) of a gn online run smoothed over the whole run under the filter's own random walk
    (:func:`rts_smooth` per region, log E and s = logit((ν − lo) / (hi − lo)) apart — the filter's covariance
    between them is not recorded): the means and σ adapt.h5 records per frame (young, young_sigma Pa, poisson,
    poisson_sigma), their model-error floor taken out (P = σ² − e², the filter's own variance: the floor is a bias
    that more frames do not average; e per frame and region from ``young_floor`` (T, R), adapt.h5's extra
    'young_model_error', else the model's one e), the walk of :func:`walk_variances`.  ν with σ at the floor (held,
    or not fitted) and a fixed ν range keep their recorded values."""
    young, poisson = np.asarray(young, np.float64), np.asarray(poisson, np.float64)
    sy, sp = np.asarray(young_sigma, np.float64), np.asarray(poisson_sigma, np.float64)
    qe, qs = walk_variances(frames, changes, model)
    log_e = np.log(young)
    floor = (model.model_error if young_floor is None
             else np.broadcast_to(np.asarray(young_floor, np.float64), young.shape))
    var_e = np.maximum(np.nan_to_num((sy / young) ** 2, nan=0.0) - floor ** 2, 0.0)
    out_e = np.exp(np.stack([rts_smooth(log_e[:, r], var_e[:, r], qe)[0] for r in range(young.shape[1])], axis=1))
    lo, hi = model.poisson_range
    if hi - lo <= 1e-9:
        return out_e, poisson.copy()
    u = np.clip((poisson - lo) / (hi - lo), 1e-9, 1 - 1e-9)
    s = logit(u)
    ds = u * (1 - u) * (hi - lo)  # dν/ds
    var_s = np.maximum(np.nan_to_num(sp ** 2, nan=0.0) - model.model_error_poisson ** 2, 0.0) / ds ** 2
    out_s = np.stack([rts_smooth(s[:, r], var_s[:, r], qs)[0] for r in range(poisson.shape[1])], axis=1)
    return out_e, lo + (hi - lo) * expit(out_s)


def calibrated_theta(young: np.ndarray, poisson: np.ndarray, calibrations: Sequence[dict],
                     changes: Sequence[int]) -> tuple[np.ndarray, np.ndarray, int]:
    """θ(t) (T, R) of an adam images run held per segment at its calibrations' fits: the segments between the
    located changes of material (``changes``, adapt.h5 extra['anchor_change_frames']); a segment whose first frame
    is a calibration's first frame (extra['anchor_calibrations'], {"frames": [first, last], "young", "poisson"})
    takes that fit — θ fitted to the segment's first frames at once, not a sliding window's steps — and keeps its
    recorded θ(t) otherwise (a change too late in the run to be calibrated).  Returns (young, poisson, the number of
    segments held)."""
    young, poisson = np.array(young, np.float64), np.array(poisson, np.float64)
    by_first = {int(c["frames"][0]): c for c in calibrations}
    held = 0
    for a, b in segments(changes, len(young)):
        cal = by_first.get(a)
        if cal is not None:
            young[a:b], poisson[a:b], held = cal["young"], cal["poisson"], held + 1
    return young, poisson, held


def replay_theta(young: np.ndarray, poisson: np.ndarray, extra: dict | None, rule: str = FORCE_THETA,
                 young_sigma: np.ndarray | None = None, poisson_sigma: np.ndarray | None = None,
                 model: FilterModel | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """θ(t) the replay uses for an online adapt.h5 (module doc) from its young/poisson (T, R) and extra: (young,
    poisson (T, R), a phrase).
    "online": as recorded (each frame's filter estimate).  "segment": :func:`smoothed_theta` with the changes the
    gn estimator detected (extra['material_changes_detected']).  "smoothed": :func:`rts_theta` from the recorded σ
    (young_sigma, poisson_sigma (T, R)) under the filter's random walk ``model`` (:func:`filter_model`).  A run
    without a change detector (Adam: no σ either) keeps its recorded θ(t), and so does "smoothed" without σ or
    model — except an Adam run with calibrations (extra['anchor_calibrations']): "segment" and "smoothed" hold them
    over their segments (:func:`calibrated_theta`).  ValueError for an unknown rule."""
    if rule not in THETA_RULES:
        raise ValueError(f"the replay's θ rule should be one of {', '.join(THETA_RULES)}, found {rule!r}")
    young, poisson = np.asarray(young, np.float64), np.asarray(poisson, np.float64)
    extra = extra or {}
    if rule == "online":
        return young, poisson, "θ(t) of adapt.h5"
    if extra.get("anchor_calibrations"):  # adam with images: fits per segment (σ of the held fits only)
        changes = [int(c) for c in extra.get("anchor_change_frames", []) or []]
        y, p, held = calibrated_theta(young, poisson, extra["anchor_calibrations"], changes)
        return y, p, (f"θ(t) of adapt.h5 held at its anchor calibrations' fits ({held} of "
                      f"{len(segments(changes, len(young)))} segment(s) between located changes)")
    if extra.get("estimator") != "gn":
        return young, poisson, "θ(t) of adapt.h5 (no change detector in this run: not smoothed)"
    changes = [int(c) for c in extra.get("material_changes_detected", []) or []]
    if rule == "smoothed":
        if young_sigma is None or poisson_sigma is None or model is None or np.size(young_sigma) != young.size:
            return young, poisson, "θ(t) of adapt.h5 (its σ or its filter settings not recorded: not smoothed)"
        floor = extra.get("young_model_error")  # per frame and region (runs before it: the model's one e)
        floor = None if floor is None or np.size(floor) != young.size else np.asarray(floor, np.float64)
        y, p = rts_theta(young, young_sigma, poisson, np.broadcast_to(poisson_sigma, poisson.shape),
                         np.arange(len(young)), changes, model, floor)
        return y, p, (f"θ(t) of adapt.h5 smoothed over the run (Rauch–Tung–Striebel, the filter's random walk, "
                      f"{len(changes)} detected change(s))")
    y, p = smoothed_theta(young, poisson, changes)
    n = len(segments(changes, len(young)))
    return y, p, f"θ(t) of adapt.h5 smoothed per segment ({n} segment(s) between detected changes)"


def force_table(rows: Sequence[tuple[int, st.SetForce]], dt: float) -> list[dict]:
    """The rows as forces.csv dicts (stages.capture.FORCE_HEADER columns, numbers as float)."""
    out = []
    for frame, f in rows:
        d = {"frame": float(frame), "time_s": frame * dt, "name": f.name, "kind": f.kind,
             "fx_N": float(f.internal[0]), "fy_N": float(f.internal[1]), "fz_N": float(f.internal[2]),
             "magnitude_sum_N": float(f.magnitude_sum), "n_vertices": float(f.n_vertices)}
        d.update({k: float(v) for k, v in zip(APPLIED, f.applied)})
        out.append(d)
    return out


def force_errors(estimated: Sequence[dict], truth: Sequence[dict], floor: float = 0.05) -> dict[str, dict]:
    """Per handle / obstacle name of the truth: {"kind", "median_relative_error" (None when no frame counts),
    "frames" (those compared), "rel_error_per_frame", "truth_max_N"} of the applied forces (module doc).
    ``estimated`` / ``truth``: forces.csv rows as dicts; only frames present in both count."""
    est = {(int(r["frame"]), r["name"]): np.array([r[k] for k in APPLIED], float) for r in estimated}
    out: dict[str, dict] = {}
    names = list(dict.fromkeys(r["name"] for r in truth))
    for name in names:
        tr = {int(r["frame"]): (np.array([r[k] for k in APPLIED], float), r["kind"]) for r in truth
              if r["name"] == name}
        common = sorted(t for t in tr if (t, name) in est)
        kind = next(iter(tr.values()))[1]
        if not common:
            out[name] = {"kind": kind, "median_relative_error": None, "frames": [], "rel_error_per_frame": [],
                         "truth_max_N": None, "note": "no frame of the estimate matches the truth's"}
            continue
        mags = np.array([np.linalg.norm(tr[t][0]) for t in common])
        top = max(float(np.linalg.norm(f)) for f, _ in tr.values())  # the truth's largest, over all its frames
        keep = mags >= floor * top if top > 0 else np.zeros(len(common), bool)
        errs = [float(np.linalg.norm(est[(t, name)] - tr[t][0]) / m) for t, m, k in zip(common, mags, keep) if k]
        out[name] = {"kind": kind, "median_relative_error": float(np.median(errs)) if errs else None,
                     "frames": [t for t, k in zip(common, keep) if k], "rel_error_per_frame": errs,
                     "truth_max_N": top}
    return out
