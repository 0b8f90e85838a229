"""Loss sweep: is each loss lowest at the true E on a capture rsl did not make?

A synthetic capture whose truth uses another discretisation than rsl adapt (quadratic tets — on a once
refined mesh in the full mode —, 3 implicit substeps per frame or --truth-substeps N, hard Dirichlet handles)
is made by `rsl synth` from sample_data/bar (a cable pulls the free end of the bar held at the other, constant E),
for each start state (equilibrium, rest).  Over a grid of fixed E (ν held at the truth's), the whole-sequence
loss is computed with the full-space forward simulation from the capture's declared start
(stages/sweep.py): the marker loss on rsl's own discretisations of the shipped mesh (P1, P1 refined once,
P2), and the vision loss (L1 image loss of the Gaussians fitted by the pipeline: calibrate → tetrahedralize → segment →
fit-gaussians) on the workspace's mesh.  The minimum is the vertex of the parabola in log E
through the grid minimum and its neighbours; its ratio to E_true is the loss's bias.

    .venv/bin/python bench/loss_sweep.py [--quick] [--no-vision] [--out docs/results]

--quick: P2 truth on the shipped mesh (no refinement); full: P2 on the once-refined mesh; both 20
frames and 9 grid points (--scales: other E/E_true values).  --starts equilibrium / --starts rest run one start
state (two processes can share the work), --rows picks the rows, --merge A.json B.json writes the report of
separate runs (a row of a later file replaces the same start/truth/loss/mesh row of an earlier one).  With
RSL_BENCH_REUSE=1 in the environment, captures, meshes and Gaussians already in --work are reused.

Two vision rows test a cause of the vision loss's bias each, on the same workspace: "visions3" simulates 3
implicit substeps per frame (the truth's time step), "visionanchor" binds the Gaussians, for every E of the grid,
to the fit frame simulated with E_true (the anchor's own dependence on E switched off).  "p2adapt" and
"visionadapt" simulate as many substeps per frame as rsl adapt does by default (AdaptConfig.substeps): the loss
its estimator minimises.  --truth-substeps 24 makes a truth converged in time (docs/results/calibration_frames.md:
24 and 48 agree within 0.5 %), so that a row's bias is rsl's, not the 3-substep truth's own time step.
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
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402

E_TRUE = 1.0e5
POISSON = 0.45


def make_capture(out: Path, start: str, frames: int, refine: int, resolution: int, substeps: int = 3) -> float:
    """The truth capture (P2, refined ``refine`` times, ``substeps`` implicit steps per frame, hard handles);
    returns synth seconds (0 when RSL_BENCH_REUSE finds it made)."""
    t0 = time.perf_counter()
    pl.foreign_capture(out, pl.bar_cable(young=E_TRUE), start=start, frames=frames, cameras=2,
                       resolution=resolution, refine=refine, substeps=substeps, poisson=POISSON)
    return time.perf_counter() - t0


def shipped_mesh(density: float, order: int):
    """rsl's mesh of the shipped object: sample_data/bar's tets, placed as rsl synth placed them."""
    import meshio

    from stages.artefacts import mesh_artefact
    from stages.steps.synth import prepare_mesh

    m = meshio.read(str(ROOT / "sample_data/bar/object.mesh"))
    pm = prepare_mesh(np.asarray(m.points, float), np.asarray(m.cells_dict["tetra"]), 0.25, "")
    return mesh_artefact(pm.vertices, pm.tets, density, order=order)


def pipeline(cap: Path, ws: Path) -> None:
    """cameras, masks, mesh and Gaussians for the vision loss (made afresh on every run unless RSL_BENCH_REUSE)."""
    pl.mesh(cap, ws)
    pl.gaussians(cap, ws, frame=0, segment_method="background")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="sized-down run (see the module docstring)")
    ap.add_argument("--no-vision", action="store_true", help="marker loss only (no pipeline)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_loss_sweep"))
    ap.add_argument("--starts", default="equilibrium,rest", help="start states to run, comma-separated")
    ap.add_argument("--rows", default="p1,p1r,p2,p2s3,p2adapt,wrongstart,vision,visionadapt",
                    help="rows to compute: p1, p1r (P1 refined once), p2, p2s3 (P2 with 3 substeps per frame), "
                         "p2adapt (P2 with rsl adapt's default substeps per frame), "
                         "wrongstart (P1 assuming the other start), vision, visions3 (vision, 3 substeps per "
                         "frame), visionadapt (vision, rsl adapt's default substeps per frame), visionanchor "
                         "(vision, Gaussians bound to the fit frame simulated with E_true)")
    ap.add_argument("--truth-substeps", type=int, default=3,
                    help="implicit steps per frame of the truth (default 3; 24: a truth converged in time, "
                         "docs/results/calibration_frames.md)")
    ap.add_argument("--scales", default="", help="grid of E / E_true, comma-separated (default: 9 values, "
                                                "0.55-1.4)")
    ap.add_argument("--merge", type=Path, nargs="*", default=None,
                    help="only merge the loss_sweep.json files of separate runs (e.g. one per start) into --out")
    a = ap.parse_args()
    if a.merge is not None:
        parts = [json.loads(p.read_text()) for p in a.merge]
        merged: dict = {}  # a later file's row replaces an earlier one with the same start, loss and mesh
        for d in parts:  # rows measured before each row had its date: their file's
            for c in d["cases"]:
                c.setdefault("date", str(d.get("date", "—"))[:16].replace("T", " "))
        for c in (c for d in parts for c in d["cases"]):
            ws = a.work / f"ws_{c['start']}"  # runs made before the label named the element order: read it
            if c["loss"] == "vision" and "tetrahedralize" not in c["adapt_mesh"] and (ws / "mesh.h5").is_file():
                c["adapt_mesh"] = _vision_label(ws)
            merged[(c["start"], _truth_substeps(c), c["loss"], c["adapt_mesh"])] = c
        cases = list(merged.values())
        starts = list(dict.fromkeys(c["start"] for c in cases))
        cases.sort(key=lambda c: starts.index(c["start"]))  # new rows beside their start's
        write(cases, a.out, parts[0]["mode"] == "quick")
        return

    from stages.artefacts import KIND_FILES, MeshArtefact
    from stages.capture import load_capture
    from stages.steps.adapt import AdaptConfig
    from stages.sweep import sweep

    s_adapt = AdaptConfig.substeps  # rsl adapt's substeps per frame (the dataclass default)

    frames, refine = (20, 0) if a.quick else (20, 1)
    scales = (np.array([0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.25, 1.4]) if a.quick else
              np.array([0.55, 0.65, 0.75, 0.85, 0.92, 1.0, 1.08, 1.2, 1.4]))
    if a.scales:
        scales = np.array(sorted(float(x) for x in a.scales.split(",")))
    grid = E_TRUE * scales
    a.work.mkdir(parents=True, exist_ok=True)
    cases = []
    for start in a.starts.split(","):
        n_truth = a.truth_substeps
        tag = "" if n_truth == 3 else f"_n{n_truth}"  # the folders of a truth with other substeps than 3
        cap_dir = a.work / f"bar_cable_{start}{tag}"
        t_synth = make_capture(cap_dir, start, frames, refine, 96, n_truth)
        cap = load_capture(cap_dir)
        truth_desc = f"P2{' refined ×1' if refine else ''}, {n_truth} substeps, hard handles"
        print(f"capture {cap_dir.name}: synth {t_synth:.0f} s", flush=True)
        rows = a.rows.split(",")
        for key, label, order, ref, sub in (("p1", "P1", 1, 0, 1), ("p1r", "P1 refined ×1", 1, 1, 1),
                                            ("p2", "P2", 2, 0, 1), ("p2s3", "P2, 3 substeps per frame", 2, 0, 3),
                                            ("p2adapt", f"P2, {s_adapt} substeps per frame (rsl adapt's default)", 2,
                                             0, s_adapt)):
            if key not in rows:
                continue
            t0 = time.perf_counter()
            res = sweep(cap, shipped_mesh(cap.density, order), grid, "markers", refine=ref, poisson=POISSON,
                        substeps=sub)
            cases.append(_case(start, truth_desc, n_truth, "markers", label, res, time.perf_counter() - t0))
            print(_row(cases[-1]), flush=True)
            _partial(cases, a.out, a.quick)
        # the start convention's weight: rsl's P1 model assuming the other start state than the capture's
        other = "rest" if start == "equilibrium" else "equilibrium"
        if "wrongstart" in rows:
            t0 = time.perf_counter()
            res = sweep(cap, shipped_mesh(cap.density, 1), grid, "markers", poisson=POISSON, start=other)
            cases.append(_case(start, truth_desc, n_truth, "markers", f"P1, assuming start = {other}", res,
                               time.perf_counter() - t0))
            print(_row(cases[-1]), flush=True)
            _partial(cases, a.out, a.quick)
        for key, suffix, kw in (("vision", "", {}), ("visionanchor", ", Gaussians bound to frame 0 simulated with "
                                                                  "E_true", {"anchor_young": E_TRUE}),
                                ("visions3", ", 3 substeps per frame", {"substeps": 3}),
                                ("visionadapt", f", {s_adapt} substeps per frame (rsl adapt's default)",
                                 {"substeps": s_adapt})):
            if a.no_vision or key not in rows:
                continue
            ws = a.work / f"ws_{start}{tag}"
            try:
                pipeline(cap_dir, ws)
                mesh = MeshArtefact.load(ws / KIND_FILES["mesh"])
                t0 = time.perf_counter()
                res = sweep(cap, mesh, grid, "vision", workspace=ws, poisson=POISSON, **kw)
            except (SystemExit, Exception) as e:  # the pipeline is another helper's: report, keep the markers
                print(f"vision sweep for start = {start} failed: {e}", flush=True)
                continue
            cases.append(_case(start, truth_desc, n_truth, "vision", _vision_label(ws) + suffix, res,
                               time.perf_counter() - t0))
            print(_row(cases[-1]), flush=True)
            _partial(cases, a.out, a.quick)
    write(cases, a.out, a.quick)


def _partial(cases: list[dict], out: Path, quick: bool) -> None:
    """The rows so far, in out/loss_sweep.partial.json (a long run that is stopped keeps what it measured)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "loss_sweep.partial.json").write_text(json.dumps({"mode": "quick" if quick else "full", "cases": cases}))


