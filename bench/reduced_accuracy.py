"""Where the reduced space's own E bias comes from, on a capture whose truth was simulated differently.

One `rsl synth` capture (sample_data/bar pulled by a cable, constant E_true, truth P2 + 3 substeps + hard
handles, start equilibrium), one P2 adapt mesh (`rsl tetrahedralize --order 2 --max-tets 500`) and several
subspaces trained on it (workspaces given as LABEL=DIR, each with mesh.h5 and subspace.h5).  Per backend,
simulated with fixed θ from the capture's start state over all frames:

- ``E_min/E_true``: the minimum of the whole-sequence marker loss over a grid of E (parabola through the
  smallest grid value and its neighbours, in log E) — the E an estimator that fits markers tends to;
- ``rms_vs_full_mm``: RMS vertex distance at E_true between the backend and the full-space simulation on the
  same mesh (the reduced space's own error, discretisation removed); ``frame0_rms_vs_full_mm`` the same at
  frame 0 alone (the start state: rest or the static equilibrium solved in the subspace);
- ``handle_dev_mm``: the largest distance of a hard-handle vertex from its target at E_true;
- ``marker_rms_mm``: RMS marker residual at E_true.

Backends: ``full`` (rsl's full space on the adapt mesh), and per workspace ``reduced`` (its cubature) and
``reduced-quad`` (every quadrature point: cubature error removed).

With --run-adapt, also `rsl adapt` (online, gn, markers, window 3, E from 0.5 E_true) in a copy of each
workspace (reduced; full on the first): the median relative E error over frames ≥ 8.

    nice .venv/bin/python bench/reduced_accuracy.py CAPTURE LABEL=WS [LABEL=WS ...] [--grid 0.8:1.2:9]
        [--run-adapt | --adapt EARLIER.json]

Cubature study (``--cubature-tols 0.01,0.002``; the table above is carried over from the existing JSON): per
workspace and tolerance, the workspace's subspace gets its cubature refitted the way `rsl train-subspace` fits it
(same poses, median material, ≤ 300 points) and is simulated with the truth's per-frame E from the capture's
start state: RMS vertex distance from the full space and from the same subspace over every quadrature point,
and (``--run-adapt``) `rsl adapt` online, markers, window 3, from 0.5 E_true in a copy of the workspace: median
E error over the settled frames (≥ w + 5 after the start and after each step of E_true, as bench/accuracy.py).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")


def backends(capture, ws: Path, label: str, with_quad: bool):
    """[(name, backend factory)] for one workspace."""
    from stages.artefacts import MeshArtefact, SubspaceArtefact
    from stages.sim.scene import frame_inputs, make_scene
    from stages.window_backends import ReducedSpace
    from stages.subspace import ReducedModel

    mesh = MeshArtefact.load(ws / "mesh.h5")
    ctl = capture.controls()
    scene = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity)
    at = (lambda f: frame_inputs(scene, ctl, f))
    out = []
    if (ws / "subspace.h5").is_file():
        sub = SubspaceArtefact.load(ws / "subspace.h5")
        out.append((f"{label} reduced", lambda: ReducedSpace(ReducedModel.from_artefacts(sub, scene), at)))
        if with_quad:
            out.append((f"{label} reduced-quad",
                        lambda: ReducedSpace(ReducedModel.from_artefacts(sub, scene, cubature=False), at)))
    return mesh, scene, ctl, at, out


def simulate(backend, start: str, T: int, E: float, nu: float) -> np.ndarray:
    """Positions (T, n, 3) from the start state."""
    from stages.windows import StartWindow

    states = StartWindow(backend, start).forward(list(range(T)), np.array([E]), np.array([nu]), None)
    return np.asarray(backend.decode(states))


def measure(name, make, capture, mesh, scene, ctl, at, grid, X_full, E_true, nu) -> dict:
    from stages.sim.scene import apply_hard_targets
    from stages.sweep import marker_loss_curve, parabolic_minimum

    P = capture.markers()
    T = len(P)
    faces = np.asarray(mesh.surface_faces)
    cache = {}
    t0 = time.process_time()

    def X_of(e):
        if e not in cache:
            cache[e] = simulate(make(), capture.start, T, e, nu)
        return cache[e]

    per = marker_loss_curve(X_of, faces, P, [E_true] + list(grid), range(T))
    loss = per.sum(axis=1)
    e_min, i, interior = parabolic_minimum(np.log(grid), loss[1:])
    X = X_of(E_true)
    dev = max(float(np.max(np.linalg.norm(X[t] - apply_hard_targets(scene, at(t), X[t]), axis=1)))
              for t in range(T))
    from stages.sim.markers import bind_markers, marker_residuals

    r = marker_residuals(bind_markers(X[0], faces, P[0]), X, P)
    row = {"backend": name, "E_min_ratio": float(np.exp(e_min)) / E_true, "interior": bool(interior),
           "handle_dev_mm": 1e3 * dev, "marker_rms_mm": 1e3 * float(np.sqrt(np.mean(np.sum(r * r, -1)))),
           "cpu_s": time.process_time() - t0, "grid": [float(g) for g in grid], "loss": loss[1:].tolist()}
    if X_full is not None:
        row["rms_vs_full_mm"] = 1e3 * float(np.sqrt(np.mean(np.sum((X - X_full) ** 2, -1))))
        row["frame0_rms_vs_full_mm"] = 1e3 * float(np.sqrt(np.mean(np.sum((X[0] - X_full[0]) ** 2, -1))))
    return row, X


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("workspaces", nargs="+", help="LABEL=DIR (mesh.h5, subspace.h5)")
    ap.add_argument("--grid", default="0.8:1.2:9", help="E/E_true: lo:hi:count (log-spaced)")
    ap.add_argument("--no-quad", action="store_true", help="skip the full-quadrature reduced rows")
    ap.add_argument("--no-full", action="store_true", help="skip the full-space row")
    ap.add_argument("--out", default=str(ROOT / "docs/results/reduced_accuracy"))
    ap.add_argument("--adapt", default="", help="an earlier run's JSON whose adapt rows (measured by "
                    "--run-adapt) are carried over")
    ap.add_argument("--run-adapt", action="store_true", help="also run rsl adapt (reduced; full on the first "
                    "workspace) in a copy of each workspace and record its settled E error")
    ap.add_argument("--cubature-tols", default="", help="comma-separated cubature tolerances: run the cubature "
                    "study (refit per tolerance, trajectories with the truth's E schedule) instead of the table")
    a = ap.parse_args()
    if a.cubature_tols:
        return cubature_study(a)
    from stages.capture import load_capture, read_truth
    from stages.window_backends import FullSpace

    cap = load_capture(a.capture)
    truth = read_truth(cap)
    E_true, nu = float(truth.young[0, 0]), float(truth.poisson[0, 0])
    lo, hi, k = a.grid.split(":")
    grid = E_true * np.geomspace(float(lo), float(hi), int(k))
    rows, X_full = [], None
    print("| backend | E_min/E_true | RMS vs full (mm) | frame-0 RMS vs full (mm) | hard-handle deviation (mm) | "
          "marker RMS at E_true (mm) | CPU s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for n, (label, d) in enumerate(w.split("=", 1) for w in a.workspaces):
        mesh, scene, ctl, at, bs = backends(cap, Path(d), label, not a.no_quad)
        if n == 0 and not a.no_full:
            bs = [("full", lambda: FullSpace(scene, at, "auto"))] + bs
        for name, make in bs:
            row, X = measure(name, make, cap, mesh, scene, ctl, at, grid, X_full, E_true, nu)
            if name == "full":
                X_full = X
            rows.append(row)
            print(_row(row), flush=True)
    adapt_rows = json.loads(Path(a.adapt).read_text()).get("adapt", []) if a.adapt else []
    if a.run_adapt:
        done = {(r["workspace"], r["space"]) for r in adapt_rows}  # carried over from --adapt: not run again
        adapt_rows += run_adapt(a.capture, [w.split("=", 1) for w in a.workspaces], not a.no_full, done)
        a.adapt = "run"
    out = Path(a.out)
    meta = {"adapt": adapt_rows, "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "capture": str(a.capture), "E_true": E_true, "poisson": nu, "cases": rows}
    if out.with_suffix(".json").is_file():  # a cubature study there is carried over
        meta["cubature"] = json.loads(out.with_suffix(".json").read_text()).get("cubature")
    out.with_suffix(".json").write_text(json.dumps(meta, indent=1))
    lines = ["# Reduced space vs full space on a capture simulated differently", "",
             f"Capture `{a.capture}` (E_true = {E_true:g} Pa, ν = {nu:g}, start {cap.start}, {len(cap.markers())} "
             f"frames); workspaces: {', '.join(a.workspaces)}.  E grid {a.grid} × E_true (log-spaced).", "",
             "| backend | E_min/E_true | RMS vs full (mm) | frame-0 RMS vs full (mm) | hard-handle deviation (mm) | "
             "marker RMS at E_true (mm) | CPU s |", "| --- | --- | --- | --- | --- | --- | --- |"]
    lines += [_row(r) for r in rows]
    if a.adapt:
        lines += ["", "rsl adapt (online, gn, markers, window 3, E initialised at 0.5 E_true) on the same capture: "
                  "median |E − E_true|/E_true over frames ≥ 8.", "",
                  "| workspace | space | median error (%) | median E/E_true |", "| --- | --- | --- | --- |"]
        for r in meta.get("adapt", []):
            if "error" in r:
                lines.append(f"| {r['workspace']} | {r['space']} | failed | — |")
                continue
            lines.append(f"| {r['workspace']} | {r['space']} | {100 * r['median_error']:.1f} | "
                         f"{r['median_ratio']:.3f} |")
    lines += ["", f"Machine: {meta['machine']}; date {meta['date']}.  Produced by `bench/reduced_accuracy.py`."]
    lines += _cubature_lines(meta.get("cubature"))
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")


def run_adapt(capture: Path, workspaces, full: bool, done=frozenset()) -> list[dict]:
    """rsl adapt online gn markers w = 3 from 0.5 E_true in a temporary copy of each workspace: median settled
    (frames ≥ 8) relative E error."""
    import shutil
    import subprocess
    import tempfile

    from stages.artefacts import AdaptArtefact
    from stages.capture import load_capture, read_truth

    truth = read_truth(load_capture(capture))
    rows = []
    jobs = [(label, d, "reduced") for label, d in workspaces]
    if full:
        jobs.insert(0, (workspaces[0][0], workspaces[0][1], "full"))
    for label, d, space in jobs:
        if (label, space) in done:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            ws = Path(tmp) / "ws"
            shutil.copytree(d, ws)
            env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
            p = subprocess.run([sys.executable, "-m", "rsl_cli.app", "adapt", str(capture), "-w", str(ws), "--space",
                                space, "--loss", "markers", "--estimator", "gn", "--window", "3", "--young-init",
                                f"{0.5 * float(truth.young[0, 0]):g}"], capture_output=True, text=True, env=env,
                               cwd=ROOT)
            if p.returncode != 0:
                rows.append({"workspace": label, "space": space, "error": p.stderr[-500:]})
                continue
            art = AdaptArtefact.load(ws / "adapt.h5")
            yt = truth.young[np.asarray(art.frames)][:, 0]
            y = np.asarray(art.young)[:, 0]
            ok = np.arange(len(y)) >= 8
            rows.append({"workspace": label, "space": space,
                         "median_error": float(np.median(np.abs(y[ok] - yt[ok]) / yt[ok])),
                         "median_ratio": float(np.median(y[ok] / yt[ok])), "young_ratio": (y / yt).tolist()})
        print(rows[-1].get("median_error", rows[-1].get("error")), label, space, flush=True)
    return rows


CUBATURE_MAX_POINTS = 300  # train-subspace's default --cubature-tets
CUBATURE_POSES = 40  # train-subspace's default --cubature-poses


def refit_cubature(ws: Path, tol: float, nu_span: list | None = None):
    """WS/subspace.h5 with its cubature refitted at ``tol`` as `rsl train-subspace` fits it (its split, seed 0,
    ``CUBATURE_POSES`` training poses, the stored median E at the ν it was fitted at — extra
    cubature_poisson_fitted, the median cubature_poisson for older files; ``nu_span``: these ν (R,) instead —, the
    viscous forces' rows where it had them, ≤ ``CUBATURE_MAX_POINTS`` points)."""
    from stages.artefacts import MeshArtefact, SnapshotsArtefact, SubspaceArtefact, read_provenance
    from stages.steps.train_subspace import _split, cubature_sampler
    from stages.subspace.cubature import fit_cubature, mesh_quadrature
    from stages.subspace.networks import SubspaceMap

    art = SubspaceArtefact.load(ws / "subspace.h5")
    cfg = read_provenance(ws / "subspace.h5").get("config", {})
    sub = SubspaceMap.from_weights(art.subspace_kind, art.weights)
    mesh, snap = MeshArtefact.load(ws / "mesh.h5"), SnapshotsArtefact.load(ws / "snapshots.h5")
    seed = int(cfg.get("seed", 0))
    tr, _, _ = _split(snap, float(cfg.get("validation_fraction", 0.15)), seed)
    quad = mesh_quadrature(mesh.vertices, mesh.tets, mesh.dm_inv, mesh.rest_volumes)
    region_q = np.asarray(mesh.tet_region)[quad.element]
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(tr), size=min(CUBATURE_POSES, len(tr)), replace=False)
    if nu_span is None:
        nu_span = art.extra.get("cubature_poisson_fitted", [art.extra["cubature_poisson"]])
    nu_span = [np.asarray(nu, np.float64) for nu in nu_span]
    sampler, _ = cubature_sampler(sub, snap, np.asarray(tr)[pick], quad, np.asarray(art.extra["cubature_young"]),
                                  nu_span, region_q, art.extra["material"], bool(art.extra.get("cubature_viscous")))
    ids, w, info = fit_cubature(sampler, region_q, len(mesh.region_names), CUBATURE_MAX_POINTS, tol, seed=seed)
    extra = dict(art.extra, cubature_points=ids.tolist(), cubature_weights=w.tolist(),
                 cubature_error_rel=info["error_rel"], cubature_poisson_fitted=[nu.tolist() for nu in nu_span])
    return SubspaceArtefact(art.subspace_kind, art.dim, art.weights, art.train_error_m, art.val_error_m, extra)


