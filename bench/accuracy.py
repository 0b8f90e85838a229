"""Accuracy of rsl adapt on captures it did not make (truth simulated on another discretisation).

Captures by `rsl synth` whose truth is P2 tets on the shipped structured mesh (fTetWild meshes the object for adapt), 3 substeps
per frame and hard (Dirichlet) handles, for each start state (equilibrium, rest; the bar also filmed mid-motion,
moving: `--start moving`, 8 lead-in frames from its equilibrium; with images, fit-gaussians poses frame 0 from its
masks):

    bar      sample_data/bar pulled by a cable, E steps E0 → 2E0 → 4E0 at T/3 and 2T/3
    dino     sample_data/dino pushed by a sphere, constant E
    beam     sample_data/bar pulled by a cable, two regions (the far half 3 × stiffer), constant

Each capture goes through the pipeline as a lab would run it: calibrate --from-json, tetrahedralize
--order 1|2 (fTetWild, --max-tets MAX_TETS), for vision segment + fit-gaussians (silhouette: segment alone), for
the reduced space generate-data + train-subspace, then `rsl adapt` online (window 3, E initialised at 0.5 E0, the default
estimator unless --estimator; --substeps passed through), `rsl export --forces` and `rsl evaluate`.

Per row: the median relative error of E per region over the settled frames (every frame at least w + 5
frames after the start and after each step of E_true), the median relative error of the handle/obstacle
forces against truth/forces.csv (as `rsl evaluate` reports it), the mean surface distance, the adapt mesh's
DOFs and the median per-frame time of adapt (adapt.h5 time_total_s).

    .venv/bin/python bench/accuracy.py [--quick] [--out docs/results] [--substeps S] [--cases bar,beam]
        [--rows 'bar/rest/2/markers/reduced;beam/equilibrium/2/markers/full'] [--work DIR]
    .venv/bin/python bench/accuracy.py --merge A/accuracy.json B/accuracy.json [--previous OLD.json]

--cameras N films the captures with N cameras instead of the scale's (a lab's capture: one).

Runs side by side need their own --work (each workspace's adapt.h5/evaluation.json belong to its last row);
--merge writes one table from them, --previous lists an older run's rows that were not re-run apart, labelled.

--quick: the bar only, 30 frames, P2 truth on the shipped mesh, markers, P1 and P2, full space.
With RSL_BENCH_REUSE=1, captures and meshes already in --work are reused.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402

E0 = 1.0e5
POISSON = 0.45
WINDOW = 3
TRUTH_SUBSTEPS = 3
TRUTH_DAMPING = 0.0  # β s of the truths' viscous damping (`rsl synth --damping`, declared in capture.toml); 0: none
MAX_TETS = 1500  # adapt mesh size (fTetWild): 964 P2 tets, 4914 DOFs on the bar
# --scale: (cameras, image side, adapt --max-tets, truth --truth-refine).  table: the main table's captures; paper:
# the paper's Bar (≈10K DOFs, c = 4 at 128²): fTetWild's --max-tets 2450 meshes the bar with ≈2K P2 tets, 9–12K
# DOFs (tried by hand: 2000 gave 7074 DOFs, 2400 8673, 2450 9369 and 11511, 2500 11943; its output varies between
# runs: the row records its DOFs), and the truth is refined once (7832 P2 tets) so that it stays finer than the mesh
# adapt uses.
SCALES = {"table": (3, 96, MAX_TETS, 0), "paper": (4, 128, 2450, 1)}
SCALE = "table"
CAMERAS = 0  # --cameras: the captures' camera count instead of the scale's (0: the scale's); a --work of its own
SEQUENCES = 4  # generate-data --sequences of the reduced rows (docs/results/training_data.md)
SUBSPACE_DIM = 30  # r, the paper's Bar (docs/results/reduced_accuracy.md: r = 12 biases E by 1.5–3.5 %)
# rsl train-subspace --cubature-tol per case: its default, 0.0005 (docs/results/cubature_tol.md: the same networks at
# 0.002 → 0.0005, mean largest settled E error 8.8 → 5.6 % over seven workspaces).  Pages before 2026-11-30 used
# 0.002 (measured better than 0.01 on three of four captures: accuracy_notes.md, 2026-11-24 afternoon); each row
# records its tolerance.
CUBATURE_TOL = {"bar": 0.0005, "beam": 0.0005, "dino": 0.0005}
EXTRA: list = []  # extra rsl adapt options (--estimator, --substeps, --adapt-option)
EXPORT = True  # also run `rsl export --forces` (evaluate computes the same replayed forces: stages/forces.py)

# (case, start, adapt element order, loss, space): the full run's rows, most telling first.
FULL_PLAN = (
    [("bar", "equilibrium", 2, "markers", sp) for sp in ("reduced", "full")]
    + [("bar", "equilibrium", 2, "vision", "reduced"), ("beam", "equilibrium", 2, "markers", "reduced"),
       ("bar", "rest", 2, "markers", "reduced"), ("dino", "equilibrium", 2, "markers", "reduced"),
       ("bar", "rest", 2, "markers", "full"), ("beam", "equilibrium", 2, "markers", "full"),
       ("bar", "equilibrium", 2, "vision", "full"), ("bar", "rest", 2, "vision", "reduced"),
       ("dino", "equilibrium", 2, "vision", "reduced"),
       ("bar", "moving", 2, "markers", "reduced"), ("bar", "moving", 2, "markers", "full"),
       ("bar", "moving", 2, "vision", "reduced"),
       ("bar", "equilibrium", 2, "silhouette", "reduced"), ("bar", "moving", 2, "silhouette", "reduced")]
    + [("bar", s, 1, "markers", sp) for s in ("equilibrium", "rest") for sp in ("reduced", "full")]
    + [("beam", "equilibrium", 1, "markers", "reduced"), ("dino", "equilibrium", 1, "markers", "reduced"),
       ("dino", "equilibrium", 2, "markers", "full")]
)
# Rows run only when --rows names them: the dinosaur and the two-region beam filmed mid-motion, further scenes for
# the loss one camera filmed mid-motion needs (accuracy_one_camera/).
ON_REQUEST = [(c, "moving", 2, loss, "reduced") for c in ("dino", "beam") for loss in ("vision", "silhouette")]
QUICK_PLAN = [("bar", s, o, "markers", "full") for s in ("equilibrium", "rest") for o in (1, 2)]


def scene_args(case: str, frames: int) -> list:
    """[mesh, rsl synth scenario options...] of a case (bench/_pipeline.py)."""
    if case == "bar":
        return pl.bar_cable(schedule=f"{E0:g}@0,{2 * E0:g}@{frames // 3},{4 * E0:g}@{2 * frames // 3}")
    if case == "dino":
        return pl.dino_push(E0)
    if case == "beam":
        return pl.bar_cable(young=E0, region=f"stiff={3 * E0:g}@x>0.5")
    raise ValueError(case)


def settled_mask(young_true: np.ndarray, first: int = 0, window: int | None = None) -> np.ndarray:
    """(T,) True at frames ≥ w + 5 after the first frame and after every change of E_true (any region); w the
    row's window (None: the bench's, WINDOW)."""
    w = WINDOW if window is None else int(window)
    T = len(young_true)
    ok = np.ones(T, bool)
    ok[: first + w + 5] = False
    for t in range(1, T):
        if np.any(young_true[t] != young_true[t - 1]):
            ok[t: t + w + 5] = False
    return ok


def capture(work: Path, case: str, start: str, frames: int, refine: int) -> Path:
    cameras, side, _, scale_refine = SCALES[SCALE]
    cameras = CAMERAS or cameras
    return pl.foreign_capture(work / f"{case}_{start}", scene_args(case, frames), start=start, frames=frames,
                              cameras=cameras, resolution=side, refine=max(refine, scale_refine),
                              substeps=TRUTH_SUBSTEPS, poisson=POISSON,
                              extra=["--damping", TRUTH_DAMPING] if TRUTH_DAMPING else [])


def workspace(work: Path, cap: Path, case: str, start: str, order: int, loss: str, space: str, frames: int) -> Path:
    ws = pl.mesh(cap, work / f"ws_{case}_{start}_p{order}", order=order, max_tets=SCALES[SCALE][2])
    if loss == "vision":
        pl.gaussians(cap, ws, frame=0)
    if loss == "silhouette" and not pl.skip(ws / "masks.h5"):  # the masks alone: no fit-gaussians
        pl.rsl("segment", cap, "-w", ws)
    if space == "reduced":
        subspace(cap, ws, frames, SUBSPACE_DIM, CUBATURE_TOL[case], SEQUENCES)
    return ws


def subspace(cap: Path, ws: Path, frames: int, dim: int, tol: float, sequences: int = SEQUENCES) -> None:
    """generate-data --sequences N (skipped per pl.skip on snapshots.h5 when it holds N sequences) + train-subspace
    --dim r --cubature-tol tol (skipped per pl.skip on subspace.h5 when the snapshots stayed and its provenance has
    the same r and tolerance)."""
    same_data = pl.skip(ws / "snapshots.h5") and _sequences(ws) == sequences
    if same_data and pl.skip(ws / "subspace.h5") and _subspace_settings(ws) == (dim, tol):
        return
    if not same_data:
        pl.rsl("generate-data", cap, "-w", ws, "--sequences", sequences, "--frames", frames, "--workers", 1)
    pl.rsl("train-subspace", "-w", ws, "--dim", dim, "--cubature-tol", tol)


def _sequences(ws: Path) -> int:
    """generate-data --sequences that WS/snapshots.h5 was made with (its provenance; -1 if not there)."""
    from stages.artefacts import read_provenance

    return int(read_provenance(ws / "snapshots.h5").get("config", {}).get("sequences", -1))


def _subspace_settings(ws: Path) -> tuple:
    """(r, cubature tolerance) that WS/subspace.h5 was trained with (its provenance)."""
    from stages.artefacts import read_provenance

    cfg = read_provenance(ws / "subspace.h5").get("config", {})
    return int(cfg.get("dim", -1)), float(cfg.get("cubature_tol", float("nan")))


def code_state() -> str:
    """`git rev-parse --short HEAD` of the repository, and whether the working tree has uncommitted changes."""
    import subprocess

    def git(*a):
        return subprocess.run(["git", *a], capture_output=True, text=True, cwd=ROOT).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "?"
    return head + (" with uncommitted changes of the session" if git("status", "--porcelain", "--untracked-files=no")
                   else "")


def run_row(work: Path, row: tuple, frames: int, refine: int) -> dict:
    from stages.artefacts import AdaptArtefact, read_provenance
    from stages.capture import load_capture, read_truth

    case, start, order, loss, space = row
    out = {"case": case, "start": start, "order": order, "loss": loss, "space": space, "scale": SCALE}
    try:
        cap = capture(work, case, start, frames, refine)
        ws = workspace(work, cap, case, start, order, loss, space, frames)
        t_adapt = pl.adapt(cap, ws, "--window", WINDOW, "--space", space, "--loss", loss,
                           "--young-init", f"{0.5 * E0:g}", *EXTRA)
        if EXPORT:
            pl.export(ws, ws / f"export_{loss}_{space}", "--forces", "--no-plots", "--no-render", "--no-vtk",
                      "--no-stress", "--no-ply")
        pl.evaluate(cap, ws, "--psnr-frames", 0, "--no-plot")
    except pl.RslFailed as e:
        return {**out, "error": str(e)[-800:]}
    truth = read_truth(load_capture(cap))
    a = AdaptArtefact.load(ws / "adapt.h5")
    prov = read_provenance(ws / "adapt.h5")
    ev = json.loads((ws / "evaluation.json").read_text())
    yt = truth.young[np.asarray(a.frames)]
    ok = settled_mask(yt)
    err = np.abs(a.young - yt) / yt  # (T, R)
    med = np.median(err[ok], axis=0) if ok.any() else np.full(yt.shape[1], np.nan)
    nut = truth.poisson[np.asarray(a.frames)]
    nu_err = np.abs(np.asarray(a.poisson) - nut)  # (T, R), absolute
    nu_med = np.median(nu_err[ok], axis=0) if ok.any() else np.full(nut.shape[1], np.nan)
    import h5py

    with h5py.File(ws / "mesh.h5", "r") as f:
        dofs = 3 * int(f["vertices"].shape[0])
    import tomllib

    synth = tomllib.loads((cap / "capture.toml").read_text()).get("synth", {})  # what rsl synth made
    out["cameras"], out["resolution"] = int(synth["cameras"]), int(synth["resolution"])
    out["truth_refine"], out["truth_tets"] = int(synth["truth_refine"]), int(synth["truth_tets"])
    out["truth_substeps"] = int(synth.get("substeps", 1))
    if space == "reduced":
        from stages.artefacts import SubspaceArtefact

        sub = SubspaceArtefact.load(ws / "subspace.h5")
        out["dim"], out["cubature_tol"] = _subspace_settings(ws)
        out["sequences"] = _sequences(ws)
        out["cubature_points"] = (len(sub.extra["cubature_points"]) if "cubature_points" in sub.extra else None)
    return {**out, "adapt_options": list(map(str, EXTRA)), "exported": EXPORT, "code": code_state(), "ended": datetime.datetime.now(datetime.timezone.utc).isoformat(
                timespec="seconds"), "load_average": os.getloadavg()[0], "estimator": prov.get("config", {}).get("estimator", "?"),
            "substeps": prov.get("config", {}).get("substeps", 1), "dofs": dofs,
            "window": WINDOW, "frames": int(len(a.frames)), "settled_frames": int(ok.sum()),
            "median_error_per_region": med.tolist(), "median_error_worst": float(np.max(med)),
            "force_error": _force_error(ev), "force_source": (ev.get("forces") or {}).get("source"),
            "surface_error_mm": _surface_mm(ev),
            "time_per_frame_s": float(np.median(a.time_total_s)), "adapt_s": t_adapt,
            "young": np.asarray(a.young).tolist(), "young_true": yt.tolist(),
            "poisson": np.asarray(a.poisson).tolist(), "poisson_true": nut.tolist(),
            "poisson_abs_error_per_region": nu_med.tolist(),
            "poisson_sigma": (np.asarray(a.poisson_sigma).tolist() if getattr(a, "poisson_sigma", None) is not None
                              else None),
            "young_sigma": (np.asarray(a.young_sigma).tolist() if getattr(a, "young_sigma", None) is not None
                            else None),
            # gn: the model-error floor in young_sigma per frame and region (bench/sigma_calibration.py)
            "young_model_error": (a.extra or {}).get("young_model_error"), "regions": list(a.region_names)}


def _force_error(ev: dict) -> float | None:
    """The median relative force error over handles/obstacles that `rsl evaluate` reports (None: not there)."""
    f = ev.get("forces")
    if isinstance(f, dict):
        for k in ("median_relative_error", "median_error"):
            if isinstance(f.get(k), (int, float)):
                return float(f[k])
    return None


def _surface_mm(ev: dict) -> float | None:
    for k in ("surface_error_mean_m", "vertex_error_mean_m", "surface_distance_mean_m"):
        if isinstance(ev.get(k), (int, float)):
            return 1e3 * float(ev[k])
    return None


def _fmt(x, scale: float = 100.0, digits: int = 1) -> str:
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{scale * x:.{digits}f}"


def _views(r: dict) -> str:
    """'c × N²' of a row's capture (rows from before this was recorded: the table's 3 × 96²)."""
    return f"{r.get('cameras', 3)} × {r.get('resolution', 96)}²"


def _row(r: dict) -> str:
    key = f"| {_case(r)} | {r['start']} | P{r['order']} | {r['loss']} | {r['space']} |"
    if "error" in r:
        return key + " — | — | — | — | — | failed | — | — | — | — | — | — | — | — |"
    names = r.get("regions") or []

    def per_region(values, fmt) -> str:
        return ", ".join((f"{names[j]} " if len(names) > 1 and j < len(names) else "") + fmt(e)
                         for j, e in enumerate(values))

    per = per_region(r["median_error_per_region"], lambda e: f"{100 * e:.1f}")
    nu = ("—" if r.get("poisson_abs_error_per_region") is None  # (rows from before ν was recorded)
          else per_region(r["poisson_abs_error_per_region"], lambda e: f"{e:.3f}"))
    cub = (f"{r['cubature_points'] if r.get('cubature_points') is not None else 'all'} ({r['cubature_tol']:g})"
           + (f", r = {r['dim']}" if r.get("dim") is not None and r["dim"] != SUBSPACE_DIM else "")
           + (f", {r.get('sequences', 4)} sequences" if r.get("sequences", 4) != SEQUENCES else "")
           if r.get("cubature_tol") is not None else "—")
    load = f"{r['load_average']:.1f}" if isinstance(r.get("load_average"), (int, float)) else "—"
    opts = [str(o) for o in r.get("adapt_options", [])]
    shown = " ".join(o for i, o in enumerate(opts)  # options other than --estimator / --substeps (own columns)
                     if o not in ("--estimator", "--substeps") and (i == 0 or opts[i - 1] not in ("--estimator",
                                                                                              "--substeps")))
    return (f"{key} {r['estimator']}{' ' + shown if shown else ''} | {r['dofs']} | {_views(r)} | "
            f"{r.get('truth_substeps', '—')} | {cub} | {per} | {nu} | {r['settled_frames']} | "
            f"{_fmt(r['force_error'])} | {_fmt(r['surface_error_mm'], 1.0, 2)} | {r['time_per_frame_s']:.2f} | "
            f"{load} | {r['substeps']} | {r.get('ended', '—')} |")


def _case(r: dict) -> str:
    """The case's name in the table: 'bar', or 'bar (paper scale)' for a row of --scale paper."""
    return r["case"] + (f" ({r['scale']} scale)" if r.get("scale", "table") != "table" else "")


