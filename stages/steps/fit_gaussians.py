"""`rsl fit-gaussians`: 3D Gaussians bound to the tet mesh, fitted to one frame's views (paper §4.1).

Reads WS/mesh.h5, WS/cameras.h5, WS/masks.h5 when present, and frame
``--frame`` of every camera.  Gaussians are seeded inside the tets (host tet
drawn ∝ volume, ``surface_bias`` times denser in tets touching the surface;
barycentric weights ~ Dirichlet(1); σ from the local spacing), coloured from
the pixels they project to, then colour, opacity, scale, rotation and the
barycentric position inside the host tet are optimised with Adam against

    L = Σ_cameras (1 − λ) |I − Î|₁ + λ (1 − SSIM(I, Î)) + w_mask |A − m|₁

where Î = I·m + b(1 − m) is the masked photo over the background colour b
(black).  Without masks the capture's background plates are used as the
per-pixel background (and the whole photo is the target); without either, a
constant background (the median border colour) is assumed.  Writes
WS/gaussians.h5 (with the fit PSNR per camera) and WS/fit_gaussians/CAM.png
(render | photo side by side).

The mesh is posed as the object is in the fit frame (``--pose capture``, docs/capture.md): frame 0 is
x_0 = the rest shape or, with ``[capture] start = "equilibrium"``, the static equilibrium under gravity and
the frame-0 controls (stages.sim.static.start_state) with capture.toml's E and ν per region; a later frame
is simulated from x_0 (stages.sim.static.simulate_from_start, one implicit-Euler step per frame, as rsl adapt
simulates).  A capture filmed mid-motion (start = "moving") has frame 0 posed from its masks: that equilibrium
corrected along its lowest vibration modes to the silhouettes (stages.moving_start.silhouette_pose).  The
Gaussians are bound in the rest frame (host element, barycentric coordinates, rest covariance Σ₀) and rendered
at those positions x_f: centre Σ_a N_a x_a, covariance F Σ₀ Fᵀ.  gaussians.h5
records x_f (``fit_positions``) and how it was made (``fit_state``), so rsl adapt's re-binding starts from the
configuration the Gaussians were really fitted at.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np

from stages.artefacts import KIND_FILES, CamerasArtefact, GaussiansArtefact, MasksArtefact, MeshArtefact, Provenance
from stages.capture import load_capture, write_image
from stages.workspace import prepare_workspace
from stages.errors import RslError
from stages.moving_start import silhouette_pose
from stages.occluders import has_occluders, ignore_mask
from stages.progress import Reporter, SilentReporter
from stages.sim.quadrature import point_map


@dataclass(frozen=True)
class FitGaussiansConfig:
    capture: Path
    """Capture folder."""
    workspace: Path
    """Workspace folder (reads mesh.h5, cameras.h5, masks.h5; writes gaussians.h5)."""
    frame: int = 0
    """Frame the Gaussians are fitted to."""
    pose: Literal["capture", "rest"] = "capture"
    """Mesh configuration the Gaussians are fitted at: capture — the fit frame's state under the capture's [capture] start (rest, or the static equilibrium under gravity and the frame-0 controls with capture.toml's E and ν; later frames simulated from it; start = "moving": frame 0 only, that equilibrium corrected to the masks' silhouettes); rest — the rest shape, whatever the frame shows."""
    iterations: int = 300
    """Adam iterations (each renders every camera once)."""
    gaussians: int = 10000
    """Number of Gaussians seeded in the tets."""
    surface_bias: float = 4.0
    """How many times denser Gaussians are seeded in tets that touch the surface."""
    sh_degree: int = 0
    """Spherical-harmonics degree of the colours (0: flat colour, 1: view-dependent)."""
    ssim_weight: float = 0.2
    """λ of the D-SSIM term in (1 − λ) L1 + λ (1 − SSIM)."""
    mask_weight: float = 0.2
    """Weight of |coverage − mask| (used when masks.h5 exists)."""
    lr: float = 0.01
    """Base learning rate (colours; opacity ×5, scales ×0.5, rotations ×0.1, barycentric ×1)."""
    max_resolution: int = 512
    """Images larger than this (px, longer side) are fitted at an integer downscale."""
    seed: int = 0
    """Seed of the Gaussian seeding."""


# --------------------------------------------------------------------------- helpers
def _scaled_camera(cam, factor: int):
    """The camera seen at 1/factor resolution (pixel centres at integer coordinates)."""
    if factor == 1:
        return cam
    K = np.array(cam.K, np.float64)
    K[0, 0] /= factor
    K[1, 1] /= factor
    K[0, 1] /= factor
    K[0, 2] = (K[0, 2] + 0.5) / factor - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / factor - 0.5
    return replace(cam, K=K, width=cam.width // factor, height=cam.height // factor)


def _downscale(img: np.ndarray, factor: int) -> np.ndarray:
    """Box-filter downscale of (H, W, ...) by an integer factor (crops the remainder)."""
    if factor == 1:
        return img
    h, w = img.shape[0] // factor, img.shape[1] // factor
    x = img[: h * factor, : w * factor].reshape(h, factor, w, factor, *img.shape[2:])
    return x.mean(axis=(1, 3))


def seed_gaussians(mesh: MeshArtefact, n: int, surface_bias: float, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Host tets (n,), barycentric weights (n, 4) and isotropic log σ (n,) for n Gaussians.

    P(tet) ∝ V · (surface_bias if the tet touches a surface vertex else 1);
    σ = ½ (V_host / (n P(host)))^{1/3}, half the expected local spacing.
    """
    surf = np.zeros(mesh.n_vertices, bool)
    surf[np.unique(mesh.surface_faces)] = True
    touches = surf[mesh.tets].any(1)
    w = mesh.rest_volumes * np.where(touches, surface_bias, 1.0)
    p = w / w.sum()
    host = rng.choice(mesh.n_tets, size=n, p=p)
    bary = rng.dirichlet(np.ones(4), size=n)
    spacing = np.cbrt(mesh.rest_volumes[host] / (n * p[host]))
    return host, bary, np.log(0.5 * spacing)


