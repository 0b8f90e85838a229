"""Full-space implicit-Euler FEM: the scene, one time step by Newton, a sequence, and the window adjoint.

Step (paper Eq. 1):  x_t = argmin_x Φ_t(x),  Φ_t = ½/Δt² ‖x − y_t‖²_M + Σ_q w_q Ψ(F_q; θ_t)
                     − (M g + f_t)·x + Σ_h ½ k_h ‖x_h − x̄_h,t‖² + contact,   y_t = 2x_{t−1} − x_{t−2},
plus, for a damped material (Scene.damping β > 0), β/Δt Σ_q w_q D(F_q, F_q(x_{t−1}); θ_t) (materials.viscous_density).
The elastic energy is a sum over quadrature points (stages.sim.quadrature): one per linear tet
(w = V, F = Ds Dm⁻¹), four per quadratic (10-node) tet.  Hard (Dirichlet) handles have no spring term:
their vertices are put at the targets x̄_h,t and Newton runs on the free DOFs (their rows and columns
of the Hessian replaced by the identity, their gradient entries zeroed).
Newton: H Δx = −∇Φ with the exact Hessian while it is positive definite, else with element Hessians
projected to PSD by the absolute value of their eigenvalues (analytic eigensystem, elements.py) —
SNH is indefinite near rest and under compression —,
sparse assembly on a fixed pattern and a sparse direct solve (linsolve.py); backtracking line
search on Φ; converged when ‖∇Φ‖ ≤ rtol · (‖∇Φ(x_init)‖ + ‖M g‖ + ‖f‖).

Adjoint over a window (paper Eqs. 9–12 in full space): with r_t = ∇_x Φ_t(x_t; x_{t−1}, x_{t−2}, θ_t) = 0,
    H_t a_t = ∂L/∂x_t − (∂r_{t+1}/∂x_t)ᵀ a_{t+1} − (∂r_{t+2}/∂x_t)ᵀ a_{t+2}     (backward in t)
    dL/dθ_t = −(∂r_t/∂θ_t)ᵀ a_t,
H_t the exact (unprojected) Hessian; the cross terms are JAX vector–Jacobian products.  On the DOFs of
hard handles x_t is an input (the target), so a_t = 0 there.
"""
from __future__ import annotations

import dataclasses
import time
import weakref
from dataclasses import dataclass
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ..domain.controls import apply_pose, select_handles
from ..errors import RslError
from . import potential as pot
from .elements import GRADIENT, HESSIAN, point_damping_terms, point_terms
from .linsolve import LinearSolver, NotPositiveDefinite, SparsePattern, resolve_solver
from .materials import MODELS, lame
from .quadrature import Quadrature, build_quadrature, element_order, linear_quadrature, mid_edge_closure

jax.config.update("jax_enable_x64", True)


# =========================================================================== scene description
@dataclass(frozen=True, eq=False)
class HandleSpec:
    name: str
    ids: np.ndarray  # (k,) vertex ids
    stiffness: float  # N/m per vertex (ignored when hard)
    hard: bool = False  # Dirichlet: the vertices sit exactly at their targets (no spring term in Φ)


@dataclass(frozen=True, eq=False)
class LoadSpec:
    name: str
    ids: np.ndarray  # (k,) vertex ids; the total force is spread evenly over them


