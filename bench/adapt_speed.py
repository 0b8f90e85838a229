"""Per-frame time of online identification (`rsl adapt`, images, reduced space) on Table 1's Bar-like case
(≈10K DOFs, r = 30, w = 3, c = 4 cameras at 128², 5000 Gaussians; bench/table1.py builds it) for both
estimators, all in one run: adam (one Adam step per frame) and gn (Gauss–Newton, one iteration per frame) with
each way of getting its image Jacobian.

Variants (switched in this process only, VisionObservation.jacobian_mode):

- adam: the default;
- gn fd: ∂r/∂p by central differences of renders (2 renders per column, window frame and camera), Jᵀ W r by
  autograd through the rasterizer — the slow twin;
- gn jvp: the exact forward mode through the projection and the rasterizer (stages/render/rasterize_jvp.py: every
  column in one pass per frame and camera; the residuals come from the same pass, Jᵀ W r from the exact J) —
  the default, with GNWindow.memo on (the change test's one-frame forward, the linearisation's window — with
  substeps, its substeps stitched from the forwards that simulated its frames, Substepped._stitch — and the anchor
  of the last θ taken from the last trajectory of the same θ and states, StartWindow.memo);
- gn jvp no-memo: the same with GNWindow.memo off (every evaluation simulates its window and anchor: the slow twin);
- gn jvp, --gn-trust 5 (row "jvp 1-eval"): the same, with a step of at most 5 posterior σ taken on the quadratic model
  (one evaluation per frame: the window's states at the estimate to first order, GNWindow.extrapolate, continued by
  the next window with one substep per frame, simulated again from them with more) instead of simulated and
  rendered there.

Each run adapts frames 0..w+timed; the values are medians over the frames after the first whose window starts
from stored states (frame > w: no first call's compilation; bench/table1.py takes the same frames): adapt.h5's
wall times (time_forward_s, time_backward_s, time_render_s, time_total_s) and the process CPU time per frame
(all threads, measured here between the reporter's per-frame calls).  Runs are interleaved (rounds × variants),
so load from other jobs falls on all alike; ratios are against adam within this run (issue 13's target: gn's
per-frame time no higher than adam's) and fd / jvp.  The E trajectories of gn jvp against gn fd, gn jvp no-memo and
gn jvp 1-eval are compared (relative difference and in units of the reported σ_E).

    nice python bench/adapt_speed.py              # 2 rounds, 4 timed frames per run
    nice python bench/adapt_speed.py --quick      # table1's --quick Bar (64², 2000 Gaussians), 1 round

Writes docs/results/adapt_speed.md and adapt_speed.json.
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import table1  # noqa: E402
from stages.artefacts import AdaptArtefact  # noqa: E402
from stages.progress import SilentReporter  # noqa: E402
from stages.observations import VisionObservation  # noqa: E402
from stages.steps import adapt  # noqa: E402

RESULTS = ROOT / "docs" / "results"
VARIANTS = (("adam", "default"), ("gn", "fd"), ("gn", "jvp"), ("gn", "jvp no-memo"), ("gn", "jvp 1-eval"))
TRUST = {"jvp 1-eval": 5.0}
# with rsl adapt's default substeps S (every variant), and with 1 substep per frame — the discretisation the capture was
# synthesised with (bench/table1.py), where E is not biased by the model's time step (the main variants)
VARIANTS_S1 = (("adam", "default"), ("gn", "jvp"), ("gn", "jvp 1-eval"))  # AdaptConfig.gn_trust of a variant (0: every step evaluated)
E_TRUE = 1e5  # the Young's modulus bench/table1.py's build() synthesises the Bar with (and capture.toml's, the start)


class _CpuClock(SilentReporter):
    """Records the process CPU time between the per-frame ``advance`` calls of adapt's progress task."""

    def __init__(self) -> None:
        super().__init__()
        self.cpu: list[float] = []

    @contextlib.contextmanager
    def task(self, description, total):
        clock = self
        last = [time.process_time()]

        class T:
            def advance(self, n=1, **fields):
                now = time.process_time()
                clock.cpu.append(now - last[0])
                last[0] = now

        yield T()


@contextlib.contextmanager
def variant(name: str):
    """gn's image Jacobian: "fd" (central differences) or "jvp" (forward mode), "no-memo": GNWindow.memo off;
    "default" changes nothing."""
    from stages.windows import GNWindow

    saved, saved_memo = VisionObservation.jacobian_mode, GNWindow.memo
    GNWindow.memo = False if "no-memo" in name else saved_memo
    if name.split()[0] in ("fd", "jvp"):
        VisionObservation.jacobian_mode = name.split()[0]
    try:
        yield
    finally:
        VisionObservation.jacobian_mode, GNWindow.memo = saved, saved_memo


