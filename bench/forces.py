"""Handle and obstacle forces of a full-space replay against the truth's, per number of substeps (issue 12).

`rsl export --forces`, `rsl evaluate` and `rsl report` compute the forces of an online adapt run by replaying the
controls in the full space with θ(t) from the capture's start state, S implicit-Euler steps per frame
(stages/forces.py replay_forces; `--force-substeps`).  This bench measures what S costs and buys on captures
rsl did not make (made as bench/accuracy.py makes them: `rsl synth --truth-order 2 --substeps 3 --handles hard`,
sample_data/bar pulled by a cable with E stepping E0 → 2E0 → 4E0 for each start state, the two-region beam, the
dinosaur pushed by a sphere), on rsl's own P2 mesh (`rsl tetrahedralize --order 2 --max-tets 1500`):

    true E     θ(t) = the truth's E(t), ν (truth/material.csv): the error left is the model's (mesh + time step)
    adapted    θ(t) of `rsl adapt` (online, full space, markers, window 3, E initialised at 0.5 E0)

Per row: the median relative error of the applied forces against truth/forces.csv, pooled over handles/obstacles
and frames as `rsl evaluate` reports it (stages.forces.force_errors), the same against the replay with the most
substeps of this run (a convergence measure that needs no truth), and the CPU seconds of the replay
(time.process_time, this process); ratios against S = 1 of the same case and θ, measured in the same run.

    nice .venv/bin/python bench/forces.py [--substeps 1,2,3,4,6] [--cases bar_equilibrium,...] [--work DIR]

With RSL_BENCH_REUSE=1, captures, meshes and adapt.h5 already in --work are reused (bench/_pipeline.py).
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

import accuracy as acc  # noqa: E402  (the accuracy captures: the same scenes, constants and adapt mesh)

E0, POISSON, MAX_TETS, WINDOW = acc.E0, acc.POISSON, acc.MAX_TETS, acc.WINDOW
FRAMES = 36
CASES = {  # name -> (scene, start): the accuracy captures (bench/accuracy.py scene_args)
    "bar_equilibrium": (lambda: acc.scene_args("bar", FRAMES), "equilibrium"),
    "bar_rest": (lambda: acc.scene_args("bar", FRAMES), "rest"),
    "beam_equilibrium": (lambda: acc.scene_args("beam", FRAMES), "equilibrium"),
    "dino_equilibrium": (lambda: acc.scene_args("dino", FRAMES), "equilibrium"),
}


def pooled(per: dict) -> float | None:
    """The median over every (handle/obstacle, frame) relative error — evaluation.json's forces
    median_relative_error."""
    errs = [e for v in per.values() for e in v["rel_error_per_frame"]]
    return float(np.median(errs)) if errs else None


def by_region(values: np.ndarray, names: list[str], want: list[str], what: str) -> np.ndarray:
    """Columns of values (T, R) in the order of the region names ``want`` (the mesh's)."""
    missing = [n for n in want if n not in names]
    if missing:
        raise SystemExit(f"{what} has no region {missing} (it has {names})")
    return np.stack([values[:, names.index(n)] for n in want], axis=1)


def run_case(work: Path, name: str, substeps: list[int], truth_substeps: int = 3, true_only: bool = False
             ) -> list[dict]:
    from stages.artefacts import AdaptArtefact, MeshArtefact, read_provenance
    from stages.capture import load_capture, read_forces_csv, read_truth
    from stages.forces import force_errors, force_table, replay_forces
    from stages.sim.scene import make_scene

    scene_fn, start = CASES[name]
    tag = "" if truth_substeps == 3 else f"_truth{truth_substeps}"
    cap_dir = pl.foreign_capture(work / f"{name}{tag}", scene_fn(), start=start, frames=FRAMES, poisson=POISSON,
                                 substeps=truth_substeps)
    ws = pl.mesh(cap_dir, work / f"ws_{name}{tag}_p2", order=2, max_tets=MAX_TETS)
    failed = "not run (--true-only)" if true_only else None
    if not true_only and not pl.skip(ws / "adapt.h5"):
        try:
            pl.adapt(cap_dir, ws, "--window", WINDOW, "--space", "full", "--loss", "markers", "--young-init",
                     f"{0.5 * E0:g}")
        except pl.RslFailed as e:  # the true-E rows are still measured; the adapted ones say why they are not
            failed = str(e).strip().splitlines()[-1][:400]
    cap = load_capture(cap_dir)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    ad = None if failed else AdaptArtefact.load(ws / "adapt.h5")
    cfg = {} if failed else read_provenance(ws / "adapt.h5").get("config", {})
    truth = read_truth(cap)
    truth_rows = read_forces_csv(cap.truth_dir / "forces.csv")
    controls = cap.controls()
    model, dt = cap.material.model, float(cap.dt)
    scene = make_scene(mesh, controls, model, dt, np.asarray(cap.gravity, np.float64))
    regions = list(mesh.region_names)
    T = FRAMES if ad is None else len(ad.frames)
    thetas = {"true E": (by_region(truth.young[:T], truth.region_names, regions, "truth/material.csv"),
                         by_region(truth.poisson[:T], truth.region_names, regions, "truth/material.csv"))}
    if ad is not None:
        thetas["adapted"] = (by_region(np.asarray(ad.young), list(ad.region_names), regions, "adapt.h5"),
                             by_region(np.asarray(ad.poisson), list(ad.region_names), regions, "adapt.h5"))
    adapt_desc = (f"{cfg.get('space', '?')} space, {cfg.get('loss', '?')}, estimator {cfg.get('estimator', '?')}, "
                  f"{cfg.get('substeps', 1)} substep(s)")
    rows = [] if failed is None or true_only else [{"case": name, "start": start, "theta": "adapted", "error": failed}]
    for label, (young, poisson) in thetas.items():
        tables = {}
        for S in substeps:
            t0 = time.process_time()
            w0 = time.perf_counter()
            out, _, _ = replay_forces(scene, controls, young, poisson, cap.start, S)
            cpu, wall = time.process_time() - t0, time.perf_counter() - w0
            tables[S] = force_table(out, dt)
            per = force_errors(tables[S], truth_rows)
            rows.append({"case": name, "start": start, "theta": label, "substeps": S, "truth_substeps": truth_substeps,
                         "median_force_error": pooled(per),
                         "per_set": {k: v["median_relative_error"] for k, v in per.items()},
                         "cpu_s": cpu, "wall_s": wall, "frames": T, "fps": float(cap.fps),
                         "dofs": 3 * int(mesh.vertices.shape[0]),
                         "adapt": adapt_desc if label == "adapted" else None})
            print(_row(rows[-1]), flush=True)
        finest = max(substeps)
        for r in rows:
            if r["theta"] == label and "error" not in r:
                r["change_vs_finest"] = pooled(force_errors(tables[r["substeps"]], tables[finest]))
                r["finest"] = finest
    for r in rows:  # ratios against S = 1 of the same case and θ, this run
        ref = next((q for q in rows if q["theta"] == r["theta"] and q.get("substeps") == 1), None)
        if ref is not None and "error" not in r:
            r["cpu_ratio"] = r["cpu_s"] / ref["cpu_s"]
            if r["median_force_error"] is not None and ref["median_force_error"]:
                r["error_ratio"] = r["median_force_error"] / ref["median_force_error"]
    return rows


def _pct(x) -> str:
    return "—" if x is None else f"{100 * x:.1f}"


def _row(r: dict) -> str:
    if "error" in r:
        return f"| {r['case']} | {r['theta']} | — | failed: {r['error']} | — | — | — | — |"
    ratio = lambda k: f"{r[k]:.2f}" if k in r else "—"  # noqa: E731
    return (f"| {r['case']} | {r['theta']} | {r['substeps']} | {_pct(r['median_force_error'])} | "
            f"{ratio('error_ratio')} | {_pct(r.get('change_vs_finest'))} | {r['cpu_s']:.1f} | {ratio('cpu_ratio')} |")


HEAD = ("| capture | θ(t) | substeps S | median force error vs truth (%) | error / error at S = 1 | "
        "median change vs the finest S (%) | replay CPU (s) | CPU / CPU at S = 1 |\n"
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")


def summary(rows: list[dict]) -> list[str]:
    """Lines made from the rows only: per θ and S, the worst and median case error, and the mean CPU ratio."""
    out = []
    for theta in dict.fromkeys(r["theta"] for r in rows):
        for S in sorted({r["substeps"] for r in rows if "error" not in r}):
            sub = [r for r in rows if "error" not in r and r["theta"] == theta and r["substeps"] == S
                   and r["median_force_error"] is not None]
            if not sub:
                continue
            errs = [r["median_force_error"] for r in sub]
            cpu = [r["cpu_ratio"] for r in sub if "cpu_ratio" in r]
            n10 = sum(e <= 0.10 for e in errs)
            out.append(f"- {theta}, S = {S}: worst case {100 * max(errs):.1f} %, median of the cases "
                       f"{100 * float(np.median(errs)):.1f} %, {n10} of {len(errs)} cases ≤ 10 %"
                       + (f"; CPU {float(np.mean(cpu)):.2f} × S = 1" if cpu else ""))
    return out


def write(rows: list[dict], out: Path, plan: dict, name: str = "forces") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "load_average_end": os.getloadavg()[0], "plan": plan, "cases": rows}
    (out / f"{name}.json").write_text(json.dumps(data, indent=1))
    table = "\n".join([HEAD] + [_row(r) for r in rows])
    md = (f"# Forces of the full-space replay against the truth, per substeps\n\n"
          f"Captures as bench/accuracy.py makes them (`rsl synth --truth-order 2 --substeps {plan.get('truth_substeps', 3)} --handles hard`, "
          f"{plan['frames']} frames at {next(r['fps'] for r in rows if 'fps' in r):g} fps, ν = {POISSON}); rsl's mesh "
          f"`rsl tetrahedralize --order 2 --max-tets {MAX_TETS}`.  θ(t) 'true E': the truth's E(t) and ν; 'adapted': adapt.h5 of `rsl adapt` "
          f"(online, window {WINDOW}, E initialised at 0.5 E0).  The forces are replayed in the full space from "
          f"the capture's start state with S implicit-Euler steps per frame (stages/forces.py replay_forces, "
          f"`--force-substeps S`) and compared with truth/forces.csv as `rsl evaluate` does (median relative "
          f"error of the applied force over handles/obstacles and frames).  'Change vs the finest S': the same "
          f"median against the replay with the most substeps of the same capture and θ(t) (no truth needed).  CPU: "
          f"time.process_time of the replay; ratios against S = 1 of the same capture and θ(t), this run.\n\n"
          f"{table}\n\n" + "\n".join(summary(rows)) + "\n\n"
          + (f"Rows merged from {len(plan['merged_from'])} runs (split by capture), ended "
             + ", ".join(f"{m['date']} (load average {m['load_average_end']:.1f})" for m in plan["merged_from"])
             + f"; machine {data['machine']}. " if plan.get("merged_from") else
             f"Machine: {data['machine']}, load average {data['load_average_end']:.1f} at the end; date "
             f"{data['date']}. ")
          + f"Produced by `bench/forces.py`.\n\n![force error over substeps]({name}.png)\n")
    (out / f"{name}.md").write_text(md)
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 3.8))
    for c, case in enumerate(dict.fromkeys(r["case"] for r in rows)):
        for theta, ls in (("true E", "-"), ("adapted", "--")):
            sub = [r for r in rows if "error" not in r and r["case"] == case and r["theta"] == theta
                   and r["median_force_error"] is not None]
            if sub:
                a0.plot([r["substeps"] for r in sub], [100 * r["median_force_error"] for r in sub], ls, marker="o",
                        ms=3, color=f"C{c}", label=f"{case}, {theta}")
                a1.plot([r["substeps"] for r in sub], [r["cpu_s"] for r in sub], ls, marker="o", ms=3, color=f"C{c}")
    a0.axhline(10, color="k", lw=0.8, ls=":")
    a0.set_xlabel("substeps S of the replay")
    a0.set_ylabel("median force error vs truth (%)")
    a0.set_yscale("log")
    a0.legend(fontsize=6)
    a1.set_xlabel("substeps S of the replay")
    a1.set_ylabel("replay CPU (s)")
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_forces"))
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--substeps", default="1,2,3,4,6", help="replay substeps S, comma-separated (include 1)")
    ap.add_argument("--truth-substeps", type=int, default=3,
                    help="implicit substeps per frame of the truth (synth --substeps); many = converged in time")
    ap.add_argument("--name", default="forces", help="file stem of the report in --out (NAME.md/.json/.png)")
    ap.add_argument("--true-only", action="store_true", help="only the true-E rows (no rsl adapt)")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="only write the report from the rows of these forces.json files (runs split by case)")
    a = ap.parse_args()
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        plan = {**runs[0]["plan"], "cases": [c for run in runs for c in run["plan"]["cases"]],
                "merged_from": [{"file": str(f), "date": run["date"], "load_average_end": run["load_average_end"]}
                                for f, run in zip(a.merge, runs)]}
        rows = [r for run in runs for r in run["cases"]]
        truth_steps = sorted({r.get("truth_substeps", 3) for r in rows})
        plan["truth_substeps"] = " / ".join(map(str, truth_steps))
        plan["substeps"] = sorted({r["substeps"] for r in rows if "substeps" in r})
        if len(truth_steps) > 1:  # the same capture simulated at several truth steps: tell them apart
            for r in rows:
                r["case"] = f"{r['case']}, truth S = {r.get('truth_substeps', 3)}"
        write(rows, a.out, plan, a.name)
        return
    substeps = sorted({int(s) for s in a.substeps.split(",")})
    cases = a.cases.split(",")
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise SystemExit(f"unknown case(s) {unknown}; known: {', '.join(CASES)}")
    a.work.mkdir(parents=True, exist_ok=True)
    plan = {"cases": cases, "substeps": substeps, "frames": FRAMES, "max_tets": MAX_TETS,
            "work": str(a.work), "truth_substeps": a.truth_substeps}
    print(HEAD, flush=True)
    rows: list[dict] = []
    for case in cases:
        rows += run_case(a.work, case, substeps, a.truth_substeps, a.true_only)
        write(rows, a.out, plan, a.name)  # after every case: a stopped run keeps what it measured
    print("\n".join(summary(rows)))


if __name__ == "__main__":
    main()
