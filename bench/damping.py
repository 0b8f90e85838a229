"""A damped material (`[material] damping`, β s): whether a damped truth is a definite quantity in time, and E and the
forces from rsl adapt when the capture declares the truth's β, against when it does not, in the same run.

Captures by `rsl synth` of sample_data/bar pulled by a cable (constant E_true, the equilibrium start, 24 frames, one
camera, 40 markers), truth on P2 tets with hard handles (bench/_pipeline.foreign_capture), for each truth damping
β_true and each truth time step (N substeps per frame).  Part 1, the truths: the RMS distance between the surfaces and
the median relative difference of the handle forces (truth/forces.csv) of the truths with N and with the finest N,
per β_true — how far each truth is from converged in time.  Part 2, rsl adapt (its P2 mesh `--max-tets 1500`,
reduced space r = 12 trained on the capture, markers, gn, window 3, E from 0.5 E_true, its default substeps) on the
finest damped truth as made (β declared in capture.toml) and on a copy that does not declare it (β = 0 simulated),
and on the undamped truth: the median relative E error over the settled frames (≥ w + 5) and, from `rsl evaluate`,
the force error against truth/forces.csv.  ``--auto``: instead, rsl adapt --damping auto (β estimated from the
first frames, stages/damping_profile.py; the subspace's cubature fitted to the viscous forces too,
train-subspace --viscous-cubature on) on the copy that does not declare β, and on the undamped truth: the same
columns, the β it estimated and each β it tried.

    nice .venv/bin/python bench/damping.py [--beta 0.003] [--substeps 3,12] [--auto] [--out docs/results]
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
FRAMES = 24


def truth(work: Path, beta: float, substeps: int) -> Path:
    """The capture of β_true = beta (declared) and N = substeps."""
    extra = ["--damping", beta] if beta else []
    return pl.foreign_capture(work / f"cap_b{beta:g}_n{substeps}", pl.bar_cable(young=E_TRUE), start="equilibrium",
                              frames=FRAMES, cameras=1, resolution=32, substeps=substeps, poisson=POISSON, extra=extra)


def undeclared(cap: Path, out: Path) -> Path:
    """A copy of the capture whose capture.toml does not declare its damping."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(cap, out)
    toml = out / "capture.toml"
    toml.write_text(re.sub(r"(?m)^damping = .*\n", "", toml.read_text()))
    return out


def truth_rows(caps: dict) -> list[dict]:
    """Per (β_true, N): the surface and the handle forces against the finest N's truth of the same β."""
    from stages.capture import read_forces_csv
    from stages.forces import force_errors

    rows = []
    for beta in sorted({b for b, _ in caps}):
        ns = sorted(n for b, n in caps if b == beta)
        ref = caps[(beta, ns[-1])]
        x_ref = np.load(ref / "truth" / "surface.npz")["vertices"]
        f_ref = read_forces_csv(ref / "truth" / "forces.csv")
        for n in ns[:-1]:
            cap = caps[(beta, n)]
            x = np.load(cap / "truth" / "surface.npz")["vertices"]
            err = force_errors(read_forces_csv(cap / "truth" / "forces.csv"), f_ref)
            rows.append({"beta": beta, "substeps": n, "reference_substeps": ns[-1],
                         "surface_rms_mm": float(1e3 * np.sqrt(np.mean(np.sum((x - x_ref) ** 2, axis=-1)))),
                         "force_difference": float(np.median([e["median_relative_error"] for e in err.values()]))})
            print(_truth_row(rows[-1]), flush=True)
    return rows


