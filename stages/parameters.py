"""The material parameters ``rsl adapt`` optimises and the optimiser that moves them.

θ = (E, ν) per region (R regions) is optimised through unbounded parameters p = (log E, s):

    E = exp(log E),   ν = ν_lo + (ν_hi − ν_lo)·σ(s),   σ(s) = 1 / (1 + e^(−s)),

so E stays positive and ν inside poisson_range.  The Jacobian is diagonal: dE/dlog E = E and
dν/ds = (ν_hi − ν_lo) σ(s)(1 − σ(s)); :func:`chain_params` applies it to dL/dθ.

:class:`Adam` steps p with optax.adam (per-component learning rates, ε relative to the largest √v̂).
Nothing here reads files or prints.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from optax import tree_utils

jax.config.update("jax_enable_x64", True)


def theta_from_params(log_young: np.ndarray, s_poisson: np.ndarray, poisson_range: tuple
                      ) -> tuple[np.ndarray, np.ndarray]:
    """E = exp(log E);  ν = ν_lo + (ν_hi − ν_lo)·sigmoid(s)  (per region; ν_lo, ν_hi scalars or (R,))."""
    lo, hi = poisson_range
    return np.exp(log_young), lo + (hi - lo) / (1.0 + np.exp(-s_poisson))


def params_from_theta(young: np.ndarray, poisson: np.ndarray, poisson_range: tuple[float, float]
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`theta_from_params` (ν is clipped strictly inside the range)."""
    lo, hi = np.asarray(poisson_range[0], float), np.asarray(poisson_range[1], float)
    width = hi - lo
    safe = np.where(width > 1e-9, width, 1.0)
    u = np.clip((np.asarray(poisson, float) - lo) / safe, 1e-4, 1 - 1e-4)
    return np.log(young), np.where(width > 1e-9, np.log(u / (1 - u)), 0.0)


def theta_jacobian(young: np.ndarray, s_poisson: np.ndarray, poisson_range: tuple
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The diagonal of dθ/dp: (dE/dlog E = E, dν/ds = (ν_hi − ν_lo) σ(s)(1 − σ(s))), each (R,)."""
    lo, hi = poisson_range
    sig = 1.0 / (1.0 + np.exp(-s_poisson))
    return np.asarray(young, float), (hi - lo) * sig * (1 - sig)


def chain_params(dL_dE: np.ndarray, dL_dnu: np.ndarray, young: np.ndarray, s_poisson: np.ndarray,
                 poisson_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """dL/dlog E = E · dL/dE;  dL/ds = (ν_hi − ν_lo) σ(s)(1 − σ(s)) · dL/dν."""
    dE_dlog, dnu_ds = theta_jacobian(young, s_poisson, poisson_range)
    return dE_dlog * dL_dE, dnu_ds * dL_dnu


# optax.adam with its hyperparameters held in the state (the learning rate per component, ε per step).
_OPTAX_ADAM = optax.inject_hyperparams(optax.adam)(learning_rate=1.0)


def _relative_eps(g: jax.Array, state, eps: float) -> jax.Array:
    """ε = eps · max √v̂_k + 1e-300, with v̂_k the bias-corrected second moment this step will use."""
    adam_state = state.inner_state[0]
    b2 = state.hyperparams["b2"]
    nu = tree_utils.tree_update_moment_per_elem_norm(g, adam_state.nu, b2, 2)
    nu_hat = tree_utils.tree_bias_correction(nu, b2, optax.safe_increment(adam_state.count))
    return eps * jnp.sqrt(jnp.max(nu_hat, initial=0.0)) + 1e-300


@jax.jit
def _adam_update(p: jax.Array, g: jax.Array, state, eps: float):
    state.hyperparams["eps"] = _relative_eps(g, state, eps)
    updates, state = _OPTAX_ADAM.update(g, state, p)
    return optax.apply_updates(p, updates), state



class Adam:
    """Adam (Kingma & Ba 2015) on a flat numpy vector p (P,), through optax.adam:
    m ← β₁m + (1−β₁)g, v ← β₂v + (1−β₂)g², p ← p − lr · m̂ / (√v̂ + ε), lr a scalar or (P,), and
    ε = eps · max √v̂ (relative, so that a component whose gradient is only round-off next to the others
    does not take full-size steps)."""

    def __init__(self, lr: np.ndarray | float, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-6):
        self.lr, self.b1, self.b2, self.eps = lr, beta1, beta2, eps
        self.state = None
        if np.ndim(lr) == 1:  # the size is known: compile the step now, not inside the first timed frame
            self._init_state(np.zeros(np.shape(lr)))
            _adam_update(jnp.zeros(np.shape(lr), jnp.float64), jnp.zeros(np.shape(lr), jnp.float64), self.state,
                         self.eps)
            self.state = None

    def _init_state(self, p) -> None:
        self.state = _OPTAX_ADAM.init(jnp.asarray(p, jnp.float64))
        hp = self.state.hyperparams
        hp["learning_rate"] = jnp.broadcast_to(jnp.asarray(self.lr, jnp.float64), np.shape(p))
        hp["b1"], hp["b2"] = jnp.asarray(self.b1, jnp.float64), jnp.asarray(self.b2, jnp.float64)

    @property
    def k(self) -> int:
        """Steps taken."""
        return 0 if self.state is None else int(self.state.count)

    def restart(self) -> None:
        """Forget the moments m, v and the step count: the next step is a first step."""
        self.state = None

    def step(self, p: np.ndarray, g: np.ndarray) -> np.ndarray:
        """p (P,) after one step along the gradient g (P,)."""
        p, g = jnp.asarray(p, jnp.float64), jnp.asarray(g, jnp.float64)
        if self.state is None:
            self._init_state(p)
        p, self.state = _adam_update(p, g, self.state, self.eps)
        return np.asarray(p)
