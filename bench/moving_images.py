"""Captures filmed mid-motion seen by cameras alone (`[capture] start = "moving"`, `rsl adapt --loss vision`): where
`rsl fit-gaussians` poses frame 0 — from its masks (stages.moving_start.silhouette_pose, the default) or at the
equilibrium of capture.toml's E (what it did before) — and what E rsl adapt then identifies, in the same run.

Captures by `rsl synth` of the cable-pulled beam of tests/test_adapt_e2e (shared/data/autodef_fulton/Coarse_beam.mesh,
E_true = 1e5 Pa, ν = 0.45), filmed from 8 frames after its equilibrium start (`--start moving --lead-frames 8`), 16
frames, C cameras at R², on the truth's own P1 mesh: only the start and the pose are unknown, so the rows isolate
them (bench/accuracy.py's row "bar moving vision" is the capture rsl did not make).  capture.toml's E is set to
k × E_true (k = 0.5, 1, 2: a lab's guess of the material), which moves the equilibrium the pose starts from.  Per
capture: rsl segment (the plates), then per pose rsl fit-gaussians (2000 Gaussians, 200 iterations) and rsl adapt
(gn, images, full space, window 3, E initialised at 0.5 E_true, 1 substep: the truth's).  Per row: the frame-0 pose's
RMS distance to the truth's frame-0 surface, the median relative error of E over the settled frames (≥ w + 5), the
range of E / E_true there, ν at the end, the largest surface error over the frames, and the seconds of the pose
and of fit-gaussians.

    nice .venv/bin/python bench/moving_images.py [--cameras 1,2] [--guesses 0.5,1,2] [--sag-priors 0.4,2.3]
        [--resolution 64] [--work /tmp/rsl_moving_images] [--out docs/results]
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
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

BEAM = ROOT.parent / "shared" / "data" / "autodef_fulton" / "Coarse_beam.mesh"
E_TRUE = 1.0e5
WINDOW = 3
LEAD = 8
FRAMES = 16


def capture(work: Path, cameras: int, guess: float, resolution: int) -> tuple[Path, Path]:
    """The capture (its capture.toml's E at ``guess`` × E_true) and a workspace with mesh, cameras and masks."""
    from stages.steps import calibrate, segment, synth, tetrahedralize

    root = work / f"c{cameras}_k{guess:g}"
    cap, ws = root / "cap", root / "ws"
    if (ws / "masks.h5").exists():
        return cap, ws
    shutil.rmtree(root, ignore_errors=True)
    synth.run(synth.SynthConfig(mesh=BEAM, out=cap, scenario="cable", cameras=cameras, frames=FRAMES,
                                resolution=resolution, young=E_TRUE, markers=30, calib_views=0, seed=0,
                                start="moving", lead_frames=LEAD))
    toml = cap / "capture.toml"
    text = toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"')
    toml.write_text(re.sub(r"^young = [\d.e+-]+", f"young = {guess * E_TRUE:g}", text, count=1, flags=re.M))
    tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1))
    calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")))
    segment.run(segment.SegmentConfig(capture=cap, workspace=ws))
    return cap, ws


