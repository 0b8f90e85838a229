"""Region sweep: is each region's loss lowest at its own E_true?  (the two-region beam of bench/accuracy.py)

The beam of docs/results/accuracy.md — sample_data/bar pulled by a cable, its far half (x > 0.5) three times
stiffer (E0 = 1e5 Pa, 3 E0), ν 0.45, 36 frames, start = equilibrium — filmed by `rsl synth` with a truth of P2 tets
on the shipped mesh, hard handles and N implicit substeps per frame (--truth-substeps; default 24, converged in time:
docs/results/calibration_frames.md).  Per row, the whole-sequence marker loss over a grid of ONE region's E, the
other region held at its E_true and ν at the truth's (stages.sweep.sweep(region=...), `rsl evaluate --sweep-region`),
full-space simulation from the declared start, minimum refined by a parabola in log E.  A row's mesh is

    rsl M      rsl's own mesh: `rsl tetrahedralize --order 2 --max-tets M` (1500: the accuracy table's)
    truth      the truth's own mesh (truth/object.vtu, P2): with S = N the truth itself (the loss vanishes at
               E_true), with another S the time step alone

and S its implicit substeps per frame (6: rsl adapt's default).  Rows are MESH/S/REGION, e.g. 'rsl1500/6/stiff'.

    .venv/bin/python bench/region_sweep.py [--rows ...] [--truth-substeps 24] [--scales 0.7,...] [--out docs/results]

With RSL_BENCH_REUSE=1 in the environment, the capture and meshes already in --work are reused.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402
import accuracy as acc  # noqa: E402  (the beam's recipe: one definition for both pages)

FRAMES = 36
DEFAULT_ROWS = "rsl1500/6/body,rsl1500/6/stiff,truth/6/stiff,rsl1500/24/stiff,rsl4000/6/stiff"
SCALES = (0.7, 0.82, 0.95, 1.1, 1.3)


def truth_mesh(cap: Path, density: float):
    """The truth's P2 mesh (CAP/truth/object.vtu, its 'region' cell data) as a MeshArtefact, regions body, stiff."""
    import meshio

    from stages.artefacts import mesh_artefact

    m = meshio.read(str(cap / "truth" / "object.vtu"))
    region = np.asarray(m.cell_data["region"][0], np.int64)
    return mesh_artefact(np.asarray(m.points, float), np.asarray(m.cells_dict["tetra10"]), density, region,
                         ("body", "stiff"))


def parse_row(spec: str) -> tuple[str, int, str]:
    mesh, s, region = spec.split("/")
    if not (mesh == "truth" or (mesh.startswith("rsl") and mesh[3:].isdigit())):
        raise SystemExit(f"row {spec!r}: the mesh is 'truth' or 'rslM' (M: --max-tets)")
    if region not in ("body", "stiff"):
        raise SystemExit(f"row {spec!r}: the region is body or stiff")
    return mesh, int(s), region


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", default=DEFAULT_ROWS, help="MESH/S/REGION rows, comma-separated")
    ap.add_argument("--truth-substeps", type=int, default=24)
    ap.add_argument("--scales", default=",".join(map(str, SCALES)), help="grid of E / E_true, comma-separated")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_region_sweep"))
    ap.add_argument("--from-json", action="store_true", help="re-write region_sweep.md/.png from --out's json")
    a = ap.parse_args()
    if a.from_json:
        data = json.loads((a.out / "region_sweep.json").read_text())
        write(data["cases"], a.out, data["truth_substeps"], data)
        return

    from stages.artefacts import KIND_FILES, MeshArtefact
    from stages.capture import load_capture, read_truth
    from stages.sweep import sweep

    rows = [parse_row(r) for r in a.rows.split(",") if r]
    scales = np.array(sorted(float(x) for x in a.scales.split(",")))
    n_truth = a.truth_substeps
    a.work.mkdir(parents=True, exist_ok=True)
    cap_dir = pl.foreign_capture(a.work / f"beam_n{n_truth}", acc.scene_args("beam", FRAMES), start="equilibrium",
                                 frames=FRAMES, substeps=n_truth, poisson=acc.POISSON)
    cap = load_capture(cap_dir)
    truth = read_truth(cap)
    names = ["body", "stiff"]
    e_true = np.array([truth.young[0, truth.region_names.index(r)] for r in names])
    cases = []
    for mesh_kind, S, region in rows:
        if mesh_kind == "truth":
            mesh = truth_mesh(cap_dir, cap.density)
        else:
            ws = pl.mesh(cap_dir, a.work / f"ws_{mesh_kind}_n{n_truth}", order=2, max_tets=int(mesh_kind[3:]))
            mesh = MeshArtefact.load(ws / KIND_FILES["mesh"])
        i = names.index(region)
        base = np.array([e_true[names.index(r)] for r in mesh.region_names])
        t0 = time.perf_counter()
        res = sweep(cap, mesh, e_true[i] * scales, "markers", poisson=acc.POISSON, substeps=S, base_young=base,
                    region=region)
        cases.append({"mesh": mesh_kind, "substeps": S, "region": region, "truth_substeps": n_truth,
                      "elements": int(res.info["n_elements"]), "vertices": int(res.info["n_vertices"]),
                      "young_true": float(e_true[i]), "grid": res.young.tolist(), "loss_values": res.loss.tolist(),
                      "young_min": res.young_min, "ratio": res.young_min / e_true[i], "interior": res.interior,
                      "curvature": _curvature(res), "seconds": time.perf_counter() - t0,
                      "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M")})
        print(_row(cases[-1]), flush=True)
    write(cases, a.out, n_truth)