def _name(r: dict) -> str:
    """'case start Pk loss space' of a row."""
    return f"{_case(r)} {r['start']} P{r['order']} {r['loss']} {r['space']}"


def row_key(r) -> tuple:
    """(case, start, order, loss, space) of a row dict or a plan tuple; a row of another --scale than the table's
    has the scale appended."""
    if not isinstance(r, dict):
        return tuple(r)
    key = (r["case"], r["start"], r["order"], r["loss"], r["space"])
    return key + ((r["scale"],) if r.get("scale", "table") != "table" else ())


def main() -> None:
    global EXTRA, EXPORT, TRUTH_SUBSTEPS, TRUTH_DAMPING, SUBSPACE_DIM, SCALE, SEQUENCES, CAMERAS, WINDOW
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_accuracy"))
    ap.add_argument("--cases", default="", help="only these cases, comma-separated (bar, dino, beam)")
    ap.add_argument("--starts", default="", help="only these start states, comma-separated")
    ap.add_argument("--losses", default="", help="only these losses, comma-separated (markers, vision, silhouette)")
    ap.add_argument("--spaces", default="", help="only these spaces, comma-separated (reduced, full)")
    ap.add_argument("--orders", default="", help="only these adapt element orders, comma-separated (1, 2)")
    ap.add_argument("--no-export", action="store_true",
                    help="skip `rsl export --forces` (the force column comes from `rsl evaluate`, the same replay)")
    ap.add_argument("--rows", default="", help="only these rows: ';'-separated case/start/order/loss/space")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="write the tables from the rows of these accuracy.json files (runs split over processes)")
    ap.add_argument("--previous", type=Path, default=None,
                    help="with --merge: an earlier accuracy.json whose rows missing from the merged runs are listed "
                         "apart, labelled as not re-run, with their date")
    ap.add_argument("--estimator", default="", help="rsl adapt --estimator (default: adapt's own default)")
    ap.add_argument("--substeps", type=int, default=0, help="rsl adapt --substeps (default: adapt's own default)")
    ap.add_argument("--adapt-option", action="append", default=[],
                    help="one more rsl adapt option (repeat for each word, e.g. --adapt-option=--lead-in --adapt-option=3)")
    ap.add_argument("--dim", type=int, default=SUBSPACE_DIM, help="train-subspace --dim, r of the reduced rows")
    ap.add_argument("--sequences", type=int, default=SEQUENCES, help="generate-data --sequences of the reduced rows")
    ap.add_argument("--truth-damping", type=float, default=TRUTH_DAMPING,
                    help="β s of the truths' viscous damping (rsl synth --damping; a --work of its own)")
    ap.add_argument("--truth-substeps", type=int, default=TRUTH_SUBSTEPS,
                    help="rsl synth --substeps of the truth (its implicit-Euler steps per frame)")
    ap.add_argument("--scale", choices=sorted(SCALES), default="table",
                    help="table: 3 cameras at 96², adapt mesh --max-tets 1500 (≈5K DOFs on the bar); paper: the "
                         "paper's Bar, 4 cameras at 128², --max-tets 2450 (≈10K DOFs), truth refined once")
    ap.add_argument("--window", type=int, default=WINDOW,
                    help="rsl adapt --window of every row (default 3, the issue's paper-scale case; rsl adapt's own "
                         "default is 5); the settled frames follow it (≥ w + 5 after each step)")
    ap.add_argument("--cameras", type=int, default=0,
                    help="the captures' camera count instead of the scale's (a --work of its own; one camera: a "
                         "lab's usual capture)")
    a = ap.parse_args()
    SCALE = a.scale
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        plan = {**{k: v for k, v in runs[0]["plan"].items() if k not in ("previous", "previous_rows")},  # (only --previous)
                "merged_from": [  # (a merged file: the runs it was merged from)
            m for f, run in zip(a.merge, runs) for m in run["plan"].get("merged_from") or [
                {"file": str(f), "date": run["date"], "load_average_end": run.get("load_average_end"),
                 "code": run.get("code", "?")}]]}
        # (rows from before r and the adapt options were recorded per row: their run's)
        rows = [{**r, "adapt_options": r.get("adapt_options", run["plan"].get("adapt_options", [])),
                 **({"dim": r.get("dim", run["plan"].get("dim", SUBSPACE_DIM))} if r.get("space") == "reduced" else {})}
                for run in runs for r in run["cases"]]
        latest: dict = {}  # a row measured in several runs: the one that ended last
        for r in rows:
            k = row_key(r)
            if k not in latest or str(r.get("ended", "")) >= str(latest[k].get("ended", "")):
                latest[k] = r
        rows = list(latest.values())
        TRUTH_SUBSTEPS = int(runs[0]["plan"].get("truth_substeps", TRUTH_SUBSTEPS))
        TRUTH_DAMPING = float(runs[0]["plan"].get("truth_damping", 0.0))
        SUBSPACE_DIM = int(runs[0]["plan"].get("dim", SUBSPACE_DIM))  # the header's r (a row with another: its own)
        SEQUENCES = int(runs[0]["plan"].get("sequences", 4))  # (runs before it was recorded: 4)
        CAMERAS = int(runs[0]["plan"].get("cameras", 0))
        WINDOW = int(runs[0]["plan"].get("window", WINDOW))  # (runs before it was recorded: 3)
        if a.previous:
            old = json.loads(a.previous.read_text())
            done = {row_key(r) for r in rows}
            plan["previous"] = {"file": str(a.previous), "date": old.get("date"), "merged_from": [
                m.get("date") for m in old.get("plan", {}).get("merged_from", [])]}
            plan["previous_rows"] = [r for r in old["cases"] if row_key(r) not in done]
        write(rows, a.out, runs[0]["mode"] == "quick", plan)
        return
    a.work.mkdir(parents=True, exist_ok=True)
    frames, refine = (30, 0) if a.quick else (36, 0)
    plan = list(QUICK_PLAN if a.quick else FULL_PLAN)
    for opt, i in ((a.cases, 0), (a.starts, 1), (a.orders, 2), (a.losses, 3), (a.spaces, 4)):
        if opt:
            plan = [r for r in plan if str(r[i]) in opt.split(",")]
    if a.rows:
        want = [tuple(int(x) if x.isdigit() else x for x in k.split("/")) for k in a.rows.split(";")]
        unknown = [k for k in want if k not in plan + ON_REQUEST]
        if unknown:
            ap.error(f"--rows: {unknown} not in the plan")
        plan = want
    TRUTH_SUBSTEPS, TRUTH_DAMPING, SUBSPACE_DIM, SEQUENCES = a.truth_substeps, a.truth_damping, a.dim, a.sequences
    CAMERAS, WINDOW = a.cameras, a.window
    EXPORT = not a.no_export
    EXTRA = ((["--estimator", a.estimator] if a.estimator else []) + (["--substeps", a.substeps] if a.substeps else [])
             + a.adapt_option)
    print(HEAD, flush=True)
    rows = []
    meta = {"frames": frames, "refine": refine, "rows": plan, "scale": SCALE, "adapt_options": EXTRA, "truth_substeps": TRUTH_SUBSTEPS,
            "truth_damping": TRUTH_DAMPING,
            "dim": SUBSPACE_DIM, "sequences": SEQUENCES, "cameras": CAMERAS, "window": WINDOW}
    for row in plan:
        rows.append(run_row(a.work, row, frames, refine))
        print(_row(rows[-1]), flush=True)
        write(rows, a.out, a.quick, meta, quiet=True)  # after every row: a stopped run keeps what it measured
    write(rows, a.out, a.quick, meta)


