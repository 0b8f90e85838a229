"""Stress and nodal forces of a deformed tet mesh (pure JAX/numpy, float64).

What the adapted simulation reveals beyond the surface (paper §"Applications"):

- first Piola–Kirchhoff stress  P = ∂Ψ/∂F  (jax.grad of the energy density of
  stages/sim/materials, so every material model gets its exact stress),
- Cauchy stress  σ = J⁻¹ P Fᵀ,  J = det F,
- von Mises stress  σ_vM = √(1.5 s:s),  s = σ − tr(σ) I / 3,
- per quadrature point for quadratic tets (point_stress: F_q = Σ_a x_a ⊗ ∇N_a(ξ_q), 4 points per
  tet; element_average gives one value per element), per tet for linear tets (tet_stress),
- per-vertex values by volume-weighted averaging of the tets around a vertex,
- internal nodal forces  f = −∂(Σ_e V_e Ψ(F_e))/∂x, assembled from P:
  for tet e with H_e = −V_e P_e D_m⁻ᵀ, vertices 1..3 get the columns of H_e and
  vertex 0 gets minus their sum,
- the force on a set of vertices (a handle, a cable, a contact patch): the
  vector sum of the internal nodal forces over the set, and the sum of their
  magnitudes (the paper's cable-tension estimate),
- the force a handle or obstacle applies to the body: the spring pull
  k Σ (x̄ − x) of a handle, −∂E_c/∂x of the contact penalty (stages/sim/potential).
  At static equilibrium a handle's applied force balances the weight it holds,
  while the internal-force sum over its vertices misses their own weight.

No I/O and no printing here.
"""
from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from stages.sim.materials import energy_density, lame
from stages.sim.mesh import deformation_gradients
from stages.sim.potential import contact_energy, obstacle_distance, scene_data

jax.config.update("jax_enable_x64", True)


