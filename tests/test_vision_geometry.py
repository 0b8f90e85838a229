"""Camera geometry against OpenCV's own functions and exact identities."""
from __future__ import annotations

import cv2
import numpy as np

from stages.vision.calibration import align_to_reference
from stages.vision.geometry import (compose, invert, matrix_to_rotvec, project, rotation_angle_deg,
                                    rotvec_to_matrix, triangulate, umeyama, undistort_points)

RNG = np.random.default_rng(0)
K = np.array([[520.0, 0, 318.2], [0, 515.0, 241.7], [0, 0, 1]])
DIST = np.array([-0.21, 0.08, 0.0012, -0.0007, -0.015])


def test_project_matches_opencv():
    pts = RNG.normal(size=(50, 3)) * 0.3 + [0, 0, 2.0]
    rv, t = np.array([0.1, -0.2, 0.05]), np.array([0.02, -0.01, 0.1])
    ours, z = project(pts, K, DIST, rotvec_to_matrix(rv), t)
    ref, _ = cv2.projectPoints(pts, rv, t, K, DIST)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < 1e-9
    assert np.all(z > 0)


def test_rotvec_matches_rodrigues():
    for _ in range(5):
        rv = RNG.normal(size=3)
        rv *= min(1.0, 3.0 / np.linalg.norm(rv))
        assert np.allclose(rotvec_to_matrix(rv), cv2.Rodrigues(rv)[0], atol=1e-12)
        assert np.allclose(matrix_to_rotvec(rotvec_to_matrix(rv)), rv, atol=1e-9)


def test_undistort_inverts_distort():
    uv = RNG.uniform([20, 20], [620, 460], size=(40, 2))
    ours = undistort_points(uv, K, DIST)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, DIST,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2)
    assert np.abs(ours - ref).max() < 1e-7
    back, _ = project(np.column_stack([ours, np.ones(len(ours))]), K, DIST, np.eye(3), np.zeros(3))
    assert np.abs(back - uv).max() < 1e-6


def test_umeyama_and_triangulate_exact():
    src = RNG.normal(size=(10, 3))
    R, s, t = rotvec_to_matrix([0.3, 0.2, -0.4]), 2.5, np.array([1.0, -2.0, 0.5])
    s2, R2, t2 = umeyama(src, s * src @ R.T + t)
    assert abs(s2 - s) < 1e-12 and np.allclose(R2, R) and np.allclose(t2, t)
    X = np.array([0.1, -0.2, 3.0])
    poses = [(rotvec_to_matrix([0, 0.1 * i, 0]), np.array([-0.2 * i, 0, 0])) for i in range(3)]
    obs = [(Rp @ X + tp)[:2] / (Rp @ X + tp)[2] for Rp, tp in poses]
    assert np.allclose(triangulate(obs, poses), X, atol=1e-12)


def test_align_to_reference_recovers_world_change():
    cams = {f"c{i}": (rotvec_to_matrix(RNG.normal(size=3)), RNG.normal(size=3)) for i in range(3)}
    W = (rotvec_to_matrix([0.5, -0.1, 0.2]), np.array([0.3, 0.1, -0.7]))  # ours -> reference world
    ref = {c: compose(T, invert(W)) for c, T in cams.items()}
    R, t = align_to_reference(cams, ref)
    assert rotation_angle_deg(R @ W[0].T) < 1e-9 and np.allclose(t, W[1], atol=1e-9)
