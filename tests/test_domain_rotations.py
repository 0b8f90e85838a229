"""stages/domain/rotations.py (scipy underneath) against independent formulas and the differentiable
JAX / torch twins: round trips, random rotations, slerp, angles, means."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from stages.domain import rotations as rot

RNG = np.random.default_rng(7)


def _random_quats(n: int) -> np.ndarray:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _hamilton_matrix(q: np.ndarray) -> np.ndarray:
    """R(q) written out from the Hamilton product (an independent formula)."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_quat_matrix_matches_formula_and_is_scalar_first() -> None:
    qs = _random_quats(50)
    R = rot.quat_wxyz_to_matrix(qs)
    assert R.shape == (50, 3, 3)
    for q, Ri in zip(qs, R):
        np.testing.assert_allclose(Ri, _hamilton_matrix(q), atol=1e-13)
    # a rotation by 90° about z: (w, x, y, z) = (cos 45°, 0, 0, sin 45°)
    Rz = rot.quat_wxyz_to_matrix([np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    np.testing.assert_allclose(Rz @ [1.0, 0, 0], [0, 1.0, 0], atol=1e-15)
    # not normalised on input: the same rotation
    np.testing.assert_allclose(rot.quat_wxyz_to_matrix(3.0 * qs[0]), R[0], atol=1e-13)


def test_matrix_quat_round_trip_with_w_nonnegative() -> None:
    qs = _random_quats(200)
    q2 = rot.matrix_to_quat_wxyz(rot.quat_wxyz_to_matrix(qs))
    assert np.all(q2[:, 0] >= 0)
    np.testing.assert_allclose(q2, qs * np.sign(qs[:, :1]), atol=1e-12)
    # near-π rotations (w ≈ 0) round trip as rotations
    q = np.array([1e-9, 0.6, 0.0, 0.8])
    np.testing.assert_allclose(rot.quat_wxyz_to_matrix(rot.matrix_to_quat_wxyz(rot.quat_wxyz_to_matrix(q))),
                               rot.quat_wxyz_to_matrix(q), atol=1e-12)


def test_rotvec_matches_rodrigues_and_round_trips() -> None:
    for _ in range(30):
        r = RNG.normal(size=3)
        r *= RNG.uniform(0, 3.0) / np.linalg.norm(r)  # angle below π: the rotation vector is unique
        np.testing.assert_allclose(rot.rotvec_to_matrix(r), cv2.Rodrigues(r)[0], atol=1e-12)
        np.testing.assert_allclose(rot.matrix_to_rotvec(rot.rotvec_to_matrix(r)), r, atol=1e-9)
    np.testing.assert_allclose(rot.rotvec_to_matrix(np.zeros(3)), np.eye(3), atol=0)
    np.testing.assert_allclose(rot.axis_angle_matrix([0, 0, 2.0], np.pi / 2) @ [1.0, 0, 0], [0, 1.0, 0],
                               atol=1e-15)
    q = rot.axis_angle_quat_wxyz(np.array([1.0, 2, 3]), 0.7)
    np.testing.assert_allclose(rot.quat_wxyz_to_matrix(q), rot.axis_angle_matrix([1.0, 2, 3], 0.7), atol=1e-13)


def test_quat_multiply_composes_matrices() -> None:
    for a, b in zip(_random_quats(20), _random_quats(20)):
        ab = rot.quat_multiply_wxyz(a, b)
        np.testing.assert_allclose(rot.quat_wxyz_to_matrix(ab),
                                   rot.quat_wxyz_to_matrix(a) @ rot.quat_wxyz_to_matrix(b), atol=1e-13)
        w = a[0] * b[0] - a[1:] @ b[1:]  # the Hamilton product's scalar part keeps its sign
        assert np.sign(ab[0]) == np.sign(w)


def test_rotation_angles() -> None:
    for _ in range(20):
        axis, angle = RNG.normal(size=3), RNG.uniform(0, np.pi)
        q0 = _random_quats(1)[0]
        q1 = rot.quat_multiply_wxyz(rot.axis_angle_quat_wxyz(axis, angle), q0)
        assert rot.rotation_angle(q0, q1) == pytest.approx(angle, abs=1e-9)
        assert rot.rotation_angle(q0, -q1) == pytest.approx(angle, abs=1e-9)  # q and −q: one rotation
        assert rot.rotation_angle_deg(rot.axis_angle_matrix(axis, angle)) == pytest.approx(np.degrees(angle),
                                                                                            abs=1e-7)
    # small angles keep their relative precision (no arccos near 1)
    assert rot.rotation_angle_deg(rot.axis_angle_matrix([0, 1.0, 0], 1e-9)) == pytest.approx(np.degrees(1e-9),
                                                                                              rel=1e-6)


def test_slerp_endpoints_constant_speed_and_shorter_arc() -> None:
    for _ in range(20):
        q0, q1 = _random_quats(2)
        np.testing.assert_allclose(rot.slerp_wxyz(q0, q1, 0.0), q0, atol=1e-12)
        end = rot.slerp_wxyz(q0, q1, 1.0)
        np.testing.assert_allclose(end * np.sign(end @ q1), q1, atol=1e-12)
        total = rot.rotation_angle(q0, q1)
        assert total <= np.pi + 1e-12
        for a in (0.25, 0.5, 0.8):
            qa = rot.slerp_wxyz(q0, q1, a)
            assert qa @ q0 >= 0 and np.linalg.norm(qa) == pytest.approx(1.0, abs=1e-12)
            assert rot.rotation_angle(q0, qa) == pytest.approx(a * total, abs=1e-9)
            assert rot.rotation_angle(qa, q1) == pytest.approx((1 - a) * total, abs=1e-9)
        # −q1 is the same rotation: the same path
        np.testing.assert_allclose(rot.slerp_wxyz(q0, -q1, 0.4), rot.slerp_wxyz(q0, q1, 0.4), atol=1e-12)


def test_mean_rotation() -> None:
    R0 = rot.axis_angle_matrix([1.0, -1, 0.5], 0.9)
    np.testing.assert_allclose(rot.mean_rotation([R0, R0, R0]), R0, atol=1e-12)
    # symmetric perturbations about R0 average back to R0
    Rs = [R0 @ rot.axis_angle_matrix([0, 0, 1.0], s * 0.2) for s in (-1, 1)]
    np.testing.assert_allclose(rot.mean_rotation(Rs), R0, atol=1e-12)
    # weights pull the mean towards the heavier rotation
    m = rot.mean_rotation(Rs, np.array([3.0, 1.0]))
    assert rot.rotation_angle_deg(m @ Rs[0].T) < rot.rotation_angle_deg(m @ Rs[1].T)


def test_jax_twin_matches() -> None:
    import jax.numpy as jnp

    from stages.sim.potential import _quat_matrix

    for q in _random_quats(20):
        np.testing.assert_allclose(np.asarray(_quat_matrix(jnp.asarray(q))), rot.quat_wxyz_to_matrix(q),
                                   atol=1e-13)


def test_torch_twin_matches() -> None:
    import torch

    from stages.render.gaussians import quat_to_rotmat, rotmat_to_quat

    qs = _random_quats(20)
    R = quat_to_rotmat(torch.as_tensor(qs)).numpy()
    np.testing.assert_allclose(R, rot.quat_wxyz_to_matrix(qs), atol=1e-13)
    np.testing.assert_allclose(rotmat_to_quat(R), qs * np.sign(qs[:, :1]), atol=1e-12)


def test_pose_track_interpolates_translation_linearly_and_rotation_by_slerp() -> None:
    from stages.domain.controls import IDENTITY_POSE, Track, apply_pose

    q1 = rot.axis_angle_quat_wxyz(np.array([0.0, 0.0, 1.0]), 1.2)
    track = Track(np.array([0, 10]), np.stack([IDENTITY_POSE, np.concatenate([[1.0, 2.0, 3.0], q1])]), True)
    mid = track.at(5)
    np.testing.assert_allclose(mid[:3], [0.5, 1.0, 1.5], atol=1e-15)
    assert rot.rotation_angle(IDENTITY_POSE[3:], mid[3:]) == pytest.approx(0.6, abs=1e-12)
    np.testing.assert_allclose(track.at(-3), IDENTITY_POSE)  # before the first key: the first value
    np.testing.assert_allclose(track.at(40)[3:], q1, atol=1e-15)  # after the last: the last
    p = RNG.normal(size=(5, 3))
    np.testing.assert_allclose(apply_pose(mid, p), p @ rot.quat_wxyz_to_matrix(mid[3:]).T + mid[:3], atol=1e-15)
