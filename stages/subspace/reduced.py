"""Reduced dynamics x = φ(z) and the reduced window adjoint (paper Eq. 3, 10–12), JAX float64.

A frame solves h(z) = ∂E/∂z = J(z)ᵀ r(φ(z)) = 0 by Newton with a backtracking line search, where

    E(z) = ½/Δt² (q − q_y)ᵀ G (q − q_y) − qᵀ Uᵀ(M g + f)                    inertia, gravity, loads
           + Σ_{q∈C} w_q V_q Ψ(F_q(φ_C(z)))                                    elastic (cubature)
           + ½ qᵀ (Σ_h k_h U_hᵀU_h) q − qᵀ Σ_h k_h U_hᵀ(x̂_h − x̄_h)              handle springs (exact)
           + contact(φ_S(z); φ_S(z_{t−1}))                                   stages.sim.potential terms
           + β/Δt Σ_{q∈C} w_q V_q D(F_q(φ_C(z)), F_q(φ_C(z_{t−1})))             viscous damping (β > 0)

with q = q(z) the decoder's PCA coefficients (x = x̄ + U q), q_y = 2 q(z_{t−1}) − q(z_{t−2}) (so
y = 2φ(z_{t−1}) − φ(z_{t−2}) = x̄ + U q_y exactly) and G = Uᵀ M U.  Inertia, gravity and loads are
thus exact and cost O(p²) whatever the mesh (the handle springs ½k‖x_h − x̂_h‖², x̂_h the targets,
are quadratic in q too, so their Hessian is precomputed and their targets projected once per frame):
only the nodes of the elements of the cubature points C (quadrature points, stages.sim.quadrature:
one per linear tet, four per quadratic tet; F_q = x[nodes_q]ᵀ grad_q) and, when the scene has
obstacles, the surface S are decoded (rows of U).  The contact terms are stages.sim.potential's own
functions evaluated on a restricted SceneData (local vertex ids, zero masses).

``reference=True`` instead evaluates the full incremental potential of stages.sim.potential on
φ(z) over every element and vertex: the literal Eq. 3, which tests hold the fast path to.

Newton uses the exact reduced Hessian ∂²E/∂z² = Jqᵀ H_q Jq + Σ_k (∂E/∂q_k) ∂²q_k/∂z² (the decoder
curvature term, zero for PCA), never a 3n×3n matrix; when it is not positive definite a multiple
of the identity is added.  Without obstacles it is assembled (``_H_jit``): F_q = F0_q + D_q q is
linear in q, so H_q = G/Δt² + K_h + Σ_{q∈C} D_qᵀ (w_q V_q ∂²Ψ/∂F²) D_q with the constant D_q (9, p)
and 9×9 material Hessians — one (p × 9c)(9c × p) product instead of r forward-over-reverse passes
(``_EGH_jit``, its twin, which tests hold it to and which scenes with contact use).  The step is
quasi-Newton: the inverse of the last exact Hessian (kept across iterations and frames) is
BFGS-updated with every accepted step and replaced by a fresh exact one when progress stalls.
The window adjoint (Eq. 10–12) solves, backward over the window,

    H_tᵀ λ_t = ∂L/∂z_t − Σ_{k=t+1}^{t+2} (∂h_k/∂z_t)ᵀ λ_k,      dL/dθ_t = −λ_tᵀ ∂h_t/∂θ_t,

and returns dL/dz of the two states before the window, −Σ_k (∂h_k/∂z_before)ᵀ λ_k.
"""
from __future__ import annotations

import dataclasses
from functools import partial
from typing import Callable, NamedTuple, Sequence

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from stages.errors import RslError  # noqa: E402
from stages.sim import potential as P  # noqa: E402
from stages.sim.materials import energy_density, lame, viscous_density  # noqa: E402
from stages.sim.mesh import boundary_faces  # noqa: E402
from stages.sim.quadrature import element_order, quadratic_surface  # noqa: E402
from stages.subspace.cubature import scene_quadrature  # noqa: E402
from stages.subspace.networks import LINEAR_KINDS, SubspaceMap, net_decode  # noqa: E402



class ReducedSolveError(RslError):
    """The reduced Newton solve failed (non-finite energy or no convergence)."""


class ReducedInputs(NamedTuple):
    """A frame's known inputs in reduced form (a pytree)."""

    handle_targets: tuple  # per handle (k, 3) m
    load_q: jnp.ndarray  # (p,) Uᵀ f, loads projected on the basis
    obstacle_poses: jnp.ndarray  # (n_obstacles, 7)
    load_forces: jnp.ndarray  # (k_sub, 3) zeros: loads are carried by load_q
    handle_q: jnp.ndarray  # (p,) Σ_h k_h U_hᵀ (targets − x̄_h): the handle springs' linear term in q


