"""How many frames does the images' first calibration need?  Where the image loss of frames 0..b−1 is lowest, for
each b, on a capture rsl did not make.

`rsl adapt --loss vision` fits θ to its first --anchor-calibration K informed frames (rule 0 of
stages/vision_anchor.py) and holds the Gaussians' anchor at that fit for the rest of the sequence.  The fit can
be no better than the minimum of the loss it minimises: L_b(E) = Σ_{t<b} Σ_c |R(G(x_t(E)), c) − Ĩ_t^c|₁.  This
bench simulates the capture's first frames over a grid of fixed E (full space, from the capture's declared
start, ν held at the truth's; stages/sweep.py, which re-binds the Gaussians to frame 0 simulated with each E as
adapt's calibration does) and reports, for every b, the vertex of the parabola in log E through the smallest
cumulative loss and its neighbours.  One simulation per E and time step serves every b (per-frame losses).

    .venv/bin/python bench/calibration_frames.py --case WORK/bar_equilibrium WORK/ws_bar_equilibrium_p2 \\
        [--case CAP WS ...] [--frames 12] [--substeps 6 3] [--out docs/results]
    .venv/bin/python bench/calibration_frames.py --merge RUN1/calibration_frames.json RUN2/... [--out docs/results]

    .venv/bin/python bench/calibration_frames.py --build WORK [--truth-substeps 3 24 48] [--starts equilibrium rest] \\
        [--substeps 6 3 12]

    .venv/bin/python bench/calibration_frames.py --segments --case CAP WS [...] [--window 8] [--substeps 6]
    .venv/bin/python bench/calibration_frames.py --segments --merge RUN1/calibration_segments.json ...

--segments: the same check for a recalibration after each step of E_true (frame c*: E_old → E_new): frames
0..c−1 simulated once with the truth's E(t) — the old material on c*..c−1 when the split c comes after the
change —, frames c..c+W−1 with each grid value × E_new (stages.sweep.sweep, past_young), for the splits
c = c* − 1, c*, c* + 1 (a change located one frame early, right, late).  Its curvature beside the first
calibration's tells how sharply the frames after the step locate E.  Writes calibration_segments.{md,json}.

CAP/WS: a capture of bench/accuracy.py (its --work folder: the capture and its workspace after
calibrate → tetrahedralize → segment → fit-gaussians); --build makes them (build()).  Writes
calibration_frames.{md,json,png} in --out.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

SCALES = (0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15)  # the grid, E / E_true
SEGMENT_SCALES = (0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.35)  # --segments: the grid, E / E_new (wider: flatter losses)


def build(work: Path, truth_substeps: list[int], starts: list[str]) -> list[list[str]]:
    """[capture, workspace] per start and N: bench/accuracy.py's bar (cable, E0 → 2E0 → 4E0 at frames 12 and 24 of
    36, P2 truth on the shipped mesh, hard handles, 3 cameras at 96²) with its truth simulated with N substeps per
    frame.  One fTetWild P2 adapt mesh per start (made from the first N's capture) serves every N, so that the
    rows of a start differ by the truth alone; cameras, masks and Gaussians are each capture's own (synth frames
    its cameras on the motion, which differs with N)."""
    import shutil

    import _pipeline as pl
    import accuracy

    cases = []
    for start in starts:
        caps = {n: pl.foreign_capture(work / f"bar_{start}_n{n}", accuracy.scene_args("bar", 36), start=start,
                                      frames=36, substeps=n, poisson=accuracy.POISSON) for n in truth_substeps}
        base = pl.mesh(caps[truth_substeps[0]], work / f"ws_{start}_mesh", order=2, max_tets=accuracy.MAX_TETS)
        for n, cap in caps.items():
            ws = work / f"ws_{start}_n{n}"
            if not pl.skip(ws / "gaussians.h5"):
                ws.mkdir(parents=True, exist_ok=True)
                pl.rsl("calibrate", cap, "-w", ws, "--from-json", cap / "cameras.json")
                shutil.copy(base / "mesh.h5", ws / "mesh.h5")
                pl.gaussians(cap, ws, frame=0, reuse=False)
            cases.append([str(cap), str(ws)])
    return cases


def truth_substeps(capture_dir: Path) -> int | None:
    """The truth's implicit-Euler steps per frame of a `rsl synth` capture (capture.toml [synth] substeps), None
    for a capture rsl synth did not make."""
    with open(Path(capture_dir) / "capture.toml", "rb") as f:
        synth = tomllib.load(f).get("synth", {})
    return int(synth["substeps"]) if "substeps" in synth else None


def minima(grid: np.ndarray, frame_loss: np.ndarray, first: int) -> list[dict]:
    """Per b = first..T (frames 0..b−1): the parabolic minimum of Σ_{t<b} loss_t over the grid (Pa), whether it is
    interior, and the loss's curvature there relative to its minimum (d² ln L / d(ln E)²: how sharply b frames
    locate E)."""
    from stages.sweep import parabolic_minimum

    lg = np.log(grid)
    out = []
    for b in range(first, frame_loss.shape[1] + 1):
        total = frame_loss[:, :b].sum(axis=1)
        lmin, i, interior = parabolic_minimum(lg, total)
        j = min(max(i, 1), len(lg) - 2)
        y = np.log(total[j - 1:j + 2])
        h1, h2 = lg[j] - lg[j - 1], lg[j + 1] - lg[j]
        curv = 2 * ((y[2] - y[1]) / h2 - (y[1] - y[0]) / h1) / (h1 + h2)
        out.append({"frames": b, "young_min": float(math.exp(lmin)), "interior": bool(interior),
                    "curvature": float(curv)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--case", nargs=2, action="append", metavar=("CAPTURE", "WORKSPACE"))
    ap.add_argument("--merge", nargs="+", type=Path, help="write one page from the rows of these runs' JSON files")
    ap.add_argument("--build", type=Path, metavar="WORK",
                    help="make the cases in WORK: bench/accuracy.py's bar with E steps, its truth simulated with each "
                         "--truth-substeps N, for each --starts (see build)")
    ap.add_argument("--truth-substeps", type=int, nargs="+", default=[3, 24, 48])
    ap.add_argument("--starts", nargs="+", default=["equilibrium", "rest"])
    ap.add_argument("--frames", type=int, default=12, help="frames 0..N−1 simulated (default 12)")
    ap.add_argument("--first", type=int, default=6, help="the smallest b reported (default 6)")
    ap.add_argument("--substeps", type=int, nargs="+", default=[6, 3])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--segments", action="store_true",
                    help="the frames after each step of E_true instead of the first frames (see above)")
    ap.add_argument("--window", type=int, default=8, help="--segments: frames in the loss after the split (8)")
    ap.add_argument("--offsets", type=int, nargs="+", default=[-1, 0, 1],
                    help="--segments: the splits c = c* + offset (default -1 0 1)")
    ap.add_argument("--changes", type=int, nargs="+", default=None,
                    help="--segments: only the steps of E_true at these frames (default every step)")
    args = ap.parse_args()
    if args.merge:
        rows = [r for f in args.merge for r in json.loads(f.read_text())["rows"]]
        (write_segments if args.segments else write)(rows, args.out)
        return
    if args.build:
        args.case = (args.case or []) + build(args.build, args.truth_substeps, args.starts)
    if not args.case:
        ap.error("give --case CAPTURE WORKSPACE, --build WORK or --merge")

    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture, read_truth
    from stages.sweep import sweep

    if args.segments:
        write_segments(segments(args.case, args.substeps, args.window, args.offsets, args.changes), args.out)
        return
    rows = []
    for cap_dir, ws in args.case:
        cap = load_capture(Path(cap_dir))
        truth = read_truth(cap)
        young = np.asarray(truth.young, float)[:args.frames, 0]
        if not np.allclose(young, young[0]):
            raise SystemExit(f"{cap_dir}: E_true changes within frames 0..{args.frames - 1}; pass fewer --frames")
        e_true = float(young[0])
        poisson = float(np.asarray(truth.poisson, float)[0, 0])
        mesh = MeshArtefact.load(Path(ws) / "mesh.h5")
        grid = [e_true * s for s in SCALES]
        for S in args.substeps:
            t0 = time.time()
            res = sweep(cap, mesh, grid, "vision", frames=(0, args.frames), workspace=Path(ws), poisson=poisson,
                        substeps=S, reporter=lambda m: print(f"  {Path(cap_dir).name} S={S}: {m}", flush=True))
            per = minima(res.young, res.frame_loss, args.first)
            rows.append({"capture": Path(cap_dir).name, "start": cap.start, "e_true": e_true,
                         "truth_substeps": truth_substeps(Path(cap_dir)), "substeps": S,
                         "order": res.info["order"], "n_vertices": res.info["n_vertices"],
                         "grid": res.young.tolist(), "frame_loss": res.frame_loss.tolist(), "minima": per,
                         "seconds": round(time.time() - t0, 1)})
            print(f"{Path(cap_dir).name} S={S}: " + ", ".join(
                f"b={m['frames']}: {m['young_min'] / e_true:.3f}" for m in per), flush=True)
    write(rows, args.out)


def segments(cases: list, substeps: list[int], window: int, offsets=(-1, 0, 1), changes=None) -> list[dict]:
    """Per case, step of E_true (at the frames ``changes``, default every step), split c = c* + offset and S: the
    minimum and curvature of the image loss of frames c..c+window−1 over E_new × SEGMENT_SCALES, the frames before c
    simulated with the truth's E(t) (the old material up to c − 1)."""
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture, read_truth
    from stages.sweep import sweep

    rows = []
    for cap_dir, ws in cases:
        cap = load_capture(Path(cap_dir))
        truth = read_truth(cap)
        young = np.asarray(truth.young, float)
        poisson = float(np.asarray(truth.poisson, float)[0, 0])
        mesh = MeshArtefact.load(Path(ws) / "mesh.h5")
        steps = [c for c in range(1, len(young)) if not np.allclose(young[c], young[c - 1])
                 and (changes is None or c in changes)]
        for cs in steps:
            e_old, e_new = float(young[cs - 1, 0]), float(young[cs, 0])
            for c in (cs + o for o in offsets):
                if c + window > len(young):
                    continue
                past = np.array([young[t] if t < cs else young[cs - 1] for t in range(c)])
                for S in substeps:
                    t0 = time.time()
                    res = sweep(cap, mesh, [e_new * x for x in SEGMENT_SCALES], "vision", frames=(c, c + window),
                                workspace=Path(ws), poisson=poisson, substeps=S, past_young=past,
                                reporter=lambda m: print(f"  {Path(cap_dir).name} c={c} S={S}: {m}", flush=True))
                    m = minima(res.young, res.frame_loss, window)[-1]
                    rows.append({"capture": Path(cap_dir).name, "start": cap.start,
                                 "truth_substeps": truth_substeps(Path(cap_dir)), "change": cs, "split": c,
                                 "e_old": e_old, "e_new": e_new, "substeps": S, "window": window,
                                 "young_min": m["young_min"], "interior": m["interior"],
                                 "curvature": m["curvature"], "grid": res.young.tolist(),
                                 "frame_loss": res.frame_loss.tolist(), "n_vertices": res.info["n_vertices"],
                                 "order": res.info["order"], "seconds": round(time.time() - t0, 1)})
                    print(f"{Path(cap_dir).name} step {e_old:.3g}→{e_new:.3g} at {cs}, split {c}, S={S}: minimum "
                          f"{m['young_min'] / e_new:.3f} E_new, curvature {m['curvature']:.3g}", flush=True)
    return rows


