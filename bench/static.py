"""Static single-view identification from images (issue 15): E from one camera's silhouette of an object at rest.

Captures rsl did not make: `rsl synth --scenario sag` hangs the object from a hard clamp on its end face (drawn
into the frames: an occluder), still in its static equilibrium from frame 0 on, simulated with quadratic tets on a
once-refined mesh (bench/_pipeline.py foreign_capture: --truth-order 2 --truth-refine 1), one camera, no
background plate.  rsl meshes the shipped surface anew (tetrahedralize --order 2 --max-tets 400), and per
capture.toml E (the guess: adapt's start and GrabCut's seed, 0.4 and 1.0 × E_true) and per mask source

* ``grabcut``: `rsl segment --method grabcut` (what a capture without a plate gets), seeded by the frame-0
  equilibria spanning the guess ÷3…×3;
* ``truth``: the synthetic truth's masks (truth/masks, read as a lab's masks: `rsl segment --method lab`),

`rsl adapt --space full --loss vision --fixed-poisson --poisson-init 0.45` (static by itself: the soft silhouette
of stages/silhouette.py against masks.h5, Gauss–Newton, σ from the cluster-robust sandwich over 8×8 pixel blocks
plus adapt's 2 % model-error floor and the silhouette's outline floor).  Each row: E/E_true, adapt's ±σ (and the
data part alone, both floors taken out), the outline floor and the outline offset b matched at the estimate,
whether E_true lies within ±2σ, adapt's wall time and render time per frame, the mask IoU of frame 0 against the
truth's mask.

Per object and resolution (--shifts N): the resolution floor, E from truth masks alone as the camera moves by
sub-pixel offsets (resolution_floor), against stages.silhouette.OUTLINE_PX.

Per object and resolution, the per-frame cost of the silhouette (coverage + forward mode in one direction +
reverse mode, at adapt's final positions, compiled beforehand, median of --repeats) of the sparse evaluation
against its dense twin (every triangle at every pixel of the object's box), in the same run.

    nice .venv/bin/python bench/static.py [--objects beam,bar] [--resolutions 64,96] [--guesses 0.4,1.0]
                                          [--masks grabcut,truth] [--shifts 6] [--work /tmp/rsl_static] [--merge]

With RSL_BENCH_REUSE=1 the captures, meshes and masks already in --work are reused (adapt always runs).
``--merge`` adds the rows to docs/results/static.json's (rows with the same key replaced).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402
from _timing import median_times  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
OBJECTS = {  # name -> (E_true Pa, mesh maker)
    "beam": 1.0e5,  # shared/data/autodef_fulton/Coarse_beam.mesh
    "bar": 5.0e5,  # a 0.2 × 0.04 × 0.04 m box bar (tests/test_static_identification.py's)
}
POISSON = 0.45


def _object_mesh(name: str, work: Path) -> Path:
    if name == "beam":
        return SHARED / "autodef_fulton" / "Coarse_beam.mesh"
    import meshio

    from stages.sim.meshgen import box_tets

    path = work / "bar.mesh"
    if not path.exists():
        v, t = box_tets((6, 2, 2), (0.2, 0.04, 0.04))
        meshio.write(str(path), meshio.Mesh(v, [("tetra", t)]), file_format="medit")
    return path


def capture(name: str, res: int, work: Path) -> tuple[Path, Path]:
    """The still capture of ``name`` at ``res``² and rsl's workspace with its mesh and cameras."""
    cap = pl.foreign_capture(work / f"{name}_{res}" / "cap",
                             [_object_mesh(name, work), "--scenario", "sag", "--young", OBJECTS[name], "--clamp",
                              "--no-plates"], start="equilibrium", frames=2, cameras=1, resolution=res, refine=1,
                             markers=10, poisson=POISSON)
    ws = work / f"{name}_{res}" / "ws"
    if not pl.skip(ws / "mesh.h5"):
        pl.rsl("calibrate", cap, "-w", ws, "--from-json", cap / "cameras.json")
        pl.rsl("tetrahedralize", cap, "-w", ws, "--order", 2, "--max-tets", 400, "--threads", 1)
    return cap, ws


