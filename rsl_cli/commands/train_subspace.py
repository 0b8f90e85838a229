"""`rsl train-subspace -w WS`: fit the neural (or PCA, or LBS) subspace and its cubature (subspace.h5)."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from rsl_cli.console import RichReporter
from rsl_cli.options import opt, workspace_option
from stages.train_subspace import TrainSubspaceConfig, run

ORDER = 60


def register(app: typer.Typer) -> None:
    @app.command("train-subspace", help="Fit x = φ(z) to the snapshots (autoencoder of Fulton et al. 2019, "
                                         "PCA, or linear-blend-skinning modes) and the optimised cubature of "
                                         "its reduced energy → subspace.h5.")
    def _cmd(
        workspace: Path = workspace_option(),
        dim: int = opt(TrainSubspaceConfig, "dim"),
        kind: str = opt(TrainSubspaceConfig, "kind"),
        epochs: int = opt(TrainSubspaceConfig, "epochs"),
        learning_rate: float = opt(TrainSubspaceConfig, "learning_rate"),
        batch_size: int = opt(TrainSubspaceConfig, "batch_size"),
        pca_dim: int = opt(TrainSubspaceConfig, "pca_dim"),
        validation_fraction: float = opt(TrainSubspaceConfig, "validation_fraction"),
        cubature_tets: int = opt(TrainSubspaceConfig, "cubature_tets"),
        cubature_tol: float = opt(TrainSubspaceConfig, "cubature_tol"),
        cubature_poses: int = opt(TrainSubspaceConfig, "cubature_poses"),
        material: str = opt(TrainSubspaceConfig, "material"),
        capture: Optional[Path] = opt(TrainSubspaceConfig, "capture"),
        seed: int = opt(TrainSubspaceConfig, "seed"),
    ) -> None:
        run(TrainSubspaceConfig(workspace=workspace, capture=capture, dim=dim, kind=kind, epochs=epochs,
                                learning_rate=learning_rate, batch_size=batch_size, pca_dim=pca_dim,
                                validation_fraction=validation_fraction, cubature_tets=cubature_tets,
                                cubature_tol=cubature_tol, cubature_poses=cubature_poses, material=material,
                                seed=seed), RichReporter())
