"""3DGS PLY: write → read → compare, header layout, covariance factorisation, bad files."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from stages.errors import RslError
from stages.render.gaussians import quat_to_rotmat
from stages.render.ply import covariance_to_scale_rotation, encode_ply, read_ply, write_ply


def _gaussians(g: int, k: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(g, 4))
    return dict(means=rng.normal(size=(g, 3)), log_scales=rng.normal(size=(g, 3)) - 4,
                rotations=q / np.linalg.norm(q, axis=1, keepdims=True), opacity_logit=rng.normal(size=g),
                sh=rng.normal(size=(g, k, 3)))


@pytest.mark.parametrize("k", [1, 4, 16])
def test_ply_round_trip(tmp_path, k):
    src = _gaussians(57, k, seed=k)
    path = write_ply(tmp_path / "g.ply", **src)
    back = read_ply(path)
    for key, val in src.items():
        np.testing.assert_allclose(back[key], np.asarray(val, np.float32), rtol=0, atol=0, err_msg=key)


def test_ply_header_is_the_3dgs_layout():
    src = _gaussians(3, 4)
    blob = encode_ply(**src)
    header = blob[: blob.index(b"end_header")].decode().splitlines()
    props = [line.split()[-1] for line in header if line.startswith("property")]
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 3"]
    assert props == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(9)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    # f_rest is channel-major: f_rest_0..2 are the red coefficients of SH bands 1..3.
    body = np.frombuffer(blob[blob.index(b"end_header\n") + 11:], "<f4").reshape(3, -1)
    np.testing.assert_allclose(body[:, 9:12], src["sh"][:, 1:, 0].astype(np.float32))


def test_covariance_factorisation():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(20, 3, 3)) * 0.01
    cov = A @ A.transpose(0, 2, 1)
    ls, q = covariance_to_scale_rotation(cov)
    R = quat_to_rotmat(torch.as_tensor(q)).numpy()
    rebuilt = R @ (np.exp(2 * ls)[:, :, None] * R.transpose(0, 2, 1))
    np.testing.assert_allclose(rebuilt, cov, rtol=1e-8, atol=1e-14)


def test_bad_ply_files(tmp_path):
    p = tmp_path / "bad.ply"
    p.write_bytes(b"not a ply")
    with pytest.raises(RslError, match="not a PLY"):
        read_ply(p)
    blob = encode_ply(**_gaussians(10, 1))
    p.write_bytes(blob[:-20])
    with pytest.raises(RslError, match="truncated"):
        read_ply(p)
    with pytest.raises(RslError, match="not found"):
        read_ply(tmp_path / "missing.ply")
