"""σ of `rsl adapt --estimator gn` against truths simulated on another discretisation: the measurement behind
the default model-error floors (`rsl adapt --model-error`: one for markers, one for images and silhouettes).

The gn estimator reports σ_E = E √(σ²_logE + e_i²) per frame and region (stages.windows.sigma_from_cov): σ_logE from
the window's Gauss–Newton normal matrix, e_i the model-error floor, the error of rsl's discretisation (mesh, time
step, reduced space) against the material, which more frames do not average out.  This script reads the rows of
bench/accuracy.py pages (accuracy.json: per frame E, E_true and σ_E of every gn row) and asks, per row and per
group of rows (space, loss):

- how often the truth lies inside E ± 2σ on the settled frames (≥ w + 5 after the start and after each step of
  E_true, bench/accuracy.settled_mask) with the floor the row ran with;
- the same with σ recomputed for other floors e′ (σ_logE kept: σ′ = E √(σ²_logE + (e′ e_i / e)²), a region's
  spread e_i / e kept);
- the smallest floor that puts the truth inside ±2σ on 90 % of the group's settled frames: per frame the floor that
  just covers it, e_t = √(max(0, (|E − E_true| / 2E)² − σ²_logE)), and its 90th percentile;
- the same for the markers rows (one floor for every space) and for the images' and silhouettes' rows pooled
  (every estimator and camera count): the two defaults (stages.steps.adapt.resolve_model_error).

Rows read: rows with σ (gn; Adam on images: its held fits) on quadratic tets (P1 in adapt is a discretisation rsl
does not default to: its E is biased by 15–25 %, docs/results/convergence.md), in the reduced space only at the
cubature tolerance given
(--cubature-tol, train-subspace's default).  The floor a row ran with is adapt.h5's young_model_error where the
page recorded it (bench/accuracy.py, rows since this script), else --model-error of the row's adapt options, else
--assumed-floor (0.02, adapt's default before this script's measurement); a row with several regions and no
recorded floors is left out (its floors were spread over the regions by information: not recoverable).

    .venv/bin/python bench/sigma_calibration.py docs/results/accuracy.json \\
        docs/results/accuracy_truth24_tol0005/accuracy.json ... --out docs/results
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]

from accuracy import code_state, settled_mask  # noqa: E402
from stages.steps.adapt import AdaptConfig, resolve_model_error  # noqa: E402


def default_floor(loss: str) -> float:
    """rsl adapt's --model-error default for a loss (markers, vision, silhouette): the floor the summary quotes a
    group's coverage at."""
    return resolve_model_error(AdaptConfig(capture="", workspace=""), loss)


FLOORS = tuple(sorted({0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.09, 0.10} | {default_floor(loss) for loss in
                                                                                ("markers", "vision", "silhouette")}))
TARGET = 0.90  # issue 13: the truth inside ±2σ on at least 90 % of the settled frames


def _option(row: dict, name: str) -> str | None:
    """The value of the rsl adapt option ``name`` in the row's adapt options (None: not passed)."""
    opts = [str(o) for o in row.get("adapt_options") or []]
    return opts[opts.index(name) + 1] if name in opts[:-1] else None


def _regions(row: dict) -> int:
    return np.asarray(row["young"], float).reshape(len(row["young"]), -1).shape[1]


def _ran_floor(row: dict, assumed: float) -> np.ndarray | None:
    """(T, R) floor e_i the row's σ carried, or None where it cannot be recovered."""
    shape = (len(row["young"]), _regions(row))
    if row.get("young_model_error") is not None:
        return np.asarray(row["young_model_error"], float).reshape(shape)
    if shape[1] > 1:
        return None
    return np.full(shape, float(_option(row, "--model-error") or assumed))


def estimator(row: dict) -> str:
    """The estimator a row ran: its --estimator, or what auto chose (stages.steps.adapt.resolve_estimator)."""
    from stages.steps.adapt import AdaptConfig, resolve_estimator

    config = AdaptConfig(capture="", workspace="", loss=row.get("loss", "vision"),
                         estimator=_option(row, "--estimator") or row.get("estimator", "auto"))
    return resolve_estimator(config, "moving" if row.get("start") == "moving" else "")


