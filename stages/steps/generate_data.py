"""`rsl generate-data`: training snapshots for the subspace (paper §5.1) → snapshots.h5.

Random interaction sequences stay within the envelope of the capture's own controls: each sequence is a keyframed
track whose keyframe k takes every handle, load and obstacle to its value at a random frame s_k of controls.json
(shared by all controls, or drawn for each), jittered by a fraction of that control's range; keyframe 0 is the
capture's frame 0.  Every sequence is released from the rest shape one frame before frame 0 (``--start
released``) or starts in the capture's own start convention (``--start capture``), and takes ``--substeps``
implicit steps per frame.  Material is sampled per frame across the prior range of capture.toml: per sequence and
region, end points log E_a, log E_b in the log range and ν_a, ν_b in the range, from a Latin hypercube over all the
sequences' ends (each 2n-th of each range holds one), linearly interpolated over the frames ("ramp"), or held
("constant").

Sequences run in a local process pool ('spawn' context: JAX does not fork safely) or as Ray
tasks on an existing cluster; the plan is drawn from the seed in this process, so the
result does not depend on where or in which order the sequences ran.
"""
from __future__ import annotations

import multiprocessing
import os
import socket
import threading
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.stats import qmc

from stages.artefacts import KIND_FILES, MeshArtefact, Provenance, SnapshotsArtefact, check_mesh_source
from stages.capture import Controls, Track, check_obstacles_clear, load_capture, parse_controls
from stages.domain.rotations import axis_angle_quat_wxyz, quat_multiply_wxyz, rotation_angle
from stages.errors import RslError
from stages.progress import Reporter, SilentReporter
from stages.workspace import prepare_workspace


@dataclass(frozen=True)
class GenerateDataConfig:
    capture: Path
    """Capture folder (capture.toml for the material range and gravity, controls.json for the envelope)."""
    workspace: Path
    """Workspace folder holding mesh.h5; snapshots.h5 is written there."""
    sequences: int = 20
    """Number of random interaction sequences."""
    frames: int = 60
    """Frames simulated per sequence."""
    workers: int = 2
    """Local worker processes (1 = run in this process)."""
    ray: str = ""
    """Address of an existing Ray cluster to run the sequences on ('auto', 'ray://host:10001', or 'local' to start
    one here); empty = local process pool."""
    material_sampling: Literal["ramp", "constant"] = "ramp"
    """Per-frame material: 'ramp' interpolates between two random end points of each sequence (log E, ν);
    'constant' holds one random value."""
    material_design: Literal["latin", "independent"] = "latin"
    """How the sequences' material end points are drawn: latin, a Latin hypercube over all the sequences' ends
    (each 2n-th of the log E and ν ranges holds one end, so few sequences still span the range); independent, each
    end uniform on its own (docs/results/training_data.md compares them)."""
    keyframe_gap: int = 0
    """Frames between random keyframes (drawn between gap and 2·gap); 0 = a quarter of the capture's control length, at
    least 5."""
    jitter: float = 0.1
    """Random offset of each keyframe as a fraction of its control's range over the capture (translation, rotation
    angle, force)."""
    newton_iterations: int = 300
    """Most Newton iterations per time step before a sequence is given up."""
    substeps: int = 1
    """Implicit-Euler steps per frame (time step 1/(fps·substeps)); snapshots record every substeps-th state."""
    start: Literal["released", "capture"] = "released"
    """The state each sequence starts from: released, released from the rest shape one frame before frame 0 (frame 0
    one frame of steps from it); capture, the capture's [capture] start convention (frame 0 the static equilibrium
    under the frame-0 controls and the sequence's material for "equilibrium" and "moving", the rest shape at rest for
    "rest")."""
    seed: int = 0
    """Seed of every random choice; equal seeds give identical snapshots."""


# =========================================================================== planning
@dataclass
class SequencePlan:
    """Everything one worker needs: controls (as JSON), per-frame material (T, R) and the scene settings."""

    index: int
    controls: dict
    young: np.ndarray  # (T, R) Pa
    poisson: np.ndarray  # (T, R)


