"""Window backends of ``rsl adapt``: the full-space FEM (stages.sim) and the neural subspace (stages.subspace)
simulate a window of frames and run its adjoint; ``Substepped`` runs S implicit steps of Δt/S per frame; the solve
guard stops a run whose states collapse (inverted elements, non-finite values)."""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stages.errors import RslError


class FullSpace:
    """Full-space FEM window simulation and adjoint (stages.sim.scene). State = positions (n, 3)."""

    space = "full"

    def __init__(self, scene, inputs: Callable[[int], object], solver: str):
        self.scene, self.inputs, self.solver = scene, inputs, solver
        self.dim = 0
        self.step_kw: dict = {}  # extra keywords of each Newton step (stages.sim.scene.step), e.g. rtol

    @property
    def rest_state(self) -> np.ndarray:
        return np.asarray(self.scene.rest)

    def decode(self, states: np.ndarray) -> np.ndarray:
        return states

    def z(self, states: np.ndarray) -> np.ndarray:
        return np.zeros((len(states), 0))

    def records(self) -> tuple:
        """What the forwards carry from one solve to the next: nothing (each Newton solve starts from its own
        states; :meth:`ReducedSpace.records` has a memory to keep)."""
        return ()

    def restore_records(self, saved: tuple) -> None:
        pass

    def forward(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray,
                before: np.ndarray) -> np.ndarray:
        """States (w, n, 3) of ``frames`` from ``before`` = [x_{t0−2}, x_{t0−1}]; young/poisson (w, R)."""
        from stages.sim.scene import simulate

        return np.asarray(simulate(self.scene, [self.inputs(t) for t in frames], young, poisson,
                                   x_prev=before[1], x_prev2=before[0], solver=self.solver, **self.step_kw))

    def backward(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, states: np.ndarray,
                 before: np.ndarray, dL_dX: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν), each (w, R): one row per window frame's θ."""
        from stages.sim.scene import window_adjoint

        g = window_adjoint(self.scene, [self.inputs(t) for t in frames], young, poisson, states, before, dL_dX)
        return np.asarray(g["young"]), np.asarray(g["poisson"])

    def sensitivity(self, frames, young, poisson, states, before, d_young, d_poisson, d_before=None):
        """dX/dp (k, w, n, 3) along k directions (stages.sim.sensitivity)."""
        from stages.sim.sensitivity import window_sensitivity

        return window_sensitivity(self.scene, [self.inputs(t) for t in frames], young, poisson, states, before,
                                  d_young, d_poisson, d_before, solver=self.solver)

    state_sensitivity = sensitivity

    @property
    def mass_diag(self) -> np.ndarray:
        """Lumped mass per DOF (3n,) kg."""
        return np.repeat(np.asarray(self.scene.masses, float), 3)

    def modes(self, x0: np.ndarray, young, poisson, count: int = 12) -> np.ndarray:
        """The ``count`` lowest vibration modes (count, n, 3) at x0: K φ = λ M φ with K the elastic + handle +
        contact Hessian (PSD-projected) at θ = (young, poisson), mass-orthonormal (φᵀ M φ = 1); computed once."""
        if getattr(self, "_modes", None) is None:
            import scipy.sparse as sp
            from scipy.sparse.linalg import eigsh

            from stages.sim.scene import hessian

            sc = self.scene
            H = hessian(sc, self.inputs(0), x0, x0, young, poisson, project=True)
            Md = sp.diags(self.mass_diag)
            K = (H - Md / sc.dt ** 2).tocsc()  # drop the inertia term of Φ
            k = min(count, 3 * sc.n_vertices - 2)
            # ARPACK's own start vector is random: the modes (their signs, and within the bending pairs of a
            # symmetric cross-section their rotation) and every pose, prior and estimate written in them would
            # differ between runs; a fixed one gives the same modes on every run
            v0 = np.random.default_rng(0).standard_normal(K.shape[0])
            _, vec = eigsh(K, k=k, M=Md.tocsc(), sigma=0.0, which="LM", v0=v0)
            self._modes = vec.T.reshape(k, -1, 3)
        return self._modes

    def decode_sensitivity(self, states, S):
        return S

    def backward_before(self, frames, young, poisson, states, before, dL_dX):
        """(dL/dE (w, R), dL/dν (w, R), dL/d before (2, n, 3))."""
        from stages.sim.scene import window_adjoint

        g = window_adjoint(self.scene, [self.inputs(t) for t in frames], young, poisson, states, before, dL_dX)
        return np.asarray(g["young"]), np.asarray(g["poisson"]), np.asarray(g["x_before"])

    def state_grad(self, state: np.ndarray, dL_dx: np.ndarray) -> np.ndarray:
        return dL_dx

    def start(self, young, poisson, kind: str, init=None, frame: int = 0) -> np.ndarray:
        """x_0 (n, 3): the rest shape or the static equilibrium under the frame's inputs (stages.sim.static)."""
        from stages.sim.static import start_state

        kw = {} if kind == "rest" else {"x_init": init, "solver": self.solver}
        return np.asarray(start_state(self.scene, self.inputs(frame), young, poisson, kind, **kw))

    def start_sensitivity(self, young, poisson, kind: str, x0, d_young, d_poisson, frame: int = 0) -> np.ndarray:
        """dx_0/dp (k, n, 3) along k directions of θ (0 for the rest start)."""
        from stages.sim.static import equilibrium_sensitivity

        k = len(d_young)
        if kind == "rest":
            return np.zeros((k,) + np.shape(x0))
        S = equilibrium_sensitivity(self.scene, self.inputs(frame), young, poisson, x0, solver=self.solver)
        return np.tensordot(np.concatenate([d_young, d_poisson], axis=1), S, axes=1)

    def start_adjoint(self, young, poisson, kind: str, x0, dL_dx0, frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν) (R,) through x_0(θ), for dL/dx_0 (n, 3)."""
        from stages.sim.static import equilibrium_adjoint

        if kind == "rest":
            return np.zeros(len(young)), np.zeros(len(young))
        g = equilibrium_adjoint(self.scene, self.inputs(frame), young, poisson, x0, dL_dx0, solver=self.solver)
        return np.asarray(g["young"]), np.asarray(g["poisson"])


class ReducedSpace:
    """Reduced window simulation and adjoint (stages.subspace.ReducedModel). State = z (r,)."""

    space = "reduced"

    def __init__(self, model, inputs: Callable[[int], object]):
        self.model, self._inputs = model, inputs
        self.dim = int(model.dim)
        self._rin: dict[int, object] = {}
        self.rtol = 1e-8  # relative residual of each reduced Newton step
        self._decoded: list[tuple[np.ndarray, np.ndarray]] = []  # the latest (z, φ(z)) pairs, newest last

    def inputs(self, t: int):
        """ReducedInputs of frame t (cached: the projection of loads is done once)."""
        if t not in self._rin:
            self._rin[t] = self.model.reduce_inputs(self._inputs(t))
        return self._rin[t]

    @property
    def rest_state(self) -> np.ndarray:
        return np.asarray(self.model.z_rest)

    def decode(self, states: np.ndarray) -> np.ndarray:
        """φ(z) (…, n, 3) of states z (…, r); the same z as one of the last few calls (e.g. a forward's states, decoded
        by the solve guard and then by the observation) gives that call's floats again without decoding."""
        z = np.asarray(states)
        for zc, xc in reversed(self._decoded):
            if zc.shape == z.shape and np.array_equal(zc, z):
                return xc.copy()
        x = np.asarray(self.model.decode(z))
        self._decoded.append((np.array(z, copy=True), x.copy()))
        del self._decoded[:-4]
        return x

    def z(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)

    def records(self) -> tuple:
        """What the forwards carry from one solve to the next (the reduced Newton's memory,
        ReducedModel.solver_memory): :meth:`restore_records` puts it back (adapt's change probes)."""
        return (self.model.solver_memory(),)

    def restore_records(self, saved: tuple) -> None:
        self.model.restore_solver_memory(saved[0])

    def forward(self, frames, young, poisson, before):
        return np.asarray(self.model.simulate([self.inputs(t) for t in frames], young, poisson,
                                              z_prev=before[1], z_prev2=before[0], rtol=self.rtol))

    def backward(self, frames, young, poisson, states, before, dL_dX):
        """dL/dX → dL/dZ = Jᵀ dL/dX → reduced adjoint over the window → (dL/dE, dL/dν) (w, R)."""
        g = self.model.window_adjoint([self.inputs(t) for t in frames], young, poisson, states, before,
                                      dL_dX=dL_dX)
        return np.asarray(g["young"]), np.asarray(g["poisson"])

    def sensitivity(self, frames, young, poisson, states, before, d_young, d_poisson, d_before=None):
        """dX/dp (k, w, n, 3) = J(z_t) dz_t/dp along k directions (stages.subspace.sensitivity)."""
        from stages.subspace.sensitivity import decode_sensitivity, window_sensitivity

        S = window_sensitivity(self.model, [self.inputs(t) for t in frames], young, poisson, states, before,
                               d_young, d_poisson, d_before)
        return decode_sensitivity(self.model, states, S)

    def state_sensitivity(self, frames, young, poisson, states, before, d_young, d_poisson, d_before=None):
        """dZ/dp (k, w, r)."""
        from stages.subspace.sensitivity import window_sensitivity

        return window_sensitivity(self.model, [self.inputs(t) for t in frames], young, poisson, states, before,
                                  d_young, d_poisson, d_before)

    def decode_sensitivity(self, states, S):
        from stages.subspace.sensitivity import decode_sensitivity

        return decode_sensitivity(self.model, states, S)

    def backward_before(self, frames, young, poisson, states, before, dL_dX):
        """(dL/dE (w, R), dL/dν (w, R), dL/d before (2, r))."""
        g = self.model.window_adjoint([self.inputs(t) for t in frames], young, poisson, states, before,
                                      dL_dX=dL_dX)
        return np.asarray(g["young"]), np.asarray(g["poisson"]), np.asarray(g["z_before"])

    def state_grad(self, state: np.ndarray, dL_dx: np.ndarray) -> np.ndarray:
        return self.model.jacobian_transpose(state, dL_dx)

    def start(self, young, poisson, kind: str, init=None, frame: int = 0) -> np.ndarray:
        """z_0 (r,): ψ(rest) or the reduced static equilibrium under the frame's inputs (stages.sim.static)."""
        from stages.sim.static import reduced_equilibrium

        if kind == "rest":
            return self.rest_state
        return np.asarray(reduced_equilibrium(self.model, self._inputs(frame), young, poisson, z_init=init))

    def start_sensitivity(self, young, poisson, kind: str, z0, d_young, d_poisson, frame: int = 0) -> np.ndarray:
        """dz_0/dp (k, r)."""
        from stages.sim.static import reduced_equilibrium_sensitivity

        if kind == "rest":
            return np.zeros((len(d_young),) + np.shape(z0))
        S = reduced_equilibrium_sensitivity(self.model, self._inputs(frame), young, poisson, z0)  # (2R, r)
        return np.concatenate([d_young, d_poisson], axis=1) @ S

    def start_adjoint(self, young, poisson, kind: str, z0, dL_dz0, frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
        from stages.sim.static import reduced_equilibrium_adjoint

        if kind == "rest":
            return np.zeros(len(young)), np.zeros(len(young))
        g = reduced_equilibrium_adjoint(self.model, self._inputs(frame), young, poisson, z0, dL_dz=dL_dz0)
        return np.asarray(g["young"]), np.asarray(g["poisson"])


class Substepped:
    """A backend whose window frames are ``S`` implicit-Euler substeps of Δt/S each (``--substeps S``), run by
    ``fine``, a backend of the same space on the scene with time step Δt/S (Δt = 1/fps).  Substep k = 1..S of
    frame t takes the inputs of the fractional frame t − 1 + k/S (frame t's own at k = S) and θ of frame t, as
    stages.sim.static.simulate_from_start; a window's states are its frames' (the last substep of each).

    Restart.  A frame's next step needs the last two *substep* states (x_{t−1/S}, x_t), but the windows pass the
    two stored *frame* states before = [x_{t0−2}, x_{t0−1}].  The substep state before x_{t0−1} is taken as
        x_{t0−1−1/S} = x_{t0−1} + (x_{t0−2} − x_{t0−1}) / S + δ_{t0−1},
    δ_t the offset of the true last substep from that interpolation, recorded by the forward that produced x_t
    (exact: the restarted window repeats the uninterrupted simulation bit for bit) and held fixed in derivatives
    (so a correction of both stored states moves the substep state by the interpolation of the two).  δ = 0 at
    frame 0 (x_{−1} = x_{−2} = x_0: the start is at rest).  A state stored under ``commit`` keeps its δ when the
    stored value is later replaced by a corrected one.
    Gradients: dL/dθ_t sums over frame t's substeps; dL/d before follows from the map above."""

    KEEP = 6  # recorded (x_{t−1}, x_t, x_{t−1/S}, δ_t) per frame (the latest forwards)
    KEEP_TRAJ = 12  # the latest forwards' substep trajectories (a window's sensitivities are stitched from them)

    def __init__(self, coarse, fine, substeps: int):
        self._coarse, self.fine, self.S = coarse, fine, int(substeps)
        self._recent: dict[int, list] = {}  # frame -> [(x_prev, x, pre, delta), ...] newest last
        self._committed: dict[int, tuple] = {}  # frame -> the record of the state stored for it
        self._traj: list = []  # (frames, young, poisson, before_fine, frame states, substep states), newest last
        self._horizon = 0  # the highest frame forwarded so far (records far behind it are dropped)

    def __getattr__(self, name: str):  # decode, start, modes, ...: the coarse backend's
        return getattr(self._coarse, name)

    # ---------------------------------------------------------------- the substep grid
    def steps(self, frames: Sequence[int]) -> list[int]:
        """Substep indices j = (t − 1)·S + k, k = 1..S, of ``frames`` (j/S is the time in frames)."""
        S = self.S
        return [(t - 1) * S + k for t in frames for k in range(1, S + 1)]

    def _expand(self, a: np.ndarray) -> np.ndarray:
        return np.repeat(np.asarray(a, float), self.S, axis=0)

    def _find(self, t: int, x_prev: np.ndarray | None, x: np.ndarray):
        """(record, exact): the latest record of frame t whose state is x (and whose previous frame is x_prev:
        exact), else the committed record of frame t (not exact), else None."""
        best = None
        for rec in reversed(self._recent.get(t, [])):
            if np.array_equal(rec[1], x):
                if x_prev is not None and np.array_equal(rec[0], x_prev):
                    return rec, True
                best = best or rec
        return (best or self._committed.get(t)), False

    def fine_before(self, t0: int, before: np.ndarray) -> np.ndarray:
        """The two substep states the first step of frame t0 starts from, (2, …), from before = [x_{t0−2}, x_{t0−1}]."""
        before = np.asarray(before, float)
        b0, b1 = before[0], before[1]
        if t0 - 1 <= 0:
            return np.stack([b1 + (b0 - b1) / self.S, b1])  # = [x_0, x_0] at the start
        rec, exact = self._find(t0 - 1, b0, b1)
        if rec is None:
            return np.stack([b1 + (b0 - b1) / self.S, b1])
        if exact:
            return np.stack([rec[2], b1])
        return np.stack([b1 + (b0 - b1) / self.S + rec[3], b1])

    def _coarse_before_grad(self, gb: np.ndarray) -> np.ndarray:
        """dL/d[x_{t0−2}, x_{t0−1}] from dL/d[x_{t0−1−1/S}, x_{t0−1}] (the restart map, δ fixed)."""
        S = self.S
        return np.stack([gb[0] / S, gb[1] + gb[0] * (1.0 - 1.0 / S)])

    def _fine_before_tangent(self, d_before) -> np.ndarray | None:
        if d_before is None:
            return None
        db = np.asarray(d_before, float)
        return np.stack([db[:, 1] + (db[:, 0] - db[:, 1]) / self.S, db[:, 1]], axis=1)

    # ---------------------------------------------------------------- forward and its records
    def forward(self, frames, young, poisson, before):
        """Frame states (w, …) of ``frames`` from before = [state t0−2, state t0−1]; young/poisson (w, R)."""
        S = self.S
        fb = self.fine_before(frames[0], before)
        Xf = np.asarray(self.fine.forward(self.steps(frames), self._expand(young), self._expand(poisson), fb))
        X = Xf[S - 1::S]
        prev = np.concatenate([fb[1:], X[:-1]])
        traj = np.concatenate([fb, Xf])  # traj[2 + j] = substep j of the window
        for i, t in enumerate(frames):
            pre = traj[i * S + S]  # the substep before frame i's last
            rec = (prev[i], X[i], pre, pre - (X[i] + (prev[i] - X[i]) / S))
            lst = self._recent.setdefault(t, [])
            lst.append(rec)
            del lst[:-self.KEEP]
        self._horizon = max(self._horizon, frames[-1])
        for t in [t for t in self._recent if t < self._horizon - 64]:
            del self._recent[t]
        for t in [t for t in self._committed if t < self._horizon - 64]:
            del self._committed[t]
        self._traj.append((list(frames), np.asarray(young, float), np.asarray(poisson, float), fb, X, Xf))
        del self._traj[:-self.KEEP_TRAJ]
        return X

    def records(self) -> tuple:
        """A copy of the forwards' records (per frame, the committed ones, the substep trajectories) and of its two
        backends' (a reduced one's Newton memory, :meth:`ReducedSpace.records`): :meth:`restore_records` puts them
        back, so that forwards that should leave no trace (adapt's change probes) do not push the records of the
        states the run keeps out of :attr:`KEEP`, nor change the last bits of the solves after them."""
        return ({t: list(v) for t, v in self._recent.items()}, dict(self._committed), list(self._traj), self._horizon,
                (self._coarse.records(), self.fine.records()))

    def restore_records(self, saved: tuple) -> None:
        """The records as :meth:`records` copied them."""
        recent, committed, traj, horizon, solvers = saved
        self._recent = {t: list(v) for t, v in recent.items()}
        self._committed, self._traj, self._horizon = dict(committed), list(traj), horizon
        for b, rec in zip((self._coarse, self.fine), solvers):
            b.restore_records(rec)

    def commit(self, t: int, state: np.ndarray) -> None:
        """Frame t's state is now ``state`` (run()'s store): keep the record of the forward that made it; a
        state no forward made (a corrected one) keeps the record of the state it replaces."""
        if t < 1:
            return
        rec, _ = self._find(t, None, np.asarray(state))
        if rec is not None:
            self._committed[t] = rec

    def _trajectory(self, frames, young, poisson, states, before) -> tuple[np.ndarray, np.ndarray]:
        """(fine before (2, …), substep states (w·S, …)) of a window whose frame states are ``states``: the
        substeps of a recorded forward of this very window, else stitched frame by frame from recorded forwards
        (:meth:`_stitch`: the window's frames taken from the trajectories they were simulated in, e.g. by
        StartWindow.memo), else simulated from ``before``."""
        fb = self.fine_before(frames[0], before)
        young, poisson, states = np.asarray(young, float), np.asarray(poisson, float), np.asarray(states)
        for fr, y, p, b, X, Xf in reversed(self._traj):
            if (fr == list(frames) and np.array_equal(y, young) and np.array_equal(p, poisson)
                    and np.array_equal(b, fb) and np.array_equal(X, states)):
                return fb, Xf
        Xf = self._stitch(frames, young, poisson, states, fb)
        if Xf is None:
            Xf = np.asarray(self.fine.forward(self.steps(frames), self._expand(young), self._expand(poisson), fb))
        return fb, Xf

    def _stitch(self, frames, young, poisson, states, fb) -> np.ndarray | None:
        """Substep states (w·S, …) of the window, each frame's S substeps taken from a recorded forward that
        simulated that frame with the same θ (young/poisson row) from the same two substep states (the previous
        frame's last two, ``fb`` for the first) and ended at the same frame state — the very substeps a forward of
        the whole window from ``fb`` takes, up to the tolerance of each step's solve (a step depends on θ, its
        inputs and the two states before it alone).  None when a frame has no such record."""
        S = self.S
        pair0, pair1 = fb[0], fb[1]
        blocks = []
        for i, t in enumerate(frames):
            blk = None
            for fr, y, p, b, X, Xf in reversed(self._traj):
                if t not in fr:
                    continue
                j = fr.index(t)
                lo, hi = ((b[0], b[1]) if j == 0 else (b[1], Xf[0]) if j * S == 1
                          else (Xf[j * S - 2], Xf[j * S - 1]))  # the two substep states before frame t's first
                if (np.array_equal(X[j], states[i]) and np.array_equal(y[j], young[i])
                        and np.array_equal(p[j], poisson[i]) and np.array_equal(lo, pair0)
                        and np.array_equal(hi, pair1)):
                    blk = Xf[j * S:(j + 1) * S]
                    break
            if blk is None:
                return None
            blocks.append(blk)
            pair0, pair1 = (blk[-2], blk[-1]) if S > 1 else (pair1, blk[-1])
        return np.concatenate(blocks)

    # ---------------------------------------------------------------- derivatives
    def _per_frame_sum(self, g: np.ndarray) -> np.ndarray:
        g = np.asarray(g)
        return g.reshape((-1, self.S) + g.shape[1:]).sum(1)

    def backward_before(self, frames, young, poisson, states, before, dL_dX):
        """(dL/dE (w, R), dL/dν (w, R), dL/d before (2, …)): the substeps' adjoint summed per frame."""
        S = self.S
        fb, Xf = self._trajectory(frames, young, poisson, states, before)
        dL_dX = np.asarray(dL_dX, float)
        dLf = np.zeros((len(Xf),) + dL_dX.shape[1:])
        dLf[S - 1::S] = dL_dX
        gE, gN, gb = self.fine.backward_before(self.steps(frames), self._expand(young), self._expand(poisson), Xf, fb,
                                               dLf)
        return self._per_frame_sum(gE), self._per_frame_sum(gN), self._coarse_before_grad(np.asarray(gb))

    def backward(self, frames, young, poisson, states, before, dL_dX):
        """(dL/dE, dL/dν), each (w, R)."""
        gE, gN, _ = self.backward_before(frames, young, poisson, states, before, dL_dX)
        return gE, gN

    def state_sensitivity(self, frames, young, poisson, states, before, d_young, d_poisson, d_before=None):
        """d states/dp (k, w, …) at the frames (the substeps' tangent model)."""
        fb, Xf = self._trajectory(frames, young, poisson, states, before)
        Sf = self.fine.state_sensitivity(self.steps(frames), self._expand(young), self._expand(poisson), Xf, fb,
                                         d_young, d_poisson, self._fine_before_tangent(d_before))
        return np.asarray(Sf)[:, self.S - 1::self.S]

    def sensitivity(self, frames, young, poisson, states, before, d_young, d_poisson, d_before=None):
        """dX/dp (k, w, n, 3)."""
        S = self.state_sensitivity(frames, young, poisson, states, before, d_young, d_poisson, d_before)
        return self._coarse.decode_sensitivity(states, S)


def substepped(backend, substeps: int, inputs_at: Callable[[float], object]):
    """``backend`` itself for substeps = 1, else a :class:`Substepped` over a fine twin (scene with Δt/S, its
    inputs of substep j at the fractional frame j/S, ``inputs_at(frame: float)``)."""
    from stages.sim.scene import substep_scene

    S = int(substeps)
    if S == 1:
        return backend

    frame_inputs = backend.inputs if backend.space == "full" else backend._inputs  # FrameInputs of a frame

    def fine_inputs(j: int):  # substep j = (t − 1)·S + k of frame t: inputs at t − 1 + k/S (frame t's at k = S)
        t1, k = divmod(j, S)
        return frame_inputs(t1) if k == 0 else inputs_at(t1 + k / S)

    if backend.space == "full":
        fine = FullSpace(substep_scene(backend.scene, S), fine_inputs, backend.solver)
    else:
        m = backend.model
        fm = type(m)(m.sub, substep_scene(m.scene, S), (np.asarray(m.cubature_points), np.asarray(m.cubature_weights)),
                     m.reference)
        fine = ReducedSpace(fm, fine_inputs)
    return Substepped(backend, fine, S)


class StoredStates(dict):
    """run()'s frame → state store; tells a substepped backend which state each frame now holds."""

    def __init__(self, backend):
        super().__init__()
        self._commit = backend.commit

    def __setitem__(self, t, state):
        super().__setitem__(t, state)
        self._commit(t, state)


class SolveCollapsed(RslError):
    """A forward solve inverted elements or diverged (raised by :class:`SolveGuard`)."""


class SolveGuard:
    """Stops a run whose simulation collapsed: after every forward solve (full or reduced space), positions must
    be finite, within 10 object sizes of rest, and at most ``max_inverted`` of the elements inverted (signed
    volume of its corners ≤ 0).  Stable Neo-Hookean recovers from an inverted sliver (one of 4766 elements in a
    reduced-space demo run at E = E_true); a collapsing material inverts many (54 of 979 at --young-init 1)."""

    max_inverted = 0.001  # fraction of the elements

    def __init__(self, vertices: np.ndarray, tets: np.ndarray, region_names: list[str], where: Path,
                 young_toml: float):
        self.rest, self.tets = np.asarray(vertices), np.asarray(tets)[:, :4]
        self.size = float(np.linalg.norm(self.rest.max(0) - self.rest.min(0)))
        self.names, self.where, self.young_toml = region_names, where, young_toml

    def __call__(self, frames: Sequence[int], X: np.ndarray, young: np.ndarray) -> None:
        """X (w, n, 3) positions of ``frames``; young (w, R) Pa."""
        X = np.asarray(X)[:, :len(self.rest)]
        for i, t in enumerate(frames):
            x = X[i]
            what = None
            if not np.all(np.isfinite(x)):
                what = "diverged (positions became NaN or infinite)"
            elif np.max(np.linalg.norm(x - self.rest, axis=1)) > 10 * self.size:
                what = "diverged (vertices moved over 10 object sizes)"
            else:
                p = x[self.tets]
                vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
                bad = int(np.sum(vol <= 0))
                if bad > self.max_inverted * len(vol):
                    what = f"inverted {bad} of {len(vol)} elements"
            if what:
                raise SolveCollapsed(
                    f"{self.where}: the simulation {what} at frame {t} with E = {self._E(young, i)}; if that is "
                    f"far too soft for this object, start from a larger E (--young-init, or [material] young = "
                    f"{self.young_toml:g} Pa) or take smaller steps (--lr).")

    def _E(self, young: np.ndarray, i: int = 0) -> str:
        rows = np.atleast_2d(young)
        return ", ".join(f"{n} {e:.3g} Pa" for n, e in zip(self.names, rows[min(i, len(rows) - 1)]))

    def failed(self, e: Exception, t: int, young: np.ndarray) -> None:
        """A solve that did not converge: the same sentence with what to change."""
        raise SolveCollapsed(
            f"{self.where}: the simulation failed at frame {t} with E = {self._E(young)} "
            f"({str(e).rstrip('.')}); if E is far below the object's stiffness start from a larger E (--young-init, "
            f"or [material] young = {self.young_toml:g} Pa), otherwise check controls.json's handles, loads and "
            f"obstacles.") from None


class Guarded:
    """A backend whose forward solves and start states are checked by a :class:`SolveGuard` (all else is the
    backend's own)."""

    def __init__(self, backend, guard: SolveGuard):
        self._backend, self._guard = backend, guard

    def __getattr__(self, name: str):
        return getattr(self._backend, name)

    def forward(self, frames, young, poisson, before):
        from stages.sim.scene import SimulationError

        try:
            states = self._backend.forward(frames, young, poisson, before)
        except SimulationError as e:
            self._guard.failed(e, frames[0], young)
        self._guard(frames, self._backend.decode(states), young)
        return states

    def start(self, young, poisson, kind, *args, **kw):
        from stages.sim.scene import SimulationError

        try:
            s0 = self._backend.start(young, poisson, kind, *args, **kw)
        except SimulationError as e:
            self._guard.failed(e, 0, young)
        self._guard([0], self._backend.decode(np.asarray(s0)[None]), young)
        return s0