def schedule_trajectory(backend, capture, young: np.ndarray, poisson: np.ndarray) -> np.ndarray:
    """Positions (T, n, 3) from the capture's start state with per-frame E, ν (T, R) (the truth's schedule)."""
    T = len(young)
    s0 = backend.start(young[0], poisson[0], capture.start, None)
    rest = backend.forward(list(range(1, T)), young[1:], poisson[1:], np.stack([s0, s0]))
    return np.asarray(backend.decode(np.concatenate([np.asarray(s0)[None], np.asarray(rest)])))


def settled(young_true: np.ndarray, window: int = 3) -> np.ndarray:
    """(T,) frames ≥ w + 5 after the start and after every change of E_true (bench/accuracy.py's rule)."""
    ok = np.ones(len(young_true), bool)
    ok[: window + 5] = False
    for t in range(1, len(young_true)):
        if np.any(young_true[t] != young_true[t - 1]):
            ok[t: t + window + 5] = False
    return ok


ADAPT_FILES = ("mesh.h5", "cameras.h5", "snapshots.h5")  # what a reduced markers run of adapt reads


def adapt_in_copy(capture: Path, ws: Path, subspace, young_init: float, options=(), files=ADAPT_FILES):
    """`rsl adapt CAPTURE` online, markers, reduced, window 3, E from ``young_init`` Pa (then ``options``) in a
    temporary copy of WS's ``files`` with ``subspace`` (a SubspaceArtefact) as its subspace.h5: (adapt.h5, None),
    or (None, the failed run's stderr)."""
    import shutil
    import subprocess
    import tempfile

    from stages.artefacts import AdaptArtefact

    with tempfile.TemporaryDirectory() as tmp:
        wt = Path(tmp) / "ws"
        wt.mkdir()
        for f in files:
            if (ws / f).is_file():
                shutil.copy(ws / f, wt / f)
        subspace.save(wt / "subspace.h5")
        env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
        p = subprocess.run([sys.executable, "-m", "rsl_cli.app", "adapt", str(capture), "-w", str(wt), "--space",
                            "reduced", "--loss", "markers", "--window", "3", "--young-init", f"{young_init:g}",
                            *options], capture_output=True, text=True, env=env, cwd=ROOT)
        if p.returncode != 0:
            return None, p.stderr
        return AdaptArtefact.load(wt / "adapt.h5"), None