@dataclass(frozen=True, eq=False)
class ObstacleSpec:
    name: str
    shape: str  # plane | sphere | box
    normal: np.ndarray | None  # plane normal in the obstacle frame
    offset: float  # plane: n·p ≥ offset is outside, m
    radius: float  # sphere, m
    half_extents: np.ndarray | None  # box, (3,) m


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything constant over a sequence (numpy float64)."""

    rest: np.ndarray  # (n, 3) m, all nodes (corners and, for quadratic tets, mid-edge nodes)
    tets: np.ndarray  # (m, 4) linear or (m, 10) quadratic tets (stages.sim.quadrature)
    dm_inv: np.ndarray  # (m, 3, 3) of the corner tets
    volumes: np.ndarray  # (m,) m³
    masses: np.ndarray  # (n,) kg
    tet_region: np.ndarray  # (m,) region index
    n_regions: int
    region_names: tuple[str, ...]
    material: str  # stable_neohookean | yeoh | linear
    dt: float  # s
    gravity: np.ndarray  # (3,) m/s²
    handles: tuple[HandleSpec, ...]
    loads: tuple[LoadSpec, ...]
    obstacles: tuple[ObstacleSpec, ...]
    friction: float  # Coulomb coefficient μ_f (0: frictionless)
    contact_stiffness: float  # κ, N/m per vertex
    contact_margin: float = 0.0  # d̂, m: the penalty acts below this distance
    friction_eps: float = 1e-5  # m, smoothing of the friction norm
    quad: Quadrature | None = None  # quadrature points of the elastic energy (built from the rest when None)
    damping: float = 0.0  # β, s: the material's viscous (Kelvin–Voigt) damping, force ≈ −β K₀ v (0: none)

    def __post_init__(self):
        if self.quad is not None and (self.quad.nodes.shape[1] != np.shape(self.tets)[1]
                                      or int(self.quad.element.max(initial=-1)) >= len(self.tets)):
            raise ValueError("the scene's quadrature points do not belong to its tets")
        if self.quad is None:
            tets = np.asarray(self.tets, np.int64)
            q = (linear_quadrature(tets, self.dm_inv, self.volumes) if element_order(tets) == 1
                 else build_quadrature(self.rest, tets))
            object.__setattr__(self, "quad", q)

    @property
    def n_vertices(self) -> int:
        return int(self.rest.shape[0])

    @property
    def order(self) -> int:
        """1 for linear, 2 for quadratic tets."""
        return element_order(self.tets)


@dataclass(frozen=True, eq=False)
class FrameInputs:
    """The known inputs of one frame."""

    handle_targets: tuple[np.ndarray, ...]  # per handle, (k, 3) target positions, m
    load_forces: np.ndarray  # (n, 3) per-vertex external force, N
    obstacle_poses: np.ndarray  # (n_obstacles, 7) [t, q]


jax.tree_util.register_pytree_node(
    FrameInputs,
    lambda f: ((tuple(f.handle_targets), f.load_forces, f.obstacle_poses), None),
    lambda _, c: FrameInputs(tuple(c[0]), c[1], c[2]))


class SimulationError(RslError):
    """A time step that failed (Newton did not converge, non-finite state)."""


def make_scene(mesh, controls, material: str, dt: float, gravity, contact_stiffness: float | None = None,
               contact_margin: float | None = None, friction_eps: float = 1e-5, damping: float = 0.0) -> Scene:
    """Scene from a MeshArtefact and Controls. Handles use the mesh's stored vertex sets when it has
    them, else the controls' selections. Default κ = 100 M max(|g|, 9.81) / d̂ (the whole weight on one
    vertex sinks d̂/100) and d̂ = 10⁻³ × the bounding-box diagonal.  ``damping``: β (s) of the material's
    viscous damping (Scene.damping; capture.toml [material] damping)."""
    if material not in MODELS:
        raise RslError(f"unknown material model {material!r}; use one of {', '.join(MODELS)}.")
    rest = np.ascontiguousarray(mesh.vertices, np.float64)
    tets = np.ascontiguousarray(mesh.tets, np.int64)
    ids_by_name = dict(getattr(mesh, "handles", {}) or {})
    missing = [h for h in controls.handles if h.name not in ids_by_name]
    if missing:  # selected on all nodes; of a quadratic mesh, with the mid-edge nodes of selected edges
        ids_by_name.update({k: mid_edge_closure(v, tets) for k, v in select_handles(controls, rest).items()})
    handles = tuple(HandleSpec(h.name, np.asarray(ids_by_name[h.name], np.int64), float(h.stiffness),
                               bool(getattr(h, "hard", False)))
                    for h in controls.handles)
    load_ids = dict(getattr(mesh, "loads", {}) or {})  # mesh.h5 maps surface ids to tet-mesh vertices
    loads = tuple(LoadSpec(ld.name, np.asarray(load_ids[ld.name] if ld.name in load_ids
                                               else mid_edge_closure(ld.select.select(rest), tets), np.int64))
                  for ld in controls.loads)
    obstacles = []
    for o in controls.obstacles:
        normal = None if o.normal is None else np.asarray(o.normal, np.float64) / np.linalg.norm(o.normal)
        half = None if o.half_extents is None else np.asarray(o.half_extents, np.float64)
        obstacles.append(ObstacleSpec(o.name, o.shape, normal, float(o.offset), float(o.radius), half))
    g = np.asarray(gravity, np.float64).reshape(3)
    masses = np.ascontiguousarray(mesh.vertex_masses, np.float64)
    diag = float(np.linalg.norm(rest.max(0) - rest.min(0)))
    margin = 1e-3 * diag if contact_margin is None else float(contact_margin)
    kappa = (100.0 * masses.sum() * max(np.linalg.norm(g), 9.81) / max(margin, 1e-9)
             if contact_stiffness is None else float(contact_stiffness))
    names = tuple(mesh.region_names)
    dm_inv = np.ascontiguousarray(mesh.dm_inv, np.float64)
    volumes = np.ascontiguousarray(mesh.rest_volumes, np.float64)
    try:
        quad = (linear_quadrature(tets, dm_inv, volumes) if element_order(tets) == 1
                else build_quadrature(rest, tets))
    except ValueError as e:
        raise RslError(f"the mesh cannot be simulated: {e}.") from None
    return Scene(rest=rest, tets=tets, dm_inv=dm_inv, volumes=volumes, quad=quad, masses=masses,
                 tet_region=np.ascontiguousarray(mesh.tet_region, np.int64), n_regions=len(names),
                 region_names=names, material=material, dt=float(dt), gravity=g, handles=handles,
                 loads=loads, obstacles=tuple(obstacles), friction=float(controls.friction),
                 contact_stiffness=kappa, contact_margin=margin, friction_eps=friction_eps, damping=float(damping))


def frame_inputs(scene: Scene, controls, frame: int) -> FrameInputs:
    """Handle targets (rigidly moved rest positions), per-vertex load forces and obstacle poses at a frame."""
    targets = tuple(apply_pose(h.poses.at(frame), scene.rest[hs.ids])
                    for h, hs in zip(controls.handles, scene.handles))
    forces = np.zeros_like(scene.rest)
    for ld, ls in zip(controls.loads, scene.loads):
        np.add.at(forces, ls.ids, np.asarray(ld.force.at(frame), np.float64) / len(ls.ids))
    poses = np.array([o.poses.at(frame) for o in controls.obstacles], np.float64).reshape(-1, 7)
    return FrameInputs(targets, forces, poses)


# =========================================================================== per-scene caches
class _SceneCache:
    def __init__(self, scene: Scene):
        self._scene = weakref.ref(scene)
        self._pattern: SparsePattern | None = None
        self.solvers: dict[str, LinearSolver] = {}
        self.dof: np.ndarray | None = None  # (3km,) global dof of each element-gradient entry
        self._fixed: tuple | None = None  # (fixed dof mask (3n,) | None, CSR slots to zero, diagonal slots)

    @property
    def pattern(self) -> SparsePattern:
        """The sparse pattern of the scene's Hessian (built on first use)."""
        if self._pattern is None:
            scene = self._scene()
            self._pattern = SparsePattern(scene.tets, scene.n_vertices)
        return self._pattern

    def fixed(self):
        """(mask (3n,) of the DOFs of hard handles or None, CSR slots in their rows/columns, their diagonal
        slots)."""
        if self._fixed is None:
            scene = self._scene()
            mask = fixed_dofs(scene)
            if mask is None:
                self._fixed = (None, None, None)
            else:
                rows, cols = self.pattern.rows_cols()
                slots = np.flatnonzero(mask[rows] | mask[cols])
                self._fixed = (mask, slots, self.pattern.diagonal[np.flatnonzero(mask)])
        return self._fixed

    def solver(self, name: str) -> LinearSolver:
        kind = resolve_solver(name)
        if kind not in self.solvers:
            self.solvers[kind] = LinearSolver(self.pattern, kind)
        return self.solvers[kind]


_CACHE: "weakref.WeakKeyDictionary[Scene, _SceneCache]" = weakref.WeakKeyDictionary()


def _cache(scene: Scene) -> _SceneCache:
    c = _CACHE.get(scene)
    if c is None:
        c = _CACHE[scene] = _SceneCache(scene)
    return c


def _region_lame(scene: Scene, young, poisson) -> tuple[np.ndarray, np.ndarray]:
    """(μ_e, λ_e) per element (numpy) from per-region (R,) θ."""
    young = np.broadcast_to(np.asarray(young, np.float64), (scene.n_regions,))
    poisson = np.broadcast_to(np.asarray(poisson, np.float64), (scene.n_regions,))
    mu, lam = lame(young, poisson)
    return np.ascontiguousarray(mu[scene.tet_region]), np.ascontiguousarray(lam[scene.tet_region])


