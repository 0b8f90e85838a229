"""Handle and obstacle forces of the full-space replay against a truth converged in time (issue 12).

`rsl export --forces`, `rsl evaluate` and `rsl report` compute the forces of an online adapt run by replaying the
controls in the full space with θ(t) from the capture's start state, S implicit-Euler steps per frame, optionally
Richardson-extrapolated over S and 2S, with θ(t) as adapt.h5 records it or smoothed per segment
(stages/forces.py: replay_forces, replay_theta; `--force-substeps`, `--force-extrapolate`, `--force-theta`).
Without material damping the dynamic part of a hard handle's reaction carries implicit Euler's numerical damping
and converges only at first order in Δt / S — on both sides: the truth's forces too.  ``--truth-damping β``: truths
of a damped material ([material] damping = β declared, the replays simulate it), where the motion is damped by the
material rather than by the integrator alone.

Captures as bench/accuracy.py makes them (`rsl synth --truth-order 2 --handles hard`; sample_data/bar pulled by a
cable with E stepping E0 → 2E0 → 4E0 for each start state, the two-region beam), each simulated with several
substep counts (``--truth-substeps``, e.g. 12,24).  The REFERENCE is the Richardson extrapolation of the two finest
truths, frame by frame (2 F_{2N} − F_N), or the single truth when only one is given.  rsl's mesh:
`rsl tetrahedralize --order 2 --max-tets 1500`.

    --part time    (1) each truth against the reference (their convergence);
                   (2) θ(t) = the truth's E(t), ν: replays with plain S and Richardson (S, 2S) for every S, 2S in
                       ``--substeps``: error against the reference vs CPU.
    --part theta   θ(t) of existing adapt.h5 (``--adapt-ws case=WS,...``; their mesh.h5 is used) under each θ
                   rule (online = as recorded; segment = the last estimate of each segment between the changes the
                   estimator detected; lagL = the estimate L frames later, within the segment; smoothed = the
                   Rauch–Tung–Striebel smoother under the gn filter's random walk, stages.forces.rts_theta;
                   smoothedE = its E with ν as recorded), replayed with each
                   of ``--replays`` (S = plain S substeps, rS = Richardson (S, 2S)); the true E alongside, and
                   each rule's forces also against the true E replayed the same way (the part of the error the
                   adapted θ(t) adds, free of the replay's own time-step error).

Per row: the median relative error of the applied forces against the reference, pooled over handles/obstacles
and frames as `rsl evaluate` reports it (stages.forces.force_errors), and the CPU seconds of the replay(s)
(time.process_time, this process; a Richardson row costs its two replays); ratios against plain S = 1 of the same
case and θ, measured in the same run.

    nice -n 5 .venv/bin/python bench/forces.py --part time --truth-substeps 12,24 --substeps 1,2,3,6,12 \\
        --work /tmp/rsl_forces_conv --name forces_converged
    # per case (its own --truth-substeps), then --merge; each WS made by `rsl adapt CAP -w WS --space full
    # --loss markers --estimator gn --window 3 --young-init 5e4` on the bench/accuracy.py capture of the case
    nice -n 5 .venv/bin/python bench/forces.py --part theta --cases bar_equilibrium --truth-substeps 12,24,48 \\
        --replays 1,r1 --work /tmp/rsl_forces_conv --cache /tmp/rsl_forces_cache \\
        --adapt-ws bar_equilibrium=WS1,bar_equilibrium=WS2 --out OUT --name theta_bar_eq
    .venv/bin/python bench/forces.py --merge OUT/theta_bar_eq.json OUT/theta_beam.json ... --name forces_theta

With RSL_BENCH_REUSE=1, captures and meshes already in --work are reused (bench/_pipeline.py).
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(Path(__file__).resolve().parent)]
os.environ.setdefault("JAX_ENABLE_X64", "1")
os.environ.setdefault("JAX_PLATFORMS", "cpu")

import _pipeline as pl  # noqa: E402

import accuracy as acc  # noqa: E402  (the accuracy captures: the same scenes, constants and adapt mesh)

E0, POISSON, MAX_TETS, WINDOW = acc.E0, acc.POISSON, acc.MAX_TETS, acc.WINDOW
FRAMES = 36
TRUTH_DAMPING: dict = {}  # --truth-damping: {"beta": β s} declared by every truth (and simulated by the replays)
CASES = {  # name -> (scene, start): the accuracy captures (bench/accuracy.py scene_args)
    "bar_equilibrium": (lambda: acc.scene_args("bar", FRAMES), "equilibrium"),
    "bar_rest": (lambda: acc.scene_args("bar", FRAMES), "rest"),
    "beam_equilibrium": (lambda: acc.scene_args("beam", FRAMES), "equilibrium"),
    "dino_equilibrium": (lambda: acc.scene_args("dino", FRAMES), "equilibrium"),
}
APPLIED = ("applied_fx_N", "applied_fy_N", "applied_fz_N")
CACHE: dict = {}  # "dir": the replay cache folder (--cache; default WORK/cache)


def pooled(per: dict) -> float | None:
    """The median over every (handle/obstacle, frame) relative error — evaluation.json's forces
    median_relative_error."""
    errs = [e for v in per.values() for e in v["rel_error_per_frame"]]
    return float(np.median(errs)) if errs else None


def by_region(values: np.ndarray, names: list[str], want: list[str], what: str) -> np.ndarray:
    """Columns of values (T, R) in the order of the region names ``want`` (the mesh's)."""
    missing = [n for n in want if n not in names]
    if missing:
        raise SystemExit(f"{what} has no region {missing} (it has {names})")
    return np.stack([values[:, names.index(n)] for n in want], axis=1)


def extrapolated_table(coarse: list[dict], fine: list[dict]) -> list[dict]:
    """forces.csv rows of two simulations of the same frames (steps h, h/2) with the applied force Richardson-
    extrapolated per (frame, name) (stages.forces.richardson)."""
    from stages.forces import richardson

    c = {(int(r["frame"]), r["name"]): r for r in coarse}
    out = []
    for r in fine:
        q = c[(int(r["frame"]), r["name"])]
        v = richardson([q[k] for k in APPLIED], [r[k] for k in APPLIED])
        out.append({**r, **dict(zip(APPLIED, map(float, v)))})
    return out


def truths(work: Path, case: str, truth_substeps: list[int]) -> tuple[dict[int, Path], dict[int, list[dict]], list[dict]]:
    """The captures of ``case`` simulated with each truth substep count (made when missing; with TRUTH_DAMPING β
    declared), their forces.csv rows, and the reference rows (Richardson of the two finest, or the one truth)."""
    from stages.capture import read_forces_csv

    scene_fn, start = CASES[case]
    caps, rows = {}, {}
    beta = TRUTH_DAMPING.get("beta", 0.0)
    for n in truth_substeps:
        caps[n] = pl.foreign_capture(work / (f"{case}_truth{n}" + (f"_b{beta:g}" if beta else "")), scene_fn(),
                                     start=start, frames=FRAMES, poisson=POISSON, substeps=n,
                                     extra=["--damping", beta] if beta else [])
        rows[n] = read_forces_csv(caps[n] / "truth" / "forces.csv")
    fine = sorted(truth_substeps)
    ref = rows[fine[-1]] if len(fine) == 1 else extrapolated_table(rows[fine[-2]], rows[fine[-1]])
    return caps, rows, ref


def reference_name(truth_substeps: list[int]) -> str:
    s = sorted(truth_substeps)
    return f"truth N = {s[0]}" if len(s) == 1 else f"Richardson of the truths N = {s[-2]}, {s[-1]}"


def truth_rows(case: str, rows: dict[int, list[dict]], ref: list[dict], before: int) -> list[dict]:
    """Each truth against the reference and against the truth with twice its substeps, and the Richardson of each
    consecutive pair but the reference's against the reference."""
    out = []
    steps = sorted(rows)
    for n in steps:
        out.append({"part": "truth", "case": case, "what": f"truth, N = {n}", "truth_substeps": n,
                    "first_change": before, **errors(rows[n], ref, before)})
        if 2 * n in rows:
            out[-1]["vs_2N"] = errors(rows[n], rows[2 * n], before)
    for a, b in zip(steps, steps[1:-1] if len(steps) > 2 else []):
        if 2 * a == b:
            out.append({"part": "truth", "case": case, "what": f"truth, Richardson N = {a}, {b}",
                        "truth_substeps": b, "first_change": before,
                        **errors(extrapolated_table(rows[a], rows[b]), ref, before)})
    return out


def replays(scene, controls, young, poisson, start: str, steps: list[int], dt: float, log: str,
            cache: Path | None = None) -> dict[int, tuple[list, float]]:
    """{S: (SetForce rows, CPU s)} of plain replays; with ``cache`` (a folder) each replay's rows and CPU are kept
    there under a hash of (mesh, controls, θ(t), start, S) and reused by a later run."""
    import hashlib

    from stages.forces import force_table, replay_forces
    from stages.sim.stress import SetForce

    out = {}
    for S in steps:
        key = hashlib.sha1(b"".join([np.ascontiguousarray(scene.rest).tobytes(), repr(controls).encode(),
                                     np.ascontiguousarray(young, np.float64).tobytes(),
                                     np.ascontiguousarray(poisson, np.float64).tobytes(),
                                     f"{start} {S} {scene.dt!r}".encode(),
                                     f" β {scene.damping!r}".encode() if scene.damping else b""])).hexdigest()[:20]
        path = None if cache is None else cache / f"{key}.json"
        if path is not None and path.is_file():
            got = json.loads(path.read_text())
            rows = [(int(r["frame"]), SetForce(r["name"], r["kind"], np.array([r["fx_N"], r["fy_N"], r["fz_N"]]),
                                               r["magnitude_sum_N"], np.array([r[k] for k in APPLIED]),
                                               int(r["n_vertices"]))) for r in got["rows"]]
            out[S] = (rows, got["cpu_s"])
            print(f"  {log}: S = {S} from the cache ({out[S][1]:.1f} s CPU when measured)", flush=True)
            continue
        t0 = time.process_time()
        rows, _, _ = replay_forces(scene, controls, young, poisson, start, S)
        out[S] = (rows, time.process_time() - t0)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({"rows": force_table(rows, dt), "cpu_s": out[S][1]}))
        print(f"  {log}: S = {S} {out[S][1]:.1f} s CPU", flush=True)
    return out


