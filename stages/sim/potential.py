"""The incremental potential of implicit Euler (paper Eq. 1) as pure JAX functions (float64).

    Φ(x) = ½/Δt² ‖x − y‖²_M + Σ_e V_e Ψ(F_e; μ_e, λ_e) − (M g + f)·x
           + Σ_h ½ k_h ‖x_h − x̄_h‖² + contact(x) + friction(x; x_prev)
           + β/Δt Σ_e V_e D(F_e, F_e(x_prev); μ_e, λ_e),      y = 2 x_{t−1} − x_{t−2},

the last term the material's viscous damping (Kelvin–Voigt on the Green strain, materials.viscous_density; β s,
Scene.damping, 0 by default).

Every function takes the scene either as a :class:`~stages.sim.scene.Scene` (numpy) or as the
:class:`SceneData` pytree built from it by :func:`scene_data`; the latter can cross ``jax.jit``.

Contact is a one-sided quadratic penalty with a small margin d̂ (so vertices rest just outside):
    E_c = Σ_i Σ_o ½ κ max(0, d̂ − d_o(x_i))²,
d_o the signed distance to obstacle o (plane, sphere or box, each moved by its pose [t, q]).
Friction (optional, μ_f > 0) is lagged in the IPC manner: normal force λ_io = κ max(0, d̂ − d_o(x_prev,i)),
tangent plane from ∇d_o at x_prev, and E_f = Σ μ_f λ_io (√(‖u_T‖² + ε²) − ε), u_T the tangential
displacement x_i − x_prev,i relative to the (static) obstacle.
"""
from __future__ import annotations

import weakref

import jax
import jax.numpy as jnp
import numpy as np

from .materials import energy_density, lame, viscous_density
from .mesh import deformation_gradients

jax.config.update("jax_enable_x64", True)


# =========================================================================== scene as a pytree
@jax.tree_util.register_pytree_node_class
class SceneData:
    """The arrays of a Scene as JAX leaves (material and obstacle shapes are static)."""

    LEAVES = ("rest", "tets", "dm_inv", "volumes", "masses", "tet_region", "gravity", "dt",
              "handle_ids", "handle_stiffness", "obstacle_normal", "obstacle_offset", "obstacle_radius",
              "obstacle_half", "friction", "contact_stiffness", "contact_margin", "friction_eps",
              "quad_nodes", "quad_grad", "quad_weight", "quad_element", "damping")
    # quad_*: the quadrature points (stages.sim.quadrature.Quadrature) of quadratic tets; None for linear
    # tets, whose one point per tet is (tets, Dm⁻¹, volumes). A hard handle has handle_stiffness 0.

    def __init__(self, leaves: dict, material: str, shapes: tuple, n_regions: int, damped: bool = False):
        for k in self.LEAVES:
            setattr(self, k, leaves[k])
        self.material = material
        self.shapes = shapes  # obstacle shapes, ("plane" | "sphere" | "box", ...)
        self.n_regions = n_regions
        # β (s) is the leaf ``damping`` (one compilation serves every β > 0: adapt --damping auto tries several);
        # whether there is any is static, so that a scene without damping traces no damping term
        self.damped = bool(damped)

    def tree_flatten(self):
        return (tuple(getattr(self, k) for k in self.LEAVES),
                (self.material, self.shapes, self.n_regions, self.damped))

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(dict(zip(cls.LEAVES, children)), *aux)


