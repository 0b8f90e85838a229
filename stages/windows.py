"""Windows of ``rsl adapt`` under the capture's start convention (docs/capture.md): ``StartWindow`` simulates frames
from x_0(θ); ``StaticWindow`` solves the static equilibria alone; ``WindowObjective`` gives the window loss and
dL/dp by the adjoint; ``GNWindow`` gives residuals and their Jacobian for Gauss–Newton (stages.estimator)."""
from __future__ import annotations

import contextlib
import time
from typing import Callable, Sequence

import numpy as np
from threadpoolctl import threadpool_limits

from stages.errors import RslError
from stages.estimator import bounded_sigma, robust_cost
from stages.parameters import chain_params, theta_from_params
from stages.window_model import Observation, Window, WindowBackend


# =========================================================================== the start convention
class StartWindow:
    """A window simulated under the capture's start convention (docs/capture.md): frame 0 is x_0(θ) — the rest
    shape, or the static equilibrium under the frame-0 controls solved with θ — with x_{−1} = x_{−2} = x_0;
    frame t ≥ 1 is an implicit-Euler step from (x_{t−1}, x_{t−2}).  A window that holds frame 0 differentiates
    through the static solve (stages.sim.static); other windows start from their two stored states.
    ``moving`` (a capture filmed mid-motion, stages/moving_start.py): frame 0 and the state before it are the
    static equilibrium x_e(θ) under the frame-0 controls plus estimated offsets, x_0 = x_e + Δ_0, x_{−1} = x_e +
    Δ_{−1}: a window that holds frame 0 takes ``before`` = (Δ_{−1}, Δ_0) (None: zero, the equilibrium at rest),
    which the Gauss–Newton state correction estimates; frame t ≥ 1 is a step as above.  With :attr:`reference`
    set (images: the state the Gaussians were fitted at), x_e is that fixed state instead of x_e(θ).
    θ = (E (R,), ν (R,)) is shared by the window frames."""

    KINDS = ("rest", "equilibrium", "moving")

    def __init__(self, backend: WindowBackend, kind: str = "rest"):
        if kind not in self.KINDS:
            raise RslError(f"the start state should be 'rest', 'equilibrium' or 'moving', found '{kind}'.")
        self.backend, self.kind = backend, kind
        self._x0 = None  # the last x_0: the warm start of the next static solve
        # ``memo`` (GNWindow.memo): frames of the last trajectory simulated with θ from two known states are taken
        # from it instead of being simulated again — x_t depends on θ, x_{t−2}, x_{t−1} and frame t's controls
        # alone, so the same states come out (up to the tolerance of the step's solve).  With substeps
        # (window_backends.Substepped) the window's sensitivities stitch its substep trajectory from the forwards
        # that simulated its frames (Substepped._stitch)
        self.memo = False
        self._traj: tuple[np.ndarray, np.ndarray, dict] | None = None  # (E, ν, {frame: state})
        # a moving start: the state its offsets are added to, fixed (independent of θ), or None for x_e(θ)
        self.reference: np.ndarray | None = None

    @staticmethod
    def _tile(a, k):
        return np.tile(np.asarray(a, float), (k, 1))

    def remember(self, frames: Sequence[int], E, nu, before, states) -> None:
        """Make (``before`` at frames[0] − 2, frames[0] − 1; ``states`` at ``frames``) the trajectory of θ = (E, ν)
        that :meth:`forward` continues (``memo``); GNWindow.extrapolate gives it the window's states to first order."""
        t0 = int(frames[0])
        traj = {t0 - 2: np.asarray(before[0]), t0 - 1: np.asarray(before[1])} if t0 >= 2 else {}
        traj.update({int(t): np.asarray(x) for t, x in zip(frames, states)})
        self._traj = (np.array(E, float), np.array(nu, float), traj)

    def _memo_forward(self, frames: list, E, nu, before) -> np.ndarray | None:
        """:meth:`forward` continuing the remembered trajectory, or None when it does not pass through ``before``
        with this θ: the frames it holds are taken, the rest simulated from it (and remembered)."""
        if self._traj is None or frames[0] < 2:
            return None
        tE, tn, traj = self._traj
        t0 = frames[0]
        if not (np.array_equal(tE, E) and np.array_equal(tn, nu) and t0 - 2 in traj and t0 - 1 in traj
                and np.array_equal(traj[t0 - 2], before[0]) and np.array_equal(traj[t0 - 1], before[1])):
            return None
        out = []
        for i, t in enumerate(frames):
            if t not in traj:  # the rest from the two states before it
                rest = self.backend.forward(frames[i:], self._tile(E, len(frames) - i), self._tile(nu, len(frames) - i),
                                            np.stack([traj[t - 2], traj[t - 1]]))
                traj.update({int(u): x for u, x in zip(frames[i:], rest)})
                out.extend(rest)
                break
            out.append(traj[t])
        return np.stack(out)

    def forward(self, frames: Sequence[int], E, nu, before) -> np.ndarray:
        """States (w, …) of ``frames``; ``before`` = [state t0−2, state t0−1] (unused when frames[0] = 0)."""
        b, w = self.backend, len(frames)
        if frames[0] == 0 and self.kind == "moving":
            xm1, x0 = self._moving_start(E, nu, before)
            if w == 1:
                return x0[None]
            rest = b.forward(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1), np.stack([xm1, x0]))
            return np.concatenate([x0[None], rest])
        if frames[0] != 0:
            memo = self.memo
            if memo:
                X = self._memo_forward(list(frames), E, nu, before)
                if X is not None:
                    return X.copy()
            X = b.forward(list(frames), self._tile(E, w), self._tile(nu, w), before)
            if memo:
                self.remember(frames, E, nu, before, X.copy())
            return X
        x0 = b.start(E, nu, self.kind, self._x0)
        self._x0 = x0
        if w == 1:
            return x0[None]
        rest = b.forward(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1), np.stack([x0, x0]))
        return np.concatenate([x0[None], rest])

    def _moving_start(self, E, nu, before) -> tuple[np.ndarray, np.ndarray]:
        """(x_{−1}, x_0) of a moving start: x_e(θ) (the static equilibrium, kept in ``_x0``: the next solve's warm
        start) plus the offsets ``before`` = (Δ_{−1}, Δ_0) (None: zero)."""
        if self.reference is not None:
            xe = np.asarray(self.reference, float)
        else:
            xe = self.backend.start(E, nu, "equilibrium", self._x0)
            self._x0 = xe
        if before is None:
            return xe, xe
        return xe + np.asarray(before[0]), xe + np.asarray(before[1])

    @staticmethod
    def _moving_states(states, before) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x_e, x_{−1}, x_0) of a moving start's window from its forward's states and offsets (no solve)."""
        x0 = np.asarray(states[0])
        if before is None:
            return x0, x0, x0
        xe = x0 - np.asarray(before[1])
        return xe, xe + np.asarray(before[0]), x0

    def backward(self, frames, E, nu, states, before, dL_dX) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν) (R,) of a loss of the window's positions, dL_dX (w, n, 3)."""
        b, w = self.backend, len(frames)
        if frames[0] == 0 and self.kind == "moving":  # through x_e(θ), which moves x_0 and x_{−1} alike
            xe, xm1, x0 = self._moving_states(states, before)
            g = b.state_grad(x0, dL_dX[0])
            gE, gN = np.zeros(len(E)), np.zeros(len(E))
            if w > 1:
                dE, dn, gb = b.backward_before(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1),
                                               states[1:], np.stack([xm1, x0]), dL_dX[1:])
                gE, gN, g = dE.sum(0), dn.sum(0), g + gb[0] + gb[1]
            if self.reference is not None:  # (a fixed x_e: no path from θ)
                return gE, gN
            a, c = b.start_adjoint(E, nu, "equilibrium", xe, g)
            return gE + a, gN + c
        if frames[0] != 0:
            dE, dn = b.backward(list(frames), self._tile(E, w), self._tile(nu, w), states, before, dL_dX)
            return dE.sum(0), dn.sum(0)
        x0 = states[0]
        g0 = b.state_grad(x0, dL_dX[0])
        gE, gN = np.zeros(len(E)), np.zeros(len(E))
        if w > 1:
            dE, dn, gb = b.backward_before(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1), states[1:],
                                           np.stack([x0, x0]), dL_dX[1:])
            gE, gN, g0 = dE.sum(0), dn.sum(0), g0 + gb[0] + gb[1]
        a, c = b.start_adjoint(E, nu, self.kind, x0, g0)
        return gE + a, gN + c

    def sensitivity(self, frames, E, nu, states, before, d_young, d_poisson, d_before=None) -> np.ndarray:
        """dX/dp (k, w, n, 3) along k directions (θ shared by the window; d_before on the stored states)."""
        b, w = self.backend, len(frames)
        if frames[0] == 0 and self.kind == "moving":  # x_e(θ)'s sensitivity, plus d_before on the offsets
            xe, xm1, x0 = self._moving_states(states, before)
            if self.reference is not None:  # a fixed x_e
                Se = np.zeros((len(d_young), 1) + np.shape(xe))
            else:
                Se = b.start_sensitivity(E, nu, "equilibrium", xe, d_young, d_poisson)[:, None]  # (k, 1, state)
            Sb = np.concatenate([Se, Se], axis=1) + (0.0 if d_before is None else np.asarray(d_before, float))
            S = Sb[:, 1:]
            if w > 1:
                Sd = b.state_sensitivity(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1), states[1:],
                                         np.stack([xm1, x0]), d_young, d_poisson, Sb)
                S = np.concatenate([S, Sd], axis=1)
        elif frames[0] != 0:
            S = b.state_sensitivity(list(frames), self._tile(E, w), self._tile(nu, w), states, before, d_young,
                                    d_poisson, d_before)
        else:
            x0 = states[0]
            S0 = b.start_sensitivity(E, nu, self.kind, x0, d_young, d_poisson)[:, None]  # (k, 1, state)
            S = S0
            if w > 1:
                Sd = b.state_sensitivity(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1), states[1:],
                                         np.stack([x0, x0]), d_young, d_poisson, np.concatenate([S0, S0], axis=1))
                S = np.concatenate([S0, Sd], axis=1)
        self.last_state_sensitivity = S  # (k, w, state): dstates/dp
        return b.decode_sensitivity(states, S)