def _random_track(track: Track, n_ref: int, key_frames: np.ndarray, ref_frames: np.ndarray, jitter: float,
                  rng: np.random.Generator) -> Track:
    """A keyframed track whose keyframe k is ``track`` at ``ref_frames[k]`` plus a jitter within its range."""
    ref = track.sample(n_ref)  # (n_ref, D)
    vals = []
    if track.is_pose:
        span_t = np.ptp(ref[:, :3], axis=0)  # (3,) translation range, m
        max_angle = max(rotation_angle(ref[0, 3:], q) for q in ref[:, 3:])
        for k, s in enumerate(ref_frames):
            v = track.at(int(s)).copy()
            if k > 0 and jitter > 0:
                v[:3] += jitter * span_t * rng.uniform(-1, 1, 3)
                if max_angle > 0:
                    dq = axis_angle_quat_wxyz(rng.normal(size=3), jitter * max_angle * rng.uniform(-1, 1))
                    v[3:] = quat_multiply_wxyz(dq, v[3:])
                    v[3:] /= np.linalg.norm(v[3:])
            vals.append(v)
    else:
        span = np.ptp(ref, axis=0)
        for k, s in enumerate(ref_frames):
            v = track.at(int(s)).copy()
            if k > 0 and jitter > 0:
                v += jitter * span * rng.uniform(-1, 1, v.shape)
            vals.append(v)
    return Track(np.asarray(key_frames, np.int64), np.array(vals), track.is_pose)


def random_controls(controls: Controls, frames: int, gap: int, jitter: float, rng: np.random.Generator) -> Controls:
    """One random interaction sequence of ``frames`` frames within the envelope of ``controls``."""
    n_ref = controls.n_frames or 1
    keys = [0]
    while keys[-1] < frames - 1:
        keys.append(keys[-1] + int(rng.integers(gap, 2 * gap + 1)))  # the last may lie past the end
    keys = np.array(keys)
    tracks = [h.poses for h in controls.handles] + [ld.force for ld in controls.loads] + \
             [o.poses for o in controls.obstacles]
    shared = rng.random() < 0.5
    common = rng.integers(0, n_ref, size=len(keys))
    new = []
    for tr in tracks:
        refs = common.copy() if shared else rng.integers(0, n_ref, size=len(keys))
        refs[0] = 0
        new.append(_random_track(tr, n_ref, keys, refs, jitter, rng))
    it = iter(new)
    out = Controls(friction=controls.friction)
    for h in controls.handles:
        # hard (Dirichlet) handles stay hard: the snapshots then hold their vertices exactly at the targets,
        # as the capture's simulation does (springs here gave a reduced space with a compliant clamp)
        out.handles.append(type(h)(h.name, h.select, h.stiffness, next(it), hard=bool(getattr(h, "hard", False))))
    for ld in controls.loads:
        out.loads.append(type(ld)(ld.name, ld.select, next(it)))
    for o in controls.obstacles:
        out.obstacles.append(type(o)(o.name, o.shape, o.normal, o.offset, o.radius, o.half_extents, next(it)))
    return out


def material_ends(young_range: tuple[float, float], poisson_range: tuple[float, float], n_sequences: int,
                  n_regions: int, rng: np.random.Generator, design: str = "latin",
                  mode: str = "ramp") -> tuple[np.ndarray, np.ndarray]:
    """log E and ν at both ends of every sequence, (n_sequences, 2, R) each.  ``latin``: a Latin hypercube
    (scipy.stats.qmc) over all 2n ends (``ramp``; the n first ends with ``constant``, the last equal to them), paired
    at random into sequences, so that each 2n-th of the log E and ν ranges holds one end: few sequences then still
    span the prior range.  ``independent``: each end uniform on its own; four sequences drawn so left the
    dinosaur's snapshots at ν 0.30–0.41 of 0.30–0.49 (docs/results/training_data.md)."""
    n_ends = 2 * n_sequences if mode == "ramp" else n_sequences
    if design == "latin":
        u = qmc.LatinHypercube(d=2 * n_regions, rng=rng).random(n_ends)  # rows in random order: random pairs
    else:
        u = rng.uniform(size=(n_ends, 2 * n_regions))
    u = u.reshape(n_sequences, -1, 2, n_regions)  # [sequence, end, (log E, ν), region]
    if mode != "ramp":
        u = np.repeat(u, 2, axis=1)
    lo, hi = np.log(young_range[0]), np.log(young_range[1])
    log_e = lo + (hi - lo) * u[:, :, 0]
    nu = poisson_range[0] + (poisson_range[1] - poisson_range[0]) * u[:, :, 1]
    return log_e, nu


