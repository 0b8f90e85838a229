"""Captures filmed mid-motion (`[capture] start = "moving"`): E from rsl adapt when it estimates frame 0's shape and
velocity, against declaring the start an equilibrium (what a capture had to claim before), in the same run.

Captures by `rsl synth` of sample_data/bar pulled by a cable (or, `--scene dino`, sample_data/dino pushed by a sphere:
contact), constant E_true, truth on P2 tets with 3 substeps per frame and hard handles (bench/_pipeline.foreign_capture): `--start moving --lead-frames K` (the capture begins K
frames into a simulation from the equilibrium) for each K, and the plain equilibrium start (K = 0) as the control.
rsl adapt runs online on its own P2 mesh (`rsl tetrahedralize --order 2 --max-tets M`), in the reduced space (its
default; a subspace of r = 12 trained on the capture's scenario) or the full space, markers, gn, window 3, E
initialised at 0.5 E_true, its default substeps; each capture once as declared and once with its
capture.toml saying `start = "equilibrium"` (a copy).  Per row: the median relative error of E over the settled
frames (≥ w + 5), the median settled E / E_true, the RMS distance of the simulated surface to the truth's (all
frames; the truth surface is on its own mesh, so compared through the markers: their positions on rsl's mesh
against markers.csv), the median per-frame time, and from `rsl evaluate` the force error (the handle forces of
the full-space replay, from the declared start, against truth/forces.csv) and the mean symmetric surface distance
to the truth.

    nice .venv/bin/python bench/moving_start.py [--scene bar|dino] [--frames 24] [--leads 4,8,16,0] [--space reduced]
        [--out docs/results] [--merge A.json B.json]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402

E_TRUE = 1.0e5
POISSON = 0.45
WINDOW = 3
TRUTH_SUBSTEPS = 3


def declared_copy(cap: Path, out: Path, start: str) -> Path:
    """A copy of the capture whose capture.toml declares ``start`` (the truth and frames unchanged)."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(cap, out)
    toml = out / "capture.toml"
    toml.write_text(re.sub(r'start = "\w+"', f'start = "{start}"', toml.read_text()))
    return out


SCENES = {"bar": lambda: pl.bar_cable(young=E_TRUE), "dino": lambda: pl.dino_push(E_TRUE)}


def run_lead(work: Path, scene: str, lead: int, frames: int, max_tets: int, space: str) -> list[dict]:
    from stages.artefacts import AdaptArtefact, MeshArtefact
    from stages.capture import load_capture, read_truth
    from stages.observations import MarkerObservation

    start = "moving" if lead else "equilibrium"
    extra = ["--lead-frames", lead] if lead else []
    tag = f"k{lead}" if scene == "bar" else f"{scene}_k{lead}"  # (the bar's folders as first named)
    cap = pl.foreign_capture(work / f"cap_{tag}", SCENES[scene](), start=start, frames=frames, cameras=1,
                             resolution=32, substeps=TRUTH_SUBSTEPS, poisson=POISSON, extra=extra)
    ws = pl.mesh(cap, work / f"ws_{tag}", order=2, max_tets=max_tets, calibrate=False)
    if space == "reduced":
        pl.subspace(cap, ws, frames=frames, dim=12)
    truth = read_truth(load_capture(cap))
    mesh = MeshArtefact.load(ws / "mesh.h5")
    rows = []
    for declared in (["moving", "equilibrium"] if lead else ["equilibrium", "moving"]):
        c = cap if declared == start else declared_copy(cap, work / f"cap_{tag}_as_{declared}", declared)
        base = {"scene": scene, "lead_frames": lead, "capture_start": start, "declared": declared, "space": space}
        try:
            pl.adapt(c, ws, "--space", space, "--loss", "markers", "--estimator", "gn", "--window", WINDOW,
                     "--young-init", f"{0.5 * E_TRUE:g}")
            pl.evaluate(c, ws, "--psnr-frames", 0, "--no-plot")
        except RuntimeError as e:
            rows.append({**base, "error": str(e)[-500:]})
            print(_row(rows[-1]), flush=True)
            continue
        ev = json.loads((ws / "evaluation.json").read_text())
        forces = ev.get("forces") or {}
        a = AdaptArtefact.load(ws / "adapt.h5")
        yt = truth.young[np.asarray(a.frames)][:, 0]
        y = np.asarray(a.young)[:, 0]
        ok = np.arange(len(y)) >= WINDOW + 5
        capture = load_capture(c)
        obs = MarkerObservation(capture, a.positions[0], mesh.surface_faces, mesh.n_vertices)
        if declared == "moving":  # bound as adapt binds them: material points fitted to the first window's tracks
            obs.fit_to_tracks(range(WINDOW), a.positions[:WINDOW])
        P = capture.markers()[np.asarray(a.frames)]
        m = obs.binding.positions(a.positions)
        miss = np.sqrt(np.nanmean(np.sum((m - P) ** 2, axis=-1), axis=1))
        rows.append({**base, "frames": int(len(y)), "settled_frames": int(ok.sum()),
                     "median_error": float(np.median(np.abs(y[ok] - yt[ok]) / yt[ok])),
                     "median_ratio": float(np.median(y[ok] / yt[ok])),
                     "marker_rms_mm": float(1e3 * np.sqrt(np.mean(miss ** 2))),
                     "marker_rms_first5_mm": float(1e3 * np.sqrt(np.mean(miss[:5] ** 2))),
                     "time_per_frame_s": float(np.median(a.time_total_s)),
                     "changes": list(a.extra.get("material_changes_detected", [])),
                     "rebinds": list(a.extra.get("moving_start_rebinds", [])),
                     "force_error": forces.get("median_relative_error"), "force_source": forces.get("source"),
                     "surface_error_mm": (1e3 * ev["vertex_error_mean_m"] if isinstance(
                         ev.get("vertex_error_mean_m"), (int, float)) else None),
                     "young": y.tolist(), "young_true": yt.tolist()})
        print(_row(rows[-1]), flush=True)
    return rows


