"""The command line: help texts from config docstrings, tetrahedralize → info → status → run, staleness."""
from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import textwrap
from pathlib import Path

import pytest

from stages import pipeline
from stages.config import field_docs
from stages.errors import RslError
from stages.pipeline import Stage, parse_sets, run_pipeline
from stages.progress import SilentReporter
from stages.steps.tetrahedralize import TetrahedralizeConfig
from stages.workspace import MISSING, OK, STALE, artefact_state, config_differences
from test_bad_inputs import run_batch


def _flat(text: str) -> str:
    return " ".join(text.replace("│", " ").split())


@pytest.fixture(scope="module")
def session(tmp_path_factory, sample_data: Path) -> dict:
    """One child process: help pages, then tetrahedralize, info, status and run on a copy of the bar."""
    base = tmp_path_factory.mktemp("cli")
    cap = base / "bar"
    shutil.copytree(sample_data / "bar", cap)
    ws = base / "ws"
    names = ["help", "tet_help", "run_help", "tet", "info", "info_json", "status", "run_skip", "dry_run",
             "capture_info", "markdown"]
    procs = run_batch([
        ["--help"], ["tetrahedralize", "--help"], ["run", "--help"],
        ["tetrahedralize", cap, "-w", ws], ["info", ws / "mesh.h5"], ["info", ws / "mesh.h5", "--json"],
        ["status", "-w", ws], ["run", cap, "-w", ws, "--only", "tetrahedralize"],
        ["run", cap, "-w", ws, "--dry-run"], ["info", cap], ["help-markdown"],
    ], base)
    first = dict(zip(names, procs))
    # Change an input: the mesh becomes stale; run remakes it; then everything is up to date again.
    controls = json.loads((cap / "controls.json").read_text())
    controls["handles"][0]["stiffness"] = 2.0e4
    (cap / "controls.json").write_text(json.dumps(controls))
    names2 = ["status_stale", "run_remake", "status_ok", "run_threads", "run_config", "run_force"]
    procs = run_batch([["status", "-w", ws], ["run", cap, "-w", ws, "--only", "tetrahedralize"], ["status", "-w", ws],
                       ["run", cap, "-w", ws, "--only", "tetrahedralize", "--set", "tetrahedralize.threads=1"],
                       ["run", cap, "-w", ws, "--only", "tetrahedralize", "--set", "tetrahedralize.optimize=false"],
                       ["run", cap, "-w", ws, "--only", "tetrahedralize", "--set", "tetrahedralize.optimize=false",
                        "--force"]], base)
    return {**first, **dict(zip(names2, procs)), "ws": ws, "cap": cap}


def test_help_lists_commands(session: dict) -> None:
    p = session["help"]
    assert p.returncode == 0, p.stderr
    text = _flat(p.stdout + p.stderr)
    for cmd in ("run", "tetrahedralize", "info", "status"):
        assert f" {cmd} " in text
    assert "Every stage in order" in text and "Tet mesh of the object" in text
    cmds = text[text.index("Commands"):]
    assert cmds.index(" run ") < cmds.index(" tetrahedralize ") < cmds.index(" info ") < cmds.index(" status ")


def test_stage_help_comes_from_config_docstrings(session: dict) -> None:
    text = _flat(session["tet_help"].stdout + session["tet_help"].stderr)
    docs = field_docs(TetrahedralizeConfig)
    for name in ("edge_length", "max_tets", "optimize", "envelope", "degenerate_tol"):
        assert "--" + name.replace("_", "-") in text
        assert " ".join(docs[name].split()[:6]) in text, name
    assert "0.05" in text  # the default, from the dataclass
    run_text = _flat(session["run_help"].stdout)
    assert "--until" in run_text and "--set" in run_text and "STAGE.OPTION=VALUE" in run_text


def test_tetrahedralize_info_status(session: dict) -> None:
    tet = session["tet"]
    assert tet.returncode == 0, tet.stderr
    assert "1959 vertices, 979 tets of order 2" in _flat(tet.stderr)  # quadratic tets by default
    info = _flat(session["info"].stdout)
    assert "kind mesh" in info and "vertices (1959, 3) float64" in info and "tets (979, 10) int64" in info
    assert "object.mesh sha256" in info and "edge_length = 0.05" in info
    data = json.loads(session["info_json"].stdout)
    assert data["attrs"]["rsl_kind"] == "mesh" and len(data["attrs"]["inputs"]) == 3
    assert {"name": "dm_inv", "shape": [979, 3, 3], "dtype": "float64"} in data["datasets"]
    status = _flat(session["status"].stdout)
    assert "tetrahedralize mesh.h5 up to date" in status and "calibrate cameras.h5 missing" in status
    cap_info = _flat(session["capture_info"].stdout)
    assert "capture bar" in cap_info and '"left", "right"' in cap_info