# =========================================================================== vertex terms
@jax.jit
def _contact_terms_jit(x, x_prev, s, poses):
    """Per-vertex contact/friction energies (n,), gradients (n, 3), Hessians (n, 3, 3)."""
    f = lambda p, q: pot.vertex_contact_energy(p, q, s, poses)  # noqa: E731
    e = jax.vmap(f)(x, x_prev)
    g = jax.vmap(jax.grad(f))(x, x_prev)
    h = jax.vmap(jax.hessian(f))(x, x_prev)
    return e, g, h


@jax.jit
def _contact_energy_jit(x, x_prev, s, poses):
    return jnp.sum(jax.vmap(lambda p, q: pot.vertex_contact_energy(p, q, s, poses))(x, x_prev))


def _vertex_terms(scene: Scene, inputs: FrameInputs, x, y, x_prev, want: int, project: bool):
    """Inertia, gravity, loads, handles and contact: energy (scalar), gradient (n, 3), blocks (n, 3, 3)."""
    energy, grad, blocks = _inertia_terms(scene, inputs, x, y, want)
    energy = _add_spring_handles(scene, inputs, x, energy, grad, blocks)
    if scene.obstacles:
        return _add_contact(scene, inputs, x, x_prev, energy, grad, blocks, want, project)
    return energy, grad, blocks


def _inertia_terms(scene: Scene, inputs: FrameInputs, x, y, want: int):
    """½/Δt² ‖x − y‖²_M − (M g + f)·x: energy, gradient (n, 3) | None, blocks (n, 3, 3) | None."""
    m = scene.masses[:, None]
    inv_dt2 = 1.0 / scene.dt ** 2
    d = x - y
    energy = 0.5 * inv_dt2 * np.sum(m * d * d) - np.sum(m * x * scene.gravity) - np.sum(inputs.load_forces * x)
    grad = inv_dt2 * m * d - m * scene.gravity - inputs.load_forces if want >= GRADIENT else None
    blocks = None
    if want >= HESSIAN:
        blocks = np.zeros((scene.n_vertices, 3, 3))
        blocks += (inv_dt2 * scene.masses)[:, None, None] * np.eye(3)
    return energy, grad, blocks


def _add_spring_handles(scene: Scene, inputs: FrameInputs, x, energy: float, grad, blocks) -> float:
    """Σ_h ½ k_h ‖x_h − x̄_h‖² over the spring handles: the energy plus it; grad and blocks (when not
    None) gain its terms in place.  Hard handles have no term (their DOFs are held at the target)."""
    for h, target in zip(scene.handles, inputs.handle_targets):
        if h.hard:
            continue
        dh = x[h.ids] - target
        energy += 0.5 * h.stiffness * np.sum(dh * dh)
        if grad is not None:
            np.add.at(grad, h.ids, h.stiffness * dh)
        if blocks is not None:
            np.add.at(blocks, h.ids, h.stiffness * np.eye(3))
    return energy


def _add_contact(scene: Scene, inputs: FrameInputs, x, x_prev, energy: float, grad, blocks, want: int,
                 project):
    """Obstacle contact and friction (lagged at x_prev; none when x_prev is None or μ_f = 0) added to
    (energy, grad, blocks); the per-vertex 3×3 blocks projected to PSD when ``project`` (True: clamp,
    "abs": |λ|).  blocks is updated in place, grad replaced."""
    s = pot.scene_data(scene)
    xp = x if (x_prev is None or scene.friction <= 0.0) else x_prev
    if x_prev is None or scene.friction <= 0.0:
        # no friction: zero the friction coefficient contribution by passing x_prev = x and μ_f = 0
        s = _frictionless(s)
    if want < GRADIENT:
        return energy + float(_contact_energy_jit(x, xp, s, inputs.obstacle_poses)), None, None
    e, g, hc = _contact_terms_jit(jnp.asarray(x), jnp.asarray(xp), s, jnp.asarray(inputs.obstacle_poses))
    energy += float(jnp.sum(e))
    if grad is not None:
        grad = grad + np.asarray(g)
    if blocks is not None:
        hc = np.asarray(hc)
        if project:
            w, q = np.linalg.eigh(0.5 * (hc + hc.transpose(0, 2, 1)))
            w = np.abs(w) if project == "abs" else np.maximum(w, 0.0)
            hc = (q * w[:, None, :]) @ q.transpose(0, 2, 1)
        blocks += hc
    return energy, grad, blocks


def _frictionless(s: pot.SceneData) -> pot.SceneData:
    """The same scene data with the friction coefficient set to 0."""
    leaves, aux = s.tree_flatten()
    d = dict(zip(pot.SceneData.LEAVES, leaves))
    d["friction"] = jnp.zeros((), jnp.float64)
    return pot.SceneData(d, *aux)


# =========================================================================== energy / forces
def _elastic(scene: Scene, x, mu, lam, want: int, project: bool, kernels: str):
    """Per element (energies (m,), gradients (m, 3k), Hessians (m, 3k, 3k)): the sums over the
    element's quadrature points; mu, lam (m,) per element."""
    q = scene.quad
    if scene.order == 1:  # one point per tet, element-ordered
        mu_q, lam_q = mu, lam
    else:
        mu_q, lam_q = np.ascontiguousarray(mu[q.element]), np.ascontiguousarray(lam[q.element])
    return point_terms(x, q.nodes, q.grad, q.weight, mu_q, lam_q, scene.material, want, project, kernels,
                       q.element, len(scene.tets))


def _material(scene: Scene, x, x_prev, mu, lam, want: int, project, kernels: str):
    """Per element, :func:`_elastic`'s terms plus, with damping (β > 0) and x_prev given, the viscous ones in x,
    β/Δt Σ_q w_q D(F_q(x), F_q(x_prev)) (materials.viscous_density)."""
    e, g, h = _elastic(scene, x, mu, lam, want, project, kernels)
    if scene.damping <= 0.0 or x_prev is None:
        return e, g, h
    q = scene.quad
    mu_q, lam_q = (mu, lam) if scene.order == 1 else (mu[q.element], lam[q.element])
    ed, gd, hd = point_damping_terms(x, np.asarray(x_prev, np.float64), q.nodes, q.grad,
                                     q.weight * (scene.damping / scene.dt), mu_q, lam_q, want, project, q.element,
                                     len(scene.tets), "jax" if kernels == "jax" else "auto")
    return (e + ed, g + gd if want >= GRADIENT else g, h + hd if want >= HESSIAN else h)


def _scatter_grad(scene: Scene, elem_grad: np.ndarray) -> np.ndarray:
    """Σ_e element gradients (m, 3k) into the flat vertex gradient (3n,)."""
    cache = _cache(scene)
    if cache.dof is None:
        cache.dof = (3 * scene.tets[:, :, None] + np.arange(3)).reshape(-1)
    return np.bincount(cache.dof, weights=elem_grad.reshape(-1), minlength=3 * scene.n_vertices)