def guess_capture(cap: Path, guess: float, e_true: float) -> Path:
    """A copy of the capture whose capture.toml says E = guess · E_true, with the truth's masks as the lab's."""
    out = cap.parent / f"cap_g{guess}"
    if not (pl.reusing() and (out / "capture.toml").exists()):
        if out.exists():
            shutil.rmtree(out)
        shutil.copytree(cap, out)
        toml = out / "capture.toml"
        text = toml.read_text()
        old = f"\nyoung = {float(e_true)}\n"
        if old not in text:
            raise RuntimeError(f"{toml}: no line 'young = {float(e_true)}' to replace")
        toml.write_text(text.replace(old, f"\nyoung = {guess * e_true}\n", 1))
        shutil.copytree(out / "truth" / "masks", out / "masks")
    return out


def mask_iou(ws: Path, cap: Path) -> float:
    """IoU of masks.h5's frame-0 mask of the first camera against truth/masks/CAM/000000.png."""
    import imageio.v3 as iio

    from stages.artefacts import MasksArtefact

    masks = MasksArtefact.load(ws / "masks.h5").masks
    cam = sorted(masks)[0]
    m = np.asarray(masks[cam][0], bool)
    t = np.asarray(iio.imread(cap / "truth" / "masks" / cam / "000000.png")) > 127
    if t.ndim == 3:
        t = t[..., 0]
    return float(np.count_nonzero(m & t) / max(np.count_nonzero(m | t), 1))


BLOCKS = (8, 16, 32)  # pixel-block sides of the σ study (8: stages.silhouette.SilhouetteObservation.block_px)


def sigma_study(capg: Path, ws: Path, young: float, h: float = 1e-3) -> dict:
    """σ of log E (data part) from the residuals r and the Jacobian J = ∂r/∂log E at adapt's estimate: with the
    pixels taken as independent (RSS/(m − 1) (JᵀJ)⁻¹, what adapt reported before the clusters) and with the
    cluster-robust sandwich over b × b pixel blocks (stages.estimator.cluster_scale2) for b in BLOCKS.  J from
    central differences (±h in log E) of the static equilibrium simulated here."""
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture
    from stages.estimator import cluster_scale2, residual_scale2
    from stages.silhouette import SilhouetteObservation
    from stages.sim.scene import make_scene
    from stages.sweep import simulate_fixed

    capture = load_capture(capg)
    mesh = MeshArtefact.load(ws / "mesh.h5")
    ctl = capture.controls()
    scene = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity)
    T = capture.frame_count()
    X = {k: simulate_fixed(scene, ctl, np.array([young * np.exp(k * h)]), np.array([POISSON]), T, "equilibrium")
         for k in (-1, 0, 1)}
    obs = SilhouetteObservation(capture, ws, "", mesh)
    frames = list(range(T))
    r = np.concatenate(obs.residuals(frames, X[0]))
    dX = ((X[1] - X[-1]) / (2 * h))[None]  # (1, T, n, 3)
    J = np.concatenate(obs.jacobian(frames, X[0], dX), axis=0)  # (m, 1)
    A = float(J[:, 0] @ J[:, 0])
    out = {"sigma_iid": float(np.sqrt(residual_scale2(r, 1.0, None, 1) / A)),
           "sigma_floor": float(obs.sigma_floor()[0]), "floor_unit": float(obs.floor_unit[0]),
           "outline_rms_px": obs.outline_rms_px, "grow_px": float(np.mean(list(obs.grow_px.values()))),
           "outline_px": float(obs.outline_px)}
    for b in BLOCKS:
        obs.block_px = b
        out[f"sigma_block{b}"] = float(np.sqrt(cluster_scale2(r, J, 1.0, None, obs.clusters(frames)) / A))
    return out


