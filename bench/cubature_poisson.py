"""The reduced space's cubature fitted at one ν against one fitted at both ends of ν's range.

The elastic energies are linear in (μ, λ), so the reduced forces are g = μ g^μ + λ g^λ.  `rsl train-subspace`
fits its cubature at the snapshots' median ν alone by default, which matches the sum there and not each part;
``--cubature-poisson range`` fits it at both ends of ν's range (stages.steps.train_subspace.cubature_materials).
Per capture and workspace given (LABEL=CAPTURE:WS, the workspace with mesh.h5, snapshots.h5 and an existing
subspace.h5), the workspace's own subspace (the same network weights) gets its cubature refitted both ways at
``--tol`` (bench/reduced_accuracy.refit_cubature: train-subspace's poses, seed and point cap), and `rsl adapt` runs
with each, one after the other, in a copy of the workspace (online, markers, reduced, window 3, E from
0.5 E_true(0), adapt's other defaults).

Columns: cubature points, the median E error per region over the settled frames (≥ w + 5 after the start and
after each step of E_true, as bench/accuracy.py), the median ν over the same frames against the truth's, and the
median s / frame of each run with its ratio to the one-ν run (measured back to back, the same machine and load).

    .venv/bin/python bench/cubature_poisson.py LABEL=CAPTURE:WS [...] [--tol 0.002] [--out docs/results]
        [--adapt-option=--loss --adapt-option=vision] [--append]
    .venv/bin/python bench/cubature_poisson.py --from-json docs/results/cubature_poisson.json
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

VARIANTS = ("one ν (median)", "both ends of ν")


def run_row(label: str, capture: Path, ws: Path, tol: float, options: list[str]) -> list[dict]:
    """The two variants' rows for one capture and workspace."""
    from reduced_accuracy import ADAPT_FILES, adapt_in_copy, last_line, refit_cubature, settled_result

    from stages.artefacts import SnapshotsArtefact
    from stages.capture import load_capture, read_truth
    from stages.steps.train_subspace import cubature_materials

    cap = load_capture(capture)
    truth = read_truth(cap)
    snap = SnapshotsArtefact.load(ws / "snapshots.h5")
    spans = {VARIANTS[0]: [np.median(snap.poisson, axis=0)],
             VARIANTS[1]: cubature_materials(snap.poisson, cap.material.poisson_range)}
    rows = []
    for variant, span in spans.items():
        art = refit_cubature(ws, tol, span)
        row = {"label": label, "capture": str(capture), "truth": truth_of(capture), "variant": variant, "tol": tol,
               "adapt_options": options,
               "nu_fitted": [np.asarray(s).tolist() for s in span], "points": len(art.extra["cubature_points"]),
               "fit_error_rel": art.extra["cubature_error_rel"]}
        ad, stderr = adapt_in_copy(capture, ws, art, 0.5 * float(np.asarray(truth.young)[0, 0]), options,
                                   ADAPT_FILES + ("masks.h5", "gaussians.h5"))
        row.update(settled_result(ad, truth) if ad is not None else {"adapt_error": last_line(stderr)})
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "young_ratio"}), flush=True)
    return rows


def truth_of(capture: str) -> str:
    """How the capture's truth was simulated, from capture.toml's [synth] table: "N = 24, β = 3 ms, start rest"."""
    import tomllib

    syn = tomllib.loads((Path(capture) / "capture.toml").read_text()).get("synth", {})
    beta = float(syn.get("damping", 0.0))
    return (f"N = {syn.get('substeps', '?')}" + (f", β = {1e3 * beta:g} ms" if beta else "")
            + f", start {syn.get('start', '?')}")


def _options(r: dict) -> str:
    """The row's extra rsl adapt options, as they were passed ("" for none)."""
    opts = " ".join(r.get("adapt_options", []))
    return f" (`{opts}`)" if opts else ""


