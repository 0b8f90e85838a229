"""The pipeline recipe the bench scripts share (issue 16): the `rsl` CLI in a child process, and one function
per step of synth → calibrate/tetrahedralize → segment → fit-gaussians → generate-data → train-subspace → adapt →
export/evaluate, each the same CLI call the scripts made by hand before.

Reuse: a step whose artefact exists is skipped when it was made earlier in this run (by any caller), or, with
RSL_BENCH_REUSE=1 in the environment, whenever the file is there (a rerun after a stop picks up the captures,
meshes, Gaussians and subspaces already made).  Pass ``reuse=False`` to always run a step.

    from _pipeline import rsl, foreign_capture, mesh, gaussians, subspace, adapt
    cap = foreign_capture(work / "bar_rest", BAR_CABLE, start="rest", frames=36)
    ws = mesh(cap, work / "ws", order=2, max_tets=1500)
    subspace(cap, ws, frames=36, dim=30)
    seconds = adapt(cap, ws, "--space", "reduced", "--loss", "markers", "--window", 3)

The scripts import it as a sibling module (bench/ is on sys.path when a bench script runs).
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Iterable

ROOT = Path(__file__).resolve().parents[1]
RSL = [sys.executable, "-m", "rsl_cli.app"]
SAMPLE_BAR = ROOT / "sample_data" / "bar" / "object.mesh"
SAMPLE_DINO = ROOT / "sample_data" / "dino" / "object.mesh"

_MADE: set[Path] = set()  # artefacts made in this run (each is made once, whatever asks for it)


class RslFailed(RuntimeError):
    """A `rsl` child process ended with a non-zero status; the message holds the command and its stderr tail."""


def rsl(*args) -> float:
    """Run ``rsl ARGS...`` (JAX in float64 on the CPU, cwd = the repository) and return its wall time in s;
    raises RslFailed with the last 3000 characters of its stderr when it fails."""
    env = dict(os.environ, JAX_ENABLE_X64="1", JAX_PLATFORMS="cpu")
    t0 = time.perf_counter()
    p = subprocess.run([*RSL, *map(str, args)], capture_output=True, text=True, env=env, cwd=ROOT)
    if p.returncode != 0:
        raise RslFailed(f"rsl {' '.join(map(str, args))} failed:\n{p.stderr[-3000:]}")
    return time.perf_counter() - t0


def reusing() -> bool:
    """Whether RSL_BENCH_REUSE is set (non-empty) in the environment."""
    return bool(os.environ.get("RSL_BENCH_REUSE"))


def skip(path: Path, reuse: bool = True) -> bool:
    """Whether the step that makes ``path`` can be skipped: the file exists and was made earlier in this run or
    RSL_BENCH_REUSE is set (and ``reuse``).  Otherwise records that this run makes it and returns False."""
    path = Path(path)
    if reuse and path.is_file() and (path in _MADE or reusing()):
        return True
    _MADE.add(path)
    return False


# ------------------------------------------------------------------------------------------------ captures
def synth(out: Path, mesh: Path, *options, reuse: bool = True) -> float:
    """``rsl synth MESH OUT OPTIONS... --overwrite`` (skipped per :func:`skip` on OUT/capture.toml); wall s, 0 when
    skipped."""
    if skip(Path(out) / "capture.toml", reuse):
        return 0.0
    return rsl("synth", mesh, out, *options, "--overwrite")


def foreign_capture(out: Path, scene: Iterable, *, start: str, frames: int, cameras: int = 3, resolution: int = 96,
                    refine: int = 0, substeps: int = 3, poisson: float = 0.45, markers: int = 40, seed: int = 0,
                    extra: Iterable = (), reuse: bool = True) -> Path:
    """A capture rsl did not make (issue 12): ``scene`` = [mesh, scenario options...] (e.g. :data:`bar_cable`),
    truth on P2 tets refined ``refine`` times, ``substeps`` implicit steps per frame, hard handles, declared
    ``start``, ``markers`` markers, no calibration views.  Returns OUT."""
    mesh_path, *scenario = list(scene)
    synth(out, mesh_path, *scenario, "--cameras", cameras, "--frames", frames, "--resolution", resolution,
          "--markers", markers, "--calib-views", 0, "--poisson", poisson, "--start", start, "--truth-order", 2,
          "--truth-refine", refine, "--substeps", substeps, "--handles", "hard", "--seed", seed, *extra,
          reuse=reuse)
    return Path(out)


def bar_cable(size: float = 0.25, young: float | None = None, schedule: str = "", region: str = "") -> list:
    """sample_data/bar pulled by a cable: constant ``young`` (Pa), or a ``schedule`` ('E@frame,...'), and an
    optional second region ('name=E@x>0.5')."""
    opts: list = [SAMPLE_BAR, "--scenario", "cable"]
    opts += ["--young-schedule", schedule] if schedule else (["--young", young] if young is not None else [])
    opts += ["--region", region] if region else []
    return opts + ["--size", size]


def dino_push(young: float, size: float = 0.22) -> list:
    """sample_data/dino pushed by a sphere at constant ``young`` (Pa)."""
    return [SAMPLE_DINO, "--scenario", "push", "--young", young, "--size", size]


# ------------------------------------------------------------------------------------------------ workspace
def mesh(cap: Path, ws: Path, order: int | None = None, max_tets: int | None = None, calibrate: bool = True,
         reuse: bool = True) -> Path:
    """``rsl calibrate CAP -w WS --from-json CAP/cameras.json`` (unless not ``calibrate``) and
    ``rsl tetrahedralize CAP -w WS [--order O] [--max-tets M]`` (skipped per :func:`skip` on WS/mesh.h5).
    Returns WS."""
    ws = Path(ws)
    if not skip(ws / "mesh.h5", reuse):
        if calibrate:
            rsl("calibrate", cap, "-w", ws, "--from-json", Path(cap) / "cameras.json")
        rsl("tetrahedralize", cap, "-w", ws, *(["--order", order] if order is not None else []),
            *(["--max-tets", max_tets] if max_tets is not None else []))
    return ws


def gaussians(cap: Path, ws: Path, frame: int = 0, segment_method: str | None = None, reuse: bool = True) -> Path:
    """``rsl segment CAP -w WS [--method M]`` and ``rsl fit-gaussians CAP -w WS --frame F`` (skipped per
    :func:`skip` on WS/gaussians.h5).  Returns WS."""
    ws = Path(ws)
    if not skip(ws / "gaussians.h5", reuse):
        rsl("segment", cap, "-w", ws, *(["--method", segment_method] if segment_method else []))
        rsl("fit-gaussians", cap, "-w", ws, "--frame", frame)
    return ws


def subspace(cap: Path, ws: Path, frames: int, dim: int, sequences: int = 4, workers: int = 1,
             reuse: bool = True, train_options: Iterable = ()) -> Path:
    """``rsl generate-data CAP -w WS --sequences N --frames F --workers K`` and ``rsl train-subspace -w WS --dim r
    TRAIN_OPTIONS...`` (skipped per :func:`skip` on WS/subspace.h5).  Returns WS."""
    ws = Path(ws)
    if not skip(ws / "subspace.h5", reuse):
        rsl("generate-data", cap, "-w", ws, "--sequences", sequences, "--frames", frames, "--workers", workers)
        rsl("train-subspace", "-w", ws, "--dim", dim, *train_options)
    return ws


# ------------------------------------------------------------------------------------------------ runs
def adapt(cap: Path, ws: Path, *options) -> float:
    """``rsl adapt CAP -w WS OPTIONS...`` (always run); its wall time in s."""
    return rsl("adapt", cap, "-w", ws, *options)


def export(ws: Path, out: Path, *options) -> float:
    """``rsl export -w WS OPTIONS... -o OUT``; wall s."""
    return rsl("export", "-w", ws, *options, "-o", out)


def evaluate(cap: Path, ws: Path, *options) -> float:
    """``rsl evaluate CAP -w WS OPTIONS...``; wall s."""
    return rsl("evaluate", cap, "-w", ws, *options)