def surface_vertices(tets: np.ndarray) -> np.ndarray:
    """Vertices on the boundary (faces used by one tet only; for quadratic tets (m, 10) with their
    mid-edge nodes)."""
    if element_order(tets) == 2:
        return np.unique(quadratic_surface(tets))
    return np.unique(boundary_faces(tets))


def _q_of_z(kind: str, net: dict, q_scale, z):
    return z if kind in LINEAR_KINDS else q_scale * net_decode(net, z)


class ReducedModel:
    """Reduced dynamics of one scene in one subspace (module docstring).

    sub: the map φ; scene: stages.sim.scene.Scene (linear or quadratic tets); cubature: (quadrature
    point ids (c,), weights (c,)) or None for every point with weight 1 (for linear tets point ids are
    tet ids); reference: evaluate the full potential on φ(z) (every element, every vertex).
    """

    def __init__(self, sub: SubspaceMap, scene, cubature: tuple[np.ndarray, np.ndarray] | None = None,
                 reference: bool = False):
        self.sub, self.scene, self.reference = sub, scene, reference
        self.kind, self.r, self.p = sub.kind, sub.dim, sub.p
        n = len(scene.rest)
        if sub.basis.shape[0] != n:
            raise RslError(f"the subspace has {sub.basis.shape[0]} vertices but the mesh has {n}; "
                           "retrain it on this mesh's snapshots.")
        basis = np.asarray(sub.basis)
        m = np.asarray(scene.masses)
        self._basis_full = jnp.asarray(basis)
        self._rest_full = jnp.asarray(np.asarray(sub.rest, np.float64))
        g_mat = np.einsum("nip,ni,niq->pq", basis, np.repeat(m[:, None], 3, 1), basis)  # Uᵀ M U
        grav_q = np.einsum("nip,ni->p", basis, m[:, None] * np.asarray(scene.gravity)[None, :])  # Uᵀ M g
        if any(getattr(h, "hard", False) for h in scene.handles):
            # a hard handle acts as a spring of its stiffness here (both the fast path and the reference see the
            # same spring).  generate-data keeps handles hard, so a subspace trained on its snapshots has rows
            # of ~1e-10 at a still hard handle's vertices: they sit at their targets for every z and the spring
            # is inert.  For a moving hard handle a stiffer spring pins the vertices closer but the rest of the
            # body follows the full space less well (docs/results/reduced_accuracy.md), so it is not stiffened.
            scene = dataclasses.replace(scene, handles=tuple(dataclasses.replace(h, hard=False)
                                                             for h in scene.handles))
        full = P.scene_data(scene)
        quad = scene_quadrature(scene)
        self.quadrature = quad
        if cubature is None:
            ids, weights = np.arange(quad.n_points), np.ones(quad.n_points)
        else:
            ids, weights = np.asarray(cubature[0], np.int64), np.asarray(cubature[1], np.float64)
            if len(ids) and (ids.min() < 0 or ids.max() >= quad.n_points):
                raise RslError(f"the cubature names quadrature point {int(ids.max())} but the mesh has "
                               f"{quad.n_points}; retrain the subspace on this mesh.")
        self.cubature_points, self.cubature_weights = ids, weights
        tets = np.asarray(scene.tets)
        # handle springs ½k‖x̄_h + U_h q − target‖² are quadratic in q: Hessian k U_hᵀU_h precomputed
        h_mat = np.zeros((basis.shape[2],) * 2)
        for h in scene.handles:
            uh = basis[np.asarray(h.ids)].reshape(-1, basis.shape[2])
            h_mat += float(h.stiffness) * uh.T @ uh
        verts = [quad.nodes[ids].ravel()]
        if len(scene.obstacles):
            verts.append(surface_vertices(tets))
        vs = np.unique(np.concatenate(verts)) if verts else np.zeros(0, np.int64)
        self.vertex_subset = vs
        local = np.full(n, -1, np.int64)
        local[vs] = np.arange(len(vs))
        leaves = {k: getattr(full, k) for k in P.SceneData.LEAVES}
        # the contact terms only (the elastic energy is over the cubature points below): the element
        # leaves stay the full scene's, unused
        leaves.update(rest=jnp.asarray(np.asarray(scene.rest)[vs]), masses=jnp.zeros(len(vs)),
                      gravity=jnp.zeros(3), handle_ids=(), handle_stiffness=())
        sub_scene = P.SceneData(leaves, full.material, full.shapes, full.n_regions, full.damped)
        nodes_l = local[quad.nodes[ids]]  # (c, k) local vertex ids
        grad_c = np.asarray(quad.grad[ids], np.float64)  # (c, k, 3)
        self.data = dict(
            cub_nodes=jnp.asarray(nodes_l, np.int32), cub_grad=jnp.asarray(grad_c),
            cub_vol=jnp.asarray(np.asarray(quad.weight)[ids] * weights),
            cub_region=jnp.asarray(np.asarray(scene.tet_region)[quad.element[ids]], np.int32),
            net={k: jnp.asarray(v) for k, v in sub.net.items()}, q_scale=jnp.asarray(sub.q_scale),
            rest_s=jnp.asarray(np.asarray(sub.rest)[vs]), basis_s=jnp.asarray(basis[vs]),
            G=jnp.asarray(g_mat), grav_q=jnp.asarray(grav_q), scene_s=sub_scene, H_handle=jnp.asarray(h_mat),
        )
        if reference:
            self.data.update(rest=jnp.asarray(sub.rest), basis=self._basis_full, scene=full)
        else:  # F_q(q) = F0_q + D_q q is linear in q: its derivative, for the assembled Hessian
            self.data.update(
                dF=jnp.asarray(np.einsum("eaj,eaip->eijp", grad_c, basis[vs][nodes_l]).reshape(len(ids), 9, -1)),
                F0=jnp.asarray(np.einsum("eaj,eai->eij", grad_c, np.asarray(sub.rest)[vs][nodes_l])))
        # the assembled Hessian (module docstring) covers the elastic and quadratic terms; contact
        # Hessians come from the forward-over-reverse kernel
        self._assembled = not reference and not len(scene.obstacles)
        self._build()

    @classmethod
    def from_artefacts(cls, subspace, scene, cubature: bool = True, reference: bool = False) -> "ReducedModel":
        """Model from a SubspaceArtefact (its cubature unless cubature=False) and a Scene."""
        from stages.subspace.networks import KINDS, required_weights

        if subspace.subspace_kind not in KINDS:
            raise RslError(f"subspace.h5: kind '{subspace.subspace_kind}' is not one of {', '.join(KINDS)}.")
        missing = [k for k in required_weights(subspace.subspace_kind) if k not in subspace.weights]
        if missing:
            raise RslError(f"subspace.h5: weights {', '.join(missing)} are missing; retrain the subspace.")
        sub = SubspaceMap.from_weights(subspace.subspace_kind, subspace.weights)
        cub = None
        extra = subspace.extra
        key = "cubature_points" if "cubature_points" in extra else "cubature_tets"  # older files: tet ids
        if cubature and key in extra:
            order = element_order(scene.tets)
            if int(extra.get("cubature_order", 1)) != order:
                raise RslError(f"subspace.h5: its cubature was fitted on a mesh of order "
                               f"{int(extra.get('cubature_order', 1))}, this mesh has order {order}; "
                               "retrain the subspace on this mesh.")
            cub = (np.asarray(extra[key], np.int64), np.asarray(extra["cubature_weights"], np.float64))
        return cls(sub, scene, cub, reference)

    @property
    def cubature_tets(self) -> np.ndarray:
        """The cubature's quadrature point ids (the older name; for linear tets they are tet ids)."""
        return self.cubature_points

    @property
    def dim(self) -> int:
        """Latent dimension r."""
        return self.r

    @property
    def z_rest(self) -> np.ndarray:
        """ψ(rest), the state of the undeformed object (0 for rsl's subspaces: φ(0) = x̄), (r,)."""
        return self.encode(self.scene.rest)

    # ------------------------------------------------------------------ the energy
    def _build(self) -> None:
        """Bind the module-level jitted kernels (shared by every model of the same shapes) to this model."""
        d, kind, ref = self.data, self.kind, self.reference
        self.energy_jax = lambda z, z1, z2, y, nu, rin: _energy(z, z1, z2, y, nu, rin, d, kind, ref)  # traceable
        self._E = lambda *a: _E_jit(*a, d, kind, ref)
        self._G = lambda *a: _G_jit(*a, d, kind, ref)
        self._EG = lambda *a: _EG_jit(*a, d, kind, ref)
        self._inv = None  # the last inverse reduced Hessian (reused by step, BFGS-updated)
        self._EGH = lambda *a: _EGH_jit(*a, d, kind, ref)
        self._H = ((lambda *a: _H_jit(*a, d, kind)) if getattr(self, "_assembled", False)
                   else (lambda *a: self._EGH(*a)[2]))
        self._hvjp = lambda *a: _hvjp_jit(*a, d, kind, ref)
        self._GN = lambda *a: _GN_jit(*a, d, kind, ref)

    # ------------------------------------------------------------------ inputs
    def reduce_inputs(self, inputs) -> ReducedInputs:
        """FrameInputs → ReducedInputs (loads projected on U: Uᵀ f, only the loaded rows)."""
        f = np.asarray(inputs.load_forces, np.float64)
        rows = np.nonzero(np.any(f != 0.0, axis=1))[0]
        basis = np.asarray(self.sub.basis)
        lq = np.einsum("nip,ni->p", basis[rows], f[rows]) if len(rows) else np.zeros(self.p)
        poses = np.asarray(inputs.obstacle_poses, np.float64).reshape(-1, 7)
        nload = len(self.scene.rest) if self.reference else len(self.vertex_subset)
        lf = jnp.asarray(f) if self.reference else jnp.zeros((nload, 3))
        if self.reference:
            return ReducedInputs(tuple(jnp.asarray(t, jnp.float64) for t in inputs.handle_targets),
                                 jnp.zeros(self.p), jnp.asarray(poses), lf, jnp.zeros(self.p))
        hq = np.zeros(self.p)
        for h, target in zip(self.scene.handles, inputs.handle_targets):
            ids = np.asarray(h.ids)
            d = np.asarray(target, np.float64) - np.asarray(self.sub.rest)[ids]
            hq += float(h.stiffness) * np.einsum("kip,ki->p", basis[ids], d)
        return ReducedInputs((), jnp.asarray(lq), jnp.asarray(poses), lf, jnp.asarray(hq))

    # ------------------------------------------------------------------ maps
    def decode(self, z) -> np.ndarray:
        """x = φ(z), z (..., r) → (..., n, 3) (SubspaceMap.decode compiled once: the same floats, no eager ops)."""
        d = self.data
        return np.asarray(_decode_jit(np.asarray(z, np.float64), d["net"], d["q_scale"], self._basis_full,
                                      self._rest_full, self.kind))

    def encode(self, x) -> np.ndarray:
        """z = ψ(x), (r,)."""
        return np.asarray(self.sub.encode(jnp.asarray(x)))

    def jacobian(self, z) -> np.ndarray:
        """J = ∂φ/∂z, (n, 3, r)."""
        return np.asarray(self.sub.jacobian(jnp.asarray(z)))

    def jacobian_transpose(self, z, v) -> np.ndarray:
        """Jᵀ v for v (n, 3) → (r,) (one VJP, no J formed)."""
        d = self.data
        return np.asarray(_jt_jit(jnp.asarray(z, jnp.float64), jnp.asarray(v, jnp.float64), d["net"], d["q_scale"],
                                  self._basis_full, self.kind))

    # ------------------------------------------------------------------ energy, gradient, Hessian
    def _args(self, z, z_prev, z_prev2, young, poisson, rin):
        # numpy float64, not jnp.asarray: the jitted kernels take numpy arguments directly, while jnp.asarray is
        # an eager dispatch (≈0.3 ms each, several per Newton iteration)
        f = lambda a: np.asarray(a, np.float64)  # noqa: E731
        return f(z), f(z_prev), f(z_prev2), f(young), f(poisson), rin

    def energy(self, z, inputs, young, poisson, z_prev, z_prev2) -> float:
        """E(z) (constants dropped; the reference path keeps them)."""
        rin = inputs if isinstance(inputs, ReducedInputs) else self.reduce_inputs(inputs)
        return float(self._E(*self._args(z, z_prev, z_prev2, young, poisson, rin)))

    def gradient(self, z, inputs, young, poisson, z_prev, z_prev2) -> np.ndarray:
        """h = ∂E/∂z = J(z)ᵀ r(φ(z)), (r,)."""
        rin = inputs if isinstance(inputs, ReducedInputs) else self.reduce_inputs(inputs)
        return np.asarray(self._G(*self._args(z, z_prev, z_prev2, young, poisson, rin)))

    def hessian(self, z, inputs, young, poisson, z_prev, z_prev2, curvature: bool = True) -> np.ndarray:
        """∂²E/∂z² (r, r); curvature=False drops the decoder-curvature term (Jᵀ H J only)."""
        rin = inputs if isinstance(inputs, ReducedInputs) else self.reduce_inputs(inputs)
        args = self._args(z, z_prev, z_prev2, young, poisson, rin)
        if curvature:
            return np.asarray(self._H(*args))
        return np.asarray(self._GN(*args))

    # ------------------------------------------------------------------ forward
    def solver_memory(self) -> np.ndarray | None:
        """What one solve hands the next (:meth:`step`'s reuse_hessian: the last inverse reduced Hessian, (r, r)),
        a copy; :meth:`restore_solver_memory` puts it back, so that solves which should leave no trace (adapt's
        change probes) do not change the iterations, and so the last bits, of the solves after them."""
        inv = getattr(self, "_inv", None)
        return None if inv is None else np.array(inv, copy=True)

    def restore_solver_memory(self, memory: np.ndarray | None) -> None:
        """The memory as :meth:`solver_memory` copied it."""
        self._inv = None if memory is None else np.array(memory, copy=True)

    def step(self, inputs, young, poisson, z_prev, z_prev2, z_init=None, rtol: float = 1e-8,
             max_iterations: int = 200, frame: int | None = None, reuse_hessian: bool = True,
             contraction: float = 0.1, refresh_every: int = 10
             ) -> tuple[np.ndarray, dict]:
        """z_t = argmin E(z) by Newton + backtracking (warm start z_init, default 2 z_{t−1} − z_{t−2}).

        reuse_hessian: quasi-Newton — keep the inverse of the last exact reduced Hessian (from this or
        an earlier frame) and BFGS-update it with each accepted step (O(r²), curvature learnt along the
        path), taking a fresh exact Hessian only when ‖h‖ has not fallen by ``contraction`` over
        ``refresh_every`` iterations, when it grows 4× in one step, or when the direction is not a
        descent; False: a fresh Hessian at every iteration (plain Newton).  Either way the solution
        is the same: converged when ‖h‖ ≤ rtol · (‖h(z_init)‖ + ‖Jqᵀ Uᵀ(M g + f)‖).  With r = 100 an
        exact Hessian costs about 20 gradient evaluations, and quasi-Newton needs 2–3 per frame where
        Newton with a reused factorisation needed 10–11.  Quasi-Newton not converged after ``max_iterations``
        goes on as plain Newton for up to ``max_iterations`` more (the dinosaur at contact with r = 60:
        quasi-Newton 208 iterations, Newton 84).
        Returns (z (r,), {"iterations", "hessians", "residual", "residual_rel", "newton_fallback"}).
        """
        rin = inputs if isinstance(inputs, ReducedInputs) else self.reduce_inputs(inputs)
        z_prev, z_prev2 = np.asarray(z_prev, np.float64), np.asarray(z_prev2, np.float64)
        z = (2.0 * z_prev - z_prev2) if z_init is None else np.asarray(z_init, np.float64)
        rest = self._args(z, z_prev, z_prev2, young, poisson, rin)[1:]
        e, g = (np.asarray(a) for a in self._EG(z, *rest))
        if not np.isfinite(e):
            z = z_prev.copy()
            e, g = (np.asarray(a) for a in self._EG(z, *rest))
        inv = self._inv if (reuse_hessian and getattr(self, "_inv", None) is not None) else None
        fresh = False
        n_hess = 0
        d = self.data
        f_ext = np.asarray(_jqt_jit(z, d["grav_q"] + rin.load_q, d["net"], d["q_scale"], self.kind))
        g0 = max(float(np.linalg.norm(g)) + float(np.linalg.norm(f_ext)), 1e-300)  # as stages.sim.scene.step
        tol = rtol * g0
        it = 0
        since, g_ref = 0, float(np.linalg.norm(g))
        fallback = False  # quasi-Newton used up max_iterations: plain Newton from there
        for it in range(1, (2 if reuse_hessian else 1) * max_iterations + 1):
            gn = float(np.linalg.norm(g))
            if gn <= tol:
                it -= 1
                break
            if reuse_hessian and it > max_iterations:
                reuse_hessian, fallback, inv = False, True, None
            if inv is not None and since >= refresh_every:
                if gn > contraction * g_ref:
                    inv = None  # quasi-Newton is making slow progress: a fresh Hessian
                since, g_ref = 0, gn
            if inv is None:
                inv = _inverse(_factorise(np.asarray(self._H(z, *rest))))
                fresh, n_hess = True, n_hess + 1
                since, g_ref = 0, gn
            since += 1
            dz = -(inv @ g)
            slope = float(g @ dz)
            alpha = 1.0
            while slope < 0 and alpha > 1e-10:  # backtracking on E; ∂E/∂z comes with it (same cost)
                z_try = z + alpha * dz
                e_new, g_new = (np.asarray(a) for a in self._EG(z_try, *rest))
                e_new = float(e_new)
                if np.isfinite(e_new) and e_new <= e + 1e-4 * alpha * slope + 1e-13 * abs(e):
                    break
                if np.isfinite(e_new) and -alpha * slope < 1e-10 * abs(e) and np.linalg.norm(g_new) < gn:
                    break  # float64 cannot resolve this energy decrease: accept as the residual falls
                alpha *= 0.5
            if slope >= 0 or alpha <= 1e-10:
                if fresh:
                    break  # no descent left at float64 precision
                inv = None  # a stale Hessian: refactorise and retry
                continue
            s_k, y_k = z_try - z, g_new - g
            z, e, g = z_try, e_new, g_new
            if not reuse_hessian or np.linalg.norm(g) > 4.0 * gn:
                inv = None  # pure Newton, or the model was poor (‖h‖ grew 4×): a fresh Hessian here
                continue
            fresh = False
            sy = float(s_k @ y_k)
            if sy > 1e-12 * float(np.linalg.norm(s_k) * np.linalg.norm(y_k)):
                # BFGS update of the inverse Hessian: curvature learnt along the step, O(r²)
                rho = 1.0 / sy
                by = inv @ y_k
                inv = (inv - rho * (np.outer(s_k, by) + np.outer(by, s_k))
                       + (rho * rho * float(y_k @ by) + rho) * np.outer(s_k, s_k))
        self._inv = inv if inv is not None else getattr(self, "_inv", None)
        res = float(np.linalg.norm(g))
        if not np.all(np.isfinite(z)) or res > max(1e3 * tol, 1e-6 * g0):
            where = f" at frame {frame}" if frame is not None else ""
            raise ReducedSolveError(f"Reduced Newton did not converge{where} (residual {res / g0:.1e} of the "
                                    f"initial after {it} iterations).")
        return z, {"iterations": it, "hessians": n_hess, "residual": res, "residual_rel": res / g0,
                   "newton_fallback": fallback}

    def simulate(self, inputs: Sequence, young, poisson, z_prev=None, z_prev2=None, rtol: float = 1e-8,
                 callback: Callable[[int], None] | None = None) -> np.ndarray:
        """Z (T, r) for per-frame inputs and θ (T, R); the previous states default to ψ(rest)."""
        z0 = self.z_rest
        z1 = z0 if z_prev is None else np.asarray(z_prev, np.float64)
        z2 = z1 if z_prev2 is None else np.asarray(z_prev2, np.float64)
        young, poisson = np.atleast_2d(young), np.atleast_2d(poisson)
        out = []
        for t, inp in enumerate(inputs):
            z, _ = self.step(inp, young[min(t, len(young) - 1)], poisson[min(t, len(poisson) - 1)], z1, z2,
                             rtol=rtol, frame=t)
            out.append(z)
            z2, z1 = z1, z
            if callback is not None:
                callback(t)
        return np.stack(out) if out else np.zeros((0, self.r))

    # ------------------------------------------------------------------ backward
    def window_adjoint(self, inputs: Sequence, young, poisson, Z, z_before, dL_dX=None, dL_dZ=None) -> dict:
        """dL/dθ_t (w, R) and dL/dz_before (2, r) for a window of solved states Z (w, r).

        z_before = [z_{t0−2}, z_{t0−1}] (2, r); give dL_dZ (w, r) or dL_dX (w, n, 3) (projected by Jᵀ).
        Returns {"young": (w, R), "poisson": (w, R), "z_before": (2, r), "lambda": (w, r)}.
        """
        Z = np.asarray(Z, np.float64)
        w = len(Z)
        young, poisson = np.asarray(young, np.float64), np.asarray(poisson, np.float64)
        if young.ndim == 1:
            young, poisson = np.tile(young, (w, 1)), np.tile(poisson, (w, 1))
        if dL_dZ is None:
            if dL_dX is None:
                raise ValueError("give dL_dX or dL_dZ")
            dL_dZ = np.stack([self.jacobian_transpose(Z[t], dL_dX[t]) for t in range(w)])
        dL_dZ = np.asarray(dL_dZ, np.float64)
        zb = np.asarray(z_before, np.float64)
        states = np.concatenate([zb, Z])  # index t + 2 is frame t of the window
        rins = [u if isinstance(u, ReducedInputs) else self.reduce_inputs(u) for u in inputs]
        rhs = dL_dZ.copy()
        lam = np.zeros_like(Z)
        gy, gn = np.zeros_like(young), np.zeros_like(poisson)
        gb = np.zeros((2, self.r))
        for t in range(w - 1, -1, -1):
            args = self._args(states[t + 2], states[t + 1], states[t], young[t], poisson[t], rins[t])
            h = np.asarray(self._H(*args))
            lam[t] = _solve_sym(h, rhs[t])
            d1, d2, dy, dn = (np.asarray(a) for a in self._hvjp(*args, lam[t]))
            gy[t], gn[t] = -dy, -dn
            for k, dk in ((t - 1, d1), (t - 2, d2)):  # h_t depends on z_{t−1}, z_{t−2}
                if k >= 0:
                    rhs[k] -= dk
                else:
                    gb[k + 2] -= dk
        return {"young": gy, "poisson": gn, "z_before": gb, "lambda": lam}


