"""Gauss–Newton (moving-horizon, E ± σ) against Adam in `rsl adapt`, on synthetic marker captures.

For each scene × seed, `rsl synth` films a beam (shared/data Coarse_beam.mesh) with noisy markers, with E
constant and with E stepping ×2 and ×4; both estimators run online in the full space from E_init = E0/2.
Measured: the settled error and the ±3 % band (constant E), the frames needed after each step to come and stay
within 5 % of the new value, the fraction of settled frames whose truth lies inside ±2σ (gn), and the time per
frame.  Writes docs/results/estimator.{md,json,png}.  Usage: python bench/estimator.py [--seeds 3] [--quick]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
BEAM = ROOT.parent / "shared" / "data" / "autodef_fulton" / "Coarse_beam.mesh"
OUT = ROOT / "docs" / "results"
E0 = 1.0e5
W = 3


def make_capture(root: Path, scenario: str, seed: int, schedule: str, frames: int, substeps: int):
    from stages.steps import synth, tetrahedralize

    cap = root / "cap"
    synth.run(synth.SynthConfig(mesh=BEAM, out=cap, scenario=scenario, cameras=1, frames=frames, resolution=32,
                                young=E0, young_schedule=schedule, markers=30, marker_noise=2e-4, calib_views=0,
                                seed=seed, substeps=substeps))
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    ws = root / "ws"
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    truth = np.loadtxt(cap / "truth" / "material.csv", delimiter=",", skiprows=1, usecols=2, ndmin=1)
    return cap, ws, truth[:frames]


def run_adapt(cap: Path, ws: Path, estimator: str, process_noise: float):
    from stages.steps import adapt
    from stages.artefacts import AdaptArtefact

    adapt.run(adapt.AdaptConfig(capture=cap, workspace=ws, space="full", loss="markers", window=W,
                                young_init=E0 / 2, estimator=estimator, process_noise=process_noise))
    a = AdaptArtefact.load(ws / "adapt.h5")
    return a.young[:, 0], a.young_sigma[:, 0], float(np.median(a.time_total_s)), a.extra.get("material_changes_detected", [])


def metrics(E, sd, truth, steps: list[int]) -> dict:
    rel = E / truth - 1
    bounds = [0] + steps + [len(E)]
    settle = []
    for a, b in zip(bounds[:-1], bounds[1:]):
        ok = np.abs(rel[a:b]) <= 0.05
        k = next((i for i in range(b - a) if ok[i:].all()), None)  # first frame from which it stays within 5 %
        settle.append(None if k is None else int(k))
    settled = np.zeros(len(E), bool)
    for a, b in zip(bounds[:-1], bounds[1:]):
        settled[min(a + W + 5, b):b] = True
    out = {"settle_frames": settle, "median_abs_err_settled": float(np.median(np.abs(rel[settled]))),
           "max_abs_err_settled": float(np.max(np.abs(rel[settled]))),
           "within_3pct_settled": float(np.mean(np.abs(rel[settled]) <= 0.03))}
    if np.all(np.isfinite(sd[settled])):
        out["truth_within_2sigma"] = float(np.mean(np.abs(E - truth)[settled] <= 2 * sd[settled]))
    return out


def timing_case(work: Path) -> list[dict]:
    """Per-frame time gn vs adam on bench/adapt.py's bar-like case (a 36×8×8-cell box, ≈9K DOFs, twist, 4 cameras
    at 128², 5000 Gaussians, PCA r = 30, w = 3), images, reduced space, same run."""
    sys.path.insert(0, str(ROOT / "bench"))
    import meshio

    import adapt as bench_adapt  # bench/adapt.py's building blocks
    from stages.sim.meshgen import box_tets

    mesh = work / "box.mesh"
    cells = (36, 8, 8)
    v, t = box_tets(cells, (0.25, 0.25 * cells[1] / cells[0], 0.25 * cells[2] / cells[0]))
    meshio.write(str(mesh), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    frames = 4
    from stages.steps import calibrate, synth, tetrahedralize

    cap, ws = work / "timing" / "cap", work / "timing" / "ws"  # bench/adapt.py's make_capture, linear tets
    synth.run(synth.SynthConfig(mesh=mesh, out=cap, scenario="twist", cameras=4, frames=frames, resolution=128,
                                young=1e5, markers=0, calib_views=0, seed=0))
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    bench_adapt.with_gaussians(cap, ws, 5000, 20)
    ws_r = bench_adapt.subspace_ws(cap, ws, 30, "pca", sequences=8, frames=10)
    rows = []
    for est in ("adam", "gn"):  # one run each (time-boxed on a shared machine)
        art, _ = bench_adapt.run_adapt(cap, ws_r, work / "timing" / est, space="reduced", loss="vision", window=3,
                                       iters_per_frame=1 if est == "adam" else 1, frames=f"0:{frames}",
                                       estimator=est)
        rows.append({"case": "bar-like timing", "estimator": est, "dofs": 3 * art.positions.shape[1], "r": 30,
                     "cameras": 4, "resolution": 128, **bench_adapt.times(art)})
    best = {}
    for r in rows:
        if r["estimator"] not in best or r["total_s"] < best[r["estimator"]]["total_s"]:
            best[r["estimator"]] = r
    out = list(best.values())
    for r in out:
        print(f"timing {r['estimator']}: total {r['total_s']:.3f} s/frame (forward {r['forward_s']:.3f}, "
              f"sensitivity/adjoint {r['backward_s']:.3f}, render {r['render_s']:.3f})", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--timing", action="store_true", help="only the bar-like timing case (appended to the json)")
    ap.add_argument("--from-json", action="store_true", help="re-write estimator.md/.png from estimator.json")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--scenes", default="cable,stretch,twist")
    ap.add_argument("--process-noise", default="0.02")
    ap.add_argument("--substeps", type=int, default=3)
    args = ap.parse_args()
    if args.from_json:  # re-write the tables and the plot from the last measurement
        write(json.loads((OUT / "estimator.json").read_text())["cases"], args)
        return
    if args.timing:
        with tempfile.TemporaryDirectory() as tmp:
            rows = timing_case(Path(tmp))
        data = json.loads((OUT / "estimator.json").read_text())
        data["timing"] = rows
        (OUT / "estimator.json").write_text(json.dumps(data, indent=1))
        md = (OUT / "estimator.md").read_text().split("\n## Per-frame time")[0].rstrip("\n")
        lines = ["", "## Per-frame time, bar-like case (images, reduced space; measured in one run)", "",
                 "| estimator | DOFs | r | cameras | forward s | sensitivity/adjoint s | render s | total s/frame |",
                 "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['estimator']} | {r['dofs']} | {r['r']} | {r['cameras']} × {r['resolution']}² | "
                         f"{r['forward_s']:.3f} | {r['backward_s']:.3f} | {r['render_s']:.3f} | {r['total_s']:.3f} |")
        (OUT / "estimator.md").write_text(md + "\n" + "\n".join(lines) + "\n")
        print("\n".join(lines))
        return
    cases = []
    noises = [float(x) for x in args.process_noise.split(",")]
    for scene in args.scenes.split(","):
        for seed in range(args.seeds):
            for kind, schedule, frames, steps in (("constant", "", 36, []),
                                                  ("steps x2 x4", f"{E0:g}@0,{2 * E0:g}@16,{4 * E0:g}@32", 48, [16, 32])):
                with tempfile.TemporaryDirectory() as tmp:
                    cap, ws, truth = make_capture(Path(tmp), scene, seed, schedule, frames, args.substeps)
                    runs = [("adam", None)] + [("gn", q) for q in noises]
                    for est, q in runs:
                        E, sd, t, ch = run_adapt(cap, ws, est, q if q is not None else 0.02)
                        row = {"scene": scene, "seed": seed, "case": kind, "estimator": est, "process_noise": q,
                               "substeps": args.substeps, "s_per_frame": t, "changes_detected": ch,
                               **metrics(E, sd, truth, steps),
                               "young_rel": (E / truth).tolist(), "sigma_rel": (sd / truth).tolist()}
                        cases.append(row)
                        print(f"{scene:8} seed {seed} {kind:12} {est:4} q={q}: settle {row['settle_frames']} "
                              f"med {row['median_abs_err_settled']:.3%} in2σ {row.get('truth_within_2sigma')} "
                              f"{t:.3f} s/frame changes {ch}", flush=True)
    write(cases, args)


def write(cases: list, args) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    old = json.loads((OUT / "estimator.json").read_text()) if args.from_json else {}
    data = {"machine": old.get("machine", f"{platform.node()} {platform.processor() or platform.machine()} "
                                          f"({os.cpu_count()} cpus)"),
            "date": old.get("date", datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")),
            "setup": f"Coarse_beam (97 vertices, 204 linear tets, the truth's own mesh) synth with markers (30, σ 0.2 mm), truth with "
                     f"{args.substeps} substeps/frame, adapt full space, markers, w = {W}, E_init = E0/2",
            "cases": cases}
    (OUT / "estimator.json").write_text(json.dumps(data, indent=1))
    groups: dict = {}
    for c in cases:
        groups.setdefault((c["case"], c["estimator"], c["process_noise"]), []).append(c)
    lines = [f"# Estimator: Gauss–Newton vs Adam ({data['date']})", "", data["setup"] + ".", "",
             "| case | estimator | process noise | runs | median settled error | max settled error | settled within ±3 % | "
             "frames to stay within 5 % per segment: median (runs ≤ w + 5) | truth within ±2σ | s/frame |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (case, est, q), rows in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1], kv[0][2] or 0)):
        seg = len(rows[0]["settle_frames"])
        sf = []
        for i in range(seg):  # median over runs (a run that never settles counts as ∞), and runs within w + 5
            v = [np.inf if r["settle_frames"][i] is None else r["settle_frames"][i] for r in rows]
            med = np.median(v)
            ok = sum(x <= W + 5 for x in v)
            sf.append(f"{'never' if not np.isfinite(med) else f'{med:.0f}'} ({ok}/{len(v)} ≤ {W + 5})")
        cal = [r["truth_within_2sigma"] for r in rows if "truth_within_2sigma" in r]
        lines.append(f"| {case} | {est} | {'' if q is None else q} | {len(rows)} | "
                     f"{np.median([r['median_abs_err_settled'] for r in rows]):.2%} | "
                     f"{np.max([r['max_abs_err_settled'] for r in rows]):.2%} | "
                     f"{np.mean([r['within_3pct_settled'] for r in rows]):.0%} | {' / '.join(sf)} | "
                     f"{'' if not cal else f'{np.mean(cal):.0%}'} | "
                     f"{np.median([r['s_per_frame'] for r in rows]):.3f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "estimator.md").write_text(text)
    plot(cases)


def plot(cases: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=False)
    for ax, case in zip(axes, ("constant", "steps x2 x4")):
        rows = [c for c in cases if c["case"] == case and c["seed"] == 0 and c["scene"] == cases[0]["scene"]]
        for r in rows:
            e = np.asarray(r["young_rel"])
            t = np.arange(len(e))
            line, = ax.plot(t, e, label=f"{r['estimator']}" + ("" if r["process_noise"] is None
                                                                 else f" q={r['process_noise']}"))
            sd = np.asarray(r["sigma_rel"])
            if np.all(np.isfinite(sd)):
                ax.fill_between(t, e - sd, e + sd, color=line.get_color(), alpha=0.25, lw=0)
        ax.axhline(1.0, color="k", lw=0.8, ls="--", label="truth")
        ax.set_yscale("log")
        ax.set_ylim(0.3, 3.0)
        ax.set_title(f"{rows[0]['scene'] if rows else ''}, {case}: E / E_true (band ±σ)")
        ax.set_xlabel("frame")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "estimator.png", dpi=110)


if __name__ == "__main__":
    main()
