"""Foreground masks of the object: background plates, chroma key, GrabCut seeded by the mesh.

All functions take RGB uint8 images (H, W, 3) and return boolean masks (H, W); no I/O.

- Background difference with shadow suppression (Horprasert et al. 1999): with plate colour
  B and frame colour I per pixel, brightness ratio α = I·B / B·B and chromaticity distortion
  δ = ‖I − α B‖.  Foreground where ‖I − B‖ > τ, except shadows: α ∈ [α_lo, α_hi] and
  δ < τ_c (darker, same colour).  τ = max(τ_min, k·σ) with σ a robust noise level
  (1.4826 · median ‖I − B‖ over the image, most of which is background).
- Chroma key: distance in the (Cr, Cb) plane of YCrCb from the key colour (given, or the
  median colour of the image border); threshold by Otsu's method on that distance.
- GrabCut (Rother et al. 2004) seeded by a prior mask (the projected rest mesh for the first
  frame, then the previous frame's mask): sure foreground = prior eroded by a band, probable
  foreground = prior, probable background = the band around it, background elsewhere.
- Clean-up: opening and closing with discs, the largest connected component, holes filled;
  temporal majority vote over a window of frames.
"""
from __future__ import annotations

import cv2
import numpy as np

from stages.vision.geometry import project