def run_once(cap: Path, ws: Path, out: Path, estimator: str, w: int, n_frames: int, name: str, substeps: int) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5", "subspace.h5"):
        shutil.copy(ws / f, out / f)
    cfg = adapt.AdaptConfig(capture=cap, workspace=out, space="reduced", loss="vision", window=w,
                            iters_per_frame=1, frames=f"0:{n_frames}", estimator=estimator,
                            gn_trust=TRUST.get(name, 0.0), substeps=substeps)
    clock = _CpuClock()
    with variant(name):
        art = AdaptArtefact.load(adapt.run(cfg, clock))
    sel = np.asarray(art.frames) > w
    med = lambda a: float(np.median(np.asarray(a)[sel]))  # noqa: E731
    return {"forward_s": med(art.time_forward_s), "backward_s": med(art.time_backward_s),
            "render_s": med(art.time_render_s), "total_s": med(art.time_total_s),
            "cpu_s": float(np.median(np.asarray(clock.cpu)[sel])), "frames_timed": int(sel.sum()),
            "young": np.asarray(art.young).tolist(), "young_sigma": np.asarray(art.young_sigma).tolist(),
            "frames": np.asarray(art.frames).tolist()}


def markdown(data: dict) -> str:
    s = data["settings"]
    lines = ["# Per-frame time of `rsl adapt` (Bar-like case): Gauss–Newton's image Jacobian, and gn against adam", "",
             f"Machine: {data['machine']}; {data['date']}; wall time of the whole run {data['wall_s'] / 60:.1f} min.",
             "",
             f"Case: {s['case']}; reduced space, images ({s['resolution']}², {s['gaussians']} Gaussians, "
             f"c = {s['cameras']}), r = {s['r']}, w = {s['w']}, one step (adam) / one Gauss–Newton iteration (gn) per "
             f"frame; {s['rounds']} round(s), runs interleaved; per run the median over frames w + 1 … w + "
             f"{s['timed']} (no compilation), then the median over the rounds; S: implicit-Euler substeps per frame (the "
             "capture was synthesised with 1; rsl adapt's default first, then 1 for the main variants).  Wall: adapt.h5's times; CPU: the "
             "process CPU time per frame (all threads).  gn / adam: this row's time over adam's, same run (issue 13's "
             "target: ≤ 1).  E error: round 1, every frame, against the E the capture was synthesised with "
             f"({E_TRUE:.3g} Pa; every run starts there).", "",
             "| S | estimator | J | fwd s | bwd s | render s | total s (wall) | CPU s / frame | gn / adam (wall) | "
             "gn / adam (CPU) | fd / this (CPU) | max \\|E/E_true − 1\\| |",
             "| ---: | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in data["rows"]:
        fd = "" if r.get("fd_over_this_cpu") is None or r["estimator"] != "gn" else f"{r['fd_over_this_cpu']:.2f}×"
        lines.append(f"| {r.get('substeps', 1)} | {r['estimator']} | {r['variant']} | {r['forward_s']:.3g} | "
                     f"{r['backward_s']:.3g} | {r['render_s']:.3g} | {r['total_s']:.3g} | {r['cpu_s']:.3g} | "
                     f"{r['over_adam_wall']:.2f} | {r['over_adam_cpu']:.2f} | {fd} | {100 * r['max_err']:.2f} % |")
    cmp_ = data["jvp_vs_fd"]
    lines += ["", f"gn with the forward-mode J against gn with central differences, the same frames (round 1): E "
              f"differs by at most {100 * cmp_['max_rel']:.2f} % (median {100 * cmp_['median_rel']:.2f} %), at most "
              f"{cmp_['max_in_sigma']:.2f} σ_E (σ_E as gn fd reports it).  gn jvp (memo) against gn jvp no-memo, "
              f"S = {s['substeps']}: E differs by at most {100 * data['memo_vs_no_memo']['max_rel']:.2g} %, at most "
              f"{data['memo_vs_no_memo']['max_in_sigma']:.2g} σ_E.  gn jvp 1-eval against gn jvp: E differs by "
              + "; ".join(f"at most {100 * one['max_rel']:.2f} % (median {100 * one['median_rel']:.2f} %), at most "
                          f"{one['max_in_sigma']:.3f} σ_E with S = {S}" for S, one in data["one_vs_two"].items())
              + ".  Per round (CPU s / frame, " + " / ".join(f"S={S} {e} {v}" for S, e, v in data["plan"]) + "): "
              + "; ".join(
                  " / ".join(f"{x:.3g}" for x in rnd) for rnd in data["per_round_cpu"]) + ".", "",
              "Generated by bench/adapt_speed.py.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="table1's --quick Bar (64², 2000 Gaussians), 1 round.")
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--timed", type=int, default=4, help="Timed frames per run (after frame w).")
    ap.add_argument("--work", default="/tmp/rsl_bench_table1", help="table1's work folder (its builds are reused).")
    args = ap.parse_args()
    case = next(c for c in table1.CASES if c.name == "Bar")
    resolution, gaussians, fit_iters, timed_t1 = (64, 2000, 10, 2) if args.quick else (128, 5000, 20, 4)
    rounds = args.rounds or (1 if args.quick else 2)
    work = Path(args.work) / ("quick" if args.quick else "full")
    cap, ws = table1.build(case, work, case.w + timed_t1 + 2, resolution, gaussians, fit_iters)
    n_avail = len(list((cap / "frames" / "cam0").glob("*.png")))
    timed = min(args.timed, n_avail - case.w - 1)
    n_frames = case.w + 1 + timed
    t0 = time.perf_counter()
    runs: dict = {}
    S0 = adapt.AdaptConfig.substeps
    plan = [(S0, est, name) for est, name in VARIANTS] + ([(1, est, name) for est, name in VARIANTS_S1] if S0 != 1 else [])
    for rnd in range(rounds):
        for S, est, name in plan:
            t = time.perf_counter()
            r = run_once(cap, ws, work / "Bar" / f"speed_{est}_{name.replace(' ', '_')}_S{S}", est, case.w, n_frames,
                         name, S)
            runs.setdefault((S, est, name), []).append(r)
            print(f"[{time.strftime('%H:%M:%S')}] round {rnd} S={S} {est} {name}: total {r['total_s']:.3f} s wall, "
                  f"{r['cpu_s']:.3f} s CPU per frame ({time.perf_counter() - t:.0f} s)", flush=True)
    rows = []
    for S, est, name in plan:
        rs = runs[(S, est, name)]
        base = runs[(S, "adam", "default")]
        row = {"estimator": est, "variant": name, "substeps": S}
        for k in ("forward_s", "backward_s", "render_s", "total_s", "cpu_s"):
            row[k] = statistics.median(r[k] for r in rs)
        row["over_adam_wall"] = row["total_s"] / statistics.median(b["total_s"] for b in base)
        row["over_adam_cpu"] = row["cpu_s"] / statistics.median(b["cpu_s"] for b in base)
        fd = runs.get((S, "gn", "fd"))
        row["fd_over_this_cpu"] = statistics.median(r["cpu_s"] for r in fd) / row["cpu_s"] if fd else None
        row["rounds"] = [{k: r[k] for k in ("total_s", "cpu_s")} for r in rs]
        row["young"] = rs[0]["young"]
        row["young_sigma"] = rs[0]["young_sigma"]
        row["max_err"] = float(np.max(np.abs(np.asarray(rs[0]["young"]) / E_TRUE - 1.0)))  # round 1, every frame
        rows.append(row)
    def compare(a: dict, b: dict) -> dict:  # E of run b against run a (σ_E as a reports it)
        ya, yb, sa = np.asarray(a["young"]), np.asarray(b["young"]), np.asarray(a["young_sigma"])
        rel = np.abs(yb - ya) / np.abs(ya)
        return {"max_rel": float(rel.max()), "median_rel": float(np.median(rel)),
                "max_in_sigma": float(np.max(np.abs(yb - ya) / sa)), "frames": a["frames"]}

    jvp_vs_fd = compare(runs[(S0, "gn", "fd")][0], runs[(S0, "gn", "jvp")][0])
    one_vs_two = {S: compare(runs[(S, "gn", "jvp")][0], runs[(S, "gn", "jvp 1-eval")][0]) for S in sorted({S0, 1})}
    memo_vs_not = compare(runs[(S0, "gn", "jvp no-memo")][0], runs[(S0, "gn", "jvp")][0])
    per_round = [[runs[v][i]["cpu_s"] for v in plan] for i in range(rounds)]
    from stages.artefacts import MeshArtefact

    mesh = MeshArtefact.load(ws / "mesh.h5")
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}, "
                       f"load average {os.getloadavg()[0]:.1f} at the end (a shared machine)",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "wall_s": time.perf_counter() - t0, "jvp_vs_fd": jvp_vs_fd, "memo_vs_no_memo": memo_vs_not,
            "one_vs_two": {str(k): v for k, v in one_vs_two.items()}, "plan": [list(x) for x in plan],
            "per_round_cpu": per_round,
            "settings": {"case": f"Bar, {case.shape}, {3 * mesh.n_vertices} DOFs, {mesh.n_tets} tets of order "
                                 f"{mesh.order}", "resolution": resolution, "gaussians": gaussians,
                         "cameras": case.c, "r": case.r, "w": case.w, "timed": timed, "rounds": rounds,
                         "substeps": adapt.AdaptConfig.substeps,
                         "quick": args.quick},
            "cases": rows, "rows": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "adapt_speed.json").write_text(json.dumps(data, indent=1))
    (RESULTS / "adapt_speed.md").write_text(markdown(data))
    print(markdown(data))


if __name__ == "__main__":
    main()
