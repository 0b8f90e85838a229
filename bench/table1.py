"""The paper's Table 1 on this CPU: per-frame cost of online system identification (`rsl adapt`, vision
loss, one Adam step per frame) in the reduced and in the full space, for four cases shaped like the
paper's — Bar (≈10K DOFs, r = 30, w = 3, c = 4), Tower (two regions, pulled by a cable; ≈12K DOFs,
r = 10, w = 3, c = 2), Dinosaur (≈15K DOFs, r = 100, w = 5, c = 8) and Gingerbread (≈3.6K DOFs, r = 80,
w = 15, c = 1) — beside the paper's RTX 4090 figures.

Each case: `rsl synth` makes a capture from the case's tet mesh (its truth mesh is the workspace's
mesh, linear tets — `tetrahedralize --order 1` — so the DOF counts are the paper's n), fit-gaussians fits the Gaussians, generate-data + train-subspace build a subspace of dimension r,
then `rsl adapt` runs in the reduced space and in the full space on the same frames, one after the
other in this process. Per frame: forward, backward and render are adapt.h5's time_forward_s,
time_backward_s and time_render_s, total its time_total_s; the value is the median over the frames after
the first whose window no longer holds frame 0 (frame > w): every timed frame simulates and differentiates w
frames from stored states, and none pays a first call's compilation (JAX traces the window that starts from
stored states at frame w, the start-state window at frames 0..w−1; numba compiles at frame 0) — adapt.h5 keeps
those frames' times, which show it.  (Earlier runs took frame ≥ w, so frame w's compilation entered the median
of the 2 timed frames of --quick.)
The ratio is full total / reduced total of the same run.  The process CPU time per frame (all threads) is
measured as well, between adapt's per-frame progress calls (cpu_per_frame.json beside each adapt.h5): on a
shared machine the wall times include waiting for the cores.

    python bench/table1.py                  # full size (Table 1's cameras and windows, 128² images)
    nice python bench/table1.py --quick     # sized down (fewer frames and Gaussians, 64² images)

Writes docs/results/table1.md and table1.json.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
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
sys.path.insert(0, str(ROOT))

from stages.steps import adapt, calibrate, fit_gaussians, generate_data, synth, tetrahedralize, train_subspace  # noqa: E402
from stages.artefacts import AdaptArtefact  # noqa: E402
from stages.progress import SilentReporter  # noqa: E402

RESULTS = ROOT / "docs" / "results"
DINO_NPZ = ROOT / "bench" / "data" / "dino_tetwild_5k.npz"

# The paper's Table 1 (../shared/paper/realsimloop.tex, table "table-problems-settings": "Parameters and
# results of experiments evaluated in this work", all on an NVIDIA RTX 4090): per frame, seconds.
PAPER = {
    "Bar": {"model": "Material Bar", "n": "10K", "r": 30, "w": 3, "c": 4, "forward_s": 0.17, "backward_s": 0.14,
            "render_s": 0.22, "total_reduced_s": 0.53, "total_full_s": 3.30, "ratio": 6.23},
    "Tower": {"model": "Eiffel tower", "n": "12K", "r": 10, "w": 3, "c": 2, "forward_s": 0.06, "backward_s": 0.07,
              "render_s": 0.05, "total_reduced_s": 0.18, "total_full_s": 1.36, "ratio": 7.56},
    "Dinosaur": {"model": "Dinosaur", "n": "15K", "r": 100, "w": 5, "c": 8, "forward_s": 0.24, "backward_s": 0.32,
                 "render_s": 0.45, "total_reduced_s": 1.01, "total_full_s": 7.77, "ratio": 7.69},
    "Gingerbread": {"model": "Gingerbread Joy", "n": "3.6K", "r": 80, "w": 15, "c": 1, "forward_s": 0.19,
                    "backward_s": 0.17, "render_s": 0.22, "total_reduced_s": 0.58, "total_full_s": 1.46,
                    "ratio": 2.52},
}
PAPER_CITATION = ("RealSimLoop (SIGGRAPH Asia 2026), Table 1 (\\label{table-problems-settings}), "
                  "measured on an NVIDIA RTX 4090 GPU")


@dataclasses.dataclass
class Case:
    name: str  # a key of PAPER
    shape: str  # how the mesh is made
    scenario: str  # rsl synth scenario
    r: int
    w: int
    c: int
    region: str = ""  # rsl synth --region (a second material region)


CASES = [
    Case("Bar", "box 40×8×8 cells, 25 × 5 × 5 cm", "cable", 30, 3, 4),
    Case("Tower", "box 9×9×40 cells, 5.6 × 5.6 × 25 cm, upper half stiffer", "cable", 10, 3, 2,
         region="top=3e5@z>0.5"),
    Case("Dinosaur", "bench/data/dino_tetwild_5k.npz (fTetWild of 25cm_dino_low)", "push", 100, 5, 8),
    Case("Gingerbread", "flat slab 19×14×3 cells, 19 × 14 × 3 cm", "twist", 80, 15, 1),
]


class Log(SilentReporter):
    def summary(self, message: str) -> None:
        super().summary(message)
        print(f"  [{time.strftime('%H:%M:%S')}] {message}", flush=True)


LOG = Log()


class CpuLog(Log):
    """Log that also records the process CPU time (all threads) between adapt's per-frame progress calls."""

    def __init__(self) -> None:
        super().__init__()
        self.cpu: list[float] = []

    @contextlib.contextmanager
    def task(self, description, total):
        clock, last = self, [time.process_time()]

        class T:
            def advance(self, n=1, **fields):
                now = time.process_time()
                clock.cpu.append(now - last[0])
                last[0] = now

        yield T()