HEAD = ("| case | start | adapt mesh | loss | space | estimator | DOFs | cameras | truth substeps | cubature points (tol) | "
        "median \\|E−E_true\\|/E_true per region (%) | median \\|ν−ν_true\\| per region | settled frames | force error (%) | "
        "surface error (mm) | s / frame | load average | adapt substeps | ended (UTC) |\n"
        "| --- | --- | --- | --- | --- | --- | ---: | --- | ---: | ---: | --- | --- | ---: | ---: | ---: | ---: | ---: "
        "| ---: | --- |")


def _tolerances(rows: list[dict]) -> str:
    """The header's cubature tolerances: per case, those its reduced rows were fitted with (CUBATURE_TOL where no
    row says), each row's own in its cubature column when a case has several."""
    tols: dict = {c: set() for c in CUBATURE_TOL}
    for r in rows:
        if r.get("cubature_tol") is not None:
            tols.setdefault(r["case"], set()).add(float(r["cubature_tol"]))
    text = ", ".join(f"{c} {' / '.join(f'{t:g}' for t in sorted(ts or {CUBATURE_TOL.get(c, 0.0)}, reverse=True))}"
                     for c, ts in tols.items())
    return text + ("; each row's in its cubature column" if any(len(ts) > 1 for ts in tols.values()) else "")


