"""Fitting subspaces: mass-weighted PCA and the autoencoder (equinox Module, Adam via optax) to snapshots,
and the data-free linear-blend-skinning (LBS) basis.

Training works on the PCA coefficients q = Uᵀ M (x − x̄) of the snapshots: since
U is M-orthonormal, ‖U(q̃ − q)‖²_M = ‖q̃ − q‖², so the autoencoder's loss in q
equals its mass-weighted displacement error up to the (fixed) part of x
outside span U, and a training step costs nothing that grows with the mesh.

LBS (lbs_basis; Jacobson et al. 2012 "Fast automatic skinning transformations", Brandt et al. 2018
"Hyper-reduced projective dynamics"): k handles c_j at farthest-point samples of the rest vertices,
harmonic skinning weights w_j (the tet mesh's scalar stiffness / cotangent Laplacian L, L w_j = 0
off the handles, w_j = 1 at handle j's vertex and 0 at the others; clipped ≥ 0, renormalised to a
partition of unity), and 12 modes per handle, u_{j,a}(x) = w_j(x) e_a ⊗ [x̄ − c_j; 1] (a 3×4 affine
map per handle), mass-orthonormalised.  Because Σ_j w_j = 1 the span holds every affine map of x̄,
rigid motions included.  On quadratic tets (m, 10) the handles are corner nodes, the weights are
solved on the corner tets and each mid-edge node takes the mean of its edge's two corner weights
(the linear interpolant along the edge, so the partition of unity holds at every node).
"""
from __future__ import annotations

import math
from typing import Callable

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402
import scipy.sparse as sp  # noqa: E402
from scipy.sparse.linalg import splu  # noqa: E402

from stages.sim.quadrature import P2_EDGES, element_order  # noqa: E402
from stages.subspace.networks import Autoencoder, SubspaceMap  # noqa: E402


