"""Accuracy of rsl adapt on captures it did not make (truth on another discretisation).

Captures by `rsl synth` whose truth is P2 tets (refined once in the full mode), 3 substeps per frame and
hard handles, for each start state (equilibrium, rest):

    bar      sample_data/bar pulled by a cable, E steps E0 → 2E0 → 4E0 at T/3 and 2T/3
    dino     sample_data/dino pushed by a sphere, constant E
    beam     sample_data/bar pulled by a cable, two regions (the far half 3 × stiffer), constant

Each is run through the pipeline (calibrate --from-json, tetrahedralize --order 1|2, and for vision segment
and fit-gaussians; for the reduced space generate-data and train-subspace) and `rsl adapt` online with the
default estimator (its name is recorded per row).  Rows: P1 vs P2 in adapt, markers vs vision, reduced vs
full.  Reported per row: the median relative error of E per region over the settled frames (every frame
at least w + 5 frames after the start or after a step of E_true), the worst region's, and the median
per-frame time of adapt.

    .venv/bin/python bench/accuracy.py [--quick] [--out docs/results]

--quick: the bar only, 36 frames, P2 truth on the shipped mesh, markers only, P1 and P2, full space;
full: all cases, 45 frames, both losses and spaces.  --starts, --orders and --estimator narrow the run or pass
rsl adapt's estimator; with RSL_BENCH_REUSE=1 in the environment, captures and meshes already in --work are
reused.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

E0 = 1.0e5
POISSON = 0.45
WINDOW = 3
EXTRA: list = []  # extra rsl adapt options (--estimator)


def rsl(*args) -> float:
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "rsl_cli.app", *map(str, args)], capture_output=True, text=True,
                       env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RuntimeError(f"rsl {' '.join(map(str, args))} failed:\n{p.stderr[-3000:]}")
    return time.perf_counter() - t0


def scene_args(case: str, frames: int) -> list:
    if case == "bar":
        sched = f"{E0:g}@0,{2 * E0:g}@{frames // 3},{4 * E0:g}@{2 * frames // 3}"
        return [ROOT / "sample_data/bar/object.mesh", "--scenario", "cable", "--young-schedule", sched,
                "--size", 0.25]
    if case == "dino":
        return [ROOT / "sample_data/dino/object.mesh", "--scenario", "push", "--young", E0, "--size", 0.22]
    if case == "beam":
        return [ROOT / "sample_data/bar/object.mesh", "--scenario", "cable", "--young", E0,
                "--region", f"stiff={3 * E0:g}@x>0.5", "--size", 0.25]
    raise ValueError(case)


def settled_mask(young_true: np.ndarray, first: int = 0) -> np.ndarray:
    """(T,) True at frames ≥ w + 5 after the first frame and after every change of E_true (any region)."""
    T = len(young_true)
    ok = np.ones(T, bool)
    ok[: first + WINDOW + 5] = False
    for t in range(1, T):
        if np.any(young_true[t] != young_true[t - 1]):
            ok[t: t + WINDOW + 5] = False
    return ok


def run_case(work: Path, case: str, start: str, frames: int, refine: int, orders, losses, spaces) -> list[dict]:
    from stages.artefacts import AdaptArtefact, read_provenance
    from stages.capture import load_capture, read_truth

    cap = work / f"{case}_{start}"
    t_synth = 0.0 if (cap / "capture.toml").is_file() and os.environ.get("RSL_BENCH_REUSE") else rsl("synth", *scene_args(case, frames), cap, "--cameras", 3, "--frames", frames, "--resolution", 96,
                  "--markers", 40, "--calib-views", 0, "--poisson", POISSON, "--start", start, "--truth-order", 2,
                  "--truth-refine", refine, "--substeps", 3, "--handles", "hard", "--seed", 0, "--overwrite")
    truth = read_truth(load_capture(cap))
    rows = []
    for order in orders:
        ws = work / f"ws_{case}_{start}_p{order}"
        if not ((ws / "mesh.h5").is_file() and os.environ.get("RSL_BENCH_REUSE")):
            rsl("calibrate", cap, "-w", ws, "--from-json", cap / "cameras.json")
            rsl("tetrahedralize", cap, "-w", ws, "--order", order)
        if "vision" in losses:
            rsl("segment", cap, "-w", ws, "--method", "background")
            rsl("fit-gaussians", cap, "-w", ws, "--frame", 0)
        if "reduced" in spaces:
            rsl("generate-data", cap, "-w", ws, "--sequences", 4, "--frames", frames, "--workers", 1)
            rsl("train-subspace", "-w", ws, "--dim", 12)
        for loss in losses:
            for space in spaces:
                try:
                    t_adapt = rsl("adapt", cap, "-w", ws, "--window", WINDOW, "--space", space, "--loss", loss,
                                  "--young-init", f"{0.5 * E0:g}", *EXTRA)
                except RuntimeError as e:
                    rows.append({"case": case, "start": start, "order": order, "loss": loss, "space": space,
                                 "error": str(e)[-500:]})
                    print(f"| {case} | {start} | P{order} | {loss} | {space} | failed |", flush=True)
                    continue
                a = AdaptArtefact.load(ws / "adapt.h5")
                prov = read_provenance(ws / "adapt.h5")
                est = prov.get("config", {}).get("estimator", "adam")
                yt = truth.young[np.asarray(a.frames)]
                ok = settled_mask(yt)
                err = np.abs(a.young - yt) / yt  # (T, R)
                med = np.median(err[ok], axis=0) if ok.any() else np.full(yt.shape[1], np.nan)
                rows.append({"case": case, "start": start, "order": order, "loss": loss, "space": space,
                             "estimator": est, "frames": int(len(a.frames)), "settled_frames": int(ok.sum()),
                             "median_error_per_region": med.tolist(), "median_error_worst": float(np.max(med)),
                             "time_per_frame_s": float(np.median(a.time_total_s)), "adapt_s": t_adapt,
                             "synth_s": t_synth, "young": np.asarray(a.young).tolist(), "young_true": yt.tolist(),
                             "regions": list(a.region_names)})
                print(_row(rows[-1]), flush=True)
    return rows


def _row(r: dict) -> str:
    if "error" in r:
        return f"| {r['case']} | {r['start']} | P{r['order']} | {r['loss']} | {r['space']} | — | failed | — | — |"
    per = ", ".join(f"{100 * e:.1f}" for e in r["median_error_per_region"])
    return (f"| {r['case']} | {r['start']} | P{r['order']} | {r['loss']} | {r['space']} | {r['estimator']} | "
            f"{per} | {r['settled_frames']} | {r['time_per_frame_s']:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_accuracy"))
    ap.add_argument("--starts", default="equilibrium,rest", help="start states to run, comma-separated")
    ap.add_argument("--estimator", default="", help="rsl adapt --estimator (default: adapt's own default)")
    ap.add_argument("--orders", default="", help="element orders in adapt, e.g. 1,2 (default: the mode's)")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    if a.quick:
        plan = dict(cases=["bar"], starts=["equilibrium", "rest"], frames=36, refine=0, orders=[1, 2],
                    losses=["markers"], spaces=["full"])
    else:
        plan = dict(cases=["bar", "dino", "beam"], starts=["equilibrium", "rest"], frames=45, refine=1,
                    orders=[1, 2], losses=["markers", "vision"], spaces=["reduced", "full"])
    plan["starts"] = a.starts.split(",")
    if a.orders:
        plan["orders"] = [int(o) for o in a.orders.split(",")]
    global EXTRA
    EXTRA = ["--estimator", a.estimator] if a.estimator else []
    rows = []
    for case in plan["cases"]:
        for start in plan["starts"]:
            rows += run_case(a.work, case, start, plan["frames"], plan["refine"], plan["orders"], plan["losses"],
                             plan["spaces"])
    write(rows, a.out, a.quick, plan)


def write(rows: list[dict], out: Path, quick: bool, plan: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "mode": "quick" if quick else "full", "plan": plan, "cases": rows}
    (out / "accuracy.json").write_text(json.dumps(data, indent=1))
    head = ("| case | start | adapt mesh | loss | space | estimator | median |E−E_true|/E_true per region (%) | "
            "settled frames | s / frame |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    table = "\n".join([head] + [_row(r) for r in rows])
    ok = [r for r in rows if "error" not in r]
    n5 = sum(r["median_error_worst"] <= 0.05 for r in ok)
    md = (f"# Accuracy on captures rsl did not make\n\nTruth: P2 tets{' refined once' if plan['refine'] else ''}, "
          f"3 substeps per frame, hard handles (`rsl synth --truth-order 2 --substeps 3 --handles hard`), "
          f"{plan['frames']} frames, ν = {POISSON}; adapt online, window {WINDOW}, E initialised at 0.5 E0; "
          f"mode {data['mode']}.  Settled frames: ≥ w + 5 after the start and after each step of E_true.\n\n"
          f"{table}\n\n{n5} of {len(ok)} rows have every region's median error ≤ 5 %.\n\n"
          f"Machine: {data['machine']}; date {data['date']}.  Produced by `bench/accuracy.py"
          f"{' --quick' if quick else ''}`.\n\n![E over time](accuracy.png)\n")
    (out / "accuracy.md").write_text(md)
    fig, axes = plt.subplots(1, max(1, len({(r['case'], r['start']) for r in ok})), figsize=(11, 3.8), squeeze=False)
    keys = sorted({(r["case"], r["start"]) for r in ok})
    for ax, key in zip(axes[0], keys):
        sub = [r for r in ok if (r["case"], r["start"]) == key]
        yt = np.asarray(sub[0]["young_true"])
        ax.plot(yt[:, 0], "k-", lw=2, label="truth")
        for r in sub:
            ax.plot(np.asarray(r["young"])[:, 0], label=f"P{r['order']} {r['loss']} {r['space']}")
        ax.set_title(f"{key[0]}, start = {key[1]}")
        ax.set_xlabel("frame")
        ax.set_ylabel("E (Pa), region 0")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "accuracy.png", dpi=110)
    print(table)


if __name__ == "__main__":
    main()