def test_run_skips_up_to_date_and_remakes_stale(session: dict) -> None:
    skip = session["run_skip"]
    assert skip.returncode == 0, skip.stderr
    assert "tetrahedralize: skipped, mesh.h5 is up to date" in _flat(skip.stderr)
    assert "0 stages ran, 1 up to date" in _flat(skip.stderr)
    dry = _flat(session["dry_run"].stdout)
    assert "tetrahedralize skip mesh.h5 is up to date" in dry
    assert "adapt run" in dry  # no adapt.h5 yet
    assert "calibrate skip not applicable: the capture lists no camera" in dry
    stale = _flat(session["status_stale"].stdout)
    assert "mesh.h5 stale" in stale and "input controls.json changed" in stale
    remake = _flat(session["run_remake"].stderr)
    assert session["run_remake"].returncode == 0 and "running (mesh.h5 stale: input controls.json changed)" in remake
    assert "mesh.h5 up to date" in _flat(session["status_ok"].stdout)
    assert "skipped, mesh.h5 is up to date" in _flat(session["run_threads"].stderr)  # threads: volatile
    cfg = _flat(session["run_config"].stderr)
    assert "running (config changed (optimize was True, now False))" in cfg
    assert "running (--force)" in _flat(session["run_force"].stderr)


def test_cli_reference_is_current(session: dict) -> None:
    """docs/cli.md documents every command there is (regenerate: rsl help-markdown > docs/cli.md)."""
    md = session["markdown"].stdout
    assert session["markdown"].returncode == 0 and "| `--edge-length` |" in md
    heads = {ln for ln in md.splitlines() if ln.startswith("## rsl ")}
    assert {"## rsl run", "## rsl tetrahedralize", "## rsl info", "## rsl status"} <= heads
    doc = Path(__file__).resolve().parents[1] / "docs" / "cli.md"
    documented = {ln for ln in doc.read_text().splitlines() if ln.startswith("## rsl ")}
    assert heads == documented, "docs/cli.md is out of date: run `rsl help-markdown > docs/cli.md`"


# --------------------------------------------------------------------------- the pipeline logic, in process
FAKE = '''
from dataclasses import dataclass
from pathlib import Path
from stages.artefacts import KIND_FILES, MeshArtefact, Provenance, SubspaceArtefact, load_any
import numpy as np
CALLS = []

@dataclass(frozen=True)
class FirstConfig:
    capture: Path
    """Capture."""
    workspace: Path
    """Workspace."""
    level: int = 1
    """A level."""

def run(config, reporter):
    CALLS.append(("first", config.level))
    src = Path(config.capture) / "input.txt"
    out = Path(config.workspace) / KIND_FILES["subspace"]
    SubspaceArtefact("pca", config.level, {"w": np.ones(2)}, 0.0, 0.0).save(out, Provenance.make(config, [src]))
    reporter.summary("first done")
    return out
'''

FAKE2 = '''
from dataclasses import dataclass
from pathlib import Path
from stages.artefacts import KIND_FILES, Provenance, AdaptArtefact
from stages.errors import RslError
import numpy as np
CALLS = []

@dataclass(frozen=True)
class SecondConfig:
    workspace: Path
    """Workspace."""
    fail: bool = False
    """Fail on purpose."""

def run(config, reporter):
    CALLS.append("second")
    if config.fail:
        raise RslError("second.txt: told to fail.")
    src = Path(config.workspace) / KIND_FILES["subspace"]
    out = Path(config.workspace) / KIND_FILES["adapt"]
    z = np.zeros((1, 1))
    AdaptArtefact(np.arange(1), z + 1, z, z, np.zeros((1, 1, 3)), z[0], z[0], z[0], z[0], z[0], ["body"],
                  "online", "full", "markers", 1).save(out, Provenance.make(config, [src]))
    return out
'''


@pytest.fixture
def fake_stages(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "first.py").write_text(textwrap.dedent(FAKE))
    (pkg / "second.py").write_text(textwrap.dedent(FAKE2))
    monkeypatch.syspath_prepend(str(tmp_path))
    for m in [m for m in sys.modules if m.startswith("fakepkg")]:
        monkeypatch.delitem(sys.modules, m)
    stages = (Stage("first", "fakepkg.first", "FirstConfig", "subspace"),
              Stage("second", "fakepkg.second", "SecondConfig", "adapt", ("subspace",)),
              Stage("third", "fakepkg.third", "ThirdConfig", "masks"))
    monkeypatch.setattr(pipeline, "STAGES", stages)
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "input.txt").write_text("one")
    return cap, tmp_path / "ws"