def rest_centres(mesh: MeshArtefact, host: np.ndarray, bary: np.ndarray, positions: np.ndarray | None = None
                 ) -> np.ndarray:
    """Positions (g, 3) m of points of host elements (g,) at barycentric (corner) coordinates (g, 4) with the mesh
    at ``positions`` (n, 3) (default its rest shape X): Σ_a N_a(β) x_a (= Σ β_k x_k for linear tets; the
    quadratic map for quadratic ones)."""
    x = mesh.vertices if positions is None else np.asarray(positions, np.float64)
    N, _, _ = point_map(mesh.vertices, mesh.tets, host, bary)
    return np.einsum("gk,gkd->gd", N, x[mesh.tets[host]])


def fit_pose(cap, mesh: MeshArtefact, frame: int, ws: Path | None = None) -> tuple[np.ndarray, dict]:
    """(x_f (n, 3) m, description): the mesh as the object is in frame ``frame`` under the capture's start
    convention with capture.toml's E and ν per region — frame 0: stages.sim.static.start_state (the rest shape,
    or the static equilibrium under gravity and the frame-0 controls; a moving start: that equilibrium corrected
    to the masks of ``ws``/masks.h5, stages.moving_start.silhouette_pose — "start" = "silhouette" —, or without
    masks the equilibrium itself); frame f > 0: simulated from it, one implicit-Euler step per frame
    (stages.sim.static.simulate_from_start), as rsl adapt simulates (a moving start: refused).  An object that
    nothing holds (no handle, no obstacle) has no static equilibrium: it is posed from its rest shape
    (description "start" = "rest", "declared_start" = "equilibrium")."""
    from stages.sim.scene import SimulationError, frame_inputs, make_scene  # jax + numba: loaded on use
    from stages.sim.static import simulate_from_start, start_state

    controls = cap.controls()
    scene = make_scene(mesh, controls, cap.material.model, cap.dt, cap.gravity,
                       damping=cap.material.damping)
    names = list(scene.region_names)
    young = np.array([cap.material.region_young(r) for r in names], float)
    poisson = np.array([cap.material.region_poisson(r) for r in names], float)
    if cap.start == "moving" and frame != 0:
        raise RslError(f"{cap.toml_path}: start = \"moving\" (frame 0 filmed mid-motion): rsl cannot pose the mesh "
                       f"as frame {frame} shows it (frame 0's shape and velocity are estimated by rsl adapt); fit the "
                       f"Gaussians to frame 0 (--frame 0), or at the rest shape with --pose rest.")
    held = bool(scene.handles or scene.obstacles)
    if cap.start == "moving" and held and ws is not None and (Path(ws) / KIND_FILES["masks"]).exists():
        try:
            return silhouette_pose(cap, ws, mesh, young, poisson, frame)
        except SimulationError as e:
            raise RslError(f"{cap.toml_path}: cannot pose the mesh as frame 0 shows it (start = 'moving', E = "
                           f"{young.tolist()} Pa): {e} Fix the capture, or fit at rest with --pose rest.") from None
    # a moving start without masks: the static equilibrium under the frame-0 controls (the caller warns)
    start = ("equilibrium" if cap.start == "moving" else cap.start) if held else "rest"
    state = {"pose": "capture", "start": start, "declared_start": cap.start, "frame": int(frame), "regions": names,
             "young": young.tolist(), "poisson": poisson.tolist()}
    try:
        if frame == 0:
            x = start_state(scene, frame_inputs(scene, controls, 0), young, poisson, start)
        else:
            x = simulate_from_start(scene, lambda f: frame_inputs(scene, controls, f), young, poisson, frame + 1,
                                    start)[-1]
    except SimulationError as e:
        raise RslError(f"{cap.toml_path}: cannot pose the mesh as frame {frame} shows it (start = '{cap.start}', "
                       f"E = {young.tolist()} Pa): {e} Fix the capture, or fit at rest with --pose rest.") from None
    return np.asarray(x, np.float64), state


