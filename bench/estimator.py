"""Gauss–Newton (moving-horizon, E ± σ) against Adam in `rsl adapt`, on marker captures that are not an inverse crime.

For each scene × seed, `rsl synth` films the shared beam (shared/data Coarse_beam.mesh, a cable pulls its free end)
with a truth on another discretisation than adapt's (quadratic tets on the once-refined mesh, 3 implicit substeps
per frame, hard Dirichlet handles, start = equilibrium) and noisy markers (30, σ 0.2 mm).  rsl adapt runs online in
the full space on the beam's own coarse mesh as quadratic tets at its default substeps per frame (``--adapt-substeps S``
passes another; the value used is read back from adapt.h5's provenance) from E_init = E0/2.
Scenes: the bar with E stepping ×2 and ×4, the bar with constant E, a two-region beam (E ×3 beyond mid-length).
Measured per run: the settled error and the ±3 % band, the frames needed after each step to come and stay within
5 % of the new value, the fraction of settled frames whose truth lies inside ±2σ (gn; E and ν), the change points
detected and the time per frame.  Writes docs/results/estimator.{md,json,png}.  Every step is the `rsl` CLI
through bench/_pipeline.py (synth, tetrahedralize, adapt).  ``--variant LABEL="ADAPT OPTIONS"`` adds a gn row
with those options in the same run (on the same captures), e.g. ``--variant "ν always fitted=--poisson-information 0"``.
``--window-sweep`` instead checks the loss before the estimator: on one capture (two-region beam, seed 1), with and
without its marker noise, where the marker loss of adapt's model at fixed E has its minimum per 3-frame window and
over frames 0 … t, and the offline gn fit of the whole sequence (docs/results/estimator_window_sweep.{md,json}).

    nice .venv/bin/python bench/estimator.py [--seeds 3] [--workers 2] [--scenes ...] [--variant LABEL=OPTIONS]
                                             [--adapt-substeps S]
    nice .venv/bin/python bench/estimator.py --window-sweep [--sweep-scene S --sweep-seed N]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
import _pipeline  # noqa: E402

BEAM = ROOT.parent / "shared" / "data" / "autodef_fulton" / "Coarse_beam.mesh"
OUT = ROOT / "docs" / "results"
E0 = 1.0e5
W = 3


SCENES = {  # name: (synth arguments, frames, step frames)
    "bar steps x2 x4": (["--young-schedule", f"{E0:g}@0,{2 * E0:g}@12,{4 * E0:g}@24"], 36, [12, 24]),
    "bar constant": ([], 24, []),
    "two-region beam": (["--region", f"stiff={3 * E0:g}@x>0.5"], 24, []),
}
TRUTH = ["--truth-order", 2, "--truth-refine", 1, "--substeps", 3, "--handles", "hard", "--start", "equilibrium"]


def make_capture(root: Path, scene: str, seed: int, marker_noise: float = 2e-4):
    """The truth capture and adapt's workspace (the beam's coarse tets as P2); truth E per frame and region."""
    import meshio

    from stages.steps.synth import prepare_mesh

    extra, frames, _ = SCENES[scene]
    cap = root / "cap"
    _pipeline.synth(cap, BEAM, "--scenario", "cable", "--cameras", 1, "--resolution", 32, "--frames", frames,
                    "--young", E0, "--markers", 30, "--marker-noise", marker_noise, "--calib-views", 0, "--seed", seed,
                    *TRUTH, *extra, reuse=False)
    # adapt's mesh: the beam's own tets (placed as synth placed them), not the truth's refined ones
    m = meshio.read(str(BEAM))
    pm = prepare_mesh(np.asarray(m.points, float), np.asarray(m.cells_dict["tetra"]), 0.2, "")
    meshio.write(str(cap / "model.mesh"), meshio.Mesh(pm.vertices, [("tetra", pm.tets)]), file_format="medit")
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "model.mesh"'))
    ws = _pipeline.mesh(cap, root / "ws", order=2, calibrate=False, reuse=False)
    import csv

    rows = list(csv.DictReader((cap / "truth" / "material.csv").open()))
    names = list(dict.fromkeys(r["region"] for r in rows))
    truth = np.array([[float(r["young"]) for r in rows if r["region"] == n] for n in names]).T  # (T, R)
    nu = np.array([[float(r["poisson"]) for r in rows if r["region"] == n] for n in names]).T
    return cap, ws, truth[:frames], nu[:frames], names


def _substeps_option(substeps: int | None) -> list:
    """adapt's --substeps option: none (adapt's default) unless ``substeps`` is given."""
    return [] if substeps is None else ["--substeps", substeps]


def adapt_substeps_used(adapt_h5: Path) -> int | None:
    """The substeps per frame an adapt run used, from adapt.h5's provenance config."""
    from stages.artefacts import read_provenance

    return (read_provenance(adapt_h5).get("config") or {}).get("substeps")


