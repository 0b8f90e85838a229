"""Camera geometry in numpy: rigid poses, OpenCV projection with distortion, alignment.

Conventions (DESIGN §2): a pose ``(R, t)`` maps points of a source frame into a target
frame, ``p_target = R p_source + t``.  A camera's pose maps world → camera
(x right, y down, z forward).  Distortion is OpenCV's 5-parameter model
``[k1, k2, p1, p2, k3]``:

    x' = X/Z, y' = Y/Z, r² = x'² + y'²,   a = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x'' = a x' + 2 p1 x'y' + p2 (r² + 2x'²),   y'' = a y' + p1 (r² + 2y'²) + 2 p2 x'y'
    u = fx x'' + s y'' + cx,   v = fy y'' + cy

Pure functions over arrays; no I/O.
"""
from __future__ import annotations

import numpy as np

from stages.domain.rotations import (matrix_to_rotvec, mean_rotation, rotation_angle_deg,  # noqa: F401 (re-exported)
                                     rotvec_to_matrix)


def skew(v: np.ndarray) -> np.ndarray:
    """[v]× such that [v]× w = v × w."""
    x, y, z = np.asarray(v, dtype=np.float64).reshape(3)
    return np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])


def compose(a: tuple, b: tuple) -> tuple:
    """a ∘ b: p ↦ R_a (R_b p + t_b) + t_a."""
    Ra, ta = a
    Rb, tb = b
    return Ra @ Rb, Ra @ tb + ta


def invert(a: tuple) -> tuple:
    """Inverse pose: p ↦ Rᵀ (p − t)."""
    R, t = a
    return R.T, -R.T @ t


def distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV distortion to normalised coordinates xy (..., 2) (equations in the module doc)."""
    d = np.zeros(5)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    d[: min(5, dist.size)] = dist[:5]
    k1, k2, p1, p2, k3 = d
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    a = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = a * x + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = a * y + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def project(points: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (k, 2) and depths (k,) of world points (k, 3) seen by camera (K, dist, R, t)."""
    Xc = np.asarray(points, dtype=np.float64) @ np.asarray(R).T + np.asarray(t).reshape(3)
    z = Xc[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    xy = distort(Xc[:, :2] / zs[:, None], dist)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], axis=1), z


def undistort_points(uv: np.ndarray, K: np.ndarray, dist: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Normalised coordinates (k, 2) of pixels (k, 2): fixed-point inversion of :func:`distort`."""
    uv = np.asarray(uv, dtype=np.float64)
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    x = (uv[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    xd = np.stack([x, y], axis=1)
    xu = xd.copy()
    for _ in range(iterations):
        err = distort(xu, dist) - xd
        xu = xu - err
    return xu


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising Σ‖dst − (s R src + t)‖² (Umeyama 1991); src, dst (k, 3)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    var = (a * a).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if with_scale and var > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def triangulate(uv_norm: list[np.ndarray], poses: list[tuple]) -> np.ndarray:
    """Linear (DLT) triangulation of one point from normalised image coordinates (2,) and
    world→camera poses (R, t) of ≥ 2 views: solve [x Pᵀ₃ − Pᵀ₁; y Pᵀ₃ − Pᵀ₂] X = 0."""
    rows = []
    for (x, y), (R, t) in zip(uv_norm, poses):
        P = np.hstack([R, np.reshape(t, (3, 1))])
        rows.append(x * P[2] - P[0])
        rows.append(y * P[2] - P[1])
    _, _, Vt = np.linalg.svd(np.asarray(rows))
    X = Vt[-1]
    return X[:3] / X[3]
