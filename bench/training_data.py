"""generate-data's choices (how materials are drawn, time step, start state) against identification.

`rsl generate-data` simulates the sequences the subspace is trained on.  Part 1, coverage (no simulation): the
fraction of the ν range and of the log E range that the snapshots' per-frame materials span (max − min over
``ramp`` sequences, one region), over many seeds, per number of sequences and material design
(stages.steps.generate_data.material_ends: ``independent`` draws each end on its own, ``latin`` takes a Latin
hypercube over all the sequences' ends).

Part 2, identification: per capture and workspace given (LABEL=CAPTURE:WS, WS holding mesh.h5 and cameras.h5), per
variant (``--variant "NAME=generate-data options"``) and seed, a copy of the workspace gets `rsl generate-data`
(``--sequences``, the capture's frames, ``--seed``, the variant's options), `rsl train-subspace --dim r
--cubature-tol 0.002` and `rsl adapt` (online, markers, reduced, window 3, E from 0.5 E_true(0), adapt's other
defaults).  Columns: the snapshots' ν span, the median E error per region over the settled frames (≥ w + 5 after
the start and after each step of E_true, as bench/accuracy.py), the median ν there against the truth's,
generate-data's wall time.

    .venv/bin/python bench/training_data.py LABEL=CAPTURE:WS [...] --variant "NAME=OPTIONS" [...] [--seeds 0 1 2]
        [--sequences 4] [--out docs/results] [--append]
    .venv/bin/python bench/training_data.py --from-json docs/results/training_data.json
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

from reduced_accuracy import earlier_rows, per_region, row_specs, run_stamp  # noqa: E402

DESIGNS = ("independent", "latin")
SEQUENCES = 4
DIM = 30


def coverage(n_sequences: int, design: str, seeds: int, frames: int = 36) -> dict:
    """Per seed, the fraction of the ν range and of the log E range spanned by the per-frame materials of
    n ``ramp`` sequences (generate_data.material_ends and sample_material, one region)."""
    from stages.steps.generate_data import material_ends, sample_material

    young_range, poisson_range = (2e4, 5e5), (0.30, 0.49)
    nu_cov, e_cov = [], []
    for seed in range(seeds):
        log_e, nu = material_ends(young_range, poisson_range, n_sequences, 1,
                                  np.random.default_rng([seed, n_sequences, 1]), design)
        mats = [sample_material(log_e[i], nu[i], young_range, frames, "ramp") for i in range(n_sequences)]
        y = np.log(np.concatenate([m[0] for m in mats]))
        p = np.concatenate([m[1] for m in mats])
        nu_cov.append(np.ptp(p) / (poisson_range[1] - poisson_range[0]))
        e_cov.append(np.ptp(y) / np.log(young_range[1] / young_range[0]))
    return {"sequences": n_sequences, "design": design, "seeds": seeds,
            "nu_median": float(np.median(nu_cov)), "nu_p10": float(np.percentile(nu_cov, 10)),
            "logE_median": float(np.median(e_cov)), "logE_p10": float(np.percentile(e_cov, 10))}


def rsl(*args, env=None) -> subprocess.CompletedProcess:
    """One rsl command in this repository's interpreter (its stderr kept for the error)."""
    return subprocess.run([sys.executable, "-m", "rsl_cli.app", *map(str, args)], capture_output=True, text=True,
                          env=env, cwd=ROOT)


