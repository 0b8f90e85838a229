"""Every stage described once: its command name, where its code and Config live, what it reads and
what it writes, and how its command line looks.  ``rsl run`` (stages/pipeline.py), ``rsl status``,
the generated commands (rsl_cli/options.stage_command) and docs/cli.md all read :data:`STAGES`.

Importing this module is cheap: a stage's module is imported only when its Config or run() is needed.
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import typing
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from stages.errors import RslError


@dataclass(frozen=True)
class Stage:
    """One stage: the command name, where its code lives, what it writes and reads.

    ``run(config, reporter)`` in ``module`` does the work; ``config_class`` in ``module`` is the frozen
    dataclass of its options (field docstrings are the --help text)."""

    name: str  # CLI command, e.g. "fit-gaussians"
    module: str  # e.g. "stages.steps.fit_gaussians"
    config_class: str  # e.g. "FitGaussiansConfig"
    produces: str | None  # artefact kind written into the workspace (stages.artefacts.KIND_FILES); None: elsewhere
    reads: tuple[str, ...] = ()  # artefact kinds it reads when present
    needs_cameras: bool = False  # not applicable to a capture that lists no camera
    volatile: tuple[str, ...] = ()  # options that do not change the artefact (threads, workers)
    summary: str = ""  # what the stage does and writes (the command's --help)
    arguments: tuple[str, ...] = ("capture",)  # Config fields given as positional arguments, in order
    flags: tuple[tuple[str, tuple[str, ...]], ...] = ()  # (field, option names) where not --field-name
    pipeline: bool = False  # one of the steps of `rsl run`
    writes: str = ""  # what it writes: the artefact's file in the workspace (KIND_FILES is made from these)

    def load(self) -> ModuleType:
        """Import the stage module; an RslError naming the stage when that fails."""
        try:
            mod = importlib.import_module(self.module)
        except ImportError as e:
            raise RslError(f"stage '{self.name}' ({self.module.replace('.', '/')}.py) not available: "
                           f"importing {self.module} failed ({e}).") from None
        if not callable(getattr(mod, "run", None)):
            raise RslError(f"stage '{self.name}' is not available: {self.module} defines no run(config, reporter).")
        return mod

    def config_cls(self, mod: ModuleType | None = None) -> type:
        mod = mod or self.load()
        cls = getattr(mod, self.config_class, None)
        if cls is None or not dataclasses.is_dataclass(cls):
            raise RslError(f"stage '{self.name}' is not available: {self.module} defines no dataclass "
                           f"{self.config_class}.")
        return cls

    def make_config(self, capture: Path | None, workspace: Path, overrides: dict[str, Any] | None = None,
                    mod: ModuleType | None = None) -> Any:
        """The stage's Config with defaults, the capture and workspace folders, and ``overrides`` (field -> value)."""
        cls = self.config_cls(mod)
        fields = {f.name: f for f in dataclasses.fields(cls)}
        kw: dict[str, Any] = {"workspace": Path(workspace)}
        if "capture" in fields:
            if capture is None:
                raise RslError(f"stage '{self.name}' needs a capture folder.")
            kw["capture"] = Path(capture)
        hints = config_hints(cls)
        for key, value in (overrides or {}).items():
            if key not in fields:
                raise RslError(f"--set {self.name}.{key}: {self.config_class} has no option '{key}' "
                               f"(options: {', '.join(n for n in fields if n not in ('capture', 'workspace'))}).")
            kw[key] = coerce(value, hints.get(key), f"{self.name}.{key}")
        missing = [n for n, f in fields.items() if n not in kw and f.default is dataclasses.MISSING
                   and f.default_factory is dataclasses.MISSING]  # type: ignore[misc]
        if missing:
            raise RslError(f"stage '{self.name}' needs option(s) {', '.join(missing)}; give them with "
                           f"--set {self.name}.{missing[0]}=VALUE.")
        return cls(**kw)


