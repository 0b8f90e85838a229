"""Vision bias: is the image loss lowest at the true E on a capture rsl did not make, and does online
identification from images reach it?

A capture like the demo's (docs/demo.sh) is made by `rsl synth` from sample_data/bar: a cable pulls the free end
of the bar held by a hard clamp, frame 0 shows the bar sagging in its static equilibrium, the truth is simulated
on quadratic tets with 2 implicit substeps per frame, constant E = E_true.  The pipeline makes rsl's own model of
it (calibrate --from-json, tetrahedralize --order 2, segment, fit-gaussians).  Over a grid of fixed E (ν held at
the truth's) the whole-sequence loss is computed (stages/sweep.py: full-space simulation from the declared start,
Gaussians re-bound to the simulated fit frame), one row per cause switched on or off:

* the Gaussians fitted with the mesh at rest (fit-gaussians --pose rest) vs posed as frame 0 shows it;
* adapt's dynamics (1 implicit step per frame) vs the truth's (2 substeps), and the marker loss on the same mesh
  and dynamics (what is left is the dynamics' bias, not the images');
* segmentation masks vs the truth's masks; the photometric L1 vs the mask (coverage) term alone;
* the loss's own renderer (stages.render.image_loss.ImageLoss.images) vs BoundGaussians.render (fit-gaussians'
  renderer, fused projection) — the Gaussians rendered without re-binding;
* 3 cameras and 1 camera.

Then the gradient the online estimators follow (dL/dlog E at 0.8 E_true, whole sequence): the adjoint with the
anchor x_f(θ) held fixed (as rsl adapt did), with the anchor's part (as it does now), and the slope of the swept
loss.  Finally `rsl adapt --loss vision` online in full space from 0.4 E_true (--estimators).

    nice .venv/bin/python bench/vision_bias.py [--quick] [--estimators adam[,gn]] [--out docs/results]

With RSL_BENCH_REUSE=1 the capture, workspaces and simulations already in --work are reused.

    nice .venv/bin/python bench/vision_bias.py --anchor-study step:full:estimated,step:full:simulated,...

adds online Adam runs per Gaussians' anchor rule (rsl adapt --vision-anchor, "estimated@C": --anchor-change C) on
bench/accuracy.py's vision bar whose E steps ×2 and ×4 ("step", made through bench/_pipeline.py) and on the
constant-E capture above ("const") to an earlier run's vision_bias.json/.md (RSL_BENCH_REUSE=1 reuses finished runs).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402

E_TRUE = 1.0e5
POISSON = 0.45


def prepare(work: Path, frames: int, resolution: int, max_tets: int, reuse: bool) -> tuple[Path, dict]:
    """The capture and two workspaces (Gaussians posed at frame 0 / at rest) sharing mesh, cameras and masks."""
    cap, ws, ws_rest = work / "cap", work / "ws", work / "ws_rest"
    if reuse and (ws / "gaussians.h5").is_file() and (ws_rest / "gaussians.h5").is_file():
        return cap, {"capture": str(cap), "reused": True}
    for d in (ws, ws_rest):
        shutil.rmtree(d, ignore_errors=True)
    t = {}
    if not (reuse and (cap / "capture.toml").is_file()):
        t["synth_s"] = pl.rsl("synth", ROOT / "sample_data/bar/object.mesh", cap, "--scenario", "cable", "--cameras", 3,
                           "--frames", frames, "--resolution", resolution, "--markers", 40, "--calib-views", 0,
                           "--young", E_TRUE, "--poisson", POISSON, "--start", "equilibrium", "--truth-order", 2,
                           "--substeps", 2, "--handles", "hard", "--size", 0.25, "--seed", 0, "--overwrite")
    t["calibrate_s"] = pl.rsl("calibrate", cap, "-w", ws, "--from-json", cap / "cameras.json")
    t["tetrahedralize_s"] = pl.rsl("tetrahedralize", cap, "-w", ws, "--order", 2, "--max-tets", max_tets)
    t["segment_s"] = pl.rsl("segment", cap, "-w", ws, "--method", "background")
    t["fit_s"] = pl.rsl("fit-gaussians", cap, "-w", ws, "--frame", 0)
    ws_rest.mkdir(parents=True)
    for f in ("mesh.h5", "cameras.h5", "masks.h5"):
        shutil.copy(ws / f, ws_rest / f)
    t["fit_rest_s"] = pl.rsl("fit-gaussians", cap, "-w", ws_rest, "--frame", 0, "--pose", "rest")
    return cap, t


def simulations(cap_dir: Path, ws: Path, scales, substeps: int, reuse: bool) -> dict:
    """X(E) (T, n, 3) per grid scale, full space from the declared start (stages.sweep.simulate_fixed)."""
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture
    from stages.sim.scene import make_scene
    from stages.sweep import simulate_fixed

    cap = load_capture(cap_dir)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    ctl = cap.controls()
    scene = make_scene(mesh, ctl, cap.material.model, cap.dt, cap.gravity)
    out = {}
    for s in scales:
        f = ws / f"sim_s{substeps}_{s:.4f}.npy"
        if reuse and f.is_file():
            out[s] = np.load(f)
            continue
        out[s] = simulate_fixed(scene, ctl, np.array([E_TRUE * s]), np.array([POISSON]), cap.frame_count(),
                                cap.start, substeps)
        np.save(f, out[s])
    return out


class Targets:
    """Masked frames Ĩ = I·m (+ black background, the Gaussians' with masks) and masks, per camera and frame."""

    def __init__(self, cap, masks):
        from stages.capture import read_image

        self.cap, self.masks, self.read = cap, masks, read_image
        self.cache = {}

    def truth_mask(self, c: str, t: int) -> np.ndarray:
        m = self.read(self.cap.root / "truth" / "masks" / c / f"{t:06d}.png")
        return (m[..., 0] if m.ndim == 3 else m) > 127

    def mask(self, c: str, t: int, kind: str) -> np.ndarray:
        return self.masks[c][t] if kind == "segment" else self.truth_mask(c, t)

    def image(self, c: str, t: int, kind: str) -> np.ndarray:
        if (c, t, kind) not in self.cache:
            img = self.read(self.cap.frame_source(c).files[t]).astype(np.float32) / 255.0
            self.cache[c, t, kind] = img * self.mask(c, t, kind)[..., None].astype(np.float32)
        return self.cache[c, t, kind]


def vision_curve(ws: Path, cap, X: dict, cams: list[str], masks: str = "segment", term: str = "photometric",
                 renderer: str = "loss") -> np.ndarray:
    """Whole-sequence loss per grid scale (K,): renderer "loss" = ImageLoss with the rebind anchor (rsl adapt's),
    "bound" = BoundGaussians.render as fitted (no re-binding); term "photometric" (L1 of the masked image) or
    "mask" (L1 of coverage − mask, BoundGaussians only)."""
    import torch

    from stages.render.image_loss import ImageLoss
    from stages.artefacts import CamerasArtefact, GaussiansArtefact, MasksArtefact, MeshArtefact
    from stages.render.gaussians import BoundGaussians

    mesh = MeshArtefact.load(ws / "mesh.h5")
    ca = CamerasArtefact.load(ws / "cameras.h5")
    gauss = GaussiansArtefact.load(ws / "gaussians.h5")
    tg = Targets(cap, MasksArtefact.load(ws / "masks.h5").masks)
    cam_objs = [ca.by_name(c) for c in cams]
    out = []
    if renderer == "loss":  # ImageLoss's value, rendered without its gradient (ImageLoss.render)
        il = ImageLoss(gauss, mesh, cam_objs)
        for s, Xs in X.items():
            il.rebind(Xs[0])
            out.append(sum(float(np.abs(r - tg.image(c, t, masks)).sum())
                           for t in range(1, len(Xs)) for c, r in zip(cams, il.render(Xs[t]))))
        return np.array(out)
    g = BoundGaussians.from_artefact(gauss, mesh)
    with torch.no_grad():
        for s, Xs in X.items():
            total = 0.0
            for t in range(1, len(Xs)):
                x = torch.as_tensor(Xs[t], dtype=torch.float32)
                for c, cam in zip(cams, cam_objs):
                    r = g.render(x, cam)
                    if term == "mask":
                        total += float((r.alpha - torch.as_tensor(tg.mask(c, t, masks), dtype=torch.float32)).abs().sum())
                    else:
                        total += float((r.image - torch.as_tensor(tg.image(c, t, masks))).abs().sum())
            out.append(total)
    return np.array(out)


def marker_curve(ws: Path, cap, X: dict) -> np.ndarray:
    from stages.sim.markers import bind_markers, marker_residuals
    from stages.artefacts import MeshArtefact

    faces = np.asarray(MeshArtefact.load(ws / "mesh.h5").surface_faces)
    P = cap.markers()
    out = []
    for s, Xs in X.items():
        r = marker_residuals(bind_markers(Xs[0], faces, P[0]), Xs, P[:len(Xs)])
        out.append(float(np.sum(r * r)))
    return np.array(out)


def gradients(ws: Path, cap, X: dict, lo: float, mid: float, hi: float, cams: list[str]) -> dict:
    """dL/dlog E of the whole-sequence vision loss at E = mid·E_true: the slope of the swept loss (central
    difference over [lo, hi]), the adjoint with the anchor held (Σ_t dL/dX_t · dX_t/dlog E) and with the anchor's
    part (+ dL/dx_0 · dx_0/dlog E), dX/dlog E from the same two simulations."""
    from stages.render.image_loss import ImageLoss
    from stages.artefacts import CamerasArtefact, GaussiansArtefact, MasksArtefact, MeshArtefact

    mesh = MeshArtefact.load(ws / "mesh.h5")
    ca = CamerasArtefact.load(ws / "cameras.h5")
    il = ImageLoss(GaussiansArtefact.load(ws / "gaussians.h5"), mesh, [ca.by_name(c) for c in cams])
    tg = Targets(cap, MasksArtefact.load(ws / "masks.h5").masks)
    dl = np.log(hi) - np.log(lo)
    dX = (X[hi] - X[lo]) / dl

    def total(s):
        il.rebind(X[s][0])
        return sum(il(X[s][t], [tg.image(c, t, "segment") for c in cams])[0] for t in range(1, len(X[s])))

    slope = (total(hi) - total(lo)) / dl
    il.rebind(X[mid][0])
    held = anchor = 0.0
    for t in range(1, len(X[mid])):
        _, g, ga = il(X[mid][t], [tg.image(c, t, "segment") for c in cams], anchor_grad=True)
        held += float(np.sum(g * dX[t]))
        anchor += float(np.sum(ga * dX[0]))
    return {"at": mid, "slope_of_swept_loss": slope, "adjoint_anchor_held": held,
            "adjoint_with_anchor": held + anchor}


def online(cap: Path, ws: Path, work: Path, estimator: str, young_init: float, window: int) -> dict:
    import h5py

    from stages.artefacts import PARTIAL_ADAPT, AdaptArtefact

    wd = work / f"ws_online_{estimator}"
    failed = None
    done = [wd / n for n in ("adapt.h5", PARTIAL_ADAPT) if (wd / n).is_file()]
    if os.environ.get("RSL_BENCH_REUSE") and done:  # an earlier run's record (complete or stopped)
        with h5py.File(done[0], "r") as f:
            seconds = float(f.attrs.get("wall_s", float("nan")))
        if done[0].name == PARTIAL_ADAPT:
            failed = "the run stopped early (adapt.partial.h5)"
    else:
        shutil.rmtree(wd, ignore_errors=True)
        wd.mkdir(parents=True)
        for f in ("mesh.h5", "cameras.h5", "masks.h5", "gaussians.h5"):
            shutil.copy(ws / f, wd / f)
        t0 = time.perf_counter()
        try:
            est, _, sub = estimator.partition("+s")  # "adam+s2": adam with --substeps 2
            seconds = pl.rsl("adapt", cap, "-w", wd, "--space", "full", "--loss", "vision", "--estimator", est,
                          "--young-init", young_init, "--window", window, "--substeps", sub or 1)
        except pl.RslFailed as e:  # a failed run (e.g. a collapse): what it kept, and its message
            seconds = time.perf_counter() - t0
            failed = [ln for ln in str(e).splitlines() if ln.startswith("error:")][-1:] or [str(e)[-300:]]
            failed = failed[0]
            if not (wd / PARTIAL_ADAPT).is_file():
                return {"estimator": estimator, "young_init": young_init, "window": window, "frames": 0,
                        "young_over_true": [], "poisson": [], "settled_from": 0, "median_settled_error": float("nan"),
                        "final_over_true": float("nan"), "seconds": seconds, "failed": failed}
    a = AdaptArtefact.load(wd / ("adapt.h5" if failed is None else PARTIAL_ADAPT), allow_partial=True)
    e = a.young[:, 0] / E_TRUE
    settled = e[len(e) // 4:]
    return {"estimator": estimator, "young_init": young_init, "window": window, "frames": int(len(e)),
            "young_over_true": e.round(4).tolist(), "poisson": a.poisson[:, 0].round(4).tolist(),
            "settled_from": int(len(e) // 4), "median_settled_error": float(np.median(np.abs(settled - 1))),
            "final_over_true": float(e[-1]), "seconds": seconds, "failed": failed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="16 frames at 64 px (a smoke run)")
    ap.add_argument("--estimators", default="adam",
                    help="online runs, comma-separated: adam, gn, adam+s2 (adam with --substeps 2), ...; empty: none")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_vision_bias"))
    ap.add_argument("--online-only", action="store_true",
                    help="only the online runs, added to --out/vision_bias.json of an earlier run (same --work)")
    ap.add_argument("--anchor-study", default="",
                    help="only the anchor rows, added to --out/vision_bias.json of an earlier run: comma-separated "
                         "CASE:SPACE:ANCHOR, CASE step (accuracy.py's bar, E ×2 at T/3, ×4 at 2T/3) or const (this "
                         "capture), SPACE full|reduced, ANCHOR estimated|simulated (rsl adapt --vision-anchor), "
                         "estimated@C adds --anchor-change C")
    a = ap.parse_args()
    if a.anchor_study:
        return anchor_study(a)
    if a.online_only:
        return online_only(a)
    from stages.capture import load_capture
    from stages.sweep import parabolic_minimum

    reuse = bool(os.environ.get("RSL_BENCH_REUSE"))
    frames, res = (16, 64) if a.quick else (20, 96)
    scales = [0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.35] if a.quick else [0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.3]
    a.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    cap_dir, prep = prepare(a.work, frames, res, 800, reuse)
    cap = load_capture(cap_dir)
    ws, ws_rest = a.work / "ws", a.work / "ws_rest"
    print(f"pipeline: {prep}", flush=True)
    X1 = simulations(cap_dir, ws, scales, 1, reuse)
    X2 = simulations(cap_dir, ws, scales, 2, reuse)
    print(f"simulations done at {time.perf_counter() - t0:.0f} s", flush=True)
    three, one = list(cap.camera_names), [cap.camera_names[0]]
    rows = []

    def row(cause, loss, dyn, cams, curve, **kw):
        t1 = time.perf_counter()
        y = curve()
        lm, i, interior = parabolic_minimum(np.log(scales), y)
        rows.append({"cause": cause, "loss": loss, "dynamics": dyn, "cameras": len(cams),
                     "ratio": float(np.exp(lm)), "interior": bool(interior), "grid": [E_TRUE * s for s in scales],
                     "loss_values": y.tolist(), "seconds": time.perf_counter() - t1, **kw})
        print(_row(rows[-1]), flush=True)

    cams = three
    row("Gaussians fitted at rest (--pose rest)", "vision", "1 step/frame", cams,
        lambda: vision_curve(ws_rest, cap, X1, cams))
    row("Gaussians posed at frame 0 (default), adapt's dynamics", "vision", "1 step/frame", cams,
        lambda: vision_curve(ws, cap, X1, cams))
    row("… with the truth's dynamics (2 substeps)", "vision", "2 substeps", cams,
        lambda: vision_curve(ws, cap, X2, cams))
    row("… truth masks instead of segment's", "vision", "2 substeps", cams,
        lambda: vision_curve(ws, cap, X2, cams, masks="truth"))
    row("… BoundGaussians.render (fit-gaussians' renderer), not re-bound", "vision", "2 substeps", cams,
        lambda: vision_curve(ws, cap, X2, cams, renderer="bound"))
    row("… mask (coverage) term alone", "vision (mask)", "2 substeps", cams,
        lambda: vision_curve(ws, cap, X2, cams, renderer="bound", term="mask"))
    cams = one
    row("Gaussians posed at frame 0 (default), adapt's dynamics", "vision", "1 step/frame", cams,
        lambda: vision_curve(ws, cap, X1, cams))
    row("… with the truth's dynamics (2 substeps)", "vision", "2 substeps", cams,
        lambda: vision_curve(ws, cap, X2, cams))
    row("markers on the same mesh, adapt's dynamics", "markers", "1 step/frame", [], lambda: marker_curve(ws, cap, X1))
    row("markers on the same mesh, the truth's dynamics", "markers", "2 substeps", [],
        lambda: marker_curve(ws, cap, X2))
    grad = gradients(ws, cap, X2, 0.7, 0.8, 0.9, three)
    print(f"gradient: {grad}", flush=True)
    runs = []
    write(rows, grad, runs, prep, a.out, a.quick, frames, res, time.perf_counter() - t0)  # kept if stopped later
    for est in [e for e in a.estimators.split(",") if e]:
        runs.append(online(cap_dir, ws, a.work, est, 0.4 * E_TRUE, 3))
        print(f"online {est}: median settled |E/E_true − 1| = {runs[-1]['median_settled_error']:.3f}", flush=True)
        write(rows, grad, runs, prep, a.out, a.quick, frames, res, time.perf_counter() - t0)


def online_only(a) -> None:
    """The online runs of --estimators on the capture of an earlier run; its vision_bias.json gains them (read
    again before writing, so that runs of other estimators finished meanwhile are kept)."""
    t0 = time.perf_counter()
    cap_dir, ws = a.work / "cap", a.work / "ws"
    for est in [e for e in a.estimators.split(",") if e]:
        run = online(cap_dir, ws, a.work, est, 0.4 * E_TRUE, 3)
        print(f"online {est}: median settled |E/E_true − 1| = {run['median_settled_error']:.3f}", flush=True)
        d = json.loads((a.out / "vision_bias.json").read_text())
        runs = [r for r in d["online"] if r["estimator"] != est] + [run]
        write(d["cases"], d["gradient"], runs, d["pipeline"], a.out, d["mode"] == "quick", d["frames"],
              d["resolution"], d["seconds"] + time.perf_counter() - t0)


STEP_FRAMES = 36  # bench/accuracy.py's bar: E0 → 2E0 at frame 12 → 4E0 at frame 24


def _step_case(work: Path) -> tuple[Path, Path]:
    """bench/accuracy.py's vision bar (through bench/_pipeline.py): truth P2, 3 substeps, hard handles, start =
    equilibrium, E steps ×2 and ×4; rsl's P2 mesh (--max-tets 1500), Gaussians fitted at frame 0, subspace r = 30."""
    n = STEP_FRAMES
    cap = pl.foreign_capture(work / "bar_equilibrium", pl.bar_cable(
        schedule=f"{E_TRUE:g}@0,{2 * E_TRUE:g}@{n // 3},{4 * E_TRUE:g}@{2 * n // 3}"), start="equilibrium", frames=n,
        cameras=3, resolution=96, substeps=3, poisson=POISSON)
    ws = pl.mesh(cap, work / "ws_bar_equilibrium_p2", order=2, max_tets=1500)
    pl.gaussians(cap, ws, frame=0)
    return cap, ws


def _settled(young_true: np.ndarray, window: int, const: bool) -> np.ndarray:
    """Frames counted as settled: constant E, frames ≥ T/4 (the online rows above); E steps, bench/accuracy.py's
    rule (frames ≥ w + 5 after the start and after each change of E_true)."""
    T = len(young_true)
    ok = np.ones(T, bool)
    if const:
        ok[: T // 4] = False
        return ok
    ok[: window + 5] = False
    for t in range(1, T):
        if young_true[t] != young_true[t - 1]:
            ok[t: t + window + 5] = False
    return ok


def anchor_run(case: str, space: str, anchor: str, work: Path, window: int = 3) -> dict:
    """One `rsl adapt --loss vision --estimator adam --vision-anchor ANCHOR` run (reused from WORK/anchor_CASE_SPACE_
    ANCHOR with RSL_BENCH_REUSE): E/E_true per frame, the anchor's E, the median settled error."""
    import h5py

    from stages.artefacts import PARTIAL_ADAPT, AdaptArtefact
    from stages.capture import load_capture, read_truth

    if case == "step":
        cap, ws = _step_case(work)
        young_init = 0.5 * E_TRUE
    else:
        cap, ws = work / "cap", work / "ws"
        young_init = 0.4 * E_TRUE
    wd = work / f"anchor_{case}_{space}_{anchor}"
    done = [wd / n for n in ("adapt.h5", PARTIAL_ADAPT) if (wd / n).is_file()]
    failed = None
    if os.environ.get("RSL_BENCH_REUSE") and done:
        with h5py.File(done[0], "r") as f:
            seconds = float(f.attrs.get("wall_s", float("nan")))
        failed = "stopped early (adapt.partial.h5)" if done[0].name == PARTIAL_ADAPT else None
    else:
        if space == "reduced" and not (ws / "subspace.h5").is_file():
            pl.subspace(cap, ws, frames=load_capture(cap).frame_count(), dim=30)
        shutil.rmtree(wd, ignore_errors=True)
        wd.mkdir(parents=True)
        for f in ("mesh.h5", "cameras.h5", "masks.h5", "gaussians.h5", "subspace.h5"):
            if (ws / f).is_file():
                shutil.copy(ws / f, wd / f)
        t0 = time.perf_counter()
        rule, _, change = anchor.partition("@")  # "estimated@0": --anchor-change 0
        try:
            seconds = pl.rsl("adapt", cap, "-w", wd, "--space", space, "--loss", "vision", "--estimator", "adam",
                          "--young-init", young_init, "--window", window, "--vision-anchor", rule,
                          *(["--anchor-change", change] if change else []))
        except pl.RslFailed as e:
            seconds, failed = time.perf_counter() - t0, str(e).splitlines()[-1][-300:]
            done = [wd / PARTIAL_ADAPT] if (wd / PARTIAL_ADAPT).is_file() else []
            if not done:
                return {"case": case, "space": space, "anchor": anchor, "failed": failed, "seconds": seconds}
        done = done or [wd / "adapt.h5"]
    a = AdaptArtefact.load(done[0], allow_partial=True)
    truth = read_truth(load_capture(cap))
    yt = truth.young[np.asarray(a.frames)][:, 0]
    e = a.young[:, 0] / yt
    ok = _settled(yt, window, case == "const")
    anchor_e = [row[0] for row in (a.extra.get("anchor_young") or [])]
    return {"case": case, "space": space, "anchor": anchor, "young_init": young_init, "window": window,
            "frames": int(len(e)), "young_over_true": e.round(4).tolist(), "young_true": yt.tolist(),
            "anchor_young_over_true0": (np.asarray(anchor_e) / yt[0]).round(4).tolist(),
            "anchor_apart_from": a.extra.get("anchor_apart_from", "not recorded"),  # None: never
            "anchor_tests": a.extra.get("anchor_tests", "not recorded"),  # [frame, loss at level, at p, change?]
            "settled_frames": int(ok.sum()), "median_settled_error": float(np.median(np.abs(e[ok] - 1))),
            "final_over_true": float(e[-1]), "seconds": seconds, "failed": failed}


def anchor_study(a) -> None:
    """The anchor rows of --anchor-study, added to (replacing rows of the same case, space and anchor in) the
    vision_bias.json of an earlier run; vision_bias.md is written again (its whole-run time stays the earlier
    run's: each anchor row has its own seconds)."""
    for spec in [s for s in a.anchor_study.split(",") if s]:
        case, space, anchor = spec.split(":")
        run = anchor_run(case, space, anchor, a.work)
        print(f"anchor {spec}: median settled |E/E_true − 1| = {run.get('median_settled_error', float('nan')):.3f}",
              flush=True)
        d = json.loads((a.out / "vision_bias.json").read_text())
        rows = [r for r in d.get("anchor_study", []) if (r["case"], r["space"], r["anchor"]) != (case, space, anchor)]
        write(d["cases"], d["gradient"], d["online"], d["pipeline"], a.out, d["mode"] == "quick", d["frames"],
              d["resolution"], d["seconds"], anchor_rows=rows + [run])


def _anchor_text(rows: list) -> str:
    if not rows:
        return ""
    order = {"step": 0, "const": 1}
    rows = sorted(rows, key=lambda r: (order.get(r["case"], 2), r["space"], r["anchor"]))
    what = {"step": f"E ×2 at frame {STEP_FRAMES // 3}, ×4 at {2 * STEP_FRAMES // 3} (bench/accuracy.py's vision bar, "
                    f"truth P2, 3 substeps, {STEP_FRAMES} frames)",
            "const": "constant E (the capture above)"}

    def label(a: str) -> str:
        rule, _, change = a.partition("@")
        return f"{rule} --anchor-change {change}" if change else a

    def line(r):
        if "median_settled_error" not in r:
            return f"| {what[r['case']]} | {r['space']} | {label(r['anchor'])} | — | — | — | — | — | {r.get('failed')} |"
        an = r["anchor_young_over_true0"]
        apart = r.get("anchor_apart_from")
        return (f"| {what[r['case']]} | {r['space']} | {label(r['anchor'])} | {r['young_init'] / E_TRUE:.2f} | "
                f"{100 * r['median_settled_error']:.1f} % ({r['settled_frames']} frames) | {r['final_over_true']:.3f} | "
                f"{'—' if apart is None else apart} | {f'{an[-1]:.3f}' if an else '—'} | "
                f"{r.get('failed') or 'complete'} |")
    table = "\n".join(["| capture | space | --vision-anchor | E_init / E_true | median settled \\|E/E_true − 1\\| | "
                       "final E / E_true | anchor its own unknown from frame | anchor's E / E_true(0) at the end | run |",
                       "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"] + [line(r) for r in rows])
    per = "\\\n".join(f"{r['case']} {r['space']} {r['anchor']}: " + ", ".join(f"{v:.2f}" for v in r["young_over_true"])
                      for r in rows if "young_over_true" in r)
    tests = "\\\n".join(
        f"{r['case']} {r['space']} {r['anchor']}: " + ("; ".join(
            f"frame {t[0]}: {t[1]:.4g} at the level, {t[2]:.4g} at the window's θ → "
            f"{'change' if t[3] else 'convergence'}" for t in r["anchor_tests"]) or "no candidate, no test")
        for r in rows if isinstance(r.get("anchor_tests"), list))
    tests = ("\n\nChange tests (the loss of the frames after the fit frame, simulated from the start with the "
             "level's θ and with the window's; stages/vision_anchor.py):\\\n" + tests) if tests else ""
    return ("\n\n## Online with E changing: the material of the Gaussians' anchor\n\n"
            "`rsl adapt --loss vision --estimator adam --window 3 --vision-anchor A`.  Settled frames: constant E, "
            "frames ≥ T/4; E steps, frames ≥ w + 5 after the start and after each step (bench/accuracy.py).\n\n"
            + table + "\n\nE / E_true per frame:\\\n" + per + tests)


def _row(c: dict) -> str:
    edge = "" if c["interior"] else " (grid end)"
    return (f"| {c['cause']} | {c['loss']} | {c['dynamics']} | {c['cameras'] or '—'} | {c['ratio']:.3f}{edge} | "
            f"{100 * (c['ratio'] - 1):+.1f} % |")


def write(rows, grad, runs, prep, out: Path, quick: bool, frames: int, res: int, seconds: float,
          anchor_rows: list | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "mode": "quick" if quick else "full", "frames": frames, "resolution": res, "young_true": E_TRUE,
            "pipeline": prep, "cases": rows, "gradient": grad, "online": runs, "seconds": seconds}
    if anchor_rows is None and (out / "vision_bias.json").is_file():  # kept from an earlier --anchor-study
        anchor_rows = json.loads((out / "vision_bias.json").read_text()).get("anchor_study")
    if anchor_rows:
        data["anchor_study"] = anchor_rows
    (out / "vision_bias.json").write_text(json.dumps(data, indent=1))
    head = ("| cause switched | loss | dynamics | cameras | E_min / E_true | bias |\n"
            "| --- | --- | --- | --- | --- | --- |")
    table = "\n".join([head] + [_row(c) for c in rows])
    vis3 = [c for c in rows if c["loss"] == "vision" and c["cameras"] == 3]
    within = [c for c in vis3 if abs(c["ratio"] - 1) <= 0.03]
    g = grad
    gtext = (f"dL/dlog E of the whole-sequence vision loss at E = {g['at']:g} E_true (3 cameras): slope of the swept "
             f"loss {g['slope_of_swept_loss']:.4g}; adjoint with the anchor x_0(θ) held fixed "
             f"{g['adjoint_anchor_held']:.4g} ({g['adjoint_anchor_held'] / g['slope_of_swept_loss']:.2f} of the "
             f"slope); adjoint with the anchor's part {g['adjoint_with_anchor']:.4g} "
             f"({g['adjoint_with_anchor'] / g['slope_of_swept_loss']:.2f} of the slope).")
    otext = ""
    if runs:
        orows = "\n".join(f"| {r['estimator']} | {r['young_init'] / E_TRUE:.2f} | {r['window']} | {r['frames']} | "
                          f"{r['median_settled_error'] * 100:.1f} % | {r['final_over_true']:.3f} | {r['seconds']:.0f} | "
                          f"{r.get('failed') or 'complete'} |" for r in runs)
        otext = ("\n\n## Online: `rsl adapt --loss vision --space full` from 0.4 E_true\n\n"
                 "| estimator | E_init / E_true | window | frames | median settled \\|E/E_true − 1\\| "
                 "(frames ≥ T/4) | final E / E_true | time (s) | run |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n"
                 + orows + "\n\nE / E_true per frame: "
                 + "; ".join(f"{r['estimator']}: " + ", ".join(f"{v:.2f}" for v in r["young_over_true"]) for r in runs))
    md = (f"# Vision bias: where the image loss is lowest, and what online identification from images reaches\n\n"
          f"Capture: `rsl synth` sample_data/bar, cable, truth P2 with 2 substeps per frame, hard clamp, start = "
          f"equilibrium, E_true = {E_TRUE:g} Pa, ν = {POISSON}, {frames} frames, 3 cameras at {res} px.  rsl's model: "
          f"calibrate --from-json, tetrahedralize --order 2 --max-tets 800, segment --method background, "
          f"fit-gaussians --frame 0.  Whole-sequence loss (frames 1–{frames - 1}) over {len(rows[0]['grid'])} fixed "
          f"E in {min(rows[0]['grid']):g}–{max(rows[0]['grid']):g} Pa, full-space simulation from the declared "
          f"start; minimum refined by a parabola in log E.  Rows marked … change one thing from the row above "
          f"them.\n\n{table}\n\n{len(within)} of {len(vis3)} three-camera vision minima lie within 3 % of E_true.\n\n"
          f"## The gradient the online estimators follow\n\n{gtext}{otext}{_anchor_text(anchor_rows or [])}\n\n"
          f"Machine: {data['machine']}; date {data['date']}; whole run {seconds / 60:.1f} min.  Produced by "
          f"`bench/vision_bias.py{' --quick' if quick else ''}`.\n\n![loss over E](vision_bias.png)\n")
    (out / "vision_bias.md").write_text(md)
    step_rows = [r for r in (anchor_rows or []) if r["case"] == "step" and "young_over_true" in r]
    ncol = 1 + bool(runs) + bool(step_rows)
    fig, axes = plt.subplots(1, ncol, figsize=(5.5 * ncol, 4), squeeze=False)
    ax = axes[0, 0]
    for c in rows:
        if c["cameras"] in (3, 0):
            y = np.asarray(c["loss_values"])
            ax.plot(np.asarray(c["grid"]) / E_TRUE, y / y.min(), "o-", ms=3, label=f"{c['cause'][:48]} ({c['loss']})")
    ax.axvline(1.0, color="k", lw=1)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("E / E_true")
    ax.set_ylabel("loss / its minimum")
    ax.set_title("whole-sequence loss (3 cameras)")
    ax.legend(fontsize=6)
    if runs:
        ax = axes[0, 1]
        for r in runs:
            ax.plot(r["young_over_true"], "o-", ms=3, label=r["estimator"])
        ax.axhline(1.0, color="k", lw=1)
        ax.set_xlabel("frame")
        ax.set_ylabel("E / E_true")
        ax.set_title("online, images, full space")
        ax.legend()
    if step_rows:
        ax = axes[0, ncol - 1]
        for r in step_rows:
            ax.plot(np.asarray(r["young_over_true"]) * np.asarray(r["young_true"]) / E_TRUE, "o-", ms=2,
                    label=f"{r['space']}, {r['anchor']}")
        ax.step(np.arange(len(step_rows[0]["young_true"])), np.asarray(step_rows[0]["young_true"]) / E_TRUE, "k",
                where="post", lw=1, label="truth")
        ax.set_yscale("log")
        ax.set_xlabel("frame")
        ax.set_ylabel("E / E_true(0)")
        ax.set_title("E steps ×2, ×4: the anchor's material")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / "vision_bias.png", dpi=110)
    print(table)


if __name__ == "__main__":
    main()
