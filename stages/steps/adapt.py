"""Stage ``rsl adapt``: online real-to-sim adaptation of E and ν per region (paper §3–4).

Online, at each new frame T_e the window W = T_e−w+1..T_e is re-simulated from the two stored
states before it with the current θ = (E, ν) per region, the window loss L (vision, Eq. 7, or
markers, Eq. 4 windowed) and dL/dX are evaluated, the adjoint over the window turns dL/dX into
dL/dθ (θ shared by the window frames: the per-frame gradients are summed), and a few Adam steps
move the parameters p = (log E, s) with ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s).  The window's
states are then stored; a state is final once its frame leaves the window.

Start convention ([capture] start, docs/capture.md): frame 0 is x_0(θ) — the rest shape, or the static
equilibrium under the frame-0 controls solved with the current θ (stages.sim.static) — with x_{−1} = x_{−2} = x_0;
frame t ≥ 1 is an implicit-Euler step (:class:`StartWindow`), or with ``--substeps S`` S steps of Δt/S, the controls
interpolated at the fractional frames (:class:`_Substepped`: what rsl synth --substeps films).  A window that holds frame 0 differentiates through
the static solve.  Observations are anchored at frame 0: markers are bound to the frame-0 surface x_0(θ), and
Gaussians fitted with the mesh at rest to frame f are re-bound to the tets of frame f simulated with the current
θ (``gaussian_anchor = "rebind"``: rendered at x_f they are exactly the fitted Gaussians; the older first-order
``"offset"`` renders at x_t − (x_f − rest)); both anchors are refreshed as θ changes.  adapt.h5 stores, per frame,
θ after that frame's update (and its σ with ``--estimator gn``), the frame's final state (z and positions), the
window loss and the time spent in forward simulation, adjoint / sensitivities, rendering and in total (wall
seconds of the frame's whole update; forward includes re-anchoring the observations, render the image loss and
its gradient through the renderer).  Frames 0..w carry the first calls' compilation (numba at frame 0, JAX for
each new window length and, at frame w, for the first window that starts from stored states): steady per-frame
times are those of frames > w (bench/table1.py, bench/adapt_speed.py).

``--estimator gn`` (stages.estimator) replaces the Adam steps by Gauss–Newton / Levenberg–Marquardt on the
window's residuals (markers, or pixels with Huber IRLS weights) with the forward sensitivities dX/dp
(stages.sim.sensitivity, stages.subspace.sensitivity), an arrival-cost prior with process noise, change-point
detection, a correction of the window's starting states, and E ± σ from the normal matrix (:func:`_online_gn`).
``--mode static`` identifies one θ from the static equilibria of the frames alone (:class:`StaticWindow`).

``--mode offline`` is the baseline of §5.3: one θ for the whole sequence, fitted by the same
machinery (forward over all frames, adjoint over all frames, Adam) for a fixed number of
iterations.  ``--space full`` runs on the full-space FEM (stages/sim), ``--space reduced`` on the
neural subspace (stages/subspace).

What the reported E means: linear tets are too stiff in bending and lock as ν → 0.5, so the E
identified on a mesh is the effective modulus *of that discretisation* — lower than the continuum
value, since the simulation offsets the mesh's extra stiffness.  ``--refine 1`` splits every tet
into eight (full space) and reports the E of the finer discretisation, closer to the continuum
value (bench/adapt.py, case refine: a 192-tet box reported 0.56 E_true, refined 0.88 E_true).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np

from stages.adapt_loss import MarkerBinding, bind_markers, marker_residuals
from stages.artefacts import (KIND_FILES, PARTIAL_ADAPT, AdaptArtefact, MeshArtefact, Provenance, check_mesh_source,
                              check_same_mesh)
from stages.capture import (IMAGE_SUFFIXES, Capture, CaptureError, check_obstacles_clear, load_capture,
                            read_image)
from stages.errors import Interrupted, RslError
from stages.interrupt import CheckedReporter, CtrlC
from stages.parameters import Adam, chain_params, params_from_theta, theta_from_params
from stages.progress import Reporter, SilentReporter
from stages.sim.meshgen import refine_tets  # noqa: F401  (re-exported: stages.steps.adapt.refine_tets)
from stages.window_model import Observation, Window, WindowBackend
from stages.workspace import prepare_workspace



@dataclass(frozen=True)
class AdaptConfig:
    capture: Path
    """Capture folder (capture.toml, frames/, controls.json, markers.csv)."""
    workspace: Path
    """Workspace folder holding mesh.h5 and the other artefacts; adapt.h5 is written there."""
    window: int = 5
    """Sliding-window size w: frames re-simulated and compared at each new frame."""
    space: Literal["reduced", "full"] = "reduced"
    """Simulate in the neural subspace (needs subspace.h5) or in the full FEM space."""
    mode: Literal["online", "offline", "static"] = "online"
    """online: sliding window, θ updated every frame; offline: one θ fitted to the whole sequence; static: one θ
    from the static equilibria of the frames alone (an object at rest under gravity and holds; chosen by itself
    when no control moves and [capture] start = "equilibrium")."""
    loss: Literal["vision", "markers"] = "vision"
    """Observation: rendered Gaussians vs images (needs gaussians.h5, cameras.h5) or markers.csv."""
    cameras: str = ""
    """Cameras used by the vision loss: indices or names, comma separated (empty: all)."""
    frames: str = ""
    """Frame range A:B (B exclusive; empty: every frame)."""
    iters_per_frame: int = 2
    """Adam steps per new frame (online) — each one a forward, a loss and an adjoint over the window."""
    lr: float = 0.15
    """Adam learning rate on log E."""
    lr_poisson: float = 0.05
    """Adam learning rate on the bounded ν parameter s (ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s))."""
    beta1: float = 0.5
    """Adam's momentum β₁ (lower reacts faster to a changing material and overshoots less)."""
    offline_iters: int = 30
    """Iterations of the offline baseline (each over the whole sequence)."""
    young_init: float | None = None
    """Initial E in Pa for every region (default: capture.toml's material and regions tables)."""
    poisson_init: float | None = None
    """Initial ν for every region (default: capture.toml)."""
    fit_poisson: bool = True
    """Adapt ν as well as E (ν stays inside capture.toml's poisson_range)."""
    refine: int = 0
    """Full space only: split every tet into 8 this many times (E of a finer discretisation)."""
    appearance: bool = False
    """Vision loss: also refine Gaussian colours and opacities by the same loss."""
    gaussian_anchor: Literal["rebind", "offset"] = "rebind"
    """Vision loss: how the Gaussians (fitted to the images of their fit frame f with the mesh posed at x_fit,
    gaussians.h5 fit_positions: frame f under the start convention with capture.toml's θ; rest for older files)
    follow the simulation.  rebind: each Gaussian is re-bound to the tet of frame f simulated with the current
    θ that holds it (exact at frame f); offset: rendered at x_t − (x_f − x_fit) (first order in x_f − x_fit)."""
    follow: bool = False
    """Process frames as they appear in the capture folder; Ctrl-C ends with everything saved."""
    follow_timeout: float = 0.0
    """With --follow: stop after this many seconds without a new frame (0: wait until Ctrl-C)."""
    solver: Literal["auto", "cholmod", "splu"] = "auto"
    """Linear solver of the full-space Newton steps (passed to stages.sim)."""
    estimator: Literal["auto", "adam", "gn"] = "auto"
    """adam: a few Adam steps on the window loss per frame; gn: Gauss–Newton / Levenberg–Marquardt on the window
    residuals with an arrival-cost prior and process noise (a moving-horizon filter), reporting E ± σ; auto: gn
    with markers (it settles in 4 frames against Adam's 33, docs/results/estimator.md), adam with images (measured
    closer to the truth than gn on images, docs/results/vision_bias.md)."""
    process_noise: float = 0.02
    """gn: σ of the random walk of log E (and of the ν parameter) per frame — how fast the material may change."""
    state_correction: Literal["states", "past", "off"] = "states"
    """gn: also estimate a correction of the window's two starting states, so the simulated past cannot drift
    from what is observed.  states: every latent coordinate of both states in the reduced space (2r unknowns),
    the 12 lowest vibration modes of both in full space (24 unknowns), each with its own prior (markers; with
    images, where each unknown costs renders, as past); past: along their sensitivities to θ only (the past
    re-simulated with another θ, 2R unknowns); off: kept as stored."""
    change_threshold: float = 3.0
    """gn: the change-of-material test (a CUSUM of the new frame's innovation z = rᵀr/(mσ²) at the predicted θ, σ the
    noise level the windows reach): a frame whose residual RMS exceeds this many σ, or a smaller excess that
    persists over a few frames, is taken as a change: the window restarts there and the θ prior is widened by
    --change-sigma (0: never)."""
    change_sigma: float = 0.5
    """gn: σ added to log E (and the ν parameter) when a change of material is detected (0.5: a factor 1.65)."""
    state_prior: float = 0.5
    """gn, --state-correction past: prior σ of the correction coefficients (in log E units: the past may look
    as if simulated with E off by this factor's exponent)."""
    substeps: int = 1
    """Implicit-Euler substeps per frame: each frame is S steps of Δt = 1/(fps·S) s, substep k taking the controls
    at the fractional frame t − 1 + k/S and θ of frame t (for a capture whose truth is finer in time)."""
    model_error: float = 0.02
    """gn: relative σ of E that the discretisation itself adds to the reported E ± σ (σ_E = E √(σ²_logE + e²)): the
    error of rsl's mesh and time step against the material, which more frames do not average out (quadratic tets:
    1–3 %, docs/results/convergence.md, loss_sweep.md; calibrated in docs/results/estimator.md)."""
    model_error_poisson: float = 0.02
    """gn: σ of ν that the discretisation itself adds to the reported ν ± σ (in quadrature; ν is weakly identified
    and absorbs model error, calibrated in docs/results/estimator.md)."""
    vision_anchor: Literal["simulated", "stored"] = "simulated"
    """adam, images: where a window after the Gaussians' fit frame anchors them — "simulated": x_f re-simulated
    from the start with the current θ (right while E is constant); "stored": the fit frame's stored state, held
    fixed, like the window's starting states (right when E changed since the fit frame).  Cable bar with E ×2, ×4
    steps: reduced 37 % → 12 % median E error, full 40 % → 43 %; constant E from 0.4 E_true, full: 5.5 % → 24 %
    (neither is right on both: experimental)."""


