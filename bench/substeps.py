"""`rsl adapt --substeps S` on captures whose truth is finer in time: settled E error and per-frame time.

Captures by `rsl synth` of sample_data/bar pulled by a cable (constant E_true), truth on P2 tets with 3
substeps per frame and hard handles, for each start state (rest: released at t = 0, a large fast motion;
equilibrium: at rest under gravity at t = 0).  rsl adapt runs online on a P2 mesh from
`rsl tetrahedralize --order 2` (coarsened by --max-tets), markers, the gn estimator, window 3, E initialised
at 0.5 E_true, in full and reduced space, with --substeps 1, 2, 3.  Per row: the median relative error of E
over the settled frames (≥ w + 5 after the start), the median settled E / E_true, and the median per-frame
time of adapt (ratio against --substeps 1 of the same start and space, measured in the same run).

    nice .venv/bin/python bench/substeps.py [--frames 30] [--starts rest,equilibrium] [--spaces full,reduced]
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
WINDOW = 3
TRUTH_SUBSTEPS = 3


def run_start(work: Path, start: str, frames: int, spaces, substeps, max_tets: int) -> list[dict]:
    from stages.artefacts import AdaptArtefact, MeshArtefact
    from stages.capture import load_capture, read_truth

    cap = pl.foreign_capture(work / f"cap_{start}", pl.bar_cable(young=E_TRUE), start=start, frames=frames,
                             cameras=3, resolution=32, substeps=TRUTH_SUBSTEPS, poisson=POISSON)
    ws = pl.mesh(cap, work / f"ws_{start}", order=2, max_tets=max_tets, calibrate=False)
    if "reduced" in spaces:
        pl.subspace(cap, ws, frames=frames, dim=12)
    truth = read_truth(load_capture(cap))
    n_vertices = MeshArtefact.load(ws / "mesh.h5").n_vertices
    rows = []
    for space in spaces:
        for S in substeps:
            base = {"start": start, "space": space, "substeps": S, "vertices": n_vertices}
            try:
                t_run = pl.adapt(cap, ws, "--space", space, "--loss", "markers", "--estimator", "gn",
                                 "--window", WINDOW, "--young-init", f"{0.5 * E_TRUE:g}", "--substeps", S)
            except RuntimeError as e:
                rows.append({**base, "error": str(e)[-500:]})
                print(_row(rows[-1]), flush=True)
                continue
            a = AdaptArtefact.load(ws / "adapt.h5")
            yt = truth.young[np.asarray(a.frames)][:, 0]
            y = np.asarray(a.young)[:, 0]
            ok = np.arange(len(y)) >= WINDOW + 5
            rows.append({**base, "frames": int(len(y)), "settled_frames": int(ok.sum()),
                         "median_error": float(np.median(np.abs(y[ok] - yt[ok]) / yt[ok])),
                         "median_ratio": float(np.median(y[ok] / yt[ok])),
                         "time_per_frame_s": float(np.median(a.time_total_s)), "adapt_s": t_run,
                         "young": y.tolist(), "young_true": yt.tolist()})
            print(_row(rows[-1]), flush=True)
    for r in rows:  # time ratio against --substeps 1 of the same start and space (this run)
        ref = [q for q in rows if q["space"] == r["space"] and q["substeps"] == 1 and "error" not in q]
        if "error" not in r and ref:
            r["time_ratio"] = r["time_per_frame_s"] / ref[0]["time_per_frame_s"]
    return rows


def _row(r: dict) -> str:
    if "error" in r:
        return f"| {r['start']} | {r['space']} | {r['substeps']} | failed | — | — | — |"
    ratio = f"{r['time_ratio']:.2f}" if "time_ratio" in r else "—"
    return (f"| {r['start']} | {r['space']} | {r['substeps']} | {100 * r['median_error']:.1f} | "
            f"{r['median_ratio']:.3f} | {r['time_per_frame_s']:.2f} | {ratio} |")


def window_cost(work: Path, start: str, spaces, substeps, reps: int = 3) -> list[dict]:
    """CPU seconds (time.process_time, less sensitive to other processes than wall time) of one gn window
    linearisation — forward, 26 sensitivity directions (θ and the state correction), adjoint — over frames
    10–12, per space and S, the S values interleaved in each repetition; median over ``reps``."""

    from stages.artefacts import MeshArtefact, SubspaceArtefact
    from stages.capture import load_capture
    from stages.sim.scene import frame_inputs, make_scene
    from stages.windows import StartWindow
    from stages.window_backends import FullSpace, ReducedSpace, substepped
    from stages.subspace import ReducedModel

    cap = load_capture(work / f"cap_{start}")
    ws = work / f"ws_{start}"
    mesh = MeshArtefact.load(ws / "mesh.h5")
    controls = cap.controls()
    scene = make_scene(mesh, controls, cap.material.model, cap.dt, cap.gravity)
    E, nu = np.array([E_TRUE]), np.array([POISSON])
    frames = [10, 11, 12]
    out = []
    for space in spaces:
        backends, befores = {}, {}
        for S in substeps:
            at = (lambda f: frame_inputs(scene, controls, f))
            b = (FullSpace(scene, at, "auto") if space == "full" else
                 ReducedSpace(ReducedModel.from_artefacts(SubspaceArtefact.load(ws / "subspace.h5"), scene), at))
            b = substepped(b, S, at)
            X = StartWindow(b, start).forward(list(range(frames[0])), E, nu, None)
            backends[S], befores[S] = b, X[-2:]
        k = 26
        times = {S: [] for S in substeps}
        for _ in range(reps):
            for S in substeps:
                b, before = backends[S], befores[S]
                dim = before.shape[1:]
                de, dn = np.zeros((k, 1)), np.zeros((k, 1))
                de[0, 0], dn[1, 0] = E_TRUE, 0.01
                db = np.random.default_rng(0).normal(size=(k, 2) + dim) * 1e-4
                db[:2] = 0.0
                Ew, nw = np.tile(E, (3, 1)), np.tile(nu, (3, 1))
                t0 = time.process_time()
                st = b.forward(frames, Ew, nw, before)
                b.state_sensitivity(frames, Ew, nw, st, before, de, dn, db)
                b.backward(frames, Ew, nw, st, before, np.ones_like(b.decode(st)))
                times[S].append(time.process_time() - t0)
        for S in substeps:
            out.append({"start": start, "space": space, "substeps": S, "window_cpu_s": float(np.median(times[S])),
                        "window_cpu_ratio": float(np.median(times[S]) / np.median(times[substeps[0]]))})
            print(f"| {space} | {S} | {out[-1]['window_cpu_s']:.2f} | {out[-1]['window_cpu_ratio']:.2f} |", flush=True)
    return out


def summary(rows: list[dict]) -> str:
    """Per space and S: the mean over the start states of the settled error and of the time ratio against S = 1;
    per space, the smallest S whose mean error is within 1 percentage point of that space's lowest."""
    import dataclasses

    from stages.steps.adapt import AdaptConfig

    defaults = {f.name: f.default for f in dataclasses.fields(AdaptConfig)}
    ok = [r for r in rows if "error" not in r]
    lines, picks = [], {}
    for space in sorted({r["space"] for r in ok}):
        mean_err = {}
        for S in sorted({r["substeps"] for r in ok if r["space"] == space}):
            sub = [r for r in ok if r["space"] == space and r["substeps"] == S]
            mean_err[S] = float(np.mean([r["median_error"] for r in sub]))
            tr = [r["time_ratio"] for r in sub if "time_ratio" in r]
            each = ", ".join(f"{r['start']} {100 * r['median_error']:.1f} %" for r in sub)
            lines.append(f"- {space}, --substeps {S}: mean settled error {100 * mean_err[S]:.1f} % over "
                         f"{len(sub)} start state(s) ({each}), per-frame time {np.mean(tr):.2f}× that of "
                         f"--substeps 1.")
        best = min(mean_err.values())
        pick = picks[space] = min(S for S, e in mean_err.items() if e <= best + 0.01)
        lines.append(f"- {space}: the smallest S whose mean settled error is within 1 percentage point of the "
                     f"lowest ({100 * best:.1f} %) is S = {pick}.")
    if defaults["space"] in picks:
        lines.append(f"\nrsl adapt's default space is {defaults['space']}: its pick above is S = "
                     f"{picks[defaults['space']]}; the default of --substeps is {defaults['substeps']}.")
    return "\n".join(lines)