HEADER = ("| scene | capture (lead-in frames) | declared start | space | median settled E error (%) | median settled E / E_true | "
          "marker RMS, all frames (mm) | marker RMS, frames 0–4 (mm) | surface error (mm) | force error (%) | "
          "s / frame | changes detected | re-bindings |\n"
          "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|---|")


def _row(r: dict) -> str:
    cap = f"{r.get('scene', 'bar')} | {r['capture_start']} ({r['lead_frames']})"
    if "error" in r:  # rsl's own sentence (after "error: "), without the folder
        why = r["error"].rsplit("error: ", 1)[-1].strip().replace("|", "/")
        why = re.sub(r"^\S*/(\w+\.\w+):", r"\1:", why)
        return f"| {cap} | {r['declared']} | {r['space']} | refused: {why} | — | — | — | — | — | — | — | — |"
    fe, se = r.get("force_error"), r.get("surface_error_mm")
    return (f"| {cap} | {r['declared']} | {r['space']} | {100 * r['median_error']:.1f} | {r['median_ratio']:.3f} | "
            f"{r['marker_rms_mm']:.2f} | {r['marker_rms_first5_mm']:.2f} | {'—' if se is None else f'{se:.2f}'} | "
            f"{'—' if fe is None else f'{100 * fe:.1f}'} | {r['time_per_frame_s']:.2f} | "
            f"{', '.join(map(str, r['changes'])) or 'none'} | {', '.join(map(str, r['rebinds'])) or '—'} |")


def capture_key(r: dict) -> tuple[str, int]:
    """(scene, lead-in frames): the capture a row ran on (rows of older runs have no scene: the bar)."""
    return r.get("scene", "bar"), r["lead_frames"]


def summary(rows: list[dict]) -> list[str]:
    """Per mid-motion capture: the declared-moving row's settled error against the declared-equilibrium row's."""
    out = []
    for scene, lead in sorted({capture_key(r) for r in rows if r["lead_frames"]}):
        by = {r["declared"]: r for r in rows if capture_key(r) == (scene, lead) and "error" not in r}
        refused = [r for r in rows if capture_key(r) == (scene, lead) and "error" in r
                   and r["declared"] == "equilibrium"]
        if "moving" in by and refused:
            mv = by["moving"]
            out.append(f"- {scene}, filmed from {lead} frames into the motion: declared moving, median settled E error "
                       f"{100 * mv['median_error']:.1f} % (E / E_true {mv['median_ratio']:.3f}); declared equilibrium, "
                       f"rsl adapt refuses the capture (its row).")
        if "moving" in by and "equilibrium" in by:
            mv, eq = by["moving"], by["equilibrium"]
            out.append(f"- {scene}, filmed from {lead} frames into the motion: declared moving, median settled E error "
                       f"{100 * mv['median_error']:.1f} % (E / E_true {mv['median_ratio']:.3f}); declared "
                       f"equilibrium {100 * eq['median_error']:.1f} % ({eq['median_ratio']:.3f}); marker RMS over "
                       f"frames 0–4 {mv['marker_rms_first5_mm']:.2f} against {eq['marker_rms_first5_mm']:.2f} mm"
                       + (f"; force error {100 * mv['force_error']:.1f} against {100 * eq['force_error']:.1f} %"
                          if mv.get("force_error") is not None and eq.get("force_error") is not None else "")
                       + ".")
    for r in rows:
        if r["lead_frames"] == 0 and r["declared"] == "moving" and "error" not in r:
            ctl = [q for q in rows if capture_key(q) == capture_key(r) and q["declared"] == "equilibrium"
                   and "error" not in q]
            if ctl:
                out.append(f"- {capture_key(r)[0]}, control, a capture that does start at its equilibrium: declared "
                           f"moving {100 * r['median_error']:.1f} %, declared equilibrium "
                           f"{100 * ctl[0]['median_error']:.1f} %.")
    return out


