"""`rsl run`: every stage in order, skipping those whose artefact is up to date (DESIGN §1).

Each stage is named by its module and Config class, imported only when its turn
comes (importlib), so a stage's heavy dependencies load only when it runs.  A
stage is skipped when its artefact exists, every input file recorded in it still
has the recorded sha256, the artefacts it reads are themselves up to date, and
the config it was made with equals the config it would run with now.
"""
from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import json
import typing
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from stages.errors import RslError
from stages.progress import Reporter, SilentReporter
from stages.workspace import INVALID, MISSING, OK, STALE, artefact_state, config_differences


@dataclass(frozen=True)
class Stage:
    """One step of the pipeline: the command name, where its code lives, what it writes and reads."""

    name: str  # CLI command, e.g. "fit-gaussians"
    module: str  # e.g. "stages.fit_gaussians"
    config_class: str  # e.g. "FitGaussiansConfig"
    produces: str  # artefact kind (stages.artefacts.KIND_FILES)
    reads: tuple[str, ...] = ()  # artefact kinds it reads when present
    needs_cameras: bool = False  # not applicable to a capture that lists no camera
    volatile: tuple[str, ...] = ()  # options that do not change the artefact (threads, workers)

    def available(self) -> bool:
        """Whether the stage's module can be found (without importing it)."""
        try:
            return importlib.util.find_spec(self.module) is not None
        except (ImportError, ValueError):
            return False

    def load(self) -> ModuleType:
        """Import the stage module; a clear RslError when it is not there (yet)."""
        if not self.available():
            raise RslError(f"stage '{self.name}' is not available: module {self.module} is not installed "
                           f"in this rsl ({self.module.replace('.', '/')}.py is missing).")
        try:
            mod = importlib.import_module(self.module)
        except ImportError as e:
            raise RslError(f"stage '{self.name}' is not available: importing {self.module} failed ({e}).") from None
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
        hints = _hints(cls)
        for key, value in (overrides or {}).items():
            if key not in fields:
                raise RslError(f"--set {self.name}.{key}: {self.config_class} has no option '{key}' "
                               f"(options: {', '.join(n for n in fields if n not in ('capture', 'workspace'))}).")
            kw[key] = _coerce(value, hints.get(key), f"{self.name}.{key}")
        missing = [n for n, f in fields.items() if n not in kw and f.default is dataclasses.MISSING
                   and f.default_factory is dataclasses.MISSING]  # type: ignore[misc]
        if missing:
            raise RslError(f"stage '{self.name}' needs option(s) {', '.join(missing)}; give them with "
                           f"--set {self.name}.{missing[0]}=VALUE.")
        return cls(**kw)


STAGES: tuple[Stage, ...] = (
    Stage("calibrate", "stages.calibrate", "CalibrateConfig", "cameras", needs_cameras=True),
    Stage("segment", "stages.segment", "SegmentConfig", "masks", ("cameras",), needs_cameras=True),
    Stage("tetrahedralize", "stages.tetrahedralize", "TetrahedralizeConfig", "mesh", volatile=("threads",)),
    Stage("fit-gaussians", "stages.fit_gaussians", "FitGaussiansConfig", "gaussians", ("mesh", "cameras", "masks"),
          needs_cameras=True),
    Stage("generate-data", "stages.generate_data", "GenerateDataConfig", "snapshots", ("mesh",),
          volatile=("workers", "ray")),
    Stage("train-subspace", "stages.train_subspace", "TrainSubspaceConfig", "subspace", ("snapshots", "mesh")),
    Stage("adapt", "stages.adapt", "AdaptConfig", "adapt", ("mesh", "cameras", "masks", "gaussians", "subspace")),
)


def stage(name: str) -> Stage:
    for s in STAGES:
        if s.name == name:
            return s
    raise RslError(f"unknown stage '{name}'; the stages are {', '.join(s.name for s in STAGES)}.")


def producer(kind: str) -> Stage | None:
    for s in STAGES:
        if s.produces == kind:
            return s
    return None


# --------------------------------------------------------------------------- options
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:
        return {}


def _coerce(value: Any, hint: Any, where: str) -> Any:
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


def parse_sets(items: list[str]) -> dict[str, dict[str, str]]:
    """["stage.field=value", ...] -> {stage: {field: value}}."""
    out: dict[str, dict[str, str]] = {}
    for item in items:
        key, sep, value = item.partition("=")
        name, dot, fld = key.partition(".")
        if not sep or not dot or not fld:
            raise RslError(f"--set {item}: write it as STAGE.OPTION=VALUE, e.g. tetrahedralize.edge_length=0.03.")
        stage(name)  # validates the stage name
        out.setdefault(name, {})[fld.replace("-", "_")] = value
    return out


# --------------------------------------------------------------------------- planning and running
@dataclass
class Step:
    """What ``rsl run`` did (or would do) with one stage."""

    stage: Stage
    action: str  # "run" | "skip"
    reason: str