def _vision_label(ws: Path) -> str:
    """'P1|P2 (rsl tetrahedralize)': the element order of the workspace's mesh.h5 (the Gaussians' mesh)."""
    from stages.artefacts import KIND_FILES, MeshArtefact

    tets = MeshArtefact.load(ws / KIND_FILES["mesh"]).tets
    return f"P{2 if np.asarray(tets).shape[1] == 10 else 1} (rsl tetrahedralize)"


def _truth_substeps(c: dict) -> int:
    """The truth's implicit steps per frame of a row (rows measured before it was recorded: 3, their truth's)."""
    return int(c.get("truth_substeps", 3))


def _at_adapt_default(cases: list[dict]) -> str:
    """' At rsl adapt's default substeps per frame (the loss it minimises): against the N-substep truth k of m within
    3 % (loss start E_min/E_true, ...); ...' from the rows so labelled, or ''."""
    rows = [c for c in cases if "rsl adapt's default" in c["adapt_mesh"]]
    parts = []
    for n in sorted({_truth_substeps(c) for c in rows}):
        cs = [c for c in rows if _truth_substeps(c) == n]
        ok = sum(abs(c["ratio"] - 1) <= 0.03 for c in cs)
        each = ", ".join(f"{c['loss']} {c['start']} {c['ratio']:.3f}" for c in cs)
        parts.append(f"against the {n}-substep truth {ok} of {len(cs)} within 3 % ({each})")
    return f"  At rsl adapt's default substeps per frame (the loss it minimises): {'; '.join(parts)}." if parts else ""


