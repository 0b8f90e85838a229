"""Stage ``rsl segment``: per-camera foreground masks of every frame -> WS/masks.h5.

Methods (stages/vision/segmentation.py):

- ``background``: difference from background/CAM.png with shadow suppression.
- ``chroma``: chroma key against a uniform backdrop (key colour given or from the border).
- ``grabcut``: GrabCut seeded in frame 0 by the object's frame-0 state projected with WS/cameras.h5
  (the tet mesh of WS/mesh.h5, or the capture's own mesh; in its static equilibrium under gravity and
  the frame-0 controls when capture.toml says ``start = "equilibrium"`` and a tet mesh is at hand, else
  at rest), then by the previous frame's mask (propagation).  An equilibrium depends on capture.toml's guessed E,
  and a seed of that one shape pulls the masks toward it (a silhouette fit of E then finds the guess back): the
  frame-0 seed spans the equilibria for E from guess ÷ ``seed_range`` to × ``seed_range`` instead — sure
  object where every one covers, sure background where none reaches, and between them each pixel starts on
  the side whose colours (of the sure regions) it resembles.
- ``sam2``: SAM 2 with a user-supplied checkpoint (optional ``sam2`` package), prompted like
  grabcut.
- ``lab``: the lab's own masks CAPTURE/masks/CAM/000000.png … (object > 127), read as they are.
- ``auto``: lab when every camera has lab masks; else background when every camera has a plate;
  else (no plate) chroma when the border of every camera's first frame is one colour
  (:func:`~stages.vision.segmentation.backdrop_uniformity`) and the chroma key finds an object
  there (that overlaps the projected frame-0 state, IoU ≥ CHROMA_AGREE, when cameras.h5 exists); else
  grabcut (mesh.h5, or the capture's mesh when tetrahedralize has not run yet: `rsl run` segments
  first); else chroma.  The method used and why is reported and recorded in masks.h5 (``method``).

Occluders (controls.json ``visual`` of handles and obstacles, stages/occluders.py): the pixels they
cover are taken out of every mask (neither object nor background; the object stays one piece across
them), except with ``lab``, whose masks are used as they are.

Every mask is cleaned (opening, closing, largest component, holes filled) and smoothed in
time by a majority vote.  When CAPTURE/truth/masks/CAM/000000.png exists, the IoU of frame 0
against it is stored per camera.  Overlays for inspection: WS/segment/CAM_XXXXXX.png.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from stages.artefacts import (KIND_FILES, CamerasArtefact, MasksArtefact, MeshArtefact, Provenance,
                              mesh_artefact)
from stages.capture import IMAGE_SUFFIXES, Capture, load_capture, read_image, write_image
from stages.workspace import prepare_workspace
from stages.errors import RslError
from stages.meshing import boundary_faces, read_tet_mesh
from stages.occluders import has_occluders, ignore_mask
from stages.progress import Reporter, SilentReporter
from stages.vision import segmentation as seg
from stages.vision.sam2_model import build_predictor, check_state_dict, sam2_mask
from stages.vision.segmentation import backdrop_uniformity, chroma_key, clean_mask, iou, mesh_silhouette

METHODS = ("auto", "background", "chroma", "grabcut", "sam2", "lab")
SPAN_STEPS = 8  # shapes projected between two consecutive equilibria of the GrabCut seed's span
UNIFORM_SPREAD = 6.0
"""auto: a frame border whose (Cr, Cb) spread (95th percentile, 0–255 units) is below this is one colour."""
CHROMA_AGREE = 0.6
"""auto: chroma only when its first-frame mask overlaps the projected rest mesh by this IoU (when cameras.h5 exists)."""


@dataclass(frozen=True)
class SegmentConfig:
    capture: Path
    """Capture folder (holds capture.toml)."""
    workspace: Path
    """Workspace folder for the artefacts."""
    method: Literal["auto", "background", "chroma", "grabcut", "sam2", "lab"] = "auto"
    """auto, background (plates), chroma (key colour), grabcut (seeded by the projected mesh), sam2, or lab
    (the capture's own masks/CAM/000000.png, used as they are)."""
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
    occluder_margin_px: int = 2
    """Occluders (controls.json visual): grow the pixels they cover by this many pixels before leaving them out."""
    seed_range: float = 3.0
    """GrabCut seeded by a frame-0 equilibrium (which depends on capture.toml's guessed E): the seed spans the
    equilibria for E from the guess ÷ this to × this — sure object only where all of them cover, sure background
    only where none reaches, the colours decide in between — so that the masks do not inherit the guess; 1 = the
    guess's shape alone."""


def run(config: SegmentConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Segment every frame of every camera and write WS/masks.h5."""
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
    method, why = _resolve(config.method, cap, ws)
    if config.method == "auto":
        reporter.info(f"segment: auto chose {method}: {why}")
    predictor = _sam2_predictor(config) if method == "sam2" else None
    prepare_workspace(ws)  # writable? (before the compute) and no stale temp files of a killed run
    inputs: list[Path] = cap.frame_inputs(backgrounds=True)  # every frame read (a hash per camera)
    priors, spans = None, {}
    if method in ("grabcut", "sam2"):
        if config.seed_range < 1:
            raise RslError(f"--seed-range must be 1 or more, found {config.seed_range}.")
        priors, inputs, seeded, spans = _mesh_priors(cap, ws, reporter, config.seed_range if method == "grabcut"
                                                     else 1.0)
        reporter.info(f"segment: {method} seeded by {seeded} projected with cameras.h5")
    key = _parse_color(config.key_color) if config.key_color else None
    occluding, cam_objs = _occluder_cameras(cap, ws, method, reporter)
    if occluding:
        inputs += [ws / KIND_FILES["cameras"], cap.controls_path]
    if method == "lab":
        inputs.append(cap.root / "masks")
    controls = cap.controls() if occluding else None
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
            raw, ignored = [], []
            prev = priors[cam] if priors is not None else None
            for i in range(n_frames):
                frame = next(frames)
                ign = None
                if occluding:
                    ign = ignore_mask(controls, i, cam_objs[cam], config.occluder_margin_px)
                    if ign.shape != frame.shape[:2]:
                        raise RslError(f"{ws / 'cameras.h5'}: camera '{cam}' is calibrated for {ign.shape[1]}x"
                                       f"{ign.shape[0]} images but its frames are {frame.shape[1]}x{frame.shape[0]}.")
                    ignored.append(ign)
                if method == "lab":
                    m = _lab_mask(cap, cam, i)
                    if m.shape != frame.shape[:2]:
                        raise RslError(f"{_lab_path(cap, cam, i)}: mask is {m.shape[1]}x{m.shape[0]} but the frames "
                                       f"of camera '{cam}' are {frame.shape[1]}x{frame.shape[0]}.")
                    raw.append(m)
                    if i in _overlay_frames(n_frames, config.overlays):
                        frames_used.append((i, frame))
                    task.advance(1, cam=cam)
                    continue
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
                elif method == "grabcut" and i == 0 and spans.get(cam) is not None:
                    inner, outer = spans[cam]
                    m = _grabcut_span(frame, inner, outer, config.band_px, config.iterations, ign)
                elif method == "grabcut":
                    # the mesh prior is exact up to calibration: a narrow reach; a propagated
                    # prior lags the motion by a frame: a wider one
                    reach = config.band_px if i == 0 else config.reach_px
                    m = seg.grabcut(frame, prev if ign is None else prev & ~ign, config.band_px, config.iterations,
                                    reach_px=reach, reach_factor=2 if i == 0 else 4)
                else:
                    m = sam2_mask(predictor, frame, prev)
                m = seg.clean_mask(m, config.open_px, config.close_px, ignore=ign)
                if prev is not None and np.any(m):
                    prev = m  # propagate to the next frame
                raw.append(m)
                if i in _overlay_frames(n_frames, config.overlays):
                    frames_used.append((i, frame))
                task.advance(1, cam=cam)
            stack = np.stack(raw) if method == "lab" else seg.temporal_majority(np.stack(raw), config.temporal)
            if ignored:  # the vote may bring back pixels an occluder covers in this frame but not its neighbours
                stack &= ~np.stack(ignored)
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
    how = f"{method} (auto: {why})" if config.method == "auto" else method
    msg = (f"segment: {len(masks)} camera(s) × {n_frames} frame(s) by {how}, object covers "
           f"{100 * cover:.1f} % of the pixels")
    if occluding:
        msg += ", occluder pixels left out"
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


def _resolve(method: str, cap: Capture, ws: Path) -> tuple[str, str]:
    """(method, why): the method asked for, or the one ``auto`` picks (module doc)."""
    if method != "auto":
        if method == "background":
            missing = [c for c in cap.camera_names if cap.background(c) is None]
            if missing:
                raise RslError(f"{cap.root / 'background'}: no plate for camera(s) {', '.join(missing)} "
                               f"(expected background/{missing[0]}.png); --method background needs one per camera.")
        if method == "lab":
            missing = [c for c in cap.camera_names if not _lab_path(cap, c, 0).is_file()]
            if missing:
                raise RslError(f"{_lab_path(cap, missing[0], 0)}: file not found; --method lab needs the lab's masks "
                               f"masks/CAM/000000.png … for every camera.")
        return method, "asked for"
    if all(_lab_path(cap, c, 0).is_file() for c in cap.camera_names):
        return "lab", "the capture holds masks/CAM/ for every camera"
    if all(cap.background(c) is not None for c in cap.camera_names):
        return "background", "every camera has a background plate"
    has_cams = (ws / KIND_FILES["cameras"]).is_file()
    spreads = {}
    for c in cap.camera_names:
        frame0 = cap.frame_source(c).read(0)
        spread, key = backdrop_uniformity(frame0)
        chroma = clean_mask(chroma_key(frame0, key)) if spread < UNIFORM_SPREAD else None
        spreads[c] = (spread, chroma, frame0.shape[:2])
    worst = max(sp for sp, _, _ in spreads.values())
    if all(ch is not None and 0.001 < ch.mean() < 0.8 for _, ch, _ in spreads.values()):
        why = (f"no background plate; the border of every first frame is one colour (chroma spread {worst:.1f} "
               f"< {UNIFORM_SPREAD:g})")
        if not has_cams:
            return "chroma", why
        # check the key against the projected object: a plain but not keyable backdrop falls through to GrabCut
        priors, _, _, _ = _mesh_priors(cap, ws)
        agree = min(iou(spreads[c][1], priors[c]) if priors[c].shape == spreads[c][2] else 0.0 for c in priors)
        if agree >= CHROMA_AGREE:
            return "chroma", why + f" and the key agrees with the projected object (IoU ≥ {agree:.2f})"
    if has_cams:
        return "grabcut", (f"no background plate and the frame border is not one colour (chroma spread "
                           f"{worst:.1f}); seeded by the object's frame-0 state projected with cameras.h5")
    return "chroma", ("no background plate and no cameras.h5 to project the object with (run rsl calibrate "
                      "for GrabCut); the chroma key is a guess here")


def _rest_surface(cap: Capture) -> tuple[np.ndarray, np.ndarray]:
    """The capture's rest mesh as (vertices (n, 3), triangles (k, 3)): a surface file, or a tet mesh's boundary."""
    path = cap.mesh_path
    if path.suffix.lower() in (".mesh", ".msh"):
        v, tets, _ = read_tet_mesh(path)
        return v, boundary_faces(tets)
    import trimesh

    try:
        m = trimesh.load(str(path), force="mesh", process=False)
    except Exception as e:
        raise RslError(f"{path}: cannot read the rest mesh ({type(e).__name__}: {e}).") from None
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def _frame0_mesh(cap: Capture, ws: Path) -> tuple[object | None, np.ndarray, np.ndarray, list[Path], str]:
    """(tet MeshArtefact or None, vertices (n, 3), surface triangles (k, 3), inputs, what it is) of the object at
    rest: mesh.h5, else the capture's tet mesh (.mesh/.msh), else the capture's surface."""
    mesh_path = ws / KIND_FILES["mesh"]
    if mesh_path.is_file():
        mesh = MeshArtefact.load(mesh_path)
        return mesh, mesh.vertices, mesh.surface_faces, [mesh_path], "mesh.h5's surface"
    if cap.mesh_path.suffix.lower() in (".mesh", ".msh"):
        v, tets, _ = read_tet_mesh(cap.mesh_path)
        mesh = mesh_artefact(v, tets, cap.density)
        return mesh, mesh.vertices, mesh.surface_faces, [cap.mesh_path], f"the rest mesh {cap.mesh_path.name}"
    v, f = _rest_surface(cap)
    return None, v, f, [cap.mesh_path], f"the rest mesh {cap.mesh_path.name}"


def _frame0_state(cap: Capture, mesh, reporter: Reporter, young_scale: float = 1.0) -> tuple[np.ndarray | None, str]:
    """Positions (n, 3) of frame 0 when the capture starts at equilibrium (capture.toml [capture] start): the static
    equilibrium under gravity and the frame-0 controls with capture.toml's initial E and ν; None (use the rest
    shape) when it starts at rest, nothing holds the object, there is no tet mesh, or the solve fails."""
    if mesh is None or getattr(cap, "start", "rest") != "equilibrium":
        return None, ""
    controls = cap.controls()
    if not controls.handles:
        return None, ""
    from stages.sim.scene import SimulationError, frame_inputs, make_scene  # JAX + numba: loaded on use
    from stages.sim.static import start_state

    try:
        scene = make_scene(mesh, controls, cap.material.model, cap.dt, cap.gravity,
                       damping=cap.material.damping)
        young = young_scale * np.array([cap.material.region_young(r) for r in scene.region_names])
        poisson = np.array([cap.material.region_poisson(r) for r in scene.region_names])
        x0 = np.asarray(start_state(scene, frame_inputs(scene, controls, 0), young, poisson, "equilibrium"))
    except SimulationError as e:
        if young_scale != 1.0:
            return None, ""
        reporter.warn(f"segment: the frame-0 equilibrium did not solve ({e}); GrabCut is seeded by the rest shape.")
        return None, ""
    return x0[: len(mesh.vertices)], " in its frame-0 equilibrium (capture.toml's E and ν)"


def _mesh_priors(cap: Capture, ws: Path, reporter: Reporter = SilentReporter(), seed_range: float = 1.0
                 ) -> tuple[dict[str, np.ndarray], list[Path], str, dict]:
    """(silhouette per camera, inputs, what was projected, spans): the frame-0 state of the object — the rest shape,
    or its static equilibrium when capture.toml says the capture starts there — of mesh.h5, or of the capture's rest
    mesh when mesh.h5 does not exist yet, projected with cameras.h5 (the first frame's GrabCut seed).  spans: per
    camera (inner, outer) (H, W) bool, the intersection and the union of the silhouettes of the equilibria for E ×
    seed_range^(−1, −½, 0, ½, 1) (those that solve) and of SPAN_STEPS shapes linearly between consecutive ones,
    when the frame-0 state is an equilibrium and seed_range > 1 (else empty)."""
    cams_path = ws / KIND_FILES["cameras"]
    if not cams_path.is_file():
        raise RslError(f"{cams_path}: file not found; mesh-seeded segmentation needs WS/cameras.h5 "
                       "(rsl calibrate) and WS/mesh.h5 (rsl tetrahedralize) or the capture's rest mesh.")
    mesh, verts, faces, paths, what = _frame0_mesh(cap, ws)
    x0, how = _frame0_state(cap, mesh, reporter)
    shapes = []
    if x0 is not None:
        verts, what = x0, what + how
        paths.append(cap.controls_path)
        if seed_range > 1:
            shapes = [x0 if e == 0 else _frame0_state(cap, mesh, reporter, seed_range ** e)[0]
                      for e in (-1.0, -0.5, 0.0, 0.5, 1.0)]
            shapes = [x for x in shapes if x is not None]  # in the order of E (a softer one may not solve)
            what += f", spanning E ÷{seed_range:g} to ×{seed_range:g} ({len(shapes)} equilibria)"
            # the shapes between two equilibria (linear in between): the span has no gap where a thin object
            # moves by more than its own width from one equilibrium to the next
            shapes = [(1 - a) * p + a * q for p, q in zip(shapes[:-1], shapes[1:])
                      for a in np.linspace(0.0, 1.0, SPAN_STEPS, endpoint=False)] + shapes[-1:]
    paths.append(cams_path)
    cams = CamerasArtefact.load(cams_path)
    out, spans = {}, {}
    for name in cap.camera_names:
        try:
            c = cams.by_name(name)
        except KeyError:
            raise RslError(f"{cams_path}: holds no camera '{name}' (rerun rsl calibrate).") from None
        sil = mesh_silhouette(verts, faces, c.K, c.dist, c.R, c.t, c.width, c.height)
        if not sil.any():
            raise RslError(f"{cams_path}: camera '{name}' does not see the rest mesh (its projection misses "
                           "the image); check the calibration's world frame.")
        out[name] = sil
        if len(shapes) > 1:
            sils = [mesh_silhouette(x, faces, c.K, c.dist, c.R, c.t, c.width, c.height) for x in shapes]
            spans[name] = (np.logical_and.reduce(sils), np.logical_or.reduce(sils))
    return out, paths, what, spans


def _grabcut_span(frame: np.ndarray, inner: np.ndarray, outer: np.ndarray, band_px: int, iterations: int,
                  ignore: np.ndarray | None = None) -> np.ndarray:
    """GrabCut on frame (H, W, 3) uint8 seeded by a span of plausible silhouettes (H, W) bool, inner ⊆ outer:
    sure object = inner eroded by the band, sure background = beyond outer dilated by the band; every pixel
    between starts as probable object or probable background by which of the two sure regions' colour
    distributions (one Gaussian each, RGB) gives it the higher likelihood — no shape inside the span is
    preferred.  band_px 0 = 6 % of the inner region's equivalent diameter (at least 2 px).  Returns (H, W) bool."""
    img = np.asarray(frame, np.uint8)
    inner, outer = np.asarray(inner, bool), np.asarray(outer, bool) | np.asarray(inner, bool)
    H, W = inner.shape
    area = int(np.count_nonzero(inner)) or int(np.count_nonzero(outer))
    if area == 0:
        return np.zeros((H, W), bool)
    band = band_px if band_px > 0 else max(2, int(round(0.06 * 2 * np.sqrt(area / np.pi))))
    sure_fg = cv2.erode(inner.astype(np.uint8), seg.disc(band)).astype(bool)
    if not sure_fg.any():
        sure_fg = inner.copy()
    near = cv2.dilate(outer.astype(np.uint8), seg.disc(band)).astype(bool)
    if ignore is not None:
        sure_fg &= ~ignore
    ys, xs = np.nonzero(near)
    pad = 2 * band + 2
    y0, y1 = max(0, ys.min() - pad), min(H, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(W, xs.max() + pad + 1)
    crop = np.ascontiguousarray(img[y0:y1, x0:x1])
    fg, bgr = sure_fg[y0:y1, x0:x1], ~near[y0:y1, x0:x1]
    gc = np.full(fg.shape, cv2.GC_BGD, np.uint8)
    between = ~fg & ~bgr
    if fg.any() and bgr.sum() >= 4:
        c = crop.reshape(-1, 3).astype(np.float64)

        def loglik(sel):
            s = c[sel.ravel()]
            mu, cov = s.mean(0), np.cov(s.T) + 4.0 * np.eye(3)  # 2 grey levels of σ at least
            d = c - mu
            return -0.5 * np.einsum("pi,ij,pj->p", d, np.linalg.inv(cov), d) - 0.5 * np.linalg.slogdet(cov)[1]

        obj = (loglik(fg) > loglik(bgr)).reshape(fg.shape)
    else:
        obj = np.asarray(inner[y0:y1, x0:x1])
    gc[between & obj] = cv2.GC_PR_FGD
    gc[between & ~obj] = cv2.GC_PR_BGD
    gc[fg] = cv2.GC_FGD
    if ignore is not None:
        gc[ignore[y0:y1, x0:x1] & between] = cv2.GC_PR_BGD
    if not np.any(gc == cv2.GC_BGD):  # GrabCut needs background samples
        gc[0, :] = gc[-1, :] = gc[:, 0] = gc[:, -1] = cv2.GC_BGD
    if not np.any((gc == cv2.GC_PR_FGD) | (gc == cv2.GC_FGD)):
        return np.zeros((H, W), bool)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(np.ascontiguousarray(crop[..., ::-1]), gc, None, bgd, fgd, int(iterations), cv2.GC_INIT_WITH_MASK)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    return out


def _occluder_cameras(cap: Capture, ws: Path, method: str, reporter: Reporter) -> tuple[bool, dict]:
    """(whether occluder pixels are left out, camera name -> Camera): needs controls.json visuals and cameras.h5."""
    if method == "lab" or not has_occluders(cap.controls()):
        return False, {}
    path = ws / KIND_FILES["cameras"]
    if not path.is_file():
        reporter.warn(f"{cap.controls_path}: handles/obstacles carry a visual, but {path} does not exist to "
                      f"project it; occluders are not left out of the masks (run rsl calibrate first).")
        return False, {}
    cams = CamerasArtefact.load(path)
    out = {}
    for name in cap.camera_names:
        try:
            out[name] = cams.by_name(name)
        except KeyError:
            raise RslError(f"{path}: holds no camera '{name}' (rerun rsl calibrate).") from None
    return True, out


def _lab_path(cap: Capture, cam: str, frame: int) -> Path:
    """CAPTURE/masks/CAM/NNNNNN.png (the first existing suffix of png, jpg, jpeg; png when none exists)."""
    for suf in IMAGE_SUFFIXES:
        p = cap.root / "masks" / cam / f"{frame:06d}{suf}"
        if p.is_file():
            return p
    return cap.root / "masks" / cam / f"{frame:06d}.png"


def _lab_mask(cap: Capture, cam: str, frame: int) -> np.ndarray:
    """The lab's mask of a frame as (H, W) bool (object where the brightest channel > 127), as it is."""
    p = _lab_path(cap, cam, frame)
    if not p.is_file():
        raise RslError(f"{p}: file not found; the lab masks of camera '{cam}' should cover every frame.")
    return read_image(p).max(axis=2) > 127


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
