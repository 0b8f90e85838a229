"""Per-frame time of online identification (`rsl adapt`, images, reduced space) on Table 1's Bar-like case
(≈10K DOFs, r = 30, w = 3, c = 4 cameras at 128², 5000 Gaussians; bench/table1.py builds it) for both
estimators, all in one run: adam (Adam steps) and gn (Gauss–Newton) with each way of getting its image Jacobian,
one step / iteration per frame and at rsl adapt's default --iters-per-frame.

Variants (switched in this process only: VisionObservation.jacobian_mode, GNWindow's switches):

- adam: the default;
- gn fd: ∂r/∂p by central differences of renders (2 renders per column, window frame and camera), Jᵀ W r by
  autograd through the rasterizer — the slow twin;
- gn jvp: the exact forward mode through the projection and the rasterizer (stages/render/rasterize_jvp.py: every
  column in one pass per frame and camera; the residuals come from the same pass, Jᵀ W r from the exact J) —
  the default, with GNWindow.memo on (the linearisation's window — with
  substeps, its substeps stitched from the forwards that simulated its frames, Substepped._stitch — and the anchor
  of the last θ taken from the last trajectory of the same θ and states, StartWindow.memo), the change test's
  residuals taken from the solve's first linearisation (GNWindow.shared_innovation) and numpy's BLAS on one thread
  over the online loop (GNWindow.blas_threads);
- gn jvp no-memo: the same with GNWindow.memo off (every evaluation simulates its window and anchor: the slow twin);
- gn jvp, --gn-trust 0: every step evaluated (rows "jvp" and its twins below);
- gn jvp, --gn-trust 5 (row "jvp 1-eval"): the same, with a step of at most 5 posterior σ taken on the quadratic model
  (one evaluation per frame: the window's states at the estimate to first order, GNWindow.extrapolate, continued by
  the next window with one substep per frame, simulated again from them with more) instead of simulated and
  rendered there;
- gn default (at rsl adapt's default --iters-per-frame): gn as a user gets it — jvp, and --gn-trust left to
  AdaptConfig's default, which resolve_gn_trust sets from the loss (the value that ran is read back from adapt.h5's
  provenance); its twin with every step evaluated is the row "jvp" of the same iterations;
- gn default no-probe, gn jvp no-probe (S = 1): the same with --change-probe 0 (no probes of the window at
  log E ± the probe after the solve): the probes' cost is the difference to the twin with them (where a probe
  declares a change, the runs part: their E are compared);
- gn jvp separate-test: the change test simulating and rendering the new frame by itself before the solve
  (GNWindow.shared_innovation off: the slow twin of taking its residuals from the solve's first linearisation);
- gn jvp blas-threads: numpy's BLAS with the threads the process has (GNWindow.blas_threads None: the twin of
  holding it to one thread over the online loop);
- gn jvp separate-test blas-threads: both switched off (the change test's own render, BLAS's threads);
- adam blas-1: adam with numpy's BLAS held to one thread over the whole run here (threadpoolctl), as gn holds it
  (adam's own loop does not): what adam would gain from the same.

Those rows take one iteration (gn) / one step (adam) per frame.  The rows "at default" run both at rsl adapt's
default --iters-per-frame (adam: that many steps per frame; gn: at most that many Gauss–Newton iterations, each a
linearisation and, unless the step is taken on the quadratic model, a Levenberg–Marquardt trial evaluation — the
iterations and window evaluations gn actually made per timed frame are counted here, around the estimator's
gauss_newton).

Adam runs with --anchor-calibration 0 (the --anchor-change rule): at the default 8 the timed frames would lie in the
calibration's growing window (frames 0..T simulated at every frame, a one-time start, like the compilation); after
it the window is the same w frames with the anchor held (no anchor adjoint), at most the cost timed here.

Each run adapts frames 0..w+timed; the values are medians over the frames after the first whose window starts
from stored states (frame > w: no first call's compilation; bench/table1.py takes the same frames): adapt.h5's
wall times (time_forward_s, time_backward_s, time_render_s, time_total_s) and the process CPU time per frame
(all threads, measured here between the reporter's per-frame calls).  Runs are interleaved (rounds × variants),
so load from other jobs falls on all alike; ratios are against adam within this run (issue 13's target: gn's
per-frame time no higher than adam's) and fd / jvp.  The E trajectories of gn jvp against gn fd, each twin, gn
jvp 1-eval and (at the default iterations) gn default are compared (relative difference and in units of the
reported σ_E).

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
from stages.artefacts import AdaptArtefact, read_provenance  # noqa: E402
from stages.progress import SilentReporter  # noqa: E402
from stages.observations import VisionObservation  # noqa: E402
from stages.steps import adapt  # noqa: E402

RESULTS = ROOT / "docs" / "results"
BOTH_OFF = "jvp separate-test blas-threads"  # gn jvp with both switches off: the path before they were made
VARIANTS = (("adam", "default"), ("gn", "fd"), ("gn", "jvp"), ("gn", "jvp no-memo"), ("gn", "jvp 1-eval"),
            ("gn", "jvp separate-test"), ("gn", "jvp blas-threads"), ("gn", BOTH_OFF), ("adam", "blas-1"))
# both estimators at rsl adapt's default --iters-per-frame (the rows above take 1), with rsl adapt's default substeps
DEFAULTS = (("adam", "default"), ("gn", "default"), ("gn", "default no-probe"), ("gn", "jvp"), ("gn", BOTH_OFF),
            ("adam", "blas-1"))
# AdaptConfig.gn_trust of a gn variant: None (AdaptConfig's default, resolve_gn_trust) for "default", else this
TRUST = {"jvp 1-eval": 5.0}
# with rsl adapt's default substeps S (every variant), and with 1 substep per frame — the discretisation the capture was
# synthesised with (bench/table1.py), where E is not biased by the model's time step (the main variants)
VARIANTS_S1 = (("adam", "default"), ("gn", "jvp"), ("gn", "jvp no-probe"), ("gn", "jvp 1-eval"))
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
    """gn's image Jacobian: "fd" (central differences) or "jvp" (forward mode), "no-memo": GNWindow.memo off,
    "separate-test": GNWindow.shared_innovation off, "blas-threads": GNWindow.blas_threads None; "blas-1": BLAS held
    to one thread over the run; "default" changes nothing."""
    from stages.windows import GNWindow

    saved = (VisionObservation.jacobian_mode, GNWindow.memo, GNWindow.shared_innovation, GNWindow.blas_threads)
    GNWindow.memo = False if "no-memo" in name else saved[1]
    GNWindow.shared_innovation = False if "separate-test" in name else saved[2]
    GNWindow.blas_threads = None if "blas-threads" in name else saved[3]
    if name.split()[0] in ("fd", "jvp"):
        VisionObservation.jacobian_mode = name.split()[0]
    limit = contextlib.nullcontext()
    if name == "blas-1":
        from threadpoolctl import threadpool_limits

        limit = threadpool_limits(limits=1, user_api="blas")
    try:
        with limit:
            yield
    finally:
        VisionObservation.jacobian_mode, GNWindow.memo, GNWindow.shared_innovation, GNWindow.blas_threads = saved


@contextlib.contextmanager
def counting_gauss_newton(log: list):
    """Appends (iterations, evaluations) of every gauss_newton call adapt makes to ``log``."""
    orig = adapt.gauss_newton

    def counted(*a, **k):
        res = orig(*a, **k)
        log.append((int(res.iterations), int(res.evaluations)))
        return res

    adapt.gauss_newton = counted
    try:
        yield
    finally:
        adapt.gauss_newton = orig


def run_once(cap: Path, ws: Path, out: Path, estimator: str, w: int, n_frames: int, name: str, substeps: int,
             iters: int = 1) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5", "subspace.h5"):
        shutil.copy(ws / f, out / f)
    trust = {} if name.startswith("default") else {"gn_trust": TRUST.get(name, 0.0)}  # "default": AdaptConfig's own
    if "no-probe" in name:  # the change probes off (--change-probe 0): their cost is the difference to the twin
        trust["change_probe"] = 0.0
    cfg = adapt.AdaptConfig(capture=cap, workspace=out, space="reduced", loss="vision", window=w,
                            iters_per_frame=iters, frames=f"0:{n_frames}", estimator=estimator, substeps=substeps,
                            anchor_calibration=0,  # (see the module's docstring: the sliding window is timed)
                            **trust)
    clock = _CpuClock()
    its: list = []
    with variant(name), counting_gauss_newton(its):
        path = adapt.run(cfg, clock)
    art = AdaptArtefact.load(path)
    sel = np.asarray(art.frames) > w
    # gn: one gauss_newton per online frame (its first frame, without an earlier one, is not counted)
    gn_its = np.asarray(its[-len(art.frames):] if its else np.zeros((0, 2)), float).reshape(-1, 2)
    med = lambda a: float(np.median(np.asarray(a)[sel]))  # noqa: E731
    return {"forward_s": med(art.time_forward_s), "backward_s": med(art.time_backward_s),
            "render_s": med(art.time_render_s), "total_s": med(art.time_total_s),
            "cpu_s": float(np.median(np.asarray(clock.cpu)[sel])), "frames_timed": int(sel.sum()),
            "gn_iterations": float(np.mean(gn_its[sel, 0])) if len(gn_its) == len(sel) else None,
            "gn_evaluations": float(np.mean(gn_its[sel, 1])) if len(gn_its) == len(sel) else None,
            "young": np.asarray(art.young).tolist(), "young_sigma": np.asarray(art.young_sigma).tolist(),
            "frames": np.asarray(art.frames).tolist(),
            # the value that ran: adapt.h5's extra (runs before it recorded it in the provenance's config)
            "gn_trust": art.extra.get("gn_trust", read_provenance(path)["config"].get("gn_trust"))}


def markdown(data: dict) -> str:
    s = data["settings"]
    I0 = data.get("iters_default", 1)
    lines = ["# Per-frame time of `rsl adapt` (Bar-like case): Gauss–Newton's image Jacobian, and gn against adam", "",
             f"Machine: {data['machine']}; {data['date']}; wall time of the whole run {data['wall_s'] / 60:.1f} min.",
             "",
             f"Case: {s['case']}; reduced space, images ({s['resolution']}², {s['gaussians']} Gaussians, "
             f"c = {s['cameras']}), r = {s['r']}, w = {s['w']}; it: steps (adam) / at most Gauss–Newton iterations "
             f"(gn) per frame — 1, and rsl adapt's default {I0} in the rows marked *default*; adam with "
             f"--anchor-calibration 0, its sliding window (the default calibrates on the first frames, a one-time "
             f"growing window); "
             f"{s['rounds']} round(s), runs interleaved; per run the median over frames w + 1 … w + "
             f"{s['timed']} (no compilation), then the median over the rounds; S: implicit-Euler substeps per frame "
             "(the capture was synthesised with 1; rsl adapt's default first, then 1 for the main variants).  Wall: "
             "adapt.h5's times (fwd includes the re-anchoring); CPU: the process CPU time per frame (all threads).  "
             "trust: the --gn-trust that ran, as adapt.h5 records it (gn default: AdaptConfig's default, resolved "
             "from the loss).  "
             "gn / adam: this row's time over adam's with the same S and it, same run (issue 13's target: ≤ 1).  "
             "its / evals: gn's "
             "Gauss–Newton iterations and evaluations of gauss_newton's residual function per timed frame (mean; a "
             "trial step evaluated with its Jacobian ahead and reused as the next linearisation, GNWindow.evaluate's "
             "ahead, counts twice but is one window pass).  E error: round 1, every frame, "
             f"against the E the capture was synthesised with ({E_TRUE:.3g} Pa; every run starts there).", "",
             "| S | it | estimator | J | trust | fwd s | bwd s | render s | total s (wall) | CPU s / frame | "
             "gn / adam (wall) | "
             "gn / adam (CPU) | fd / this (CPU) | its / evals | max \\|E/E_true − 1\\| |",
             "| ---: | ---: | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in data["rows"]:
        fd = "" if r.get("fd_over_this_cpu") is None or r["estimator"] != "gn" else f"{r['fd_over_this_cpu']:.2f}×"
        it = r.get("iters_per_frame", 1)
        ev = "" if r.get("gn_iterations") is None else f"{r['gn_iterations']:.2g} / {r['gn_evaluations']:.2g}"
        trust = "" if r["estimator"] != "gn" or r.get("gn_trust") is None else f"{r['gn_trust']:g}"
        lines.append(f"| {r.get('substeps', 1)} | {it}{' *default*' if it == I0 and I0 != 1 else ''} | "
                     f"{r['estimator']} | {r['variant']} | {trust} | {r['forward_s']:.3g} | "
                     f"{r['backward_s']:.3g} | {r['render_s']:.3g} | {r['total_s']:.3g} | {r['cpu_s']:.3g} | "
                     f"{r['over_adam_wall']:.2f} | {r['over_adam_cpu']:.2f} | {fd} | {ev} | "
                     f"{100 * r['max_err']:.2f} % |")
    cmp_ = data["jvp_vs_fd"]
    row = {(r.get("substeps", 1), r.get("iters_per_frame", 1), r["estimator"], r["variant"]): r for r in data["rows"]}
    S0 = s["substeps"]
    summary = []

    def gn_part(label: str, g: dict) -> str:
        return (f"{label} {g['total_s']:.3g} s wall per frame (gn / adam {g['over_adam_wall']:.2f} wall, "
                f"{g['over_adam_cpu']:.2f} CPU; {g['gn_iterations']:.2g} iterations and {g['gn_evaluations']:.2g} "
                f"evaluations per frame; max E error {100 * g['max_err']:.1f} %)")

    for it in sorted({1, I0}):
        a, g = row.get((S0, it, "adam", "default")), row.get((S0, it, "gn", "jvp"))
        # gn as rsl adapt runs it by default (the row "default"; at 1 iteration the row with the same --gn-trust)
        d = row.get((S0, it, "gn", "default"))
        if d is None:
            d = next((r for r in data["rows"] if r.get("substeps", 1) == S0 and r.get("iters_per_frame", 1) == it
                      and r["estimator"] == "gn" and r["variant"] != "jvp" and r.get("gn_trust") is not None
                      and r["gn_trust"] == data.get("gn_trust_default")), None)
        if a and g:
            summary.append(f"{it} step(s) / at most {it} iteration(s) per frame"
                           f"{' (the defaults)' if it == I0 else ''}: "
                           f"adam {a['total_s']:.3g} s (max E error {100 * a['max_err']:.1f} %); "
                           + (gn_part(f"gn with --gn-trust {d['gn_trust']:g} (the default with images, row "
                                      f"{d['variant']})", d) + "; " if d else "")
                           + gn_part("gn with every step evaluated (--gn-trust 0)", g)
                           + (f"; adam with BLAS on one thread {b['total_s']:.3g} s (gn jvp / that "
                              f"{g['total_s'] / b['total_s']:.2f} wall, {g['cpu_s'] / b['cpu_s']:.2f} CPU)"
                              if (b := row.get((S0, it, "adam", "blas-1"))) else "")
                           + (f"; gn {BOTH_OFF} {o['total_s']:.3g} s wall, {o['cpu_s']:.3g} s CPU (gn jvp / that "
                              f"{g['total_s'] / o['total_s']:.2f} wall, {g['cpu_s'] / o['cpu_s']:.2f} CPU)"
                              if (o := row.get((S0, it, "gn", BOTH_OFF))) else ""))
    twins = data.get("twins", {})
    for pr in data.get("probes_vs_none") or []:
        d = row.get((pr["S"], pr["it"], "gn", pr["variant"]))
        n = row.get((pr["S"], pr["it"], "gn", pr["variant"] + " no-probe"))
        if d and n:
            summary.append(f"the change probes (--change-probe {data['change_probe_default']:g}; row {pr['variant']} "
                           f"against {pr['variant']} no-probe, S = {pr['S']}, it = {pr['it']}): "
                           f"{d['total_s'] - n['total_s']:+.3g} s wall, {d['cpu_s'] - n['cpu_s']:+.3g} s CPU per "
                           f"frame ({d['cpu_s'] / n['cpu_s']:.2f}× CPU); gn without them {n['total_s']:.3g} s wall, "
                           f"gn / adam {n['over_adam_wall']:.2f}; E differs by at most {100 * pr['max_rel']:.2g} %, "
                           f"{pr['max_in_sigma']:.2g} σ_E")
    lines += ["", f"At S = {S0}: " + "; ".join(summary) + ".", "",
              f"gn with the forward-mode J against gn with central differences, the same frames (round 1): E "
              f"differs by at most {100 * cmp_['max_rel']:.2f} % (median {100 * cmp_['median_rel']:.2f} %), at most "
              f"{cmp_['max_in_sigma']:.2f} σ_E (σ_E as gn fd reports it).  gn jvp (memo) against gn jvp no-memo, "
              f"S = {s['substeps']}: E differs by at most {100 * data['memo_vs_no_memo']['max_rel']:.2g} %, at most "
              f"{data['memo_vs_no_memo']['max_in_sigma']:.2g} σ_E.  "
              + "".join(f"gn jvp against gn {n}: E differs by at most {100 * c['max_rel']:.2g} %, at most "
                        f"{c['max_in_sigma']:.2g} σ_E.  " for n, c in twins.items())
              + "gn taking small last steps on the quadratic model against gn with every step evaluated (--gn-trust "
              "0, row jvp), the same S and it: E differs by "
              + "; ".join(f"at most {100 * one['max_rel']:.2f} % (median {100 * one['median_rel']:.2f} %), at most "
                          f"{one['max_in_sigma']:.3f} σ_E ({one['variant']}, --gn-trust {one['gn_trust']:g}, "
                          f"S = {one['S']}, it = {one['it']})" for one in data["one_vs_two"])
              + ".  Per round (CPU s / frame, " + " / ".join(f"S={p[0]} {p[1]} {p[2]} it={p[3] if len(p) > 3 else 1}"
                                                            for p in data["plan"]) + "): "
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
    # rsl adapt's default on this capture (start equilibrium, images): steps (adam) / at most iterations (gn) per frame
    I0 = adapt.resolve_iterations(adapt.AdaptConfig(capture=cap, workspace=ws), "gn", "vision", "")
    plan = ([(S0, est, name, 1) for est, name in VARIANTS]
            + ([(1, est, name, 1) for est, name in VARIANTS_S1] if S0 != 1 else [])
            + ([(S0, est, name, I0) for est, name in DEFAULTS] if I0 != 1 else []))
    for rnd in range(rounds):
        for S, est, name, it in plan:
            t = time.perf_counter()
            r = run_once(cap, ws, work / "Bar" / f"speed_{est}_{name.replace(' ', '_')}_S{S}_i{it}", est, case.w,
                         n_frames, name, S, it)
            runs.setdefault((S, est, name, it), []).append(r)
            print(f"[{time.strftime('%H:%M:%S')}] round {rnd} S={S} {est} {name} {it} it/frame: total "
                  f"{r['total_s']:.3f} s wall, {r['cpu_s']:.3f} s CPU per frame ({time.perf_counter() - t:.0f} s)",
                  flush=True)
    rows = []
    for S, est, name, it in plan:
        rs = runs[(S, est, name, it)]
        base = runs[(S, "adam", "default", it)]  # adam with as many steps per frame as this row's iterations
        row = {"estimator": est, "variant": name, "substeps": S, "iters_per_frame": it}
        for k in ("forward_s", "backward_s", "render_s", "total_s", "cpu_s"):
            row[k] = statistics.median(r[k] for r in rs)
        for k in ("gn_iterations", "gn_evaluations"):  # mean per timed frame, over the rounds
            row[k] = statistics.mean(r[k] for r in rs) if rs[0][k] is not None else None
        row["over_adam_wall"] = row["total_s"] / statistics.median(b["total_s"] for b in base)
        row["over_adam_cpu"] = row["cpu_s"] / statistics.median(b["cpu_s"] for b in base)
        fd = runs.get((S, "gn", "fd", it))
        row["fd_over_this_cpu"] = statistics.median(r["cpu_s"] for r in fd) / row["cpu_s"] if fd else None
        row["rounds"] = [{k: r[k] for k in ("total_s", "cpu_s")} for r in rs]
        row["gn_trust"] = rs[0]["gn_trust"] if est == "gn" else None  # as adapt.h5 records it
        row["young"] = rs[0]["young"]
        row["young_sigma"] = rs[0]["young_sigma"]
        row["max_err"] = float(np.max(np.abs(np.asarray(rs[0]["young"]) / E_TRUE - 1.0)))  # round 1, every frame
        rows.append(row)
    def compare(a: dict, b: dict) -> dict:  # E of run b against run a (σ_E as a reports it)
        ya, yb, sa = np.asarray(a["young"]), np.asarray(b["young"]), np.asarray(a["young_sigma"])
        rel = np.abs(yb - ya) / np.abs(ya)
        return {"max_rel": float(rel.max()), "median_rel": float(np.median(rel)),
                "max_in_sigma": float(np.max(np.abs(yb - ya) / sa)), "frames": a["frames"]}

    jvp_vs_fd = compare(runs[(S0, "gn", "fd", 1)][0], runs[(S0, "gn", "jvp", 1)][0])
    one_vs_two = [dict(compare(runs[(S, "gn", "jvp", it)][0], runs[(S, "gn", name, it)][0]), S=S, it=it,
                       variant=name, gn_trust=runs[(S, "gn", name, it)][0]["gn_trust"])
                  for S, est, name, it in plan if est == "gn" and name in ("jvp 1-eval", "default")]
    memo_vs_not = compare(runs[(S0, "gn", "jvp no-memo", 1)][0], runs[(S0, "gn", "jvp", 1)][0])
    # the fast paths against their twins: E of gn jvp (all on) against each with one switched off
    twins = {name: compare(runs[(S0, "gn", name, 1)][0], runs[(S0, "gn", "jvp", 1)][0])
             for name in ("jvp separate-test", "jvp blas-threads", BOTH_OFF)}
    # the change probes: each "… no-probe" run (--change-probe 0) against its twin with the default probes
    probes = [{"S": S, "it": it, "variant": name.replace(" no-probe", ""),
               **compare(runs[(S, "gn", name, it)][0], runs[(S, "gn", name.replace(" no-probe", ""), it)][0])}
              for S, est, name, it in plan if "no-probe" in name]
    per_round = [[runs[v][i]["cpu_s"] for v in plan] for i in range(rounds)]
    from stages.artefacts import MeshArtefact

    mesh = MeshArtefact.load(ws / "mesh.h5")
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}, "
                       f"load average {os.getloadavg()[0]:.1f} at the end (a shared machine)",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "wall_s": time.perf_counter() - t0, "jvp_vs_fd": jvp_vs_fd, "memo_vs_no_memo": memo_vs_not,
            "twins": twins, "iters_default": I0, "probes_vs_none": probes,
            "change_probe_default": adapt.AdaptConfig.change_probe,
            "one_vs_two": one_vs_two, "plan": [list(x) for x in plan],
            # --gn-trust as AdaptConfig's default resolves it with images (the "default" runs' adapt.h5)
            "gn_trust_default": next((r[0]["gn_trust"] for (S, e, n, it), r in runs.items() if n == "default"
                                      and e == "gn"), None),
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
