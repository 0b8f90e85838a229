"""Markers hidden when the capture starts (a gripper or a clamp over one end): E from rsl adapt when it binds each such
marker to its track once a window sees it, against deleting those markers (what a capture needed before: every
marker had to be seen at frame 0) and against every marker seen, in the same run.

Captures as bench/moving_start.py makes them (the same work folder: `RSL_BENCH_REUSE=1` reuses them): sample_data/bar
pulled by a cable, constant E_true, truth on P2 tets with 3 substeps per frame and hard handles, the equilibrium start
and a start 8 frames into the pull (`--start moving --lead-frames 8`).  The hidden markers are the quarter with the
largest frame-0 x (the bar's +x end), not seen over frames 0..H−1 for each H.  rsl adapt: its P2 mesh, reduced space
(r = 12), markers, gn, window 3, E from 0.5 E_true, its defaults otherwise.  Per row: the median relative error of E
over the settled frames (≥ w + 5; with the markers hidden past that, from frame H + w + 5), the median settled
E / E_true, the frames whose windows bound hidden markers, and the RMS distance of the hidden markers, as bound, to
markers.csv over the frames ≥ H that see them (adapt.h5's positions; "all seen": the same markers bound at frame 0).

    nice .venv/bin/python bench/late_markers.py [--hidden 4,12] [--leads 0,8] [--out docs/results]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402
from moving_start import E_TRUE, POISSON, TRUTH_SUBSTEPS, WINDOW  # noqa: E402

FRAMES = 24
HIDDEN_FRACTION = 0.25


def capture_pair(work: Path, lead: int, max_tets: int) -> tuple[Path, Path]:
    """bench/moving_start.py's capture and workspace of this lead-in (made when absent or not reused)."""
    start = "moving" if lead else "equilibrium"
    extra = ["--lead-frames", lead] if lead else []
    cap = pl.foreign_capture(work / f"cap_k{lead}", pl.bar_cable(young=E_TRUE), start=start, frames=FRAMES,
                             cameras=1, resolution=32, substeps=TRUTH_SUBSTEPS, poisson=POISSON, extra=extra)
    ws = pl.mesh(cap, work / f"ws_k{lead}", order=2, max_tets=max_tets, calibrate=False)
    pl.subspace(cap, ws, frames=FRAMES, dim=12)
    return cap, ws


def variant(cap: Path, out: Path, hidden: np.ndarray, until: int, drop: bool) -> Path:
    """A copy of the capture whose markers ``hidden`` are not seen before frame ``until`` (drop: never)."""
    from stages.capture import read_markers, write_markers

    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(cap, out)
    P = read_markers(cap / "markers.csv")
    if drop:
        P = P[:, ~hidden]
    else:
        P[:until, hidden] = np.nan
    write_markers(out / "markers.csv", P)
    return out


