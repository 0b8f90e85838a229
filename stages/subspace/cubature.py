"""Optimised cubature for the reduced elastic energy (An et al. 2008), over quadrature points.

The elastic energy is a sum over quadrature points q (stages.sim.quadrature.Quadrature: P1 one
point per tet, P2 four per tet), Σ_q V_q Ψ(F_q(φ(z))) with F_q = x[nodes_q]ᵀ grad_q; the reduced
model replaces it by Σ_{q∈C} w_q V_q Ψ(F_q(φ(z))) over a few hundred points C with w_q ≥ 0, chosen so
that the reduced forces match on training poses z_k:

    min_w ‖A w − b‖,  w ≥ 0,   A[(k, R), q] = g_q(z_k) [q ∈ R] / ‖b_k‖,
    b[(k, R)] = Σ_{q∈R} g_q(z_k) / ‖b_k‖,   g_q(z) = ∂/∂z V_q Ψ(F_q(φ(z))) ∈ ℝʳ

(one block of rows per material region R, so each region's sum is matched on its own).  Points are
added greedily from random candidate pools by the score ⟨A_q, residual⟩ / ‖A_q‖ and the weights
re-solved with scipy.optimize.nnls.  For P1 meshes point ids are tet ids.  A material with viscous damping adds
the rows of the viscous forces ∂/∂z V_q D(F_q(φ(z)), F_q(x_prev)) at consecutive training poses
(:class:`ViscousForceSampler`, :class:`StackedSampler`): one set of weights integrates both terms.
"""
from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.optimize import nnls  # noqa: E402

from functools import partial  # noqa: E402

from stages.sim.materials import energy_density, viscous_density  # noqa: E402
from stages.sim.quadrature import Quadrature, build_quadrature, element_order, linear_quadrature  # noqa: E402
from stages.subspace.networks import SubspaceMap  # noqa: E402


def p1_quadrature(tets: np.ndarray, dm_inv: np.ndarray, volumes: np.ndarray) -> Quadrature:
    """The one-point quadrature of linear tets (m, 4): point e is tet e (quadrature.linear_quadrature)."""
    return linear_quadrature(tets, dm_inv, volumes)


def mesh_quadrature(vertices: np.ndarray, tets: np.ndarray, dm_inv: np.ndarray | None = None,
                    volumes: np.ndarray | None = None) -> Quadrature:
    """Quadrature points of a mesh or scene: P1 from (dm_inv, volumes) when given, else
    stages.sim.quadrature.build_quadrature (P2: four points per tet)."""
    if element_order(tets) == 1 and dm_inv is not None and volumes is not None \
            and np.shape(dm_inv) == (len(tets), 3, 3):
        return p1_quadrature(tets, dm_inv, volumes)
    return build_quadrature(np.asarray(vertices, np.float64), np.asarray(tets, np.int64))


def scene_quadrature(scene) -> Quadrature:
    """The scene's quadrature points (``scene.quad`` when the Scene carries them)."""
    q = getattr(scene, "quad", None)
    if isinstance(q, Quadrature):
        return q
    return mesh_quadrature(scene.rest, scene.tets, getattr(scene, "dm_inv", None), getattr(scene, "volumes", None))


def point_energies(x, quad: Quadrature, mu, lam, model: str):
    """V_q Ψ(F_q; μ_q, λ_q) per quadrature point, x (n, 3) → (q,) J (μ, λ per point)."""
    psi = energy_density(model)
    f = jnp.einsum("qki,qkj->qij", x[jnp.asarray(quad.nodes)], jnp.asarray(quad.grad))
    return jnp.asarray(quad.weight) * jax.vmap(psi)(f, mu, lam)


def tet_energies(x, tets, dm_inv, volumes, mu, lam, model: str):
    """V_e Ψ(F_e; μ_e, λ_e) per linear tet, x (n, 3) → (m,) J."""
    return point_energies(x, p1_quadrature(tets, dm_inv, volumes), mu, lam, model)


VISCOUS = "viscous"
"""The ``model`` of :func:`_point_grads` whose energy is the viscous term V_q D(F_q, F_q,prev) (ViscousForceSampler)."""


def _point_grads(xe, xpe, grad, weight, mu, lam, model):
    """∂(V_q Ψ_q)/∂x_e for points given by their element's node positions xe (c, k, 3) → (c, k, 3); with model
    :data:`VISCOUS` of V_q D(F_q, F_q,prev) instead, F_q,prev from the positions before, xpe (unused otherwise)."""
    if model == VISCOUS:
        def one(xe, xpe, g, v, mu, lam):
            return v * viscous_density(xe.T @ g, xpe.T @ g, mu, lam)
    else:
        psi = energy_density(model)

        def one(xe, xpe, g, v, mu, lam):
            return v * psi(xe.T @ g, mu, lam)

    return jax.vmap(jax.grad(one))(xe, xpe, grad, weight, mu, lam)


