"""`rsl segment`: foreground masks of every frame -> WS/masks.h5."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.segment import SegmentConfig, run

ORDER = 20


def register(app: typer.Typer) -> None:
    @app.command("segment", help="Masks of the object in every frame (plates, chroma, GrabCut, SAM 2) -> masks.h5.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder (holds capture.toml)."),
        workspace: Path = workspace_option(),
        method: str = opt(SegmentConfig, "method"),
        threshold: float = opt(SegmentConfig, "threshold"),
        shadow_low: float = opt(SegmentConfig, "shadow_low"),
        shadow_high: float = opt(SegmentConfig, "shadow_high"),
        key_color: str = opt(SegmentConfig, "key_color"),
        band_px: int = opt(SegmentConfig, "band_px"),
        reach_px: int = opt(SegmentConfig, "reach_px"),
        iterations: int = opt(SegmentConfig, "iterations"),
        open_px: int = opt(SegmentConfig, "open_px"),
        close_px: int = opt(SegmentConfig, "close_px"),
        temporal: int = opt(SegmentConfig, "temporal"),
        overlays: int = opt(SegmentConfig, "overlays"),
        checkpoint: str = opt(SegmentConfig, "checkpoint"),
        sam2_config: str = opt(SegmentConfig, "sam2_config"),
        seed: int = opt(SegmentConfig, "seed"),
    ) -> None:
        run(SegmentConfig(capture, workspace, method, threshold, shadow_low, shadow_high, key_color, band_px,
                          reach_px, iterations, open_px, close_px, temporal, overlays, checkpoint, sam2_config, seed),
            RichReporter())
