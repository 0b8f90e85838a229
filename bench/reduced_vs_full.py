"""Reduced (neural subspace + cubature) vs full-space simulation: per-frame forward and backward time
and the trajectory error, measured in the same run.

    .venv/bin/python bench/reduced_vs_full.py [--quick] [--cases bar,dino] [--sequences 6] [--frames 16]

For each mesh: full-space snapshots (stages.sim.scene.simulate, solver "auto") of a clamp that moves and
turns by a random amount per sequence, under gravity; the last sequence is held out.  An autoencoder
(stages.subspace.train, r latent, PCA layer p) and its cubature are trained on the others.  On the held-out
sequence: forward = median seconds per frame of a step (warm), backward = median over window end frames
of window_adjoint time / w; ratio = (full fwd + bwd) / (reduced fwd + bwd); trajectory_error_rel = mean
vertex distance of the reduced trajectory to the full one over the bounding-box diagonal.

Prints a Markdown table and writes docs/results/reduced_vs_full.md and .json.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import jax.numpy as jnp  # noqa: E402

from stages.domain.rotations import axis_angle_matrix  # noqa: E402
from stages.sim import potential as P  # noqa: E402
from stages.sim.mesh import rest_quantities  # noqa: E402
from stages.sim.meshgen import box_tets  # noqa: E402
from stages.sim.scene import FrameInputs, HandleSpec, Scene, simulate, step, window_adjoint  # noqa: E402
from stages.subspace import ReducedModel  # noqa: E402
from stages.sim.quadrature import element_order, quadratic_tets  # noqa: E402
from stages.subspace.cubature import ReducedForceSampler, fit_cubature, scene_quadrature  # noqa: E402
from stages.subspace.train import fit_subspace, reconstruction_error  # noqa: E402

DENSITY, YOUNG, POISSON = 1000.0, 5e4, 0.45
RTOL = 1e-6  # relative Newton residual, full and reduced alike
DATA = ROOT.parent / "shared" / "data"


def read_medit(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and tets of a Medit .mesh (positive orientation)."""
    import meshio

    m = meshio.read(path)
    t = np.concatenate([c.data for c in m.cells if c.type == "tetra"]).astype(np.int64)
    v = np.asarray(m.points, np.float64)
    used = np.unique(t)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    v, t = v[used], remap[t]
    p = v[t]
    neg = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    return v, t


def read_dino_5k() -> tuple[np.ndarray, np.ndarray]:
    """bench/data/dino_tetwild_5k.npz: fTetWild (stages.meshing.tetwild, edge 0.015 × the diagonal, one
    thread) of the boundary of autodef_fulton/25cm_dino_low.mesh — 5036 vertices, 20280 tets, 15108
    DOFs.  fTetWild is not deterministic, so the mesh was made once and is stored (positive orientation)."""
    d = np.load(ROOT / "bench" / "data" / "dino_tetwild_5k.npz")
    v, t = np.asarray(d["vertices"], np.float64), np.asarray(d["tets"], np.int64)
    p = v[t]
    neg = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) < 0
    t[neg] = t[neg][:, [0, 2, 1, 3]]
    return v, t


def make_case(name: str, quick: bool):
    if name in ("bar", "bar_p2"):
        # bar_p2: the same 36 cm bar with quadratic tets on a coarser grid of about the same DOFs
        if name == "bar":
            cells = (12, 3, 3) if quick else (36, 9, 9)
        else:
            cells = (6, 2, 2) if quick else (18, 4, 4)
        v, t = box_tets(cells, (0.36, 0.09, 0.09))
        if name == "bar_p2":
            v, t = quadratic_tets(v, t)
        axis, frac = 0, 0.02
        r, w = (10 if quick else 30), 3
    else:
        if quick:
            v, t = read_medit(DATA / "autodef_fulton" / "dino_ultra_low.mesh")
        else:
            v, t = read_dino_5k()
        axis, frac = 2, 0.12  # the feet are clamped
        r, w = 100, 5
        if quick:
            r = 20
    vol, dmi, m = rest_quantities(v, t, DENSITY)
    lo, hi = v[:, axis].min(), v[:, axis].max()
    hid = np.nonzero(v[:, axis] <= lo + frac * (hi - lo))[0]
    scene = Scene(rest=v, tets=t, dm_inv=dmi, volumes=vol, masses=m, tet_region=np.zeros(len(t), np.int64),
                  n_regions=1, region_names=("body",), material="stable_neohookean", dt=1 / 30,
                  gravity=np.array([0.0, 0.0, -9.81]), handles=(HandleSpec("clamp", hid, 1e4),), loads=(),
                  obstacles=(), friction=0.0, contact_stiffness=1e4)
    return scene, r, w