def last_line(stderr: str) -> str:
    """A failed run's last stderr line (≤ 300 characters), "failed" when it printed nothing."""
    return stderr.strip().splitlines()[-1][:300] if stderr.strip() else "failed"


def settled_result(adapt, truth) -> dict:
    """adapt.h5 against the capture's truth, per region of adapt.h5 (the truth's columns in its order), over the
    settled frames (:func:`settled`): the median relative E error, the median ν and the truth's; the median s / frame
    after frame 0; E / E_true per frame."""
    fr = np.asarray(adapt.frames)
    cols = [list(truth.region_names).index(r) for r in adapt.region_names]
    yt = np.asarray(truth.young, float)[fr][:, cols]
    nt = np.asarray(truth.poisson, float)[fr][:, cols]
    ok = settled(yt)
    y, nu = np.asarray(adapt.young, float), np.asarray(adapt.poisson, float)
    return {"regions": list(adapt.region_names),
            "median_error": np.median(np.abs(y - yt)[ok] / yt[ok], axis=0).tolist(),
            "median_poisson": np.median(nu[ok], axis=0).tolist(),
            "poisson_true": np.median(nt[ok], axis=0).tolist(),
            "s_per_frame": float(np.median(np.asarray(adapt.time_total_s)[1:])),
            "young_ratio": (y / yt).tolist()}