# =========================================================================== helpers
def disc(radius: int) -> np.ndarray:
    """Elliptic structuring element of the given radius (pixels)."""
    r = max(int(radius), 0)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of a boolean mask (empty stays empty)."""
    m = np.asarray(mask, np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    if n <= 1:
        return m.astype(bool)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == k


def fill_holes(mask: np.ndarray) -> np.ndarray:
    """Mask with every background region not connected to the image border filled."""
    m = np.asarray(mask, np.uint8)
    h, w = m.shape
    pad = np.zeros((h + 2, w + 2), np.uint8)
    pad[1:-1, 1:-1] = m
    flood = pad.copy()
    ff = np.zeros((h + 4, w + 4), np.uint8)
    cv2.floodFill(flood, ff, (0, 0), 1)
    return (pad | (1 - flood))[1:-1, 1:-1].astype(bool)


def clean_mask(mask: np.ndarray, open_px: int = 1, close_px: int = 2, largest: bool = True,
               holes: bool = True, ignore: np.ndarray | None = None) -> np.ndarray:
    """Opening (removes specks), closing (bridges gaps), largest component, holes filled.

    ``ignore`` (H, W) bool: pixels an occluder covers, neither object nor background.  They are removed from
    the result, but connect across: the object cut in two by a gripper in front of it stays whole (the
    kept component is the component of mask ∪ ignore holding the most mask pixels, and holes of that
    component are filled before the ignored pixels are taken out).
    """
    ign = None if ignore is None or not np.any(ignore) else np.asarray(ignore, bool)
    m = np.asarray(mask, bool)
    if ign is not None:
        m = m & ~ign
    m = m.astype(np.uint8)
    if open_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, disc(open_px))
    if close_px > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, disc(close_px))
    out = m.astype(bool)
    if ign is None:
        if largest:
            out = largest_component(out)
        if holes:
            out = fill_holes(out)
        return out
    if not out.any():
        return out
    bridged = out | ign
    if largest:
        n, labels = cv2.connectedComponents(bridged.astype(np.uint8), connectivity=8)
        counts = np.bincount(labels[out], minlength=n)
        counts[0] = 0
        bridged = labels == int(np.argmax(counts))
    if holes:
        bridged = fill_holes(bridged)
    return bridged & ~ign


def temporal_majority(masks: np.ndarray, window: int = 3) -> np.ndarray:
    """Per-pixel majority over a centred window of frames (T, H, W) bool; window 1 = unchanged.
    At the ends the window shrinks (ties keep the frame's own value)."""
    masks = np.asarray(masks, bool)
    T = masks.shape[0]
    h = max(int(window), 1) // 2
    if h == 0 or T < 2:
        return masks.copy()
    csum = np.concatenate([np.zeros((1,) + masks.shape[1:], np.int32), np.cumsum(masks, axis=0, dtype=np.int32)])
    out = np.empty_like(masks)
    for t in range(T):
        a, b = max(0, t - h), min(T, t + h + 1)
        votes = csum[b] - csum[a]
        n = b - a
        out[t] = np.where(2 * votes == n, masks[t], 2 * votes > n)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """|a ∧ b| / |a ∨ b| (1 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else float(np.count_nonzero(a & b) / union)


# =========================================================================== background
def background_difference(frame: np.ndarray, plate: np.ndarray, threshold: float = 0.0, noise_k: float = 4.0,
                          min_threshold: float = 12.0, shadow_low: float = 0.4, shadow_high: float = 0.95,
                          shadow_chroma: float = 0.0) -> np.ndarray:
    """Raw foreground (H, W) bool from a background plate, shadows suppressed (module doc).

    threshold: τ in RGB units (0–255·√3); 0 = adaptive max(min_threshold, noise_k·σ).
    shadow_chroma: τ_c; 0 = the same as τ · 0.5.
    """
    I = np.asarray(frame, np.float64)
    B = np.asarray(plate, np.float64)
    d = np.linalg.norm(I - B, axis=2)
    if threshold <= 0:
        sigma = 1.4826 * float(np.median(d))
        threshold = max(min_threshold, noise_k * sigma)
    fg = d > threshold
    if shadow_high > shadow_low:
        bb = np.maximum(np.sum(B * B, axis=2), 1.0)
        alpha = np.sum(I * B, axis=2) / bb
        delta = np.linalg.norm(I - alpha[..., None] * B, axis=2)
        tc = shadow_chroma if shadow_chroma > 0 else 0.5 * threshold
        shadow = (alpha >= shadow_low) & (alpha <= shadow_high) & (delta < tc)
        fg &= ~shadow
    return fg


# =========================================================================== chroma
def border_color(image: np.ndarray, width: int = 4) -> np.ndarray:
    """Median RGB (3,) of the image's outer ``width``-pixel frame."""
    img = np.asarray(image)
    w = max(1, int(width))
    border = np.concatenate([img[:w].reshape(-1, 3), img[-w:].reshape(-1, 3),
                             img[:, :w].reshape(-1, 3), img[:, -w:].reshape(-1, 3)])
    return np.median(border, axis=0)


def chroma_key(frame: np.ndarray, key_rgb: np.ndarray | None = None, threshold: float = 0.0) -> np.ndarray:
    """Raw foreground (H, W) bool: (Cr, Cb) distance from the key colour above τ
    (τ = 0: Otsu's threshold on the distance image, at least 8)."""
    img = np.asarray(frame, np.uint8)
    key = border_color(img) if key_rgb is None else np.asarray(key_rgb, np.float64)
    ycc = cv2.cvtColor(img, cv2.COLOR_RGB2YCrCb).astype(np.float64)
    kycc = cv2.cvtColor(np.clip(key, 0, 255).astype(np.uint8).reshape(1, 1, 3), cv2.COLOR_RGB2YCrCb)
    kycc = kycc.reshape(3).astype(np.float64)
    d = np.hypot(ycc[..., 1] - kycc[1], ycc[..., 2] - kycc[2])
    if threshold <= 0:
        d8 = np.clip(d * (255.0 / max(d.max(), 1e-9)), 0, 255).astype(np.uint8)
        t8, _ = cv2.threshold(d8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
        threshold = max(8.0, t8 * max(d.max(), 1e-9) / 255.0)
    return d > threshold


def backdrop_uniformity(image: np.ndarray, width: int = 4) -> tuple[float, np.ndarray]:
    """(spread, key RGB (3,)) of the image's outer ``width``-pixel frame: spread = the 95th percentile of the
    distance of the border pixels' shading-free chroma c = 128 (Cr − 128, Cb − 128) / max(Y, 16) (YCrCb, 0–255
    units; a colour scaled by a shading factor keeps its c) from their median.  A backdrop of one colour
    (a chroma-key screen, a plain wall), shaded or not, gives a few units; a scene gives tens."""
    img = np.asarray(image, np.uint8)
    w = max(1, int(width))
    border = np.concatenate([img[:w].reshape(-1, 3), img[-w:].reshape(-1, 3),
                             img[:, :w].reshape(-1, 3), img[:, -w:].reshape(-1, 3)])
    ycc = cv2.cvtColor(border.reshape(-1, 1, 3), cv2.COLOR_RGB2YCrCb).reshape(-1, 3).astype(np.float64)
    c = 128.0 * (ycc[:, 1:] - 128.0) / np.maximum(ycc[:, :1], 16.0)
    med = np.median(c, axis=0)
    d = np.hypot(c[:, 0] - med[0], c[:, 1] - med[1])
    return float(np.percentile(d, 95)), np.median(border, axis=0).astype(np.float64)


# =========================================================================== grabcut
def grabcut(frame: np.ndarray, prior: np.ndarray, band_px: int = 0, iterations: int = 4, reach_px: int = 0,
            reach_factor: float = 4.0) -> np.ndarray:
    """GrabCut seeded by a prior mask (module doc); works on the prior's padded bounding box.

    Labels: probable foreground = the prior, probable background = up to ``reach_px`` outside
    it, sure background beyond, sure foreground = the prior eroded by ``reach_px`` (room for the
    object to have moved, grown or shrunk since the prior; the erosion shrinks, down to
    ``band_px``, while it would keep under 10 % of the prior).  band_px 0 = 6 % of the prior's
    equivalent diameter (at least 2 px); reach_px 0 = reach_factor × band_px.  Returns (H, W) bool.
    """
    img = np.asarray(frame, np.uint8)
    prior = np.asarray(prior, bool)
    H, W = prior.shape
    area = int(np.count_nonzero(prior))
    if area == 0:
        return np.zeros_like(prior)
    if band_px <= 0:
        band_px = max(2, int(round(0.06 * 2 * np.sqrt(area / np.pi))))
    if reach_px <= 0:
        reach_px = int(round(reach_factor * band_px))
    ys, xs = np.nonzero(prior)
    pad = reach_px + band_px + 2
    y0, y1 = max(0, ys.min() - pad), min(H, ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(W, xs.max() + pad + 1)
    p = prior[y0:y1, x0:x1].astype(np.uint8)
    r = reach_px
    sure_fg = cv2.erode(p, disc(r)).astype(bool)
    while r > band_px and np.count_nonzero(sure_fg) < 0.1 * area:
        r = max(band_px, r // 2)
        sure_fg = cv2.erode(p, disc(r)).astype(bool)
    maybe_bg = cv2.dilate(p, disc(reach_px)).astype(bool)
    gc = np.full(p.shape, cv2.GC_BGD, np.uint8)
    gc[maybe_bg] = cv2.GC_PR_BGD
    gc[p.astype(bool)] = cv2.GC_PR_FGD
    gc[sure_fg] = cv2.GC_FGD
    if not np.any(gc == cv2.GC_BGD):  # GrabCut needs background samples
        gc[0, :] = gc[-1, :] = gc[:, 0] = gc[:, -1] = cv2.GC_BGD
    if not np.any(gc == cv2.GC_FGD):
        gc[p.astype(bool)] = cv2.GC_FGD
    crop = np.ascontiguousarray(img[y0:y1, x0:x1, ::-1])  # OpenCV expects BGR
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.grabCut(crop, gc, None, bgd, fgd, int(iterations), cv2.GC_INIT_WITH_MASK)
    out = np.zeros((H, W), bool)
    out[y0:y1, x0:x1] = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    return out


# =========================================================================== mesh silhouettes
def mesh_silhouette(vertices: np.ndarray, faces: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
                    t: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixels (H, W) bool whose centre (integer coordinates, OpenCV) lies in a projected triangle
    (vertices (n, 3) m, faces (k, 3)); triangles with a vertex behind the camera are skipped.
    A centre is inside when all three edge functions e_i(p) = (b − a) × (p − a) share the sign
    of the triangle's area (≥ 0 after orientation, so shared edges leave no gap)."""
    uv, z = project(vertices, np.asarray(K), np.asarray(dist), np.asarray(R), np.asarray(t))
    faces = np.asarray(faces, np.int64)
    ok = np.all(z[faces] > 1e-6, axis=1)
    m = np.zeros((height, width), bool)
    for tri in uv[faces[ok]]:
        x0, y0 = np.maximum(np.ceil(tri.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.floor(tri.max(0)).astype(int), [width - 1, height - 1])
        if x1 < x0 or y1 < y0:
            continue
        a, b, c = tri
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if abs(area) < 1e-12:
            continue
        ys, xs = np.mgrid[y0:y1 + 1, x0:x1 + 1]
        sgn = np.sign(area)
        inside = np.ones(xs.shape, bool)
        for p, q in ((a, b), (b, c), (c, a)):
            inside &= sgn * ((q[0] - p[0]) * (ys - p[1]) - (q[1] - p[1]) * (xs - p[0])) >= 0
        m[y0:y1 + 1, x0:x1 + 1] |= inside
    return m


def overlay(frame: np.ndarray, mask: np.ndarray, color=(255, 64, 64), alpha: float = 0.45,
            truth: np.ndarray | None = None) -> np.ndarray:
    """RGB picture for inspection: the mask tinted and outlined (and the truth outline in green)."""
    img = np.asarray(frame, np.uint8).copy()
    m = np.asarray(mask, bool)
    tint = np.asarray(color, np.float64)
    img[m] = np.clip((1 - alpha) * img[m] + alpha * tint, 0, 255).astype(np.uint8)
    cs, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(img, cs, -1, tuple(int(c) for c in color), 1)
    if truth is not None:
        cs, _ = cv2.findContours(np.asarray(truth, np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(img, cs, -1, (0, 255, 0), 1)
    return img
