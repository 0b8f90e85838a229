"""`rsl adapt --substeps S` against truths finer in time, on the bar whose E steps E0 → 2E0 → 4E0.

The accuracy captures (bench/accuracy.py's bar: sample_data/bar pulled by a cable, 36 frames, E steps at frames
12 and 24, truth on P2 tets with hard handles, either start state) simulated with N implicit-Euler substeps per
frame for each N of --truth-substeps.  After an instantaneous step of E the undamped bar rings; how much of that
ringing survives depends on the truth's own time step (docs/results/forces_converged.md), and rsl adapt's model of
it on S, the implicit-Euler steps per frame it simulates (`--substeps`).  rsl adapt runs online with markers, the
default estimator, window 3, E initialised at 0.5 E0, on its own P2 mesh (`rsl tetrahedralize --order 2
--max-tets 1500`), reduced space r = 30 (and full space where --spaces says so), for each S of --substeps.

Per row: the median and the largest relative error of E over the settled frames (≥ w + 5 frames after the start and
after each step of E_true), the largest error in the w + 5 frames after each step (the transient), and the median
per-frame time of adapt (adapt.h5 time_total_s) with its ratio against S = 1 of the same capture and space, this run.

    nice .venv/bin/python bench/time_step.py [--truth-substeps 3,12] [--starts equilibrium,rest] \\
        [--substeps 1,2,3,6] [--spaces reduced] [--work /tmp/rsl_time_step] [--out docs/results]
    .venv/bin/python bench/time_step.py --from-json RUN.json [RUN2.json ...]   (the page again from measured runs,
        e.g. after a default changed, or two runs' rows together)

With RSL_BENCH_REUSE=1, captures, meshes and subspaces already in --work are reused (bench/_pipeline.py).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402
from accuracy import (E0, MAX_TETS, POISSON, SUBSPACE_DIM, WINDOW, scene_args,  # noqa: E402  (that bench's captures,
                      settled_mask)  # adapt mesh, subspace and settled frames)

FRAMES = 36
WORKSPACE_FILES = ("cameras.h5", "mesh.h5", "subspace.h5", "snapshots.h5")


def steps_of(young_true: np.ndarray) -> list[int]:
    """Frames where E_true changes (any region), (T, R) → list."""
    return [t for t in range(1, len(young_true)) if np.any(young_true[t] != young_true[t - 1])]


def run_case(work: Path, start: str, truth_substeps: int, spaces, substeps) -> list[dict]:
    from stages.artefacts import AdaptArtefact
    from stages.capture import load_capture, read_truth

    cap = pl.foreign_capture(work / f"bar_{start}_truth{truth_substeps}", scene_args("bar", FRAMES), start=start,
                             frames=FRAMES, poisson=POISSON, substeps=truth_substeps)
    # one mesh and subspace per start state, made from the capture with the fewest truth substeps: the object, the
    # controls and the start are the same for every N, so adapt's model is the same for every truth
    ws = work / f"ws_bar_{start}"
    pl.mesh(cap, ws, order=2, max_tets=MAX_TETS)  # (made once per run: bench/_pipeline.skip)
    pl.subspace(cap, ws, frames=FRAMES, dim=SUBSPACE_DIM)
    truth = np.asarray(read_truth(load_capture(cap)).young, float).reshape(FRAMES, -1)
    ok, steps = settled_mask(truth), steps_of(truth)
    rows = []
    for space in spaces:
        for S in substeps:
            base = {"start": start, "truth_substeps": truth_substeps, "space": space, "substeps": S}
            run = work / f"run_{start}_N{truth_substeps}_{space}_S{S}"
            shutil.rmtree(run, ignore_errors=True)
            run.mkdir(parents=True)
            for f in WORKSPACE_FILES:
                shutil.copy(ws / f, run / f)
            try:
                pl.adapt(cap, run, "--space", space, "--loss", "markers", "--window", WINDOW, "--young-init",
                         f"{0.5 * E0:g}", "--substeps", S)
            except RuntimeError as e:
                rows.append({**base, "error": str(e)[-500:]})
                print(_row(rows[-1]), flush=True)
                continue
            a = AdaptArtefact.load(run / "adapt.h5")
            fr = np.asarray(a.frames)
            y, yt = np.asarray(a.young)[:, 0], truth[fr, 0]
            err = np.abs(y / yt - 1.0)
            m = ok[fr]
            after = [float(err[(fr >= s) & (fr < s + WINDOW + 5)].max()) for s in steps]
            rows.append({**base, "settled_frames": int(m.sum()), "median_error": float(np.median(err[m])),
                         "max_error": float(err[m].max()), "max_error_after_steps": after,
                         "time_per_frame_s": float(np.median(np.asarray(a.time_total_s)[WINDOW:])),
                         "young": y.tolist(), "young_true": yt.tolist()})
            print(_row(rows[-1]), flush=True)
    for r in rows:  # time ratio against S = 1 of the same capture and space (this run)
        ref = [q for q in rows if q["space"] == r["space"] and q["substeps"] == 1 and "error" not in q]
        if "error" not in r and ref:
            r["time_ratio"] = r["time_per_frame_s"] / ref[0]["time_per_frame_s"]
    return rows


def window_cost(work: Path, steps_per_frame: list[int]) -> list[dict]:
    """CPU s of one gn window linearisation (forward, 26 sensitivity directions, adjoint; frames 10–12) in the
    reduced space per S, the S values interleaved, median of 3 (bench/substeps.py's window_cost, which reads
    WORK/cap_START and WORK/ws_START: links to this bench's equilibrium capture with N = 3 and its workspace)."""
    import tempfile

    import substeps as substeps_bench

    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "cap_equilibrium").symlink_to(work / "bar_equilibrium_truth3")
        (Path(tmp) / "ws_equilibrium").symlink_to(work / "ws_bar_equilibrium")
        return substeps_bench.window_cost(Path(tmp), "equilibrium", ["reduced"], steps_per_frame)


