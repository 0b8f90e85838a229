"""`rsl synth MESH CAPTURE_OUT`: a synthetic capture with ground truth (frames, masks, markers, truth/)."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt
from stages.synth import SynthConfig, run

ORDER = 5


def register(app: typer.Typer) -> None:
    @app.command("synth", help="Simulate a scenario (stretch, twist, push, drop, cable) on a mesh and film it "
                               "with a ring of cameras → a complete capture folder with ground truth "
                               "(truth/material.csv, truth/surface.npz, truth masks, markers.csv).")
    def _cmd(
        mesh: Path = typer.Argument(..., help="Object mesh: a closed surface (obj/ply/stl/off) or a tet mesh "
                                              "(.mesh/.msh)."),
        out: Path = typer.Argument(..., help="Capture folder to create."),
        scenario: str = opt(SynthConfig, "scenario"),
        amplitude: float = opt(SynthConfig, "amplitude"),
        cameras: int = opt(SynthConfig, "cameras"),
        frames: int = opt(SynthConfig, "frames"),
        resolution: int = opt(SynthConfig, "resolution"),
        fps: float = opt(SynthConfig, "fps"),
        young: float = opt(SynthConfig, "young"),
        young_schedule: str = opt(SynthConfig, "young_schedule"),
        ramp: bool = opt(SynthConfig, "ramp", "--ramp/--steps"),
        poisson: float = opt(SynthConfig, "poisson"),
        region: str = opt(SynthConfig, "region", "--region", "--region-young"),
        markers: int = opt(SynthConfig, "markers"),
        marker_noise: float = opt(SynthConfig, "marker_noise"),
        marker_visibility: int = opt(SynthConfig, "marker_visibility"),
        seed: int = opt(SynthConfig, "seed"),
        size: float = opt(SynthConfig, "size"),
        density: float = opt(SynthConfig, "density"),
        model: str = opt(SynthConfig, "model"),
        edge_length: float = opt(SynthConfig, "edge_length"),
        max_tets: int = opt(SynthConfig, "max_tets"),
        elevation: float = opt(SynthConfig, "elevation"),
        calib_views: int = opt(SynthConfig, "calib_views"),
        board: str = opt(SynthConfig, "board"),
        noise: float = opt(SynthConfig, "noise"),
        supersample: int = opt(SynthConfig, "supersample"),
        newton_iterations: int = opt(SynthConfig, "newton_iterations"),
        overwrite: bool = opt(SynthConfig, "overwrite", "--overwrite"),
    ) -> None:
        run(SynthConfig(mesh=mesh, out=out, scenario=scenario, amplitude=amplitude, cameras=cameras,
                        frames=frames, resolution=resolution, fps=fps, young=young, young_schedule=young_schedule,
                        ramp=ramp, poisson=poisson, region=region, markers=markers,
                        marker_noise=marker_noise, marker_visibility=marker_visibility, seed=seed, size=size,
                        density=density, model=model, edge_length=edge_length, max_tets=max_tets,
                        elevation=elevation, calib_views=calib_views, board=board, noise=noise,
                        supersample=supersample, newton_iterations=newton_iterations, overwrite=overwrite),
            RichReporter())