def first_change(young: np.ndarray) -> int:
    """The first frame whose E (T, R) differs from the previous frame's in any region; T when none."""
    young = np.asarray(young)
    moved = np.flatnonzero(np.any(young[1:] != young[:-1], axis=1))
    return int(moved[0]) + 1 if len(moved) else len(young)


def errors(estimated: list[dict], ref: list[dict], before: int) -> dict:
    """{"median_force_error": pooled over all frames, "median_force_error_before_change": over frames < before,
    "per_set"} against the reference rows."""
    from stages.forces import force_errors

    per = force_errors(estimated, ref)
    early = [e for v in per.values() for t, e in zip(v["frames"], v["rel_error_per_frame"]) if t < before]
    return {"median_force_error": pooled(per),
            "median_force_error_before_change": float(np.median(early)) if early else None,
            "per_set": {k: v["median_relative_error"] for k, v in per.items()},
            "per_frame": {k: [[int(t), float(e)] for t, e in zip(v["frames"], v["rel_error_per_frame"])]
                          for k, v in per.items()}}


def method_rows(plain: dict[int, tuple[list, float]], specs: list[str], ref: list[dict], dt: float, base: dict,
                before: int, keep_table: bool = False) -> list[dict]:
    """Rows per replay spec ('S' plain, 'rS' Richardson (S, 2S)) from the plain replays; with ``keep_table`` each
    row also holds its forces.csv rows under "table"."""
    from stages.forces import force_table, richardson_rows

    out = []
    for spec in specs:
        if spec.startswith("r"):
            S = int(spec[1:])
            if S not in plain or 2 * S not in plain:
                continue
            rows, cpu = richardson_rows(plain[S][0], plain[2 * S][0]), plain[S][1] + plain[2 * S][1]
            method, label, cost = "richardson", f"Richardson ({S}, {2 * S})", 3 * S
        else:
            S = int(spec)
            rows, cpu = plain[S]
            method, label, cost = "plain", f"plain, S = {S}", S
        table = force_table(rows, dt)
        out.append({**base, "method": method, "replay": label, "substeps": S, "steps_per_frame": cost,
                    **errors(table, ref, before), "cpu_s": cpu, **({"table": table} if keep_table else {})})
    return out


