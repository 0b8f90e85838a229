"""`rsl evaluate`: errors of adapt.h5 against a synthetic capture's truth/."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.evaluate import EvaluateConfig, run

ORDER = 75


def register(app: typer.Typer) -> None:
    @app.command("evaluate", help="Compare adapt.h5 with CAPTURE/truth (E, ν, surface distance, PSNR); "
                                  "writes WS/evaluation.json and WS/evaluation_young.png.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Synthetic capture folder with truth/."),
        workspace: Path = workspace_option(),
        psnr_frames: int = opt(EvaluateConfig, "psnr_frames", "--psnr-frames"),
        plot: bool = opt(EvaluateConfig, "plot", "--plot/--no-plot"),
    ) -> None:
        run(EvaluateConfig(capture=capture, workspace=workspace, psnr_frames=psnr_frames, plot=plot),
            RichReporter())
