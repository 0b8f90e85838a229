"""Optimised cubature for the reduced elastic energy (An et al. 2008).

The reduced elastic energy Σ_e V_e Ψ(F_e(φ(z))) over all m tets is replaced by
Σ_{e∈C} w_e V_e Ψ(F_e(φ(z))) over a few hundred tets C with w_e ≥ 0, chosen so
that the reduced forces match on training poses z_k:

    min_w ‖A w − b‖,  w ≥ 0,   A[(k, R), e] = g_e(z_k) [e ∈ R] / ‖b_k‖,
    b[(k, R)] = Σ_{e∈R} g_e(z_k) / ‖b_k‖,   g_e(z) = ∂/∂z V_e Ψ(F_e(φ(z))) ∈ ℝʳ

(one block of rows per material region R, so each region's sum is matched on its
own).  Tets are added greedily from random candidate pools by the score
⟨A_e, residual⟩ / ‖A_e‖ and the weights re-solved with scipy.optimize.nnls.
"""
from __future__ import annotations

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy.optimize import nnls  # noqa: E402

from functools import partial  # noqa: E402

from stages.sim.materials import energy_density  # noqa: E402
from stages.sim.mesh import deformation_gradients  # noqa: E402
from stages.subspace.networks import SubspaceMap  # noqa: E402


def tet_energies(x, tets, dm_inv, volumes, mu, lam, model: str):
    """V_e Ψ(F_e; μ_e, λ_e) per tet, x (n, 3) → (m,) J."""
    psi = energy_density(model)
    f = deformation_gradients(x, tets, dm_inv)
    return volumes * jax.vmap(psi)(f, mu, lam)


def _tet_grads(xe, dm_inv, volumes, mu, lam, model):
    """∂(V_e Ψ_e)/∂x_e for tets given by their vertex positions xe (c, 4, 3) → (c, 4, 3)."""
    psi = energy_density(model)

    def one(xe, dmi, v, mu, lam):
        ds = (xe[1:4] - xe[0:1]).T
        return v * psi(ds @ dmi, mu, lam)

    return jax.vmap(jax.grad(one))(xe, dm_inv, volumes, mu, lam)


@partial(jax.jit, static_argnames=("model",))
def _cols_jit(x, jq, tet_ids, basis, tets, dm_inv, volumes, mu, lam, model):
    """g_e for the tets tet_ids at one pose, (c, r)."""
    te = tets[tet_ids]
    ge = _tet_grads(x[te], dm_inv[tet_ids], volumes[tet_ids], mu[tet_ids], lam[tet_ids], model)  # (c, 4, 3)
    return jnp.einsum("cai,caip->cp", ge, basis[te]) @ jq


@partial(jax.jit, static_argnames=("model",))
def _totals_jit(x, jq, region_onehot, basis, tets, dm_inv, volumes, mu, lam, model):
    """Σ_{e∈R} g_e at one pose, (R, r): forces scattered to vertices first, then projected (O(n p))."""
    ge = _tet_grads(x[tets], dm_inv, volumes, mu, lam, model)  # (m, 4, 3)
    f = jnp.zeros((region_onehot.shape[1],) + x.shape).at[:, tets].add(
        region_onehot.T[:, :, None, None] * ge[None])  # (R, n, 3)
    return jnp.einsum("Rni,nip->Rp", f, basis) @ jq


class ReducedForceSampler:
    """g_e(z_k) for chosen tets at fixed poses z_k (K, r): the columns of A.

    Per pose, the full positions x_k = φ(z_k) and Jq_k = ∂q/∂z are kept; a tet's
    reduced force is (∂q/∂z)ᵀ Σ_a U_aᵀ ∂(V_eΨ_e)/∂x_a, never forming the (3n × r) J.
    """

    def __init__(self, sub: SubspaceMap, z: np.ndarray, tets, dm_inv, volumes, mu_tet, lam_tet, model: str):
        self.sub, self.model = sub, model
        self.tets, self.dm_inv, self.volumes = np.asarray(tets), np.asarray(dm_inv), np.asarray(volumes)
        self.mu, self.lam = np.asarray(mu_tet, np.float64), np.asarray(lam_tet, np.float64)
        zj = jnp.asarray(z)
        self.x = np.asarray(sub.decode(zj))  # (K, n, 3)
        self.jq = np.asarray(jax.vmap(sub.jacobian_q)(zj))  # (K, p, r)
        arrays = (jnp.asarray(sub.basis), jnp.asarray(self.tets), jnp.asarray(self.dm_inv),
                  jnp.asarray(self.volumes), jnp.asarray(self.mu), jnp.asarray(self.lam))

        def cols(x, jq, tet_ids):
            return _cols_jit(x, jq, tet_ids, *arrays, model)

        def totals(x, jq, region_onehot):
            return _totals_jit(x, jq, region_onehot, *arrays, model)

        self._cols, self._totals = cols, totals

    def columns(self, tet_ids: np.ndarray) -> np.ndarray:
        """g_e(z_k) for each pose and tet, (K, c, r)."""
        ids = jnp.asarray(tet_ids)
        return np.stack([np.asarray(self._cols(self.x[k], self.jq[k], ids)) for k in range(len(self.x))])

    def region_totals(self, tet_region: np.ndarray, n_regions: int) -> np.ndarray:
        """Σ_{e∈R} g_e(z_k), (K, R, r)."""
        onehot = jnp.asarray(np.eye(n_regions)[tet_region])
        return np.stack([np.asarray(self._totals(self.x[k], self.jq[k], onehot)) for k in range(len(self.x))])