def _curvature(res) -> float:
    """d² ln L / d(ln E)² at the grid minimum (3-point, its neighbours): how sharply the data tell the region's E
    (NaN at a grid end)."""
    i = res.i_min
    if not 0 < i < len(res.young) - 1:
        return float("nan")
    x, y = np.log(res.young[i - 1:i + 2]), np.log(res.loss[i - 1:i + 2])
    h0, h1 = x[1] - x[0], x[2] - x[1]
    return float(2 * (h0 * (y[2] - y[1]) - h1 * (y[1] - y[0])) / (h0 * h1 * (h0 + h1)))


def _mesh_label(c: dict) -> str:
    return "the truth's (P2)" if c["mesh"] == "truth" else f"rsl's, --max-tets {c['mesh'][3:]} (P2)"


def _row(c: dict) -> str:
    edge = "" if c["interior"] else " (grid end)"
    g = np.asarray(c["grid"]) / c["young_true"]
    return (f"| {c['region']} | {_mesh_label(c)} | {c['elements']} | {c['substeps']} | "
            f"{len(g)}: {g.min():.2f}–{g.max():.2f} | {c['ratio']:.3f}{edge} | {100 * (c['ratio'] - 1):+.1f} % | "
            f"{c['curvature']:.2f} | {min(c['loss_values']):.3g} | {c['seconds']:.0f} | {c['date']} |")


def write(cases: list[dict], out: Path, n_truth: int, previous: dict | None = None) -> None:
    """region_sweep.{json,md,png} of the rows (``previous``: the json they were read from, its machine and date)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = previous or {
        "machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "truth_substeps": n_truth, "cases": cases}
    (out / "region_sweep.json").write_text(json.dumps(data, indent=1))
    head = ("| region swept | rsl's mesh | tets | substeps per frame | grid: points, E/E_true | E_min / E_true | "
            "bias | "
            "curvature d² ln L / d(ln E)² | lowest loss on the grid (m²) | time (s) | measured (UTC) |\n"
            "| --- | --- | ---: | ---: | --- | --- | --- | ---: | ---: | ---: | --- |")
    table = "\n".join([head] + [_row(c) for c in cases])
    within = [c for c in cases if abs(c["ratio"] - 1) <= 0.03]
    md = (f"# Region sweep: is each region's loss lowest at its own E?\n\n"
          f"Truth: the two-region beam of [accuracy.md](accuracy.md) (sample_data/bar pulled by a cable, the far half "
          f"x > 0.5 three times stiffer: body {acc.E0:g} Pa, stiff {3 * acc.E0:g} Pa; ν = {acc.POISSON}), P2 tets "
          f"on the shipped mesh, hard handles, {n_truth} implicit substeps per "
          f"frame, start = equilibrium, {FRAMES} frames, 40 markers.  Each row: the whole-sequence marker loss over a "
          f"grid of one region's E, the other region at its E_true, ν at the truth's, full-space simulation from the "
          f"declared start (`rsl evaluate --sweep --sweep-region`); the minimum refined by a parabola in log E.  "
          f"Curvature: how sharply the loss tells that region's E.  A row on the truth's own mesh at its {n_truth} "
          f"substeps is the truth's own model: its minimum checks the sweep itself.\n\n{table}\n\n"
          f"{len(within)} of {len(cases)} minima lie within 3 % of E_true.\n\n"
          f"Machine: {data['machine']}; date {data['date']}.  Produced by `bench/region_sweep.py`.\n\n"
          f"![loss over each region's E](region_sweep.png)\n")
    (out / "region_sweep.md").write_text(md)
    regions = sorted({c["region"] for c in cases})
    fig, axes = plt.subplots(1, len(regions), figsize=(6.5 * len(regions), 4.5), squeeze=False)
    for region, ax in zip(regions, axes[0]):
        for c in (c for c in cases if c["region"] == region):
            y = np.asarray(c["loss_values"])
            ax.plot(np.asarray(c["grid"]) / c["young_true"], y, "o-", ms=3,
                    label=f"{_mesh_label(c)}, {c['substeps']} substeps")
            ax.axvline(c["ratio"], color=ax.lines[-1].get_color(), ls=":", lw=1)
        ax.axvline(1.0, color="k", lw=1)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"E / E_true of region {region} (the other at its truth)")
        ax.set_ylabel("marker loss, whole sequence (m²)")
        ax.set_title(f"region {region}, truth {n_truth} substeps per frame")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "region_sweep.png", dpi=110)
    print(table)


if __name__ == "__main__":
    main()