def write(rows: list[dict], out: Path, quick: bool, plan: dict, quiet: bool = False) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "load_average_end": os.getloadavg()[0],
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "code": code_state(), "mode": "quick" if quick else "full",
            "plan": {**plan, "adapt_options": list(map(str, plan["adapt_options"]))}, "cases": rows}
    (out / "accuracy.json").write_text(json.dumps(data, indent=1))
    order: dict = {}
    for k in FULL_PLAN + [row_key(r) for r in rows]:  # FULL_PLAN's order, then rows outside it
        order.setdefault(k, len(order))
    rows = sorted(rows, key=lambda r: order[row_key(r)])
    table = "\n".join([HEAD] + [_row(r) for r in rows])
    previous = plan.get("previous_rows") or []
    if previous:
        prev = plan["previous"]
        table += (f"\n\n**Not re-run** — these rows are the PREVIOUS table's numbers (runs ended "
                  f"{', '.join(prev['merged_from']) or prev['date']}, code of that time, before that session's "
                  f"fixes), not measured with the code above:\n\n" + "\n".join([HEAD] + [_row(r) for r in previous]))
    up = Path(os.path.relpath(ROOT / "docs" / "results", out)).as_posix() + "/"  # links to the other pages
    up = "" if up == "./" else up
    per_row = {tuple(map(str, r.get("adapt_options", plan["adapt_options"]))) for r in rows}
    options = (", rsl adapt options per row (estimator column)" if len(per_row) > 1 else
               ", options " + " ".join(map(str, plan["adapt_options"])) if plan["adapt_options"] else "")
    sources = sorted({re.sub(r"\d+ detected change\(s\)", "the changes it detected", r["force_source"])
                      for r in rows if r.get("force_source")})  # one sentence per kind of replay
    unexported = [r for r in rows if r.get("exported") is False]
    ok = [r for r in rows if "error" not in r]
    n5 = sum(r["median_error_worst"] <= 0.05 for r in ok)
    red = [r for r in ok if r["space"] == "reduced"]
    n5_red = [_name(r) for r in red if r["median_error_worst"] <= 0.05]
    multi = [r for r in ok if len(r["median_error_per_region"]) > 1]
    n10_multi = [_name(r) for r in multi if r["median_error_worst"] <= 0.10]
    nf = [r for r in ok if r["force_error"] is not None]
    n10 = sum(r["force_error"] <= 0.10 for r in nf)
    n10_names = [_name(r) for r in nf if r["force_error"] <= 0.10]
    failed = "".join(f"\n- {r['case']} {r['start']} P{r['order']} {r['loss']} {r['space']}: "
                     f"`{r['error'].strip().splitlines()[-1][:200]}`" for r in rows if "error" in r)
    cams, side, max_tets, _ = SCALES["table"]
    cams = CAMERAS or cams
    paper = [r for r in rows + previous if r.get("scale", "table") == "paper"]
    paper_note = ("" if not paper else
                  f" Rows marked (paper scale), `bench/accuracy.py --scale paper`: the paper's Bar, "
                  f"{SCALES['paper'][0]} cameras at {SCALES['paper'][1]}², adapt mesh `--max-tets {SCALES['paper'][2]}`, "
                  f"the truth's mesh refined once (`--truth-refine {SCALES['paper'][3]}`, "
                  f"{paper[0].get('truth_tets', '?')} P2 tets).")
    one_truth = {r.get("truth_substeps") for r in rows + previous} == {TRUTH_SUBSTEPS}  # every row recorded it
    substeps = (f"{TRUTH_SUBSTEPS} substeps per frame" if one_truth else
                f"substeps per frame as the truth-substeps column says (— : a row from before the bench recorded "
                f"them; the first merged run's truths had {TRUTH_SUBSTEPS})")
    md = (f"# Accuracy on captures rsl did not make\n\nTruth: P2 tets{' on the mesh refined once' if plan['refine'] else ''}, "
          f"{substeps}, hard handles (`rsl synth --truth-order 2 --truth-refine "
          f"{plan['refine']} --substeps {TRUTH_SUBSTEPS if one_truth else 'N'} --handles hard"
          f"{f' --damping {TRUTH_DAMPING:g}' if TRUTH_DAMPING else ''}`), "
          f"{f'viscous damping β = {TRUTH_DAMPING:g} s declared in capture.toml, ' if TRUTH_DAMPING else ''}"
          f"{plan['frames']} frames, ν = {POISSON} (rsl adapt starts ν there, capture.toml's value, unless the options "
          f"say --poisson-init), "
          f"{cams} camera{'s' if cams != 1 else ''} at {side}², 40 markers. rsl: fTetWild mesh (`--max-tets {max_tets}`), reduced space r = {SUBSPACE_DIM} "
          f"(generate-data {SEQUENCES} sequences; `train-subspace --cubature-tol` "
          f"{_tolerances(rows)}), adapt online, window "
          f"{WINDOW}, E initialised at 0.5 E0{options}; "
          f"mode {data['mode']}.{paper_note} Settled frames: ≥ w + 5 after the start and after each step of E_true. "
          f"Force error: median relative error of the handle/obstacle forces of `rsl export --forces` against "
          f"truth/forces.csv, as `rsl evaluate` reports it"
          f"{' (' + '; '.join(sources) + ')' if sources else ''}"
          f"{f'; on {len(unexported)} row(s) `rsl export` was skipped and the column is evaluate’s own replay (the same stages/forces.py rule)' if unexported else ''}"
          f".\n\n{table}\n\n"
          f"{n5} of {len(ok)} rows have every region's median E error ≤ 5 %; in the reduced space {len(n5_red)} of "
          f"{len(red)}{' (' + '; '.join(n5_red) + ')' if n5_red else ''}. {len(n10_multi)} of {len(multi)} rows with "
          f"more than one region have every region within 10 %{' (' + '; '.join(n10_multi) + ')' if n10_multi else ''}. "
          f"{n10} of {len(nf)} rows with a force error have it ≤ 10 %{' (' + '; '.join(n10_names) + ')' if n10_names else ''}."
          f"{' Failed rows:' + failed if failed else ''}\n\n"
          "s / frame: median wall time of one adapt frame in that row's run (adapt.h5 time_total_s) on this shared "
          "machine, at the load average given (1-minute, when the row ended), on the row's mesh (DOFs column). The "
          "paper-scale reduced case (≈10K DOFs, r = 30, w = 3, c = 4 at 128², images) is timed by bench/table1.py "
          f"([table1.md]({up}table1.md)) and bench/adapt_speed.py ([adapt_speed.md]({up}adapt_speed.md)); P2 against P1 in the "
          f"reduced space by bench/p2_cost.py ([p2_cost.md]({up}p2_cost.md)). Where each loss is lowest over a grid of fixed "
          f"E on such a capture: bench/loss_sweep.py ([loss_sweep.md]({up}loss_sweep.md)). Hand-written interpretation: "
          f"[accuracy_notes.md]({up}accuracy_notes.md).\n\n"
          + (f"Rows merged from {len(plan['merged_from'])} runs (a row measured in several: the run that ended last), ended "
             + ", ".join(f"{m['date']} (load average {m['load_average_end']:.1f}, code {m.get('code', '?')})"
                         for m in plan["merged_from"])
             + f"; machine {data['machine']}. " if plan.get("merged_from") else
             f"Machine: {data['machine']}, load average {data['load_average_end']:.1f} at the end; date {data['date']}; "
             f"code {data['code']}. ")
          + f"Produced by `bench/accuracy.py{' --quick' if quick else ''}`.\n\n![E over time](accuracy.png)\n")
    (out / "accuracy.md").write_text(md)
    keys = sorted({(r["case"], r["start"]) for r in ok})
    fig, axes = plt.subplots(1, max(1, len(keys)), figsize=(4.2 * max(1, len(keys)), 3.8), squeeze=False)
    for ax, key in zip(axes[0], keys):
        sub = [r for r in ok if (r["case"], r["start"]) == key]
        yt = np.asarray(sub[0]["young_true"])
        for j in range(yt.shape[1]):
            ax.plot(yt[:, j], "k-", lw=2, label="truth" if j == 0 else None)
        for c, r in enumerate(sub):
            y = np.asarray(r["young"])
            for j in range(y.shape[1]):  # one colour per row, a dashed line per further region
                ax.plot(y[:, j], lw=1, color=f"C{c}", ls="-" if j == 0 else "--",
                        label=f"P{r['order']} {r['loss']} {r['space']}"
                              + (f" ({r['scale']} scale)" if r.get("scale", "table") != "table" else "")
                        if j == 0 else None)
        ax.set_title(f"{key[0]}, start = {key[1]}")
        ax.set_xlabel("frame")
        ax.set_ylabel("E (Pa)")
        ax.set_yscale("log")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "accuracy.png", dpi=110)
    plt.close(fig)
    if not quiet:
        print(table)


if __name__ == "__main__":
    main()