def test_pipeline_runs_skips_and_reruns(fake_stages) -> None:
    cap, ws = fake_stages
    with pytest.raises(RslError, match=r"stage 'third' \(fakepkg/third.py\) not available"):
        run_pipeline(cap, ws)
    r = SilentReporter()
    steps = run_pipeline(cap, ws, r, until="second")
    import fakepkg.first as first
    import fakepkg.second as second

    assert [s.action for s in steps] == ["run", "run"] and first.CALLS == [("first", 1)]
    assert "first done" in r.messages and r.messages[-1].startswith("rsl run: 2 stages ran, 0 up to date")
    steps = run_pipeline(cap, ws, until="second")
    assert [s.action for s in steps] == ["skip", "skip"] and len(first.CALLS) == 1
    # A changed input remakes the first stage, and so the second that reads its artefact.
    (cap / "input.txt").write_text("two")
    assert artefact_state(ws, "subspace").state == STALE
    steps = run_pipeline(cap, ws, until="second")
    assert [(s.action, s.reason) for s in steps] == [("run", "subspace.h5 stale: input input.txt changed"),
                                                      ("run", "subspace was remade")]
    # A changed option remakes only what depends on it.
    steps = run_pipeline(cap, ws, only=["second"], overrides={"second": {"fail": "false"}})
    assert [s.action for s in steps] == ["skip"]
    steps = run_pipeline(cap, ws, until="second", overrides=parse_sets(["first.level=3"]))
    assert steps[0].reason == "config changed (level was 1, now 3)" and first.CALLS[-1] == ("first", 3)
    assert steps[1].reason == "subspace was remade"  # its config is the same; it reads a remade artefact
    assert second.CALLS == ["second"] * 3
    # A failing stage names itself and leaves its old artefact in place.
    with pytest.raises(RslError, match=r"stage 'second' failed: second.txt: told to fail"):
        run_pipeline(cap, ws, only=["second"], overrides={"second": {"fail": "true"}})
    assert artefact_state(ws, "adapt").state == OK
    (ws / "subspace.h5").unlink()
    assert artefact_state(ws, "subspace").state == MISSING
    assert artefact_state(ws, "adapt").state == STALE


def test_pipeline_stage_errors(fake_stages) -> None:
    cap, ws = fake_stages
    with pytest.raises(RslError, match="unknown stage 'fourth'"):
        run_pipeline(cap, ws, until="fourth")
    with pytest.raises(RslError, match="write it as STAGE.OPTION=VALUE"):
        parse_sets(["first.level"])
    with pytest.raises(RslError, match=r"--set first.level=x: cannot read the value as int"):
        run_pipeline(cap, ws, only=["first"], overrides=parse_sets(["first.level=x"]))


def test_real_pipeline_names_every_stage() -> None:
    names = [s.name for s in pipeline.STAGES]
    assert names == ["calibrate", "tetrahedralize", "segment", "fit-gaussians", "generate-data",
                     "train-subspace", "adapt"]
    assert [s.module for s in pipeline.STAGES] == [
        "stages.steps.calibrate", "stages.steps.tetrahedralize", "stages.steps.segment", "stages.steps.fit_gaussians",
        "stages.steps.generate_data", "stages.steps.train_subspace", "stages.steps.adapt"]
    t = pipeline.stage("tetrahedralize")
    cfg = t.make_config(Path("c"), Path("w"), {"max_tets": "500", "optimize": "false"})
    assert cfg == TetrahedralizeConfig(Path("c"), Path("w"), max_tets=500, optimize=False)


def test_config_differences() -> None:
    cfg = TetrahedralizeConfig(Path("sample_data/bar"), Path("ws"))
    stored = json.loads(json.dumps(dataclasses.asdict(cfg), default=str))
    assert config_differences(stored, cfg) == []
    stored["capture"] = str(Path("sample_data/bar").resolve())  # same folder, written another way
    stored["workspace"] = "elsewhere"  # ignored
    assert config_differences(stored, cfg) == []
    stored["edge_length"] = 0.1
    del stored["threads"]
    assert config_differences(stored, cfg) == ["edge_length was 0.1, now 0.05", "option threads is new"]
    assert config_differences(stored, cfg, ignore=("threads",)) == ["edge_length was 0.1, now 0.05"]