def write(rows: list[dict], out: Path, plan: dict, measured: dict | None = None, cost: list | None = None) -> None:
    """docs/results/substeps.{md,json,png}; ``measured``: a previous run's JSON (its machine and date kept)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = measured or {
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "plan": plan,
        "load_average_end": list(os.getloadavg()), "cases": rows, "window_cost": cost or [], "window_cost_reps": 3}
    (out / "substeps.json").write_text(json.dumps(data, indent=1))
    head = ("| start | space | --substeps | median \\|E−E_true\\|/E_true (%) | median E/E_true | s / frame | "
            "time / time(S=1) |\n| --- | --- | --- | --- | --- | --- | --- |")
    table = "\n".join([head] + [_row(r) for r in rows])
    nv = sorted({r["vertices"] for r in rows})
    cost = ""
    if data.get("window_cost"):
        wc = data["window_cost"]
        cost = ("CPU time of one gn window "
                f"linearisation (forward, 26 sensitivity directions, adjoint; frames 10–12, start {wc[0]['start']}, "
                f"S values interleaved, median of {data.get('window_cost_reps', 3)}):\n\n| space | --substeps | "
                "CPU s | CPU / CPU(S=1) |\n| --- | --- | --- | --- |\n"
                + "\n".join(f"| {c['space']} | {c['substeps']} | {c['window_cpu_s']:.2f} | {c['window_cpu_ratio']:.2f} |"
                             for c in wc) + "\n\n")
    la = data.get("load_average_end")
    load = f" (load average {la[0]:.1f} at the end: the times are under that load)" if la else ""
    md = (f"# rsl adapt --substeps: a capture finer in time than one step per frame\n\n"
          f"Truth: sample_data/bar pulled by a cable, P2 tets, {TRUTH_SUBSTEPS} substeps per frame, hard handles "
          f"(`rsl synth --truth-order 2 --substeps {TRUTH_SUBSTEPS} --handles hard --start rest|equilibrium`), "
          f"E_true = {E_TRUE:g} Pa, ν = {POISSON}, {plan['frames']} frames, 3 cameras, markers.  rsl adapt: "
          f"P2 mesh from `rsl tetrahedralize --order 2 --max-tets {plan['max_tets']}` ({', '.join(map(str, nv))} "
          f"vertices), markers, gn estimator, online, window {WINDOW}, E initialised at 0.5 E_true, reduced "
          f"space r = 12.  Settled frames: ≥ w + 5 after the start.\n\n{table}\n\n{summary(rows)}\n\n{cost}"
          f"Machine: {data['machine']}{load}; date {data['date']}.  Produced by `bench/substeps.py`.\n\n"
          f"![E over time](substeps.png)\n")
    (out / "substeps.md").write_text(md)
    ok = [r for r in rows if "error" not in r]
    keys = sorted({(r["start"], r["space"]) for r in ok})
    fig, axes = plt.subplots(1, max(1, len(keys)), figsize=(3.2 * max(1, len(keys)), 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        sub = [r for r in ok if (r["start"], r["space"]) == key]
        ax.plot(sub[0]["young_true"], "k-", lw=2, label="truth")
        for r in sub:
            ax.plot(r["young"], label=f"S = {r['substeps']}")
        ax.set_title(f"start {key[0]}, {key[1]}", fontsize=9)
        ax.set_xlabel("frame")
        ax.set_ylabel("E (Pa)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "substeps.png", dpi=100)
    print(table)
    print(summary(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_substeps"))
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--starts", default="rest,equilibrium")
    ap.add_argument("--spaces", default="full,reduced")
    ap.add_argument("--substeps", default="1,2,3")
    ap.add_argument("--max-tets", type=int, default=500)
    ap.add_argument("--from-json", type=Path, default=None, help="rewrite the page from a previous run's JSON")
    ap.add_argument("--cost", default="", help="with --from-json: also measure the CPU time of one window on the "
                    "captures of this start state in --work")
    a = ap.parse_args()
    if a.from_json is not None:
        data = json.loads(a.from_json.read_text())
        if a.cost:  # add the CPU cost of one window (measured now) to that run's page
            data["window_cost"] = window_cost(a.work, a.cost, data["plan"]["spaces"], data["plan"]["substeps"])
            data["window_cost_reps"] = 3
            data["window_cost_date"] = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        write(data["cases"], a.out, data["plan"], data)
        return
    a.work.mkdir(parents=True, exist_ok=True)
    plan = {"frames": a.frames, "starts": a.starts.split(","), "spaces": a.spaces.split(","),
            "substeps": [int(s) for s in a.substeps.split(",")], "max_tets": a.max_tets}
    print("| start | space | --substeps | median err (%) | median E/E_true | s / frame | time ratio |", flush=True)
    rows = []
    for start in plan["starts"]:
        rows += run_start(a.work, start, a.frames, plan["spaces"], plan["substeps"], a.max_tets)
    cost = window_cost(a.work, plan["starts"][0], plan["spaces"], plan["substeps"])
    write(rows, a.out, plan, None, cost)


if __name__ == "__main__":
    main()