# =========================================================================== pure kernels
@partial(jax.jit, static_argnames=("kind",))
def _jqt_jit(z, w, net, q_scale, kind):
    """(∂q/∂z)ᵀ w, w (p,) → (r,)."""
    _, vjp = jax.vjp(lambda zz: _q_of_z(kind, net, q_scale, zz), z)
    return vjp(w)[0]


@partial(jax.jit, static_argnames=("kind",))
def _decode_jit(z, net, q_scale, basis, rest, kind):
    """φ(z) = x̄ + U q(z), z (..., r) → (..., n, 3): SubspaceMap.decode, compiled."""
    return rest + jnp.einsum("nip,...p->...ni", basis, _q_of_z(kind, net, q_scale, z))


@partial(jax.jit, static_argnames=("kind",))
def _jt_jit(z, v, net, q_scale, basis, kind):
    """Jᵀ v = (∂q/∂z)ᵀ Uᵀ v, v (n, 3) → (r,)."""
    uv = jnp.einsum("nip,ni->p", basis, v)
    _, vjp = jax.vjp(lambda zz: _q_of_z(kind, net, q_scale, zz), z)
    return vjp(uv)[0]


def _energy_q(q, q1, q2, young, poisson, rin, d, reference: bool):
    """E as a function of the PCA coefficients q, q_{t−1}, q_{t−2} (module docstring)."""
    if reference:
        full = d["scene"]

        def phi(qq):
            return d["rest"] + jnp.einsum("nip,p->ni", d["basis"], qq)

        return P.step_potential(phi(q), phi(q1), phi(q2), young, poisson, full, rin)
    s = d["scene_s"]
    dq = q - (2.0 * q1 - q2)
    e = 0.5 / s.dt ** 2 * dq @ (d["G"] @ dq) - q @ (d["grav_q"] + rin.load_q + rin.handle_q) \
        + 0.5 * q @ (d["H_handle"] @ q)
    x = d["rest_s"] + jnp.einsum("nip,p->ni", d["basis_s"], q)
    x1 = d["rest_s"] + jnp.einsum("nip,p->ni", d["basis_s"], q1)
    e = e + _cubature_elastic(x, young, poisson, d, s.material) + P.external_energy(x, x, s, rin, x1)
    return e if not s.damped else e + _cubature_damping(x, x1, young, poisson, d, s)


