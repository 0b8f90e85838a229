"""Occluders (INTERFACES §7): the pixels a handle's or obstacle's ``visual`` covers in a camera at frame t.

A visual is a box or a triangle mesh in the frame its pose moves: at frame t its world points are
p_world = R(q_t) p + t_t with the pose [t, q] of the handle's / obstacle's track at t (the same rigid motion
that moves the handle's rest positions onto their targets).  Its triangles are projected with the camera's
OpenCV model (stages/render/mesh_raster.py: distortion included) and rasterized; a pixel is covered when its
centre lies inside a projected triangle, and the covered region is dilated by ``margin_px`` pixels (the
visual's silhouette is anti-aliased and the lab's geometry is approximate).  Covered pixels are excluded
from segmentation and from the image loss: neither object nor background.

Pure functions over arrays (the cameras are stages.domain / artefacts Camera objects); no files, no printing.
"""
from __future__ import annotations

import cv2
import numpy as np

from stages.domain.controls import Controls, Track, Visual, apply_pose


def occluders(controls: Controls) -> list[tuple[str, Visual, Track]]:
    """(name, visual, pose track) of every handle and obstacle that carries a visual."""
    out = [(h.name, h.visual, h.poses) for h in controls.handles if getattr(h, "visual", None) is not None]
    out += [(o.name, o.visual, o.poses) for o in controls.obstacles if getattr(o, "visual", None) is not None]
    return out


def has_occluders(controls: Controls) -> bool:
    return bool(occluders(controls))


def visual_world(visual: Visual, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (k, 3) m in the world, faces (f, 3)) of a visual moved by pose [tx, ty, tz, qw, qx, qy, qz]."""
    v, f = visual.triangles()
    return apply_pose(pose, v), f


def coverage(vertices: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """(H, W) bool: pixel centres inside the projection of triangles (vertices (k, 3) world, faces (f, 3));
    triangles with a vertex behind the camera (z ≤ 1 mm) are skipped."""
    from stages.render.mesh_raster import project_points, rasterize

    uv, z = project_points(vertices, camera.K, camera.R, camera.t, camera.dist)
    return rasterize(uv, z, faces, int(camera.height), int(camera.width), near=1e-3).mask


def ignore_mask(controls: Controls, frame: int, camera, margin_px: int = 2) -> np.ndarray:
    """(H, W) bool: pixels of ``camera`` covered at ``frame`` by any occluder, dilated by ``margin_px``."""
    H, W = int(camera.height), int(camera.width)
    m = np.zeros((H, W), bool)
    for _, vis, poses in occluders(controls):
        v, f = visual_world(vis, poses.at(frame))
        m |= coverage(v, f, camera)
    if margin_px > 0 and m.any():
        r = int(margin_px)
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        m = cv2.dilate(m.astype(np.uint8), disc).astype(bool)
    return m


def ignore_masks(controls: Controls, frame: int, cameras: list, margin_px: int = 2) -> dict[str, np.ndarray]:
    """camera name -> (H, W) bool ignore mask at ``frame`` (see :func:`ignore_mask`)."""
    return {c.name: ignore_mask(controls, frame, c, margin_px) for c in cameras}


def draw_occluders(image: np.ndarray, controls: Controls, frame: int, camera, albedo=(0.22, 0.23, 0.26),
                   supersample: int = 2) -> np.ndarray:
    """``image`` (H, W, 3) float in [0, 1] with every visual of ``controls`` at ``frame`` drawn over it:
    Lambert-shaded in a flat ``albedo`` (stages/render/mesh_raster.render_mesh, anti-aliased by
    ``supersample``), composited as c = c_visual + (1 − coverage) · c_image — in front of everything, as a clamp
    that encloses the part it holds is.  For synthetic captures with a visible gripper."""
    from stages.render.mesh_raster import render_mesh

    out = np.asarray(image, np.float64).copy()
    albedo = np.asarray(albedo, np.float64)
    for _, vis, poses in occluders(controls):
        v, f = visual_world(vis, poses.at(frame))
        rgb, cov, _ = render_mesh(v, f, v, camera.K, camera.R, camera.t, int(camera.width), int(camera.height),
                                  lambda p: np.broadcast_to(albedo, p.shape), None, camera.dist, supersample)
        out = rgb + (1.0 - cov)[..., None] * out
    return np.clip(out, 0.0, 1.0)


def clamp_visual(held: np.ndarray, pad: float = 0.12) -> Visual:
    """A box visual around the points a handle holds (k, 3), grown by ``pad`` × its largest side on every side:
    what a clamp gripping those vertices looks like (rsl synth --clamp)."""
    held = np.asarray(held, np.float64)
    lo, hi = held.min(0), held.max(0)
    grow = pad * float(np.max(hi - lo))
    return Visual("box", box=np.stack([lo - grow, hi + grow]))