def run_case(label: str, capture: Path, ws: Path, variant: str, options: list[str], seed: int,
             sequences: int = SEQUENCES, dim: int = DIM) -> dict:
    """One variant of generate-data's options, seed and number of sequences on one capture: generate-data,
    train-subspace, adapt in a copy of WS."""
    from reduced_accuracy import last_line, settled_result

    from stages.artefacts import AdaptArtefact, SnapshotsArtefact, read_provenance
    from stages.capture import load_capture, read_truth

    truth = read_truth(load_capture(capture))
    T = truth.young.shape[0]
    E0 = float(np.asarray(truth.young)[0, 0])
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
    row = {"label": label, "capture": str(capture), "variant": variant, "options": options, "seed": seed,
           "sequences": sequences, "dim": dim}
    with tempfile.TemporaryDirectory() as tmp:
        wt = Path(tmp) / "ws"
        wt.mkdir()
        for f in ("mesh.h5", "cameras.h5"):
            if (ws / f).is_file():
                shutil.copy(ws / f, wt / f)
        steps = [("generate-data", capture, "-w", wt, "--sequences", sequences, "--frames", T, "--workers", 1,
                  "--seed", seed, *options),
                 ("train-subspace", "-w", wt, "--dim", dim, "--cubature-tol", 0.002),
                 ("adapt", capture, "-w", wt, "--space", "reduced", "--loss", "markers", "--window", 3,
                  "--young-init", f"{0.5 * E0:g}")]
        for step in steps:
            p = rsl(*step, env=env)
            if p.returncode != 0:
                return {**row, "error": f"{step[0]}: {last_line(p.stderr)}"}
        snap = SnapshotsArtefact.load(wt / "snapshots.h5")
        row.update({"snapshot_poisson": [float(snap.poisson.min()), float(snap.poisson.max())],
                    "snapshot_young": [float(snap.young.min()), float(snap.young.max())],
                    **settled_result(AdaptArtefact.load(wt / "adapt.h5"), truth),
                    "generate_s": float(read_provenance(wt / "snapshots.h5").get("wall_s", float("nan")))})
    return row


def _fmt(x) -> str:
    """Seconds, or — where the run did not record them."""
    return "—" if x is None or not np.isfinite(x) else f"{x:.0f}"


def setting(r: dict) -> tuple[str, int, int]:
    """(variant, sequences, r) of a run."""
    return r["variant"], r.get("sequences", SEQUENCES), r.get("dim", DIM)


def variants_of(rows: list[dict]) -> list[tuple[str, int, int]]:
    """The (variant, sequences, r) settings measured, in the order first measured."""
    return list(dict.fromkeys(setting(r) for r in rows))


def summary(rows: list[dict]) -> list[str]:
    """Per variant, number of sequences and r, over every capture and seed measured: the mean and the largest of each
    run's largest median settled E error, and how many runs meet the accuracy issue's targets (≤ 5 % with one
    region, ≤ 10 % per region with several)."""
    out = []
    for variant, n_seq, dim in variants_of(rows):
        errs = [(max(r["median_error"]), len(r["median_error"])) for r in rows
                if setting(r) == (variant, n_seq, dim) and "error" not in r]
        if errs:
            met = sum(e <= (0.05 if n == 1 else 0.10) for e, n in errs)
            out.append(f"- {variant}, {n_seq} sequences, r = {dim}: mean of the runs' largest median settled E error "
                       f"{100 * np.mean([e for e, _ in errs]):.1f} %, largest {100 * max(e for e, _ in errs):.1f} %, "
                       f"over {len(errs)} runs; {met} of {len(errs)} within the targets (≤ 5 %, ≤ 10 % per region "
                       "with several).")
    return out


