"""Loss sweeps: the whole-sequence (or window) loss of a capture over a grid of fixed E — the check that a
loss is unbiased (its minimum at E_true) before an optimiser runs on it.

For each E of the grid (one value for every region, a scale of each region's E, or one region's E with the
others held), the capture is
simulated in full space from its declared start state (docs/capture.md: x_0 = rest or the static
equilibrium with this E, x_{−1} = x_{−2} = x_0, one implicit-Euler step per frame), observations are
anchored to the simulated frame-0 state as ``rsl adapt`` anchors them (markers bound to the nearest point of
the frame-0 surface; Gaussians re-bound to the frame-0 tets), and the loss is summed over the frames:

    markers     L(E) = Σ_t Σ_i ‖m_i(x_t(E)) − p_t^i‖²  (m²)
    vision      L(E) = Σ_t Σ_c |R(G(x_t(E)), c) − Ĩ_t^c|₁  (stages.render.image_loss.ImageLoss)
    silhouette  L(E) = Σ_t Σ_c Σ_px (A_c(x_t(E)) − m_t^c)²  over the pixels no occluder covers, A the
                coverage of the mesh's surface (rasterized at 4× supersampling), m the masks of masks.h5

The silhouette loss depends on the geometry alone: on a static capture (the object at rest in its frame-0
equilibrium all along) it is the image term that still depends on E, whereas the Gaussians, fitted to that
very frame and re-bound to x_0(E), reproduce it for every E (the vision loss is then flat).

The minimum is refined by a parabola in log E through the grid minimum and its two neighbours.
Not a stage: it writes nothing; ``bench/loss_sweep.py`` and ``rsl evaluate --sweep`` call it.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stages.artefacts import KIND_FILES, CamerasArtefact, GaussiansArtefact, MasksArtefact, read_provenance
from stages.errors import RslError
from stages.observations import read_frame, render_backgrounds, target_image
from stages.occluders import has_occluders, ignore_mask
from stages.render.image_loss import ImageLoss
from stages.sim.markers import bind_markers, marker_residuals
from stages.sim.mesh import rest_quantities
from stages.sim.meshgen import refine_tets, surface_faces


@dataclass
class SweepResult:
    """Losses over a grid of E and the refined minimum."""

    young: np.ndarray  # (K,) Pa, the grid (region 0's E when regions are scaled together, else the swept region's)
    loss: np.ndarray  # (K,) summed loss per grid point
    frame_loss: np.ndarray  # (K, T) per frame
    young_min: float  # Pa, parabolic refinement in log E (the grid minimum at the grid's ends)
    i_min: int  # index of the grid minimum
    interior: bool  # the grid minimum is not at an end of the grid
    info: dict = field(default_factory=dict)


def parabolic_minimum(x: np.ndarray, y: np.ndarray) -> tuple[float, int, bool]:
    """(x at the minimum, grid index, interior?) of samples y(x): the vertex of the parabola through the
    smallest sample and its neighbours (x may be unevenly spaced); the grid point itself at an end."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    i = int(np.nanargmin(y))
    if i == 0 or i == len(x) - 1:
        return float(x[i]), i, False
    x0, x1, x2 = x[i - 1:i + 2]
    y0, y1, y2 = y[i - 1:i + 2]
    d = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / d
    b = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / d
    if not a > 0:
        return float(x1), i, True
    return float(np.clip(-b / (2 * a), x0, x2)), i, True


def simulate_fixed(scene, controls, young: np.ndarray, poisson: np.ndarray, frames: int, start: str,
                   substeps: int = 1, **step_kw) -> np.ndarray:
    """Positions (T, n, 3) for constant per-region young (R,) Pa / poisson (R,) from the declared start."""
    from stages.sim.scene import frame_inputs  # JAX and numba physics: loaded on use (rsl evaluate --help)
    from stages.sim.static import simulate_from_start

    return simulate_from_start(scene, lambda f: frame_inputs(scene, controls, f), young, poisson, frames, start,
                               substeps, **step_kw)


def marker_loss_curve(X_of: Callable[[float], np.ndarray], faces: np.ndarray, markers: np.ndarray,
                      grid: Sequence[float], frames: Sequence[int]) -> np.ndarray:
    """Per grid value: the per-frame marker loss (K, T) with markers bound to the simulated frame-0 surface
    (as rsl adapt binds them).  X_of(E) -> positions (T_all, n, 3) from frame 0."""
    out = np.zeros((len(grid), len(frames)))
    for k, e in enumerate(grid):
        X = X_of(e)
        binding = bind_markers(X[0], faces, markers[0])
        r = marker_residuals(binding, X[list(frames)], markers[list(frames)])
        out[k] = np.sum(r * r, axis=(1, 2))
    return out


