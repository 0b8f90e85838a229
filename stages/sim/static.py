"""Static equilibrium under gravity, loads, handles and contact, and its derivatives in θ = (E, ν).

The static potential is the incremental potential of implicit Euler without inertia and friction
(½/Δt² = 0, i.e. Δt = ∞, μ_f = 0):

    Π(x; θ) = Σ_e V_e Ψ(F_e; θ) − (M g + f)·x + Σ_h ½ k_h ‖x_h − x̄_h‖² + contact(x),

and the equilibrium x*(θ) = argmin Π solves r(x*, θ) = ∇_x Π = 0.  It is found by the same Newton
solver as a time step (stages.sim.scene.step on a copy of the scene with dt = ∞), started from
``x_init`` (default the rest shape); when plain Newton fails, by continuation on the external
load: gravity, loads and the handle targets' displacement from ``x_init`` scaled by λ = 1/k, …, 1,
each stage started from the last (k = 4, 16, 64 until one succeeds).

Derivatives (implicit function theorem, H = ∂r/∂x the exact Hessian of Π at x*):
    adjoint      H a = ∂L/∂x,   dL/dθ = −(∂r/∂θ)ᵀ a
    sensitivity  dx*/dθ = −H⁻¹ ∂r/∂θ      (2R, n, 3): E of every region, then ν.
Hard handles (``HandleSpec.hard``) fix their vertices: those DOFs are removed from H (identity rows)
and their sensitivity and adjoint are zero.

The reduced twin (``reduced_*``) does the same in a subspace x = φ(z): a ReducedModel built on the
dt = ∞, frictionless scene (:func:`static_model`), with h(z) = ∂Π(φ(z))/∂z = 0.
"""
from __future__ import annotations

import dataclasses
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from . import scene as sc
from .linsolve import NotPositiveDefinite

jax.config.update("jax_enable_x64", True)

_STATIC: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_STATIC_MODELS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
CONTINUATION = (1, 4, 16, 64)  # load stages tried in turn


def static_scene(scene: sc.Scene) -> sc.Scene:
    """The scene without inertia, friction and damping (dt = ∞, μ_f = 0, β = 0); cached per scene object."""
    if getattr(scene, "dt", None) == np.inf and scene.friction == 0.0 and getattr(scene, "damping", 0.0) == 0.0:
        return scene
    s = _STATIC.get(scene)
    if s is None:
        s = _STATIC[scene] = dataclasses.replace(scene, dt=np.inf, friction=0.0, damping=0.0)
    return s


def _hard_ids(scene) -> np.ndarray:
    """Vertex ids held by hard (Dirichlet) handles, (k,)."""
    ids = [np.asarray(h.ids) for h in scene.handles if getattr(h, "hard", False)]
    return np.unique(np.concatenate(ids)) if ids else np.zeros(0, np.int64)


def _scaled_inputs(scene, inputs, x_ref: np.ndarray, lam: float):
    """Inputs whose external load is λ (M g + f) (gravity folded into the loads) and whose handle
    targets are x_ref + λ (x̄ − x_ref)."""
    g_force = scene.masses[:, None] * scene.gravity[None, :]
    loads = lam * (np.asarray(inputs.load_forces) + g_force) - g_force
    targets = tuple(x_ref[h.ids] + lam * (np.asarray(t) - x_ref[h.ids])
                    for h, t in zip(scene.handles, inputs.handle_targets))
    return dataclasses.replace(inputs, load_forces=loads, handle_targets=targets)


def equilibrium(scene: sc.Scene, inputs: sc.FrameInputs, young, poisson, x_init=None, solver: str = "auto", *,
                rtol: float = 1e-10, max_iterations: int = 60, info: dict | None = None,
                **step_kw) -> np.ndarray:
    """The static equilibrium x* (n, 3) m under ``inputs`` with per-region young (R,) Pa, poisson (R,).

    x_init (n, 3): the Newton start (default the rest shape).  ``info`` (optional dict) receives
    {"iterations", "stages", "residual"}.  Raises SimulationError when no continuation converges
    (e.g. an object held by nothing, whose potential has no minimum)."""
    if not scene.handles and not scene.obstacles:
        raise sc.SimulationError("the static equilibrium needs handles or an obstacle: an object held by nothing "
                                 "falls, its static potential has no minimum.")
    ss = static_scene(scene)
    x0 = np.array(scene.rest if x_init is None else x_init, np.float64)
    last: Exception | None = None
    total = 0
    for k in CONTINUATION:
        x = x0.copy()
        try:
            for j in range(1, k + 1):
                inp = inputs if j == k else _scaled_inputs(scene, inputs, x0, j / k)
                x, inf = sc.step(ss, inp, young, poisson, x, x, x, solver, rtol=rtol,
                                 max_iterations=max_iterations, **step_kw)
                total += inf["iterations"]
        except sc.SimulationError as e:
            last = e
            continue
        if info is not None:
            info.update(iterations=total, stages=k, residual=inf["residual"])
        return x
    raise sc.SimulationError(f"the static equilibrium did not converge with up to {CONTINUATION[-1]} load "
                             f"stages ({last}); is the object held by handles or supported by an obstacle?")


