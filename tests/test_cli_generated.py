"""The stage commands generated from the Configs (rsl_cli/options.py, stages/registry.py): one option per
field with the field's default, type, choices and docstring; the command forms of DESIGN §7 parse."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pytest
import typer
from typer.testing import CliRunner

from conftest import run_rsl
from rsl_cli.options import config_command
from stages.config import _ast_docs, field_default, field_docs
from stages.registry import PIPELINE, STAGES


def _click(app: typer.Typer):
    return typer.main.get_command(app)


@pytest.fixture(scope="module")
def root():
    from rsl_cli.app import app

    return _click(app)


def _command(root, name: str):
    ctx = root.make_context("rsl", [name, "--help"], resilient_parsing=True)
    return root.get_command(ctx, name)


@pytest.mark.parametrize("s", STAGES, ids=lambda s: s.name)
def test_every_config_field_is_an_option(root, s) -> None:
    cls = s.config_cls()
    cmd = _command(root, s.name)
    params = {p.name: p for p in cmd.params if p.name != "help"}
    fields = [f.name for f in dataclasses.fields(cls)]
    assert sorted(params) == sorted(fields)
    assert [p.name for p in cmd.params if p.param_type_name == "argument"] == list(s.arguments)
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    for name, p in params.items():
        assert p.help == docs[name], name
        default = field_default(cls, name)
        if default is ...:
            assert p.required, name
        else:
            assert not p.required and p.default == default, name
        if typing.get_origin(hints[name]) is Literal:
            assert tuple(p.type_descriptor.choices) == typing.get_args(hints[name]), name
        if p.param_type_name == "option" and hints[name] is bool:
            flags = dict(s.flags).get(name)
            assert p.secondary_opts == ([flags[0].split("/")[1]] if flags else ["--no-" + name.replace("_", "-")])
    assert cmd.help == s.summary


def test_field_docs_scan_matches_the_parsed_source() -> None:
    """field_docs reads docstrings line by line (fast); the ast of the class source is the slow twin."""
    for s in STAGES:
        cls = s.config_cls()
        assert field_docs(cls) == _ast_docs(cls), s.name
        assert set(field_docs(cls)) == {f.name for f in dataclasses.fields(cls)}, s.name  # every field documented


@dataclass(frozen=True)
class _Demo:
    source: Path
    """Where from."""
    workspace: Path
    """Workspace."""
    level: int = 3
    """A level."""
    mode: Literal["fast", "slow"] = "fast"
    """How."""
    scale: float | None = None
    """A scale, or none."""
    keep: bool = True
    """Keep it."""
    out: Path | None = None
    """Out."""


def test_generated_command_builds_the_config() -> None:
    got = []
    app = typer.Typer()
    app.command("demo")(config_command(_Demo, got.append, ("source",), {"out": ("--out", "-o")}))
    app.command("other")(lambda: None)  # two commands: typer then keeps the command name
    runner = CliRunner()
    r = runner.invoke(app, ["demo", "src", "-w", "ws"])
    assert r.exit_code == 0, r.output
    assert got[-1] == _Demo(Path("src"), Path("ws"))
    r = runner.invoke(app, ["demo", "src", "-w", "ws", "--level", "5", "--mode", "slow", "--scale", "0.5",
                            "--no-keep", "-o", "o"])
    assert r.exit_code == 0, r.output
    assert got[-1] == _Demo(Path("src"), Path("ws"), 5, "slow", 0.5, False, Path("o"))
    assert isinstance(got[-1].scale, float) and isinstance(got[-1].level, int)
    n = len(got)
    r = runner.invoke(app, ["demo", "src", "-w", "ws", "--mode", "sideways"])
    assert r.exit_code != 0 and "sideways" in r.output and len(got) == n  # click refuses it; nothing ran
    r = runner.invoke(app, ["demo", "src"])
    assert r.exit_code != 0 and "--workspace" in r.output  # a field without default is required
    r = runner.invoke(app, ["demo", "--help"])
    text = " ".join(r.output.replace("│", " ").split())
    assert "fast|slow" in text and "A scale, or none." in text and "--no-keep" in text and "[default: 3]" in text


# The forms of DESIGN §7 (and a few more long-standing ones): every one must parse.
FORMS = [
    "synth MESH OUT --scenario twist --cameras 4 --frames 60 --resolution 256 --fps 30 --young 1e5 --poisson 0.45 "
    "--markers 40 --seed 0",
    "synth MESH OUT --young-schedule 1e4@0,2e4@20 --region-young left=1e5 --ramp",
    "synth MESH OUT --steps --region left=1e5",
    "calibrate C -w W --board chessboard:9x6:0.025",
    "calibrate C -w W --board charuco:5x7:0.04:0.02:DICT_6X6_250",
    "calibrate C -w W --sfm",
    "calibrate C -w W --from-json F",
    "calibrate C -w W --from-colmap D",
    "segment C -w W --method sam2",
    "tetrahedralize C -w W --edge-length 0.05 --max-tets 2000 --no-optimize",
    "fit-gaussians C -w W --frame 0 --iterations 10 --gaussians 100",
    "generate-data C -w W --sequences 20 --frames 60 --workers 2 --ray auto",
    "train-subspace -w W --dim 30 --kind pca --epochs 5",
    "adapt C -w W --window 5 --space full --mode offline --loss markers --cameras 0,1,2 --frames 0:60 --follow",
    "adapt C -w W --fixed-poisson --young-init 1e5",
    "evaluate C -w W",
    "export -w W --out D --stress --forces --vtk --ply --render --plots",
    "export -w W -o D --source rollout",
    "rollout C -w W --controls NEW.json",
]


@pytest.mark.parametrize("form", FORMS)
def test_design_command_forms_parse(root, form: str) -> None:
    args = form.split()
    cmd = _command(root, args[0])
    ctx = cmd.make_context(args[0], args[1:])  # parses and validates; runs nothing
    assert ctx.params


def test_bad_choice_is_refused_by_the_cli() -> None:
    p = run_rsl("adapt", "nowhere", "-w", "nowhere_ws", "--space", "sideways")
    assert p.returncode != 0 and "sideways" in p.stderr and "reduced" in p.stderr
    assert "Traceback" not in p.stderr


def test_rsl_help_imports_no_stage_module() -> None:
    """`rsl --help` lists the stages from the registry: no stage module, no jax / torch is imported."""
    code = ("import sys, rsl_cli.app; from typer.main import get_command; get_command(rsl_cli.app.app); "
            "sys.argv = ['rsl', '--help']\n"
            "try:\n    rsl_cli.app.main()\nexcept SystemExit:\n    pass\n"
            "print('MODULES', sorted(m for m in sys.modules if m.split('.')[0] in "
            "('jax', 'torch', 'numba', 'optax', 'h5py') or m in ('scipy.spatial',) or m in "
            + repr(sorted({s.module for s in STAGES})) + "))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "Commands" in out and "tetrahedralize" in out
    assert out.strip().splitlines()[-1] == "MODULES []"


def test_a_stage_command_imports_only_its_stage() -> None:
    code = ("import sys, rsl_cli.app; sys.argv = ['rsl', 'evaluate', '--help']\n"
            "try:\n    rsl_cli.app.main()\nexcept SystemExit:\n    pass\n"
            "print('MODULES', sorted(m for m in sys.modules if m in " + repr(sorted({s.module for s in STAGES})) + "))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "--psnr-frames" in out
    assert out.strip().splitlines()[-1] == "MODULES ['stages.steps.evaluate']"


def test_a_stage_that_cannot_load_breaks_only_its_command(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    from rsl_cli.options import LazyStageCommand
    from stages import registry
    from stages.errors import RslError

    broken = registry.Stage("broken", "stages.no_such_stage", "NoConfig", None, summary="Broken on purpose.")
    monkeypatch.setattr(registry, "STAGES", registry.STAGES + (broken,))
    from rsl_cli.options import RslGroup
    import typer._click as click

    monkeypatch.setattr(RslGroup, "lazy", {**RslGroup.lazy, "broken": broken.summary})
    group = RslGroup(name="rsl")
    text = group.get_help(click.Context(group, info_name="rsl")) + capsys.readouterr().out  # (typer prints it)
    assert "Broken on purpose." in text and "tetrahedralize" in text
    cmd = group.get_command(click.Context(group, info_name="rsl"), "broken")
    assert isinstance(cmd, LazyStageCommand)
    with pytest.raises(RslError, match=r"stage 'broken' \(stages/no_such_stage.py\) not available"):
        cmd.make_context("broken", [])


def test_pipeline_is_the_registry_order() -> None:
    from stages import pipeline

    assert pipeline.STAGES == PIPELINE
    assert [s.name for s in PIPELINE] == [s.name for s in STAGES if s.pipeline]
    from stages.artefacts import KIND_FILES

    for s in STAGES:
        assert s.produces is None or KIND_FILES[s.produces] == s.writes, s.name
        assert set(s.reads) <= set(KIND_FILES), s.name
    assert set(KIND_FILES) == {s.produces for s in PIPELINE}  # each artefact kind is made by one `rsl run` step


def test_cli_reference_is_generated_from_the_cli() -> None:
    """docs/cli.md is exactly what `rsl help-markdown` prints (every option, default and choice)."""
    p = run_rsl("help-markdown")
    assert p.returncode == 0, p.stderr
    doc = (Path(__file__).resolve().parents[1] / "docs" / "cli.md").read_text()
    assert p.stdout == doc, "docs/cli.md is out of date: run `rsl help-markdown > docs/cli.md`"


def test_export_products_switched_off_alone_leave_the_others_made(tmp_path) -> None:
    """`rsl export --no-forces`: every product whose inputs exist except forces (a `bool | None` field is a
    --x/--no-x flag pair, unset when not given); `--stress` alone: stress only."""
    from stages.artefacts import KIND_FILES
    from stages.steps.export import PRODUCTS, ExportConfig, chosen_products

    got = []
    app = typer.Typer()
    app.command("export")(config_command(ExportConfig, got.append, (), {}))
    app.command("other")(lambda: None)
    runner = CliRunner()
    for args in (["--no-forces"], ["--stress"], []):
        r = runner.invoke(app, ["export", "-w", str(tmp_path), *args])
        assert r.exit_code == 0, r.output
    no_forces, stress_only, plain = got
    assert no_forces.forces is False and all(getattr(no_forces, p) is None for p in PRODUCTS if p != "forces")
    everything = {"stress", "forces", "vtk", "plots"}
    assert chosen_products(plain, tmp_path) == everything
    assert chosen_products(no_forces, tmp_path) == everything - {"forces"}
    assert chosen_products(stress_only, tmp_path) == {"stress"}
    (tmp_path / KIND_FILES["gaussians"]).write_bytes(b"")  # with Gaussians, PLY and renders too
    assert chosen_products(no_forces, tmp_path) == everything - {"forces"} | {"ply", "render"}
