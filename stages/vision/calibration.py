"""Multi-camera calibration from board views (OpenCV + a joint least-squares refinement).

1. Intrinsics per camera: ``cv2.calibrateCamera`` on every view where the board was found;
   per-view RMS eᵥ = √(mean‖project − detected‖²); views with eᵥ > max(f·median, e_min)
   are dropped and the camera recalibrated once.
2. Extrinsics: the board pose in each view, B_v (board → world), and each camera's pose
   T_c (world → camera) satisfy T_c ∘ B_v = P_cv, P_cv the board → camera pose from step 1.
   With one gauge fixed (the board in the first view seen by ≥ 2 cameras is the world,
   or known board poses), cameras are added one at a time through shared views (robust
   consensus over views; for chessboards, the half-turn ambiguity of each detection is
   resolved against the consensus), then all T_c and free B_v are refined jointly by
   minimising Σ ‖π(K_c, d_c, T_c B_v X_k) − u_cvk‖² with intrinsics held fixed.

Pure functions over arrays; the stage (stages/steps/calibrate.py) reads images and writes files.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from stages.errors import RslError
from stages.vision.boards import Board, Detection
from stages.vision.geometry import (compose, invert, matrix_to_rotvec, mean_rotation, project,
                                    rotation_angle_deg, rotvec_to_matrix)


@dataclass
class Intrinsics:
    """Result of one camera's intrinsic calibration."""

    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    rms_px: float  # OpenCV's RMS over the kept views
    views: list[str]  # kept view names
    view_rms_px: dict[str, float]  # per kept view
    board_to_cam: dict[str, tuple]  # view -> (R (3,3), t (3,)) board → camera
    dropped: dict[str, float] = field(default_factory=dict)  # view -> its RMS before dropping


def calibration_flags(fix_aspect_ratio: bool = False, zero_tangent: bool = False, fix_k3: bool = False,
                      fix_principal_point: bool = False) -> int:
    """OpenCV ``calibrateCamera`` flags from named switches."""
    f = 0
    if fix_aspect_ratio:
        f |= cv2.CALIB_FIX_ASPECT_RATIO
    if zero_tangent:
        f |= cv2.CALIB_ZERO_TANGENT_DIST
    if fix_k3:
        f |= cv2.CALIB_FIX_K3
    if fix_principal_point:
        f |= cv2.CALIB_FIX_PRINCIPAL_POINT
    return f


def _opencv_calibrate(board: Board, dets: dict[str, Detection], size: tuple[int, int], flags: int):
    names = list(dets)
    obj = [board.object_points[dets[n].ids].astype(np.float32) for n in names]
    img = [dets[n].image_points.astype(np.float32).reshape(-1, 1, 2) for n in names]
    K0 = np.eye(3)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(obj, img, tuple(size), K0, np.zeros(5), flags=flags)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    d5 = np.zeros(5)
    d5[: min(5, dist.size)] = dist[:5]
    poses, errs = {}, {}
    for n, rv, tv in zip(names, rvecs, tvecs):
        R, t = rotvec_to_matrix(np.ravel(rv)), np.ravel(tv).astype(np.float64)
        poses[n] = (R, t)
        errs[n] = view_rms(board, dets[n], K, d5, R, t)
    return float(rms), np.asarray(K, dtype=np.float64), d5, poses, errs


def view_rms(board: Board, det: Detection, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
             t: np.ndarray) -> float:
    """√(mean ‖π(K, d, R X + t) − u‖²) over the detected corners of one view, pixels."""
    uv, _ = project(board.object_points[det.ids], K, dist, R, t)
    return float(np.sqrt(np.mean(np.sum((uv - det.image_points) ** 2, axis=1))))