def internal_forces(x, scene: Scene, young, poisson, kernels: str = "auto", x_prev=None) -> np.ndarray:
    """−∂(Σ V_e Ψ)/∂x, (n, 3) N, for per-region young (R,) Pa and poisson (R,); with damping and the step's x_prev,
    the viscous force −β/Δt ∂(Σ w D)/∂x too."""
    mu, lam = _region_lame(scene, young, poisson)
    _, g, _ = _material(scene, np.asarray(x, np.float64), x_prev, mu, lam, GRADIENT, True, kernels)
    return -_scatter_grad(scene, g).reshape(-1, 3)


def total_energy(scene: Scene, inputs: FrameInputs, x, y, x_prev, mu, lam, kernels: str = "auto") -> float:
    """Φ(x) in numpy (the value :func:`potential.incremental_potential` computes in JAX)."""
    e, _, _ = _material(scene, x, x_prev, mu, lam, 0, True, kernels)
    ev, _, _ = _vertex_terms(scene, inputs, x, y, x_prev, 0, True)
    return float(np.sum(e)) + ev


def hessian(scene: Scene, inputs: FrameInputs, x, x_prev, young, poisson, project: bool,
            kernels: str = "auto"):
    """The assembled 3n×3n Hessian of Φ at x as scipy CSR (projected to PSD per element when ``project``)."""
    mu, lam = _region_lame(scene, young, poisson)
    _, _, he = _material(scene, x, x_prev, mu, lam, HESSIAN, project, kernels)
    _, _, hv = _vertex_terms(scene, inputs, x, x, x_prev, HESSIAN, project)
    pattern = _cache(scene).pattern
    return pattern.matrix(pattern.assemble(he, hv))


# =========================================================================== hard (Dirichlet) handles
def fixed_dofs(scene: Scene) -> np.ndarray | None:
    """(3n,) bool: the DOFs held by hard handles (None when the scene has none)."""
    hard = [h.ids for h in scene.handles if h.hard]
    if not hard:
        return None
    mask = np.zeros((scene.n_vertices, 3), bool)
    mask[np.concatenate(hard)] = True
    return mask.reshape(-1)


def apply_hard_targets(scene: Scene, inputs: FrameInputs, x) -> np.ndarray:
    """A copy of x (n, 3) with the vertices of every hard handle at their targets."""
    x = np.array(x, np.float64)
    for h, target in zip(scene.handles, inputs.handle_targets):
        if h.hard:
            x[h.ids] = target
    return x


def _constrain(cache: _SceneCache, data: np.ndarray) -> np.ndarray:
    """CSR data with the rows and columns of fixed DOFs zeroed and their diagonal set to the mean
    |diagonal| (so H Δx = −g with g = 0 there gives Δx = 0 there); in place, returned."""
    mask, slots, diag = cache.fixed()
    if mask is None:
        return data
    scale = float(np.mean(np.abs(data[cache.pattern.diagonal]))) or 1.0
    data[slots] = 0.0
    data[diag] = scale
    return data


def solve_free(scene: Scene, H, rhs: np.ndarray, solver: str = "auto") -> np.ndarray:
    """The solution a (3n,) of H_ff a_f = rhs_f with a = 0 on the DOFs of hard handles (all DOFs free
    when there are none); H a scipy CSR matrix on the scene's pattern (:func:`hessian`), symmetric.
    Cholesky when H_ff is positive definite, else LU."""
    cache = _cache(scene)
    rhs = np.array(rhs, np.float64).reshape(-1)
    mask = cache.fixed()[0]
    data = np.array(H.data, np.float64)
    if not (H.indptr is cache.pattern.indptr or np.array_equal(H.indptr, cache.pattern.indptr)):
        raise ValueError("Hessian pattern does not match the scene")
    if mask is not None:
        rhs[mask] = 0.0
        _constrain(cache, data)
    return _solve_data(cache.solver(solver), cache, data, rhs)


def handle_reactions(scene: Scene, inputs: FrameInputs, x, x_prev, x_prev2, young, poisson,
                     kernels: str = "auto") -> np.ndarray:
    """The total force (h, 3) N each handle exerts on the object at the solved state x (n, 3).
    Spring handle: Σ_i k (x̄_i − x_i).  Hard handle: Σ_i r_i over its vertices, r = ∇_x Φ without the
    handle terms (elastic and viscous, inertia with y = 2x_prev − x_prev2, gravity, loads, contact, friction
    lagged at x_prev); at a solved step the free vertices have r = 0, so this is the force that keeps the
    held vertices where they are (for a spring handle the same expression gives k Σ (x̄ − x))."""
    x = np.asarray(x, np.float64)
    out = np.zeros((len(scene.handles), 3))
    if any(h.hard for h in scene.handles):
        x_prev = np.asarray(x_prev, np.float64)
        y = 2.0 * x_prev - np.asarray(x_prev2, np.float64)
        mu, lam = _region_lame(scene, young, poisson)
        _, ge, _ = _material(scene, x, x_prev, mu, lam, GRADIENT, True, kernels)
        _, gv, _ = _vertex_terms(scene, inputs, x, y, x_prev, GRADIENT, True)
        r = _scatter_grad(scene, ge).reshape(-1, 3) + gv
        for i, h in enumerate(scene.handles):  # remove the spring pulls: Φ without the handle terms
            if not h.hard:
                np.add.at(r, h.ids, -h.stiffness * (x[h.ids] - inputs.handle_targets[i]))
    for i, (h, target) in enumerate(zip(scene.handles, inputs.handle_targets)):
        if h.hard:
            out[i] = r[h.ids].sum(axis=0)
        else:
            out[i] = h.stiffness * np.sum(np.asarray(target) - x[h.ids], axis=0)
    return out


