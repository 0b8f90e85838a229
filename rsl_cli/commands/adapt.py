"""`rsl adapt`: online (or offline) identification of E and ν per region."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.adapt import AdaptConfig, run

ORDER = 70


def register(app: typer.Typer) -> None:
    @app.command("adapt", help="Adapt the material (E, ν per region) to the capture, frame by frame, "
                               "over a sliding window; writes WS/adapt.h5.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder.", exists=False),
        workspace: Path = workspace_option(),
        window: int = opt(AdaptConfig, "window", "--window"),
        space: str = opt(AdaptConfig, "space", "--space"),
        mode: str = opt(AdaptConfig, "mode", "--mode"),
        loss: str = opt(AdaptConfig, "loss", "--loss"),
        cameras: str = opt(AdaptConfig, "cameras", "--cameras"),
        frames: str = opt(AdaptConfig, "frames", "--frames"),
        iters_per_frame: int = opt(AdaptConfig, "iters_per_frame", "--iters-per-frame"),
        lr: float = opt(AdaptConfig, "lr", "--lr"),
        lr_poisson: float = opt(AdaptConfig, "lr_poisson", "--lr-poisson"),
        beta1: float = opt(AdaptConfig, "beta1", "--beta1"),
        offline_iters: int = opt(AdaptConfig, "offline_iters", "--offline-iters"),
        young_init: Optional[float] = opt(AdaptConfig, "young_init", "--young-init"),
        poisson_init: Optional[float] = opt(AdaptConfig, "poisson_init", "--poisson-init"),
        fit_poisson: bool = opt(AdaptConfig, "fit_poisson", "--fit-poisson/--fixed-poisson"),
        refine: int = opt(AdaptConfig, "refine", "--refine"),
        appearance: bool = opt(AdaptConfig, "appearance", "--appearance/--no-appearance"),
        gaussian_anchor: str = opt(AdaptConfig, "gaussian_anchor", "--gaussian-anchor"),
        follow: bool = opt(AdaptConfig, "follow", "--follow"),
        follow_timeout: float = opt(AdaptConfig, "follow_timeout", "--follow-timeout"),
        solver: str = opt(AdaptConfig, "solver", "--solver"),
        seed: int = opt(AdaptConfig, "seed", "--seed"),
    ) -> None:
        for name, value, choices in (("--space", space, ("reduced", "full")), ("--mode", mode, ("online", "offline")),
                                     ("--loss", loss, ("vision", "markers")),
                                     ("--gaussian-anchor", gaussian_anchor, ("rebind", "offset"))):
            if value not in choices:
                raise typer.BadParameter(f"{name} should be one of {', '.join(choices)}, found '{value}'.")
        run(AdaptConfig(capture=capture, workspace=workspace, window=window, space=space, mode=mode, loss=loss,
                        cameras=cameras, frames=frames, iters_per_frame=iters_per_frame, lr=lr, lr_poisson=lr_poisson,
                        beta1=beta1, offline_iters=offline_iters, young_init=young_init, poisson_init=poisson_init,
                        fit_poisson=fit_poisson, refine=refine, appearance=appearance,
                        gaussian_anchor=gaussian_anchor, follow=follow,
                        follow_timeout=follow_timeout, solver=solver, seed=seed), RichReporter())
