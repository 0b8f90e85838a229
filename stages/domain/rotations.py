"""Rotations in NumPy, all through :class:`scipy.spatial.transform.Rotation`.

rsl writes quaternions scalar-first, (w, x, y, z) (poses are [tx, ty, tz, qw, qx, qy, qz],
COLMAP and the Gaussian PLY files agree); scipy is scalar-last, (x, y, z, w).  These helpers
are the one place that converts.  (Differentiable twins: ``sim.potential._quat_matrix`` in JAX,
``render.gaussians.quat_to_rotmat`` in torch.)

scipy is imported on first use: ``scipy.spatial`` costs ~0.5 s and ``rsl --help`` must not pay it.
"""
from __future__ import annotations

import numpy as np


def _R():
    # scipy.spatial.transform takes ~0.5 s to import: loaded on first use (rsl status/info stay fast)
    from scipy.spatial.transform import Rotation

    return Rotation


def quat_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of quaternion(s) (w, x, y, z); q (..., 4) is normalised first -> (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    m = _R().from_quat(q.reshape(-1, 4)[:, [1, 2, 3, 0]]).as_matrix()
    return m.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (w, x, y, z) with w ≥ 0 of rotation matrix(es) R (..., 3, 3) -> (..., 4)."""
    R = np.asarray(R, dtype=np.float64)
    q = _R().from_matrix(R.reshape(-1, 3, 3)).as_quat(canonical=True)[:, [3, 0, 1, 2]]
    return q.reshape(R.shape[:-2] + (4,))


def rotvec_to_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues: R = exp([r]×), θ = |r| radians about r/θ; r (..., 3) -> (..., 3, 3)."""
    r = np.asarray(r, dtype=np.float64)
    return _R().from_rotvec(r.reshape(-1, 3)).as_matrix().reshape(r.shape[:-1] + (3, 3))


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis · angle, |r| ≤ π) of rotation matrix(es) R (..., 3, 3) -> (..., 3)."""
    R = np.asarray(R, dtype=np.float64)
    return _R().from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about ``axis`` (3,) (normalised first) -> (3, 3)."""
    axis = np.asarray(axis, dtype=np.float64)
    return rotvec_to_matrix(axis / np.linalg.norm(axis) * float(angle))


def axis_angle_quat_wxyz(axis: np.ndarray, angle: float) -> np.ndarray:
    """Quaternion (w, x, y, z) of a rotation by ``angle`` radians about ``axis`` (3,); not canonicalised,
    so angles past π give w < 0 (the same rotation)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis])


def quat_multiply_wxyz(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of quaternions (w, x, y, z), normalised (rotation b first, then a);
    the sign is the product's own (scipy composes the stored quaternions without canonicalising)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return (_R().from_quat(a[[1, 2, 3, 0]]) * _R().from_quat(b[[1, 2, 3, 0]])).as_quat()[[3, 0, 1, 2]]


def rotation_angle(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle (radians, in [0, π]) of the rotation taking quaternion q0 to q1, both (w, x, y, z)."""
    r0 = _R().from_quat(np.asarray(q0, dtype=np.float64)[[1, 2, 3, 0]])
    r1 = _R().from_quat(np.asarray(q1, dtype=np.float64)[[1, 2, 3, 0]])
    return float((r0.inv() * r1).magnitude())


def slerp_wxyz(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical linear interpolation between quaternions (w, x, y, z) along the shorter arc, a ∈ [0, 1];
    the result lies in q0's hemisphere (q · q0 ≥ 0)."""
    from scipy.spatial.transform import Slerp

    q0 = np.asarray(q0, dtype=np.float64)
    q0 = q0 / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64)
    key = _R().from_quat(np.stack([q0, q1])[:, [1, 2, 3, 0]])
    q = Slerp([0.0, 1.0], key)([float(a)]).as_quat()[0][[3, 0, 1, 2]]
    return -q if q @ q0 < 0 else q


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix R (3, 3), degrees, in [0, 180] (scipy: 2 atan2(|v|, |w|), precise near 0)."""
    return float(np.degrees(_R().from_matrix(np.asarray(R, dtype=np.float64)).magnitude()))


def mean_rotation(Rs: list[np.ndarray], weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted chordal mean of rotation matrices [(3, 3)] (scipy ``Rotation.mean``: the rotation whose
    quaternion maximises Σ wᵢ (q · qᵢ)²) -> (3, 3)."""
    return _R().from_matrix(np.stack([np.asarray(R, dtype=np.float64) for R in Rs])).mean(weights).as_matrix()