def summary(rows: list[dict]) -> list[str]:
    """Per variant, over the captures (label, truth, options; a capture measured twice: its last pair): the mean of
    each row's largest median settled E error, and how many rows meet the accuracy issue's targets (every region
    ≤ 5 % with one region, ≤ 10 % with several)."""
    last: dict = {}
    for r in rows:
        if "adapt_error" not in r:
            last[(r["label"], r.get("truth") or truth_of(r["capture"]), tuple(r.get("adapt_options", [])),
                  r["variant"])] = r
    out = []
    for v in VARIANTS:
        errs = [(max(r["median_error"]), len(r["median_error"])) for k, r in last.items() if k[3] == v]
        if errs:
            met = sum(e <= (0.05 if n == 1 else 0.10) for e, n in errs)
            mean = 100 * np.mean([e for e, _ in errs])
            out.append(f"- {v}: mean of the rows' largest median settled E error {mean:.1f} % over {len(errs)} "
                       f"captures; {met} of {len(errs)} within the targets (≤ 5 %, ≤ 10 % per "
                       f"region with several).")
    return out


def markdown(res: dict) -> str:
    """The page, from the measured rows alone."""
    rows = res["rows"]
    lines = ["# The reduced space's cubature: fitted at one ν or at two", "",
             f"Each capture's own subspace (the same network), its cubature refitted at tol {res['tol']:g} at the "
             "snapshots' median ν alone (`rsl train-subspace`'s default, `--cubature-poisson median`) and at two ν "
             "(`--cubature-poisson range`, `train_subspace.cubature_materials`: the ends of capture.toml's "
             "poisson_range; the first rows measured took the ends of the snapshots' ν, the column ν fitted gives "
             "them); `rsl adapt` online, "
             "markers unless the options say otherwise, reduced, window 3, E from 0.5 E_true, once with each, back "
             "to back. Truth: P2 tets, hard handles, N substeps per frame (capture.toml [synth]). Settled frames: "
             "≥ w + 5 after the start and after each step of E_true. Produced by `bench/cubature_poisson.py`.", "",
             "| capture | truth | cubature fitted at | ν fitted | points | median settled E error per region (%) | "
             "median settled ν (truth) | s / frame | s / frame ÷ one-ν run |",
             "| --- | --- | --- | --- | ---: | --- | --- | ---: | ---: |"]
    base: dict = {}
    for r in rows:
        truth = r.get("truth") or truth_of(r["capture"])
        nus = " / ".join(", ".join(f"{x:.3f}" for x in s) for s in r["nu_fitted"])
        if "adapt_error" in r:
            lines.append(f"| {r['label']}{_options(r)} | {truth} | {r['variant']} | {nus} | {r['points']} | "
                         f"adapt failed: {r['adapt_error']} | — | — | — |")
            continue
        key = (r["label"], tuple(r.get("adapt_options", [])))
        if r["variant"] == VARIANTS[0]:
            base[key] = r["s_per_frame"]
        ratio = r["s_per_frame"] / base[key] if key in base else float("nan")
        err = per_region(r, "median_error", lambda x: f"{100 * x:.1f}")
        nu = per_region(r, "median_poisson", lambda x: f"{x:.3f}")
        nu_true = ", ".join(f"{x:.2f}" for x in r["poisson_true"])
        lines.append(f"| {r['label']}{_options(r)} | {truth} | {r['variant']} | {nus} | {r['points']} | {err} | "
                     f"{nu} ({nu_true}) | {r['s_per_frame']:.2f} | {ratio:.2f} |")
    lines += [""] + summary(rows)
    lines += ["", f"Ended {res['ended']} (load average {res['load_average']:.1f}), {res['machine']}.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", nargs="*", help="LABEL=CAPTURE:WS (split at the last =)")
    ap.add_argument("--tol", type=float, default=0.002, help="train-subspace --cubature-tol of the refits")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--from-json", type=Path, default=None, help="rewrite the page from this JSON")
    ap.add_argument("--adapt-option", action="append", default=[],
                    help="one more rsl adapt option for these rows (repeat per word: --adapt-option=--loss "
                         "--adapt-option=vision)")
    ap.add_argument("--append", action="store_true", help="add these rows to the page's existing JSON")
    a = ap.parse_args()
    if a.from_json is not None:
        res = json.loads(a.from_json.read_text())
    else:
        rows = earlier_rows(a.out / "cubature_poisson.json", a.append)
        for label, capture, ws in row_specs(a.rows):
            rows += run_row(label, capture, ws, a.tol, a.adapt_option)
        res = {"tol": a.tol, "rows": rows, **run_stamp()}
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "cubature_poisson.json").write_text(json.dumps(res, indent=1))
    page = markdown(res)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "cubature_poisson.md").write_text(page)
    print(page)


if __name__ == "__main__":
    main()