def _sample_colours(centres: np.ndarray, cams: list, images: list, masks: list) -> tuple[np.ndarray, list]:
    """Mean colour of the pixels each centre projects to (inside the mask); (n, 3), seen-count per camera."""
    import torch  # torch and the numba kernels load when the stage runs: `rsl fit-gaussians --help` stays light

    from stages.render import projection as proj

    acc = np.zeros((len(centres), 3))
    cnt = np.zeros(len(centres))
    seen = []
    for cam, img, m in zip(cams, images, masks):
        uv, z = proj.project_points(torch.as_tensor(centres), proj.CameraTensors.from_camera(cam, torch.float64))
        uv, z = uv.numpy(), z.numpy()
        px = np.round(uv).astype(np.int64)
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
        seen.append(int(ok.sum()))
        idx = np.nonzero(ok)[0]
        if m is not None:
            idx = idx[m[px[idx, 1], px[idx, 0]] > 0.5]
        acc[idx] += img[px[idx, 1], px[idx, 0]]
        cnt[idx] += 1
    col = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 0.5)
    return col, seen


def _side_by_side(render: np.ndarray, photo: np.ndarray) -> np.ndarray:
    gap = np.ones((render.shape[0], 4, 3))
    return np.clip(np.concatenate([render, gap, photo], 1), 0, 1)


