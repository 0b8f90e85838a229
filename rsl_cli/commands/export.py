"""`rsl export`: stress, forces, VTU/PVD, 3DGS PLY, renders, plots, scan distance, COLMAP model."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option

ORDER = 80


def register(app: typer.Typer) -> None:
    from stages.export import ExportConfig

    @app.command("export", help="Export what the adapted simulation reveals: stress, handle and contact "
                                "forces, a ParaView series, 3DGS PLYs, stress renders and plots. With no "
                                "product flag, everything the workspace allows.")
    def _cmd(
        workspace: Path = workspace_option(),
        out: Optional[Path] = opt(ExportConfig, "out", "--out", "-o"),
        source: str = opt(ExportConfig, "source", "--source"),
        stress: bool = opt(ExportConfig, "stress", "--stress"),
        forces: bool = opt(ExportConfig, "forces", "--forces"),
        vtk: bool = opt(ExportConfig, "vtk", "--vtk"),
        ply: bool = opt(ExportConfig, "ply", "--ply"),
        render: bool = opt(ExportConfig, "render", "--render"),
        plots: bool = opt(ExportConfig, "plots", "--plots"),
        colmap: Optional[Path] = opt(ExportConfig, "colmap", "--colmap"),
        scan: Optional[Path] = opt(ExportConfig, "scan", "--scan"),
        scan_frame: int = opt(ExportConfig, "scan_frame", "--scan-frame"),
        frames: str = opt(ExportConfig, "frames", "--frames"),
        capture: Optional[Path] = opt(ExportConfig, "capture", "--capture"),
        contact_distance: float = opt(ExportConfig, "contact_distance", "--contact-distance"),
        ply_stress: bool = opt(ExportConfig, "ply_stress", "--ply-stress"),
        stress_max: float = opt(ExportConfig, "stress_max", "--stress-max"),
        orbit_views: int = opt(ExportConfig, "orbit_views", "--orbit-views"),
        render_size: int = opt(ExportConfig, "render_size", "--render-size"),
        video_fps: float = opt(ExportConfig, "video_fps", "--video-fps"),
    ) -> None:
        from stages.export import run

        run(ExportConfig(
            workspace=workspace, out=out, source=source, stress=stress, forces=forces, vtk=vtk, ply=ply,
            render=render, plots=plots, colmap=colmap, scan=scan, scan_frame=scan_frame, frames=frames,
            capture=capture, contact_distance=contact_distance, ply_stress=ply_stress, stress_max=stress_max,
            orbit_views=orbit_views, render_size=render_size, video_fps=video_fps,
        ), RichReporter())
