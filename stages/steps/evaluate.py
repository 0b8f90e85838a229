"""Stage ``rsl evaluate``: compare adapt.h5 with the truth of a synthetic capture (DESIGN §7).

* E and ν per frame and region: e_E = |E − E_true| / E_true, e_ν = |ν − ν_true|.
* Vertex error: the symmetric mean distance between the simulated surface (mesh.h5 surface
  faces over adapt.h5 positions) and truth/surface.npz — the meshes need not match:
  d(A, B) = ½ (mean_{p∈A} dist(p, B) + mean_{q∈B} dist(q, A)), the means taken over a 3-point
  area-weighted quadrature of each triangle, dist a point-to-triangle distance (open3d).
  It is also given over the truth's bounding-box diagonal.
* PSNR of the Gaussians rendered on the adapted mesh against the (masked) images, when
  gaussians.h5 exists: PSNR = 10 log10(1 / MSE) on [0, 1] RGB.
* Forces, when the capture has truth/forces.csv: the force each handle and obstacle exerts, computed from
  adapt.h5 as ``rsl export --forces`` computes it (stages.forces: θ(t) replayed in the full space from the
  start state with adapt's substeps, the truth's definition), against the truth's: per handle/obstacle
  the median over frames of ‖F − F_true‖ / ‖F_true‖ (frames where ‖F_true‖ ≥ 5 % of its largest value), and
  the median over every compared (frame, handle/obstacle) pair.
* ``--sweep``: the loss (markers, images or silhouettes) of the capture over a grid of fixed E, ν fixed at the
  truth's, simulated in full space on mesh.h5 from the declared start (stages.sweep) — its minimum beside E_true, the
  check that a loss is unbiased before an optimiser runs on it; it needs no adapt.h5.

Writes WS/evaluation.json (atomic), WS/evaluation_young.png (E(t) estimated vs truth) and, with ``--sweep``,
WS/evaluation_sweep.png (the loss over E, its minimum and E_true).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from stages.artefacts import (KIND_FILES, PARTIAL_ADAPT, AdaptArtefact, CamerasArtefact, GaussiansArtefact,
                              MasksArtefact, MeshArtefact, Provenance, _jsonable, check_same_mesh,
                              read_provenance)
from stages.capture import load_capture, read_forces_csv, read_truth
from stages.errors import RslError
from stages.forces import (FORCE_EXTRAPOLATE, FORCE_SUBSTEPS, FORCE_THETA, adapted_forces, filter_model, force_errors,
                           force_table, replay_substeps, replayable)
from stages.observations import render_backgrounds, target_image
from stages.progress import Reporter, SilentReporter
from stages.render.image_loss import ImageLoss
from stages.results import compute_stress, gaussian_anchor, material_damping, material_setting
from stages.sweep import sweep
from stages.workspace import write_text_atomic

_QUAD = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])  # (3, 3) barycentrics


@dataclass(frozen=True)
class EvaluateConfig:
    capture: Path
    """Synthetic capture folder with truth/ (material.csv, surface.npz)."""
    workspace: Path
    """Workspace holding adapt.h5 and mesh.h5; evaluation.json is written there."""
    psnr_frames: int = 8
    """Frames (evenly spaced) at which renders are compared with the images (0: skip PSNR)."""
    plot: bool = True
    """Write evaluation_young.png (E(t) estimated vs truth)."""
    partial: bool = False
    """Evaluate adapt.partial.h5, the frames an interrupted or failed `rsl adapt` kept (refused otherwise)."""
    forces: bool = True
    """Compare the handle and obstacle forces of adapt.h5 (as `rsl export --forces` computes them) with truth/forces.csv when the capture has it."""
    sweep: bool = False
    """Also sweep the loss over a grid of fixed E (ν at the truth's) from the declared start on mesh.h5, and write evaluation_sweep.png; works without adapt.h5, except on a capture filmed mid-motion (start = "moving"), whose sweep starts from adapt.h5's estimated start state."""
    sweep_loss: Literal["markers", "vision", "silhouette"] = "markers"
    """Loss of the sweep: markers (markers.csv), vision (the Gaussians of gaussians.h5 against the images) or silhouette (the mesh's coverage against masks.h5: geometry alone, what still depends on E on a static capture)."""
    sweep_points: int = 9
    """Number of E values in the sweep, evenly spaced in log E."""
    sweep_min: float = 0.5
    """Smallest E of the sweep as a fraction of the reference E (the truth's at the first swept frame)."""
    sweep_max: float = 2.0
    """Largest E of the sweep as a fraction of the reference E."""
    sweep_frames: str = ""
    """Frames of the sweep, 'A:B' (B excluded); empty = the whole sequence."""
    sweep_substeps: int = 1
    """Implicit-Euler steps per frame in the sweep's simulation."""
    sweep_region: str = ""
    """Sweep only this region's E, every other region held at the truth's; empty = every region's E scaled together."""
    sweep_past: Literal["grid", "truth"] = "grid"
    """Frames before --sweep-frames' first: simulated with each E of the grid (grid), or once with the truth's E(t) and each E of the grid from there on (truth: the loss of the frames after a change of material, given the past)."""
    force_substeps: int = FORCE_SUBSTEPS
    """Implicit-Euler steps per frame S of the full-space replay the forces are computed on; 0 (the default) = adapt's --substeps, the time step θ was estimated with (docs/results/forces_converged.md, forces_damped.md)."""
    force_extrapolate: bool = FORCE_EXTRAPOLATE
    """Richardson-extrapolate the replay's forces in time, 2 F(2S) − F(S) from replays with S and 2S steps per frame: cancels implicit Euler's first-order error, costs 3S steps per frame.  Off by default: plain at adapt's 6 substeps came closer to truths converged in time than Richardson (1, 2) on every capture measured (docs/results/forces_converged.md, forces_damped.md)."""
    force_theta: Literal["online", "segment", "smoothed"] = FORCE_THETA
    """θ(t) of the replay: smoothed (the default) = adapt.h5's E ± σ and ν ± σ smoothed over the whole run (Rauch–Tung–Striebel) under the gn filter's own random walk (its --process-noise, --change-sigma at each detected change); online = each frame's estimate as adapt.h5 records it (frame t's force uses estimates up to t); segment = the last estimate of each segment between the material changes adapt's gn estimator detected.  On the frames where the truth's force converges in time (a constant E; before a step of E) smoothed erred less than online on every capture measured (two-region beam 26 → 5 %, bar before its step 7.8 → 1.1 %, docs/results/forces_theta.md); it carries a later material into earlier frames when a change is detected a few frames before the true one.  An adam run with images is held per segment between its located changes at its anchor calibrations' fits (adapt.h5 anchor_calibrations); one without keeps its recorded θ(t)."""


def surface_samples(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Quadrature points (3F, 3) on the triangles and their weights (3F,) = area/3, normalised to 1."""
    tri = vertices[faces]  # (F, 3, 3)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    pts = np.einsum("qk,fkd->fqd", _QUAD, tri).reshape(-1, 3)
    w = np.repeat(area / 3.0, 3)
    return pts, w / max(w.sum(), 1e-300)


def point_surface_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Distance (P,) from each point to the triangle surface (vertices (n, 3), faces (F, 3))."""
    import open3d as o3d  # ~1 s to import: only when distances are measured

    scene = o3d.t.geometry.RaycastingScene()
    centre = vertices.mean(0)  # centre for float32 accuracy
    scene.add_triangles(o3d.core.Tensor((vertices - centre).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(faces, np.uint32)))
    d = scene.compute_distance(o3d.core.Tensor((points - centre).astype(np.float32)))
    return d.numpy().astype(np.float64)


def symmetric_surface_distance(va: np.ndarray, fa: np.ndarray, vb: np.ndarray, fb: np.ndarray) -> float:
    """½ (mean over A of dist to B + mean over B of dist to A), area-weighted (m)."""
    pa, wa = surface_samples(va, fa)
    pb, wb = surface_samples(vb, fb)
    return 0.5 * (float(wa @ point_surface_distance(pa, vb, fb)) + float(wb @ point_surface_distance(pb, va, fa)))


def run(config: EvaluateConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Errors of adapt.h5 against CAPTURE/truth (and the loss sweep); writes WS/evaluation.json."""
    ws = Path(config.workspace)
    capture = load_capture(config.capture)
    truth = read_truth(capture)
    adapt_path = ws / (PARTIAL_ADAPT if config.partial else KIND_FILES["adapt"])
    mesh_path = ws / KIND_FILES["mesh"]
    if config.sweep:
        _check_sweep(config)
    out: dict = {"capture": str(Path(config.capture).resolve())}
    inputs = [mesh_path]
    summary = []
    if adapt_path.exists() or not config.sweep:  # a sweep alone needs no adapt.h5
        out.update(_adapt_errors(config, ws, capture, truth, adapt_path, mesh_path, reporter))
        inputs.insert(0, adapt_path)
        ps = f", PSNR {out['psnr_mean']:.2f} dB" if out["psnr_mean"] is not None else ""
        summary.append(f"E error median {out['young_rel_error_median']:.1%} (final {out['young_rel_error_final']:.1%})"
                       f", ν error median {out['poisson_abs_error_median']:.3f}, vertex error "
                       f"{out['vertex_error_mean_m'] * 1e3:.2f} mm ({out['vertex_error_rel_mean']:.2%} of the "
                       f"diagonal){ps}")
        f = out.get("forces")
        if f and f.get("median_relative_error") is not None:
            summary.append(f"force error median {f['median_relative_error']:.1%}")
    if config.sweep:
        out["sweep"] = _sweep(config, ws, capture, truth, MeshArtefact.load(mesh_path), reporter)
        sw = out["sweep"]
        where = "" if sw["interior"] else " (at an end of the grid: widen it)"
        if sw["loss_contrast"] < 1e-4:
            where += (f" — but the loss is flat over the grid (it varies by {sw['loss_contrast']:.1e}): it does not "
                      f"tell E")
        of = f" of region {sw['region']}" if sw["region"] else ""
        summary.append(f"{sw['loss']} loss lowest at E{of} = {sw['young_min']:.4g} Pa = {sw['min_over_true']:.3f} "
                       f"E_true{where}")
    out["provenance"] = Provenance.make(config, inputs).inputs
    path = ws / "evaluation.json"
    write_text_atomic(path, json.dumps(_jsonable(out), indent=1))
    if config.plot and config.sweep:
        _plot_sweep(ws / "evaluation_sweep.png", out["sweep"])
    reporter.summary(f"{'; '.join(summary)} → {path}")
    return path


def _adapt_errors(config, ws, capture, truth, adapt_path, mesh_path, reporter) -> dict:
    """E, ν, surface, PSNR and force errors of adapt.h5 (the keys of evaluation.json); draws evaluation_young.png."""
    adapt = AdaptArtefact.load(adapt_path, allow_partial=config.partial)
    mesh = MeshArtefact.load(mesh_path)
    check_same_mesh(mesh_path, adapt_path)  # made from this very mesh.h5, whatever the counts
    frames = adapt.frames
    if adapt.positions.shape[1] != mesh.n_vertices:
        raise RslError(f"{adapt_path}: positions hold {adapt.positions.shape[1]} vertices but {mesh_path} has "
                       f"{mesh.n_vertices}; rerun rsl adapt.")
    t_truth = min(len(truth.young), len(truth.vertices))
    if frames.max() >= t_truth:
        raise RslError(f"{capture.truth_dir}: truth covers {t_truth} frames but adapt.h5 holds frame "
                       f"{int(frames.max())}.")
    missing = [r for r in adapt.region_names if r not in truth.region_names]
    if missing:
        raise RslError(f"{capture.truth_dir / 'material.csv'}: lists no region '{missing[0]}' of adapt.h5 "
                       f"(it lists {', '.join(truth.region_names)}).")
    idx = [truth.region_names.index(r) for r in adapt.region_names]
    e_true = truth.young[frames][:, idx]
    nu_true = truth.poisson[frames][:, idx]
    e_rel = np.abs(adapt.young - e_true) / e_true  # (T, R)
    nu_abs = np.abs(adapt.poisson - nu_true)

    diag = float(np.linalg.norm(np.ptp(truth.vertices[0], axis=0)))
    vert_err = np.zeros(len(frames))
    with reporter.task("surface distance to truth", len(frames)) as task:
        for i, t in enumerate(frames):
            vert_err[i] = symmetric_surface_distance(adapt.positions[i], mesh.surface_faces,
                                                     truth.vertices[t], truth.faces)
            task.advance(1)

    psnr, psnr_frames = _psnr(config, ws, capture, adapt, mesh, reporter)
    out = {
        "mode": adapt.mode, "space": adapt.space, "loss_kind": adapt.loss_kind, "window": adapt.window,
        "frames": frames.tolist(),
        "region_names": adapt.region_names,
        "young_rel_error_median": float(np.median(e_rel.max(axis=1))),
        "young_rel_error_per_frame": e_rel.max(axis=1).tolist(),
        "young_rel_error_per_region": {r: e_rel[:, k].tolist() for k, r in enumerate(adapt.region_names)},
        "young_rel_error_final": float(e_rel[-1].max()),
        # the fraction of (frame, region) where the truth lies inside the estimator's ±2σ (null without σ)
        "young_within_2sigma": _within_2sigma(adapt, e_true),
        "poisson_abs_error_median": float(np.median(nu_abs.max(axis=1))),
        "poisson_abs_error_per_frame": nu_abs.max(axis=1).tolist(),
        "vertex_error_mean_m": float(vert_err.mean()),
        "vertex_error_rel_mean": float(vert_err.mean() / diag),
        "vertex_error_per_frame_m": vert_err.tolist(),
        "bbox_diagonal_m": diag,
        "psnr_mean": float(np.mean(psnr)) if psnr else None,
        "psnr_per_frame": dict(zip(map(str, psnr_frames), psnr)),
        "forces": _forces(config, capture, adapt, mesh, reporter,
                          filter_model(read_provenance(adapt_path).get("config"), capture.material.poisson_range,
                                       adapt.extra)),
    }
    if config.plot:
        _plot(ws / "evaluation_young.png", frames, adapt, truth, idx, vert_err)
    return out


def _forces(config, capture, adapt, mesh, reporter, walk=None) -> dict | None:
    """Force errors against truth/forces.csv (stages.forces.force_errors), None without the file or --forces."""
    from stages.sim.scene import make_scene  # JAX and numba physics: loaded on use (rsl evaluate --help)

    path = capture.truth_dir / "forces.csv"
    if not config.forces or not path.is_file():
        return None
    if config.force_substeps < 0:
        raise RslError(f"--force-substeps should be 0 (adapt's) or at least 1, found {config.force_substeps}.")
    truth_rows = read_forces_csv(path)
    controls = capture.controls()
    model, dt, gravity = material_setting(capture, adapt)
    scene = make_scene(mesh, controls, model, dt, gravity, damping=material_damping(capture, adapt))
    substeps = replay_substeps(config.force_substeps, adapt)
    if not (adapt.mode == "online" and replayable(adapt.frames)):
        reporter.warn("adapt.h5 is not an online run from frame 0: forces from its recorded positions (frame-level "
                      "differences), not from a replay; see docs/capture.md.")
    rows, _, source = adapted_forces(scene, controls, adapt, capture.start, substeps,
                                     lambda: compute_stress(adapt, mesh, model, reporter, sigma=False).forces,
                                     reporter=reporter, extrapolate=config.force_extrapolate,
                                     theta=config.force_theta, model=walk)
    per = force_errors(force_table(rows, dt), truth_rows)
    pooled = [e for v in per.values() for e in v["rel_error_per_frame"]]
    return {"truth": str(path), "median_relative_error": float(np.median(pooled)) if pooled else None,
            "per_set": per, "source": source}


def _check_sweep(config: EvaluateConfig) -> None:
    if config.sweep_points < 3:
        raise RslError(f"--sweep-points should be at least 3 (a minimum needs neighbours), found "
                       f"{config.sweep_points}.")
    if not 0 < config.sweep_min < config.sweep_max:
        raise RslError(f"--sweep-min and --sweep-max should satisfy 0 < min < max, found {config.sweep_min} and "
                       f"{config.sweep_max}.")
    if config.sweep_substeps < 1:
        raise RslError(f"--sweep-substeps should be at least 1, found {config.sweep_substeps}.")


def _sweep_frames(spec: str, capture) -> tuple[int, int] | None:
    spec = spec.strip()
    if not spec:
        return None
    try:
        a, b = (int(p) for p in spec.split(":"))
    except ValueError:
        raise RslError(f"--sweep-frames '{spec}' is not a range like 0:20.") from None
    if not 0 <= a < b:
        raise RslError(f"--sweep-frames '{spec}' should be A:B with 0 ≤ A < B.")
    return a, b


def _sweep(config, ws, capture, truth, mesh, reporter) -> dict:
    """The loss over a grid of E (stages.sweep.sweep): every region's E scaled with region 0's (or, with
    --sweep-region, that region's alone, the others at the truth's), ν at the truth's (per region, at the first
    swept frame); the grid around E_ref = the truth's E of region 0 (the swept region) there."""
    frames = _sweep_frames(config.sweep_frames, capture)
    f0 = frames[0] if frames else 0
    if f0 >= len(truth.young):
        raise RslError(f"{capture.truth_dir / 'material.csv'}: lists no frame {f0} (--sweep-frames).")
    names = list(mesh.region_names)
    missing = [r for r in names if r not in truth.region_names]
    if missing:
        raise RslError(f"{capture.truth_dir / 'material.csv'}: lists no region '{missing[0]}' of mesh.h5.")
    region = config.sweep_region.strip() or None
    if region is not None and region not in names:
        raise RslError(f"{ws / KIND_FILES['mesh']}: has no region '{region}' (--sweep-region); its regions are "
                       f"{', '.join(names)}.")
    ref = names.index(region) if region is not None else 0
    idx = [truth.region_names.index(r) for r in names]
    e_true = truth.young[f0, idx]  # (R,)
    nu_true = truth.poisson[f0, idx]
    if len(np.unique(nu_true)) > 1:
        reporter.warn(f"{capture.truth_dir / 'material.csv'}: regions differ in ν; the sweep holds every region at "
                      f"ν = {nu_true[ref]:g} (region {names[ref]}).")
    grid = e_true[ref] * np.geomspace(config.sweep_min, config.sweep_max, config.sweep_points)
    if config.sweep_loss == "markers" and capture.markers() is None:
        raise RslError(f"{capture.root}: holds no markers.csv (or markers.c3d); use --sweep-loss vision.")
    before = _sweep_start(capture, ws) if capture.start == "moving" else None
    # (material.csv lists frame f0, checked above, so the frames before it too)
    past = truth.young[:f0, idx] if config.sweep_past == "truth" and f0 > 0 else None
    what = f"E of region {region}" if region is not None else "E"
    with reporter.task(f"{config.sweep_loss} loss sweep over {len(grid)} values of {what}", len(grid)) as task:
        try:  # base_young = the truth's E: scaled together (its ratios between regions kept), or held but one
            res = sweep(capture, mesh, grid, config.sweep_loss, frames=frames, workspace=ws,
                        poisson=float(nu_true[ref]), substeps=config.sweep_substeps, base_young=e_true,
                        reporter=lambda _m: task.advance(1), region=region, past_young=past, before=before)
        except ValueError as e:  # a missing or mismatched input of the loss, said in one sentence
            raise RslError(f"{str(e).rstrip('.')}.") from None
    e_ref = float(e_true[ref])
    return {"loss": config.sweep_loss, "frames": res.info["frames"], "start": res.info["start"],
            "substeps": config.sweep_substeps, "poisson": float(nu_true[ref]), "region": region,
            "past": "truth" if past is not None else "grid",
            "young_pa": res.young.tolist(),
            "loss_values": res.loss.tolist(), "young_min": res.young_min, "interior": res.interior,
            # (max − min) / max over the grid: ~0 when the loss does not depend on E (e.g. images of a still capture)
            "loss_contrast": float((res.loss.max() - res.loss.min()) / max(abs(res.loss.max()), 1e-300)),
            "young_true": e_ref, "min_over_true": res.young_min / e_ref,
            "constant_truth": bool(np.all(truth.young[res.info["frames"][0]:res.info["frames"][1], idx[ref]] == e_ref)),
            "order": res.info["order"], "n_vertices": res.info["n_vertices"]}


def _sweep_start(capture, ws: Path) -> np.ndarray:
    """(2, n, 3) m: (x_{−1}, x_0) of a capture filmed mid-motion as rsl adapt estimated them (adapt.h5
    start_positions), the start every E of the sweep is simulated from."""
    path = ws / KIND_FILES["adapt"]
    if not path.exists():
        raise RslError(f"{capture.toml_path}: start = \"moving\": the loss sweep starts from the start state rsl adapt "
                       f"estimates, and {path} is not there; run rsl adapt first.")
    before = AdaptArtefact.load(path).start_positions
    if before is None:
        raise RslError(f"{path}: records no estimated start state (start_positions), which the loss sweep of a capture "
                       f"filmed mid-motion starts from; run rsl adapt again.")
    return before


def _plot_sweep(path: Path, sw: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e, l = np.asarray(sw["young_pa"]), np.asarray(sw["loss_values"])
    fig, ax = plt.subplots(figsize=(6.5, 4))
    ax.plot(e, l, "o-", color="k", label=f"{sw['loss']} loss")
    ax.axvline(sw["young_min"], color="tab:blue", label=f"minimum {sw['young_min']:.4g} Pa "
                                                       f"({sw['min_over_true']:.3f} E_true)")
    ax.axvline(sw["young_true"], color="tab:red", ls="--", label=f"E_true {sw['young_true']:.4g} Pa")
    ax.set_xscale("log")
    ax.set_xlabel("Young's modulus E (Pa)" + (f", region {sw['region']} (the others at the truth's)"
                                              if sw.get("region") else ""))
    ax.set_ylabel(f"{sw['loss']} loss, frames {sw['frames'][0]}..{sw['frames'][1] - 1}")
    ax.set_title(f"loss sweep (start {sw['start']}, ν = {sw['poisson']:g}, P{sw['order']} mesh)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = path.with_name("." + path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def _psnr(config, ws, capture, adapt, mesh, reporter) -> tuple[list[float], list[int]]:
    gpath, cpath = ws / KIND_FILES["gaussians"], ws / KIND_FILES["cameras"]
    if config.psnr_frames <= 0 or not gpath.exists() or not cpath.exists():
        return [], []
    cams = CamerasArtefact.load(cpath)
    names = [c.name for c in cams.cameras if c.name in capture.camera_names]
    if not names:
        return [], []
    masks_path = ws / KIND_FILES["masks"]
    masks = MasksArtefact.load(masks_path).masks if masks_path.exists() else None
    renderer = ImageLoss(GaussiansArtefact.load(gpath), mesh, [cams.by_name(c) for c in names])
    renderer.set_backgrounds(render_backgrounds(capture, names, masks))  # as rsl adapt composites them
    anchor = gaussian_anchor(renderer, adapt, gpath)  # the Gaussians follow the mesh as rsl adapt made them
    pick = np.unique(np.linspace(0, len(adapt.frames) - 1, min(config.psnr_frames, len(adapt.frames))).round()
                     .astype(int))
    out = []
    with reporter.task("PSNR of renders", len(pick)) as task:
        for i in pick:
            t = int(adapt.frames[i])
            imgs = renderer.render(adapt.positions[i] - anchor)
            mse = []
            for c, img in zip(names, imgs):
                ref = target_image(capture.frame_source(c).read(t), masks, c, t, renderer.background)
                mse.append(float(np.mean((img - ref) ** 2)))
            out.append(float(10 * np.log10(1.0 / max(np.mean(mse), 1e-12))))
            task.advance(1)
    return out, [int(adapt.frames[i]) for i in pick]


def _within_2sigma(adapt, e_true: np.ndarray) -> float | None:
    """Fraction of the (frame, region) pairs with |E − E_true| ≤ 2σ, over those with a known σ (None: none)."""
    sd = np.asarray(getattr(adapt, "young_sigma", np.full(adapt.young.shape, np.nan)))
    ok = np.isfinite(sd)
    if not ok.any():
        return None
    return float(np.mean(np.abs(adapt.young - e_true)[ok] <= 2 * sd[ok]))


def _plot(path: Path, frames, adapt, truth, idx, vert_err) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a0, a1) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for k, r in enumerate(adapt.region_names):
        line, = a0.plot(frames, adapt.young[:, k], label=f"{r} estimated")
        sd = np.asarray(getattr(adapt, "young_sigma", np.full(adapt.young.shape, np.nan)))[:, k]
        if np.any(np.isfinite(sd)):  # the estimator's E ± σ as a band
            lo = np.maximum(adapt.young[:, k] - sd, 1e-12 * adapt.young[:, k])
            a0.fill_between(frames, lo, adapt.young[:, k] + sd, color=line.get_color(), alpha=0.25, lw=0,
                            label=f"{r} E ± σ")
        a0.plot(frames, truth.young[frames, idx[k]], "--", color=line.get_color(), label=f"{r} truth")
    a0.set_yscale("log")
    a0.set_ylabel("Young's modulus E (Pa)")
    a0.set_title(f"rsl adapt: {adapt.mode}, {adapt.space} space, {adapt.loss_kind}, w={adapt.window}")
    a0.legend(fontsize=8)
    a1.plot(frames, vert_err * 1e3, color="k")
    a1.set_ylabel("surface error (mm)")
    a1.set_xlabel("frame")
    fig.tight_layout()
    tmp = path.with_name("." + path.name + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
