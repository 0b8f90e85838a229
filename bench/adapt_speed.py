"""Per-frame time of online identification (`rsl adapt`, images, reduced space) on Table 1's Bar-like case
(≈10K DOFs, r = 30, w = 3, c = 4 cameras at 128², 5000 Gaussians; bench/table1.py builds it), with and
without each speed fix, for both estimators (adam: one Adam step per frame; gn: Gauss–Newton), all in one run.

Variants (each fix switched off by replacing, in this process only, the function that carries it):

- before: torch's default intra-op thread count during the run, and ImageLoss.rebind locating every Gaussian
  by the k-d tree search (no host hint) — the code before the fixes;
- threads: adapt runs under stages.render.gaussians.one_torch_thread() (torch's thread pool only spins against
  the numba rasterizer's threads), rebind still without the hint;
- after: both (rebind keeps each Gaussian's host while it stays strictly inside it: the same floats).

Each run adapts frames 0..w+timed; the values are medians over the frames after the first whose window starts
from stored states (frame > w: no first call's compilation; bench/table1.py takes the same frames): adapt.h5's
wall times (time_forward_s, time_backward_s, time_render_s, time_total_s) and the process CPU time per frame
(all threads, measured here between the reporter's per-frame calls).  Runs are interleaved (rounds × estimators
× variants), so load from other jobs falls on all alike; ratios are before / variant within this run.  The
E trajectories of the variants are compared (the fixes must not change the result).

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
from stages.render import gaussians as render_gaussians  # noqa: E402
from stages.render import image_loss  # noqa: E402
from stages.steps import adapt  # noqa: E402

RESULTS = ROOT / "docs" / "results"
TARGET_S = 0.26  # issue 13: the Bar-like case's per-frame time with Adam some weeks ago
VARIANTS = ("before", "threads", "after")


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
    """Switch the fixes off for ``before`` (both) and ``threads`` (the rebind hint)."""
    saved_threads, saved_locate = render_gaussians.one_torch_thread, image_loss.locate_in_elements
    if name == "before":
        render_gaussians.one_torch_thread = contextlib.nullcontext
    if name in ("before", "threads"):
        image_loss.locate_in_elements = lambda *a, hint=None, **k: saved_locate(*a, **k)
    try:
        yield
    finally:
        render_gaussians.one_torch_thread, image_loss.locate_in_elements = saved_threads, saved_locate


def run_once(cap: Path, ws: Path, out: Path, estimator: str, w: int, n_frames: int, name: str) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5", "subspace.h5"):
        shutil.copy(ws / f, out / f)
    cfg = adapt.AdaptConfig(capture=cap, workspace=out, space="reduced", loss="vision", window=w,
                            iters_per_frame=1, frames=f"0:{n_frames}", estimator=estimator)
    clock = _CpuClock()
    with variant(name):
        art = AdaptArtefact.load(adapt.run(cfg, clock))
    sel = np.asarray(art.frames) > w
    med = lambda a: float(np.median(np.asarray(a)[sel]))  # noqa: E731
    return {"forward_s": med(art.time_forward_s), "backward_s": med(art.time_backward_s),
            "render_s": med(art.time_render_s), "total_s": med(art.time_total_s),
            "cpu_s": float(np.median(np.asarray(clock.cpu)[sel])), "frames_timed": int(sel.sum()),
            "young": np.asarray(art.young).tolist()}


def markdown(data: dict) -> str:
    s = data["settings"]
    lines = ["# Per-frame time of `rsl adapt` (Bar-like case) with and without the speed fixes", "",
             f"Machine: {data['machine']}; {data['date']}; wall time of the whole run {data['wall_s'] / 60:.1f} min.",
             "",
             f"Case: {s['case']}; reduced space, images ({s['resolution']}², {s['gaussians']} Gaussians, "
             f"c = {s['cameras']}), r = {s['r']}, w = {s['w']}, one step per frame; {s['rounds']} round(s), runs "
             f"interleaved; per run the median over frames w + 1 … w + {s['timed']} (no compilation), then the "
             "median over the rounds.  Wall: adapt.h5's times; CPU: the process CPU time per frame (all threads). "
             f"Ratio: before / this variant, same run.  Issue 13's target: ≤ {TARGET_S} s per frame.", "",
             "| estimator | variant | fwd s | bwd s | render s | total s (wall) | CPU s / frame | ratio wall | "
             "ratio CPU | ≤ target (wall) | ≤ target (CPU) | max rel. E difference vs before |",
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- | ---: |"]
    for r in data["rows"]:
        lines.append(f"| {r['estimator']} | {r['variant']} | {r['forward_s']:.3g} | {r['backward_s']:.3g} | "
                     f"{r['render_s']:.3g} | {r['total_s']:.3g} | {r['cpu_s']:.3g} | {r['ratio_wall']:.2f}× | "
                     f"{r['ratio_cpu']:.2f}× | {'yes' if r['total_s'] <= TARGET_S else 'no'} | "
                     f"{'yes' if r['cpu_s'] <= TARGET_S else 'no'} | {r['young_rel_diff']:.1e} |")
    lines += ["", "Variants: before = torch's default thread count and rebind's full search; threads = "
              "one_torch_thread() only; after = both fixes.  Generated by bench/adapt_speed.py.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="table1's --quick Bar (64², 2000 Gaussians), 1 round.")
    ap.add_argument("--rounds", type=int, default=None)
    ap.add_argument("--timed", type=int, default=4, help="Timed frames per run (after frame w).")
    ap.add_argument("--estimators", default="adam,gn")
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
    for rnd in range(rounds):
        for est in args.estimators.split(","):
            for name in VARIANTS:
                t = time.perf_counter()
                r = run_once(cap, ws, work / "Bar" / f"speed_{est}_{name}", est, case.w, n_frames, name)
                runs.setdefault((est, name), []).append(r)
                print(f"[{time.strftime('%H:%M:%S')}] round {rnd} {est} {name}: total {r['total_s']:.3f} s wall, "
                      f"{r['cpu_s']:.3f} s CPU per frame ({time.perf_counter() - t:.0f} s)", flush=True)
    rows = []
    for est in args.estimators.split(","):
        base = runs[(est, "before")]
        for name in VARIANTS:
            rs = runs[(est, name)]
            row = {"estimator": est, "variant": name}
            for k in ("forward_s", "backward_s", "render_s", "total_s", "cpu_s"):
                row[k] = statistics.median(r[k] for r in rs)
            row["ratio_wall"] = statistics.median(b["total_s"] for b in base) / row["total_s"]
            row["ratio_cpu"] = statistics.median(b["cpu_s"] for b in base) / row["cpu_s"]
            yb, yv = np.asarray(base[0]["young"]), np.asarray(rs[0]["young"])
            row["young_rel_diff"] = float(np.max(np.abs(yv - yb) / np.abs(yb)))
            row["rounds"] = [{k: r[k] for k in ("total_s", "cpu_s")} for r in rs]
            rows.append(row)
    from stages.artefacts import MeshArtefact

    mesh = MeshArtefact.load(ws / "mesh.h5")
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}, "
                       f"load average {os.getloadavg()[0]:.1f} at the end (a shared machine)",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "wall_s": time.perf_counter() - t0, "target_s": TARGET_S,
            "settings": {"case": f"Bar, {case.shape}, {3 * mesh.n_vertices} DOFs, {mesh.n_tets} tets of order "
                                 f"{mesh.order}", "resolution": resolution, "gaussians": gaussians,
                         "cameras": case.c, "r": case.r, "w": case.w, "timed": timed, "rounds": rounds,
                         "quick": args.quick},
            "cases": rows, "rows": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "adapt_speed.json").write_text(json.dumps(data, indent=1))
    (RESULTS / "adapt_speed.md").write_text(markdown(data))
    print(markdown(data))


if __name__ == "__main__":
    main()
