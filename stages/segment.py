"""Stage ``rsl segment``: per-camera foreground masks of every frame -> WS/masks.h5.

Methods (stages/vision/segmentation.py):

- ``background``: difference from background/CAM.png with shadow suppression.
- ``chroma``: chroma key against a uniform backdrop (key colour given or from the border).
- ``grabcut``: GrabCut seeded by the rest mesh (WS/mesh.h5) projected with WS/cameras.h5 in
  frame 0, then by the previous frame's mask (propagation).
- ``sam2``: SAM 2 with a user-supplied checkpoint (optional ``sam2`` package), prompted like
  grabcut.
- ``auto``: background when every camera has a plate, else grabcut when mesh.h5 and
  cameras.h5 exist, else chroma.

Every mask is cleaned (opening, closing, largest component, holes filled) and smoothed in
time by a majority vote.  When CAPTURE/truth/masks/CAM/000000.png exists, the IoU of frame 0
against it is stored per camera.  Overlays for inspection: WS/segment/CAM_XXXXXX.png.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from stages.artefacts import KIND_FILES, CamerasArtefact, MasksArtefact, MeshArtefact, Provenance
from stages.capture import Capture, load_capture, read_image, write_image
from stages.errors import RslError
from stages.progress import Reporter, SilentReporter

METHODS = ("auto", "background", "chroma", "grabcut", "sam2")


@dataclass(frozen=True)
class SegmentConfig:
    capture: Path
    """Capture folder (holds capture.toml)."""
    workspace: Path
    """Workspace folder for the artefacts."""
    method: Literal["auto", "background", "chroma", "grabcut", "sam2"] = "auto"
    """auto, background (plates), chroma (key colour), grabcut (seeded by the projected mesh) or sam2."""
    threshold: float = 0.0
    """Colour-difference threshold (RGB units) for background/chroma; 0 = adaptive."""
    shadow_low: float = 0.4
    """Shadows: a pixel this much darker than the plate or less (brightness ratio ≥ this) may be a shadow."""
    shadow_high: float = 0.95
    """Shadows: brightness ratio at most this; set equal to shadow-low to disable shadow suppression."""
    key_color: str = ""
    """Chroma key colour R,G,B (0-255); empty = the median colour of the image border."""
    band_px: int = 0
    """GrabCut: width of the uncertain band around the prior mask, pixels; 0 = 6 % of the object size."""
    reach_px: int = 0
    """GrabCut: how far outside the previous frame's mask the object may have moved, pixels; 0 = 4 × band."""
    iterations: int = 4
    """GrabCut iterations per frame."""
    open_px: int = 1
    """Clean-up: opening radius, pixels (removes specks)."""
    close_px: int = 2
    """Clean-up: closing radius, pixels (bridges gaps)."""
    temporal: int = 3
    """Frames in the temporal majority vote (odd; 1 disables)."""
    overlays: int = 3
    """Overlay PNGs per camera (first, middle, last frame ...); 0 = none."""
    checkpoint: str = ""
    """SAM 2 checkpoint file (.pt) that you supply; nothing is downloaded."""
    sam2_config: str = ""
    """SAM 2 model config of the checkpoint, e.g. configs/sam2.1/sam2.1_hiera_t.yaml."""
    seed: int = 0
    """Seed of OpenCV's random generator (GrabCut's GMM initialisation)."""


