"""The interfaces of ``rsl adapt``'s window model, as typing.Protocol classes (structural: the classes in
stages/window_backends.py, stages/windows.py and stages/observations.py do not inherit from them; tests/test_window_model.py holds them to these).

* :class:`WindowBackend` — a simulator of a window of frames in some state space (full: positions (n, 3);
  reduced: subspace coordinates z (r,)), its adjoint and its sensitivities: ``FullSpace``, ``ReducedSpace``.
* :class:`Window` — a window under a start convention, θ = (E (R,), ν (R,)) shared by its frames:
  ``StartWindow`` (dynamics), ``StaticWindow`` (one static equilibrium per frame).
* :class:`Observation` — what a window is compared with, per frame: ``MarkerObservation`` (markers.csv), ``VisionObservation``
  (images through the Gaussians).

Shapes: w window frames, R regions, n vertices, k directions of p = (log E, s) (k ≤ 2R), ``state`` the
backend's state shape.  ``before`` = [state t0−2, state t0−1] (2, *state).
"""
from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

import numpy as np


@runtime_checkable
class WindowBackend(Protocol):
    """Simulation of a window of frames, its adjoint and its sensitivities, in one state space."""

    space: str  # "full" | "reduced"
    dim: int  # subspace dimension r (0 in full space)

    @property
    def rest_state(self) -> np.ndarray:
        """The state of the rest shape (*state)."""

    def decode(self, states: np.ndarray) -> np.ndarray:
        """Positions (w, n, 3) m of states (w, *state)."""

    def z(self, states: np.ndarray) -> np.ndarray:
        """Subspace coordinates (w, r) of states (w, 0 in full space)."""

    def forward(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, before: np.ndarray
                ) -> np.ndarray:
        """States (w, *state) of ``frames`` from ``before``; young Pa / poisson (w, R) per frame."""

    def backward(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, states: np.ndarray,
                 before: np.ndarray, dL_dX: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν), each (w, R), of a loss of the positions with gradient dL_dX (w, n, 3)."""

    def backward_before(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, states: np.ndarray,
                        before: np.ndarray, dL_dX: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dL/dE (w, R), dL/dν (w, R), dL/d before (2, *state))."""

    def sensitivity(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, states: np.ndarray,
                    before: np.ndarray, d_young: np.ndarray, d_poisson: np.ndarray,
                    d_before: np.ndarray | None = None) -> np.ndarray:
        """Position sensitivities dX/dp (k, w, n, 3) along k directions (d_young, d_poisson (k, R))."""

    def state_sensitivity(self, frames: Sequence[int], young: np.ndarray, poisson: np.ndarray, states: np.ndarray,
                          before: np.ndarray, d_young: np.ndarray, d_poisson: np.ndarray,
                          d_before: np.ndarray | None = None) -> np.ndarray:
        """State sensitivities (k, w, *state)."""

    def decode_sensitivity(self, states: np.ndarray, S: np.ndarray) -> np.ndarray:
        """Position sensitivities (k, w, n, 3) of state sensitivities S (k, w, *state)."""

    def state_grad(self, state: np.ndarray, dL_dx: np.ndarray) -> np.ndarray:
        """dL/d state (*state) of dL/dx (n, 3) at ``state``."""

    def start(self, young: np.ndarray, poisson: np.ndarray, kind: str, init: np.ndarray | None = None,
              frame: int = 0) -> np.ndarray:
        """The start state (*state): the rest shape (kind "rest") or the static equilibrium under the frame's
        controls ("equilibrium"); young, poisson (R,)."""

    def start_sensitivity(self, young: np.ndarray, poisson: np.ndarray, kind: str, state0: np.ndarray,
                          d_young: np.ndarray, d_poisson: np.ndarray, frame: int = 0) -> np.ndarray:
        """d state0/dp (k, *state) along k directions (0 for the rest start)."""

    def start_adjoint(self, young: np.ndarray, poisson: np.ndarray, kind: str, state0: np.ndarray,
                      dL_dstate0: np.ndarray, frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν) (R,) through state0(θ)."""

    def records(self) -> tuple:
        """A copy of what the forwards carry from one solve to the next (a solver's memory, substeps' records)."""

    def restore_records(self, saved: tuple) -> None:
        """Put back what :meth:`records` copied: forwards in between (adapt's change probes) leave no trace."""


@runtime_checkable
class Window(Protocol):
    """A window of frames under a start convention, θ = (E (R,), ν (R,)) shared by its frames."""

    def forward(self, frames: Sequence[int], E: np.ndarray, nu: np.ndarray, before: np.ndarray | None
                ) -> np.ndarray:
        """States (w, *state) of ``frames``."""

    def backward(self, frames: Sequence[int], E: np.ndarray, nu: np.ndarray, states: np.ndarray,
                 before: np.ndarray | None, dL_dX: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dL/dE, dL/dν) (R,) of a loss of the window's positions, dL_dX (w, n, 3)."""

    def sensitivity(self, frames: Sequence[int], E: np.ndarray, nu: np.ndarray, states: np.ndarray,
                    before: np.ndarray | None, d_young: np.ndarray, d_poisson: np.ndarray,
                    d_before: np.ndarray | None = None) -> np.ndarray:
        """Position sensitivities dX/dp (k, w, n, 3) along k directions (d_young, d_poisson (k, R))."""


@runtime_checkable
class Observation(Protocol):
    """What the simulated positions X (w, n, 3) of a window are compared with, frame by frame."""

    kind: str  # "markers" | "vision"
    huber: float | None  # Huber δ in units of σ for Gauss–Newton's IRLS weights (None: plain least squares)
    noise_floor: float  # the smallest σ of one residual the estimator assumes (m or intensity)

    def available(self) -> int:
        """Frames observed so far (the files may grow in --follow mode)."""

    def rebind(self, x_anchor: np.ndarray) -> None:
        """Anchor the observation model at the simulated anchor-frame positions (n, 3)."""

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame losses (w,) and dL/dX (w, n, 3) (markers: Σ‖m − p‖² m²; images: L1)."""

    def residuals(self, frames: Sequence[int], X: np.ndarray) -> list[np.ndarray]:
        """Per frame, the flattened residual vector r_f."""

    def jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray) -> list[np.ndarray]:
        """Per frame, ∂r_f/∂p (len r_f, k) for position sensitivities dX (k, w, n, 3)."""

    def noise_scale(self, r: np.ndarray) -> float:
        """σ of one residual estimated from residuals r."""

