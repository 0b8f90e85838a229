"""CPU splatting benchmark: one view, forward and forward+backward, fast (numba) vs tiled pure PyTorch.

    .venv/bin/python bench/render.py [--quick] [--repeats 7]

The scene is the sample dinosaur tet mesh (sample_data/dino) scaled to 0.2 m with Gaussians
seeded as `rsl fit-gaussians` seeds them (denser near the surface, opacity 0.88, random
colours), seen by a camera that the object fills to about 70 %.  One "view" is the whole
render path the adapt stage runs: bind to the mesh (centres, F Σ Fᵀ), EWA projection,
colours, rasterization, background; the backward pass goes to the vertex positions
(float64, as adapt hands them) and every appearance parameter.  The fast path runs binding
and projection fused in numba (stages/render/bind_project.py) and the numba tile rasterizer;
the reference is the same render in pure PyTorch: binding and projection as torch ops and
the tiled rasterizer of stages/render/_torch_ref.rasterize_tiled (tile binning and sorting in
torch ops — the same tile lists as the numba binning — then dense maths per tile, autograd
backward).  "lean" is that rasterizer on the compiled numba binning (the baseline of earlier
runs), reported as an extra column.  The dense reference (pixels × Gaussians) would hold
20K × 65K float32 ≈ 5 GB in each of its several intermediates at 256², so it is not a baseline.
For the largest case the fast view's one-thread CPU time is also split into its parts.

Prints a Markdown table and writes docs/results/render.md and docs/results/render.json.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numba  # noqa: E402
import torch  # noqa: E402

from stages.artefacts import Camera, GaussiansArtefact, MeshArtefact  # noqa: E402
from stages.steps.fit_gaussians import seed_gaussians  # noqa: E402
from stages.render import _torch_ref  # noqa: E402
from stages.render import rasterize as rast  # noqa: E402
from stages.render.bind_project import bind_project  # noqa: E402
from stages.render.gaussians import BoundGaussians, color_to_sh0, sh_to_color  # noqa: E402
from stages.render.projection import project_gaussians  # noqa: E402
from stages.render.rasterize import tile_stats  # noqa: E402
from stages.sim.mesh import rest_quantities  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/, also when imported by a test
from _timing import median_times  # noqa: E402

CASES = [(5000, 128), (5000, 256), (20000, 128), (20000, 256)]
QUICK = [(2000, 64)]


def dino_mesh() -> MeshArtefact:
    import meshio

    m = meshio.read(ROOT / "sample_data" / "dino" / "object.mesh")
    v = np.asarray(m.points, np.float64)
    tets = np.asarray(m.cells_dict["tetra"], np.int64)
    v = (v - v.mean(0)) * (0.2 / np.ptp(v, 0).max())
    p = v[tets]
    vol = np.linalg.det(np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], -1))
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    faces = np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]])
    _, inv, cnt = np.unique(np.sort(faces, 1), axis=0, return_inverse=True, return_counts=True)
    faces = faces[cnt[inv.ravel()] == 1]
    vol, dm_inv, masses = rest_quantities(v, tets, 1000.0)
    return MeshArtefact(v, tets, faces, np.zeros(len(tets), np.int64), ["body"], vol, dm_inv, masses, 1000.0)


def camera(size: int) -> Camera:
    eye = np.array([0.3, -0.25, 0.15])
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(fwd, right), fwd])
    f = 2.4 * size
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1]])
    return Camera("bench", K, np.zeros(5), R, -R @ eye, size, size)


def gaussians(mesh: MeshArtefact, n: int) -> BoundGaussians:
    rng = np.random.default_rng(0)
    host, bary, log_s = seed_gaussians(mesh, n, 4.0, rng)
    art = GaussiansArtefact(host, bary, np.repeat(log_s[:, None], 3, 1), np.tile([1.0, 0, 0, 0], (n, 1)),
                            np.full(n, 2.0), color_to_sh0(rng.uniform(size=(n, 3)))[:, None, :])
    return BoundGaussians.from_artefact(art, mesh)


def run_case(mesh: MeshArtefact, n: int, size: int, repeats: int) -> dict:
    g = gaussians(mesh, n)
    cam = camera(size)
    x = torch.as_tensor(mesh.vertices)  # float64, as adapt passes them
    target = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1))

    def fwd(r):
        return lambda: g.render(x, cam, rasterizer=r).image

    def fwd_bwd(r):
        def f():
            xr = x.clone().requires_grad_(True)
            g.zero_grad(set_to_none=True)
            loss = (g.render(xr, cam, rasterizer=r).image - target).abs().sum()
            loss.backward()
        return f

    with torch.no_grad():
        img = g.render(x, cam).image
        proj = project_gaussians(g.centres(x), g.covariances(x), g.camera(cam))
        st = tile_stats(proj.means2d, proj.conics, g.opacities(), proj.depths, proj.visible, size, size)
    coverage = float((img - g.background).abs().sum(-1).gt(1e-3).float().mean())
    out = {"gaussians": n, "resolution": size, "tile_pairs": st["pairs"], "max_per_tile": st["max_per_tile"],
           "coverage": round(coverage, 3)}
    # Interleaved: every round times each variant once (the fast ones 3 times), so load from other
    # processes falls on all of them alike; medians over the rounds.
    threads = numba.get_num_threads()

    def one_thread(f):
        def g1():
            numba.set_num_threads(1)
            try:
                f()
            finally:
                numba.set_num_threads(threads)
        return g1

    runs = {"fast_fwd": (fwd("fast"), 3), "fast_fwd_bwd": (fwd_bwd("fast"), 3),
            "fast_fwd_bwd_1thread": (one_thread(fwd_bwd("fast")), 3), "reference_fwd": (fwd("tiled"), 1),
            "reference_fwd_bwd": (fwd_bwd("tiled"), 1), "lean_fwd_bwd": (fwd_bwd("tiled_lean"), 1)}
    wall = {k: [] for k in runs}
    cpu = {k: [] for k in runs}
    for f, _ in runs.values():
        f()  # warm-up (and compilation)
    for _ in range(repeats):
        for k, (f, times) in runs.items():
            for _ in range(times):
                w, c = median_times(f, 1)
                wall[k].append(w)
                cpu[k].append(c)
    for k in runs:
        out[k + "_s"] = statistics.median(wall[k])
        out[k + "_cpu_s"] = statistics.median(cpu[k])
    out["ratio"] = out["reference_fwd_bwd_s"] / out["fast_fwd_bwd_s"]
    out["ratio_cpu"] = out["reference_fwd_bwd_cpu_s"] / out["fast_fwd_bwd_cpu_s"]
    out["ratio_lean"] = out["lean_fwd_bwd_s"] / out["fast_fwd_bwd_s"]
    out["ratio_lean_cpu"] = out["lean_fwd_bwd_cpu_s"] / out["fast_fwd_bwd_cpu_s"]
    return out


def split(mesh: MeshArtefact, n: int, size: int, repeats: int) -> dict:
    """One-thread CPU ms of the fast view's parts (numba pinned to one thread; medians of warm runs)."""
    g = gaussians(mesh, n)
    cam = g.camera(camera(size))
    x = torch.as_tensor(mesh.vertices)
    target = torch.rand(size, size, 3, generator=torch.Generator().manual_seed(1))
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    cpu = lambda f: median_times(f, repeats, warmup=True)[1] * 1e3  # noqa: E731

    def whole():
        xr = x.clone().requires_grad_(True)
        g.zero_grad(set_to_none=True)
        (g.render(xr, cam).image - target).abs().sum().backward()

    def project():
        xr = x.clone().requires_grad_(True)
        m, c, _, _ = bind_project(xr, g.bary_logits, g.log_scales, g.rotations, g.host_vertices, g.dm_inv, cam)
        (m.sum() + c.sum()).backward()

    with torch.no_grad():
        m2d, con, dep, vis = bind_project(x, g.bary_logits, g.log_scales, g.rotations, g.host_vertices, g.dm_inv, cam)
        col, op = sh_to_color(g.sh, None), g.opacities()
    gd = rast._pack(m2d, con, col, op)
    dn, vn = dep.numpy(), vis.numpy()
    ext = (gd[:, 9].astype(np.float64), gd[:, 10].astype(np.float64))

    def binning():
        gdp = rast._pack(m2d, con, col, op)
        e = (gdp[:, 9].astype(np.float64), gdp[:, 10].astype(np.float64))
        ts, _, order = rast._bin_ranked(gdp[:, 0:2], gdp[:, 2:5], gdp[:, 5], dn, vn, size, size, e, True)
        rast._schedule(ts, 1)
        return np.ascontiguousarray(gdp[order])

    ts, ent, order = rast._bin_ranked(gd[:, 0:2], gd[:, 2:5], gd[:, 5], dn, vn, size, size, ext, True)
    gd = np.ascontiguousarray(gd[order])
    to, bs = rast._schedule(ts, 1)
    ec = rast.exp_coefficients(gd.dtype)
    c, a = np.empty((size, size, 3), gd.dtype), np.empty((size, size), gd.dtype)
    tf, nc = np.empty((size, size), gd.dtype), np.empty((size, size), np.int32)
    gc = np.random.default_rng(0).normal(size=(size, size, 3)).astype(gd.dtype)
    ga = np.random.default_rng(1).normal(size=(size, size)).astype(gd.dtype)
    ge = np.empty((ent.shape[0], 9))
    parts = {"whole view": cpu(whole), "binding + projection fwd+bwd (numba)": cpu(project),
             "packing, depth sort, binning, scheduling": cpu(binning),
             "rasterizer forward kernel": cpu(lambda: rast._forward(gd, ts, ent, to, bs, size, size, rast.TILE, ec,
                                                                    c, a, tf, nc)),
             "rasterizer backward kernel": cpu(lambda: rast._backward(gd, ts, ent, to, bs, size, size, rast.TILE, ec,
                                                                      tf, nc, gc, ga, ge))}
    parts["the rest (colours, loss, autograd, copies)"] = parts["whole view"] - sum(
        v for k, v in parts.items() if k != "whole view")
    numba.set_num_threads(threads)
    # the two baselines differ only in their binning: its cost in torch ops and in numba
    with torch.no_grad():
        pm, pc, pd, pv, _ = g.project(x, cam, fused=False)
    f = lambda t: t.detach().numpy()  # noqa: E731
    binning_ms = {"torch": cpu(lambda: _torch_ref.bin_gaussians_torch(pm, pc, op, pd, pv, size, size)),
                  "numba": cpu(lambda: rast.bin_gaussians(f(pm), f(pc), f(op), f(pd), f(pv), size, size))}
    return parts, binning_ms


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one tiny case (a smoke run)")
    ap.add_argument("--repeats", type=int, default=7, help="rounds of the interleaved timing")
    args = ap.parse_args()
    torch.set_num_threads(1)  # docs/results/render_notes.md: torch's pool only waits on a shared machine
    mesh = dino_mesh()
    load_start = os.getloadavg()[0]
    repeats = args.repeats
    cases = []
    for n, size in QUICK if args.quick else CASES:
        c = run_case(mesh, n, size, args.repeats)
        cases.append(c)
        print(f"  {n} Gaussians {size}²: fast {c['fast_fwd_bwd_s'] * 1e3:.1f} ms, "
              f"reference {c['reference_fwd_bwd_s'] * 1e3:.0f} ms, lean {c['lean_fwd_bwd_s'] * 1e3:.0f} ms",
              file=sys.stderr)
    parts, binning_ms = split(mesh, *(QUICK[0] if args.quick else CASES[-1]), max(args.repeats, 7))
    load = os.getloadavg()[0]
    machine = (f"{platform.node() or 'vm'} {platform.machine()} {os.cpu_count()} cores, "
               f"numba {numba.__version__} ({numba.threading_layer()} layer, {numba.get_num_threads()} threads), "
               f"torch {torch.__version__} ({torch.get_num_threads()} threads), load {load:.1f} at the end")
    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    data = {"machine": machine, "date": date, "load_start": load_start, "repeats": repeats, "cases": cases,
            "split_cpu_ms": parts, "binning_cpu_ms": binning_ms}
    text = markdown(data)
    print(text)
    if args.quick:
        return
    out = ROOT / "docs" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / "render.md").write_text(text)
    (out / "render.json").write_text(json.dumps(data, indent=1))
    print(f"wrote {out / 'render.md'} and {out / 'render.json'}", file=sys.stderr)


