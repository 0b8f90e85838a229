"""`rsl fit-gaussians CAPTURE -w WS`: Gaussians bound to the mesh, fitted to one frame (gaussians.h5)."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.fit_gaussians import FitGaussiansConfig, run

ORDER = 40


def register(app: typer.Typer) -> None:
    @app.command("fit-gaussians", help="Seed 3D Gaussians in the tets and fit their appearance to one frame's "
                                       "masked views (L1 + D-SSIM) → gaussians.h5 and fit_gaussians/CAM.png.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder (capture.toml, frames/)."),
        workspace: Path = workspace_option(),
        frame: int = opt(FitGaussiansConfig, "frame"),
        iterations: int = opt(FitGaussiansConfig, "iterations"),
        gaussians: int = opt(FitGaussiansConfig, "gaussians"),
        surface_bias: float = opt(FitGaussiansConfig, "surface_bias"),
        sh_degree: int = opt(FitGaussiansConfig, "sh_degree"),
        ssim_weight: float = opt(FitGaussiansConfig, "ssim_weight"),
        mask_weight: float = opt(FitGaussiansConfig, "mask_weight"),
        lr: float = opt(FitGaussiansConfig, "lr"),
        max_resolution: int = opt(FitGaussiansConfig, "max_resolution"),
        seed: int = opt(FitGaussiansConfig, "seed"),
    ) -> None:
        run(FitGaussiansConfig(capture=capture, workspace=workspace, frame=frame, iterations=iterations,
                               gaussians=gaussians, surface_bias=surface_bias, sh_degree=sh_degree,
                               ssim_weight=ssim_weight, mask_weight=mask_weight, lr=lr,
                               max_resolution=max_resolution, seed=seed), RichReporter())