def _cubature_lame(young, poisson, d):
    """(μ, λ) at each cubature point, from per-region young (R,) Pa and poisson (R,)."""
    mu, lam = lame(jnp.asarray(young, jnp.float64), jnp.asarray(poisson, jnp.float64))
    return mu[d["cub_region"]], lam[d["cub_region"]]


def _cubature_elastic(x, young, poisson, d, material: str):
    """Σ_{q∈C} w_q V_q Ψ(F_q), F_q = x[nodes_q]ᵀ grad_q, x (n_s, 3) the decoded vertex subset."""
    mu, lam = _cubature_lame(young, poisson, d)
    return jnp.sum(d["cub_vol"] * jax.vmap(energy_density(material))(_cubature_F(x, d), mu, lam))


def _cubature_F(x, d):
    """F_q = x[nodes_q]ᵀ grad_q at the cubature points (c, 3, 3), x (n_s, 3) the decoded vertex subset."""
    return jnp.einsum("cki,ckj->cij", x[d["cub_nodes"]], d["cub_grad"])


def _cubature_damping(x, x1, young, poisson, d, s):
    """β/Δt Σ_{q∈C} w_q V_q D(F_q, F_q,prev) (materials.viscous_density) on the cubature points of the elastic
    energy, x, x1 (n_s, 3) the decoded vertex subset now and at the frame before."""
    mu, lam = _cubature_lame(young, poisson, d)
    return s.damping / s.dt * jnp.sum(d["cub_vol"] * jax.vmap(viscous_density)(_cubature_F(x, d), _cubature_F(x1, d),
                                                                                 mu, lam))


