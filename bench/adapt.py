"""Online adaptation experiments (issue 7) on captures made by `rsl synth`.

    .venv/bin/python bench/adapt.py [--cases step,markers_vs_vision,regions,ablation,timing] [--work DIR]

Cases (each builds its capture with stages.steps.synth, a workspace whose mesh.h5 is the simulated tet mesh
— truth/object.mesh — so that identified and true E refer to one discretisation, and runs rsl adapt /
rsl evaluate in-process):

  step               E(t) = 10 → 20 → 40 kPa (steps at frames 20 and 40), online vs offline.
                     settle_frames: frames after a step until the estimate stays within 5 % of the new value.
  markers_vs_vision  dinosaur pushed by a sphere: 40 markers vs 2 cameras' images (online, full space).
  regions            two regions whose E differ 3× (body 1e5, stiff 3e5): both estimates vs truth.
  markers_vs_vision_noisy  the dinosaur again, markers with 0 / 2 / 5 mm Gaussian noise (rsl synth
                     --marker-noise) vs images from 4 cameras at 96² and 128².
  markers_vs_vision_rebind  the dinosaur of markers_vs_vision_noisy after the fix of the Gaussians' anchor
                     (ImageLoss.rebind): markers 0 / 2 / 5 mm and images (4 cameras, 96² / 128², 2000 / 4000
                     Gaussians; the first-order offset anchor rerun for comparison; appearance refinement on
                     and off), plus the window loss L(E) swept over E / E_true at windows ending at frames
                     10, 20, 30 with the truth states before the window (where is the minimum, how sharp).
  markers_vs_vision_rebind_steps  the 4×96² vision run of markers_vs_vision_rebind with 1 and 4 Adam steps per
                     frame instead of 2.
  markers_visibility  the dinosaur of markers_vs_vision_rebind with realistic motion capture: markers written
                     only where at least 2 of the 4 cameras (96²) see them (rsl synth --marker-visibility 2:
                     occlusion by the object itself, from the renderer's depth buffer), without and with 2 mm
                     noise, adapted online as there (markers, full, w = 3, from E_true / 4); reports the fraction
                     of marker observations lost, and plots them beside that case's markers and vision runs.
  regions_nu         two regions, ν fitted: more frames (80), more Adam steps per frame (4), a smaller ν
                     learning rate (0.01), and a wrong ν start (0.40).
  ablation           window w ∈ {1, 3, 5, 10} (markers, full) and subspace dimension r ∈ {4, 8, 16}
                     (markers, reduced, PCA) on the step capture.
  ablation_w9        window w = 9 (markers, full) on the step capture, as ablation.
  ablation_r         subspace dimension r ∈ {10, 30, 60, 90, 120} with the autoencoder (40 epochs; PCA layer
                     capped at 170 modes), markers, reduced, w = 5, on the step capture.
  ablation_c         cameras c ∈ {1, 2, 4, 8} with the vision loss: one 8-camera 64² capture of the beam,
                     full space, w = 3; `--cameras 0` / `0,1` / `0,1,2,3` / all.
                     ablation* cases also write adapt_ablation.png (error and time vs w, r, c).
  refine             a coarse 8×2×2-cell box adapting to a capture simulated on a 24×6×6-cell box:
                     E / E_true with and without --refine 1 (DESIGN §5, effective E of a discretisation).
  timing             per-frame forward / backward / render / total on a bar-like box of ~9K DOFs,
                     r = 30, w = 3, c = 4 cameras at 128², reduced vs full, one Adam step per frame.

Per-frame times are medians over the adapted frames (the first frame, which compiles, is dropped); the
timing case keeps the better of two runs of each variant (the machine is shared).
Prints a Markdown table and writes docs/results/adapt.md, docs/results/adapt.json and PNG plots.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages.steps import adapt, calibrate, evaluate, fit_gaussians, generate_data, synth, tetrahedralize, train_subspace  # noqa: E402
from stages.artefacts import AdaptArtefact  # noqa: E402
from stages.progress import SilentReporter  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "docs" / "results"
BEAM = DATA / "autodef_fulton" / "Coarse_beam.mesh"
DINO = DATA / "autodef_fulton" / "dino_ultra_low.mesh"


class Log(SilentReporter):
    """Prints summaries (the stages' one-line results) with a timestamp."""

    def summary(self, message: str) -> None:
        super().summary(message)
        print(f"  [{time.strftime('%H:%M:%S')}] {message}", flush=True)


LOG = Log()


# =========================================================================== building blocks
def make_capture(work: Path, name: str, mesh: Path, scenario: str, frames: int, cameras: int = 1,
                 resolution: int = 32, young: float = 1e5, young_schedule: str = "", region: str = "",
                 markers: int = 40, marker_noise: float = 0.0, marker_visibility: int = 0) -> tuple[Path, Path]:
    """`rsl synth` capture + workspace (mesh.h5 from truth/object.mesh, cameras.h5 from cameras.json)."""
    cap, ws = work / name / "cap", work / name / "ws"
    if not (cap / "capture.toml").exists():
        synth.run(synth.SynthConfig(mesh=mesh, out=cap, scenario=scenario, cameras=cameras, frames=frames,
                                    resolution=resolution, young=young, young_schedule=young_schedule,
                                    region=region, markers=markers, marker_noise=marker_noise,
                                    marker_visibility=marker_visibility, calib_views=0, seed=0), LOG)
        toml = cap / "capture.toml"
        toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    if not (ws / "mesh.h5").exists():
        tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws), LOG)
        calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")), LOG)
    return cap, ws


def with_gaussians(cap: Path, ws: Path, n: int, iterations: int) -> None:
    if not (ws / "gaussians.h5").exists():
        fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=ws, iterations=iterations,
                                                           gaussians=n), LOG)


