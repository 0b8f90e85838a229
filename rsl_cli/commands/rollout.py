"""`rsl rollout`: predict new handle/obstacle motions with the adapted material."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option

ORDER = 85


def register(app: typer.Typer) -> None:
    from stages.rollout import RolloutConfig

    @app.command("rollout", help="Simulate new controls (handle and obstacle motions) with the adapted "
                                 "material, from the adapted state or from rest; writes WS/rollout.h5 "
                                 "(read it with `rsl export --source rollout`).")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder (material model, fps, gravity).",
                                       file_okay=False),
        workspace: Path = workspace_option(),
        controls: Path = opt(RolloutConfig, "controls", "--controls", default=...),
        frames: int = opt(RolloutConfig, "frames", "--frames"),
        material: str = opt(RolloutConfig, "material", "--material"),
        from_rest: bool = opt(RolloutConfig, "from_rest", "--from-rest"),
        space: str = opt(RolloutConfig, "space", "--space"),
        solver: str = opt(RolloutConfig, "solver", "--solver"),
        contact_distance: float = opt(RolloutConfig, "contact_distance", "--contact-distance"),
    ) -> None:
        from stages.rollout import run

        run(RolloutConfig(capture=capture, workspace=workspace, controls=controls, frames=frames,
                          material=material, from_rest=from_rest, space=space, solver=solver,
                          contact_distance=contact_distance), RichReporter())