def write_segments(rows: list[dict], out: Path) -> None:
    """calibration_segments.{md,json} in ``out``, rows by capture, step, split and S."""
    rows = sorted(rows, key=lambda r: (r["capture"], r["change"], r["split"], r["substeps"]))
    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "rows": rows}
    (out / "calibration_segments.json").write_text(json.dumps(data, indent=1))
    lines = ["| capture | start | truth substeps N | step of E_true | split c (located) | adapt substeps S | "
             "frames in the loss | E at the minimum / E_new | curvature d² ln L / d(ln E)² | time (s) |",
             "| --- | --- | ---: | --- | --- | ---: | --- | ---: | ---: | ---: |"]
    for r in rows:
        off = r["split"] - r["change"]
        where = "right" if off == 0 else (f"{-off} early" if off < 0 else f"{off} late")
        lines.append(f"| {r['capture']} | {r['start']} | {r.get('truth_substeps') or '?'} | {r['e_old']:.3g} → "
                     f"{r['e_new']:.3g} Pa at frame {r['change']} | {r['split']} ({where}) | {r['substeps']} | "
                     f"{r['split']}–{r['split'] + r['window'] - 1} | {r['young_min'] / r['e_new']:.3f}"
                     f"{'' if r['interior'] else ' (grid end)'} | {r['curvature']:.3g} | {r['seconds']:.0f} |")
    md = ("# After a step of E: where the image loss of the frames after the split is lowest, given the past\n\n"
          "E at the minimum of L(E) = Σ_{t=c..c+W−1} image loss_t over a grid of fixed E "
          f"({', '.join(f'{s:g}' for s in SEGMENT_SCALES)} × E_new, parabola in log E), divided by E_new: "
          "frames 0..c−1 simulated once in full space with the truth's E(t) — the old material on the frames from "
          "the change to c − 1 when the split c comes after the change, the new one on frame c* − 1 when it comes "
          "before — and frames c.. continued with each grid value (stages.sweep.sweep, past_young); ν at the "
          "truth's; the Gaussians re-bound to frame 0 of that past.  This is the loss `rsl adapt`'s recalibration "
          "fits after rule 5 has located a change at c (its own past, ν and space aside).  Curvature: "
          "d² ln L / d(ln E)² at the minimum; the first calibration's (frames 0..8) is in calibration_frames.md.\n\n"
          + "\n".join(lines) + "\n\n"
          f"Machine: {data['machine']}; date {data['date']}.  Produced by `bench/calibration_frames.py --segments`.\n")
    (out / "calibration_segments.md").write_text(md)
    print("\n".join(lines))