def calibrate_intrinsics(board: Board, dets: dict[str, Detection], size: tuple[int, int], flags: int = 0,
                         outlier_factor: float = 3.0, outlier_min_px: float = 1.0, min_views: int = 3,
                         camera: str = "camera") -> Intrinsics:
    """Intrinsics and distortion of one camera from its board detections (view name -> Detection).

    A view whose RMS exceeds max(outlier_factor · median, outlier_min_px) is dropped and the
    camera recalibrated once; outlier_factor ≤ 0 keeps every view.
    """
    if len(dets) < min_views:
        raise RslError(f"camera '{camera}': the board was found in {len(dets)} view(s); intrinsic "
                       f"calibration needs at least {min_views}.")
    rms, K, dist, poses, errs = _opencv_calibrate(board, dets, size, flags)
    dropped: dict[str, float] = {}
    if outlier_factor > 0:
        med = float(np.median(list(errs.values())))
        limit = max(outlier_factor * med, outlier_min_px)
        bad = {n: e for n, e in errs.items() if e > limit}
        if bad and len(dets) - len(bad) >= min_views:
            dropped = bad
            dets = {n: d for n, d in dets.items() if n not in bad}
            rms, K, dist, poses, errs = _opencv_calibrate(board, dets, size, flags)
    return Intrinsics(K, dist, rms, list(dets), errs, poses, dropped)


# =========================================================================== extrinsics
@dataclass
class Observation:
    """Board corners seen by one camera in one view."""

    camera: str
    view: str
    object_points: np.ndarray  # (k, 3) board frame, m
    image_points: np.ndarray  # (k, 2) pixels


@dataclass
class Extrinsics:
    """World → camera poses and board → world poses from the joint refinement."""

    cameras: dict[str, tuple]  # name -> (R, t)
    boards: dict[str, tuple]  # view -> (R, t) board → world
    rms_px: dict[str, float]  # per camera over its observations in the joint model
    observations: list[Observation]
    world_view: str | None  # the view whose board is the world (gauge), if any