def _q(z, d, kind):
    return _q_of_z(kind, d["net"], d["q_scale"], z)


def _energy(z, z1, z2, young, poisson, rin, d, kind: str, reference: bool):
    """E(z; z_{t−1}, z_{t−2}, θ, inputs)."""
    return _energy_q(_q(z, d, kind), _q(z1, d, kind), _q(z2, d, kind), young, poisson, rin, d, reference)


_grad = jax.grad(_energy)
_STATIC = ("kind", "reference")


@partial(jax.jit, static_argnames=_STATIC)
def _E_jit(z, z1, z2, y, nu, rin, d, kind, reference):
    return _energy(z, z1, z2, y, nu, rin, d, kind, reference)


@partial(jax.jit, static_argnames=_STATIC)
def _G_jit(z, z1, z2, y, nu, rin, d, kind, reference):
    return _grad(z, z1, z2, y, nu, rin, d, kind, reference)


@partial(jax.jit, static_argnames=_STATIC)
def _EG_jit(z, z1, z2, y, nu, rin, d, kind, reference):
    return jax.value_and_grad(_energy)(z, z1, z2, y, nu, rin, d, kind, reference)


@partial(jax.jit, static_argnames=_STATIC)
def _EGH_jit(z, z1, z2, y, nu, rin, d, kind, reference):
    """(E, ∂E/∂z, ∂²E/∂z²) — the Hessian includes the decoder curvature."""
    e, g = jax.value_and_grad(_energy)(z, z1, z2, y, nu, rin, d, kind, reference)
    return e, g, jax.jacfwd(_grad)(z, z1, z2, y, nu, rin, d, kind, reference)


