"""Fitting subspaces to snapshots: mass-weighted PCA and the autoencoder (Adam, optax).

Training works on the PCA coefficients q = Uᵀ M (x − x̄) of the snapshots: since
U is M-orthonormal, ‖U(q̃ − q)‖²_M = ‖q̃ − q‖², so the autoencoder's loss in q
equals its mass-weighted displacement error up to the (fixed) part of x
outside span U, and a training step costs nothing that grows with the mesh.
"""
from __future__ import annotations

from functools import partial
from typing import Callable

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optax  # noqa: E402

from stages.subspace.networks import SubspaceMap, init_net, net_decode, net_encode  # noqa: E402


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


def _loss(net, q, scale, total_mass):
    """mean_s ‖q̃_s − q_s‖² / M_total, q̃ = s ⊙ D̂(Ê(q/s))."""
    rec = scale * net_decode(net, net_encode(net, q / scale))
    return jnp.mean(jnp.sum((rec - q) ** 2, axis=-1)) / total_mass


_loss_jit = jax.jit(_loss)


@partial(jax.jit, static_argnames=("learning_rate", "batch_size"))
def _epoch(net, state, key, q_train, scale, total_mass, learning_rate, batch_size):
    """One pass of Adam over shuffled mini-batches (compiled once per shape, shared across calls)."""
    opt = optax.adam(learning_rate)
    s, p = q_train.shape
    nb = max(1, s // batch_size)
    size = batch_size if s >= batch_size else s
    perm = jax.random.permutation(key, s)[: nb * size]
    batches = q_train[perm].reshape(nb, size, p)

    def body(carry, qb):
        net, state = carry
        loss, g = jax.value_and_grad(_loss)(net, qb, scale, total_mass)
        upd, state = opt.update(g, state, net)
        return (optax.apply_updates(net, upd), state), loss

    (net, state), losses = jax.lax.scan(body, (net, state), batches)
    return net, state, jnp.mean(losses)


def train_autoencoder(q_train: np.ndarray, q_val: np.ndarray, r: int, epochs: int, seed: int = 0,
                      learning_rate: float = 1e-3, batch_size: int = 64, total_mass: float = 1.0,
                      callback: Callable[[int, float, float], None] | None = None
                      ) -> tuple[dict, np.ndarray, list[tuple[float, float]]]:
    """Adam on L = mean_s ‖q̃_s − q_s‖² / M_total (m²), q̃ = s ⊙ D̂(Ê(q/s)).

    q_train (S, p), q_val (S_v, p).  Returns (net weights, scale s (p,), [(train, val) per epoch]).
    Keeps the weights of the epoch with the lowest validation loss (train loss without validation data).
    """
    q_train = jnp.asarray(q_train)
    q_val = jnp.asarray(q_val) if len(q_val) else q_train
    p = q_train.shape[1]
    rms = jnp.sqrt(jnp.mean(q_train ** 2, axis=0))
    scale = jnp.maximum(rms, 1e-3 * jnp.max(rms) + 1e-300)  # modes the data barely spans are not blown up
    key = jax.random.PRNGKey(seed)
    key, k0 = jax.random.split(key)
    net = init_net(k0, r, p)
    opt = optax.adam(learning_rate)
    state = opt.init(net)

    opt_args = (learning_rate, int(batch_size))
    mass = jnp.asarray(total_mass, jnp.float64)
    history = []
    best = (float(_loss_jit(net, q_val, scale, mass)), net)
    for e in range(epochs):
        key, ke = jax.random.split(key)
        net, state, tl = _epoch(net, state, ke, q_train, scale, mass, *opt_args)
        vl = float(_loss_jit(net, q_val, scale, mass))
        history.append((float(tl), vl))
        if vl < best[0]:
            best = (vl, net)
        if callback is not None:
            callback(e, float(tl), vl)
    return {k: np.asarray(v) for k, v in best[1].items()}, np.asarray(scale), history


def fit_subspace(kind: str, rest: np.ndarray, masses: np.ndarray, x_train: np.ndarray, r: int,
                 x_val: np.ndarray | None = None, epochs: int = 300, seed: int = 0, pca_dim: int | None = None,
                 learning_rate: float = 1e-3, batch_size: int = 64,
                 callback: Callable[[int, float, float], None] | None = None) -> tuple[SubspaceMap, dict]:
    """Fit a subspace of latent dimension r to snapshots x_train (S, n, 3).

    PCA: U = the r leading mass-weighted modes.  Autoencoder: U = the p leading modes
    (p = pca_dim, default min(max(2r, r + 20), rank)), then the MLP trained on q.
    Returns (map, info{"pca_dim", "history", "singular_values"}).
    """
    x_val = np.zeros((0,) + x_train.shape[1:]) if x_val is None else x_val
    u = x_train - rest[None]
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