def sample_material(log_e_ends: np.ndarray, nu_ends: np.ndarray, young_range: tuple[float, float], frames: int,
                    mode: str) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame material (T, R) each from one sequence's ends (2, R) of log E and ν (material_ends): interpolated
    linearly over the frames (``ramp``) or held at the first end (``constant``)."""
    e_ends, nu_ends = np.array(log_e_ends, float), np.array(nu_ends, float)
    a = (np.arange(frames) / max(frames - 1, 1))[:, None]
    if mode == "constant":
        a = np.zeros_like(a)
    young = np.exp((1 - a) * e_ends[0] + a * e_ends[1])
    young = np.clip(young, young_range[0], young_range[1])  # exp(log) round-off stays inside the range
    poisson = (1 - a) * nu_ends[0] + a * nu_ends[1]
    return young, poisson


def plan_sequences(config: GenerateDataConfig, controls: Controls, young_range, poisson_range,
                   n_regions: int) -> list[SequencePlan]:
    """The random plan of every sequence, drawn from the seed (sequence i's controls use the stream [seed, i]; the
    materials, one Latin hypercube over all sequences, the stream [seed, sequences, 1])."""
    n_ref = controls.n_frames or 1
    gap = config.keyframe_gap if config.keyframe_gap > 0 else max(5, n_ref // 4)
    log_e, nu = material_ends(young_range, poisson_range, config.sequences, n_regions,
                              np.random.default_rng([config.seed, config.sequences, 1]), config.material_design,
                              config.material_sampling)
    plans = []
    for i in range(config.sequences):
        rng = np.random.default_rng([config.seed, i])
        ctl = random_controls(controls, config.frames, gap, config.jitter, rng)
        young, poisson = sample_material(log_e[i], nu[i], young_range, config.frames, config.material_sampling)
        plans.append(SequencePlan(i, ctl.to_json(), young, poisson))
    return plans


# =========================================================================== one sequence (runs in a worker)
def simulate_sequence(mesh: MeshArtefact, plan: SequencePlan, model: str, dt: float, gravity: np.ndarray,
                      newton_iterations: int, damping: float = 0.0, start: str = "released",
                      substeps: int = 1) -> tuple[int, np.ndarray | None, str]:
    """(index, positions (T, n, 3) or None, error message) of one planned sequence, ``substeps`` implicit steps per
    frame (stages.sim.static.simulate_from_start).  ``start`` "released": released from the rest shape one frame
    before frame 0 (frame 0 is one frame of steps from it, under the frame-0 controls and material); "rest" and
    "equilibrium": frame 0 is that state (stages.sim.static.start_state, with the frame-0 controls and material).
    ``damping`` β s (the capture's [material] damping)."""
    from stages.sim.scene import SimulationError, frame_inputs, make_scene  # JAX + numba: loaded on use
    from stages.sim.static import simulate_from_start

    try:
        ctl = parse_controls(plan.controls, Path(f"sequence {plan.index}"))
        scene = make_scene(mesh, ctl, model, dt, gravity, damping=damping)
        T = plan.young.shape[0]
        if start == "released":  # one frame more, before frame 0, holding frame 0's controls and material
            young, poisson = (np.concatenate([a[:1], a]) for a in (plan.young, plan.poisson))
            x = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, max(f - 1.0, 0.0)), young, poisson,
                                    T + 1, "rest", substeps, max_iterations=newton_iterations)[1:]
        else:
            x = simulate_from_start(scene, lambda f: frame_inputs(scene, ctl, f), plan.young, plan.poisson, T, start,
                                    substeps, max_iterations=newton_iterations)
    except SimulationError as e:
        return plan.index, None, str(e)
    if not np.all(np.isfinite(x)):
        return plan.index, None, "non-finite positions"
    return plan.index, x, ""