def vision_loss_curve(X_of: Callable[[float], np.ndarray], image_loss, targets: Callable[[int], list],
                      grid: Sequence[float], frames: Sequence[int], fit_frame: int = 0,
                      anchor_young: float | None = None, anchor: np.ndarray | None = None) -> np.ndarray:
    """Per grid value, the per-frame L1 image loss (K, T) of stages.render.image_loss.ImageLoss with the Gaussians
    re-bound to the simulated fit frame (adapt's ``rebind`` anchor); with ``anchor_young`` (Pa), to the fit frame
    simulated with that E for every grid value (the anchor's dependence on E switched off); with ``anchor`` (n, 3)
    m, to those positions for every grid value (a capture filmed mid-motion: the fit pose x_f, as adapt binds them)."""
    if anchor_young is not None and anchor is not None:
        raise ValueError("vision_loss_curve takes anchor_young or anchor, not both")
    out = np.zeros((len(grid), len(frames)))
    if anchor_young is not None:
        anchor = np.array(X_of(anchor_young)[fit_frame])
    for k, e in enumerate(grid):
        X = X_of(e)
        image_loss.rebind(X[fit_frame] if anchor is None else anchor)
        for j, t in enumerate(frames):
            out[k, j] = image_loss(X[t], targets(t))[0]
    return out


def silhouette_coverage(x: np.ndarray, faces: np.ndarray, camera, supersample: int = 4) -> np.ndarray:
    """Fraction (H, W) of each pixel covered by the triangles faces (F, 3) at positions x (n, 3), from a
    z-buffer at ``supersample``× the camera's resolution (stages.render.mesh_raster)."""
    from stages.render.mesh_raster import project_points, rasterize, supersampled_K  # numba: loaded on use

    S = int(supersample)
    uv, z = project_points(x, supersampled_K(camera.K, S), camera.R, camera.t, camera.dist)
    hit = rasterize(uv, z, faces, int(camera.height) * S, int(camera.width) * S, near=1e-3).face >= 0
    return hit.reshape(int(camera.height), S, int(camera.width), S).mean(axis=(1, 3))


def silhouette_loss_curve(X_of: Callable[[float], np.ndarray], faces: np.ndarray, cameras: Sequence,
                          masks: Callable[[int, int], np.ndarray], keep: Callable[[int, int], np.ndarray | None],
                          grid: Sequence[float], frames: Sequence[int]) -> np.ndarray:
    """Per grid value, the per-frame silhouette loss (K, T): Σ_c Σ_px (A_c(x_t) − m_t^c)² over the pixels
    ``keep(t, c)`` (None: all) with masks(t, c) (H, W) in [0, 1]."""
    out = np.zeros((len(grid), len(frames)))
    for k, e in enumerate(grid):
        X = X_of(e)
        for j, t in enumerate(frames):
            for c, cam in enumerate(cameras):
                d = silhouette_coverage(X[t], faces, cam) - masks(t, c)
                w = keep(t, c)
                out[k, j] += float(np.sum(d * d) if w is None else np.sum(d[w] ** 2))
    return out


