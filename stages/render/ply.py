"""The standard 3DGS PLY (binary little-endian) that splat viewers open.

One vertex per Gaussian with float32 properties, in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..3(K−1)−1 opacity scale_0..2 rot_0..3`` —
positions in metres, ``opacity`` a logit, ``scale_*`` log standard deviations,
``rot_*`` a quaternion wxyz, ``f_rest`` channel-major (all red coefficients,
then green, then blue), as the 3DGS reference code writes them.

``gaussians_to_ply_arrays`` turns world-space covariances (e.g. F R S² Rᵀ Fᵀ
of deformed Gaussians) into the scale/rotation pair the format stores.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.domain.rotations import matrix_to_quat_wxyz
from stages.errors import RslError


def _names(k: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + rest
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def encode_ply(means: np.ndarray, log_scales: np.ndarray, rotations: np.ndarray,
               opacity_logit: np.ndarray, sh: np.ndarray) -> bytes:
    """PLY bytes from means (G,3) m, log_scales (G,3), rotations (G,4) wxyz, opacity_logit (G,), sh (G,K,3)."""
    g = means.shape[0]
    sh = np.asarray(sh, np.float32).reshape(g, -1, 3)
    k = sh.shape[1]
    cols = [np.asarray(means, np.float32), np.zeros((g, 3), np.float32), sh[:, 0, :],
            sh[:, 1:, :].transpose(0, 2, 1).reshape(g, -1),
            np.asarray(opacity_logit, np.float32).reshape(g, 1), np.asarray(log_scales, np.float32),
            np.asarray(rotations, np.float32)]
    data = np.ascontiguousarray(np.concatenate(cols, 1), dtype="<f4")
    names = _names(k)
    assert data.shape[1] == len(names)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {g}"]
    header += [f"property float {n}" for n in names]
    header += ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + data.tobytes()


def decode_ply(blob: bytes, where: str = "PLY") -> dict[str, np.ndarray]:
    """Inverse of ``encode_ply``: dict of means, log_scales, rotations, opacity_logit, sh (G,K,3)."""
    end = blob.find(b"end_header\n")
    if not blob.startswith(b"ply") or end < 0:
        raise RslError(f"{where}: not a PLY file (no 'ply' magic or no end_header).")
    header = blob[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise RslError(f"{where}: only binary little-endian PLY files of 3D Gaussians are supported.")
    count, props = None, []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            count = int(parts[2])
        elif parts[:1] == ["property"] and count is not None:
            if parts[1] != "float":
                raise RslError(f"{where}: property '{parts[-1]}' is {parts[1]}, expected float.")
            props.append(parts[2])
    if count is None:
        raise RslError(f"{where}: has no vertex element.")
    need = {"x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0"}
    if not need <= set(props):
        raise RslError(f"{where}: is not a 3D Gaussian splat PLY (missing {sorted(need - set(props))}).")
    body = blob[end + len(b"end_header\n"):]
    if len(body) < count * 4 * len(props):
        raise RslError(f"{where}: truncated ({len(body)} bytes of vertex data, {count * 4 * len(props)} expected).")
    data = np.frombuffer(body, dtype="<f4", count=count * len(props)).reshape(count, len(props))
    col = {n: data[:, i] for i, n in enumerate(props)}
    n_rest = sum(1 for p in props if p.startswith("f_rest_"))
    k = 1 + n_rest // 3
    rest = np.stack([col[f"f_rest_{i}"] for i in range(n_rest)], 1).reshape(count, 3, k - 1) \
        if n_rest else np.zeros((count, 3, 0), np.float32)
    sh = np.concatenate([np.stack([col[f"f_dc_{i}"] for i in range(3)], 1)[:, None, :],
                         rest.transpose(0, 2, 1)], 1)
    return {
        "means": np.stack([col["x"], col["y"], col["z"]], 1),
        "log_scales": np.stack([col[f"scale_{i}"] for i in range(3)], 1),
        "rotations": np.stack([col[f"rot_{i}"] for i in range(4)], 1),
        "opacity_logit": col["opacity"].copy(),
        "sh": sh,
    }


def write_ply(path: str | Path, means, log_scales, rotations, opacity_logit, sh) -> Path:
    """Write a 3DGS PLY (see ``encode_ply``); returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(encode_ply(means, log_scales, rotations, opacity_logit, sh))
    tmp.replace(path)
    return path


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a 3DGS PLY written by ``write_ply`` or by the 3DGS reference code."""
    path = Path(path)
    if not path.is_file():
        raise RslError(f"{path}: file not found.")
    return decode_ply(path.read_bytes(), str(path))


def covariance_to_scale_rotation(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World covariances (G,3,3) → (log std devs (G,3), quaternions wxyz (G,4)) with R S² Rᵀ = Σ."""
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    w, v = np.linalg.eigh(np.asarray(cov, np.float64))
    det = np.linalg.det(v)
    v[:, :, 0] *= np.sign(det)[:, None]  # proper rotation
    return 0.5 * np.log(np.maximum(w, 1e-30)), matrix_to_quat_wxyz(v)