def run_pose(cap: Path, ws: Path, out: Path, pose: str, prior: float | None) -> dict:
    """fit-gaussians with frame 0 posed by ``pose`` ("silhouette" with POSE_SAG_PRIOR ``prior``, or "equilibrium")
    in a copy of ``ws`` at ``out``, then rsl adapt; the row."""
    import stages.moving_start as ms
    from stages.artefacts import AdaptArtefact, GaussiansArtefact, MeshArtefact
    from stages.steps import adapt, fit_gaussians

    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for f in ("mesh.h5", "cameras.h5", "masks.h5"):
        shutil.copy(ws / f, out / f)
    default_prior, silhouette_pose = ms.POSE_SAG_PRIOR, fit_gaussians.silhouette_pose
    pose_s = [0.0]

    def timed_pose(*a, **k):
        t = time.perf_counter()
        result = silhouette_pose(*a, **k) if pose == "silhouette" else equilibrium_pose(*a, **k)
        pose_s[0] = time.perf_counter() - t
        return result
    try:
        ms.POSE_SAG_PRIOR = default_prior if prior is None else prior
        fit_gaussians.silhouette_pose = timed_pose  # (what fit_pose calls)
        t = time.perf_counter()
        fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=out, gaussians=2000, iterations=200))
        fit_s = time.perf_counter() - t
    finally:
        ms.POSE_SAG_PRIOR, fit_gaussians.silhouette_pose = default_prior, silhouette_pose
    t = time.perf_counter()
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(capture=cap, workspace=out, loss="vision", window=WINDOW,
                                                         estimator="gn", space="full", young_init=0.5 * E_TRUE,
                                                         substeps=1)))
    adapt_s = time.perf_counter() - t
    ids = np.unique(MeshArtefact.load(out / "mesh.h5").surface_faces)
    truth = np.load(cap / "truth" / "surface.npz")["vertices"]
    g = GaussiansArtefact.load(out / "gaussians.h5")
    pose_err = float(np.sqrt(np.mean(np.sum((g.fit_positions[ids] - truth[0]) ** 2, axis=-1))))
    surf = np.sqrt(np.mean(np.sum((art.positions[:, ids] - truth[art.frames]) ** 2, axis=-1), axis=1))
    ratio = art.young[:, 0] / E_TRUE
    settled = ratio[WINDOW + 5:]
    return {"pose": pose, "sag_prior": ms.POSE_SAG_PRIOR if prior is None else prior,
            "fit_state_start": g.fit_state.get("start"), "pose_error_mm": 1e3 * pose_err,
            "median_E_error_pct": float(100 * np.median(np.abs(settled - 1))),
            "settled_E_ratio": [float(settled.min()), float(settled.max())], "nu_final": float(art.poisson[-1, 0]),
            "max_surface_error_mm": float(1e3 * surf.max()), "E_ratio": ratio.tolist(),
            "pose_s": pose_s[0], "fit_gaussians_s": fit_s, "adapt_s": adapt_s}


def equilibrium_pose(capture, ws, mesh, young, poisson, frame: int = 0, **_) -> tuple[np.ndarray, dict]:
    """The "equilibrium" rows' stand-in for silhouette_pose: frame 0 at the static equilibrium of capture.toml's E
    and ν under the frame-0 controls, the masks not looked at (the Gaussians are still fitted against them)."""
    from stages.sim.scene import frame_inputs, make_scene
    from stages.sim.static import start_state

    controls = capture.controls()
    scene = make_scene(mesh, controls, capture.material.model, capture.dt, capture.gravity)
    x = start_state(scene, frame_inputs(scene, controls, frame), young, poisson, "equilibrium")
    return np.asarray(x), {"pose": "capture", "start": "equilibrium", "declared_start": "moving", "frame": frame,
                           "young": list(map(float, young)), "poisson": list(map(float, poisson))}