def adapt_row(cap: Path, ws: Path, beta_true: float, declared: float, substeps: int,
              damping_frames: int | None = None) -> dict:
    """One rsl adapt row; ``damping_frames``: --damping auto over that many frames (the subspace's cubature fitted to
    the viscous forces too)."""
    from stages.artefacts import AdaptArtefact
    from stages.capture import load_capture, read_truth

    auto = damping_frames is not None
    base = {"beta_true": beta_true, "declared": declared, "truth_substeps": substeps,
            "option": "auto" if auto else ("declared" if declared > 0 else "not declared")}
    pl.mesh(cap, ws, order=2, max_tets=1500, calibrate=False)
    pl.subspace(cap, ws, frames=FRAMES, dim=12, train_options=["--viscous-cubature", "on"] if auto else [])
    extra = ["--damping", "auto", "--damping-frames", damping_frames] if auto else []
    try:
        pl.adapt(cap, ws, "--space", "reduced", "--loss", "markers", "--estimator", "gn", "--window", WINDOW,
                 "--young-init", f"{0.5 * E_TRUE:g}", *extra)
        pl.evaluate(cap, ws, "--psnr-frames", 0, "--no-plot")
    except RuntimeError as e:
        return {**base, "error": str(e)[-500:]}
    ev = json.loads((ws / "evaluation.json").read_text())
    a = AdaptArtefact.load(ws / "adapt.h5")
    y = np.asarray(a.young)[:, 0]
    yt = read_truth(load_capture(cap)).young[np.asarray(a.frames)][:, 0]
    ok = np.arange(len(y)) >= WINDOW + 5
    prof = a.extra.get("damping_profile") or {}
    if auto:
        base.update(damping_frames=damping_frames, tried=prof.get("tried", []), flat=prof.get("flat"))
    return {**base, "simulated": float(a.extra.get("damping", 0.0)), "settled_frames": int(ok.sum()),
            "median_error": float(np.median(np.abs(y[ok] - yt[ok]) / yt[ok])),
            "median_ratio": float(np.median(y[ok] / yt[ok])),
            "force_error": (ev.get("forces") or {}).get("median_relative_error"),
            "time_per_frame_s": float(np.median(a.time_total_s)), "young": y.tolist(), "young_true": yt.tolist()}


TRUTH_HEADER = ("| β_true (s) | truth N | against N | surface RMS (mm) | median handle-force difference (%) |\n"
                "|---:|---:|---:|---:|---:|")
ADAPT_HEADER = ("| β_true (s) | truth N | β in rsl | β simulated (s) | median settled E error (%) | median settled E / "
                "E_true | force error (%) | s / frame |\n|---:|---:|---|---:|---:|---:|---:|---:|")


def _option(r: dict) -> str:
    """How rsl had β: declared in capture.toml, not declared (0 simulated), or --damping auto over K frames."""
    o = r.get("option") or ("declared" if r["declared"] > 0 else "not declared")
    return f"auto ({r['damping_frames']} frames)" if o == "auto" else o


def _truth_row(r: dict) -> str:
    return (f"| {r['beta']:g} | {r['substeps']} | {r['reference_substeps']} | {r['surface_rms_mm']:.3f} | "
            f"{100 * r['force_difference']:.1f} |")


def _adapt_row(r: dict) -> str:
    head = f"| {r['beta_true']:g} | {r['truth_substeps']} | {_option(r)}"
    if "error" in r:
        return f"{head} | — | failed: {r['error'].rsplit('error: ', 1)[-1].strip()} | — | — | — |"
    fe = r.get("force_error")
    return (f"{head} | {r.get('simulated', r['declared']):.3g} | {100 * r['median_error']:.1f} | "
            f"{r['median_ratio']:.3f} | "
            f"{'—' if fe is None else f'{100 * fe:.1f}'} | {r['time_per_frame_s']:.2f} |")