def resolution_floor(name: str, res: int, cap: Path, ws0: Path, shifts: int) -> dict:
    """E from truth masks alone as the camera moves by sub-pixel offsets (the principal point shifted by (u, v),
    u, v uniform in [0, 1) px; the first unshifted): the masks are made as rsl synth makes truth/masks (2 × 2
    supersampled coverage of the truth surface ≥ ½, the clamp's pixels removed), E minimises the silhouette loss
    along the static equilibria (a cubic spline in log E through 10 solves over 0.8…1.25 E_true).  The spread
    of log E over the offsets is the resolution floor of the estimate; ``floor_unit`` (σ of log E per pixel of
    outline error per block, stages/silhouette.py) turns it into the outline error in pixels it amounts to."""
    import dataclasses

    from scipy.interpolate import CubicSpline
    from scipy.optimize import minimize_scalar

    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture
    from stages.occluders import ignore_mask
    from stages.silhouette import SilhouetteObservation, SoftSilhouette
    from stages.sim.scene import make_scene
    from stages.sweep import silhouette_coverage, simulate_fixed

    e_true = OBJECTS[name]
    capture = load_capture(cap)
    mesh = MeshArtefact.load(ws0 / "mesh.h5")
    ctl = capture.controls()
    scene = make_scene(mesh, ctl, capture.material.model, capture.dt, capture.gravity)
    truth = np.load(cap / "truth" / "surface.npz")
    from stages.artefacts import CamerasArtefact

    cam0 = CamerasArtefact.load(ws0 / "cameras.h5").cameras[0]
    lg = np.log(e_true) + np.linspace(np.log(0.8), np.log(1.25), 10)
    spl = CubicSpline(lg, np.stack([simulate_fixed(scene, ctl, np.array([np.exp(v)]), np.array([POISSON]), 1,
                                                   "equilibrium")[0] for v in lg]), axis=0)
    faces = np.asarray(mesh.surface_faces)[:, :3]
    rng = np.random.default_rng(0)
    est, units, rms = [], [], []
    for k in range(shifts):
        u, v = (0.0, 0.0) if k == 0 else rng.random(2)
        K = np.array(cam0.K, np.float64)
        K[0, 2] += u
        K[1, 2] += v
        cam = dataclasses.replace(cam0, K=K)
        m = silhouette_coverage(truth["vertices"][0], truth["faces"], cam, supersample=2) >= 0.5
        m &= ~ignore_mask(ctl, 0, cam, margin_px=0)
        obs = SilhouetteObservation.__new__(SilhouetteObservation)  # one camera, the masks made here
        obs.n, obs.cameras, obs.masks, obs._cams = mesh.n_vertices, [cam.name], {cam.name: m[None]}, [cam]
        obs.soft, obs.grow_px = [SoftSilhouette(faces, cam)], {}
        obs._ignore = {0: [(~ignore_mask(ctl, 0, cam)).astype(np.float64)]}
        best = minimize_scalar(lambda q: float(np.sum(obs.residual_images(0, spl(q))[0] ** 2)),
                               bounds=(lg[0], lg[-1]), method="bounded", options={"xatol": 1e-4})
        est.append(float(best.x - np.log(e_true)))
        obs.jacobian([0], spl(best.x)[None], spl(best.x, 1)[None, None])
        units.append(float(obs.floor_unit[0]))
        rms.append(obs.outline_rms_px)
    spread = float(np.std(est, ddof=1))
    return {"kind": "resolution", "object": name, "resolution": res, "shifts": shifts,
            "log_E_over_true": est, "mean_E_over_true": float(np.exp(np.mean(est))), "std_log_E": spread,
            "max_abs_log_E": float(np.max(np.abs(est))), "floor_unit": float(np.mean(units)),
            "outline_rms_px": float(np.mean(rms)), "outline_px_implied": spread / float(np.mean(units))}


def identify(name: str, res: int, guess: float, masks: str, cap: Path, ws0: Path, iters: int) -> dict:
    e_true = OBJECTS[name]
    capg = guess_capture(cap, guess, e_true)
    ws = ws0.parent / f"ws_g{guess}_{masks}"
    if not pl.skip(ws / "masks.h5"):
        ws.mkdir(parents=True, exist_ok=True)
        for f in ("mesh.h5", "cameras.h5"):
            shutil.copy(ws0 / f, ws / f)
        pl.rsl("segment", capg, "-w", ws, "--method", "grabcut" if masks == "grabcut" else "lab")
    wall = pl.adapt(capg, ws, "--space", "full", "--loss", "vision", "--fixed-poisson", "--poisson-init", POISSON,
                    "--offline-iters", iters)
    from stages.artefacts import AdaptArtefact

    art = AdaptArtefact.load(ws / "adapt.h5")
    assert art.mode == "static" and art.loss_kind == "silhouette", (art.mode, art.loss_kind)
    E, sE = float(art.young[-1, 0]), float(art.young_sigma[-1, 0])
    rel = sE / E
    study = sigma_study(capg, ws, E)
    # adapt's --model-error 0.02 and the silhouette's outline floor (both in quadrature) taken out
    data = float(np.sqrt(max(rel ** 2 - 0.02 ** 2 - study["sigma_floor"] ** 2, 0.0)))
    for k in [k for k in study if k.startswith("sigma_") and k != "sigma_floor"]:
        study[f"inside_2{k}"] = bool(abs(np.log(E / e_true)) <= 2 * study[k])
        study[f"inside_2{k}_floor"] = bool(abs(np.log(E / e_true))
                                           <= 2 * np.sqrt(study[k] ** 2 + 0.02 ** 2 + study["sigma_floor"] ** 2))
    return {"kind": "identification", "object": name, "resolution": res, "masks": masks, "guess": guess,
            "E_over_true": E / e_true, "sigma_rel": rel, "sigma_data_rel": data,
            "inside_2sigma": bool(abs(E - e_true) <= 2 * sE),
            "inside_2sigma_data": bool(abs(E - e_true) <= 2 * data * E),
            "adapt_wall_s": wall, "s_per_frame": float(np.mean(art.time_total_s)),
            "render_s_per_frame": float(np.mean(art.time_render_s)), "mask_iou": mask_iou(ws, capg),
            "offline_iters": iters, "ws": str(ws), **study}