def _row(r: dict) -> str:
    head = f"| {r['truth_substeps']} | {r['start']} | {r['space']} | {r['substeps']} |"
    if "error" in r:
        return head + " failed | — | — | — | — |"
    ratio = f"{r['time_ratio']:.2f}" if "time_ratio" in r else "—"
    after = ", ".join(f"{100 * e:.0f}" for e in r["max_error_after_steps"])
    return (f"{head} {100 * r['median_error']:.1f} | {100 * r['max_error']:.1f} | {after} | "
            f"{r['time_per_frame_s']:.2f} | {ratio} |")


def summary(rows: list[dict]) -> str:
    """Per space and S: the mean over the captures of the settled median error and of the time ratio; per space,
    the smallest S whose mean error is within 1 percentage point of the lowest; the default of --substeps."""
    import dataclasses

    from stages.steps.adapt import AdaptConfig

    default = {f.name: f.default for f in dataclasses.fields(AdaptConfig)}["substeps"]
    ok = [r for r in rows if "error" not in r]
    lines = []
    for space in sorted({r["space"] for r in ok}):
        mean_err = {}
        for S in sorted({r["substeps"] for r in ok if r["space"] == space}):
            sub = [r for r in ok if r["space"] == space and r["substeps"] == S]
            mean_err[S] = float(np.mean([r["median_error"] for r in sub]))
            worst = max(max(r["max_error_after_steps"]) for r in sub)
            tr = [r["time_ratio"] for r in sub if "time_ratio" in r]
            caps = ", ".join(f"N = {r['truth_substeps']} {r['start']}" for r in sub)
            time = f"per-frame time {np.mean(tr):.2f}× that of S = 1" if tr else "no S = 1 in the same run to time against"
            lines.append(f"- {space}, S = {S}: mean settled median error {100 * mean_err[S]:.1f} % over {len(sub)} "
                         f"capture(s) ({caps}), the largest error in the w + 5 frames after a step {100 * worst:.0f} %, "
                         f"{time}.")
        # the pick compares S values measured on the same captures: those run on every capture of this space
        n_caps = len({(r["truth_substeps"], r["start"]) for r in ok if r["space"] == space})
        full = {S: e for S, e in mean_err.items()
                if len([r for r in ok if r["space"] == space and r["substeps"] == S]) == n_caps}
        if full:
            best = min(full.values())
            pick = min(S for S, e in full.items() if e <= best + 0.01)
            lines.append(f"- {space}: of the S measured on all {n_caps} captures, the smallest whose mean settled error "
                         f"is within 1 percentage point of the lowest ({100 * best:.1f} %) is S = {pick}.")
    lines.append(f"\nThe default of rsl adapt --substeps is {default}.")
    return "\n".join(lines)