def summary(truths: list[dict], adapts: list[dict]) -> list[str]:
    """Per damped β_true: E declared against undeclared, beside the undamped truth; the truths' convergence."""
    out = []
    base = [r for r in adapts if r["beta_true"] == 0 and "error" not in r and _option(r) == "not declared"]
    for r in adapts:
        if "error" not in r and r.get("option") == "auto":
            tried = ", ".join(f"{b:.3g}" for b, _ in sorted(r["tried"]))
            out.append(f"- β_true = {r['beta_true']:g} s, --damping auto over {r['damping_frames']} frames: β = "
                       f"{r['simulated']:.3g} s (tried {tried} s{'; flat' if r.get('flat') else ''}), median settled "
                       f"E error {100 * r['median_error']:.1f} % (E / E_true {r['median_ratio']:.3f}).")
    for beta in sorted({r["beta_true"] for r in adapts if r["beta_true"] > 0}):
        by = {r["declared"] > 0: r for r in adapts if r["beta_true"] == beta and "error" not in r
              and r.get("option") != "auto"}
        if True in by and False in by:
            d, u = by[True], by[False]
            out.append(f"- β_true = {beta:g} s: declared, median settled E error {100 * d['median_error']:.1f} % "
                       f"(E / E_true {d['median_ratio']:.3f}); undeclared {100 * u['median_error']:.1f} % "
                       f"({u['median_ratio']:.3f})"
                       + (f"; the undamped truth {100 * base[0]['median_error']:.1f} % ({base[0]['median_ratio']:.3f})"
                          if base else "") + ".")
    for beta in sorted({r["beta"] for r in truths}):
        rs = [r for r in truths if r["beta"] == beta]
        out.append(f"- β_true = {beta:g} s, the truths against N = {rs[0]['reference_substeps']}: "
                   + ", ".join(f"N = {r['substeps']} differs by {r['surface_rms_mm']:.2f} mm and "
                               f"{100 * r['force_difference']:.1f} % in force" for r in rs) + ".")
    return out