def _case(start, truth, truth_substeps, loss, adapt_mesh, res, seconds) -> dict:
    return {"start": start, "truth": truth, "truth_substeps": truth_substeps, "loss": loss, "adapt_mesh": adapt_mesh,
            "n_vertices": res.info["n_vertices"], "n_elements": res.info["n_elements"],
            "frames": res.info["frames"], "young_true": E_TRUE, "young_min": res.young_min,
            "ratio": res.young_min / E_TRUE, "interior": res.interior, "grid": res.young.tolist(),
            "loss_values": res.loss.tolist(), "seconds": seconds,
            "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M")}


def _row(c: dict) -> str:
    edge = "" if c["interior"] else " (grid end)"
    g = np.asarray(c["grid"]) / c["young_true"]
    return (f"| {c['start']} | {_truth_substeps(c)} | {c['loss']} | {c['adapt_mesh']} | {c['n_vertices']} | "
            f"{len(g)}: {g.min():.2f}–{g.max():.2f} | "
            f"{c['young_min']:.4g}{edge} | {c['ratio']:.3f} | {100 * (c['ratio'] - 1):+.1f} % | "
            f"{c['seconds']:.0f} | {c.get('date', '—')} |")


def write(cases: list[dict], out: Path, quick: bool) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "mode": "quick" if quick else "full", "cases": cases}
    (out / "loss_sweep.json").write_text(json.dumps(data, indent=1))
    head = ("| start | truth substeps per frame | loss | rsl's mesh | vertices | grid: points, E/E_true | "
            "E at the minimum (Pa) | E_min / E_true | bias | time (s) | measured (UTC) |\n"
            "| --- | ---: | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    table = "\n".join([head] + [_row(c) for c in cases])
    within = [c for c in cases if abs(c["ratio"] - 1) <= 0.03]
    default_rows = _at_adapt_default(cases)
    md = (f"# Loss sweep: where each loss is lowest\n\n"
          f"Truth: {cases[0]['truth'].split(', ')[0]}, hard handles, N substeps per frame (column 2) "
          f"(`rsl synth --truth-order 2 --substeps N --handles hard`), "
          f"sample_data/bar pulled by a cable, E_true = {E_TRUE:g} Pa, ν = {POISSON}; frames "
          f"{cases[0]['frames'][0]}–{cases[0]['frames'][1] - 1}; mode {data['mode']}.  Whole-sequence loss over a "
          f"grid of fixed E (per row), full-space simulation from the capture's declared start, minimum refined by "
          f"a parabola in log E.\n\n{table}\n\n"
          f"{len(within)} of {len(cases)} minima lie within 3 % of E_true.{default_rows}\n\n"
          f"Machine: {data['machine']}; date {data['date']}.  Produced by `bench/loss_sweep.py"
          f"{' --quick' if quick else ''}`.\n\n![loss over E](loss_sweep.png)\n")
    (out / "loss_sweep.md").write_text(md)
    starts = sorted({c["start"] for c in cases})
    truths = sorted({_truth_substeps(c) for c in cases})  # one row of panels per truth time step
    fig, axes = plt.subplots(len(truths), len(starts), figsize=(6.5 * len(starts), 4.5 * len(truths)),
                             squeeze=False)
    for (n, st), ax in zip([(n, st) for n in truths for st in starts], axes.ravel()):
        for c in (c for c in cases if c["start"] == st and _truth_substeps(c) == n):
            y = np.asarray(c["loss_values"])
            ax.plot(np.asarray(c["grid"]) / E_TRUE, y / y.min(), "o-", ms=3, label=f"{c['loss']}, {c['adapt_mesh']}")
            ax.axvline(c["ratio"], color=ax.lines[-1].get_color(), ls=":", lw=1)
        ax.axvline(1.0, color="k", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("E / E_true")
        ax.set_ylabel("loss / its minimum")
        ax.set_title(f"start = {st}, truth {n} substeps per frame")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "loss_sweep.png", dpi=110)
    print(table)


if __name__ == "__main__":
    main()