def sweep(capture, mesh, grid: Sequence[float], loss: str = "markers", frames: tuple[int, int] | None = None,
          workspace: Path | None = None, cameras: Sequence[str] | None = None, poisson: float | None = None,
          start: str | None = None, refine: int = 0, substeps: int = 1,
          reporter: Callable[[str], None] | None = None, base_young: Sequence[float] | None = None,
          anchor_young: float | None = None, past_young: np.ndarray | None = None,
          region: str | None = None, before: np.ndarray | None = None) -> SweepResult:
    """The loss of ``capture`` (stages.capture.Capture) on ``mesh`` (a MeshArtefact: P1 or P2; ``refine``
    splits its tets 8-fold that many times) over the grid of E (Pa; every region's E scaled with region 0's
    ``base_young`` value (R,) Pa, default capture.toml's; one region: E itself) with ν fixed (``poisson`` or
    capture.toml's), frames
    [a, b) (default all), start (default capture.start).  loss "vision" needs ``workspace`` with cameras.h5
    and gaussians.h5 (masks.h5 when there); "silhouette" cameras.h5 and masks.h5.  ``anchor_young`` (Pa,
    vision): the Gaussians bound to the fit frame simulated with this E for every grid value (None: with each).
    ``past_young`` (a, R) Pa: frames 0..a−1 simulated once with this E per frame (a history of the material, e.g.
    the truth's before a step of E; ν as above), frames a..b−1 continued from them with each grid value
    (stages.sim.static.continue_frames): the loss of the frames after a change of material, given the past
    (a = frames[0]).  ``region``: only that region's E takes the grid's values, every other region held at its
    ``base_young`` (the check that one region's loss is lowest at its own E_true, the others known).
    ``before`` (2, n, 3) m: (x_{−1}, x_0) of a capture filmed mid-motion (start "moving"), e.g. adapt.h5's estimated
    start_positions — every E of the grid is simulated from that same start (stages.sim.static.simulate_from_start),
    and the Gaussians stay bound to their fit pose (gaussians.h5 fit_positions) as adapt binds them."""
    from stages.sim.scene import frame_inputs, make_scene  # JAX and numba physics: loaded on use
    from stages.sim.static import continue_frames, last_states, simulate_from_start

    start = start or getattr(capture, "start", "equilibrium")
    if start == "moving" and before is None:
        raise RslError(f"{capture.toml_path}: the loss sweep simulates every E from the start state, which a capture "
                       f"filmed mid-motion (start = \"moving\") does not give; pass the estimated start state "
                       f"(adapt.h5's start_positions: `rsl evaluate --sweep` after `rsl adapt`), or start \"rest\" or "
                       f"\"equilibrium\" for a capture that starts there.")
    if before is not None:
        before = np.asarray(before, np.float64)
        if start != "moving":
            raise ValueError(f"a start state before frame 0 is given, but the sweep's start is {start!r}, not moving")
        if before.shape != (2, mesh.n_vertices, 3):
            raise ValueError(f"the start state (x_{{-1}}, x_0) should be (2, {mesh.n_vertices}, 3) on the mesh's "
                             f"nodes, not {before.shape}")
        if refine:
            raise ValueError("a moving start's state is given on the mesh's own nodes: it cannot be refined")
    ctl = capture.controls()
    if refine:
        v, t, reg = mesh.vertices, mesh.tets, mesh.tet_region
        for _ in range(refine):
            v, t, reg = refine_tets(v, t, reg)
        vol, dmi, masses = rest_quantities(v, t, mesh.density)
        mesh = dataclasses.replace(mesh, vertices=v, tets=t, tet_region=reg, rest_volumes=vol, dm_inv=dmi,
                                   vertex_masses=masses, surface_faces=surface_faces(t), handles={})
    scene = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity,
                       damping=capture.material.damping)
    names = list(scene.region_names)
    base = (np.array([capture.material.region_young(r) for r in names], float) if base_young is None
            else np.asarray(base_young, float).reshape(len(names)))
    if region is not None and region not in names:
        raise ValueError(f"the mesh has no region {region!r} (its regions: {', '.join(names)})")
    swept = names.index(region) if region is not None else None
    nu = np.array([poisson if poisson is not None else capture.material.region_poisson(r) for r in names], float)
    obs_T = None
    if loss == "markers":
        P = capture.markers()
        if P is None:
            raise ValueError(f"{capture.root}: no markers.csv for a marker-loss sweep")
        obs_T = len(P)
    else:
        obs_T = capture.frame_count()
    a, b = frames if frames is not None else (0, obs_T)
    b = min(b, obs_T)
    T_sim = b
    cache: dict[float, np.ndarray] = {}

    def inputs_at(f: float):  # the controls at a (fractional) frame
        return frame_inputs(scene, ctl, f)

    past = None
    if past_young is not None:
        past_young = np.asarray(past_young, float).reshape(-1, len(names))
        if len(past_young) != a or a < 1:
            raise ValueError(f"past_young should hold the {a} frames before the swept ones (frames[0] ≥ 1), not "
                             f"{len(past_young)}")
        states: list = []
        past = simulate_from_start(scene, inputs_at, past_young, np.tile(nu, (a, 1)), a, start, substeps,
                                   states=states, before=before)
        last = last_states(past, states)

    def X_of(e: float) -> np.ndarray:
        if e not in cache:
            young = base * (e / base[0]) if swept is None else np.where(np.arange(len(base)) == swept, e, base)
            cache.clear()
            if past is None:
                cache[e] = simulate_fixed(scene, ctl, young, nu, T_sim, start, substeps, before=before)
            else:
                cache[e] = np.concatenate([past, continue_frames(scene, inputs_at, young, nu, range(a, T_sim), *last,
                                                                 substeps)])
            if reporter is not None:
                reporter(f"E = {e:.4g} Pa simulated")
        return cache[e]

    fr = list(range(a, b))
    if loss == "markers":
        n = scene.n_vertices
        faces = np.asarray(mesh.surface_faces)
        if faces.max() >= n:
            raise ValueError("surface faces index beyond the mesh's vertices")
        per = marker_loss_curve(X_of, faces, P, grid, fr)
    elif loss == "vision":
        per = _vision(capture, workspace, cameras, mesh, X_of, grid, fr, anchor_young, start == "moving")
    elif loss == "silhouette":
        per = _silhouette(capture, workspace, cameras, mesh, X_of, grid, fr)
    else:
        raise ValueError(f"loss is markers, vision or silhouette, not {loss!r}")
    total = per.sum(axis=1)
    lg = np.log(np.asarray(grid, float))
    lmin, i, interior = parabolic_minimum(lg, total)
    return SweepResult(np.asarray(grid, float), total, per, float(math.exp(lmin)), i, interior,
                       {"start": start, "frames": [a, b], "n_vertices": int(scene.n_vertices),
                        "n_elements": int(len(scene.tets)), "order": int(np.asarray(mesh.tets).shape[1] == 10) + 1,
                        "refine": int(refine), "loss": loss, "region": region})


