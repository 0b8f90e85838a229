"""`rsl adapt --process-noise` (or another adapt option, --option) on captures filmed mid-motion: the measurement
behind its default for images.

For each value of --process-noise (σ per frame of the gn filter's random walk on log E), the same rows of
bench/accuracy.py are re-run on ONE set of captures, meshes and subspaces (its --work, RSL_BENCH_REUSE=1 after
the first value): only `rsl adapt`, `rsl export --forces` and `rsl evaluate` differ between the columns.  The
truth is bench/accuracy.py's (P2, --truth-substeps, hard handles; the bar's E steps E0 → 2E0 → 4E0).

Per row and value: the median relative error of E over the settled frames (≥ w + 5 after the start and after each
step of E_true), the same per segment of constant E_true, and the median handle-force error of `rsl evaluate`.
The baseline column is the first value (the default for markers and for equilibrium starts).

    .venv/bin/python bench/process_noise.py --values 0.005,0.03,0.05 --cameras 1 --truth-substeps 24 \\
        --rows 'bar/moving/2/vision/reduced;bar/moving/2/silhouette/reduced' --work /tmp/pn1 \\
        --out docs/results/process_noise_one_camera
    .venv/bin/python bench/process_noise.py --merge A/process_noise.json B/process_noise.json --out DIR
    .venv/bin/python bench/process_noise.py --option=--unseen-gaussians --values keep,ignore --cameras 1 ...

--option: the `rsl adapt` option whose --values are compared (default --process-noise); its page and JSON are named
after it (unseen_gaussians.md for --unseen-gaussians).  Each value's bench/accuracy.py page is kept under
WORK/q_<value>/.  --merge writes one page from several runs (their rows side by side; each run's captures and
meshes are its own, named in the table).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]

from accuracy import code_state, settled_mask  # noqa: E402


def segment_errors(young: np.ndarray, young_true: np.ndarray) -> list[float]:
    """Median |E − E_true| / E_true over the settled frames of each segment of constant E_true (first region)."""
    y, yt = np.asarray(young, float)[:, 0], np.asarray(young_true, float)
    ok = settled_mask(yt)
    yt = yt[:, 0]
    bounds = [0] + [t for t in range(1, len(yt)) if yt[t] != yt[t - 1]] + [len(yt)]
    out = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        m = ok[a:b]
        out.append(float(np.median(np.abs(y[a:b][m] / yt[a:b][m] - 1))) if m.any() else float("nan"))
    return out


def value(q) -> float | str:
    """An option's value as the page keys it: a number where it is one (--process-noise), else the text."""
    try:
        return float(q)
    except ValueError:
        return str(q)


def _v(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)


def stem(option: str) -> str:
    """The page's file name of an option: process_noise for --process-noise."""
    return option.strip("-").replace("-", "_")


SCENES = {"bar": "the bar's E steps E0 → 2E0 → 4E0 at T/3 and 2T/3",
          "dino": "the dinosaur pushed by a sphere at constant E",
          "beam": "the two-region beam (its far half 3 × stiffer) at constant E"}


def run_value(q: str, a: argparse.Namespace, first: bool) -> dict:
    """bench/accuracy.py for the rows with `rsl adapt OPTION q`; its accuracy.json."""
    out = a.work / f"q_{q}"
    cmd = [sys.executable, str(ROOT / "bench" / "accuracy.py"), "--rows", a.rows, "--work", str(a.work),
           "--out", str(out), "--truth-substeps", str(a.truth_substeps), "--sequences", str(a.sequences),
           f"--adapt-option={a.option}", f"--adapt-option={q}"]
    if a.cameras:
        cmd += ["--cameras", str(a.cameras)]
    env = {**os.environ, **({} if first and not a.reuse else {"RSL_BENCH_REUSE": "1"})}
    print(f"{a.option} {q}: {' '.join(cmd[1:])}", flush=True)
    subprocess.run(cmd, check=True, env=env, cwd=ROOT)
    return json.loads((out / "accuracy.json").read_text())