class StaticWindow:
    """Static identification (``--mode static``): every frame's state is the static equilibrium under that
    frame's controls, solved with θ (stages.sim.static) — no dynamics, no state carried between frames; the
    adjoint and the sensitivities pass through each static solve.  Same interface as :class:`StartWindow`."""

    kind = "equilibrium"

    def __init__(self, backend: WindowBackend):
        self.backend = backend
        self._last: dict[int, np.ndarray] = {}  # frame -> last equilibrium (warm start)

    def forward(self, frames, E, nu, before=None) -> np.ndarray:
        out = []
        for t in frames:
            x = self.backend.start(E, nu, "equilibrium", self._last.get(t), frame=t)
            self._last[t] = x
            out.append(x)
        return np.stack(out)

    def backward(self, frames, E, nu, states, before, dL_dX) -> tuple[np.ndarray, np.ndarray]:
        b = self.backend
        gE, gN = np.zeros(len(E)), np.zeros(len(E))
        for i, t in enumerate(frames):
            a, c = b.start_adjoint(E, nu, "equilibrium", states[i], b.state_grad(states[i], dL_dX[i]), frame=t)
            gE, gN = gE + a, gN + c
        return gE, gN

    def sensitivity(self, frames, E, nu, states, before, d_young, d_poisson, d_before=None) -> np.ndarray:
        b = self.backend
        S = np.stack([b.start_sensitivity(E, nu, "equilibrium", states[i], d_young, d_poisson, frame=t)
                      for i, t in enumerate(frames)], axis=1)  # (k, w, state)
        self.last_state_sensitivity = S
        return b.decode_sensitivity(states, S)


