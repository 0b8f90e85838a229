"""`rsl tetrahedralize CAPTURE -w WS`: the rest shape as a tet mesh (mesh.h5)."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.tetrahedralize import TetrahedralizeConfig, run

ORDER = 30


def register(app: typer.Typer) -> None:
    @app.command("tetrahedralize", help="Tet mesh of the object (fTetWild from its surface, or its tet mesh as "
                                        "it is) with regions, handles, rest quantities and a quality report "
                                        "→ mesh.h5.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder (capture.toml, object mesh, controls.json)."),
        workspace: Path = workspace_option(),
        edge_length: float = opt(TetrahedralizeConfig, "edge_length"),
        max_tets: int = opt(TetrahedralizeConfig, "max_tets"),
        optimize: bool = opt(TetrahedralizeConfig, "optimize", "--optimize/--no-optimize"),
        threads: int = opt(TetrahedralizeConfig, "threads"),
        envelope: float = opt(TetrahedralizeConfig, "envelope"),
        degenerate_tol: float = opt(TetrahedralizeConfig, "degenerate_tol"),
        preview: bool = opt(TetrahedralizeConfig, "preview", "--preview/--no-preview"),
    ) -> None:
        run(TetrahedralizeConfig(capture=capture, workspace=workspace, edge_length=edge_length,
                                 max_tets=max_tets, optimize=optimize, threads=threads,
                                 envelope=envelope, degenerate_tol=degenerate_tol, preview=preview), RichReporter())