def _worker_init(parent_pid: int | None = None) -> None:
    """Worker set-up: float64 JAX on the CPU, and a watchdog thread that ends the worker as soon as its parent
    is gone (a kill -9 of `rsl generate-data` must not leave ~300 MB workers behind)."""
    os.environ.setdefault("JAX_ENABLE_X64", "1")
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    if parent_pid is not None:
        def watch() -> None:
            while os.getppid() == parent_pid:
                time.sleep(0.5)
            os._exit(1)  # the parent died: the worker was re-parented

        threading.Thread(target=watch, name="rsl-parent-watchdog", daemon=True).start()


def _run_pool(tasks: list, workers: int, reporter: Reporter, task) -> list:
    ctx = multiprocessing.get_context("spawn")
    results = []
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                             initargs=(os.getpid(),)) as pool:
        futures = [pool.submit(simulate_sequence, *t) for t in tasks]
        for fut in as_completed(futures):
            results.append(fut.result())
            task.advance(1)
    return results


RAY_ENV = {"JAX_ENABLE_X64": "1", "JAX_PLATFORMS": "cpu"}  # set in every Ray worker (runtime_env)


def _ray_endpoint(address: str) -> tuple[str, int] | None:
    """(host, port) of a 'HOST:PORT' or 'ray://HOST:PORT' address; None for 'auto' / 'local' / other forms."""
    a = address.strip()
    a = a[len("ray://"):] if a.startswith("ray://") else a
    host, sep, port = a.rpartition(":")
    if not sep or not host or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def connect_ray(address: str, timeout_s: float = 10.0):
    """``ray`` connected to the cluster at ``address`` ('auto', 'HOST:PORT', 'ray://HOST:10001', or 'local' to
    start one here); returns (ray module, whether this call connected — then the caller shuts it down).

    A HOST:PORT where nothing answers within ``timeout_s`` is refused at once (Ray itself would retry for
    minutes)."""
    try:
        import ray
    except ImportError:
        raise RslError("--ray needs Ray, an optional extra of rsl: pip install 'rsl[ray]'.") from None
    if ray.is_initialized():
        return ray, False
    end = _ray_endpoint(address)
    if end is not None:
        try:
            socket.create_connection(end, timeout=timeout_s).close()
        except OSError as e:
            raise RslError(f"--ray {address}: nothing answers at {end[0]}:{end[1]} ({e.strerror or e}); is the Ray "
                           f"head running there (`ray start --head`) and the port reachable?") from None
    try:
        ray.init(address=None if address == "local" else address, runtime_env={"env_vars": dict(RAY_ENV)},
                 log_to_driver=False, include_dashboard=False)
    except Exception as e:  # ConnectionError and friends
        raise RslError(f"--ray {address}: cannot connect to the Ray cluster ({type(e).__name__}: {e}).") from None
    return ray, True


def _run_ray(tasks: list, address: str, reporter: Reporter, task) -> list:
    ray, started_here = connect_ray(address)
    try:
        remote = ray.remote(simulate_sequence)
        mesh_ref = ray.put(tasks[0][0]) if tasks else None
        refs = [remote.remote(mesh_ref, *t[1:]) for t in tasks]
        pending, results = list(refs), []
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            results.append(ray.get(done[0]))
            task.advance(1)
        return results
    finally:
        if started_here:
            ray.shutdown()


