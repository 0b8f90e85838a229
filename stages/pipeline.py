"""`rsl run`: every stage in order, skipping those whose artefact is up to date (DESIGN §1).

The stages and their order are those of stages/registry.py (``pipeline=True``); a
stage's module is imported when ``rsl run`` selects it, so heavy dependencies load
only for the stages that run.  A stage is skipped when its artefact exists, every input file recorded in it still
has the recorded sha256, the artefacts it reads are themselves up to date, and
the config it was made with equals the config it would run with now.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stages.capture import load_capture
from stages.errors import Interrupted, RslError
from stages.progress import Reporter, SilentReporter
from stages.registry import PIPELINE, Stage
from stages.registry import stage as _stage
from stages.workspace import INVALID, MISSING, OK, STALE, artefact_state, config_differences

STAGES: tuple[Stage, ...] = PIPELINE  # `rsl run`'s steps, in order (described in stages/registry.py)


def stage(name: str) -> Stage:
    """The pipeline stage called ``name``."""
    return _stage(name, STAGES)


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


def _capture_kind(capture: Path | None, overrides: dict[str, dict[str, Any]] | None = None) -> tuple[bool, bool]:
    """(whether capture.toml lists cameras, whether it is adapted from its markers because it was filmed
    mid-motion) from one reading: start = "moving" with markers.csv or markers.c3d, and adapt.loss not set to
    vision in ``overrides`` (without markers such a capture goes through segment, fit-gaussians and the images).
    An unreadable capture counts as one with cameras that starts at rest or equilibrium: the stages will say
    what is wrong."""
    if capture is None:
        return False, False
    try:
        cap = load_capture(capture)
    except RslError:
        return True, False
    loss = (overrides or {}).get("adapt", {}).get("loss", "markers")
    return bool(cap.camera_names), cap.start == "moving" and cap.markers_path.exists() and loss == "markers"


MOVING_SKIPS = ("segment", "fit-gaussians")
"""The stages a capture filmed mid-motion ([capture] start = "moving") that has markers leaves out: rsl adapt
estimates its frame 0 from the markers (docs/capture.md); its images would need the Gaussians, fitted with frame 0
posed from its masks."""


def not_applicable(s: Stage, cams: bool, moving: bool) -> str | None:
    """Why stage ``s`` does not apply to the capture (it lists cameras: ``cams``; it starts mid-motion and is adapted
    from its markers: ``moving``), or None when it does."""
    if s.needs_cameras and not cams:
        return "not applicable: the capture lists no camera"
    if moving and s.name in MOVING_SKIPS:
        return "not applicable: a capture filmed mid-motion (start = \"moving\") is adapted from its markers"
    return None


def with_capture_defaults(overrides: dict[str, dict[str, Any]] | None, moving: bool) -> dict[str, dict[str, Any]]:
    """``overrides`` with what the capture implies: a moving start with markers adapts from them (adapt.loss)
    unless set."""
    out = {k: dict(v) for k, v in (overrides or {}).items()}
    if moving:
        out.setdefault("adapt", {}).setdefault("loss", "markers")
    return out


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
    cams, moving = _capture_kind(capture, overrides)
    overrides = with_capture_defaults(overrides, moving)
    for s in selected(until, only):
        why_not = not_applicable(s, cams, moving)
        if why_not:
            steps.append(Step(s, "skip", why_not))
            continue
        config = s.make_config(capture, workspace, overrides.get(s.name))
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
    cams, moving = _capture_kind(capture, overrides)
    stages = [s for s in selected(until, only) if not not_applicable(s, cams, moving)]
    if not stages:
        raise RslError(f"{capture}: nothing to run; the selected stages need cameras and capture.toml lists none.")
    if len(stages) < len(selected(until, only)):
        reporter.info("the capture lists no camera: calibrate, segment and fit-gaussians do not apply" if not cams
                      else "the capture was filmed mid-motion (start = \"moving\"): segment and fit-gaussians do "
                           "not apply, adapt uses the markers (--set adapt.loss=vision: the images)")
    overrides = with_capture_defaults(overrides, moving)
    mods = {s.name: s.load() for s in stages}  # every selected stage importable before any runs
    steps: list[Step] = []
    remade: set[str] = set()
    hashes: dict[str, str] = {}
    for i, s in enumerate(stages, start=1):
        mod = mods[s.name]
        config = s.make_config(capture, workspace, overrides.get(s.name), mod)
        action, why = ("run", "--force") if force else decide(s, config, workspace, remade, hashes)
        if action == "skip":
            reporter.info(f"[{i}/{len(stages)}] {s.name}: skipped, {why}")
            steps.append(Step(s, action, why))
            continue
        reporter.info(f"[{i}/{len(stages)}] {s.name}: running ({why})")
        try:
            mod.run(config, reporter)
        except Interrupted:
            raise
        except RslError as e:
            raise RslError(f"stage '{s.name}' failed: {e}") from None
        hashes.clear()  # files may have changed
        steps.append(Step(s, "run", why))
        remade.add(s.produces)
    ran = sum(st.action == "run" for st in steps)
    reporter.summary(f"rsl run: {ran} stage{'s' if ran != 1 else ''} ran, {len(steps) - ran} up to date; "
                     f"artefacts in {workspace}")
    return steps