# =========================================================================== Newton
class _Newton:
    """Φ_t of one step (paper Eq. 1) and its derivatives at trial states, the linear solver, and the
    seconds spent ("elements", "vertex", "assembly", "solve", "line_search") added to ``timings``."""

    def __init__(self, scene: Scene, inputs: FrameInputs, young, poisson, x_prev, x_prev2, solver: str,
                 kernels: str, timings: dict):
        self.scene, self.inputs, self.kernels, self.tm = scene, inputs, kernels, timings
        self.x_prev = x_prev
        self.y = 2.0 * x_prev - x_prev2
        self.mu, self.lam = _region_lame(scene, young, poisson)
        self.cache = _cache(scene)
        self.fixed = self.cache.fixed()[0]
        self.lin = self.cache.solver(solver)
        for k in ("elements", "assembly", "solve", "vertex", "line_search"):
            timings.setdefault(k, 0.0)

    def energy(self, x) -> float:
        """Φ(x) (x (n, 3)), for the line search."""
        t0 = time.perf_counter()
        e = total_energy(self.scene, self.inputs, x, self.y, self.x_prev, self.mu, self.lam, self.kernels)
        self.tm["line_search"] += time.perf_counter() - t0
        return e

    def gradient(self, x) -> tuple[float, np.ndarray]:
        """(Φ(x), ∇Φ(x) (3n,)) with the gradient zeroed on the DOFs of hard handles."""
        t0 = time.perf_counter()
        ee, ge, _ = _material(self.scene, x, self.x_prev, self.mu, self.lam, GRADIENT, True, self.kernels)
        t1 = time.perf_counter()
        ev, gv, _ = _vertex_terms(self.scene, self.inputs, x, self.y, self.x_prev, GRADIENT, True)
        t2 = time.perf_counter()
        grad = _scatter_grad(self.scene, ge) + gv.reshape(-1)
        if self.fixed is not None:
            grad[self.fixed] = 0.0  # Newton on the free DOFs
        self.tm["elements"] += t1 - t0
        self.tm["vertex"] += t2 - t1
        return float(np.sum(ee)) + ev, grad

    def hessian_data(self, x, how: str) -> np.ndarray:
        """The CSR data of ∇²Φ(x) ("exact" | "projected": element eigenvalues clamped at 0 | "abs":
        replaced by |λ|), hard-handle rows and columns replaced by a scaled identity."""
        t0 = time.perf_counter()
        proj = {"exact": False, "projected": True, "abs": "abs"}[how]
        _, _, he = _material(self.scene, x, self.x_prev, self.mu, self.lam, HESSIAN, proj, self.kernels)
        t1 = time.perf_counter()
        _, _, hv = _vertex_terms(self.scene, self.inputs, x, self.y, self.x_prev, HESSIAN, proj)
        t2 = time.perf_counter()
        data = _constrain(self.cache, self.cache.pattern.assemble(he, hv))
        self.tm["elements"] += t1 - t0
        self.tm["vertex"] += t2 - t1
        self.tm["assembly"] += time.perf_counter() - t2
        return data

    def jacobians(self, x) -> np.ndarray:
        """J = det F at every quadrature point of x (n, 3), and for quadratic tets also of every corner tet
        (its signed volume over the rest one, what the window guard checks): a curved element can fold between
        its four quadrature points, which the energy does not see."""
        q = self.scene.quad
        J = np.linalg.det(np.einsum("qai,qaj->qij", x[q.nodes], q.grad))
        if self.scene.order == 1:
            return J
        c = self.scene.tets[:, :4]
        ds = (x[c[:, 1:]] - x[c[:, :1]]).transpose(0, 2, 1)  # (m, 3, 3) columns x_k − x_0
        return np.concatenate([J, np.linalg.det(ds @ self.scene.dm_inv)])

    def factor(self, data: np.ndarray) -> None:
        t0 = time.perf_counter()
        try:
            self.lin.factor(data)
        finally:
            self.tm["solve"] += time.perf_counter() - t0

    def newton_step(self, grad: np.ndarray) -> np.ndarray:
        """Δx = −H⁻¹ ∇Φ (3n,) with the last factorised H."""
        t0 = time.perf_counter()
        dx = -self.lin.solve(grad)
        self.tm["solve"] += time.perf_counter() - t0
        return dx


# The Newton direction of each hessian_mode: (newton, x, ∇Φ, the mode of this iteration) -> (Δx (3n,), the
# Hessian it used, which is the mode of the next iteration before "auto" returns to "exact").
_FALLBACK = "abs"


def _direction_exact(nt: _Newton, x, grad, mode: str) -> tuple[np.ndarray, str]:
    """The exact Hessian; LU (this and the next iterations) once Cholesky finds it indefinite."""
    data = nt.hessian_data(x, "exact")
    try:
        nt.factor(data)
    except NotPositiveDefinite:
        nt.lin = nt.cache.solver("splu")
        nt.factor(data)
    return nt.newton_step(grad), "exact"


def _direction_projected(nt: _Newton, x, grad, mode: str) -> tuple[np.ndarray, str]:
    """A projected Hessian (mode "projected" or "abs"); |λ| from here on if Cholesky refuses it."""
    try:
        nt.factor(nt.hessian_data(x, mode))
    except NotPositiveDefinite:
        mode = _FALLBACK
        nt.factor(nt.hessian_data(x, mode))
    return nt.newton_step(grad), mode


def _direction_auto(nt: _Newton, x, grad, mode: str) -> tuple[np.ndarray, str]:
    """The exact Hessian while it gives a descent direction (CHOLMOD: while the Cholesky factorisation
    accepts it; LU cannot tell an indefinite matrix, a non-descent direction does), else the |λ| one."""
    if mode != "exact":
        return _direction_projected(nt, x, grad, mode)
    try:
        nt.factor(nt.hessian_data(x, "exact"))
    except NotPositiveDefinite:
        pass
    else:
        dx = nt.newton_step(grad)
        if nt.lin.kind == "cholmod" or float(grad @ dx) < 0.0:
            return dx, "exact"
    nt.factor(nt.hessian_data(x, _FALLBACK))  # indefinite: this and the next steps projected
    return nt.newton_step(grad), _FALLBACK


_DIRECTIONS = {"exact": _direction_exact, "projected": _direction_projected, "abs": _direction_projected,
               "auto": _direction_auto}


def _line_search(nt: _Newton, x, dx, e_x: float, slope: float, gnorm: float, expand: bool, feasible: bool = False
                 ) -> tuple[float, np.ndarray]:
    """(α, x + α Δx) for x, Δx (n, 3), Φ(x) = e_x, slope = ∇Φ·Δx < 0, ‖∇Φ(x)‖ = gnorm.
    ``feasible``: α ≤ α_max, the largest of 1, ½, ¼, … that inverts no element that x does not
    (:func:`_feasible_step`; else α_max = 1).
    Near the solution the predicted decrease −slope/2 drowns in the round-off of Φ (a sum of element
    energies that cancel to strain² μV): there the full step is taken when it lowers ‖∇Φ‖.  Else Armijo
    backtracking on Φ from α_max; α_max when no decrease is measurable.  ``expand``: a full step that Φ
    accepts is doubled (up to 64×) while Φ keeps falling (:func:`_expand`)."""
    a_max, ok = _feasible_step(nt, x, dx) if feasible else (1.0, None)
    if a_max == 1.0 and -slope <= 1e-9 * (abs(e_x) + 1e-300):
        x_new = x + dx
        if float(np.linalg.norm(nt.gradient(x_new)[1])) < gnorm:
            return 1.0, x_new
    alpha, x_new, e_new = _backtrack(nt, x, dx, e_x, slope, a_max)
    if alpha < 1e-10:  # no decrease measurable: near round-off, take the (feasible) Newton step
        return a_max, x + dx if a_max == 1.0 else x + a_max * dx
    if alpha == 1.0 and expand:
        x_new = _expand(nt, x, dx, x_new, e_new, ok)
    return alpha, x_new


