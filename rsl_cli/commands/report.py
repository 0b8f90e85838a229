"""`rsl report -w WS`: one self-contained HTML page of the workspace's results → WS/report.html."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option

ORDER = 85


def register(app: typer.Typer) -> None:
    from stages.report import ReportConfig

    @app.command("report", help="Write one self-contained HTML page (WS/report.html): E(t) ± σ per region against "
                                "the truth, renders beside the photos, stress renders, handle/contact forces, "
                                "timings and every artefact's provenance. Sections the workspace cannot make "
                                "say why.")
    def _cmd(
        workspace: Path = workspace_option(),
        out: Optional[Path] = opt(ReportConfig, "out", "--out", "-o"),
        capture: Optional[Path] = opt(ReportConfig, "capture", "--capture"),
        frames: int = opt(ReportConfig, "frames"),
        cameras: int = opt(ReportConfig, "cameras"),
        contact_distance: float = opt(ReportConfig, "contact_distance"),
    ) -> None:
        from stages.report import run

        run(ReportConfig(workspace=workspace, out=out, capture=capture, frames=frames, cameras=cameras,
                         contact_distance=contact_distance), RichReporter())