# --------------------------------------------------------------------------- stage
def run(config: FitGaussiansConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Seed and fit Gaussians to frame ``config.frame``; writes WS/gaussians.h5."""
    # The rasterizer's numba kernels use every core; torch's own thread pool on the small
    # per-Gaussian ops only spins against them (measured: 4-5x slower wall time with both).
    import torch  # loaded on use, as in _run

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _run(config, reporter)
    finally:
        torch.set_num_threads(threads)


def _run(config: FitGaussiansConfig, reporter: Reporter) -> Path:
    import torch  # torch and the numba renderer load when the stage runs: `rsl fit-gaussians --help` stays light

    from stages.render import gaussians as gauss
    from stages.render import loss as rloss

    t0 = time.perf_counter()
    if config.gaussians < 1:
        raise RslError(f"--gaussians should be at least 1, found {config.gaussians}.")
    if config.iterations < 0:
        raise RslError(f"--iterations should be non-negative, found {config.iterations}.")
    if config.sh_degree not in (0, 1):
        raise RslError(f"--sh-degree should be 0 or 1, found {config.sh_degree}.")
    ws = Path(config.workspace)
    cap = load_capture(config.capture)
    prepare_workspace(ws)  # writable? (before the compute) and no stale temp files of a killed run
    mesh_path, cams_path, masks_path = (ws / KIND_FILES[k] for k in ("mesh", "cameras", "masks"))
    mesh = MeshArtefact.load(mesh_path)
    cams_all = CamerasArtefact.load(cams_path).cameras
    by_name = {c.name: c for c in cams_all}
    names = [n for n in cap.camera_names if n in by_name] or [c.name for c in cams_all]
    masks_art = MasksArtefact.load(masks_path) if masks_path.exists() else None

    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)

    # ---------------------------------------------------------------- images, masks, backgrounds
    cams, targets, masks, plates, inputs = [], [], [], [], [mesh_path, cams_path]
    if masks_art is not None:
        inputs.append(masks_path)
    for name in names:
        cam = by_name[name]
        src = cap.frame_source(name)
        img = src.read(config.frame).astype(np.float64) / 255.0
        inputs.append(src.files[config.frame] if src.files is not None else src.video)
        if img.shape[:2] != (cam.height, cam.width):
            raise RslError(f"{cap.root / 'frames' / name}: frame {config.frame} is {img.shape[1]}x{img.shape[0]} "
                           f"px but cameras.h5 says camera '{name}' is {cam.width}x{cam.height}.")
        m = None
        if masks_art is not None and name in masks_art.masks:
            mk = masks_art.masks[name]
            if config.frame >= mk.shape[0]:
                raise RslError(f"{masks_path}: camera '{name}' holds {mk.shape[0]} masks, frame {config.frame} "
                               f"is out of range.")
            m = mk[config.frame].astype(np.float64)
            if m.shape != img.shape[:2]:
                raise RslError(f"{masks_path}: mask of camera '{name}' is {m.shape[1]}x{m.shape[0]} px, "
                               f"the frame is {img.shape[1]}x{img.shape[0]}.")
        plate = cap.background(name) if masks_art is None else None
        factor = max(1, math.ceil(max(cam.width, cam.height) / config.max_resolution))
        cam = _scaled_camera(cam, factor)
        img = _downscale(img, factor)[: cam.height, : cam.width]
        if m is not None:
            m = _downscale(m, factor)[: cam.height, : cam.width]
        if plate is not None:
            plate = _downscale(plate.astype(np.float64) / 255.0, factor)[: cam.height, : cam.width]
        cams.append(cam)
        targets.append(img)
        masks.append(m)
        plates.append(plate)

    if any(m is not None for m in masks):
        background = np.zeros(3)
        mode = "masks"
    elif all(p is not None for p in plates):
        background = np.median(np.concatenate([p.reshape(-1, 3) for p in plates]), 0)
        mode = "background plates"
    else:
        border = np.concatenate([np.concatenate([t[0], t[-1], t[:, 0], t[:, -1]]) for t in targets])
        background = np.median(border, 0)
        plates = [None] * len(cams)
        mode = "no masks (constant background)"
        reporter.warn("no masks.h5 and no background plates: fitting the whole image with a constant "
                      "background colour; run `rsl segment` first for a clean fit.")

    # ---------------------------------------------------------------- the fit frame's configuration
    if config.pose == "capture":
        x_fit, fit_state = fit_pose(cap, mesh, config.frame, ws)
        inputs += [cap.toml_path] + ([cap.controls_path] if cap.controls_path.exists() else [])
        if fit_state["start"] == "silhouette":
            reporter.info(f"{masks_path}: frame 0 (filmed mid-motion) posed from its masks, "
                          f"{1e3 * fit_state['moved_m']:.1f} mm RMS from the equilibrium of capture.toml's E "
                          f"(silhouette residual RMS {fit_state['silhouette_rms'][0]:.3f} → "
                          f"{fit_state['silhouette_rms'][1]:.3f}).")
        elif cap.start == "moving" and fit_state["start"] == "equilibrium":
            reporter.warn(f"{masks_path}: not found, so frame 0 (filmed mid-motion) is posed at the equilibrium of "
                          f"capture.toml's E, which may not be the shape it shows; run `rsl segment` first.")
        elif fit_state["start"] != fit_state["declared_start"]:
            reporter.warn(f"{cap.toml_path}: start = '{cap.start}' but nothing holds the object (no handle or "
                          f"obstacle in controls.json): fitting with the mesh at rest.")
    elif config.pose == "rest":
        x_fit, fit_state = np.array(mesh.vertices, np.float64), {"pose": "rest", "frame": int(config.frame)}
    else:
        raise RslError(f"--pose should be capture or rest, found '{config.pose}'.")

    # ---------------------------------------------------------------- seeding
    host, bary, log_sigma = seed_gaussians(mesh, config.gaussians, config.surface_bias, rng)
    centres = rest_centres(mesh, host, bary, x_fit)
    colour, seen = _sample_colours(centres, cams, targets, masks)
    for cam, s in zip(cams, seen):
        if s == 0:
            raise RslError(f"{cams_path}: camera '{cam.name}' sees none of the mesh (no Gaussian projects into "
                           f"its {cam.width}x{cam.height} image); check the calibration or the mesh units.")
    k = (config.sh_degree + 1) ** 2
    sh = np.zeros((config.gaussians, k, 3))
    sh[:, 0] = gauss.color_to_sh0(colour)
    g = gauss.BoundGaussians(mesh.tets, mesh.dm_inv, host, bary, np.repeat(log_sigma[:, None], 3, 1),
                       np.tile([1.0, 0.0, 0.0, 0.0], (config.gaussians, 1)),
                       np.zeros(config.gaussians), sh, background, rest=mesh.vertices)
    positions = torch.as_tensor(x_fit, dtype=torch.float32)  # the Gaussians are rendered (and fitted) at x_f

    # occluders (controls.json visual, stages/occluders.py): their pixels at the fit frame weigh nothing
    controls = cap.controls()
    ign_t = [torch.as_tensor(ignore_mask(controls, config.frame, c)) if has_occluders(controls) else None
             for c in cams]
    if has_occluders(controls) and cap.controls_path not in inputs:
        inputs.append(cap.controls_path)
    tgt_t, mask_t, bg_t = [], [], []
    for t, m, p in zip(targets, masks, plates):
        if m is not None:
            t = t * m[..., None] + background * (1 - m[..., None])
        tgt_t.append(torch.as_tensor(t, dtype=torch.float32))
        mask_t.append(None if m is None else torch.as_tensor(m, dtype=torch.float32))
        bg_t.append(None if p is None else torch.as_tensor(p, dtype=torch.float32))

    lr = config.lr
    opt = torch.optim.Adam([
        {"params": [g.sh], "lr": lr},
        {"params": [g.opacity_logit], "lr": 5 * lr},
        {"params": [g.log_scales], "lr": 0.5 * lr},
        {"params": [g.rotations], "lr": 0.1 * lr},
        {"params": [g.bary_logits], "lr": lr},
    ], eps=1e-15)
    lam = config.ssim_weight

    # ---------------------------------------------------------------- optimisation
    with reporter.task(f"fitting {config.gaussians} Gaussians to {len(cams)} views", config.iterations) as task:
        for it in range(config.iterations):
            opt.zero_grad(set_to_none=True)
            ps = []
            for cam, tgt, m, bg, ig in zip(cams, tgt_t, mask_t, bg_t, ign_t):
                out = g.render(positions, cam, bg)
                if ig is not None:  # an occluder's pixels: the target is the render itself (no loss, no gradient)
                    tgt = torch.where(ig[..., None], out.image.detach(), tgt)
                    m = None if m is None else torch.where(ig, out.alpha.detach(), m)
                loss = (1 - lam) * rloss.l1(out.image, tgt) + lam * (1 - rloss.ssim(out.image, tgt))
                if m is not None and config.mask_weight > 0:
                    loss = loss + config.mask_weight * (out.alpha - m).abs().mean()
                if not torch.isfinite(loss):
                    raise RslError(f"{ws / KIND_FILES['gaussians']}: the fit diverged at iteration {it} "
                                   f"(non-finite loss in camera '{cam.name}'); lower --lr.")
                (loss / len(cams)).backward()
                ps.append(rloss.psnr(out.image, tgt))
            opt.step()
            task.advance(1, psnr=f"{np.mean(ps):.2f} dB")

    # ---------------------------------------------------------------- results
    fit_psnr = {}
    out_dir = ws / "fit_gaussians"
    with torch.no_grad():
        for cam, tgt, bg in zip(cams, tgt_t, bg_t):
            img = g.render(positions, cam, bg).image
            fit_psnr[cam.name] = round(rloss.psnr(img, tgt), 3)
            write_image(out_dir / f"{cam.name}.png", _side_by_side(img.numpy(), tgt.numpy()))
    art = GaussiansArtefact(**g.arrays(), fit_psnr=fit_psnr, fit_positions=x_fit, fit_state=fit_state)
    path = art.save(ws / KIND_FILES["gaussians"], Provenance.make(config, inputs))
    vals = list(fit_psnr.values())
    where = (f"the mesh posed as frame {config.frame} under start = '{fit_state['start']}'"
             if fit_state["pose"] == "capture" else "the mesh at rest")
    reporter.summary(f"fitted {config.gaussians} Gaussians to frame {config.frame} of {len(cams)} cameras "
                     f"({mode}; {where}): PSNR {np.mean(vals):.2f} dB mean, {np.min(vals):.2f} dB worst, "
                     f"in {time.perf_counter() - t0:.1f} s → {path}")
    return path
