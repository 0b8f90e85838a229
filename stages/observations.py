"""What ``rsl adapt`` compares the simulation with: motion-capture markers bound to the frame-0 surface, or images
rendered from the Gaussians bound to the tets (the window loss L, Eq. 4 / Eq. 7, its residuals r and dL/dX), and the
capture's frames, read per camera."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from stages.artefacts import (KIND_FILES, CamerasArtefact, GaussiansArtefact, MasksArtefact, MeshArtefact,
                              read_provenance)
from stages.capture import IMAGE_SUFFIXES, Capture, CaptureError, read_image
from stages.errors import RslError
from stages.occluders import has_occluders, ignore_mask
from stages.sim.markers import (MarkerBinding, bind_markers, closest_points_on_triangles, fit_binding_to_tracks,
                                 marker_residuals)


class MarkerObservation:
    """Marker observations (markers.csv) bound to the frame-0 surface.

    A marker seen at frame 0 is *anchored*: bound to the surface point nearest its frame-0 position (re-bound as
    the frame-0 state changes with θ, :meth:`rebind`).  A marker first seen later (hidden by a gripper at frame 0,
    say) counts as a gap until :meth:`bind_late` fits its material point to its track over the frames of the first
    window that sees it (stages.sim.markers.fit_binding_to_tracks, on the window's estimated states); it is held
    there from then on."""

    kind = "markers"

    def __init__(self, capture: Capture, vertices: np.ndarray, faces: np.ndarray, n_vertices: int):
        self.capture, self.faces, self.n = capture, faces, n_vertices
        self._raw = self._read()  # (T, M, 3) as read, NaN at a gap
        self.anchored = np.all(np.isfinite(self._raw[0]), axis=-1)  # (M,) seen at frame 0
        self.bound = self.anchored.copy()  # (M,) whose residuals count (a later marker: once bind_late placed it)
        self._mask()
        M = self._raw.shape[1]
        # the smallest marker noise σ the estimator assumes: 10⁻⁴ of the object's size (0.02 mm on a 0.2 m
        # object; mocap is rarely better) — without a floor, noise-free synthetic markers give σ → 0 and the
        # arrival cost becomes rigid against the slightest model or linearisation error
        self.noise_floor = 1e-4 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        self.binding = MarkerBinding(np.zeros((M, 3), np.int64), np.tile([1.0, 0.0, 0.0], (M, 1)), np.zeros(M))
        self.rebind(vertices, keep=False)  # (no triangle to keep yet)
        self.far = self._far(vertices)

    def _mask(self) -> None:
        """P (T, M, 3): the markers as read, with the ones not bound yet as gaps."""
        self.P = np.where(self.bound[None, :, None], self._raw, np.nan)

    def _far(self, x0: np.ndarray) -> float:
        """The largest binding distance of a bound marker over the bounding-box diagonal of x0 (n, 3)."""
        diag = float(np.linalg.norm(np.ptp(x0[:self.n], axis=0)))
        return float(self.binding.distance[self.bound].max(initial=0.0)) / max(diag, 1e-12)

    @property
    def late(self) -> np.ndarray:
        """(M,) markers first seen after frame 0 that are not bound yet."""
        return ~self.bound

    def rebind(self, x0: np.ndarray, keep: bool = True) -> None:
        """Bind each anchored marker to the triangle of the frame-0 surface x0 (n, 3) nearest its frame-0 position,
        at the projection of that position on the triangle's plane (the nearest point itself when it projects
        inside the triangle; unclamped at an edge, so that the binding is a smooth function of x0 for a given
        triangle — the Gauss–Newton Jacobian differentiates it, :meth:`binding_jacobian`).  A marker keeps the
        triangle it is bound to while that one is within :attr:`noise_floor` of the nearest: near a tie (a marker
        as far from two triangles) the choice would otherwise follow the last bits of x0, and the residuals jump
        between two close θ (``keep`` False: the nearest, whatever the binding before).  Markers bound by
        :meth:`bind_late` keep their binding."""
        a = self.anchored
        x, p = x0[:self.n], self._raw[0][a]
        b = bind_markers(x, self.faces, p)
        faces, dist = self.binding.faces.copy(), self.binding.distance.copy()
        new_faces, new_dist = b.faces, b.distance
        if keep and a.any():
            held = faces[a]
            d_held = np.empty(len(p))
            for s in range(0, len(p), 64):  # in chunks: marker i against triangle j of the chunk, i = j kept
                closest, _ = closest_points_on_triangles(p[s:s + 64], x[held[s:s + 64]])
                i = np.arange(len(closest))
                d_held[s:s + 64] = np.linalg.norm(closest[i, i] - p[s:s + 64], axis=-1)
            kept = d_held <= new_dist + self.noise_floor
            new_faces = np.where(kept[:, None], held, new_faces)
            new_dist = np.where(kept, d_held, new_dist)
        faces[a], dist[a] = new_faces, new_dist
        self.binding = MarkerBinding(faces, self._plane_bary(x, faces), dist)

    def fit_to_tracks(self, frames: Sequence[int], X: np.ndarray) -> float:
        """Bind each bound marker seen in ``frames`` again, at the material point whose track over them fits its
        observations best, X (w, n, 3) the window's positions, frames[0] the frame the binding's distances refer to
        (stages.sim.markers.fit_binding_to_tracks); a marker not seen there keeps its binding, and a marker not bound
        yet is left to :meth:`bind_late` and its rule on how many frames must see it.  Updates :attr:`far`.
        Returns the RMS motion of the markers bound before, on X[0], m."""
        x0 = X[0, :self.n]
        was = self.bound.copy()
        old = self.binding.positions(x0)
        self._fit(frames, X, was & (self._seen(frames) >= 1))
        self.far = self._far(x0)
        d = np.sum((self.binding.positions(x0) - old)[was] ** 2, axis=-1)
        return float(np.sqrt(np.mean(d))) if len(d) else 0.0

    def bind_late(self, frames: Sequence[int], X: np.ndarray, need: int = 1) -> int:
        """Bind the markers not bound yet that at least ``need`` of ``frames`` see: each at the material point whose
        track over the frames (X (w, n, 3), the window's estimated positions) fits its observations best.  Returns
        how many."""
        new = self.late & (self._seen(frames) >= need)
        if new.any():
            self._fit(frames, X, new)
        return int(new.sum())

    def _seen(self, frames: Sequence[int]) -> np.ndarray:
        """(M,) how many of ``frames`` observe each marker (as read, bound or not)."""
        return np.sum(np.all(np.isfinite(self._raw[list(frames)]), axis=-1), axis=0)

    def _fit(self, frames: Sequence[int], X: np.ndarray, which: np.ndarray) -> None:
        """fit_binding_to_tracks for the markers ``which`` (M,) over ``frames``; they become bound."""
        b = fit_binding_to_tracks(X[:, :self.n], self.faces, self._raw[list(frames)][:, which])
        faces, bary, dist = self.binding.faces.copy(), self.binding.bary.copy(), self.binding.distance.copy()
        faces[which], bary[which], dist[which] = b.faces, b.bary, b.distance
        self.binding = MarkerBinding(faces, bary, dist)
        self.bound = self.bound | which
        self._mask()

    def _read(self) -> np.ndarray:
        P = self.capture.markers()
        if P is None:
            raise CaptureError(f"{self.capture.markers_path}: file not found; --loss markers needs markers.csv.")
        return P

    def available(self) -> int:
        """Frames observed so far (markers.csv is re-read: it may grow in --follow mode).  Since a marker may
        be missing from a frame (a gap), a writer in --follow mode should add each frame's rows at once
        (e.g. write a new file and rename it over markers.csv): the rows of a frame read while still being
        written count as gaps."""
        if self.capture.markers_path.exists():
            try:
                self._raw = self._read()
            except CaptureError:
                pass  # a half-written line: keep what we had
            if self._raw.shape[1] != len(self.bound):  # (a marker never seen before is a gap until bound)
                self.bound = np.concatenate([self.bound, np.zeros(self._raw.shape[1] - len(self.bound), bool)])
            self._mask()
        return len(self.P)

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame losses (w,) and dL/dX (w, n, 3) for X on the mesh (n, 3) per frame; only the observed
        markers count (a gap, NaN in markers.csv's array, adds nothing; a frame seeing none gives 0)."""
        P = self.P[list(frames)]
        r = marker_residuals(self.binding, X[:, :self.n], P)
        grad = np.zeros_like(X)
        grad[:, :self.n] = self.binding.scatter(2.0 * r, self.n)
        return np.sum(r * r, axis=(1, 2)), grad

    def _plane_bary(self, x0: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """Barycentric coordinates (M, 3) of each anchored marker's frame-0 position projected on the plane of its
        triangle (``faces`` (M, 3)) of x0 — the binding as a smooth function of x0 (the same as the closest point
        while it lies inside); the other markers' rows are their binding's (they do not depend on x0)."""
        a = self.anchored
        tri = x0[faces[a]]  # (M_a, 3, 3)
        o, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
        d = self._raw[0][a] - o
        g = np.stack([np.stack([np.sum(e1 * e1, -1), np.sum(e1 * e2, -1)], -1),
                      np.stack([np.sum(e1 * e2, -1), np.sum(e2 * e2, -1)], -1)], -2)
        rhs = np.stack([np.sum(e1 * d, -1), np.sum(e2 * d, -1)], -1)
        uv = np.linalg.solve(g, rhs[..., None])[..., 0]
        bary = self.binding.bary.copy()
        bary[a] = np.concatenate([1 - uv.sum(-1, keepdims=True), uv], -1)
        return bary

    def binding_jacobian(self, frames: Sequence[int], X: np.ndarray, x0: np.ndarray, dx0: np.ndarray
                         ) -> list[np.ndarray]:
        """Per frame, the part of ∂r_f/∂p (3·M_f, k) that comes from the binding's dependence on the anchor
        configuration x0 (n, 3) moving by dx0 (k, n, 3): Σ_k (∂b_ik/∂p) x_f[f_ik], ∂b/∂p by central
        differences of :meth:`_plane_bary` (smooth, cheap: M 2×2 solves)."""
        x0 = x0[:self.n]
        scale = float(np.linalg.norm(np.ptp(x0, axis=0)))
        dB = []
        for v in dx0[:, :self.n]:
            vmax = float(np.abs(v).max())
            if vmax == 0.0:
                dB.append(np.zeros_like(self.binding.bary))
                continue
            h = 1e-6 * scale / vmax
            f = self.binding.faces
            dB.append((self._plane_bary(x0 + h * v, f) - self._plane_bary(x0 - h * v, f)) / (2 * h))
        dB = np.stack(dB)  # (k, M, 3)
        out = []
        for t, x in zip(frames, X):
            ok = np.all(np.isfinite(self.P[t]), axis=-1)
            dm = np.einsum("kmj,mjd->kmd", dB, x[self.binding.faces])[:, ok]  # (k, M_f, 3)
            out.append(dm.reshape(len(dB), -1).T)
        return out

    def residuals(self, frames: Sequence[int], X: np.ndarray) -> list[np.ndarray]:
        """Per frame, r_f = m_i(x_f) − p_f^i over the observed markers, flattened (3·M_f,), m."""
        out = []
        for t, x in zip(frames, X):
            P = self.P[t]
            ok = np.all(np.isfinite(P), axis=-1)
            out.append((self.binding.positions(x[:self.n])[ok] - P[ok]).reshape(-1))
        return out

    def jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray) -> list[np.ndarray]:
        """Per frame, ∂r_f/∂p (3·M_f, k) for position sensitivities dX (k, w, n, 3) (markers are linear in x)."""
        out = []
        for i, t in enumerate(frames):
            ok = np.all(np.isfinite(self.P[t]), axis=-1)
            dm = self.binding.positions(dX[:, i, :self.n])[:, ok]  # (k, M_f, 3)
            out.append(dm.reshape(len(dX), -1).T)
        return out

    def noise_scale(self, r: np.ndarray) -> float:
        """σ of one residual from residuals r: their RMS (Gaussian marker noise), m."""
        return float(np.sqrt(np.mean(r * r))) if len(r) else 0.0

    huber = None  # marker noise is Gaussian: plain least squares


def _forget_before(cache: dict, first: int) -> None:
    """Drop the frames before ``first`` from a per-frame cache (the frames a window may still revisit stay)."""
    for old in [k for k in cache if k < first]:
        del cache[old]


UNSEEN_OUTLINE_PX = 2
"""VisionObservation.unseen keeps the pixels within this many of the object mask's outline."""


class VisionObservation:
    """Image observations: render the Gaussians bound to the mesh in each chosen camera (stages.render)."""

    kind = "vision"

    def __init__(self, capture: Capture, ws: Path, cam_spec: str, mesh: MeshArtefact, appearance: bool,
                 anchor: str = "rebind", unseen: str = "keep"):
        from stages.render.image_loss import ImageLoss  # loads scipy.spatial: rsl adapt --help stays light

        self.capture, self.n = capture, mesh.n_vertices
        cams_art = CamerasArtefact.load(ws / KIND_FILES["cameras"])
        gauss = GaussiansArtefact.load(ws / KIND_FILES["gaussians"])
        masks_path = ws / KIND_FILES["masks"]
        self.masks = MasksArtefact.load(masks_path).masks if masks_path.exists() else None
        self.cameras = pick_cameras(cam_spec, [c.name for c in cams_art.cameras], ws / KIND_FILES["cameras"])
        for name in self.cameras:
            if name not in capture.camera_names:
                raise CaptureError(f"{capture.toml_path}: camera '{name}' of cameras.h5 is not listed in "
                                   f"[capture] cameras.")
        self.sources = {c: capture.frame_source(c) for c in self.cameras}
        self.loss_fn = ImageLoss(gauss, mesh, [cams_art.by_name(c) for c in self.cameras], appearance=appearance)
        # Occluders (controls.json handle/obstacle ``visual``): the pixels they cover at frame t are left out
        # of the loss (stages/occluders.py), whatever the frame and the mask hold there.
        self.controls = capture.controls()
        self.occluded = has_occluders(self.controls)
        self._cams = [cams_art.by_name(c) for c in self.cameras]
        self._ignore: dict[int, list[np.ndarray | None]] = {}
        # Without masks the renders are composited over the capture's background plates (when there are
        # any) and compared with the raw frames; with masks, the frames' backgrounds are replaced.
        self.loss_fn.set_backgrounds(render_backgrounds(capture, self.cameras, self.masks))
        self._cache: dict[int, list[np.ndarray]] = {}
        # The Gaussians were fitted to frame ``fit_frame`` with the mesh at rest: they are anchored to the
        # object's configuration at that frame, x_fit simulated with the current θ (re-anchored as θ
        # changes, like the marker binding; the anchor is held fixed within one gradient).  "rebind":
        # re-bound to the tets of x_fit (ImageLoss.rebind), rendered at x_t; "offset": rendered at
        # x_t − (x_fit − rest) (first order in x_fit − rest).
        if anchor not in ("rebind", "offset"):
            raise RslError(f"gaussian_anchor should be 'rebind' or 'offset', found '{anchor}'.")
        self.anchor_kind = anchor

        self.fit_frame = int(read_provenance(ws / KIND_FILES["gaussians"]).get("config", {}).get("frame", 0) or 0)
        self.rest = self.loss_fn.fit_positions  # (n, 3) where the Gaussians were fitted (rest for older files)
        self.anchor = np.zeros_like(mesh.vertices)  # (n, 3) x_fit(θ) − fit_positions
        # Gaussians whose colours the fit hardly saw (a face hidden from its cameras, or seen edge-on, that turns
        # into view): the pixels they paint are left out (:meth:`unseen`).  The fit's evidence of each Gaussian,
        # W_i: its blending weight summed over the images of the cameras fit-gaussians fitted (capture.toml's
        # cameras in cameras.h5), at the fit pose with the binding as fitted.  --appearance refines the colours
        # online instead, so it keeps them.
        if unseen not in ("ignore", "keep"):
            raise RslError(f"unseen_gaussians should be 'ignore' or 'keep', found '{unseen}'.")
        self.unseen_ignored = unseen == "ignore" and not appearance
        self._unseen: dict[int, list[np.ndarray | None]] = {}
        self.unseen_pixels: dict[int, int] = {}  # frame -> pixels :meth:`unseen` left out (over the cameras)
        self.fit_weight = None
        if self.unseen_ignored:
            names = [c.name for c in cams_art.cameras]
            fit_cams = [cams_art.by_name(c) for c in capture.camera_names if c in names] or list(cams_art.cameras)
            self.fit_weight = self.loss_fn.blend_weights(self.rest, fit_cams).sum(axis=0)  # (G,) px
            self._fit_size = self._image_size(self.rest)  # (C, G): what scales a Gaussian's weight, at the fit

    def rebind(self, x_fit: np.ndarray) -> None:
        """Anchor the Gaussians at the simulated fit-frame positions x_fit (n, 3)."""
        if self.anchor_kind == "rebind":
            self.loss_fn.rebind(x_fit[:self.n])
        else:
            self.anchor = x_fit[:self.n] - self.rest

    def count_checked(self) -> int:
        """Outside --follow: every frame of every chosen camera (PNG/JPG files or a video, read as segment
        reads them: capture.FrameSource) must decode, at the image size its camera in cameras.h5 was
        calibrated for; an unreadable frame anywhere is an error naming the file.  The frame count."""
        counts = {c: s.count for c, s in self.sources.items()}
        if len(set(counts.values())) > 1:
            detail = ", ".join(f"{c}: {k}" for c, k in counts.items())
            raise CaptureError(f"{self.capture.root / 'frames'}: cameras hold unequal frame counts ({detail}).")
        for cam, (c, src) in zip(self._cams, self.sources.items()):
            for t in range(src.count if src.files is not None else min(src.count, 1)):
                img = src.read(t)  # names the file (or the video) it cannot decode
                if img.shape[:2] != (cam.height, cam.width):
                    where = src.files[t] if src.files is not None else src.video
                    raise CaptureError(f"{where}: the frame is {img.shape[1]}x{img.shape[0]} but camera '{c}' in "
                                       f"cameras.h5 is calibrated for {cam.width}x{cam.height} images.")
        return next(iter(counts.values()), 0)

    def available(self) -> int:
        """Frames whose images exist and decode in every chosen camera (counted on from the last call)."""
        n = getattr(self, "_n_ready", 0)
        while frame_ready(self.capture, self.cameras, n):
            n += 1
        self._n_ready = n
        return n

    def targets(self, t: int) -> list[np.ndarray]:
        """Masked images Ĩ_t^c = I·m + bg·(1 − m) (raw I without masks), float32 (H, W, 3) in [0, 1]."""
        if t not in self._cache:
            out = []
            for c in self.cameras:
                src = self.sources[c]
                img = src.read(t) if src.video is not None else read_frame(self.capture, c, t)
                out.append(target_image(img, self.masks, c, t, self.loss_fn.background))
            self._cache[t] = out
            _forget_before(self._cache, t - 64)
        return self._cache[t]

    def ignore(self, t: int, x: np.ndarray | None = None) -> list[np.ndarray | None]:
        """Per chosen camera, the (H, W) pixels left out at frame t (None: none): those the occluders cover, and
        those :meth:`unseen` finds (from the render positions x (n, 3) at the frame's first evaluation; later
        calls, x or not, take that frame's pixels as found then)."""
        occ = [None] * len(self.cameras)
        if self.occluded:
            if t not in self._ignore:
                self._ignore[t] = [ignore_mask(self.controls, t, c) for c in self._cams]
                _forget_before(self._ignore, t - 64)
            occ = self._ignore[t]
        if not self.unseen_ignored or (x is None and t not in self._unseen):
            return occ
        un = self.unseen(t, x)
        return [a if b is None else (b if a is None else a | b) for a, b in zip(occ, un)]

    UNSEEN_RATIO = 1.5
    """A Gaussian paints unseen colour in a camera when its blending weight there exceeds this many times the fit's
    evidence of it, scaled by how much larger it now images (:meth:`_image_size`; + :attr:`UNSEEN_FLOOR`): the
    one-camera bar filmed mid-motion, whose end face turns into view, flagged that face alone at 1.5 and 2 (2 with
    holes in it) and nothing of the faces the fit saw (accuracy_notes.md, twenty-seventh stop)."""
    UNSEEN_FLOOR = 0.05
    """Pixels of blending weight below which no Gaussian is flagged (:attr:`UNSEEN_RATIO`)."""

    def _image_size(self, x: np.ndarray) -> np.ndarray:
        """(C, G): per chosen camera, each Gaussian's image area were it seen face-on, up to a constant:
        √(λ₁ λ₂) / z² (λ₁, λ₂ the two largest eigenvalues of its world covariance, z its depth in the camera) at
        the render positions x (n, 3) — what a Gaussian's blending weight grows with when it comes nearer or its
        surface stretches, unlike turning towards the camera."""
        mu, cov = self.loss_fn.geometry(x)
        lam = np.linalg.eigvalsh(cov)
        area = np.sqrt(np.clip(lam[:, 1] * lam[:, 2], 0.0, None))
        z = np.stack([(mu @ np.asarray(c.R, float).T + np.asarray(c.t, float).ravel())[:, 2] for c in self._cams])
        return area[None] / np.maximum(z, 1e-9) ** 2

    def unseen(self, t: int, x: np.ndarray) -> list[np.ndarray | None]:
        """Per chosen camera, the (H, W) pixels of frame t painted at least half by Gaussians whose colour the fit
        did not see: Gaussian i is flagged in camera c when w_i^c(x) > UNSEEN_RATIO · W_i · a_i^c(x) / a_i^c(x_fit)
        + UNSEEN_FLOOR (w its blending weight summed over the image at the render positions x (n, 3), W the fit's,
        ImageLoss.blend_weights; a its face-on image size, :meth:`_image_size`), and a pixel of coverage A ≥ 0.05
        is left out when the flagged Gaussians paint ≥ A / 2 of it (ImageLoss.painted_share) and, with masks.h5,
        it lies inside the frame's object mask more than UNSEEN_OUTLINE_PX from its outline (there the coverage,
        right whatever the colours, still tells the shape).  Computed at the frame's first call and kept (None:
        no pixel)."""
        if t not in self._unseen:
            w = self.loss_fn.blend_weights(x)
            grown = self._image_size(x) / self._fit_size  # (C, G): nearer the camera, or the surface stretched
            flags = w > self.UNSEEN_RATIO * self.fit_weight[None] * grown + self.UNSEEN_FLOOR
            out = []
            for c, (share, cover) in zip(self.cameras, self.loss_fn.painted_share(x, flags)):
                m = (cover >= 0.05) & (share >= 0.5 * cover)
                if self.masks is not None and c in self.masks and t < len(self.masks[c]):
                    # the object's outline stays: its coverage is right whatever the colours
                    obj = (np.asarray(self.masks[c][t]) > 0.5).astype(np.uint8)
                    m &= cv2.erode(obj, np.ones((3, 3), np.uint8), iterations=UNSEEN_OUTLINE_PX).astype(bool)
                out.append(m if m.any() else None)
            self._unseen[t] = out
            self.unseen_pixels[t] = int(sum(m.sum() for m in out if m is not None))
            _forget_before(self._unseen, t - 64)
        return self._unseen[t]

    def loss(self, frames: Sequence[int], X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(per-frame L1 losses (w,), dL/dX (w, n, 3)); also sets ``anchor_grad`` (n, 3) = dL/dx_f, the derivative
        with respect to the anchor configuration x_f(θ) of the last :meth:`rebind` (rebind: through
        ImageLoss.anchored_geometry; offset: −Σ_t dL/dx_t), which a gradient in θ must carry too."""
        losses, grad = np.zeros(len(frames)), np.zeros_like(X)
        ga = np.zeros((self.n, 3))
        for i, t in enumerate(frames):
            x = X[i, :self.n] - self.anchor
            li, gi, gai = self.loss_fn(x, self.targets(t), self.ignore(t, x), anchor_grad=True)
            losses[i], grad[i, :self.n] = li, gi
            ga += gai if self.anchor_kind == "rebind" else -gi
        self.anchor_grad = ga
        return losses, grad

    # Gauss–Newton residuals: the pixel differences themselves (every camera, RGB), weighted by Huber IRLS
    # (stages.estimator) — L2 near the solution, L1-like on outlying pixels, like the L1 loss of Adam.
    huber = 1.345  # Huber δ in units of σ (95 % efficiency under Gaussian noise)
    noise_floor = 1e-3  # of the [0, 1] intensity range (a quarter of one 8-bit grey level)

    def _renders(self, x: np.ndarray) -> np.ndarray:
        return np.concatenate([im.reshape(-1) for im in self.loss_fn.render(x[:self.n] - self.anchor)]
                              ).astype(np.float64)

    def _keep(self, t: int, x: np.ndarray | None = None) -> np.ndarray | float:
        """1 for the pixels that count at frame t, 0 for those :meth:`ignore` leaves out (flattened like the
        residuals), or 1.0 when it leaves none; ``x``: the render positions (n, 3) of the frame's evaluation."""
        masks = self.ignore(t, x)
        if all(m is None for m in masks):
            return 1.0
        return np.concatenate([np.repeat(~(np.zeros(c.height * c.width, bool) if m is None else m.reshape(-1)), 3)
                               for c, m in zip(self._cams, masks)]).astype(np.float64)

    def _target_flat(self, t: int) -> np.ndarray:
        """Frame t's :meth:`targets` of every camera flattened like the residuals, float64 (kept for t and the 7
        frames nearest it: every evaluation of a window subtracts them)."""
        flat = getattr(self, "_flat", None)
        if flat is None:
            flat = self._flat = {}
        if t not in flat:
            for old in [u for u in sorted(flat, key=lambda u: abs(u - t))][7:]:  # the 7 frames nearest t stay
                del flat[old]
            flat[t] = np.concatenate([im.reshape(-1) for im in self.targets(t)]).astype(np.float64)
        return flat[t]

    @staticmethod
    def _masked(a: np.ndarray, keep: np.ndarray | float) -> np.ndarray:
        """a × keep (rows of a (m,) or (m, k) zeroed under an occluder); a itself when nothing is occluded (the
        same floats, without the copy)."""
        if isinstance(keep, float) and keep == 1.0:
            return a
        return a * (keep[:, None] if a.ndim == 2 else keep)

    def residuals(self, frames: Sequence[int], X: np.ndarray) -> list[np.ndarray]:
        """Per frame, r_f = R(G(x_f), c) − Ĩ_f^c over every pixel, channel and camera, flattened (0 where
        :meth:`ignore` leaves a pixel out)."""
        return [self._masked(self._renders(x) - self._target_flat(t), self._keep(t, x[:self.n] - self.anchor))
                for t, x in zip(frames, X)]

    #: how GNWindow gets ∂r/∂p: "jvp" — exact forward mode through projection and rasterizer, all k columns in one
    #: pass per frame and camera (:meth:`residuals_and_jacobian`), where the renderer supports it
    #: (ImageLoss.jvp_supported); "fd" — central differences (:meth:`jacobian`, :meth:`binding_jacobian`, 2 renders
    #: per column, frame and camera) with Jᵀ W r from autograd (:meth:`exact_jtwr`): the slow twin the tests hold
    #: the jvp path to
    jacobian_mode = "jvp"

    def uses_jvp(self) -> bool:
        """Whether GN takes J from :meth:`residuals_and_jacobian` (else :meth:`jacobian` + :meth:`binding_jacobian`)."""
        return self.jacobian_mode == "jvp" and self.loss_fn.jvp_supported

    def residuals_and_jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray, dXa: np.ndarray | None = None
                               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """(per frame r_f — the floats of :meth:`residuals` —, per frame ∂r_f/∂p (pixels, k) exactly): the renderer's
        derivative along each position sensitivity dX[j, f] (k, w, n, 3) and, with ``dXa`` (k, n, 3), along the
        anchor x_f(θ)'s own sensitivity jointly (rebind: the binding of ImageLoss.anchored_geometry moves with it;
        offset: the renders at x − (x_a − x_fit), along v − v_a) — by forward mode (ImageLoss.images_jvp: one pass
        per frame and camera for all k columns).  The exact derivative of the float32 render (the one autograd
        gives, so Jᵀ W r from this J is :meth:`exact_jtwr`'s); 0 under an occluder."""
        lf = self.loss_fn
        rs, Js = [], []
        k = len(dX)
        if dXa is not None and self.anchor_kind == "rebind":
            binding = lf.binding_jvp(lf._anchor_x, dXa[:, :self.n], k)  # once: the anchor is every frame's
        else:
            binding = lf.binding_jvp(k=k)
        for i, (t, x) in enumerate(zip(frames, X)):
            V = dX[:, i, :self.n]
            if dXa is not None and self.anchor_kind == "offset":
                V = V - dXa[:, :self.n]
            out = lf.images_jvp(x[:self.n] - self.anchor, V, binding)
            keep = self._keep(t, x[:self.n] - self.anchor)
            rs.append(self._masked(np.concatenate([o[0].reshape(-1) for o in out]).astype(np.float64)
                                   - self._target_flat(t), keep))
            J = np.concatenate([o[1].reshape(len(V), -1) for o in out], axis=1).T.astype(np.float64)  # (m, k)
            Js.append(self._masked(J, keep))
        return rs, Js

    def jacobian(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray, rel_step: float = 1e-2,
                 skip: Sequence[int] = ()) -> list[np.ndarray]:
        """Per frame, ∂r_f/∂p (pixels, k) approximately: the renderer's directional derivative along each
        position sensitivity dX[j, f] by central differences, (R(x + ε v) − R(x − ε v)) / 2ε with ε·max|v| =
        ``rel_step`` × the object's size (2k renders per frame; the slow twin of :meth:`residuals_and_jacobian`'s
        forward mode, which GN uses where the renderer supports it, :attr:`jacobian_mode`).  3DGS
        rasterization is only piecewise smooth (the α < 1/255 cut-off) and renders in float32, so these
        columns carry errors of several % (tests); Gauss–Newton therefore takes its gradient from
        :meth:`exact_jtwr` and uses J only for the normal matrix (step shape and σ).  (One-sided differences
        reusing the residual's render, k renders, measured too inexact: Jᵀ W r 2.6× the exact value at this ε,
        1.3× at ε/10, docs/results/estimator.md.)  Columns ``skip`` are returned as zeros without rendering (those
        :meth:`binding_jacobian` differences jointly anyway)."""
        self._dXa = None  # the anchor's sensitivity, set by binding_jacobian for exact_jtwr of this evaluation
        size = float(np.linalg.norm(np.ptp(self.rest, axis=0)))
        out = []
        for i, x in enumerate(X):
            cols = []
            for j in range(len(dX)):
                v = dX[j, i]
                vmax = float(np.abs(v[:self.n]).max())
                if vmax == 0.0 or j in skip:
                    cols.append(np.zeros(0))
                    continue
                eps = rel_step * size / vmax
                cols.append((self._renders(x + eps * v) - self._renders(x - eps * v)) / (2 * eps) * self._keep(frames[i]))
            m = sum(c.height * c.width * 3 for c in self._cams)
            out.append(np.stack([c if len(c) else np.zeros(m) for c in cols], axis=1))
        self._last_jac = (dX, out)  # binding_jacobian replaces these columns by joint differences
        return out

    def binding_jacobian(self, frames: Sequence[int], X: np.ndarray, x_anchor: np.ndarray, dXa: np.ndarray
                         ) -> list[np.ndarray]:
        """Per frame, the part of ∂r_f/∂p (pixels, k) that comes from the anchor x_f(θ) moving by dXa (k, n, 3).
        On a sagging capture the two parts nearly cancel (the anchor moves the Gaussians back where they were
        fitted), so each column is differenced jointly — positions along dX[j] (of the :meth:`jacobian` call of
        this evaluation) and the anchor along dXa[j] together: rebind, (R(x + εv; x_a + εv_a) − R(x − εv;
        x_a − εv_a)) / 2ε with the Gaussians kept in their elements (ImageLoss.anchored_geometry, smooth in x_a);
        offset, the renders at x − (x_a − x_fit) along v − v_a — and this returns the joint columns minus those
        :meth:`jacobian` returned (GN adds the two).  :meth:`exact_jtwr` then adds the anchor's exact part."""
        torch = self.loss_fn.torch
        self._dXa = dXa
        dX, J_pos = self._last_jac
        size = float(np.linalg.norm(np.ptp(self.rest, axis=0)))
        xa = np.asarray(x_anchor, np.float64)[:self.n]

        def renders(x, a):
            with torch.no_grad():
                ims = self.loss_fn.images(torch.tensor(np.asarray(x[:self.n], np.float64)), torch.tensor(a))
            return np.concatenate([im.numpy().reshape(-1) for im in ims]).astype(np.float64)

        out = []
        for i, x in enumerate(X):
            cols = []
            for j in range(len(dXa)):
                v, va = dX[j, i, :self.n], dXa[j, :self.n]
                vmax = max(float(np.abs(v).max()), float(np.abs(va).max()))
                if vmax == 0.0 or not np.any(va):  # (the anchor does not move along p_j: jacobian's column holds)
                    cols.append(J_pos[i][:, j])
                    continue
                eps = 1e-2 * size / vmax
                if self.anchor_kind == "rebind":
                    col = (renders(x[:self.n] + eps * v, xa + eps * va) - renders(x[:self.n] - eps * v, xa - eps * va))
                else:
                    col = self._renders(x[:self.n] + eps * (v - va)) - self._renders(x[:self.n] - eps * (v - va))
                cols.append(col / (2 * eps) * self._keep(frames[i]))
            out.append(np.stack(cols, axis=1) - J_pos[i])
        return out

    def exact_jtwr(self, frames: Sequence[int], X: np.ndarray, dX: np.ndarray, rs: list, Ws: list) -> np.ndarray:
        """Jᵀ W r (k,) exactly: per frame, dℓ/dx of ℓ = ½ Σ W (R(x) − Ĩ)² by torch autograd through the
        rasterizer, projected on the sensitivities dX (k, w, n, 3) — plus, after :meth:`binding_jacobian` in the
        same evaluation, dℓ/dx_a (ImageLoss.anchored_geometry; offset: −dℓ/dx) projected on the anchor's
        sensitivities."""
        torch = self.loss_fn.torch
        g = np.zeros(len(dX))
        dXa = getattr(self, "_dXa", None)
        for i, t in enumerate(frames):
            xt = torch.tensor(np.asarray(X[i, :self.n] - self.anchor, np.float64), requires_grad=True)
            xa = None
            if dXa is not None and self.anchor_kind == "rebind" and self.loss_fn._anchor_x is not None:
                xa = torch.tensor(self.loss_fn._anchor_x, requires_grad=True)
            imgs = self.loss_fn.images(xt, xa)
            tg = torch.cat([torch.as_tensor(a, dtype=torch.float64).reshape(-1) for a in self.targets(t)])
            rend = torch.cat([im.reshape(-1) for im in imgs]).double()
            w = torch.as_tensor(np.asarray(Ws[i], np.float64) * self._keep(t))  # occluded pixels weigh 0
            (0.5 * (w * (rend - tg) ** 2).sum()).backward()
            g += np.einsum("ni,kni->k", xt.grad.numpy(), dX[:, i, :self.n])
            if dXa is not None and (xa is not None or self.anchor_kind == "offset"):
                ga = xa.grad.numpy() if xa is not None else -xt.grad.numpy()
                g += np.einsum("ni,kni->k", ga, dXa[:, :self.n])
        return g

    block_px = 8  # side of the pixel blocks whose errors are taken as correlated (:meth:`clusters`)

    def clusters(self, frames: Sequence[int]) -> np.ndarray:
        """Cluster id (m,) of each residual of :meth:`residuals` over ``frames``: its camera's block of
        ``block_px`` × ``block_px`` pixels (every channel, every window frame: the misfit of a shape error is
        correlated over neighbouring pixels, the colour channels and consecutive frames), for the estimator's
        cluster-robust σ (stages.estimator.cluster_scale2)."""
        b = self.block_px
        kept = getattr(self, "_clusters", None)  # (block_px, frames, ids): the last window's
        if kept is not None and kept[0] == b and kept[1] == len(frames):
            return kept[2]
        ids, base = [], 0
        for c in self._cams:
            yy, xx = np.divmod(np.arange(c.height * c.width), c.width)
            nbx = -(-c.width // b)
            ids.append(np.repeat(base + (yy // b) * nbx + xx // b, 3))
            base += nbx * -(-c.height // b)
        out = np.tile(np.concatenate(ids), len(frames))
        out.flags.writeable = False  # (shared by the windows of this many frames)
        self._clusters = (b, len(frames), out)
        return out

    def noise_scale(self, r: np.ndarray) -> float:
        """σ of one pixel residual: 1.4826 × the median |r| over the pixels that differ (robust; the
        background pixels that match exactly are left out)."""
        a = np.abs(r[np.abs(r) > 1e-6])
        return float(1.4826 * np.median(a)) if len(a) else 0.0


def render_backgrounds(capture: Capture, cameras: Sequence[str], masks: dict | None) -> list[np.ndarray | None]:
    """Per camera, what the renders are composited over (ImageLoss.set_backgrounds): None — the Gaussians'
    background colour — for a camera with masks (its frames' backgrounds are replaced by that colour,
    :func:`target_image`), else the capture's background plate (H, W, 3) float32 in [0, 1] (None without one)."""
    plates = [None if masks is not None and c in masks else capture.background(c) for c in cameras]
    return [None if p is None else p.astype(np.float32) / 255.0 for p in plates]


def target_image(image: np.ndarray, masks: dict | None, camera: str, t: int, background: np.ndarray) -> np.ndarray:
    """What a render of camera ``camera`` at frame t is compared with: Ĩ = I·m + bg·(1 − m), float32 (H, W, 3) in
    [0, 1], for the frame I (H, W, 3) uint8, its mask m (H, W) in masks.h5 and the Gaussians' background colour
    bg (3,); I/255 where the camera has no mask at frame t."""
    img = image.astype(np.float32) / 255.0
    if masks is not None and camera in masks and t < len(masks[camera]):
        m = masks[camera][t][..., None].astype(np.float32)
        img = img * m + background[None, None, :] * (1 - m)
    return img


def pick_cameras(spec: str, names: list[str], path: Path) -> list[str]:
    if not spec.strip():
        return list(names)
    out = []
    for tok in (s.strip() for s in spec.split(",") if s.strip()):
        if tok.isdigit():
            k = int(tok)
            if k >= len(names):
                raise RslError(f"{path}: --cameras asks for camera {k} but it holds {len(names)} cameras.")
            out.append(names[k])
        elif tok in names:
            out.append(tok)
        else:
            raise RslError(f"{path}: --cameras names '{tok}', which is not one of {', '.join(names)}.")
    return list(dict.fromkeys(out))


def frame_file(capture: Capture, cam: str, t: int) -> Path | None:
    folder = capture.root / "frames" / cam
    for stem in (f"{t:06d}", str(t)):
        for suf in IMAGE_SUFFIXES:
            p = folder / f"{stem}{suf}"
            if p.is_file():
                return p
    return None


def read_frame(capture: Capture, cam: str, t: int) -> np.ndarray:
    p = frame_file(capture, cam, t)
    if p is None:
        return capture.frame_source(cam).read(t)
    return read_image(p)


def frame_ready(capture: Capture, cams: Sequence[str], t: int) -> bool:
    """Frame t counts when every camera's image for it exists and decodes completely."""
    for c in cams:
        p = frame_file(capture, c, t)
        if p is None:
            return False
        data = np.fromfile(p, dtype=np.uint8)
        if p.suffix.lower() == ".png" and not data[-12:].tobytes().endswith(b"IEND\xaeB`\x82"):
            return False  # still being written
        if data.size == 0 or cv2.imdecode(data, cv2.IMREAD_COLOR) is None:
            return False
    return True