def markdown(res: dict) -> str:
    """The page, from the measured rows alone."""
    lines = ["# generate-data's training sequences against identification", "",
             "`rsl generate-data` simulates the sequences `rsl train-subspace` learns the reduced space from. Produced "
             "by `bench/training_data.py`.", "", "## Coverage of the prior ranges by the materials drawn", "",
             "`--material-design independent` draws log E and ν at each end of each sequence on its own; `latin` takes "
             "a Latin hypercube over all the sequences' ends (`generate_data.material_ends`). Fraction of the range "
             "spanned by the snapshots' per-frame materials (`ramp` sequences, one region, ν in 0.30–0.49, E in "
             f"20–500 kPa), over {res['coverage'][0]['seeds']} seeds.", "",
             "| sequences | design | ν span, median | ν span, 10th percentile | log E span, median | "
             "log E span, 10th percentile |", "| ---: | --- | ---: | ---: | ---: | ---: |"]
    for c in res["coverage"]:
        lines.append(f"| {c['sequences']} | {c['design']} | {c['nu_median']:.2f} | {c['nu_p10']:.2f} | "
                     f"{c['logE_median']:.2f} | {c['logE_p10']:.2f} |")
    lines += ["", "## Identification with the reduced space trained on each", "",
              "Per capture, variant (generate-data's options), number of sequences n, latent dimension r and seed: "
              "`rsl generate-data --sequences n` (the capture's frames, `--seed`, the variant's options), "
              "`rsl train-subspace --dim r "
              "--cubature-tol 0.002`, `rsl adapt` online, markers, reduced, window 3, E from 0.5 E_true, in a copy of "
              "the workspace (its mesh.h5 and cameras.h5). Truth: P2 tets, hard handles, N substeps per frame "
              "(capture.toml [synth]). Settled frames: ≥ w + 5 after the start and after each step of E_true.", "",
              "Variants: " + "; ".join(f"{v} = `{' '.join(o) or '(defaults)'}`" for v, o in
                                       dict((r["variant"], r["options"]) for r in res["rows"]).items()) + ".", "",
              "| capture | variant | sequences | r | seed | snapshots' ν | median settled E error per region (%) | "
              "median settled ν (truth) | s / frame | generate-data (s) |",
              "| --- | --- | ---: | ---: | ---: | --- | --- | --- | ---: | ---: |"]
    for r in res["rows"]:
        head = (f"| {r['label']} | {r['variant']} | {r.get('sequences', SEQUENCES)} | {r.get('dim', DIM)} | "
                f"{r['seed']} | ")
        if "error" in r:
            lines.append(head + f"— | failed: {r['error']} | — | — | — |")
            continue
        err = per_region(r, "median_error", lambda x: f"{100 * x:.1f}")
        nu = per_region(r, "median_poisson", lambda x: f"{x:.3f}")
        nu_true = ", ".join(f"{x:.2f}" for x in r["poisson_true"])
        lo, hi = r["snapshot_poisson"]
        lines.append(head + f"{lo:.3f}–{hi:.3f} | {err} | {nu} ({nu_true}) | {r['s_per_frame']:.2f} | "
                     f"{_fmt(r.get('generate_s'))} |")
    lines += [""] + summary(res["rows"])
    lines += ["", f"Ended {res['ended']} (load average {res['load_average']:.1f}), {res['machine']}."
              + (f" {res['note'][0].upper()}{res['note'][1:]}." if res.get("note") else ""), ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", nargs="*", help="LABEL=CAPTURE:WS (split at the last =)")
    ap.add_argument("--variant", action="append", default=[],
                    help='NAME=generate-data options, split at the first = ("latin, S = 6=--substeps 6" does not '
                         'work: a name holds no =)')
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="generate-data --seed of each run")
    ap.add_argument("--sequences", type=int, default=SEQUENCES, help="generate-data --sequences of each run")
    ap.add_argument("--dim", type=int, default=DIM, help="train-subspace --dim of each run")
    ap.add_argument("--coverage-seeds", type=int, default=500)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--from-json", type=Path, default=None, help="rewrite the page from this JSON")
    ap.add_argument("--append", action="store_true", help="add these rows to the page's existing JSON")
    a = ap.parse_args()
    if a.from_json is not None:
        res = json.loads(a.from_json.read_text())
    else:
        rows = earlier_rows(a.out / "training_data.json", a.append)
        variants = [(v.split("=", 1)[0].strip(), v.split("=", 1)[1].split()) for v in a.variant] or [("defaults", [])]
        for label, capture, ws in row_specs(a.rows):
            for seed in a.seeds:
                for name, options in variants:
                    rows.append(run_case(label, capture, ws, name, options, seed, a.sequences, a.dim))
                    print(json.dumps({k: v for k, v in rows[-1].items() if k != "young_ratio"}), flush=True)
        cov = [coverage(n, d, a.coverage_seeds) for n in (4, 8, 20) for d in DESIGNS]
        res = {"coverage": cov, "rows": rows, **run_stamp()}
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "training_data.json").write_text(json.dumps(res, indent=1))
    page = markdown(res)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "training_data.md").write_text(page)
    print(page)


if __name__ == "__main__":
    main()