# --------------------------------------------------------------------------- material per tet
def tet_lame_from_regions(young: np.ndarray, poisson: np.ndarray, tet_region: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(μ, λ) per tet, (m,) each, from θ per region: young (R,) Pa, poisson (R,), tet_region (m,) int."""
    young = np.asarray(young, np.float64).reshape(-1)
    poisson = np.asarray(poisson, np.float64).reshape(-1)
    mu, lam = lame(young, poisson)
    region = np.asarray(tet_region, np.int64)
    return np.asarray(mu)[region], np.asarray(lam)[region]


# --------------------------------------------------------------------------- stress measures
@functools.lru_cache(maxsize=None)
def _piola_fn(model: str):
    """vmapped, jitted P(F, μ, λ) = ∂Ψ/∂F for one material model."""
    psi = energy_density(model)
    return jax.jit(jax.vmap(jax.grad(psi, argnums=0)))


def first_piola(F: np.ndarray, mu: np.ndarray, lam: np.ndarray, model: str = "stable_neohookean"
                ) -> np.ndarray:
    """First Piola–Kirchhoff stress P = ∂Ψ/∂F, (m, 3, 3) Pa; F (m, 3, 3), μ and λ (m,) Pa."""
    F = jnp.asarray(F, jnp.float64)
    if F.shape[0] == 0:
        return np.zeros((0, 3, 3))
    return np.asarray(_piola_fn(model)(F, jnp.asarray(mu, jnp.float64), jnp.asarray(lam, jnp.float64)))


def cauchy_stress(F: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Cauchy stress σ = J⁻¹ P Fᵀ, (m, 3, 3) Pa, from F and P (m, 3, 3); J = det F."""
    F = np.asarray(F, np.float64)
    J = np.linalg.det(F)
    return np.einsum("mij,mkj->mik", P, F) / J[:, None, None]


def von_mises(sigma: np.ndarray) -> np.ndarray:
    """σ_vM = √(1.5 s:s), s = σ − tr(σ) I/3; sigma (..., 3, 3) Pa -> (...,) Pa."""
    sigma = np.asarray(sigma, np.float64)
    sym = 0.5 * (sigma + np.swapaxes(sigma, -1, -2))  # σ is symmetric; guard round-off
    tr = np.trace(sym, axis1=-2, axis2=-1)
    s = sym - tr[..., None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.sum(s * s, axis=(-2, -1)))


def tet_stress(x: np.ndarray, tets: np.ndarray, dm_inv: np.ndarray, mu: np.ndarray, lam: np.ndarray,
               model: str = "stable_neohookean") -> dict[str, np.ndarray]:
    """Stress state of every tet at positions x (n, 3) m.

    Returns ``F`` (m,3,3), ``J`` (m,), ``P`` (m,3,3) Pa, ``sigma`` (m,3,3) Pa and
    ``von_mises`` (m,) Pa.  μ, λ: (m,) Pa per tet.
    """
    _linear_only(tets, "tet_stress", "point_stress")
    F = deformation_gradients(np.asarray(x, np.float64), tets, dm_inv)
    P = first_piola(F, mu, lam, model)
    sigma = cauchy_stress(F, P)
    return {"F": F, "J": np.linalg.det(F), "P": P, "sigma": sigma, "von_mises": von_mises(sigma)}


def _linear_only(tets, name: str, instead: str) -> None:
    if np.shape(tets)[-1] != 4:
        raise ValueError(f"{name} takes linear tets (m, 4); for quadratic tets use {instead} over the "
                         f"scene's quadrature points")


def point_stress(x: np.ndarray, quad, mu: np.ndarray, lam: np.ndarray, model: str = "stable_neohookean"
                 ) -> dict[str, np.ndarray]:
    """Stress state at every quadrature point (stages.sim.quadrature.Quadrature ``quad``; linear tets:
    one point per tet, quadratic tets: 4) at positions x (n, 3) m: F_q = Σ_a x_a ⊗ ∇N_a(ξ_q).

    Returns ``F`` (q,3,3), ``J`` (q,), ``P`` (q,3,3) Pa, ``sigma`` = J⁻¹ P Fᵀ (q,3,3) Pa and
    ``von_mises`` (q,) Pa.  μ, λ: (q,) Pa per point (e.g. per element indexed by quad.element).
    """
    x = np.asarray(x, np.float64)
    F = np.einsum("qki,qkj->qij", x[quad.nodes], quad.grad)
    P = first_piola(F, mu, lam, model)
    sigma = cauchy_stress(F, P)
    return {"F": F, "J": np.linalg.det(F), "P": P, "sigma": sigma, "von_mises": von_mises(sigma)}


def element_average(values: np.ndarray, quad, n_elements: int) -> np.ndarray:
    """Weight-averaged value per element, Σ_q w_q a_q / Σ_q w_q over its points; values (q, ...) -> (m, ...)."""
    values = np.asarray(values, np.float64)
    flat = values.reshape(len(values), -1)
    num = np.zeros((n_elements, flat.shape[1]))
    np.add.at(num, quad.element, flat * quad.weight[:, None])
    den = np.bincount(quad.element, weights=quad.weight, minlength=n_elements)
    return (num / den[:, None]).reshape((n_elements,) + values.shape[1:])


def point_nodal_forces(P: np.ndarray, quad, n_vertices: int) -> np.ndarray:
    """Internal nodal forces f_a = −Σ_q w_q P_q ∇N_a(ξ_q), (n, 3) N, from the first Piola–Kirchhoff
    stress P (q, 3, 3) Pa of every quadrature point (the negative gradient of Σ_q w_q Ψ(F_q))."""
    fq = -np.einsum("q,qij,qaj->qai", quad.weight, np.asarray(P, np.float64), quad.grad)  # (q, k, 3)
    f = np.zeros((n_vertices, 3))
    np.add.at(f, quad.nodes.reshape(-1), fq.reshape(-1, 3))
    return f


def principal_stresses(sigma: np.ndarray) -> np.ndarray:
    """Eigenvalues of the symmetric Cauchy stress, descending, (..., 3) Pa."""
    sym = 0.5 * (sigma + np.swapaxes(sigma, -1, -2))
    return np.linalg.eigvalsh(sym)[..., ::-1]


# --------------------------------------------------------------------------- per-vertex values
def vertex_average(values: np.ndarray, tets: np.ndarray, volumes: np.ndarray, n_vertices: int
                   ) -> np.ndarray:
    """Volume-weighted average onto vertices: a_i = Σ_{e∋i} V_e a_e / Σ_{e∋i} V_e.

    values (m, ...) per element, tets (m, 4) or (m, 10) (every node of an element gets its value),
    volumes (m,) m³ -> (n, ...).  A vertex that belongs to no element gets 0.
    """
    values = np.asarray(values, np.float64)
    vol = np.asarray(volumes, np.float64)
    tail = values.shape[1:]
    weighted = (values.reshape(len(vol), -1) * vol[:, None])
    num = np.zeros((n_vertices, weighted.shape[1]))
    den = np.zeros(n_vertices)
    for k in range(np.shape(tets)[1]):
        np.add.at(num, tets[:, k], weighted)
        np.add.at(den, tets[:, k], vol)
    out = np.divide(num, den[:, None], out=np.zeros_like(num), where=den[:, None] > 0)
    return out.reshape((n_vertices,) + tail)


# --------------------------------------------------------------------------- nodal forces
def nodal_forces(P: np.ndarray, tets: np.ndarray, dm_inv: np.ndarray, volumes: np.ndarray,
                 n_vertices: int) -> np.ndarray:
    """Internal nodal forces f = −∂(Σ_e V_e Ψ(F_e))/∂x, (n, 3) N, from P (m,3,3) Pa.

    With F = D_s D_m⁻¹, ∂(V Ψ)/∂D_s = V P D_m⁻ᵀ; so H_e = −V_e P_e D_m⁻ᵀ holds the
    forces on vertices 1..3 as columns and vertex 0 gets −(h1 + h2 + h3).
    """
    _linear_only(tets, "nodal_forces", "point_nodal_forces")
    H = -np.asarray(volumes, np.float64)[:, None, None] * np.einsum("mij,mkj->mik", P, dm_inv)
    cols = np.swapaxes(H, 1, 2)  # (m, 3 vertices, 3 components)
    f = np.zeros((n_vertices, 3))
    np.add.at(f, tets[:, 0], -cols.sum(axis=1))
    for k in range(3):
        np.add.at(f, tets[:, k + 1], cols[:, k])
    return f


def force_sum(forces: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, float]:
    """Force on a vertex set: (Σ_i f_i  (3,) N,  Σ_i ‖f_i‖  N) over ids; forces (n, 3) N."""
    ids = np.asarray(ids, np.int64)
    if ids.size == 0:
        return np.zeros(3), 0.0
    sel = np.asarray(forces, np.float64)[ids]
    return sel.sum(axis=0), float(np.linalg.norm(sel, axis=1).sum())


# --------------------------------------------------------------------------- summaries
SUMMARY_PERCENTILES = (50.0, 90.0, 99.0)


def stress_summary(vm: np.ndarray, volumes: np.ndarray | None = None) -> dict[str, float]:
    """Max, mean (volume-weighted when volumes are given) and percentiles of a von Mises field (Pa)."""
    vm = np.asarray(vm, np.float64)
    out = {"max_pa": float(vm.max(initial=0.0))}
    if volumes is not None and vm.size:
        out["mean_pa"] = float(np.sum(vm * volumes) / np.sum(volumes))
    else:
        out["mean_pa"] = float(vm.mean()) if vm.size else 0.0
    for q in SUMMARY_PERCENTILES:
        out[f"p{int(q)}_pa"] = float(np.percentile(vm, q)) if vm.size else 0.0
    return out


# --------------------------------------------------------------------------- handle and contact forces
@dataclass(frozen=True)
class SetForce:
    """The force on one handle or obstacle at one frame."""

    name: str
    kind: str  # "handle" | "obstacle"
    internal: np.ndarray  # (3,) Σ_i f_int,i over its vertices, N (the body's pull on the handle)
    magnitude_sum: float  # Σ_i ‖f_int,i‖, N (the paper's cable-tension estimate)
    applied: np.ndarray  # (3,) what the handle springs / the contact exert on the body, N
    n_vertices: int  # handle vertices, or vertices in contact with the obstacle


def hard_handle_forces(scene, inputs, x: np.ndarray, x_prev: np.ndarray, x_prev2: np.ndarray,
                       f_int: np.ndarray) -> np.ndarray:
    """Per-vertex force (n, 3) N that would hold every vertex in place: ∇_x Φ without handle terms,
    r_i = m_i (x_i − y_i)/Δt² − m_i g − f_load,i − f_int,i − f_contact,i, y = 2 x_prev − x_prev2
    (stages.sim.scene.handle_reactions).  At a solved step it vanishes on the free vertices; on the
    vertices of a hard (Dirichlet) handle it is the force the handle exerts on the body."""
    x = np.asarray(x, np.float64)
    y = 2.0 * np.asarray(x_prev, np.float64) - np.asarray(x_prev2, np.float64)
    m = np.asarray(scene.masses, np.float64)[:, None]
    r = m * (x - y) / scene.dt ** 2 - m * np.asarray(scene.gravity)[None, :] - np.asarray(inputs.load_forces) \
        - np.asarray(f_int, np.float64)
    if scene.obstacles:
        s, all_inputs = _contact_inputs(scene, inputs)
        xp = jnp.asarray(x_prev, jnp.float64) if scene.friction > 0.0 else None
        r -= np.asarray(_contact_forces(jnp.asarray(x, jnp.float64), xp, s, all_inputs))
    return r


def _hard_forces_or_fail(scene, inputs, x, x_prev, x_prev2, f_int):
    if not any(getattr(h, "hard", False) for h in scene.handles):
        return None
    if x_prev2 is None or f_int is None:
        raise ValueError("the force of a hard handle needs x_prev2 and f_int (the inertia and elastic terms)")
    return hard_handle_forces(scene, inputs, x, x_prev, x_prev2, f_int)


def set_forces(scene, inputs, x: np.ndarray, x_prev: np.ndarray, f_int: np.ndarray,
               contact_distance: float = 1.0e-3, x_prev2: np.ndarray | None = None) -> list[SetForce]:
    """Forces of every handle and obstacle of a stages.sim Scene at positions x (n, 3) m.

    f_int (n, 3) N: internal nodal forces (:func:`nodal_forces`).  Handles sum over their vertex
    set; ``applied`` = Σ k (x̄ − x), the springs' pull, or for a hard handle the force holding its
    vertices (:func:`hard_handle_forces`, which needs x_prev2 = x_{t−2} (n, 3) for the inertia).
    Obstacles sum over the vertices whose signed distance is below the contact margin d̂ +
    ``contact_distance`` (m); ``applied`` = −∂E_c/∂x summed, the penalty contact force (with the
    lagged friction from x_prev (n, 3) when friction is on).
    """
    out = []
    hard = _hard_forces_or_fail(scene, inputs, x, x_prev, x_prev2, f_int)
    for h, target in zip(scene.handles, inputs.handle_targets):
        vec, mag = force_sum(f_int, h.ids)
        if getattr(h, "hard", False):
            applied = hard[h.ids].sum(axis=0)
        else:
            applied = h.stiffness * np.sum(np.asarray(target) - x[h.ids], axis=0)
        out.append(SetForce(h.name, "handle", vec, mag, applied, int(len(h.ids))))
    for o, ob in enumerate(scene.obstacles):
        ids, applied = contact_force(scene, inputs, o, x, x_prev, contact_distance)
        vec, mag = force_sum(f_int, ids)
        out.append(SetForce(ob.name, "obstacle", vec, mag, applied, int(len(ids))))
    return out


@functools.partial(jax.jit, static_argnums=(1,))
def _obstacle_distances(x, shape, normal, offset, radius, half, pose):
    """Signed distances (n,) m of points x (n, 3) to one obstacle (stages.sim.potential.obstacle_distance)."""
    return jax.vmap(lambda p: obstacle_distance(p, shape, normal, offset, radius, half, pose))(x)


@jax.jit
def _contact_forces(x, x_prev, s, inputs):
    """−∂E_c/∂x (n, 3) N of stages.sim.potential.contact_energy (friction lagged at x_prev, or None)."""
    return -jax.grad(contact_energy)(x, s, inputs, x_prev)


def _contact_inputs(scene, inputs, obstacles: tuple | None = None):
    """(SceneData, FrameInputs) of the contact terms, restricted to some obstacles (all by default)."""
    poses = np.asarray(inputs.obstacle_poses, np.float64).reshape(-1, 7)
    if obstacles is not None:
        scene = dataclasses.replace(scene, obstacles=tuple(scene.obstacles[o] for o in obstacles))
        poses = poses[list(obstacles)]
    return scene_data(scene), dataclasses.replace(inputs, obstacle_poses=poses)


def contact_force(scene, inputs, o: int, x: np.ndarray, x_prev: np.ndarray, contact_distance: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(ids of the vertices touching obstacle o, (3,) total force it applies to the body, N)."""
    ob = scene.obstacles[o]
    poses = np.asarray(inputs.obstacle_poses, np.float64).reshape(-1, 7)
    f64 = lambda a: jnp.asarray(a, jnp.float64)  # noqa: E731
    dist = _obstacle_distances(f64(x), ob.shape, f64(ob.normal if ob.normal is not None else np.zeros(3)),
                               f64(ob.offset), f64(ob.radius),
                               f64(ob.half_extents if ob.half_extents is not None else np.zeros(3)), f64(poses[o]))
    margin = float(getattr(scene, "contact_margin", 0.0))
    ids = np.flatnonzero(np.asarray(dist) < margin + contact_distance)
    s, one_inputs = _contact_inputs(scene, inputs, (o,))
    xp = f64(x_prev) if scene.friction > 0.0 else None
    f = np.asarray(_contact_forces(f64(x), xp, s, one_inputs))
    return ids, f.sum(axis=0)


def applied_forces(scene, inputs, x: np.ndarray, x_prev: np.ndarray, x_prev2: np.ndarray | None = None,
                   f_int: np.ndarray | None = None) -> np.ndarray:
    """Per-vertex force (n, 3) N that the handles (k (x̄ − x); hard handles: :func:`hard_handle_forces`,
    which needs x_prev2 and f_int) and obstacles (−∂E_c/∂x) exert on the body."""
    f = np.zeros_like(np.asarray(x, np.float64))
    hard = _hard_forces_or_fail(scene, inputs, x, x_prev, x_prev2, f_int)
    for h, target in zip(scene.handles, inputs.handle_targets):
        if getattr(h, "hard", False):
            np.add.at(f, h.ids, hard[h.ids])
        else:
            np.add.at(f, h.ids, h.stiffness * (np.asarray(target) - x[h.ids]))
    if scene.obstacles:
        s, all_inputs = _contact_inputs(scene, inputs)
        xp = jnp.asarray(x_prev, jnp.float64) if scene.friction > 0.0 else None
        f += np.asarray(_contact_forces(jnp.asarray(x, jnp.float64), xp, s, all_inputs))
    return f