def write(rows: list[dict], out: Path, plan: dict, measured: dict | None = None) -> None:
    """docs/results/time_step.{md,json,png}; ``measured``: a previous run's JSON (its machine, date and load kept)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = measured or {
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "plan": plan,
        "load_average_end": list(os.getloadavg()), "cases": rows}
    (out / "time_step.json").write_text(json.dumps(data, indent=1))
    head = ("| truth substeps N | start | space | adapt --substeps S | settled median \\|E−E_true\\|/E_true (%) | "
            "settled max (%) | max in the w + 5 frames after each step (%) | s / frame | time / time(S=1) |\n"
            "| ---: | --- | --- | ---: | ---: | ---: | --- | ---: | ---: |")
    table = "\n".join([head] + [_row(r) for r in rows])
    if data.get("window_cost"):
        table += ("\n\nCPU time of one gn window linearisation in the reduced space (forward, 26 sensitivity "
                  "directions, adjoint; frames 10–12 of the equilibrium capture, S values interleaved, median of 3; "
                  "CPU time is less sensitive to the machine's load than the wall times above):\n\n"
                  "| adapt --substeps S | CPU s | CPU / CPU(S=1) |\n| ---: | ---: | ---: |\n"
                  + "\n".join(f"| {c['substeps']} | {c['window_cpu_s']:.3f} | {c['window_cpu_ratio']:.2f} |"
                               for c in data["window_cost"]))
    la = data["load_average_end"][0]
    md = (f"# rsl adapt --substeps against truths finer in time (the bar with E steps)\n\n"
          f"Truth: sample_data/bar pulled by a cable, E {E0:g} → {2 * E0:g} → {4 * E0:g} Pa at frames {FRAMES // 3} "
          f"and {2 * FRAMES // 3} of {FRAMES}, ν = {POISSON}, P2 tets, hard handles, N implicit-Euler substeps per "
          f"frame (`rsl synth --truth-order 2 --substeps N --handles hard`), 40 markers.  rsl adapt: its own P2 mesh "
          f"(`rsl tetrahedralize --order 2 --max-tets {MAX_TETS}`), reduced space r = {SUBSPACE_DIM} "
          f"(default cubature), "
          f"markers, the default estimator, online, window {WINDOW}, E initialised at 0.5 E0, S implicit-Euler steps "
          f"per frame.  Settled frames: ≥ w + 5 after the start and after each step of E_true.\n\n{table}\n\n"
          f"{summary(rows)}\n\nMachine: {data['machine']} (load average {la:.1f} at the end: the times are under "
          f"that load); date {data['date']}.  Produced by `bench/time_step.py`.\n\n![E over time](time_step.png)\n")
    (out / "time_step.md").write_text(md)
    ok = [r for r in rows if "error" not in r]
    keys = sorted({(r["truth_substeps"], r["start"], r["space"]) for r in ok})
    colour = {S: f"C{i}" for i, S in enumerate(sorted({r["substeps"] for r in ok}))}  # one colour per S
    n = max(1, len(keys))
    fig, axes = plt.subplots(1, n, figsize=(3.3 * n, 3.4), squeeze=False)
    for ax, key in zip(axes[0], keys):
        sub = [r for r in ok if (r["truth_substeps"], r["start"], r["space"]) == key]
        ax.plot(sub[0]["young_true"], "k-", lw=2, label="truth")
        for r in sub:
            ax.plot(r["young"], color=colour[r["substeps"]], label=f"S = {r['substeps']}")
        ax.set_title(f"truth N = {key[0]}, start {key[1]}, {key[2]}", fontsize=8)
        ax.set_xlabel("frame")
        ax.set_ylabel("E (Pa)")
        ax.set_ylim(0, 8 * E0)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "time_step.png", dpi=100)
    print(table)
    print(summary(rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_time_step"))
    ap.add_argument("--truth-substeps", default="3,12")
    ap.add_argument("--starts", default="equilibrium,rest")
    ap.add_argument("--spaces", default="reduced")
    ap.add_argument("--substeps", default="1,2,3,6")
    ap.add_argument("--cost", action="store_true",
                    help="with --from-json: also measure the CPU time of one gn window per S (bench/substeps.py's "
                         "window_cost, on --work's equilibrium capture with N = 3 and its workspace)")
    ap.add_argument("--from-json", type=Path, nargs="+", default=None,
                    help="rewrite the page from previous runs' JSON (several: their rows together, each run's date)")
    a = ap.parse_args()
    if a.from_json:
        runs = [json.loads(p.read_text()) for p in a.from_json]
        measured = dict(runs[0])
        if len(runs) > 1:  # one row per setting (the first run's; each row's time ratio is against its own run's S = 1)
            key = (lambda r: (r["start"], r["truth_substeps"], r["space"], r["substeps"]))
            seen: dict = {}
            for r in (r for run in runs for r in run["cases"]):
                seen.setdefault(key(r), r)
            measured["cases"] = [seen[k] for k in sorted(seen)]
            measured["date"] = ", ".join(run["date"] for run in runs)
            measured["load_average_end"] = [max(run["load_average_end"][0] for run in runs)]
            measured["plan"] = {**runs[0]["plan"], "runs": [run["plan"] for run in runs]}
        if a.cost:
            measured["window_cost"] = window_cost(a.work, sorted({r["substeps"] for r in measured["cases"]}))
        write(measured["cases"], a.out, measured["plan"], measured)
        return
    ints = (lambda s: [int(v) for v in s.split(",") if v])
    plan = {"truth_substeps": ints(a.truth_substeps), "starts": a.starts.split(","), "spaces": a.spaces.split(","),
            "substeps": ints(a.substeps), "frames": FRAMES, "max_tets": MAX_TETS, "dim": SUBSPACE_DIM,
            "work": str(a.work)}
    a.work.mkdir(parents=True, exist_ok=True)
    print("| truth substeps N | start | space | S | settled median (%) | settled max (%) | after steps (%) | s / frame "
          "| ratio |", flush=True)
    rows = []
    for start in plan["starts"]:
        for n in plan["truth_substeps"]:
            rows += run_case(a.work, start, n, plan["spaces"], plan["substeps"])
    write(rows, a.out, plan)


if __name__ == "__main__":
    main()