def plot(rows: list[dict], path: Path) -> bool:
    """E / E_true per frame of each mid-motion capture (one panel each), declared moving against declared
    equilibrium, with the ±5 % band; False when no row has its series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    caps = sorted({capture_key(r) for r in rows if r["lead_frames"] > 0 and "young" in r})
    if not caps:
        return False
    fig, axes = plt.subplots(1, len(caps), figsize=(3.6 * len(caps), 3.0), sharey=True, squeeze=False)
    for ax, (scene, lead) in zip(axes[0], caps):
        for r in rows:
            if capture_key(r) == (scene, lead) and "young" in r:
                ratio = np.asarray(r["young"]) / np.asarray(r["young_true"])
                ax.plot(ratio, "o-" if r["declared"] == "moving" else "s--", ms=3,
                        label=f"declared {r['declared']}")
        ax.axhspan(0.95, 1.05, color="0.9")
        ax.axvline(WINDOW + 5 - 0.5, color="0.6", lw=0.8)
        ax.set_title(f"{scene}, filmed {lead} frames in", fontsize=9)
        ax.set_xlabel("frame")
    axes[0][0].set_ylabel("E / E_true")
    axes[0][0].set_ylim(0.4, 1.6)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def write(rows: list[dict], out: Path, plan: dict) -> None:
    """docs/results/moving_start.{md,json,png}."""
    out.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    data = {"plan": plan, "cases": rows, "ended": datetime.datetime.now(datetime.timezone.utc).isoformat(
        timespec="seconds"), "load_average": load, "machine": f"{platform.machine()} {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}"}
    (out / "moving_start.json").write_text(json.dumps(data, indent=1))
    md = ["# Captures filmed mid-motion: frame 0's shape and velocity estimated", "",
          f"Bar pulled by a cable (scene bar), dinosaur pushed by a sphere (dino), E_true = {E_TRUE:g} Pa, ν = {POISSON}; truth P2, {TRUTH_SUBSTEPS} substeps per "
          f"frame, hard handles, {plan['frames']} frames; `--start moving --lead-frames K` begins K frames into a "
          f"simulation from the equilibrium. rsl adapt: P2 mesh (`--max-tets {plan['max_tets']}`), "
          f"{plan['space']} space, markers, gn, window {WINDOW}, E from 0.5 E_true, default substeps; each capture as declared and with its "
          f"capture.toml saying the other start. Settled: frames ≥ w + 5. Marker RMS: the markers bound on rsl's "
          f"frame-0 surface (declared moving: as adapt binds them, each marker's material point fitted to its track "
          f"over the first window), followed through adapt.h5's positions, against markers.csv. Re-bindings: per "
          f"window holding frame 0, the fits of the markers' material points to the window's tracks "
          f"(`MOVING_REBINDS`).", "", HEADER]
    md += [_row(r) for r in rows]
    if plot(rows, out / "moving_start.png"):
        md += ["", "![E / E_true per frame, declared moving against declared equilibrium; grey band ±5 %, vertical "
               "line: the first settled frame](moving_start.png)"]
    md += ["", *summary(rows), "",
           f"Ended {data['ended']} (load average {load:.1f}), {data['machine']}. Produced by "
           f"`bench/moving_start.py`."]
    (out / "moving_start.md").write_text("\n".join(md) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="bar", choices=sorted(SCENES))
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="write the page from the rows of these moving_start.json files (a row in several: the last file's)")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--leads", default="4,8,16,0", help="lead-in frames of each capture (0: the equilibrium control)")
    ap.add_argument("--max-tets", type=int, default=1500)
    ap.add_argument("--space", default="reduced", choices=("reduced", "full"))
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_moving_start"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    a = ap.parse_args()
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        latest: dict = {}
        for run in runs:
            for r in run["cases"]:
                latest[(*capture_key(r), r["declared"], r["space"])] = r
        write(list(latest.values()), a.out, runs[0]["plan"])
        print("\n".join(summary(list(latest.values()))))
        return
    leads = [int(k) for k in a.leads.split(",") if k.strip()]
    plan = {"frames": a.frames, "leads": leads, "max_tets": a.max_tets, "space": a.space, "scene": a.scene}
    print(HEADER, flush=True)
    rows = []
    for lead in leads:
        rows += run_lead(a.work, a.scene, lead, a.frames, a.max_tets, a.space)
    write(rows, a.out, plan)
    print("\n".join(summary(rows)))


if __name__ == "__main__":
    main()