def run_adapt(cap: Path, ws: Path, estimator: str, options=(), substeps: int | None = None):
    from stages.artefacts import AdaptArtefact

    _pipeline.adapt(cap, ws, "--space", "full", "--loss", "markers", "--window", W, "--young-init", E0 / 2,
                    "--estimator", estimator, *_substeps_option(substeps), *options)
    a = AdaptArtefact.load(ws / "adapt.h5")
    return a, list(a.extra.get("region_names", [])) or None


def metrics(E, sd, truth, steps: list[int], nu=None, sd_nu=None, nu_true=None) -> dict:
    """E, sd, truth (T,) of one region."""
    rel = E / truth - 1
    bounds = [0] + steps + [len(E)]
    settle = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        ok = np.abs(rel[a:b]) <= 0.05
        k = next((i for i in range(b - a) if ok[i:].all()), None)  # first frame from which it stays within 5 %
        settle.append(None if k is None else int(k))
    settled = np.zeros(len(E), bool)
    for a, b in zip(bounds[:-1], bounds[1:]):
        settled[min(a + W + 5, b):b] = True
    out = {"settle_frames": settle, "settled_frames": int(settled.sum()),
           "median_abs_err_settled": float(np.median(np.abs(rel[settled]))),
           "max_abs_err_settled": float(np.max(np.abs(rel[settled]))),
           "within_3pct_settled": float(np.mean(np.abs(rel[settled]) <= 0.03))}
    if np.all(np.isfinite(sd[settled])):
        out["truth_within_2sigma"] = float(np.mean(np.abs(E - truth)[settled] <= 2 * sd[settled]))
        out["inside_2sigma"] = int(np.sum(np.abs(E - truth)[settled] <= 2 * sd[settled]))
        out["median_sigma_rel_settled"] = float(np.median((sd / truth)[settled]))
    if nu is not None and sd_nu is not None and np.all(np.isfinite(sd_nu[settled])):
        out["nu_within_2sigma"] = float(np.mean(np.abs(nu - nu_true)[settled] <= 2 * sd_nu[settled]))
        out["nu_median_abs_err_settled"] = float(np.median(np.abs(nu - nu_true)[settled]))
        out["nu_median_sigma_settled"] = float(np.median(sd_nu[settled]))
    return out


def run_case(scene: str, seed: int, with_adam: bool, variants: dict | None = None,
             substeps: int | None = None) -> list[dict]:
    """One capture, gn (and adam, and gn with each variant's extra adapt options), adapt at ``substeps`` per frame
    (None: adapt's default): a row per estimator and region (none, with the error printed, if it failed)."""
    try:
        return _run_case(scene, seed, with_adam, variants or {}, substeps)
    except (Exception, SystemExit) as e:  # one failed case must not lose the others' measurements
        print(f"{scene} seed {seed} FAILED: {type(e).__name__}: {e}", flush=True)
        return []


def _run_case(scene: str, seed: int, with_adam: bool, variants: dict, substeps: int | None) -> list[dict]:
    import time

    _, _, steps = SCENES[scene]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cap, ws, truth, nu_true, names = make_capture(Path(tmp), scene, seed)
        t_synth = time.perf_counter() - t0
        runs = [("gn", "gn", ())] + [(f"gn, {k}", "gn", tuple(v.split())) for k, v in variants.items()]
        runs += [("adam", "adam", ())] if with_adam else []
        for label, est, options in runs:
            t1 = time.perf_counter()
            a, _ = run_adapt(cap, ws, est, options, substeps)
            adapt_wall_s = time.perf_counter() - t1
            used = adapt_substeps_used(ws / "adapt.h5")
            T = len(a.young)
            for r, name in enumerate(names):
                sd = np.asarray(a.young_sigma)[:, r] if a.young_sigma is not None else np.full(T, np.nan)
                sdn = np.asarray(a.poisson_sigma)[:, r] if a.poisson_sigma is not None else np.full(T, np.nan)
                row = {"scene": scene, "seed": seed, "region": name, "estimator": label, "options": list(options),
                       "steps": steps, "synth_s": t_synth, "adapt_substeps": used, "adapt_wall_s": adapt_wall_s,
                       "s_per_frame": float(np.median(a.time_total_s)),
                       "changes_detected": a.extra.get("material_changes_detected", []),
                       "innovation_ratio": a.extra.get("innovation_ratio", []),
                       **metrics(a.young[:, r], sd, truth[:T, r], steps, a.poisson[:, r], sdn, nu_true[:T, r]),
                       "young_rel": (a.young[:, r] / truth[:T, r]).tolist(),
                       "sigma_rel": (sd / truth[:T, r]).tolist(), "poisson": a.poisson[:, r].tolist(),
                       "poisson_sigma": sdn.tolist()}
                floors = a.extra.get("young_model_error")  # gn: the per-region floor in σ_E/E, per frame
                if floors is not None and np.shape(floors) == a.young.shape:
                    row["model_error_floor"] = np.asarray(floors, float)[:, r].tolist()
                rows.append(row)
                print(f"{scene:16} seed {seed} {name:6} {label:4}: settle {row['settle_frames']} "
                      f"med {row['median_abs_err_settled']:.2%} max {row['max_abs_err_settled']:.2%} "
                      f"in2σ {row.get('truth_within_2sigma')} changes {row['changes_detected']} "
                      f"{row['s_per_frame']:.3f} s/frame (S = {used}, adapt {adapt_wall_s:.0f} s)", flush=True)
    return rows


