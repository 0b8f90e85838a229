"""`rsl run CAPTURE -w WS`: every stage in order, skipping what is up to date."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from rsl_cli.console import RichReporter, out
from rsl_cli.options import workspace_option
from stages.registry import PIPELINE

ORDER = 1


def register(app: typer.Typer) -> None:
    @app.command("run", help=f"Every stage in order ({', '.join(s.name for s in PIPELINE)}), skipping a stage "
                             "whose artefact is up to date with its inputs and config.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder."),
        workspace: Path = workspace_option(),
        until: Optional[str] = typer.Option(None, "--until", help="Stop after this stage."),
        only: Optional[List[str]] = typer.Option(None, "--only", help="Run just this stage (repeatable)."),
        force: bool = typer.Option(False, "--force", help="Run every selected stage even if up to date."),
        set_: Optional[List[str]] = typer.Option(
            None, "--set", help="A stage option, STAGE.OPTION=VALUE (repeatable), e.g. tetrahedralize.max_tets=2000."),
        dry_run: bool = typer.Option(False, "--dry-run", help="Only say which stages would run and why."),
    ) -> None:
        from stages.pipeline import parse_sets, plan, run_pipeline  # loaded on use (`rsl --help` stays fast)

        overrides = parse_sets(set_ or [])
        if dry_run:
            for step in plan(capture, workspace, until=until, only=only, force=force, overrides=overrides):
                out(f"{step.stage.name:<16} {step.action:<5} {step.reason}", markup=False)
            return
        run_pipeline(capture, workspace, RichReporter(), until=until, only=only, force=force, overrides=overrides)