def run_capture(work: Path, lead: int, hiddens: list[int], max_tets: int) -> list[dict]:
    from stages.artefacts import AdaptArtefact, MeshArtefact
    from stages.capture import load_capture, read_markers, read_truth
    from stages.observations import MarkerObservation

    cap, ws = capture_pair(work, lead, max_tets)
    P = read_markers(cap / "markers.csv")
    x = P[0, :, 0]
    hidden = x >= np.quantile(x, 1.0 - HIDDEN_FRACTION)
    truth = read_truth(load_capture(cap))
    mesh = MeshArtefact.load(ws / "mesh.h5")
    plans = [("all seen", 0, False)] + [(how, h, how == "deleted") for h in hiddens
                                         for how in ("bound late", "deleted")]
    rows = []
    for how, h, drop in plans:
        c = cap if how == "all seen" else variant(cap, work / f"cap_k{lead}_late{h}_{how.split()[0]}", hidden, h,
                                                  drop)
        base = {"lead_frames": lead, "start": "moving" if lead else "equilibrium", "markers": how,
                "hidden_frames": h, "hidden_markers": int(hidden.sum()), "all_markers": int(len(hidden))}
        try:
            pl.adapt(c, ws, "--space", "reduced", "--loss", "markers", "--estimator", "gn", "--window", WINDOW,
                     "--young-init", f"{0.5 * E_TRUE:g}")
        except RuntimeError as e:
            rows.append({**base, "error": str(e)[-500:]})
            print(_row(rows[-1]), flush=True)
            continue
        a = AdaptArtefact.load(ws / "adapt.h5")
        y = np.asarray(a.young)[:, 0]
        yt = truth.young[np.asarray(a.frames)][:, 0]
        ok = np.arange(len(y)) >= max(h, 0) + WINDOW + 5
        late_rms = None
        if not drop:  # the hidden markers as adapt bound them, through adapt.h5's positions, over frames ≥ H
            obs = MarkerObservation(load_capture(c), a.positions[0], mesh.surface_faces, mesh.n_vertices)
            if lead:
                obs.fit_to_tracks(range(WINDOW), a.positions[:WINDOW])
            for t, _ in a.extra.get("late_markers_bound", []):
                fr = list(range(max(0, t - WINDOW + 1), t + 1))
                obs.bind_late(fr, a.positions[fr])
            m = obs.binding.positions(a.positions)[h:, hidden]
            d = np.sum((m - P[np.asarray(a.frames)][h:, hidden]) ** 2, axis=-1)
            late_rms = float(1e3 * np.sqrt(np.nanmean(d)))
        rows.append({**base, "settled_frames": int(ok.sum()),
                     "median_error": float(np.median(np.abs(y[ok] - yt[ok]) / yt[ok])),
                     "median_ratio": float(np.median(y[ok] / yt[ok])),
                     "late_bound": [list(b) for b in a.extra.get("late_markers_bound", [])],
                     "hidden_rms_mm": late_rms, "time_per_frame_s": float(np.median(a.time_total_s)),
                     "young": y.tolist(), "young_true": yt.tolist()})
        print(_row(rows[-1]), flush=True)
    return rows


HEADER = ("| capture (lead-in frames) | hidden markers | frames hidden | markers | median settled E error (%) | "
          "median settled E / E_true | settled frames | bound at frame (count) | hidden markers' RMS (mm) | s / frame |\n"
          "|---|---:|---:|---|---:|---:|---:|---|---:|---:|")


def _row(r: dict) -> str:
    head = (f"| {r['start']} ({r['lead_frames']}) | {r['hidden_markers']} of {r['all_markers']} | "
            f"{r['hidden_frames'] or '—'} | {r['markers']}")
    if "error" in r:
        return f"{head} | refused: {r['error'].rsplit('error: ', 1)[-1].strip()} | — | — | — | — | — |"
    lb = ", ".join(f"{t} ({n})" for t, n in r["late_bound"]) or "—"
    rms = "—" if r["hidden_rms_mm"] is None else f"{r['hidden_rms_mm']:.2f}"
    return (f"{head} | {100 * r['median_error']:.1f} | {r['median_ratio']:.3f} | {r['settled_frames']} | {lb} | "
            f"{rms} | {r['time_per_frame_s']:.2f} |")


def same_frames_error(r: dict, hidden: int) -> float:
    """A row's median relative E error over the frames settled after ``hidden`` hidden frames (≥ H + w + 5)."""
    y, yt = np.asarray(r["young"]), np.asarray(r["young_true"])
    ok = np.arange(len(y)) >= hidden + WINDOW + 5
    return float(np.median(np.abs(y[ok] - yt[ok]) / yt[ok]))


def summary(rows: list[dict]) -> list[str]:
    """Per capture and hidden span: bound late against deleted, with every marker seen beside."""
    out = []
    for lead in sorted({r["lead_frames"] for r in rows}):
        by = {(r["markers"], r["hidden_frames"]): r for r in rows if r["lead_frames"] == lead and "error" not in r}
        ref = by.get(("all seen", 0))
        for h in sorted({r["hidden_frames"] for r in rows if r["hidden_frames"]}):
            late, gone = by.get(("bound late", h)), by.get(("deleted", h))
            if late and gone:
                out.append(f"- {late['start']} start ({lead}), {late['hidden_markers']} markers hidden over frames "
                           f"0–{h - 1}: bound late {100 * late['median_error']:.1f} %, deleted "
                           f"{100 * gone['median_error']:.1f} %"
                           + (f", every marker seen {100 * same_frames_error(ref, h):.1f} % over the same frames"
                              if ref else "") + ".")
    return out