def row_frames(row: dict, assumed: float) -> dict | None:
    """The settled frames with a σ of one row (gn; Adam on images: its held fits): relative error, σ_logE and the
    floor's spread e_i / e (all flattened over frames and regions), or None where the row has no σ or its floors
    are unknown."""
    if row.get("young_sigma") is None:
        return None
    E = np.asarray(row["young"], float)
    E = E.reshape(len(E), -1)
    Et = np.asarray(row["young_true"], float).reshape(E.shape)
    S = np.asarray(row["young_sigma"], float).reshape(E.shape)
    floor = _ran_floor(row, assumed)
    if floor is None or not np.isfinite(S).any():
        return None
    floor = np.where(np.isfinite(floor), floor, np.nanmin(floor) if np.isfinite(floor).any() else assumed)
    ok = settled_mask(Et, window=row.get("window")) & np.all(np.isfinite(S), axis=1)  # (Adam: σ of its held fits only, NaN elsewhere)
    base = float(np.min(floor))  # the run's e: the best-informed region's floor (e_i = e · min(√(I_max/I_i), 6))
    s_log2 = np.maximum((S / E) ** 2 - floor ** 2, 0.0)
    return {"rel": (np.abs(E - Et) / E)[ok].ravel(), "s_log2": s_log2[ok].ravel(),
            "spread": (floor / base)[ok].ravel(), "floor": base,
            "error": float(np.median(np.abs(E - Et)[ok] / Et[ok])) if ok.any() else float("nan")}


def coverage(f: dict, e: float | None = None) -> np.ndarray:
    """Per settled frame: the truth inside ±2σ, σ with the floor e (None: the floor the row ran with)."""
    e = f["floor"] if e is None else e
    return f["rel"] <= 2.0 * np.sqrt(f["s_log2"] + (e * f["spread"]) ** 2)


def needed_floor(f: dict) -> np.ndarray:
    """Per settled frame the smallest floor whose ±2σ holds the truth (the spread e_i / e kept)."""
    return np.sqrt(np.maximum((f["rel"] / 2.0) ** 2 - f["s_log2"], 0.0)) / f["spread"]


def load_rows(pages: list[Path], cubature_tol: float, assumed: float) -> tuple[list[dict], list[str]]:
    rows, skipped = [], []
    for page in pages:
        data = json.loads(page.read_text())
        plan = data.get("plan") or {}
        name = str(page.relative_to(ROOT) if page.is_relative_to(ROOT) else page)
        for r in data.get("cases", []):
            label = f"{name}: {r.get('case')} {r.get('start')} {r.get('loss')} {r.get('space')}"
            if r.get("order") != 2:
                continue
            if r.get("space") == "reduced" and r.get("cubature_tol") != cubature_tol:
                continue
            f = row_frames(r, assumed)
            if f is None:
                if r.get("young_sigma") is not None and _regions(r) > 1:
                    skipped.append(f"{label} (several regions, floors not recorded)")
                continue
            rows.append({"page": name, "case": r.get("case"), "start": r.get("start"), "loss": r.get("loss"),
                         "estimator": estimator(r),
                         "space": r.get("space"), "cameras": r.get("cameras") or plan.get("cameras"),
                         "truth_substeps": plan.get("truth_substeps", 3), "adapt_options": r.get("adapt_options") or [],
                         "ended": r.get("ended"), "frames": f})
    return rows, skipped


def group_summary(rows: list[dict], key) -> dict:
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(key(r), []).append(r)
    out = {}
    for g, rs in sorted(groups.items()):
        frames = len(np.concatenate([r["frames"]["rel"] for r in rs]))
        cov = {str(e): float(np.mean(np.concatenate([coverage(r["frames"], e) for r in rs]))) for e in FLOORS}
        ran = float(np.mean(np.concatenate([coverage(r["frames"]) for r in rs])))
        need = float(np.quantile(np.concatenate([needed_floor(r["frames"]) for r in rs]), TARGET))
        out[g] = {"rows": len(rs), "frames": frames, "coverage_ran": ran, "coverage": cov, "floor_for_target": need,
                  "losses": sorted({r["loss"] for r in rs})}
    return out