# =========================================================================== the stage
def run(config: GenerateDataConfig, reporter: Reporter = SilentReporter()) -> Path:
    """Simulate the random sequences and write WS/snapshots.h5; returns its path."""
    c = config
    if c.sequences < 1 or c.frames < 1 or c.workers < 1 or c.substeps < 1:
        raise RslError("--sequences, --frames, --workers and --substeps should each be at least 1.")
    if c.start not in ("released", "capture"):
        raise RslError(f"--start {c.start!r} is unknown; use released or capture.")
    if c.material_sampling not in ("ramp", "constant"):
        raise RslError(f"--material-sampling {c.material_sampling!r} is unknown; use ramp or constant.")
    if c.material_design not in ("latin", "independent"):
        raise RslError(f"--material-design {c.material_design!r} is unknown; use latin or independent.")
    if c.jitter < 0:
        raise RslError(f"--jitter should not be negative, found {c.jitter}.")
    cap = load_capture(c.capture)
    prepare_workspace(c.workspace)  # writable? (before the compute) and no stale temp files of a killed run
    mesh_path = Path(c.workspace) / KIND_FILES["mesh"]
    if not mesh_path.exists():
        raise RslError(f"{mesh_path}: file not found; run `rsl tetrahedralize {c.capture} -w {c.workspace}` first.")
    mesh = MeshArtefact.load(mesh_path)
    check_mesh_source(mesh_path, cap.mesh_path)
    controls = cap.controls()
    check_obstacles_clear(controls, mesh.vertices, cap.controls_path, start=cap.start)
    mat = cap.material
    plans = plan_sequences(c, controls, mat.young_range, mat.poisson_range, len(mesh.region_names))
    start = ("released" if c.start == "released" else  # the capture's convention (a moving capture: its sag)
             "rest" if cap.start == "rest" else "equilibrium")
    tasks = [(mesh, p, mat.model, cap.dt, cap.gravity, c.newton_iterations, mat.damping, start, c.substeps)
             for p in plans]

    t0 = time.perf_counter()
    where = f"Ray ({c.ray})" if c.ray else (f"{c.workers} workers" if c.workers > 1 else "this process")
    with reporter.task(f"simulating {c.sequences} sequences × {c.frames} frames on {where}", c.sequences) as task:
        if c.ray:
            results = _run_ray(tasks, c.ray, reporter, task)
        elif c.workers > 1 and c.sequences > 1:
            results = _run_pool(tasks, min(c.workers, c.sequences), reporter, task)
        else:
            results = []
            for t in tasks:
                results.append(simulate_sequence(*t))
                task.advance(1)
    elapsed = time.perf_counter() - t0

    results.sort(key=lambda r: r[0])
    kept = [(i, x) for i, x, _ in results if x is not None]
    for i, _, err in results:
        if err:
            reporter.warn(f"sequence {i} dropped: {err}")
    if not kept:
        raise RslError(f"{c.capture}: every one of the {c.sequences} sequences failed to simulate "
                       f"(first: {results[0][2]}).")
    T = c.frames
    positions = np.concatenate([x for _, x in kept])
    young = np.concatenate([plans[i].young for i, _ in kept])
    poisson = np.concatenate([plans[i].poisson for i, _ in kept])
    sequence = np.repeat([i for i, _ in kept], T)
    frame = np.tile(np.arange(T), len(kept))
    art = SnapshotsArtefact(positions, young, poisson, sequence, frame, list(mesh.region_names))
    out = Path(c.workspace) / KIND_FILES["snapshots"]
    inputs = [mesh_path, cap.toml_path] + ([cap.controls_path] if cap.controls_path.exists() else [])
    art.save(out, Provenance.make(c, inputs))
    disp = float(np.linalg.norm(positions - mesh.vertices[None], axis=2).max())
    reporter.summary(
        f"{out}: {len(kept)} sequences × {T} frames = {len(positions)} snapshots of {mesh.vertices.shape[0]} "
        f"vertices; E {young.min():.3g}–{young.max():.3g} Pa, ν {poisson.min():.3f}–{poisson.max():.3f}; "
        f"max displacement {disp * 1000:.1f} mm; {elapsed:.1f} s on {where}"
        + (f"; {c.sequences - len(kept)} dropped" if len(kept) < c.sequences else ""))
    return out
