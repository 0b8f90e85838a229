"""Subspace maps x = φ(z) as pure JAX functions over named arrays (PCA and the Fulton et al. 2019 autoencoder).

Both kinds share one outer linear layer, the mass-orthonormal PCA basis U of the
training displacements (Uᵀ M U = I, M the lumped mass matrix):

    x = φ(z) = x̄ + U q(z)                 x̄ rest positions (n, 3), U (n, 3, p), q ∈ ℝᵖ
    z = ψ(x) = e(q),   q = Uᵀ M (x − x̄)   (the M-orthogonal projection onto span U)

PCA: p = r and q(z) = z, e(q) = q.  Autoencoder (Fulton et al. 2019, §3): the
PCA layer is the outer layer of both halves; between it and the latent code sit
fully connected layers 2×200 with ELU, plus a linear skip initialised to the
PCA truncation, so that training starts from the PCA subspace:

    q(z) = s ⊙ (z S_d + D(z) − D(0)),   e(q) = (q/s) S_e + E(q/s) − E(0),

D, E the MLPs, s the per-coefficient scale of the training q.  Subtracting
D(0), E(0) makes φ(0) = x̄ and ψ(x̄) = 0 exactly.  Because x − x̄ = U q, the
decoder is linear after q: decoding a vertex subset only needs U's rows.
"""
from __future__ import annotations

from dataclasses import dataclass

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

KINDS = ("autoencoder", "pca")
HIDDEN = (200, 200)  # paper §5.1


def _mlp(ws: list, x):
    """ELU MLP: x → elu(x W₁ + b₁) → elu(· W₂ + b₂) → · W₃ + b₃ (ws = [W₁, b₁, W₂, b₂, W₃, b₃])."""
    h = x
    n = len(ws) // 2
    for i in range(n):
        h = h @ ws[2 * i] + ws[2 * i + 1]
        if i < n - 1:
            h = jax.nn.elu(h)
    return h


def net_decode(net: dict, z):
    """q̂(z) = z S_d + D(z) − D(0) (normalised coefficients), z (..., r) → (..., p)."""
    ws = [net[k] for k in ("dec_w1", "dec_b1", "dec_w2", "dec_b2", "dec_w3", "dec_b3")]
    return z @ net["dec_skip"] + _mlp(ws, z) - _mlp(ws, jnp.zeros_like(z))


def net_encode(net: dict, qn):
    """z(q̂) = q̂ S_e + E(q̂) − E(0), q̂ (..., p) → (..., r)."""
    ws = [net[k] for k in ("enc_w1", "enc_b1", "enc_w2", "enc_b2", "enc_w3", "enc_b3")]
    return qn @ net["enc_skip"] + _mlp(ws, qn) - _mlp(ws, jnp.zeros_like(qn))


def init_net(key, r: int, p: int, hidden=HIDDEN, out_scale: float = 1e-2) -> dict:
    """Autoencoder weights: skips = PCA truncation (S_e = [I; 0], S_d = [I, 0]); MLPs Glorot, last layer × out_scale."""
    keys = jax.random.split(key, 6)

    def glorot(k, a, b, scale=1.0):
        return scale * jax.random.normal(k, (a, b)) * np.sqrt(2.0 / (a + b))

    net = {"enc_skip": jnp.eye(p, r), "dec_skip": jnp.eye(r, p)}
    for prefix, dims, ks in (("enc", (p, *hidden, r), keys[:3]), ("dec", (r, *hidden, p), keys[3:])):
        for i in range(3):
            scale = out_scale if i == 2 else 1.0
            net[f"{prefix}_w{i + 1}"] = glorot(ks[i], dims[i], dims[i + 1], scale)
            net[f"{prefix}_b{i + 1}"] = jnp.zeros(dims[i + 1])
    return net


@dataclass(frozen=True)
class SubspaceMap:
    """φ and ψ of one trained subspace (numpy/JAX arrays, float64)."""

    kind: str  # "autoencoder" | "pca"
    rest: np.ndarray  # (n, 3) x̄, m
    basis: np.ndarray  # (n, 3, p) U, mass-orthonormal: Uᵀ M U = I
    masses: np.ndarray  # (n,) lumped masses M, kg
    q_scale: np.ndarray  # (p,) s
    net: dict  # named MLP arrays (empty for PCA)

    @property
    def dim(self) -> int:
        return int(self.net["dec_skip"].shape[0]) if self.kind == "autoencoder" else int(self.basis.shape[2])

    @property
    def p(self) -> int:
        return int(self.basis.shape[2])

    # ------------------------------------------------------------------ q-space
    def q_of_z(self, z):
        """q(z), (..., r) → (..., p)."""
        if self.kind == "pca":
            return z
        return self.q_scale * net_decode(self.net, z)

    def z_of_q(self, q):
        """e(q), (..., p) → (..., r)."""
        if self.kind == "pca":
            return q
        return net_encode(self.net, q / self.q_scale)

    def project(self, x):
        """q = Uᵀ M (x − x̄), x (..., n, 3) → (..., p)."""
        d = (x - self.rest) * self.masses[:, None]
        return jnp.einsum("...ni,nip->...p", d, self.basis)

    # ------------------------------------------------------------------ φ, ψ
    def decode(self, z):
        """x = x̄ + U q(z), z (..., r) → (..., n, 3)."""
        return self.rest + jnp.einsum("nip,...p->...ni", self.basis, self.q_of_z(z))

    def decode_rows(self, z, vertex_ids):
        """φ restricted to vertices: x̄[ids] + U[ids] q(z), (k, 3)."""
        return self.rest[vertex_ids] + jnp.einsum("nip,p->ni", self.basis[vertex_ids], self.q_of_z(z))

    def encode(self, x):
        """z = e(Uᵀ M (x − x̄)), x (..., n, 3) → (..., r)."""
        return self.z_of_q(self.project(x))

    def jacobian_q(self, z):
        """∂q/∂z (p, r)."""
        if self.kind == "pca":
            return jnp.eye(self.p)
        return jax.jacfwd(self.q_of_z)(z)

    def jacobian(self, z):
        """J = ∂φ/∂z = U ∂q/∂z, (n, 3, r)."""
        return jnp.einsum("nip,pr->nir", self.basis, self.jacobian_q(z))

    # ------------------------------------------------------------------ storage
    def to_weights(self) -> dict:
        """Named arrays for SubspaceArtefact.weights."""
        w = {"rest": np.asarray(self.rest), "basis": np.asarray(self.basis), "masses": np.asarray(self.masses),
             "q_scale": np.asarray(self.q_scale)}
        w.update({k: np.asarray(v) for k, v in self.net.items()})
        return w

    @staticmethod
    def from_weights(kind: str, weights: dict) -> "SubspaceMap":
        net = {k: jnp.asarray(v, jnp.float64) for k, v in weights.items()
               if k.startswith(("enc_", "dec_"))}
        return SubspaceMap(kind, np.asarray(weights["rest"], np.float64), np.asarray(weights["basis"], np.float64),
                           np.asarray(weights["masses"], np.float64), np.asarray(weights["q_scale"], np.float64),
                           net)


def required_weights(kind: str) -> tuple[str, ...]:
    """Names a SubspaceArtefact of this kind must hold."""
    base = ("rest", "basis", "masses", "q_scale")
    if kind == "pca":
        return base
    return base + tuple(f"{h}_{k}" for h in ("enc", "dec") for k in ("skip", "w1", "b1", "w2", "b2", "w3", "b3"))
