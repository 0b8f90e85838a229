"""Stage ``rsl calibrate``: cameras (intrinsics, distortion, poses in one world) -> WS/cameras.h5.

Sources, in order of precedence:

- ``--from-json FILE`` (rsl cameras.json), ``--from-colmap DIR`` (COLMAP text or binary
  model), ``--from-transforms FILE`` (nerfstudio transforms.json): imported as they are.
- ``--sfm``: pycolmap structure-from-motion on frame 0 of every camera (plus calib views),
  scaled to metres by the board (``--board``) or by ``--known-distance camA:camB:METRES``.
- ``--board SPEC``: board views ``calib/CAM/VIEW.png``; equal VIEW names across cameras were
  taken at the same instant.  Intrinsics per camera, then extrinsics through shared views,
  refined jointly (stages/vision/calibration.py).
- nothing given: CAPTURE/cameras.json is imported (method "json") when it exists, else the
  board named in capture.toml ``[calibration] board = SPEC`` is used on calib/ views.

The world frame of a board calibration (``--world``):

- ``auto`` (default): ``poses`` when CAPTURE/calib/board_poses.json exists, else ``board``.
- ``board``: the board frame (stages/vision/boards.py) in view ``--world-view`` (default: the
  first view, by name, that the most cameras see), placed in the world at ``--board-pose``
  ``tx,ty,tz,qw,qx,qy,qz`` (default identity: the board *is* the world).
- ``poses``: every view's board pose in the world is read from calib/board_poses.json
  ``{"board": SPEC, "poses": {VIEW: [tx,ty,tz,qw,qx,qy,qz]}}`` (p_world = R(q) p_board + t);
  ``rsl synth`` writes it, so calibrated cameras land in the capture's own world.
- ``json``: calibrate in the ``board`` frame, then move the whole rig rigidly onto the
  cameras of CAPTURE/cameras.json with the same names (rotation and translation averaged).

Diagnostics: WS/calibrate/CAM.png shows detected corners (green) and reprojected corners
(red) on up to four views with their RMS.
"""
from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from stages.artefacts import KIND_FILES, Camera, CamerasArtefact, Provenance
from stages.capture import Capture, load_capture, read_cameras_json, read_image, write_image
from stages.domain.rotations import quat_wxyz_to_matrix as quat_to_matrix
from stages.errors import RslError
from stages.workspace import prepare_workspace
from stages.progress import Reporter, SilentReporter
from stages.vision.boards import center_offset, detect, parse_board
from stages.vision.calibration import (align_to_reference, calibrate_extrinsics, calibrate_intrinsics,
                                       calibration_flags)
from stages.vision.colmap_io import cameras_from_transforms, read_colmap
from stages.vision.geometry import compose, invert, project
from stages.vision.sfm import reconstruct, scale_by_board, scale_by_distance


@dataclass(frozen=True)
class CalibrateConfig:
    capture: Path
    """Capture folder (holds capture.toml)."""
    workspace: Path
    """Workspace folder for the artefacts."""
    board: str = ""
    """Board spec: chessboard:COLSxROWS:SQUARE_M or charuco:SXxSY:SQUARE_M:MARKER_M:DICT."""
    sfm: bool = False
    """Structure-from-motion (pycolmap) on frame 0 of every camera instead of board views."""
    from_json: str = ""
    """Import cameras from an rsl cameras.json file."""
    from_colmap: str = ""
    """Import cameras from a COLMAP model folder (cameras/images .txt or .bin)."""
    from_transforms: str = ""
    """Import cameras from a nerfstudio transforms.json file."""
    world: Literal["auto", "board", "poses", "json"] = "auto"
    """World frame of a board calibration: auto, board, poses (calib/board_poses.json) or json
    (align to CAPTURE/cameras.json)."""
    world_view: str = ""
    """Calibration view whose board defines the world (default: first view seen by the most cameras)."""
    board_pose: str = ""
    """Pose tx,ty,tz,qw,qx,qy,qz of the world-view board in the world (default identity)."""
    fix_aspect_ratio: bool = False
    """Keep fx = fy during intrinsic calibration."""
    zero_tangent: bool = False
    """Assume no tangential distortion (p1 = p2 = 0)."""
    fix_k3: bool = False
    """Keep the sixth-order radial coefficient k3 at 0 (advisable with few views)."""
    outlier_factor: float = 3.0
    """Drop a view whose RMS exceeds this many times the median (and outlier-min-px); 0 keeps all."""
    outlier_min_px: float = 1.0
    """A view is never dropped below this RMS, pixels."""
    known_distance: str = ""
    """SfM scale: camA:camB:METRES, the distance between two camera centres."""
    sfm_single_camera: bool = False
    """SfM: all cameras share one set of intrinsics (identical cameras; steadier with few images)."""
    sfm_max_image_size: int = 1600
    """SfM: images are downscaled to at most this many pixels for feature extraction."""
    sfm_threads: int = 2
    """SfM: threads of feature extraction, matching and mapping (pycolmap).  1 makes a run repeatable: with more,
    thread scheduling changes the matches, and three photos' self-calibrated focal length moves by several %."""
    seed: int = 0
    """Seed of the random choices in SfM."""


