"""The local colour check measured in the frames (cystomap.compare.consistency.contrasts):
a region's contrast to its ring per frame, and the change of its median between sessions."""

from __future__ import annotations

import cv2
import numpy as np

from cystomap.compare.consistency import Samples, contrasts, frame_local_delta_e


def _lab(rgb: tuple[float, float, float]) -> np.ndarray:
    return cv2.cvtColor(np.asarray([[rgb]], np.float32) / 255.0, cv2.COLOR_RGB2Lab)[0, 0]


def _samples(region: tuple[float, float, float], ring: tuple[float, float, float], views: int,
             rng: np.random.Generator, glint_view: int | None = None) -> Samples:
    """``views`` frames of 40 region and 60 ring points with pixel noise; the colours as
    :func:`cystomap.compare.consistency.sample` leaves them (exposure-normalised on the ring)."""
    n_r, n_s = 40, 60
    col = np.empty((views, n_r + n_s, 3), np.float32)
    col[:, :n_r] = region
    col[:, n_r:] = ring
    col += rng.normal(0, 3.0, col.shape).astype(np.float32)
    vis = rng.random((views, n_r + n_s)) < 0.8
    if glint_view is not None:  # one frame whose region is washed out by a reflection
        col[glint_view, :n_r] = 250.0
    return Samples(col, vis, n_r)


def test_contrast_is_the_regions_lab_minus_its_rings() -> None:
    rng = np.random.default_rng(3)
    s = _samples((150, 92, 84), (128, 128, 128), 8, rng)
    c = contrasts(s)
    want = _lab((150, 92, 84)) - _lab((128, 128, 128))
    assert c.shape == (8, 3)
    assert np.abs(np.median(c, axis=0) - want).max() < 0.6, (np.median(c, axis=0), want)


def test_frame_local_delta_e_sees_the_patch_not_one_bad_frame() -> None:
    """A patch that turned redder between the sessions gives its ΔE; an unchanged one about 0,
    even with one frame of the seven washed out by a glint; too few frames give None."""
    rng = np.random.default_rng(4)
    wall = (128.0, 128.0, 128.0)
    a = _samples((140, 110, 104), wall, 7, rng)
    b = _samples((150, 100, 98), wall, 7, rng, glint_view=2)
    want = float(np.linalg.norm(_lab((150, 100, 98)) - _lab((140, 110, 104))))
    got = frame_local_delta_e(b, a)
    assert got is not None and abs(got - want) < 0.8, (got, want)
    same = frame_local_delta_e(_samples((140, 110, 104), wall, 7, rng, glint_view=5), a)
    assert same is not None and same < 0.8, same
    assert frame_local_delta_e(2, a) is None and frame_local_delta_e(b, 0) is None