def _solve_pnp(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> tuple:
    ok, rv, tv = cv2.solvePnP(obj.astype(np.float64), img.astype(np.float64).reshape(-1, 1, 2), K, dist,
                              flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise RslError("solvePnP failed on a board view.")
    return rotvec_to_matrix(np.ravel(rv)), np.ravel(tv).astype(np.float64)


def _variants(board: Board, det: Detection) -> list[np.ndarray]:
    """Corner-id labellings a detection may mean.  A chessboard's corner order is fixed only up
    to the grid's symmetries: the half turn, and — when the board is seen from its back or
    printed mirrored (z of the board frame towards the camera) — the two mirror images."""
    if board.kind != "chessboard":
        return [det.ids]
    c, r = board.cols, board.rows
    i, j = det.ids % c, det.ids // c
    return [det.ids, (r - 1 - j) * c + (c - 1 - i), j * c + (c - 1 - i), (r - 1 - j) * c + i]


def _pose_distance(a: tuple, b: tuple, scale: float) -> float:
    """Rotation difference in degrees plus centre distance in units of ``scale`` × 10 degrees."""
    ca, cb = -a[0].T @ a[1], -b[0].T @ b[1]
    return rotation_angle_deg(a[0] @ b[0].T) + 10.0 * float(np.linalg.norm(ca - cb)) / max(scale, 1e-9)


def _consensus(cands: list[tuple], scale: float) -> int:
    """Index of the candidate pose that agrees (distance < 5) with the most others."""
    best, best_n = 0, -1
    for i, a in enumerate(cands):
        n = sum(_pose_distance(a, b, scale) < 5.0 for b in cands)
        if n > best_n:
            best, best_n = i, n
    return best


def calibrate_extrinsics(board: Board, intr: dict[str, Intrinsics], dets: dict[str, dict[str, Detection]],
                         known_boards: dict[str, tuple] | None = None, world_view: str | None = None,
                         world_pose: tuple | None = None, refine: bool = True) -> Extrinsics:
    """Poses of all cameras in one world frame (module doc, step 2).

    ``dets[camera][view]``; only views kept by the intrinsic calibration are used.
    The world: ``known_boards`` (view -> board → world pose) when given; else the board in
    ``world_view`` (default: the first view, in name order, seen by the most cameras, ties by
    the first camera) placed at ``world_pose`` (default identity).
    Raises RslError naming a camera that cannot be linked to the others.
    """
    cams = list(intr)
    kept = {c: {v: dets[c][v] for v in intr[c].views} for c in cams}
    scale = float(np.median([np.linalg.norm(p[1]) for c in cams for p in intr[c].board_to_cam.values()]))
    var: dict[tuple[str, str], np.ndarray] = {}  # chosen ids per (camera, view)
    P: dict[tuple[str, str], tuple] = {}  # board -> camera for the chosen ids

    def pnp(c: str, v: str, ids: np.ndarray) -> tuple:
        return _solve_pnp(board.object_points[ids], kept[c][v].image_points, intr[c].K, intr[c].dist)

    B: dict[str, tuple] = {}
    T: dict[str, tuple] = {}
    fixed: set[str] = set()
    if known_boards:
        B = {v: known_boards[v] for v in known_boards if any(v in kept[c] for c in cams)}
        fixed = set(B)
        if not B:
            raise RslError("calib/board_poses.json names no view in which a camera found the board.")
        world_view = None
    else:
        seen = {}
        for c in cams:
            for v in kept[c]:
                seen.setdefault(v, []).append(c)
        if world_view is None:
            shared = [v for v in seen if len(seen[v]) >= 2] if len(cams) > 1 else list(seen)
            if not shared:
                raise RslError("no calibration view shows the board to two cameras at once; extrinsics need "
                               "shared views (same file name in calib/CAM/ for each camera).")
            most = max(len(seen[v]) for v in shared)
            shared = sorted(v for v in shared if len(seen[v]) == most)
            world_view = shared[0]
        if world_view not in seen:
            raise RslError(f"view '{world_view}' shows the board to no camera; it cannot define the world.")
        B[world_view] = world_pose if world_pose is not None else (np.eye(3), np.zeros(3))
        fixed = {world_view}
        c0 = seen[world_view][0]
        var[(c0, world_view)] = kept[c0][world_view].ids
        P[(c0, world_view)] = intr[c0].board_to_cam[world_view]
        T[c0] = compose(P[(c0, world_view)], invert(B[world_view]))

    def assign_views(c: str) -> None:
        # Choose the variant of each of c's views that agrees with known boards; define new boards.
        for v, det in kept[c].items():
            if (c, v) in var:
                continue
            opts = _variants(board, det)
            if v in B:
                pred = compose(T[c], B[v])
                poses = [intr[c].board_to_cam[v] if k == 0 else pnp(c, v, ids) for k, ids in enumerate(opts)]
                k = int(np.argmin([_pose_distance(p, pred, scale) for p in poses]))
            else:
                k, poses = 0, [intr[c].board_to_cam[v]]
                B[v] = compose(invert(T[c]), poses[0])
            var[(c, v)], P[(c, v)] = opts[k], poses[k]

    if T:
        assign_views(next(iter(T)))
    while len(T) < len(cams):
        # The unknown camera sharing the most views with known boards joins next.
        todo = [c for c in cams if c not in T]
        links = {c: [v for v in kept[c] if v in B] for c in todo}
        c = max(todo, key=lambda k: (len(links[k]), -cams.index(k)))
        if not links[c]:
            detail = ", ".join(todo)
            raise RslError(f"camera '{c}' shares no calibration view with the calibrated cameras "
                           f"(no name in calib/{c}/ matches a view seen by another camera; unlinked: {detail}).")
        cands = []
        for v in links[c]:
            for k, ids in enumerate(_variants(board, kept[c][v])):
                Pcv = intr[c].board_to_cam[v] if k == 0 else pnp(c, v, ids)
                cands.append(compose(Pcv, invert(B[v])))
        i = _consensus(cands, scale)
        agree = [p for p in cands if _pose_distance(p, cands[i], scale) < 5.0]
        T[c] = (mean_rotation([p[0] for p in agree]), np.mean([p[1] for p in agree], axis=0))
        assign_views(c)

    obs = [Observation(c, v, board.object_points[var[(c, v)]], kept[c][v].image_points)
           for c in cams for v in kept[c]]
    if refine:
        T, B = _refine(intr, obs, T, B, fixed)
    rms = {}
    for c in cams:
        sq = []
        for o in obs:
            if o.camera == c:
                R, t = compose(T[c], B[o.view])
                uv, _ = project(o.object_points, intr[c].K, intr[c].dist, R, t)
                sq.append(np.sum((uv - o.image_points) ** 2, axis=1))
        rms[c] = float(np.sqrt(np.mean(np.concatenate(sq))))
    return Extrinsics(T, B, rms, obs, world_view)


def _refine(intr: dict[str, Intrinsics], obs: list[Observation], T: dict, B: dict, fixed: set[str]
            ) -> tuple[dict, dict]:
    """Joint least squares over camera poses and free board poses (rotation vectors + translations)."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    cams = list(T)
    free = [v for v in B if v not in fixed]
    ci = {c: i for i, c in enumerate(cams)}
    vi = {v: len(cams) + i for i, v in enumerate(free)}

    def pack() -> np.ndarray:
        blocks = [np.concatenate([matrix_to_rotvec(T[c][0]), T[c][1]]) for c in cams]
        blocks += [np.concatenate([matrix_to_rotvec(B[v][0]), B[v][1]]) for v in free]
        return np.concatenate(blocks)

    def unpack(x: np.ndarray) -> tuple[dict, dict]:
        x = x.reshape(-1, 6)
        Tn = {c: (rotvec_to_matrix(x[ci[c], :3]), x[ci[c], 3:]) for c in cams}
        Bn = dict(B)
        for v in free:
            Bn[v] = (rotvec_to_matrix(x[vi[v], :3]), x[vi[v], 3:])
        return Tn, Bn

    def residuals(x: np.ndarray) -> np.ndarray:
        Tn, Bn = unpack(x)
        out = []
        for o in obs:
            R, t = compose(Tn[o.camera], Bn[o.view])
            uv, _ = project(o.object_points, intr[o.camera].K, intr[o.camera].dist, R, t)
            out.append((uv - o.image_points).ravel())
        return np.concatenate(out)

    n_res = sum(2 * len(o.image_points) for o in obs)
    sparsity = lil_matrix((n_res, 6 * (len(cams) + len(free))), dtype=np.int8)
    row = 0
    for o in obs:
        k = 2 * len(o.image_points)
        sparsity[row:row + k, 6 * ci[o.camera]:6 * ci[o.camera] + 6] = 1
        if o.view in vi:
            sparsity[row:row + k, 6 * vi[o.view]:6 * vi[o.view] + 6] = 1
        row += k
    sol = least_squares(residuals, pack(), jac_sparsity=sparsity, method="trf", x_scale="jac",
                        xtol=1e-9, ftol=1e-9, gtol=1e-9, max_nfev=100)
    return unpack(sol.x)


def align_to_reference(cameras: dict[str, tuple], reference: dict[str, tuple]) -> tuple:
    """Rigid world change W (ours → reference) that best maps our cameras onto the reference
    cameras of the same names: W_c = T_ref,c⁻¹ ∘ T_c for each camera, rotations averaged
    (chordal mean) and translations averaged.  Returns W as (R, t)."""
    common = [c for c in cameras if c in reference]
    if not common:
        raise RslError("cameras.json holds none of the calibrated camera names; cannot align to it.")
    Ws = [compose(invert(reference[c]), cameras[c]) for c in common]
    R = mean_rotation([w[0] for w in Ws])
    # t: least squares over camera centres: c_ref = R c_ours + t
    c_ours = np.array([-cameras[c][0].T @ cameras[c][1] for c in common])
    c_ref = np.array([-reference[c][0].T @ reference[c][1] for c in common])
    t = np.mean(c_ref - c_ours @ R.T, axis=0)
    return R, t
