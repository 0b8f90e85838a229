"""`rsl generate-data CAPTURE -w WS`: random interaction sequences with sampled material → snapshots.h5."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.generate_data import GenerateDataConfig, run

ORDER = 50


def register(app: typer.Typer) -> None:
    @app.command("generate-data", help="Simulate random interaction sequences within the envelope of the "
                                       "capture's controls, with E and ν sampled per frame across the prior "
                                       "range of capture.toml → snapshots.h5 (training data of the subspace).")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder (capture.toml, controls.json)."),
        workspace: Path = workspace_option(),
        sequences: int = opt(GenerateDataConfig, "sequences"),
        frames: int = opt(GenerateDataConfig, "frames"),
        workers: int = opt(GenerateDataConfig, "workers"),
        ray: str = opt(GenerateDataConfig, "ray"),
        material_sampling: str = opt(GenerateDataConfig, "material_sampling"),
        keyframe_gap: int = opt(GenerateDataConfig, "keyframe_gap"),
        jitter: float = opt(GenerateDataConfig, "jitter"),
        newton_iterations: int = opt(GenerateDataConfig, "newton_iterations"),
        seed: int = opt(GenerateDataConfig, "seed"),
    ) -> None:
        run(GenerateDataConfig(capture=capture, workspace=workspace, sequences=sequences, frames=frames,
                               workers=workers, ray=ray, material_sampling=material_sampling,
                               keyframe_gap=keyframe_gap, jitter=jitter, newton_iterations=newton_iterations,
                               seed=seed), RichReporter())