@partial(jax.jit, static_argnames=("model",))
def _cols_jit(x, xp, jq, ids, basis, nodes, grad, weight, mu, lam, model):
    """g_q for the points ids at one pose (x, and xp before it for the viscous term), (c, r)."""
    te = nodes[ids]
    ge = _point_grads(x[te], xp[te], grad[ids], weight[ids], mu[ids], lam[ids], model)  # (c, k, 3)
    return jnp.einsum("cai,caip->cp", ge, basis[te]) @ jq


@partial(jax.jit, static_argnames=("model",))
def _totals_jit(x, xp, jq, region_onehot, basis, nodes, grad, weight, mu, lam, model):
    """Σ_{q∈R} g_q at one pose, (R, r): forces scattered to vertices first, then projected (O(n p))."""
    ge = _point_grads(x[nodes], xp[nodes], grad, weight, mu, lam, model)  # (Q, k, 3)
    f = jnp.zeros((region_onehot.shape[1],) + x.shape).at[:, nodes].add(
        region_onehot.T[:, :, None, None] * ge[None])  # (R, n, 3)
    return jnp.einsum("Rni,nip->Rp", f, basis) @ jq


class ReducedForceSampler:
    """g_q(z_k) for chosen quadrature points at fixed poses z_k (K, r): the columns of A.

    ``ReducedForceSampler(sub, z, quad, mu_q, lam_q, model)`` with a Quadrature and μ, λ per point
    (q,); the older form ``(sub, z, tets, dm_inv, volumes, mu_tet, lam_tet, model)`` of linear tets
    builds the P1 quadrature (point = tet).  Per pose, the full positions x_k = φ(z_k) and
    Jq_k = ∂q/∂z are kept; a point's reduced force is (∂q/∂z)ᵀ Σ_a U_aᵀ ∂(V_qΨ_q)/∂x_a, never
    forming the (3n × r) J.
    """

    def __init__(self, sub: SubspaceMap, z: np.ndarray, quad, *args):
        if isinstance(quad, Quadrature):
            mu_q, lam_q, model = args
        else:
            dm_inv, volumes, mu_q, lam_q, model = args
            quad = p1_quadrature(quad, dm_inv, volumes)
        self.sub, self.model, self.quad = sub, model, quad
        self.mu, self.lam = np.asarray(mu_q, np.float64), np.asarray(lam_q, np.float64)
        if self.mu.shape != (quad.n_points,):
            raise ValueError(f"μ has shape {self.mu.shape}; expected one value per quadrature point "
                             f"({quad.n_points},)")
        zj = jnp.asarray(z)
        self.x = np.asarray(sub.decode(zj))  # (K, n, 3)
        self.xp = self.x  # the positions before each pose: the viscous term's (ViscousForceSampler), unused here
        self.jq = np.asarray(jax.vmap(sub.jacobian_q)(zj))  # (K, p, r)
        arrays = (jnp.asarray(sub.basis), jnp.asarray(np.asarray(quad.nodes, np.int64)), jnp.asarray(quad.grad),
                  jnp.asarray(quad.weight), jnp.asarray(self.mu), jnp.asarray(self.lam))

        def cols(x, xp, jq, ids):
            return _cols_jit(x, xp, jq, ids, *arrays, model)

        def totals(x, xp, jq, region_onehot):
            return _totals_jit(x, xp, jq, region_onehot, *arrays, model)

        self._cols, self._totals = cols, totals

    @property
    def n_points(self) -> int:
        return self.quad.n_points

    def columns(self, point_ids: np.ndarray) -> np.ndarray:
        """g_q(z_k) for each pose and point, (K, c, r)."""
        ids = jnp.asarray(point_ids)
        return np.stack([np.asarray(self._cols(self.x[k], self.xp[k], self.jq[k], ids)) for k in range(len(self.x))])

    def region_totals(self, point_region: np.ndarray, n_regions: int) -> np.ndarray:
        """Σ_{q∈R} g_q(z_k), (K, R, r)."""
        onehot = jnp.asarray(np.eye(n_regions)[point_region])
        return np.stack([np.asarray(self._totals(self.x[k], self.xp[k], self.jq[k], onehot))
                         for k in range(len(self.x))])


class ViscousForceSampler(ReducedForceSampler):
    """The reduced viscous forces of the points, ∂/∂z V_q D(F_q(φ(z)), F_q(x_prev)) (materials.viscous_density) at
    pose pairs (z_k, x_prev,k): a material with damping (Scene.damping), whose cubature must integrate this term
    too — its integrand, strain rates, differs from the elastic one.  ``x_prev`` (K, n, 3)."""

    def __init__(self, sub: SubspaceMap, z: np.ndarray, x_prev: np.ndarray, quad: Quadrature, mu_q, lam_q):
        super().__init__(sub, z, quad, mu_q, lam_q, VISCOUS)
        self.xp = np.asarray(x_prev, np.float64)


class StackedSampler:
    """Several samplers' poses as one (their rows stacked): a cubature fitted to all of their forces."""

    def __init__(self, *samplers):
        self.samplers = samplers

    @property
    def n_points(self) -> int:
        return self.samplers[0].n_points

    def columns(self, point_ids: np.ndarray) -> np.ndarray:
        return np.concatenate([s.columns(point_ids) for s in self.samplers])

    def region_totals(self, point_region: np.ndarray, n_regions: int) -> np.ndarray:
        return np.concatenate([s.region_totals(point_region, n_regions) for s in self.samplers])