def controls_static(inputs: Callable[[int], object], frames: Sequence[int]) -> bool:
    """Whether no control moves over ``frames``: handle targets, loads and obstacle poses all equal frame 0's."""
    a = inputs(frames[0])
    for t in frames[1:]:
        b = inputs(t)
        if not (all(np.array_equal(p, q) for p, q in zip(a.handle_targets, b.handle_targets))
                and np.array_equal(a.load_forces, b.load_forces) and np.array_equal(a.obstacle_poses, b.obstacle_poses)):
            return False
    return True


# =========================================================================== the window objective
class WindowObjective:
    """L(p) over a window of frames and dL/dp, p = (log E (R,), s (R,)), θ shared by the window:

        X = sim(θ; x_{t0−2}, x_{t0−1}),  L = Σ_t loss_t(X_t),
        dL/dθ = Σ_t (adjoint over the window of dL/dX)_t,  dL/dp by the chain rule of the transforms.

    The observation is first re-anchored with θ: markers are bound to the frame-0 surface simulated with
    θ, Gaussians anchored at their fit frame simulated with θ.  Markers: the binding is held fixed within the
    gradient; images: dL/dθ also carries the anchor's part, (dL/dx_f)(dx_f/dθ) through the fit frame's simulation
    (without it frame f's loss, constant in θ, would still pull θ: docs/results/vision_bias.md).  With
    ``anchor_p`` set (the fit frame's material after a change, AdaptConfig.vision_anchor) the anchor is simulated
    with θ(p_a) instead, dL/dp has no anchor part and dL/dp_a = (dL/dx_f)(dx_f/dp_a) goes to ``last_anchor_g``.
    """

    def __init__(self, backend: WindowBackend, obs: Observation, n_regions: int, poisson_range: tuple[float, float],
                 start: str = "rest"):
        self.backend, self.obs, self.R, self.prange = backend, obs, n_regions, poisson_range
        self.win: Window = StartWindow(backend, start)  # StaticWindow for --mode static
        self.rebind = True
        self.anchor_frame = int(getattr(obs, "fit_frame", 0))
        # The material of the anchor frame, p_a = (log E, s) (2R,): None while it is the window's own θ (no change
        # of material since the anchor frame); set, the anchor x_f(θ(p_a)) is held at it (no anchor part in dL/dp)
        # and, when ``want_anchor_grad``, dL/dp_a of that held anchor is left in ``last_anchor_g``.
        self.anchor_p: np.ndarray | None = None
        self.anchor_own = False  # the online loop estimates p_a (AdaptConfig.vision_anchor "estimated")
        self.want_anchor_grad = False
        self.last_anchor_g: np.ndarray | None = None
        self._held: tuple[np.ndarray, np.ndarray] | None = None  # (p_a, x_f(θ(p_a))) of the last held anchor

    def anchor_positions(self, E: np.ndarray, nu: np.ndarray) -> np.ndarray:
        """The anchor frame (0 for markers, the Gaussians' fit frame for images) simulated with θ under the start
        convention (frame 0 = x_0(θ); a moving start: x_e(θ), the offsets being the window's), positions (n, 3)."""
        k = self.anchor_frame + 1
        aE, anu, X = getattr(self, "_anchor_states", (None, None, None))
        if not (getattr(self.win, "memo", False) and X is not None and np.array_equal(aE, E)
                and np.array_equal(anu, nu)):  # (memo: the last anchor of this θ, the same floats to rebind at)
            X = self.win.forward(list(range(k)), E, nu, None)
            self._anchor_states = (np.array(E, float), np.array(nu, float), X)  # reused by the anchor's adjoint
        return self.backend.decode(X[-1:])[0]

    def _anchor_adjoint(self, E: np.ndarray, nu: np.ndarray, ga: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν) (R,) through the anchor x_f(θ): dL/dx_f = ``ga`` (n, 3) back through the simulation of
        frames 0..f under the start convention."""
        k = self.anchor_frame + 1
        aE0, anu0, sa = getattr(self, "_anchor_states", (None, None, None))
        if sa is None or not (np.array_equal(aE0, E) and np.array_equal(anu0, nu)):
            sa = self.win.forward(list(range(k)), E, nu, None)
        dXa = np.zeros((k,) + self.backend.decode(sa[-1:]).shape[1:])
        dXa[-1, :len(ga)] = ga
        return self.win.backward(list(range(k)), E, nu, sa, None, dXa)

    def simulate(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray) -> tuple[np.ndarray, float]:
        """(states (w, …), forward seconds) of ``frames`` simulated with θ(p) from ``before``: what :meth:`__call__`
        simulates, without the observation's loss (no render)."""
        E, nu = theta_from_params(p[:self.R], p[self.R:], self.prange)
        t0 = time.perf_counter()
        states = self.win.forward(list(frames), E, nu, before)
        return states, time.perf_counter() - t0

    def __call__(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, need_grad: bool = True,
                 lead: int = 0):
        """(states (w, …), per-frame losses (w − lead,), dL/dp (2R,) or None, (forward_s, backward_s, loss_s)).

        ``lead``: the first ``lead`` frames are a lead-in — simulated with θ (and differentiated through) but not
        observed, L = Σ_{t ≥ frames[lead]} loss_t: the observed frames start from states simulated with θ rather
        than from the stored past (AdaptConfig.lead_in)."""
        R, backend = self.R, self.backend
        E, nu = theta_from_params(p[:R], p[R:], self.prange)
        t0 = time.perf_counter()
        rebind = self.rebind
        held = None  # θ of a held anchor (anchor_p)
        self.last_anchor_g = None
        if rebind and self.anchor_p is not None:
            pa = np.asarray(self.anchor_p, float)
            held = theta_from_params(pa[:R], pa[R:], self.prange)
            if self._held is None or not np.array_equal(self._held[0], pa):
                self._held = (pa.copy(), self.anchor_positions(*held))
            self.obs.rebind(self._held[1])
            rebind = False  # the anchor moves with p_a, not with the window's θ
        elif rebind:
            self.obs.rebind(self.anchor_positions(E, nu))
        states = self.win.forward(list(frames), E, nu, before)
        X = backend.decode(states)
        t1 = time.perf_counter()
        losses, dX = self.obs.loss(frames[lead:], X[lead:])
        if lead:
            dX = np.concatenate([np.zeros((lead,) + dX.shape[1:]), dX])
        t2 = time.perf_counter()
        g = None
        if need_grad:
            dE, dnu = self.win.backward(list(frames), E, nu, states, before, dX)
            ga = getattr(self.obs, "anchor_grad", None)  # images: the anchor x_f(θ) moves the Gaussians too
            if rebind and ga is not None and np.any(ga):
                aE, anu = self._anchor_adjoint(E, nu, ga)
                dE, dnu = dE + aE, dnu + anu
                if self.want_anchor_grad:  # the anchor's part alone, dL/dp_a at p_a = p
                    self.last_anchor_g = np.concatenate(chain_params(aE, anu, E, p[R:], self.prange))
            if held is not None and self.want_anchor_grad and ga is not None:
                self.last_anchor_g = np.concatenate(chain_params(*self._anchor_adjoint(*held, ga), held[0],
                                                                 np.asarray(self.anchor_p, float)[R:], self.prange))
            g = np.concatenate(chain_params(dE, dnu, E, p[R:], self.prange))
        t3 = time.perf_counter()
        return states, losses, g, (t1 - t0, t3 - t2, t2 - t1)