# The commands in the order `rsl --help` lists them; the `pipeline` ones are `rsl run`'s steps, in order.
STAGES: tuple[Stage, ...] = (
    Stage("synth", "stages.steps.synth", "SynthConfig", None, writes="a capture folder", arguments=("mesh", "out"),
          flags=(("ramp", ("--ramp/--steps",)), ("region", ("--region", "--region-young"))),
          summary="Simulate a scenario (stretch, twist, push, drop, cable, sag) on a mesh and film it with a ring of "
                  "cameras → a complete capture folder with ground truth (truth/material.csv, truth/surface.npz, "
                  "truth masks, markers.csv)."),
    Stage("calibrate", "stages.steps.calibrate", "CalibrateConfig", "cameras", writes="cameras.h5", needs_cameras=True,
          pipeline=True,
          summary="Camera intrinsics, distortion and poses in one world frame -> cameras.h5."),
    Stage("tetrahedralize", "stages.steps.tetrahedralize", "TetrahedralizeConfig", "mesh", writes="mesh.h5",
          volatile=("threads",), pipeline=True,
          summary="Tet mesh of the object (fTetWild from its surface, or its tet mesh as it is) with regions, "
                  "handles, rest quantities and a quality report → mesh.h5."),
    Stage("segment", "stages.steps.segment", "SegmentConfig", "masks", writes="masks.h5", reads=("cameras", "mesh"),
          needs_cameras=True, pipeline=True,
          summary="Masks of the object in every frame (plates, chroma, GrabCut, SAM 2) -> masks.h5."),
    Stage("fit-gaussians", "stages.steps.fit_gaussians", "FitGaussiansConfig", "gaussians", writes="gaussians.h5",
          reads=("mesh", "cameras", "masks"), needs_cameras=True, pipeline=True,
          summary="Seed 3D Gaussians in the tets and fit their appearance to one frame's masked views "
                  "(L1 + D-SSIM) → gaussians.h5 and fit_gaussians/CAM.png."),
    Stage("generate-data", "stages.steps.generate_data", "GenerateDataConfig", "snapshots", writes="snapshots.h5",
          reads=("mesh",), volatile=("workers", "ray"), pipeline=True,
          summary="Simulate random interaction sequences within the envelope of the capture's controls, with E "
                  "and ν sampled per frame across the prior range of capture.toml → snapshots.h5 (training data "
                  "of the subspace)."),
    Stage("train-subspace", "stages.steps.train_subspace", "TrainSubspaceConfig", "subspace", writes="subspace.h5",
          reads=("snapshots", "mesh"), arguments=(), pipeline=True,
          summary="Fit x = φ(z) to the snapshots (autoencoder of Fulton et al. 2019, PCA, or linear-blend-skinning "
                  "modes) and the optimised cubature of its reduced energy → subspace.h5."),
    Stage("adapt", "stages.steps.adapt", "AdaptConfig", "adapt", writes="adapt.h5",
          reads=("mesh", "cameras", "masks", "gaussians", "subspace"),
          flags=(("fit_poisson", ("--fit-poisson/--fixed-poisson",)),), pipeline=True,
          summary="Adapt the material (E, ν per region) to the capture, frame by frame, over a sliding window; "
                  "writes WS/adapt.h5."),
    Stage("evaluate", "stages.steps.evaluate", "EvaluateConfig", None, writes="evaluation.json, evaluation_young.png",
          reads=("adapt", "mesh", "gaussians", "cameras", "masks"),
          summary="Compare adapt.h5 with CAPTURE/truth (E, ν, surface distance, PSNR, handle and obstacle forces) "
                  "and, with --sweep, the loss over a grid of fixed E; writes WS/evaluation.json and its plots."),
    Stage("export", "stages.steps.export", "ExportConfig", None, writes="export/", reads=("adapt", "mesh", "gaussians",
                                                                                   "cameras"),
          arguments=(), flags=(("out", ("--out", "-o")),),
          summary="Export what the adapted simulation reveals: stress, handle and contact forces, a ParaView "
                  "series, 3DGS PLYs, stress renders and plots. With no product flag, everything the workspace "
                  "allows."),
    Stage("report", "stages.steps.report", "ReportConfig", None, writes="report.html",
          reads=("adapt", "mesh", "gaussians", "cameras"), arguments=(), flags=(("out", ("--out", "-o")),),
          summary="Write one self-contained HTML page (WS/report.html): E(t) ± σ per region against the truth, "
                  "renders beside the photos, stress renders, handle/contact forces, timings and every "
                  "artefact's provenance. Sections the workspace cannot make say why."),
    Stage("rollout", "stages.steps.rollout", "RolloutConfig", None, writes="rollout.h5", reads=("adapt", "mesh", "subspace"),
          summary="Simulate new controls (handle and obstacle motions) with the adapted material, from the adapted "
                  "state or from rest; writes WS/rollout.h5 (read it with `rsl export --source rollout`)."),
)

PIPELINE: tuple[Stage, ...] = tuple(s for s in STAGES if s.pipeline)


def stage(name: str, stages: tuple[Stage, ...] | None = None) -> Stage:
    """The stage called ``name`` among ``stages`` (default: all of :data:`STAGES`); an RslError otherwise."""
    stages = STAGES if stages is None else stages
    for s in stages:
        if s.name == name:
            return s
    raise RslError(f"unknown stage '{name}'; the stages are {', '.join(s.name for s in stages)}.")


# --------------------------------------------------------------------------- options
def config_hints(cls: type) -> dict[str, Any]:
    """Field name -> resolved type of a Config dataclass ({} when the annotations cannot be resolved)."""
    try:
        return typing.get_type_hints(cls)
    except Exception:
        return {}


def coerce(value: Any, hint: Any, where: str) -> Any:
    """A --set value (string from the command line, or already typed) as the field's type."""
    if not isinstance(value, str):
        return value
    origin = typing.get_origin(hint)
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if origin is typing.Union or str(origin) == "<class 'types.UnionType'>":
        hint = args[0] if len(args) == 1 else None
        origin = typing.get_origin(hint)
    try:
        if hint is bool:
            low = value.lower()
            if low not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError(value)
            return low in ("true", "1", "yes")
        if hint is int:
            return int(value)
        if hint is float:
            return float(value)
        if hint is Path:
            return Path(value)
        if hint is str or origin is typing.Literal:
            if origin is typing.Literal and value not in typing.get_args(hint):
                raise ValueError(f"choose one of {', '.join(map(str, typing.get_args(hint)))}")
            return value
    except ValueError as e:
        raise RslError(f"--set {where}={value}: cannot read the value as {getattr(hint, '__name__', hint)} ({e}).") \
            from None
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        return value