def _rows(cols: np.ndarray, ids: np.ndarray, point_region: np.ndarray, n_regions: int, norms: np.ndarray):
    """Columns of A for points: (K, c, r) forces → (K·R·r, c) with each point in its region's block."""
    k, c, r = cols.shape
    a = np.zeros((k, n_regions, r, c))
    a[:, point_region[ids], :, np.arange(c)] = np.transpose(cols, (1, 0, 2))
    return (a / norms[:, None, None, None]).reshape(k * n_regions * r, c)


def _carries_force(col_norms: np.ndarray, rel: float = 1e-6) -> np.ndarray:
    """(c,) bool: the points whose reduced-force column is not negligible (> rel × the median column).  A point
    whose nodes the subspace holds still (the rows of U at a hard handle's vertices are ~1e-10 when the
    snapshots held them) has a round-off column: normalised by its own norm it could win the greedy score,
    and NNLS would give it a weight of ~1e27 (a huge, noisy energy term)."""
    c = np.asarray(col_norms, np.float64)
    ref = float(np.median(c[c > 0])) if np.any(c > 0) else 0.0
    return c > rel * ref


def fit_cubature(sampler: ReducedForceSampler, point_region: np.ndarray, n_regions: int, max_points: int = 300,
                 tol: float = 0.01, candidates: int = 1000, seed: int = 0, *, max_tets: int | None = None
                 ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Greedy NNLS cubature: (point ids (c,), weights (c,), {"error_rel", "iterations"}).

    point_region (q,): the material region of each quadrature point (point_region[quad.element]).
    Stops when ‖A w − b‖/‖b‖ < tol or max_points points are used (``max_tets``: the older name).
    """
    if max_tets is not None:
        max_points = max_tets
    rng = np.random.default_rng(seed)
    point_region = np.asarray(point_region)
    m = len(point_region)
    totals = sampler.region_totals(point_region, n_regions)  # (K, R, r)
    norms = np.maximum(np.linalg.norm(totals.reshape(len(totals), -1), axis=1), 1e-300)
    b = (totals / norms[:, None, None]).reshape(-1)
    bnorm = max(np.linalg.norm(b), 1e-300)
    if max_points >= m:
        ids = np.arange(m)
        a = _rows(sampler.columns(ids), ids, point_region, n_regions, norms)
        a = a * _carries_force(np.linalg.norm(a, axis=0))[None, :]  # a zero column gets weight 0
        w, _ = nnls(a, b, maxiter=50 * m)
        keep = w > 0
        return ids[keep], w[keep], {"error_rel": float(np.linalg.norm(a @ w - b) / bnorm), "iterations": 1}
    per_iter = max(1, max_points // 25)
    sel = np.zeros(0, np.int64)
    a_sel = np.zeros((len(b), 0))
    w = np.zeros(0)
    res = b.copy()
    err = 1.0
    it = 0
    for it in range(1, 4 * max_points + 1):
        pool = np.setdiff1d(np.arange(m), sel)
        if len(pool) == 0:
            break
        cand = rng.choice(pool, size=min(candidates, len(pool)), replace=False)
        ac = _rows(sampler.columns(cand), cand, point_region, n_regions, norms)
        cn = np.linalg.norm(ac, axis=0)
        score = np.where(_carries_force(cn), (ac.T @ res) / np.maximum(cn, 1e-300), -np.inf)
        take = min(per_iter, max_points - len(sel))
        best = np.argsort(-score)[:take]
        best = best[score[best] > 0]
        if len(best) == 0:
            break
        sel = np.concatenate([sel, cand[best]])
        a_sel = np.concatenate([a_sel, ac[:, best]], axis=1)
        w, _ = nnls(a_sel, b, maxiter=50 * a_sel.shape[1] + 100)
        keep = w > 0
        sel, a_sel, w = sel[keep], a_sel[:, keep], w[keep]
        res = b - a_sel @ w
        err = float(np.linalg.norm(res) / bnorm)
        if err < tol or len(sel) >= max_points:
            break
    order = np.argsort(sel)
    return sel[order], w[order], {"error_rel": err, "iterations": it}


def cubature_error(sampler: ReducedForceSampler, point_region: np.ndarray, n_regions: int,
                   point_ids: np.ndarray, weights: np.ndarray) -> float:
    """‖A w − b‖/‖b‖ of a cubature at the sampler's poses (e.g. held-out ones)."""
    totals = sampler.region_totals(np.asarray(point_region), n_regions)
    norms = np.maximum(np.linalg.norm(totals.reshape(len(totals), -1), axis=1), 1e-300)
    b = (totals / norms[:, None, None]).reshape(-1)
    a = _rows(sampler.columns(np.asarray(point_ids)), np.asarray(point_ids), np.asarray(point_region), n_regions, norms)
    return float(np.linalg.norm(a @ weights - b) / max(np.linalg.norm(b), 1e-300))