def timing(name: str, res: int, ws: Path, repeats: int) -> dict:
    """Per-frame silhouette cost (coverage + jvp in one direction + vjp) sparse vs dense, at adapt's positions."""
    from stages.artefacts import AdaptArtefact, CamerasArtefact, MeshArtefact
    from stages.silhouette import SoftSilhouette

    mesh = MeshArtefact.load(ws / "mesh.h5")
    cam = CamerasArtefact.load(ws / "cameras.h5").cameras[0]
    x = np.asarray(AdaptArtefact.load(ws / "adapt.h5").positions[-1], np.float64)[:mesh.n_vertices]
    faces = np.asarray(mesh.surface_faces)[:, :3]
    rng = np.random.default_rng(0)
    V = 1e-3 * rng.standard_normal((1,) + x.shape)
    g = rng.standard_normal((cam.height, cam.width))
    out = {"kind": "timing", "object": name, "resolution": res, "faces": len(faces)}
    res_ = {}
    for label, dense in (("sparse", False), ("dense", True)):
        s = SoftSilhouette(faces, cam, dense=dense)
        t0 = time.perf_counter()
        s.coverage(x), s.jvp(x, V), s.vjp(x, g)
        out[f"{label}_first_s"] = time.perf_counter() - t0  # with compilation
        wall, cpu = median_times(lambda: (s.coverage(x), s.jvp(x, V), s.vjp(x, g)), repeats)
        out[f"{label}_s"], out[f"{label}_cpu_s"] = wall, cpu
        res_[label] = s.coverage(x)
        if dense:
            y0, y1, x0, x1 = s.box(x)
            out["dense_pairs"] = (y1 - y0) * (x1 - x0) * len(faces)
        else:
            out["sparse_pairs"] = s.pairs
    out["speedup"] = out["dense_s"] / out["sparse_s"]
    out["max_abs_diff_A"] = float(np.abs(res_["sparse"] - res_["dense"]).max())
    return out


def _outline_px() -> float:
    from stages.silhouette import OUTLINE_PX

    return OUTLINE_PX


def _key(c: dict) -> tuple:
    return (c["kind"], c["object"], c["resolution"], c.get("masks"), c.get("guess"))