def resolve_estimator(config: AdaptConfig) -> str:
    """The estimator an "auto" config runs: gn with markers (docs/results/estimator.md), adam with images
    (docs/results/vision_bias.md)."""
    if config.estimator != "auto":
        return config.estimator
    return "gn" if config.loss == "markers" else "adam"


# =========================================================================== backends
class _FullSpace:
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
            _, vec = eigsh(K, k=k, M=Md.tocsc(), sigma=0.0, which="LM")
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


class _ReducedSpace:
    """Reduced window simulation and adjoint (stages.subspace.ReducedModel). State = z (r,)."""

    space = "reduced"

    def __init__(self, model, inputs: Callable[[int], object]):
        self.model, self._inputs = model, inputs
        self.dim = int(model.dim)
        self._rin: dict[int, object] = {}
        self.rtol = 1e-8  # relative residual of each reduced Newton step

    def inputs(self, t: int):
        """ReducedInputs of frame t (cached: the projection of loads is done once)."""
        if t not in self._rin:
            self._rin[t] = self.model.reduce_inputs(self._inputs(t))
        return self._rin[t]

    @property
    def rest_state(self) -> np.ndarray:
        return np.asarray(self.model.z_rest)

    def decode(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(self.model.decode(states))

    def z(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(states)

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


class _Substepped:
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
        del self._traj[:-4]
        return X

    def commit(self, t: int, state: np.ndarray) -> None:
        """Frame t's state is now ``state`` (run()'s store): keep the record of the forward that made it; a
        state no forward made (a corrected one) keeps the record of the state it replaces."""
        if t < 1:
            return
        rec, _ = self._find(t, None, np.asarray(state))
        if rec is not None:
            self._committed[t] = rec

    def _trajectory(self, frames, young, poisson, states, before) -> tuple[np.ndarray, np.ndarray]:
        """(fine before (2, …), substep states (w·S, …)) of a window whose frame states are ``states``."""
        fb = self.fine_before(frames[0], before)
        young, poisson, states = np.asarray(young, float), np.asarray(poisson, float), np.asarray(states)
        for fr, y, p, b, X, Xf in reversed(self._traj):
            if (fr == list(frames) and np.array_equal(y, young) and np.array_equal(p, poisson)
                    and np.array_equal(b, fb) and np.array_equal(X, states)):
                return fb, Xf
        Xf = np.asarray(self.fine.forward(self.steps(frames), self._expand(young), self._expand(poisson), fb))
        return fb, Xf

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
    """``backend`` itself for substeps = 1, else a :class:`_Substepped` over a fine twin (scene with Δt/S, its
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
        fine = _FullSpace(substep_scene(backend.scene, S), fine_inputs, backend.solver)
    else:
        m = backend.model
        fm = type(m)(m.sub, substep_scene(m.scene, S), (np.asarray(m.cubature_points), np.asarray(m.cubature_weights)),
                     m.reference)
        fine = _ReducedSpace(fm, fine_inputs)
    return _Substepped(backend, fine, S)


class _StoredStates(dict):
    """run()'s frame → state store; tells a substepped backend which state each frame now holds."""

    def __init__(self, backend):
        super().__init__()
        self._commit = backend.commit

    def __setitem__(self, t, state):
        super().__setitem__(t, state)
        self._commit(t, state)


class SolveCollapsed(RslError):
    """A forward solve inverted elements or diverged (raised by :class:`_SolveGuard`)."""


class _SolveGuard:
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


class _Guarded:
    """A backend whose forward solves and start states are checked by a :class:`_SolveGuard` (all else is the
    backend's own)."""

    def __init__(self, backend, guard: _SolveGuard):
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


# =========================================================================== observations
class _Markers:
    """Marker observations (markers.csv) bound to the rest surface."""

    kind = "markers"

    def __init__(self, capture: Capture, vertices: np.ndarray, faces: np.ndarray, n_vertices: int):
        self.capture, self.faces, self.n = capture, faces, n_vertices
        self.P = self._read()
        self.rebind(vertices)
        far = float(self.binding.distance.max())
        diag = float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        self.far = far / max(diag, 1e-12)
        # the smallest marker noise σ the estimator assumes: 10⁻⁴ of the object's size (0.02 mm on a 0.2 m
        # object; mocap is rarely better) — without a floor, noise-free synthetic markers give σ → 0 and the
        # arrival cost becomes rigid against the slightest model or linearisation error
        self.noise_floor = 1e-4 * diag

    def rebind(self, x0: np.ndarray) -> None:
        """Bind each marker to the triangle of the frame-0 surface x0 (n, 3) nearest its frame-0 position, at
        the projection of that position on the triangle's plane (the nearest point itself when it projects
        inside the triangle; unclamped at an edge, so that the binding is a smooth function of x0 for a given
        triangle — the Gauss–Newton Jacobian differentiates it, :meth:`binding_jacobian`)."""
        b = bind_markers(x0[:self.n], self.faces, self.P[0])
        self.binding = b
        self.binding = MarkerBinding(b.faces, self._plane_bary(x0[:self.n]), b.distance)

    def _read(self) -> np.ndarray:
        P = self.capture.markers()
        if P is None:
            raise CaptureError(f"{self.capture.markers_path}: file not found; --loss markers needs markers.csv.")
        return P

    def available(self) -> int:
        """Frames observed so far (markers.csv is re-read: it may grow in --follow mode).  Since a marker may
        be missing from a frame (a gap), a writer in --follow mode should add each frame's rows at once
        (e.g. write a new file and rename it over markers.csv): the rows of a frame read while still being
        written count as gaps."""
        if self.capture.markers_path.exists():
            try:
                self.P = self._read()
            except CaptureError:
                pass  # a half-written line: keep what we had
        return len(self.P)

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame losses (w,) and dL/dX (w, n, 3) for X on the mesh (n, 3) per frame; only the observed
        markers count (a gap, NaN in markers.csv's array, adds nothing; a frame seeing none gives 0)."""
        P = self.P[list(frames)]
        r = marker_residuals(self.binding, X[:, :self.n], P)
        grad = np.zeros_like(X)
        grad[:, :self.n] = self.binding.scatter(2.0 * r, self.n)
        return np.sum(r * r, axis=(1, 2)), grad

    def _plane_bary(self, x0: np.ndarray) -> np.ndarray:
        """Barycentric coordinates (M, 3) of each frame-0 marker projected on the plane of its bound triangle of
        x0 — the binding as a smooth function of x0 (the same as the closest point while it lies inside)."""
        tri = x0[self.binding.faces]  # (M, 3, 3)
        a, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        d = self.P[0] - a
        g = np.stack([np.stack([np.sum(e1 * e1, -1), np.sum(e1 * e2, -1)], -1),
                      np.stack([np.sum(e1 * e2, -1), np.sum(e2 * e2, -1)], -1)], -2)
        rhs = np.stack([np.sum(e1 * d, -1), np.sum(e2 * d, -1)], -1)
        uv = np.linalg.solve(g, rhs[..., None])[..., 0]
        return np.concatenate([1 - uv.sum(-1, keepdims=True), uv], -1)

    def binding_jacobian(self, frames: Sequence[int], X: np.ndarray, x0: np.ndarray, dx0: np.ndarray
                         ) -> list[np.ndarray]:
        """Per frame, the part of ∂r_f/∂p (3·M_f, k) that comes from the binding's dependence on the anchor
        configuration x0 (n, 3) moving by dx0 (k, n, 3): Σ_k (∂b_ik/∂p) x_f[f_ik], ∂b/∂p by central
        differences of :meth:`_plane_bary` (smooth, cheap: M 2×2 solves)."""
        x0 = x0[:self.n]
        scale = float(np.linalg.norm(np.ptp(x0, axis=0)))
        dB = []
        for v in dx0[:, :self.n]:
            vmax = float(np.abs(v).max())
            if vmax == 0.0:
                dB.append(np.zeros_like(self.binding.bary))
                continue
            h = 1e-6 * scale / vmax
            dB.append((self._plane_bary(x0 + h * v) - self._plane_bary(x0 - h * v)) / (2 * h))
        dB = np.stack(dB)  # (k, M, 3)
        out = []
        for t, x in zip(frames, X):
            ok = np.all(np.isfinite(self.P[t]), axis=-1)
            dm = np.einsum("kmj,mjd->kmd", dB, x[self.binding.faces])[:, ok]  # (k, M_f, 3)
            out.append(dm.reshape(len(dB), -1).T)
        return out

    def residuals(self, frames: Sequence[int], X: np.ndarray) -> list[np.ndarray]:
        """Per frame, r_f = m_i(x_f) − p_f^i over the observed markers, flattened (3·M_f,), m."""
        out = []
        for t, x in zip(frames, X):
            P = self.P[t]
            ok = np.all(np.isfinite(P), axis=-1)
            out.append((self.binding.positions(x[:self.n])[ok] - P[ok]).reshape(-1))
        return out

    def jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray) -> list[np.ndarray]:
        """Per frame, ∂r_f/∂p (3·M_f, k) for position sensitivities dX (k, w, n, 3) (markers are linear in x)."""
        out = []
        for i, t in enumerate(frames):
            ok = np.all(np.isfinite(self.P[t]), axis=-1)
            dm = self.binding.positions(dX[:, i, :self.n])[:, ok]  # (k, M_f, 3)
            out.append(dm.reshape(len(dX), -1).T)
        return out

    def noise_scale(self, r: np.ndarray) -> float:
        """σ of one residual from residuals r: their RMS (Gaussian marker noise), m."""
        return float(np.sqrt(np.mean(r * r))) if len(r) else 0.0

    huber = None  # marker noise is Gaussian: plain least squares


class _Vision:
    """Image observations: render the Gaussians bound to the mesh in each chosen camera (stages.render)."""

    kind = "vision"

    def __init__(self, capture: Capture, ws: Path, cam_spec: str, mesh: MeshArtefact, appearance: bool,
                 anchor: str = "rebind"):
        from stages.artefacts import CamerasArtefact, GaussiansArtefact, MasksArtefact
        from stages.adapt_loss import ImageLoss

        self.capture, self.n = capture, mesh.n_vertices
        cams_art = CamerasArtefact.load(ws / KIND_FILES["cameras"])
        gauss = GaussiansArtefact.load(ws / KIND_FILES["gaussians"])
        masks_path = ws / KIND_FILES["masks"]
        self.masks = MasksArtefact.load(masks_path).masks if masks_path.exists() else None
        self.cameras = _pick_cameras(cam_spec, [c.name for c in cams_art.cameras], ws / KIND_FILES["cameras"])
        for name in self.cameras:
            if name not in capture.camera_names:
                raise CaptureError(f"{capture.toml_path}: camera '{name}' of cameras.h5 is not listed in "
                                   f"[capture] cameras.")
        self.sources = {c: capture.frame_source(c) for c in self.cameras}
        self.loss_fn = ImageLoss(gauss, mesh, [cams_art.by_name(c) for c in self.cameras], appearance=appearance)
        # Occluders (controls.json handle/obstacle ``visual``): the pixels they cover at frame t are left out
        # of the loss (stages/occluders.py), whatever the frame and the mask hold there.
        from stages.occluders import has_occluders

        self.controls = capture.controls()
        self.occluded = has_occluders(self.controls)
        self._cams = [cams_art.by_name(c) for c in self.cameras]
        self._ignore: dict[int, list[np.ndarray | None]] = {}
        # Without masks the renders are composited over the capture's background plates (when there are
        # any) and compared with the raw frames; with masks, the frames' backgrounds are replaced.
        self.plates = {c: (None if self.masks is not None and c in self.masks else capture.background(c))
                       for c in self.cameras}
        self.loss_fn.set_backgrounds([None if p is None else p.astype(np.float32) / 255.0
                                      for p in self.plates.values()])
        self._cache: dict[int, list[np.ndarray]] = {}
        # The Gaussians were fitted to frame ``fit_frame`` with the mesh at rest: they are anchored to the
        # object's configuration at that frame, x_fit simulated with the current θ (re-anchored as θ
        # changes, like the marker binding; the anchor is held fixed within one gradient).  "rebind":
        # re-bound to the tets of x_fit (ImageLoss.rebind), rendered at x_t; "offset": rendered at
        # x_t − (x_fit − rest) (first order in x_fit − rest).
        from stages.artefacts import read_provenance

        if anchor not in ("rebind", "offset"):
            raise RslError(f"gaussian_anchor should be 'rebind' or 'offset', found '{anchor}'.")
        self.anchor_kind = anchor

        self.fit_frame = int(read_provenance(ws / KIND_FILES["gaussians"]).get("config", {}).get("frame", 0) or 0)
        self.rest = self.loss_fn.fit_positions  # (n, 3) where the Gaussians were fitted (rest for older files)
        self.anchor = np.zeros_like(mesh.vertices)  # (n, 3) x_fit(θ) − fit_positions

    def rebind(self, x_fit: np.ndarray) -> None:
        """Anchor the Gaussians at the simulated fit-frame positions x_fit (n, 3)."""
        if self.anchor_kind == "rebind":
            self.loss_fn.rebind(x_fit[:self.n])
        else:
            self.anchor = x_fit[:self.n] - self.rest

    def count_checked(self) -> int:
        """Outside --follow: every frame of every chosen camera (PNG/JPG files or a video, read as segment
        reads them: capture.FrameSource) must decode, at the image size its camera in cameras.h5 was
        calibrated for; an unreadable frame anywhere is an error naming the file.  The frame count."""
        counts = {c: s.count for c, s in self.sources.items()}
        if len(set(counts.values())) > 1:
            detail = ", ".join(f"{c}: {k}" for c, k in counts.items())
            raise CaptureError(f"{self.capture.root / 'frames'}: cameras hold unequal frame counts ({detail}).")
        for cam, (c, src) in zip(self._cams, self.sources.items()):
            for t in range(src.count if src.files is not None else min(src.count, 1)):
                img = src.read(t)  # names the file (or the video) it cannot decode
                if img.shape[:2] != (cam.height, cam.width):
                    where = src.files[t] if src.files is not None else src.video
                    raise CaptureError(f"{where}: the frame is {img.shape[1]}x{img.shape[0]} but camera '{c}' in "
                                       f"cameras.h5 is calibrated for {cam.width}x{cam.height} images.")
        return next(iter(counts.values()), 0)

    def available(self) -> int:
        """Frames whose images exist and decode in every chosen camera (counted on from the last call)."""
        n = getattr(self, "_n_ready", 0)
        while _frame_ready(self.capture, self.cameras, n):
            n += 1
        self._n_ready = n
        return n

    def targets(self, t: int) -> list[np.ndarray]:
        """Masked images Ĩ_t^c = I·m + bg·(1 − m) (raw I without masks), float32 (H, W, 3) in [0, 1]."""
        if t not in self._cache:
            out = []
            for c in self.cameras:
                src = self.sources[c]
                img = (src.read(t) if src.video is not None else _read_frame(self.capture, c, t)).astype(np.float32) / 255.0
                if self.masks is not None and c in self.masks and t < len(self.masks[c]):
                    m = self.masks[c][t][..., None].astype(np.float32)
                    img = img * m + self.loss_fn.background[None, None, :] * (1 - m)
                out.append(img)
            self._cache[t] = out
            for old in [k for k in self._cache if k < t - 64]:
                del self._cache[old]
        return self._cache[t]

    def ignore(self, t: int) -> list[np.ndarray | None]:
        """Per chosen camera, the (H, W) pixels the occluders cover at frame t (None: no occluder)."""
        if not self.occluded:
            return [None] * len(self.cameras)
        if t not in self._ignore:
            from stages.occluders import ignore_mask

            self._ignore[t] = [ignore_mask(self.controls, t, c) for c in self._cams]
            for old in [k for k in self._ignore if k < t - 64]:
                del self._ignore[old]
        return self._ignore[t]

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(per-frame L1 losses (w,), dL/dX (w, n, 3)); also sets ``anchor_grad`` (n, 3) = dL/dx_f, the derivative
        with respect to the anchor configuration x_f(θ) of the last :meth:`rebind` (rebind: through
        ImageLoss.anchored_geometry; offset: −Σ_t dL/dx_t), which a gradient in θ must carry too."""
        losses, grad = np.zeros(len(frames)), np.zeros_like(X)
        ga = np.zeros((self.n, 3))
        for i, t in enumerate(frames):
            li, gi, gai = self.loss_fn(X[i, :self.n] - self.anchor, self.targets(t), self.ignore(t), anchor_grad=True)
            losses[i], grad[i, :self.n] = li, gi
            ga += gai if self.anchor_kind == "rebind" else -gi
        self.anchor_grad = ga
        return losses, grad

    # Gauss–Newton residuals: the pixel differences themselves (every camera, RGB), weighted by Huber IRLS
    # (stages.estimator) — L2 near the solution, L1-like on outlying pixels, like the L1 loss of Adam.
    huber = 1.345  # Huber δ in units of σ (95 % efficiency under Gaussian noise)
    noise_floor = 1e-3  # of the [0, 1] intensity range (a quarter of one 8-bit grey level)

    def _renders(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([im.reshape(-1) for im in self.loss_fn.render(x[:self.n] - self.anchor)]
                              ).astype(np.float64)

    def _keep(self, t: int) -> np.ndarray | float:
        """1 for the pixels that count at frame t, 0 under an occluder (flattened like the residuals), or 1.0."""
        if not self.occluded:
            return 1.0
        return np.concatenate([np.repeat(~(np.zeros(c.height * c.width, bool) if m is None else m.reshape(-1)), 3)
                               for c, m in zip(self._cams, self.ignore(t))]).astype(np.float64)

    def residuals(self, frames: Sequence[int], X: np.ndarray) -> list[np.ndarray]:
        """Per frame, r_f = R(G(x_f), c) − Ĩ_f^c over every pixel, channel and camera, flattened (0 under an
        occluder)."""
        return [(self._renders(x) - np.concatenate([im.reshape(-1) for im in self.targets(t)]).astype(np.float64))
                * self._keep(t) for t, x in zip(frames, X)]

    def jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray, rel_step: float = 1e-2
                 ) -> list[np.ndarray]:
        """Per frame, ∂r_f/∂p (pixels, k) approximately: the renderer's directional derivative along each
        position sensitivity dX[j, f] by central differences, (R(x + ε v) − R(x − ε v)) / 2ε with ε·max|v| =
        ``rel_step`` × the object's size (the rasterizer has no forward mode; 2k renders per frame).  3DGS
        rasterization is only piecewise smooth (the α < 1/255 cut-off) and renders in float32, so these
        columns carry errors of several % (tests); Gauss–Newton therefore takes its gradient from
        :meth:`exact_jtwr` and uses J only for the normal matrix (step shape and σ)."""
        self._dXa = None  # the anchor's sensitivity, set by binding_jacobian for exact_jtwr of this evaluation
        size = float(np.linalg.norm(np.ptp(self.rest, axis=0)))
        out = []
        for i, x in enumerate(X):
            cols = []
            for j in range(len(dX)):
                v = dX[j, i]
                vmax = float(np.abs(v[:self.n]).max())
                if vmax == 0.0:
                    cols.append(np.zeros(0))
                    continue
                eps = rel_step * size / vmax
                cols.append((self._renders(x + eps * v) - self._renders(x - eps * v)) / (2 * eps) * self._keep(frames[i]))
            m = max((len(c) for c in cols), default=0)
            out.append(np.stack([c if len(c) else np.zeros(m) for c in cols], axis=1))
        self._last_jac = (dX, out)  # binding_jacobian replaces these columns by joint differences
        return out

    def binding_jacobian(self, frames: Sequence[int], X: np.ndarray, x_anchor: np.ndarray, dXa: np.ndarray
                         ) -> list[np.ndarray]:
        """Per frame, the part of ∂r_f/∂p (pixels, k) that comes from the anchor x_f(θ) moving by dXa (k, n, 3).
        On a sagging capture the two parts nearly cancel (the anchor moves the Gaussians back where they were
        fitted), so each column is differenced jointly — positions along dX[j] (of the :meth:`jacobian` call of
        this evaluation) and the anchor along dXa[j] together: rebind, (R(x + εv; x_a + εv_a) − R(x − εv;
        x_a − εv_a)) / 2ε with the Gaussians kept in their elements (ImageLoss.anchored_geometry, smooth in x_a);
        offset, the renders at x − (x_a − x_fit) along v − v_a — and this returns the joint columns minus those
        :meth:`jacobian` returned (GN adds the two).  :meth:`exact_jtwr` then adds the anchor's exact part."""
        torch = self.loss_fn.torch
        self._dXa = dXa
        dX, J_pos = self._last_jac
        size = float(np.linalg.norm(np.ptp(self.rest, axis=0)))
        xa = np.asarray(x_anchor, np.float64)[:self.n]

        def renders(x, a):
            with torch.no_grad():
                ims = self.loss_fn.images(torch.tensor(np.asarray(x[:self.n], np.float64)), torch.tensor(a))
            return np.concatenate([im.numpy().reshape(-1) for im in ims]).astype(np.float64)

        out = []
        for i, x in enumerate(X):
            cols = []
            for j in range(len(dXa)):
                v, va = dX[j, i, :self.n], dXa[j, :self.n]
                vmax = max(float(np.abs(v).max()), float(np.abs(va).max()))
                if vmax == 0.0:
                    cols.append(np.zeros(J_pos[i].shape[0]))
                    continue
                eps = 1e-2 * size / vmax
                if self.anchor_kind == "rebind":
                    col = (renders(x[:self.n] + eps * v, xa + eps * va) - renders(x[:self.n] - eps * v, xa - eps * va))
                else:
                    col = self._renders(x[:self.n] + eps * (v - va)) - self._renders(x[:self.n] - eps * (v - va))
                cols.append(col / (2 * eps) * self._keep(frames[i]))
            out.append(np.stack(cols, axis=1) - J_pos[i])
        return out

    def exact_jtwr(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray, rs: list, Ws: list) -> np.ndarray:
        """Jᵀ W r (k,) exactly: per frame, dℓ/dx of ℓ = ½ Σ W (R(x) − Ĩ)² by torch autograd through the
        rasterizer, projected on the sensitivities dX (k, w, n, 3) — plus, after :meth:`binding_jacobian` in the
        same evaluation, dℓ/dx_a (ImageLoss.anchored_geometry; offset: −dℓ/dx) projected on the anchor's
        sensitivities."""
        torch = self.loss_fn.torch
        g = np.zeros(len(dX))
        dXa = getattr(self, "_dXa", None)
        for i, t in enumerate(frames):
            xt = torch.tensor(np.asarray(X[i, :self.n] - self.anchor, np.float64), requires_grad=True)
            xa = None
            if dXa is not None and self.anchor_kind == "rebind" and self.loss_fn._anchor_x is not None:
                xa = torch.tensor(self.loss_fn._anchor_x, requires_grad=True)
            imgs = self.loss_fn.images(xt, xa)
            tg = torch.cat([torch.as_tensor(a, dtype=torch.float64).reshape(-1) for a in self.targets(t)])
            rend = torch.cat([im.reshape(-1) for im in imgs]).double()
            w = torch.as_tensor(np.asarray(Ws[i], np.float64) * self._keep(t))  # occluded pixels weigh 0
            (0.5 * (w * (rend - tg) ** 2).sum()).backward()
            g += np.einsum("ni,kni->k", xt.grad.numpy(), dX[:, i, :self.n])
            if dXa is not None and (xa is not None or self.anchor_kind == "offset"):
                ga = xa.grad.numpy() if xa is not None else -xt.grad.numpy()
                g += np.einsum("ni,kni->k", ga, dXa[:, :self.n])
        return g

    def noise_scale(self, r: np.ndarray) -> float:
        """σ of one pixel residual: 1.4826 × the median |r| over the pixels that differ (robust; the
        background pixels that match exactly are left out)."""
        a = np.abs(r[np.abs(r) > 1e-6])
        return float(1.4826 * np.median(a)) if len(a) else 0.0


def _pick_cameras(spec: str, names: list[str], path: Path) -> list[str]:
    if not spec.strip():
        return list(names)
    out = []
    for tok in (s.strip() for s in spec.split(",") if s.strip()):
        if tok.isdigit():
            k = int(tok)
            if k >= len(names):
                raise RslError(f"{path}: --cameras asks for camera {k} but it holds {len(names)} cameras.")
            out.append(names[k])
        elif tok in names:
            out.append(tok)
        else:
            raise RslError(f"{path}: --cameras names '{tok}', which is not one of {', '.join(names)}.")
    return list(dict.fromkeys(out))


def _frame_file(capture: Capture, cam: str, t: int) -> Path | None:
    folder = capture.root / "frames" / cam
    for stem in (f"{t:06d}", str(t)):
        for suf in IMAGE_SUFFIXES:
            p = folder / f"{stem}{suf}"
            if p.is_file():
                return p
    return None


def _read_frame(capture: Capture, cam: str, t: int) -> np.ndarray:
    p = _frame_file(capture, cam, t)
    if p is None:
        return capture.frame_source(cam).read(t)
    return read_image(p)


def _frame_ready(capture: Capture, cams: Sequence[str], t: int) -> bool:
    """Frame t counts when every camera's image for it exists and decodes completely."""
    import cv2

    for c in cams:
        p = _frame_file(capture, c, t)
        if p is None:
            return False
        data = np.fromfile(p, dtype=np.uint8)
        if p.suffix.lower() == ".png" and not data[-12:].tobytes().endswith(b"IEND\xaeB`\x82"):
            return False  # still being written
        if data.size == 0 or cv2.imdecode(data, cv2.IMREAD_COLOR) is None:
            return False
    return True


# =========================================================================== the start convention
class StartWindow:
    """A window simulated under the capture's start convention (docs/capture.md): frame 0 is x_0(θ) — the rest
    shape, or the static equilibrium under the frame-0 controls solved with θ — with x_{−1} = x_{−2} = x_0;
    frame t ≥ 1 is an implicit-Euler step from (x_{t−1}, x_{t−2}).  A window that holds frame 0 differentiates
    through the static solve (stages.sim.static); other windows start from their two stored states.
    θ = (E (R,), ν (R,)) is shared by the window frames."""

    def __init__(self, backend: WindowBackend, kind: str = "rest"):
        if kind not in ("rest", "equilibrium"):
            raise RslError(f"the start state should be 'rest' or 'equilibrium', found '{kind}'.")
        self.backend, self.kind = backend, kind
        self._x0 = None  # the last x_0: the warm start of the next static solve

    @staticmethod
    def _tile(a, k):
        return np.tile(np.asarray(a, float), (k, 1))

    def forward(self, frames: Sequence[int], E, nu, before) -> np.ndarray:
        """States (w, …) of ``frames``; ``before`` = [state t0−2, state t0−1] (unused when frames[0] = 0)."""
        b, w = self.backend, len(frames)
        if frames[0] != 0:
            return b.forward(list(frames), self._tile(E, w), self._tile(nu, w), before)
        x0 = b.start(E, nu, self.kind, self._x0)
        self._x0 = x0
        if w == 1:
            return x0[None]
        rest = b.forward(list(frames[1:]), self._tile(E, w - 1), self._tile(nu, w - 1), np.stack([x0, x0]))
        return np.concatenate([x0[None], rest])

    def backward(self, frames, E, nu, states, before, dL_dX) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν) (R,) of a loss of the window's positions, dL_dX (w, n, 3)."""
        b, w = self.backend, len(frames)
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
        if frames[0] != 0:
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
    (without it frame f's loss, constant in θ, would still pull θ: docs/results/vision_bias.md).
    """

    def __init__(self, backend: WindowBackend, obs: Observation, n_regions: int, poisson_range: tuple[float, float],
                 start: str = "rest"):
        self.backend, self.obs, self.R, self.prange = backend, obs, n_regions, poisson_range
        self.win: Window = StartWindow(backend, start)  # StaticWindow for --mode static
        self.rebind = True
        self.anchor_frame = int(getattr(obs, "fit_frame", 0))
        # run()'s frame → state store.  A window after the anchor frame starts from stored states that were
        # simulated from the *stored* anchor state, under the θ of their own time (E may have changed since):
        # it anchors the observations there, held fixed, like its starting states (re-simulating x_f with the
        # current θ moved the Gaussians off the trajectory once E had changed).  Set by run() for
        # --vision-anchor stored; None: always re-simulated (AdaptConfig.vision_anchor).
        self.stored: dict[int, np.ndarray] | None = None

    def anchor_positions(self, E: np.ndarray, nu: np.ndarray) -> np.ndarray:
        """The anchor frame (0 for markers, the Gaussians' fit frame for images) simulated with θ under the start
        convention (frame 0 = x_0(θ)), positions (n, 3)."""
        k = self.anchor_frame + 1
        X = self.win.forward(list(range(k)), E, nu, None)
        self._anchor_states = (np.array(E, float), np.array(nu, float), X)  # reused by the anchor's adjoint
        return self.backend.decode(X[-1:])[0]

    def __call__(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, need_grad: bool = True):
        """(states (w, …), per-frame losses (w,), dL/dp (2R,) or None, (forward_s, backward_s, loss_s))."""
        R, backend = self.R, self.backend
        E, nu = theta_from_params(p[:R], p[R:], self.prange)
        w = len(frames)
        Ew, nuw = np.tile(E, (w, 1)), np.tile(nu, (w, 1))
        t0 = time.perf_counter()
        rebind = self.rebind
        if rebind and self.stored is not None and isinstance(self.win, StartWindow) and frames[0] > \
                self.anchor_frame and self.anchor_frame in self.stored:
            self.obs.rebind(backend.decode(np.asarray(self.stored[self.anchor_frame])[None])[0])
            rebind = False  # the stored anchor does not move with θ: no anchor part in dL/dθ
        elif rebind:
            self.obs.rebind(self.anchor_positions(E, nu))
        states = self.win.forward(list(frames), E, nu, before)
        X = backend.decode(states)
        t1 = time.perf_counter()
        losses, dX = self.obs.loss(frames, X)
        t2 = time.perf_counter()
        g = None
        if need_grad:
            dE, dnu = self.win.backward(list(frames), E, nu, states, before, dX)
            ga = getattr(self.obs, "anchor_grad", None)  # images: the anchor x_f(θ) moves the Gaussians too
            if rebind and ga is not None and np.any(ga):
                k = self.anchor_frame + 1
                aE0, anu0, sa = getattr(self, "_anchor_states", (None, None, None))
                if sa is None or not (np.array_equal(aE0, E) and np.array_equal(anu0, nu)):
                    sa = self.win.forward(list(range(k)), E, nu, None)
                dXa = np.zeros((k,) + backend.decode(sa[-1:]).shape[1:])
                dXa[-1, :len(ga)] = ga
                aE, anu = self.win.backward(list(range(k)), E, nu, sa, None, dXa)
                dE, dnu = dE + aE, dnu + anu
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

    def __init__(self, objective: "WindowObjective", fit_poisson: bool, s_fixed: np.ndarray):
        self.obj, self.fit_poisson, self.s_fixed = objective, fit_poisson, s_fixed
        self.young_range: tuple[float, float] | None = None  # bounds of E (Pa), [material] young_range
        self.rebind_anchor = True  # re-anchor the observations at x_anchor(θ) (until a material change)
        self.rebind_next = True  # re-anchor at the next linearisation
        self.R = objective.R
        self.k_theta = self.R * (2 if fit_poisson else 1)
        self.times = [0.0, 0.0, 0.0]  # forward, sensitivity, residuals/render
        self.last_states = None
        self.last_frames: list[np.ndarray] = []  # per frame residuals of the last evaluation
        self.last_jac: list[np.ndarray] = []

    def theta(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(E, ν, s) from the unknowns."""
        R = self.R
        s = p[R:2 * R] if self.fit_poisson else self.s_fixed
        E, nu = theta_from_params(p[:R], s, self.obj.prange)
        return E, nu, s

    def evaluate(self, frames: Sequence[int], p: np.ndarray, before: np.ndarray, D: np.ndarray | None,
                 need_jac: bool, rebind: bool = True):
        """(r (m,), J (m, k) or None); the window's states are kept in ``last_states``."""
        obj, R = self.obj, self.R
        backend = obj.backend
        E, nu, s = self.theta(p)
        w = len(frames)
        Ew, nuw = np.tile(E, (w, 1)), np.tile(nu, (w, 1))
        c = p[self.k_theta:]
        b = before if D is None or not len(c) else before + np.tensordot(c, D, axes=1)
        t0 = time.perf_counter()
        anchored = rebind and obj.rebind and self.rebind_anchor
        smooth = getattr(obj.obs, "binding_jacobian", None) is not None  # markers: d binding/dθ goes into J
        x_anchor = None
        if anchored and (smooth or (need_jac and self.rebind_next)):
            # markers: re-anchored at every evaluation (r(p) is one smooth function of p, its J includes the
            # binding's derivative); images: once per solve, at its first linearisation (J leaves it out)
            self.rebind_next = False
            x_anchor = obj.anchor_positions(E, nu)
            obj.obs.rebind(x_anchor)
        states = obj.win.forward(list(frames), E, nu, b)
        X = backend.decode(states)
        t1 = time.perf_counter()
        rs = obj.obs.residuals(frames, X)
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
        Js = obj.obs.jacobian(frames, X, dX)
        if x_anchor is not None and smooth:
            # the anchor frame's own sensitivity (frame 0 = x_0(θ), or the fit frame simulated from it)
            ka = obj.anchor_frame + 1
            sa = obj.win.forward(list(range(ka)), E, nu, None)
            dXa = obj.win.sensitivity(list(range(ka)), E, nu, sa, None, de, dn)[:, -1]
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


def _sigma_from_cov(gn: GNWindow, p: np.ndarray, cov: np.ndarray, model_error: float = 0.0,
                    model_error_poisson: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """σ of E and of ν per region from the covariance of p (k, k):

        σ_E = E √(σ²_logE + e²),   σ_ν = √((ν'(s) σ_s)² + e_ν²)  (0 when ν is held),

    e = ``model_error``, e_ν = ``model_error_poisson`` (the error of E, relative, and of ν that the discretisation
    itself makes, added in quadrature: it does not average out over frames).  A parameter held at a bound of its range ([material] young_range, poisson_range)
    reports at least the σ of a uniform prior over the range (stages.estimator.bounded_sigma): there the data
    do not locate it (and the sigmoid's slope ν'(s) → 0 would shrink σ_ν to nothing)."""
    from stages.estimator import bounded_sigma

    R = gn.R
    E, nu, s = gn.theta(p)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    s_log = np.sqrt(sd[:R] ** 2 + float(model_error) ** 2)
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


def _state_directions(backend, stored: dict, t0: int, first: int, scale: float, theta=None
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


def _past_directions(sens: dict, t0: int, k_theta: int, sigma: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Correction directions of the two states before a window starting at t0 along their sensitivities to θ
    (``sens``: frame → d state/dp (k_θ, …), propagated through every window since frame 0): a correction
    c (k_θ,) moves them by Σ_j c_j ∂x/∂p_j — to first order, the past re-simulated with p + c.  Returns
    (D (k_θ, 2, …), prior σ (k_θ,)), or None when those sensitivities are not known (frames before the range)."""
    a, b = max(t0 - 2, 0), max(t0 - 1, 0)
    if t0 < 1 or a not in sens or b not in sens:
        return None
    return np.stack([sens[a], sens[b]], axis=1), np.full(k_theta, float(sigma))


# =========================================================================== mesh refinement
def _refined_mesh(mesh: MeshArtefact, levels: int) -> MeshArtefact:
    from stages.sim.mesh import rest_quantities

    v, t, reg = mesh.vertices, mesh.tets, mesh.tet_region
    for _ in range(levels):
        v, t, reg = refine_tets(v, t, reg)
    vol, dm_inv, masses = rest_quantities(v, t, mesh.density)
    return dataclasses.replace(mesh, vertices=v, tets=t, tet_region=reg, rest_volumes=vol, dm_inv=dm_inv,
                               vertex_masses=masses, handles={})


# =========================================================================== the stage
@dataclass
class _Record:
    frames: list = dataclasses.field(default_factory=list)
    young: list = dataclasses.field(default_factory=list)
    poisson: list = dataclasses.field(default_factory=list)
    loss: list = dataclasses.field(default_factory=list)
    frame_loss: list = dataclasses.field(default_factory=list)
    t_fwd: list = dataclasses.field(default_factory=list)
    t_bwd: list = dataclasses.field(default_factory=list)
    t_ren: list = dataclasses.field(default_factory=list)
    t_tot: list = dataclasses.field(default_factory=list)
    young_sigma: list = dataclasses.field(default_factory=list)
    poisson_sigma: list = dataclasses.field(default_factory=list)


def _parse_frames(spec: str, n_avail: int | None, where: Path) -> tuple[int, int | None]:
    if not spec.strip():
        return 0, n_avail
    try:
        a_s, b_s = spec.split(":")
        a = int(a_s) if a_s.strip() else 0
        b = int(b_s) if b_s.strip() else n_avail
    except ValueError:
        raise RslError(f"{where}: --frames should be A:B (e.g. 0:60), found '{spec}'.") from None
    if a < 0 or (b is not None and b <= a):
        raise RslError(f"{where}: --frames {spec} is an empty or negative range.")
    if n_avail is not None and b is not None and b > n_avail:
        raise RslError(f"{where}: --frames {spec} asks for frames up to {b - 1} but only {n_avail} exist.")
    return a, b


def run(config: AdaptConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Adapt θ = (E, ν) per region to the capture; writes WS/adapt.h5."""
    if config.loss != "vision":
        return _run(config, reporter)
    from stages.render.gaussians import one_torch_thread

    with one_torch_thread():  # torch's pool only spins against the rasterizer's threads (20× per render under load)
        return _run(config, reporter)


def _run(config: AdaptConfig, reporter: Reporter) -> Path:
    from stages.sim.scene import frame_inputs, make_scene

    ws = Path(config.workspace)
    capture = load_capture(config.capture)
    prepare_workspace(ws)  # writable? (checked before any compute) and no stale temp files
    if not (isinstance(config.substeps, int) and config.substeps >= 1):
        raise RslError(f"{capture.toml_path}: --substeps must be a whole number of at least 1, found "
                       f"{config.substeps}.")
    if config.window < 1:
        raise RslError(f"{capture.toml_path}: --window must be at least 1, found {config.window}.")
    if config.estimator not in ("auto", "adam", "gn"):
        raise RslError(f"{capture.toml_path}: --estimator should be auto, adam or gn, found '{config.estimator}'.")
    estimator = resolve_estimator(config)
    if not config.process_noise >= 0:
        raise RslError(f"{capture.toml_path}: --process-noise must be 0 or more, found {config.process_noise}.")
    if config.iters_per_frame < 1 or config.offline_iters < 1:
        raise RslError(f"{capture.toml_path}: --iters-per-frame and --offline-iters must be at least 1.")
    if config.refine and config.space != "full":
        raise RslError(f"{ws / KIND_FILES['subspace']}: --refine needs --space full (the subspace is "
                       f"trained on mesh.h5's vertices).")
    mesh_path = ws / KIND_FILES["mesh"]
    mesh = MeshArtefact.load(mesh_path)
    check_mesh_source(mesh_path, capture.mesh_path)
    controls = capture.controls()
    check_obstacles_clear(controls, mesh.vertices, capture.controls_path)
    sim_mesh = _refined_mesh(mesh, config.refine) if config.refine else mesh
    scene = make_scene(sim_mesh, controls, capture.material.model, capture.dt, capture.gravity)
    n = mesh.n_vertices
    inputs_cache: dict[int, object] = {}

    def inputs(t: int):
        if t not in inputs_cache:
            inputs_cache[t] = frame_inputs(scene, controls, t)
        return inputs_cache[t]

    inputs_used = [mesh_path, capture.toml_path, capture.controls_path]
    if config.space == "full":
        backend = _FullSpace(scene, inputs, config.solver)
    else:
        from stages.artefacts import SubspaceArtefact
        from stages.subspace import ReducedModel

        sub_path = ws / KIND_FILES["subspace"]
        check_same_mesh(mesh_path, sub_path)
        backend = _ReducedSpace(ReducedModel.from_artefacts(SubspaceArtefact.load(sub_path), scene), inputs)
        inputs_used.append(sub_path)

    R = scene.n_regions
    names = list(scene.region_names)
    mat = capture.material
    young0 = np.array([config.young_init or mat.region_young(r) for r in names], float)
    if config.young_init is not None and not mat.young_range[0] <= config.young_init <= mat.young_range[1]:
        raise RslError(f"{capture.toml_path}: --young-init {config.young_init:g} Pa lies outside [material] "
                       f"young_range {list(mat.young_range)}; give a value inside it or widen the range.")
    backend = substepped(backend, config.substeps, lambda f: frame_inputs(scene, controls, f))  # --substeps
    backend = _Guarded(backend, _SolveGuard(sim_mesh.vertices, sim_mesh.tets, names, capture.toml_path, mat.young))
    poisson0 = np.array([config.poisson_init if config.poisson_init is not None else mat.region_poisson(r)
                         for r in names], float)
    if config.loss == "markers":
        # Markers bind to the simulated frame-0 surface; the binding is refreshed as θ changes
        # (frame 0 is x_0(θ): with start = "equilibrium" it depends on θ).
        x0 = backend.decode(StartWindow(backend, capture.start).forward([0], young0, poisson0, None))[0]
        obs = _Markers(capture, x0, mesh.surface_faces, n)
        inputs_used.append(capture.markers_path)
        if obs.far > 0.05:
            reporter.warn(f"{capture.markers_path}: a frame-0 marker lies {obs.far:.1%} of the object size "
                          f"away from the frame-0 surface simulated with the initial E; is the marker frame the "
                          f"mesh's frame, or is the initial E far off?")
    else:
        check_same_mesh(mesh_path, ws / KIND_FILES["gaussians"])
        obs = _Vision(capture, ws, config.cameras, mesh, config.appearance, config.gaussian_anchor)
        inputs_used += [ws / KIND_FILES[k] for k in ("cameras", "gaussians", "masks")]
        inputs_used += [capture.root / "frames" / c if src.files is not None else src.video
                        for c, src in obs.sources.items()]  # the frames read (a hash per camera)

    prange = mat.poisson_range
    if not config.fit_poisson:  # ν held at its initial value, per region
        prange = (poisson0.copy(), poisson0.copy())
    if np.any(young0 <= 0):
        raise RslError(f"{capture.toml_path}: the initial Young's modulus must be positive.")
    if config.fit_poisson and config.poisson_init is not None and not prange[0] <= config.poisson_init <= prange[1]:
        raise RslError(f"{capture.toml_path}: --poisson-init {config.poisson_init} lies outside "
                       f"poisson_range {list(prange)}.")
    log_e, s_nu = params_from_theta(young0, np.clip(poisson0, *prange), prange)

    n_avail = None if config.follow else (obs.count_checked() if hasattr(obs, "count_checked") else obs.available())
    if n_avail == 0:
        raise CaptureError(f"{capture.root}: holds no frame to adapt to.")
    first, last = _parse_frames(config.frames, n_avail, capture.toml_path)
    rec = _Record()
    # frame -> latest state (positions or z); with --substeps it tells the backend which state a frame holds
    stored: dict[int, np.ndarray] = _StoredStates(backend) if config.substeps > 1 else {}
    t_start = time.perf_counter()
    interrupted = False
    status = "failed"
    failure: BaseException | None = None

    def state_at(t: int) -> np.ndarray:
        """The stored state of frame t; before frame 0, x_{−1} = x_{−2} = x_0 (the start convention)."""
        t = max(t, 0)
        return stored[t] if t in stored else backend.rest_state  # (a window holding frame 0 ignores it)

    # Frames before the range: a plain forward simulation with the initial θ.
    if first > 0:
        with reporter.task("simulating frames before the range", None):
            X0 = StartWindow(backend, capture.start).forward(list(range(first)), young0,
                                                             theta_from_params(log_e, s_nu, prange)[1], None)
        for t in range(first):
            stored[t] = X0[t]

    lr = np.concatenate([np.full(R, config.lr), np.full(R, config.lr_poisson if config.fit_poisson else 0.0)])
    adam = Adam(lr, beta1=config.beta1)
    params = np.concatenate([log_e, s_nu])

    objective = WindowObjective(backend, obs, R, prange, capture.start)
    if config.loss == "vision" and config.vision_anchor == "stored":
        objective.stored = stored  # windows after the Gaussians' fit frame anchor them at its stored state
    elif config.vision_anchor not in ("simulated", "stored"):
        raise RslError(f"{capture.toml_path}: --vision-anchor should be simulated or stored, found "
                       f"'{config.vision_anchor}'.")
    if (config.mode == "online" and not config.follow and capture.start == "equilibrium" and last is not None
            and last - first >= 1 and controls_static(inputs, list(range(first, last)))):
        reporter.info(f"{capture.controls_path}: no control moves over frames {first}..{last - 1}: identifying the "
                      f"material from the static equilibria (--mode static).")
        config = dataclasses.replace(config, mode="static")
    if config.mode == "static":
        if last is None:
            raise RslError(f"{capture.toml_path}: --mode static needs a finite frame range (not --follow without "
                           f"--frames).")
        objective.win = StaticWindow(backend)
        if config.loss == "vision" and controls_static(inputs, list(range(first, last))):
            # every frame is the fit frame's equilibrium, and the Gaussians re-bound to x_0(θ) render it alike
            # for every θ (docs/tutorial.md, "Static captures")
            reporter.warn(f"{capture.controls_path}: no control moves, so every frame shows the equilibrium the "
                          f"Gaussians were fitted to: the image loss hardly depends on E here; use --loss markers, "
                          f"or check with `rsl evaluate --sweep --sweep-loss silhouette`.")
        if config.loss == "markers":  # the markers bind to the frame-0 equilibrium
            obs.rebind(backend.decode(objective.win.forward([0], young0, poisson0)[0][None])[0])

    def evaluate(frames: list[int], p: np.ndarray, need_grad: bool):
        before = np.stack([state_at(frames[0] - 2), state_at(frames[0] - 1)])
        return objective(frames, p, before, need_grad)

    # Ctrl-C raises KeyboardInterrupt at once as usual, but is also counted (stages/interrupt.py): one that
    # compiled code lost ends the loop when the frame is recorded (the progress step), and none can abort the save
    ctrl_c = CtrlC()
    loop_reporter = CheckedReporter(reporter, ctrl_c)
    try:
        ctrl_c.install()
        if estimator == "gn" and config.mode == "online":
            _online_gn(config, obs, first, last, log_e, s_nu, objective, state_at, stored, rec, prange,
                       loop_reporter, backend, mat.young_range)
        elif estimator == "gn":  # offline or static: one θ for every frame
            if last is None:
                raise RslError(f"{capture.toml_path}: --mode offline needs a finite frame range (not --follow "
                               f"without --frames).")
            _offline_gn(config, obs, first, last, log_e, s_nu, objective, state_at, stored, rec, prange,
                        loop_reporter, mat.young_range)
        elif config.mode == "online":
            _online(config, obs, capture, first, last, params, adam, evaluate, stored, rec, R, prange,
                    loop_reporter, backend)
        else:
            if last is None:
                raise RslError(f"{capture.toml_path}: --mode offline needs a finite frame range (not --follow "
                               f"without --frames).")
            params = _offline(config, first, last, params, adam, evaluate, stored, rec, R, prange, loop_reporter)
        status = "complete"
    except KeyboardInterrupt:
        # With --follow, Ctrl-C is the way to end: the frames so far are the complete result.
        interrupted, status = True, ("complete" if config.follow else "interrupted")
    except Exception as e:
        if ctrl_c.pressed:  # after a Ctrl-C an error is its doing (numba turns a KeyboardInterrupt into SystemError)
            interrupted, status = True, ("complete" if config.follow else "interrupted")
        elif isinstance(e, RslError):
            failure = e
        else:
            raise
    finally:
        ctrl_c.defer = True  # first: from here a Ctrl-C is only counted, it cannot abort the save
        # Whatever ends the loop (the last frame, Ctrl-C, a failed solve), the frames so far are saved
        # (atomically); extra["status"] says which.  Only a complete run writes adapt.h5: an interrupted or
        # failed one goes to adapt.partial.h5 and the previous adapt.h5 stays as it was.
        try:
            _trim_record(rec)
            if rec.frames:
                path = _save(config, ws, backend, mesh, rec, stored, names, inputs_used, obs,
                             status, time.perf_counter() - t_start, n, ended_by_ctrl_c=interrupted)
        finally:
            ctrl_c.restore()
    final = ws / KIND_FILES["adapt"]
    unchanged = f"{final.name} is unchanged" if final.exists() else f"no {final.name} was written"
    if failure is not None:
        kept = (f"the {len(rec.frames)} frame(s) done are kept in {path.name}, {unchanged}" if rec.frames
                else unchanged)
        raise type(failure)(f"{str(failure).rstrip('.')} ({kept}).") from None
    if not rec.frames:
        if interrupted:
            raise Interrupted(f"no frame was finished; {unchanged}.")
        raise RslError(f"{capture.root}: no frame was processed (none arrived within --follow-timeout).")
    if interrupted and not config.follow:
        raise Interrupted(f"the {len(rec.frames)} frame(s) done are kept in {path}; {unchanged}.")
    _report(config, reporter, rec, names, backend, scene, mesh, path, interrupted)
    return path


def _online(config, obs, capture, first, last, params, adam, evaluate, stored, rec, R, prange, reporter, backend):
    w = config.window
    total = None if last is None else last - first
    with reporter.task(f"adapt online ({backend.space}, {obs.kind}, w={w})", total) as task:
        T = first
        while last is None or T < last:
            if config.follow and not _wait_for(obs, T, config.follow_timeout, reporter=reporter):
                break
            frames = list(range(max(first, T - w + 1), T + 1))
            tt = time.perf_counter()
            tf = tb = tr = 0.0
            for _ in range(config.iters_per_frame):
                states, losses, g, (a, b, c) = evaluate(frames, params, True)
                tf, tb, tr = tf + a, tb + b, tr + c
                params[:] = adam.step(params, g)
            for i, t in enumerate(frames):
                stored[t] = states[i]
            E, nu = theta_from_params(params[:R], params[R:], prange)
            rec.frames.append(T)
            rec.young.append(E)
            rec.poisson.append(nu)
            rec.loss.append(float(losses.sum()))
            rec.frame_loss.append(float(losses[-1]))
            rec.t_fwd.append(tf)
            rec.t_bwd.append(tb)
            rec.t_ren.append(tr)
            rec.t_tot.append(time.perf_counter() - tt)
            task.advance(1, frame=T, E=" ".join(f"{e:.4g}" for e in E), loss=float(losses.sum()),
                         s_per_frame=rec.t_tot[-1])
            T += 1


def _frame_loss(obs, r: np.ndarray) -> float:
    """The loss Adam minimises, from one frame's residuals: Σ r² (markers), Σ |r| (images, L1)."""
    return float(r @ r) if obs.kind == "markers" else float(np.abs(r).sum())


def _gn_prior(p: np.ndarray) -> "object":
    """The initial arrival cost: N(p, I) — σ = 1 on log E (a factor e either way) and on s."""
    from stages.estimator import Prior

    return Prior(p.copy(), np.eye(len(p)))


def _gn_solve(gn: GNWindow, frames, p0, prior, before, D, sigma, obs, iterations: int):
    """One window's Gauss–Newton solve; afterwards gn.last_* hold the window evaluated at the estimate.
    log E stays inside [material] young_range and moves at most 0.5 (a factor 1.65) per iteration: in the
    stiff regime the motion hardly depends on E and an unbounded step could run away."""
    from stages.estimator import gauss_newton

    k, kt = len(p0), gn.k_theta
    lower, upper, cap = np.full(k, np.nan), np.full(k, np.nan), np.full(k, np.inf)
    if gn.young_range is not None:
        lower[:gn.R], upper[:gn.R] = np.log(gn.young_range[0]), np.log(gn.young_range[1])
    cap[:kt] = 0.5
    gn.rebind_next = True
    first = [True]

    def evaluate(pp, nj):
        # a trial step whose simulation collapses (inverted elements, a failed solve) is a rejected step: the
        # damping grows and a shorter step is tried; the first evaluation (the starting point) still raises
        try:
            return gn.evaluate(frames, pp, before, D, nj)
        except SolveCollapsed:
            if nj or first[0]:
                raise
            gn.last_p = np.full(len(pp), np.nan)  # the observations may be bound to the failed trial: re-evaluate
            return np.full(1, np.inf), None
        finally:
            first[0] = False

    res = gauss_newton(evaluate, p0, prior, sigma,
                       max_iterations=iterations, huber=obs.huber, max_step=cap, lower=lower, upper=upper)
    lin = (list(gn.last_frames), list(gn.last_jac))  # per-frame residuals and Jacobians at res.p_lin
    if not np.array_equal(gn.last_p, res.p):
        gn.evaluate(frames, res.p, before, D, False)
    return res, lin


def _online_gn(config, obs, first, last, log_e, s_nu, objective, state_at, stored, rec, prange, reporter, backend,
               young_range=None):
    """Online moving-horizon estimation (stages.estimator): per new frame, Gauss–Newton on the window's
    unknowns against the arrival-cost prior; the frame leaving the window is folded into the prior, which then
    takes one frame of process noise."""
    from scipy.linalg import block_diag

    from stages.estimator import ChangeDetector, Prior, WindowFilter, huber_weights

    R, w = objective.R, config.window
    gn = GNWindow(objective, config.fit_poisson, s_nu)
    gn.young_range = young_range
    k_th = gn.k_theta
    p_th = np.concatenate([log_e, s_nu]) if config.fit_poisson else log_e.copy()
    filt = WindowFilter(_gn_prior(p_th), np.full(k_th, float(config.process_noise)))
    sigma = None
    sens: dict[int, np.ndarray] = {}  # frame -> d state/dp (k_θ, …)
    sig_hist: list[float] = []
    changes: list[int] = []  # frames where a change of material was detected
    detector = ChangeDetector(config.change_threshold)
    rec.innovation = []  # per frame: the normalised innovation z of the change test (NaN: not tested)
    start_w = first  # the window never reaches before the last change point
    modes_failed = False
    total = None if last is None else last - first
    with reporter.task(f"adapt online gn ({backend.space}, {obs.kind}, w={w})", total) as task:
        T = first
        while last is None or T < last:
            if config.follow and not _wait_for(obs, T, config.follow_timeout, reporter=reporter):
                break
            frames = list(range(max(start_w, T - w + 1), T + 1))
            t0 = frames[0]
            before = np.stack([state_at(t0 - 2), state_at(t0 - 1)])
            tt = time.perf_counter()
            gn.times = [0.0, 0.0, 0.0]
            z_innov = float("nan")
            if (sigma is not None and config.change_threshold > 0 and T >= 2 and len(frames) > 1
                    and (not changes or T - changes[-1] > w)):  # at most once per window length
                # innovation test (stages.estimator.ChangeDetector): the new frame simulated from the stored
                # states with the predicted θ, its residuals against the noise level the windows reach
                Ep, nup, _ = gn.theta(p_th)
                xs = objective.win.forward([T], Ep, nup, np.stack([state_at(T - 2), state_at(T - 1)]))
                rn = obs.residuals([T], backend.decode(xs))[0]
                z_innov = ChangeDetector.ratio(rn, sigma)
                if len(rn) and detector.update(z_innov):
                    # a change point: the window restarts at T (the frames before it saw the old material and
                    # are not folded into the arrival cost) and the θ prior is widened
                    filt.prior = Prior(filt.prior.mean, filt.prior.cov + np.eye(k_th) * config.change_sigma ** 2)
                    changes.append(T)
                    # the anchor frame (0, or the Gaussians' fit frame) showed the old material: its binding is
                    # kept as it is from here on instead of being re-simulated with the new θ
                    gn.rebind_anchor = False
                    start_w = T
                    frames = [T]
                    t0 = T
                    before = np.stack([state_at(t0 - 2), state_at(t0 - 1)])
                    rec.changes = changes
            rec.innovation.append(z_innov)
            sc, past_dirs = None, False
            if config.state_correction == "states" and obs.kind == "markers" and not modes_failed:
                try:
                    sc = _state_directions(backend, stored, t0, first, STATE_PRIOR_SCALE, gn.theta(p_th)[:2])
                except (ArithmeticError, RuntimeError, ValueError) as e:  # eigsh / a singular K: fall back
                    reporter.warn(f"the vibration modes for --state-correction states failed ({e}); correcting "
                                  f"along the θ sensitivities instead (--state-correction past).")
                    modes_failed = True
            if sc is None and config.state_correction != "off" and (modes_failed or obs.kind == "vision"
                                                                     or config.state_correction == "past"):
                # "past", or "states" with images: there each correction direction costs 2 renders per frame and
                # camera (the Jacobian's central differences), so the 2R sensitivity directions are used
                sc = _past_directions(sens, t0, k_th, config.state_prior)
                past_dirs = True
            D, prior, p0 = None, filt.prior, p_th.copy()
            if sc is not None:
                D, sd = sc
                prior = Prior(np.concatenate([filt.prior.mean, np.zeros(len(D))]),
                              block_diag(filt.prior.cov, np.diag(sd ** 2)))
                p0 = np.concatenate([p_th, np.zeros(len(D))])
            if sigma is None:  # the first window: the noise level seen at the initial θ (conservative)
                r0, _ = gn.evaluate(frames, p0, before, D, False)
                sigma = max(obs.noise_scale(r0), obs.noise_floor)
            res, (r_lin, J_lin) = _gn_solve(gn, frames, p0, prior, before, D, sigma, obs, config.iters_per_frame)
            p_th = res.p[:k_th].copy()
            for i, t in enumerate(frames):
                stored[t] = gn.last_states[i]
                S = gn.last_state_sens  # (k, w, …) at the last linearisation
                # d x_t/dp through the whole past: the window's θ columns plus, by linearity, the columns of the
                # "past" correction (whose directions are the before states' own sensitivities)
                sens[t] = S[:k_th, i] + (S[k_th:2 * k_th, i] if past_dirs and D is not None else 0.0)
            if D is not None and t0 >= 1:  # the corrected starting states replace the stored ones
                stored[max(t0 - 2, 0)], stored[t0 - 1] = gn.last_before[0], gn.last_before[1]
            # σ from the covariance with the noise level this window's own residuals show (RSS/dof, Huber-
            # consistent: estimator.residual_scale2), the ν bounds and the model-error floor (_sigma_from_cov)
            sE, sN = _sigma_from_cov(gn, res.p, res.cov_scaled[:k_th, :k_th], config.model_error,
                                     config.model_error_poisson)
            if len(frames) == w:  # frame t0 leaves the window: fold it into the arrival cost
                r0 = r_lin[0] + J_lin[0][:, k_th:] @ (res.p[k_th:] - res.p_lin[k_th:])
                s_fold = sigma * float(np.sqrt(max(res.scale2, 1.0)))  # never more certain than σ says
                filt.leave(res.p_lin[:k_th], r0, J_lin[0][:, :k_th], s_fold, huber_weights(r0, sigma, obs.huber))
            r_all = np.concatenate(gn.last_rs)
            # the noise level: the median over the last 5 frames of the windows' residual scale per degree of
            # freedom, √(RSS/(m − k)) (robust: one window's transient misfit does not inflate it at once)
            dof = max(len(r_all) - len(res.p), 1)
            sig_hist.append(max(obs.noise_scale(r_all) * float(np.sqrt(len(r_all) / dof)), obs.noise_floor))
            sigma = float(np.median(sig_hist[-5:]))
            E, nu, _ = gn.theta(res.p)
            losses = [_frame_loss(obs, r) for r in gn.last_rs]
            rec.frames.append(T)
            rec.young.append(E)
            rec.poisson.append(nu)
            rec.young_sigma.append(sE)
            rec.poisson_sigma.append(sN)
            rec.loss.append(float(np.sum(losses)))
            rec.frame_loss.append(losses[-1])
            rec.t_fwd.append(gn.times[0])
            rec.t_bwd.append(gn.times[1])
            rec.t_ren.append(gn.times[2])
            rec.t_tot.append(time.perf_counter() - tt)
            task.advance(1, frame=T, E=" ".join(f"{e:.4g}±{s:.2g}" for e, s in zip(E, sE)),
                         loss=rec.loss[-1], s_per_frame=rec.t_tot[-1])
            T += 1


def _offline_gn(config, obs, first, last, log_e, s_nu, objective, state_at, stored, rec, prange, reporter,
                young_range=None):
    """Offline baseline with the same Gauss–Newton machinery: one θ, every frame in one window."""
    gn = GNWindow(objective, config.fit_poisson, s_nu)
    gn.young_range = young_range
    p = np.concatenate([log_e, s_nu]) if config.fit_poisson else log_e.copy()
    frames = list(range(first, last))
    before = np.stack([state_at(first - 2), state_at(first - 1)])
    with reporter.task(f"adapt offline gn ({len(frames)} frames)", None):
        r0, _ = gn.evaluate(frames, p, before, None, False)
        sigma = max(obs.noise_scale(r0), obs.noise_floor)
        done, q = 0, p.copy()
        while done < config.offline_iters:  # solves of ≤ 5 iterations, the observations re-anchored before each
            n_it = min(5, config.offline_iters - done)
            res, _ = _gn_solve(gn, frames, q, _gn_prior(p), before, None, sigma, obs, n_it)
            done += n_it
            moved = float(np.max(np.abs(res.p - q)))
            q = res.p
            if moved < 1e-4:
                break
        # σ of the estimate with the noise level of the final residuals
        sigma2 = max(obs.noise_scale(np.concatenate(gn.last_rs)), obs.noise_floor)
        res, _ = _gn_solve(gn, frames, q, _gn_prior(p), before, None, sigma2, obs, 1)
    E, nu, _ = gn.theta(res.p)
    sE, sN = _sigma_from_cov(gn, res.p, res.cov_scaled, config.model_error, config.model_error_poisson)
    k = len(frames)
    tf, tb, tr = gn.times
    for i, t in enumerate(frames):
        stored[t] = gn.last_states[i]
        rec.frames.append(t)
        rec.young.append(E)
        rec.poisson.append(nu)
        rec.young_sigma.append(sE)
        rec.poisson_sigma.append(sN)
        loss = _frame_loss(obs, gn.last_rs[i])
        rec.loss.append(loss)
        rec.frame_loss.append(loss)
        rec.t_fwd.append(tf / k)
        rec.t_bwd.append(tb / k)
        rec.t_ren.append(tr / k)
        rec.t_tot.append((tf + tb + tr) / k)


def _wait_for(obs, t: int, timeout: float, poll: float = 0.1, reporter: Reporter = SilentReporter()) -> bool:
    """Wait until frame t is observed; False after ``timeout`` s without it (0: wait for ever).
    Says once that it waits, so a user (or a script) sees the frames so far are done."""
    t0 = time.monotonic()
    if obs.available() <= t:
        reporter.info(f"waiting for frame {t} (frames 0–{t - 1} done; Ctrl-C ends and saves them)")
    while obs.available() <= t:
        if timeout and time.monotonic() - t0 > timeout:
            return False
        time.sleep(poll)
    return True


def _offline(config, first, last, params, adam, evaluate, stored, rec, R, prange, reporter):
    frames = list(range(first, last))
    tf = tb = tr = 0.0
    best = (math.inf, params.copy())
    with reporter.task(f"adapt offline ({len(frames)} frames)", config.offline_iters) as task:
        for _ in range(config.offline_iters):
            _, losses, g, (a, b, c) = evaluate(frames, params, True)
            tf, tb, tr = tf + a, tb + b, tr + c
            if losses.sum() < best[0]:
                best = (float(losses.sum()), params.copy())
            params = adam.step(params, g)
            E, _ = theta_from_params(params[:R], params[R:], prange)
            task.advance(1, E=" ".join(f"{e:.4g}" for e in E), loss=float(losses.sum()))
        states, losses, _, (a, b, c) = evaluate(frames, params, False)
        tf, tr = tf + a, tr + c
        if losses.sum() > best[0]:  # keep the best iterate
            params = best[1]
            states, losses, _, _ = evaluate(frames, params, False)
    E, nu = theta_from_params(params[:R], params[R:], prange)
    k = len(frames)
    for i, t in enumerate(frames):
        stored[t] = states[i]
        rec.frames.append(t)
        rec.young.append(E)
        rec.poisson.append(nu)
        rec.loss.append(float(losses[i]))
        rec.frame_loss.append(float(losses[i]))
        rec.t_fwd.append(tf / k)
        rec.t_bwd.append(tb / k)
        rec.t_ren.append(tr / k)
        rec.t_tot.append((tf + tb + tr) / k)
    return params


def _trim_record(rec: _Record) -> None:
    """Drop a frame whose record a Ctrl-C cut half-way (its entries are appended one by one): every per-frame
    list keeps the frames all of them have."""
    names = [f.name for f in dataclasses.fields(rec) if f.name not in ("young_sigma", "poisson_sigma")]
    names += [k for k in ("young_sigma", "poisson_sigma") if getattr(rec, k)]  # empty with Adam
    k = min(len(getattr(rec, f)) for f in names)
    for f in names:
        del getattr(rec, f)[k:]
    if hasattr(rec, "innovation"):  # gn: appended before the frame's other entries
        del rec.innovation[k:]


def _save(config, ws, backend, mesh, rec, stored, names, inputs_used, obs, status, wall_s, n,
          ended_by_ctrl_c: bool = False) -> Path:
    frames = np.asarray(rec.frames, np.int64)
    states = np.stack([stored[t] for t in rec.frames])
    X = backend.decode(states)[:, :n]
    extra = {
        "capture": str(Path(config.capture).resolve()),
        "frame_loss": rec.frame_loss,
        "iters_per_frame": config.iters_per_frame,
        "cameras": getattr(obs, "cameras", []),
        "gaussian_anchor": getattr(obs, "anchor_kind", None),
        "refine": config.refine,
        "substeps": config.substeps,
        "status": status,  # complete | interrupted | failed
        "estimator": resolve_estimator(config),
        "material_changes_detected": list(getattr(rec, "changes", [])),  # gn: frames whose innovation widened θ
        # gn: per frame, the change test's normalised innovation rᵀr/(mσ²) (None: not tested)
        "innovation_ratio": [None if not np.isfinite(z) else float(z) for z in getattr(rec, "innovation", [])],
        "ended": "ctrl-c" if ended_by_ctrl_c else ("last frame" if status == "complete" else "error"),
        "wall_s": wall_s,
        "young_meaning": _young_meaning(config, mesh),
    }
    art = AdaptArtefact(
        frames=frames, young=np.asarray(rec.young), poisson=np.asarray(rec.poisson), z=backend.z(states),
        positions=X, loss=np.asarray(rec.loss), time_forward_s=np.asarray(rec.t_fwd),
        time_backward_s=np.asarray(rec.t_bwd), time_render_s=np.asarray(rec.t_ren),
        time_total_s=np.asarray(rec.t_tot), region_names=names, mode=config.mode, space=backend.space,
        loss_kind=obs.kind, window=config.window if config.mode == "online" else len(frames), extra=extra,
        **_sigmas(rec))
    path = ws / (KIND_FILES["adapt"] if status == "complete" else PARTIAL_ADAPT)
    art.save(path, Provenance.make(config, inputs_used))
    if status == "complete":
        (ws / PARTIAL_ADAPT).unlink(missing_ok=True)  # superseded by this complete run
    return path


def _sigmas(rec: _Record) -> dict:
    """young_sigma / poisson_sigma (T, R) of the record (NaN where the estimator gives none: Adam)."""
    T, R = len(rec.frames), len(rec.young[0])
    out = {}
    for k in ("young_sigma", "poisson_sigma"):
        v = getattr(rec, k)
        out[k] = np.asarray(v, float) if len(v) == T else np.full((T, R), np.nan)
    return out


def _young_meaning(config: AdaptConfig, mesh: MeshArtefact) -> str:
    m = mesh.n_tets * 8 ** config.refine
    if mesh.order == 2:
        return (f"E is the modulus of the material as quadratic (10-node) tets resolve it ({m} tets; on the "
                f"sample bar their static sag is within 2.4 % of a fine reference, docs/results/convergence.md), "
                f"under the declared start state; fast motion at one implicit step per frame can still bias it.")
    return (f"E is the effective modulus of the linear-tet discretisation used ({m} tets"
            + (f", mesh.h5 refined {config.refine}x" if config.refine else "")
            + "): coarse linear tets are too stiff (they lock as ν → 0.5), so the adapted E is lower than the "
            "continuum E"
            + ("" if config.refine else "; --space full --refine 1 estimates it on a finer mesh") + ".")


def _report(config, reporter, rec, names, backend, scene, mesh, path, interrupted) -> None:
    med = lambda a: float(np.median(a)) if a else float("nan")  # noqa: E731
    f, b, r, t = med(rec.t_fwd), med(rec.t_bwd), med(rec.t_ren), med(rec.t_tot)
    reporter.info(f"{'space':>8} {'dofs':>7} {'r':>4} {'w':>3} | {'forward':>8} {'backward':>8} "
                  f"{'render':>8} {'total':>8}  (median s/frame)")
    reporter.info(f"{backend.space:>8} {3 * len(scene.rest):>7} {backend.dim:>4} {config.window:>3} | "
                  f"{f:8.3f} {b:8.3f} {r:8.3f} {t:8.3f}")
    reporter.info(_young_meaning(config, mesh))
    E, nu = rec.young[-1], rec.poisson[-1]
    if rec.young_sigma:  # the estimator's 1σ (E ± σ: the truth lies inside ±2σ about 95 % of the time)
        sE, sN = rec.young_sigma[-1], rec.poisson_sigma[-1]
        mats = ", ".join(f"{nm}: E={e:.4g} ± {se:.2g} Pa ν={v:.3f} ± {sn:.2g}"
                         for nm, e, se, v, sn in zip(names, E, sE, nu, sN))
    else:
        mats = ", ".join(f"{nm}: E={e:.4g} Pa ν={v:.3f}" for nm, e, v in zip(names, E, nu))
    stop = " (stopped early)" if interrupted else ""
    reporter.summary(f"adapted {len(rec.frames)} frames{stop} {config.mode} in {backend.space} space from "
                     f"{'markers' if config.loss == 'markers' else 'images'}: {mats} "
                     f"({'E of the material, P2 tets' if mesh.order == 2 else 'effective E of this linear mesh'}); "
                     f"per frame forward {f:.3f} s, backward {b:.3f} s, "
                     f"render {r:.3f} s, total {t:.3f} s → {path}")
