"""Structure from motion with pycolmap (SIFT features, exhaustive matching, incremental mapping),
and putting the result in metres.

pycolmap works on files, so :func:`reconstruct` writes the given images into a scratch folder
the caller provides; nothing else touches the disk.  Image names may hold one folder level
(``cam0/frame0``): images in one folder share one camera (intrinsics).

Scale: SfM is known up to a similarity.  :func:`scale_by_distance` uses a known distance
between two camera centres; :func:`scale_by_board` triangulates board corners seen in two or
more registered images and compares corner spacings with the board's (s = median of
d_board / d_sfm over corner pairs).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from stages.errors import RslError
from stages.vision.boards import detect
from stages.vision.colmap_io import intrinsics_from_model
from stages.vision.geometry import triangulate, undistort_points


@dataclass
class SfmResult:
    """Registered images of the largest reconstruction (arbitrary scale and world frame)."""

    poses: dict[str, tuple]  # image name -> (R (3,3), t (3,)) world -> camera
    intrinsics: dict[str, tuple]  # image name -> (K (3,3), dist (5,))
    points: np.ndarray  # (P, 3) triangulated scene points
    rms_px: float  # mean reprojection error reported by COLMAP
    registered: int = 0
    total: int = 0
    extra: dict = field(default_factory=dict)


def reconstruct(images: dict[str, np.ndarray], workdir: Path, seed: int = 0, max_image_size: int = 1600,
                camera_model: str = "SIMPLE_RADIAL", num_threads: int = 2, single_camera: bool = False
                ) -> SfmResult:
    """Run SIFT extraction, exhaustive matching and incremental mapping on RGB images (name -> (H, W, 3)).
    Intrinsics: one camera per folder of the names, or one for all with ``single_camera``.

    Raises RslError when no model with at least two images can be built."""
    import pycolmap

    workdir = Path(workdir)
    img_dir = workdir / "images"
    names = {}
    for name, img in images.items():
        rel = f"{name}.png"
        p = img_dir / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(p), cv2.cvtColor(np.asarray(img, np.uint8), cv2.COLOR_RGB2BGR))
        names[rel] = name
    db = workdir / "database.db"
    if db.exists():
        db.unlink()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(max_image_size)
    extraction.num_threads = int(num_threads)
    extraction.use_gpu = False
    nested = all(Path(r).parent != Path(".") for r in names)
    mode = pycolmap.CameraMode.PER_FOLDER if nested else pycolmap.CameraMode.PER_IMAGE
    if single_camera:
        mode = pycolmap.CameraMode.SINGLE
    pycolmap.extract_features(db, img_dir, image_names=sorted(names), camera_mode=mode, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = int(num_threads)
    matching.use_gpu = False
    pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.random_seed = int(seed)
    opts.num_threads = int(num_threads)
    opts.min_model_size = 2
    out = workdir / "sparse"
    out.mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(db, img_dir, out, opts)
    if not recs:
        raise RslError(f"structure from motion registered no image pair among {len(images)} images "
                       "(too little texture or overlap).")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    return result_from_reconstruction(rec, names, len(images))


def result_from_reconstruction(rec, names: dict[str, str], total: int) -> SfmResult:
    """Convert a pycolmap.Reconstruction (image names mapped back through ``names``)."""
    poses, intr = {}, {}
    for im in rec.images.values():
        if not (im.has_pose if not callable(getattr(im, "has_pose", None)) else im.has_pose()):
            continue
        pose = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        name = names.get(im.name, im.name)
        poses[name] = (np.asarray(pose.rotation.matrix(), np.float64), np.asarray(pose.translation, np.float64))
        cam = rec.cameras[im.camera_id]
        intr[name] = intrinsics_from_model(cam.model.name, np.asarray(cam.params), f"SfM camera {im.camera_id}")
    pts = np.array([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() else np.zeros((0, 3))
    try:
        rms = float(rec.compute_mean_reprojection_error())
    except AttributeError:
        rms = float("nan")
    return SfmResult(poses, intr, pts, rms, len(poses), total)


def scale_by_distance(rec: SfmResult, a: str, b: str, metres: float) -> float:
    """Scale s making the distance between the centres of images a and b equal ``metres``."""
    ca = -rec.poses[a][0].T @ rec.poses[a][1]
    cb = -rec.poses[b][0].T @ rec.poses[b][1]
    d = float(np.linalg.norm(ca - cb))
    if d < 1e-12:
        raise RslError(f"SfM put images '{a}' and '{b}' at the same place; cannot scale by their distance.")
    return metres / d


def scale_by_board(rec: SfmResult, board, images: dict[str, np.ndarray]) -> float:
    """Scale s from board corners triangulated with the SfM cameras (module doc)."""
    seen: dict[int, list] = {}
    for name, img in images.items():
        if name not in rec.poses:
            continue
        det = detect(board, img)
        if det is None:
            continue
        K, d = rec.intrinsics[name]
        xn = undistort_points(det.image_points, K, d)
        for cid, x in zip(det.ids, xn):
            seen.setdefault(int(cid), []).append((x, rec.poses[name]))
    corners = {cid: triangulate([o[0] for o in obs], [o[1] for o in obs]) for cid, obs in seen.items() if len(obs) >= 2}
    if len(corners) < 4:
        raise RslError(f"the board {board.spec} was found in fewer than two registered SfM images; "
                       "cannot scale the reconstruction (use --known-distance).")
    ids = sorted(corners)
    obj = board.object_points
    ratios = []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            dtrue = float(np.linalg.norm(obj[a] - obj[b]))
            dsfm = float(np.linalg.norm(corners[a] - corners[b]))
            if dsfm > 1e-12 and dtrue > 0:
                ratios.append(dtrue / dsfm)
    return float(np.median(ratios))
