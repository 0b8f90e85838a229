"""COLMAP sparse-model I/O (cameras, images; text and binary) and nerfstudio transforms.json.

COLMAP stores, per image, the world → camera pose as a quaternion (qw, qx, qy, qz) and a
translation, OpenCV axes (x right, y down, z forward) — the same convention as rsl's
``Camera`` (R world→camera, t).  Camera models understood: SIMPLE_PINHOLE, PINHOLE,
SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV (others raise).  rsl writes OPENCV
(fx fy cx cy k1 k2 p1 p2) when k3 = 0 and FULL_OPENCV otherwise, so a round trip is exact.

nerfstudio's transforms.json holds camera → world matrices in OpenGL axes (x right, y up,
z backward); R_cv = diag(1, −1, −1) R_glᵀ… handled in :func:`cameras_from_transforms`.

This module reads and writes the files it is given (I/O of one format, no printing).
"""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from stages.domain.cameras import Camera
from stages.domain.rotations import matrix_to_quat_wxyz as matrix_to_quat
from stages.domain.rotations import quat_wxyz_to_matrix as quat_to_matrix
from stages.errors import RslError

# id: (name, number of params)
MODELS = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
          4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
          8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12)}
MODEL_IDS = {name: (i, n) for i, (name, n) in MODELS.items()}