def table(cases: list[dict]) -> str:
    ids = sorted((c for c in cases if c["kind"] == "identification"),
                 key=lambda c: (c["object"], c["resolution"], c["masks"], c["guess"]))
    lines = ["| object | px | masks | toml E / E_true | E / E_true | ±σ (adapt) | ±σ data | ±σ outline floor | "
             "outline offset b px | inside 2σ | inside 2σ data | s/frame | render s/frame | mask IoU |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in ids:
        so = f" (σ_o {max(c['outline_px'], c['outline_rms_px']):.3f} px)" if "outline_px" in c else ""
        fl = f"{c['sigma_floor']:.1%}{so} | {c['grow_px']:+.2f}" if "sigma_floor" in c else "– | –"
        lines.append(f"| {c['object']} | {c['resolution']}² | {c['masks']} | {c['guess']:.1f} | {c['E_over_true']:.3f} "
                     f"| {c['sigma_rel']:.1%} | {c['sigma_data_rel']:.1%} | {fl} "
                     f"| {'yes' if c['inside_2sigma'] else 'no'} "
                     f"| {'yes' if c['inside_2sigma_data'] else 'no'} | {c['s_per_frame']:.1f} "
                     f"| {c['render_s_per_frame']:.1f} | {c['mask_iou']:.3f} |")
    old = [c for c in ids if "sigma_floor" not in c]
    if old:
        lines += ["", f"{len(old)} rows (– in the floor columns) were measured before the outline offset b and the "
                      "outline floor (static.json keeps them as they were)."]
    if ids:
        n = len(ids)
        k = sum(c["inside_2sigma"] for c in ids)
        kd = sum(c["inside_2sigma_data"] for c in ids)
        err = [abs(c["E_over_true"] - 1) for c in ids]
        lines += ["", f"E_true within ±2σ: {k} of {n} rows (adapt's σ), {kd} of {n} (data part alone); "
                      f"|E/E_true − 1|: median {np.median(err):.1%}, largest {max(err):.1%}."]
    ids = [c for c in ids if "sigma_iid" in c]
    if ids:
        keys = ["sigma_iid"] + [f"sigma_block{b}" for b in BLOCKS]
        names = ["pixels independent"] + [f"{b}×{b} blocks" for b in BLOCKS]
        lines += ["", "σ study at adapt's estimate (data part of σ(log E); J by central differences of the equilibrium): "
                      "the pixels taken as independent (RSS/(m − 1)) vs the cluster-robust sandwich over pixel blocks:",
                  "", "| object | px | masks | toml E / E_true | |log(E/E_true)| | " + " | ".join(names) + " |",
                  "|---|---|---|---|---|" + "---|" * len(keys)]
        for c in ids:
            lines.append(f"| {c['object']} | {c['resolution']}² | {c['masks']} | {c['guess']:.1f} | "
                         f"{abs(np.log(c['E_over_true'])):.1%} | " + " | ".join(f"{c[k]:.2%}" for k in keys) + " |")
        lines += ["", "E_true within ±2σ of that σ alone / with adapt's 2 % model-error floor and the outline floor "
                      "in quadrature: "
                  + "; ".join(f"{nm} {sum(c[f'inside_2{k}'] for c in ids)}/{sum(c[f'inside_2{k}_floor'] for c in ids)} "
                              f"of {len(ids)}" for k, nm in zip(keys, names)) + "."]
    rf = sorted((c for c in cases if c["kind"] == "resolution"), key=lambda c: (c["object"], c["resolution"]))
    if rf:
        lines += ["", "Resolution floor: E from truth masks alone (made as rsl synth makes truth/masks) as the camera "
                      "moves by sub-pixel offsets (bench/static.py resolution_floor); the spread of log E over the "
                      "offsets, and the outline error per 8×8 block it amounts to (spread / floor unit):", "",
                  "| object | px | offsets | mean E / E_true | std log E | largest abs log E | floor unit (σ log E per "
                  "px) | outline error px | RMS outline misfit px |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for c in rf:
            lines.append(f"| {c['object']} | {c['resolution']}² | {c['shifts']} | {c['mean_E_over_true']:.3f} | "
                         f"{c['std_log_E']:.2%} | {c['max_abs_log_E']:.2%} | {c['floor_unit']:.3f} | "
                         f"{c['outline_px_implied']:.3f} | {c['outline_rms_px']:.3f} |")
        lines += ["", f"Largest outline error implied: {max(c['outline_px_implied'] for c in rf):.3f} px "
                      f"(stages.silhouette.OUTLINE_PX, the floor adapt adds: {_outline_px():.3f} px)."]
    tim = sorted((c for c in cases if c["kind"] == "timing"), key=lambda c: (c["object"], c["resolution"]))
    if tim:
        lines += ["", "Silhouette per frame (coverage + jvp + vjp, compiled), sparse vs dense twin, same run:", "",
                  "| object | px | faces | pairs sparse | pairs dense | sparse s | dense s | dense / sparse | "
                  "sparse CPU s | dense CPU s | CPU dense / sparse | max \\|ΔA\\| | sparse first call s | "
                  "dense first call s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for c in tim:
            lines.append(f"| {c['object']} | {c['resolution']}² | {c['faces']} | {c['sparse_pairs']} | "
                         f"{c['dense_pairs']} | {c['sparse_s']:.3f} | {c['dense_s']:.3f} | {c['speedup']:.1f}× | "
                         f"{c['sparse_cpu_s']:.3f} | {c['dense_cpu_s']:.3f} | "
                         f"{c['dense_cpu_s'] / c['sparse_cpu_s']:.1f}× | "
                         f"{c['max_abs_diff_A']:.1e} | {c['sparse_first_s']:.1f} | {c['dense_first_s']:.1f} |")
        lines += ["", "(wall times under the machine's load, shown in its line above; CPU: this process's own time.)"]
    return "\n".join(lines)


def markdown(data: dict) -> str:
    return ("# Static single-view identification from the silhouette (bench/static.py)\n\n"
            f"{data['machine']}, {data['date']}\n\n" + table(data["cases"]) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", default="beam,bar")
    ap.add_argument("--resolutions", default="64,96")
    ap.add_argument("--guesses", default="0.4,1.0")
    ap.add_argument("--masks", default="grabcut,truth")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--offline-iters", type=int, default=30, help="rsl adapt --offline-iters (its default: 30)")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--shifts", type=int, default=6, help="sub-pixel camera offsets of the resolution floor (0: none)")
    ap.add_argument("--only-floor", action="store_true", help="only the resolution floor rows")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_static"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--merge", action="store_true")
    ap.add_argument("--from-json", action="store_true", help="only rewrite static.md from static.json")
    args = ap.parse_args()
    jpath = args.out / "static.json"
    if args.from_json:
        data = json.loads(jpath.read_text())
        (args.out / "static.md").write_text(markdown(data))
        print(markdown(data))
        return
    args.work.mkdir(parents=True, exist_ok=True)
    for name in args.objects.split(","):
        for res in map(int, args.resolutions.split(",")):
            cap, ws0 = capture(name, res, args.work)
            last_ws = None
            for guess in map(float, args.guesses.split(",") if not args.only_floor else []):
                for masks in args.masks.split(","):
                    try:
                        c = identify(name, res, guess, masks, cap, ws0, args.offline_iters)
                    except pl.RslFailed as e:
                        print(f"{name} {res} {masks} {guess}: {e}", file=sys.stderr)
                        continue
                    last_ws = Path(c["ws"])
                    print(f"{name} {res}² {masks} toml×{guess}: E/E_true {c['E_over_true']:.3f} "
                          f"±{c['sigma_rel']:.1%} ({c['s_per_frame']:.1f} s/frame)", flush=True)
                    save(args.out, [c], args.merge)
            if args.shifts > 1:
                c = resolution_floor(name, res, cap, ws0, args.shifts)
                print(f"{name} {res}²: resolution floor std log E {c['std_log_E']:.2%} "
                      f"= {c['outline_px_implied']:.3f} px of outline", flush=True)
                save(args.out, [c], args.merge)
            if last_ws is not None and not args.no_timing and not args.only_floor:
                c = timing(name, res, last_ws, args.repeats)
                print(f"{name} {res}²: dense/sparse {c['speedup']:.1f}×", flush=True)
                save(args.out, [c], args.merge)
    print(markdown(json.loads((args.out / "static.json").read_text())))


def save(out: Path, cases: list[dict], merge: bool) -> None:
    """Write static.json/.md with ``cases`` added (after each measurement; under a lock: several runs may add
    rows at once); without ``merge`` the first save of this run starts the file anew."""
    import fcntl

    out.mkdir(parents=True, exist_ok=True)
    jpath = out / "static.json"
    with open(Path(tempfile.gettempdir()) / "rsl_bench_static.lock", "w") as lock:  # not in docs/results
        fcntl.flock(lock, fcntl.LOCK_EX)
        fresh = not merge and not _STARTED
        old = [] if fresh or not jpath.exists() else json.loads(jpath.read_text())["cases"]
        _STARTED.append(True)
        keys = {_key(c) for c in cases}
        data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, "
                           f"{platform.python_version()}, load {os.getloadavg()[0]:.1f}",
                "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "cases": [c for c in old if _key(c) not in keys] + cases}
        jpath.write_text(json.dumps(data, indent=1))
        (out / "static.md").write_text(markdown(data))


_STARTED: list = []


if __name__ == "__main__":
    main()
