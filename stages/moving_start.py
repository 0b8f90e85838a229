"""A capture filmed mid-motion (``[capture] start = "moving"``, docs/capture.md): frame 0 shows neither the rest
shape nor an equilibrium but an unknown deformation with an unknown velocity.

``rsl adapt`` (--estimator gn) writes frame 0 and the state before it as the static equilibrium under the frame-0
controls with the current θ plus offsets, x_0 = x_e(θ) + Δ_0 and x_{−1} = x_e(θ) + Δ_{−1}
(stages.windows.StartWindow), and estimates the offsets in every window that holds frame 0, together with θ, as
the Gauss–Newton state correction estimates the starting states of later windows:

- Δ = Σ_j a_j b_j on both states (a correction of the shape) and Σ_j v_j b_j on x_{−1} alone (minus the velocity:
  one frame's displacement), b_j the reduced space's unit vectors of z or the full space's lowest vibration modes
  (:func:`start_directions`);
- each coefficient with a zero-mean prior whose σ is about four frames of the observed motion (:func:`start_prior`),
  so that frame 0's markers and the frames after it fix the shape and the velocity.

Where each marker sits on the body is then unknown too: while a window holds frame 0, each marker's material
point is fitted to its track over the window's frames and the window solved again with it held, until it
settles (adapt._rebind_moving_start, stages.sim.markers.fit_binding_to_tracks); then it is held.  Pure functions
over a window backend."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

START_MOTION_SCALE = 4.0
"""Prior σ of the start's shape and velocity offsets, in frames of the observed motion (the RMS marker
displacement from frame 0 to frame 1): all m directions at 1 σ together move the body by this many frames of
motion (RMS over its vertices).  bench/moving_start.py's bar filmed 4 / 8 / 16 frames in, median settled E error
by this scale (markers fitted to their tracks; accuracy_notes.md, seventeenth stop): 1 → 0.4 / 1.2 / 4.0 %;
2 → 0.7 / 0.8 / 3.1 %; 4 → 0.6 / 1.1 / 2.1 %; 8 → 0.6 / 1.2 / 2.7 %; the capture that starts at its equilibrium
1.4 / 1.0 / 1.0 / 1.1 %.  Flat from 2 to 8: the middle, and the least mean error."""


@dataclass(frozen=True)
class StartBasis:
    """The directions a moving start's offsets are written in, and their size."""

    basis: np.ndarray  # (m, state): unit vectors of z (reduced space) or vibration modes (full space)
    gain: np.ndarray  # (m,) m, the RMS vertex displacement per unit coefficient along each direction


def start_basis(backend, state: np.ndarray, young, poisson) -> StartBasis:
    """The directions at the equilibrium ``state``: the reduced space's unit vectors of z, or the full space's
    lowest vibration modes (mass-orthonormal, backend.modes), as stages.windows.state_directions; with their gains
    (decode's derivative along each, RMS over the vertices)."""
    if backend.space == "reduced":
        basis = np.eye(backend.dim)
    else:
        basis = np.asarray(backend.modes(state, young, poisson))
    dX = np.asarray(backend.decode_sensitivity(np.asarray(state)[None], basis[:, None]))[:, 0]  # (m, n, 3)
    return StartBasis(basis, np.sqrt(np.mean(np.sum(dX * dX, axis=-1), axis=-1)))


def start_prior(sb: StartBasis, markers: np.ndarray, size: float) -> np.ndarray:
    """Prior σ (2m,) of the shape and velocity coefficients (:func:`start_directions`):
    σ_j = START_MOTION_SCALE · s / (g_j √m), s the RMS marker displacement from frame 0 to frame 1 (markers
    (T, M, 3) m; 1 % of the object's ``size`` m when frame 1 is not there yet), g_j direction j's gain."""
    s = 0.01 * size
    if len(markers) > 1:
        d = markers[1] - markers[0]
        ok = np.all(np.isfinite(d), axis=-1)
        if ok.any():
            s = float(np.sqrt(np.mean(np.sum(d[ok] ** 2, axis=-1))))
    g = np.maximum(sb.gain, 1e-3 * max(float(sb.gain.max()), 1e-300))
    sigma = START_MOTION_SCALE * max(s, 1e-6 * size) / (g * np.sqrt(len(g)))
    return np.concatenate([sigma, sigma])


def start_directions(sb: StartBasis) -> np.ndarray:
    """D (2m, 2, state) on the offsets (Δ_{−1}, Δ_0) (GNWindow's correction of a window's ``before``): coefficient
    j < m moves both along basis j (the shape), j ≥ m moves Δ_{−1} alone (minus the velocity)."""
    m = len(sb.basis)
    D = np.zeros((2 * m, 2) + sb.basis.shape[1:])
    D[:m, 0] = sb.basis
    D[:m, 1] = sb.basis
    D[m:, 0] = sb.basis
    return D
