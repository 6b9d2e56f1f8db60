"""Specular glints: the saturated, near-white highlights of the wet wall and their rims,
masked per frame (preprocess ``masks/``) before features, matching and densification; and
clipped pixels (preprocess ``clipped/``), whose colour the atlas does not blend."""

from __future__ import annotations

import math

import cv2
import numpy as np


def glint_mask(bgr: np.ndarray, mask: np.ndarray, z: float, dilate: float) -> np.ndarray:
    """Specular highlights of one (levelled) BGR frame: bool image, True = glint or its rim.

    Thresholds come from the frame itself, inside ``mask``: whiteness w = min(B, G, R) is
    high only where every channel is bright (a highlight of the light's colour), chroma
    1 - min/max low where the pixel is near-white. Cores: w above median + ``z`` robust
    standard deviations of w and chroma below the frame's median (tissue is coloured); the
    blob grows into connected pixels with w above median + z/2 sigma (the halo), then is
    dilated by ``dilate`` times the image diagonal (descriptor support around the rim).
    """
    inside = mask > 0
    h, w = mask.shape
    if not inside.any():
        return np.zeros((h, w), bool)
    b, g, r = cv2.split(bgr)
    lo = cv2.min(cv2.min(b, g), r)  # uint8
    step = max(1, round(math.sqrt(np.count_nonzero(inside) / 65536)))  # stats from ~64k px
    sub = inside[::step, ::step]
    values = lo[::step, ::step][sub].astype(np.float32)
    med = float(np.median(values))
    sigma = max(1.4826 * float(np.median(np.abs(values - med))), 1.0)  # >= 1 DN (8-bit steps)
    grow = inside & (lo > med + 0.5 * z * sigma)
    if not (lo[grow] > med + z * sigma).any():
        return np.zeros((h, w), bool)
    hi = cv2.max(cv2.max(b, g), r).astype(np.float32)
    chroma = 1.0 - lo.astype(np.float32) / np.maximum(hi, 1.0)
    typical = float(np.median(chroma[::step, ::step][sub]))
    core = grow & (lo > med + z * sigma) & (chroma < typical)
    if not core.any():
        return np.zeros((h, w), bool)
    n, labels = cv2.connectedComponents(grow.view(np.uint8), connectivity=8)
    hit = np.zeros(n, bool)
    hit[np.unique(labels[core])] = True
    hit[0] = False
    return grown(hit[labels], dilate)


def grown(blobs: np.ndarray, dilate: float) -> np.ndarray:
    """``blobs`` (bool image) dilated by a disc of ``dilate`` times the image diagonal."""
    h, w = blobs.shape
    r = round(dilate * math.hypot(w, h))
    if r <= 0:
        return blobs
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(blobs.view(np.uint8), kernel) > 0


def clipped_mask(bgr: np.ndarray, mask: np.ndarray, level: int, dilate: float) -> np.ndarray:
    """Pixels of one (undistorted, not levelled) BGR frame where any channel reaches ``level``
    (8-bit clipping: overexposure, glints), inside ``mask``, dilated by ``dilate`` times the
    image diagonal: bool image, True = clipped or next to it.

    A clipped channel is not the wall's colour: an overexposed frame with its red channel cut
    at 255 shows reddish mucosa paler and yellower, however its exposure is corrected later.
    """
    hit = (cv2.max(cv2.max(bgr[..., 0], bgr[..., 1]), bgr[..., 2]) >= level) & (mask > 0)
    if not hit.any():
        return hit
    return grown(hit, dilate) & (mask > 0)