def subspace_ws(cap: Path, ws: Path, r: int, kind: str = "pca", sequences: int = 4, frames: int = 0,
                epochs: int = 300) -> Path:
    """A copy of ws with snapshots.h5 and a subspace of dimension r."""
    ws_r = ws.parent / f"ws_{kind}{r}"
    ws_r.mkdir(exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5"):
        if (ws / f).exists() and not (ws_r / f).exists():
            shutil.copy(ws / f, ws_r / f)
    snap = ws.parent / "snapshots.h5"
    if not snap.exists():
        generate_data.run(generate_data.GenerateDataConfig(capture=cap, workspace=ws_r, sequences=sequences,
                                                           frames=frames or 30, workers=1), LOG)
        shutil.copy(ws_r / "snapshots.h5", snap)
    elif not (ws_r / "snapshots.h5").exists():
        shutil.copy(snap, ws_r / "snapshots.h5")
    if not (ws_r / "subspace.h5").exists():
        train_subspace.run(train_subspace.TrainSubspaceConfig(workspace=ws_r, capture=cap, dim=r, kind=kind,
                                                              epochs=epochs), LOG)
    return ws_r


def run_adapt(cap: Path, ws: Path, out: Path, **kw) -> tuple[AdaptArtefact, dict]:
    """rsl adapt + rsl evaluate into folder ``out`` (a copy of the workspace's inputs)."""
    out.mkdir(parents=True, exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5", "subspace.h5"):
        if (ws / f).exists():
            shutil.copy(ws / f, out / f)
    path = adapt.run(adapt.AdaptConfig(capture=cap, workspace=out, **kw), LOG)
    evaluate.run(evaluate.EvaluateConfig(capture=cap, workspace=out, psnr_frames=4), LOG)
    return AdaptArtefact.load(path), json.loads((out / "evaluation.json").read_text())


def times(art: AdaptArtefact) -> dict:
    sl = slice(1, None) if len(art.frames) > 2 else slice(None)
    med = lambda a: float(np.median(a[sl]))  # noqa: E731
    return {"forward_s": med(art.time_forward_s), "backward_s": med(art.time_backward_s),
            "render_s": med(art.time_render_s), "total_s": med(art.time_total_s)}


def case_row(name: str, art: AdaptArtefact, ev: dict, r: int = 0, cameras: int = 0, **extra) -> dict:
    dofs = 3 * art.positions.shape[1]
    row = {"name": name, "space": art.space, "mode": art.mode, "loss": art.loss_kind, "dofs": dofs, "r": r,
           "w": art.window, "cameras": cameras, **times(art),
           "young_final": art.young[-1].tolist(), "young_rel_error_final": ev["young_rel_error_final"],
           "young_rel_error_median": ev["young_rel_error_median"], "vertex_error_mean_m": ev["vertex_error_mean_m"],
           "vertex_error_rel_mean": ev["vertex_error_rel_mean"], "psnr_mean": ev["psnr_mean"]}
    row.update(extra)
    return row


def settle_frames(young: np.ndarray, truth: np.ndarray, steps: list[int], tol: float = 0.05) -> list[int | None]:
    """Per step frame s: frames after s until |E − E_true|/E_true ≤ tol holds up to the next step (None: never)."""
    out = []
    bounds = steps + [len(young)]
    for s, e in zip(steps, bounds[1:]):
        ok = np.abs(young[s:e] - truth[s:e]) / truth[s:e] <= tol
        k = None
        for i in range(len(ok)):
            if ok[i:].all():
                k = i
                break
        out.append(k)
    return out


def plot_young(path: Path, title: str, series: dict, truth: np.ndarray | None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.6))
    for label, (frames, y) in series.items():
        ax.plot(frames, y, label=label)
    if truth is not None:
        ax.plot(np.arange(len(truth)), truth, "k--", label="truth")
    ax.set_yscale("log")
    ax.set_xlabel("frame")
    ax.set_ylabel("E (Pa)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# =========================================================================== cases
def case_step(work: Path, quick: bool) -> list[dict]:
    cap, ws = make_capture(work, "step", BEAM, "cable", frames=60, young=1e4, young_schedule="1e4@0,2e4@20,4e4@40")
    truth = np.repeat([1e4, 2e4, 4e4], 20)
    rows, series = [], {}
    w = 5
    for mode, kw in (("online", {}), ("offline", {"offline_iters": 15 if quick else 30, "lr": 0.2})):
        art, ev = run_adapt(cap, ws, work / "step" / f"{mode}", space="full", loss="markers", mode=mode, window=w,
                            young_init=2.5e3, **kw)
        series[f"{mode} (markers, full)"] = (art.frames, art.young[:, 0])
        extra = {"settle_frames": settle_frames(art.young[:, 0], truth, [0, 20, 40])} if mode == "online" else {}
        rows.append(case_row(f"step 10→20→40 kPa, {mode}", art, ev, cameras=0, **extra))
    on, off = rows
    on["offline_over_online_vertex_error"] = off["vertex_error_mean_m"] / on["vertex_error_mean_m"]
    plot_young(RESULTS / "adapt_step.png", "Step-wise E(t): online vs offline (markers, full space, w=5)",
               series, truth)
    return rows


def case_markers_vs_vision(work: Path, quick: bool) -> list[dict]:
    cap, ws = make_capture(work, "dino", DINO, "push", frames=40, cameras=2, resolution=64, young=1e5, markers=40)
    with_gaussians(cap, ws, 2000, 60 if quick else 150)
    rows, series = [], {}
    for loss in ("markers", "vision"):
        art, ev = run_adapt(cap, ws, work / "dino" / loss, space="full", loss=loss, window=3, young_init=2.5e4)
        series[loss] = (art.frames, art.young[:, 0])
        rows.append(case_row(f"dinosaur push, {loss}", art, ev, cameras=2 if loss == "vision" else 0))
    plot_young(RESULTS / "adapt_markers_vs_vision.png", "Dinosaur: 40 markers vs images (2 cameras, 64²)",
               series, np.full(40, 1e5))
    return rows


def case_regions(work: Path, quick: bool) -> list[dict]:
    cap, ws = make_capture(work, "regions", BEAM, "cable", frames=40, young=1e5, region="stiff=3e5@x>0.5")
    rows, series = [], {}
    for label, fit in (("ν fitted", True), ("ν fixed", False)):
        art, ev = run_adapt(cap, ws, work / "regions" / f"online_{'fit' if fit else 'fixed'}", space="full",
                            loss="markers", window=5, young_init=3e4, fit_poisson=fit)
        per_region = {r: float(np.median(np.abs(np.array(v[-8:])))) for r, v in ev["young_rel_error_per_region"].items()}
        series.update({f"{r} ({label})": (art.frames, art.young[:, k]) for k, r in enumerate(art.region_names)})
        rows.append(case_row(f"two regions (E ×3), {label}", art, ev, young_rel_error_last8_per_region=per_region,
                             regions=art.region_names))
    plot_young(RESULTS / "adapt_regions.png", "Two regions (E 1e5 / 3e5 Pa), markers, full space", series, None)
    return rows


def case_ablation(work: Path, quick: bool) -> list[dict]:
    cap, ws = make_capture(work, "step", BEAM, "cable", frames=60, young=1e4, young_schedule="1e4@0,2e4@20,4e4@40")
    rows = []
    for w in ((1, 5) if quick else (1, 3, 5, 10)):
        art, ev = run_adapt(cap, ws, work / "step" / f"w{w}", space="full", loss="markers", window=w, young_init=2.5e3)
        rows.append(case_row(f"ablation w={w}", art, ev))
    for r in ((4, 16) if quick else (4, 8, 16)):
        ws_r = subspace_ws(cap, ws, r, "pca", sequences=4, frames=60)
        art, ev = run_adapt(cap, ws_r, work / "step" / f"r{r}", space="reduced", loss="markers", window=5,
                            young_init=2.5e3)
        rows.append(case_row(f"ablation r={r} (PCA)", art, ev, r=r))
    return rows


def case_timing(work: Path, quick: bool) -> list[dict]:
    import meshio

    from stages.sim.meshgen import box_tets

    mesh = work / "box.mesh"
    if not mesh.exists():
        cells = (24, 6, 6) if quick else (36, 8, 8)
        v, t = box_tets(cells, (0.25, 0.25 * cells[1] / cells[0], 0.25 * cells[2] / cells[0]))
        meshio.write(str(mesh), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    frames = 10
    cap, ws = make_capture(work, "timing", mesh, "twist", frames=frames, cameras=4, resolution=128, young=1e5,
                           markers=0)
    with_gaussians(cap, ws, 5000, 20)
    ws_r = subspace_ws(cap, ws, 30, "pca", sequences=8, frames=frames)
    rows = []
    n_adapt = 4 if quick else 6
    # The machine is shared: each variant runs twice, alternating, and the run with the lower median
    # total per frame is kept (best of 2).
    runs: dict[str, list] = {"reduced": [], "full": []}
    for _ in range(2):
        runs["reduced"].append(run_adapt(cap, ws_r, work / "timing" / "reduced", space="reduced", loss="vision",
                                         window=3, iters_per_frame=1, frames=f"0:{n_adapt}"))
        runs["full"].append(run_adapt(cap, ws, work / "timing" / "full", space="full", loss="vision", window=3,
                                      iters_per_frame=1, frames=f"0:{min(n_adapt, 4)}"))
    red, ev_r = min(runs["reduced"], key=lambda a: times(a[0])["total_s"])
    full, ev_f = min(runs["full"], key=lambda a: times(a[0])["total_s"])
    rows.append(case_row("bar-like, reduced", red, ev_r, r=30, cameras=4, runs=2))
    rows.append(case_row("bar-like, full", full, ev_f, cameras=4, runs=2))
    tr, tf = times(red), times(full)
    rows[0]["physics_speedup"] = (tf["forward_s"] + tf["backward_s"]) / (tr["forward_s"] + tr["backward_s"])
    rows[0]["total_speedup"] = tf["total_s"] / tr["total_s"]
    return rows


def case_refine(work: Path, quick: bool) -> list[dict]:
    """DESIGN §5: E identified on a coarse linear-tet mesh is an effective value; --refine shrinks the gap.
    Truth: a box of 24×6×6 cells (5184 tets); workspace: the same box with 8×2×2 cells (192 tets; its first
    cell as thin as the fine one, so both are clamped over the same slab), and the same with --refine 1."""
    import meshio

    from stages.sim.meshgen import box_tets

    fine = work / "box_fine.mesh"
    if not fine.exists():
        v, t = box_tets((24, 6, 6), (0.24, 0.06, 0.06))
        meshio.write(str(fine), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    cap, _ = make_capture(work, "refine", fine, "cable", frames=40, young=1e5)
    cap_c = work / "refine" / "cap_coarse"
    if not cap_c.exists():
        shutil.copytree(cap, cap_c)
        tv = meshio.read(cap / "truth" / "object.mesh").points
        lo, hi = tv.min(0), tv.max(0)
        v, t = box_tets((8, 2, 2), tuple(hi - lo), tuple(lo))
        # the clamp holds the vertices within 8 % of the length from the end: give the coarse box the fine
        # box's second x layer, so that both meshes are clamped over the same slab
        fine_x = np.unique(np.round(tv[:, 0], 9))
        levels = np.linspace(lo[0], hi[0], 9)
        target = np.concatenate([[lo[0], fine_x[1]], np.linspace(fine_x[1], hi[0], 8)[1:]])
        v[:, 0] = np.interp(v[:, 0], levels, target)
        meshio.write(str(cap_c / "coarse.mesh"), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
        toml = cap_c / "capture.toml"
        toml.write_text(toml.read_text().replace('mesh = "truth/object.mesh"', 'mesh = "coarse.mesh"'))
        # the cable load selects vertex ids of the fine mesh: move it to the nearest coarse vertices
        ctl = json.loads((cap_c / "controls.json").read_text())
        for ld in ctl["loads"]:
            ids = ld["select"].get("ids")
            if ids is not None:
                near = np.argmin(np.linalg.norm(tv[ids][:, None] - v[None], axis=2), axis=1)
                ld["select"]["ids"] = sorted({int(i) for i in near})
        (cap_c / "controls.json").write_text(json.dumps(ctl))
    ws_c = work / "refine" / "ws_coarse"
    if not (ws_c / "mesh.h5").exists():
        tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap_c, workspace=ws_c), LOG)
    rows = []
    for level in (0, 1):
        art, ev = run_adapt(cap_c, ws_c, work / "refine" / f"refine{level}", space="full", loss="markers",
                            window=5, young_init=2.5e4, fit_poisson=False, refine=level)
        rows.append(case_row(f"coarse 8×2×2 box, refine {level} ({192 * 8 ** level} tets)", art, ev,
                             young_over_truth_last8=float(np.median(art.young[-8:, 0]) / 1e5)))
    return rows


def case_markers_vs_vision_noisy(work: Path, quick: bool) -> list[dict]:
    """Experiment 2 made fair: 40 markers with motion-capture noise (std 0, 2 and 5 mm, `rsl synth
    --marker-noise`) vs images from 4 cameras at 96² and at 128² (same simulation, same seed: one truth
    surface). vertex_error_last_half_m: mean vertex error over the second half of the frames (after the
    estimate has moved away from its 4×-too-soft start)."""
    def last_half(ev: dict) -> float:
        v = np.asarray(ev["vertex_error_per_frame_m"])
        return float(v[len(v) // 2:].mean())

    rows, series = [], {}
    for mn in (0.0, 0.002, 0.005):
        name = f"dino_mn{int(round(mn * 1000))}mm"
        cap, ws = make_capture(work, name, DINO, "push", frames=40, cameras=1, resolution=32, young=1e5,
                               markers=40, marker_noise=mn)
        art, ev = run_adapt(cap, ws, work / name / "markers", space="full", loss="markers", window=3,
                            young_init=2.5e4)
        series[f"40 markers, noise {mn * 1000:g} mm"] = (art.frames, art.young[:, 0])
        rows.append(case_row(f"dinosaur push, markers σ={mn * 1000:g} mm", art, ev, marker_noise_m=mn,
                             vertex_error_last_half_m=last_half(ev)))
    for res, n_g, iters in ((96, 2000, 60 if quick else 120), (128, 2000, 60 if quick else 150),
                            (128, 4000, 100 if quick else 250)):
        name = f"dino_4cam{res}"
        label = f"dinosaur push, vision 4×{res}², {n_g} Gaussians"
        cap, ws = make_capture(work, name, DINO, "push", frames=40, cameras=4, resolution=res, young=1e5,
                               markers=40)
        ws_g = ws.parent / f"ws_g{n_g}"
        if not ws_g.exists():
            shutil.copytree(ws, ws_g)
        with_gaussians(cap, ws_g, n_g, iters)
        try:
            art, ev = run_adapt(cap, ws_g, work / name / f"vision_g{n_g}", space="full", loss="vision", window=3,
                                young_init=2.5e4)
        except Exception as e:  # a variant that fails is reported, not hidden
            rows.append({"name": label, "space": "full", "mode": "online", "loss": "vision", "cameras": 4,
                         "gaussians": n_g, "failed": f"{type(e).__name__}: {e}"})
            print(f"  failed: {rows[-1]['failed']}", flush=True)
            continue
        series[f"vision, 4 cameras {res}², {n_g} G"] = (art.frames, art.young[:, 0])
        rows.append(case_row(label, art, ev, cameras=4, gaussians=n_g, vertex_error_last_half_m=last_half(ev)))
    plot_young(RESULTS / "adapt_markers_vs_vision_noisy.png",
               "Dinosaur: markers (0, 2, 5 mm noise) vs images (4 cameras, 96² / 128²)", series, np.full(40, 1e5))
    return rows


def loss_sweep(cap: Path, ws: Path, loss: str, factors: list[float], ends=(10, 20, 30), **obs_kw) -> dict:
    """The window loss L(θ) (w = 3, ν = 0.45) at E = f·E_true for f in ``factors``, the two states before each
    window taken from the truth simulation (E_true), the observation anchored as rsl adapt does (markers bound
    to, Gaussians re-bound to / offset by frame 0 simulated with the swept θ); per window
    end: losses, dL/dlog E, and the argmin of a parabola through the three grid points around the smallest."""
    from stages.parameters import params_from_theta
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture
    from stages.sim.scene import frame_inputs, make_scene, simulate

    capture = load_capture(cap)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    controls = capture.controls()
    scene = make_scene(mesh, controls, capture.material.model, capture.dt, capture.gravity)
    T = max(ends) + 1
    inputs = [frame_inputs(scene, controls, t) for t in range(T)]
    X = np.asarray(simulate(scene, inputs, np.full((T, 1), 1e5), np.full((T, 1), 0.45)))
    backend = adapt.FullSpace(scene, lambda t: inputs[t], "auto")
    prange = capture.material.poisson_range
    if loss == "markers":
        obs = adapt.MarkerObservation(capture, X[0], mesh.surface_faces, mesh.n_vertices)
    else:
        obs = adapt.VisionObservation(capture, ws, "", mesh, False, **obs_kw)
    objective = adapt.WindowObjective(backend, obs, 1, prange)
    out = {"factors": list(factors)}
    for t in ends:
        frames = [t - 2, t - 1, t]
        before = np.stack([X[t - 4], X[t - 3]])
        ls, gs = [], []
        for f in factors:
            p = np.concatenate(params_from_theta(np.array([1e5 * f]), np.array([0.45]), prange))
            _, losses, g, _ = objective(frames, p, before, True)
            ls.append(float(losses.sum()))
            gs.append(float(g[0]))
        k = int(np.clip(np.argmin(ls), 1, len(ls) - 2))
        lf = np.log(factors[k - 1:k + 2])
        c = np.polyfit(lf, ls[k - 1:k + 2], 2)
        arg = float(np.exp(-c[1] / (2 * c[0]))) if c[0] > 0 else float(factors[int(np.argmin(ls))])
        out[str(t)] = {"loss": ls, "dL_dlogE": gs, "argmin_E_over_true": arg}
    return out


def case_markers_vs_vision_rebind(work: Path, quick: bool) -> list[dict]:
    """Experiment 2 after the fix of the Gaussians' anchor (stages.render.image_loss.ImageLoss.rebind): the same
    captures as markers_vs_vision_noisy, markers (0 / 2 / 5 mm noise) and vision rerun in one run; vision with
    the re-bound Gaussians (default) and with the first-order offset anchor of before, with and without
    appearance refinement; and L(E) sweeps showing where each loss has its minimum."""
    def last_half(ev: dict) -> float:
        v = np.asarray(ev["vertex_error_per_frame_m"])
        return float(v[len(v) // 2:].mean())

    factors = [0.7, 0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.25]
    rows, series, verr, sweeps = [], {}, {}, {}
    for mn in (0.0, 0.002, 0.005):
        name = f"dino_mn{int(round(mn * 1000))}mm"
        cap, ws = make_capture(work, name, DINO, "push", frames=40, cameras=1, resolution=32, young=1e5,
                               markers=40, marker_noise=mn)
        art, ev = run_adapt(cap, ws, work / name / "markers_r", space="full", loss="markers", window=3,
                            young_init=2.5e4)
        lab = f"markers σ={mn * 1000:g} mm"
        series[lab], verr[lab] = (art.frames, art.young[:, 0]), ev["vertex_error_per_frame_m"]
        extra = {}
        if mn in (0.0, 0.005):
            sweeps[lab] = extra["loss_sweep"] = loss_sweep(cap, ws, "markers", factors)
        rows.append(case_row(f"dinosaur push (rerun), {lab}", art, ev, marker_noise_m=mn,
                             vertex_error_last_half_m=last_half(ev), **extra))
    variants = [(96, 2000, "rebind", False), (96, 2000, "offset", False), (96, 2000, "rebind", True),
                (128, 2000, "rebind", False), (128, 4000, "rebind", False)]
    if quick:
        variants = variants[:2]
    for res, n_g, anchor, appearance in variants:
        name = f"dino_4cam{res}"
        lab = f"vision 4×{res}², {n_g} G, {anchor}" + (", appearance" if appearance else "")
        label = f"dinosaur push (rerun), {lab}"
        cap, ws = make_capture(work, name, DINO, "push", frames=40, cameras=4, resolution=res, young=1e5,
                               markers=40)
        ws_g = ws.parent / f"ws_g{n_g}"
        if not ws_g.exists():
            shutil.copytree(ws, ws_g)
        with_gaussians(cap, ws_g, n_g, {2000: 120 if res == 96 else 150, 4000: 250}[n_g])
        extra = {}
        if res == 96 and n_g == 2000 and not appearance:
            sweeps[lab] = extra["loss_sweep"] = loss_sweep(cap, ws_g, "vision", factors, anchor=anchor)
        out = work / name / f"vision_g{n_g}_{anchor}{'_app' if appearance else ''}"
        try:
            art, ev = run_adapt(cap, ws_g, out, space="full", loss="vision", window=3, young_init=2.5e4,
                                gaussian_anchor=anchor, appearance=appearance)
        except Exception as e:  # a variant that fails is reported, not hidden
            rows.append({"name": label, "space": "full", "mode": "online", "loss": "vision", "cameras": 4,
                         "gaussians": n_g, "gaussian_anchor": anchor, "appearance": appearance,
                         "failed": f"{type(e).__name__}: {e}", **extra})
            print(f"  failed: {rows[-1]['failed']}", flush=True)
            continue
        series[lab], verr[lab] = (art.frames, art.young[:, 0]), ev["vertex_error_per_frame_m"]
        rows.append(case_row(label, art, ev, cameras=4, gaussians=n_g, gaussian_anchor=anchor,
                             appearance=appearance, vertex_error_last_half_m=last_half(ev), **extra))
    plot_e_and_surface(RESULTS / "adapt_markers_vs_vision_rebind.png", series, verr,
                       lambda lab: "--" if "offset" in lab else "-", sweeps)
    return rows


def case_markers_vs_vision_rebind_steps(work: Path, quick: bool) -> list[dict]:
    """Adam steps per frame for the vision loss after the anchor fix: 1 and 4 steps per frame (the other cases
    use 2) on the 4×96² dinosaur, 2000 Gaussians, re-bound anchor, w = 3, lr 0.15."""
    def last_half(ev: dict) -> float:
        v = np.asarray(ev["vertex_error_per_frame_m"])
        return float(v[len(v) // 2:].mean())

    cap, ws = make_capture(work, "dino_4cam96", DINO, "push", frames=40, cameras=4, resolution=96, young=1e5,
                           markers=40)
    ws_g = ws.parent / "ws_g2000"
    if not ws_g.exists():
        shutil.copytree(ws, ws_g)
    with_gaussians(cap, ws_g, 2000, 120)
    rows = []
    for iters in ((4,) if quick else (1, 4)):
        art, ev = run_adapt(cap, ws_g, work / "dino_4cam96" / f"vision_g2000_rebind_it{iters}", space="full",
                            loss="vision", window=3, young_init=2.5e4, iters_per_frame=iters)
        rows.append(case_row(f"dinosaur push (rerun), vision 4×96², 2000 G, rebind, {iters} Adam steps/frame", art,
                             ev, cameras=4, gaussians=2000, gaussian_anchor="rebind", iters_per_frame=iters,
                             vertex_error_last_half_m=last_half(ev)))
    return rows


def case_markers_visibility(work: Path, quick: bool) -> list[dict]:
    """Markers with occlusion gaps (rsl synth --marker-visibility 2: a marker is written at a frame only when
    at least 2 of the 4 cameras at 96² see it; markers not seen at frame 0 are left out) on the dinosaur push of
    markers_vs_vision_rebind (same simulation, same 40 marker positions, same seed), without and with 2 mm noise;
    adapted online as there.  The plot adds that case's all-visible markers and 4×96² vision runs from their
    adapt.h5 / evaluation.json in the work folder, when present."""
    from stages.capture import read_markers

    def last_half(ev: dict) -> float:
        v = np.asarray(ev["vertex_error_per_frame_m"])
        return float(v[len(v) // 2:].mean())

    rows, series, verr = [], {}, {}
    need = 2
    for mn in ((0.0,) if quick else (0.0, 0.002)):
        name = f"dino_vis{need}_mn{int(round(mn * 1000))}mm"
        cap, ws = make_capture(work, name, DINO, "push", frames=40, cameras=4, resolution=96, young=1e5,
                               markers=40, marker_noise=mn, marker_visibility=need)
        P = read_markers(cap / "markers.csv")
        seen = np.isfinite(P[..., 0])
        total = P.shape[0] * 40  # observations of the 40 markers placed
        art, ev = run_adapt(cap, ws, work / name / "markers", space="full", loss="markers", window=3,
                            young_init=2.5e4)
        lab = f"markers σ={mn * 1000:g} mm, seen by ≥{need} of 4 cameras"
        series[lab], verr[lab] = (art.frames, art.young[:, 0]), ev["vertex_error_per_frame_m"]
        rows.append(case_row(f"dinosaur push, {lab}", art, ev, marker_noise_m=mn, marker_visibility=need,
                             markers_placed=40, markers_kept=int(P.shape[1]),
                             observed_fraction=float(seen.sum() / total),
                             observed_fraction_of_kept=float(seen.mean()),
                             frames_without_markers=int(np.sum(~seen.any(axis=1))),
                             markers_per_frame_min=int(seen.sum(axis=1).min()),
                             vertex_error_last_half_m=last_half(ev)))
    for lab, sub in (("markers σ=0 mm, all seen (rebind case)", "dino_mn0mm/markers_r"),
                     ("markers σ=2 mm, all seen (rebind case)", "dino_mn2mm/markers_r"),
                     ("vision 4×96², 2000 G, rebind (rebind case)", "dino_4cam96/vision_g2000_rebind")):
        d = work / sub
        if (d / "adapt.h5").exists() and (d / "evaluation.json").exists():
            a = AdaptArtefact.load(d / "adapt.h5")
            series[lab] = (a.frames, a.young[:, 0])
            verr[lab] = json.loads((d / "evaluation.json").read_text())["vertex_error_per_frame_m"]
    plot_e_and_surface(RESULTS / "adapt_markers_visibility.png", series, verr,
                       lambda lab: "-" if "seen by" in lab else ":")
    return rows


def plot_e_and_surface(path: Path, series: dict, verr: dict, line_style, sweeps: dict | None = None) -> None:
    """E(t) and the surface error per frame (``line_style(label)`` gives each series' matplotlib style), plus
    with ``sweeps`` the normalised window loss L(E)/L(E_true) at the window ending at frame 20."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3 if sweeps else 2, figsize=(15 if sweeps else 11, 4))
    for lab, (fr, y) in series.items():
        ls = line_style(lab)
        ax[0].plot(fr, y / 1e5, ls, label=lab)
        ax[1].plot(np.arange(len(verr[lab])), np.asarray(verr[lab]) * 1e3, ls, label=lab)
    ax[0].axhline(1.0, color="k", lw=0.8)
    ax[0].set_ylim(0.2, 1.4)
    ax[0].set_xlabel("frame")
    ax[0].set_ylabel("E / E_true")
    ax[0].set_title("E(t), started at E_true / 4")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("frame")
    ax[1].set_ylabel("surface error vs truth (mm)")
    ax[1].set_title("symmetric surface distance")
    for lab, sw in (sweeps or {}).items():
        L = np.asarray(sw["20"]["loss"])
        i1 = sw["factors"].index(1.0)
        ax[2].plot(sw["factors"], L / L[i1] if L[i1] > 1e-12 else L / L.max(), "o-", label=lab)
    if sweeps:
        ax[2].axvline(1.0, color="k", lw=0.8)
        ax[2].set_xlabel("E / E_true")
        ax[2].set_ylabel("L(E) / L(E_true)  (markers σ=0: / max)")
        ax[2].set_title("window loss, frames 18–20")
    for a in ax:
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def case_regions_nu(work: Path, quick: bool) -> list[dict]:
    """Two regions with ν fitted: do more frames, more Adam steps per frame or a smaller ν learning rate get
    both regions within 10 %?"""
    rows, series = [], {}
    variants = [("40 frames, 4 iters/frame", 40, {"iters_per_frame": 4}),
                ("40 frames, lr_ν 0.01", 40, {"lr_poisson": 0.01}),
                ("40 frames, 4 iters/frame, lr_ν 0.01", 40, {"iters_per_frame": 4, "lr_poisson": 0.01}),
                ("80 frames", 80, {}),
                ("80 frames, lr_ν 0.01", 80, {"lr_poisson": 0.01}),
                ("80 frames, 4 iters/frame, lr_ν 0.01", 80, {"iters_per_frame": 4, "lr_poisson": 0.01}),
                ("40 frames, ν₀ 0.40", 40, {"poisson_init": 0.40}),
                ("40 frames, lr_ν 0.01, ν₀ 0.40", 40, {"lr_poisson": 0.01, "poisson_init": 0.40})]
    for k, (label, frames, kw) in enumerate(variants):
        name = "regions" if frames == 40 else f"regions{frames}"
        cap, ws = make_capture(work, name, BEAM, "cable", frames=frames, young=1e5, region="stiff=3e5@x>0.5")
        art, ev = run_adapt(cap, ws, work / name / f"nu{k}", space="full", loss="markers", window=5,
                            young_init=3e4, fit_poisson=True, **kw)
        per_region = {r: float(np.median(np.abs(np.array(v[-8:])))) for r, v in ev["young_rel_error_per_region"].items()}
        final = {r: float(abs(v[-1])) for r, v in ev["young_rel_error_per_region"].items()}
        worst = {r: float(np.abs(np.array(v[len(v) // 2:])).max()) for r, v in ev["young_rel_error_per_region"].items()}
        series.update({f"{r} ({label})": (art.frames, art.young[:, j]) for j, r in enumerate(art.region_names)})
        rows.append(case_row(f"two regions (E ×3), ν fitted, {label}", art, ev,
                             young_rel_error_last8_per_region=per_region, regions=art.region_names,
                             poisson_final=art.poisson[-1].tolist() if hasattr(art, "poisson") else None,
                             young_rel_error_final_per_region=final, young_rel_error_max_second_half=worst,
                             settings=kw, frames_total=frames))
    plot_young(RESULTS / "adapt_regions_nu.png", "Two regions, ν fitted: frames / iterations / lr_ν", series, None)
    return rows


def case_ablation_w9(work: Path, quick: bool) -> list[dict]:
    """Window w = 9 (issue 7 experiment 4 asks for w ∈ {1, 3, 5, 9}); same settings as the ablation case."""
    cap, ws = make_capture(work, "step", BEAM, "cable", frames=60, young=1e4, young_schedule="1e4@0,2e4@20,4e4@40")
    art, ev = run_adapt(cap, ws, work / "step" / "w9", space="full", loss="markers", window=9, young_init=2.5e3)
    return [case_row("ablation w=9", art, ev)]


def case_ablation_r(work: Path, quick: bool) -> list[dict]:
    """Subspace dimension r ∈ {10, 30, 60, 90, 120} with the autoencoder subspace (few epochs), online, reduced
    space, markers, w = 5, on the step capture. The snapshots are the ablation case's (4 sequences × 60 frames,
    3 for training = 180 snapshots); the autoencoder's PCA layer is capped at 170 modes (the default
    max(2r, r + 20) would exceed the 180 training snapshots for r ≥ 90)."""
    cap, ws = make_capture(work, "step", BEAM, "cable", frames=60, young=1e4, young_schedule="1e4@0,2e4@20,4e4@40")
    rows = []
    epochs = 40
    for r in ((10, 60) if quick else (10, 30, 60, 90, 120)):
        ws_r = ws.parent / f"ws_autoencoder{r}"
        if not (ws_r / "subspace.h5").exists():
            ws_r.mkdir(exist_ok=True)
            for f in ("mesh.h5", "cameras.h5"):
                if (ws / f).exists():
                    shutil.copy(ws / f, ws_r / f)
            subspace_ws(cap, ws, 4, "pca", sequences=4, frames=60)  # makes step/snapshots.h5 if missing
            shutil.copy(ws.parent / "snapshots.h5", ws_r / "snapshots.h5")
            t0 = time.time()
            train_subspace.run(train_subspace.TrainSubspaceConfig(
                workspace=ws_r, capture=cap, dim=r, kind="autoencoder", epochs=epochs,
                pca_dim=min(max(2 * r, r + 20), 170)), LOG)
            (ws_r / "train_s.txt").write_text(f"{time.time() - t0:.1f}")
        train_s = float((ws_r / "train_s.txt").read_text()) if (ws_r / "train_s.txt").exists() else None
        art, ev = run_adapt(cap, ws_r, work / "step" / f"ae{r}", space="reduced", loss="markers", window=5,
                            young_init=2.5e3)
        rows.append(case_row(f"ablation r={r} (AE)", art, ev, r=r, epochs=epochs, train_s=train_s))
    return rows


def case_ablation_c(work: Path, quick: bool) -> list[dict]:
    """Cameras c ∈ {1, 2, 4, 8} with the vision loss: one 8-camera capture (beam pulled by a cable, constant
    E = 1e5 Pa, 64² images, 1000 Gaussians), full space, w = 3, 40 frames, started at E_true / 4; c = 1, 2, 4
    use the first c cameras."""
    cap, ws = make_capture(work, "cams8_40", BEAM, "cable", frames=40, cameras=8, resolution=64, young=1e5)
    with_gaussians(cap, ws, 1000, 60)
    rows = []
    for c in ((1, 8) if quick else (1, 2, 4, 8)):
        art, ev = run_adapt(cap, ws, work / "cams8_40" / f"c{c}", space="full", loss="vision", window=3,
                            young_init=2.5e4, cameras=",".join(str(k) for k in range(c)))
        rows.append(case_row(f"ablation c={c} (vision)", art, ev, cameras=c))
    return rows


def plot_ablation(rows: list[dict]) -> None:
    """docs/results/adapt_ablation.png: E error (median) and time per frame vs w, r and c."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = [("window w (markers, full)", [r for r in rows if r["name"].startswith("ablation w=")], "w"),
              ("subspace dim r (markers, reduced)", [r for r in rows if r["name"].startswith("ablation r=")], "r"),
              ("cameras c (vision, full)", [r for r in rows if r["name"].startswith("ablation c=")], "cameras")]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6))
    for j, (title, rs, key) in enumerate(groups):
        series = {}
        for r in rs:
            if r.get("failed"):
                continue
            lab = "AE" if "(AE)" in r["name"] else "PCA" if "(PCA)" in r["name"] else "vision" if key == "cameras" \
                else "markers"
            series.setdefault(lab, []).append((r[key], r["young_rel_error_median"], r["total_s"], r.get("render_s")))
        for lab, pts in series.items():
            pts.sort()
            x = [p[0] for p in pts]
            axes[0, j].plot(x, [p[1] for p in pts], "o-", label=lab)
            axes[1, j].plot(x, [p[2] for p in pts], "o-", label=f"{lab} total")
            if key == "cameras":
                axes[1, j].plot(x, [p[3] for p in pts], "s--", label=f"{lab} render")
        axes[0, j].set_title(title)
        axes[0, j].set_ylabel("median |E error| (rel.)")
        axes[0, j].set_yscale("log")
        axes[1, j].set_ylabel("s / frame")
        axes[1, j].set_xlabel(key)
        for a in axes[:, j]:
            if series:
                a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(RESULTS / "adapt_ablation.png", dpi=100)
    plt.close(fig)


CASES = {"refine": case_refine, "step": case_step, "markers_vs_vision": case_markers_vs_vision, "regions": case_regions,
         "ablation": case_ablation, "timing": case_timing,
         "markers_vs_vision_noisy": case_markers_vs_vision_noisy, "regions_nu": case_regions_nu,
         "markers_vs_vision_rebind": case_markers_vs_vision_rebind,
         "markers_vs_vision_rebind_steps": case_markers_vs_vision_rebind_steps,
         "markers_visibility": case_markers_visibility,
         "ablation_w9": case_ablation_w9, "ablation_r": case_ablation_r, "ablation_c": case_ablation_c}


# =========================================================================== report
def fmt(v) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, list):
        return "[" + ", ".join(fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return ", ".join(f"{k} {fmt(x)}" for k, x in v.items())
    return str(v)


def table(rows: list[dict]) -> str:
    cols = ["name", "space", "mode", "loss", "dofs", "r", "w", "cameras", "forward_s", "backward_s", "render_s",
            "total_s", "young_rel_error_final", "vertex_error_mean_m", "psnr_mean"]
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        out.append("| " + " | ".join(fmt(r.get(c)) for c in cols) + " |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", "--only", default=",".join(CASES),
                    help="Comma-separated cases to run; the other cases' rows are kept from adapt.json.")
    ap.add_argument("--work", default="/tmp/rsl_bench_adapt", help="Folder for captures and workspaces (reused).")
    ap.add_argument("--quick", action="store_true", help="Fewer iterations and variants.")
    ap.add_argument("--report-only", action="store_true", help="Rewrite adapt.md from adapt.json; run nothing.")
    args = ap.parse_args()
    if args.report_only:
        data = json.loads((RESULTS / "adapt.json").read_text())
        (RESULTS / "adapt.md").write_text(_markdown(data))
        print(table(data["cases"]))
        return
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / "adapt.json"
    previous = json.loads(json_path.read_text()).get("cases", []) if json_path.exists() else []
    rows: list[dict] = []
    failed: dict[str, str] = {}
    ran = [c.strip() for c in args.cases.split(",") if c.strip()]
    for name in ran:
        print(f"== {name}", flush=True)
        t0 = time.time()
        try:
            new = CASES[name](work, args.quick)
        except Exception as e:  # record and go on with the other cases
            failed[name] = f"{type(e).__name__}: {e}"
            print(f"  failed: {failed[name]}", flush=True)
            continue
        for r in new:
            r["case"] = name
        rows += new
        print(table(new), flush=True)
        print(f"  ({time.time() - t0:.0f} s)", flush=True)
    # keep earlier results of cases not rerun
    rows = [r for r in previous if r.get("case") not in ran] + rows
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "cases": rows, "failed": failed}
    json_path.write_text(json.dumps(data, indent=1))
    (RESULTS / "adapt.md").write_text(_markdown(data))
    if any(r["name"].startswith("ablation") for r in rows):
        plot_ablation(rows)
    print(table(rows))


def _markdown(data: dict) -> str:
    rows = data["cases"]
    md = ["# rsl adapt — online adaptation experiments", "",
          f"Machine: {data['machine']}; date {data['date']}. Produced by `bench/adapt.py`; times are medians over "
          "the adapted frames in seconds per frame (the first, compiling frame dropped).", "",
          table(rows), ""]
    notes = _results_paragraph(rows)
    md += notes
    if data.get("failed"):
        md += ["", "Cases that failed in the last run:", ""] + [f"- {k}: {v}" for k, v in data["failed"].items()]
    md += ["", "Everything above is generated from the measured rows.  The setup in words and the interpretation "
           "are in the hand-written, dated [adapt_notes.md](adapt_notes.md), which this script does not rewrite."]
    return "\n".join(md) + "\n"


def _results_paragraph(rows: list[dict]) -> list[str]:
    by = {r["name"]: r for r in rows}
    out = ["## Results", ""]
    on = by.get("step 10→20→40 kPa, online")
    if on:
        out.append(f"- **Step-wise E(t)** (beam pulled by a cable, 40 markers, full space, w = 5, started 4× too "
                   f"soft): frames to settle within 5 % after each step: {fmt(on.get('settle_frames'))} "
                   f"(target ≤ w + 10 = 15); offline / online mean surface error = "
                   f"{fmt(on.get('offline_over_online_vertex_error'))} (target ≥ 3). Plot: adapt_step.png.")
    mv, vv = by.get("dinosaur push, markers"), by.get("dinosaur push, vision")
    if mv and vv:
        out.append(f"- **Markers vs vision** (dinosaur pushed by a sphere, 2 cameras at 64², Gaussians placed by the "
                   f"first-order offset anchor, before the fix): final E error markers "
                   f"{fmt(mv['young_rel_error_final'])}, vision {fmt(vv['young_rel_error_final'])}; mean surface "
                   f"error markers {fmt(mv['vertex_error_mean_m'])} m, vision {fmt(vv['vertex_error_mean_m'])} m. "
                   f"Plot: adapt_markers_vs_vision.png.")
    noisy = [r for r in rows if r.get("case") == "markers_vs_vision_noisy"]
    if noisy:
        out.append("- **Markers (noisy) vs vision, before the anchor fix** (the same dinosaur push, same simulation "
                   "and truth surface; 40 markers with Gaussian position noise of std σ per frame and axis, `rsl "
                   "synth --marker-noise`; images from 4 cameras, Gaussians placed by the first-order offset "
                   "anchor; w = 3; started at E_true / 4): " + "; ".join(
                       f"{r['name'][15:]}: failed ({r['failed'].rstrip('.')})" if r.get("failed") else
                       f"{r['name'][15:]}: E error final {fmt(r['young_rel_error_final'])}, median "
                       f"{fmt(r['young_rel_error_median'])}, vertex error vs the truth surface mean "
                       f"{fmt(r['vertex_error_mean_m'])} m (second half {fmt(r.get('vertex_error_last_half_m'))} m)"
                       for r in noisy) + ". Plot: adapt_markers_vs_vision_noisy.png.")
    reb = [r for r in rows if r.get("case") in ("markers_vs_vision_rebind", "markers_vs_vision_rebind_steps")]
    if reb:
        def _one(r: dict) -> str:
            lab = r["name"].split("(rerun), ", 1)[1]
            if r.get("failed"):
                return f"{lab}: failed ({r['failed'].rstrip('.')})"
            return (f"{lab}: E error median {fmt(r['young_rel_error_median'])}, final "
                    f"{fmt(r['young_rel_error_final'])}; surface error mean {fmt(r['vertex_error_mean_m'] * 1e3)} mm, "
                    f"second half {fmt(r['vertex_error_last_half_m'] * 1e3)} mm; {fmt(r['total_s'])} s/frame")
        out.append("- **Markers vs vision, after the anchor fix** (rerun in one run on the same captures as the "
                   "row above; vision with the Gaussians re-bound to the simulated fit frame — `gaussian_anchor = "
                   "rebind`, the new default — or with the old first-order offset; 'appearance': colours and "
                   "opacities refined online; two Adam steps per frame unless the name says otherwise, those rows "
                   "from a separate run): " + "; ".join(_one(r) for r in reb)
                   + ". Plot: adapt_markers_vs_vision_rebind.png.")
        sw = [(r["name"].split("(rerun), ", 1)[1], r["loss_sweep"]) for r in reb if r.get("loss_sweep")]

        def _ratio(s_: dict) -> str:  # L(0.9 E_true) / L(E_true) at the window ending at frame 20
            ls, fs = s_["20"]["loss"], s_["factors"]
            return fmt(ls[fs.index(0.9)] / ls[fs.index(1.0)]) if ls[fs.index(1.0)] > 1e-12 else "∞"
        if sw:
            out.append("- **Where the window loss has its minimum** (L(E) at E = f·E_true, f ∈ "
                       f"{fmt(sw[0][1]['factors'])}, w = 3, ν = 0.45, the two states before the window from the "
                       "truth simulation; argmin of a parabola in log E through the three grid points around the "
                       "smallest, for windows ending at frames 10 / 20 / 30): " + "; ".join(
                           f"{lab}: " + " / ".join(fmt(s_[k]["argmin_E_over_true"]) for k in ("10", "20", "30"))
                           + f" (L(0.9 E_true) / L(E_true) at frame 20: {_ratio(s_)})"
                           for lab, s_ in sw) + ".")
    vis = [r for r in rows if r.get("case") == "markers_visibility"]
    if vis:
        def _vis(r: dict) -> str:
            lab = r["name"].split("push, ", 1)[1]
            if r.get("failed"):
                return f"{lab}: failed ({r['failed'].rstrip('.')})"
            return (f"{lab}: {r['markers_kept']} of {r['markers_placed']} markers seen at frame 0, "
                    f"{fmt(100 * r['observed_fraction'])} % of the {r['markers_placed']} markers' observations "
                    f"written ({fmt(100 * (1 - r['observed_fraction']))} % lost to occlusion), "
                    f"{fmt(100 * r['observed_fraction_of_kept'])} % of the kept markers' observations, at least "
                    f"{r['markers_per_frame_min']} markers per frame; E error median "
                    f"{fmt(r['young_rel_error_median'])}, final {fmt(r['young_rel_error_final'])}; surface error "
                    f"mean {fmt(r['vertex_error_mean_m'] * 1e3)} mm, second half "
                    f"{fmt(r['vertex_error_last_half_m'] * 1e3)} mm; {fmt(r['total_s'])} s/frame")
        out.append("- **Markers with occlusion gaps vs vision** (the dinosaur push of the 'after the anchor fix' bullet, same simulation "
                   "and the same 40 marker positions; `rsl synth --marker-visibility 2`: at each frame a marker is "
                   "written only when at least 2 of the 4 cameras at 96² see it — inside the image and within 1.5 "
                   "pixel footprints of the depth the renderer sees at its pixel — and a marker not seen at frame 0, "
                   "where rsl adapt binds it, is left out; noise added after the visibility test; markers loss over "
                   "the observed (frame, marker) pairs only; online, full space, w = 3, from E_true / 4): "
                   + "; ".join(_vis(r) for r in vis) + ". Plot: adapt_markers_visibility.png (dotted: the "
                   "all-visible markers and the 4×96² vision run of the 'after the anchor fix' bullet).")
    for rg in (r for r in rows if r["name"].startswith("two regions") and r.get("case") == "regions"):
        out.append(f"- **Two regions** (E 1e5 and 3e5 Pa, {rg['name'].split(', ')[-1]}): median error over the last "
                   f"8 frames per region {fmt(rg.get('young_rel_error_last8_per_region'))} (target < 0.10). "
                   f"Plot: adapt_regions.png.")
    nu = [r for r in rows if r.get("case") == "regions_nu"]
    if nu:
        out.append("- **Two regions, ν fitted: frames / iterations / lr_ν** (ν starts at the truth 0.45 unless "
                   "ν₀ says otherwise; per region: median |E error| over the last 8 frames / at the last frame / "
                   "worst over the second half): " + "; ".join(
                       f"{r['name'].split('ν fitted, ', 1)[1]}: " + ", ".join(
                           f"{k} {fmt(r['young_rel_error_last8_per_region'][k])} / "
                           f"{fmt(r['young_rel_error_final_per_region'][k])} / "
                           f"{fmt(r['young_rel_error_max_second_half'][k])}" for k in r["regions"])
                       + f" (ν final {fmt([round(x, 3) for x in r['poisson_final']])})" for r in nu)
                   + ". Plot: adapt_regions_nu.png.")
    def _abl(rs: list[dict], extra=lambda r: "") -> str:
        return "; ".join(f"{r['name'][9:]}: E error median {fmt(r['young_rel_error_median'])}, surface error "
                         f"{fmt(r['vertex_error_mean_m'])} m, {fmt(r['total_s'])} s/frame{extra(r)}" for r in rs)

    abl_w = sorted((r for r in rows if r["name"].startswith("ablation w=")), key=lambda r: r["w"])
    abl_p = sorted((r for r in rows if r["name"].startswith("ablation r=") and "(PCA)" in r["name"]),
                   key=lambda r: r["r"])
    abl_a = sorted((r for r in rows if r["name"].startswith("ablation r=") and "(AE)" in r["name"]),
                   key=lambda r: r["r"])
    abl_c = sorted((r for r in rows if r["name"].startswith("ablation c=")), key=lambda r: r["cameras"])
    if abl_w or abl_p:
        out.append("- **Ablations, window w and PCA r** (step capture, markers, full space for w, reduced space "
                   "with a PCA subspace and w = 5 for r): " + _abl(abl_w + abl_p) + ". Plot: adapt_ablation.png.")
    if abl_a:
        out.append("- **Ablation, subspace dimension r with the autoencoder** (step capture, 60 frames, 40 markers, "
                   "online, reduced space, w = 5, started at E_true / 4; autoencoder trained for "
                   f"{abl_a[0].get('epochs')} epochs on 180 training snapshots — the ablation case's 4 sequences "
                   "× 60 frames, one held out — with its PCA layer max(2r, r + 20) capped at 170 modes, so r = 90 "
                   "and 120 have p = 170 rather than 180 / 240): " + _abl(
                       abl_a, lambda r: f" (forward {fmt(r['forward_s'])}, backward {fmt(r['backward_s'])}"
                                        + (f"; training {fmt(r['train_s'])} s" if r.get("train_s") else "") + ")")
                   + ". Plot: adapt_ablation.png.")
    if abl_c:
        out.append("- **Ablation, cameras c with the vision loss** (one `rsl synth` capture of the beam pulled by "
                   "a cable, 8 cameras at 64², 40 frames, E_true = 1e5 Pa; 1000 Gaussians fitted on all 8 views; "
                   "full space, 291 DOFs, w = 3, started at E_true / 4; c = 1, 2, 4 use cameras 0..c−1 via "
                   "`--cameras`): " + _abl(abl_c, lambda r: f" (render {fmt(r['render_s'])} s, PSNR "
                                                            f"{fmt(r['psnr_mean'])} dB, final E error "
                                                            f"{fmt(r['young_rel_error_final'])})")
                   + ". Plot: adapt_ablation.png.")
    ref = [r for r in rows if r["name"].startswith("coarse 8×2×2 box")]
    if ref:
        out.append("- **Effective E of a coarse mesh** (truth simulated on a 24×6×6-cell box, 5184 tets; adapted "
                   "on an 8×2×2-cell box, ν fixed at the truth): E / E_true over the last 8 frames: " + "; ".join(
                       f"{r['name'][17:]}: {fmt(r.get('young_over_truth_last8'))}" for r in ref)
                   + ".")
    tr, tf = by.get("bar-like, reduced"), by.get("bar-like, full")
    if tr and tf:
        out.append(f"- **Time per frame** (bar-like box, {tr['dofs']} DOFs, r = 30, w = 3, 4 cameras at 128², one "
                   f"Adam step per frame): reduced total {fmt(tr['total_s'])} s (forward {fmt(tr['forward_s'])}, "
                   f"backward {fmt(tr['backward_s'])}, render {fmt(tr['render_s'])}); full total "
                   f"{fmt(tf['total_s'])} s; physics speed-up {fmt(tr.get('physics_speedup'))}×, total "
                   f"{fmt(tr.get('total_speedup'))}× (targets: reduced ≤ 0.5 s/frame, physics ≥ 10×).")
    return out


if __name__ == "__main__":
    main()