def write(rows: list[dict], out: Path, plan: dict) -> None:
    """moving_images.md / .json (and .png: E / E_true over the frames) from the measured rows."""
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    machine = f"{platform.node() or 'machine'} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}"
    (out / "moving_images.json").write_text(json.dumps({"plan": plan, "rows": rows, "ended": stamp,
                                                        "machine": machine}, indent=1))
    md = ["# A capture filmed mid-motion, images only: where frame 0 is posed", "",
          f"Beam pulled by a cable (tests/test_adapt_e2e), filmed from {LEAD} frames after its equilibrium start, "
          f"{FRAMES} frames at {plan['resolution']}², E_true = {E_TRUE:g} Pa, ν = 0.45, truth on its own P1 mesh "
          f"(only the start and the pose unknown). capture.toml's E = k × E_true. rsl fit-gaussians (2000 Gaussians, "
          f"200 iterations) with frame 0 posed from the masks (silhouette: the sag of E_s = e^q E, σ_q the prior of "
          f"q, and {plan['pose_modes']} vibration modes within {plan['pose_motion_frames']:g} frame(s) of the masks' "
          f"motion) or at the equilibrium of capture.toml's E; rsl adapt gn, images, full space, window {WINDOW}, "
          f"from 0.5 E_true. "
          f"Settled: frames ≥ {WINDOW + 5}.", "",
          "| cameras | k | frame-0 pose | σ_q | pose error (mm) | median settled E error (%) | settled E / E_true "
          "| ν at the end | largest surface error (mm) | pose (s) | fit-gaussians (s) | adapt (s) |",
          "| ---: | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lo, hi = r["settled_E_ratio"]
        sq = "–" if r["pose"] == "equilibrium" else format(r["sag_prior"], ".2g")
        md.append(f"| {r['cameras']} | {r['guess']:g} | {r['pose']} | {sq} | {r['pose_error_mm']:.2f} | "
                  f"{r['median_E_error_pct']:.1f} | {lo:.2f}–{hi:.2f} | {r['nu_final']:.3f} | "
                  f"{r['max_surface_error_mm']:.2f} | {r['pose_s']:.1f} | {r['fit_gaussians_s']:.1f} | "
                  f"{r['adapt_s']:.1f} |")
    default = [r for r in rows if r["pose"] == "silhouette" and r["sag_prior"] == plan["default_prior"]]
    base = {(r["cameras"], r["guess"]): r for r in rows if r["pose"] == "equilibrium"}
    pairs = [(r, base[(r["cameras"], r["guess"])]) for r in default if (r["cameras"], r["guess"]) in base]
    if pairs:
        md += ["", "Median settled E error, frame 0 posed from the masks (default σ_q) against at the equilibrium "
               "of capture.toml's E, per capture: " + "; ".join(
                   f"{r['cameras']} camera(s), k = {r['guess']:g}: {r['median_E_error_pct']:.1f} % against "
                   f"{b['median_E_error_pct']:.1f} %" for r, b in pairs) + "."]
    if plot(rows, out / "moving_images.png"):
        md += ["", "![E over the frames](moving_images.png)"]
    md += ["", f"Ended {stamp} on {machine}. Produced by `bench/moving_images.py`."]
    (out / "moving_images.md").write_text("\n".join(md) + "\n")


def plot(rows: list[dict], path: Path) -> bool:
    """E / E_true over the frames, one line per row (solid: posed from the masks; dashed: at the equilibrium)."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for r in rows:
        style = "-" if r["pose"] == "silhouette" else "--"
        prior = "" if r["pose"] == "equilibrium" else f", σ_q {r['sag_prior']:.2g}"
        ax.plot(r["E_ratio"], style, label=f"{r['cameras']} cam, k = {r['guess']:g}, {r['pose']}{prior}")
    ax.axhline(1.0, color="k", lw=0.8)
    ax.axvline(WINDOW + 5, color="0.6", lw=0.8, ls=":")
    ax.set_xlabel("frame")
    ax.set_ylabel("E / E_true")
    ax.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", default="1,2")
    ap.add_argument("--guesses", default="0.5,1,2", help="capture.toml's E as multiples of E_true")
    ap.add_argument("--sag-priors", default="0.4,2.3", help="other POSE_SAG_PRIOR values (σ of log E_s), on the "
                    "1-camera k = 0.5 capture")
    ap.add_argument("--resolution", type=int, default=64)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_moving_images"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    a = ap.parse_args()
    import stages.moving_start as ms

    if not BEAM.is_file():
        raise SystemExit(f"{BEAM}: not found (the shared data).")
    plan = {"cameras": [int(c) for c in a.cameras.split(",")], "guesses": [float(k) for k in a.guesses.split(",")],
            "priors": [float(p) for p in a.sag_priors.split(",") if p], "resolution": a.resolution,
            "default_prior": ms.POSE_SAG_PRIOR, "pose_modes": ms.POSE_MODES,
            "pose_motion_frames": ms.POSE_MOTION_FRAMES}
    rows = []
    for cams in plan["cameras"]:
        for k in plan["guesses"]:
            cap, ws = capture(a.work, cams, k, a.resolution)
            variants = [("silhouette", None), ("equilibrium", None)]
            if cams == min(plan["cameras"]) and k == min(plan["guesses"]):
                variants += [("silhouette", p) for p in plan["priors"]]
            for pose, prior in variants:
                name = f"{pose}" + ("" if prior is None else f"_{prior:g}")
                row = {"cameras": cams, "guess": k, **run_pose(cap, ws, ws.parent / name, pose, prior)}
                rows.append(row)
                print(f"{cams} cam k={k:g} {name}: pose {row['pose_error_mm']:.2f} mm, E error "
                      f"{row['median_E_error_pct']:.1f} % ({row['settled_E_ratio'][0]:.2f}–"
                      f"{row['settled_E_ratio'][1]:.2f}), surface ≤ {row['max_surface_error_mm']:.2f} mm", flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    write(rows, a.out, plan)
    print(f"wrote {a.out / 'moving_images.md'}")


if __name__ == "__main__":
    main()