def pca_basis(displacements: np.ndarray, masses: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Mass-orthonormal basis of the leading p modes of displacements u (S, n, 3).

    SVD of the mass-weighted data M^½ u = A Σ Vᵀ; U = M^-½ V[:, :p] so that Uᵀ M U = I.
    Returns (U (n, 3, p), singular values (min(S, 3n),)).
    """
    s, n, _ = displacements.shape
    sq = np.sqrt(masses)
    a = (displacements * sq[None, :, None]).reshape(s, 3 * n)
    _, sig, vt = np.linalg.svd(a, full_matrices=False)
    p = int(min(p, vt.shape[0]))
    basis = (vt[:p].T.reshape(n, 3, p)) / sq[:, None, None]
    # fix each mode's sign for reproducibility: largest-magnitude entry positive
    flat = basis.reshape(3 * n, p)
    sign = np.sign(flat[np.argmax(np.abs(flat), axis=0), np.arange(p)])
    return basis * sign, sig


def mean_vertex_error(x_rec: np.ndarray, x: np.ndarray) -> float:
    """Mean over snapshots and vertices of ‖x̃_i − x_i‖, metres."""
    return float(np.mean(np.linalg.norm(np.asarray(x_rec) - np.asarray(x), axis=-1)))


def reconstruction_error(sub: SubspaceMap, x: np.ndarray, batch: int = 64) -> float:
    """Mean vertex distance (m) between x (S, n, 3) and φ(ψ(x))."""
    if len(x) == 0:
        return float("nan")
    errs = []
    fn = jax.jit(lambda xb: jnp.linalg.norm(sub.decode(sub.encode(xb)) - xb, axis=-1).mean(axis=1))
    for i in range(0, len(x), batch):
        errs.append(np.asarray(fn(jnp.asarray(x[i:i + batch]))))
    return float(np.mean(np.concatenate(errs)))


# ---------------------------------------------------------------------------------------------------- LBS
def farthest_point_samples(points: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """k vertex ids by farthest-point sampling (Euclidean): the first one drawn with default_rng(seed),
    each next one the vertex farthest from those chosen (ties: lowest id).  points (n, 3) → (k,) int."""
    n = len(points)
    if not 1 <= k <= n:
        raise ValueError(f"cannot pick {k} handles among {n} vertices")
    ids = [int(np.random.default_rng(seed).integers(n))]
    dist = np.linalg.norm(points - points[ids[0]], axis=1)
    for _ in range(k - 1):
        ids.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[ids[-1]], axis=1))
    return np.asarray(ids, np.int64)


def stiffness_laplacian(rest: np.ndarray, tets: np.ndarray):
    """The scalar P1 stiffness ("cotangent") matrix of a tet mesh, K_ab = Σ_t V_t ∇λ_a·∇λ_b (n × n, CSR).

    λ the barycentric (hat) functions of each tet; symmetric positive semi-definite, K 1 = 0, and
    ½ fᵀ K f = ½ ∫|∇f|² for piecewise-linear f.  Degenerate tets (zero volume) add nothing.
    """
    x = rest[tets]  # (m, 4, 3)
    e = np.transpose(x[:, 1:] - x[:, :1], (0, 2, 1))  # (m, 3, 3), columns x_i − x_0
    det = np.linalg.det(e)
    ok = np.abs(det) > 1e-14 * np.max(np.abs(det), initial=0.0)
    inv = np.zeros_like(e)
    inv[ok] = np.linalg.inv(e[ok])  # rows = ∇λ_1..3
    grads = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)  # (m, 4, 3)
    vol = np.where(ok, np.abs(det) / 6.0, 0.0)
    ke = vol[:, None, None] * np.einsum("mai,mbi->mab", grads, grads)  # (m, 4, 4)
    rows = np.repeat(tets, 4, axis=1).ravel()
    cols = np.tile(tets, (1, 4)).ravel()
    n = len(rest)
    return sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(n, n))


def harmonic_weights(rest: np.ndarray, tets: np.ndarray, handle_ids: np.ndarray) -> np.ndarray:
    """Skinning weights W (n, k): W[:, j] solves L w = 0 off the handle vertices with w = 1 at handle j's
    vertex and 0 at the other handles (sparse LU, scipy; one factorisation, k right-hand sides), then
    clipped ≥ 0 and renormalised so that every row sums to 1 (a partition of unity).

    Vertices the handles cannot reach (a component without a handle) get the uniform 1/k.
    Quadratic tets (m, 10): solved on the corner tets (handles must be corners), mid-edge nodes
    interpolated linearly along their edges.
    """
    n, k = len(rest), len(handle_ids)
    handle_ids = np.asarray(handle_ids, np.int64)
    tets = np.asarray(tets, np.int64)
    if element_order(tets) == 2:
        corners = np.unique(tets[:, :4])
        local = np.full(n, -1, np.int64)
        local[corners] = np.arange(len(corners))
        if np.any(local[handle_ids] < 0):
            raise ValueError("LBS handles of a quadratic mesh must be corner nodes")
        Wc = harmonic_weights(rest[corners], local[tets[:, :4]], local[handle_ids])
        W = np.zeros((n, k))
        W[corners] = Wc
        for e, (a, b) in enumerate(P2_EDGES):
            W[tets[:, 4 + e]] = 0.5 * (W[tets[:, a]] + W[tets[:, b]])
        return W
    if len(np.unique(handle_ids)) != k:
        raise ValueError("handle vertices must be distinct")
    L = stiffness_laplacian(rest, tets).tocsc()
    free = np.setdiff1d(np.arange(n), handle_ids)
    W = np.zeros((n, k))
    W[handle_ids, np.arange(k)] = 1.0
    if len(free):
        L_ff = L[free][:, free]
        # a tiny diagonal shift keeps L_ff regular where a component holds no handle (isolated vertices)
        shift = 1e-12 * float(np.mean(np.abs(L.diagonal()))) + 1e-300
        lu = splu((L_ff + shift * sp.identity(len(free), format="csc")).tocsc())
        rhs = -np.asarray(L[free][:, handle_ids].todense())  # (n_free, k)
        W[free] = lu.solve(rhs)
    W = np.clip(W, 0.0, None)
    tot = W.sum(axis=1, keepdims=True)
    lost = tot[:, 0] <= 1e-9
    W[lost], tot[lost] = 1.0 / k, 1.0
    return W / tot


def lbs_modes(rest: np.ndarray, weights: np.ndarray, handles: np.ndarray) -> np.ndarray:
    """The raw LBS columns U (n, 3, 12k): column 12 j + 4 a + b is w_j(x) e_a [x̄ − c_j; 1]_b
    (a ∈ 0..2 the displaced coordinate, b ∈ 0..3 the affine map's column; c_j the handle positions (k, 3))."""
    n, k = weights.shape
    h = np.concatenate([rest[:, None, :] - handles[None], np.ones((n, k, 1))], axis=2)  # (n, k, 4)
    U = np.zeros((n, 3, k, 3, 4))
    for a in range(3):
        U[:, a, :, a, :] = weights[:, :, None] * h
    return U.reshape(n, 3, 12 * k)


def mass_orthonormalise(U: np.ndarray, masses: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """An M-orthonormal basis (n, 3, p) of span U (n, 3, c), Bᵀ M B = I, p ≤ c.

    Columns are scaled to unit M-norm, then B = U V Λ^-½ from the eigenpairs (Λ, V) of the Gram
    matrix Uᵀ M U, keeping eigenvalues above tol · max (directions closer to dependent are dropped).
    Order: largest eigenvalue first.
    """
    n, _, c = U.shape
    flat = U.reshape(3 * n, c)
    mw = np.repeat(masses, 3)
    norm = np.sqrt(np.einsum("ic,i,ic->c", flat, mw, flat))
    keep = norm > 0
    flat = flat[:, keep] / norm[keep]
    G = flat.T @ (mw[:, None] * flat)
    lam, V = np.linalg.eigh(G)
    order = np.argsort(lam)[::-1]
    lam, V = lam[order], V[:, order]
    good = lam > tol * lam[0] if len(lam) else np.zeros(0, bool)
    B = flat @ (V[:, good] / np.sqrt(lam[good]))
    # one Gram–Schmidt-style correction pass in M for the last bits of rounding
    C = np.linalg.cholesky(B.T @ (mw[:, None] * B))
    B = np.linalg.solve(C, B.T).T
    return B.reshape(n, 3, -1)


def lbs_basis(rest: np.ndarray, tets: np.ndarray, masses: np.ndarray, r: int,
              displacements: np.ndarray | None = None, seed: int = 0, tol: float = 1e-9) -> tuple[np.ndarray, dict]:
    """The LBS subspace basis U (n, 3, r) with Uᵀ M U = I (module docstring).

    k = ceil(r / 12) handles give a span of dimension P ≤ 12k (near-dependent directions dropped).
    When P > r, the r kept directions are the leading ones of a mass-weighted PCA of the
    displacements (S, n, 3) projected onto the span (the span coordinates' SVD, completed by an
    orthonormal complement within the span when the data has rank < r); without displacements,
    the r leading eigen-directions of the span's Gram matrix.
    Returns (U, info{"handle_ids" (k,), "handles" (k, 3), "weights" (n, k), "span" (n, 3, P),
    "span_dim" P, "selection"}).
    """
    k = max(1, math.ceil(r / 12))
    if element_order(tets) == 2:  # handles at corner nodes
        corners = np.unique(np.asarray(tets)[:, :4])
        ids = corners[farthest_point_samples(rest[corners], k, seed)]
    else:
        ids = farthest_point_samples(rest, k, seed)
    handles = rest[ids]
    W = harmonic_weights(rest, tets, ids)
    span = mass_orthonormalise(lbs_modes(rest, W, handles), masses, tol)
    P = span.shape[2]
    if P < r:
        raise ValueError(f"the {k} LBS handles span only {P} independent directions, fewer than r = {r}")
    n = len(rest)
    if P == r:
        U, selection = span, "the whole LBS span"
    elif displacements is not None and len(displacements):
        c = np.einsum("sni,n,nip->sp", displacements, masses, span)  # span coordinates, ‖·‖ = the M-norm
        lam, V = np.linalg.eigh(c.T @ c)  # (P, P): a complete orthonormal set even when rank c < r
        rot = V[:, np.argsort(lam, kind="stable")[::-1][:r]]  # (P, r), leading first
        U = np.einsum("nip,pr->nir", span, rot)
        selection = f"the {r} leading mass-weighted PCA directions of the snapshots inside the {P}-dim LBS span"
    else:
        U, selection = span[:, :, :r], f"the {r} leading Gram eigen-directions of the {P}-dim LBS span"
    flat = U.reshape(3 * n, r)
    sign = np.sign(flat[np.argmax(np.abs(flat), axis=0), np.arange(r)])
    U = U * np.where(sign == 0, 1.0, sign)
    return U, {"handle_ids": ids, "handles": handles, "weights": W, "span": span, "span_dim": int(P),
               "selection": selection}


def _loss(model: Autoencoder, q, scale, total_mass):
    """mean_s ‖q̃_s − q_s‖² / M_total, q̃ = s ⊙ D̂(Ê(q/s)); q (S, p), scale (p,)."""
    rec = scale * model(q / scale)
    return jnp.mean(jnp.sum((rec - q) ** 2, axis=-1)) / total_mass


_loss_jit = eqx.filter_jit(_loss)


@eqx.filter_jit
def _epoch(model: Autoencoder, state, key, q_train, scale, total_mass, learning_rate: float, batch_size: int):
    """One pass of Adam over shuffled mini-batches (compiled once per shape, shared across calls).

    learning_rate and batch_size are Python numbers, hence static under filter_jit.
    """
    opt = optax.adam(learning_rate)
    s, p = q_train.shape
    nb = max(1, s // batch_size)
    size = batch_size if s >= batch_size else s
    perm = jax.random.permutation(key, s)[: nb * size]
    batches = q_train[perm].reshape(nb, size, p)
    params, static = eqx.partition(model, eqx.is_inexact_array)

    def body(carry, qb):
        params, state = carry
        loss, g = eqx.filter_value_and_grad(_loss)(eqx.combine(params, static), qb, scale, total_mass)
        upd, state = opt.update(g, state, params)
        return (eqx.apply_updates(params, upd), state), loss

    (params, state), losses = jax.lax.scan(body, (params, state), batches)
    return eqx.combine(params, static), state, jnp.mean(losses)


def train_autoencoder(q_train: np.ndarray, q_val: np.ndarray, r: int, epochs: int, seed: int = 0,
                      learning_rate: float = 1e-3, batch_size: int = 64, total_mass: float = 1.0,
                      callback: Callable[[int, float, float], None] | None = None
                      ) -> tuple[dict, np.ndarray, list[tuple[float, float]]]:
    """Adam on L = mean_s ‖q̃_s − q_s‖² / M_total (m²), q̃ = s ⊙ D̂(Ê(q/s)), over an Autoencoder module.

    q_train (S, p), q_val (S_v, p).  Returns (net weights as named arrays (numpy), scale s (p,),
    [(train, val) per epoch]).  Keeps the weights of the epoch with the lowest validation loss
    (train loss without validation data).
    """
    q_train = jnp.asarray(q_train)
    q_val = jnp.asarray(q_val) if len(q_val) else q_train
    p = q_train.shape[1]
    rms = jnp.sqrt(jnp.mean(q_train ** 2, axis=0))
    scale = jnp.maximum(rms, 1e-3 * jnp.max(rms) + 1e-300)  # modes the data barely spans are not blown up
    key = jax.random.PRNGKey(seed)
    key, k0 = jax.random.split(key)
    model = Autoencoder.init(k0, r, p)
    state = optax.adam(learning_rate).init(eqx.filter(model, eqx.is_inexact_array))

    opt_args = (float(learning_rate), int(batch_size))
    mass = jnp.asarray(total_mass, jnp.float64)
    history = []
    best = (float(_loss_jit(model, q_val, scale, mass)), model)
    for e in range(epochs):
        key, ke = jax.random.split(key)
        model, state, tl = _epoch(model, state, ke, q_train, scale, mass, *opt_args)
        vl = float(_loss_jit(model, q_val, scale, mass))
        history.append((float(tl), vl))
        if vl < best[0]:
            best = (vl, model)
        if callback is not None:
            callback(e, float(tl), vl)
    return {k: np.asarray(v) for k, v in best[1].to_named().items()}, np.asarray(scale), history


def fit_subspace(kind: str, rest: np.ndarray, masses: np.ndarray, x_train: np.ndarray, r: int,
                 x_val: np.ndarray | None = None, epochs: int = 300, seed: int = 0, pca_dim: int | None = None,
                 learning_rate: float = 1e-3, batch_size: int = 64,
                 callback: Callable[[int, float, float], None] | None = None,
                 tets: np.ndarray | None = None) -> tuple[SubspaceMap, dict]:
    """Fit a subspace of latent dimension r to snapshots x_train (S, n, 3).

    PCA: U = the r leading mass-weighted modes.  Autoencoder: U = the p leading modes
    (p = pca_dim, default min(max(2r, r + 20), rank)), then the MLP trained on q.
    LBS (needs tets): lbs_basis with ceil(r/12) handles (seed picks the first), the snapshots only
    choosing r directions inside the span; info adds "lbs" (lbs_basis's info).
    Returns (map, info{"pca_dim", "history", "singular_values"}).
    """
    x_val = np.zeros((0,) + x_train.shape[1:]) if x_val is None else x_val
    u = x_train - rest[None]
    if kind == "lbs":
        if tets is None:
            raise ValueError("the lbs subspace needs the mesh's tets")
        basis, info = lbs_basis(rest, np.asarray(tets), masses, r, u, seed)
        aux = {"lbs_handles": info["handles"], "lbs_skin_weights": info["weights"]}
        sub = SubspaceMap("lbs", rest, basis, masses, np.ones(r), {}, aux)
        return sub, {"pca_dim": r, "history": [], "singular_values": [], "lbs": info}
    if kind == "pca":
        basis, sig = pca_basis(u, masses, r)
        if basis.shape[2] < r:
            basis = np.concatenate([basis, np.zeros(basis.shape[:2] + (r - basis.shape[2],))], axis=2)
        sub = SubspaceMap("pca", rest, basis, masses, np.ones(r), {})
        return sub, {"pca_dim": r, "history": [], "singular_values": sig[: 2 * r].tolist()}
    if kind != "autoencoder":
        raise ValueError(f"unknown subspace kind {kind!r}")
    p = pca_dim or max(2 * r, r + 20)
    basis, sig = pca_basis(u, masses, p)
    p = basis.shape[2]
    if p < r:
        raise ValueError(f"the snapshots span only {p} modes, fewer than the latent dimension {r}")
    tmp = SubspaceMap("pca", rest, basis, masses, np.ones(p), {})
    q_tr = np.asarray(tmp.project(jnp.asarray(x_train)))
    q_va = np.asarray(tmp.project(jnp.asarray(x_val))) if len(x_val) else np.zeros((0, p))
    net, scale, hist = train_autoencoder(q_tr, q_va, r, epochs, seed, learning_rate, batch_size,
                                         float(np.sum(masses)), callback)
    sub = SubspaceMap("autoencoder", rest, basis, masses, scale, {k: jnp.asarray(v) for k, v in net.items()})
    return sub, {"pca_dim": p, "history": hist, "singular_values": sig[: 2 * p].tolist()}