def markdown(data: dict) -> str:
    """docs/results/render.md from the measured data alone (interpretation: render_notes.md, by hand)."""
    cases, parts, binning_ms = data["cases"], data["split_cpu_ms"], data["binning_cpu_ms"]
    rows = ["| Gaussians | resolution | tile pairs | fast fwd (ms) | fast fwd+bwd (ms) | fast fwd+bwd CPU (ms) "
            "| fast fwd+bwd 1 thread CPU (ms) | reference fwd (ms) | reference fwd+bwd (ms) | ratio (wall) "
            "| ratio (CPU) | lean fwd+bwd (ms) | ratio vs lean (wall) | ratio vs lean (CPU) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        rows.append(f"| {c['gaussians']} | {c['resolution']}² | {c['tile_pairs']} | {c['fast_fwd_s'] * 1e3:.1f} "
                    f"| {c['fast_fwd_bwd_s'] * 1e3:.1f} | {c['fast_fwd_bwd_cpu_s'] * 1e3:.1f} "
                    f"| {c['fast_fwd_bwd_1thread_cpu_s'] * 1e3:.1f} | {c['reference_fwd_s'] * 1e3:.0f} "
                    f"| {c['reference_fwd_bwd_s'] * 1e3:.0f} | {c['ratio']:.1f} | {c['ratio_cpu']:.1f} "
                    f"| {c['lean_fwd_bwd_s'] * 1e3:.0f} | {c['ratio_lean']:.1f} | {c['ratio_lean_cpu']:.1f} |")
    table = "\n".join(rows)
    whole = parts["whole view"]
    split_rows = ["| part (fast view, one numba thread) | CPU (ms) | share |", "|---|---|---|"]
    split_rows += [f"| {k} | {v:.1f} | {100 * v / whole:.0f} % |" for k, v in parts.items()]
    split_table = "\n".join(split_rows)
    if not any(c["gaussians"] == 20000 and c["resolution"] == 256 for c in cases):  # a --quick run
        return f"{table}\n\n{split_table}\n"
    big = next(c for c in cases if c["gaussians"] == 20000 and c["resolution"] == 256)
    machine, load_start, date, repeats = data["machine"], data["load_start"], data["date"], data["repeats"]
    ref_wait = big["reference_fwd_bwd_s"] / big["reference_fwd_bwd_cpu_s"]
    text = f"""# CPU Gaussian splatting (bench/render.py)

Machine: {machine} (at the start: {load_start:.1f}); {date}.

One view of the sample dinosaur (sample_data/dino, 256 vertices, scaled to 0.2 m) with N Gaussians seeded
as `rsl fit-gaussians` seeds them (host tets ∝ volume, 4× denser at the surface, opacity 0.88, random
colours), filling about {big['coverage'] * 100:.0f} % of the image.  "fwd" is the whole render path the
adapt stage runs — centres and F Σ Fᵀ from the vertex positions, EWA projection, colours, rasterization,
background — and "fwd+bwd" adds an L1 loss and the backward pass to the float64 vertex positions and all
appearance parameters.  "fast" runs binding and projection fused in numba (stages/render/bind_project.py)
and the numba tile rasterizer (stages/render/rasterize.py), 2 threads.  The **reference** is the same render
entirely in PyTorch: binding and projection as torch ops (the twin the tests hold bind_project.py to) and
the tiled rasterizer of stages/render/_torch_ref.py — tile binning in torch ops (footprint boxes →
(tile, depth rank) keys → sort → per-tile ranges; the tests hold its lists equal to the numba binning's),
then dense maths per 16×16 tile over the tile's list and an autograd backward.  **Lean** is that rasterizer
on the compiled numba binning (the reference of earlier runs of this benchmark), kept as an extra column.
The dense pixels × Gaussians twin would hold {big['gaussians'] * big['resolution'] ** 2 * 4 / 1e9:.1f} GB
(N × pixels float32) in each of several intermediates at 20K/256² and is kept for the tests.  Timing is interleaved: each of {repeats} rounds runs every variant once (the fast ones
three times), so load from other jobs falls on all alike; the table gives medians, and the ratios are
reference (or lean) over fast from the same run.  CPU columns are process CPU time (all threads): this
machine's 2 cores are shared with other jobs (see the load above), so wall times are pessimistic and
"1 thread CPU" — the fast path pinned to one numba thread — is the contention-free cost on one core.
Torch runs with one intra-op thread for every variant, as `rsl fit-gaussians` sets it.

{table}

Result: forward+backward of one 256² view of 20K Gaussians took {big['fast_fwd_bwd_s'] * 1e3:.0f} ms wall
({big['fast_fwd_bwd_1thread_cpu_s'] * 1e3:.0f} ms of CPU on one thread) against
{big['reference_fwd_bwd_s'] * 1e3:.0f} ms for the pure-PyTorch render: {big['ratio']:.1f}× in wall time,
{big['ratio_cpu']:.1f}× in CPU time.  Against the lean baseline ({big['lean_fwd_bwd_s'] * 1e3:.0f} ms) the
ratios are {big['ratio_lean']:.1f}× (wall) and {big['ratio_lean_cpu']:.1f}× (CPU).  Targets: ≤ 100 ms
({"met" if big['fast_fwd_bwd_s'] <= 0.1 else "not met"}) and ≥ 20× against the pure-PyTorch render
({"met" if min(big['ratio'], big['ratio_cpu']) >= 20 else "not met"} in both columns); against the lean
baseline {"met" if min(big['ratio_lean'], big['ratio_lean_cpu']) >= 20 else "not met"} in both columns.  The
reference's wall time was {ref_wait:.2f}× its CPU time, the fast view's
{big['fast_fwd_bwd_s'] / big['fast_fwd_bwd_1thread_cpu_s']:.2f}× its one-thread CPU time.  The two baselines
differ only in their binning, which cost {binning_ms['torch']:.1f} ms in torch ops and {binning_ms['numba']:.1f} ms
in numba at 20K/256² (one-thread CPU), against {big['reference_fwd_bwd_cpu_s'] * 1e3:.0f} ms for the whole
reference view.

One-thread CPU split of the fast 20K/256² view (numba pinned to one thread; each part timed on its own,
"the rest" is the whole minus the parts):

{split_table}

Interpretation, earlier runs and what changed in the code: the hand-written, dated
[render_notes.md](render_notes.md), which this script does not rewrite.
"""
    return text


if __name__ == "__main__":
    main()
