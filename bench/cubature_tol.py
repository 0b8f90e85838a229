"""The reduced space's cubature tolerance against identification: the same networks, their cubature refitted.

`rsl train-subspace` fits its cubature (non-negative least squares over quadrature points, stages.subspace.cubature)
until the reduced forces of its training poses are matched to ``--cubature-tol`` (relative).  Per capture and
workspace given (LABEL=CAPTURE:WS, the workspace with mesh.h5, snapshots.h5 and a subspace.h5), the workspace's own
subspace (the same network weights) gets its cubature refitted at each tolerance (bench/reduced_accuracy.
refit_cubature: train-subspace's poses, seed and materials, at most ``--max-points`` points), and `rsl adapt` runs
with each, one after the other, in a copy of the workspace (online, markers, reduced, window 3, E from
0.5 E_true(0), adapt's other defaults).

Columns: cubature points, the fit's relative error, the median E error per region over the settled frames (≥ w + 5
after the start and after each step of E_true, as bench/accuracy.py), and the median s / frame of each run with
its ratio to the first tolerance's run (measured back to back, the same machine and load).

    .venv/bin/python bench/cubature_tol.py LABEL=CAPTURE:WS [...] [--tols 0.002 0.0005] [--max-points 600]
        [--out docs/results] [--append]
    .venv/bin/python bench/cubature_tol.py --from-json docs/results/cubature_tol.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

from reduced_accuracy import earlier_rows, per_region, row_specs, run_stamp  # noqa: E402


def run_row(label: str, capture: Path, ws: Path, tols: list[float], max_points: int) -> list[dict]:
    """One row per tolerance for one capture and workspace."""
    import reduced_accuracy as ra

    from stages.artefacts import read_provenance
    from stages.capture import load_capture, read_truth

    truth = read_truth(load_capture(capture))
    E0 = float(np.asarray(truth.young)[0, 0])
    sequences = int(read_provenance(ws / "snapshots.h5").get("config", {}).get("sequences", -1))
    ra.CUBATURE_MAX_POINTS = max_points
    rows = []
    for tol in tols:
        art = ra.refit_cubature(ws, tol)
        row = {"label": label, "capture": str(capture), "workspace": str(ws), "sequences": sequences,
               "dim": int(art.dim), "tol": tol, "max_points": max_points,
               "points": len(art.extra["cubature_points"]), "fit_error_rel": float(art.extra["cubature_error_rel"])}
        ad, stderr = ra.adapt_in_copy(capture, ws, art, 0.5 * E0)
        row.update(ra.settled_result(ad, truth) if ad is not None else {"adapt_error": ra.last_line(stderr)})
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "young_ratio"}), flush=True)
    return rows


def summary(rows: list[dict]) -> list[str]:
    """Per tolerance, over the workspaces measured: the mean and the largest of each row's largest median settled E
    error, how many rows meet the accuracy issue's targets (≤ 5 % with one region, ≤ 10 % per region with several),
    and the median s / frame ratio to each workspace's first tolerance."""
    out = []
    first: dict = {}
    for r in rows:
        if "adapt_error" not in r:
            first.setdefault(r["workspace"], r)
    for tol in dict.fromkeys(r["tol"] for r in rows):
        ok = [r for r in rows if r["tol"] == tol and "adapt_error" not in r]
        if not ok:
            continue
        errs = [(max(r["median_error"]), len(r["median_error"])) for r in ok]
        met = sum(e <= (0.05 if n == 1 else 0.10) for e, n in errs)
        ratio = np.median([r["s_per_frame"] / first[r["workspace"]]["s_per_frame"] for r in ok])
        out.append(f"- tol {tol:g}: mean of the rows' largest median settled E error "
                   f"{100 * np.mean([e for e, _ in errs]):.1f} %, largest {100 * max(e for e, _ in errs):.1f} %, over "
                   f"{len(ok)} workspaces; {met} of {len(ok)} within the targets (≤ 5 %, ≤ 10 % per region with "
                   f"several); s / frame {ratio:.2f} × the first tolerance's (median).")
    return out


def markdown(res: dict) -> str:
    """The page, from the measured rows alone."""
    lines = ["# The reduced space's cubature tolerance", "",
             "Each workspace's own subspace (the same network), its cubature refitted at each tolerance as `rsl "
             "train-subspace --cubature-tol` fits it (at most the points given); `rsl adapt` online, markers, reduced, "
             "window 3, E from 0.5 E_true, once with each, back to back. Truth: P2 tets, hard handles, N substeps per "
             "frame (capture.toml [synth]). Settled frames: ≥ w + 5 after the start and after each step of E_true. "
             "Produced by `bench/cubature_tol.py`.", "",
             "| capture | training sequences | r | tol | points | fit error (%) | "
             "median settled E error per region (%) | s / frame | ÷ first tol |",
             "| --- | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    first: dict = {}
    for r in res["rows"]:
        head = (f"| {r['label']} | {r['sequences']} | {r['dim']} | {r['tol']:g} | {r['points']} | "
                f"{100 * r['fit_error_rel']:.2f} | ")
        if "adapt_error" in r:
            lines.append(head + f"adapt failed: {r['adapt_error']} | — | — |")
            continue
        base = first.setdefault(r["workspace"], r["s_per_frame"])
        lines.append(head + f"{per_region(r, 'median_error', lambda x: f'{100 * x:.1f}')} | "
                     f"{r['s_per_frame']:.2f} | {r['s_per_frame'] / base:.2f} |")
    lines += [""] + summary(res["rows"])
    lines += ["", f"Ended {res['ended']} (load average {res['load_average']:.1f}), {res['machine']}."
              + (f" {res['note'][0].upper()}{res['note'][1:]}." if res.get("note") else ""), ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", nargs="*", help="LABEL=CAPTURE:WS (split at the last =)")
    ap.add_argument("--tols", type=float, nargs="+", default=[0.002, 0.0005])
    ap.add_argument("--max-points", type=int, default=600, help="most cubature points of a refit")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--from-json", type=Path, default=None, help="rewrite the page from this JSON")
    ap.add_argument("--append", action="store_true", help="add these rows to the page's existing JSON")
    a = ap.parse_args()
    if a.from_json is not None:
        res = json.loads(a.from_json.read_text())
    else:
        rows = earlier_rows(a.out / "cubature_tol.json", a.append)
        for label, capture, ws in row_specs(a.rows):
            rows += run_row(label, capture, ws, a.tols, a.max_points)
        res = {"rows": rows, **run_stamp()}
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "cubature_tol.json").write_text(json.dumps(res, indent=1))
    page = markdown(res)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "cubature_tol.md").write_text(page)
    print(page)


if __name__ == "__main__":
    main()
