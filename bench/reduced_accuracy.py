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
    from stages.steps.adapt import _FullSpace, _ReducedSpace
    from stages.subspace import ReducedModel

    mesh = MeshArtefact.load(ws / "mesh.h5")
    ctl = capture.controls()
    scene = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity)
    at = (lambda f: frame_inputs(scene, ctl, f))
    out = []
    if (ws / "subspace.h5").is_file():
        sub = SubspaceArtefact.load(ws / "subspace.h5")
        out.append((f"{label} reduced", lambda: _ReducedSpace(ReducedModel.from_artefacts(sub, scene), at)))
        if with_quad:
            out.append((f"{label} reduced-quad",
                        lambda: _ReducedSpace(ReducedModel.from_artefacts(sub, scene, cubature=False), at)))
    return mesh, scene, ctl, at, out


def simulate(backend, start: str, T: int, E: float, nu: float) -> np.ndarray:
    """Positions (T, n, 3) from the start state."""
    from stages.steps.adapt import StartWindow

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
    from stages.adapt_loss import bind_markers, marker_residuals

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
    a = ap.parse_args()
    from stages.capture import load_capture, read_truth
    from stages.steps.adapt import _FullSpace

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
            bs = [("full", lambda: _FullSpace(scene, at, "auto"))] + bs
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


def _row(r: dict) -> str:
    full = f"{r['rms_vs_full_mm']:.2f}" if "rms_vs_full_mm" in r else "—"
    f0 = f"{r['frame0_rms_vs_full_mm']:.2f}" if "frame0_rms_vs_full_mm" in r else "—"
    return (f"| {r['backend']} | {r['E_min_ratio']:.3f}{'' if r['interior'] else ' (grid end)'} | {full} | {f0} | "
            f"{r['handle_dev_mm']:.3f} | {r['marker_rms_mm']:.2f} | {r['cpu_s']:.0f} |")


if __name__ == "__main__":
    main()