def _feasible_step(nt: _Newton, x, dx) -> tuple[float, np.ndarray]:
    """(α_max, the quadrature points not inverted at x (Q,) bool): the largest α = 2⁻ᵏ ≤ 1 with det F > 0 at
    x + α Δx on every point where det F(x) > 0.  Stable Neo-Hookean has no barrier at det F = 0, and Newton
    from the extrapolated state y can otherwise step through it into an inverted local minimum of Φ (a
    pushed dinosaur: Φ = −2.1e−4 J with 3 elements inverted, where the minimum reached from x_{t−1} has
    Φ = −1.8e−2 J and none).  1 when no such α ≥ 1e−10 exists (the step is then not restricted)."""
    ok = nt.jacobians(x) > 0.0
    a = 1.0
    while a >= 1e-10:
        if np.all(nt.jacobians(x + a * dx)[ok] > 0.0):
            return a, ok
        a *= 0.5
    return 1.0, ok


def _backtrack(nt: _Newton, x, dx, e_x: float, slope: float, a_max: float = 1.0
               ) -> tuple[float, np.ndarray, float]:
    """Armijo on Φ: the first α = a_max, a_max/2, … (down to 1e-10) with Φ(x + α Δx) ≤ Φ(x) + 10⁻⁴ α slope
    (+ round-off); (α, x + α Δx, Φ there)."""
    tol_round = 1e-12 * (abs(e_x) + 1e-300)
    a = a_max
    while True:
        z = x + a * dx
        e = nt.energy(z)
        if (np.isfinite(e) and e <= e_x + 1e-4 * a * slope + tol_round) or a < 1e-10:
            return a, z, e
        a *= 0.5


def _expand(nt: _Newton, x, dx, x_full, e_full: float, ok: np.ndarray | None) -> np.ndarray:
    """x + 2^k Δx for the largest k ≤ 6 while Φ keeps falling from Φ(x_full = x + Δx) = e_full (and, given ``ok``,
    no point of it — those not inverted at x — inverts): a full projected step can be too short along the
    directions whose curvature the projection flipped."""
    e_best, x_best = e_full, x_full
    a = 2.0
    while a <= 64.0:
        z = x + a * dx
        if ok is not None and not np.all(nt.jacobians(z)[ok] > 0.0):
            break
        e = nt.energy(z)
        if not (np.isfinite(e) and e < e_best):
            break
        e_best, x_best = e, z
        a *= 2.0
    return x_best


def step(scene: Scene, inputs: FrameInputs, young, poisson, x_prev, x_prev2, x_init=None,
         solver: str = "auto", *, rtol: float = 1e-8, xtol: float = 1e-12, max_iterations: int = 100,
         frame: int | None = None,
         kernels: str = "auto", hessian_mode: str = "auto", timings: dict | None = None
         ) -> tuple[np.ndarray, dict]:
    """One implicit-Euler step: x_t (n, 3) and info {"iterations", "residual", "history"} (relative
    residual ‖∇Φ‖ / (‖∇Φ(x_init)‖ + ‖M g‖ + ‖f‖) and its value at each iteration).
    Converged when the residual ≤ rtol, or when a full Newton step moves no vertex by more than
    xtol × the bounding-box diagonal (round-off floor).

    young, poisson (R,) per region; x_prev = x_{t−1}, x_prev2 = x_{t−2} (n, 3); x_init the Newton start
    (default y; when it inverts quadrature points that x_{t−1} has upright, the last upright point on the segment
    from x_{t−1} to it — :func:`_upright_start`, info["start_alpha"] — ). Raises SimulationError when Newton does
    not converge in ``max_iterations``.
    hessian_mode: "projected" (element eigenvalues clamped at 0), "abs" (element eigenvalues replaced
    by their absolute values, Chen et al. 2024), "exact", or "auto" (exact while the Cholesky
    factorisation succeeds — with splu: while the step is a descent direction —, else "abs" until
    an abs-projected Newton step is accepted in full, then exact again).  Clamping makes the
    projected Hessian nearly singular along the buckling modes of compressed elements, and projected
    Newton then converges linearly; |λ| keeps the curvature's magnitude, and a full |λ| step that
    lowers Φ is doubled (up to 64×) while Φ keeps falling.  On a 2738-vertex dinosaur turning about
    its clamped feet: 350 instead of 484 iterations over two sequences, worst frame 17 instead of 46
    (not every frame gains: one 5K-vertex dinosaur frame takes 59 with |λ|, 21 with clamping).
    info["fallback"] counts the projected iterations of "auto".
    A solution with elements inverted (det F ≤ 0 at a quadrature point) that are upright in x_{t−1} is rejected:
    stable Neo-Hookean has no barrier at det F = 0, and a full Newton step from y can cross it into an inverted
    local minimum of Φ (seen on a pushed P2 dinosaur); the step is then solved again with every line-search step
    kept upright (:func:`_feasible_step`), info["inversion_retry"] = True, iterations counting both solves.  When that
    second solve stalls against det F = 0 at a Φ above the inverted minimum's (:func:`_solve`), no upright minimum lies
    on its way and the inverted minimum is kept, info["retry_blocked"] = True (a dinosaur turned hard about its clamped
    feet: one to a few elements near the clamp inverted, det F down to −0.08).
    ``timings`` (optional dict) accumulates seconds spent in "elements", "assembly", "solve", "vertex",
    "line_search".
    """
    where = f"frame {frame}" if frame is not None else "this step"
    nt = _Newton(scene, inputs, young, poisson, np.asarray(x_prev, np.float64), np.asarray(x_prev2, np.float64),
                 solver, kernels, timings if timings is not None else {})
    if hessian_mode not in _DIRECTIONS:
        raise ValueError(f"hessian_mode must be auto, projected, abs or exact, not {hessian_mode!r}")
    upright = nt.jacobians(nt.x_prev) > 0.0
    x0, start_alpha = _upright_start(nt, nt.y if x_init is None else x_init, upright)
    x, info = _solve(nt, x0, hessian_mode, rtol, xtol, max_iterations, where, feasible=False)
    if np.any(nt.jacobians(x)[upright] <= 0.0):
        # Newton stepped through det F = 0 (stable Neo-Hookean has no barrier there) into a minimum with elements
        # inverted that x_{t−1} has upright: solve again with the line search kept on the upright side, unless that
        # solve stalls against det F = 0 above Φ of this minimum (then this minimum is the step's solution)
        x_again, again = _solve(nt, x0, hessian_mode, rtol, xtol, max_iterations, where, feasible=True,
                                ceiling=nt.energy(x))
        info = {**(info if again.get("blocked") else again), "iterations": info["iterations"] + again["iterations"],
                "inversion_retry": True}
        if again.get("blocked"):
            info["retry_blocked"] = True
        else:
            x = x_again
    if start_alpha < 1.0:
        info["start_alpha"] = start_alpha
    return x, info