def run(config: CalibrateConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Calibrate or import the cameras and write WS/cameras.h5."""
    cap = load_capture(config.capture)
    out = Path(config.workspace) / KIND_FILES["cameras"]
    prepare_workspace(config.workspace)  # writable? (before the compute) and no stale temp files
    names = cap.camera_names
    if not names:
        raise RslError(f"{cap.toml_path}: 'capture.cameras' lists no camera.")
    inputs: list[Path] = []
    if config.from_json:
        cams = _order(read_cameras_json(config.from_json), names, Path(config.from_json))
        method, inputs = "json", [Path(config.from_json)]
    elif config.from_colmap:
        cams, method = read_colmap(config.from_colmap, names), "colmap"
    elif config.from_transforms:
        cams, method = cameras_from_transforms(config.from_transforms, names), "transforms"
        inputs = [Path(config.from_transforms)]
    elif config.sfm:
        if config.sfm_threads < 1:
            raise RslError(f"--sfm-threads should be at least 1, found {config.sfm_threads}.")
        cams, method = _sfm(cap, config, reporter), "sfm"
    elif config.board:
        cams, method, inputs = _board(cap, config, reporter, Path(config.workspace))
    elif cap.cameras_json.is_file():
        cams = _order(read_cameras_json(cap.cameras_json), names, cap.cameras_json)
        method, inputs = "json", [cap.cameras_json]
    elif _toml_board(cap):
        reporter.info(f"board {_toml_board(cap)} from {cap.toml_path} [calibration]")
        cams, method, inputs = _board(cap, replace(config, board=_toml_board(cap)), reporter, Path(config.workspace))
    else:
        raise RslError(f"{cap.root}: no cameras.json; give --board SPEC (with calib/CAM/*.png), --sfm, "
                       "--from-json, --from-colmap or --from-transforms.")
    _check_frame_sizes(cap, cams)
    CamerasArtefact(cams, method).save(out, Provenance.make(config, inputs))
    rms = [c.rms_px for c in cams if np.isfinite(c.rms_px)]
    spread = max((np.linalg.norm(a.center - b.center) for a in cams for b in cams), default=0.0)
    reporter.summary(f"calibrate: {len(cams)} camera(s) by {method}"
                     + (f", RMS {min(rms):.3f}–{max(rms):.3f} px" if rms else "")
                     + f", widest baseline {spread:.3f} m -> {out}")
    return out


def _toml_board(cap: Capture) -> str:
    """capture.toml ``[calibration] board = SPEC`` when calib views exist, else ''."""
    tab = cap.raw.get("calibration", {})
    spec = tab.get("board", "") if isinstance(tab, dict) else ""
    return str(spec) if spec and cap.calib_views() else ""


def _order(cams: list[Camera], names: list[str], path: Path) -> list[Camera]:
    by = {c.name: c for c in cams}
    missing = [n for n in names if n not in by]
    if missing:
        raise RslError(f"{path}: holds no camera named {', '.join(missing)} (capture.toml lists "
                       f"{', '.join(names)}).")
    return [by[n] for n in names]


def _check_frame_sizes(cap: Capture, cams: list[Camera]) -> None:
    """Frames, when present, must match each camera's image size; counts must agree."""
    if not (cap.root / "frames").is_dir():
        return
    cap.frame_count()  # unequal counts across cameras raise
    for c in cams:
        src = cap.frame_source(c.name)
        if src.count == 0:
            continue
        h, w = src.read(0).shape[:2]
        if (w, h) != (c.width, c.height):
            raise RslError(f"{cap.root / 'frames'}: camera '{c.name}' frames are {w}x{h} but its calibration "
                           f"is for {c.width}x{c.height} images.")


# =========================================================================== board
def _parse_pose(text: str, where: str) -> tuple:
    try:
        v = np.array([float(x) for x in text.replace(" ", "").split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (7,) or not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9:
        raise RslError(f"{where}: expected a pose tx,ty,tz,qw,qx,qy,qz, found '{text}'.")
    return quat_to_matrix(v[3:]), v[:3]


def read_board_poses(path: Path, board_spec: str) -> dict[str, tuple]:
    """calib/board_poses.json -> view -> (R, t) board → world (format in the module doc)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise RslError(f"{path}: cannot read board poses ({e}).") from None
    poses = data.get("poses") if isinstance(data, dict) else None
    if not isinstance(poses, dict) or not poses:
        raise RslError(f"{path}: should hold {{\"board\": SPEC, \"poses\": {{VIEW: [tx,ty,tz,qw,qx,qy,qz]}}}}.")
    spec = data.get("board")
    if spec and board_spec and spec.replace(" ", "") != board_spec.replace(" ", ""):
        if parse_board(str(spec)) != parse_board(board_spec):
            raise RslError(f"{path}: poses are for board '{spec}' but --board is '{board_spec}'.")
    origin = data.get("origin", "first_corner")
    if origin not in ("first_corner", "center"):
        raise RslError(f"{path}: 'origin' should be 'first_corner' or 'center', found {json.dumps(origin)}.")
    c0 = center_offset(parse_board(board_spec or spec)) if origin == "center" else np.zeros(3)
    out = {}
    for view, pose in poses.items():
        R, t = _parse_pose(",".join(map(str, pose)) if isinstance(pose, list) else str(pose),
                           f"{path} view '{view}'")
        out[str(view)] = (R, t - R @ c0)  # world = R (p − c0) + t for board-frame p
    return out


def _board(cap: Capture, config: CalibrateConfig, reporter: Reporter, ws: Path
           ) -> tuple[list[Camera], str, list[Path]]:
    board = parse_board(config.board)
    views = cap.calib_views()
    calib_dir = cap.root / "calib"
    for c in cap.camera_names:
        if c not in views:
            raise RslError(f"{calib_dir / c}: no calibration images for camera '{c}' (expected "
                           f"{calib_dir / c}/VIEW.png).")
    dets: dict[str, dict] = {c: {} for c in cap.camera_names}
    sizes: dict[str, tuple[int, int]] = {}
    images: dict[str, dict[str, Path]] = {c: views[c] for c in cap.camera_names}
    total = sum(len(v) for v in images.values())
    with reporter.task(f"detecting {board.kind} corners", total) as task:
        for c, vs in images.items():
            for v, p in vs.items():
                img = read_image(p)
                h, w = img.shape[:2]
                if sizes.setdefault(c, (w, h)) != (w, h):
                    raise RslError(f"{p}: image is {w}x{h} but other calibration views of camera '{c}' are "
                                   f"{sizes[c][0]}x{sizes[c][1]}.")
                d = detect(board, img)
                if d is not None:
                    dets[c][v] = d
                task.advance(1, found=sum(len(x) for x in dets.values()))
    for c in cap.camera_names:
        if not dets[c]:
            raise RslError(f"{calib_dir / c}: no {board.spec} board found in any of the {len(images[c])} views "
                           "(check --board: a chessboard counts inner corners).")
    flags = calibration_flags(config.fix_aspect_ratio, config.zero_tangent, config.fix_k3)
    intr = {}
    with reporter.task("intrinsics", len(cap.camera_names)) as task:
        for c in cap.camera_names:
            intr[c] = calibrate_intrinsics(board, dets[c], sizes[c], flags, config.outlier_factor,
                                           config.outlier_min_px, camera=c)
            for v, e in intr[c].dropped.items():
                reporter.warn(f"camera '{c}': dropped view '{v}' (RMS {e:.2f} px, outlier).")
            task.advance(1, rms=intr[c].rms_px)
    world = config.world
    poses_path = calib_dir / "board_poses.json"
    if world == "auto":
        world = "poses" if poses_path.is_file() else "board"
    if world not in ("board", "poses", "json"):
        raise RslError(f"--world '{config.world}': use auto, board, poses or json.")
    known = world_pose = None
    if world == "poses":
        if not poses_path.is_file():
            raise RslError(f"{poses_path}: file not found; --world poses needs the board pose of each view.")
        known = read_board_poses(poses_path, board.spec)
    if config.board_pose:
        world_pose = _parse_pose(config.board_pose, "--board-pose")
    with reporter.task("extrinsics (joint refinement)", None):
        ext = calibrate_extrinsics(board, intr, dets, known_boards=known,
                                   world_view=config.world_view or None, world_pose=world_pose)
    poses = dict(ext.cameras)
    inputs = [p for vs in images.values() for p in vs.values()]
    if world == "json":
        if not cap.cameras_json.is_file():
            raise RslError(f"{cap.cameras_json}: file not found; --world json aligns to it.")
        ref = {c.name: (c.R, c.t) for c in read_cameras_json(cap.cameras_json)}
        W = align_to_reference(poses, ref)
        poses = {c: compose(T, invert(W)) for c, T in poses.items()}
        inputs.append(cap.cameras_json)
    if known is not None:
        inputs.append(poses_path)
    cams = [Camera(c, intr[c].K, intr[c].dist, poses[c][0], poses[c][1], sizes[c][0], sizes[c][1],
                   ext.rms_px[c]) for c in cap.camera_names]
    _diagnostics(ws / "calibrate", board, images, dets, intr, ext)
    where = {"board": f"board in view '{ext.world_view}'", "poses": "calib/board_poses.json",
             "json": "cameras.json"}[world]
    reporter.info(f"world frame: {where}; per-camera RMS "
                  + ", ".join(f"{c} {ext.rms_px[c]:.3f} px" for c in cap.camera_names))
    return cams, board.kind, inputs


def _diagnostics(folder: Path, board, images, dets, intr, ext) -> None:
    """WS/calibrate/CAM.png: up to four views, detected corners (green) and reprojections (red)."""
    folder.mkdir(parents=True, exist_ok=True)
    for c, vs in images.items():
        obs = {o.view: o for o in ext.observations if o.camera == c}
        tiles = []
        for v in intr[c].views[:4]:
            img = read_image(vs[v]).copy()
            det = dets[c][v]
            if v in obs and v in ext.boards:
                R, t = compose(ext.cameras[c], ext.boards[v])
                objp = obs[v].object_points
            else:
                R, t = intr[c].board_to_cam[v]
                objp = board.object_points[det.ids]
            uv, _ = project(objp, intr[c].K, intr[c].dist, R, t)
            err = float(np.sqrt(np.mean(np.sum((uv - det.image_points) ** 2, axis=1))))
            for p in det.image_points:
                cv2.circle(img, (int(round(p[0])), int(round(p[1]))), 4, (0, 255, 0), 1, cv2.LINE_AA)
            for p in uv:
                x, y = int(round(p[0])), int(round(p[1]))
                cv2.line(img, (x - 3, y), (x + 3, y), (255, 0, 0), 1, cv2.LINE_AA)
                cv2.line(img, (x, y - 3), (x, y + 3), (255, 0, 0), 1, cv2.LINE_AA)
            cv2.putText(img, f"{c}/{v}  RMS {err:.3f} px", (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.6,
                        (255, 255, 0), 2, cv2.LINE_AA)
            tiles.append(img)
        if not tiles:
            continue
        while len(tiles) % 2 and len(tiles) > 1:
            tiles.append(np.zeros_like(tiles[0]))
        rows = [np.hstack(tiles[i:i + 2]) for i in range(0, len(tiles), 2)] if len(tiles) > 1 else tiles
        mosaic = np.vstack(rows)
        scale = min(1.0, 1600 / mosaic.shape[1])
        if scale < 1:
            mosaic = cv2.resize(mosaic, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        write_image(folder / f"{c}.png", mosaic)


# =========================================================================== sfm
def _sfm(cap: Capture, config: CalibrateConfig, reporter: Reporter) -> list[Camera]:
    """pycolmap SfM on frame 0 of every camera (and its calib views), scaled to metres."""
    images: dict[str, np.ndarray] = {}
    for c in cap.camera_names:
        images[f"{c}/frame0"] = cap.frame_source(c).read(0)
    for c, vs in cap.calib_views().items():
        if c in cap.camera_names:
            for v, p in vs.items():
                images[f"{c}/{v}"] = read_image(p)
    with tempfile.TemporaryDirectory(prefix="rsl_sfm_") as tmp, reporter.task("structure from motion", None):
        rec = reconstruct(images, Path(tmp), seed=config.seed, max_image_size=config.sfm_max_image_size,
                          single_camera=config.sfm_single_camera, num_threads=config.sfm_threads)
    missing = [c for c in cap.camera_names if f"{c}/frame0" not in rec.poses]
    if missing:
        raise RslError(f"{cap.root / 'frames'}: SfM could not register frame 0 of camera(s) "
                       f"{', '.join(missing)} (too little texture or overlap).")
    if config.known_distance:
        parts = config.known_distance.split(":")
        try:
            a, b, dist = parts[0], parts[1], float(parts[2])
        except (IndexError, ValueError):
            raise RslError(f"--known-distance '{config.known_distance}': expected camA:camB:METRES.") from None
        for n in (a, b):
            if n not in cap.camera_names:
                raise RslError(f"--known-distance: '{n}' is not a camera of {cap.toml_path}.")
        s = scale_by_distance(rec, f"{a}/frame0", f"{b}/frame0", dist)
    elif config.board:
        s = scale_by_board(rec, parse_board(config.board), images)
    else:
        reporter.warn("SfM without --board or --known-distance: the scale is arbitrary, not metres.")
        s = 1.0
    cams = []
    for c in cap.camera_names:
        R, t = rec.poses[f"{c}/frame0"]
        K, d = rec.intrinsics[f"{c}/frame0"]
        h, w = images[f"{c}/frame0"].shape[:2]
        cams.append(Camera(c, K, d, R, s * t, w, h, rec.rms_px))
    return cams