def sequence(scene: Scene, seed: int, frames: int, scale: float = 1.0) -> list[FrameInputs]:
    """The clamp translates and turns about its centre by a random amount, easing in over 10 frames."""
    rng = np.random.default_rng(seed)
    diag = np.linalg.norm(scene.rest.max(0) - scene.rest.min(0))
    amp = scale * rng.uniform(-1, 1, 6) * np.array([0.05 * diag, 0.05 * diag, 0.05 * diag, 0.3, 0.3, 0.3])
    hid = scene.handles[0].ids
    c = scene.rest[hid].mean(0)
    out = []
    for f in range(frames):
        s = np.sin(0.5 * np.pi * min(f / 10, 1.0))
        R = np.eye(3)
        for k in range(3):
            R = R @ axis_angle_matrix(np.eye(3)[k], amp[3 + k] * s)
        target = (scene.rest[hid] - c) @ R.T + c + amp[:3] * s
        out.append(FrameInputs((target,), np.zeros_like(scene.rest), np.zeros((0, 7))))
    return out


def run_case(name: str, quick: bool, n_seq: int, frames: int, epochs: int, cub_tets: int, log,
             cub_tol: float = 0.001) -> dict:
    scene, r, w = make_case(name, quick)
    n = len(scene.rest)
    diag = np.linalg.norm(scene.rest.max(0) - scene.rest.min(0))
    E, nu = np.array([YOUNG]), np.array([POISSON])
    t0 = time.perf_counter()
    scale = 1.0 if name == "bar" else 0.5  # the dinosaur turns about its feet: gentler motions
    n_seq = max(n_seq, -(-(r + 12) // frames) + 1)  # the PCA layer needs p > r training frames
    cache = Path(os.environ.get("RSL_BENCH_CACHE", "")) / f"reduced_vs_full_{name}_{n}v_{n_seq}x{frames}.npy"
    ins = [sequence(scene, s, frames, scale) for s in range(n_seq)]
    if os.environ.get("RSL_BENCH_CACHE") and cache.exists():
        xs = np.load(cache)
    else:
        xs = np.stack([simulate(scene, inp, E, nu, rtol=RTOL, max_iterations=100) for inp in ins])
        if os.environ.get("RSL_BENCH_CACHE"):
            np.save(cache, xs)
    seqs = list(zip(ins, xs))
    log(f"{name}: {n} vertices, {len(scene.tets)} tets; {n_seq}×{frames} full-space frames in "
        f"{time.perf_counter() - t0:.0f} s")
    train = np.concatenate([x for _, x in seqs[:-1]])
    t0 = time.perf_counter()
    p = min(2 * r, len(train) - 1)
    sub, _ = fit_subspace("autoencoder", scene.rest, scene.masses, train, r, None, epochs=epochs, seed=0,
                          pca_dim=p)
    rec = reconstruction_error(sub, seqs[-1][1]) / diag
    mu, lam = P.tet_lame(scene, E, nu)
    quad = scene_quadrature(scene)  # cubature over quadrature points (one per linear tet, four per quadratic)
    pick = np.random.default_rng(0).choice(len(train), size=min(40, len(train)), replace=False)
    sampler = ReducedForceSampler(sub, np.asarray(sub.encode(jnp.asarray(train[pick]))), quad,
                                  np.asarray(mu)[quad.element], np.asarray(lam)[quad.element], scene.material)
    ids, wts, cinfo = fit_cubature(sampler, scene.tet_region[quad.element], 1, max_points=cub_tets, tol=cub_tol,
                                   seed=0)
    log(f"{name}: autoencoder r={r} p={sub.p} (held-out reconstruction {rec:.2%} of the diagonal), cubature "
        f"{len(ids)} of {quad.n_points} points (force error {cinfo['error_rel']:.2%}) in "
        f"{time.perf_counter() - t0:.0f} s")
    model = ReducedModel(sub, scene, (ids, wts))
    inp, x_full = seqs[-1]

    # forward, per frame (warm: one untimed step first)
    model.step(inp[0], E, nu, model.z_rest, model.z_rest, rtol=RTOL)
    step(scene, inp[0], E, nu, scene.rest, scene.rest, rtol=RTOL)
    z1 = z2 = model.z_rest
    Z, tr, its, hess = [], [], [], []
    for t in range(frames):
        t0 = time.perf_counter()
        z, info = model.step(inp[t], E, nu, z1, z2, rtol=RTOL)
        tr.append(time.perf_counter() - t0)
        its.append(info["iterations"])
        hess.append(info["hessians"])
        Z.append(z)
        z2, z1 = z1, z
    Z = np.stack(Z)
    tf, fits, ffb = [], [], []
    x1 = x2 = scene.rest
    for t in range(frames):  # the same frames as the reduced forward
        t0 = time.perf_counter()
        x, finfo = step(scene, inp[t], E, nu, x1, x2, solver="auto", rtol=RTOL, max_iterations=100)
        tf.append(time.perf_counter() - t0)
        fits.append(finfo["iterations"])
        ffb.append(finfo.get("fallback", 0))
        x2, x1 = x1, x
    err = float(np.linalg.norm(model.decode(Z) - x_full, axis=-1).mean() / diag)

    # backward: window adjoint ending at several frames, per frame
    rng = np.random.default_rng(1)
    ends = list(range(max(w + 1, frames - 5), frames))
    bf, br = [], []
    Zb = np.concatenate([np.tile(model.z_rest, (2, 1)), Z])
    Xb = np.concatenate([np.tile(scene.rest, (2, 1, 1)), x_full])
    fr = list(range(ends[0] - w + 1, ends[0] + 1))  # warm-up of the reduced adjoint's kernels (untimed)
    model.window_adjoint([inp[t] for t in fr], np.tile(E, (w, 1)), np.tile(nu, (w, 1)), Z[fr],
                         Zb[fr[0]:fr[0] + 2], dL_dX=rng.normal(size=(w, n, 3)))
    for te in ends:
        fr = list(range(te - w + 1, te + 1))
        dX = rng.normal(size=(w, n, 3))
        ins = [inp[t] for t in fr]
        Ew, nw = np.tile(E, (w, 1)), np.tile(nu, (w, 1))
        t0 = time.perf_counter()
        model.window_adjoint(ins, Ew, nw, Z[fr], Zb[fr[0]:fr[0] + 2], dL_dX=dX)
        br.append((time.perf_counter() - t0) / w)
        t0 = time.perf_counter()
        window_adjoint(scene, ins, Ew, nw, x_full[fr], Xb[fr[0]:fr[0] + 2], dX, solver="auto")
        bf.append((time.perf_counter() - t0) / w)
    med = statistics.median
    case = {"name": name, "dofs": 3 * n, "vertices": n, "tets": int(len(scene.tets)), "r": r, "w": w,
            "order": element_order(scene.tets), "quadrature_points": quad.n_points,
            "pca_dim": sub.p, "cubature_tets": int(len(ids)), "cubature_error_rel": cinfo["error_rel"],
            "reconstruction_error_rel": rec,
            "full_forward_s": med(tf), "full_backward_s": med(bf), "reduced_forward_s": med(tr),
            "reduced_backward_s": med(br), "full_newton_iterations": float(np.mean(fits)),
            "reduced_newton_iterations": float(np.mean(its)), "reduced_hessians_per_frame": float(np.mean(hess)),
            "reduced_newton_iterations_max": int(np.max(its)), "full_newton_iterations_max": int(np.max(fits)),
            "full_projected_iterations": float(np.mean(ffb)), "sequences": len(seqs), "frames": frames}
    case["ratio"] = (case["full_forward_s"] + case["full_backward_s"]) / (case["reduced_forward_s"]
                                                                          + case["reduced_backward_s"])
    case["trajectory_error_rel"] = err
    return case


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small meshes, few frames (smoke test)")
    ap.add_argument("--cases", default="bar,dino")
    ap.add_argument("--sequences", type=int, default=6)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--cubature-tets", type=int, default=300)
    ap.add_argument("--cubature-tol", type=float, default=0.001)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--md-only", action="store_true", help="rewrite the .md from the stored .json and stop")
    args = ap.parse_args()
    if args.md_only:
        d = json.loads((args.out / "reduced_vs_full.json").read_text())
        (args.out / "reduced_vs_full.md").write_text(markdown(d["machine"], d["date"], d["cases"]))
        return
    cases = []
    for name in args.cases.split(","):
        cases.append(run_case(name, args.quick, args.sequences, args.frames, args.epochs, args.cubature_tets,
                              lambda s: print(s, flush=True), args.cubature_tol))
        if not args.quick:
            write(args.out, cases)
    print(table(cases))


def table(cases: list[dict]) -> str:
    head = ("| case | DOFs | r | w | cubature tets | full fwd s | full bwd s | reduced fwd s | reduced bwd s "
            "| ratio | trajectory error |\n|---|---|---|---|---|---|---|---|---|---|---|\n")
    return head + "".join(
        f"| {c['name']} | {c['dofs']} | {c['r']} | {c['w']} | {c['cubature_tets']} | "
        f"{c['full_forward_s']:.4f} | {c['full_backward_s']:.4f} | {c['reduced_forward_s']:.4f} | "
        f"{c['reduced_backward_s']:.4f} | {c['ratio']:.1f}× | {c['trajectory_error_rel']:.2%} |\n" for c in cases)


def write(out: Path, new_cases: list[dict]) -> None:
    """Write docs/results/reduced_vs_full.{json,md}, keeping earlier cases of other names (one run per case)."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "reduced_vs_full.json"
    old = json.loads(path.read_text()).get("cases", []) if path.exists() else []
    names = {c["name"] for c in new_cases}
    cases = [c for c in old if c["name"] not in names] + new_cases
    load = os.getloadavg()[0]
    machine = f"{platform.node()} {platform.machine()} {os.cpu_count()} cores, load {load:.1f} at the end"
    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    path.write_text(json.dumps({"machine": machine, "date": date, "cases": cases}, indent=1))
    (out / "reduced_vs_full.md").write_text(markdown(machine, date, cases))


def markdown(machine: str, date: str, cases: list[dict]) -> str:
    """The results page: table and what was measured, from the measured cases only."""
    notes = []
    for c in cases:
        its = (f" Newton iterations per frame: full {c['full_newton_iterations']:.1f}, reduced "
               f"{c['reduced_newton_iterations']:.1f} with {c['reduced_hessians_per_frame']:.1f} reduced Hessians."
               if "reduced_newton_iterations" in c else "")
        if "full_newton_iterations_max" in c:
            its += (f" At most {c['full_newton_iterations_max']} full and {c['reduced_newton_iterations_max']} "
                    f"reduced iterations in a frame; {c['full_projected_iterations']:.1f} of the full iterations "
                    f"per frame used the |λ|-projected Hessian. {c['sequences']} sequences × {c['frames']} frames.")
        notes.append(f"- **{c['name']}** ({c['vertices']} vertices, {c['tets']} tets, r = {c['r']}, PCA layer "
                     f"p = {c['pca_dim']}, {c['cubature_tets']} cubature tets with a {c['cubature_error_rel']:.2%} "
                     f"reduced-force error): reduced forward + backward {c['ratio']:.1f}× faster than the full "
                     f"space; held-out reconstruction error {c['reconstruction_error_rel']:.2%} of the diagonal, "
                     f"trajectory error {c['trajectory_error_rel']:.2%}.{its}")
    return (
        "# Reduced vs full-space simulation\n\n"
        f"Machine: {machine}; {date}.\n\n" + table(cases) + "\n"
        "What was measured (bench/reduced_vs_full.py): per frame, in seconds, forward = one implicit-Euler "
        "step (median over the 16 frames of a held-out sequence, warm, the same frames in both spaces); "
        "backward = the window adjoint's time "
        "divided by w (median over window ends, warm). Full space: stages.sim.scene step / window_adjoint with "
        "solver \"auto\" (CHOLMOD with its symbolic analysis reused; exact Hessian while it factorises, else "
        "element Hessians with |λ| eigenvalues). Reduced: stages.subspace.ReducedModel (autoencoder of latent "
        "size r on a PCA layer, elastic energy by optimised cubature, inertia / gravity / handle springs exact "
        "in q; quasi-Newton: BFGS updates of the last exact reduced Hessian, assembled as Jqᵀ H_q Jq + decoder "
        "curvature). Both solvers stop at a relative residual of 1e-6 on the same scale (‖∇‖ at the start + "
        "‖Mg‖ + ‖f‖). "
        "Training data: full-space sequences of a clamp that moves and turns by random amounts under gravity "
        "(bar: a 36 cm cantilever, E = 50 kPa, ν = 0.45; dinosaur: bench/data/dino_tetwild_5k.npz, fTetWild "
        "of the 25cm_dino_low surface at edge 0.015 × diagonal, clamped at its feet, gentler motions), the "
        "last sequence held out. The trajectory error is the mean vertex "
        "distance between the reduced and full trajectories of the held-out sequence over the bounding-box "
        "diagonal. Each ratio is taken within one run (the machine's load is given above).\n\n"
        + "\n".join(notes) + "\n\n"
        "Against the 10× target of forward + backward: " + ", ".join(
            f"{c['name']} {c['ratio']:.1f}× ({'met' if c['ratio'] >= 10 else 'not met'})" for c in cases) + ".\n\n"
        "Interpretation: the hand-written, dated [reduced_vs_full_notes.md](reduced_vs_full_notes.md) "
        "(this script does not rewrite it).\n")


if __name__ == "__main__":
    main()