def make_mesh(case: Case, path: Path) -> None:
    """The case's tet mesh as a MEDIT file."""
    import meshio

    from stages.sim.meshgen import box_tets

    if case.name == "Bar":
        v, t = box_tets((40, 8, 8), (0.25, 0.05, 0.05))
    elif case.name == "Tower":
        v, t = box_tets((9, 9, 40), (0.05625, 0.05625, 0.25))
    elif case.name == "Gingerbread":
        v, t = box_tets((19, 14, 3), (0.19, 0.14, 0.03))
    else:
        d = np.load(DINO_NPZ)
        v, t = np.asarray(d["vertices"], np.float64), np.asarray(d["tets"], np.int64)
    meshio.write(str(path), meshio.Mesh(v, [("tetra", t)]), file_format="medit")


def build(case: Case, work: Path, frames: int, resolution: int, gaussians: int, fit_iters: int,
          wait: bool = True) -> tuple[Path, Path]:
    """Capture and workspace with mesh.h5, cameras.h5, gaussians.h5, snapshots.h5 and subspace.h5."""
    root = work / case.name
    cap, ws = root / "cap", root / "ws"
    mesh = root / "object.mesh"
    root.mkdir(parents=True, exist_ok=True)
    lock = root / ".building"  # another process building this case (--build-only): wait for it
    while wait and lock.exists():
        time.sleep(10)
    if not mesh.exists():
        make_mesh(case, mesh)
    if not (cap / "capture.toml").exists():
        synth.run(synth.SynthConfig(mesh=mesh, out=cap, scenario=case.scenario, cameras=case.c, frames=frames,
                                    resolution=resolution, young=1e5, region=case.region, markers=0,
                                    calib_views=0, seed=0), LOG)
        toml = cap / "capture.toml"
        toml.write_text(toml.read_text().replace('mesh = "object.obj"', 'mesh = "truth/object.mesh"'))
    if not (ws / "mesh.h5").exists():
        tetrahedralize.run(tetrahedralize.TetrahedralizeConfig(capture=cap, workspace=ws, order=1), LOG)
        calibrate.run(calibrate.CalibrateConfig(capture=cap, workspace=ws, from_json=str(cap / "cameras.json")), LOG)
    if not (ws / "gaussians.h5").exists():
        fit_gaussians.run(fit_gaussians.FitGaussiansConfig(capture=cap, workspace=ws, iterations=fit_iters,
                                                           gaussians=gaussians), LOG)
    if not (ws / "snapshots.h5").exists():
        seq_frames = 20
        sequences = max(4, -(-(case.r + 10) // seq_frames))  # PCA of dimension r needs more than r snapshots
        generate_data.run(generate_data.GenerateDataConfig(capture=cap, workspace=ws, sequences=sequences,
                                                           frames=seq_frames, workers=1), LOG)
    if not (ws / "subspace.h5").exists():
        train_subspace.run(train_subspace.TrainSubspaceConfig(workspace=ws, capture=cap, dim=case.r, kind="pca"),
                           LOG)
    return cap, ws


def run_adapt(cap: Path, ws: Path, out: Path, space: str, w: int, n_frames: int) -> AdaptArtefact:
    out.mkdir(parents=True, exist_ok=True)
    for f in ("mesh.h5", "cameras.h5", "gaussians.h5", "subspace.h5"):
        shutil.copy(ws / f, out / f)
    kw = dict(capture=cap, workspace=out, space=space, loss="vision", window=w, iters_per_frame=1,
              frames=f"0:{n_frames}")
    if "estimator" in {f.name for f in dataclasses.fields(adapt.AdaptConfig)}:
        kw["estimator"] = "adam"  # the paper's gradient step
    log = CpuLog()
    art = AdaptArtefact.load(adapt.run(adapt.AdaptConfig(**kw), log))
    (out / "cpu_per_frame.json").write_text(json.dumps(log.cpu))  # per frame, in adapt.h5's frame order
    return art


def per_frame(art: AdaptArtefact, w: int, cpu_file: Path | None = None) -> dict:
    """Medians over the frames after the first whose window starts from stored states (frame > w), s."""
    sel = art.frames > w
    if not sel.any():
        raise SystemExit(f"adapt.h5 holds no frame > w = {w}; run more frames.")
    med = lambda a: float(np.median(np.asarray(a)[sel]))  # noqa: E731
    cpu = json.loads(cpu_file.read_text()) if cpu_file is not None and cpu_file.exists() else None
    return {"forward_s": med(art.time_forward_s), "backward_s": med(art.time_backward_s),
            "render_s": med(art.time_render_s), "total_s": med(art.time_total_s), "frames_timed": int(sel.sum()),
            "cpu_s": med(cpu) if cpu is not None and len(cpu) == len(sel) else None}


def measure(case: Case, work: Path, timed: int, resolution: int, gaussians: int, fit_iters: int) -> dict:
    n_frames = case.w + 1 + timed  # frames 0..w: the compiling ones (per_frame); the capture has w + timed + 2
    t0 = time.perf_counter()
    cap, ws = build(case, work, n_frames + 2, resolution, gaussians, fit_iters)
    setup_s = time.perf_counter() - t0
    run_adapt(cap, ws, work / case.name / "reduced", "reduced", case.w, n_frames)
    run_adapt(cap, ws, work / case.name / "full", "full", case.w, n_frames)
    return dict(collect(case, work, resolution, gaussians), setup_s=setup_s)


def collect(case: Case, work: Path, resolution: int, gaussians: int) -> dict:
    """The row of a case from the adapt.h5 files its reduced and full runs wrote under ``work``."""
    from stages.artefacts import MeshArtefact

    ws = work / case.name / "ws"
    red = AdaptArtefact.load(work / case.name / "reduced" / "adapt.h5")
    full = AdaptArtefact.load(work / case.name / "full" / "adapt.h5")
    tr, tf = (per_frame(a, case.w, work / case.name / s / "cpu_per_frame.json")
              for a, s in ((red, "reduced"), (full, "full")))
    mesh = MeshArtefact.load(ws / "mesh.h5")
    return {"name": case.name, "shape": case.shape, "scenario": case.scenario, "dofs": 3 * mesh.n_vertices,
            "tets": int(mesh.n_tets), "regions": list(mesh.region_names), "r": case.r, "w": case.w, "c": case.c,
            "resolution": resolution, "gaussians": gaussians, "reduced": tr, "full": tf,
            "ratio": tf["total_s"] / tr["total_s"], "physics_ratio":
            (tf["forward_s"] + tf["backward_s"]) / (tr["forward_s"] + tr["backward_s"]),
            "paper": PAPER[case.name]}


def markdown(data: dict) -> str:
    s = data["settings"]
    lines = ["# Table 1 on this CPU", "",
             f"Machine: {data['machine']}; {data['date']}; {'sized-down run (--quick)' if s['quick'] else 'full-size run'}: "
             f"{s['timed_frames']} timed frames per case (frames w + 1 … w + timed), images {s['resolution']}², "
             f"{s['gaussians']} Gaussians, PCA subspace (train-subspace --kind pca), vision loss, one Adam step "
             f"per frame; "
             + (f"wall time of the whole run {data['wall_s'] / 60:.1f} min." if data.get("wall_s") else
                "rows collected from the adapt.h5 files of the runs (bench/table1.py --collect)."),
             "",
             "Per frame, seconds (median over the timed frames). Reduced: forward / backward / render / total; "
             "full: total; ratio = full total / reduced total, both from the same run. Paper: "
             + PAPER_CITATION + ".", "",
             "| case | DOFs | r | w | c | fwd | bwd | render | total T_r | total T_f | ratio | "
             "paper n | paper fwd | paper bwd | paper 3DGS | paper T_r | paper T_f | paper ratio |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | "
             "---: | ---: | ---: | ---: |"]
    for c in data["cases"]:
        r, f, p = c["reduced"], c["full"], c["paper"]
        lines.append(f"| {c['name']} | {c['dofs']} | {c['r']} | {c['w']} | {c['c']} | {r['forward_s']:.3g} | "
                     f"{r['backward_s']:.3g} | {r['render_s']:.3g} | {r['total_s']:.3g} | {f['total_s']:.3g} | "
                     f"{c['ratio']:.2f}× | {p['n']} | {p['forward_s']} | {p['backward_s']} | {p['render_s']} | "
                     f"{p['total_reduced_s']} | {p['total_full_s']} | {p['ratio']}× |")
    cpu = lambda d: "–" if d.get("cpu_s") is None else f"{d['cpu_s']:.3g}"  # noqa: E731
    lines += ["", "Full space in detail (same runs); CPU = the process CPU time per frame (all threads, median over "
              "the same frames; on a shared machine the wall times above include waiting for the cores):", "",
              "| case | fwd | bwd | render | total | forward + backward ratio full / reduced | CPU reduced | CPU full | "
              "timed frames | mesh | regions |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |"]
    for c in data["cases"]:
        f = c["full"]
        lines.append(f"| {c['name']} | {f['forward_s']:.3g} | {f['backward_s']:.3g} | {f['render_s']:.3g} | "
                     f"{f['total_s']:.3g} | {c['physics_ratio']:.1f}× | {cpu(c['reduced'])} | {cpu(f)} | "
                     f"{f['frames_timed']} | {c['shape']}, "
                     f"{c['tets']} tets, `rsl synth --scenario {c['scenario']}` | {', '.join(c['regions'])} |")
    lines += ["", "Generated by bench/table1.py from table1.json.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="Sized down: 2 timed frames, 64² images, 2000 Gaussians.")
    ap.add_argument("--cases", default=",".join(c.name for c in CASES), help="Comma-separated case names.")
    ap.add_argument("--work", default="/tmp/rsl_bench_table1", help="Folder for captures and workspaces (reused).")
    ap.add_argument("--report-only", action="store_true", help="Rewrite table1.md from table1.json; run nothing.")
    ap.add_argument("--collect", action="store_true",
                    help="Measure nothing: make the table from the adapt.h5 files an earlier run of the same mode "
                         "left under --work (e.g. after that run was stopped).")
    ap.add_argument("--build-only", action="store_true",
                    help="Only build the cases' captures and workspaces (e.g. in a second process ahead of the "
                         "measuring one, which waits for them); measure nothing.")
    args = ap.parse_args()
    if args.report_only:
        data = json.loads((RESULTS / "table1.json").read_text())
        (RESULTS / "table1.md").write_text(markdown(data))
        print(markdown(data))
        return
    timed, resolution, gaussians, fit_iters = (2, 64, 2000, 10) if args.quick else (4, 128, 5000, 20)
    work = Path(args.work) / ("quick" if args.quick else "full")
    by_name = {c.name: c for c in CASES}
    unknown = [n for n in args.cases.split(",") if n not in by_name]
    if unknown:
        raise SystemExit(f"--cases: unknown case {unknown[0]!r}; the cases are {', '.join(by_name)}.")
    wanted = [by_name[n] for n in args.cases.split(",")]  # in the order given
    if args.build_only:
        for case in wanted:
            lock = work / case.name / ".building"
            lock.parent.mkdir(parents=True, exist_ok=True)
            lock.touch()
            try:
                build(case, work, case.w + timed + 2, resolution, gaussians, fit_iters, wait=False)
            finally:
                lock.unlink()
        return
    t0 = time.perf_counter()
    cases = []
    for case in wanted:
        print(f"== {case.name}", flush=True)
        if args.collect:
            cases.append(collect(case, work, resolution, gaussians))
        else:
            cases.append(measure(case, work, timed, resolution, gaussians, fit_iters))
    load = os.getloadavg()[0]
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}, "
                       f"load average {load:.1f} at the end (a shared machine)",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "settings": {"quick": args.quick, "timed_frames": timed, "resolution": resolution,
                         "gaussians": gaussians, "fit_iterations": fit_iters, "subspace": "pca"},
            "wall_s": None if args.collect else time.perf_counter() - t0, "collected": args.collect,
            "paper_citation": PAPER_CITATION,
            "cases": sorted(cases, key=lambda c: [k.name for k in CASES].index(c["name"]))}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "table1.json").write_text(json.dumps(data, indent=1))
    (RESULTS / "table1.md").write_text(markdown(data))
    print(markdown(data))


if __name__ == "__main__":
    main()