@partial(jax.jit, static_argnames=_STATIC)
def _hvjp_jit(z, z1, z2, y, nu, rin, lam, d, kind, reference):
    """λᵀ ∂h/∂(z_{t−1}, z_{t−2}, E, ν) for h = ∂E/∂z."""
    _, vjp = jax.vjp(lambda a, b, c, e: _grad(z, a, b, c, e, rin, d, kind, reference), z1, z2, y, nu)
    return vjp(lam)


@partial(jax.jit, static_argnames=_STATIC)
def _GN_jit(z, z1, z2, y, nu, rin, d, kind, reference):
    """Jqᵀ H_q Jq (no decoder curvature), H_q = ∂²E/∂q² at q(z)."""
    jq = jax.jacfwd(lambda zz: _q(zz, d, kind))(z)  # (p, r)
    h_q = jax.hessian(_energy_q)(_q(z, d, kind), _q(z1, d, kind), _q(z2, d, kind), y, nu, rin, d, reference)
    return jq.T @ h_q @ jq


@partial(jax.jit, static_argnames=("kind",))
def _H_jit(z, z1, z2, young, poisson, rin, d, kind):
    """∂²E/∂z² assembled (no obstacles): Jqᵀ (G/Δt² + K_h + Σ_q D_qᵀ w_q V_q ∂²Ψ/∂F² D_q) Jq + the decoder
    curvature Σ_k (∂E/∂q_k) ∂²q_k/∂z², with Jq = ∂q/∂z (p, r) and D_q = ∂vec F_q/∂q (9, p) constant."""
    s = d["scene_s"]
    q, q1, q2 = _q(z, d, kind), _q(z1, d, kind), _q(z2, d, kind)
    jq = jax.jacfwd(lambda zz: _q(zz, d, kind))(z)  # (p, r)
    mu, lam = _cubature_lame(young, poisson, d)
    F = d["F0"] + (d["dF"] @ q).reshape(-1, 3, 3)
    psi = energy_density(s.material)
    hf = jax.vmap(lambda f, m, l: jax.hessian(psi)(f, m, l).reshape(9, 9))(F, mu, lam)  # (c, 9, 9)
    if s.damped:  # the viscous term's ∂²/∂F² at F_prev = F of q_{t−1}, times β/Δt
        F1 = d["F0"] + (d["dF"] @ q1).reshape(-1, 3, 3)
        hf = hf + s.damping / s.dt * jax.vmap(lambda f, f1, m, l: jax.hessian(viscous_density)(f, f1, m, l)
                                              .reshape(9, 9))(F, F1, mu, lam)
    b = jnp.einsum("cfg,cgp->cfp", hf * d["cub_vol"][:, None, None], d["dF"])
    h_q = jnp.einsum("cfp,cfs->ps", d["dF"], b) + d["G"] / s.dt ** 2 + d["H_handle"]  # (p, p)
    h = jq.T @ h_q @ jq
    if kind in LINEAR_KINDS:
        return h
    g_q = jax.grad(_energy_q)(q, q1, q2, young, poisson, rin, d, False)
    return h + jax.hessian(lambda zz: jnp.dot(jax.lax.stop_gradient(g_q), _q(zz, d, kind)))(z)


def _factorise(h: np.ndarray) -> np.ndarray:
    """Cholesky factor of H + τI with the smallest τ ≥ 0 (from 0, then growing) that is positive definite."""
    hs = 0.5 * (h + h.T)
    tau = 0.0
    scale = max(float(np.max(np.abs(np.diag(hs)))), 1e-300)
    for _ in range(80):
        try:
            return np.linalg.cholesky(hs + tau * np.eye(len(h)))
        except np.linalg.LinAlgError:
            tau = max(2.0 * tau, 1e-8 * scale)
    return np.sqrt(scale) * np.eye(len(h))


def _inverse(c: np.ndarray) -> np.ndarray:
    """(C Cᵀ)⁻¹ for a lower-triangular Cholesky factor C (symmetric, (r, r))."""
    from scipy.linalg import solve_triangular

    ci = solve_triangular(c, np.eye(len(c)), lower=True)
    return ci.T @ ci


def _solve_sym(h: np.ndarray, b: np.ndarray) -> np.ndarray:
    """H⁻¹ b for the reduced Hessian, symmetrised: ½ (H + Hᵀ) z = b (numpy's LAPACK gesv, an LU solve)."""
    return np.linalg.solve(0.5 * (h + h.T), b)