_DATA_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def scene_data(scene) -> SceneData:
    """The SceneData of a Scene (cached per scene object); a SceneData is returned as it is."""
    if isinstance(scene, SceneData):
        return scene
    try:
        return _DATA_CACHE[scene]
    except (KeyError, TypeError):
        pass
    obs = scene.obstacles
    f = np.float64
    leaves = dict(
        rest=jnp.asarray(scene.rest, f), tets=jnp.asarray(scene.tets, np.int32),
        dm_inv=jnp.asarray(scene.dm_inv, f), volumes=jnp.asarray(scene.volumes, f),
        masses=jnp.asarray(scene.masses, f), tet_region=jnp.asarray(scene.tet_region, np.int32),
        gravity=jnp.asarray(scene.gravity, f), dt=jnp.asarray(scene.dt, f),
        handle_ids=tuple(jnp.asarray(h.ids, np.int32) for h in scene.handles),
        handle_stiffness=tuple(jnp.asarray(0.0 if getattr(h, "hard", False) else h.stiffness, f)
                               for h in scene.handles),
        obstacle_normal=jnp.asarray(np.array([o.normal if o.normal is not None else np.zeros(3) for o in obs],
                                             f).reshape(-1, 3)),
        obstacle_offset=jnp.asarray(np.array([o.offset for o in obs], f)),
        obstacle_radius=jnp.asarray(np.array([o.radius for o in obs], f)),
        obstacle_half=jnp.asarray(np.array([o.half_extents if o.half_extents is not None else np.zeros(3)
                                            for o in obs], f).reshape(-1, 3)),
        friction=jnp.asarray(scene.friction, f), contact_stiffness=jnp.asarray(scene.contact_stiffness, f),
        contact_margin=jnp.asarray(getattr(scene, "contact_margin", 0.0), f),
        friction_eps=jnp.asarray(getattr(scene, "friction_eps", 1e-5), f),
        quad_nodes=None, quad_grad=None, quad_weight=None, quad_element=None,
        damping=jnp.asarray(float(getattr(scene, "damping", 0.0)), f),
    )
    quad = getattr(scene, "quad", None)
    if quad is not None and np.shape(scene.tets)[-1] == 10:
        leaves.update(quad_nodes=jnp.asarray(quad.nodes, np.int32), quad_grad=jnp.asarray(quad.grad, f),
                      quad_weight=jnp.asarray(quad.weight, f), quad_element=jnp.asarray(quad.element, np.int32))
    data = SceneData(leaves, scene.material, tuple(o.shape for o in obs), int(scene.n_regions),
                     float(getattr(scene, "damping", 0.0)) > 0.0)
    try:
        _DATA_CACHE[scene] = data
    except TypeError:
        pass
    return data


# =========================================================================== material parameters
def tet_lame(scene, young, poisson):
    """(μ_e, λ_e) per element, (m,) each, from per-region θ: young (R,) Pa, poisson (R,)."""
    s = scene_data(scene)
    mu, lam = lame(jnp.asarray(young, jnp.float64), jnp.asarray(poisson, jnp.float64))
    return mu[s.tet_region], lam[s.tet_region]


# =========================================================================== energies
def _deformation_gradients(x, s: "SceneData"):
    """F at every quadrature point (q, 3, 3) of x (n, 3): one per linear tet, four per quadratic."""
    if s.quad_nodes is None:
        return deformation_gradients(x, s.tets, s.dm_inv)
    return jnp.einsum("qki,qkj->qij", x[s.quad_nodes], s.quad_grad)


def elastic_energy(x, scene, mu_tet, lam_tet):
    """Σ_q w_q Ψ(F_q; μ, λ of the point's element) over the quadrature points, x (n, 3) m -> J;
    mu_tet, lam_tet (m,) per element.  Linear tets: one point per tet, Σ_e V_e Ψ(Ds Dm⁻¹).
    Quadratic tets: F_q = Σ_a x_a ⊗ ∇N_a(ξ_q) (stages.sim.quadrature)."""
    s = scene_data(scene)
    psi = jax.vmap(energy_density(s.material))
    F = _deformation_gradients(x, s)
    if s.quad_nodes is None:
        return jnp.sum(s.volumes * psi(F, mu_tet, lam_tet))
    return jnp.sum(s.quad_weight * psi(F, mu_tet[s.quad_element], lam_tet[s.quad_element]))


def damping_energy(x, x_prev, scene, mu_tet, lam_tet):
    """β/Δt Σ_q w_q D(F_q, F_q,prev; μ, λ of the point's element) (materials.viscous_density: Kelvin–Voigt on the
    Green strain), x, x_prev (n, 3) m -> J; 0 when the scene has no damping (β = 0)."""
    s = scene_data(scene)
    if not s.damped:
        return 0.0
    D = jax.vmap(viscous_density)
    F, Fp = _deformation_gradients(x, s), _deformation_gradients(x_prev, s)
    if s.quad_nodes is None:
        return s.damping / s.dt * jnp.sum(s.volumes * D(F, Fp, mu_tet, lam_tet))
    q = s.quad_element
    return s.damping / s.dt * jnp.sum(s.quad_weight * D(F, Fp, mu_tet[q], lam_tet[q]))