def _upright_start(nt: _Newton, guess, upright: np.ndarray) -> tuple[np.ndarray, float]:
    """(Newton's start (n, 3), α): the guess (n, 3) with the hard handles at their targets when that keeps every
    quadrature point (and corner tet) in ``upright`` (Q,) upright, else x_{t−1} + α (guess − x_{t−1}) (hard handles
    at their targets) with the largest α = 2⁻ᵏ (k ≤ 30, or α = 0) that does; the guess itself when none does.
    The inertial guess y = 2x_{t−1} − x_{t−2} of a body moving fast into an obstacle or a clamp can lie beyond
    det F = 0 (a 4 cm P2 box moving down at 3 m/s over its clamped base: all 540 points inverted at y).  Stable
    Neo-Hookean has no barrier there, and Newton from such a start crosses the everted, non-convex region: on that
    box |λ| Newton went to a symmetric saddle (exact Hessian eigenvalues −12 … −0.5 on the free DOFs), left it
    only through round-off, and needed 816 iterations to end in a local minimum with Φ = 0.6845 J; from the
    upright start (α = ¼) it takes 8 iterations (CHOLMOD; 36 with SuperLU) to a lower one, Φ = 0.6676 J, the one
    Newton from x_{t−1} reaches (tests/test_newton_saddle.py).  Steps whose guess inverts nothing are unchanged."""
    scene, inputs = nt.scene, nt.inputs
    x0 = apply_hard_targets(scene, inputs, guess)
    if np.all(nt.jacobians(x0)[upright] > 0.0):
        return x0, 1.0
    d = np.asarray(guess, np.float64) - nt.x_prev
    for k in range(1, 32):
        a = 0.5 ** k if k < 31 else 0.0
        z = apply_hard_targets(scene, inputs, nt.x_prev + a * d)
        if np.all(nt.jacobians(z)[upright] > 0.0):
            return z, a
    return x0, 1.0


# A feasible solve whose step is below this fraction of the Newton step has stalled against det F = 0.
_BLOCKED_ALPHA = 1e-3


def _solve(nt: _Newton, x, hessian_mode: str, rtol: float, xtol: float, max_iterations: int, where: str,
           feasible: bool, ceiling: float = np.inf) -> tuple[np.ndarray, dict]:
    """Newton's iteration of :func:`step` from x (n, 3); ``feasible``: every step keeps det F > 0 where it is
    (:func:`_feasible_step`).  A feasible solve stops early, info["blocked"] = True, when a step is shorter than
    _BLOCKED_ALPHA × the Newton step while Φ is still above ``ceiling`` (Φ of the inverted minimum the unrestricted
    solve found): the upright side is then walled off by det F = 0 below that Φ, and the iteration would only creep
    towards the wall (α_max halving each iteration) until no upright α ≥ 1e-10 is left, cross it unrestricted and
    return to an inverted minimum — on the 2738-vertex dinosaur's frame 7 (seed 1) the same one, after 36 more
    iterations than the 16 of the first solve; on the 5K-vertex one after 91 more."""
    scene, inputs = nt.scene, nt.inputs
    direction, auto = _DIRECTIONS[hessian_mode], hessian_mode == "auto"
    force_scale = np.linalg.norm(scene.masses[:, None] * scene.gravity) + np.linalg.norm(inputs.load_forces)
    size = float(np.linalg.norm(scene.rest.max(0) - scene.rest.min(0)))
    mode = "exact" if hessian_mode in ("exact", "auto") else hessian_mode  # the Hessian of the next step
    scale = None
    residual = np.inf
    history: list[float] = []
    n_fallback = 0
    for it in range(max_iterations + 1):
        e_x, grad = nt.gradient(x)
        gnorm = float(np.linalg.norm(grad))
        if not np.isfinite(gnorm):
            raise SimulationError(f"Newton met a non-finite residual at {where} (iteration {it}).")
        if scale is None:
            scale = max(gnorm + force_scale, 1e-300)
        residual = gnorm / scale
        if residual <= rtol or gnorm == 0.0:
            history.append(residual)
            return x, {"iterations": it, "residual": residual, "history": history, "fallback": n_fallback}
        if it == max_iterations:
            break
        dx, mode = direction(nt, x, grad, mode)
        projected = mode != "exact"
        n_fallback += projected and auto
        slope = float(grad @ dx)
        if slope >= 0.0:  # cannot happen for a positive definite H; guard against round-off
            dx, slope = -grad, -gnorm ** 2
        dx = dx.reshape(-1, 3)
        alpha, x = _line_search(nt, x, dx, e_x, slope, gnorm, expand=auto and projected, feasible=feasible)
        history.append(residual)
        if feasible and alpha < _BLOCKED_ALPHA and nt.energy(x) > ceiling:
            return x, {"iterations": it + 1, "residual": residual, "history": history, "fallback": n_fallback,
                       "blocked": True}
        if auto and projected and alpha == 1.0:
            mode = "exact"  # a full projected step was taken: try the exact Hessian again (quadratic basin)
        if alpha == 1.0 and float(np.abs(dx).max()) <= xtol * size:
            # the full Newton step moved no vertex by more than xtol × the object size: x is resolved
            # to round-off (stiff handles can keep ‖∇Φ‖ above rtol by cancellation alone)
            return x, {"iterations": it + 1, "residual": residual, "history": history, "fallback": n_fallback}
    raise SimulationError(f"Newton did not converge at {where} (residual {residual:.1e} after "
                          f"{max_iterations} iterations).")


_SUBSTEP: "weakref.WeakKeyDictionary[Scene, dict]" = weakref.WeakKeyDictionary()


