"""Binary morphology on atlas grids whose columns wrap around (azimuth is periodic):
connected components across the seam, discs, opening/closing, rings, hole filling."""

from __future__ import annotations

import numpy as np


def label_wrapped(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected labels (1 …) of ``mask``, joined across the azimuth seam; 0 = background."""
    import cv2

    n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return lab.astype(np.int32), 0
    parent = np.arange(n)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = int(parent[i])
        return i

    left, right = lab[:, 0], lab[:, -1]
    h = len(left)
    for r in range(h):
        if left[r] == 0:
            continue
        for dr in (-1, 0, 1):
            rr = r + dr
            if 0 <= rr < h and right[rr]:
                a, b = find(int(left[r])), find(int(right[rr]))
                if a != b:
                    parent[max(a, b)] = min(a, b)
    roots = np.array([find(i) for i in range(n)])
    uniq, new = np.unique(roots, return_inverse=True)
    return new[lab].astype(np.int32), len(uniq) - 1


def _disc(radius_px: float) -> np.ndarray:
    import cv2

    r = max(1, round(float(radius_px)))
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def _morph(mask: np.ndarray, op: int, kernel: np.ndarray) -> np.ndarray:
    import cv2

    pad = kernel.shape[1]
    m = cv2.copyMakeBorder(mask.astype(np.uint8), 0, 0, pad, pad, cv2.BORDER_WRAP)
    return cv2.morphologyEx(m, op, kernel)[:, pad:-pad].astype(bool)


def _ring(mask: np.ndarray, width: int) -> np.ndarray:
    import cv2

    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * width + 1, 2 * width + 1))
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_fill_holes

    return binary_fill_holes(mask)
