"""The textured-mesh rasterizer of `rsl synth` and the synthetic views (camera ring, chessboard)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from stages.render.mesh_raster import (interpolate, look_at, project_points, rasterize, rasterize_reference,
                                       render_mesh, supersampled_K, vertex_normals)
from stages.synth_views import (background_plate, board_corners_world, board_poses, camera_ring,
                                first_corner_pose, render_board)

K64 = np.array([[60.0, 0, 31.5], [0, 60.0, 31.5], [0, 0, 1]])


def _identity_cam():
    return np.eye(3), np.zeros(3)


def test_near_triangle_occludes_far_one_in_either_order():
    # Two overlapping triangles facing the camera: z = 1 (near, red) and z = 2 (far, green).
    tri = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0]])
    x = np.concatenate([tri + [0, 0, 1.0], tri * 3 + [0, 0, 2.0]])
    R, t = _identity_cam()
    uv, z = project_points(x, K64, R, t)
    for faces, near_id in ((np.array([[0, 1, 2], [3, 4, 5]]), 0), (np.array([[3, 4, 5], [0, 1, 2]]), 1)):
        ras = rasterize(uv, z, faces, 64, 64)
        centre = ras.face[32, 32]
        assert centre == near_id
        assert ras.depth[32, 32] == pytest.approx(1.0)
        # Where only the far triangle covers the pixel, it is visible at depth 2.
        only_far = (ras.face == 1 - near_id)
        assert only_far.any()
        assert np.allclose(ras.depth[only_far], 2.0)


def test_plane_image_matches_analytic_projection():
    # A tilted square plane n·p = d seen by a rotated camera; every covered pixel's depth equals the
    # ray–plane intersection, and coverage equals the projected quad (pixel centres inside it).
    R, t = look_at(np.array([0.3, -0.2, -1.5]), np.array([0.0, 0.05, 0.0]), np.array([0, -1.0, 0]))
    n = np.array([0.2, 0.1, 1.0])
    n /= np.linalg.norm(n)
    e1 = np.cross(n, [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    c = np.array([0.0, 0.0, 0.1])
    quad = np.array([c + 0.3 * (a * e1 + b * e2) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv, z = project_points(quad, K64, R, t)
    ras = rasterize(uv, z, faces, 64, 64)
    # analytic depth: camera ray r = K⁻¹ (u, v, 1) in camera frame; plane in camera frame n_c·x = d_c
    n_c = R @ n
    d_c = n @ c + n_c @ t  # n·p = n·c with p = Rᵀ(x − t)  =>  (R n)·x = n·c + (R n)·t
    ii, jj = np.nonzero(ras.mask)
    rays = np.linalg.solve(K64, np.stack([jj, ii, np.ones_like(ii)]).astype(float))  # (3, P), z = 1
    depth = d_c / (n_c @ rays)
    assert np.allclose(ras.depth[ii, jj], depth, rtol=1e-10, atol=1e-12)
    # coverage: pixel centres inside the projected convex quad (same winding test, with a margin)
    grid_i, grid_j = np.mgrid[0:64, 0:64]
    p = np.stack([grid_j.ravel(), grid_i.ravel()], axis=1).astype(float)
    cross = []
    for k in range(4):
        a, b = uv[k], uv[(k + 1) % 4]
        cross.append((b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0]))
    cross = np.stack(cross, axis=1)
    edge_len = np.max(np.linalg.norm(np.diff(np.vstack([uv, uv[:1]]), axis=0), axis=1))
    inside = np.all(cross > 1e-6 * edge_len, axis=1) | np.all(cross < -1e-6 * edge_len, axis=1)
    assert ras.mask.sum() > 200
    assert np.array_equal(ras.mask.ravel(), inside)


def test_fast_rasterizer_matches_reference_on_random_triangles():
    rng = np.random.default_rng(3)
    n_tri = 60
    x = rng.uniform(-0.5, 0.5, (3 * n_tri, 3)) + [0, 0, 2.0]
    faces = np.arange(3 * n_tri).reshape(-1, 3)
    R, t = look_at(np.array([0.2, 0.1, -0.5]), np.array([0, 0, 2.0]), np.array([0, -1.0, 0]))
    uv, z = project_points(x, K64, R, t)
    fast = rasterize(uv, z, faces, 64, 48)
    ref = rasterize_reference(uv, z, faces, 64, 48)
    assert np.array_equal(fast.face, ref.face)
    assert np.array_equal(fast.depth, ref.depth)
    assert np.array_equal(fast.bary, ref.bary)
    assert fast.mask.mean() > 0.1


def test_interpolated_points_project_back_to_their_pixel():
    # Perspective-correct barycentrics: the interpolated 3-D point of a pixel projects onto it.
    rng = np.random.default_rng(0)
    x = np.array([[-0.4, -0.3, 1.0], [0.5, -0.2, 3.0], [0.0, 0.45, 1.8]])
    faces = np.array([[0, 1, 2]])
    R, t = _identity_cam()
    uv, z = project_points(x, K64, R, t)
    ras = rasterize(uv, z, faces, 64, 64)
    p = interpolate(ras, x, faces)
    ii, jj = np.nonzero(ras.mask)
    back, _ = project_points(p[ii, jj], K64, R, t)
    assert np.allclose(back, np.stack([jj, ii], axis=1), atol=1e-9)
    assert rng is not None and len(ii) > 300


def test_projection_with_distortion_matches_opencv():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.3, 0.3, (50, 3)) + [0, 0, 1.5]
    R, t = look_at(np.array([0.1, 0.2, -0.3]), np.array([0, 0, 1.5]), np.array([0, -1.0, 0]))
    dist = np.array([-0.12, 0.03, 0.001, -0.002, 0.004])
    uv, _ = project_points(pts, K64, R, t, dist)
    ref, _ = cv2.projectPoints(pts, cv2.Rodrigues(R)[0], t, K64, dist)
    assert np.allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_supersampled_intrinsics_keep_pixel_centres():
    # A point projecting to pixel (u, v) lands at the centre of the f×f block of that pixel.
    pts = np.array([[0.05, -0.02, 1.0]])
    R, t = _identity_cam()
    uv, _ = project_points(pts, K64, R, t)
    uv4, _ = project_points(pts, supersampled_K(K64, 4), R, t)
    assert np.allclose(uv4, 4 * (uv + 0.5) - 0.5)


def test_render_mesh_shading_and_coverage():
    # A square facing the camera: coverage 1 inside, shading bounded by the albedo, normals unit.
    quad = np.array([[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    R, t = _identity_cam()
    bg = np.zeros((64, 64, 3))
    albedo = np.array([0.8, 0.5, 0.2])
    rgb, cov, depth = render_mesh(quad, faces, quad, K64, R, t, 64, 64, lambda p: np.tile(albedo, (len(p), 1)),
                                  bg, supersample=2, lights=np.array([[0, 0, -1.0, 1.0]]), ambient=0.2)
    assert cov[32, 32] == 1.0 and cov[2, 2] == 0.0
    # light straight from the camera side: n·l = 1 → full albedo
    assert np.allclose(rgb[32, 32], albedo, atol=1e-9)
    assert depth[32, 32] == pytest.approx(1.0)
    assert np.isinf(depth[2, 2])
    assert np.allclose(np.linalg.norm(vertex_normals(quad, faces), axis=1), 1.0)


def test_camera_ring_looks_at_target():
    target = np.array([0.1, -0.2, 0.3])
    cams = camera_ring(4, target, 0.15, 64, np.array([0, 0, 1.0]), elevation_deg=40)
    centres = np.array([c.center for c in cams])
    assert np.allclose(np.linalg.norm(centres - target, axis=1), np.linalg.norm(centres[0] - target))
    for c in cams:
        assert np.allclose(c.R @ c.R.T, np.eye(3)) and np.linalg.det(c.R) == pytest.approx(1.0)
        uv, z = project_points(target[None], c.K, c.R, c.t)
        assert np.allclose(uv, 31.5) and z[0] > 0
        # world up points up in the image (negative v)
        uv_up, _ = project_points((target + [0, 0, 0.05])[None], c.K, c.R, c.t)
        assert uv_up[0, 1] < 31.5
        # a sphere of radius 0.15 around the target stays inside the image
        rng = np.random.default_rng(0)
        d = rng.normal(size=(200, 3))
        sphere = target + 0.15 * d / np.linalg.norm(d, axis=1, keepdims=True)
        uvs, _ = project_points(sphere, c.K, c.R, c.t)
        assert uvs.min() >= -0.5 and uvs.max() <= 63.5


def test_chessboard_views_are_detected_at_their_true_corners():
    cams = camera_ring(3, np.zeros(3), 0.15, 256, np.array([0, 0, 1.0]), elevation_deg=45)
    square = 0.018
    poses = board_poses(cams, np.zeros(3), np.array([0, 0, 1.0]), 9, 6, square, 2, seed=0, shift_m=0.01)
    assert len(poses) == 2
    errors = []
    for pose in poses:
        truth = board_corners_world(pose, 9, 6, square)
        for i, c in enumerate(cams):
            img = render_board(c, pose, 9, 6, square, background_plate(256, 256, i))
            gray = cv2.cvtColor(np.round(img * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
            found, corners = cv2.findChessboardCorners(gray, (9, 6))
            assert found
            corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
            uv, _ = project_points(truth, c.K, c.R, c.t)
            d = np.linalg.norm(corners.reshape(-1, 1, 2) - uv[None], axis=2).min(axis=1)
            errors.append(d.max())
        # the pose written to calib/board_poses.json puts the calibrate stage's board frame on the same corners
        from stages.capture import apply_pose
        from stages.vision.boards import parse_board

        obj = parse_board(f"chessboard:9x6:{square}").object_points
        moved = apply_pose(first_corner_pose(pose, 9, 6, square), obj)
        assert np.allclose(moved, truth, atol=1e-12)
    assert max(errors) < 0.5, errors
