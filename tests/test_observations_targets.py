"""The image observation model in one place: what a render is compared with (stages.observations.target_image) and
what it is composited over (render_backgrounds) — used alike by rsl adapt (VisionObservation), rsl evaluate (PSNR)."""
from __future__ import annotations

import numpy as np

from stages.observations import render_backgrounds, target_image


def test_target_image_replaces_the_masked_background_and_leaves_unmasked_frames_raw():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    mask = rng.random((5, 7)) > 0.5
    bg = np.array([0.1, 0.5, 0.9], np.float32)
    masks = {"a": np.stack([mask, ~mask])}
    got = target_image(img, masks, "a", 1, bg)
    want = np.where(~mask[..., None], img / 255.0, bg)  # frame 1's mask is ~mask
    assert got.dtype == np.float32 and np.allclose(got, want, atol=1e-7)
    raw = img.astype(np.float32) / 255.0
    for args in ((None, "a", 0), (masks, "b", 0), (masks, "a", 2)):  # no masks / camera not masked / past the end
        assert np.array_equal(target_image(img, *args, bg), raw)


class _Capture:
    def __init__(self, plates):
        self.plates = plates

    def background(self, c):
        return self.plates.get(c)


def test_render_backgrounds_use_the_plate_only_for_unmasked_cameras():
    plate = np.full((2, 3, 3), 255, np.uint8)
    cap = _Capture({"a": plate, "b": plate})
    got = render_backgrounds(cap, ["a", "b", "c"], {"a": np.zeros((1, 2, 3), bool)})
    assert got[0] is None and got[2] is None  # masked camera; no plate
    assert got[1].dtype == np.float32 and np.array_equal(got[1], np.ones((2, 3, 3), np.float32))
    assert all(p is not None for p in render_backgrounds(cap, ["a", "b"], None))