def _rows(cols: np.ndarray, tet_ids: np.ndarray, tet_region: np.ndarray, n_regions: int, norms: np.ndarray):
    """Columns of A for tets: (K, c, r) forces → (K·R·r, c) with each tet in its region's block."""
    k, c, r = cols.shape
    a = np.zeros((k, n_regions, r, c))
    a[:, tet_region[tet_ids], :, np.arange(c)] = np.transpose(cols, (1, 0, 2))
    return (a / norms[:, None, None, None]).reshape(k * n_regions * r, c)


def fit_cubature(sampler: ReducedForceSampler, tet_region: np.ndarray, n_regions: int, max_tets: int = 300,
                 tol: float = 0.01, candidates: int = 1000, seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Greedy NNLS cubature: (tet ids (c,), weights (c,), {"error_rel", "iterations"}).

    Stops when ‖A w − b‖/‖b‖ < tol or max_tets tets are used.
    """
    rng = np.random.default_rng(seed)
    tet_region = np.asarray(tet_region)
    m = len(tet_region)
    totals = sampler.region_totals(tet_region, n_regions)  # (K, R, r)
    norms = np.maximum(np.linalg.norm(totals.reshape(len(totals), -1), axis=1), 1e-300)
    b = (totals / norms[:, None, None]).reshape(-1)
    bnorm = max(np.linalg.norm(b), 1e-300)
    if max_tets >= m:
        ids = np.arange(m)
        a = _rows(sampler.columns(ids), ids, tet_region, n_regions, norms)
        w, _ = nnls(a, b, maxiter=50 * m)
        keep = w > 0
        return ids[keep], w[keep], {"error_rel": float(np.linalg.norm(a @ w - b) / bnorm), "iterations": 1}
    per_iter = max(1, max_tets // 25)
    sel = np.zeros(0, np.int64)
    a_sel = np.zeros((len(b), 0))
    w = np.zeros(0)
    res = b.copy()
    err = 1.0
    it = 0
    for it in range(1, 4 * max_tets + 1):
        pool = np.setdiff1d(np.arange(m), sel)
        if len(pool) == 0:
            break
        cand = rng.choice(pool, size=min(candidates, len(pool)), replace=False)
        ac = _rows(sampler.columns(cand), cand, tet_region, n_regions, norms)
        score = (ac.T @ res) / np.maximum(np.linalg.norm(ac, axis=0), 1e-300)
        take = min(per_iter, max_tets - len(sel))
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
        if err < tol or len(sel) >= max_tets:
            break
    order = np.argsort(sel)
    return sel[order], w[order], {"error_rel": err, "iterations": it}


def cubature_error(sampler: ReducedForceSampler, tet_region: np.ndarray, n_regions: int,
                   tet_ids: np.ndarray, weights: np.ndarray) -> float:
    """‖A w − b‖/‖b‖ of a cubature at the sampler's poses (e.g. held-out ones)."""
    totals = sampler.region_totals(np.asarray(tet_region), n_regions)
    norms = np.maximum(np.linalg.norm(totals.reshape(len(totals), -1), axis=1), 1e-300)
    b = (totals / norms[:, None, None]).reshape(-1)
    a = _rows(sampler.columns(np.asarray(tet_ids)), np.asarray(tet_ids), np.asarray(tet_region), n_regions, norms)
    return float(np.linalg.norm(a @ weights - b) / max(np.linalg.norm(b), 1e-300))