def write(rows: list[dict], out: Path, plan: dict, run: dict | None = None) -> None:
    """docs/results/late_markers.{md,json}; ``run``: the ended / load_average / machine of a run merged (default: now,
    this machine)."""
    out.mkdir(parents=True, exist_ok=True)
    data = {"plan": plan, "cases": rows, "ended": datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec="seconds"), "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan"),
        "machine": f"{platform.machine()} {os.cpu_count()} CPUs, Python {platform.python_version()}"}
    data.update({k: run[k] for k in ("ended", "load_average", "machine") if run and k in run})
    load = data["load_average"]
    (out / "late_markers.json").write_text(json.dumps(data, indent=1))
    md = ["# Markers hidden when the capture starts: bound to their tracks once seen", "",
          f"Bar pulled by a cable, E_true = {E_TRUE:g} Pa, ν = {POISSON}; truth P2, {TRUTH_SUBSTEPS} substeps per "
          f"frame, hard handles, {FRAMES} frames, 1 camera (the captures of bench/moving_start.py). Hidden: the "
          f"{HIDDEN_FRACTION:.0%} of the markers with the largest frame-0 x (the bar's +x end), not seen over frames "
          f"0..H−1. Markers: 'bound late' — the capture as such, rsl adapt binds each hidden marker to its track "
          f"when a window first sees it; 'deleted' — those markers removed from markers.csv (what a capture needed "
          f"before: every marker seen at frame 0); 'all seen' — the capture unchanged. rsl adapt: P2 mesh "
          f"(`--max-tets {plan['max_tets']}`), reduced space r = 12, markers, gn, window {WINDOW}, E from 0.5 "
          f"E_true. Settled: frames ≥ H + w + 5. Hidden markers' RMS: their distance to markers.csv over the frames ≥ H, "
          f"bound again as adapt binds them (its frames, adapt.h5's positions).", "", HEADER]
    md += [_row(r) for r in rows]
    md += ["", *summary(rows), "",
           f"Ended {data['ended']} (load average {load:.1f}), {data['machine']}. Produced by "
           f"`bench/late_markers.py`."]
    (out / "late_markers.md").write_text("\n".join(md) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hidden", default="4,12", help="frames the hidden markers are not seen (0..H−1), per run")
    # (the page's rows in the order of a run: per capture, all seen, then per H bound late and deleted)
    ap.add_argument("--leads", default="0,8", help="lead-in frames of each capture (0: the equilibrium start)")
    ap.add_argument("--max-tets", type=int, default=1500)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_moving_start"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="write the page from the rows of these late_markers.json files (a row in several: the last)")
    a = ap.parse_args()
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        latest = {(r["lead_frames"], r["markers"], r["hidden_frames"]): r for run in runs for r in run["cases"]}
        rows = sorted(latest.values(), key=lambda r: (-r["lead_frames"], r["hidden_frames"], r["markers"] != "all seen",
                                                      r["markers"]))
        write(rows, a.out, runs[-1]["plan"], runs[-1])
        print("\n".join(summary(rows)))
        return
    hiddens = [int(k) for k in a.hidden.split(",") if k.strip()]
    leads = [int(k) for k in a.leads.split(",") if k.strip()]
    plan = {"frames": FRAMES, "hidden": hiddens, "leads": leads, "max_tets": a.max_tets}
    print(HEADER, flush=True)
    rows = []
    for lead in leads:
        rows += run_capture(a.work, lead, hiddens, a.max_tets)
    write(rows, a.out, plan)
    print("\n".join(summary(rows)))


if __name__ == "__main__":
    main()
