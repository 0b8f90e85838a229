"""Views of a synthetic capture: a ring of cameras, background plates and chessboard
calibration views (used by ``rsl synth``).

Cameras follow the OpenCV convention (x right, y down, z forward; x_cam = R x_world + t).
Pure functions over arrays: no file I/O.
"""
from __future__ import annotations

import numpy as np

from stages.artefacts import Camera
from stages.domain.rotations import axis_angle_matrix, matrix_to_quat_wxyz, quat_wxyz_to_matrix
from stages.render.mesh_raster import look_at, project_points, render_mesh


# --------------------------------------------------------------------------- cameras
def camera_ring(n: int, target: np.ndarray, radius_m: float, resolution: int, up: np.ndarray,
                elevation_deg: float = 35.0, fov_deg: float = 50.0, azimuth0_deg: float = 20.0,
                names: list[str] | None = None, points: np.ndarray | None = None,
                fill: float = 0.9) -> list[Camera]:
    """``n`` cameras evenly spaced on a ring around ``target``, all looking at it.

    The ring lies ``elevation_deg`` above the plane ⟂ ``up``; each camera sits at a distance such
    that a sphere of ``radius_m`` around the target fits the field of view (d = r / sin(fov/2)),
    or, given ``points`` (P, 3), at the nearest distance (bisection, never beyond the sphere's)
    where every point projects within ``fill`` of the half-image; f = (W/2) / tan(fov/2),
    principal point at the image centre.
    """
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    a = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    e1 = a - up * (a @ up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    half = np.radians(fov_deg) / 2
    dist = radius_m / np.sin(half)
    f = (resolution / 2) / np.tan(half)
    K = np.array([[f, 0, (resolution - 1) / 2], [0, f, (resolution - 1) / 2], [0, 0, 1.0]])
    el = np.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = np.radians(azimuth0_deg) + 2 * np.pi * i / n
        direction = np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up
        d = dist if points is None else _fit_distance(points, target, direction, up, dist, np.tan(half) * fill)
        R, t = look_at(np.asarray(target) + d * direction, target, up)
        cams.append(Camera(names[i] if names else f"cam{i}", K.copy(), np.zeros(5), R, t,
                           resolution, resolution, 0.0))
    return cams


def _fit_distance(points: np.ndarray, target: np.ndarray, direction: np.ndarray, up: np.ndarray,
                  d_max: float, limit: float) -> float:
    """Smallest distance along ``direction`` (≤ d_max) at which every point has |x/z|, |y/z| ≤ limit."""
    def fits(d: float) -> bool:
        R, t = look_at(np.asarray(target) + d * direction, target, up)
        pc = points @ R.T + t
        if np.any(pc[:, 2] <= 1e-6):
            return False
        return bool(np.all(np.abs(pc[:, :2]) <= limit * pc[:, 2:3]))

    lo, hi = 0.0, float(d_max)
    if not fits(hi):
        return hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    return hi


# --------------------------------------------------------------------------- marker visibility
def visible_points(points: np.ndarray, camera: Camera, depth: np.ndarray, tol_px: float = 1.5) -> np.ndarray:
    """Which surface points (P, 3) camera ``camera`` sees (P,) bool, given the depth buffer (H, W) (camera z,
    inf where empty) of the scene rendered by it (render_mesh's third output).

    A point is seen when it lies in front of the camera, projects inside the image (the pixel it falls in
    exists), and is not behind the surface the pixel sees: z ≤ depth[pixel] + tol, with tol = ``tol_px``
    pixel footprints at the point's depth (tol_px · z / f_x).  The depth buffer keeps the nearest
    supersample of each pixel, so a point on a surface slanted away from the camera lies somewhat behind its
    own pixel's depth: with 1.5 px, surfaces up to about 60–70° from facing the camera count as seen (more
    oblique ones, like real markers at grazing view, are lost), while a point behind another part of the object
    nearer than the tolerance is still taken as seen.
    """
    uv, z = project_points(np.asarray(points, np.float64), camera.K, camera.R, camera.t, camera.dist)
    h, w = depth.shape
    j, i = np.floor(uv[:, 0] + 0.5).astype(np.int64), np.floor(uv[:, 1] + 0.5).astype(np.int64)
    inside = (z > 0) & (j >= 0) & (j < w) & (i >= 0) & (i < h)
    d = np.full(len(z), -np.inf)
    d[inside] = depth[i[inside], j[inside]]
    tol = tol_px * np.abs(z) / float(camera.K[0, 0])
    return inside & (z <= d + tol)


def visible_points_reference(points: np.ndarray, camera: Camera, x: np.ndarray, faces: np.ndarray,
                             tol_px: float = 1.5) -> np.ndarray:
    """The slow obvious twin of :func:`visible_points` for tests: a point is seen when it projects inside the
    image and no triangle of the mesh (x, faces) crosses the ray from the camera centre to it more than
    ``tol_px`` pixel footprints (measured in camera z) in front of it (Möller–Trumbore, each point against
    every triangle)."""
    uv, z = project_points(np.asarray(points, np.float64), camera.K, camera.R, camera.t, camera.dist)
    c = camera.center
    out = np.zeros(len(points), bool)
    for k, p in enumerate(np.asarray(points, np.float64)):
        if not (z[k] > 0 and -0.5 <= uv[k, 0] < camera.width - 0.5 and -0.5 <= uv[k, 1] < camera.height - 0.5):
            continue
        d = p - c
        tol = tol_px * z[k] / float(camera.K[0, 0])
        tri = x[faces]
        e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        q = np.cross(d, e2)
        a = np.sum(e1 * q, axis=1)
        ok = np.abs(a) > 1e-15
        a = np.where(ok, a, 1.0)
        s_ = c - tri[:, 0]
        u = np.sum(s_ * q, axis=1) / a
        r = np.cross(s_, e1)
        v = (r @ d) / a
        s = np.sum(e2 * r, axis=1) / a  # the hit is c + s d; s = 1 at the point itself
        blocked = np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0) & ((1 - s) * z[k] > tol))
        out[k] = not blocked
    return out