def residual(scene: sc.Scene, inputs: sc.FrameInputs, young, poisson, x) -> np.ndarray:
    """r = ∇_x Π (n, 3) N at x (zero at the equilibrium, except at hard-handle vertices)."""
    ss = static_scene(scene)
    x = jnp.asarray(x, jnp.float64)
    r = np.asarray(sc._residual(x, x, x, jnp.asarray(young, jnp.float64), jnp.asarray(poisson, jnp.float64),
                                sc._data_for(ss), inputs))
    hard = _hard_ids(scene)
    if len(hard):
        r = r.copy()
        r[hard] = 0.0
    return r


def _solve(scene: sc.Scene, inputs, young, poisson, x, rhs: np.ndarray, solver: str) -> np.ndarray:
    """H⁻¹ rhs (columns of rhs (3n, k)) for the exact Hessian of Π at x; zero on the DOFs of hard handles
    (scene.solve_free)."""
    ss = static_scene(scene)
    x = np.asarray(x, np.float64)
    H = sc.hessian(ss, inputs, x, x, young, poisson, project=False)
    rhs = np.array(rhs, np.float64).reshape(H.shape[0], -1)
    return np.stack([sc.solve_free(ss, H, rhs[:, i], solver) for i in range(rhs.shape[1])], axis=1)


@jax.jit
def _residual_theta_vjp(x, young, poisson, s, inputs, a):
    """(∂r/∂E)ᵀ a, (∂r/∂ν)ᵀ a of the static residual."""
    _, vjp = jax.vjp(lambda E, nu: sc._residual(x, x, x, E, nu, s, inputs), young, poisson)
    return vjp(a)


@jax.jit
def _residual_theta_jac(x, young, poisson, s, inputs):
    """∂r/∂E (n, 3, R), ∂r/∂ν (n, 3, R) of the static residual."""
    return jax.jacfwd(lambda E, nu: sc._residual(x, x, x, E, nu, s, inputs), argnums=(0, 1))(young, poisson)


def _theta(scene, young, poisson):
    R = scene.n_regions
    f = lambda a: jnp.asarray(np.broadcast_to(np.asarray(a, np.float64), (R,)))  # noqa: E731
    return f(young), f(poisson)


def equilibrium_adjoint(scene: sc.Scene, inputs: sc.FrameInputs, young, poisson, x, dL_dx,
                        solver: str = "auto") -> dict:
    """dL/dθ of a loss L(x*(θ)) given dL_dx (n, 3) at the equilibrium x (n, 3):
    {"young": (R,), "poisson": (R,), "lambda": (n, 3) the adjoint a}."""
    a = _solve(scene, inputs, young, poisson, x, np.asarray(dL_dx, np.float64).reshape(-1), solver)[:, 0]
    E, nu = _theta(scene, young, poisson)
    dE, dnu = _residual_theta_vjp(jnp.asarray(x, jnp.float64), E, nu, sc._data_for(static_scene(scene)), inputs,
                                  jnp.asarray(a.reshape(-1, 3)))
    return {"young": -np.asarray(dE), "poisson": -np.asarray(dnu), "lambda": a.reshape(-1, 3)}


def equilibrium_sensitivity(scene: sc.Scene, inputs: sc.FrameInputs, young, poisson, x,
                            solver: str = "auto") -> np.ndarray:
    """dx*/dθ (2R, n, 3) m per unit of θ: rows 0..R−1 per Pa of each region's E, rows R..2R−1 per unit ν."""
    E, nu = _theta(scene, young, poisson)
    jE, jnu = _residual_theta_jac(jnp.asarray(x, jnp.float64), E, nu, sc._data_for(static_scene(scene)), inputs)
    n = np.asarray(x).shape[0]
    J = np.concatenate([np.asarray(jE).reshape(3 * n, -1), np.asarray(jnu).reshape(3 * n, -1)], axis=1)
    S = -_solve(scene, inputs, young, poisson, x, J, solver)  # (3n, 2R)
    return S.T.reshape(-1, n, 3)


# =========================================================================== reduced space
def static_model(model):
    """A ReducedModel of the same subspace and cubature on the static scene (dt = ∞, no friction); cached."""
    s = _STATIC_MODELS.get(model)
    if s is None:
        cub = (np.asarray(model.cubature_tets), np.asarray(model.cubature_weights))
        s = _STATIC_MODELS[model] = type(model)(model.sub, static_scene(model.scene), cub, model.reference)
    return s