def summarise(q: str, run: dict) -> list[dict]:
    rows = []
    for r in run["cases"]:
        base = {"value": value(q), "case": r["case"], "start": r["start"], "loss": r["loss"], "space": r["space"],
                "cameras": r.get("cameras"), "dofs": r.get("dofs"), "ended": r.get("ended"), "code": r.get("code")}
        if "error" in r:
            rows.append({**base, "error": r["error"]})
            continue
        rows.append({**base, "median_error": r["median_error_worst"],
                     "segment_errors": segment_errors(r["young"], r["young_true"]),
                     "force_error": r.get("force_error"), "time_per_frame_s": r.get("time_per_frame_s"),
                     "young": r["young"], "young_true": r["young_true"]})
    return rows


def _pct(x) -> str:
    return "—" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def write(rows: list[dict], values: list, out: Path, meta: dict) -> None:
    """The page OUT/<option>.md (--process-noise: process_noise.md), its JSON and its E(t) plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {**meta, "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, "
                               f"{platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "rows": rows}
    option = meta.get("option", "--process-noise")
    name = stem(option)
    (out / f"{name}.json").write_text(json.dumps(data, indent=1))
    # a row per capture, loss, mesh and code (runs of one workspace by different code: one row each)
    keys = list(dict.fromkeys((r["case"], r["start"], r["loss"], r["space"], r["cameras"], r["dofs"], r.get("code"))
                              for r in rows))
    by = {(r["case"], r["start"], r["loss"], r["space"], r["cameras"], r["dofs"], r.get("code"), r["value"]): r
          for r in rows}
    head = ("| capture | loss | cameras | DOFs | code | " + " | ".join(_v(v) for v in values)
            + " | best | best ÷ " + _v(values[0]) + " |\n|---|---|---|---:|---|" + "---:|" * len(values)
            + "---|---:|")
    lines, seg_lines, force_lines = [head], [], []
    for k in keys:
        got = [by.get((*k, v)) for v in values]
        med = [g.get("median_error", np.nan) if g else np.nan for g in got]
        finite = [i for i, m in enumerate(med) if np.isfinite(m)]
        best = min(finite, key=lambda i: med[i]) if finite else None
        label = f"| {k[0]} {k[1]} | {k[2]} | {k[4]} | {k[5]} | {k[6]} | "
        lines.append(label + " | ".join(("**" + _pct(m) + "**") if i == best else _pct(m) for i, m in enumerate(med))
                     + f" | {_v(values[best])} | " + (f"{med[best] / med[0]:.2f}" if best is not None and
                                                    np.isfinite(med[0]) and med[0] > 0 else "—") + " |"
                     if best is not None else label + " | ".join("failed" for _ in med) + " | — | — |")
        seg_lines.append(label + " | ".join(" / ".join(_pct(s) for s in g["segment_errors"]) if g and "segment_errors"
                                            in g else "—" for g in got) + " |")
        force_lines.append(label + " | ".join(_pct(g.get("force_error")) if g else "—" for g in got) + " |")
    sub_head = ("| capture | loss | cameras | DOFs | code | " + " | ".join(_v(v) for v in values)
                + " |\n|---|---|---|---:|---|" + "---:|" * len(values))
    moving = all(r["start"] == "moving" for r in rows)
    scenes = "; ".join(SCENES[c] for c in dict.fromkeys(r["case"] for r in rows) if c in SCENES)
    md = ((f"# `rsl adapt {option}` on captures filmed mid-motion\n\n"
           "gn on images (Gaussians) or silhouettes, start = moving.") if moving else
          (f"# `rsl adapt {option}` on the accuracy bench's captures\n\n"
           "Images (Gaussians) or silhouettes; each row's start state in its capture column (moving: filmed "
           "mid-motion), the estimator `auto`'s choice.")) + (
          f" Truth: P2, {meta['truth_substeps']} substeps per "
          f"frame, hard handles; {scenes}; rsl: P2 fTetWild mesh, reduced "
          f"r = 30, {meta['sequences']} training sequences, window 3, E initialised at 0.5 E0. Each row's columns "
          f"share its captures, mesh and subspace; only adapt's {option} differs.\n\n"
          f"Median |E − E_true| / E_true over the settled frames (%), by {option} (bold: the lowest of the "
          f"row):\n\n" + "\n".join(lines)
          + "\n\nPer segment of constant E_true (E0 / 2E0 / 4E0, settled frames, %):\n\n" + sub_head + "\n"
          + "\n".join(seg_lines)
          + "\n\nMedian handle-force error of `rsl export --forces` against truth/forces.csv (%, `rsl evaluate`):\n\n"
          + sub_head + "\n" + "\n".join(force_lines)
          + f"\n\nMachine {data['machine']}; runs: "
          + "; ".join(f"{r['date']} (code {r['code']})" for r in meta["runs"])
          + ". Produced by `bench/process_noise.py`; each value's full accuracy page under its --work.\n\n"
          f"![E over time by {option}]({name}.png)\n")
    (out / f"{name}.md").write_text(md)
    fig, axes = plt.subplots(1, max(1, len(keys)), figsize=(4.4 * max(1, len(keys)), 3.8), squeeze=False)
    for ax, k in zip(axes[0], keys):
        got = [(v, by.get((*k, v))) for v in values]
        truth = next((g for _, g in got if g and "young_true" in g), None)
        if truth is not None:
            ax.plot(np.asarray(truth["young_true"])[:, 0], "k-", lw=2, label="truth")
        for c, (v, g) in enumerate(got):
            if g and "young" in g:
                ax.plot(np.asarray(g["young"])[:, 0], color=f"C{c}", lw=1, label=f"{option} {_v(v)}")
        ax.set_title(f"{k[0]} {k[1]}, {k[2]}, {k[4]} camera(s), {str(k[6])[:7]}", fontsize=8)
        ax.set_xlabel("frame")
        ax.set_ylabel("E (Pa)")
        ax.set_yscale("log")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=110)
    plt.close(fig)
    print("\n".join(lines), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--option", default="--process-noise", help="the rsl adapt option compared")
    ap.add_argument("--values", default="0.005,0.03,0.05", help="its values, comma-separated; the first is the "
                                                                "baseline")
    ap.add_argument("--rows", default="bar/moving/2/vision/reduced;bar/moving/2/silhouette/reduced",
                    help="bench/accuracy.py --rows")
    ap.add_argument("--cameras", type=int, default=0, help="bench/accuracy.py --cameras (0: the table's)")
    ap.add_argument("--truth-substeps", type=int, default=24)
    ap.add_argument("--sequences", type=int, default=12)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_process_noise"))
    ap.add_argument("--reuse", action="store_true", help="reuse --work's captures for the first value as well")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results" / "process_noise")
    ap.add_argument("--merge", nargs="+", type=Path, default=None)
    a = ap.parse_args()
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        values = list(dict.fromkeys(value(v) for run in runs for v in run["values"]))
        if all(isinstance(v, float) for v in values):
            values = sorted(values)
        write([r for run in runs for r in run["rows"]], values, a.out,
              {**{k: runs[0][k] for k in ("truth_substeps", "sequences")}, "values": values,
               "option": runs[0].get("option", "--process-noise"),
               "runs": [x for run in runs for x in run["runs"]]})
        return
    values = [v.strip() for v in a.values.split(",") if v.strip()]
    rows, runs = [], []
    meta = {"truth_substeps": a.truth_substeps, "sequences": a.sequences, "values": [value(v) for v in values],
            "option": a.option, "rows_plan": a.rows, "cameras": a.cameras, "runs": runs}
    for i, q in enumerate(values):
        run = run_value(q, a, first=i == 0)
        runs.append({"value": value(q), "date": run["date"], "code": run.get("code", code_state())})
        rows += summarise(q, run)
        write(rows, [value(v) for v in values], a.out, meta)  # after every value: a stopped run keeps its rows


if __name__ == "__main__":
    main()