def _vision(capture, workspace, cameras, mesh, X_of, grid, frames, anchor_young=None, moving=False) -> np.ndarray:
    ws = Path(workspace)
    cams_art = CamerasArtefact.load(ws / KIND_FILES["cameras"])
    gauss = GaussiansArtefact.load(ws / KIND_FILES["gaussians"])
    names = list(cameras) if cameras else [c.name for c in cams_art.cameras]
    masks_path = ws / KIND_FILES["masks"]
    masks = MasksArtefact.load(masks_path).masks if masks_path.exists() else None
    il = ImageLoss(gauss, mesh, [cams_art.by_name(c) for c in names])
    il.set_backgrounds(render_backgrounds(capture, names, masks))  # the compositing adapt's image loss uses
    fit_frame = int(read_provenance(ws / KIND_FILES["gaussians"]).get("config", {}).get("frame", 0) or 0)
    cache: dict[int, list] = {}

    def targets(t: int) -> list:
        if t not in cache:
            cache[t] = [target_image(read_frame(capture, c, t), masks, c, t, il.background) for c in names]
        return cache[t]

    anchor = None
    if moving:  # frame 0 is estimated about the fit pose x_f, where adapt keeps the Gaussians bound
        if gauss.fit_positions is None or np.shape(gauss.fit_positions) != np.shape(mesh.vertices):
            raise ValueError(f"{ws / KIND_FILES['gaussians']}: records no fit pose on mesh.h5's nodes (fit_positions), "
                             f"which a capture filmed mid-motion binds its Gaussians to; run rsl fit-gaussians again")
        anchor = np.asarray(gauss.fit_positions, np.float64)
    return vision_loss_curve(X_of, il, targets, grid, frames, fit_frame, anchor_young, anchor)


def _silhouette(capture, workspace, cameras, mesh, X_of, grid, frames) -> np.ndarray:
    ws = Path(workspace)
    cams_art = CamerasArtefact.load(ws / KIND_FILES["cameras"])
    masks_path = ws / KIND_FILES["masks"]
    if not masks_path.exists():
        raise ValueError(f"{masks_path}: not found; the silhouette loss compares with the masks of rsl segment")
    masks = MasksArtefact.load(masks_path).masks
    names = [c for c in (list(cameras) if cameras else [c.name for c in cams_art.cameras]) if c in masks]
    if not names:
        raise ValueError(f"{masks_path}: holds no mask of the cameras of cameras.h5")
    cams = [cams_art.by_name(c) for c in names]
    controls = capture.controls()
    occluded = has_occluders(controls)
    for t in frames:
        if any(t >= len(masks[c]) for c in names):
            raise ValueError(f"{masks_path}: holds no mask of frame {t}")

    def keep(t: int, c: int):
        return ~ignore_mask(controls, t, cams[c]) if occluded else None

    faces = np.asarray(mesh.surface_faces)[:, :3]
    return silhouette_loss_curve(X_of, faces, cams, lambda t, c: masks[names[c]][t].astype(np.float64), keep,
                                 grid, frames)
