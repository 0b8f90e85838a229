"""Re-binding the Gaussians (ImageLoss.rebind → stages.sim.locate) on the Bar-like case of bench/adapt_speed.py: the
Relocator (a walk from each Gaussian's last tet, one k-d tree query for the rest) against its slow twins, on the
anchor configurations `rsl adapt` re-binds at.

The configurations are recorded from one `rsl adapt` run per estimator at rsl adapt's defaults (images, reduced
space, w = 3; gn: its trial steps and estimates, Adam: its steps, larger), then each re-binding is replayed, in
order, with the hint of the last one (as ImageLoss.rebind does):

- search: locate_in_elements without a hint (a k-d tree query of every Gaussian, locate_in_tets);
- hint search: with the hint, the Gaussians strictly inside their hinted tet kept, the others searched (the path
  rebind took before the Relocator: the slow twin);
- relocator: with the hint and the Relocator (what rebind takes now).

Prints a table: median seconds per re-binding, the ratio against the hint search, and whether the tets and
barycentrics are the same floats as the search's.

    nice python bench/locate_speed.py              # table1's Bar (128², 5000 Gaussians), 4 timed frames
    nice python bench/locate_speed.py --quick      # table1's --quick Bar (64², 2000 Gaussians)
"""
from __future__ import annotations

import argparse
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
from stages.progress import SilentReporter  # noqa: E402
from stages.render.image_loss import ImageLoss  # noqa: E402
from stages.sim.locate import Relocator, locate_in_elements  # noqa: E402
from stages.steps import adapt  # noqa: E402


def record(cap: Path, ws: Path, out: Path, estimator: str, n_frames: int) -> tuple:
    """(points (P, 3), tets, the host tets before the first re-binding, [configurations (n, 3)]) of one run."""
    out.mkdir(parents=True, exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5", "subspace.h5"):
        shutil.copy(ws / f, out / f)
    seen: list = []
    orig = ImageLoss.rebind

    def rebind(self, x_fit):
        if x_fit is not None and (self._anchor_x is None or not np.array_equal(x_fit, self._anchor_x)):
            if not seen:
                seen.append((self._fit_means.copy(), self._tets.copy(), self.host_tet.copy()))
            seen.append(np.array(x_fit, np.float64))
        return orig(self, x_fit)

    ImageLoss.rebind = rebind
    try:
        adapt.run(adapt.AdaptConfig(capture=cap, workspace=out, space="reduced", loss="vision", window=3,
                                    frames=f"0:{n_frames}", estimator=estimator, anchor_calibration=0),
                  SilentReporter())
    finally:
        ImageLoss.rebind = orig
    (points, tets, host0), configs = seen[0], seen[1:]
    return points, tets, host0, configs


def replay(points, tets, host0, configs) -> dict:
    """Per path: seconds per re-binding (list) and whether every result equals the search's floats."""
    reloc = Relocator(points, tets)
    times = {"search": [], "hint search": [], "relocator": []}
    same = {"hint search": True, "relocator": True}
    hint = {"hint search": host0, "relocator": host0}
    for x in configs:
        t = time.perf_counter()
        ref = locate_in_elements(points, x, tets)
        times["search"].append(time.perf_counter() - t)
        for name, kw in (("hint search", {}), ("relocator", {"relocator": reloc})):
            t = time.perf_counter()
            got = locate_in_elements(points, x, tets, hint=hint[name], **kw)
            times[name].append(time.perf_counter() - t)
            same[name] &= bool(np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1]))
            hint[name] = got[0]
    return {"times": times, "same": same}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="table1's --quick Bar (64², 2000 Gaussians).")
    ap.add_argument("--timed", type=int, default=4, help="Frames adapted after the first window.")
    ap.add_argument("--work", default="/tmp/rsl_bench_table1", help="table1's work folder (its builds are reused).")
    args = ap.parse_args()
    case = next(c for c in table1.CASES if c.name == "Bar")
    resolution, gaussians, fit_iters, timed_t1 = (64, 2000, 10, 2) if args.quick else (128, 5000, 20, 4)
    work = Path(args.work) / ("quick" if args.quick else "full")
    cap, ws = table1.build(case, work, case.w + timed_t1 + 2, resolution, gaussians, fit_iters)
    n_frames = case.w + 1 + args.timed
    rows = []
    for est in ("gn", "adam"):
        points, tets, host0, configs = record(cap, ws, work / "Bar" / f"locate_{est}", est, n_frames)
        r = replay(points, tets, host0, configs)
        base = statistics.median(r["times"]["hint search"])
        for name, ts in r["times"].items():
            med = statistics.median(ts)
            rows.append((est, len(configs), name, med, med / base, r["same"].get(name, True)))
    print(f"Bar, {len(points)} Gaussians in {len(tets)} tets; the re-bindings of rsl adapt over frames "
          f"0..{n_frames - 1} (defaults), replayed in order\n")
    print("| estimator | re-bindings | path | s / re-binding (median) | / hint search | = search's floats |")
    print("| --- | ---: | --- | ---: | ---: | --- |")
    for est, n, name, med, ratio, same in rows:
        print(f"| {est} | {n} | {name} | {med:.4f} | {ratio:.2f} | {'yes' if same else 'NO'} |")


if __name__ == "__main__":
    main()