def _scaled_rinputs(model, rin, lam: float):
    """Reduced inputs with the external load λ (Uᵀ(M g + f)) and the handle pull λ Σ k U_hᵀ(x̄_h − x̂_h)
    (continuation from the rest state)."""
    gq = np.asarray(model.data["grav_q"])
    return rin._replace(load_q=jnp.asarray(lam * (np.asarray(rin.load_q) + gq) - gq),
                        handle_q=jnp.asarray(lam * np.asarray(rin.handle_q)))


def reduced_equilibrium(model, inputs, young, poisson, z_init=None, *, rtol: float = 1e-10,
                        max_iterations: int = 200, info: dict | None = None) -> np.ndarray:
    """The static equilibrium z* (r,) in the subspace of ``model`` (a ReducedModel of the dynamic scene;
    its static twin is built on first use).  inputs: FrameInputs or the static model's ReducedInputs."""
    sm = static_model(model)
    rin = inputs if hasattr(inputs, "handle_q") else sm.reduce_inputs(inputs)
    z0 = np.array(sm.z_rest if z_init is None else z_init, np.float64)
    last: Exception | None = None
    for k in CONTINUATION:
        z = z0.copy()
        try:
            for j in range(1, k + 1):
                r = rin if j == k else _scaled_rinputs(sm, rin, j / k)
                z, inf = sm.step(r, young, poisson, z, z, z_init=z, rtol=rtol, max_iterations=max_iterations)
        except Exception as e:  # ReducedSolveError
            if not isinstance(e, sc.RslError):
                raise
            last = e
            continue
        if info is not None:
            info.update(stages=k, residual=inf["residual_rel"])
        return z
    raise sc.SimulationError(f"the reduced static equilibrium did not converge with up to {CONTINUATION[-1]} "
                             f"load stages ({last}).")


def reduced_equilibrium_adjoint(model, inputs, young, poisson, z, dL_dz=None, dL_dx=None) -> dict:
    """dL/dθ for a loss of z* (dL_dz (r,)) or of x = φ(z*) (dL_dx (n, 3), projected by Jᵀ):
    {"young": (R,), "poisson": (R,), "lambda": (r,)}."""
    sm = static_model(model)
    rin = inputs if hasattr(inputs, "handle_q") else sm.reduce_inputs(inputs)
    z = np.asarray(z, np.float64)
    if dL_dz is None:
        if dL_dx is None:
            raise ValueError("give dL_dz or dL_dx")
        dL_dz = sm.jacobian_transpose(z, dL_dx)
    E, nu = _theta(sm.scene, young, poisson)
    args = sm._args(z, z, z, E, nu, rin)
    h = np.asarray(sm._H(*args))
    lam = np.linalg.solve(0.5 * (h + h.T), np.asarray(dL_dz, np.float64))
    _, _, dy, dn = sm._hvjp(*args, jnp.asarray(lam))
    return {"young": -np.asarray(dy), "poisson": -np.asarray(dn), "lambda": lam}


def reduced_equilibrium_sensitivity(model, inputs, young, poisson, z) -> np.ndarray:
    """dz*/dθ (2R, r): −H⁻¹ ∂h/∂θ, rows E of every region then ν."""
    sm = static_model(model)
    rin = inputs if hasattr(inputs, "handle_q") else sm.reduce_inputs(inputs)
    z = np.asarray(z, np.float64)
    E, nu = _theta(sm.scene, young, poisson)
    args = sm._args(z, z, z, E, nu, rin)
    h = np.asarray(sm._H(*args))
    jE, jnu = _dgrad_dtheta(sm)(args[0], args[1], args[2], E, nu, rin)
    J = np.concatenate([np.asarray(jE), np.asarray(jnu)], axis=1)  # (r, 2R)
    return -np.linalg.solve(0.5 * (h + h.T), J).T


_DGRAD_DTHETA: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _dgrad_dtheta(sm):
    """∂h/∂(E, ν) of the static model's gradient h(z; θ), jitted once per model (an eager jacfwd re-traced the
    energy at every call: half of a reduced gn window's time while frame 0 anchors the markers)."""
    f = _DGRAD_DTHETA.get(sm)
    if f is None:
        grad = jax.grad(sm.energy_jax, argnums=0)
        f = _DGRAD_DTHETA[sm] = jax.jit(jax.jacfwd(grad, argnums=(3, 4)))
    return f


# =========================================================================== a sequence from a declared start
START_STATES = ("equilibrium", "rest")  # the starts start_state solves; "moving" starts from given states