# =========================================================================== Gauss–Newton window
class GNWindow:
    """Residuals and their Jacobian over a window for the Gauss–Newton estimator (stages.estimator).

    Unknowns p = (log E (R), s (R) when ν is fitted, c (k_c) when the starting states are corrected): θ as
    for Adam (ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s)) and the coefficients of a correction of the two states
    before the window, before + Σ_j c_j D_j (D (k_c, 2, …), the reduced space's unit vectors).
    r(p) = the observations' residuals of every window frame (markers or pixels);
    ∂r/∂p = (∂r/∂X)(dX/dp) with dX/dp the forward sensitivities of the window (stages.sim.sensitivity,
    stages.subspace.sensitivity): ∂X/∂log E = E ∂X/∂E, ∂X/∂s = ν'(s) ∂X/∂ν.
    """

    #: StartWindow.memo: the change test's one-frame forward, the linearisation's window (the frames the last
    #: evaluation simulated at this θ from the same states; with --substeps its substeps stitched from those
    #: forwards, window_backends.Substepped._stitch) and the anchor of the last θ are not simulated again — the
    #: same estimates to the tolerance of the steps' solves (tests/test_gn_speed*.py).  False: every evaluation
    #: simulates its window and anchor — the slow twin
    memo: bool = True
    #: images: the online change test (adapt._online_gn) judges the new frame by the residuals of the window's first
    #: linearisation at the predicted θ, which the solve then starts from (its last frame: the state and render the
    #: test would make, to rounding — one render of the new frame less per frame; the linearisation is made again
    #: only when a change is declared).  False (and markers, whose residuals cost nothing): the test simulates and
    #: renders the new frame by itself first — the slow twin (tests/test_gn_speed.py)
    shared_innovation: bool = True
    #: images (adapt._online_gn): numpy's BLAS (OpenBLAS) held to this many threads over the online loop — its
    #: vector and thin-matrix products over the window's ~10⁵–10⁶ pixel residuals (the cost's dot products, Jᵀ W J,
    #: Jᵀ W r) gain nothing from threads, which wait for a core of their own between calls: on the shared 2-core
    #: machine 13 ms against 1 ms per cost evaluation, ≈0.2 s of gn's 0.9 s per frame at 2 iterations (Bar-like
    #: case, by hand, 2026-11-25; bench/adapt_speed.py's row "jvp blas-threads").  None: BLAS's threads as the
    #: process has them — the twin the bench compares
    blas_threads: int | None = 1
    #: images, forward-mode J (adapt._gn_solve): a trial step of an iteration before the last is evaluated with the
    #: Jacobian (:meth:`evaluate`'s ``ahead``) — one pass that renders and differentiates, instead of a render for
    #: the trial and, once it is accepted (nearly always), the same window simulated, rendered and differentiated
    #: again for the next linearisation; a rejected trial's Jacobian is wasted.  False: the trial renders alone — the
    #: slow twin (the same floats, tests/test_gn_trial_jacobian.py)
    trial_jacobian: bool = True
    _LINEARISATION = ("last_jac", "last_frames", "last_state_sens")  # (what a linearisation sets, a trial not)
    _EVALUATION = ("last_states", "last_before", "last_p", "last_rs")

    def __init__(self, objective: "WindowObjective", fit_poisson: bool, s_fixed: np.ndarray):
        self.obj, self.fit_poisson, self.s_fixed = objective, fit_poisson, s_fixed
        self.young_range: tuple[float, float] | None = None  # bounds of E (Pa), [material] young_range
        self.rebind_anchor = True  # re-anchor the observations at x_anchor(θ) (until a material change)
        self.rebind_next = True  # re-anchor at the next linearisation
        # images: jacobian() leaves the θ columns, which binding_jacobian() differences jointly, unrendered (False:
        # render them too, as binding_jacobian's subtrahend — the slow twin the tests hold this to)
        self.skip_joint = True
        self.R = objective.R
        self.k_theta = self.R * (2 if fit_poisson else 1)
        self.times = [0.0, 0.0, 0.0]  # forward, sensitivity, residuals/render
        # AdaptConfig.gn_trust: a last Gauss–Newton step of at most this many posterior σ is taken without
        # evaluating the window there (:meth:`extrapolate`; 0: every step is evaluated, Levenberg–Marquardt)
        self.trust = 0.0
        self.prediction: tuple[dict, float] | None = None  # ({frame: r̂ at the last estimate}, s² σ²) of extrapolate
        self.last_prediction_error: float | None = None  # its prediction_error, where the last solve checked one
        self.last_states = None
        self.last_frames: list[np.ndarray] = []  # per frame residuals of the last evaluation
        self.last_jac: list[np.ndarray] = []
        self._ahead: tuple | None = None  # a trial's evaluation with the Jacobian (:meth:`evaluate`'s ``ahead``)

    def blas_limit(self, kind: str):
        """The context that holds numpy's BLAS to :attr:`blas_threads` threads for observations of ``kind``
        ("vision"; a no-op for markers, or with blas_threads None)."""
        if kind != "vision" or self.blas_threads is None:
            return contextlib.nullcontext()
        return threadpool_limits(limits=int(self.blas_threads), user_api="blas")

    def theta(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(E, ν, s) from the unknowns."""
        R = self.R
        s = p[R:2 * R] if self.fit_poisson else self.s_fixed
        E, nu = theta_from_params(p[:R], s, self.obj.prange)
        return E, nu, s

    def evaluate(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, D: np.ndarray | None,
                 need_jac: bool, rebind: bool = True, ahead: bool = False):
        """(r (m,), J (m, k) or None); the window's states are kept in ``last_states``.

        ``ahead`` (with need_jac False: a trial step that the solve linearises at next when it is accepted,
        adapt._gn_solve): images with the forward-mode Jacobian (:attr:`trial_jacobian`) make the Jacobian here
        too, in the one pass that gives the residuals (the same floats), and keep it; the next call, when it asks
        for the Jacobian at the same p, frames, ``before`` and D, returns it without simulating or rendering the
        window again.  The attributes a linearisation sets (``last_jac``, ``last_frames``, ``last_state_sens``)
        stay those of the last linearisation until then, as after a trial evaluated without it."""
        kept, self._ahead = self._ahead, None
        if need_jac and kept is not None and kept[0] == (list(frames), rebind) and kept[2] is before \
                and kept[3] is D and np.array_equal(kept[1], p):
            for name, v in kept[5].items():
                setattr(self, name, v)
            return kept[4]
        obs = self.obj.obs
        if not (ahead and not need_jac and self.trial_jacobian and getattr(obs, "uses_jvp", None) is not None
                and obs.uses_jvp()):
            return self._evaluate(frames, p, before, D, need_jac, rebind)
        lin = {name: getattr(self, name, None) for name in self._LINEARISATION}
        try:
            out = self._evaluate(frames, p, before, D, True, rebind)
            state = {name: getattr(self, name, None) for name in self._LINEARISATION + self._EVALUATION}
        finally:  # (as a trial without the Jacobian leaves them)
            for name, v in lin.items():
                setattr(self, name, v)
        self._ahead = ((list(frames), rebind), np.array(p, float), before, D, out, state)
        return out[0], None

    def _evaluate(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, D: np.ndarray | None,
                  need_jac: bool, rebind: bool = True):
        """:meth:`evaluate` itself."""
        obj, R = self.obj, self.R
        backend = obj.backend
        E, nu, s = self.theta(p)
        c = p[self.k_theta:]
        b = before if D is None or not len(c) else before + np.tensordot(c, D, axes=1)
        if hasattr(obj.win, "memo"):  # the windows continue the trajectories they remember (StartWindow.memo)
            obj.win.memo = bool(self.memo)
        t0 = time.perf_counter()
        anchored = rebind and obj.rebind and self.rebind_anchor
        smooth = getattr(obj.obs, "binding_jacobian", None) is not None  # markers: d binding/dθ goes into J
        x_anchor = None
        if anchored and (smooth or (need_jac and self.rebind_next)):
            # re-anchored at every evaluation (r(p) is one smooth function of p; J includes the binding's or the
            # anchor's derivative: markers' binding_jacobian, the images' anchored Gaussians)
            self.rebind_next = False
            x_anchor = obj.anchor_positions(E, nu)
            obj.obs.rebind(x_anchor)
        states = obj.win.forward(list(frames), E, nu, b)
        X = backend.decode(states)
        t1 = time.perf_counter()
        # images with a forward-mode renderer: the residuals come with J from one pass (the same floats)
        jvp = need_jac and getattr(obj.obs, "uses_jvp", None) is not None and obj.obs.uses_jvp()
        rs = None if jvp else obj.obs.residuals(frames, X)
        t2 = time.perf_counter()
        self.times[0] += t1 - t0
        self.times[2] += t2 - t1
        self.last_states, self.last_before, self.last_p, self.last_rs = states, b, p.copy(), rs
        if not need_jac:
            return np.concatenate(rs), None
        k = len(p)
        de, dn = np.zeros((k, R)), np.zeros((k, R))
        de[np.arange(R), np.arange(R)] = E  # ∂E/∂log E
        if self.fit_poisson:
            lo, hi = self.obj.prange
            sig = 1.0 / (1.0 + np.exp(-s))
            dn[R + np.arange(R), np.arange(R)] = (np.asarray(hi) - np.asarray(lo)) * sig * (1 - sig)
        db = None
        if D is not None and len(c):
            db = np.zeros((k,) + np.shape(before))
            db[self.k_theta:] = D
        dX = obj.win.sensitivity(list(frames), E, nu, states, b, de, dn, db)
        t3 = time.perf_counter()
        self.last_state_sens = obj.win.last_state_sensitivity  # (k, w, …) of the window's states
        dXa = None
        if x_anchor is not None and smooth:
            # the anchor frame's own sensitivity (frame 0 = x_0(θ), or the fit frame simulated from it), from the
            # states anchor_positions simulated for this θ
            ka = obj.anchor_frame + 1
            aE, anu, sa = getattr(obj, "_anchor_states", (None, None, None))
            if sa is None or not (np.array_equal(aE, E) and np.array_equal(anu, nu)):
                sa = obj.win.forward(list(range(ka)), E, nu, None)
            dXa = obj.win.sensitivity(list(range(ka)), E, nu, sa, None, de, dn)[:, -1]
        if jvp:  # exact J (anchor included) and the residuals in one forward-mode pass; Jᵀ W r from it
            rs, Js = obj.obs.residuals_and_jacobian(frames, X, dX, dXa)
            t4 = time.perf_counter()
            self.times[1] += t3 - t2
            self.times[2] += t4 - t3
            self.last_rs, self.last_frames, self.last_jac = rs, rs, Js
            r, J = np.concatenate(rs), np.concatenate(Js, axis=0)
            return r, J  # J is exact: gauss_newton forms Jᵀ W r from it (the autograd product)
        if x_anchor is not None and smooth and obj.obs.kind == "vision" and self.skip_joint:
            # binding_jacobian differences the θ columns jointly (positions and anchor): jacobian skips them
            Js = obj.obs.jacobian(frames, X, dX, skip=range(self.k_theta))
        else:
            Js = obj.obs.jacobian(frames, X, dX)
        if dXa is not None:
            Js = [J + Jb for J, Jb in zip(Js, obj.obs.binding_jacobian(frames, X, x_anchor, dXa))]
        t4 = time.perf_counter()
        self.times[1] += t3 - t2
        self.times[2] += t4 - t3
        self.last_frames, self.last_jac = rs, Js
        exact = getattr(obj.obs, "exact_jtwr", None)
        if exact is None:
            return np.concatenate(rs), np.concatenate(Js, axis=0)
        sizes = np.cumsum([len(x) for x in rs])[:-1]

        def jtw(W):  # Jᵀ W r exactly (autograd through the renderer), J only approximate
            t5 = time.perf_counter()
            g = exact(frames, X, dX, rs, np.split(W, sizes))
            self.times[2] += time.perf_counter() - t5
            return g
        return np.concatenate(rs), np.concatenate(Js, axis=0), jtw

    def extrapolate(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, D: np.ndarray | None,
                    scale2: float, r_lin: np.ndarray | None = None, J_lin: np.ndarray | None = None) -> None:
        """Take the window to the unknowns p from the last linearisation p_l by first order instead of simulating
        and rendering it there (the one-evaluation path, :attr:`trust`):

            X_t(p) = X_t(p_l) + S_t (p − p_l),   r_t(p) = r_t(p_l) + J_t (p − p_l),   before(p) = before + Σ c_j D_j

        (S the window's state sensitivities, J the residuals' Jacobian; the corrected states before the window are
        exact, linear in c).  ``last_*`` then describe the window at p, the window's trajectory is remembered for
        the next frame's (StartWindow.remember; with one substep per frame), and the predicted residuals are kept in
        :attr:`prediction` for :meth:`prediction_error` (``scale2`` = σ² s², the data term's variance).  ``r_lin``
        (m,), ``J_lin`` (m, k): the last evaluation's residuals and Jacobian concatenated, when at hand (one product
        instead of one per frame)."""
        self._ahead = None  # (the observations are bound at p below, the window remembered there)
        dp = np.asarray(p, float) - self.last_p
        S = self.last_state_sens  # (k, w, …)
        states = self.last_states + np.tensordot(dp, S, axes=1)
        c = p[self.k_theta:]
        b = before if D is None or not len(c) else before + np.tensordot(c, D, axes=1)
        if r_lin is None:
            rs = [r + J @ dp for r, J in zip(self.last_frames, self.last_jac)]
        else:
            rs = np.split(r_lin + J_lin @ dp, np.cumsum([len(r) for r in self.last_frames])[:-1])
        self.last_states, self.last_before, self.last_p, self.last_rs = states, b, np.array(p, float), rs
        E, nu, _ = self.theta(p)
        if hasattr(self.obj.win, "remember") and getattr(self.obj.backend, "S", 1) == 1:
            # (with --substeps S > 1 not: the window's sensitivities need a substep trajectory through its states,
            # which no forward made for these — the next window simulates from the stored ones instead)
            self.obj.win.remember(list(frames), E, nu, b, states)
        obj = self.obj
        if obj.rebind and self.rebind_anchor and getattr(obj.obs, "binding_jacobian", None) is not None:
            # the observations anchored at the estimate, as an evaluation there leaves them (what the next frame's
            # change test renders with; its linearisation then finds this anchor remembered, StartWindow.memo)
            obj.obs.rebind(obj.anchor_positions(E, nu))
        self.prediction = ({int(t): r for t, r in zip(frames, rs)}, float(scale2))

    def prediction_error(self, frames: Sequence[int], sigma: float, huber: float | None) -> float:
        """How far the last :meth:`extrapolate`'s first-order residuals missed: over the frames of the last
        evaluation (now at that estimate, simulated and rendered) that it predicted, (C_data(r) − C_data(r̂)) / (σ² s²)
        — the data term's cost at the actual residuals less that at the predicted ones (estimator.robust_cost), in
        the units of the Gauss–Newton cost (a step's decrease there is ½ its size² in posterior σ).  0 when nothing
        was predicted; the prediction is used once."""
        pred, self.prediction = self.prediction, None
        if pred is None:
            return 0.0
        got = dict(zip((int(t) for t in frames), self.last_frames))
        common = [t for t in pred[0] if t in got and len(got[t]) == len(pred[0][t])]
        if not common:
            return 0.0
        a = sum(robust_cost(got[t], sigma, huber) for t in common)
        b = sum(robust_cost(pred[0][t], sigma, huber) for t in common)
        return (a - b) / pred[1]


MODEL_ERROR_SPREAD_MAX = 6.0
"""Largest factor by which a weakly informed region's model-error floor exceeds ``model_error``.  On the two-region
beam the stiff half's information is ~1 % of the body's (the √ ratio alone would give 20 e), and its loss minimum
lies 0.79–1.12 E_true over four discretisations (docs/results/region_sweep.md): 6 e = 12 % keeps each of them
within 2σ without the 40 % band of 20 e."""


def model_error_floors(model_error: float, information: np.ndarray) -> np.ndarray:
    """Per-region relative model-error floor of E (R,):

        e_i = e · min(√(max_j I_j / I_i), MODEL_ERROR_SPREAD_MAX),   I_i = (Jᵀ W J)_ii

    I_i is the data's information on log E_i (R,) (adapt: Jᵀ W J summed over the run's windows so far, or the
    offline fit's).  A systematic error δ of the model's residuals (the discretisation's) biases a least-squares
    estimate by (Jᵀ J)⁻¹ Jᵀ δ, ≈ |δ| / √I_i for region i: a region the data tell weakly carries that error many
    times over (the two-region beam's stiff half: its loss minimum lies 0.79–1.12 E_true over four
    discretisations, docs/results/region_sweep.md).  e (``model_error``, calibrated on single-region scenes) is the
    best-informed region's floor; one region, equal information, or none at all: e for every region."""
    info = np.asarray(information, np.float64).reshape(-1)
    top = float(np.max(info)) if info.size else 0.0
    if not top > 0:
        return np.full(info.size, float(model_error))
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.sqrt(np.where(info > 0, top / info, np.inf))
    return float(model_error) * np.minimum(ratio, MODEL_ERROR_SPREAD_MAX)


def sigma_from_cov(gn: GNWindow, p: np.ndarray, cov: np.ndarray, model_error: float | np.ndarray = 0.0,
                   model_error_poisson: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """σ of E and of ν per region from the covariance of p (k, k):

        σ_E = E √(σ²_logE + e_i²),   σ_ν = √((ν'(s) σ_s)² + e_ν²)  (0 when ν is held),

    e_i = ``model_error`` (one for every region, or per region (R,): :func:`model_error_floors`), e_ν =
    ``model_error_poisson`` (the error of E, relative, and of ν that the discretisation itself makes, added in
    quadrature: it does not average out over frames).  A
    parameter held at a bound of its range ([material] young_range, poisson_range)
    reports at least the σ of a uniform prior over the range (stages.estimator.bounded_sigma): there the data
    do not locate it (and the sigmoid's slope ν'(s) → 0 would shrink σ_ν to nothing)."""
    R = gn.R
    E, nu, s = gn.theta(p)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    s_log = np.sqrt(sd[:R] ** 2 + np.asarray(model_error, np.float64) ** 2)
    if gn.young_range is not None:
        s_log = bounded_sigma(np.log(E), s_log, np.log(gn.young_range[0]), np.log(gn.young_range[1]))
    sE = E * s_log
    if gn.fit_poisson:
        lo, hi = gn.obj.prange
        sig = 1.0 / (1.0 + np.exp(-s))
        sN = np.hypot((np.asarray(hi) - np.asarray(lo)) * sig * (1 - sig) * sd[R:2 * R], float(model_error_poisson))
        sN = bounded_sigma(nu, sN, lo, hi)
    else:
        sN = np.zeros(R)
    return sE, np.broadcast_to(sN, (R,)).astype(float)


STATE_PRIOR_SCALE = 0.5
"""--state-correction states: prior σ of each correction coordinate, as a fraction of that coordinate's RMS
excursion over the stored frames (0.5 kept a constant-E cable segment within ±1 %, 0.05 let it drift by 2 % and
lagged after a step of E: measured on a P2-truth capture, docs/results/estimator.md)."""


def state_directions(backend, stored: dict, t0: int, first: int, scale: float, theta=None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """Correction directions of the two states before a window starting at t0 and the prior σ of each
    coefficient.  Reduced space: unit vectors of z_{t0−2} and z_{t0−1}, (2r, 2, r); full space: the lowest
    vibration modes φ_i (K φ = λ M φ at the start state) of each, (2m, 2, n, 3).  σ = ``scale`` × the RMS of that
    coordinate's excursion over the stored frames (its typical motion).  None when a state before the window is
    not a stored frame (frames before t = 1: the start state is known)."""
    if t0 < 1 or any(max(t, 0) not in stored for t in (t0 - 2, t0 - 1)):
        return None
    past = np.stack([stored[t] for t in sorted(stored) if t < t0])
    if backend.space == "reduced":
        basis = np.eye(backend.dim).reshape(backend.dim, backend.dim)  # (m, r)
    else:
        basis = backend.modes(stored[0], *theta)  # (m, n, 3), mass-orthonormal
    m = len(basis)
    B = basis.reshape(m, -1)
    coords = (past - stored[0]).reshape(len(past), -1) @ (B.T if backend.space == "reduced" else
                                                            (B * backend.mass_diag[None]).T)
    rms = np.sqrt(np.mean(coords * coords, axis=0))
    rms = np.maximum(rms, 1e-3 * rms.max() + 1e-300)
    D = np.zeros((2 * m, 2) + basis.shape[1:])
    for i in range(2):
        D[i * m:(i + 1) * m, i] = basis
    return D, scale * np.concatenate([rms, rms])


def past_directions(sens: dict, t0: int, k_theta: int, sigma: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Correction directions of the two states before a window starting at t0 along their sensitivities to θ
    (``sens``: frame → d state/dp (k_θ, …), propagated through every window since frame 0): a correction
    c (k_θ,) moves them by Σ_j c_j ∂x/∂p_j — to first order, the past re-simulated with p + c.  Returns
    (D (k_θ, 2, …), prior σ (k_θ,)), or None when those sensitivities are not known (frames before the range)."""
    a, b = max(t0 - 2, 0), max(t0 - 1, 0)
    if t0 < 1 or a not in sens or b not in sens:
        return None
    return np.stack([sens[a], sens[b]], axis=1), np.full(k_theta, float(sigma))