def ratios(rows: list[dict]) -> None:
    """CPU / error ratios against plain S = 1 of the same case and θ (this run), in place."""
    for r in rows:
        ref = next((q for q in rows if q.get("case") == r.get("case") and q.get("theta") == r.get("theta")
                    and q.get("adapt") == r.get("adapt") and q.get("method") == "plain" and q.get("substeps") == 1),
                   None)
        if ref is not None and "cpu_s" in r:
            r["cpu_ratio"] = r["cpu_s"] / ref["cpu_s"]
            if r["median_force_error"] is not None and ref["median_force_error"]:
                r["error_ratio"] = r["median_force_error"] / ref["median_force_error"]


def part_time(work: Path, case: str, truth_substeps: list[int], substeps: list[int]) -> list[dict]:
    from stages.artefacts import MeshArtefact
    from stages.capture import load_capture, read_truth
    from stages.sim.scene import make_scene

    caps, trows, ref = truths(work, case, truth_substeps)
    finest = caps[max(caps)]
    ws = pl.mesh(finest, work / f"ws_{finest.name}_p2", order=2, max_tets=MAX_TETS)
    cap, mesh = load_capture(finest), MeshArtefact.load(ws / "mesh.h5")
    truth = read_truth(cap)
    controls = cap.controls()
    dt = float(cap.dt)
    scene = make_scene(mesh, controls, cap.material.model, dt, np.asarray(cap.gravity, np.float64),
                       damping=cap.material.damping)
    regions = list(mesh.region_names)
    young = by_region(truth.young[:FRAMES], truth.region_names, regions, "truth/material.csv")
    poisson = by_region(truth.poisson[:FRAMES], truth.region_names, regions, "truth/material.csv")
    before = first_change(young)
    rows = [{**r, "reference": reference_name(truth_substeps)} for r in truth_rows(case, trows, ref, before)]
    plain = replays(scene, controls, young, poisson, cap.start, substeps, dt, f"{case}, true E",
                    CACHE.get("dir", work / "cache"))
    specs = [str(S) for S in substeps] + [f"r{S}" for S in substeps if 2 * S in substeps]
    base = {"part": "replay", "case": case, "theta": "true E", "adapt": None, "frames": FRAMES, "fps": float(cap.fps),
            "dofs": 3 * int(mesh.vertices.shape[0]), "first_change": before,
            "reference": reference_name(truth_substeps)}
    rep = method_rows(plain, specs, ref, dt, base, before)
    ratios(rep)
    return rows + rep