def timing_case(work: Path) -> list[dict]:
    """Per-frame time gn vs adam on bench/adapt.py's bar-like case (a 36×8×8-cell box, ≈9K DOFs, twist, 4 cameras
    at 128², 5000 Gaussians, PCA r = 30, w = 3), images, reduced space, same run."""
    sys.path.insert(0, str(ROOT / "bench"))
    import meshio

    import adapt as bench_adapt  # bench/adapt.py's building blocks
    from stages.sim.meshgen import box_tets

    mesh = work / "box.mesh"
    cells = (36, 8, 8)
    v, t = box_tets(cells, (0.25, 0.25 * cells[1] / cells[0], 0.25 * cells[2] / cells[0]))
    meshio.write(str(mesh), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    frames = 4
    from stages.steps import calibrate, synth, tetrahedralize

    cap, ws = work / "timing" / "cap", work / "timing" / "ws"  # bench/adapt.py's make_capture, linear tets
    synth.run(synth.SynthConfig(mesh=mesh, out=cap, scenario="twist", cameras=4, frames=frames, resolution=128,
                                young=1e5, markers=0, calib_views=0, seed=0))
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    bench_adapt.with_gaussians(cap, ws, 5000, 20)
    ws_r = bench_adapt.subspace_ws(cap, ws, 30, "pca", sequences=8, frames=10)
    rows = []
    for est in ("adam", "gn"):  # one run each (time-boxed on a shared machine)
        art, _ = bench_adapt.run_adapt(cap, ws_r, work / "timing" / est, space="reduced", loss="vision", window=3,
                                       iters_per_frame=1 if est == "adam" else 1, frames=f"0:{frames}",
                                       estimator=est)
        rows.append({"case": "bar-like timing", "estimator": est, "dofs": 3 * art.positions.shape[1], "r": 30,
                     "cameras": 4, "resolution": 128, **bench_adapt.times(art)})
    best = {}
    for r in rows:
        if r["estimator"] not in best or r["total_s"] < best[r["estimator"]]["total_s"]:
            best[r["estimator"]] = r
    out = list(best.values())
    for r in out:
        print(f"timing {r['estimator']}: total {r['total_s']:.3f} s/frame (forward {r['forward_s']:.3f}, "
              f"sensitivity/adjoint {r['backward_s']:.3f}, render {r['render_s']:.3f})", flush=True)
    return out


def _parabola_min(x: np.ndarray, y: np.ndarray) -> float:
    """x at the minimum of samples y(x) (x > 0): the vertex of the parabola in log x through the smallest sample
    and its neighbours (the end sample's neighbours at an end of the grid; NaN where that parabola opens down)."""
    i = int(np.clip(np.argmin(y), 1, len(x) - 2))
    c = np.polyfit(np.log(x[i - 1:i + 2]), y[i - 1:i + 2], 2)
    return float(np.exp(-c[1] / (2 * c[0]))) if c[0] > 0 else float("nan")


def window_sweep(scene: str, seed: int, body: list[float], stiff: list[float], substeps: int | None = None) -> dict:
    """The marker loss adapt's gn minimises, at FIXED θ, per frame: adapt's model (the beam's coarse tets as P2,
    ``substeps`` per frame (None: adapt's default), the capture's start) simulated from frame 0 with E = scale × E_true per region and the
    true ν, markers bound to the simulated frame-0 surface (stages.sweep).  Per frame t: the E of each region at the
    minimum of the w-frame window's loss (t − w + 1 … t) and of the loss of frames 0 … t (the other region at its
    truth; parabola in log E through the grid), on the capture with its marker noise and on the same capture
    without noise (model error alone); and rsl adapt --mode offline (gn, the whole sequence) with ν fitted and
    with ν held at the truth."""
    from stages.artefacts import AdaptArtefact, MeshArtefact
    from stages.capture import load_capture
    from stages.sim.markers import bind_markers, marker_residuals
    from stages.sim.scene import make_scene
    from stages.sweep import simulate_fixed

    S = int(_default("substeps")) if substeps is None else substeps
    out: dict = {"scene": scene, "seed": seed, "window": W, "body_scales": body, "stiff_scales": stiff,
                 "adapt_substeps": S}
    with tempfile.TemporaryDirectory() as tmp:
        for label, noise in (("noisy", 2e-4), ("noise-free", 0.0)):
            cap, ws, truth, nu_true, names = make_capture(Path(tmp) / label, scene, seed, marker_noise=noise)
            capture = load_capture(cap)
            mesh = MeshArtefact.load(ws / "mesh.h5")
            ctl = capture.controls()
            sc = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity)
            order = [names.index(n) for n in sc.region_names]
            E_true, nu = truth[0, order], nu_true[0, order]
            P = capture.markers()
            faces = np.asarray(mesh.surface_faces)

            def frame_loss(scale) -> np.ndarray:
                X = simulate_fixed(sc, ctl, E_true * np.asarray(scale), nu, len(P), capture.start, S)
                r = marker_residuals(bind_markers(X[0], faces, P[0]), X, P)
                return np.sum(r * r, axis=(1, 2))

            Lb = np.array([frame_loss([b, 1.0]) for b in body])  # (K, T), region order of the scene
            Ls = np.array([frame_loss([1.0, s]) for s in stiff])
            T = Lb.shape[1]
            rows = []
            for t in range(T):
                a = max(0, t - W + 1)
                rows.append({"frame": t,
                             "window_body": _parabola_min(np.array(body), Lb[:, a:t + 1].sum(1)),
                             "window_stiff": _parabola_min(np.array(stiff), Ls[:, a:t + 1].sum(1)),
                             "cumulative_body": _parabola_min(np.array(body), Lb[:, :t + 1].sum(1)),
                             "cumulative_stiff": _parabola_min(np.array(stiff), Ls[:, :t + 1].sum(1))})
            out[label] = {"regions": list(sc.region_names), "frames": rows,
                          "loss_at_truth": float(Lb[list(np.isclose(body, 1.0)).index(True)].sum())}
            print(f"{label}: swept", flush=True)
            if label == "noisy":
                off = {}
                for tag, opts in (("ν fitted", ()), ("ν held at the truth", ("--fixed-poisson",))):
                    _pipeline.adapt(cap, ws, "--space", "full", "--loss", "markers", "--mode", "offline",
                                    "--estimator", "gn", "--young-init", E0 / 2, *_substeps_option(substeps), *opts)
                    art = AdaptArtefact.load(ws / "adapt.h5")
                    if adapt_substeps_used(ws / "adapt.h5") != S:
                        raise RuntimeError(f"offline adapt ran at {adapt_substeps_used(ws / 'adapt.h5')} substeps, "
                                           f"the sweep at {S}")
                    rn = list(art.extra.get("region_names", [])) or list(sc.region_names)
                    off[tag] = {n: {"young_rel": float(art.young[-1, i] / truth[0, names.index(n)]),
                                    "poisson": float(art.poisson[-1, i])} for i, n in enumerate(rn)}
                    print(f"offline {tag}: {off[tag]}", flush=True)
                out["offline"] = off
    return out