def write(rows: list[dict], skipped: list[str], pages: list[Path], out: Path, cubature_tol: float) -> None:
    by_space = group_summary(rows, lambda r: r["space"])
    by_space_loss = group_summary(rows, lambda r: f"{r['space']}, {r['loss']}, {r['estimator']}")
    markers = group_summary([r for r in rows if r["loss"] == "markers"], lambda r: r["space"])
    # the cameras' losses pooled (images and silhouettes, every estimator and camera count): one default floor
    cameras = group_summary([r for r in rows if r["loss"] != "markers"], lambda r: "images and silhouettes")
    head = " | ".join(f"e′ = {e:g}" for e in FLOORS)
    lines = [
        "# σ of the gn estimator against truths on another discretisation",
        "",
        "The truth inside E ± 2σ on the settled frames (≥ w + 5 after the start and after each step of E_true) of "
        "bench/accuracy.py's rows that report σ (gn; Adam on images: its held calibration fits, frames without σ "
        "left out): with the model-error floor e each row ran with, and with σ recomputed for "
        "other floors e′ (σ_E = E √(σ²_logE + e′²), σ_logE of the row kept). \"floor for 90 %\": the 90th percentile "
        "over the group's settled frames of the floor that just covers each frame. Rows: quadratic tets in adapt; "
        f"reduced space at cubature tolerance {cubature_tol:g}. Produced by `bench/sigma_calibration.py` from the "
        "pages listed below (no run of its own).",
        "",
        "## Per row",
        "",
        "| page | case | start | loss | space | cameras | truth substeps | settled frames | median settled E error "
        f"| e ran | within ±2σ (e ran) | {head} |",
        "|" + " --- |" * 6 + " ---: |" * (5 + len(FLOORS)),
    ]
    for r in rows:
        f = r["frames"]
        cov = " | ".join(f"{100 * np.mean(coverage(f, e)):.0f} %" for e in FLOORS)
        opts = f" ({' '.join(r['adapt_options'])})" if r["adapt_options"] else ""
        lines.append(f"| {r['page']} | {r['case']} | {r['start']}{opts} | {r['loss']} | {r['space']} | {r['cameras']} "
                     f"| {r['truth_substeps']} | {len(f['rel'])} | {100 * f['error']:.1f} % | {f['floor']:g} "
                     f"| {100 * np.mean(coverage(f)):.0f} % | {cov} |")
    for title, summary in (("By space", by_space), ("By space, loss and estimator", by_space_loss),
                           ("Markers rows by space", markers), ("Images and silhouettes pooled", cameras)):
        lines += ["", f"## {title}", "",
                  f"| group | rows | settled frames | within ±2σ (e ran) | {head} | floor for 90 % |",
                  "| --- |" + " ---: |" * (4 + len(FLOORS))]
        for g, s in summary.items():
            cov = " | ".join(f"{100 * s['coverage'][str(e)]:.0f} %" for e in FLOORS)
            lines.append(f"| {g} | {s['rows']} | {s['frames']} | {100 * s['coverage_ran']:.0f} % | {cov} "
                         f"| {s['floor_for_target']:.3f} |")
    lines += ["", "## Summary (computed from the tables above)", ""]
    for g, s in markers.items():
        grid = [e for e in FLOORS if s["coverage"][str(e)] >= TARGET]
        lines.append(f"- Markers, {g} space: {100 * s['coverage_ran']:.0f} % of {s['frames']} settled frames within "
                     f"±2σ at the floors the rows ran with; the smallest floor of the grid reaching "
                     f"{100 * TARGET:.0f} %: " + (f"{min(grid):g}" if grid else "none") +
                     f"; the floor for {100 * TARGET:.0f} % exactly: {s['floor_for_target']:.3f}.")
    both = [e for e in FLOORS if all(s["coverage"][str(e)] >= TARGET for s in markers.values())]
    lines.append(f"- One floor for the markers rows of every space: the smallest of the grid with each space at "
                 f"{100 * TARGET:.0f} % or more: " + (f"{min(both):g} (" + ", ".join(
                     f"{g} {100 * s['coverage'][str(min(both))]:.0f} %" for g, s in markers.items()) + ")"
                     if both else "none") + ".")
    for g, s in cameras.items():
        grid = [e for e in FLOORS if s["coverage"][str(e)] >= TARGET]
        lines.append(f"- {g.capitalize()} pooled ({s['rows']} rows, {s['frames']} settled frames): "
                     f"{100 * s['coverage_ran']:.0f} % at the floors the rows ran with; the smallest floor of the grid "
                     f"reaching {100 * TARGET:.0f} %: " + (f"{min(grid):g}" if grid else "none")
                     + f"; the floor for {100 * TARGET:.0f} % exactly: {s['floor_for_target']:.3f}.")
    for g, s in by_space_loss.items():
        (loss,) = s["losses"]  # (grouped by loss: one per group)
        e = default_floor(loss)
        lines.append(f"- {g}: {100 * s['coverage_ran']:.0f} % at the floors run, "
                     f"{100 * s['coverage'][str(e)]:.0f} % at e′ = {e:g} (rsl adapt's default for {loss}), the floor "
                     f"for {100 * TARGET:.0f} %: {s['floor_for_target']:.3f} ({s['rows']} rows, {s['frames']} "
                     "frames).")
    if skipped:
        lines += ["", "Left out (σ recorded, floors not recoverable): " + "; ".join(skipped) + "."]
    lines += ["", "Pages read: " + ", ".join(f"`{p.relative_to(ROOT) if p.is_relative_to(ROOT) else p}`"
                                           for p in pages) + ".",
              "", f"Machine: {platform.machine()} {platform.python_version()}; code {code_state()}; date "
              f"{datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}.",
              "", "![coverage over the floor](sigma_calibration.png)", ""]
    out.mkdir(parents=True, exist_ok=True)
    (out / "sigma_calibration.md").write_text("\n".join(lines))
    js = {"target": TARGET, "floors": list(FLOORS), "cubature_tol": cubature_tol,
          "pages": [str(p) for p in pages], "skipped": skipped,
          "rows": [{**{k: v for k, v in r.items() if k != "frames"}, "settled_frames": len(r["frames"]["rel"]),
                    "median_error": r["frames"]["error"], "floor_ran": r["frames"]["floor"],
                    "coverage_ran": float(np.mean(coverage(r["frames"]))),
                    "coverage": {str(e): float(np.mean(coverage(r["frames"], e))) for e in FLOORS}} for r in rows],
          "by_space": by_space, "by_space_loss": by_space_loss, "markers_by_space": markers,
          "images_and_silhouettes": cameras,
          "defaults": {loss: default_floor(loss) for loss in ("markers", "vision", "silhouette")}}
    (out / "sigma_calibration.json").write_text(json.dumps(js, indent=1))
    _plot(out / "sigma_calibration.png", by_space_loss)
    print("\n".join(lines))


def _plot(path: Path, summary: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for g, s in summary.items():
        ax.plot(FLOORS, [100 * s["coverage"][str(e)] for e in FLOORS], "o-", label=f"{g} ({s['frames']} frames)")
    ax.axhline(100 * TARGET, color="k", lw=0.8, ls="--")
    ax.set_xlabel("model-error floor e′ (relative σ of E)")
    ax.set_ylabel("truth inside E ± 2σ (% of settled frames)")
    ax.set_ylim(0, 102)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pages", nargs="+", type=Path, help="accuracy.json files of bench/accuracy.py")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--cubature-tol", type=float, default=0.0005,
                    help="reduced rows: only those whose subspace's cubature was fitted at this tolerance")
    ap.add_argument("--assumed-floor", type=float, default=0.02,
                    help="the floor of a row that recorded none and passed no --model-error")
    args = ap.parse_args()
    pages = [p.resolve() for p in args.pages]
    rows, skipped = load_rows(pages, args.cubature_tol, args.assumed_floor)
    if not rows:
        sys.exit("no rows with σ on quadratic tets in the pages given")
    write(rows, skipped, pages, args.out, args.cubature_tol)


if __name__ == "__main__":
    main()