def _quat_matrix(q):
    """Rotation matrix of a unit quaternion [w, x, y, z] (JAX)."""
    q = q / jnp.linalg.norm(q)
    w, x, y, z = q[0], q[1], q[2], q[3]
    return jnp.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _safe_norm(v):
    """‖v‖ with a zero (not NaN) gradient at v = 0."""
    sq = jnp.sum(v * v)
    pos = sq > 0.0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def obstacle_distance(p, shape: str, normal, offset, radius, half, pose):
    """Signed distance (m) of one point p (3,) to an obstacle moved by pose [t (3), q (4)];
    positive outside. plane: n·p_l − offset; sphere: ‖p − t‖ − r; box: the usual box SDF."""
    t, R = pose[:3], _quat_matrix(pose[3:])
    pl = R.T @ (p - t)  # point in the obstacle frame
    if shape == "plane":
        n = normal / jnp.linalg.norm(normal)
        return jnp.dot(n, pl) - offset
    if shape == "sphere":
        return _safe_norm(pl) - radius
    q = jnp.abs(pl) - half
    return _safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q), 0.0)


def vertex_contact_energy(p, p_prev, s: SceneData, obstacle_poses):
    """Contact penalty + lagged friction of one vertex p (3,) m -> J (p_prev (3,) or None: no friction)."""
    e = 0.0
    kappa, dhat = s.contact_stiffness, s.contact_margin
    for o, shape in enumerate(s.shapes):
        args = (shape, s.obstacle_normal[o], s.obstacle_offset[o], s.obstacle_radius[o], s.obstacle_half[o],
                obstacle_poses[o])
        d = obstacle_distance(p, *args)
        e = e + 0.5 * kappa * jnp.maximum(dhat - d, 0.0) ** 2
        if p_prev is not None:
            d0, n0 = jax.value_and_grad(lambda q: obstacle_distance(q, *args))(p_prev)
            lam_n = kappa * jnp.maximum(dhat - d0, 0.0)  # lagged normal force, N
            u = p - p_prev
            ut = u - jnp.dot(n0, u) * n0
            eps = s.friction_eps
            e = e + s.friction * lam_n * (jnp.sqrt(jnp.sum(ut * ut) + eps * eps) - eps)
    return e


def contact_energy(x, scene, inputs, x_prev=None):
    """Σ over vertices of :func:`vertex_contact_energy`, x (n, 3) -> J (0 without obstacles)."""
    s = scene_data(scene)
    if not s.shapes:
        return jnp.zeros((), jnp.float64)
    poses = jnp.asarray(inputs.obstacle_poses)
    use_friction = x_prev is not None and _has_friction(s)
    if use_friction:
        e = jax.vmap(lambda p, q: vertex_contact_energy(p, q, s, poses))(x, x_prev)
    else:
        e = jax.vmap(lambda p: vertex_contact_energy(p, None, s, poses))(x)
    return jnp.sum(e)


def _has_friction(s: SceneData) -> bool:
    """Friction is switched on by a nonzero (concrete) coefficient; traced values count as on."""
    try:
        return float(s.friction) > 0.0
    except Exception:  # a tracer: keep the term (it vanishes when the coefficient is 0)
        return True


def external_energy(x, y, scene, inputs, x_prev=None):
    """Everything of Φ except the elastic energy: inertia, gravity and loads, handles, contact."""
    s = scene_data(scene)
    m = s.masses[:, None]
    e = 0.5 / s.dt ** 2 * jnp.sum(m * (x - y) ** 2)
    e = e - jnp.sum(m * x * s.gravity[None, :]) - jnp.sum(jnp.asarray(inputs.load_forces) * x)
    for ids, k, target in zip(s.handle_ids, s.handle_stiffness, inputs.handle_targets):
        e = e + 0.5 * k * jnp.sum((x[ids] - jnp.asarray(target)) ** 2)
    return e + contact_energy(x, s, inputs, x_prev)


def incremental_potential(x, y, scene, inputs, mu_tet, lam_tet, x_prev=None):
    """Φ(x) of implicit Euler (module docstring), x, y (n, 3) m; friction and damping only when x_prev is given."""
    e = elastic_energy(x, scene, mu_tet, lam_tet) + external_energy(x, y, scene, inputs, x_prev)
    return e if x_prev is None else e + damping_energy(x, x_prev, scene, mu_tet, lam_tet)


def inertia_target(x_prev, x_prev2):
    """y = x_{t−1} + (x_{t−1} − x_{t−2}) = x_{t−1} + Δt v_{t−1}."""
    return 2.0 * x_prev - x_prev2


def step_potential(x, x_prev, x_prev2, young, poisson, scene, inputs):
    """Φ_t(x) as a function of everything a frame's solution depends on (used by the adjoint)."""
    mu, lam = tet_lame(scene, young, poisson)
    return incremental_potential(x, inertia_target(x_prev, x_prev2), scene, inputs, mu, lam, x_prev)
