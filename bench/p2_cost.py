"""What quadratic (P2, 10-node) tets cost in the reduced space: per-frame forward + backward time of the
bar-like case at r = 30 with linear tets (≈11K DOFs) and with quadratic tets on a coarser grid of about the
same DOFs, measured in the same run (bench/reduced_vs_full.py's run_case for both).

    .venv/bin/python bench/p2_cost.py [--quick] [--sequences 6] [--frames 16] [--epochs 300]

Prints a Markdown table and writes docs/results/p2_cost.md and .json.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import reduced_vs_full as rvf  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CASES = ("bar", "bar_p2")


def table(cases: list[dict]) -> str:
    head = ("| case | order | DOFs | elements | quadrature points | cubature points | r | reduced fwd s "
            "| reduced bwd s | reduced fwd+bwd s | full fwd s | full bwd s | trajectory error |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    return head + "".join(
        f"| {c['name']} | P{c['order']} | {c['dofs']} | {c['tets']} | {c['quadrature_points']} | "
        f"{c['cubature_tets']} | {c['r']} | {c['reduced_forward_s']:.4f} | {c['reduced_backward_s']:.4f} | "
        f"{c['reduced_forward_s'] + c['reduced_backward_s']:.4f} | {c['full_forward_s']:.4f} | "
        f"{c['full_backward_s']:.4f} | {c['trajectory_error_rel']:.2%} |\n" for c in cases)


def markdown(machine: str, date: str, cases: list[dict]) -> str:
    by = {c["name"]: c for c in cases}
    lines = []
    if "bar" in by and "bar_p2" in by:
        p1, p2 = by["bar"], by["bar_p2"]
        t1 = p1["reduced_forward_s"] + p1["reduced_backward_s"]
        t2 = p2["reduced_forward_s"] + p2["reduced_backward_s"]
        lines.append(f"Reduced forward + backward per frame: P1 {t1:.4f} s ({p1['dofs']} DOFs, "
                     f"{p1['cubature_tets']} cubature points), P2 {t2:.4f} s ({p2['dofs']} DOFs, "
                     f"{p2['cubature_tets']} cubature points): P2 / P1 = {t2 / t1:.2f}. Full space: P1 "
                     f"{p1['full_forward_s'] + p1['full_backward_s']:.3f} s, P2 "
                     f"{p2['full_forward_s'] + p2['full_backward_s']:.3f} s per frame.")
    return ("# What quadratic tets cost in the reduced space\n\n"
            f"Machine: {machine}; {date}.\n\n" + table(cases) + "\n" + "\n".join(lines) + "\n\n"
            "What was measured (bench/p2_cost.py, with bench/reduced_vs_full.py's run_case for every row, in one "
            "run): the 36 cm cantilever bar under gravity whose clamp moves and turns (E = 50 kPa, ν = 0.45), "
            "full-space snapshots, an autoencoder of latent size r on a PCA layer and an optimised cubature over "
            "quadrature points (one per linear tet, four per quadratic tet); reduced forward = median seconds "
            "of one warm implicit-Euler step on a held-out sequence, backward = the window adjoint (w = 3) "
            "divided by w; both solvers stop at a relative residual of 1e-6. \"bar\" has linear tets on a "
            "36×9×9 grid, \"bar_p2\" quadratic tets on an 18×4×4 grid (about the same DOFs). Trajectory error = "
            "mean vertex distance of the reduced to the full trajectory over the bounding-box diagonal.\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small meshes (smoke test; nothing written)")
    ap.add_argument("--sequences", type=int, default=6)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--cubature-points", type=int, default=300)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    args = ap.parse_args()
    cases = [rvf.run_case(name, args.quick, args.sequences, args.frames, args.epochs, args.cubature_points,
                          lambda s: print(s, flush=True)) for name in CASES]
    print(table(cases))
    if args.quick:
        return
    args.out.mkdir(parents=True, exist_ok=True)
    machine = (f"{platform.node()} {platform.machine()} {os.cpu_count()} cores, "
               f"load {os.getloadavg()[0]:.1f} at the end")
    date = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    (args.out / "p2_cost.json").write_text(json.dumps({"machine": machine, "date": date, "cases": cases}, indent=1))
    (args.out / "p2_cost.md").write_text(markdown(machine, date, cases))


if __name__ == "__main__":
    main()