def start_state(scene: sc.Scene, inputs0: sc.FrameInputs, young, poisson, start: str, **kw) -> np.ndarray:
    """x_0 (n, 3), the state frame 0 shows: "rest" — the rest shape (hard-handle vertices at their frame-0
    targets); "equilibrium" — :func:`equilibrium` under the frame-0 inputs with θ of frame 0."""
    if start == "rest":
        apply = getattr(sc, "apply_hard_targets", None)
        return apply(scene, inputs0, scene.rest) if apply is not None else np.array(scene.rest, np.float64)
    if start == "equilibrium":
        return equilibrium(scene, inputs0, young, poisson, **kw)
    raise ValueError(f"start is one of {', '.join(START_STATES)}, not {start!r}")


def simulate_from_start(scene: sc.Scene, inputs_at, young, poisson, frames: int, start: str, substeps: int = 1,
                        callback=None, x0=None, states: list | None = None, before=None, **step_kw) -> np.ndarray:
    """Positions (T, n, 3) of frames 0..T−1 under the start convention of docs/capture.md:
    x_0 = :func:`start_state`, x_{−1} = x_{−2} = x_0, and frames t ≥ 1 by :func:`continue_frames` from (x_0, x_0).
    young/poisson (T, R) or (R,).  x0 (optional) replaces the start state.  ``states`` (optional list)
    receives, per frame, (x_{t−1}, x_{t−2}) at the substep level (what the last step was taken from).
    start "moving" (a capture filmed mid-motion): frame 0 is given, ``before`` = (x_{−1}, x_0) (2, n, 3), and frame 1
    steps from x_0 and the substep state before it interpolated, x_0 + (x_{−1} − x_0) / substeps (as
    stages.window_backends.Substepped restarts); ``states``' frame-0 entry takes the interpolation's substeps."""
    T, R = frames, scene.n_regions
    young, poisson = sc._per_frame(young, T, R), sc._per_frame(poisson, T, R)
    if substeps < 1:
        raise ValueError(f"substeps must be at least 1, not {substeps}")
    if start == "moving":
        if before is None:
            raise ValueError("a moving start needs the state before frame 0 and frame 0's (before)")
        xm1, x = (np.array(b, np.float64) for b in before)
        xp2 = x + (xm1 - x) / substeps  # the substep state before frame 0's
    else:
        x = (start_state(scene, inputs_at(0), young[0], poisson[0], start) if x0 is None
             else np.array(x0, np.float64))
        xp2 = x
    out = np.empty((T, scene.n_vertices, 3))
    out[0] = x
    if states is not None:  # (the substep states before frame 0's last, on the line through x_0 and xp2)
        states.append((xp2.copy(), 2 * xp2 - x))
    if callback is not None:
        callback(0)
    if T > 1:
        out[1:] = continue_frames(scene, inputs_at, young[1:], poisson[1:], range(1, T), x, xp2, substeps, callback,
                                  states, **step_kw)
    return out


def continue_frames(scene: sc.Scene, inputs_at, young, poisson, frames: range, x_prev, x_prev2, substeps: int = 1,
                    callback=None, states: list | None = None, **step_kw) -> np.ndarray:
    """Positions (len(frames), n, 3) of the consecutive ``frames`` from x_prev (the state of frame frames[0] − 1)
    and x_prev2 (the (sub)step state before it): frame t = ``substeps`` implicit-Euler steps of Δt / substeps
    (scene.dt = Δt, the frame interval), the inputs of substep k taken at the fractional frame t − 1 + k / substeps
    (``inputs_at(frame: float) -> FrameInputs``), θ of frame t.  young/poisson (len(frames), R) or (R,).
    ``states`` and ``callback`` as :func:`simulate_from_start`'s; :func:`last_states` of a run is what continues it
    (the same floats as the uninterrupted run)."""
    young, poisson = (sc._per_frame(a, len(frames), scene.n_regions) for a in (young, poisson))
    fine = scene if substeps == 1 else dataclasses.replace(scene, dt=scene.dt / substeps)
    xp, xpp = np.array(x_prev, np.float64), np.array(x_prev2, np.float64)
    out = np.empty((len(frames), scene.n_vertices, 3))
    for i, t in enumerate(frames):
        for k in range(1, substeps + 1):
            xpp_step, xp_step = xpp, xp
            x, _ = sc.step(fine, inputs_at(t - 1 + k / substeps if k < substeps else t), young[i], poisson[i], xp,
                           xpp, None, frame=t, **step_kw)
            xpp, xp = xp, x
        out[i] = x
        if states is not None:
            states.append((xp_step, xpp_step))
        if callback is not None:
            callback(t)
    return out


def last_states(X: np.ndarray, states: list) -> tuple[np.ndarray, np.ndarray]:
    """(x, x_prev) at the end of the last frame of a :func:`simulate_from_start` run (positions X, its ``states``
    list): what :func:`continue_frames` continues from."""
    return X[-1], states[-1][0]