def lag_of(rule: str) -> int | None:
    return int(rule[3:]) if rule.startswith("lag") else None


def part_theta(work: Path, case: str, truth_substeps: list[int], adapt_ws: list[Path], rules: list[str],
               specs: list[str]) -> list[dict]:
    from stages.artefacts import AdaptArtefact, MeshArtefact, read_provenance
    from stages.capture import load_capture, read_truth
    from stages.forces import filter_model, replay_theta, smoothed_theta
    from stages.results import material_damping
    from stages.sim.scene import make_scene

    caps, trows, ref = truths(work, case, truth_substeps)
    cap = load_capture(caps[max(caps)])
    truth = read_truth(cap)
    # the truths against the reference and each other: where they converge in time, the force is defined
    rows_truth = [{**r, "reference": reference_name(truth_substeps)}
                  for r in truth_rows(case, trows, ref, first_change(np.asarray(truth.young[:FRAMES])))]
    controls = cap.controls()
    dt = float(cap.dt)
    steps = sorted({int(s.lstrip("r")) * m for s in specs for m in ((1, 2) if s.startswith("r") else (1,))})
    rows: list[dict] = rows_truth
    true_tables: dict = {}  # (vertices, T) -> {replay label: forces.csv rows of the true E}
    for ws in adapt_ws:
        mesh = MeshArtefact.load(ws / "mesh.h5")
        ad = AdaptArtefact.load(ws / "adapt.h5")
        cfg = read_provenance(ws / "adapt.h5").get("config", {})
        beta = material_damping(cap, ad)  # the β adapt simulated (declared or estimated)
        scene = make_scene(mesh, controls, cap.material.model, dt, np.asarray(cap.gravity, np.float64), damping=beta)
        scene_true = scene if beta == cap.material.damping else make_scene(
            mesh, controls, cap.material.model, dt, np.asarray(cap.gravity, np.float64), damping=cap.material.damping)
        regions = list(mesh.region_names)
        T = len(ad.frames)
        young = by_region(np.asarray(ad.young), list(ad.region_names), regions, "adapt.h5")
        poisson = by_region(np.asarray(ad.poisson), list(ad.region_names), regions, "adapt.h5")
        desc = (f"{ws.name}: {cfg.get('space', '?')} space, {cfg.get('loss', '?')}, estimator "
                f"{(ad.extra or {}).get('estimator', cfg.get('estimator', '?'))}, {cfg.get('substeps', 1)} substep(s), "
                f"window {cfg.get('window', '?')}, process noise {cfg.get('process_noise', '?')}"
                + (f" ({cfg['process_noise_change']} after a change)" if cfg.get("process_noise_change") is not None
                   else "") + ", E initialised at "
                f"{cfg.get('young_init', '?')} Pa, capture "
                f"{Path(str((ad.extra or {}).get('capture', '?'))).name}")
        changes = list((ad.extra or {}).get("material_changes_detected", []) or [])
        base = {"part": "theta", "case": case, "adapt": desc, "changes": changes, "frames": T, "fps": float(cap.fps),
                "dofs": 3 * int(mesh.vertices.shape[0]),
                "adapt_capture_substeps": capture_substeps((ad.extra or {}).get("capture"))}
        key = (mesh.vertices.shape[0], T)
        thetas = {}
        if key not in true_tables:  # the true E on this mesh, once
            thetas["true E"] = (by_region(truth.young[:T], truth.region_names, regions, "truth/material.csv"),
                                by_region(truth.poisson[:T], truth.region_names, regions, "truth/material.csv"))
        sy = by_region(np.asarray(ad.young_sigma), list(ad.region_names), regions, "adapt.h5")
        sp = by_region(np.broadcast_to(np.asarray(ad.poisson_sigma), np.shape(ad.poisson)), list(ad.region_names),
                       regions, "adapt.h5")
        model = filter_model(cfg, cap.material.poisson_range, ad.extra)
        for rule in rules:
            if rule.startswith("lag"):
                thetas[rule] = smoothed_theta(young, poisson, changes, lag_of(rule))
            elif rule == "smoothedE":  # E smoothed as "smoothed" does, ν as recorded
                thetas[rule] = (replay_theta(young, poisson, ad.extra, "smoothed", sy, sp, model)[0], poisson)
            else:
                thetas[rule] = replay_theta(young, poisson, ad.extra, rule, sy, sp, model)[:2]
        before = first_change(by_region(truth.young[:T], truth.region_names, regions, "truth/material.csv"))
        for label, (y, p) in thetas.items():
            plain = replays(scene_true if label == "true E" else scene, controls, y, p, cap.start, steps, dt,
                            f"{case}, {ws.name}, {label}",
                            CACHE.get("dir", work / "cache"))
            got = method_rows(plain, specs, ref, dt, {**base, "theta": label, "first_change": before,
                                                       "reference": reference_name(truth_substeps),
                                                       "adapt": None if label == "true E" else desc}, before,
                              keep_table=True)
            if label == "true E":
                true_tables[key] = {r["replay"]: r["table"] for r in got}
            for r in got:  # the part of the error the θ rule adds: against the true E replayed the same way
                if label != "true E" and r["replay"] in true_tables.get(key, {}):
                    r["vs_true_E"] = errors(r["table"], true_tables[key][r["replay"]], before)
                del r["table"]
            rows += got
    return rows


