"""The pinhole camera (OpenCV convention), shared by calibration, rendering and the stages."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Camera:
    """One pinhole camera, OpenCV convention: x_cam = R x_world + t; pixel = K x_cam / z."""

    name: str
    K: np.ndarray  # (3, 3)
    dist: np.ndarray  # (5,) k1 k2 p1 p2 k3
    R: np.ndarray  # (3, 3) world -> camera
    t: np.ndarray  # (3,) metres
    width: int
    height: int
    rms_px: float = float("nan")  # reprojection RMS of the calibration

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, -Rᵀ t."""
        return -self.R.T @ self.t