def write_window_sweep(d: dict) -> None:
    """docs/results/estimator_window_sweep.{md,json} from :func:`window_sweep`'s result."""
    (OUT / "estimator_window_sweep.json").write_text(json.dumps(d, indent=1))
    settled = lambda rows: [r for r in rows if r["frame"] >= W + 5]  # noqa: E731
    lines = [f"# Estimator: where the marker loss has its minimum, window by window ({d['date']})", "",
             f"Scene {d['scene']!r}, seed {d['seed']} of bench/estimator.py (same capture recipe; once with its marker "
             f"noise, once without). adapt's model ({d.get('adapt_substeps', 2)} substeps, P2 on the coarse beam) simulated at "
             f"FIXED E = scale × E_true per region from frame 0, ν at the truth, markers bound to the simulated "
             f"frame-0 surface. Per frame t: E/E_true at the minimum of the loss of the w = {W} frames t − {W - 1} … t "
             f"('window') and of frames 0 … t ('cumulative'), one region swept with the other at its truth "
             f"(parabola in log E; grids: body {d['body_scales']}, stiff {d['stiff_scales']}).", "",
             "| frame | window body (noisy) | window stiff (noisy) | cumulative body (noisy) | cumulative stiff (noisy) "
             "| window body (noise-free) | window stiff (noise-free) | cumulative body (noise-free) "
             "| cumulative stiff (noise-free) |", "|---|---|---|---|---|---|---|---|---|"]
    def cell(v: float, grid: list) -> str:  # a minimum beyond the grid is an extrapolation: only its side is known
        return f"> {max(grid):g}" if v > max(grid) else (f"< {min(grid):g}" if v < min(grid) else f"{v:.3f}")

    for a, b in zip(d["noisy"]["frames"], d["noise-free"]["frames"]):
        lines.append(f"| {a['frame']} | " + " | ".join(
            cell(x[k], d["body_scales"] if k.endswith("body") else d["stiff_scales"]) for x in (a, b) for k in (
                "window_body", "window_stiff", "cumulative_body", "cumulative_stiff")) + " |")
    lines += ["", f"## Summary (frames ≥ w + 5 = {W + 5}, computed from the table)", ""]
    for label in ("noisy", "noise-free"):
        rows = settled(d[label]["frames"])
        for k in ("window_body", "window_stiff", "cumulative_body", "cumulative_stiff"):
            v = np.array([r[k] for r in rows])
            v = v[np.isfinite(v)]
            g = d["body_scales"] if k.endswith("body") else d["stiff_scales"]
            lines.append(f"- {label}, {k.replace('_', ' ')}: E/E_true from {cell(v.min(), g)} to {cell(v.max(), g)} "
                         f"({np.mean(np.abs(v - 1) <= 0.03):.0%} of the frames within ±3 %)")
    for tag, regs in d.get("offline", {}).items():
        lines.append(f"- rsl adapt --mode offline (gn, the whole noisy sequence, {tag}): " + ", ".join(
            f"{n} E/E_true {v['young_rel']:.3f}, ν {v['poisson']:.3f}" for n, v in regs.items()))
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "estimator_window_sweep.md").write_text(text)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--timing", action="store_true", help="only the bar-like timing case (appended to the json)")
    ap.add_argument("--from-json", action="store_true", help="re-write estimator.md/.png from estimator.json")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--workers", type=int, default=1, help="processes running cases side by side")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL=OPTIONS",
                    help="an extra gn row: LABEL=\"adapt options\" run on the same captures")
    ap.add_argument("--adam-seeds", type=int, default=1, help="seeds that also run adam (the first N)")
    ap.add_argument("--window-sweep", action="store_true",
                    help="only the fixed-E loss sweep per window on one capture (estimator_window_sweep.md)")
    ap.add_argument("--sweep-scene", default="two-region beam")
    ap.add_argument("--sweep-seed", type=int, default=1)
    ap.add_argument("--adapt-substeps", type=int, default=None,
                    help="rsl adapt --substeps for every run (default: not passed, adapt's own default)")
    args = ap.parse_args()
    if args.window_sweep and args.from_json:  # re-write the table from the last sweep
        write_window_sweep(json.loads((OUT / "estimator_window_sweep.json").read_text()))
        return
    if args.window_sweep:
        d = window_sweep(args.sweep_scene, args.sweep_seed, [0.94, 0.97, 1.0, 1.03, 1.06, 1.09],
                         [0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3], args.adapt_substeps)
        d["date"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        write_window_sweep(d)
        return
    if args.from_json:  # re-write the tables and the plot from the last measurement
        write(json.loads((OUT / "estimator.json").read_text())["cases"], args)
        return
    if args.timing:
        with tempfile.TemporaryDirectory() as tmp:
            rows = timing_case(Path(tmp))
        data = json.loads((OUT / "estimator.json").read_text())
        data["timing"] = rows
        (OUT / "estimator.json").write_text(json.dumps(data, indent=1))
        md = (OUT / "estimator.md").read_text().split("\n## Per-frame time")[0].rstrip("\n")
        lines = ["", "## Per-frame time, bar-like case (images, reduced space; measured in one run)", "",
                 "| estimator | DOFs | r | cameras | forward s | sensitivity/adjoint s | render s | total s/frame |",
                 "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['estimator']} | {r['dofs']} | {r['r']} | {r['cameras']} × {r['resolution']}² | "
                         f"{r['forward_s']:.3f} | {r['backward_s']:.3f} | {r['render_s']:.3f} | {r['total_s']:.3f} |")
        (OUT / "estimator.md").write_text(md + "\n" + "\n".join(lines) + "\n")
        print("\n".join(lines))
        return
    sys.path.insert(0, str(ROOT / "bench"))
    from _parallel import map_tasks

    variants = dict(v.split("=", 1) for v in args.variant)
    # seed-major: a run stopped early has every scene at the first seeds
    tasks = [(scene, seed, seed < args.adam_seeds, variants, args.adapt_substeps) for seed in range(args.seeds)
             for scene in args.scenes.split(",")]
    import time

    t0 = time.perf_counter()
    cases = [row for rows in map_tasks(run_case, tasks, workers=args.workers) for row in rows]
    args.wall_s = time.perf_counter() - t0
    if not cases:  # every case failed: keep the last measurement's pages
        sys.exit("bench/estimator.py: every case failed (see above); docs/results/estimator.* left as they were.")
    write(cases, args)


def _used_substeps(cases: list) -> str:
    """The substeps per frame adapt used, as recorded in the rows (from adapt.h5's provenance): one value, or the
    values found ('unrecorded' for rows measured before the bench recorded it)."""
    v = sorted({str(c.get("adapt_substeps", "unrecorded")) for c in cases})
    return v[0] if len(v) == 1 else " / ".join(v)


def _z(row: dict, t: int) -> float | None:
    z = row.get("innovation_ratio", [])
    return z[t] if t < len(z) else None


def _cusum_h() -> float:
    from stages.estimator import ChangeDetector

    d = ChangeDetector(_default("change_threshold"))
    return d.threshold ** 2 - 1.0 - d.drift


def _cusum_max(rows: list) -> float:
    """The largest CUSUM statistic g of the change test over the runs (from their recorded innovations)."""
    from stages.estimator import ChangeDetector

    best = 0.0
    for r in rows:
        d = ChangeDetector(1e9)  # never declares: g only accumulates
        for z in r.get("innovation_ratio", []):
            if z is not None:
                d.update(z)
                best = max(best, d.g)
    return best


def _default(field: str) -> float:
    """The AdaptConfig default the runs used (0 for a field this version of rsl does not have; --process-noise and
    --model-error: the ones markers take, adapt.PROCESS_NOISE and adapt.MODEL_ERROR_MARKERS)."""
    from stages.steps import adapt

    resolved = {"process_noise": "PROCESS_NOISE", "model_error": "MODEL_ERROR_MARKERS"}  # None in AdaptConfig
    if field in resolved:
        return float(getattr(adapt, resolved[field]))
    return float(getattr(adapt.AdaptConfig, field, 0.0))


def _segments(rows: list) -> list[str]:
    """Per segment: median frames to stay within 5 % over runs (never = ∞) and the runs within w + 5."""
    out = []
    for i in range(len(rows[0]["settle_frames"])):
        v = [np.inf if r["settle_frames"][i] is None else r["settle_frames"][i] for r in rows]
        med = np.median(v)
        out.append(f"{'never' if not np.isfinite(med) else f'{med:.0f}'} ({sum(x <= W + 5 for x in v)}/{len(v)})")
    return out


def write(cases: list, args) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    old = json.loads((OUT / "estimator.json").read_text()) if args.from_json else {}
    data = {"machine": old.get("machine", f"{platform.node()} {platform.processor() or platform.machine()} "
                                          f"({os.cpu_count()} cpus)"),
            "date": old.get("date", datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")),
            "wall_s": old.get("wall_s", getattr(args, "wall_s", None)),
            "model_error": old.get("model_error", _default("model_error")),
            "model_error_poisson": old.get("model_error_poisson", _default("model_error_poisson")),
            "poisson_true": 0.45,
            "adapt_substeps": _used_substeps(cases),
            "setup": old.get("setup", (
                f"Coarse_beam (the shared beam, 0.2 m) pulled by a cable, filmed by rsl synth with a truth of "
                f"quadratic tets on the once-refined mesh (1632 tets), 3 substeps per frame, hard handles, start = equilibrium, "
                f"30 markers with σ 0.2 mm noise; rsl adapt: full space, quadratic tets on the beam's own 204 tets, "
                f"{_used_substeps(cases)} substeps per frame (its default, read from adapt.h5's provenance), markers, w = {W}, E_init = E0/2, default --process-noise "
                f"({_default('process_noise'):g}; {_default('process_noise_change'):g} after a detected change), "
                f"--model-error, --change-threshold")),
            "cases": cases}
    if "timing" in old:
        data["timing"] = old["timing"]
    (OUT / "estimator.json").write_text(json.dumps(data, indent=1))
    groups: dict = {}
    for c in cases:
        groups.setdefault((c["scene"], c["estimator"]), []).append(c)
    lines = [f"# Estimator: Gauss–Newton vs Adam ({data['date']})", "", data["setup"] + ".", "",
             "Rows: one per scene and estimator over its runs (seeds × regions); settled = from w + 5 frames after "
             "the start or a step of E to the end of that segment."
             + ("" if any(c["estimator"] == "adam" for c in cases) else " Adam was not run (--adam-seeds 0)."), "",
             "| scene | estimator | runs | median settled error | max settled error | settled within ±3 % | "
             "frames to stay within 5 % per segment: median (runs ≤ w + 5) | truth within ±2σ (E) | "
             "median σ_E/E settled | truth within ±2σ (ν) | change points detected | s/frame |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (scene, est), rows in groups.items():
        cal = [r for r in rows if "truth_within_2sigma" in r]
        cal_in = sum(r["inside_2sigma"] for r in cal)
        cal_n = sum(r["settled_frames"] for r in cal)
        caln = [r["nu_within_2sigma"] for r in rows if "nu_within_2sigma" in r]
        ch = "; ".join(sorted({str(r["changes_detected"]) for r in rows})) if est.startswith("gn") else ""
        sig = f"{np.median([r['median_sigma_rel_settled'] for r in cal]):.2%}" if cal else ""
        cov = f"{cal_in / cal_n:.0%} ({cal_in}/{cal_n})" if cal else ""
        nuc = f"{np.mean(caln):.0%}" if caln else ""
        lines.append(f"| {scene} | {est} | {len(rows)} | "
                     f"{np.median([r['median_abs_err_settled'] for r in rows]):.2%} | "
                     f"{np.max([r['max_abs_err_settled'] for r in rows]):.2%} | "
                     f"{np.mean([r['within_3pct_settled'] for r in rows]):.0%} | {' / '.join(_segments(rows))} | "
                     f"{cov} | {sig} | {nuc} | {ch} | "
                     f"{np.median([r['s_per_frame'] for r in rows]):.3f} |")
    gn = [r for r in cases if r["estimator"] == "gn" and "inside_2sigma" in r]
    if gn:
        scenes = sorted({r["scene"] for r in gn})
        seeds = sorted({r["seed"] for r in gn})
        tot_in, tot_n = sum(r["inside_2sigma"] for r in gn), sum(r["settled_frames"] for r in gn)
        steps = [r for r in gn if r["steps"]]
        after = [x for r in steps for x in r["settle_frames"][1:]]
        ok = sum(x is not None and x <= W + 5 for x in after)
        const = [r for r in gn if not r["steps"]]
        lines += ["", "## Summary (gn, computed from the rows above)", "",
                  f"- σ calibration: the truth lies inside E ± 2σ on {tot_in}/{tot_n} = {tot_in / tot_n:.1%} of the "
                  f"settled frames over {len(scenes)} scenes × {len(seeds)} seeds.",
                  f"- E steps: within 5 % of the new value in ≤ w + 5 = {W + 5} frames after {ok}/{len(after)} steps.",
                  "- Constant-E runs: none in this run." if not const else
                  f"- Constant-E runs: {np.mean([r['within_3pct_settled'] for r in const]):.0%} of the settled "
                  f"frames within ±3 % (worst {np.max([r['max_abs_err_settled'] for r in const]):.2%}); change points "
                  f"declared on them: {sum(len(r['changes_detected']) for r in const)}; the change test's CUSUM "
                  f"statistic reached at most {_cusum_max(const):.1f} there (declared above "
                  f"{_cusum_h():.1f}); the innovation z at the steps: "
                  f"{', '.join(f'{z:.0f}' for z in sorted({z for r in steps for t in r['steps'] for z in [_z(r, t)] if z}))}.",
                  f"- Wall time of the run: {data['wall_s'] / 60:.1f} min." if data.get("wall_s") else ""]
    labels = list(dict.fromkeys(c["estimator"] for c in cases if c["estimator"].startswith("gn")))
    if len(labels) > 1:  # gn variants measured on the same captures
        lines += ["", "## gn variants on the same captures (computed from the runs above)", "",
                  "| gn run | adapt options | constant-E settled frames within ±3 % | worst constant-E settled error | "
                  "steps within 5 % in ≤ w + 5 | worst settled error, step runs | median settled error, all |",
                  "|---|---|---|---|---|---|---|"]
        for lab in labels:
            rs = [r for r in cases if r["estimator"] == lab]
            const, stp = [r for r in rs if not r["steps"]], [r for r in rs if r["steps"]]
            after = [x for r in stp for x in r["settle_frames"][1:]]
            lines.append(
                f"| {lab} | {' '.join(rs[0].get('options', [])) or '(defaults)'} | "
                f"{_frac([r['within_3pct_settled'] for r in const], const)} | "
                f"{_worst(const)} | "
                f"{f'{sum(x is not None and x <= W + 5 for x in after)}/{len(after)}' if after else ''} | "
                f"{_worst(stp)} | "
                f"{np.median([r['median_abs_err_settled'] for r in rs]):.2%} |")
    if gn:
        lines += _floor_table(gn, data)
    if "timing" in data:
        lines += ["", "## Per-frame time, bar-like case (images, reduced space; measured in one run, earlier)", "",
                  "| estimator | DOFs | r | cameras | forward s | sensitivity/adjoint s | render s | total s/frame |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in data["timing"]:
            lines.append(f"| {r['estimator']} | {r['dofs']} | {r['r']} | {r['cameras']} × {r['resolution']}² | "
                         f"{r['forward_s']:.3f} | {r['backward_s']:.3f} | {r['render_s']:.3f} | {r['total_s']:.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "estimator.md").write_text(text)
    plot(cases)


def _worst(rows: list) -> str:
    """The largest settled error over the runs ('' for none)."""
    return f"{np.max([r['max_abs_err_settled'] for r in rows]):.2%}" if rows else ""


def _frac(values: list, rows: list) -> str:
    """The mean of per-run fractions, weighted by the runs' settled frames."""
    if not rows:
        return ""
    n = np.array([r["settled_frames"] for r in rows], float)
    return f"{float(np.sum(np.asarray(values) * n) / max(n.sum(), 1)):.0%}"


def _floor_table(gn: list, data: dict) -> list[str]:
    """Coverage of E ± 2σ and ν ± 2σ on the settled frames had the run reported another model-error floor: the
    floor enters σ only in quadrature (σ_E/E = √(σ²_logE + e²), σ_ν = √(σ²_ν,stat + e_ν²); the estimates do not
    depend on it), so the statistical part is recovered from the stored σ and the floor swapped.  A row that recorded
    its per-region floors (adapt.h5 extra young_model_error: e spread over the regions, stages.windows.
    model_error_floors) keeps its spread: e' × (floor / e) replaces the floor."""
    e_run, en_run = data.get("model_error", 0.02), data.get("model_error_poisson", 0.0)
    es, ens = (0.0, 0.01, 0.02, 0.03, 0.04), (0.0, 0.01, 0.02, 0.03)
    cov_e, cov_n = {e: [0, 0] for e in es}, {e: [0, 0] for e in ens}
    for r in gn:
        rel, sr = np.asarray(r["young_rel"]), np.asarray(r["sigma_rel"])
        nu, sn = np.asarray(r["poisson"]), np.asarray(r["poisson_sigma"])
        steps, T = r["steps"], len(rel)
        settled = np.zeros(T, bool)
        for a, b in zip([0] + steps, steps + [T]):
            settled[min(a + W + 5, b):b] = True
        floor = np.asarray(r.get("model_error_floor", np.full(T, e_run)), float)
        spread = floor / e_run if e_run > 0 else np.ones(T)
        s_log = np.sqrt(np.maximum((sr / rel) ** 2 - floor ** 2, 0.0))
        s_nu = np.sqrt(np.maximum(sn ** 2 - en_run ** 2, 0.0))
        for e in es:
            ok = np.abs(rel - 1) <= 2 * rel * np.sqrt(s_log ** 2 + (e * spread) ** 2)
            cov_e[e][0] += int(ok[settled].sum())
            cov_e[e][1] += int(settled.sum())
        for e in ens:
            ok = np.abs(nu - data.get("poisson_true", 0.45)) <= 2 * np.sqrt(s_nu ** 2 + e ** 2)
            cov_n[e][0] += int(ok[settled].sum())
            cov_n[e][1] += int(settled.sum())
    return ["", f"## Calibration of the model-error floor (gn; this run reported e = {e_run:g}, e_ν = {en_run:g})", "",
            "Truth inside ±2σ on the settled frames of every gn run above, with σ recomputed for another floor.", "",
            "| e (relative, E) | " + " | ".join(f"{e:g}" for e in es) + " |",
            "|---|" + "---|" * len(es),
            "| truth within E ± 2σ | " + " | ".join(f"{a / max(n, 1):.1%}" for a, n in cov_e.values()) + " |", "",
            "| e_ν (absolute, ν) | " + " | ".join(f"{e:g}" for e in ens) + " |",
            "|---|" + "---|" * len(ens),
            "| truth within ν ± 2σ | " + " | ".join(f"{a / max(n, 1):.1%}" for a, n in cov_n.values()) + " |"]


def plot(cases: list) -> None:
    """Top row: seed 0's E/E_true ± 2σ per scene and region (log scale); bottom row: every seed's E/E_true zoomed to
    ±10 % with the ±3 % band (colour: estimator, line style: seed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = list(dict.fromkeys((c["scene"], c["region"]) for c in cases))
    fig, axes = plt.subplots(2, len(panels), figsize=(5 * len(panels), 7.5), squeeze=False)
    labels = list(dict.fromkeys(c["estimator"] for c in cases))
    colours = {lab: f"C{i}" for i, lab in enumerate(labels)}
    styles = ["-", "--", ":", "-."]
    for ax, zoom, (scene, region) in zip(axes[0], axes[1], panels):
        rows = [c for c in cases if c["scene"] == scene and c["region"] == region and c["seed"] == 0]
        for r in rows:
            e = np.asarray(r["young_rel"])
            t = np.arange(len(e))
            ax.plot(t, e, color=colours[r["estimator"]], label=r["estimator"])
            sd = np.asarray(r["sigma_rel"])
            if np.all(np.isfinite(sd)):
                ax.fill_between(t, e - 2 * sd, e + 2 * sd, color=colours[r["estimator"]], alpha=0.25, lw=0,
                                label=f"{r['estimator']} ± 2σ")
        for c in [c for c in cases if c["scene"] == scene and c["region"] == region]:
            e = np.asarray(c["young_rel"])
            zoom.plot(np.arange(len(e)), e, color=colours[c["estimator"]], ls=styles[c["seed"] % len(styles)], lw=1,
                      label=f"{c['estimator']}, seed {c['seed']}")
        steps = next((c["steps"] for c in cases if c["scene"] == scene), [])
        for a in (ax, zoom):
            a.axhline(1.0, color="k", lw=0.8, ls="--", label="truth" if a is ax else None)
            for s in steps:
                a.axvline(s, color="grey", lw=0.6, ls=":")
            a.set_xlabel("frame")
        zoom.axhspan(0.97, 1.03, color="grey", alpha=0.15, lw=0, label="±3 %")
        zoom.set_ylim(0.9, 1.1)
        zoom.set_title(f"{scene} ({region}), every seed: E / E_true", fontsize=9)
        ax.set_yscale("log")
        ax.set_ylim(0.3, 3.0)
        ax.set_title(f"{scene} ({region}), seed 0: E / E_true ± 2σ", fontsize=9)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    seeds = sorted({c["seed"] for c in cases})
    handles = ([Line2D([], [], color=colours[lab], label=lab) for lab in labels]
               + [Line2D([], [], color="k", ls=styles[s % len(styles)], lw=1, label=f"seed {s}") for s in seeds]
               + [Line2D([], [], color="k", ls="--", lw=0.8, label="truth"),
                  Patch(color="grey", alpha=0.3, label="±3 % (bottom row)")])
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(OUT / "estimator.png", dpi=110)


if __name__ == "__main__":
    main()