def capture_substeps(capture) -> int | None:
    """[synth] substeps of the capture.toml in folder ``capture`` (the truth's implicit steps per frame); None when
    it is not there."""
    path = Path(str(capture)) / "capture.toml" if capture else None
    if path is None or not path.is_file():
        return None
    got = tomllib.loads(path.read_text()).get("synth", {}).get("substeps")
    return None if got is None else int(got)


def _pct(x) -> str:
    return "—" if x is None else f"{100 * x:.1f}"


def _ratio(r: dict, k: str) -> str:
    return f"{r[k]:.2f}" if k in r else "—"


TRUTH_HEAD = ("| capture | truth | reference | vs reference, all frames (%) | vs reference, frames before the first "
              "change of E (%) | vs the truth with 2N, all frames (%) | vs the truth with 2N, before the change (%) |\n"
              "| --- | --- | --- | ---: | ---: | ---: | ---: |")
TIME_HEAD = ("| capture | replay | implicit steps per frame | vs reference, all frames (%) | vs reference, frames before "
             "the first change of E (%) | error / plain S = 1 (all frames) | replay CPU (s) | CPU / plain S = 1 |\n"
             "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
THETA_HEAD = ("| capture | adapt.h5 | θ(t) | replay | vs reference, all frames (%) | vs reference, frames before the "
              "first change of E (%) | vs the true E replayed alike, all frames (%) | vs the true E replayed alike, "
              "before the change (%) | replay CPU (s) |\n| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: |")


def _before(r: dict) -> str:
    return f"{_pct(r.get('median_force_error_before_change'))} (frames < {r.get('first_change', '?')})"


def _truth_row(r: dict) -> str:
    two = r.get("vs_2N") or {}
    return (f"| {r['case']} | {r['what']} | {r.get('reference', '—')} | {_pct(r['median_force_error'])} | {_before(r)} | "
            f"{_pct(two.get('median_force_error'))} | {_pct(two.get('median_force_error_before_change'))} |")


def _time_row(r: dict) -> str:
    return (f"| {r['case']} | {r['replay']} | {r['steps_per_frame']} | {_pct(r['median_force_error'])} | {_before(r)} | "
            f"{_ratio(r, 'error_ratio')} | {r['cpu_s']:.1f} | {_ratio(r, 'cpu_ratio')} |")


def _theta_row(r: dict) -> str:
    adapt = "—" if r.get("adapt") is None else r["adapt"].split(":")[0]
    vs = r.get("vs_true_E") or {}
    return (f"| {r['case']} | {adapt} | {r['theta']} | {r['replay']} | {_pct(r['median_force_error'])} | "
            f"{_before(r)} | {_pct(vs.get('median_force_error'))} | {_pct(vs.get('median_force_error_before_change'))} "
            f"| {r['cpu_s']:.1f} |")


THETA_METRICS = (("converged", None, "vs reference, frames where the truths converge in time (before the first "
                                     "change of E; all frames when E is constant)"),
                 ("median_force_error", None, "vs reference, all frames"),
                 ("median_force_error_before_change", None, "vs reference, before the first change of E"),
                 ("median_force_error", "vs_true_E", "vs the true E replayed alike, all frames"),
                 ("median_force_error_before_change", "vs_true_E", "vs the true E replayed alike, before the change"))


def _metric(r: dict, key: str, sub: str | None):
    if key == "converged":  # frames < first change: every frame when E is constant (first_change = T)
        key = "median_force_error_before_change"
    return (r.get(sub) or {}).get(key) if sub else r.get(key)


def theta_summary(rows: list[dict], incumbent: str = "online") -> list[str]:
    """A Markdown table made from the θ rows only: per replay and metric, for each other rule, on how many adapt.h5
    its error is below the ``incumbent``'s and on which it is not (the metrics before the first change of E only
    for captures whose E changes)."""
    th = [r for r in rows if r["part"] == "theta" and r.get("adapt")]
    present = list(dict.fromkeys(r["theta"] for r in th))
    rules = [k for k in present if k != incumbent]
    if not rules or incumbent not in present:  # (one rule measured: nothing to compare)
        return []
    out = ["| replay | error | " + " | ".join(f"'{k}' below '{incumbent}'" for k in rules) + " |",
           "| --- | --- | " + " | ".join("---" for _ in rules) + " |"]
    for replay in dict.fromkeys(r["replay"] for r in th):
        for key, sub, what in THETA_METRICS:
            cells = []
            for rule in rules:
                runs, not_lower = 0, []
                for (case, adapt) in dict.fromkeys((r["case"], r["adapt"]) for r in th if r["replay"] == replay):
                    got = {r["theta"]: _metric(r, key, sub) for r in th
                           if r["replay"] == replay and r["case"] == case and r["adapt"] == adapt
                           and not (key.endswith("before_change") and r.get("first_change", 0) >= r.get("frames", 0))}
                    if got.get(rule) is None or got.get(incumbent) is None:
                        continue
                    runs += 1
                    if not got[rule] < got[incumbent]:
                        not_lower.append(f"{adapt.split(':')[0]} {100 * got[rule]:.1f} vs {100 * got[incumbent]:.1f} %")
                cells.append(f"{runs - len(not_lower)} of {runs}" + (f" (not: {'; '.join(not_lower)})" if not_lower
                                                                     else ""))
            out.append(f"| {replay} | {what} | " + " | ".join(cells) + " |")
    return out


def summary(rows: list[dict]) -> list[str]:
    """Lines made from the replay rows only: per replay, the worst and median case error and the mean CPU ratio."""
    out = []
    rep = [r for r in rows if r["part"] == "replay" and r["median_force_error"] is not None]
    for label in dict.fromkeys(r["replay"] for r in sorted(rep, key=lambda r: r["steps_per_frame"])):
        sub = [r for r in rep if r["replay"] == label]
        errs = [r["median_force_error"] for r in sub]
        cpu = [r["cpu_ratio"] for r in sub if "cpu_ratio" in r]
        early = [r["median_force_error_before_change"] for r in sub
                 if r.get("median_force_error_before_change") is not None]
        out.append(f"- {label} ({sub[0]['steps_per_frame']} step(s) per frame): all frames: worst case "
                   f"{100 * max(errs):.1f} %, median of the cases {100 * float(np.median(errs)):.1f} %, "
                   f"{sum(e <= 0.10 for e in errs)} of {len(errs)} cases ≤ 10 %"
                   + (f"; before the first change of E: worst {100 * max(early):.1f} %, "
                      f"{sum(e <= 0.10 for e in early)} of {len(early)} ≤ 10 %" if early else "")
                   + (f"; CPU {float(np.mean(cpu)):.2f} × plain S = 1" if cpu else ""))
    return out


def default_line() -> str:
    from stages.forces import FORCE_EXTRAPOLATE, FORCE_SUBSTEPS, FORCE_THETA

    s = f"{FORCE_SUBSTEPS}" if FORCE_SUBSTEPS else "adapt.h5's substeps"
    rep = f"Richardson ({s}, 2 × {s})" if FORCE_EXTRAPOLATE else f"plain, S = {s}"
    return (f"stages.forces defaults when this report was written (`rsl export --forces`, `rsl evaluate`, `rsl report`): replay "
            f"'{rep}', θ(t) '{FORCE_THETA}'.")


def write(rows: list[dict], out: Path, plan: dict, name: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    data = {"machine": f"{platform.node()} {platform.machine()} {os.cpu_count()} CPUs, {platform.python_version()}",
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "load_average_end": os.getloadavg()[0], "plan": plan, "cases": rows}
    (out / f"{name}.json").write_text(json.dumps(data, indent=1))
    refs = dict.fromkeys(r["reference"] for r in rows if r.get("reference"))
    ref = "; ".join(refs) or reference_name(plan["truth_substeps"])
    per_case = {r["case"]: r["reference"] for r in rows if r.get("reference")}
    parts = [f"# Forces of the full-space replay against a truth refined in time\n\n"
             f"Captures as bench/accuracy.py makes them (`rsl synth --truth-order 2 --handles hard`, {FRAMES} "
             f"frames at 30 fps, ν = {POISSON}), each simulated with several numbers N of implicit-Euler substeps "
             f"per frame"
             + (f", with a viscous damping β = {plan['truth_damping']:g} s declared (`rsl synth --damping`) that the "
                f"replays simulate too" if plan.get("truth_damping") else "")
             + ".  Reference per capture ("
             + "; ".join(f"{c}: {v}" for c, v in per_case.items()) + f"): the Richardson "
             f"extrapolation of its two finest truths, frame by frame (2 F_2N − F_N: cancels implicit Euler's "
             f"first-order error where the truths are in their asymptotic range), or its one truth.  Errors: median "
             f"relative error of the applied force over handles/obstacles and frames, as `rsl evaluate` reports it "
             f"(stages.forces.force_errors), over all frames and over the frames before the first change of the "
             f"true E (the bars' E steps at frame {FRAMES // 3}; the beam's E is constant).  Replays "
             f"in the full space from the capture's start state (stages.forces.replay_forces): 'plain, S' = S "
             f"implicit-Euler steps per frame; 'Richardson (S, 2S)' = 2 F_2S − F_S (3S steps per frame).  CPU: "
             f"time.process_time of the replay(s); ratios against plain S = 1 of the same capture and θ(t), "
             f"this run.\n"]
    tr = [r for r in rows if r["part"] == "truth"]
    if tr:
        parts.append("## The truths against the reference\n\n" + "\n".join([TRUTH_HEAD] + [_truth_row(r) for r in tr])
                     + "\n")
    rep = [r for r in rows if r["part"] == "replay"]
    if rep:
        parts.append(f"## Replays of the true E(t) (rsl's mesh `rsl tetrahedralize --order 2 --max-tets {MAX_TETS}`)"
                     f"\n\n" + "\n".join([TIME_HEAD] + [_time_row(r) for r in rep]) + "\n\n"
                     + "\n".join(summary(rows)) + "\n")
    th = [r for r in rows if r["part"] == "theta"]
    if th:
        ads = dict.fromkeys(r["adapt"] for r in th if r.get("adapt"))
        subs = sorted({r["adapt_capture_substeps"] for r in th if r.get("adapt_capture_substeps")})
        made = (f"the truth simulated with {', '.join(map(str, subs))} substep(s) per frame" if subs
                else "its substeps not recorded")
        parts.append("## Replays of an adapted θ(t)\n\nθ(t) rules: 'online' = as adapt.h5 records it (each frame's "
                     "filter estimate); 'segment' = the last estimate of each segment between the changes the "
                     "estimator detected (stages.forces.smoothed_theta); 'lagL' = the estimate L frames later, "
                     "within the segment; 'smoothed' = the Rauch–Tung–Striebel smoother of the recorded E ± σ, ν ± σ "
                     "under the gn filter's own random walk (stages.forces.rts_theta); 'smoothedE' = its E with ν as "
                     "recorded; 'true E' = the truth's E(t), ν.  The adapt.h5 were made by `rsl adapt` on "
                     f"captures of the same scenes and controls ({made}), each replayed on its own mesh.h5 and "
                     "compared with the refined reference, and with the true E(t) replayed on the same mesh with the "
                     "same replay (the part of the error the adapted θ(t) adds):\n\n"
                     + "\n".join(f"- {a}; detected changes at frames "
                                 f"{next(r['changes'] for r in th if r.get('adapt') == a)}" for a in ads) + "\n\n"
                     + "\n".join([THETA_HEAD] + [_theta_row(r) for r in th]) + "\n\n"
                     + "\n".join(theta_summary(rows)) + "\n")
    if plan.get("cache"):
        parts.append(f"Each replay (its forces and CPU seconds, as measured when made) is read from the cache "
                     f"{plan['cache']} when an earlier run made it for the same mesh, controls, θ(t), start and S.\n")
    parts.append(default_line() + " "
                 + (f"Rows merged from {len(plan['merged_from'])} runs, ended "
                    + ", ".join(f"{m['date']} (load average {m['load_average_end']:.1f})" for m in plan["merged_from"])
                    + f"; machine {data['machine']}. " if plan.get("merged_from") else
                    f"Machine: {data['machine']}, load average {data['load_average_end']:.1f} at the end; date "
                    f"{data['date']}. ") + "Produced by `bench/forces.py`.\n")
    if rep:
        parts.append(f"![force error against CPU]({name}.png)\n")
    (out / f"{name}.md").write_text("\n".join(parts))
    if not rep:
        return
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for c, case in enumerate(dict.fromkeys(r["case"] for r in rep)):
        for method, ls in (("plain", "-"), ("richardson", "--")):
            sub = sorted((r for r in rep if r["case"] == case and r["method"] == method
                          and r["median_force_error"] is not None), key=lambda r: r["cpu_s"])
            if sub:
                ax.plot([r["cpu_s"] for r in sub], [100 * r["median_force_error"] for r in sub], ls, marker="o",
                        ms=3, color=f"C{c}", label=f"{case}, {method}")
    ax.axhline(10, color="k", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("replay CPU (s)")
    ax.set_ylabel(f"median force error vs {ref} (%)", fontsize=7)
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=("time", "theta"), default="time")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "results")
    ap.add_argument("--work", type=Path, default=Path("/tmp/rsl_forces_conv"))
    ap.add_argument("--cases", default="bar_equilibrium,bar_rest,beam_equilibrium",
                    help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--truth-substeps", default="12,24",
                    help="substeps per frame of the truths (synth --substeps); the two finest make the reference")
    ap.add_argument("--substeps", default="1,2,3,6,12", help="--part time: plain replay substeps S (include 1)")
    ap.add_argument("--adapt-ws", default="", help="--part theta: CASE=WORKSPACE,... holding adapt.h5 and mesh.h5")
    ap.add_argument("--rules", default="online,segment,smoothed,smoothedE", help="--part theta: θ(t) rules")
    ap.add_argument("--replays", default="3,r1,r3", help="--part theta: S (plain) or rS (Richardson (S, 2S))")
    ap.add_argument("--cache", type=Path, default=None,
                    help="folder of the replay cache (default WORK/cache; a new folder re-measures every replay)")
    ap.add_argument("--name", default="forces_converged", help="file stem of the report in --out (NAME.md/.json/.png)")
    ap.add_argument("--truth-damping", type=float, default=0.0,
                    help="β (s) of a viscous damping every truth simulates and declares (rsl synth --damping); the "
                         "replays simulate it too (use a --cache of its own)")
    ap.add_argument("--merge", nargs="+", type=Path, default=None,
                    help="only write the report from the rows of these NAME.json files (runs split by case)")
    a = ap.parse_args()
    if a.merge:
        runs = [json.loads(f.read_text()) for f in a.merge]
        plan = {**runs[0]["plan"], "cases": [c for run in runs for c in run["plan"]["cases"]],
                "merged_from": [{"file": str(f), "date": run["date"], "load_average_end": run["load_average_end"]}
                                for f, run in zip(a.merge, runs)]}
        write([r for run in runs for r in run["cases"]], a.out, plan, a.name)
        return
    if a.cache is not None:
        CACHE["dir"] = a.cache
    if a.truth_damping:
        TRUTH_DAMPING["beta"] = a.truth_damping
    truth_substeps = sorted({int(s) for s in a.truth_substeps.split(",")})
    cases = a.cases.split(",")
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise SystemExit(f"unknown case(s) {unknown}; known: {', '.join(CASES)}")
    a.work.mkdir(parents=True, exist_ok=True)
    plan = {"part": a.part, "cases": cases, "frames": FRAMES, "max_tets": MAX_TETS, "work": str(a.work),
            "truth_substeps": truth_substeps, "cache": str(CACHE.get("dir", a.work / "cache")),
            "truth_damping": a.truth_damping}
    rows: list[dict] = []
    if a.part == "time":
        substeps = sorted({int(s) for s in a.substeps.split(",")})
        plan["substeps"] = substeps
        for case in cases:
            rows += part_time(a.work, case, truth_substeps, substeps)
            write(rows, a.out, plan, a.name)  # after every case: a stopped run keeps what it measured
        print("\n".join([TRUTH_HEAD] + [_truth_row(r) for r in rows if r["part"] == "truth"]))
        print("\n".join([TIME_HEAD] + [_time_row(r) for r in rows if r["part"] == "replay"]))
        print("\n".join(summary(rows)))
        return
    ws_of: dict[str, list[Path]] = {}
    for item in filter(None, a.adapt_ws.split(",")):
        case, _, ws = item.partition("=")
        ws_of.setdefault(case, []).append(Path(ws))
    rules, specs = a.rules.split(","), a.replays.split(",")
    plan.update(rules=rules, replays=specs, adapt_ws={k: list(map(str, v)) for k, v in ws_of.items()})
    for case in cases:
        if case not in ws_of:
            raise SystemExit(f"--adapt-ws names no workspace for {case}")
        rows += part_theta(a.work, case, truth_substeps, ws_of[case], rules, specs)
        write(rows, a.out, plan, a.name)
    print("\n".join([THETA_HEAD] + [_theta_row(r) for r in rows if r["part"] == "theta"]))
    print("\n".join(theta_summary(rows)))


if __name__ == "__main__":
    main()
