"""`rsl calibrate`: cameras from board views, SfM, or an import -> WS/cameras.h5."""
from __future__ import annotations

from pathlib import Path

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.calibrate import CalibrateConfig, run

ORDER = 10


def register(app: typer.Typer) -> None:
    @app.command("calibrate", help="Camera intrinsics, distortion and poses in one world frame -> cameras.h5.")
    def _cmd(
        capture: Path = typer.Argument(..., help="Capture folder (holds capture.toml).", exists=False),
        workspace: Path = workspace_option(),
        board: str = opt(CalibrateConfig, "board"),
        sfm: bool = opt(CalibrateConfig, "sfm"),
        from_json: str = opt(CalibrateConfig, "from_json"),
        from_colmap: str = opt(CalibrateConfig, "from_colmap"),
        from_transforms: str = opt(CalibrateConfig, "from_transforms"),
        world: str = opt(CalibrateConfig, "world"),
        world_view: str = opt(CalibrateConfig, "world_view"),
        board_pose: str = opt(CalibrateConfig, "board_pose"),
        fix_aspect_ratio: bool = opt(CalibrateConfig, "fix_aspect_ratio"),
        zero_tangent: bool = opt(CalibrateConfig, "zero_tangent"),
        fix_k3: bool = opt(CalibrateConfig, "fix_k3"),
        outlier_factor: float = opt(CalibrateConfig, "outlier_factor"),
        outlier_min_px: float = opt(CalibrateConfig, "outlier_min_px"),
        known_distance: str = opt(CalibrateConfig, "known_distance"),
        sfm_single_camera: bool = opt(CalibrateConfig, "sfm_single_camera"),
        sfm_max_image_size: int = opt(CalibrateConfig, "sfm_max_image_size"),
        seed: int = opt(CalibrateConfig, "seed"),
    ) -> None:
        run(CalibrateConfig(capture, workspace, board, sfm, from_json, from_colmap, from_transforms, world,
                            world_view, board_pose, fix_aspect_ratio, zero_tangent, fix_k3, outlier_factor,
                            outlier_min_px, known_distance, sfm_single_camera, sfm_max_image_size, seed),
            RichReporter())