def per_region(r: dict, key: str, fmt) -> str:
    """One value per region of a row, named when there are several ("body 1.8, stiff 7.5")."""
    v = r[key]
    return ", ".join(fmt(x) if len(v) == 1 else f"{name} {fmt(x)}" for name, x in zip(r["regions"], v))


def row_specs(specs) -> list[tuple[str, Path, Path]]:
    """The benches' LABEL=CAPTURE:WS arguments as (label, capture, workspace): split at the last = (a label may hold
    "=": "N = 3"), then at the first :."""
    out = []
    for spec in specs:
        label, rest = spec.rsplit("=", 1)
        capture, ws = rest.split(":", 1)
        out.append((label, Path(capture), Path(ws)))
    return out


def earlier_rows(path: Path, append: bool) -> list:
    """The rows of a page's existing JSON ``path`` when a run --append s to it, else none."""
    return json.loads(path.read_text())["rows"] if append and path.is_file() else []


def run_stamp() -> dict:
    """When and where a bench run ended: {"ended": UTC time, "load_average": the 1-minute load, "machine"}."""
    return {"ended": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "load_average": os.getloadavg()[0],
            "machine": f"{platform.machine()} {os.cpu_count()} CPUs, Python {platform.python_version()}"}


def cubature_study(a) -> None:
    """Per workspace × tolerance: refit, trajectories vs full / all points, optionally rsl adapt."""
    from stages.artefacts import MeshArtefact, SubspaceArtefact
    from stages.capture import load_capture, read_truth
    from stages.sim.scene import frame_inputs, make_scene
    from stages.subspace import ReducedModel
    from stages.window_backends import FullSpace, ReducedSpace

    cap = load_capture(a.capture)
    truth = read_truth(cap)
    T = len(cap.markers())
    Y, N = np.asarray(truth.young[:T], float), np.asarray(truth.poisson[:T], float)
    E0 = float(Y[0, 0])
    tols = [float(t) for t in a.cubature_tols.split(",")]
    rows = []
    print("| workspace | r | tol | points | fit error (%) | RMS vs all points (mm) | RMS vs full (mm) | "
          "adapt settled median E error (%) |")
    for label, d in (w.split("=", 1) for w in a.workspaces):
        ws = Path(d)
        mesh = MeshArtefact.load(ws / "mesh.h5")
        ctl = cap.controls()
        scene = make_scene(mesh, ctl, cap.material.model, cap.dt, cap.gravity)
        at = (lambda f: frame_inputs(scene, ctl, f))
        X_full = schedule_trajectory(FullSpace(scene, at, "auto"), cap, Y, N)
        art0 = SubspaceArtefact.load(ws / "subspace.h5")
        X_all = schedule_trajectory(ReducedSpace(ReducedModel.from_artefacts(art0, scene, cubature=False), at),
                                    cap, Y, N)
        rms = lambda A, B: 1e3 * float(np.sqrt(np.mean(np.sum((A - B) ** 2, -1))))  # noqa: E731
        for tol in tols:
            art = refit_cubature(ws, tol)
            X = schedule_trajectory(ReducedSpace(ReducedModel.from_artefacts(art, scene), at), cap, Y, N)
            row = {"workspace": label, "dim": int(art.dim), "tol": tol,
                   "points": len(art.extra["cubature_points"]), "fit_error_rel": art.extra["cubature_error_rel"],
                   "rms_vs_all_points_mm": rms(X, X_all), "rms_vs_full_mm": rms(X, X_full),
                   "all_points_rms_vs_full_mm": rms(X_all, X_full)}
            if a.run_adapt:
                ad, stderr = adapt_in_copy(a.capture, ws, art, 0.5 * E0)
                if ad is None:
                    row["adapt_error"] = stderr[-500:]
                else:
                    yt = Y[np.asarray(ad.frames)]
                    err = np.abs(np.asarray(ad.young) - yt) / yt
                    ok = settled(yt)
                    row["adapt_median_error"] = float(np.max(np.median(err[ok], axis=0)))
                    row["adapt_young_ratio"] = (np.asarray(ad.young) / yt).tolist()
            rows.append(row)
            print(_cub_row(row), flush=True)
    out = Path(a.out)
    meta = json.loads(out.with_suffix(".json").read_text()) if out.with_suffix(".json").is_file() else {}
    study = {"capture": str(a.capture), "start": cap.start, "frames": T, "young_schedule": Y[:, 0].tolist(),
             "rows": rows, "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs",
             "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}
    # one study per capture: a rerun on the same capture replaces its study, others are kept
    meta["cubature"] = [s for s in _studies(meta.get("cubature")) if s["capture"] != study["capture"]] + [study]
    out.with_suffix(".json").write_text(json.dumps(meta, indent=1))
    md = out.with_suffix(".md")
    text = md.read_text() if md.is_file() else ""
    head = text.split(CUBATURE_HEADING)[0].rstrip("\n")
    md.write_text((head + "\n" if head else "") + "\n".join(_cubature_lines(meta["cubature"])) + "\n")


def _studies(c) -> list[dict]:
    """The JSON's cubature studies as a list (one older run stored a single study)."""
    return [] if not c else ([c] if isinstance(c, dict) else list(c))


CUBATURE_HEADING = "## Cubature tolerance"


def _cub_row(r: dict) -> str:
    ad = (f"{100 * r['adapt_median_error']:.1f}" if "adapt_median_error" in r
          else ("failed" if "adapt_error" in r else "—"))
    return (f"| {r['workspace']} | {r['dim']} | {r['tol']:g} | {r['points']} | {100 * r['fit_error_rel']:.2f} | "
            f"{r['rms_vs_all_points_mm']:.2f} | {r['rms_vs_full_mm']:.2f} | {ad} |")


def _cubature_lines(studies) -> list[str]:
    lines = []
    for n, c in enumerate(_studies(studies)):
        lines += _study_lines(c, heading=n == 0)
    return lines


def _study_lines(c: dict, heading: bool) -> list[str]:
    E = np.asarray(c["young_schedule"])
    steps = ", ".join(f"{E[t]:g} Pa from frame {t}" for t in range(len(E)) if t == 0 or E[t] != E[t - 1])
    lines = (["", CUBATURE_HEADING] if heading else []) + ["",
             f"Capture `{c['capture']}` (start {c['start']}, {c['frames']} frames, E_true: {steps}). The workspace's "
             f"subspace with its cubature refitted as `rsl train-subspace` fits it (≤ {CUBATURE_MAX_POINTS} points, "
             f"{CUBATURE_POSES} training poses) at each tolerance, simulated with the truth's E schedule from the "
             "start state; the all-point rows use the same subspace over every quadrature point. Adapt: `rsl adapt` "
             "online, markers, window 3, from 0.5 E_true; median relative E error over the settled frames.", "",
             "| workspace | r | tol | points | fit error (%) | RMS vs all points (mm) | RMS vs full (mm) | "
             "adapt settled median E error (%) |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    lines += [_cub_row(r) for r in c["rows"]]
    seen = {}
    for r in c["rows"]:
        seen.setdefault(r["workspace"], r["all_points_rms_vs_full_mm"])
    lines += ["", "All points (no cubature) vs full space: " +
              ", ".join(f"{k} {v:.2f} mm" for k, v in seen.items()) + ".", "",
              f"Machine: {c['machine']}; date {c['date']}.  Produced by `bench/reduced_accuracy.py --cubature-tols`."]
    return lines


def _row(r: dict) -> str:
    full = f"{r['rms_vs_full_mm']:.2f}" if "rms_vs_full_mm" in r else "—"
    f0 = f"{r['frame0_rms_vs_full_mm']:.2f}" if "frame0_rms_vs_full_mm" in r else "—"
    return (f"| {r['backend']} | {r['E_min_ratio']:.3f}{'' if r['interior'] else ' (grid end)'} | {full} | {f0} | "
            f"{r['handle_dev_mm']:.3f} | {r['marker_rms_mm']:.2f} | {r['cpu_s']:.0f} |")


if __name__ == "__main__":
    main()