def substep_scene(scene: Scene, substeps: int) -> Scene:
    """The scene of one substep: the same object with time step Δt / substeps (Δt = scene.dt, the frame
    interval); the scene itself for substeps = 1.  Cached per scene, so its solver caches persist."""
    if substeps < 1:
        raise ValueError(f"substeps must be at least 1, not {substeps}")
    if substeps == 1:
        return scene
    by_s = _SUBSTEP.setdefault(scene, {})
    if substeps not in by_s:
        by_s[substeps] = dataclasses.replace(scene, dt=scene.dt / substeps)
    return by_s[substeps]


def _per_frame(theta, T: int, R: int) -> np.ndarray:
    a = np.asarray(theta, np.float64)
    if a.ndim <= 1:
        a = np.broadcast_to(a.reshape(-1) if a.ndim else a, (R,))
        a = np.broadcast_to(a, (T, R))
    if a.shape != (T, R):
        raise ValueError(f"material parameters must have shape ({T}, {R}) or ({R},), got {a.shape}")
    return a


def simulate(scene: Scene, inputs: Sequence[FrameInputs], young, poisson, x_prev=None, x_prev2=None,
             solver: str = "auto", callback: Callable[[int], None] | None = None, **step_kw) -> np.ndarray:
    """Positions (T, n, 3) of frames 0..T−1 (young/poisson (T, R) or (R,)); x_prev/x_prev2 default to
    the rest shape (start at rest); callback(t) after each frame."""
    T, R = len(inputs), scene.n_regions
    young, poisson = _per_frame(young, T, R), _per_frame(poisson, T, R)
    xp = scene.rest.copy() if x_prev is None else np.asarray(x_prev, np.float64)
    xpp = xp.copy() if x_prev2 is None else np.asarray(x_prev2, np.float64)
    out = np.empty((T, scene.n_vertices, 3))
    for t in range(T):
        x, _ = step(scene, inputs[t], young[t], poisson[t], xp, xpp, None, solver, frame=t, **step_kw)
        out[t] = x
        xpp, xp = xp, x
        if callback is not None:
            callback(t)
    return out


# =========================================================================== adjoint
def _residual(x, x_prev, x_prev2, young, poisson, s, inputs):
    """r = ∇_x Φ_t (n, 3)."""
    return jax.grad(pot.step_potential)(x, x_prev, x_prev2, young, poisson, s, inputs)


@jax.jit
def _residual_vjp(x, x_prev, x_prev2, young, poisson, s, inputs, a):
    """(∂r/∂x_prev)ᵀa, (∂r/∂x_prev2)ᵀa, (∂r/∂E)ᵀa, (∂r/∂ν)ᵀa."""
    _, vjp = jax.vjp(lambda xp, xpp, E, nu: _residual(x, xp, xpp, E, nu, s, inputs), x_prev, x_prev2, young,
                     poisson)
    return vjp(a)


def _data_for(scene: Scene) -> pot.SceneData:
    s = pot.scene_data(scene)
    return s if scene.friction > 0.0 and scene.obstacles else _frictionless(s)


def window_adjoint(scene: Scene, inputs: Sequence[FrameInputs], young, poisson, X, x_before, dL_dX,
                   solver: str = "auto", kernels: str = "auto") -> dict:
    """dL/dθ for a window of w solved frames: young/poisson (w, R) (θ of each frame), X (w, n, 3),
    x_before (2, n, 3) = [x_{t0−2}, x_{t0−1}], dL_dX (w, n, 3). Returns {"young": (w, R),
    "poisson": (w, R), "x_before": (2, n, 3)} (module docstring for the recursion)."""
    X = np.asarray(X, np.float64)
    w = X.shape[0]
    R = scene.n_regions
    young, poisson = _per_frame(young, w, R), _per_frame(poisson, w, R)
    x_before = np.asarray(x_before, np.float64)
    dL_dX = np.asarray(dL_dX, np.float64)
    s = _data_for(scene)
    cache = _cache(scene)
    lin = cache.solver(solver)
    fixed = cache.fixed()[0]

    def prev(k, j):  # x_{k−j} with the two frames before the window
        i = k - j
        return X[i] if i >= 0 else x_before[2 + i]

    c1 = [None] * w  # (∂r_k/∂x_{k−1})ᵀ a_k
    c2 = [None] * w  # (∂r_k/∂x_{k−2})ᵀ a_k
    g_young = np.zeros((w, R))
    g_poisson = np.zeros((w, R))
    for k in range(w - 1, -1, -1):
        rhs = dL_dX[k].reshape(-1).copy()
        if k + 1 < w:
            rhs -= c1[k + 1]
        if k + 2 < w:
            rhs -= c2[k + 2]
        H = hessian(scene, inputs[k], X[k], prev(k, 1), young[k], poisson[k], project=False, kernels=kernels)
        if fixed is not None:  # x_k on hard-handle DOFs is an input (the target): a_k = 0 there
            rhs[fixed] = 0.0
            H.data = _constrain(cache, np.array(H.data))
        a = _solve_symmetric(lin, cache, H, rhs)
        d_xp, d_xpp, d_e, d_nu = _residual_vjp(jnp.asarray(X[k]), jnp.asarray(prev(k, 1)), jnp.asarray(prev(k, 2)),
                                               jnp.asarray(young[k]), jnp.asarray(poisson[k]), s, inputs[k],
                                               jnp.asarray(a.reshape(-1, 3)))
        c1[k] = np.asarray(d_xp).reshape(-1)
        c2[k] = np.asarray(d_xpp).reshape(-1)
        g_young[k] = -np.asarray(d_e)
        g_poisson[k] = -np.asarray(d_nu)
    gb = np.zeros_like(x_before)
    gb[1] = -(c1[0] + (c2[1] if w > 1 else 0.0)).reshape(-1, 3)
    gb[0] = -c2[0].reshape(-1, 3)
    return {"young": g_young, "poisson": g_poisson, "x_before": gb}


def _solve_symmetric(lin: LinearSolver, cache: _SceneCache, H, rhs: np.ndarray) -> np.ndarray:
    """H⁻¹ rhs for the exact Hessian (Cholesky when positive definite, else LU)."""
    data = np.asarray(H.data)
    if not (H.indptr is cache.pattern.indptr or np.array_equal(H.indptr, cache.pattern.indptr)):
        raise ValueError("Hessian pattern does not match the scene")
    return _solve_data(lin, cache, data, rhs)


def _solve_data(lin: LinearSolver, cache: _SceneCache, data: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    try:
        lin.factor(data)
        return lin.solve(rhs)
    except NotPositiveDefinite:
        lu = cache.solver("splu")
        lu.factor(data)
        return lu.solve(rhs)