def write(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "rows": rows}
    (out / "calibration_frames.json").write_text(json.dumps(data, indent=1))
    bs = [m["frames"] for m in rows[0]["minima"]]
    head = ("| capture | start | truth substeps N | adapt mesh (vertices) | adapt substeps S | "
            + " | ".join(f"b = {b}" for b in bs) + " | time (s) |\n|" + " --- |" * (6 + len(bs)))
    lines = [head]
    for r in rows:
        cells = [f"{m['young_min'] / r['e_true']:.3f}{'' if m['interior'] else ' (grid end)'}" for m in r["minima"]]
        lines.append(f"| {r['capture']} | {r['start']} | {r.get('truth_substeps') or '?'} | P{r['order']} "
                     f"({r['n_vertices']}) | {r['substeps']} | "
                     + " | ".join(cells) + f" | {r['seconds']:.0f} |")
    curv = [f"{r['capture']} N={r.get('truth_substeps') or '?'} S={r['substeps']}: "
            + ", ".join(f"{m['curvature']:.2g}" for m in r["minima"])
            for r in rows]
    md = ("# The first calibration's frames: where the image loss of frames 0..b−1 is lowest\n\n"
          "E at the minimum of L_b(E) = Σ_{t<b} image loss_t over a grid of fixed E "
          f"({', '.join(f'{s:g}' for s in SCALES)} × E_true, parabola in log E), divided by E_true: full-space "
          "simulation of the capture's first frames from its declared start with ν at the truth's, the Gaussians "
          "re-bound to frame 0 simulated with each E (as `rsl adapt`'s calibration binds them).  `rsl adapt "
          "--anchor-calibration K` fits θ to the first K informed frames, i.e. b = K + 1 on these captures (the "
          "object moves from frame 1).  N: the truth's implicit-Euler substeps per frame (rsl synth --substeps); S: "
          "those of the simulation the loss is evaluated with (rsl adapt --substeps).\n\n" + "\n".join(lines) + "\n\n"
          "Curvature d² ln L_b / d(ln E)² at the minimum (how sharply b frames locate E), per b: "
          + "; ".join(curv) + ".\n\n"
          f"Machine: {data['machine']}; date {data['date']}.  Produced by `bench/calibration_frames.py`.\n\n"
          "![minimum over b](calibration_frames.png)\n")
    (out / "calibration_frames.md").write_text(md)
    starts = sorted({r["start"] for r in rows})
    fig, axes = plt.subplots(1, len(starts), figsize=(5.2 * len(starts), 4.2), sharey=True, squeeze=False)
    truths = sorted({r.get("truth_substeps") or 0 for r in rows})
    steps = sorted({r["substeps"] for r in rows})
    for ax, start in zip(axes[0], starts):
        for r in (r for r in rows if r["start"] == start):
            n = r.get("truth_substeps") or 0
            ax.plot([m["frames"] for m in r["minima"]], [m["young_min"] / r["e_true"] for m in r["minima"]],
                    color=f"C{truths.index(n)}", ls=("-", "--", ":", "-.")[steps.index(r["substeps"]) % 4],
                    marker="o", ms=3, label=f"truth N={n or '?'}, S={r['substeps']}")
        ax.axhline(1.0, color="k", lw=1)
        ax.axhspan(0.97, 1.03, color="0.9")
        ax.set_title(f"start = {start}")
        ax.set_xlabel("b (frames 0..b−1 in the loss)")
    axes[0][0].set_ylabel("E at the loss minimum / E_true")
    axes[0][-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    fig.savefig(out / "calibration_frames.png", dpi=110)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
