"""SAM 2 (Ravi et al. 2024) as an optional segmenter, prompted by a prior mask.

The ``sam2`` package is optional (``pip install sam2``); nothing is ever downloaded: the
user supplies the checkpoint (read by stages/steps/segment.py) and the name of its model config.
Each frame is prompted with the prior's bounding box and one positive point at the prior's
most interior pixel (maximum of the distance transform); the prior is the projected rest
mesh for the first frame, then the previous frame's mask.
"""
from __future__ import annotations

import cv2
import numpy as np

from stages.errors import RslError

REQUIRED_PREFIXES = ("image_encoder.", "sam_mask_decoder.")


def sam2_available() -> bool:
    """Whether the sam2 package can be imported."""
    try:
        import sam2  # noqa: F401
    except ImportError:
        return False
    return True


def check_state_dict(ckpt: object, where: str) -> dict:
    """The model state dict of a SAM 2 checkpoint ({"model": {name: tensor}}), validated."""
    sd = ckpt.get("model", ckpt) if isinstance(ckpt, dict) else None
    if not isinstance(sd, dict) or not sd:
        raise RslError(f"{where}: not a SAM 2 checkpoint (expected a dict with a 'model' state dict).")
    missing = [p for p in REQUIRED_PREFIXES if not any(str(k).startswith(p) for k in sd)]
    if missing:
        raise RslError(f"{where}: not a SAM 2 checkpoint (no {' / '.join(missing)} weights).")
    return sd


def build_predictor(state_dict: dict, config_name: str, where: str, device: str = "cpu"):
    """SAM2ImagePredictor for ``config_name`` (e.g. configs/sam2.1/sam2.1_hiera_t.yaml) with the
    given weights; RslError when sam2 is missing or the weights do not fit the config."""
    if not sam2_available():
        raise RslError(f"{where}: --method sam2 needs the optional 'sam2' package (pip install sam2); "
                       "it is not installed.")
    if not config_name:
        raise RslError(f"{where}: --method sam2 needs --sam2-config naming the checkpoint's model config "
                       "(e.g. configs/sam2.1/sam2.1_hiera_t.yaml).")
    from sam2.build_sam import build_sam2
    from sam2.sam2_image_predictor import SAM2ImagePredictor

    try:
        model = build_sam2(config_name, ckpt_path=None, device=device, mode="eval")
    except Exception as e:  # hydra: unknown config
        raise RslError(f"{where}: cannot build SAM 2 model config '{config_name}' ({type(e).__name__}: {e}).") from None
    try:
        model.load_state_dict(state_dict, strict=True)
    except RuntimeError as e:
        first = str(e).splitlines()[0]
        raise RslError(f"{where}: the checkpoint does not match model config '{config_name}' ({first}).") from None
    return SAM2ImagePredictor(model)


def prompt_from_prior(prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(box [x0, y0, x1, y1], point [[x, y]]) prompting SAM 2 from a prior mask (H, W) bool."""
    ys, xs = np.nonzero(prior)
    box = np.array([xs.min(), ys.min(), xs.max(), ys.max()], np.float32)
    dt = cv2.distanceTransform(np.asarray(prior, np.uint8), cv2.DIST_L2, 5)
    y, x = np.unravel_index(int(np.argmax(dt)), dt.shape)
    return box, np.array([[x, y]], np.float32)


def sam2_mask(predictor, frame: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Foreground (H, W) bool of one RGB frame prompted by a prior mask (best-scoring output)."""
    if not np.any(prior):
        return np.zeros(prior.shape, bool)
    box, point = prompt_from_prior(prior)
    predictor.set_image(np.asarray(frame, np.uint8))
    masks, scores, _ = predictor.predict(point_coords=point, point_labels=np.array([1]), box=box,
                                         multimask_output=True)
    return np.asarray(masks[int(np.argmax(scores))]) > 0.5