def _has_cameras(capture: Path | None) -> bool:
    """Whether capture.toml lists cameras (an unreadable capture counts as yes: the stage will say what is wrong)."""
    if capture is None:
        return False
    from stages.capture import load_capture

    try:
        return bool(load_capture(capture).camera_names)
    except RslError:
        return True


def selected(until: str | None = None, only: list[str] | None = None) -> list[Stage]:
    """The stages to consider: all in order, up to ``until``, or just ``only``."""
    if only:
        names = {stage(n).name for n in only}
        return [s for s in STAGES if s.name in names]
    if until:
        idx = STAGES.index(stage(until))
        return list(STAGES[: idx + 1])
    return list(STAGES)


def decide(s: Stage, config: Any, workspace: Path, remade: set[str], hashes: dict[str, str]) -> tuple[str, str]:
    """("run"|"skip", why) for one stage, given the kinds remade earlier in this run."""
    st = artefact_state(workspace, s.produces, hashes)
    if st.state in (MISSING, INVALID):
        return "run", f"{st.path.name} {st.state}" + (f": {st.reasons[0]}" if st.reasons else "")
    for k in s.reads:
        if k in remade:
            return "run", f"{k} was remade"
        up = artefact_state(workspace, k, hashes)
        if up.state in (STALE, INVALID):
            return "run", f"{up.path.name} it reads is {up.state}"
    if st.state != OK:
        return "run", f"{st.path.name} {st.state}: {st.reasons[0]}"
    diffs = config_differences(st.config, config, ignore=s.volatile)
    if diffs:
        return "run", f"config changed ({diffs[0]})"
    return "skip", f"{st.path.name} is up to date"


def plan(capture: Path | None, workspace: Path, *, until: str | None = None, only: list[str] | None = None,
         force: bool = False, overrides: dict[str, dict[str, Any]] | None = None) -> list[Step]:
    """What ``rsl run`` would do, without running anything (a stage due to run counts as remade)."""
    steps: list[Step] = []
    remade: set[str] = set()
    hashes: dict[str, str] = {}
    cams = _has_cameras(capture)
    for s in selected(until, only):
        if s.needs_cameras and not cams:
            steps.append(Step(s, "skip", "not applicable: the capture lists no camera"))
            continue
        if not s.available():
            steps.append(Step(s, "run", f"not available ({s.module.replace('.', '/')}.py is missing)"))
            remade.add(s.produces)
            continue
        config = s.make_config(capture, workspace, (overrides or {}).get(s.name))
        action, why = ("run", "--force") if force else decide(s, config, Path(workspace), remade, hashes)
        if action == "run":
            remade.add(s.produces)
        steps.append(Step(s, action, why))
    return steps


def run_pipeline(capture: Path | None, workspace: Path, reporter: Reporter = SilentReporter(), *,
                 until: str | None = None, only: list[str] | None = None, force: bool = False,
                 overrides: dict[str, dict[str, Any]] | None = None) -> list[Step]:
    """Run the selected stages in order; stop at the first failure (an RslError naming the stage)."""
    workspace = Path(workspace)
    cams = _has_cameras(capture)
    stages = [s for s in selected(until, only) if cams or not s.needs_cameras]
    if not stages:
        raise RslError(f"{capture}: nothing to run; the selected stages need cameras and capture.toml lists none.")
    if len(stages) < len(selected(until, only)):
        reporter.info("the capture lists no camera: calibrate, segment and fit-gaussians do not apply")
    overrides = overrides or {}
    missing = [s for s in stages if not s.available()]
    if missing:
        names = ", ".join(f"'{s.name}' ({s.module.replace('.', '/')}.py)" for s in missing)
        raise RslError(f"stage{'s' if len(missing) > 1 else ''} {names} not available in this rsl yet; "
                       f"run the stages before it with --until, or the others with --only.")
    steps: list[Step] = []
    remade: set[str] = set()
    hashes: dict[str, str] = {}
    for i, s in enumerate(stages, start=1):
        mod = s.load()
        config = s.make_config(capture, workspace, overrides.get(s.name), mod)
        action, why = ("run", "--force") if force else decide(s, config, workspace, remade, hashes)
        if action == "skip":
            reporter.info(f"[{i}/{len(stages)}] {s.name}: skipped, {why}")
            steps.append(Step(s, action, why))
            continue
        reporter.info(f"[{i}/{len(stages)}] {s.name}: running ({why})")
        try:
            mod.run(config, reporter)
        except RslError as e:
            raise RslError(f"stage '{s.name}' failed: {e}") from None
        hashes.clear()  # files may have changed
        steps.append(Step(s, "run", why))
        remade.add(s.produces)
    ran = sum(st.action == "run" for st in steps)
    reporter.summary(f"rsl run: {ran} stage{'s' if ran != 1 else ''} ran, {len(steps) - ran} up to date; "
                     f"artefacts in {workspace}")
    return steps