def run(config: SegmentConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Segment every frame of every camera and write WS/masks.h5."""
    import cv2

    from stages.vision import segmentation as seg

    cap = load_capture(config.capture)
    ws = Path(config.workspace)
    out = ws / KIND_FILES["masks"]
    if config.method not in METHODS:
        raise RslError(f"--method '{config.method}': use one of {', '.join(METHODS)}.")
    if not cap.camera_names:
        raise RslError(f"{cap.toml_path}: 'capture.cameras' lists no camera.")
    n_frames = cap.frame_count()  # unequal counts across cameras raise
    if n_frames == 0:
        raise RslError(f"{cap.root / 'frames'}: holds no frame.")
    method = _resolve(config.method, cap, ws)
    predictor = _sam2_predictor(config) if method == "sam2" else None
    inputs: list[Path] = []
    priors = None
    if method in ("grabcut", "sam2"):
        priors, inputs = _mesh_priors(cap, ws)
    key = _parse_color(config.key_color) if config.key_color else None
    cv2.setRNGSeed(int(config.seed))
    masks: dict[str, np.ndarray] = {}
    ious: dict[str, float] = {}
    (ws / "segment").mkdir(parents=True, exist_ok=True)
    with reporter.task(f"segmenting ({method})", n_frames * len(cap.camera_names)) as task:
        for cam in cap.camera_names:
            src = cap.frame_source(cam)
            frames = _iter_frames(src, n_frames)
            plate = cap.background(cam) if method == "background" else None
            frames_used = []
            raw = []
            prev = priors[cam] if priors is not None else None
            for i in range(n_frames):
                frame = next(frames)
                if plate is not None and plate.shape != frame.shape:
                    raise RslError(f"{cap.root / 'background'}: plate of camera '{cam}' is "
                                   f"{plate.shape[1]}x{plate.shape[0]} but its frames are "
                                   f"{frame.shape[1]}x{frame.shape[0]}.")
                if prev is not None and prev.shape != frame.shape[:2]:
                    raise RslError(f"{ws / 'cameras.h5'}: camera '{cam}' is calibrated for "
                                   f"{prev.shape[1]}x{prev.shape[0]} images but its frames are "
                                   f"{frame.shape[1]}x{frame.shape[0]}.")
                if method == "background":
                    m = seg.background_difference(frame, plate, config.threshold,
                                                  shadow_low=config.shadow_low, shadow_high=config.shadow_high)
                elif method == "chroma":
                    m = seg.chroma_key(frame, key, config.threshold)
                elif method == "grabcut":
                    # the mesh prior is exact up to calibration: a narrow reach; a propagated
                    # prior lags the motion by a frame: a wider one
                    reach = config.band_px if i == 0 else config.reach_px
                    m = seg.grabcut(frame, prev, config.band_px, config.iterations, reach_px=reach,
                                    reach_factor=2 if i == 0 else 4)
                else:
                    from stages.vision.sam2_model import sam2_mask

                    m = sam2_mask(predictor, frame, prev)
                m = seg.clean_mask(m, config.open_px, config.close_px)
                if prev is not None and np.any(m):
                    prev = m  # propagate to the next frame
                raw.append(m)
                if i in _overlay_frames(n_frames, config.overlays):
                    frames_used.append((i, frame))
                task.advance(1, cam=cam)
            stack = seg.temporal_majority(np.stack(raw), config.temporal)
            empty = [i for i in range(n_frames) if not stack[i].any()]
            if len(empty) == n_frames:
                raise RslError(f"{cap.root / 'frames' / cam}: the {method} segmentation found no object in any "
                               f"frame of camera '{cam}'.")
            if empty:
                reporter.warn(f"camera '{cam}': empty mask in {len(empty)} frame(s), first {empty[0]}.")
            masks[cam] = stack
            truth = _truth_mask(cap, cam)
            if truth is not None:
                if truth.shape != stack.shape[1:]:
                    raise RslError(f"{cap.truth_dir / 'masks' / cam}: truth mask size {truth.shape[::-1]} differs "
                                   f"from the frames {stack.shape[1:][::-1]}.")
                ious[cam] = seg.iou(stack[0], truth)
            all_truth = [(i, _truth_mask(cap, cam, i)) for i in range(1, n_frames)]
            later = [seg.iou(stack[i], t) for i, t in all_truth if t is not None and t.shape == stack.shape[1:]]
            if later:
                reporter.info(f"camera '{cam}': IoU vs truth over frames 1..{n_frames - 1}: mean "
                              f"{np.mean(later):.3f}, min {np.min(later):.3f}")
            for i, frame in frames_used:
                write_image(ws / "segment" / f"{cam}_{i:06d}.png",
                            seg.overlay(frame, stack[i], truth=truth if i == 0 else None))
    MasksArtefact(masks, method, ious).save(out, Provenance.make(config, inputs))
    cover = np.mean([m.mean() for m in masks.values()])
    msg = (f"segment: {len(masks)} camera(s) × {n_frames} frame(s) by {method}, object covers "
           f"{100 * cover:.1f} % of the pixels")
    if ious:
        msg += f", IoU vs truth {min(ious.values()):.3f}–{max(ious.values()):.3f}"
    reporter.summary(msg + f" -> {out}")
    return out


def _iter_frames(src, n: int):
    """Frames 0..n-1 of a FrameSource in order; a video is decoded once, sequentially."""
    if src.video is None:
        for i in range(n):
            yield src.read(i)
        return
    import cv2

    vc = cv2.VideoCapture(str(src.video))
    try:
        for i in range(n):
            ok, img = vc.read()
            if not ok:
                raise RslError(f"{src.video}: cannot decode frame {i} (the file announces {src.count} frames).")
            yield cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    finally:
        vc.release()


def _overlay_frames(n: int, k: int) -> set[int]:
    if k <= 0:
        return set()
    if k == 1:
        return {0}
    return {int(round(i * (n - 1) / (k - 1))) for i in range(k)}


def _resolve(method: str, cap: Capture, ws: Path) -> str:
    if method != "auto":
        if method == "background":
            missing = [c for c in cap.camera_names if cap.background(c) is None]
            if missing:
                raise RslError(f"{cap.root / 'background'}: no plate for camera(s) {', '.join(missing)} "
                               f"(expected background/{missing[0]}.png); --method background needs one per camera.")
        return method
    if all(cap.background(c) is not None for c in cap.camera_names):
        return "background"
    if (ws / KIND_FILES["mesh"]).is_file() and (ws / KIND_FILES["cameras"]).is_file():
        return "grabcut"
    return "chroma"


def _mesh_priors(cap: Capture, ws: Path) -> tuple[dict[str, np.ndarray], list[Path]]:
    """Silhouette of the rest mesh in every camera (the first frame's seed)."""
    from stages.vision.segmentation import mesh_silhouette

    paths = [ws / KIND_FILES["mesh"], ws / KIND_FILES["cameras"]]
    for p in paths:
        if not p.is_file():
            raise RslError(f"{p}: file not found; mesh-seeded segmentation needs WS/mesh.h5 "
                           "(rsl tetrahedralize) and WS/cameras.h5 (rsl calibrate).")
    mesh = MeshArtefact.load(paths[0])
    cams = CamerasArtefact.load(paths[1])
    out = {}
    for name in cap.camera_names:
        try:
            c = cams.by_name(name)
        except KeyError:
            raise RslError(f"{paths[1]}: holds no camera '{name}' (rerun rsl calibrate).") from None
        sil = mesh_silhouette(mesh.vertices, mesh.surface_faces, c.K, c.dist, c.R, c.t, c.width, c.height)
        if not sil.any():
            raise RslError(f"{paths[1]}: camera '{name}' does not see the rest mesh (its projection misses "
                           "the image); check the calibration's world frame.")
        out[name] = sil
    return out, paths


def _truth_mask(cap: Capture, cam: str, frame: int = 0) -> np.ndarray | None:
    """CAPTURE/truth/masks/CAM/NNNNNN.png as (H, W) bool, or None."""
    p = cap.truth_dir / "masks" / cam / f"{frame:06d}.png"
    if not p.is_file():
        return None
    return read_image(p).max(axis=2) > 127


def _parse_color(text: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or np.any(v < 0) or np.any(v > 255):
        raise RslError(f"--key-color '{text}': expected R,G,B with values in 0..255.")
    return v


def _sam2_predictor(config: SegmentConfig):
    """Load the user's SAM 2 checkpoint (validated) and build the predictor."""
    from stages.vision.sam2_model import build_predictor, check_state_dict

    if not config.checkpoint:
        raise RslError("--method sam2 needs --checkpoint FILE (a SAM 2 checkpoint you supply; nothing is "
                       "downloaded).")
    path = Path(config.checkpoint)
    if not path.is_file():
        raise RslError(f"{path}: SAM 2 checkpoint not found.")
    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise RslError(f"{path}: cannot read the checkpoint ({type(e).__name__}: {e}).") from None
    sd = check_state_dict(ckpt, str(path))
    return build_predictor(sd, config.sam2_config, str(path))
