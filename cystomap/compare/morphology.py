"""Binary morphology on atlas grids whose columns wrap around (azimuth is periodic) and whose
first and last rows border the poles: connected components across the seam and across the
poles, discs, opening/closing, rings, hole filling, and neighbourhoods measured on the wall."""

from __future__ import annotations

import numpy as np


def pole_neighbours(width: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Column pairs of a pole row that touch across the pole: column ``c`` of the first (or
    last) row lies half a row from the pole, as does column ``c + width / 2`` on its other
    side (the azimuth opposite), one row height away; 8-connected, the columns beside it too."""
    c = np.arange(width)
    half = width // 2
    return [(c, (c + half + k) % width) for k in (-1, 0, 1)]


def label_wrapped(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """8-connected labels (1 …) of ``mask``, joined across the azimuth seam and across the
    poles (the first and last rows: see :func:`pole_neighbours`); 0 = background."""
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

    # label pairs that touch across the seam (8-connected) and across the poles
    left, right = lab[:, 0], lab[:, -1]
    h = len(left)
    pairs = [np.stack([left[max(0, -dr):h - max(0, dr)], right[max(0, dr):h - max(0, -dr)]], 1)
             for dr in (-1, 0, 1)]
    for row in (lab[0], lab[-1]):
        pairs += [np.stack([row[ca], row[cb]], 1) for ca, cb in pole_neighbours(len(row))]
    touching = np.concatenate(pairs)
    touching = touching[(touching[:, 0] > 0) & (touching[:, 1] > 0)
                        & (touching[:, 0] != touching[:, 1])]
    for x, y in np.unique(touching, axis=0):
        a, b = find(int(x)), find(int(y))
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


def follow_into(outline: np.ndarray, into: np.ndarray) -> np.ndarray:
    """``outline`` with the connected pieces of ``into`` that touch it (8-connected)."""
    import cv2

    if not into.any():
        return outline
    _, lab = cv2.connectedComponents((outline | into).astype(np.uint8), connectivity=8)
    keep = np.unique(lab[outline])
    return np.isin(lab, keep[keep > 0]) | outline


def _fill_holes(mask: np.ndarray) -> np.ndarray:
    from scipy.ndimage import binary_fill_holes

    return binary_fill_holes(mask)


def near_on_wall(mask: np.ndarray, points: np.ndarray, radius_mm: float,
                 candidates: np.ndarray | None = None) -> np.ndarray:
    """Pixels (of ``candidates``, default all with a wall point) whose wall point lies within
    ``radius_mm`` (straight line, about the distance along the wall at these scales) of a
    wall point of ``mask``: a neighbourhood measured on the wall, not in atlas pixels, whose
    columns shrink towards the poles (and across a pole, if the window holds both sides).
    ``points`` (H, W, 3) are the pixels' wall points (NaN: none)."""
    import cv2
    from scipy.spatial import cKDTree

    ok = np.isfinite(points).all(axis=-1)
    out = mask & ok
    # the mask's boundary suffices: a point within the radius of the mask is within it of
    # the boundary or inside
    edge = mask & ~(cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8),
                              borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0) & ok
    query = (ok & ~mask) if candidates is None else (candidates & ok & ~mask)
    if not edge.any() or not query.any() or radius_mm <= 0:
        return out
    edge_pts = points[edge]
    # only pixels inside the edge's bounding box grown by the radius can be within it
    lo, hi = edge_pts.min(axis=0) - radius_mm, edge_pts.max(axis=0) + radius_mm
    query &= ((points >= lo) & (points <= hi)).all(axis=-1)
    if not query.any():
        return out
    tree = cKDTree(edge_pts)
    d, _ = tree.query(points[query], distance_upper_bound=radius_mm)
    hit = np.zeros_like(mask)
    hit[query] = np.isfinite(d)
    return out | hit