def intrinsics_from_model(model: str, params: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(K (3,3), dist (5,)) of a COLMAP camera model and its parameters."""
    p = np.asarray(params, dtype=np.float64)
    d = np.zeros(5)
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx = fy = f
    elif model == "PINHOLE":
        fx, fy, cx, cy = p
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, d[0] = p
        fx = fy = f
    elif model == "RADIAL":
        f, cx, cy, d[0], d[1] = p
        fx = fy = f
    elif model == "OPENCV":
        fx, fy, cx, cy, d[0], d[1], d[2], d[3] = p
    elif model == "FULL_OPENCV":
        fx, fy, cx, cy, d[0], d[1], d[2], d[3], d[4], k4, k5, k6 = p
        if abs(k4) + abs(k5) + abs(k6) > 1e-12:
            raise RslError(f"{where}: FULL_OPENCV camera with rational coefficients k4..k6 is not supported.")
    else:
        raise RslError(f"{where}: camera model {model} is not supported (use a pinhole or OPENCV model).")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return K, d


def model_from_intrinsics(K: np.ndarray, dist: np.ndarray) -> tuple[str, np.ndarray]:
    """COLMAP model name and params for (K, dist): OPENCV, or FULL_OPENCV when k3 ≠ 0."""
    d = np.zeros(5)
    dist = np.ravel(dist)
    d[: min(5, dist.size)] = dist[:5]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if d[4] != 0:
        return "FULL_OPENCV", np.array([fx, fy, cx, cy, *d[:4], d[4], 0, 0, 0])
    return "OPENCV", np.array([fx, fy, cx, cy, *d[:4]])


# =========================================================================== reading
def _lines(path: Path) -> list[str]:
    return [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def _read_cameras_text(path: Path) -> dict[int, tuple]:
    out = {}
    for ln in _lines(path):
        f = ln.split()
        try:
            out[int(f[0])] = (f[1], int(f[2]), int(f[3]), np.array([float(v) for v in f[4:]]))
        except (ValueError, IndexError):
            raise RslError(f"{path}: malformed camera line '{ln[:60]}'.") from None
    return out


def _read_images_text(path: Path) -> dict[int, tuple]:
    out = {}
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
    i = 0
    while i < len(lines):
        ln = lines[i].strip()
        if not ln:
            i += 1
            continue
        f = ln.split()
        try:
            iid = int(f[0])
            q = np.array([float(v) for v in f[1:5]])
            t = np.array([float(v) for v in f[5:8]])
            out[iid] = (q, t, int(f[8]), " ".join(f[9:]))
        except (ValueError, IndexError):
            raise RslError(f"{path}: malformed image line '{ln[:60]}'.") from None
        i += 2  # the next line lists 2-D points
    return out


def _read_cameras_bin(path: Path) -> dict[int, tuple]:
    out = {}
    data = path.read_bytes()
    try:
        (n,), o = struct.unpack_from("<Q", data, 0), 8
        for _ in range(n):
            cid, mid, w, h = struct.unpack_from("<iiQQ", data, o)
            o += 24
            if mid not in MODELS:
                raise RslError(f"{path}: unknown camera model id {mid}.")
            name, npar = MODELS[mid]
            params = np.array(struct.unpack_from(f"<{npar}d", data, o))
            o += 8 * npar
            out[cid] = (name, w, h, params)
    except struct.error:
        raise RslError(f"{path}: truncated or malformed cameras.bin.") from None
    return out


def _read_images_bin(path: Path) -> dict[int, tuple]:
    out = {}
    data = path.read_bytes()
    try:
        (n,), o = struct.unpack_from("<Q", data, 0), 8
        for _ in range(n):
            vals = struct.unpack_from("<i7di", data, o)
            o += 64
            end = data.index(b"\0", o)
            name = data[o:end].decode()
            o = end + 1
            (npts,) = struct.unpack_from("<Q", data, o)
            o += 8 + 24 * npts
            out[vals[0]] = (np.array(vals[1:5]), np.array(vals[5:8]), vals[8], name)
    except (struct.error, ValueError):
        raise RslError(f"{path}: truncated or malformed images.bin.") from None
    return out


def camera_name_of_image(name: str) -> str:
    """Camera name of a COLMAP image name: its folder (``cam0/000000.png``) or else its stem."""
    p = Path(name)
    return p.parts[0] if len(p.parts) > 1 else p.stem


def read_colmap(folder: str | Path, names: list[str] | None = None) -> list[Camera]:
    """Cameras of a COLMAP sparse model folder (cameras/images .txt or .bin).

    Each image becomes a camera named :func:`camera_name_of_image`; with ``names``, only
    those cameras (in that order; a missing one is an error)."""
    folder = Path(folder)
    if (folder / "sparse" / "0").is_dir():
        folder = folder / "sparse" / "0"
    if (folder / "cameras.txt").is_file() and (folder / "images.txt").is_file():
        cams, imgs = _read_cameras_text(folder / "cameras.txt"), _read_images_text(folder / "images.txt")
    elif (folder / "cameras.bin").is_file() and (folder / "images.bin").is_file():
        cams, imgs = _read_cameras_bin(folder / "cameras.bin"), _read_images_bin(folder / "images.bin")
    else:
        raise RslError(f"{folder}: no COLMAP model (cameras.txt + images.txt or cameras.bin + images.bin).")
    out: dict[str, Camera] = {}
    for iid in sorted(imgs):
        q, t, cid, name = imgs[iid]
        if cid not in cams:
            raise RslError(f"{folder}: image '{name}' refers to camera id {cid}, which is not defined.")
        model, w, h, params = cams[cid]
        K, d = intrinsics_from_model(model, params, f"{folder} camera {cid}")
        cname = camera_name_of_image(name)
        if cname not in out:
            out[cname] = Camera(cname, K, d, quat_to_matrix(q), np.asarray(t, dtype=np.float64), int(w), int(h))
    if names is None:
        return list(out.values())
    missing = [n for n in names if n not in out]
    if missing:
        raise RslError(f"{folder}: the COLMAP model has no image for camera(s) {', '.join(missing)} "
                       f"(images are named CAM.png or CAM/…; found {', '.join(sorted(out)) or 'none'}).")
    return [out[n] for n in names]


# =========================================================================== writing
def write_colmap(cameras: list[Camera], folder: str | Path, binary: bool = False,
                 image_names: dict[str, str] | None = None) -> Path:
    """Write cameras.{txt,bin}, images.{txt,bin} and an empty points3D into ``folder``: one COLMAP
    camera and one image per rsl camera; image name ``image_names[cam]`` or ``CAM.png``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, c in enumerate(cameras, start=1):
        model, params = model_from_intrinsics(np.asarray(c.K), np.asarray(c.dist))
        name = (image_names or {}).get(c.name, f"{c.name}.png")
        rows.append((i, model, int(c.width), int(c.height), params, matrix_to_quat(c.R), np.ravel(c.t), name))
    if binary:
        with open(folder / "cameras.bin", "wb") as f:
            f.write(struct.pack("<Q", len(rows)))
            for i, model, w, h, params, *_ in rows:
                f.write(struct.pack("<iiQQ", i, MODEL_IDS[model][0], w, h))
                f.write(struct.pack(f"<{len(params)}d", *params))
        with open(folder / "images.bin", "wb") as f:
            f.write(struct.pack("<Q", len(rows)))
            for i, _, _, _, _, q, t, name in rows:
                f.write(struct.pack("<i7di", i, *q, *t, i))
                f.write(name.encode() + b"\0")
                f.write(struct.pack("<Q", 0))
        (folder / "points3D.bin").write_bytes(struct.pack("<Q", 0))
        return folder
    with open(folder / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        f.write(f"# Number of cameras: {len(rows)}\n")
        for i, model, w, h, params, *_ in rows:
            f.write(f"{i} {model} {w} {h} " + " ".join(repr(float(p)) for p in params) + "\n")
    with open(folder / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        f.write(f"# Number of images: {len(rows)}, mean observations per image: 0\n")
        for i, _, _, _, _, q, t, name in rows:
            f.write(f"{i} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {i} {name}\n\n")
    (folder / "points3D.txt").write_text("# 3D point list with one line of data per point:\n"
                                         "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as "
                                         "(IMAGE_ID, POINT2D_IDX)\n# Number of points: 0, mean track length: 0\n")
    return folder


# =========================================================================== nerfstudio
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def cameras_from_transforms(path: str | Path, names: list[str] | None = None) -> list[Camera]:
    """Cameras of a nerfstudio / instant-ngp transforms.json.

    Intrinsics come from the frame (``fl_x, fl_y, cx, cy, w, h, k1, k2, k3, p1, p2``) or the
    file's top level; ``transform_matrix`` is camera → world in OpenGL axes, so
    R_world→cam = diag(1,−1,−1) R_c2wᵀ and t = −R_world→cam c.  A frame's camera name is
    its ``camera`` key, else the folder of ``file_path`` when that is a capture camera, else
    the file stem."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise RslError(f"{path}: cannot read transforms.json ({e}).") from None
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not frames:
        raise RslError(f"{path}: holds no 'frames' list.")
    out: dict[str, Camera] = {}
    for i, fr in enumerate(frames):
        def get(key, default=None):
            return fr.get(key, data.get(key, default))

        try:
            M = np.asarray(fr["transform_matrix"], dtype=np.float64)
            w, h = int(get("w")), int(get("h"))
            if get("fl_x") is None and get("camera_angle_x") is not None:
                fx = 0.5 * w / np.tan(0.5 * float(get("camera_angle_x")))
            else:
                fx = float(get("fl_x"))
            fy = float(get("fl_y", fx))
            cx, cy = float(get("cx", w / 2)), float(get("cy", h / 2))
        except (KeyError, TypeError, ValueError) as e:
            raise RslError(f"{path}: frames[{i}] lacks a valid transform_matrix or intrinsics ({e}).") from None
        if M.shape not in ((4, 4), (3, 4)):
            raise RslError(f"{path}: frames[{i}].transform_matrix should be 4x4, found {M.shape}.")
        dist = np.array([float(get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")])
        Rc2w, c = M[:3, :3], M[:3, 3]
        R = _GL_TO_CV @ Rc2w.T
        t = -R @ c
        fp = Path(str(fr.get("file_path", f"frame_{i}")))
        if "camera" in fr:
            name = str(fr["camera"])
        elif names and len(fp.parts) > 1 and fp.parent.name in names:
            name = fp.parent.name
        else:
            name = fp.stem
        if name not in out:
            out[name] = Camera(name, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), dist, R, t, w, h)
    if names is None:
        return list(out.values())
    missing = [n for n in names if n not in out]
    if missing:
        raise RslError(f"{path}: no frame for camera(s) {', '.join(missing)} (found {', '.join(sorted(out))}).")
    return [out[n] for n in names]


def cameras_to_transforms(cameras: list[Camera]) -> dict:
    """The inverse of :func:`cameras_from_transforms`: a transforms.json object, one frame per camera."""
    frames = []
    for c in cameras:
        R = _GL_TO_CV @ np.asarray(c.R)  # R_c2w_glᵀ = diag · R  ⇒  R_c2w = (diag R)ᵀ
        M = np.eye(4)
        M[:3, :3] = R.T
        M[:3, 3] = c.center
        k1, k2, p1, p2, k3 = np.ravel(c.dist)[:5]
        frames.append({"file_path": f"{c.name}.png", "camera": c.name, "transform_matrix": M.tolist(),
                       "w": int(c.width), "h": int(c.height), "fl_x": float(c.K[0, 0]), "fl_y": float(c.K[1, 1]),
                       "cx": float(c.K[0, 2]), "cy": float(c.K[1, 2]), "k1": float(k1), "k2": float(k2),
                       "k3": float(k3), "p1": float(p1), "p2": float(p2)})
    return {"camera_model": "OPENCV", "frames": frames}