# --------------------------------------------------------------------------- backgrounds
def background_plate(width: int, height: int, seed: int) -> np.ndarray:
    """A static textured backdrop (H, W, 3) float in [0, 1]: a vertical two-colour gradient with
    smooth low-contrast waves, so background subtraction has something to subtract."""
    rng = np.random.default_rng(seed)
    top = rng.uniform(0.55, 0.8, 3) * np.array([0.85, 0.9, 1.0])
    bottom = rng.uniform(0.2, 0.4, 3)
    v = np.linspace(0, 1, height)[:, None, None]
    img = top * (1 - v) + bottom * v
    img = np.broadcast_to(img, (height, width, 3)).copy()
    yy, xx = np.mgrid[0:height, 0:width] / max(width, height)
    for _ in range(5):
        k = rng.normal(size=2) * 12
        img += 0.05 * np.sin(k[0] * xx + k[1] * yy + rng.uniform(0, 2 * np.pi))[..., None] \
            * rng.uniform(0.5, 1.0, 3)
    return np.clip(img, 0.0, 1.0)


# --------------------------------------------------------------------------- chessboard
def board_mesh(cols: int, rows: int, square_m: float, margin_squares: float = 1.0
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A flat board in its own frame (z = 0, centred): (vertices (4, 3), faces (2, 3), inner
    corners (rows·cols, 3) in OpenCV's row-major order).

    ``cols`` × ``rows`` inner corners means (cols+1) × (rows+1) squares plus a white margin.
    """
    w = (cols + 1 + 2 * margin_squares) * square_m / 2
    h = (rows + 1 + 2 * margin_squares) * square_m / 2
    v = np.array([[-w, -h, 0], [w, -h, 0], [w, h, 0], [-w, h, 0]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    cx = (np.arange(cols) - (cols - 1) / 2) * square_m
    cy = (np.arange(rows) - (rows - 1) / 2) * square_m
    gx, gy = np.meshgrid(cx, cy)
    corners = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    return v, faces, corners


def chessboard_texture(cols: int, rows: int, square_m: float):
    """Albedo of the board at board-frame points (P, 3): black/white squares, white margin."""
    def texture(p: np.ndarray) -> np.ndarray:
        i = np.floor(p[:, 0] / square_m + (cols + 1) / 2).astype(np.int64)
        j = np.floor(p[:, 1] / square_m + (rows + 1) / 2).astype(np.int64)
        inside = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
        black = inside & ((i + j) % 2 == 0)
        val = np.where(black, 0.05, 0.95)
        return np.repeat(val[:, None], 3, axis=1)

    return texture


def board_poses(cameras: list[Camera], center: np.ndarray, up: np.ndarray, cols: int, rows: int,
                square_m: float, count: int, seed: int, max_tilt_deg: float = 15.0,
                shift_m: float = 0.0, max_view_angle_deg: float = 70.0, margin_px: float = 4.0,
                tries: int = 500) -> list[np.ndarray]:
    """``count`` board poses [t, q] (board frame -> world) that every camera sees whole.

    The board faces ``up``, tilted by ≤ ``max_tilt_deg`` about a random horizontal axis, spun about
    its normal at random and shifted by ≤ ``shift_m``; a pose is kept when, for every camera, the
    angle between the board normal and the direction to the camera is below ``max_view_angle_deg``
    and all four outer corners project ``margin_px`` inside the image.
    """

    rng = np.random.default_rng(seed)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    verts, _, _ = board_mesh(cols, rows, square_m)
    a = np.array([1.0, 0, 0]) if abs(up[0]) < 0.9 else np.array([0, 1.0, 0])
    bx = a - up * (a @ up)
    bx /= np.linalg.norm(bx)
    base = np.stack([bx, np.cross(up, bx), up], axis=1)  # columns: board x, y, normal in world
    poses: list[np.ndarray] = []
    for _ in range(tries):
        if len(poses) == count:
            break
        spin = rng.uniform(0, 2 * np.pi)
        tilt_axis = rng.normal(size=3)
        tilt_axis -= up * (tilt_axis @ up)
        tilt_axis /= np.linalg.norm(tilt_axis)
        tilt = np.radians(rng.uniform(0, max_tilt_deg)) if len(poses) else 0.0
        Rb = axis_angle_matrix(tilt_axis, tilt) @ base @ axis_angle_matrix(np.array([0, 0, 1.0]), spin)
        shift = rng.uniform(-1, 1, 3) * shift_m if len(poses) else np.zeros(3)
        shift -= up * (shift @ up)
        tb = np.asarray(center, np.float64) + shift
        world = verts @ Rb.T + tb
        normal = Rb[:, 2]
        ok = True
        for c in cameras:
            to_cam = c.center - tb
            cosang = normal @ to_cam / np.linalg.norm(to_cam)
            if cosang < np.cos(np.radians(max_view_angle_deg)):
                ok = False
                break
            uv, z = project_points(world, c.K, c.R, c.t, c.dist)
            if np.any(z <= 0) or np.any(uv < margin_px) or np.any(uv[:, 0] > c.width - 1 - margin_px) \
                    or np.any(uv[:, 1] > c.height - 1 - margin_px):
                ok = False
                break
        if ok:
            poses.append(np.concatenate([tb, matrix_to_quat_wxyz(Rb)]))
    return poses


def render_board(camera: Camera, pose: np.ndarray, cols: int, rows: int, square_m: float,
                 background: np.ndarray, supersample: int = 4) -> np.ndarray:
    """One chessboard view (H, W, 3) float in [0, 1] of the board at ``pose`` [t, q] over a plate."""
    verts, faces, _ = board_mesh(cols, rows, square_m)
    world = verts @ quat_wxyz_to_matrix(pose[3:]).T + pose[:3]
    lights = np.array([[0.0, 0.0, 1.0, 0.6]])
    rgb, _, _ = render_mesh(world, faces, verts, camera.K, camera.R, camera.t, camera.width,
                            camera.height, chessboard_texture(cols, rows, square_m), background,
                            camera.dist, supersample, lights=lights, ambient=0.6)
    return rgb


def board_corners_world(pose: np.ndarray, cols: int, rows: int, square_m: float) -> np.ndarray:
    """Inner corners (rows·cols, 3) of the board at ``pose`` in world coordinates."""
    _, _, corners = board_mesh(cols, rows, square_m)
    return corners @ quat_wxyz_to_matrix(pose[3:]).T + pose[:3]


def first_corner_pose(pose: np.ndarray, cols: int, rows: int, square_m: float) -> np.ndarray:
    """The same board pose for a board frame whose origin is the first inner corner (the frame of
    stages/vision/boards.py, corner (i, j) at (i·s, j·s, 0)): p_world = R p_centred + t =
    R p_first + (t − R c), c the centre of the corner grid."""
    pose = np.asarray(pose, np.float64)
    c = np.array([(cols - 1) / 2 * square_m, (rows - 1) / 2 * square_m, 0.0])
    return np.concatenate([pose[:3] - quat_wxyz_to_matrix(pose[3:]) @ c, pose[3:]])