def plot(adapts: list[dict], path: Path) -> bool:
    """E / E_true per frame of each adapt row (one panel per β_true > 0, the undamped truth's row in each), with the
    ±5 % band; False when no row has its series."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    betas = sorted({r["beta_true"] for r in adapts if r["beta_true"] > 0 and "young" in r})
    if not betas:
        return False
    fig, axes = plt.subplots(1, len(betas), figsize=(4.2 * len(betas), 3.0), sharey=True, squeeze=False)
    for ax, beta in zip(axes[0], betas):
        for r in adapts:
            if "young" in r and r["beta_true"] in (beta, 0.0):
                label = (f"β_true {r['beta_true']:g} s, {_option(r)}" if r["beta_true"]
                         else f"undamped truth, {_option(r)}")
                ax.plot(np.asarray(r["young"]) / np.asarray(r["young_true"]), "o-", ms=3, label=label)
        ax.axhspan(0.95, 1.05, color="0.9")
        ax.axvline(WINDOW + 5 - 0.5, color="0.6", lw=0.8)
        ax.set_xlabel("frame")
        ax.set_title(f"β_true = {beta:g} s", fontsize=9)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel("E / E_true")
    axes[0][0].set_ylim(0.5, 1.5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def write(truths: list[dict], adapts: list[dict], out: Path, plan: dict, run: dict | None = None) -> None:
    """docs/results/damping.{md,json}; ``run``: the ended / load_average / machine of a run merged (default: now)."""
    out.mkdir(parents=True, exist_ok=True)
    data = {"plan": plan, "truths": truths, "adapt": adapts, "ended": datetime.datetime.now(
        datetime.timezone.utc).isoformat(timespec="seconds"),
        "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan"),
        "machine": f"{platform.machine()} {os.cpu_count()} CPUs, Python {platform.python_version()}"}
    data.update({k: run[k] for k in ("ended", "load_average", "machine") if run and k in run})
    load = data["load_average"]
    (out / "damping.json").write_text(json.dumps(data, indent=1))
    md = ["# A damped material: truths converged in time, and E with and without the damping declared", "",
          f"Bar pulled by a cable, E_true = {E_TRUE:g} Pa, ν = {POISSON}, {FRAMES} frames from the equilibrium; truth "
          f"P2, hard handles, viscous damping β_true (`rsl synth --damping`, Kelvin–Voigt on the Green strain, force "
          f"≈ −β K₀ v), N implicit-Euler substeps per frame. Part 1: each truth against the truth of the same β with "
          f"the finest N (surface RMS over all frames; median over handles of the median relative difference of "
          f"their forces). Part 2: rsl adapt on its P2 mesh (`--max-tets 1500`), reduced space r = 12, markers, gn, "
          f"window {WINDOW}, E from 0.5 E_true, its default substeps, on the capture as made (β declared in "
          f"capture.toml [material] damping), on a copy that does not declare it (rsl simulates β = 0), and on that "
          f"copy with `rsl adapt --damping auto` (β estimated from the first K frames by the profile of the loss over "
          f"β with E and ν fitted, stages/damping_profile.py; its subspace's cubature fitted to the viscous forces "
          f"too, `train-subspace --viscous-cubature on`). Settled: "
          f"frames ≥ w + 5. Force error: `rsl evaluate` against truth/forces.csv.", "",
          "## The truths in time", "", TRUTH_HEADER, *[_truth_row(r) for r in truths], "",
          "## rsl adapt", "", ADAPT_HEADER, *[_adapt_row(r) for r in adapts], ""]
    if plot(adapts, out / "damping.png"):
        md += ["![E / E_true per frame; grey band ±5 %, vertical line: the first settled frame](damping.png)", ""]
    md += [*summary(truths, adapts), "",
          f"Ended {data['ended']} (load average {load:.1f}), {data['machine']}. Produced by `bench/damping.py`."]
    (out / "damping.md").write_text("\n".join(md) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--beta", type=float, default=0.003, help="β_true of the damped truths, s")
    ap.add_argument("--substeps", default="3,12", help="truth substeps per frame N; the last is the finest")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_damping"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--auto", type=int, default=0, metavar="K",
                    help="rows of rsl adapt --damping auto over K frames instead (the copy without β, the undamped "
                         "truth)")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="write the page from the rows of these damping.json files (a row in several: the last)")
    a = ap.parse_args()
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        truths = list({(r["beta"], r["substeps"]): r for run in runs for r in run["truths"]}.values())
        adapts = list({(r["beta_true"], r["declared"], r["truth_substeps"], _option(r)): r
                       for run in runs for r in run["adapt"]}.values())
        truths.sort(key=lambda r: (r["beta"], r["substeps"]))
        adapts.sort(key=lambda r: (r["beta_true"] == 0, r["beta_true"], -r["declared"], _option(r)))
        write(truths, adapts, a.out, {**runs[-1]["plan"], "beta": sorted({b for p in runs for b in np.atleast_1d(p["plan"]["beta"]).tolist()})},
              runs[-1])
        print("\n".join(summary(truths, adapts)))
        return
    ns = [int(k) for k in a.substeps.split(",") if k.strip()]
    plan = {"beta": a.beta, "substeps": ns, "frames": FRAMES, "auto": a.auto}
    caps = {(b, n): truth(a.work, b, n) for b in (0.0, a.beta) for n in ns}
    if a.auto:
        n = ns[-1]
        print(ADAPT_HEADER, flush=True)
        adapts = []
        for cap, ws, beta_true in (
                (undeclared(caps[(a.beta, n)], a.work / f"cap_b{a.beta:g}_n{n}_undeclared"),
                 a.work / f"ws_b{a.beta:g}_n{n}_auto", a.beta),
                (caps[(0.0, n)], a.work / f"ws_b0_n{n}_auto", 0.0)):
            adapts.append(adapt_row(cap, ws, beta_true, 0.0, n, a.auto))
            print(_adapt_row(adapts[-1]), flush=True)
        write([], adapts, a.out, plan)
        return
    print(TRUTH_HEADER, flush=True)
    truths = truth_rows(caps)
    print(ADAPT_HEADER, flush=True)
    n = ns[-1]
    damped = caps[(a.beta, n)]
    adapts = []
    for cap, ws, beta_true, declared in (
            (damped, a.work / f"ws_b{a.beta:g}_n{n}", a.beta, a.beta),
            (undeclared(damped, a.work / f"cap_b{a.beta:g}_n{n}_undeclared"), a.work / f"ws_b{a.beta:g}_n{n}_undeclared",
             a.beta, 0.0),
            (caps[(0.0, n)], a.work / f"ws_b0_n{n}", 0.0, 0.0)):
        adapts.append(adapt_row(cap, ws, beta_true, declared, n))
        print(_adapt_row(adapts[-1]), flush=True)
    write(truths, adapts, a.out, plan)


if __name__ == "__main__":
    main()
